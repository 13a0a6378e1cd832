//! The bus on virtual time, byte by byte: the seed's traces, every behaviour of issue 4.

use std::time::Duration;

use crate::protocol::{
    parse_hex, EventPoll, EventPriority, EventRange, EventSource, LineSettings, Parity,
    RegisterType, Reply, ReplyBody, Request, RequestPdu,
};

use super::bus::Bus;
use super::device::{DeviceSpec, VirtualDevice};
use super::faults::Faults;
use super::line::MasterLine;
use super::registers::RegisterMap;
use super::wire::Wire;

const MCM8_SERIAL: u32 = 0xFE40_00AC;
const MR6C_SERIAL: u32 = 0xFED2_A3A6;
const FAST_LINE: LineSettings = LineSettings::new(115_200, Parity::None, 2);

fn registers() -> RegisterMap {
    let mut map = RegisterMap::new();
    map.define(RegisterType::Coil, 0, 8, true);
    map.define(RegisterType::DiscreteInput, 0, 8, false);
    map.define(RegisterType::Holding, 0, 10, true);
    map.define(RegisterType::Input, 0, 10, false);
    map.define(RegisterType::Input, 471, 1, false);
    map.define(RegisterType::Input, 60, 2, false);
    for coil in 0..6 {
        map.mark_event_source(RegisterType::Coil, coil, 1);
    }
    map.mark_event_source(RegisterType::Input, 471, 1);
    map.mark_event_source(RegisterType::Input, 60, 2);
    map.mark_event_source(RegisterType::DiscreteInput, 0, 1);
    map
}

fn spec(name: &str, address: u8, serial: u32) -> DeviceSpec {
    DeviceSpec {
        name: name.into(),
        template: "test".into(),
        serial,
        address,
        line: FAST_LINE,
        fast: true,
        turnaround: Duration::from_micros(500),
        model: "WBMCM8".into(),
        firmware: "1.2.3".into(),
        signature: "mcm8".into(),
        registers: registers(),
    }
}

fn seed_bus() -> Bus {
    Bus::new(
        vec![
            VirtualDevice::new(spec("mcm8", 20, MCM8_SERIAL)),
            VirtualDevice::new(spec("mr6c", 241, MR6C_SERIAL)),
        ],
        1,
    )
}

fn master() -> MasterLine {
    MasterLine::exact(FAST_LINE)
}

fn send(bus: &mut Bus, request: &Request) -> Vec<u8> {
    bus.exchange(&request.encode().unwrap(), master(), Duration::ZERO)
        .bytes()
}

fn hex(text: &str) -> Vec<u8> {
    parse_hex(text).unwrap()
}

fn with_crc(text: &str) -> Vec<u8> {
    let mut frame = hex(text);
    crate::protocol::crc::append_crc(&mut frame);
    frame
}

fn ff(count: usize) -> Vec<u8> {
    vec![0xFF; count]
}

fn cat(a: Vec<u8>, b: Vec<u8>) -> Vec<u8> {
    [a, b].concat()
}

fn poll(min_address: u8, max_data_len: u8, ack_address: u8, ack_flag: u8) -> Request {
    Request::poll_events(EventPoll {
        min_address,
        max_data_len,
        ack_address,
        ack_flag,
    })
}

fn enable(
    address: u8,
    register_type: RegisterType,
    start: u16,
    priorities: Vec<EventPriority>,
) -> Vec<u8> {
    let mut bus_request = Request::configure_events(
        address,
        vec![EventRange::registers(register_type, start, priorities)],
    );
    bus_request.address = address;
    bus_request.encode().unwrap()
}

#[test]
fn classic_read_is_byte_exact_and_timed() {
    let mut bus = seed_bus();
    let request = hex("14 03 00 80 00 01 87 27");
    let start = Duration::from_millis(3);
    let reply = bus.exchange(&request, master(), start);
    assert_eq!(reply.bytes(), hex("14 03 02 00 14 B5 88"));
    let first = reply.bursts[0].start;
    assert_eq!(
        first,
        start + FAST_LINE.wire_time(8) + Duration::from_micros(500)
    );
    let last = reply.end().unwrap() - first;
    assert!(last.abs_diff(FAST_LINE.wire_time(7)) < Duration::from_micros(1));
}

#[test]
fn classic_functions_and_exceptions() {
    let mut bus = seed_bus();
    let write_coil = Request::classic(
        20,
        RequestPdu::WriteSingleCoil {
            address: 2,
            value: true,
        },
    );
    assert_eq!(send(&mut bus, &write_coil), write_coil.encode().unwrap());
    let read_coils = Request::classic(20, RequestPdu::ReadCoils { start: 0, count: 8 });
    assert_eq!(send(&mut bus, &read_coils), with_crc("14 01 01 04"));
    let write_regs = Request::classic(
        20,
        RequestPdu::WriteMultipleRegisters {
            start: 1,
            values: vec![0x1234, 0x5678],
        },
    );
    assert_eq!(send(&mut bus, &write_regs), with_crc("14 10 00 01 00 02"));
    let read = Request::classic(20, RequestPdu::ReadHoldingRegisters { start: 0, count: 3 });
    assert_eq!(
        send(&mut bus, &read),
        with_crc("14 03 06 00 00 12 34 56 78")
    );
    let coils = Request::classic(
        20,
        RequestPdu::WriteMultipleCoils {
            start: 0,
            values: vec![true, false, true],
        },
    );
    assert_eq!(send(&mut bus, &coils), with_crc("14 0F 00 00 00 03"));
    let inputs = Request::classic(20, RequestPdu::ReadDiscreteInputs { start: 0, count: 3 });
    assert_eq!(send(&mut bus, &inputs), with_crc("14 02 01 00"));
    let input = Request::classic(20, RequestPdu::ReadInputRegisters { start: 0, count: 1 });
    assert_eq!(send(&mut bus, &input), with_crc("14 04 02 00 00"));
    // Unknown register: illegal data address; read-only serial number: the same.
    let unknown = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 5000,
            count: 1,
        },
    );
    assert_eq!(send(&mut bus, &unknown), with_crc("14 83 02"));
    let across_hole = Request::classic(20, RequestPdu::ReadInputRegisters { start: 8, count: 4 });
    assert_eq!(send(&mut bus, &across_hole), with_crc("14 84 02"));
    let serial = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 270,
            value: 1,
        },
    );
    assert_eq!(send(&mut bus, &serial), with_crc("14 86 02"));
    let bad_address = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 128,
            value: 0,
        },
    );
    assert_eq!(send(&mut bus, &bad_address), with_crc("14 86 03"));
    // Unknown function: illegal function; bad count: illegal data value.
    assert_eq!(
        bus.exchange(&with_crc("14 2B 0E 01 00"), master(), Duration::ZERO)
            .bytes(),
        with_crc("14 AB 01")
    );
    assert_eq!(
        bus.exchange(&with_crc("14 03 00 00 00 00"), master(), Duration::ZERO)
            .bytes(),
        with_crc("14 83 03")
    );
    assert_eq!(
        bus.exchange(&with_crc("14 03 00 00 00 7E"), master(), Duration::ZERO)
            .bytes(),
        with_crc("14 83 03")
    );
    assert_eq!(
        bus.exchange(&with_crc("14 05 00 00 12 34"), master(), Duration::ZERO)
            .bytes(),
        with_crc("14 85 03")
    );
    // Other addresses and broadcasts: silence (a broadcast write still executes).
    let other = Request::classic(21, RequestPdu::ReadCoils { start: 0, count: 1 });
    assert!(send(&mut bus, &other).is_empty());
    let broadcast = Request::classic(
        0,
        RequestPdu::WriteSingleCoil {
            address: 7,
            value: true,
        },
    );
    assert!(send(&mut bus, &broadcast).is_empty());
    let coil7 = Request::classic(241, RequestPdu::ReadCoils { start: 7, count: 1 });
    assert_eq!(send(&mut bus, &coil7), with_crc("F1 01 01 01"));
    // A bad CRC is noise.
    assert!(bus
        .exchange(&hex("14 03 00 80 00 01 87 28"), master(), Duration::ZERO)
        .is_empty());
}

/// The scan rounds of seed 000: 22, 15 and 20 filler bytes.
#[test]
fn scan_reproduces_the_seed_trace() {
    let mut bus = seed_bus();
    let start = Request::scan_start();
    assert_eq!(
        send(&mut bus, &start),
        cat(ff(22), with_crc("FD 46 03 FE 40 00 AC 14"))
    );
    let next = Request::scan_continue();
    assert_eq!(
        send(&mut bus, &next),
        cat(ff(15), with_crc("FD 46 03 FE D2 A3 A6 F1"))
    );
    assert_eq!(send(&mut bus, &next), cat(ff(20), hex("FD 46 04 D3 93")));
    // A new scan starts over.
    assert_eq!(
        send(&mut bus, &start),
        cat(ff(22), with_crc("FD 46 03 FE 40 00 AC 14"))
    );
}

#[test]
fn arbitration_is_timed_window_by_window() {
    let mut bus = seed_bus();
    let at = Duration::from_millis(1);
    let frame = Request::scan_start().encode().unwrap();
    let reply = bus.exchange(&frame, master(), at);
    let end = at + FAST_LINE.wire_time(frame.len());
    let first_window = end + FAST_LINE.device_arbitration_wait();
    // The article's figure at 115200: 93 bits.
    assert_eq!(first_window - end, FAST_LINE.bits_time(93));
    let window = FAST_LINE.arbitration_window();
    // Window 0: both markers 0b0110 start with a 0 bit.
    assert_eq!(reply.bursts[0].start, first_window);
    assert_eq!(reply.bursts[0].bytes, vec![0xFF]);
    // Window 1 is recessive for both (marker bit 1): the next filler is in window 3.
    assert_eq!(reply.bursts[1].start, first_window + window * 3);
    let frame_burst = reply.bursts.last().unwrap();
    assert_eq!(frame_burst.start, first_window + window * 32);
    assert!(frame_burst.start <= end + FAST_LINE.scan_reply_timeout());
}

/// A scan under the deprecated 0x60 (what wb-device-manager sends) is answered under 0x60 with
/// the legacy timing: the first window 44 bits after the request, windows of 20 bits; reads by
/// serial number under 0x60 are answered under 0x60 too.
#[test]
fn a_legacy_scan_is_answered_under_0x60_with_its_own_windows() {
    use crate::protocol::fast::LEGACY_FUNCTION;
    let mut bus = seed_bus();
    let at = Duration::from_millis(1);
    let frame = Request::scan_start()
        .with_fast_function(LEGACY_FUNCTION)
        .encode()
        .unwrap();
    assert_eq!(frame[1], 0x60);
    let reply = bus.exchange(&frame, master(), at);
    let end = at + FAST_LINE.wire_time(frame.len());
    let first_window = end + FAST_LINE.bits_time(44);
    let window = FAST_LINE.bits_time(20);
    assert_eq!(reply.bursts[0].start, first_window);
    assert_eq!(reply.bursts[0].bytes, vec![0xFF]);
    assert_eq!(reply.bursts[1].start, first_window + window * 3);
    let found = reply.bursts.last().unwrap();
    assert_eq!(found.start, first_window + window * 32);
    assert_eq!(found.bytes, with_crc("FD 60 03 FE 40 00 AC 14"));

    let read = Request::by_serial(
        MCM8_SERIAL,
        RequestPdu::ReadHoldingRegisters { start: 0, count: 1 },
    )
    .with_fast_function(LEGACY_FUNCTION);
    let answer = send(&mut bus, &read);
    assert_eq!(&answer[..3], &[0xFD, 0x60, 0x09], "{answer:02X?}");
}

/// Below 52500 baud 3.5 characters outlast 800 µs, and a device counts them as 42 bits (3.5
/// characters of 12 bits, as the article computes its wait), whatever its own framing: at 9600
/// 8N1 the first window opens 4.375 ms after the request, not 3.65 ms (3.5 characters of 10 bits).
#[test]
fn arbitration_waits_42_bits_below_52500_baud() {
    for (line, first_window_us) in [
        (LineSettings::new(9600, Parity::None, 1), 4375),
        (LineSettings::new(9600, Parity::None, 2), 4375),
        (LineSettings::new(1200, Parity::Even, 1), 35_000),
        (LineSettings::new(115_200, Parity::None, 1), 807),
    ] {
        let mut device = spec("slow", 20, MCM8_SERIAL);
        device.line = line;
        let mut bus = Bus::new(vec![VirtualDevice::new(device)], 1);
        let frame = Request::scan_start().encode().unwrap();
        let reply = bus.exchange(&frame, MasterLine::exact(line), Duration::ZERO);
        let end = line.wire_time(frame.len());
        let wait = reply.bursts[0].start - end;
        assert_eq!(reply.bursts[0].bytes, vec![0xFF], "{line:?}");
        assert_eq!(wait.as_micros(), first_window_us, "{line:?}");
        let events = bus.exchange(
            &poll(0, 0xFF, 0, 0).encode().unwrap(),
            MasterLine::exact(line),
            Duration::ZERO,
        );
        let end = line.wire_time(9);
        assert_eq!(
            (events.bursts[0].start - end).as_micros(),
            first_window_us,
            "{line:?}"
        );
    }
}

/// The three event rounds of seed 000, byte for byte.
#[test]
fn events_reproduce_the_seed_trace() {
    let mut bus = seed_bus();
    let relay_enable = enable(241, RegisterType::Coil, 0, vec![EventPriority::High]);
    assert_eq!(
        bus.exchange(&relay_enable, master(), Duration::ZERO)
            .bytes(),
        hex("F1 46 18 01 01 0C CA")
    );
    let counter_enable = enable(20, RegisterType::Input, 471, vec![EventPriority::Low]);
    assert_eq!(
        bus.exchange(&counter_enable, master(), Duration::ZERO)
            .bytes(),
        with_crc("14 46 18 01 01")
    );
    bus.write_register(1, RegisterType::Coil, 0, &[1], Duration::ZERO)
        .unwrap();
    bus.write_register(0, RegisterType::Input, 471, &[1], Duration::ZERO)
        .unwrap();
    let round1 = bus.exchange(&hex("FD 46 10 00 FF 00 00 C8 9A"), master(), Duration::ZERO);
    assert_eq!(
        round1.bytes(),
        cat(
            ff(6),
            hex("F1 46 11 00 02 09 01 01 00 00 01 00 0F 00 00 10 64")
        )
    );
    let round2 = bus.exchange(&hex("FD 46 10 00 FF F1 00 8D 0A"), master(), Duration::ZERO);
    assert_eq!(
        round2.bytes(),
        cat(
            ff(8),
            with_crc("14 46 11 00 02 0A 02 04 01 D7 01 00 00 0F 00 00")
        )
    );
    let round3 = bus.exchange(&hex("FD 46 10 00 FF 14 00 C7 9A"), master(), Duration::ZERO);
    assert_eq!(round3.bytes(), cat(ff(6), hex("FD 46 12 52 5D")));
    // The next packets of both devices carry flag 1.
    bus.write_register(1, RegisterType::Coil, 0, &[0], Duration::ZERO)
        .unwrap();
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(6), with_crc("F1 46 11 01 01 05 01 01 00 00 00"))
    );
    // Only the first round had both devices with events arbitrating for the bus.
    let stats = bus.stats();
    assert_eq!(
        (
            stats.event_polls,
            stats.contended_event_polls,
            stats.max_event_contenders
        ),
        (4, 1, 2)
    );
}

#[test]
fn a_lost_ack_resends_under_the_same_flag() {
    let mut bus = seed_bus();
    bus.exchange(
        &enable(20, RegisterType::Coil, 0, vec![EventPriority::Low; 2]),
        master(),
        Duration::ZERO,
    );
    // The reboot event first, confirmed.
    let reboot = cat(ff(8), with_crc("14 46 11 00 01 04 00 0F 00 00"));
    assert_eq!(send(&mut bus, &poll(0, 0xFF, 0, 0)), reboot);
    bus.write_register(0, RegisterType::Coil, 0, &[1], Duration::ZERO)
        .unwrap();
    let packet = cat(ff(8), with_crc("14 46 11 01 01 05 01 01 00 00 01"));
    assert_eq!(send(&mut bus, &poll(0, 0xFF, 20, 0)), packet);
    // The master missed it: it confirms nothing (or the wrong flag). Same flag, new events added.
    assert_eq!(send(&mut bus, &poll(0, 0xFF, 0, 0)), packet);
    bus.write_register(0, RegisterType::Coil, 1, &[1], Duration::ZERO)
        .unwrap();
    let both = cat(
        ff(8),
        with_crc("14 46 11 01 02 0A 01 01 00 00 01 01 01 00 01 01"),
    );
    assert_eq!(send(&mut bus, &poll(0, 0xFF, 20, 0)), both);
    // Confirmed: device 20 has nothing left, so 241's reboot event comes through; then silence.
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 20, 1)),
        cat(ff(5), with_crc("F1 46 11 00 01 04 00 0F 00 00"))
    );
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 241, 0)),
        cat(ff(6), hex("FD 46 12 52 5D"))
    );
    // The flag of device 20 toggled for its next packet.
    bus.write_register(0, RegisterType::Coil, 1, &[0], Duration::ZERO)
        .unwrap();
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(8), with_crc("14 46 11 00 01 05 01 01 00 01 00"))
    );
}

#[test]
fn a_change_after_sending_survives_the_ack() {
    let mut bus = seed_bus();
    bus.exchange(
        &enable(20, RegisterType::Coil, 0, vec![EventPriority::Low]),
        master(),
        Duration::ZERO,
    );
    send(&mut bus, &poll(0, 0xFF, 0, 0));
    send(&mut bus, &poll(0, 0xFF, 20, 0));
    bus.write_register(0, RegisterType::Coil, 0, &[1], Duration::ZERO)
        .unwrap();
    // Reboot of the other device confirmed first, so that only device 20 has events.
    bus.exchange(
        &enable(241, RegisterType::Coil, 0, vec![EventPriority::Low]),
        master(),
        Duration::ZERO,
    );
    let sent = send(&mut bus, &poll(0, 0xFF, 0, 0));
    assert_eq!(
        sent,
        cat(ff(8), with_crc("14 46 11 01 01 05 01 01 00 00 01"))
    );
    bus.write_register(0, RegisterType::Coil, 0, &[0], Duration::ZERO)
        .unwrap();
    let again = send(&mut bus, &poll(0, 0xFF, 20, 1));
    assert_eq!(
        again,
        cat(ff(8), with_crc("14 46 11 00 01 05 01 01 00 00 00"))
    );
}

#[test]
fn min_address_excludes_lower_devices() {
    let mut bus = seed_bus();
    // Both have their reboot event pending; 20 would win on address.
    assert_eq!(
        send(&mut bus, &poll(21, 0xFF, 0, 0)),
        cat(ff(5), with_crc("F1 46 11 00 01 04 00 0F 00 00"))
    );
    // Nobody at or above 242: silence.
    assert!(send(&mut bus, &poll(242, 0xFF, 0, 0)).is_empty());
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(8), with_crc("14 46 11 00 01 04 00 0F 00 00"))
    );
}

#[test]
fn max_data_len_truncates_packets() {
    let mut bus = seed_bus();
    bus.exchange(
        &enable(20, RegisterType::Coil, 0, vec![EventPriority::High; 3]),
        master(),
        Duration::ZERO,
    );
    bus.exchange(
        &enable(241, RegisterType::Coil, 0, vec![EventPriority::Disabled]),
        master(),
        Duration::ZERO,
    );
    bus.write_register(0, RegisterType::Coil, 0, &[1, 1, 1], Duration::ZERO)
        .unwrap();
    // 4 events of 5, 5, 5 and 4 bytes; 12 bytes fit two.
    let first = send(&mut bus, &poll(0, 12, 0, 0));
    assert_eq!(
        first,
        cat(
            ff(9),
            with_crc("14 46 11 00 02 0A 01 01 00 00 01 01 01 00 01 01")
        )
    );
    let second = send(&mut bus, &poll(0, 12, 20, 0));
    assert_eq!(
        second,
        cat(
            ff(9),
            with_crc("14 46 11 01 02 09 01 01 00 02 01 00 0F 00 00")
        )
    );
    // Not even one fits: the count alone.
    bus.write_register(0, RegisterType::Coil, 0, &[0], Duration::ZERO)
        .unwrap();
    let none = send(&mut bus, &poll(0, 3, 20, 1));
    assert_eq!(none, cat(ff(9), with_crc("14 46 11 00 01 00")));
}

#[test]
fn configure_events_replies_with_mixed_bitmasks() {
    let mut bus = seed_bus();
    let request = Request::configure_events(
        20,
        vec![
            // Coils 0–5 can send events, 6–9 cannot (0 bits even when asked).
            EventRange::registers(RegisterType::Coil, 0, vec![EventPriority::Low; 10]),
            // Priority 0 disables.
            EventRange::registers(RegisterType::Input, 471, vec![EventPriority::Disabled]),
            // A 32-bit value: its base sends events, its second register does not.
            EventRange::registers(RegisterType::Input, 60, vec![EventPriority::High; 2]),
            EventRange::registers(RegisterType::Holding, 0, vec![EventPriority::High]),
            EventRange {
                source: EventSource::System,
                start: 0,
                priorities: vec![EventPriority::Disabled],
            },
        ],
    );
    assert_eq!(
        send(&mut bus, &request),
        with_crc("14 46 18 06 3F 00 00 01 00 00")
    );
    // The wb-mqtt-serial frame with the reboot record (§7.4 of the reference) answers alike.
    let wb = hex("01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D");
    let mut one = Bus::new(vec![VirtualDevice::new(spec("one", 1, 1))], 1);
    assert_eq!(one.devices()[0].events_configured_at, None);
    assert_eq!(
        one.exchange(&wb, master(), Duration::ZERO).bytes(),
        hex("01 46 18 02 00 00 2F 65")
    );
    // When (the end of the request on the wire), for the benchmark of event enabling.
    let configured = one.devices()[0].events_configured_at.expect("stamped");
    assert!(configured > Duration::ZERO, "{configured:?}");
    // A bad priority is an illegal data value.
    assert_eq!(
        bus.exchange(
            &with_crc("14 46 18 05 01 00 00 01 07"),
            master(),
            Duration::ZERO
        )
        .bytes(),
        with_crc("14 C6 03")
    );
}

#[test]
fn reboot_event_after_every_restart() {
    let mut bus = seed_bus();
    bus.exchange(
        &enable(241, RegisterType::Coil, 0, vec![EventPriority::High]),
        master(),
        Duration::ZERO,
    );
    send(&mut bus, &poll(0, 0xFF, 0, 0));
    send(&mut bus, &poll(0, 0xFF, 20, 0));
    send(&mut bus, &poll(0, 0xFF, 241, 0));
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(6), hex("FD 46 12 52 5D"))
    );
    bus.device_mut(1).unwrap().reboot();
    // Flag back to 0, settings gone: a coil change sends nothing, the reboot event is pending.
    bus.write_register(1, RegisterType::Coil, 0, &[1], Duration::ZERO)
        .unwrap();
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(5), with_crc("F1 46 11 00 01 04 00 0F 00 00"))
    );
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 241, 0)),
        cat(ff(6), hex("FD 46 12 52 5D"))
    );
}

#[test]
fn by_serial_access_and_address_change() {
    let mut bus = seed_bus();
    let model = bus.exchange(
        &hex("FD 46 08 FE 40 00 AC 03 00 C8 00 14 91 BA"),
        master(),
        Duration::ZERO,
    );
    let reply = Reply::decode(&model.bytes()).unwrap();
    let ReplyBody::Fast {
        reply: crate::protocol::FastReply::BySerial { serial, pdu },
        ..
    } = reply.body
    else {
        panic!("not a 0x09 reply");
    };
    assert_eq!(serial, MCM8_SERIAL);
    let crate::protocol::ResponsePdu::ReadHoldingRegisters { values } = pdu else {
        panic!()
    };
    assert_eq!(&values[..7], &[0x57, 0x42, 0x4D, 0x43, 0x4D, 0x38, 0]);
    let set = bus.exchange(
        &hex("FD 46 08 FE 40 00 AC 06 00 80 00 C8 DC 35"),
        master(),
        Duration::ZERO,
    );
    assert_eq!(
        set.bytes(),
        hex("FD 46 09 FE 40 00 AC 06 00 80 00 C8 8D F0")
    );
    assert_eq!(bus.devices()[0].address(), 200);
    let read = Request::classic(
        200,
        RequestPdu::ReadHoldingRegisters {
            start: 270,
            count: 2,
        },
    );
    assert_eq!(send(&mut bus, &read), with_crc("C8 03 04 FE 40 00 AC"));
    // Exceptions travel inside 0x09; an unknown serial is silence.
    let bad = Request::by_serial(
        MCM8_SERIAL,
        RequestPdu::ReadHoldingRegisters {
            start: 9999,
            count: 1,
        },
    );
    assert_eq!(send(&mut bus, &bad), with_crc("FD 46 09 FE 40 00 AC 83 02"));
    assert_eq!(
        bus.exchange(
            &with_crc("FD 46 08 FE 40 00 AC 2B 0E 01 00"),
            master(),
            Duration::ZERO
        )
        .bytes(),
        with_crc("FD 46 09 FE 40 00 AC AB 01")
    );
    let nobody = Request::by_serial(
        0x0D00_0001,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert!(send(&mut bus, &nobody).is_empty());
    // The old address is free now.
    assert!(send(
        &mut bus,
        &Request::classic(
            20,
            RequestPdu::ReadHoldingRegisters {
                start: 128,
                count: 1
            }
        )
    )
    .is_empty());
}

/// Silence, proved on virtual time rather than by listening: no address, no settings, nobody.
#[test]
fn nobody_answers_an_absent_address_or_unused_settings() {
    let mut bus = seed_bus();
    let read = |address| {
        Request::classic(address, RequestPdu::ReadCoils { start: 0, count: 1 })
            .encode()
            .unwrap()
    };
    assert!(bus.exchange(&read(99), master(), Duration::ZERO).is_empty());
    assert!(!bus.exchange(&read(20), master(), Duration::ZERO).is_empty());
    // Nothing on the bus uses 19200 8N1: a scan start there gets not even a filler.
    let unused = MasterLine::exact(LineSettings::new(19200, Parity::None, 1));
    let scan = Request::scan_start().encode().unwrap();
    assert!(bus.exchange(&scan, unused, Duration::ZERO).is_empty());
    assert!(bus.exchange(&read(20), unused, Duration::ZERO).is_empty());
    // A pty cannot tell parity none from even: such a master is heard by both, not by odd.
    let pty = MasterLine {
        baud: 115_200,
        data_bits: 8,
        stop_bits: 2,
        parity: super::line::ObservedParity::NoneOrEven,
    };
    assert!(!bus.exchange(&read(20), pty, Duration::ZERO).is_empty());
    let odd = MasterLine::exact(LineSettings::new(115_200, Parity::Odd, 2));
    assert!(bus.exchange(&read(20), odd, Duration::ZERO).is_empty());
}

#[test]
fn port_settings_change_after_the_reply() {
    let mut bus = seed_bus();
    let set_baud = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 110,
            value: 96,
        },
    );
    let reply = bus.exchange(&set_baud.encode().unwrap(), master(), Duration::ZERO);
    assert_eq!(reply.bytes(), set_baud.encode().unwrap());
    // The echo still went out at 115200.
    assert_eq!(reply.bursts[0].char_time, FAST_LINE.char_time());
    let read = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 110,
            count: 3,
        },
    );
    assert!(send(&mut bus, &read).is_empty());
    let slow = MasterLine::exact(LineSettings::new(9600, Parity::None, 2));
    let answer = bus.exchange(&read.encode().unwrap(), slow, Duration::ZERO);
    assert_eq!(answer.bytes(), with_crc("14 03 06 00 60 00 00 00 02"));
    let bad = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 110,
            value: 97,
        },
    );
    assert_eq!(
        bus.exchange(&bad.encode().unwrap(), slow, Duration::ZERO)
            .bytes(),
        with_crc("14 86 03")
    );
}

#[test]
fn classic_only_devices_ignore_the_extension() {
    let mut classic = spec("classic", 30, 0x0D00_0030);
    classic.fast = false;
    let mut bus = Bus::new(vec![VirtualDevice::new(classic)], 1);
    assert!(send(&mut bus, &Request::scan_start()).is_empty());
    assert!(send(&mut bus, &poll(0, 0xFF, 0, 0)).is_empty());
    let by_serial = Request::by_serial(
        0x0D00_0030,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert!(send(&mut bus, &by_serial).is_empty());
    let request = enable(30, RegisterType::Coil, 0, vec![EventPriority::High]);
    assert_eq!(
        bus.exchange(&request, master(), Duration::ZERO).bytes(),
        with_crc("1E C6 01")
    );
}

#[test]
fn shared_address_corrupts_classic_replies_but_scan_lists_both() {
    let mut bus = Bus::new(
        vec![
            VirtualDevice::new(spec("a", 20, MCM8_SERIAL)),
            VirtualDevice::new(spec("b", 20, MR6C_SERIAL)),
        ],
        1,
    );
    let read = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 270,
            count: 2,
        },
    );
    let garbage = send(&mut bus, &read);
    assert_eq!(garbage.len(), 9);
    assert!(!crate::protocol::crc::crc_is_valid(&garbage));
    // Identical replies at identical times are still spoiled.
    let same = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert!(!crate::protocol::crc::crc_is_valid(&send(&mut bus, &same)));
    assert_eq!(
        send(&mut bus, &Request::scan_start()),
        cat(ff(22), with_crc("FD 46 03 FE 40 00 AC 14"))
    );
    assert_eq!(
        send(&mut bus, &Request::scan_continue()),
        cat(ff(15), with_crc("FD 46 03 FE D2 A3 A6 14"))
    );
    assert_eq!(
        send(&mut bus, &Request::scan_continue()),
        cat(ff(20), hex("FD 46 04 D3 93"))
    );
}

#[test]
fn devices_at_other_settings_do_not_hear() {
    let mut slow = spec("slow", 5, 0x0D00_0005);
    slow.line = LineSettings::new(9600, Parity::Odd, 1);
    let mut bus = Bus::new(
        vec![
            VirtualDevice::new(spec("fast", 20, MCM8_SERIAL)),
            VirtualDevice::new(slow),
        ],
        1,
    );
    assert_eq!(
        send(&mut bus, &Request::scan_start()),
        cat(ff(22), with_crc("FD 46 03 FE 40 00 AC 14"))
    );
    assert_eq!(
        send(&mut bus, &Request::scan_continue()),
        cat(ff(20), hex("FD 46 04 D3 93"))
    );
    let read = Request::classic(
        5,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert!(send(&mut bus, &read).is_empty());
    let odd = MasterLine::exact(LineSettings::new(9600, Parity::Odd, 1));
    assert_eq!(
        bus.exchange(&read.encode().unwrap(), odd, Duration::ZERO)
            .bytes(),
        with_crc("05 03 02 00 05")
    );
}

#[test]
fn stop_bits_do_not_keep_devices_apart() {
    // A UART checks only the first stop bit: devices at 8N1 and 8N2 both hear a master at
    // either, and both take part in one scan and answer one address.
    let mut one_stop_bit = spec("one", 20, MR6C_SERIAL);
    one_stop_bit.line = LineSettings::new(115_200, Parity::None, 1);
    let mut bus = Bus::new(
        vec![
            VirtualDevice::new(spec("two", 20, MCM8_SERIAL)),
            VirtualDevice::new(one_stop_bit),
        ],
        1,
    );
    for master in [
        MasterLine::exact(LineSettings::new(115_200, Parity::None, 1)),
        MasterLine::exact(FAST_LINE),
    ] {
        let mut exchange = |request: &Request| {
            bus.exchange(&request.encode().unwrap(), master, Duration::ZERO)
                .bytes()
        };
        assert_eq!(
            exchange(&Request::scan_start()),
            cat(ff(22), with_crc("FD 46 03 FE 40 00 AC 14"))
        );
        assert_eq!(
            exchange(&Request::scan_continue()),
            cat(ff(15), with_crc("FD 46 03 FE D2 A3 A6 14"))
        );
        assert_eq!(
            exchange(&Request::scan_continue()),
            cat(ff(20), hex("FD 46 04 D3 93"))
        );
        // The shared address collides, as on a real bus.
        let read = Request::classic(
            20,
            RequestPdu::ReadHoldingRegisters {
                start: 112,
                count: 1,
            },
        );
        assert!(!crate::protocol::crc::crc_is_valid(&exchange(&read)));
    }
    // Each reply keeps its device's own stop bits on the wire.
    let by_serial = |serial| {
        Request::by_serial(
            serial,
            RequestPdu::ReadHoldingRegisters {
                start: 112,
                count: 1,
            },
        )
        .encode()
        .unwrap()
    };
    let reply = bus.exchange(&by_serial(MR6C_SERIAL), master(), Duration::ZERO);
    assert_eq!(
        reply.bursts[0].char_time,
        LineSettings::new(115_200, Parity::None, 1).char_time()
    );
    assert_eq!(reply.bytes(), with_crc("FD 46 09 FE D2 A3 A6 03 02 00 01"));
    let reply = bus.exchange(&by_serial(MCM8_SERIAL), master(), Duration::ZERO);
    assert_eq!(reply.bursts[0].char_time, FAST_LINE.char_time());
    assert_eq!(reply.bytes(), with_crc("FD 46 09 FE 40 00 AC 03 02 00 02"));
}

#[test]
fn faults_drop_corrupt_and_delay() {
    let mut bus = seed_bus();
    let read = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    bus.device_mut(0).unwrap().faults = Faults {
        drop_reply: 1.0,
        ..Faults::default()
    };
    assert!(send(&mut bus, &read).is_empty());
    bus.device_mut(0).unwrap().faults = Faults {
        corrupt_crc: 1.0,
        ..Faults::default()
    };
    assert_eq!(send(&mut bus, &read), hex("14 03 02 00 14 B5 77"));
    bus.device_mut(0).unwrap().faults = Faults {
        delay_reply: 1.0,
        ..Faults::default()
    };
    let late = bus.exchange(&read.encode().unwrap(), master(), Duration::ZERO);
    assert!(late.bursts[0].start > Duration::from_secs(1));
    // A lost event packet stays unconfirmed.
    bus.device_mut(0).unwrap().faults = Faults {
        drop_reply: 1.0,
        ..Faults::default()
    };
    bus.device_mut(1).unwrap().plugged = false;
    assert_eq!(send(&mut bus, &poll(0, 0xFF, 0, 0)), ff(8));
    bus.device_mut(0).unwrap().faults = Faults::default();
    assert_eq!(
        send(&mut bus, &poll(0, 0xFF, 0, 0)),
        cat(ff(8), with_crc("14 46 11 00 01 04 00 0F 00 00"))
    );
}

#[test]
fn line_errors_reach_the_wire_as_drawn() {
    let mut bus = seed_bus();
    let read = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    let clean = hex("14 03 02 00 14 B5 88");
    let faulty = |bus: &mut Bus, faults: Faults| {
        bus.device_mut(0).unwrap().faults = faults;
        send(bus, &read)
    };
    for _ in 0..20 {
        let flipped = faulty(
            &mut bus,
            Faults {
                flip_bit: 1.0,
                ..Faults::default()
            },
        );
        let differing: u32 = flipped
            .iter()
            .zip(&clean)
            .map(|(a, b)| (a ^ b).count_ones())
            .sum();
        assert_eq!(
            (flipped.len(), differing),
            (clean.len(), 1),
            "{flipped:02X?}"
        );
        let cut = faulty(
            &mut bus,
            Faults {
                truncate: 1.0,
                ..Faults::default()
            },
        );
        assert!(!cut.is_empty() && cut.len() < clean.len());
        assert_eq!(cut[..], clean[..cut.len()]);
        let stray = faulty(
            &mut bus,
            Faults {
                glitch: 1.0,
                ..Faults::default()
            },
        );
        assert_eq!(stray.len(), clean.len() + 1);
        assert!(stray[1..] == clean[..] || stray[..clean.len()] == clean[..]);
    }
}

#[test]
fn unplugged_devices_are_silent() {
    let mut bus = seed_bus();
    bus.device_mut(0).unwrap().plugged = false;
    let read = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert!(send(&mut bus, &read).is_empty());
    bus.device_mut(0).unwrap().plugged = true;
    assert_eq!(send(&mut bus, &read), hex("14 03 02 00 14 B5 88"));
}

#[test]
fn register_changes_are_recorded() {
    let mut bus = seed_bus();
    let write = Request::classic(
        20,
        RequestPdu::WriteSingleCoil {
            address: 0,
            value: true,
        },
    );
    send(&mut bus, &write);
    send(&mut bus, &write);
    bus.write_register(1, RegisterType::Input, 0, &[7], Duration::from_secs(2))
        .unwrap();
    let changes = bus.take_changes();
    assert_eq!(changes.len(), 2);
    assert_eq!(changes[0].origin, super::ChangeOrigin::Master);
    assert_eq!((changes[1].address, changes[1].change.new), (241, 7));
    assert!(bus.take_changes().is_empty());
}

/// A request read before a control command but handled after it (the reading thread waited
/// for the bus): its change comes after the command's in the log, as in the devices' history.
#[test]
fn a_request_handled_after_a_control_command_is_logged_after_it() {
    let mut bus = seed_bus();
    let control_at = Duration::from_millis(10);
    crate::sim::control::execute_line(
        &mut bus,
        control_at,
        r#"{"cmd":"set","device":20,"type":"coil","address":0,"value":0}"#,
    );
    let write = Request::classic(
        20,
        RequestPdu::WriteSingleCoil {
            address: 0,
            value: true,
        },
    );
    let read_at = Duration::from_millis(5);
    bus.exchange(&write.encode().unwrap(), master(), read_at);
    let changes = bus.take_changes();
    assert_eq!(changes.len(), 1, "{changes:?}");
    assert_eq!(changes[0].origin, super::ChangeOrigin::Master);
    assert!(changes[0].at > control_at, "{changes:?}");
    // A control change keeps its own time.
    bus.write_register(0, RegisterType::Coil, 0, &[0], Duration::from_millis(1))
        .unwrap();
    assert_eq!(bus.take_changes()[0].at, Duration::from_millis(1));
}

#[test]
fn garbage_never_panics_and_a_corrupt_frame_gets_no_answer() {
    let mut bus = seed_bus();
    let mut rng = super::faults::XorShift64::new(7);
    for _ in 0..20_000 {
        let len = (rng.next_u64() % 40) as usize;
        let mut frame: Vec<u8> = (0..len).map(|_| rng.next_u64() as u8).collect();
        if rng.chance(0.5) && frame.len() > 2 {
            frame[0] = [0xFD, 20, 241, 0][(rng.next_u64() % 4) as usize];
            frame[1] = [0x46, 3, 16, 15][(rng.next_u64() % 4) as usize];
            frame.truncate(frame.len() - 2);
            crate::protocol::crc::append_crc(&mut frame);
        }
        let answer = bus.exchange(&frame, master(), Duration::ZERO);
        if !crate::protocol::crc::crc_is_valid(&frame) {
            assert!(answer.is_empty(), "an answer to {frame:02X?}: {answer:?}");
        }
    }
}

// The half-duplex wire (issue 15, defect 10): frame gaps, requests colliding with replies, and
// replies colliding with each other, byte for byte on virtual time.

fn read_holding(address: u8, start: u16, count: u16) -> Vec<u8> {
    Request::classic(address, RequestPdu::ReadHoldingRegisters { start, count })
        .encode()
        .unwrap()
}

/// Each byte of `frame` sent back to back from `start`, with its arrival time.
fn arrivals_from(start: Duration, line: LineSettings, frame: &[u8]) -> Vec<(Duration, u8)> {
    frame
        .iter()
        .enumerate()
        .map(|(i, &byte)| (start + line.char_time() * (i as u32 + 1), byte))
        .collect()
}

fn and(a: &[u8], b: &[u8]) -> Vec<u8> {
    a.iter().zip(b).map(|(x, y)| x & y).collect()
}

/// The seed bus after the master's read of holding 128 of device 20 at 0 and the silence after
/// it: the device's reply is on the wire.
fn answered_read_of_20() -> (Bus, Wire) {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(20, 128, 1),
        Duration::ZERO
    ));
    (bus, wire)
}

/// Writes `frame` at `at`, then lets the line fall silent; returns whether it collided.
fn write(wire: &mut Wire, bus: &mut Bus, frame: &[u8], at: Duration) -> bool {
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    let collided = wire
        .master_writes(frame, at, master(), &mut respond)
        .collided;
    let deadline = wire.silence_deadline().unwrap();
    wire.on_silence(deadline, &mut respond);
    collided
}

/// A request whose bytes stop for more than 1.5 characters (less than the 3.5 that end a frame)
/// is an incomplete frame to a Modbus RTU slave: discarded, with whatever follows it before the
/// next frame gap. A pause of up to 1.5 characters is fine.
#[test]
fn a_frame_with_a_silence_over_one_and_a_half_characters_is_dropped() {
    let request = read_holding(20, 128, 1);
    let char_time = FAST_LINE.char_time();
    let split = |gap: Duration| {
        let mut bus = seed_bus();
        let mut wire = Wire::new();
        let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
        let start = Duration::from_millis(1);
        wire.master_writes(&request[..3], start, master(), &mut respond);
        let rest_at = start + FAST_LINE.wire_time(3) + gap;
        wire.master_writes(&request[3..], rest_at, master(), &mut respond);
        let deadline = wire.silence_deadline().unwrap();
        wire.on_silence(deadline, &mut respond);
        let answered = !wire.arrivals().is_empty();
        // The next request, after a frame gap, is answered as usual.
        let next_at = deadline + Duration::from_millis(5);
        wire.master_writes(&request, next_at, master(), &mut respond);
        let deadline = wire.silence_deadline().unwrap();
        wire.on_silence(deadline, &mut respond);
        assert!(wire.arrivals().iter().any(|&(at, _)| at > next_at));
        answered
    };
    assert!(split(Duration::ZERO));
    assert!(split(char_time));
    assert!(split(char_time * 3 / 2));
    assert!(!split(char_time * 2));
    assert!(!split(char_time * 3));
}

#[test]
fn requests_written_together_are_one_run_that_nobody_answers() {
    let first = read_holding(20, 128, 1);
    let second = read_holding(241, 128, 1);
    let mut bus = seed_bus();
    // Written at once: the master's UART sends them back to back, with no frame gap between.
    let together = [first.clone(), second.clone()].concat();
    assert!(bus.exchange(&together, master(), Duration::ZERO).is_empty());
    // 0.3 ms apart: the second waits for the first to leave the UART, still no gap.
    let mut wire = Wire::new();
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    wire.master_writes(&first, Duration::ZERO, master(), &mut respond);
    let gap_deadline = wire.silence_deadline().unwrap();
    wire.master_writes(&second, Duration::from_micros(300), master(), &mut respond);
    assert!(wire.silence_deadline().unwrap() > gap_deadline);
    assert!(!wire.on_silence(Duration::MAX, &mut respond));
    assert!(wire.arrivals().is_empty());
    // Either alone is answered.
    assert_eq!(
        bus.exchange(&first, master(), Duration::ZERO).bytes(),
        hex("14 03 02 00 14 B5 88")
    );
}

#[test]
fn a_reply_starts_a_frame_gap_after_the_request_at_least() {
    let slow_line = LineSettings::new(9600, Parity::None, 2);
    let mut slow = spec("slow", 5, 0x0D00_0005);
    slow.line = slow_line;
    let mut bus = Bus::new(vec![VirtualDevice::new(slow)], 1);
    let request = read_holding(5, 128, 1);
    let reply = bus.exchange(&request, MasterLine::exact(slow_line), Duration::ZERO);
    // 500 µs turnaround, but 3.5 characters at 9600 8N2 are 4.01 ms.
    let end = slow_line.wire_time(request.len());
    assert_eq!(reply.bursts[0].start, end + slow_line.char_time() * 7 / 2);
}

#[test]
fn a_request_after_the_reply_is_answered_after_it() {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    let first = read_holding(20, 128, 1);
    assert!(!write(&mut wire, &mut bus, &first, Duration::ZERO));
    let turnaround = Duration::from_micros(500);
    let first_reply_start = FAST_LINE.wire_time(8) + turnaround;
    let first_reply = arrivals_from(first_reply_start, FAST_LINE, &hex("14 03 02 00 14 B5 88"));
    assert_eq!(wire.arrivals(), first_reply);
    // Written 3.5 characters after the last reply byte arrived.
    let second_at = first_reply.last().unwrap().0 + FAST_LINE.frame_gap();
    let second = read_holding(241, 128, 1);
    assert!(!write(&mut wire, &mut bus, &second, second_at));
    let second_reply = arrivals_from(
        second_at + FAST_LINE.wire_time(8) + turnaround,
        FAST_LINE,
        &with_crc("F1 03 02 00 F1"),
    );
    assert_eq!(wire.arrivals(), second_reply);
}

#[test]
fn a_request_right_behind_a_reply_is_its_continuation_to_the_devices() {
    // Device 241 heard device 20's reply: a request that follows it within 3.5 characters is
    // more bytes of that frame to it (a slave delimits frames by silence), so nobody answers.
    let (mut bus, mut wire) = answered_read_of_20();
    let reply_end = wire.arrivals().last().unwrap().0;
    let gap = FAST_LINE.frame_gap();
    let too_soon = reply_end + gap - FAST_LINE.char_time();
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(241, 128, 1),
        too_soon
    ));
    wire.forget_delivered(too_soon);
    assert_eq!(wire.arrivals(), [], "no answer");
    // With the gap kept, the same request is answered.
    let in_time = too_soon + Duration::from_millis(5);
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(241, 128, 1),
        in_time
    ));
    assert!(!wire.arrivals().is_empty());
}

#[test]
fn a_request_written_during_a_reply_collides_with_it() {
    let (mut bus, mut wire) = answered_read_of_20();
    let char_time = FAST_LINE.char_time();
    let reply_start = FAST_LINE.wire_time(8) + Duration::from_micros(500);
    let reply = hex("14 03 02 00 14 B5 88");
    // The second request's first byte goes out with the reply's third.
    let second = read_holding(241, 128, 1);
    let at = reply_start + char_time * 2;
    assert!(write(&mut wire, &mut bus, &second, at));
    // The master reads the wired AND of both where they overlap; devices hear garbage and stay
    // silent (no reply to 241 follows).
    let merged = and(&reply[2..], &second[..5]);
    assert_eq!(
        wire.arrivals(),
        arrivals_from(reply_start + char_time * 2, FAST_LINE, &merged)
    );
    assert!(!crate::protocol::crc::crc_is_valid(
        &[reply[..2].to_vec(), merged].concat()
    ));
}

#[test]
fn a_request_after_the_frame_gap_but_before_the_reply_collides() {
    let (mut bus, mut wire) = answered_read_of_20();
    // 400 µs after the request: past its frame gap (334 µs), 100 µs before the reply starts.
    let at = FAST_LINE.wire_time(8) + Duration::from_micros(400);
    assert!(write(&mut wire, &mut bus, &read_holding(241, 128, 1), at));
    let bytes: Vec<u8> = wire.arrivals().iter().map(|&(_, byte)| byte).collect();
    assert_eq!(bytes.len(), 7);
    assert_ne!(bytes, hex("14 03 02 00 14 B5 88"));
}

#[test]
fn two_devices_at_one_address_merge_by_wired_and() {
    let mut bus = Bus::new(
        vec![
            VirtualDevice::new(spec("a", 20, MCM8_SERIAL)),
            VirtualDevice::new(spec("b", 20, MR6C_SERIAL)),
        ],
        1,
    );
    let request = read_holding(20, 270, 2);
    let reply = bus.exchange(&request, master(), Duration::ZERO);
    let from_a = with_crc("14 03 04 FE 40 00 AC");
    let from_b = with_crc("14 03 04 FE D2 A3 A6");
    let start = FAST_LINE.wire_time(8) + Duration::from_micros(500);
    assert_eq!(
        reply.arrivals(),
        arrivals_from(start, FAST_LINE, &and(&from_a, &from_b))
    );
}

#[test]
fn a_late_reply_merges_with_the_next_reply_by_wired_and() {
    let mut bus = seed_bus();
    let late = Duration::from_millis(20);
    bus.device_mut(0).unwrap().faults = Faults {
        delay_reply: 1.0,
        delay: late,
        ..Faults::default()
    };
    let mut wire = Wire::new();
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(20, 128, 1),
        Duration::ZERO
    ));
    // The second request goes out `late` after the first: both replies start together.
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(241, 128, 1),
        late
    ));
    let start = late + FAST_LINE.wire_time(8) + Duration::from_micros(500);
    let merged = and(&hex("14 03 02 00 14 B5 88"), &with_crc("F1 03 02 00 F1"));
    assert_eq!(wire.arrivals(), arrivals_from(start, FAST_LINE, &merged));
}

/// Overlapping device bytes merge by wired AND with every byte they overlap, whatever the
/// order they were put on the wire in: checked against a scan of every byte already there
/// (what `Wire::transmit` did before it looked only where overlaps can be).
#[test]
fn overlapping_device_bytes_merge_as_a_scan_of_the_whole_wire_would_merge_them() {
    use super::transmission::{Burst, Transmission};
    const ROUNDING: Duration = Duration::from_nanos(100);
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move |bound: u64| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % bound
    };
    for _ in 0..200 {
        let mut wire = Wire::new();
        // (start, char time, byte) as the naive scan keeps them.
        let mut expected: Vec<(Duration, Duration, u8)> = Vec::new();
        for _ in 0..1 + next(6) {
            let char_time = [
                FAST_LINE.char_time(),
                LineSettings::new(9600, Parity::None, 2).char_time(),
            ][usize::from(next(4) == 0)];
            let burst = Burst {
                start: Duration::from_micros(next(20_000)),
                char_time,
                bytes: (0..1 + next(40)).map(|_| next(256) as u8).collect(),
            };
            for (index, &byte) in burst.bytes.iter().enumerate() {
                let start = burst.start + char_time * index as u32;
                let end = start + char_time;
                let mut merged = false;
                for other in expected.iter_mut() {
                    let shared = (other.0 + other.1)
                        .min(end)
                        .saturating_sub(other.0.max(start));
                    if shared > ROUNDING {
                        other.2 &= byte;
                        merged = true;
                    }
                }
                if !merged {
                    let at = expected.partition_point(|other| other.0 <= start);
                    expected.insert(at, (start, char_time, byte));
                }
            }
            wire.transmit(&Transmission {
                bursts: vec![burst],
            });
        }
        let expected: Vec<(Duration, u8)> = expected
            .iter()
            .map(|&(start, char_time, byte)| (start + char_time, byte))
            .collect();
        assert_eq!(wire.arrivals(), expected);
    }
}

// A second master on the bus (the `other_master` control command): its bytes reach the master
// as the wire carries them, the devices answer it, and it collides like anyone else.

/// The other master sends `frame` at `at`, then the line falls silent: (collided, answered).
fn other_master_sends(wire: &mut Wire, bus: &mut Bus, frame: &[u8], at: Duration) -> (bool, bool) {
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    let collided = wire.other_master_sends(frame, at, master(), &mut respond);
    let gap_over = at + FAST_LINE.wire_time(frame.len()) + FAST_LINE.frame_gap();
    (collided, wire.on_silence(gap_over, &mut respond))
}

#[test]
fn another_masters_request_and_its_answer_reach_the_master() {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    let theirs = read_holding(241, 128, 1);
    let at = Duration::from_millis(1);
    assert_eq!(
        other_master_sends(&mut wire, &mut bus, &theirs, at),
        (false, true)
    );
    let reply_start = at + FAST_LINE.wire_time(8) + Duration::from_micros(500);
    let expected = [
        arrivals_from(at, FAST_LINE, &theirs),
        arrivals_from(reply_start, FAST_LINE, &with_crc("F1 03 02 00 F1")),
    ]
    .concat();
    assert_eq!(wire.arrivals(), expected);
    // The master's own request a frame gap after that reply is answered as usual.
    let after = expected.last().unwrap().0 + FAST_LINE.frame_gap();
    wire.forget_delivered(after);
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(20, 128, 1),
        after
    ));
    assert_eq!(
        wire.arrivals().iter().map(|&(_, b)| b).collect::<Vec<_>>(),
        hex("14 03 02 00 14 B5 88")
    );
}

#[test]
fn another_master_talking_over_the_masters_request_garbles_both() {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    let ours = read_holding(20, 128, 1);
    assert!(
        !wire
            .master_writes(&ours, Duration::ZERO, master(), &mut respond)
            .collided
    );
    // Their first byte goes out with our third.
    let at = FAST_LINE.wire_time(2);
    let theirs = read_holding(241, 128, 1);
    assert!(wire.other_master_sends(&theirs, at, master(), &mut respond));
    // Nobody answers either; the master, deaf while it talks, hears only their bytes after
    // its own.
    assert!(!wire.on_silence(Duration::MAX, &mut respond));
    let after_ours = arrivals_from(at, FAST_LINE, &theirs)
        .into_iter()
        .skip(6)
        .collect::<Vec<_>>();
    assert_eq!(wire.arrivals(), after_ours);
}

#[test]
fn another_master_talking_over_a_reply_garbles_it_and_gets_no_answer() {
    let (mut bus, mut wire) = answered_read_of_20();
    let reply_start = FAST_LINE.wire_time(8) + Duration::from_micros(500);
    let reply = hex("14 03 02 00 14 B5 88");
    let at = reply_start + FAST_LINE.char_time() * 3;
    let theirs = read_holding(241, 128, 1);
    assert_eq!(
        other_master_sends(&mut wire, &mut bus, &theirs, at),
        (true, false)
    );
    // The reply's first three bytes had reached the master by then; the rest merge.
    let merged = [and(&reply[3..], &theirs[..4]), theirs[4..].to_vec()].concat();
    assert_eq!(wire.arrivals(), arrivals_from(at, FAST_LINE, &merged));
    // Right behind a reply (within 3.5 characters) is the reply's continuation to the devices.
    let mut wire = Wire::new();
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(20, 128, 1),
        Duration::ZERO
    ));
    let reply_end = wire.arrivals().last().unwrap().0;
    let too_soon = reply_end + FAST_LINE.frame_gap() - FAST_LINE.char_time();
    assert_eq!(
        other_master_sends(&mut wire, &mut bus, &theirs, too_soon),
        (true, false)
    );
}

#[test]
fn the_masters_request_in_another_masters_frame_gap_garbles_both() {
    // The simulator may read the master's bytes after it has put the other master's request on
    // the wire, though they went out before that request's frame gap ended: nobody may have
    // answered it then.
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    let theirs = read_holding(241, 128, 1);
    assert!(!wire.other_master_sends(&theirs, Duration::ZERO, master(), &mut respond));
    let ours = read_holding(20, 128, 1);
    let within_gap = FAST_LINE.wire_time(8) + FAST_LINE.char_time();
    assert!(
        !wire
            .master_writes(&ours, within_gap, master(), &mut respond)
            .answered
    );
    assert!(!wire.on_silence(Duration::MAX, &mut respond));
    // Their bytes had reached the master by then; no answer follows to either.
    assert_eq!(wire.arrivals(), []);
    assert_eq!(bus.stats().answered, 0);
    assert_eq!(bus.stats().other_master_answered, 0);
}

#[test]
fn another_masters_request_followed_within_its_frame_gap_by_a_reply_gets_no_answer() {
    // Device 20 answers the master 5 ms after its request; the other master's read of 241 ends
    // a character before that reply starts: to 241 the reply is more bytes of that frame.
    let mut bus = seed_bus();
    bus.device_mut(0).unwrap().turnaround = Duration::from_millis(5);
    let mut wire = Wire::new();
    assert!(!write(
        &mut wire,
        &mut bus,
        &read_holding(20, 128, 1),
        Duration::ZERO
    ));
    let reply_start = FAST_LINE.wire_time(8) + Duration::from_millis(5);
    let theirs = read_holding(241, 128, 1);
    let at = reply_start - FAST_LINE.char_time() - FAST_LINE.wire_time(8);
    assert_eq!(
        other_master_sends(&mut wire, &mut bus, &theirs, at),
        (false, false)
    );
    assert_eq!(bus.stats().other_master_answered, 0);
}

#[test]
fn a_master_that_listens_may_talk_a_frame_gap_after_the_last_byte_on_the_wire() {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    assert_eq!(wire.quiet_at(master()), FAST_LINE.frame_gap());
    let request = read_holding(20, 128, 1);
    let mut respond = |request: &super::line::ReceivedRequest| bus.handle(request);
    wire.master_writes(&request, Duration::ZERO, master(), &mut respond);
    // The request's frame gap, before the reply is known.
    assert_eq!(
        wire.quiet_at(master()),
        FAST_LINE.wire_time(8) + FAST_LINE.frame_gap()
    );
    wire.on_silence(Duration::MAX, &mut respond);
    let reply_end = wire.arrivals().last().unwrap().0;
    assert_eq!(wire.quiet_at(master()), reply_end + FAST_LINE.frame_gap());
}

#[test]
fn the_masters_request_during_another_masters_exchange_collides() {
    let mut bus = seed_bus();
    let mut wire = Wire::new();
    let theirs = read_holding(241, 128, 1);
    assert_eq!(
        other_master_sends(&mut wire, &mut bus, &theirs, Duration::ZERO),
        (false, true)
    );
    // Ours goes out while device 241 answers them: no answer to ours.
    let their_reply_start = FAST_LINE.wire_time(8) + Duration::from_micros(500);
    let at = their_reply_start + FAST_LINE.char_time();
    assert!(write(&mut wire, &mut bus, &read_holding(20, 128, 1), at));
    assert!(wire.arrivals().iter().all(|&(arrival, _)| arrival
        < their_reply_start + FAST_LINE.wire_time(7) + FAST_LINE.char_time()));
}

/// Continuous read (holding 114 = 1, as a Wiren Board device has it): a read over registers
/// the device lacks answers them as 0xFFFE (bits as 0) as long as it covers one it has; a read
/// of none it has is still refused; a restart turns it off.
#[test]
fn continuous_read_answers_missing_registers_until_a_restart() {
    let mut bus = seed_bus();
    let holding =
        |start, count| Request::classic(20, RequestPdu::ReadHoldingRegisters { start, count });
    let coils = Request::classic(20, RequestPdu::ReadCoils { start: 6, count: 4 });
    let refused = |function: &str| with_crc(&format!("14 {function} 02"));
    assert_eq!(send(&mut bus, &holding(9, 2)), refused("83"));
    assert_eq!(send(&mut bus, &coils), refused("81"));
    let on = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 114,
            value: 1,
        },
    );
    assert_eq!(send(&mut bus, &on), on.encode().unwrap());
    assert_eq!(
        send(&mut bus, &holding(9, 2)),
        with_crc("14 03 04 00 00 FF FE")
    );
    assert_eq!(send(&mut bus, &coils), with_crc("14 01 01 00"));
    assert_eq!(send(&mut bus, &holding(10, 2)), refused("83"));
    bus.device_mut(0).unwrap().reboot();
    assert_eq!(send(&mut bus, &holding(9, 2)), refused("83"));
}

/// Wiren Board templates read the firmware version from input 250.. ("FW Version"): a device
/// whose template has those registers holds the version there too, as in holding 250.
#[test]
fn the_firmware_version_is_in_the_input_registers_a_template_reads_it_from() {
    let mut registers = registers();
    registers.define(RegisterType::Input, 250, 16, false);
    let device = VirtualDevice::new(DeviceSpec {
        registers,
        ..spec("msw", 20, MCM8_SERIAL)
    });
    let version: Vec<u16> = "1.2.3".bytes().map(u16::from).chain([0; 11]).collect();
    let map = device.registers();
    assert_eq!(
        map.read_range(RegisterType::Input, 250, 16),
        Some(version.clone())
    );
    assert_eq!(
        map.read_range(RegisterType::Holding, 250, 16),
        Some(version)
    );
}
