//! The simulator's sans-IO request path on arbitrary bytes: chunks arriving at arbitrary times
//! and port settings, assembled into requests and answered by a bus of fast, classic and
//! duplicate-address devices. Never a panic; every reply is timed after its request.
#![no_main]

use std::time::Duration;

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::protocol::{LineSettings, Parity, RegisterType};
use rtu2mqtt::sim::{Bus, DeviceSpec, Faults, MasterLine, RegisterMap, RequestAssembler, VirtualDevice};

fn bus() -> Bus {
    let mut registers = RegisterMap::new();
    registers.define(RegisterType::Coil, 0, 16, true);
    registers.define(RegisterType::DiscreteInput, 0, 8, false);
    registers.define(RegisterType::Holding, 0, 32, true);
    registers.define(RegisterType::Input, 0, 32, false);
    registers.define(RegisterType::Input, 60, 4, false);
    for coil in 0..8 {
        registers.mark_event_source(RegisterType::Coil, coil, 1);
    }
    registers.mark_event_source(RegisterType::Input, 60, 2);
    registers.mark_event_source(RegisterType::Holding, 0, 4);
    let spec = |address, serial, fast, line| DeviceSpec {
        name: format!("d{address}"),
        template: "fuzz".into(),
        serial,
        address,
        line,
        fast,
        turnaround: Duration::from_micros(300),
        model: "FUZZ".into(),
        firmware: "1".into(),
        signature: "fuzz".into(),
        registers: registers.clone(),
    };
    let fast = LineSettings::new(115_200, Parity::None, 2);
    let mut devices = vec![
        VirtualDevice::new(spec(1, 0xFE00_0001, true, fast)),
        VirtualDevice::new(spec(20, 0xFE40_00AC, true, fast)),
        VirtualDevice::new(spec(20, 0xFED2_A3A6, true, fast)),
        VirtualDevice::new(spec(247, 0x0D00_0001, false, fast)),
        VirtualDevice::new(spec(5, 0x0D00_0005, true, LineSettings::new(9600, Parity::Even, 1))),
    ];
    devices[1].faults = Faults { drop_reply: 0.1, corrupt_crc: 0.1, delay_reply: 0.1, ..Faults::default() };
    Bus::new(devices, 7)
}

fuzz_target!(|data: &[u8]| {
    let Some((&control, bytes)) = data.split_first() else { return };
    let mut bus = bus();
    let mut assembler = RequestAssembler::new();
    let lines = [
        MasterLine::exact(LineSettings::new(115_200, Parity::None, 2)),
        MasterLine::exact(LineSettings::new(9600, Parity::Even, 1)),
    ];
    let mut now = Duration::ZERO;
    for (i, piece) in bytes.chunks(usize::from(control % 16).max(1)).enumerate() {
        // Gaps sometimes longer than the frame silence.
        now += Duration::from_micros(u64::from(piece[0]) * 20);
        let line = lines[usize::from((control >> 4) & 1 == 1 && i % 5 == 4)];
        let mut requests = assembler.receive(piece, now, line);
        if i % 7 == 6 {
            requests.extend(assembler.on_silence());
        }
        for request in requests {
            let transmission = bus.handle(&request);
            if let Some(first) = transmission.bursts.first() {
                assert!(first.start >= request.last_byte_at);
            }
            let _ = bus.take_changes();
        }
        if i % 11 == 10 {
            if let Some(device) = bus.device_mut(usize::from(piece[0]) % 5) {
                device.reboot();
            }
        }
    }
    for request in assembler.on_silence() {
        let _ = bus.handle(&request);
    }
});
