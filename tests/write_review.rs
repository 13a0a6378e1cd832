//! Write-path review: register writes as they reach the bus, for payloads and sequences the
//! other suites do not cover (bit fields written one after another before the first is done,
//! setup bits in a write-only register, values that overflow after scale).

use std::path::Path;
use std::sync::Arc;

use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::TemplateLibrary;
use rtu2mqtt::device::{resolve_config, RegisterType, ResolvedDevice};
use rtu2mqtt::device_updates::{DeviceUpdate, Repeats};
use rtu2mqtt::gateway::device_model::DeviceModel;
use rtu2mqtt::port::{PortEvent, RegisterSpan, RegisterWrite};
use serde_json::{json, Value};

/// One Modbus device (slave 1) with `channels` inline and `settings` (setup …), resolved as
/// the daemon would.
fn device_with(channels: Value, settings: Value) -> ResolvedDevice {
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
    ports.remove(0).devices.remove(0)
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
