//! The Wiren Board layout of one device: device and control meta (JSON and the legacy
//! subtopics), error topics, and the removal of all of it. Pure functions of the resolved device.

use std::collections::BTreeMap;

use serde_json::{json, Value};

use super::topics::TopicScheme;
use super::Publication;
use crate::device::number_text::format_g;
use crate::device::{ResolvedChannel, ResolvedDevice};
use crate::device_updates::DeviceIdentity;

/// `driver` in device meta.
pub const DRIVER_NAME: &str = "rtu2mqtt";

/// Device meta JSON, `meta/name`, `meta/driver` (no `meta/error`: that is state). What the
/// device told about itself goes into the JSON as `model`, `serial_number` and `firmware`
/// once known (Wiren Board clients ignore keys they do not know).
pub fn device_meta(
    topics: &TopicScheme,
    device: &ResolvedDevice,
    identity: &DeviceIdentity,
) -> Vec<Publication> {
    let mut meta = json!({ "driver": DRIVER_NAME, "title": { "en": device.name } });
    for (key, value) in [
        ("model", &identity.model),
        ("serial_number", &identity.serial_number),
        ("firmware", &identity.firmware),
    ] {
        if let Some(value) = value {
            meta[key] = json!(value);
        }
    }
    vec![
        Publication::retained(topics.device_meta(&device.id, None), meta.to_string()),
        Publication::retained(topics.device_meta(&device.id, Some("name")), &device.name),
        Publication::retained(topics.device_meta(&device.id, Some("driver")), DRIVER_NAME),
    ]
}

/// Device `meta/error`: `r` while the device does not answer.
pub fn device_error(topics: &TopicScheme, device_id: &str, online: bool) -> Publication {
    Publication::retained(
        topics.device_meta(device_id, Some("error")),
        if online { "" } else { "r" },
    )
}

/// Control meta JSON and the legacy subtopics (`type`, `order`, `readonly`, and `min`, `max`,
/// `precision`, `units` when set).
pub fn control_meta(
    topics: &TopicScheme,
    device_id: &str,
    channel: &ResolvedChannel,
) -> Vec<Publication> {
    let topic = |sub: Option<&str>| topics.control_meta(device_id, &channel.id, sub);
    let mut out = vec![Publication::retained(
        topic(None),
        control_meta_json(channel).to_string(),
    )];
    let mut legacy = vec![
        ("type", channel.control_type.clone()),
        ("order", channel.order.to_string()),
        (
            "readonly",
            if channel.readonly { "1" } else { "0" }.to_string(),
        ),
    ];
    for (key, value) in [
        ("min", channel.min),
        ("max", channel.max),
        ("precision", channel.precision),
    ] {
        if let Some(value) = value.filter(|v| v.is_finite()) {
            legacy.push((key, format_g(value, 15)));
        }
    }
    if let Some(units) = &channel.units {
        legacy.push(("units", units.clone()));
    }
    out.extend(
        legacy
            .into_iter()
            .map(|(key, value)| Publication::retained(topic(Some(key)), value)),
    );
    out
}

/// The control meta JSON, keys sorted as wb-mqtt-serial prints them; limits as floats
/// (`255.0`), `order` as an integer.
pub fn control_meta_json(channel: &ResolvedChannel) -> Value {
    let mut meta: BTreeMap<&str, Value> = BTreeMap::new();
    meta.insert("type", json!(channel.control_type));
    meta.insert("order", json!(channel.order));
    meta.insert("readonly", json!(channel.readonly));
    for (key, value) in [
        ("min", channel.min),
        ("max", channel.max),
        ("precision", channel.precision),
    ] {
        if let Some(value) = value.filter(|v| v.is_finite()) {
            meta.insert(key, json!(value));
        }
    }
    if let Some(units) = &channel.units {
        meta.insert("units", json!(units));
    }
    if !channel.title.is_empty() {
        meta.insert("title", json!(channel.title));
    }
    if !channel.enum_titles.is_empty() {
        let titles: BTreeMap<&str, &crate::device::Titles> = channel
            .enum_titles
            .iter()
            .map(|e| (e.value.as_str(), &e.title))
            .collect();
        meta.insert("enum", json!(titles));
    }
    if channel.hidden {
        meta.insert("hidden", json!(true));
    }
    json!(meta)
}

/// Control `meta/error`: letters `r`, `w`, `p` in that order, empty when fine.
pub fn control_error(
    topics: &TopicScheme,
    device_id: &str,
    control_id: &str,
    letters: &str,
) -> Publication {
    Publication::retained(
        topics.control_meta(device_id, control_id, Some("error")),
        letters,
    )
}

/// A control's value: retained, except for pushbuttons (a retained press would fire again for
/// every new subscriber).
pub fn control_value(
    topics: &TopicScheme,
    device_id: &str,
    channel: &ResolvedChannel,
    value: &str,
) -> Publication {
    let topic = topics.control(device_id, &channel.id);
    if is_pushbutton(channel) {
        Publication::transient(topic, value)
    } else {
        Publication::retained(topic, value)
    }
}

pub fn is_pushbutton(channel: &ResolvedChannel) -> bool {
    channel.control_type == "pushbutton"
}

/// Whether clients may write the control (it gets an `/on` subscription).
pub fn is_writable(channel: &ResolvedChannel) -> bool {
    !channel.readonly
}

/// Every retained topic the driver publishes for a control (value, meta, legacy meta, error).
pub fn control_topics(
    topics: &TopicScheme,
    device_id: &str,
    channel: &ResolvedChannel,
) -> Vec<String> {
    let mut out = vec![topics.control(device_id, &channel.id)];
    out.extend(
        control_meta(topics, device_id, channel)
            .into_iter()
            .map(|p| p.topic),
    );
    out.push(topics.control_meta(device_id, &channel.id, Some("error")));
    out
}

/// The legacy meta subtopics a control may have (those of [`control_meta`], and `error`).
const CONTROL_META_SUBTOPICS: [&str; 8] = [
    "type",
    "order",
    "readonly",
    "min",
    "max",
    "precision",
    "units",
    "error",
];

/// Every retained topic the driver may have published for a control of this id, whatever its
/// channel was (the value, meta and every legacy meta subtopic): what to delete for a control
/// found on the broker that the config no longer has.
pub fn any_control_topics(topics: &TopicScheme, device_id: &str, control_id: &str) -> Vec<String> {
    let mut out = vec![
        topics.control(device_id, control_id),
        topics.control_meta(device_id, control_id, None),
    ];
    out.extend(
        CONTROL_META_SUBTOPICS
            .iter()
            .map(|sub| topics.control_meta(device_id, control_id, Some(sub))),
    );
    out
}

/// Every retained WB topic of a device, controls first and device meta last, so a reader that
/// watches device meta sees the device disappear after its controls.
pub fn device_topics(topics: &TopicScheme, device: &ResolvedDevice) -> Vec<String> {
    let mut out: Vec<String> = device
        .channels
        .iter()
        .flat_map(|c| control_topics(topics, &device.id, c))
        .collect();
    out.push(topics.device_availability(&device.id));
    out.push(topics.device_meta(&device.id, Some("error")));
    out.extend(
        device_meta(topics, device, &DeviceIdentity::default())
            .into_iter()
            .map(|p| p.topic),
    );
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::device::{
        ChannelRegister, EnumTitle, EventMode, RegisterFormat, Titles, ValueCodec,
    };

    pub(crate) fn channel(id: &str, control_type: &str) -> ResolvedChannel {
        ResolvedChannel {
            id: id.to_string(),
            name: id.to_string(),
            title: Titles::from([("en".to_string(), id.to_string())]),
            registers: vec![ChannelRegister {
                read: None,
                write: None,
                write_function: Default::default(),
                codec: ValueCodec::plain(RegisterFormat::U16),
                press_counter: false,
            }],
            control_type: control_type.to_string(),
            units: None,
            min: None,
            max: None,
            precision: None,
            readonly: false,
            write_only: false,
            order: 1,
            enum_titles: Vec::new(),
            events: EventMode::Polled,
            read_period: None,
            read_rate_limit: None,
            fw: None,
            hidden: false,
            group: None,
        }
    }

    /// What a control found on the broker but not in the config gets deleted: everything
    /// any channel of that id publishes.
    #[test]
    fn any_control_topics_cover_every_topic_of_a_control() {
        let topics = TopicScheme::new("", "rtu2mqtt").unwrap();
        let mut full = channel("Level", "range");
        full.min = Some(0.0);
        full.max = Some(100.0);
        full.precision = Some(0.1);
        full.units = Some("%".into());
        let any = any_control_topics(&topics, "dev", "Level");
        for topic in control_topics(&topics, "dev", &full) {
            assert!(any.contains(&topic), "{topic}");
        }
        assert_eq!(any.len(), 10);
    }

    #[test]
    fn meta_json_matches_wb_mqtt_serial() {
        let mut dimmer = channel("Dimmer", "dimmer");
        dimmer.max = Some(255.0);
        dimmer.title.clear();
        assert_eq!(
            control_meta_json(&dimmer).to_string(),
            r#"{"max":255.0,"order":1,"readonly":false,"type":"dimmer"}"#
        );
        let mut value = channel("V", "value");
        value.precision = Some(0.01);
        value.title.clear();
        assert_eq!(
            control_meta_json(&value).to_string(),
            r#"{"order":1,"precision":0.01,"readonly":false,"type":"value"}"#
        );
    }

    #[test]
    fn enum_hidden_and_units_are_in_meta() {
        let mut mode = channel("Mode", "value");
        mode.units = Some("deg C".into());
        mode.hidden = true;
        mode.enum_titles = vec![EnumTitle {
            value: "0".into(),
            title: Titles::from([("en".into(), "Off".into())]),
        }];
        let meta = control_meta_json(&mode).to_string();
        assert_eq!(
            meta,
            r#"{"enum":{"0":{"en":"Off"}},"hidden":true,"order":1,"readonly":false,"title":{"en":"Mode"},"type":"value","units":"deg C"}"#
        );
    }

    #[test]
    fn pushbutton_values_are_not_retained() {
        let topics = TopicScheme::new("", "rtu2mqtt").unwrap();
        let button = channel("Reset", "pushbutton");
        assert!(!control_value(&topics, "d", &button, "1").retain);
        assert!(control_value(&topics, "d", &channel("K1", "switch"), "1").retain);
    }
}
