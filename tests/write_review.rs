//! Write-path review: register writes as they reach the bus, for payloads and sequences the
//! other suites do not cover (bit fields written one after another before the first is done,
//! setup bits in a write-only register, values that overflow after scale, a bit the device
//! changes while a write of another bit of its register waits).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::TemplateLibrary;
use rtu2mqtt::device::model::ResolvedPort;
use rtu2mqtt::device::{resolve_config, RegisterType, ResolvedDevice};
use rtu2mqtt::device_updates::{DeviceUpdate, Repeats};
use rtu2mqtt::gateway::device_model::{apply_port_events, DeviceModel};
use rtu2mqtt::gateway::port_plan::port_plan;
use rtu2mqtt::port::{NextStep, PortEvent, PortScheduler, RegisterSpan, RegisterWrite};
use rtu2mqtt::protocol::{
    Reply, RequestBody, RequestPdu, ResponsePdu, Transaction, TransactionOutcome,
};
use serde_json::{json, Value};

/// One Modbus device (slave 1) with `channels` inline and `settings` (setup …), resolved as
/// the daemon would.
fn device_with(channels: Value, settings: Value) -> ResolvedDevice {
    port_with(channels, settings).devices.remove(0)
}

/// The port of [`device_with`]'s device.
fn port_with(channels: Value, settings: Value) -> ResolvedPort {
    let mut device = json!({"name": "Review", "id": "review", "slave_id": 1, "channels": channels});
    if let (Some(device), Some(settings)) = (device.as_object_mut(), settings.as_object()) {
        for (key, value) in settings {
            device.insert(key.clone(), value.clone());
        }
    }
    let config =
        json!({"ports": [{"path": "/dev/ttyREVIEW", "baud_rate": 9600, "devices": [device]}]});
    let source = SourceText::from_text(Path::new("write_review.json"), &config.to_string());
    let loaded = load_config_source(source, false).expect("config loads");
    let mut ports = resolve_config(&loaded, &TemplateLibrary::default()).expect("config resolves");
    ports.remove(0)
}

fn model(device: ResolvedDevice) -> DeviceModel {
    DeviceModel::new(Arc::new(device), 0, Repeats::All)
}

fn apply(model: &mut DeviceModel, event: PortEvent) -> Vec<DeviceUpdate> {
    let mut out = Vec::new();
    model.apply(event, &mut out);
    out
}

fn values(register_type: RegisterType, start: u16, words: &[u16]) -> PortEvent {
    PortEvent::Values {
        device: 0,
        span: RegisterSpan::new(register_type, start, u16::try_from(words.len()).unwrap()),
        values: words.to_vec().into(),
    }
}

/// What the scheduler reports of a write it carried out: done, then its words.
fn done(model: &mut DeviceModel, write: &RegisterWrite) {
    apply(
        model,
        PortEvent::WriteDone {
            device: 0,
            register_type: write.register_type,
            address: write.address,
        },
    );
    apply(
        model,
        values(write.register_type, write.address, &write.values),
    );
}

/// (address, values) of the writes of an accepted payload.
fn take(model: &mut DeviceModel, control: &str, payload: &str) -> Vec<(u16, Vec<u16>)> {
    model
        .take_write(control, payload, &mut Vec::new())
        .unwrap_or_else(|err| panic!("`{payload}` on {control} refused: {err}"))
        .into_iter()
        .map(|w| (w.address, w.values))
        .collect()
}

fn three_bits() -> ResolvedDevice {
    device_with(
        json!([
            {"name": "B0", "reg_type": "holding", "address": "72:0:1", "type": "switch", "format": "u16"},
            {"name": "B1", "reg_type": "holding", "address": "72:1:1", "type": "switch", "format": "u16"},
            {"name": "B2", "reg_type": "holding", "address": "72:2:1", "type": "switch", "format": "u16"}
        ]),
        json!({}),
    )
}

/// Two bit fields of one register set one after the other, the second before the first is
/// written: the scheduler keeps only the latest write of a register, so the second must carry
/// the first field's new bit, not the bit as last read (which would undo the first).
#[test]
fn a_bit_field_written_before_the_last_write_of_its_register_is_done_keeps_it() {
    let mut model = model(three_bits());
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0005]));
    assert_eq!(take(&mut model, "B1", "1"), vec![(72, vec![0x0007])]);
    assert_eq!(take(&mut model, "B2", "0"), vec![(72, vec![0x0003])]);
}

/// The words of a write not yet done stand for its register until the write is shown done
/// (its words read or written back) or given up; then the register's reads count again.
#[test]
fn a_pending_write_stands_for_its_register_until_done_or_given_up() {
    let mut model = model(three_bits());
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0005]));
    let first = model.take_write("B1", "1", &mut Vec::new()).unwrap();
    assert_eq!(first[0].values, vec![0x0007]);
    // A read made before the write went out still shows the old bits: the write stands.
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0005]));
    assert_eq!(take(&mut model, "B2", "0"), vec![(72, vec![0x0003])]);
    // The first write (in flight when the second was queued) is done: the second stands.
    done(&mut model, &first[0]);
    let third = model.take_write("B0", "0", &mut Vec::new()).unwrap();
    assert_eq!(third[0].values, vec![0x0002]);
    // Done; the device then changes a bit itself: the next write goes over the read.
    done(&mut model, &third[0]);
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0082]));
    assert_eq!(take(&mut model, "B2", "1"), vec![(72, vec![0x0086])]);
    // Given up: the device kept what it had, as read.
    apply(
        &mut model,
        PortEvent::WriteFailed {
            device: 0,
            register_type: RegisterType::Holding,
            address: 72,
            permanent: true,
        },
    );
    assert_eq!(take(&mut model, "B0", "1"), vec![(72, vec![0x0083])]);
}

/// A bit field in a register no channel reads goes over what the device's setup wrote there
/// (written on every connect), as wb-mqtt-serial's register cache holds the setup writes: not
/// over zeros, which would clear the setup's bits.
#[test]
fn a_bit_field_in_a_write_only_register_keeps_the_setup_bits() {
    let device = device_with(
        json!([{"name": "Mode", "reg_type": "holding", "write_address": "100:4:4",
            "format": "u16", "type": "value"}]),
        json!({"setup": [{"title": "low", "address": "100:0:4", "value": 3}]}),
    );
    assert!(device.channels[0].write_only);
    let mut model = model(device);
    assert_eq!(take(&mut model, "Mode", "5"), vec![(100, vec![0x0053])]);
}

/// A bit field over two registers no channel reads, one of them with a write not yet done:
/// that write's bits stay, the other register's unknown bits are zeros.
#[test]
fn a_wide_bit_field_keeps_a_pending_write_in_one_of_its_registers() {
    let device = device_with(
        json!([
            {"name": "Low", "reg_type": "holding", "write_address": "101:0:4",
             "format": "u16", "type": "value"},
            {"name": "Wide", "reg_type": "holding", "write_address": "100:8:16",
             "format": "u16", "type": "value"}
        ]),
        json!({}),
    );
    let mut model = model(device);
    assert_eq!(take(&mut model, "Low", "5"), vec![(101, vec![0x0005])]);
    assert_eq!(
        take(&mut model, "Wide", "4660"),
        vec![(100, vec![0x0012, 0x3405])]
    );
}

/// The `/on` message for bit 1 of register 72 arrives while a read of the register is out,
/// the write composed over the 0x0004 the model knows; the read shows that the device has set
/// bit 4 meanwhile (0x0014). The write that goes out keeps bit 4 (0x0016): the one composed
/// when the message arrived (0x0006) would clear it. The model then holds the words written,
/// shows bit 4 still set, and its next write goes over them.
#[test]
fn a_bit_field_write_keeps_a_bit_the_device_set_while_it_waited() {
    let (mut scheduler, mut models) = scheduled(json!([
        {"name": "B1", "reg_type": "holding", "address": "72:1:1", "type": "switch", "format": "u16"},
        {"name": "B4", "reg_type": "holding", "address": "72:4:1", "type": "switch", "format": "u16"}
    ]));
    let mut registers = BTreeMap::from([(72u16, 0x0004u16)]);
    let mut written = Vec::new();
    let mut published = Vec::new();
    let mut reads = 0;
    let mut now = Duration::ZERO;
    let mut run = |scheduler: &mut PortScheduler,
                   models: &mut Vec<DeviceModel>,
                   registers: &mut BTreeMap<u16, u16>,
                   until_writes: usize| {
        for _ in 0..10_000 {
            if written.len() >= until_writes {
                return;
            }
            let transaction = next_transaction(scheduler, &mut now);
            let body = &transaction.request.body;
            match body {
                RequestBody::Classic(RequestPdu::ReadHoldingRegisters { .. }) => {
                    reads += 1;
                    if reads == 2 {
                        // The message arrives while the second read is out; the device has
                        // set bit 4 since the first.
                        let writes = models[0]
                            .take_write("B1", "1", &mut Vec::new())
                            .expect("accepted");
                        assert_eq!(writes.len(), 1);
                        assert_eq!(writes[0].values, [0x0006], "composed over 0x0004");
                        for write in writes {
                            assert_eq!(scheduler.queue_write(now, write), None);
                        }
                        registers.insert(72, 0x0014);
                    }
                }
                RequestBody::Classic(RequestPdu::WriteSingleRegister { value, .. }) => {
                    written.push(*value);
                }
                _ => {}
            }
            let pdu = holding_answer(registers, body);
            now += transaction.estimated;
            let address = transaction.request.address;
            published.extend(complete_for(scheduler, models, now, address, pdu));
        }
        panic!("no write went out");
    };
    run(&mut scheduler, &mut models, &mut registers, 1);
    assert_eq!(written, [0x0016], "bit 4, set by the device, is kept");
    assert_eq!(registers[&72], 0x0016);
    assert_eq!(
        published
            .iter()
            .rev()
            .find(|(id, _)| id == "B4")
            .map(|(_, v)| v.as_str()),
        Some("1"),
        "bit 4 shown as the device holds it"
    );
    // The model's next bit-field write goes over the words written, not over its own.
    let next = models[0]
        .take_write("B1", "0", &mut Vec::new())
        .expect("accepted");
    assert_eq!(next[0].values, [0x0014]);
}

/// A bit field's write carries the mask of its bits, and a read that shows its bits before it
/// went does not settle it (the device may change them again before it goes): a bit field of
/// the register written next goes over the pending write, not over that read, so the write
/// that replaces both in the scheduler still sets the first field.
#[test]
fn a_read_showing_a_pending_bit_field_by_chance_does_not_settle_it() {
    let mut model = model(three_bits());
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0000]));
    let first = model.take_write("B1", "1", &mut Vec::new()).unwrap();
    assert_eq!(first[0].values, [0x0002]);
    assert_eq!(first[0].defined, [0x0002]);
    // The device sets bit 1 itself, then clears it, before the write goes.
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0002]));
    apply(&mut model, values(RegisterType::Holding, 72, &[0x0000]));
    assert_eq!(take(&mut model, "B2", "1"), vec![(72, vec![0x0006])]);
}

/// A `holding_single` u32 counter at 10–11 (65535) and a channel on its low word: `/on` 65536
/// goes out as 11 ← 0 then 10 ← 1 (one 0x06 per register, the last first), and the counter is
/// never published as 0, the value made of the new 11 and the old 10 that the device was
/// never given; it is published as 65536 once both registers hold their words.
#[test]
fn a_value_written_one_register_at_a_time_is_published_only_whole() {
    let (mut scheduler, mut models) = scheduled(json!([
        {"name": "Counter", "reg_type": "holding_single", "address": 10, "format": "u32", "type": "value"},
        {"name": "Low", "reg_type": "holding", "address": 11, "type": "value", "readonly": true}
    ]));
    let mut registers = BTreeMap::from([(10u16, 0u16), (11, 0xFFFF)]);
    let mut written = Vec::new();
    let mut published: Vec<(String, String)> = Vec::new();
    let mut now = Duration::ZERO;
    let mut queued = false;
    for _ in 0..10_000 {
        if written.len() == 2 && published.iter().any(|(_, v)| v == "65536") {
            break;
        }
        if !queued
            && published
                .iter()
                .any(|(id, v)| id == "Counter" && v == "65535")
        {
            let writes = models[0]
                .take_write("Counter", "65536", &mut Vec::new())
                .expect("accepted");
            for write in writes {
                assert_eq!(scheduler.queue_write(now, write), None);
            }
            queued = true;
        }
        let transaction = next_transaction(&mut scheduler, &mut now);
        let body = &transaction.request.body;
        if let RequestBody::Classic(RequestPdu::WriteSingleRegister { address, value }) = body {
            written.push((*address, *value));
        }
        let pdu = holding_answer(&mut registers, body);
        now += transaction.estimated;
        let address = transaction.request.address;
        published.extend(complete_for(&mut scheduler, &mut models, now, address, pdu));
    }
    assert_eq!(written, [(11, 0), (10, 1)], "last register first");
    let counter: Vec<&str> = published
        .iter()
        .filter(|(id, _)| id == "Counter")
        .map(|(_, v)| v.as_str())
        .collect();
    assert!(
        !counter.contains(&"0"),
        "half-written value published: {counter:?}"
    );
    assert_eq!(
        counter.iter().rev().find(|v| **v != "65535"),
        Some(&"65536")
    );
}

/// A device's answer to `request`, holding registers `registers`: a read of them, or a single
/// register written there.
fn holding_answer(registers: &mut BTreeMap<u16, u16>, request: &RequestBody) -> ResponsePdu {
    match request {
        RequestBody::Classic(RequestPdu::ReadHoldingRegisters { start, count }) => {
            ResponsePdu::ReadHoldingRegisters {
                values: (*start..*start + *count)
                    .map(|a| registers.get(&a).copied().unwrap_or(0))
                    .collect(),
            }
        }
        RequestBody::Classic(RequestPdu::WriteSingleRegister { address, value }) => {
            registers.insert(*address, *value);
            ResponsePdu::WriteSingleRegister {
                address: *address,
                value: *value,
            }
        }
        other => panic!("unexpected request {other:?}"),
    }
}

/// Completes the transaction in flight with `pdu` from `address` at `now` and hands its
/// events to `models`: the (control, value) published.
fn complete_for(
    scheduler: &mut PortScheduler,
    models: &mut [DeviceModel],
    now: Duration,
    address: u8,
    pdu: ResponsePdu,
) -> Vec<(String, String)> {
    let events = scheduler.complete(now, TransactionOutcome::Reply(Reply::classic(address, pdu)));
    let mut out = Vec::new();
    apply_port_events(models, events, &mut out);
    out.into_iter()
        .filter_map(|update| match update {
            DeviceUpdate::Value {
                control_id, value, ..
            } => Some((control_id.to_string(), value.to_string())),
            _ => None,
        })
        .collect()
}

/// The scheduler of [`port_with`]'s port with `channels`, and its device's model.
fn scheduled(channels: Value) -> (PortScheduler, Vec<DeviceModel>) {
    let port = port_with(channels, json!({}));
    let plan = port_plan(&port, false);
    let scheduler = PortScheduler::new(plan.settings, plan.devices);
    let models = vec![DeviceModel::new(
        Arc::new(port.devices[0].clone()),
        0,
        Repeats::All,
    )];
    (scheduler, models)
}

/// The scheduler's next transaction, `now` moved on through its waits.
fn next_transaction(scheduler: &mut PortScheduler, now: &mut Duration) -> Transaction {
    for _ in 0..10_000 {
        match scheduler.next(*now) {
            NextStep::Transmit(transaction) => return transaction,
            NextStep::Wait { until } => *now = until.max(*now + Duration::from_millis(1)),
        }
    }
    panic!("the scheduler sends nothing");
}
