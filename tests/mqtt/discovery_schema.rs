//! Home Assistant discovery configs of every WB control type validate against a JSON Schema of
//! the fields HA requires (`tests/data/ha-discovery.schema.json`, written from HA's docs).

use std::collections::BTreeSet;

use crate::mqtt_support::{repo, template_device};
use rtu2mqtt::device::{EnumTitle, ResolvedDevice, Titles};
use rtu2mqtt::device_updates::DeviceIdentity;
use rtu2mqtt::mqtt::discovery::{device_configs, DiscoverySettings};
use rtu2mqtt::mqtt::TopicScheme;
use serde_json::{json, Value};

fn validator() -> jsonschema::Validator {
    let text = std::fs::read_to_string(repo("tests/data/ha-discovery.schema.json")).unwrap();
    let schema: Value = serde_json::from_str(&text).unwrap();
    jsonschema::validator_for(&schema).unwrap()
}

/// The climate sensor with one extra control per WB type, writable and read-only.
fn every_control_type() -> ResolvedDevice {
    let mut device = (*template_device("rtu2mqtt-climate", 2)).clone();
    let base = device.channels[0].clone();
    let types = [
        "switch",
        "alarm",
        "pushbutton",
        "range",
        "dimmer",
        "rgb",
        "text",
        "value",
        "unixtime",
        "w1-id",
        "temperature",
        "rel_humidity",
        "atmospheric_pressure",
        "rainfall",
        "wind_speed",
        "power",
        "power_consumption",
        "voltage",
        "water_flow",
        "water_consumption",
        "resistance",
        "concentration",
        "heat_power",
        "heat_energy",
        "current",
        "pressure",
        "lux",
        "sound_level",
    ];
    for control_type in types {
        for readonly in [false, true] {
            let mut channel = base.clone();
            channel.id = format!("{control_type} {}", if readonly { "ro" } else { "rw" });
            channel.title.clear();
            channel.control_type = control_type.to_string();
            channel.units = None;
            channel.readonly = readonly;
            device.channels.make_mut().push(channel);
        }
    }
    // A writable value with titled values: a select.
    let mut mode = base.clone();
    mode.id = "mode".to_string();
    mode.control_type = "value".to_string();
    mode.readonly = false;
    mode.enum_titles = ["Auto", "Low", "High"]
        .iter()
        .enumerate()
        .map(|(value, title)| EnumTitle {
            value: value.to_string(),
            title: Titles::from([("en".to_string(), (*title).to_string())]),
        })
        .collect();
    device.channels.make_mut().push(mode);
    for (units, id) in [
        ("kWh", "energy"),
        ("m^3", "water"),
        ("mbar", "pressure mbar"),
        ("Hz", "f"),
    ] {
        let mut channel = base.clone();
        channel.id = id.to_string();
        channel.units = Some(units.to_string());
        device.channels.make_mut().push(channel);
    }
    device
}

fn messages(device: &ResolvedDevice, identity: &DeviceIdentity) -> Vec<(String, Value)> {
    let topics = TopicScheme::new("", "rtu2mqtt").unwrap();
    let settings = DiscoverySettings {
        prefix: "homeassistant".into(),
    };
    device_configs(&settings, &topics, device, identity)
        .into_iter()
        .map(|c| (c.topic, c.payload))
        .collect()
}

#[test]
fn every_control_type_validates() {
    let validator = validator();
    let device = every_control_type();
    let identity = DeviceIdentity {
        model: Some("WBMSW4".into()),
        serial_number: Some("123456".into()),
        firmware: Some("4.12.0".into()),
    };
    let messages = messages(&device, &identity);
    let components: BTreeSet<&str> = messages
        .iter()
        .filter_map(|(topic, _)| topic.split('/').nth(1))
        .collect();
    assert_eq!(
        components.into_iter().collect::<Vec<_>>(),
        [
            "binary_sensor",
            "button",
            "number",
            "select",
            "sensor",
            "switch",
            "text"
        ]
    );
    // A read-only pushbutton has no entity; every other control has one.
    assert_eq!(messages.len(), device.channels.len() - 1);
    let mut unique_ids = BTreeSet::new();
    for (topic, payload) in &messages {
        let message = json!({ "topic": topic, "payload": payload });
        let errors: Vec<String> = validator
            .iter_errors(&message)
            .map(|e| format!("{} at {}", e, e.instance_path()))
            .collect();
        assert!(errors.is_empty(), "{topic}: {errors:#?}\n{payload:#}");
        assert!(
            unique_ids.insert(payload["unique_id"].to_string()),
            "{topic}"
        );
        assert_eq!(payload["device"]["serial_number"], "123456");
        assert_eq!(payload["device"]["sw_version"], "4.12.0");
    }
}

#[test]
fn schema_rejects_ha_defaults_that_clash_with_wb_values() {
    let validator = validator();
    let device = every_control_type();
    let messages = messages(&device, &DeviceIdentity::default());
    let find = |component: &str| {
        messages
            .iter()
            .find(|(t, _)| t.split('/').nth(1) == Some(component))
            .cloned()
            .unwrap()
    };
    for (component, key) in [
        ("switch", "payload_on"),
        ("binary_sensor", "payload_off"),
        ("number", "min"),
        ("button", "payload_press"),
        ("sensor", "state_topic"),
    ] {
        let (topic, mut payload) = find(component);
        let message = json!({ "topic": topic, "payload": payload });
        assert!(validator.is_valid(&message), "{topic}");
        payload.as_object_mut().unwrap().remove(key);
        let message = json!({ "topic": topic, "payload": payload });
        assert!(!validator.is_valid(&message), "{topic} without {key}");
    }
}
