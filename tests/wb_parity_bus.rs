//! wb-mqtt-serial's own test suite as an oracle for the bus side: which requests go out (merged
//! reads, holes, `max_read_registers`, reads refused by the device, `unsupported_value`), the
//! Fast Modbus frames (event setup, event polls, confirmation, reboot) and the timing settings
//! that change what the bus carries. Each test names the wb-mqtt-serial test it mirrors
//! (`Suite.Test`, from the `test/` directory of github.com/wirenboard/wb-mqtt-serial: the
//! `.cpp` sources, `configs/*.json`, `modbus_expectations.cpp` and the gold `.dat` files of the
//! frames they exchanged).
//!
//! The configs are wb-mqtt-serial's, resolved by the crate's loader and planned by
//! `gateway::port_plan`; the port's scheduler is driven on a fake clock against a fake device
//! that answers from a register map, and the requests it sends are compared with the frames
//! wb-mqtt-serial sent. Where rtu2mqtt differs on purpose (merging from the first cycle, the
//! keep-alive period, the event poll order), the test asserts rtu2mqtt's behaviour and its
//! comment says what wb-mqtt-serial does and where the choice is documented.

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::TemplateLibrary;
use rtu2mqtt::device::model::ResolvedPort;
use rtu2mqtt::device::resolve_config;
use rtu2mqtt::device_updates::Repeats;
use rtu2mqtt::gateway::device_model::{apply_port_events, stop_unsupported_reads, DeviceModel};
use rtu2mqtt::gateway::port_plan::port_plan;
use rtu2mqtt::port::{
    DevicePlan, EventMode, HealthPolicy, MergeLimits, NextStep, PlannedRead, PortEvent,
    PortScheduler, PortSettings, RegisterSpan,
};
use rtu2mqtt::protocol::fast::{enabled_registers, EventPacket, FastReply, FastRequest};
use rtu2mqtt::protocol::pdu::{pack_bits, unpack_bits};
use rtu2mqtt::protocol::{
    crc16, hex, parse_hex, Event, EventPoll, EventPriority, EventRange, EventSource, ExceptionCode,
    LineSettings, Parity, RegisterType, Reply, Request, RequestBody, RequestPdu, ResponsePdu,
    Transaction, TransactionOutcome,
};
use rtu2mqtt::transport::exchange::{Exchange, LinkConfig};
use serde_json::{json, Value};

// ---------------------------------------------------------------------------------------------
// Helpers: a config, its scheduler, and a fake bus
// ---------------------------------------------------------------------------------------------

/// The port of a config with `devices` (wb-mqtt-serial format, channels inline) on a serial
/// line at `baud` 8N1, resolved as the daemon resolves it.
fn port_with(baud: u32, devices: Value) -> ResolvedPort {
    let config = json!({"ports": [{"path": "/dev/ttyPARITY", "baud_rate": baud, "parity": "N",
        "data_bits": 8, "stop_bits": 1, "devices": devices}]});
    let source = SourceText::from_text(Path::new("wb_parity_bus.json"), &config.to_string());
    let loaded = load_config_source(source, false).expect("config loads");
    let mut ports = resolve_config(&loaded, &TemplateLibrary::default()).expect("config resolves");
    ports.remove(0)
}

/// The scheduler the daemon builds for `port` (`fast_modbus`: the site-wide switch).
fn scheduler(port: &ResolvedPort, fast_modbus: bool) -> PortScheduler {
    let plan = port_plan(port, fast_modbus);
    PortScheduler::new(plan.settings, plan.devices)
}

/// One simulated device: the registers it has (bits as 0/1), and how it answers reads.
#[derive(Default)]
struct FakeDevice {
    address: u8,
    registers: BTreeMap<(RegisterType, u16), u16>,
    /// A read that covers a register the device does not have gets this exception; `None`:
    /// such registers read as 0 (a device that fills holes).
    missing_exception: Option<u8>,
    /// Reads covering exactly these spans get this exception (a device that refuses a read
    /// with holes although it has every register it was asked).
    refused_spans: Vec<(RegisterType, u16, u16, u8)>,
}

impl FakeDevice {
    fn new(address: u8) -> Self {
        Self {
            address,
            ..Self::default()
        }
    }

    fn with(mut self, register_type: RegisterType, addresses: &[u16], value: u16) -> Self {
        for &address in addresses {
            self.registers.insert((register_type, address), value);
        }
        self
    }

    fn strict(mut self, exception: u8) -> Self {
        self.missing_exception = Some(exception);
        self
    }

    fn read(&self, register_type: RegisterType, start: u16, count: u16) -> Result<Vec<u16>, u8> {
        if let Some(&(.., code)) = self
            .refused_spans
            .iter()
            .find(|&&(t, s, c, _)| (t, s, c) == (register_type, start, count))
        {
            return Err(code);
        }
        (start..start + count)
            .map(
                |address| match self.registers.get(&(register_type, address)) {
                    Some(&value) => Ok(value),
                    None => self.missing_exception.map_or(Ok(0), Err),
                },
            )
            .collect()
    }

    fn answer(&self, pdu: &RequestPdu) -> ResponsePdu {
        let (register_type, start, count) = match *pdu {
            RequestPdu::ReadCoils { start, count } => (RegisterType::Coil, start, count),
            RequestPdu::ReadDiscreteInputs { start, count } => {
                (RegisterType::DiscreteInput, start, count)
            }
            RequestPdu::ReadHoldingRegisters { start, count } => {
                (RegisterType::Holding, start, count)
            }
            RequestPdu::ReadInputRegisters { start, count } => (RegisterType::Input, start, count),
            RequestPdu::WriteSingleRegister { address, value } => {
                return ResponsePdu::WriteSingleRegister { address, value }
            }
            RequestPdu::WriteSingleCoil { address, value } => {
                return ResponsePdu::WriteSingleCoil { address, value }
            }
            RequestPdu::WriteMultipleRegisters { start, ref values } => {
                return ResponsePdu::WriteMultipleRegisters {
                    start,
                    count: values.len() as u16,
                }
            }
            RequestPdu::WriteMultipleCoils { start, ref values } => {
                return ResponsePdu::WriteMultipleCoils {
                    start,
                    count: values.len() as u16,
                }
            }
        };
        let function = pdu.function();
        match self.read(register_type, start, count) {
            Err(code) => ResponsePdu::Exception {
                function,
                code: ExceptionCode(code),
            },
            Ok(values) => match register_type {
                RegisterType::Holding => ResponsePdu::ReadHoldingRegisters { values },
                RegisterType::Input => ResponsePdu::ReadInputRegisters { values },
                RegisterType::Coil | RegisterType::DiscreteInput => {
                    let bits: Vec<bool> = values.iter().map(|&v| v != 0).collect();
                    let packed = pack_bits(&bits);
                    if register_type == RegisterType::Coil {
                        ResponsePdu::ReadCoils { packed }
                    } else {
                        ResponsePdu::ReadDiscreteInputs { packed }
                    }
                }
            },
        }
    }
}

/// The bus: the devices, the event packets the next event polls bring, and every request sent.
#[derive(Default)]
struct Bus {
    devices: Vec<FakeDevice>,
    /// Answers to the next event polls (then "no events").
    event_replies: VecDeque<Reply>,
    /// Every request, with when it went out.
    sent: Vec<(Duration, Request)>,
    /// What the scheduler reported.
    events: Vec<PortEvent>,
}

impl Bus {
    fn with(devices: Vec<FakeDevice>) -> Self {
        Self {
            devices,
            ..Self::default()
        }
    }

    fn answer(&mut self, request: &Request) -> TransactionOutcome {
        match &request.body {
            RequestBody::Fast(FastRequest::PollEvents(_)) => TransactionOutcome::Reply(
                self.event_replies
                    .pop_front()
                    .unwrap_or_else(|| Reply::fast(0xFD, FastReply::NoEvents)),
            ),
            RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) => {
                // Every register asked for is enabled (the mask bit of a disabled entry clear).
                let masks = ranges
                    .iter()
                    .flat_map(|range| {
                        let bits: Vec<bool> = range
                            .priorities
                            .iter()
                            .map(|&p| p != EventPriority::Disabled)
                            .collect();
                        pack_bits(&bits)
                    })
                    .collect();
                TransactionOutcome::Reply(Reply::fast(
                    request.address,
                    FastReply::EventsConfigured { masks },
                ))
            }
            RequestBody::Fast(_) => TransactionOutcome::NoReply,
            RequestBody::Classic(pdu) => {
                match self.devices.iter().find(|d| d.address == request.address) {
                    Some(device) => TransactionOutcome::Reply(Reply::classic(
                        request.address,
                        device.answer(pdu),
                    )),
                    None => TransactionOutcome::NoReply,
                }
            }
        }
    }

    /// Runs the scheduler from `now` until `end` (virtual time: each transaction takes its
    /// estimated time, at least 1 ms); returns the time reached.
    fn run(&mut self, scheduler: &mut PortScheduler, mut now: Duration, end: Duration) -> Duration {
        while now < end {
            match scheduler.next(now) {
                NextStep::Transmit(transaction) => {
                    self.sent.push((now, transaction.request.clone()));
                    let outcome = self.answer(&transaction.request);
                    now += transaction.estimated.max(Duration::from_millis(1));
                    self.events.extend(scheduler.complete(now, outcome));
                }
                NextStep::Wait { until } => now = until.max(now + Duration::from_micros(1)),
            }
        }
        now
    }

    /// As [`Self::run`], with the port's device models taking the events as the port task
    /// hands them over, values decoded and reads that answered `unsupported_value` stopped.
    fn run_with_models(
        &mut self,
        scheduler: &mut PortScheduler,
        port: &ResolvedPort,
        end: Duration,
    ) {
        let mut models: Vec<DeviceModel> = port
            .devices
            .iter()
            .enumerate()
            .map(|(i, device)| DeviceModel::new(Arc::new(device.clone()), i, Repeats::None))
            .collect();
        let mut now = Duration::ZERO;
        while now < end {
            match scheduler.next(now) {
                NextStep::Transmit(transaction) => {
                    self.sent.push((now, transaction.request.clone()));
                    let outcome = self.answer(&transaction.request);
                    now += transaction.estimated.max(Duration::from_millis(1));
                    let events = scheduler.complete(now, outcome);
                    let mut updates = Vec::new();
                    apply_port_events(&mut models, events, &mut updates);
                    stop_unsupported_reads(&mut models, scheduler, now);
                }
                NextStep::Wait { until } => now = until.max(now + Duration::from_micros(1)),
            }
        }
    }

    /// Classic reads sent, as (function, start, count), in order.
    fn reads(&self) -> Vec<(u8, u16, u16)> {
        self.sent
            .iter()
            .filter_map(|(_, request)| match &request.body {
                RequestBody::Classic(pdu) => read_of(pdu),
                RequestBody::Fast(_) => None,
            })
            .collect()
    }

    /// Every frame sent, as hex.
    fn frames(&self) -> Vec<String> {
        self.sent
            .iter()
            .map(|(_, request)| hex(&request.encode().expect("encodes")))
            .collect()
    }
}

fn read_of(pdu: &RequestPdu) -> Option<(u8, u16, u16)> {
    match *pdu {
        RequestPdu::ReadCoils { start, count } => Some((1, start, count)),
        RequestPdu::ReadDiscreteInputs { start, count } => Some((2, start, count)),
        RequestPdu::ReadHoldingRegisters { start, count } => Some((3, start, count)),
        RequestPdu::ReadInputRegisters { start, count } => Some((4, start, count)),
        _ => None,
    }
}

/// The reads up to the first one asked again: one poll cycle, sorted (wb-mqtt-serial orders a
/// cycle by register type, rtu2mqtt by channel; the order within a cycle is not compared).
fn first_cycle(reads: &[(u8, u16, u16)]) -> Vec<(u8, u16, u16)> {
    let mut cycle: Vec<(u8, u16, u16)> = Vec::new();
    for read in reads {
        if cycle.contains(read) {
            break;
        }
        cycle.push(*read);
    }
    cycle.sort_unstable();
    cycle
}

/// The distinct reads from the `skip`th on: what a device gets asked once its reads have
/// settled.
fn settled(reads: &[(u8, u16, u16)], skip: usize) -> Vec<(u8, u16, u16)> {
    assert!(reads.len() > skip + 10, "too few reads: {reads:?}");
    let mut settled: Vec<(u8, u16, u16)> = reads[skip..].to_vec();
    settled.sort_unstable();
    settled.dedup();
    settled
}

fn sorted(mut reads: Vec<(u8, u16, u16)>) -> Vec<(u8, u16, u16)> {
    reads.sort_unstable();
    reads
}

fn ms(ms: u64) -> Duration {
    Duration::from_millis(ms)
}

/// A frame in hex with its CRC appended (wb-mqtt-serial's `.dat` frames end with it).
fn with_crc(text: &str) -> String {
    let mut bytes = parse_hex(text).expect("hex");
    let crc = crc16(&bytes);
    bytes.extend_from_slice(&crc.to_le_bytes());
    hex(&bytes)
}

// ---------------------------------------------------------------------------------------------
// TModbusIntegrationTest (configs/config-modbus-test.json)
// ---------------------------------------------------------------------------------------------

/// The channels of wb-mqtt-serial's `configs/config-modbus-test.json` (its `Modbus-sample`
/// device), shared with `tests/wb_parity.rs`.
fn modbus_sample_channels() -> Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/wb_parity/modbus-sample-channels.json");
    serde_json::from_str(&std::fs::read_to_string(path).expect("the fixture")).expect("JSON")
}

/// configs/config-modbus-test.json: one device, `max_read_registers` 0, 9600 8N1, with `extra`
/// device settings (`max_reg_hole` …).
fn modbus_test_port(extra: Value) -> ResolvedPort {
    let mut device = json!({
        "slave_id": 1, "name": "Modbus-sample", "id": "modbus-sample",
        "max_read_registers": 0, "frame_timeout_ms": 0, "response_timeout_ms": 8,
        "channels": modbus_sample_channels()
    });
    if let (Some(device), Some(extra)) = (device.as_object_mut(), extra.as_object()) {
        for (key, value) in extra {
            device.insert(key.clone(), value.clone());
        }
    }
    port_with(9600, json!([device]))
}

/// The device of config-modbus-test.json as modbus_expectations.cpp answers it: every
/// configured register present, the holes between them too (read as 0) unless `strict`.
fn modbus_test_device() -> FakeDevice {
    FakeDevice::new(1)
        .with(RegisterType::Holding, &[4, 5, 6, 7, 8, 9, 18], 1)
        .with(RegisterType::Holding, &(30..34).collect::<Vec<_>>(), 1)
        .with(RegisterType::Holding, &[50, 51, 70], 1)
        .with(RegisterType::Holding, &(90..100).collect::<Vec<_>>(), 1)
        .with(RegisterType::Input, &[40], 0x66)
        .with(RegisterType::Coil, &[0, 1], 1)
        .with(RegisterType::Coil, &(72..82).collect::<Vec<_>>(), 1)
        .with(RegisterType::DiscreteInput, &[20], 1)
}

/// A merged read of the config's registers with `max_reg_hole` 10 and `max_bit_hole` 80.
fn holes_port() -> ResolvedPort {
    modbus_test_port(json!({"max_reg_hole": 10, "max_bit_hole": 80}))
}

/// TModbusIntegrationTest.Holes, second cycle ("holes enabled", gold .dat): holding 4…18 in one
/// read across the 8-register hole (`01 03 00 04 00 0F`), s64 at 30, float at 50, u16 at 70
/// alone (their gaps are 11 and more), and coils 0…81 in one read across the 70-bit hole
/// (`01 01 00 00 00 52`). (Holding 90…99 is checked by the next test.)
#[test]
fn holes_merge_registers_and_coils_within_max_hole() {
    let port = holes_port();
    let mut scheduler = scheduler(&port, false);
    let mut bus = Bus::with(vec![modbus_test_device()]);
    bus.run(&mut scheduler, Duration::ZERO, ms(3000));
    let settled: Vec<_> = settled(&bus.reads(), 20)
        .into_iter()
        .filter(|&(_, start, _)| start < 90)
        .collect();
    assert_eq!(
        settled,
        vec![
            (1, 0, 82),
            (2, 20, 1),
            (3, 4, 15),
            (3, 30, 4),
            (3, 50, 2),
            (3, 70, 1),
            (4, 40, 1),
        ]
    );
}

/// TModbusIntegrationTest.Holes (and every cycle of .Poll/.HolesAutoDisable after the first)
/// has `holding_single` 90…94 and `holding_multi` 95…99 read as two ranges
/// (`01 03 00 5A 00 05`, `01 03 00 5F 00 05`): wb-mqtt-serial never merges registers of
/// different `reg_type`s. rtu2mqtt reads them together (`01 03 00 5A 00 0A`): both are read with
/// function 3 from one table, and `holding_single`/`_multi` choose only the write function. A
/// device that refuses the joint read gets its parts read apart (the refused-read tests).
#[test]
fn holding_single_and_holding_multi_are_read_together() {
    let port = holes_port();
    let mut scheduler = scheduler(&port, false);
    let mut bus = Bus::with(vec![modbus_test_device()]);
    bus.run(&mut scheduler, Duration::ZERO, ms(3000));
    let settled: Vec<_> = settled(&bus.reads(), 20)
        .into_iter()
        .filter(|&(_, start, _)| start >= 90)
        .collect();
    assert_eq!(settled, vec![(3, 90, 10)]);
}

/// TModbusIntegrationTest.Poll (gold .dat, the first cycle) has registers whose availability is
/// not known yet read one value at a time, to find those the device lacks: holding 4, 5, 6 (the
/// three of RGB), 7, 8, 9, 18 one by one, the u64 at 90 and the u16 at 94 apart. rtu2mqtt
/// merges from the first cycle (as later cycles do) and finds a missing register only when a
/// merged read is refused (the refused-read tests): one read fewer per register on a device
/// that has them all, the usual case.
#[test]
fn first_cycle_is_merged_as_the_later_ones() {
    let port = modbus_test_port(json!({}));
    let mut scheduler = scheduler(&port, false);
    let mut bus = Bus::with(vec![modbus_test_device()]);
    bus.run(&mut scheduler, Duration::ZERO, ms(2000));
    assert_eq!(
        first_cycle(&bus.reads()),
        sorted(vec![
            (1, 0, 2),
            (1, 72, 10),
            (2, 20, 1),
            (3, 4, 6),
            (3, 18, 1),
            (3, 30, 4),
            (3, 50, 2),
            (3, 70, 1),
            (3, 90, 10),
            (4, 40, 1),
        ])
    );
}

/// TModbusIntegrationTest.HolesAutoDisable (third cycle, "read without holes"): once the merged
/// read across the hole (holding 4…18) was refused with exception 3, holes are off for the
/// device, and its registers are read in the ranges they make without holes: holding 4…9
/// (`01 03 00 04 00 06`) and 18 (`01 03 00 12 00 01`), not one by one.
#[test]
fn refused_read_with_holes_turns_holes_off_and_keeps_merging() {
    let port = modbus_test_port(json!({"max_reg_hole": 10}));
    let mut scheduler = scheduler(&port, false);
    let mut device = modbus_test_device();
    device.refused_spans.push((RegisterType::Holding, 4, 15, 3));
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(3000));
    let holding_low: Vec<_> = settled(&bus.reads(), 30)
        .into_iter()
        .filter(|&(function, start, _)| function == 3 && start < 30)
        .collect();
    assert_eq!(holding_low, vec![(3, 4, 6), (3, 18, 1)]);
}

/// TModbusIntegrationTest.HolesAutoDisable: the merged read across the hole is the first one
/// refused; rtu2mqtt, like wb-mqtt-serial, asks the registers again (none of them is lost:
/// each value is read and published), and never asks holding 4…18 again.
#[test]
fn refused_read_with_holes_is_not_asked_again_and_its_values_are_read() {
    let port = modbus_test_port(json!({"max_reg_hole": 10}));
    let mut scheduler = scheduler(&port, false);
    let mut device = modbus_test_device();
    device.refused_spans.push((RegisterType::Holding, 4, 15, 3));
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(3000));
    let reads = bus.reads();
    assert_eq!(
        reads.iter().filter(|&&r| r == (3, 4, 15)).count(),
        1,
        "{reads:?}"
    );
    let mut covered = [false; 19];
    for event in &bus.events {
        if let PortEvent::Values { span, .. } = event {
            if span.register_type == RegisterType::Holding && span.start < 19 {
                for address in span.start..span.start + span.count {
                    covered[usize::from(address)] = true;
                }
            }
        }
    }
    for address in [4, 5, 6, 7, 8, 9, 18] {
        assert!(covered[address], "holding {address} read");
    }
    assert!(bus.events.iter().all(|e| !matches!(
        e,
        PortEvent::ReadFailed {
            unsupported: true,
            ..
        }
    )));
}

/// TModbusIntegrationTest.MaxReadRegisters (second cycle, gold .dat): `max_read_registers` 3
/// cuts holding 4…9 into 4…6 and 7…9 (`01 03 00 04 00 03`, `01 03 00 07 00 03`) and coils
/// 72…81 into 72, 75, 78 (3 each) and 81; a value wider than the limit is read whole (the u64
/// at 90: 4 registers, then 94 alone; the u64 at 95, then 99).
#[test]
fn max_read_registers_limits_each_read() {
    let port = modbus_test_port(json!({"max_read_registers": 3}));
    let mut scheduler = scheduler(&port, false);
    let mut bus = Bus::with(vec![modbus_test_device()]);
    bus.run(&mut scheduler, Duration::ZERO, ms(4000));
    assert_eq!(
        settled(&bus.reads(), 30),
        sorted(vec![
            (3, 4, 3),
            (3, 7, 3),
            (3, 18, 1),
            (3, 30, 4),
            (3, 50, 2),
            (3, 70, 1),
            (4, 40, 1),
            (1, 0, 2),
            (1, 72, 3),
            (1, 75, 3),
            (1, 78, 3),
            (1, 81, 1),
            (2, 20, 1),
            (3, 90, 4),
            (3, 94, 1),
            (3, 95, 4),
            (3, 99, 1),
        ])
    );
}

/// wb-mqtt-serial's default `max_read_registers` is 1 (TDeviceConfig, `MaxReadRegisters = 1`):
/// without the key, adjacent registers are read one request each.
#[test]
fn without_max_read_registers_each_register_is_read_alone() {
    let port = port_with(
        9600,
        json!([{"slave_id": 1, "name": "D", "id": "d", "channels": [
            {"name": "A", "reg_type": "holding", "address": 7, "type": "value"},
            {"name": "B", "reg_type": "holding", "address": 8, "type": "value"},
            {"name": "C", "reg_type": "coil", "address": 1, "type": "switch"},
            {"name": "E", "reg_type": "coil", "address": 2, "type": "switch"}
        ]}]),
    );
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 8], 1)
        .with(RegisterType::Coil, &[1, 2], 1);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(1000));
    assert_eq!(
        settled(&bus.reads(), 0),
        vec![(1, 1, 1), (1, 2, 1), (3, 7, 1), (3, 8, 1)]
    );
}

/// TModbusTest.MinReadRegisters (`EnqueueHoldingReadU16Min2ReadResponse`): with
/// `min_read_registers` 2 a single u16 at 110 is read as 2 registers (`01 03 00 6E 00 02`),
/// for devices that refuse shorter reads.
#[test]
fn min_read_registers_pads_a_short_read() {
    let port = port_with(
        9600,
        json!([{"slave_id": 1, "name": "D", "id": "d", "min_read_registers": 2, "channels": [
            {"name": "A", "reg_type": "holding", "address": 110, "format": "u16", "type": "value"}
        ]}]),
    );
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1).with(RegisterType::Holding, &[110, 111], 0x15);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(500));
    assert_eq!(settled(&bus.reads(), 0), vec![(3, 110, 2)]);
}

// ---------------------------------------------------------------------------------------------
// TModbusUnavailableRegistersIntegrationTest (configs/config-modbus-unavailable-registers*.json)
// ---------------------------------------------------------------------------------------------

/// configs/config-modbus-unavailable-registers-test.json: holding 7…12, `max_read_registers` 0,
/// `unsupported_value` 0xFFFE on 7, 9 and 12 when `with_unsupported`.
fn unavailable_port(with_unsupported: bool) -> ResolvedPort {
    let unsupported = |value: Value| {
        if with_unsupported {
            with(value, json!({"unsupported_value": "0xFFFE"}))
        } else {
            value
        }
    };
    port_with(
        9600,
        json!([{"slave_id": 1, "name": "Modbus-sample", "id": "modbus-sample",
        "max_read_registers": 0, "frame_timeout_ms": 0, "response_timeout_ms": 8,
        "channels": [
            unsupported(json!({"name": "White", "reg_type": "holding", "address": 7, "type": "dimmer", "max": "0xff"})),
            {"name": "RGB_All", "reg_type": "holding", "address": 8, "type": "range", "max": 100},
            unsupported(json!({"name": "White1", "reg_type": "holding", "address": 9, "type": "range", "max": 100})),
            {"name": "Voltage", "reg_type": "holding", "address": 10, "type": "text"},
            {"name": "Holding2", "reg_type": "holding", "address": 11, "type": "value"},
            unsupported(json!({"name": "Holding1", "reg_type": "holding", "address": 12, "type": "value"}))
        ]}]),
    )
}

fn with(mut base: Value, extra: Value) -> Value {
    if let (Some(base), Some(extra)) = (base.as_object_mut(), extra.as_object()) {
        for (key, value) in extra {
            base.insert(key.clone(), value.clone());
        }
    }
    base
}

/// TModbusUnavailableRegistersIntegrationTest.UnavailableRegisterOnBorder: holding 12 answers
/// exception 3 and is not read again; 7…11, which the device has, go on being read in one
/// request (`01 03 00 07 00 05`).
#[test]
fn unavailable_register_on_the_border_is_left_out_of_the_range() {
    let port = unavailable_port(false);
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 8, 9, 10, 11], 0x0A)
        .strict(3);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(1500));
    assert_eq!(settled(&bus.reads(), 10), vec![(3, 7, 5)]);
}

/// TModbusUnavailableRegistersIntegrationTest.UnavailableRegisterOnBorder/InTheMiddle: the
/// register the device refuses (exception 3 to a read of it alone) is never read again, and its
/// control gets the read error.
#[test]
fn unavailable_register_is_not_read_again() {
    let port = unavailable_port(false);
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 8, 10, 11, 12], 0x0A)
        .strict(3);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(1500));
    let reads = bus.reads();
    let settled = settled(&reads, 10);
    assert!(
        settled
            .iter()
            .all(|&(_, start, count)| !(start..start + count).contains(&9)),
        "{settled:?}"
    );
    assert!(bus.events.iter().any(|e| matches!(
        e,
        PortEvent::ReadFailed { span, unsupported: true, .. }
            if *span == RegisterSpan::new(RegisterType::Holding, 9, 1)
    )));
}

/// TModbusUnavailableRegistersIntegrationTest.UnavailableRegisterInTheMiddle: holding 9 is
/// refused; the range splits in two and each part is read in one request: 7…8
/// (`01 03 00 07 00 02`) and 10…12 (`01 03 00 0A 00 03`).
#[test]
fn unavailable_register_in_the_middle_splits_the_range_in_two() {
    let port = unavailable_port(false);
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 8, 10, 11, 12], 0x0A)
        .strict(3);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(1500));
    assert_eq!(settled(&bus.reads(), 10), vec![(3, 7, 2), (3, 10, 3)]);
}

/// TModbusUnavailableRegistersIntegrationTest.UnsupportedRegisterOnBorder: 7, 9 and 12 answer
/// their `unsupported_value` 0xFFFE; from then on they are not read: 8 (`01 03 00 08 00 01`)
/// and 10…11 (`01 03 00 0A 00 02`).
#[test]
fn unsupported_value_stops_reading_the_register() {
    let port = unavailable_port(true);
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 9, 12], 0xFFFE)
        .with(RegisterType::Holding, &[8, 10, 11], 0x14);
    let mut bus = Bus::with(vec![device]);
    bus.run_with_models(&mut scheduler, &port, ms(1500));
    assert_eq!(settled(&bus.reads(), 10), vec![(3, 8, 1), (3, 10, 2)]);
}

/// Bit fields of one register share its read: one field at its `unsupported_value` (the low
/// byte 0xFE) stops only itself, the other field (the high byte, 0x12) goes on being read and
/// published. wb-mqtt-serial keeps each field as a register of its own and stops only the
/// unsupported one. Reading the register alone (no other field) stops it, as above.
#[test]
fn an_unsupported_bit_field_does_not_stop_the_other_fields_of_its_register() {
    let port = port_with(
        9600,
        json!([{"slave_id": 1, "name": "Fields", "id": "fields",
        "channels": [
            {"name": "Low", "reg_type": "holding", "address": "20:0:8", "type": "value",
             "unsupported_value": "0xFE"},
            {"name": "High", "reg_type": "holding", "address": "20:8:8", "type": "value"},
            {"name": "Other", "reg_type": "holding", "address": 30, "type": "value"}
        ]}]),
    );
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[20], 0x12FE)
        .with(RegisterType::Holding, &[30], 7);
    let mut bus = Bus::with(vec![device]);
    bus.run_with_models(&mut scheduler, &port, ms(1500));
    let settled = settled(&bus.reads(), 10);
    assert!(
        settled
            .iter()
            .any(|&(_, start, count)| (start..start + count).contains(&20)),
        "register 20 is no longer read: {settled:?}"
    );
}

/// TModbusUnavailableRegistersAndHolesIntegrationTest.HolesAndUnavailable
/// (configs/config-modbus-unavailable-registers-and-holes-test.json, `max_reg_hole` 10): 9 and
/// 11 are refused, the read across the hole (7…12) is refused and turns holes off; what is
/// left is read as 7…8 (`01 03 00 07 00 02`) and 12 (`01 03 00 0C 00 01`).
#[test]
fn holes_and_unavailable_registers_settle_on_the_ranges_left() {
    let port = port_with(
        9600,
        json!([{"slave_id": 1, "name": "Modbus-sample", "id": "modbus-sample",
        "max_read_registers": 0, "frame_timeout_ms": 0, "max_reg_hole": 10,
        "channels": [
            {"name": "White", "reg_type": "holding", "address": 7, "type": "dimmer", "max": "0xff"},
            {"name": "RGB_All", "reg_type": "holding", "address": 8, "type": "range", "max": 100},
            {"name": "White1", "reg_type": "holding", "address": 9, "type": "range", "max": 100},
            {"name": "Holding2", "reg_type": "holding", "address": 11, "type": "value"},
            {"name": "Holding1", "reg_type": "holding", "address": 12, "type": "value"}
        ]}]),
    );
    let mut scheduler = scheduler(&port, false);
    let device = FakeDevice::new(1)
        .with(RegisterType::Holding, &[7, 8, 12], 0x0A)
        .strict(3);
    let mut bus = Bus::with(vec![device]);
    bus.run(&mut scheduler, Duration::ZERO, ms(1500));
    assert_eq!(settled(&bus.reads(), 10), vec![(3, 7, 2), (3, 12, 1)]);
}

// ---------------------------------------------------------------------------------------------
// Fast Modbus: TModbusExtTest (test/modbus_ext_common_test.cpp) and TPollTest (poll_test.cpp)
// ---------------------------------------------------------------------------------------------

/// TModbusExtTest.EventsEnablerOneReg: coil 101 at high priority on device 10 is
/// `0A 46 18 05 01 00 65 01 02 C5 90`; the reply `0A 46 18 01 01 E9 1E` enables it.
#[test]
fn events_enabler_one_register_frame_and_reply() {
    let ranges = vec![EventRange::registers(
        RegisterType::Coil,
        101,
        vec![EventPriority::High],
    )];
    let request = Request::configure_events(10, ranges.clone());
    assert_eq!(
        hex(&request.encode().unwrap()),
        hex(&parse_hex("0A 46 18 05 01 00 65 01 02 C5 90").unwrap())
    );
    let reply = Reply::decode(&parse_hex("0A 46 18 01 01 E9 1E").unwrap()).expect("reply");
    let Reply {
        body:
            rtu2mqtt::protocol::ReplyBody::Fast {
                reply: FastReply::EventsConfigured { masks },
                ..
            },
        ..
    } = reply
    else {
        panic!("not a 0x18 reply: {reply:?}");
    };
    assert_eq!(
        enabled_registers(&masks, &ranges),
        Some(vec![(EventSource::Register(RegisterType::Coil), 101, true)])
    );
}

/// TModbusExtTest.EventsEnablerTwoRanges: coils 101…102 (high) and inputs 103…112 (low, then
/// high from 110) are two records, `0A 46 18 14 01 0065 02 02 02 04 0067 0A 01…01 02 02 02
/// 25 F0`; the reply masks 03 FB 02 leave 105 and 111 disabled.
#[test]
fn events_enabler_two_ranges_frame_and_reply() {
    use EventPriority::{High, Low};
    let ranges = vec![
        EventRange::registers(RegisterType::Coil, 101, vec![High, High]),
        EventRange::registers(
            RegisterType::Input,
            103,
            vec![Low, Low, Low, Low, Low, Low, Low, High, High, High],
        ),
    ];
    let request = Request::configure_events(10, ranges.clone());
    assert_eq!(
        hex(&request.encode().unwrap()),
        hex(&parse_hex(
            "0A 46 18 14 01 00 65 02 02 02 04 00 67 0A 01 01 01 01 01 01 01 02 02 02 25 F0"
        )
        .unwrap())
    );
    let reply = Reply::decode(&parse_hex("0A 46 18 03 03 FB 02 AD 11").unwrap()).expect("reply");
    let Reply {
        body:
            rtu2mqtt::protocol::ReplyBody::Fast {
                reply: FastReply::EventsConfigured { masks },
                ..
            },
        ..
    } = reply
    else {
        panic!("not a 0x18 reply: {reply:?}");
    };
    let enabled = enabled_registers(&masks, &ranges).expect("masks fit");
    let off: Vec<u16> = enabled
        .iter()
        .filter(|(_, _, on)| !on)
        .map(|&(_, address, _)| address)
        .collect();
    assert_eq!(enabled.len(), 12);
    assert_eq!(off, vec![105, 111]);
}

/// A device plan made by hand: `reads` (type, address, high priority), sporadic, no setup.
fn sporadic_device(address: u8, reads: &[(RegisterType, u16, bool)]) -> DevicePlan {
    DevicePlan {
        name: format!("dev{address}"),
        address,
        response_timeout: ms(500),
        merge: MergeLimits {
            max_read_registers: 0,
            max_register_hole: 0,
            max_bit_hole: 0,
            min_read_registers: 1,
        },
        health: HealthPolicy::default(),
        reads: reads
            .iter()
            .map(|&(register_type, start, high)| PlannedRead {
                span: RegisterSpan::new(register_type, start, 1),
                period: high.then(|| ms(1000)),
                rate_limit: None,
                events: EventMode::Sporadic,
                min_firmware: None,
            })
            .collect(),
        setup: Vec::new(),
        continuous_read: false,
        write_retry_time: Duration::from_secs(600),
    }
}

fn settings_115200() -> PortSettings {
    PortSettings::for_line(LineSettings::new(115_200, Parity::None, 2))
}

/// The event registers of `TModbusExtTest.EventsEnablerRangesWithHoles` (type, address, high
/// priority).
const EVENTS_ENABLER_REGISTERS: &[(RegisterType, u16, bool)] = &[
    (RegisterType::Coil, 101, true),
    (RegisterType::Coil, 102, true),
    (RegisterType::Input, 103, false),
    (RegisterType::Input, 104, false),
    (RegisterType::Input, 107, false),
    (RegisterType::Input, 108, false),
    (RegisterType::Input, 109, false),
    (RegisterType::Input, 110, true),
    (RegisterType::Input, 111, true),
    (RegisterType::Input, 112, true),
];

/// TModbusExtTest.EventsEnablerRangesWithHoles, as the driver sends it
/// (TSerialClientEventsReader::EnableEvents: DISABLE_EVENTS_IN_HOLES, then the reboot event
/// disabled): inputs 103, 104, 107…112 share a record with 105…106 at priority 0, but 118…119
/// start a record of their own (wb-mqtt-serial fills a gap of at most 4 registers:
/// `lastAddr + 5 < addr` starts a new one), then `0F 0000 01 00`.
#[test]
fn events_enabler_fills_gaps_of_at_most_four_registers() {
    let mut registers = EVENTS_ENABLER_REGISTERS.to_vec();
    registers.extend([
        (RegisterType::Input, 118, true),
        (RegisterType::Input, 119, true),
    ]);
    let device = sporadic_device(10, &registers);
    let mut scheduler = PortScheduler::new(settings_115200(), vec![device]);
    let NextStep::Transmit(transaction) = scheduler.next(Duration::ZERO) else {
        panic!("the event setup goes first");
    };
    assert_eq!(
        hex(&transaction.request.encode().unwrap()),
        with_crc(
            "0A 46 18 1F 01 00 65 02 02 02 04 00 67 0A 01 01 00 00 01 01 01 02 02 02 \
             04 00 76 02 02 02 0F 00 00 01 00"
        )
    );
}

/// TModbusExtTest.EventsEnablerRangesWithHoles, a gap wb-mqtt-serial fills: 105…106 between
/// inputs 104 and 107 go at priority 0 in the same record.
#[test]
fn events_enabler_fills_a_gap_of_two_with_disabled_entries() {
    let device = sporadic_device(10, EVENTS_ENABLER_REGISTERS);
    let mut scheduler = PortScheduler::new(settings_115200(), vec![device]);
    let NextStep::Transmit(transaction) = scheduler.next(Duration::ZERO) else {
        panic!("the event setup goes first");
    };
    assert_eq!(
        hex(&transaction.request.encode().unwrap()),
        with_crc(
            "0A 46 18 19 01 00 65 02 02 02 04 00 67 0A 01 01 00 00 01 01 01 02 02 02 \
             0F 00 00 01 00"
        )
    );
}

/// One device at 1 with holding 1 `sporadic` (TPollTest's `ONLY_EVENTS`), 115200 8N1.
fn single_sporadic_port() -> ResolvedPort {
    port_with(
        115_200,
        json!([{"slave_id": 1, "name": "device1", "id": "device1", "frame_timeout_ms": 0,
            "channels": [{"name": "R", "reg_type": "holding", "address": 1, "type": "value",
                "sporadic": true}]}]),
    )
}

/// The frames of TPollTest.SingleDeviceSingleRegisterWithEvents (gold .dat).
fn single_sporadic_frames() -> (String, String, String) {
    let setup = hex(&parse_hex("01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D").unwrap());
    let read = hex(&parse_hex("01 03 00 01 00 01 D5 CA").unwrap());
    let poll = hex(&parse_hex("FD 46 10 00 F8 00 00 79 5B").unwrap());
    (setup, read, poll)
}

/// TPollTest.SingleDeviceSingleRegisterWithEvents (gold .dat): the event setup
/// `01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D` (holding 1 at low priority, the reboot
/// event disabled) goes first, holding 1 is read once `01 03 00 01 00 01 D5 CA`, and the rest
/// of the first half second is event polls `FD 46 10 00 F8 00 00 79 5B` only.
#[test]
fn event_setup_one_read_and_event_polls() {
    let port = single_sporadic_port();
    let mut scheduler = scheduler(&port, true);
    let mut bus = Bus::with(vec![FakeDevice::new(1).with(
        RegisterType::Holding,
        &[1],
        0,
    )]);
    bus.run(&mut scheduler, Duration::ZERO, ms(480));
    let frames = bus.frames();
    let (setup, read, poll) = single_sporadic_frames();
    assert_eq!(frames[0], setup);
    assert_eq!(
        frames.iter().filter(|f| **f == read).count(),
        1,
        "{frames:?}"
    );
    assert!(
        frames[1..].iter().all(|f| *f == read || *f == poll),
        "{frames:?}"
    );
    assert!(frames.len() >= 9, "a poll every 50 ms: {frames:?}");
}

/// TPollTest.SingleDeviceSingleRegisterWithEvents (gold .dat) has the first read follow the
/// event setup at once, the event polls after it. rtu2mqtt polls events as soon as they are
/// enabled (an event that is already pending comes at once) and reads next (docs/performance.md,
/// "no event poll before every device is set up").
#[test]
fn an_event_poll_follows_the_event_setup_then_the_first_read() {
    let port = single_sporadic_port();
    let mut scheduler = scheduler(&port, true);
    let mut bus = Bus::with(vec![FakeDevice::new(1).with(
        RegisterType::Holding,
        &[1],
        0,
    )]);
    bus.run(&mut scheduler, Duration::ZERO, ms(100));
    let (setup, read, poll) = single_sporadic_frames();
    assert_eq!(bus.frames()[..3], [setup, poll, read]);
}

/// TPollTest.SingleDeviceSingleRegisterWithEvents (gold .dat) has a device whose values all
/// come by events read again after 500 ms of event polls (the read at 504.67 ms). rtu2mqtt's
/// keep-alive read of such a device comes once a second (docs/performance.md: it only checks
/// that the device is still there, and every read costs the event polls a slot).
#[test]
fn events_only_device_is_read_again_after_a_second() {
    let port = single_sporadic_port();
    let mut scheduler = scheduler(&port, true);
    let mut bus = Bus::with(vec![FakeDevice::new(1).with(
        RegisterType::Holding,
        &[1],
        0,
    )]);
    bus.run(&mut scheduler, Duration::ZERO, ms(600));
    assert_eq!(bus.reads(), vec![(3, 1, 1)]);
    bus.run(&mut scheduler, ms(600), ms(1100));
    assert_eq!(bus.reads(), vec![(3, 1, 1), (3, 1, 1)]);
}

/// TModbusExtTest.ReadEventsNoEventsNoConfirmation / ReadEventsWithConfirmation: the poll
/// confirms the packet it follows: after a packet from device 5 with flag 1 (input 464 = 4),
/// the next request carries `05 01` (confirmed slave id and flag), the one after "no events"
/// `00 00` again; the value is reported as it came, little-endian.
#[test]
fn event_poll_confirms_the_packet_received() {
    let port = port_with(
        115_200,
        json!([{"slave_id": 5, "name": "D", "id": "d", "frame_timeout_ms": 0,
            "channels": [{"name": "I", "reg_type": "input", "address": 464, "type": "value",
                "sporadic": true}]}]),
    );
    let mut scheduler = scheduler(&port, true);
    let mut bus = Bus::with(vec![FakeDevice::new(5).with(
        RegisterType::Input,
        &[464],
        0,
    )]);
    let now = bus.run(&mut scheduler, Duration::ZERO, ms(60));
    // wb-mqtt-serial's reply to the first poll: FF FF FF (arbitration) then this frame.
    let packet =
        Reply::decode(&parse_hex("05 46 11 01 01 06 02 04 01 D0 04 00 2B AC").expect("hex"))
            .expect("event packet");
    bus.event_replies.push_back(packet);
    let polls_before = bus.sent.len();
    bus.run(&mut scheduler, now, now + ms(200));
    let polls: Vec<EventPoll> = bus.sent[polls_before..]
        .iter()
        .filter_map(|(_, r)| match &r.body {
            RequestBody::Fast(FastRequest::PollEvents(poll)) => Some(*poll),
            _ => None,
        })
        .collect();
    assert!(polls.len() >= 3, "{polls:?}");
    assert_eq!((polls[0].ack_address, polls[0].ack_flag), (0, 0));
    assert_eq!((polls[1].ack_address, polls[1].ack_flag), (5, 1));
    assert_eq!((polls[2].ack_address, polls[2].ack_flag), (0, 0));
    assert!(bus.events.iter().any(|e| matches!(
        e,
        PortEvent::EventValue { device: 0, register_type: RegisterType::Input, address: 464, payload }
            if payload == &vec![0x04, 0x00]
    )));
}

/// TModbusExtTest.ReadEventsNoEventsNoConfirmation: the first poll at 115200 asks the whole bus
/// for up to 248 bytes, confirming nothing: `FD 46 10 00 F8 00 00 79 5B`; "no events" is
/// `FD 46 12 52 5D`.
#[test]
fn first_event_poll_frame_at_115200() {
    let poll = Request::poll_events(EventPoll {
        min_address: 0,
        max_data_len: 0xF8,
        ack_address: 0,
        ack_flag: 0,
    });
    assert_eq!(
        hex(&poll.encode().unwrap()),
        hex(&parse_hex("FD 46 10 00 F8 00 00 79 5B").unwrap())
    );
    let reply = Reply::decode(&parse_hex("FD 46 12 52 5D").unwrap()).expect("reply");
    assert_eq!(reply, Reply::fast(0xFD, FastReply::NoEvents));
    // And the second request of ReadEventsWithConfirmation, field for field.
    let poll = Request::poll_events(EventPoll {
        min_address: 5,
        max_data_len: 0x2C,
        ack_address: 5,
        ack_flag: 1,
    });
    assert_eq!(
        hex(&poll.encode().unwrap()),
        hex(&parse_hex("FD 46 10 05 2C 05 01 FB 3F").unwrap())
    );
}

/// TPollTest.ReconnectWithOnlyEvents (and TModbusExtTest.ReadEventsReboot): after the reboot
/// event from device 1 (`01 46 11 00 01 04 00 0F 00 00`), the next poll confirms it (`01 00`);
/// wb-mqtt-serial's starts at the sender (`FD 46 10 01 F8 01 00`), rtu2mqtt's asks the whole bus
/// when no device sits above the sender (the `min_address` rotation, docs/performance.md).
#[test]
fn poll_after_a_packet_confirms_it() {
    let (polls, _) = reboot_scenario();
    assert_eq!(
        (
            polls[1].min_address,
            polls[1].ack_address,
            polls[1].ack_flag
        ),
        (0, 1, 0)
    );
}

/// TPollTest.ReconnectWithOnlyEvents: after the reboot event the poll confirms it (`01 00`),
/// then the device is set up again: the same event setup
/// `01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D`, then holding 1 is read again
/// (`01 03 00 01 00 01 D5 CA`).
#[test]
fn reboot_event_is_confirmed_and_the_device_set_up_again() {
    let (polls, frames) = reboot_scenario();
    assert_eq!((polls[1].ack_address, polls[1].ack_flag), (1, 0));
    let setup = hex(&parse_hex("01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D").unwrap());
    let read = hex(&parse_hex("01 03 00 01 00 01 D5 CA").unwrap());
    let after: Vec<&String> = frames
        .iter()
        .filter(|f| **f == setup || **f == read)
        .collect();
    assert_eq!(after, vec![&setup, &read], "{frames:?}");
}

/// Set up, events polled; then the device reports a reboot. The polls and the frames sent from
/// the reboot packet on.
fn reboot_scenario() -> (Vec<EventPoll>, Vec<String>) {
    let port = single_sporadic_port();
    let mut scheduler = scheduler(&port, true);
    let mut bus = Bus::with(vec![FakeDevice::new(1).with(
        RegisterType::Holding,
        &[1],
        0,
    )]);
    let now = bus.run(&mut scheduler, Duration::ZERO, ms(200));
    let reboot = Reply::decode(&parse_hex(&with_crc("01 46 11 00 01 04 00 0F 00 00")).unwrap())
        .expect("reboot packet");
    assert_eq!(
        reboot,
        Reply::fast(
            1,
            FastReply::Events(EventPacket {
                flag: 0,
                event_count: 1,
                events: vec![Event::reboot()],
            })
        )
    );
    bus.event_replies.push_back(reboot);
    let from = bus.sent.len();
    bus.run(&mut scheduler, now, now + ms(300));
    let sent = &bus.sent[from..];
    let polls = sent
        .iter()
        .filter_map(|(_, r)| match &r.body {
            RequestBody::Fast(FastRequest::PollEvents(poll)) => Some(*poll),
            _ => None,
        })
        .collect();
    let frames = sent
        .iter()
        .map(|(_, r)| hex(&r.encode().unwrap()))
        .collect();
    (polls, frames)
}

// ---------------------------------------------------------------------------------------------
// Timing that changes the bus: guard_interval_us
// ---------------------------------------------------------------------------------------------

/// Two devices at 115200: 1 with `guard_interval_us` 10000, 2 without.
fn guard_port() -> ResolvedPort {
    port_with(
        115_200,
        json!([
            {"slave_id": 1, "name": "Slow", "id": "slow", "guard_interval_us": 10000,
             "channels": [{"name": "R", "reg_type": "holding", "address": 1, "type": "value"}]},
            {"slave_id": 2, "name": "Fast", "id": "fast",
             "channels": [{"name": "R", "reg_type": "holding", "address": 1, "type": "value"}]}
        ]),
    )
}

/// When the transport would send `request`, the line having been busy until 0, with the guard
/// set as the daemon sets it before each transaction (`port_task`: the plan's guard interval
/// of the request's device).
fn transmit_at(port: &ResolvedPort, request: Request) -> Duration {
    let plan = port_plan(port, true);
    let line = plan.settings.line;
    let mut exchange = Exchange::new(LinkConfig::serial(line));
    exchange.set_guard_interval(plan.settings.guard_intervals.before(request.address));
    exchange.line_was_busy(Duration::ZERO);
    let transaction = Transaction::to_device(&line, request, ms(500));
    exchange.start(&transaction).expect("starts");
    exchange.transmit_at()
}

/// TModbusIntegrationTest.GuardInterval / TPollTest.SingleDeviceSeveralRegisters
/// (`RequestDelay`, gold .dat `Sleep(10000)` before each request): a device's requests wait its
/// guard interval of silence after the line was last busy.
#[test]
fn guard_interval_is_kept_before_the_device_requests() {
    let port = guard_port();
    let at = transmit_at(
        &port,
        Request::classic(1, RequestPdu::ReadHoldingRegisters { start: 1, count: 1 }),
    );
    assert!(at >= ms(10), "{at:?}");
}

/// TPollTest.SingleDeviceSingleRegisterWithEvents (gold .dat): with `RequestDelay` 10 ms the
/// event setup waits `Sleep(1000)` and every event poll `Sleep(335)` (3.5 characters), not the
/// device's 10 ms; likewise another device's requests: `guard_interval_us` is the device's own
/// (`SleepSinceLastInteraction(device RequestDelay)`).
#[test]
fn guard_interval_is_the_device_own() {
    let port = guard_port();
    let other = transmit_at(
        &port,
        Request::classic(2, RequestPdu::ReadHoldingRegisters { start: 1, count: 1 }),
    );
    let poll = transmit_at(
        &port,
        Request::poll_events(EventPoll {
            min_address: 0,
            max_data_len: 0xF8,
            ack_address: 0,
            ack_flag: 0,
        }),
    );
    assert!(other < ms(1), "device 2 waits {other:?}");
    assert!(poll < ms(1), "the event poll waits {poll:?}");
}

/// Bits of a read come back as 0/1 words, one per bit asked (coils 0…81 of the holes test).
#[test]
fn bit_reads_unpack_to_one_word_per_bit() {
    let packed = parse_hex("01 00 00 00 00 00 00 00 00 49 02").unwrap();
    let bits = unpack_bits(&packed, 82);
    assert_eq!(bits.len(), 82);
    assert!(bits[0] && !bits[1]);
    // 0x49 0x02 at bits 72…81: coils 72, 75, 78, 81 on (Coil 2, 5, 8, 11 publish 1).
    let on: Vec<usize> = (72..82).filter(|&i| bits[i]).collect();
    assert_eq!(on, vec![72, 75, 78, 81]);
}
