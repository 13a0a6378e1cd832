//! Templates in the wb-mqtt-serial format (small fixtures of our own in tests/data/wb-templates,
//! written to exercise the features the real library uses) load unchanged and resolve to the
//! right registers, formats and event flags.

use std::path::{Path, PathBuf};

use rtu2mqtt::config::TemplateFile;
use rtu2mqtt::device::{
    check_template, resolve_template_device, EventMode, Reading, RegisterFormat, RegisterType,
    ResolvedDevice, WordOrder,
};
use serde_json::json;

fn corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/wb-templates")
}

fn template(name: &str) -> TemplateFile {
    TemplateFile::load(&corpus().join(name)).unwrap_or_else(|e| panic!("{e}"))
}

fn device(name: &str, config: serde_json::Value) -> ResolvedDevice {
    resolve_template_device(&template(name), &config).unwrap_or_else(|e| panic!("{e}"))
}

/// Why the fixture `name` refuses `config` (fails if it does not).
fn refused(name: &str, config: serde_json::Value) -> String {
    match resolve_template_device(&template(name), &config) {
        Ok(_) => panic!("{name} accepted {config}"),
        Err(err) => err.to_string(),
    }
}

#[test]
fn all_fixtures_load_and_resolve() {
    let mut count = 0;
    for entry in std::fs::read_dir(corpus()).unwrap() {
        let path = entry.unwrap().path();
        let file = TemplateFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
        // Warnings (channels left out on purpose) do not fail a template, as in check-templates.
        let mut errors = check_template(&file);
        errors.retain(|e| !matches!(e.problem, rtu2mqtt::config::Problem::Warning(_)));
        assert!(
            errors.is_empty(),
            "{}: {}",
            path.display(),
            errors
                .iter()
                .map(|e| e.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        );
        count += 1;
    }
    assert_eq!(count, 21);
}

/// Asserts a channel's first register: table, address, format and event mode.
fn assert_channel(
    device: &ResolvedDevice,
    id: &str,
    reg_type: RegisterType,
    address: u16,
    format: RegisterFormat,
    events: EventMode,
) {
    let channel = device.channel(id).unwrap_or_else(|| {
        panic!(
            "{}: no channel `{id}`; have {:?}",
            device.id,
            device.channels.iter().map(|c| &c.id).collect::<Vec<_>>()
        )
    });
    let register = &channel.registers[0];
    let read = register.read.or(register.write).unwrap();
    assert_eq!(
        (
            read.reg_type,
            read.address,
            register.codec.format,
            channel.events
        ),
        (reg_type, address, format, events),
        "{id}"
    );
}

use EventMode::{Polled, SemiSporadic, Sporadic};
use RegisterFormat::{Bcd16, Float, S16, S32, U16, U32, U64, U8};
use RegisterType::*;

#[test]
fn floats_and_timing() {
    let d = device("config-test-meter.json", json!({"slave_id": 3}));
    assert_eq!(
        (d.id.as_str(), d.name.as_str(), d.is_wb),
        ("test_meter_3", "Test Meter 3", false)
    );
    assert_channel(&d, "Voltage", Input, 0, Float, Polled);
    assert_channel(&d, "Frequency", Input, 0x46, Float, Polled);
    assert_eq!(
        d.channel("Voltage").unwrap().registers[0].codec.word_count,
        2
    );
    assert_eq!(d.timing.frame_timeout.as_millis(), 0);
    assert_eq!(d.timing.guard_interval.as_micros(), 40_000);
    assert_eq!(
        d.channel("Voltage")
            .unwrap()
            .decode(&[&[0x4366, 0x8000]])
            .unwrap(),
        Reading::Value("230.5".into())
    );
}

#[test]
fn semi_sporadic_and_error_values() {
    let d = device("config-test-wb-sensor.json", json!({"slave_id": 22}));
    assert!(d.is_wb);
    assert_channel(&d, "Temperature", Input, 4, S16, Polled);
    assert_channel(&d, "Max Motion", Input, 280, U16, SemiSporadic);
    assert_channel(&d, "Illuminance", Input, 9, U32, Polled);
    let temperature = d.channel("Temperature").unwrap();
    assert_eq!(temperature.units.as_deref(), Some("deg C"));
    assert_eq!(
        temperature.decode(&[&[0x7FFF]]).unwrap(),
        Reading::DeviceError
    );
    assert_eq!(
        temperature.decode(&[&[2150]]).unwrap(),
        Reading::Value("21.5".into())
    );
    assert!(
        d.channel("Dew Point").is_none(),
        "disabled channels are not created"
    );
}

#[test]
fn word_order_u64_offset_and_serial() {
    let d = device("config-test-meter.json", json!({"slave_id": 1}));
    assert_channel(&d, "Current", Input, 0x1410, U32, SemiSporadic);
    assert_channel(&d, "Energy", Input, 0x1200, U64, Polled);
    let energy = d.channel("Energy").unwrap();
    assert_eq!(
        energy.registers[0].codec.word_order,
        WordOrder::LittleEndian
    );
    assert_eq!(energy.precision, Some(1e-06));
    let peak = d.channel("Peak").unwrap();
    assert_eq!(
        peak.decode(&[&[0xFFFE, 0xFFFE]]).unwrap(),
        Reading::Unsupported
    );
    let serial = d.serial_number.as_ref().unwrap();
    assert_eq!(serial.read.unwrap().address, 270);
    assert_eq!(
        serial.codec.decode(&[0xFE00, 0x0102]).unwrap(),
        Reading::Value("258".into())
    );
}

#[test]
fn conditions_bit_fields_and_sporadic() {
    let d = device("config-test-wb-sensor.json", json!({"slave_id": 1}));
    // show_mode_as_range defaults to 0: `==1` is false, `!=1` is true.
    let mode = d.channel("Mode").unwrap();
    assert_eq!(mode.control_type, "value");
    assert_eq!(mode.enum_titles.len(), 3);
    assert_channel(&d, "Mode", Holding, 1, U16, Sporadic);
    assert_channel(&d, "Active", Coil, 1, U8, Sporadic);
    assert_channel(&d, "Timer: Enabled", Holding, 55, U8, Polled);
    let timer = d.channel("Timer: Enabled").unwrap();
    assert_eq!(
        (
            timer.registers[0].codec.bit_shift,
            timer.registers[0].codec.bit_width
        ),
        (4, 1)
    );
    assert!(
        d.channel("Timer: Heater").is_none(),
        "condition show_timer==1 is false"
    );

    let d = device(
        "config-test-wb-sensor.json",
        json!({"slave_id": 1, "show_mode_as_range": 1, "show_timer": 1}),
    );
    assert_eq!(d.channel("Mode").unwrap().control_type, "range");
    let heater = d.channel("Timer: Heater").unwrap();
    assert_eq!(
        heater.decode(&[&[0b1000]]).unwrap(),
        Reading::Value("0".into())
    );
    assert!(d
        .setup
        .iter()
        .any(|s| s.register.reg_type == Coil && s.register.address == 95 && s.words == vec![1]));
}

#[test]
fn write_only_pushbutton_and_readonly_float() {
    let d = device("config-test-meter.json", json!({"slave_id": 1}));
    let reset = d.channel("Reset").unwrap();
    assert!(reset.write_only && reset.registers[0].read.is_none());
    assert_eq!(reset.registers[0].write.unwrap().address, 1111);
    assert_eq!(reset.encode("1", &[None]).unwrap(), vec![vec![0, 0]]);
    assert_channel(&d, "Pressure", Holding, 1099, Float, Polled);
    assert!(d.channel("Pressure").unwrap().readonly);
}

#[test]
fn bcd_and_on_off() {
    let d = device("config-test-meter.json", json!({"slave_id": 1}));
    assert_channel(&d, "Hour", Holding, 6, Bcd16, Polled);
    assert_eq!(
        d.channel("Hour").unwrap().decode(&[&[0x0023]]).unwrap(),
        Reading::Value("23".into())
    );
    let err = d
        .channel("Hour")
        .unwrap()
        .encode("24", &[None])
        .unwrap_err()
        .to_string();
    assert!(err.contains("0 … 23"), "the channel max is checked: {err}");
    assert_channel(&d, "Thermostat", Holding, 3, U16, Polled);
}

#[test]
fn subdevices_and_parameters() {
    let d = device(
        "config-test-wb-inputs.json",
        json!({"slave_id": 7, "baud_rate": 192, "channels": [{"name": "Input 1", "device_type": "in1_discrete"}]}),
    );
    assert_channel(&d, "Discrete Input 1", DiscreteInput, 1, U8, Polled);
    assert_channel(&d, "Counter 1 pulses", Input, 278, U16, Polled);
    assert!(d.channel("External Sensor 1").is_none());
    let setup: Vec<(u16, Vec<u16>)> = d
        .setup
        .iter()
        .map(|s| (s.register.address, s.words.clone()))
        .collect();
    assert_eq!(setup, vec![(110, vec![192]), (275, vec![1])]);

    let d = device("config-test-wb-inputs.json", json!({"slave_id": 7}));
    assert_channel(&d, "External Sensor 1", Input, 7, S16, Polled);
}

#[test]
fn translations() {
    let d = device("config-test-wb-sensor.json", json!({"slave_id": 7}));
    assert_eq!(
        d.channel("Temperature")
            .unwrap()
            .title
            .get("ru")
            .map(String::as_str),
        Some("Температура")
    );
}

#[test]
fn subdevice_shift_and_stride() {
    let d = device(
        "config-test-wb-inputs.json",
        json!({"slave_id": 7, "channels": [{"name": "Input 2", "device_type": "analog_pair", "channels": [
            {"name": "IN_P", "device_type": "analog", "data_rate": 20},
            {"name": "IN_N", "device_type": "analog", "data_rate": 45}]}]}),
    );
    // Input 2 is shifted by 0x2000; the N channel of the pair moves by its own width (stride 1).
    assert_channel(&d, "IN 2 P Current", Input, 0x2500, S32, Polled);
    assert_channel(&d, "IN 2 N Current", Input, 0x2502, S32, Polled);
    assert_channel(&d, "IN 2 N Value", Input, 0x2505, S16, Polled);
    assert!(d
        .setup
        .iter()
        .any(|s| s.register.address == 0x2401 && s.words == vec![4866]));
}

/// Subdevice parameters named like channel keys (the legacy WB-MAI11's `min` and `max`, the
/// range an input's `Value` is scaled to) are written as wb-mqtt-serial writes them
/// (`MergeChannelProperties` copies every key of the override into the slot, `AppendSetupItems`
/// makes a setup item of each named like a parameter); they were dropped as channel keys. The
/// range is no channel property of the slot's channels (wb builds them from the subdevice).
#[test]
fn subdevice_parameters_named_like_channel_keys_are_written() {
    let d = device(
        "config-test-wb-inputs.json",
        json!({"slave_id": 7, "channels": [{"name": "Input 2", "device_type": "analog_pair", "channels": [
            {"name": "IN_P", "device_type": "analog", "data_rate": 20, "min": 5, "max": 2000},
            {"name": "IN_N", "device_type": "analog", "data_rate": 45, "max": 3000}]}]}),
    );
    let writes = setup_writes(&d);
    for (address, value) in [
        (0x2408, 5),    // IN_P min
        (0x240A, 2000), // IN_P max
        (0x240B, 3000), // IN_N max (stride 1: moved by its own width)
        (0x2402, 20),   // IN_P data_rate, as before
    ] {
        assert!(
            writes.contains(&(address, vec![value])),
            "{address:#x} = {value} missing from {writes:?}"
        );
    }
    // IN_N's `min` is not given: not written (a parameter is written only when given).
    assert!(!writes.iter().any(|(a, _)| *a == 0x2409), "{writes:?}");
    for id in ["IN 2 P Value", "IN 2 P Current", "IN 2 N Value"] {
        let channel = d.channel(id).unwrap();
        assert_eq!((channel.min, channel.max), (None, None), "{id}");
    }
}

/// A nested slot (`IN_P`, of the one subdevice `analog`) overridden without `device_type` is
/// refused, as wb-mqtt-serial refuses it (`CheckDeviceType`: "… device_type must be
/// 'analog'"), with what to add; it used to take the slot's own subdevice.
#[test]
fn a_nested_slot_overridden_without_device_type_is_refused() {
    let err = refused(
        "config-test-wb-inputs.json",
        json!({"slave_id": 7, "channels": [{"name": "Input 2", "device_type": "analog_pair", "channels": [
            {"name": "IN_P", "data_rate": 20}]}]}),
    );
    assert!(err.contains("channels[0].channels[0]"), "{err}");
    assert!(
        err.contains(r#"subdevice slot `IN_P` without saying which subdevice it holds"#)
            && err.contains(r#"add "device_type": "analog" (the only subdevice this slot takes)"#),
        "{err}"
    );
}

#[test]
fn u64_counters_ranges_and_readonly() {
    let d = device("config-test-wb-inputs.json", json!({"slave_id": 1}));
    assert_channel(&d, "Counter 1", Input, 20, U64, Polled);
    assert_channel(&d, "Counter 2", Input, 24, U64, Polled);
    assert_eq!(
        d.channel("Counter 1").unwrap().registers[0]
            .codec
            .word_count,
        4
    );
    assert!(d.channel("Button 1").unwrap().readonly);
    assert_eq!(
        d.channel("Input Voltage")
            .unwrap()
            .decode(&[&[12034]])
            .unwrap(),
        Reading::Value("12.034".into())
    );
}

#[test]
fn config_overrides_follow_merge_rules() {
    let d = device(
        "config-test-wb-sensor.json",
        json!({"slave_id": 2, "id": "hall", "name": "Hall", "channels": [
            {"name": "Temperature", "read_period_ms": 500, "address": 99, "readonly": false},
            {"name": "Dew Point", "enabled": true},
            {"name": "Extra", "reg_type": "holding", "address": 1000}
        ]}),
    );
    assert_eq!((d.id.as_str(), d.name.as_str()), ("hall", "Hall"));
    let temperature = d.channel("Temperature").unwrap();
    assert_eq!(temperature.read_period.map(|p| p.as_millis()), Some(500));
    assert_eq!(
        temperature.registers[0].read.unwrap().address,
        4,
        "address cannot be overridden"
    );
    assert!(temperature.readonly);
    assert!(d.channel("Dew Point").is_some());
    assert_channel(&d, "Extra", Holding, 1000, U16, Polled);
    assert_eq!(d.channels.last().unwrap().order as usize, d.channels.len());
}

/// Same-named channels that differ only by condition: an override reaches every one of them
/// (wb-mqtt-serial), so it also reaches the one in effect.
#[test]
fn override_reaches_every_channel_of_that_name() {
    // in2_mode defaults to 1: the second "Input 2 counter" is in effect.
    let d = device(
        "config-test-wb-sensor.json",
        json!({"slave_id": 1, "channels": [
            {"name": "Input 2 counter", "read_period_ms": 500},
            {"name": "Input 1 counter", "enabled": false}
        ]}),
    );
    let counter = d.channel("Input 2 counter").unwrap();
    assert_eq!(counter.read_period.map(|p| p.as_millis()), Some(500));
    assert_eq!(counter.events, SemiSporadic);
    assert!(d.channel("Input 1 counter").is_none());
    let d = device(
        "config-test-wb-sensor.json",
        json!({"slave_id": 1, "in1_mode": 1, "channels": [{"name": "Input 1 counter", "enabled": false}]}),
    );
    assert!(d.channel("Input 1 counter").is_none());
}

fn rules_fixture(name: &str) -> TemplateFile {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/wb-rules")
        .join(name);
    TemplateFile::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

/// WBIO modules: wb-mqtt-serial's shift ((module - 1) % 4 + 1) × stride + shift.
#[test]
fn modbus_io_module_shift() {
    let template = rules_fixture("config-test-wbio.json");
    for (slave_id, shift) in [("1:1", 1016), ("1:2", 1032), ("1:4", 1064), ("1:5", 1016)] {
        let d = resolve_template_device(&template, &json!({"slave_id": slave_id}))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_channel(&d, "K1", Coil, shift, U8, Polled);
        assert_channel(&d, "A1", Input, shift + 2, U16, Polled);
        assert_eq!(d.slave_id, 1);
    }
}

/// `"127:8:0"`: a bit width of 0 means the format's own width.
#[test]
fn bit_width_zero_is_the_format_width() {
    let template = rules_fixture("config-test-rules.json");
    let d = resolve_template_device(&template, &json!({"slave_id": 1, "param1": 2}))
        .unwrap_or_else(|e| panic!("{e}"));
    let codec = &d.channel("Status high byte").unwrap().registers[0].codec;
    assert_eq!((codec.bit_shift, codec.bit_width), (8, 16));
}

/// Groups with only an `id`, a parameter without an address used only by conditions (its
/// `default` is substituted before they are evaluated), and conditional template setup items.
#[test]
fn untitled_groups_and_condition_only_parameter() {
    let setup = |d: &ResolvedDevice| -> Vec<(u16, Vec<u16>)> {
        d.setup
            .iter()
            .map(|s| (s.register.address, s.words.clone()))
            .collect()
    };
    // Default mode 1: "sensor off" and "room sensor"; the address-less parameter is never written.
    let d = device("config-test-boiler-gateway.json", json!({"slave_id": 1}));
    assert_eq!(setup(&d), vec![(20, vec![0]), (22, vec![1])]);
    assert_channel(&d, "status", Input, 5, U16, Polled);
    assert_channel(&d, "fault", Input, 5, U16, Polled);
    assert_eq!(
        d.channel("fault").unwrap().decode(&[&[0x0003]]).unwrap(),
        Reading::Value("1".into())
    );
    assert_eq!(
        d.channel("pressure").unwrap().decode(&[&[1234]]).unwrap(),
        Reading::Value("23.4".into())
    );

    // Mode 2 from the config: the conditional parameter is written too.
    let d = device(
        "config-test-boiler-gateway.json",
        json!({"slave_id": 1, "mode": 2, "curve": 5}),
    );
    assert_eq!(setup(&d), vec![(20, vec![0]), (22, vec![2]), (30, vec![5])]);

    // Mode 0: the parameter's condition is false, so `curve` is not written.
    let d = device(
        "config-test-boiler-gateway.json",
        json!({"slave_id": 1, "mode": 0, "curve": 5}),
    );
    assert_eq!(setup(&d), vec![(21, vec![0])]);
}

fn setup_writes(d: &ResolvedDevice) -> Vec<(u16, Vec<u16>)> {
    d.setup
        .iter()
        .map(|s| (s.register.address, s.words.clone()))
        .collect()
}

/// WB-LED declares `in1_sp` once per dimmer mode, each with its own `enum` and an exclusive
/// condition: a value is checked against the declaration in effect, and when none is in effect
/// (here the input is a latching switch) nothing is written and nothing is checked, as in
/// wb-mqtt-serial, whose validator only knows the declarations whose condition holds.
#[test]
fn parameter_declared_once_per_mode() {
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 256, "in1_sp": 4102}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![(1000, vec![4102]), (4000, vec![256])]
    );
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 0, "in1_sp": 4097}),
    );
    assert_eq!(setup_writes(&d), vec![(1000, vec![4097]), (4000, vec![0])]);
    // The value of another mode is refused for this mode …
    let err = resolve_template_device(
        &template("config-test-wb-dimmer.json"),
        &json!({"slave_id": 1, "dimmer_mode": 0, "in1_sp": 4102}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("`in1_sp` cannot be 4102"), "{err}");
    // … and not checked (nor written) while no declaration is in effect.
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 256, "input_1_mode": 1, "in1_sp": 4102}),
    );
    assert_eq!(setup_writes(&d), vec![(1020, vec![1]), (4000, vec![256])]);
}

/// MDM3: two parameters on one address; the condition on a third parameter picks which one is
/// written.
#[test]
fn parameters_sharing_an_address() {
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 256, "out_number": 100, "action_single": 2, "action_all": 3}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![(768, vec![100]), (832, vec![3]), (4000, vec![256])]
    );
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 256, "out_number": 1, "action_single": 2, "action_all": 3}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![(768, vec![1]), (832, vec![2]), (4000, vec![256])]
    );
}

/// MR6C/MCM8: the same channel name twice, sporadic or polled by the input mode (a parameter
/// default counts as defined); RGB of three registers; `error_value` as a hex string; one
/// address read as s32 or s16 by condition.
#[test]
fn channels_chosen_by_condition_rgb_and_hex_error_value() {
    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 256}),
    );
    assert_channel(&d, "Input 1", DiscreteInput, 0, U8, Sporadic);
    assert_eq!(d.channels.iter().filter(|c| c.id == "Input 1").count(), 1);
    let rgb = d.channel("RGB Palette").unwrap();
    assert_eq!(
        (rgb.control_type.as_str(), rgb.registers.len(), rgb.events),
        ("rgb", 3, Sporadic)
    );
    assert_eq!(
        rgb.decode(&[&[255], &[128], &[0]]).unwrap(),
        Reading::Value("255;128;0".into())
    );
    assert_eq!(
        rgb.encode("1;2;3", &[None, None, None]).unwrap(),
        vec![vec![1], vec![2], vec![3]]
    );
    let hue = d.channel("RGB Strip Hue").unwrap();
    assert_eq!(hue.decode(&[&[0xFFFF]]).unwrap(), Reading::DeviceError);
    assert_eq!(hue.decode(&[&[180]]).unwrap(), Reading::Value("180".into()));
    assert_channel(&d, "Encoder revolutions", Holding, 368, S16, Polled);
    assert!(d.channel("Encoder position").is_none());
    assert!(d.channel("Channel 1 Brightness").is_none());
    let overcurrent = d.channel("Overcurrent").unwrap();
    assert_eq!(overcurrent.control_type, "switch");
    assert_eq!(
        overcurrent.decode(&[&[1]]).unwrap(),
        Reading::Value("1".into())
    );

    let d = device(
        "config-test-wb-dimmer.json",
        json!({"slave_id": 1, "dimmer_mode": 0, "input_1_mode": 3}),
    );
    assert_channel(&d, "Input 1", DiscreteInput, 0, U8, Polled);
    assert_channel(&d, "Encoder position", Holding, 368, S32, Polled);
    assert!(d.channel("RGB Palette").is_none());
}

/// An older WB-MWAC-v2 template had trailing commas; jsoncpp (wb-mqtt-serial's reader) accepts
/// them. A key given twice in one object takes the last value, as in jsoncpp (WB-MRWM2).
#[test]
fn trailing_commas_are_accepted() {
    let d = device(
        "config-test-trailing-commas.json",
        json!({"slave_id": 4, "timer_min": 30}),
    );
    assert_channel(&d, "Leak", DiscreteInput, 0, U8, Polled);
    let text = d.channel("Text, with commas,").unwrap();
    assert_eq!(text.enum_titles.len(), 2);
    assert_eq!(setup_writes(&d), vec![(975, vec![30])]);
}

/// 1-Wire sensor ids are u64 parameters (WB-M1W2 v.3): a value above 2^53 is written exactly,
/// from a parameter and from a config `setup` item alike. WB-MS v.2: a scaled s16 parameter with
/// a negative value, and a coil parameter.
#[test]
fn u64_parameter_is_written_exactly() {
    let d = device(
        "config-test-w1-ids.json",
        json!({"slave_id": 1, "bus1_sens1_id": 0x2900_0000_0000_0029_u64, "filter_deg": 0.5,
               "setup": [{"title": "id", "address": 5700, "format": "u64", "value": u64::MAX}]}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![
            (99, vec![8]),
            (5632, vec![0x2900, 0, 0, 0x0029]),
            (5700, vec![0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF]),
        ]
    );
    let d2 = device(
        "config-test-w1-ids.json",
        json!({"slave_id": 1, "bus1_sens1_temp_offset_deg": -0.5, "heater_enabled": 1}),
    );
    let writes: Vec<(RegisterType, u16, Vec<u16>)> = d2
        .setup
        .iter()
        .map(|s| (s.register.reg_type, s.register.address, s.words.clone()))
        .collect();
    assert_eq!(
        writes,
        vec![(Coil, 2, vec![1]), (Holding, 1616, vec![0xFFF8])]
    );
    let temperature = d.channel("External Sensor 1").unwrap();
    assert_eq!(temperature.name, "Input 1 Temperature");
    assert_eq!(
        temperature.decode(&[&[0x0191]]).unwrap(),
        Reading::Value("25.05".into())
    );
}

/// Values as the meters of wb-mqtt-serial's library publish them: little-endian word order,
/// scale then `round_to`, hex `error_value` compared on the raw register value.
#[test]
fn meter_values_scale_round_and_error_values() {
    let d = device("config-test-energy-meter.json", json!({"slave_id": 1}));
    let value = |id: &str, words: &[u16]| d.channel(id).unwrap().decode(&[words]).unwrap();
    let text = |s: &str| Reading::Value(s.into());
    assert_eq!(value("Power", &[0x1234, 0x0001]), text("7020"));
    assert_eq!(value("Energy", &[12345, 0]), text("1.2345"));
    assert_eq!(
        value("AP energy", &[0xCD15, 0x075B, 0, 0]),
        text("1234.56789")
    );
    assert_eq!(value("Ipeak", &[0xFC18, 0xFFFF]), text("-16"));
    assert_eq!(value("P Current", &[0x7FFF, 0xFFFF]), Reading::DeviceError);
    assert_eq!(value("P Current", &[0x00BC, 0x614E]), text("12.35"));
    assert_eq!(value("Temp 1", &[0xFFFF]), Reading::DeviceError);
    assert_eq!(value("Temp 1", &[0xFFF0]), text("-1"));
    assert_eq!(value("Temp 1", &[0x0190]), text("25"));
    assert_channel(&d, "Period", Holding, 0x8007, U8, Polled);
    assert_eq!(value("Period", &[0x1234]), text("52"));
}

/// Breezart-style HVAC constructs: one bit read as a status and written as an inverted switch
/// (the other bits of the register are kept), 8-bit fields, pushbuttons that share a register,
/// a scaled setpoint.
#[test]
fn hvac_bit_fields_inverted_switch_and_shared_pushbuttons() {
    let d = device("config-test-hvac.json", json!({"slave_id": 1}));
    assert_eq!(d.timing.guard_interval.as_micros(), 5000);
    let channel = |id: &str| d.channel(id).unwrap();
    assert_eq!(
        channel("unit_status").decode(&[&[0xFFF6]]).unwrap(),
        Reading::Value("2".into())
    );
    assert_eq!(
        channel("error_code").decode(&[&[0xFFFE, 0xFFFF]]).unwrap(),
        Reading::Value("-2".into())
    );
    assert_channel(&d, "current_time_program", Input, 64008, U8, Polled);
    assert_eq!(
        channel("current_time_program")
            .decode(&[&[0x12FF]])
            .unwrap(),
        Reading::Value("255".into())
    );
    // Bit 7 clear: the status says 0 ("On"), the inverted switch says 1.
    assert_eq!(
        channel("time_program_auto_status")
            .decode(&[&[0x0F0F]])
            .unwrap(),
        Reading::Value("0".into())
    );
    assert!(channel("time_program_auto_status").readonly);
    let autorun = channel("time_program_autorun");
    assert_eq!(
        autorun.decode(&[&[0x0F0F]]).unwrap(),
        Reading::Value("1".into())
    );
    assert_eq!(
        autorun.decode(&[&[0x0F8F]]).unwrap(),
        Reading::Value("0".into())
    );
    assert_eq!(
        autorun.encode("1", &[Some(&[0x00FF][..])]).unwrap(),
        vec![vec![0x007F]]
    );
    assert_eq!(
        autorun.encode("0", &[Some(&[0x0F0F][..])]).unwrap(),
        vec![vec![0x0F8F]]
    );
    assert_eq!(
        channel("setpoint_temperature")
            .encode("21.5", &[None])
            .unwrap(),
        vec![vec![215]]
    );
    assert_eq!(
        channel("setpoint_temperature")
            .decode(&[&[0xFFEC]])
            .unwrap(),
        Reading::Value("-2".into())
    );
    for (id, word) in [("time_program_1", 1), ("time_program_3", 3)] {
        let button = channel(id);
        assert!(button.write_only, "{id}");
        assert_eq!(
            button.encode("1", &[None]).unwrap(),
            vec![vec![word]],
            "{id}"
        );
    }
}

/// Leak-protection controllers (Ensystec): `required` parameters behind a condition on another
/// parameter's default. wb-mqtt-serial's validator evaluates those conditions over the config's
/// own values (`TJsonParams(config)`, no defaults), so `zone1_type` is required only once the
/// config gives `zone1_enable`; `readonly` parameters are never written.
#[test]
fn required_parameter_behind_a_defaulted_condition() {
    let d = device("config-test-leak-protect.json", json!({"slave_id": 1}));
    assert_eq!(setup_writes(&d), vec![]);
    // The defaults choose the leak-sensor channel.
    assert_channel(&d, "zone_1", Holding, 3, U16, Polled);
    assert!(d.channel("zone_1_counter").is_none());

    let err = resolve_template_device(
        &template("config-test-leak-protect.json"),
        &json!({"slave_id": 1, "zone1_enable": 1}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("requires parameter `zone1_type`"), "{err}");
    assert!(!err.contains("zone2_type"), "{err}");

    // Readonly parameters are shown, never written; `address` is an ordinary parameter id.
    let d = device(
        "config-test-leak-protect.json",
        json!({"slave_id": 1, "zone1_enable": 1, "zone1_type": 0, "address": 20}),
    );
    assert_eq!(setup_writes(&d), vec![(15, vec![20])]);
    assert_eq!(d.slave_id, 1);
    assert_channel(&d, "zone_1_counter", Holding, 17, S32, Polled);
    assert!(d.channel("zone_1").is_none());
}

/// A valve switch with only a `write_address` is write-only and writes on_value/off_value;
/// inverted read-only bits, a 2-bit status and a high byte decode from their fields.
#[test]
fn write_only_valve_and_status_fields() {
    let d = device("config-test-leak-protect.json", json!({"slave_id": 1}));
    let channel = |id: &str| d.channel(id).unwrap();
    let valve = channel("valve_1");
    assert!(valve.write_only);
    assert!(valve.registers[0].read.is_none());
    assert_eq!(valve.registers[0].write.unwrap().address, 6);
    assert_eq!(valve.encode("1", &[None]).unwrap(), vec![vec![3]]);
    assert_eq!(valve.encode("0", &[None]).unwrap(), vec![vec![1]]);
    assert_eq!(
        channel("low_battery").decode(&[&[0x0000]]).unwrap(),
        Reading::Value("1".into())
    );
    assert_eq!(
        channel("low_battery").decode(&[&[0x0004]]).unwrap(),
        Reading::Value("0".into())
    );
    assert_eq!(
        channel("valve_1_status").decode(&[&[0x0300]]).unwrap(),
        Reading::Value("3".into())
    );
    assert_eq!(
        channel("hardware_version").decode(&[&[0x1234]]).unwrap(),
        Reading::Value("18".into())
    );
}

/// WB-MAI2-MINI/CC: the bounds are required only once the config gives the mode (wb-mqtt-serial's
/// validator sees no defaults), the scale parameter's condition is a bare parameter name, and the
/// declaration and channel of the scale in effect are used.
#[test]
fn bounds_required_once_the_mode_is_given() {
    let d = device("config-test-analog-scale.json", json!({"slave_id": 1}));
    assert_eq!(setup_writes(&d), vec![]);
    assert_eq!(
        d.channel("in1_value")
            .unwrap()
            .decode(&[&[0xFFF6]])
            .unwrap(),
        Reading::Value("-10".into())
    );

    let err = resolve_template_device(
        &template("config-test-analog-scale.json"),
        &json!({"slave_id": 1, "in1_mode": 2}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("requires parameter `in1_min`"), "{err}");
    assert!(err.contains("requires parameter `in1_scale`"), "{err}");

    // Mode 0: the bare condition `in1_mode` is false, so the range is not required.
    let d = device(
        "config-test-analog-scale.json",
        json!({"slave_id": 1, "in1_mode": 0, "in1_min": -5}),
    );
    assert_eq!(setup_writes(&d), vec![(8, vec![0]), (10, vec![0xFFFB])]);

    // Scale 10: the second declaration is in effect (-3276.8 is raw -32768); the readonly scale
    // itself is never written.
    let d = device(
        "config-test-analog-scale.json",
        json!({"slave_id": 1, "in1_mode": 1, "in1_scale": 10, "in1_min": -3276.8}),
    );
    assert_eq!(setup_writes(&d), vec![(8, vec![1]), (10, vec![0x8000])]);
    assert_eq!(
        d.channel("in1_value")
            .unwrap()
            .decode(&[&[0xFFF6]])
            .unwrap(),
        Reading::Value("-1".into())
    );
}

/// WBE2-I-OPENTHERM (with an s16 enum and a u8 parameter of Eliwell IDPlus and a filter time of
/// WB-MSW v.4): a readonly selector that has an address picks the template setup items and is
/// never written itself; where a parameter and a template setup item write one address, the
/// parameter is written (wb-mqtt-serial keeps the first item of an address: config setup,
/// parameters, template setup); one channel name is a write-only or a read-only setpoint by
/// condition; scale and offset apply both ways.
#[test]
fn readonly_selector_and_parameter_before_template_setup() {
    let fixture = "config-test-boiler-interface.json";
    // Direct control: `season` and the "winter" item both write 212; the parameter wins.
    let d = device(fixture, json!({"slave_id": 1, "heating": 0, "season": 2}));
    assert_eq!(
        setup_writes(&d),
        vec![(205, vec![0]), (207, vec![0]), (212, vec![2])]
    );
    let setpoint = d.channel("Heating Setpoint").unwrap();
    assert!(setpoint.write_only);
    assert!(setpoint.registers[0].read.is_none());
    assert_eq!(setpoint.registers[0].write.unwrap().address, 203);
    assert!(d.channel("Room Temperature").is_none());

    // Outdoor sensor: the curve is written between the template items, in address order.
    let d = device(fixture, json!({"slave_id": 1, "heating": 2, "curve": 7}));
    assert_eq!(
        setup_writes(&d),
        vec![
            (203, vec![0]),
            (206, vec![7]),
            (207, vec![2]),
            (212, vec![1])
        ]
    );

    // Heating off: the setpoint is read, not written.
    let d = device(fixture, json!({"slave_id": 1, "heating": 3}));
    assert_eq!(setup_writes(&d), vec![(203, vec![0]), (205, vec![0])]);
    let setpoint = d.channel("Heating Setpoint").unwrap();
    assert!(setpoint.readonly && !setpoint.write_only);
    assert_eq!(setpoint.registers[0].read.unwrap().address, 203);

    // Room sensor: value = raw * 0.1 - 100, written back the same way.
    let d = device(fixture, json!({"slave_id": 1, "heating": 1}));
    let room = d.channel("Room Temperature").unwrap();
    assert_eq!(room.encode("21.5", &[None]).unwrap(), vec![vec![1215]]);
    assert_eq!(room.encode("-50", &[None]).unwrap(), vec![vec![500]]);
    assert_eq!(
        room.decode(&[&[1215]]).unwrap(),
        Reading::Value("21.5".into())
    );
    assert_eq!(
        d.channel("Water Pressure")
            .unwrap()
            .decode(&[&[1015]])
            .unwrap(),
        Reading::Value("1.5".into())
    );
    assert_eq!(
        d.channel("Flame").unwrap().decode(&[&[0x0008]]).unwrap(),
        Reading::Value("1".into())
    );

    // An s16 enum of negative values, a u8 parameter and a scale of 10.
    let d = device(
        fixture,
        json!({"slave_id": 1, "heating": 3, "input_mode": -4, "buzzer": 4, "filter_ms": 50}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![
            (91, vec![5]),
            (203, vec![0]),
            (205, vec![0]),
            (16430, vec![0xFFFC]),
            (49260, vec![4])
        ]
    );

    // The selector is required whatever its default, as by wb-mqtt-serial's validator.
    let err = resolve_template_device(&template(fixture), &json!({"slave_id": 1}))
        .unwrap_err()
        .to_string();
    assert!(err.contains("requires parameter `heating`"), "{err}");
}

/// Danfoss EKC 204A1 (WB-REF): r36 is declared `u16` with scale 0.1 and a range of -15 … -3 °C.
/// wb-mqtt-serial takes such a config and writes a negative value on an unsigned format as its
/// two's complement; rtu2mqtt used to refuse every allowed value ("out of range for u16").
#[test]
fn negative_values_on_unsigned_formats_are_twos_complement() {
    let fixture = "config-test-refrigeration-controller.json";
    let d = device(
        fixture,
        json!({"slave_id": 1, "heating_differential": -15, "setpoint_min": -50, "differential": 0.5}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![
            (10101, vec![5]),
            (10103, vec![0xFE0C]),
            (10105, vec![0]),
            (10149, vec![0xFF6A])
        ]
    );
    let d = device(
        fixture,
        json!({"slave_id": 1, "heating_differential": -3.5}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![(10105, vec![0]), (10149, vec![0xFFDD])]
    );
    // The template's range still applies, in the value's units.
    let err = resolve_template_device(
        &template(fixture),
        &json!({"slave_id": 1, "heating_differential": -20}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("heating_differential"), "{err}");
    // A channel on an unsigned format takes a negative value the same way.
    let cutout = d.channel("Cutout").unwrap();
    assert_eq!(cutout.encode("-2.5", &[None]).unwrap(), vec![vec![0xFFE7]]);
}

/// A bare parameter name beside `||`/`&&`: wb-mqtt-serial's evaluator (`EvalImpl` in
/// `src/expression_evaluator.cpp`) makes `||` and `&&` false while either operand is undefined,
/// so `zone_mode||boost==1` drops the channel until the config gives `zone_mode`, however
/// `boost` (default 1) stands. rtu2mqtt used to take the bare name as false and evaluate the
/// rest, polling the channel and writing the parameter and setup item.
#[test]
fn undefined_bare_name_makes_or_and_false() {
    let fixture = "config-test-zone-controller.json";
    let ids = |d: &ResolvedDevice| d.channels.iter().map(|c| c.id.clone()).collect::<Vec<_>>();

    let d = device(fixture, json!({"slave_id": 1, "zone_limit": 30}));
    assert_eq!(ids(&d), vec!["Zone Alarm"]);
    assert_eq!(setup_writes(&d), vec![(51, vec![0])]);

    // `zone_mode: 0` is defined (and false): the `boost==1` operand decides.
    let d = device(
        fixture,
        json!({"slave_id": 1, "zone_mode": 0, "zone_limit": 30}),
    );
    assert_eq!(ids(&d), vec!["Zone Temperature", "Zone Alarm"]);
    assert_eq!(
        setup_writes(&d),
        vec![(40, vec![0]), (42, vec![30]), (50, vec![1])]
    );

    let d = device(fixture, json!({"slave_id": 1, "zone_mode": 2, "boost": 1}));
    assert_eq!(ids(&d), vec!["Zone Temperature", "Zone Valve"]);
}

/// `on_value`/`off_value` are in the channel's units: wb-mqtt-serial (`GetTextValue` and
/// `SetValueToChannel` in `src/serial_port_driver.cpp`, the conversion in `src/register.cpp`)
/// compares the published text with the decimal on_value and writes on_value through scale
/// and offset, masked to the field. rtu2mqtt used to compare and write them raw.
#[test]
fn on_off_values_after_scale_and_offset() {
    let d = device("config-test-scaled-switches.json", json!({"slave_id": 1}));
    let channel = |id: &str| d.channel(id).unwrap();
    let read = |id: &str, word: u16| channel(id).decode(&[&[word]]).unwrap();
    let write = |id: &str, text: &str| channel(id).encode(text, &[Some(&[0u16][..])]).unwrap();

    // Scale 0.1: "on" is raw 100.
    assert_eq!(read("Heater", 100), Reading::Value("1".into()));
    assert_eq!(read("Heater", 0), Reading::Value("0".into()));
    assert_eq!(read("Heater", 55), Reading::Value("5.5".into()));
    assert_eq!(write("Heater", "1"), vec![vec![100]]);
    assert_eq!(write("Heater", "0"), vec![vec![0]]);

    // Scale -1, offset 1: "on" (1) is raw 0, "off" (0) raw 1.
    assert_eq!(read("Bypass", 0), Reading::Value("1".into()));
    assert_eq!(read("Bypass", 1), Reading::Value("0".into()));
    assert_eq!(write("Bypass", "1"), vec![vec![0]]);
    assert_eq!(write("Bypass", "0"), vec![vec![1]]);

    // s16 with on_value 0xFFFF: written as 0xFFFF, read back as -1 (not "1"), as upstream.
    assert_eq!(write("Pump", "1"), vec![vec![0xFFFF]]);
    assert_eq!(read("Pump", 0xFFFF), Reading::Value("-1".into()));

    // on_value 3 on a 1-bit field: written masked (bit 2 set), the bit reads as "1".
    assert_eq!(write("Mode Bit", "1"), vec![vec![0b100]]);
    assert_eq!(read("Mode Bit", 0b100), Reading::Value("1".into()));
}

/// A float32 with a scale prints with 7 significant digits, as wb-mqtt-serial's
/// `ToScaledTextValue<float>` (`src/register.cpp`); rtu2mqtt printed 15 once scaled.
#[test]
fn scaled_float_prints_seven_digits() {
    let d = device("config-test-scaled-switches.json", json!({"slave_id": 1}));
    let bits = 123456.7f32.to_bits();
    assert_eq!(
        d.channel("Energy")
            .unwrap()
            .decode(&[&[(bits >> 16) as u16, bits as u16]])
            .unwrap(),
        Reading::Value("123.4567".into())
    );
}

/// A channel whose register cannot be loaded (a `string` without `string_data_size`) is left
/// out with a warning naming file, line and channel, and the rest of the device loads, as
/// wb-mqtt-serial's `LoadSimpleChannel` (`src/serial_config.cpp`) does. rtu2mqtt used to refuse
/// the whole device.
#[test]
fn unloadable_channel_is_left_out_with_a_warning() {
    let fixture = "config-test-unloadable-channels.json";
    let (d, warnings) = rtu2mqtt::device::resolve_template_device_with_warnings(
        &template(fixture),
        &json!({"slave_id": 1}),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let ids: Vec<&str> = d.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Temperature", "Status"]);
    let texts: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    assert_eq!(texts.len(), 2, "{texts:#?}");
    for (text, line, index, name) in [
        (&texts[0], ":11:", "channels[1]", "`Firmware`"),
        (&texts[1], ":12:", "channels[2]", "`Model`"),
    ] {
        assert!(text.contains(fixture) && text.contains(line), "{text}");
        assert!(text.contains(index) && text.contains(name), "{text}");
        assert!(
            text.contains("is ignored") && text.contains("string_data_size"),
            "{text}"
        );
    }

    // check-templates reports them as warnings, not errors.
    let found = check_template(&template(fixture));
    assert_eq!(found.len(), 2, "{found:#?}");
    assert!(found
        .iter()
        .all(|e| matches!(e.problem, rtu2mqtt::config::Problem::Warning(_))));

    // A part of `consists_of` that cannot be loaded still refuses the device, as wb-mqtt-serial
    // throws there; so does a negative `error_value`, which its schema refuses.
    for channel in [
        json!({"name": "Pair", "consists_of": [
            {"reg_type": "input", "address": 5},
            {"reg_type": "input", "address": 6, "format": "string"}]}),
        json!({"name": "Humidity", "reg_type": "input", "address": 2, "error_value": -1}),
    ] {
        let err = resolve_template_device(
            &template(fixture),
            &json!({"slave_id": 1, "channels": [channel]}),
        );
        assert!(err.is_err(), "{channel}");
    }
}

/// `on_value` on a `consists_of` channel: wb-mqtt-serial's `LoadSimpleChannel` applies it to a
/// single register and refuses it on more; rtu2mqtt ignored it on both.
#[test]
fn on_value_on_consists_of() {
    let fixture = "config-test-scaled-switches.json";
    let err = resolve_template_device(
        &template(fixture),
        &json!({"slave_id": 1, "channels": [{"name": "Pair", "type": "switch", "on_value": 1,
            "consists_of": [{"reg_type": "holding", "address": 5}, {"reg_type": "holding", "address": 6}]}]}),
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("on_value") && err.contains("one register"),
        "{err}"
    );
    let d = device(
        fixture,
        json!({"slave_id": 1, "channels": [{"name": "Single", "type": "switch", "on_value": 5, "off_value": 2,
            "consists_of": [{"reg_type": "holding", "address": 5}]}]}),
    );
    let single = d.channel("Single").unwrap();
    assert_eq!(single.decode(&[&[5]]).unwrap(), Reading::Value("1".into()));
    assert_eq!(single.encode("0", &[None]).unwrap(), vec![vec![2]]);
}

/// `enum` and `enum_titles` of different lengths: wb-mqtt-serial's `LoadSimpleChannel`
/// (`src/serial_config.cpp`) warns and publishes no titles for the channel; rtu2mqtt used to
/// pair them by position.
#[test]
fn enum_titles_of_another_length_are_not_published() {
    let fixture = "config-test-enum-titles.json";
    let (d, warnings) = rtu2mqtt::device::resolve_template_device_with_warnings(
        &template(fixture),
        &json!({"slave_id": 1}),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let mode = &d.channel("Mode").unwrap().enum_titles;
    assert_eq!(
        mode.iter().map(|t| t.value.as_str()).collect::<Vec<_>>(),
        vec!["0", "1", "2"]
    );
    assert!(mode[0]
        .title
        .iter()
        .any(|(lang, text)| lang == "ru" && text == "Выкл"));
    assert!(d.channel("Fan").unwrap().enum_titles.is_empty());
    let level = &d.channel("Level").unwrap().enum_titles;
    assert_eq!(
        level.iter().map(|t| t.value.as_str()).collect::<Vec<_>>(),
        vec!["0", "1", "2.5"]
    );
    let texts: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    assert_eq!(texts.len(), 1, "{texts:#?}");
    assert!(
        texts[0].contains(fixture)
            && texts[0].contains(":11:")
            && texts[0].contains("channels[1].enum_titles")
            && texts[0].contains("`Fan`"),
        "{}",
        texts[0]
    );
}

/// Object-form parameters become setup items in the byte order of their keys, as
/// wb-mqtt-serial's `AppendSetupItems` (`src/config_merge_template.cpp`) walks a jsoncpp object
/// (a sorted map): of two on one address the first in that order is written, and
/// `preserve_setup_order` writes in that order. rtu2mqtt used the declaration order.
#[test]
fn object_parameters_in_key_order() {
    let d = device(
        "config-test-parameter-order.json",
        json!({"slave_id": 1, "zeta_delay": 5, "alpha_mode": 1, "Beta_delay": 7}),
    );
    assert_eq!(setup_writes(&d), vec![(20, vec![7]), (10, vec![1])]);
}

/// `condition`s inside a subdevice: wb-mqtt-serial evaluates them for the device only
/// (`MergeChannelConfigWithTemplate` in `src/config_merge_template.cpp` calls
/// `AppendSetupItems` without an expression cache, so `CheckCondition` holds; and
/// `RemoveDisabledChannels` looks at the device's own channels). So a subdevice's parameters and
/// setup items are written and its channels kept whatever their condition; rtu2mqtt evaluated
/// them over the subdevice's values and wrote and polled less.
#[test]
fn conditions_inside_a_subdevice_are_not_evaluated() {
    let fixture = "config-test-subdevice-conditions.json";
    let d = device(
        fixture,
        json!({"slave_id": 1, "channels": [{"name": "Boiler", "device_type": "boiler_gas", "curve_shift": 5}]}),
    );
    // `curve` stays at its default 0, so `curve>0` is false; all the same, the parameter and the
    // setup item behind it are written and the channel is polled.
    assert_eq!(setup_writes(&d), vec![(203, vec![1]), (207, vec![5])]);
    assert_channel(&d, "Boiler Outdoor", Input, 211, U16, Polled);
    assert!(d.channel("Boiler Mode").is_some());
    // The device's own conditions still hold sway (`zones` defaults to 1).
    assert!(d.channel("Zone 2 Temperature").is_none());
    let d = device(fixture, json!({"slave_id": 1, "zones": 2}));
    assert!(d.channel("Zone 2 Temperature").is_some());
}

/// Enum titles in a subdevice: wb-mqtt-serial translates them with the subdevice's context
/// (`Translate(title, true, context)` in `LoadSimpleChannel`, `src/serial_config.cpp`) and
/// publishes them in the control's meta (`SetEnumValueTitles` in `TSerialPortDriver`), so they
/// carry the subdevice's name as a prefix, in each language. rtu2mqtt published the titles
/// alone.
#[test]
fn enum_titles_in_a_subdevice_carry_its_name() {
    let d = device(
        "config-test-subdevice-conditions.json",
        json!({"slave_id": 1, "channels": [{"name": "Boiler", "device_type": "boiler_gas"}]}),
    );
    let mode = d.channel("Boiler Mode").unwrap();
    let titles: Vec<(&str, Option<&str>, Option<&str>)> = mode
        .enum_titles
        .iter()
        .map(|e| {
            (
                e.value.as_str(),
                e.title.get("en").map(String::as_str),
                e.title.get("ru").map(String::as_str),
            )
        })
        .collect();
    assert_eq!(
        titles,
        vec![
            ("0", Some("Boiler Off"), Some("Котёл Off")),
            ("1", Some("Boiler On"), Some("Котёл Вкл")),
        ]
    );
}

/// Bit fields as wb-mqtt-serial cuts them out: unsigned (`GetRegisterValueFromReadData` in
/// `src/modbus_common.cpp`), then converted as the format's whole width (`ConvertFromRawValue`
/// in `src/register.cpp`, `Get<int16_t>`), so a 4-bit `s16` field reads 0xF as 15 where
/// rtu2mqtt extended the field's own top bit (-1).
#[test]
fn narrow_signed_field_reads_unsigned() {
    let d = rtu2mqtt::device::resolve_template_device_with_warnings(
        &template("config-test-bit-fields.json"),
        &json!({"slave_id": 1}),
    )
    .unwrap_or_else(|e| panic!("{e}"))
    .0;
    let nibble = d.channel("Offset Nibble").unwrap();
    assert_eq!(
        nibble.decode(&[&[0xFF0F]]).unwrap(),
        Reading::Value("15".into())
    );
    let byte = d.channel("Signed Byte").unwrap();
    assert_eq!(
        byte.decode(&[&[0x0FFF]]).unwrap(),
        Reading::Value("-1".into())
    );
}

/// A bit shift above 255 (`"5:300:1"`): wb-mqtt-serial's `LoadRegisterBitsAddress` throws inside
/// `LoadSimpleChannel`'s `try`, so the channel is ignored and the rest of the device loads.
/// rtu2mqtt refused the whole template when it read it.
#[test]
fn bit_shift_above_255_leaves_the_channel_out() {
    let fixture = "config-test-bit-fields.json";
    let (d, warnings) = rtu2mqtt::device::resolve_template_device_with_warnings(
        &template(fixture),
        &json!({"slave_id": 1}),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let ids: Vec<&str> = d.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Offset Nibble", "Signed Byte", "Status"]);
    let texts: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    assert_eq!(texts.len(), 2, "{texts:#?}");
    let text = texts
        .iter()
        .find(|t| t.contains("`Far Flag`"))
        .unwrap_or_else(|| panic!("{texts:#?}"));
    assert!(text.contains(fixture) && text.contains(":14:"), "{text}");
    assert!(text.contains("channels[3].address"), "{text}");
    assert!(
        text.contains("is ignored") && text.contains("300"),
        "{text}"
    );
    let found = check_template(&template(fixture));
    assert_eq!(found.len(), 2, "{found:#?}");
    assert!(found
        .iter()
        .all(|f| matches!(f.problem, rtu2mqtt::config::Problem::Warning(_))));
    // In a setup item (or a parameter) the address is still refused, as wb-mqtt-serial throws
    // there outside any `try`.
    let err = resolve_template_device(
        &template(fixture),
        &json!({"slave_id": 1, "setup": [{"title": "far", "address": "5:300:1", "value": 1}]}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("300"), "{err}");
}

/// A bit shift at or beyond the width of the value's format (`"5:8:8"` on an `s8`, `"400:16:8"`
/// on a `u16`): wb-mqtt-serial's `TRegisterConfig` throws "bit offset must not exceed 8 bits"
/// (`src/register.cpp`) inside `LoadSimpleChannel`'s `try`, which warns that the channel "is
/// ignored" and loads the rest of the device. rtu2mqtt read such a channel from the registers
/// after it (a u16 at `"400:16:8"` published the low byte of register 401).
#[test]
fn bit_shift_beyond_the_format_leaves_the_channel_out() {
    let fixture = "config-test-bit-fields.json";
    let (d, warnings) = rtu2mqtt::device::resolve_template_device_with_warnings(
        &template(fixture),
        &json!({"slave_id": 1}),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(d.channel("High Signed Byte").is_none());
    let texts: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    let text = texts
        .iter()
        .find(|t| t.contains("`High Signed Byte`"))
        .unwrap_or_else(|| panic!("{texts:#?}"));
    assert!(text.contains("channels[2].address"), "{text}");
    assert!(
        text.contains("is ignored")
            && text.contains("bit shift 8")
            && text.contains("8 bits of format `s8`"),
        "{text}"
    );

    let inline = |channels: serde_json::Value| {
        let raw = json!({"device_type": "shift", "device": {"name": "S", "id": "s",
            "channels": channels}});
        let template = rtu2mqtt::config::TemplateFile::from_source(
            rtu2mqtt::config::parse::SourceText::from_text(
                std::path::Path::new("shift.json"),
                &raw.to_string(),
            ),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        rtu2mqtt::device::resolve_template_device_with_warnings(&template, &json!({"slave_id": 1}))
    };
    let (d, warnings) = inline(json!([
        {"name": "Shift", "reg_type": "input", "address": "400:16:8"},
        {"name": "Wide", "reg_type": "input", "address": "400:15:8"},
        {"name": "Byte", "reg_type": "input", "address": "402:7:1", "format": "u8"}
    ]))
    .unwrap_or_else(|e| panic!("{e}"));
    let ids: Vec<&str> = d.channels.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, vec!["Wide", "Byte"]);
    let texts: Vec<String> = warnings.iter().map(|w| w.to_string()).collect();
    assert_eq!(texts.len(), 1, "{texts:#?}");
    assert!(
        texts[0].contains("`Shift`") && texts[0].contains("16 bits of format `u16`"),
        "{texts:#?}"
    );
    // A setup item is refused, as wb-mqtt-serial throws there outside any `try`.
    let err = resolve_template_device(
        &template(fixture),
        &json!({"slave_id": 1, "setup": [{"title": "hi", "address": "5:8:8", "format": "u8",
            "value": 1}]}),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("bit shift 8"), "{err}");
}

/// WB-MAO4's light scenes: a `required` parameter with a `default` behind a condition must be
/// given once the condition holds over the config's values, as wb-mqtt-serial's validator
/// requires it (`MakeDeviceParametersSchema` in `src/config_schema_generator.cpp` adds it to the
/// schema's `required`; `IsRequiredSetupRegister` reads `required` alone, `default` is not in
/// that schema). Bounds and enums are checked for the declarations whose condition holds over
/// the config's own values, without defaults, as that schema has them (one whose condition
/// holds only while a parameter is not given is checked, and not written), and also for the
/// declaration in effect once the defaults are in, the one written: a value outside it is
/// refused where wb-mqtt-serial, which merges the defaults in after validating, writes it.
#[test]
fn parameter_rules_over_the_configs_own_values() {
    let fixture = "config-test-light-scenes.json";

    let err = refused(fixture, json!({"slave_id": 1, "ls_1_ch_1_action_off": 2}));
    assert!(
        err.contains("requires parameter `ls_1_ch_1_fading_off`"),
        "{err}"
    );
    assert!(!err.contains("ls_1_ch_1_level_off"), "{err}");
    let d = device(
        fixture,
        json!({"slave_id": 1, "ls_1_ch_1_action_off": 3, "ls_1_ch_1_fading_off": 0, "ls_1_ch_1_level_off": 100}),
    );
    assert_eq!(
        setup_writes(&d),
        vec![(1280, vec![3]), (1288, vec![0]), (1296, vec![100])]
    );
    let d = device(fixture, json!({"slave_id": 1, "ls_1_ch_1_action_off": 0}));
    assert_eq!(setup_writes(&d), vec![(1280, vec![0])]);

    // `input_1_mode==0` holds only through the default: wb-mqtt-serial's validator does not
    // check the value but the value is written, so its bounds apply; within them it is written.
    let err = refused(fixture, json!({"slave_id": 1, "input_1_hold_time": 300}));
    assert!(err.contains("outside its range 500…5000"), "{err}");
    let d = device(fixture, json!({"slave_id": 1, "input_1_hold_time": 700}));
    assert_eq!(setup_writes(&d), vec![(1100, vec![700])]);
    let err = refused(
        fixture,
        json!({"slave_id": 1, "input_1_mode": 0, "input_1_hold_time": 300}),
    );
    assert!(err.contains("outside its range 500…5000"), "{err}");
    // Another mode: the declaration is not in effect either way, the value neither checked nor
    // written.
    let d = device(
        fixture,
        json!({"slave_id": 1, "input_1_mode": 1, "input_1_hold_time": 300}),
    );
    assert_eq!(setup_writes(&d), vec![(416, vec![1])]);

    // `isDefined(input_1_mode)==0` holds over the config's values: checked; with the defaults
    // merged in it does not: not written.
    let err = refused(fixture, json!({"slave_id": 1, "input_1_legacy_time": 300}));
    assert!(err.contains("outside its range 0…250"), "{err}");
    let d = device(fixture, json!({"slave_id": 1, "input_1_legacy_time": 200}));
    assert_eq!(setup_writes(&d), vec![]);
}

/// A value refused by both checks (the declaration wb-mqtt-serial's validator sees and the one
/// written), each with its own `enum`: both are said. Saying only the first sent the user to a
/// value the second refuses (`input_1_action: 1`, "allowed: 0, 1", then "allowed: 0, 2").
#[test]
fn a_value_refused_by_both_declarations_names_both() {
    let fixture = "config-test-light-scenes.json";
    let err = refused(fixture, json!({"slave_id": 1, "input_1_action": 3}));
    assert!(err.contains("allowed: 0, 1"), "{err}");
    assert!(err.contains("allowed: 0, 2"), "{err}");
    // Within the one the validator sees, outside the one written: refused, that one named.
    let err = refused(fixture, json!({"slave_id": 1, "input_1_action": 1}));
    assert!(err.contains("allowed: 0, 2"), "{err}");
    let err = refused(fixture, json!({"slave_id": 1, "input_1_action": 2}));
    assert!(err.contains("allowed: 0, 1"), "{err}");
    let d = device(fixture, json!({"slave_id": 1, "input_1_action": 0}));
    assert_eq!(setup_writes(&d), vec![(1130, vec![0])]);
    let d = device(
        fixture,
        json!({"slave_id": 1, "input_1_mode": 0, "input_1_action": 2}),
    );
    assert_eq!(setup_writes(&d), vec![(416, vec![0]), (1130, vec![2])]);
}

/// Two declarations of one id that both hold only once the defaults are in: a config that
/// leaves the parameter out is accepted (nothing of it is written, and wb-mqtt-serial's
/// validator, over the config's own values, sees neither); one that gives it is refused, since
/// rtu2mqtt would not know which register to write.
#[test]
fn declarations_that_clash_only_through_defaults_matter_only_for_a_value_given() {
    let fixture = "config-test-light-scenes.json";
    let d = device(fixture, json!({"slave_id": 1}));
    assert_eq!(setup_writes(&d), vec![]);
    let err = refused(fixture, json!({"slave_id": 1, "input_1_repeat": 3}));
    assert!(
        err.contains("parameter `input_1_repeat` is declared 2 times and more than one applies"),
        "{err}"
    );
    // The mode given: both hold over the config's own values too, refused either way.
    let err = refused(fixture, json!({"slave_id": 1, "repeat_mode": 0}));
    assert!(
        err.contains("`input_1_repeat` is declared 2 times"),
        "{err}"
    );
}

/// A parameter left out takes, for conditions, the `default` of its first declaration that has
/// one (`MergeDeviceConfigWithTemplate` fills it in so), not nothing because the first
/// declaration has none: `LED Blinking` (condition `led_mode==2`) is polled with nothing given.
#[test]
fn a_missing_value_takes_the_first_default_declared() {
    let fixture = "config-test-light-scenes.json";
    let names = |config: serde_json::Value| -> Vec<String> {
        device(fixture, config)
            .channels
            .iter()
            .map(|c| c.name.clone())
            .collect()
    };
    assert!(names(json!({"slave_id": 1})).contains(&"LED Blinking".to_string()));
    assert!(!names(json!({"slave_id": 1, "led_mode": 1})).contains(&"LED Blinking".to_string()));
    // The default is filled in whatever its declaration's condition, as there.
    assert!(names(json!({"slave_id": 1, "repeat_mode": 2})).contains(&"LED Blinking".to_string()));
}

/// A subdevice's parameter is written whatever its condition (wb-mqtt-serial's
/// `AppendSetupItems` without an expression cache; `conditions_inside_a_subdevice_are_not_evaluated`),
/// so its bounds apply whatever its condition: `curve_shift` (`min` -20, `max` 20, behind
/// `curve>0` with `curve` at its default 0) at 50 was written to the device unchecked.
#[test]
fn a_subdevice_parameter_written_whatever_its_condition_is_checked() {
    let fixture = "config-test-subdevice-conditions.json";
    let config = |shift: i64| json!({"slave_id": 1, "channels": [{"name": "Boiler", "device_type": "boiler_gas", "curve_shift": shift}]});
    let err = resolve_template_device(&template(fixture), &config(50))
        .unwrap_err()
        .to_string();
    assert!(err.contains("outside its range -20…20"), "{err}");
    let d = device(fixture, config(-5));
    assert_eq!(setup_writes(&d), vec![(203, vec![1]), (207, vec![0xFFFB])]);
}
