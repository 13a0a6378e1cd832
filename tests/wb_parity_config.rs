//! wb-mqtt-serial's config parser tests as an oracle: each test restates one expectation of
//! `TConfigParserTest` (`test/serial_config_test.cpp` of github.com/wirenboard/wb-mqtt-serial,
//! the gold prints `test/TConfigParserTest.*.dat`, the configs `test/configs/*.json` and the
//! templates `test/device-templates/*.json`, `test/parser_test/templates/*.json` they load) and
//! checks rtu2mqtt resolves the config the same way. The templates are restated in
//! `tests/data/wb_parity/templates/` (same `device_type`s, only what the test needs); the
//! configs are written inline.
//!
//! A test marked `#[ignore = "differs from wb-mqtt-serial: …"]` asserts wb-mqtt-serial's
//! behaviour where rtu2mqtt does otherwise: it fails with `--ignored`.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::TemplateLibrary;
use rtu2mqtt::device::ResolvedPort;
use rtu2mqtt::device::{resolve_config, Reading, RegisterType, ResolvedChannel, ResolvedDevice};
use serde_json::{json, Value};

// ---------------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------------

fn templates_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/wb_parity/templates")
}

/// Loads and resolves `config` as the daemon would, with the fixture templates.
fn try_load(config: &Value) -> Result<Vec<ResolvedPort>, String> {
    let source = SourceText::from_text(Path::new("wb_parity_config.json"), &config.to_string());
    let loaded = load_config_source(source, false).map_err(|err| err.to_string())?;
    let library = TemplateLibrary::load_dirs(&[templates_dir()]);
    resolve_config(&loaded, &library).map_err(|err| err.to_string())
}

fn load(config: &Value) -> Vec<ResolvedPort> {
    try_load(config).unwrap_or_else(|err| panic!("config is refused: {err}"))
}

/// A config of one serial port `/dev/ttyNSC0` with `devices`, as wb-mqtt-serial's tests write.
fn one_port(devices: Value) -> Value {
    json!({"ports": [{"path": "/dev/ttyNSC0", "baud_rate": 9600, "devices": devices}]})
}

fn devices(config: &Value) -> Vec<ResolvedDevice> {
    load(config)
        .into_iter()
        .flat_map(|port| port.devices)
        .collect()
}

fn device(config: &Value) -> ResolvedDevice {
    let mut all = devices(config);
    assert_eq!(all.len(), 1, "one device expected");
    all.remove(0)
}

/// (title, address, words) of every setup write, in write order.
fn setup(device: &ResolvedDevice) -> Vec<(String, u16, Vec<u16>)> {
    device
        .setup
        .iter()
        .map(|item| {
            (
                item.title.clone(),
                item.register.address,
                item.words.clone(),
            )
        })
        .collect()
}

/// (address, words) of every setup write, in write order.
fn setup_writes(device: &ResolvedDevice) -> Vec<(u16, Vec<u16>)> {
    device
        .setup
        .iter()
        .map(|item| (item.register.address, item.words.clone()))
        .collect()
}

fn item(title: &str, address: u16, words: &[u16]) -> (String, u16, Vec<u16>) {
    (title.to_string(), address, words.to_vec())
}

fn channel<'a>(device: &'a ResolvedDevice, id: &str) -> &'a ResolvedChannel {
    device
        .channel(id)
        .unwrap_or_else(|| panic!("no channel {id} in {}", device.id))
}

/// The read rate limit a channel's registers get: its own, else its device's (which holds
/// the port's when the device has none).
fn rate_limit(device: &ResolvedDevice, id: &str) -> Option<Duration> {
    channel(device, id)
        .read_rate_limit
        .or(device.timing.read_rate_limit)
}

fn refused(config: &Value) -> String {
    match try_load(config) {
        Ok(_) => panic!("config is accepted, wb-mqtt-serial refuses it"),
        Err(err) => err,
    }
}

fn error_value_device(error_value: Value) -> Value {
    one_port(json!([{
        "name": "ErrorValueTest", "id": "ErrorValueTest", "slave_id": "0x91",
        "channels": [{
            "name": "c", "reg_type": "holding", "address": "0x00", "type": "switch",
            "error_value": error_value
        }]
    }]))
}

const MS: fn(u64) -> Duration = Duration::from_millis;

// ---------------------------------------------------------------------------------------------
// Setup items
// ---------------------------------------------------------------------------------------------

/// TConfigParserTest.SameSetupItems: a config setup item at the address of a template setup
/// item replaces it ("s2 override" 100 at 9992, not the template's 0xfff2); the template's
/// other item stays, its value 10 with scale 2 written as 5.
#[test]
fn same_setup_items_config_item_replaces_template_item_at_its_address() {
    let dev = device(&one_port(json!([{
        "device_type": "with setup", "slave_id": 2,
        "setup": [{"title": "s2 override", "address": 9992, "value": 100}]
    }])));
    assert_eq!(dev.id, "with setup_2");
    assert_eq!(dev.name, "with setup 2");
    assert_eq!(
        setup(&dev),
        vec![item("s2 override", 9992, &[100]), item("s3", 9995, &[5])]
    );
}

/// TConfigParserTest.SetupCondition (device 1): a setup item whose `condition` is false (the
/// parameter has no value) is not written; the unconditional one is.
#[test]
fn setup_condition_false_leaves_the_item_out() {
    let dev = device(&one_port(json!([
        {"device_type": "setup with condition", "slave_id": 1}
    ])));
    assert_eq!(dev.id, "setup with condition_1");
    assert_eq!(setup(&dev), vec![item("s3", 9995, &[5])]);
}

/// TConfigParserTest.SetupCondition (device 2, `p1` 1): the conditional setup item, the
/// parameter and the other setup item, written in address order (s2 9992, p1 9993, s3 9995).
#[test]
fn setup_condition_true_writes_items_and_parameters_in_address_order() {
    let dev = device(&one_port(json!([
        {"device_type": "setup with condition", "slave_id": 2, "p1": 1}
    ])));
    assert_eq!(
        setup(&dev),
        vec![
            item("s2", 9992, &[0xfff2]),
            item("p1", 9993, &[1]),
            item("s3", 9995, &[5]),
        ]
    );
}

/// TConfigParserTest.ParseReadonlyParameters: `readonly` parameters are never written (p1 is
/// only used by conditions, p4 has an address), of p2/p3 only the one whose condition holds:
/// a single setup item, p2.
#[test]
fn readonly_parameters_are_not_written() {
    let dev = device(&one_port(json!([{
        "device_type": "readonly parameters", "slave_id": 2, "p1": 1, "p2": 3, "p3": 2
    }])));
    assert_eq!(setup(&dev), vec![item("p2", 9996, &[3])]);
}

// ---------------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------------

/// TConfigParserTest.ParametersAsArray: parameters as an array, two declarations of `p2`
/// with exclusive conditions; with `p1` 1 the second one (9997) is written.
#[test]
fn parameters_as_array_write_the_declaration_in_effect() {
    let dev = device(&one_port(json!([{
        "device_type": "parameters array", "slave_id": 2, "p1": 1, "p2": 3
    }])));
    assert_eq!(dev.id, "parameters array_2");
    assert_eq!(
        setup(&dev),
        vec![item("p1", 9992, &[1]), item("p2", 9997, &[3])]
    );
}

/// TConfigParserTest.ParametersFwVariants (device 2): declarations of one parameter that
/// differ by `fw` are variants of it; a value only the newest variant allows (p1 2, p2 5,
/// p3 7) is accepted and written.
#[test]
fn parameter_fw_variants_accept_values_of_the_newest_variant() {
    let dev = device(&one_port(json!([{
        "device_type": "parameters fw variants", "slave_id": 2, "p1": 2, "p2": 5, "p3": 7
    }])));
    assert_eq!(dev.id, "parameters fw variants_2");
    assert_eq!(
        setup_writes(&dev),
        vec![(20, vec![2]), (21, vec![5]), (22, vec![7])]
    );
}

/// TConfigParserTest.ParametersFwVariants (device 3): values of the oldest variants are
/// written; `p2`'s condition is false, so its value (99, allowed by no variant) is neither
/// checked nor written.
#[test]
fn parameter_fw_variants_skip_a_parameter_whose_condition_is_false() {
    let dev = device(&one_port(json!([{
        "device_type": "parameters fw variants", "slave_id": 3, "p1": 1, "p2": 99, "p3": 3
    }])));
    assert_eq!(setup_writes(&dev), vec![(20, vec![1]), (22, vec![3])]);
}

// ---------------------------------------------------------------------------------------------
// Channels, registers, timing
// ---------------------------------------------------------------------------------------------

/// TConfigParserTest.ParseModbusDevideWithWriteAddress: a channel with `write_address` is
/// read at `address` (110) and written at `write_address` (115).
#[test]
fn write_address_is_where_the_channel_is_written() {
    let dev = device(&one_port(json!([{
        "name": "WriteAddressTest", "id": "WriteAddressTest", "slave_id": "0x92",
        "channels": [{
            "name": "Holding U16 with write_address", "reg_type": "holding",
            "address": 110, "write_address": 115, "type": "value", "format": "u16"
        }]
    }])));
    assert_eq!(dev.slave_id, 0x92);
    let register = &dev.channels[0].registers[0];
    assert_eq!(register.read.as_ref().map(|r| r.address), Some(110));
    assert_eq!(register.write.as_ref().map(|r| r.address), Some(115));
}

/// TConfigParserTest.ParametersAsArray / SetupCondition: the device defaults the gold prints
/// (MaxRegHole 0, MaxBitHole 0, MaxReadRegisters 1, MinReadRegisters 1, GuardInterval 0,
/// DeviceTimeout 3000, Response timeout 500 — printed as -1, "unset", by newer versions —,
/// Frame timeout 20), and the template channel: `Temperature`, type value, order 1, read-only
/// input 0x504 as s32, big-endian words, scale 1, no error value.
#[test]
fn template_device_defaults() {
    let dev = device(&one_port(json!([{
        "device_type": "parameters array", "slave_id": 2, "p1": 1, "p2": 3
    }])));
    let t = &dev.timing;
    assert_eq!(t.max_reg_hole, 0);
    assert_eq!(t.max_bit_hole, 0);
    assert_eq!(t.max_read_registers, 1);
    assert_eq!(t.min_read_registers, 1);
    assert_eq!(t.guard_interval, Duration::ZERO);
    assert_eq!(t.device_timeout, Some(MS(3000)));
    assert_eq!(t.response_timeout, MS(500));
    assert_eq!(t.frame_timeout, MS(20));
    let temp = channel(&dev, "Temperature");
    assert_eq!(temp.name, "Temperature");
    assert_eq!(temp.control_type, "value");
    assert_eq!(temp.order, 1);
    assert!(temp.readonly);
    assert_eq!(temp.min, None);
    assert_eq!(temp.max, None);
    let reg = &temp.registers[0];
    let read = reg.read.as_ref().expect("read register");
    assert_eq!((read.reg_type, read.address), (RegisterType::Input, 1284));
    assert!(reg.write.is_none());
    assert_eq!(format!("{:?}", reg.codec.format), "S32");
    assert_eq!(format!("{:?}", reg.codec.word_order), "BigEndian");
    assert_eq!(reg.codec.scale, 1.0);
    assert_eq!(reg.codec.offset, 0.0);
    assert_eq!(reg.codec.round_to, 0.0);
    assert_eq!(reg.codec.error_value, None);
    assert_eq!(reg.codec.unsupported_value, None);
}

/// TConfigParserTest.Parse (OnValueTest, LC-103, WB-MRGB): `slave_id` "0x90" is 144,
/// `on_value` 500 kept; coils and discrete inputs as switches (the discrete one read-only);
/// an `rgb` channel of `consists_of` registers in the order given (1, 0, 2); a `readonly`
/// holding register is not written; `max_reg_hole`/`max_bit_hole` from the config.
#[test]
fn parse_custom_devices() {
    let config = json!({"ports": [
        {"path": "/dev/ttyNSC0", "baud_rate": 9600, "stop_bits": 2, "devices": [
            {"name": "OnValueTest", "id": "OnValueTest", "slave_id": "0x90",
             "channels": [{"name": "Relay 1", "reg_type": "holding", "address": "0x00",
                           "type": "switch", "on_value": 500}]}
        ]},
        {"path": "/dev/ttyNSC1", "baud_rate": 9600, "devices": [
            {"name": "LC-103", "id": "lc103", "slave_id": "0x04", "channels": [
                {"name": "Relay 1", "reg_type": "coil", "address": "0x00", "type": "switch"},
                {"name": "Switch AC In", "reg_type": "discrete", "address": "0x00"}
            ]},
            {"name": "WB-MRGB", "id": "wb-mrgb", "slave_id": 2,
             "max_reg_hole": 2, "max_bit_hole": 2, "channels": [
                {"name": "RGB", "type": "rgb", "consists_of": [
                    {"reg_type": "holding", "address": 1},
                    {"reg_type": "holding", "address": 0},
                    {"reg_type": "holding", "address": 2}
                ]},
                {"name": "Button 1 counter", "reg_type": "holding", "readonly": true,
                 "address": 32, "type": "value"}
            ]}
        ]}
    ]});
    let all = devices(&config);
    let on_value = &all[0];
    assert_eq!(
        (on_value.id.as_str(), on_value.slave_id),
        ("OnValueTest", 144)
    );
    let relay = channel(on_value, "Relay 1");
    assert_eq!(relay.control_type, "switch");
    assert_eq!(relay.registers[0].codec.on_value, Some(500));
    assert!(!relay.readonly);

    let lc103 = &all[1];
    assert_eq!(lc103.slave_id, 4);
    let coil = channel(lc103, "Relay 1");
    assert_eq!(coil.control_type, "switch");
    assert_eq!(
        coil.registers[0].read.as_ref().unwrap().reg_type,
        RegisterType::Coil
    );
    assert!(!coil.readonly);
    let discrete = channel(lc103, "Switch AC In");
    assert_eq!(discrete.control_type, "switch");
    assert_eq!(
        discrete.registers[0].read.as_ref().unwrap().reg_type,
        RegisterType::DiscreteInput
    );
    assert!(discrete.readonly);
    assert_eq!(discrete.order, 2);

    let mrgb = &all[2];
    assert_eq!((mrgb.timing.max_reg_hole, mrgb.timing.max_bit_hole), (2, 2));
    let rgb = channel(mrgb, "RGB");
    assert_eq!(rgb.control_type, "rgb");
    let addresses: Vec<u16> = rgb
        .registers
        .iter()
        .map(|r| r.read.as_ref().unwrap().address)
        .collect();
    assert_eq!(addresses, vec![1, 0, 2]);
    let counter = channel(mrgb, "Button 1 counter");
    assert!(counter.readonly);
    assert!(counter.registers[0].write.is_none());
}

/// TConfigParserTest.ParseRateLimit: a register's read rate limit is the channel's
/// (`read_rate_limit_ms`, legacy `poll_interval`), else the device's, else the port's: port
/// `poll_interval` 10 / device `poll_interval` 200 / channel 300 → 200 and 300, the other
/// device 10; port `read_rate_limit_ms` 101 with device `poll_interval` 201, channel 301;
/// port 102, device `read_rate_limit_ms` 202, channel `poll_interval` 302; port 103, device
/// 203, channel `read_rate_limit_ms` 303; no limit at all on the last port.
#[test]
fn read_rate_limit_channel_then_device_then_port() {
    let dev = |slave: u32, extra: Value| {
        let mut d = json!({"device_type": "rate limit", "slave_id": slave});
        for (k, v) in extra.as_object().unwrap() {
            d[k] = v.clone();
        }
        d
    };
    let config = json!({"ports": [
        {"path": "/dev/ttyNSC0", "poll_interval": 10, "devices": [
            dev(2, json!({"poll_interval": 200,
                          "channels": [{"name": "Illuminance", "poll_interval": 300}]})),
            dev(1, json!({}))
        ]},
        {"path": "/dev/ttyNSC1", "read_rate_limit_ms": 101, "devices": [
            dev(3, json!({"poll_interval": 201,
                          "channels": [{"name": "Illuminance", "poll_interval": 301}]})),
            dev(10, json!({}))
        ]},
        {"path": "/dev/ttyNSC2", "read_rate_limit_ms": 102, "devices": [
            dev(4, json!({"read_rate_limit_ms": 202,
                          "channels": [{"name": "Illuminance", "poll_interval": 302}]}))
        ]},
        {"path": "/dev/ttyNSC3", "read_rate_limit_ms": 103, "devices": [
            dev(5, json!({"read_rate_limit_ms": 203,
                          "channels": [{"name": "Illuminance", "read_rate_limit_ms": 303}]}))
        ]},
        {"path": "/dev/ttyNSC4", "devices": [dev(6, json!({}))]}
    ]});
    let all = devices(&config);
    let limits: Vec<(u8, Option<Duration>, Option<Duration>)> = all
        .iter()
        .map(|d| {
            (
                d.slave_id,
                rate_limit(d, "Temp 1"),
                rate_limit(d, "Illuminance"),
            )
        })
        .collect();
    let some = |v: u64| Some(MS(v));
    assert_eq!(
        limits,
        vec![
            (2, some(200), some(300)),
            (1, some(10), some(10)),
            (3, some(201), some(301)),
            (10, some(101), some(101)),
            (4, some(202), some(302)),
            (5, some(203), some(303)),
            (6, None, None),
        ]
    );
    // A rate limit is no read period.
    assert!(all
        .iter()
        .all(|d| d.channels.iter().all(|c| c.read_period.is_none())));
}

/// TConfigParserTest.ParseMaxPublishInterval (devices 1 and 2): `max_publish_interval` in a
/// template (device and channel) and on a config device is accepted (wb-mqtt-serial publishes
/// an unchanged value again after that many seconds, per channel; rtu2mqtt says, in a warning,
/// that its top-level `max_unchanged_interval` applies instead).
#[test]
fn max_publish_interval_is_accepted_on_a_config_device() {
    let config = one_port(json!([
        {"device_type": "max_publish_interval_test", "slave_id": 1},
        {"device_type": "max_publish_interval_test", "slave_id": 2, "max_publish_interval": 30},
        {"device_type": "max_publish_interval_test", "slave_id": 3,
         "channels": [{"name": "Own", "max_publish_interval": 3}]}
    ]));
    assert_eq!(devices(&config).len(), 3);
    // Said, as it is not applied per device.
    let source = SourceText::from_text(Path::new("wb_parity_config.json"), &config.to_string());
    let loaded = load_config_source(source, false).expect("loads");
    let library = TemplateLibrary::load_dirs(&[templates_dir()]);
    let (_, warnings) = rtu2mqtt::device::configure::resolve_config_checked(&loaded, &library);
    let said: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    assert!(
        said.iter()
            .any(|w| w.contains("devices[1].max_publish_interval")
                && w.contains("max_publish_interval is not applied per device")),
        "{said:?}"
    );
}

/// TConfigParserTest.ParseMaxPublishInterval (device 1): a template with
/// `max_publish_interval` loads and its channels are all there.
#[test]
fn max_publish_interval_in_a_template_loads() {
    let dev = device(&one_port(json!([
        {"device_type": "max_publish_interval_test", "slave_id": 1}
    ])));
    assert_eq!(dev.id, "max-publish-interval_1");
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Inherited", "Own"]);
}

// ---------------------------------------------------------------------------------------------
// Configs wb-mqtt-serial refuses (TConfigParserTest.UnsuccessfulParse)
// ---------------------------------------------------------------------------------------------

/// unsuccessful-0: a negative `error_value`.
#[test]
fn refuses_negative_error_value() {
    refused(&error_value_device(json!(-4)));
}

/// unsuccessful-1: a negative `error_value` as a string.
#[test]
fn refuses_negative_error_value_string() {
    refused(&error_value_device(json!("-4")));
}

/// unsuccessful-2: an `error_value` that is no number.
#[test]
fn refuses_error_value_text() {
    refused(&error_value_device(json!("blah")));
}

/// unsuccessful-3: an `error_value` above 32 bits (4294967296).
#[test]
fn refuses_error_value_above_32_bits() {
    refused(&error_value_device(json!(4_294_967_296_u64)));
}

/// unsuccessful-7: a setup item without `address` (in a subdevice channel's override).
#[test]
fn refuses_setup_item_without_address_in_subdevice() {
    refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "device_type": "subdevice1",
                      "setup": [{"title": "bad", "value": 10}]}]
    }])));
}

/// unsuccessful-7, on the device itself: a setup item without `address`.
#[test]
fn refuses_setup_item_without_address() {
    refused(&one_port(json!([{
        "device_type": "with setup", "slave_id": 2,
        "setup": [{"title": "bad", "value": 10}]
    }])));
}

/// unsuccessful-11: a `required` parameter missing (first device), though the second device
/// of the same template has it.
#[test]
fn refuses_missing_required_parameter() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "with conditions"},
        {"slave_id": 23, "device_type": "with conditions", "param1": 1}
    ])));
    assert!(err.contains("param1"), "{err}");
}

/// unsuccessful-12: a parameter value outside its `enum` (second device, 1 where 11 or 12
/// are allowed).
#[test]
fn refuses_parameter_value_outside_enum() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "with conditions", "param1": 2, "param3": 11},
        {"slave_id": 23, "device_type": "with conditions", "param1": 2, "param3": 1}
    ])));
    assert!(err.contains("param3"), "{err}");
}

/// unsuccessful-14: a value no fw variant of the parameter allows (`p1` 7). rtu2mqtt refuses
/// it too, but for another reason: it takes the fw variants for duplicate declarations (see
/// `fw_variants_template_with_allowed_values_loads`).
#[test]
fn refuses_value_of_no_fw_variant() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "fw variants", "p1": 7}
    ])));
    assert!(err.contains("p1"), "{err}");
}

/// unsuccessful-15: a value out of range of the newest fw variant (`p2` 20, max 10). Refused
/// by rtu2mqtt for the reason of unsuccessful-14.
#[test]
fn refuses_value_out_of_range_of_newest_fw_variant() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "fw variants", "p2": 20}
    ])));
    assert!(err.contains("p2"), "{err}");
}

/// unsuccessful-17: two declarations of a parameter with different conditions both in effect
/// (`p1` 1 makes `p1==1` and `p1>0` true) are a duplicate definition, not fw variants.
#[test]
fn refuses_overlapping_declarations_that_are_no_fw_chain() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "fw variants condition overlap", "p1": 1}
    ])));
    assert!(err.contains("p2"), "{err}");
}

/// TConfigParserTest.ParametersFwVariants: the fixture of unsuccessful-14/15 with values
/// every variant allows loads (so the refusals above are about the values).
#[test]
fn fw_variants_template_with_allowed_values_loads() {
    let dev = device(&one_port(json!([
        {"slave_id": 22, "device_type": "fw variants", "p1": 1, "p2": 3}
    ])));
    assert_eq!(setup_writes(&dev), vec![(10, vec![1]), (11, vec![3])]);
}

/// TConfigParserTest.MergeDeviceConfigWithTemplate (merge_template_ok14): with no parameter in
/// the config, the `default` of the first declaration of a parameter with fw variants (0)
/// decides conditions: channel `c2` (`p1==1`) is left out.
#[test]
fn fw_variants_default_of_first_declaration_decides_conditions() {
    let dev = device(&one_port(
        json!([{"device_type": "fw variants", "slave_id": 7}]),
    ));
    assert_eq!(
        (dev.id.as_str(), dev.name.as_str()),
        ("fw-variants_7", "fw variants 7")
    );
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["c1"]);
    assert!(dev.setup.is_empty());
}

// ---------------------------------------------------------------------------------------------
// Merging a config device with its template (TConfigParserTest.MergeDeviceConfigWithTemplate)
// ---------------------------------------------------------------------------------------------

/// merge_template_ok2 / res2 with TConfigParserTest.SetupCondition's order: the template's
/// channels and setup items; the setup is written in address order (CONFIG-FLAG 9999 before
/// IODIR 10000, declared the other way round); id and name are the template's with the slave
/// id.
#[test]
fn merge_template_setup_written_in_address_order() {
    let dev = device(&one_port(json!([
        {"device_type": "merge simple with setup", "slave_id": 2}
    ])));
    assert_eq!(dev.id, "merge-simple-with-setup_2");
    assert_eq!(dev.name, "merge simple with setup 2");
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Voltage", "Temperature"]);
    assert_eq!(
        setup(&dev),
        vec![
            item("CONFIG-FLAG", 9999, &[1]),
            item("IODIR", 10000, &[0xffff])
        ]
    );
}

/// merge_template_ok3 / res3: the config's `id` and `name` replace the template's, an extra
/// channel comes after the template's, an extra setup item joins the template's (written in
/// address order: 9999, 10000, 50000).
#[test]
fn merge_template_config_id_name_extra_channel_and_setup() {
    let dev = device(&one_port(json!([{
        "device_type": "merge simple with setup", "slave_id": 2, "id": "1", "name": "2",
        "channels": [{"name": "New channel", "reg_type": "input", "address": "0x0506",
                      "format": "s32"}],
        "setup": [{"title": "new setup", "address": 50000, "value": "0xffff"}]
    }])));
    assert_eq!((dev.id.as_str(), dev.name.as_str()), ("1", "2"));
    let ids: Vec<(&str, u32)> = dev
        .channels
        .iter()
        .map(|c| (c.id.as_str(), c.order))
        .collect();
    assert_eq!(
        ids,
        vec![("Voltage", 1), ("Temperature", 2), ("New channel", 3)]
    );
    let new = channel(&dev, "New channel");
    assert_eq!(new.registers[0].read.as_ref().unwrap().address, 0x0506);
    assert_eq!(
        setup_writes(&dev),
        vec![
            (9999, vec![1]),
            (10000, vec![0xffff]),
            (50000, vec![0xffff])
        ]
    );
}

/// merge_template_ok4 / res4: a subdevice's channels come in (named after the subdevice
/// channel, "Sub c1"), shifted by its `shift` (0x500 + 100), and its setup items with them:
/// named and shifted the same way (wb-mqtt-serial's `LoadSetupItem` prefixes the title with
/// the subdevice name and loads the register with the subdevice's base address), written in
/// address order.
#[test]
fn merge_template_subdevice_channels_and_setup() {
    let dev = device(&one_port(
        json!([{"device_type": "merge subdevice", "slave_id": 2}]),
    ));
    assert_eq!(dev.id, "merge-subdevice_2");
    let channels: Vec<(&str, u16)> = dev
        .channels
        .iter()
        .map(|c| (c.id.as_str(), c.registers[0].read.as_ref().unwrap().address))
        .collect();
    assert_eq!(
        channels,
        vec![
            ("Voltage", 0x500),
            ("Temperature", 0x504),
            ("Sub c1", 0x500 + 100),
            ("Sub c2", 0x504 + 100),
        ]
    );
    assert_eq!(
        setup(&dev),
        vec![
            item("Sub s2", 9999 + 100, &[1]),
            item("Sub s1", 10000 + 100, &[0xffff]),
        ]
    );
}

/// merge_template_ok5 / res5: a subdevice channel overridden in the config: its channel `c1`
/// gets `poll_interval` 100 (a read rate limit), `c2` is disabled (no control), and a setup
/// item added to the subdevice is written with the subdevice's own (shifted like them).
#[test]
fn merge_template_subdevice_overrides() {
    let dev = device(&one_port(json!([{
        "device_type": "merge subdevice", "slave_id": 2,
        "channels": [{
            "name": "Sub", "device_type": "subdevice1",
            "channels": [
                {"name": "c1", "poll_interval": 100},
                {"enabled": false, "name": "c2"}
            ],
            "setup": [{"address": 20000, "title": "31", "value": "0xffff"}]
        }]
    }])));
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Voltage", "Temperature", "Sub c1"]);
    assert_eq!(channel(&dev, "Sub c1").read_rate_limit, Some(MS(100)));
    assert_eq!(
        setup(&dev),
        vec![
            item("Sub s2", 9999 + 100, &[1]),
            item("Sub s1", 10000 + 100, &[0xffff]),
            item("Sub 31", 20000 + 100, &[0xffff]),
        ]
    );
}

/// merge_template_ok8 / res8: no parameter given: every channel whose `condition` reads a
/// parameter is left out (only `c1`), nothing is written.
#[test]
fn merge_template_conditions_without_parameters() {
    let dev = device(&one_port(
        json!([{"device_type": "merge condition", "slave_id": 2}]),
    ));
    assert_eq!(dev.id, "merge-condition_2");
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["c1"]);
    assert!(dev.setup.is_empty());
}

/// merge_template_ok9 / res9: `param1` 1 brings channels c2 and c3 and is written (0x401).
#[test]
fn merge_template_conditions_with_a_parameter() {
    let dev = device(&one_port(json!([
        {"device_type": "merge condition", "slave_id": 2, "param1": 1}
    ])));
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["c1", "c2", "c3"]);
    assert_eq!(setup(&dev), vec![item("p1", 0x401, &[1])]);
}

/// merge_template_ok10 / res10: `param3` (condition `param1==1`) is written too, after p1.
#[test]
fn merge_template_conditional_parameter_written_when_its_condition_holds() {
    let dev = device(&one_port(json!([
        {"device_type": "merge condition", "slave_id": 2, "param1": 1, "param3": 3}
    ])));
    assert_eq!(
        setup(&dev),
        vec![item("p1", 0x401, &[1]), item("p3", 0x403, &[3])]
    );
}

/// merge_template_ok12 / res12: a value for a parameter whose condition is false (`param3`
/// with `param1` 2) is not written, and not refused; `c5` (`param1==2&&param2==3`) stays out
/// as `param2` has no value.
#[test]
fn merge_template_parameter_of_false_condition_is_ignored() {
    let dev = device(&one_port(json!([
        {"device_type": "merge condition", "slave_id": 2, "param1": 2, "param3": 3}
    ])));
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["c1"]);
    assert_eq!(setup(&dev), vec![item("p1", 0x401, &[2])]);
}

/// merge_template_ok13 / res13: two parameters at one address (param1 1, param2 2 whose
/// condition holds): both are in wb-mqtt-serial's merged config; of a register written twice
/// the first declared is kept (docs/migrating.md, "Of two parameters on one address"), so
/// address 10 gets 1.
#[test]
fn merge_template_two_parameters_on_one_address() {
    let dev = device(&one_port(json!([
        {"device_type": "with conditions", "slave_id": 2, "param1": 1, "param2": 2}
    ])));
    assert_eq!(dev.id, "with conditions_2");
    assert_eq!(setup_writes(&dev), vec![(10, vec![1])]);
}

/// TConfigParserTest (parse_test_preserve_setup_order.json with config-preserve-setup-order):
/// `preserve_setup_order` writes the setup items as declared (100, 300, 200), not in address
/// order.
#[test]
fn preserve_setup_order_writes_in_declared_order() {
    let dev = device(&one_port(json!([
        {"device_type": "preserve setup order", "slave_id": 1}
    ])));
    assert_eq!(
        setup(&dev),
        vec![
            item("s_third", 100, &[3]),
            item("s_first", 300, &[1]),
            item("s_second", 200, &[2]),
        ]
    );
}

/// UnsuccessfulParse's schema (unsuccessful-0…3): an `error_value` is a number 0…4294967295
/// or a "0x…" string; a hex string is accepted.
#[test]
fn error_value_as_hex_string_is_accepted() {
    let dev = device(&error_value_device(json!("0xFFFF")));
    assert_eq!(dev.channels[0].registers[0].codec.error_value, Some(0xFFFF));
}

/// UnsuccessfulParse's schema (unsuccessful-3): any `error_value` up to 4294967295 passes,
/// whatever the register's width, and it is compared with the raw register value as it is
/// (`TRegister::SetValue`: `ErrorValue.value() == value`): 70000 on a 16-bit register never
/// matches, so a read of 4464 (70000 cut to 16 bits) is a value.
#[test]
fn error_value_wider_than_the_register_never_matches() {
    let dev = device(&one_port(json!([{
        "name": "ErrorValueTest", "id": "ErrorValueTest", "slave_id": "0x91",
        "channels": [{"name": "c", "reg_type": "holding", "address": "0x00", "type": "value",
                      "error_value": 70000}]
    }])));
    assert_eq!(
        dev.channels[0].decode(&[&[4464]]).expect("decodes"),
        Reading::Value("4464".into())
    );
}

/// TConfigParserTest.SameSetupItems / SetupCondition / ParametersAsArray (the port lines of
/// the gold): a port given only its `path` is `</dev/ttyNSC0 9600 8 N 1>`, reopened after 2
/// failed cycles (ConnectionMaxFailCycles) and 5000 ms (MaxFailTime), no guard interval,
/// response timeout and read rate limit.
#[test]
fn port_defaults() {
    let ports = load(&json!({"ports": [{"path": "/dev/ttyNSC0", "devices": [
        {"device_type": "with setup", "slave_id": 2}
    ]}]}));
    let port = &ports[0].config;
    assert_eq!(port.path.as_deref(), Some("/dev/ttyNSC0"));
    assert_eq!(
        (port.baud_rate, port.data_bits, port.stop_bits),
        (9600, 8, 1)
    );
    assert_eq!(port.parity, rtu2mqtt::protocol::Parity::None);
    assert_eq!(port.connection_max_fail_cycles, 2);
    assert_eq!(port.connection_timeout_ms, 5000);
    assert_eq!(port.guard_interval_us, None);
    assert_eq!(port.response_timeout_ms, None);
    assert_eq!(port.read_rate_limit_ms, None);
    assert_eq!(ports[0].devices[0].timing.read_rate_limit, None);
}

// ---------------------------------------------------------------------------------------------
// Subdevices (TConfigParserTest.UnsuccessfulParse with test/parser_test/templates/subdevice.json,
// restated in tests/data/wb_parity/templates/subdevice.json)
// ---------------------------------------------------------------------------------------------

/// unsuccessful-4: slot `Sub1` takes only `subdevice1`; `subdevice2` is refused (wb: the
/// schema's `device_type` enum of the slot).
#[test]
fn refuses_subdevice_type_the_slot_does_not_take() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "device_type": "subdevice2"}]
    }])));
    assert!(err.contains("devices[0].channels[0].device_type"), "{err}");
    assert!(err.contains("subdevice1"), "{err}");
}

/// unsuccessful-5 and unsuccessful-10 (the same config): slot `Sub2` may be `subdevice3`, whose
/// `required` parameter `s12` is not given (wb: "Missing required property 's12'" at
/// `[channels][0]`).
#[test]
fn refuses_missing_required_parameter_of_a_subdevice() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub2", "device_type": "subdevice3"}]
    }])));
    assert!(err.contains("devices[0].channels[0]"), "{err}");
    assert!(err.contains("s12"), "{err}");
}

/// unsuccessful-5 with `s12` given: the same slot loads, and `s12` is written at its address
/// shifted by the slot's `shift` (20000 + 100), in address order with the setup of `Sub1`'s
/// own nested subdevice `c2` (shifted 100 + 200).
#[test]
fn subdevice_with_its_required_parameter_loads() {
    let dev = device(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub2", "device_type": "subdevice3", "s12": 7}]
    }])));
    assert_eq!(
        setup(&dev),
        vec![
            item("Sub1 c2 s22", 9992 + 300, &[2]),
            item("Sub2 s12", 20000 + 100, &[7]),
            item("Sub1 c2 s12", 20000 + 300, &[0xfff2]),
        ]
    );
    assert!(dev.channel("Sub2 c12").is_some());
}

/// unsuccessful-6: a setup item without `value` in a subdevice (wb: `"Sub1 bad" bad value ""`).
#[test]
fn refuses_setup_item_without_value_in_subdevice() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "device_type": "subdevice1",
                      "setup": [{"title": "bad", "address": 10}]}]
    }])));
    assert!(err.contains("channels[0].setup[0]"), "{err}");
}

/// unsuccessful-8: slot `Sub2` (a `oneOf` slot) overridden without `device_type`, with a
/// setup item that has no address: refused for the missing `device_type`, as wb-mqtt-serial
/// refuses it (its schema, and `CheckDeviceType`: `'… channel "Sub2"' must contain
/// device_type`).
#[test]
fn refuses_one_of_slot_override_without_device_type() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub2", "setup": [{"title": "bad", "value": 10}]}]
    }])));
    assert!(err.contains("devices[0].channels[0]"), "{err}");
    assert!(
        err.contains("overrides subdevice slot `Sub2` without saying which subdevice it holds"),
        "{err}"
    );
}

/// unsuccessful-8 without the setup item: a `oneOf` slot overridden without `device_type` is
/// refused on its own (it used to take the slot's default subdevice, a leniency wb-mqtt-serial
/// does not have); the error says what to add, the choices and the template's default.
#[test]
fn refuses_one_of_slot_override_without_device_type_alone() {
    for channel in [
        json!({"name": "Sub2", "channels": [{"name": "c11", "enabled": false}]}),
        json!({"name": "Sub2", "enabled": false}),
    ] {
        let err = refused(&one_port(json!([{
            "device_type": "subdevice", "slave_id": 2, "channels": [channel]
        }])));
        assert!(err.contains("devices[0].channels[0]"), "{err}");
        assert!(
            err.contains(r#"add "device_type": one of "subdevice1", "subdevice2", "subdevice3" (the template's default is "subdevice1")"#),
            "{err}"
        );
    }
}

/// A slot of one subdevice type (`Sub1`) overridden without `device_type` is refused, as
/// wb-mqtt-serial refuses it (`CheckDeviceType`: `'"subdevice 2" channel "Sub1"' device_type
/// must be 'subdevice1'`), though there is no choice to make; with it, the override applies.
#[test]
fn single_type_slot_override_needs_its_device_type() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "enabled": false}]
    }])));
    assert!(
        err.contains(r#"add "device_type": "subdevice1" (the only subdevice this slot takes)"#),
        "{err}"
    );
    let dev = device(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "device_type": "subdevice1",
                      "setup": [{"title": "own", "address": 1, "value": 3}]}]
    }])));
    assert!(setup(&dev).contains(&item("Sub1 own", 101, &[3])));
}

/// unsuccessful-9: `c11`, a plain channel of subdevice1, given a `device_type` (wb:
/// `'"subdevice 2" Sub1 channel "c11"' can't contain device_type`).
#[test]
fn refuses_device_type_on_a_plain_subdevice_channel() {
    let err = refused(&one_port(json!([{
        "device_type": "subdevice", "slave_id": 2,
        "channels": [{"name": "Sub1", "device_type": "subdevice1",
                      "channels": [{"name": "c11", "device_type": "subdevice1"}]}]
    }])));
    assert!(
        err.contains("devices[0].channels[0].channels[0].device_type"),
        "{err}"
    );
}

/// unsuccessful-13: `param4` declared twice, unconditionally and with `param1==4`; with
/// `param1` 4 both apply (wb: `duplicate definition of parameter "param4" in device
/// template`).
#[test]
fn refuses_two_declarations_in_effect() {
    let err = refused(&one_port(json!([
        {"slave_id": 22, "device_type": "with conditions", "param1": 4}
    ])));
    assert!(err.contains("param4"), "{err}");
}

/// unsuccessful-13's template with `param1` 1: only the unconditional `param4` applies, so
/// the template loads.
#[test]
fn two_declarations_one_in_effect_load() {
    let dev = device(&one_port(json!([
        {"slave_id": 22, "device_type": "with conditions", "param1": 1, "param2": 1, "param4": 5}
    ])));
    assert_eq!(setup_writes(&dev), vec![(4, vec![5]), (10, vec![1])]);
}

// ---------------------------------------------------------------------------------------------
// MergeDeviceConfigWithTemplate (test/parser_test/merge_template_ok*.json / res*.json), the
// cases not restated above
// ---------------------------------------------------------------------------------------------

/// merge_template_ok1 / res1: a template device with nothing in the config: the template's
/// channels, id and name with the slave id, no setup.
#[test]
fn merge_template_plain() {
    let dev = device(&one_port(
        json!([{"device_type": "merge simple", "slave_id": 2}]),
    ));
    assert_eq!(
        (dev.id.as_str(), dev.name.as_str()),
        ("merge-simple_2", "merge simple 2")
    );
    let ids: Vec<(&str, u16)> = dev
        .channels
        .iter()
        .map(|c| (c.id.as_str(), c.registers[0].read.as_ref().unwrap().address))
        .collect();
    assert_eq!(ids, vec![("Voltage", 0x500), ("Temperature", 0x504)]);
    assert!(dev.setup.is_empty());
}

/// merge_template_ok6 / res6: a subdevice inside a subdevice: `Sub` (shift 100) holds `c2`
/// (subdevice2, shift 200): its channels and setup items are named with both prefixes and
/// shifted by both shifts (wb's `LoadSubdeviceChannel` adds each `shift` to the base
/// address it hands down).
#[test]
fn merge_template_nested_subdevices() {
    let dev = device(&one_port(
        json!([{"device_type": "merge subdevice2", "slave_id": 2}]),
    ));
    assert_eq!(dev.id, "merge-subdevice2_2");
    let channels: Vec<(&str, u16)> = dev
        .channels
        .iter()
        .map(|c| (c.id.as_str(), c.registers[0].read.as_ref().unwrap().address))
        .collect();
    assert_eq!(
        channels,
        vec![
            ("Temperature", 0x504),
            ("Sub c11", 0x501 + 100),
            ("Sub c2 c12", 0x502 + 300),
            ("Sub c2 c22", 0x506 + 300),
        ]
    );
    assert_eq!(
        setup(&dev),
        vec![
            item("Sub c2 s22", 9992 + 300, &[2]),
            item("Sub c2 s12", 20000 + 300, &[0xfff2]),
        ]
    );
}

/// merge_template_ok7 / res7: overrides two levels down: `c12` gets `read_period_ms` 100,
/// `c22` is disabled, and a setup item is added to `c2` (shifted like its own: 25000 + 300).
#[test]
fn merge_template_nested_subdevice_overrides() {
    let dev = device(&one_port(json!([{
        "device_type": "merge subdevice2", "slave_id": 2,
        "channels": [{
            "name": "Sub", "device_type": "subdevice1",
            "channels": [{
                "name": "c2", "device_type": "subdevice2",
                "channels": [
                    {"name": "c12", "read_period_ms": 100},
                    {"enabled": false, "name": "c22"}
                ],
                "setup": [{"address": 25000, "title": "31", "value": "0xffff"}]
            }]
        }]
    }])));
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Temperature", "Sub c11", "Sub c2 c12"]);
    assert_eq!(channel(&dev, "Sub c2 c12").read_period, Some(MS(100)));
    assert_eq!(
        setup(&dev),
        vec![
            item("Sub c2 s22", 9992 + 300, &[2]),
            item("Sub c2 s12", 20000 + 300, &[0xfff2]),
            item("Sub c2 31", 25000 + 300, &[0xffff]),
        ]
    );
}

/// merge_template_ok11 / res11: `param1` 2 and `param2` 3: channels c4 (`param2==3`) and c5
/// (`param1==2&&param2==3`) come in, c2/c3 (`param1==1`) stay out; both parameters written.
#[test]
fn merge_template_conditions_with_two_parameters() {
    let dev = device(&one_port(json!([
        {"device_type": "merge condition", "slave_id": 2, "param1": 2, "param2": 3}
    ])));
    let ids: Vec<&str> = dev.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["c1", "c4", "c5"]);
    assert_eq!(
        setup(&dev),
        vec![item("p1", 0x401, &[2]), item("p2", 0x402, &[3])]
    );
}

// ---------------------------------------------------------------------------------------------
// TConfigParserTest.Parse: the gold print, restated
// ---------------------------------------------------------------------------------------------

/// The parts of a resolved device that `TConfigParserTest`'s `PrintConfig` prints and that
/// rtu2mqtt models, one line per device, channel and register, in the gold's units (ms, µs).
fn print_device(dev: &ResolvedDevice) -> Vec<String> {
    let t = &dev.timing;
    let ms = |d: Duration| d.as_millis();
    let mut out = vec![format!(
        "{} | {} | slave {} | reg hole {} bit hole {} max read {} | guard {} us | device timeout {} | response {} | frame {}",
        dev.id,
        dev.name,
        dev.slave_id,
        t.max_reg_hole,
        t.max_bit_hole,
        t.max_read_registers,
        t.guard_interval.as_micros(),
        t.device_timeout.map_or(-1, |d| d.as_millis() as i64),
        ms(t.response_timeout),
        ms(t.frame_timeout),
    )];
    for c in dev.channels.iter() {
        let limit = c.read_rate_limit.or(t.read_rate_limit);
        out.push(format!(
            "  {} | {} | order {} | readonly {} | on {:?} | rate limit {:?}",
            c.id,
            c.control_type,
            c.order,
            c.readonly,
            c.registers[0].codec.on_value,
            limit.map(ms),
        ));
        for r in &c.registers {
            let read = r.read.as_ref().expect("a polled register");
            out.push(format!(
                "    {:?} {} | {:?} | scale {} | error {:?} | written {}",
                read.reg_type,
                read.address,
                r.codec.format,
                r.codec.scale,
                r.codec.error_value,
                r.write.is_some(),
            ));
        }
    }
    out
}

/// TConfigParserTest.Parse (`test/configs/parse_test.json`, gold
/// `test/TConfigParserTest.Parse.dat` at 03ac6ead, templates `test/device-templates/
/// config-msu34.json`, `test-device-override.json`, `test-device-override2.json` restated in
/// `tests/data/wb_parity/templates/`): every device of the gold on its two serial ports, with
/// what the gold prints of it that rtu2mqtt models.
///
/// The config is the stored `parse_test.json` (04b88661) with what that gold shows it had
/// besides (`frame_timeout_ms` 111, `response_timeout_ms` 222, `device_timeout_ms` 2000, the
/// ErrorValueTest and TestDeviceOverride2 devices). Left out: the gold's TCP ports without
/// devices (nothing to resolve), and ErrorValueTest's `str-uint64` / `str-hex-uint64` channels
/// (64-bit `error_value`s that newer wb-mqtt-serial refuses too: unsuccessful-3).
///
/// Where the gold is of an older wb-mqtt-serial than the rules this project follows, the
/// newer rule is asserted and the gold's value said here:
/// - `poll_interval` is a read rate limit (the gold's `PollInterval`): the channel's, else the
///   device's, else the port's. A `consists_of` register's own `poll_interval` (RGB's first,
///   103 in the gold) is not read: newer `LoadSimpleChannel` gives every register of the
///   channel the channel's limit (102).
/// - Frame timeout 20 ms where unset (the gold: 0; newer `DefaultFrameTimeout`), as
///   `template_device_defaults` asserts from the ParametersAsArray gold.
/// - A channel without `type` is a `value` (the gold: `text`).
/// - `Response timeout` is the device's: 500 ms unless the device or its port sets one (222 on
///   the second port).
#[test]
fn parse_gold() {
    let config = json!({"debug": false, "ports": [
        {"path": "/dev/ttyNSC0", "baud_rate": 9600, "parity": "N", "data_bits": 8,
         "stop_bits": 2, "poll_interval": 10, "enabled": true, "devices": [
            {"device_type": "MSU34", "slave_id": 2, "enabled": true, "channels": [
                {"name": "Illuminance", "poll_interval": 300},
                {"name": "Pressure", "poll_interval": 10000}
            ]},
            {"name": "OnValueTest", "id": "OnValueTest", "enabled": true, "slave_id": "0x90",
             "frame_timeout_ms": 111, "channels": [
                {"name": "Relay 1", "reg_type": "holding", "address": "0x00", "type": "switch",
                 "on_value": 500}
            ]},
            {"name": "ErrorValueTest", "id": "ErrorValueTest", "slave_id": "0x91", "channels": [
                {"name": "uint16", "reg_type": "holding", "address": 0, "type": "switch",
                 "error_value": 65535},
                {"name": "uint32", "reg_type": "holding", "address": 1, "type": "switch",
                 "error_value": 4_294_967_295_u32},
                {"name": "str-uint32", "reg_type": "holding", "address": 2, "type": "switch",
                 "error_value": "4294967295"},
                {"name": "str-hex-uint32", "reg_type": "holding", "address": 3,
                 "type": "switch", "error_value": "0xFFFFFFFF"}
            ]}
        ]},
        {"path": "/dev/ttyNSC1", "baud_rate": 9600, "parity": "N", "data_bits": 8,
         "stop_bits": 1, "poll_interval": 100, "guard_interval_us": 105,
         "response_timeout_ms": 222, "enabled": true, "devices": [
            {"name": "LC-103", "id": "lc103", "enabled": true, "slave_id": "0x04",
             "guard_interval_us": 1000, "device_timeout_ms": 2000, "channels": [
                {"name": "Relay 1", "reg_type": "coil", "address": "0x00", "type": "switch"},
                {"name": "Relay 2", "reg_type": "coil", "address": "0x01", "type": "switch"},
                {"name": "Relay 3", "reg_type": "coil", "address": "0x02", "type": "switch"},
                {"name": "Switch AC In", "reg_type": "discrete", "address": "0x00"}
            ]},
            {"name": "WB-MRGB", "id": "wb-mrgb", "slave_id": 2, "poll_interval": 101,
             "max_read_registers": 0, "channels": [
                {"name": "RGB", "type": "rgb", "poll_interval": 102, "consists_of": [
                    {"reg_type": "holding", "address": 1, "poll_interval": 103},
                    {"reg_type": "holding", "address": 0},
                    {"reg_type": "holding", "address": 2}
                ]},
                {"name": "Button 1 counter", "reg_type": "holding", "readonly": true,
                 "address": 32, "type": "value"}
            ]},
            {"device_type": "TestDeviceOverride", "slave_id": 5,
             "name": "TestDeviceOverride:config", "id": "TestDeviceOverride:config",
             "max_reg_hole": 2, "max_bit_hole": 2, "max_read_registers": 42},
            {"device_type": "TestDeviceOverride", "slave_id": 6},
            {"device_type": "TestDeviceOverride2", "slave_id": 7, "channels": [
                {"name": "Input", "poll_interval": 300},
                {"name": "Holding", "readonly": true, "poll_interval": 10000},
                {"name": "Holding readonly", "readonly": false, "poll_interval": 1000}
            ]}
        ]}
    ]});
    let got: Vec<String> = devices(&config).iter().flat_map(print_device).collect();
    let gold = r#"
msu34tlp_2 | MSU34+TLP 2 | slave 2 | reg hole 0 bit hole 0 max read 1 | guard 20000 us | device timeout 3000 | response 500 | frame 20
  Temp 1 | temperature | order 1 | readonly true | on None | rate limit Some(10)
    Input 0 | S8 | scale 1 | error None | written false
  Illuminance | lux | order 2 | readonly true | on None | rate limit Some(300)
    Input 1 | U16 | scale 1 | error None | written false
  Pressure | pressure | order 3 | readonly true | on None | rate limit Some(10000)
    Input 2 | U16 | scale 0.075 | error None | written false
  Temp 2 | temperature | order 4 | readonly true | on None | rate limit Some(10)
    Input 3 | S8 | scale 1 | error None | written false
OnValueTest | OnValueTest | slave 144 | reg hole 0 bit hole 0 max read 1 | guard 0 us | device timeout 3000 | response 500 | frame 111
  Relay 1 | switch | order 1 | readonly false | on Some(500) | rate limit Some(10)
    Holding 0 | U16 | scale 1 | error None | written true
ErrorValueTest | ErrorValueTest | slave 145 | reg hole 0 bit hole 0 max read 1 | guard 0 us | device timeout 3000 | response 500 | frame 20
  uint16 | switch | order 1 | readonly false | on None | rate limit Some(10)
    Holding 0 | U16 | scale 1 | error Some(65535) | written true
  uint32 | switch | order 2 | readonly false | on None | rate limit Some(10)
    Holding 1 | U16 | scale 1 | error Some(4294967295) | written true
  str-uint32 | switch | order 3 | readonly false | on None | rate limit Some(10)
    Holding 2 | U16 | scale 1 | error Some(4294967295) | written true
  str-hex-uint32 | switch | order 4 | readonly false | on None | rate limit Some(10)
    Holding 3 | U16 | scale 1 | error Some(4294967295) | written true
lc103 | LC-103 | slave 4 | reg hole 0 bit hole 0 max read 1 | guard 1000 us | device timeout 2000 | response 222 | frame 20
  Relay 1 | switch | order 1 | readonly false | on None | rate limit Some(100)
    Coil 0 | U8 | scale 1 | error None | written true
  Relay 2 | switch | order 2 | readonly false | on None | rate limit Some(100)
    Coil 1 | U8 | scale 1 | error None | written true
  Relay 3 | switch | order 3 | readonly false | on None | rate limit Some(100)
    Coil 2 | U8 | scale 1 | error None | written true
  Switch AC In | switch | order 4 | readonly true | on None | rate limit Some(100)
    DiscreteInput 0 | U8 | scale 1 | error None | written false
wb-mrgb | WB-MRGB | slave 2 | reg hole 0 bit hole 0 max read 0 | guard 105 us | device timeout 3000 | response 222 | frame 20
  RGB | rgb | order 1 | readonly false | on None | rate limit Some(102)
    Holding 1 | U16 | scale 1 | error None | written true
    Holding 0 | U16 | scale 1 | error None | written true
    Holding 2 | U16 | scale 1 | error None | written true
  Button 1 counter | value | order 2 | readonly true | on None | rate limit Some(101)
    Holding 32 | U16 | scale 1 | error None | written false
TestDeviceOverride:config | TestDeviceOverride:config | slave 5 | reg hole 2 bit hole 2 max read 42 | guard 105 us | device timeout 3000 | response 222 | frame 20
  Chan 1 | temperature | order 1 | readonly true | on None | rate limit Some(100)
    Input 0 | S8 | scale 1 | error None | written false
TestDeviceOverride:template_6 | TestDeviceOverride:template 6 | slave 6 | reg hole 1 bit hole 1 max read 1 | guard 105 us | device timeout 3000 | response 222 | frame 20
  Chan 1 | temperature | order 1 | readonly true | on None | rate limit Some(100)
    Input 0 | S8 | scale 1 | error None | written false
TestDeviceOverride2:template_7 | TestDeviceOverride2:template 7 | slave 7 | reg hole 0 bit hole 0 max read 1 | guard 105 us | device timeout 3000 | response 222 | frame 20
  Input | value | order 1 | readonly true | on None | rate limit Some(300)
    Input 0 | U16 | scale 1 | error None | written false
  Holding | value | order 2 | readonly true | on None | rate limit Some(10000)
    Holding 1 | U16 | scale 1 | error None | written false
  Holding readonly | value | order 3 | readonly true | on None | rate limit Some(1000)
    Holding 2 | U16 | scale 1 | error None | written false
"#;
    let want: Vec<String> = gold.trim().lines().map(String::from).collect();
    assert_eq!(got, want);
}

// ---------------------------------------------------------------------------------------------
// Configs wb-mqtt-serial accepts though a key means nothing to it (review of 26 Nov, evening)
// ---------------------------------------------------------------------------------------------

/// The warnings `resolve_config_checked` gives for `config`, as text.
fn warnings_of(config: &Value) -> Vec<String> {
    let source = SourceText::from_text(Path::new("wb_parity_config.json"), &config.to_string());
    let loaded = load_config_source(source, false).expect("loads");
    let library = TemplateLibrary::load_dirs(&[templates_dir()]);
    let (result, warnings) = rtu2mqtt::device::configure::resolve_config_checked(&loaded, &library);
    result.unwrap_or_else(|err| panic!("config is refused: {err}"));
    warnings.iter().map(|w| w.to_string()).collect()
}

/// A device key that is neither a device setting nor a parameter of the template (a parameter
/// a newer template dropped or renamed, kept in a config the web UI saved): wb-mqtt-serial's
/// device schema (`AddDeviceSchema`, `src/config_schema_generator.cpp`) has no
/// `additionalProperties`, and `MergeDeviceConfigWithTemplate` copies the key into the device
/// where nothing reads it. The device runs there; here too, with a warning naming the key.
#[test]
fn a_device_key_the_template_does_not_know_is_ignored_with_a_warning() {
    let config = one_port(json!([
        {"device_type": "parameters array", "slave_id": 1, "p1": 0, "old_param": 3}
    ]));
    let dev = device(&config);
    assert_eq!(setup_writes(&dev), vec![(9992, vec![0])]);
    let said = warnings_of(&config);
    assert!(
        said.iter().any(|w| w.contains("devices[0].old_param")
            && w.contains("ignored")
            && w.contains("wb-mqtt-serial")),
        "{said:?}"
    );
    // A misspelt parameter is still named.
    let said = warnings_of(&one_port(json!([
        {"device_type": "parameters array", "slave_id": 1, "p3": 0}
    ])));
    assert!(said.iter().any(|w| w.contains("`p3`")), "{said:?}");
}

/// The same in a subdevice slot's override: `MergeChannelConfigWithTemplate` takes `name`,
/// `shift`, `stride`, `id`, the subdevice's parameters and `channels`, nothing else, and the
/// slot's schema (`MakeSubDeviceSchema`) has no `additionalProperties`.
#[test]
fn a_subdevice_key_the_template_does_not_know_is_ignored_with_a_warning() {
    let config = one_port(json!([
        {"device_type": "merge subdevice", "slave_id": 1,
         "channels": [{"name": "Sub", "device_type": "subdevice1", "old_param": 1}]}
    ]));
    let dev = device(&config);
    assert!(
        dev.channels.iter().any(|c| c.id == "Sub c1"),
        "{:?}",
        dev.channels
    );
    let said = warnings_of(&config);
    assert!(
        said.iter()
            .any(|w| w.contains("channels[0].old_param") && w.contains("ignored")),
        "{said:?}"
    );
}

/// Keys of a port or of the file's top level that wb-mqtt-serial does not read: its ports
/// schema (`wb-mqtt-serial-ports.schema.json`) has no `additionalProperties`, so a `title` or
/// a note on a port loads there. A warning here, naming the closest key for a typo.
#[test]
fn unknown_port_and_top_level_keys_are_ignored_with_a_warning() {
    let config = json!({
        "note": "site A",
        "ports": [{"path": "/dev/ttyNSC0", "title": "Bus 1", "baudrate": 19200, "devices": [
            {"device_type": "parameters array", "slave_id": 1}
        ]}]
    });
    let ports = load(&config);
    assert_eq!(ports[0].devices.len(), 1);
    // The misspelt key does nothing, as there: the default speed stays.
    assert_eq!(ports[0].config.baud_rate, 9600);
    let said = warnings_of(&config);
    for key in ["note", "ports[0].title", "ports[0].baudrate"] {
        assert!(
            said.iter()
                .any(|w| w.contains(&format!("at {key}:")) && w.contains("ignored")),
            "{key}: {said:?}"
        );
    }
    assert!(said.iter().any(|w| w.contains("`baud_rate`")), "{said:?}");
}

/// The web UI's "custom period" of a channel goes up to 172800000 ms (2 days,
/// `tableChannelSettings.period` in `wb-mqtt-serial-confed-common.schema.json`) and is saved
/// as the channel's `read_period_ms` (`HomeuiToConfigChannel`, `src/confed_channel_modes.cpp`),
/// its "not faster than" mode as `read_rate_limit_ms`: such a config must load.
#[test]
fn a_read_period_of_two_days_from_the_web_ui_loads() {
    let dev = device(&one_port(json!([
        {"device_type": "parameters array", "slave_id": 1,
         "channels": [{"name": "Temperature", "read_period_ms": 172_800_000_u64}]}
    ])));
    assert_eq!(
        channel(&dev, "Temperature").read_period,
        Some(MS(172_800_000))
    );
    let dev = device(&one_port(json!([
        {"device_type": "parameters array", "slave_id": 1,
         "channels": [{"name": "Temperature", "read_rate_limit_ms": 172_800_000_u64}]}
    ])));
    assert_eq!(rate_limit(&dev, "Temperature"), Some(MS(172_800_000)));
}

/// A parameter given as no number while no declaration of it is in effect (its `condition` is
/// false over the config's values): wb-mqtt-serial's device schema has no entry for it
/// (`MakeDeviceParametersSchema` adds only the declarations whose condition holds), and
/// `AppendSetupItems` logs "… is not an integer" and writes nothing. The device runs there, so
/// it runs here, with a warning; in effect, such a value is still refused (as by its schema).
#[test]
fn a_parameter_that_is_no_number_is_ignored_while_its_condition_is_false() {
    let config = one_port(json!([
        {"device_type": "parameters array", "slave_id": 1, "p1": 5, "p2": "auto"}
    ]));
    let dev = device(&config);
    assert_eq!(setup_writes(&dev), vec![(9992, vec![5])]);
    let said = warnings_of(&config);
    assert!(
        said.iter()
            .any(|w| w.contains("devices[0].p2") && w.contains("ignored")),
        "{said:?}"
    );
    let err = refused(&one_port(json!([
        {"device_type": "parameters array", "slave_id": 1, "p1": 0, "p2": "auto"}
    ])));
    assert!(err.contains("p2"), "{err}");
}
