//! Home Assistant MQTT discovery: one HA device per bus device, one entity per control, in the
//! per-component form `<prefix>/<component>/<node>_<device>/<control>/config`.
//!
//! WB values are "1"/"0" and plain numbers, so every entity spells out its payloads and number
//! limits instead of relying on HA's defaults ("ON"/"OFF", "PRESS", min 1 max 100).

use serde_json::{json, Map, Value};

use super::topics::{topic_level, TopicScheme};
use crate::device::{ResolvedChannel, ResolvedDevice};
use crate::device_updates::DeviceIdentity;

/// Where discovery configs go and how ids are made.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiscoverySettings {
    /// `homeassistant` by default.
    pub prefix: String,
}

impl DiscoverySettings {
    /// Home Assistant's birth / last-will topic: `online` means "send your configs again".
    pub fn status_topic(&self) -> String {
        format!("{}/status", self.prefix)
    }
}

/// One entity's discovery message.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscoveryConfig {
    pub component: &'static str,
    pub topic: String,
    pub payload: Value,
}

/// HA device identifier: `<client id>_<device id>`, unique across controllers sharing a broker
/// (their client ids differ).
pub fn device_identifier(topics: &TopicScheme, device_id: &str) -> String {
    format!("{}_{}", topics.driver_node(), topic_level(device_id))
}

/// The HA entity kind for a control, or None when it gets no entity.
pub fn component_for(channel: &ResolvedChannel) -> Option<&'static str> {
    let writable = !channel.readonly;
    Some(match channel.control_type.as_str() {
        "switch" if writable => "switch",
        "switch" | "alarm" => "binary_sensor",
        "pushbutton" if writable => "button",
        "pushbutton" => return None,
        "text" | "rgb" if writable => "text",
        "text" | "rgb" | "unixtime" | "w1-id" => "sensor",
        _ if writable && select_options(channel).is_some() => "select",
        _ if writable => "number",
        _ => "sensor",
    })
}

/// Discovery configs of every control of `device`.
pub fn device_configs(
    settings: &DiscoverySettings,
    topics: &TopicScheme,
    device: &ResolvedDevice,
    identity: &DeviceIdentity,
) -> Vec<DiscoveryConfig> {
    device
        .channels
        .iter()
        .filter_map(|c| control_config(settings, topics, device, identity, c))
        .collect()
}

/// Where the discovery config of one control goes; None for a control without one. Depends on
/// the device's id and the channel only, so the topics to delete are found again from the
/// device, not kept.
pub fn config_topic(
    settings: &DiscoverySettings,
    topics: &TopicScheme,
    device_id: &str,
    channel: &ResolvedChannel,
) -> Option<String> {
    let component = component_for(channel)?;
    Some(format!(
        "{}/{component}/{}/{}/config",
        settings.prefix,
        device_identifier(topics, device_id),
        topic_level(&channel.id).to_lowercase()
    ))
}

/// The discovery config of one control.
pub fn control_config(
    settings: &DiscoverySettings,
    topics: &TopicScheme,
    device: &ResolvedDevice,
    identity: &DeviceIdentity,
    channel: &ResolvedChannel,
) -> Option<DiscoveryConfig> {
    let component = component_for(channel)?;
    let device_uid = device_identifier(topics, &device.id);
    let object = topic_level(&channel.id).to_lowercase();
    let state_topic = topics.control(&device.id, &channel.id);
    let command_topic = topics.control_on(&device.id, &channel.id);

    let mut config = Map::new();
    let name = channel
        .title
        .get("en")
        .cloned()
        .unwrap_or_else(|| channel.id.clone());
    config.insert("name".into(), json!(name));
    config.insert("unique_id".into(), json!(format!("{device_uid}_{object}")));
    config.insert("device".into(), device_block(topics, device, identity));
    config.insert(
        "origin".into(),
        json!({ "name": "rtu2mqtt", "sw_version": env!("CARGO_PKG_VERSION") }),
    );
    config.insert(
        "availability".into(),
        json!([
            { "topic": topics.driver_status(), "payload_available": "online", "payload_not_available": "offline" },
            { "topic": topics.device_availability(&device.id), "payload_available": "online", "payload_not_available": "offline" },
        ]),
    );
    config.insert("availability_mode".into(), json!("all"));
    config.insert("qos".into(), json!(1));
    if channel.hidden {
        config.insert("enabled_by_default".into(), json!(false));
    }

    match component {
        "switch" => {
            config.insert("state_topic".into(), json!(state_topic));
            config.insert("command_topic".into(), json!(command_topic));
            for (key, value) in [
                ("payload_on", "1"),
                ("payload_off", "0"),
                ("state_on", "1"),
                ("state_off", "0"),
            ] {
                config.insert(key.into(), json!(value));
            }
        }
        "binary_sensor" => {
            config.insert("state_topic".into(), json!(state_topic));
            config.insert("payload_on".into(), json!("1"));
            config.insert("payload_off".into(), json!("0"));
            if channel.control_type == "alarm" {
                config.insert("device_class".into(), json!("problem"));
            }
        }
        "button" => {
            config.insert("command_topic".into(), json!(command_topic));
            config.insert("payload_press".into(), json!("1"));
        }
        "text" => {
            config.insert("state_topic".into(), json!(state_topic));
            config.insert("command_topic".into(), json!(command_topic));
            if channel.control_type == "rgb" {
                config.insert("pattern".into(), json!(r"^\d{1,3};\d{1,3};\d{1,3}$"));
            }
        }
        "select" => {
            config.insert("state_topic".into(), json!(state_topic));
            config.insert("command_topic".into(), json!(command_topic));
            let options = select_options(channel).unwrap_or_default();
            // HA shows and sends the titles; the control's topics carry the values. A value
            // with no title (a device state the template does not name) is rendered `None`,
            // which HA shows as unknown: any other text not among the options would be refused
            // and leave the previous option on show.
            let to_value: Map<String, Value> = options
                .iter()
                .map(|(value, title)| (title.clone(), json!(value)))
                .collect();
            config.insert(
                "options".into(),
                json!(options.iter().map(|(_, title)| title).collect::<Vec<_>>()),
            );
            config.insert(
                "value_template".into(),
                json!(format!(
                    "{{{{ {}.get(value, 'None') }}}}",
                    Value::Object(title_of_value(&options))
                )),
            );
            config.insert(
                "command_template".into(),
                json!(format!("{{{{ {}[value] }}}}", Value::Object(to_value))),
            );
        }
        "number" => {
            config.insert("state_topic".into(), json!(state_topic));
            config.insert("command_topic".into(), json!(command_topic));
            number_limits(channel, &mut config);
            if let Some(unit) = units_of(channel) {
                config.insert(
                    "unit_of_measurement".into(),
                    json!(unit_class(unit).ha_unit),
                );
            }
        }
        _ => {
            config.insert("state_topic".into(), json!(state_topic));
            sensor_fields(channel, &mut config);
            // A read-only enum shows its titles too; a value without one shows as itself.
            if let Some(options) = enum_titles(channel) {
                config.insert(
                    "value_template".into(),
                    json!(format!(
                        "{{{{ {}.get(value, value) }}}}",
                        Value::Object(title_of_value(&options))
                    )),
                );
            }
        }
    }
    Some(DiscoveryConfig {
        component,
        topic: config_topic(settings, topics, &device.id, channel)?,
        payload: Value::Object(config),
    })
}

fn device_block(topics: &TopicScheme, device: &ResolvedDevice, identity: &DeviceIdentity) -> Value {
    let mut block = Map::new();
    block.insert(
        "identifiers".into(),
        json!([device_identifier(topics, &device.id)]),
    );
    block.insert("name".into(), json!(device.name));
    let model = identity
        .model
        .clone()
        .or_else(|| device.device_type.clone());
    if let Some(model) = model {
        block.insert("model".into(), json!(model));
    }
    if device.is_wb {
        block.insert("manufacturer".into(), json!("Wiren Board"));
    }
    if let Some(serial) = &identity.serial_number {
        block.insert("serial_number".into(), json!(serial));
    }
    if let Some(firmware) = &identity.firmware {
        block.insert("sw_version".into(), json!(firmware));
    }
    Value::Object(block)
}

/// The (value, English title) pairs of a control's `enum`, in its order (a value without an
/// English title by itself).
fn enum_titles(channel: &ResolvedChannel) -> Option<Vec<(String, String)>> {
    if channel.enum_titles.is_empty() {
        return None;
    }
    Some(
        channel
            .enum_titles
            .iter()
            .map(|entry| {
                let title = entry
                    .title
                    .get("en")
                    .cloned()
                    .unwrap_or_else(|| entry.value.clone());
                (entry.value.clone(), title)
            })
            .collect(),
    )
}

/// The titles of a control's `enum` when they make a select: every value titled, no title
/// twice (HA's options are the titles), none HA reads as "no option" (`None` in any case).
fn select_options(channel: &ResolvedChannel) -> Option<Vec<(String, String)>> {
    let options = enum_titles(channel)?;
    let titles: std::collections::BTreeSet<&str> =
        options.iter().map(|(_, title)| title.as_str()).collect();
    let usable = titles.len() == options.len()
        && titles
            .iter()
            .all(|title| !title.trim().is_empty() && !title.eq_ignore_ascii_case("none"));
    usable.then_some(options)
}

fn title_of_value(options: &[(String, String)]) -> Map<String, Value> {
    options
        .iter()
        .map(|(value, title)| (value.clone(), json!(title)))
        .collect()
}

/// HA's number defaults (1…100, step 1) do not fit WB controls: always send min, max, step.
fn number_limits(channel: &ResolvedChannel, config: &mut Map<String, Value>) {
    let is_range = matches!(channel.control_type.as_str(), "range" | "dimmer");
    let (default_min, default_max): (f64, f64) = if is_range {
        (0.0, 65535.0)
    } else {
        (-1e9, 1e9)
    };
    let min = channel.min.filter(|v| v.is_finite()).unwrap_or(default_min);
    let max = channel
        .max
        .filter(|v| v.is_finite() && *v > min)
        .unwrap_or(default_max.max(min + 1.0));
    // Integer registers hold values a `scale` apart (22.5 on a scale of 0.5): a coarser step
    // would keep HA from setting them, a finer one offers values the device cannot hold (a
    // `precision` finer than the scale included).
    let scales: Vec<f64> = channel
        .registers
        .iter()
        .filter(|register| register.codec.format.is_integer())
        .map(|register| register.codec.scale.abs())
        .collect();
    let integer_step = match scales.first() {
        Some(&scale)
            if scales.len() == channel.registers.len()
                && scale.is_finite()
                && scale > 0.0
                && scales.iter().all(|other| *other == scale) =>
        {
            Some(scale)
        }
        _ => None,
    };
    let precision = channel.precision.filter(|p| p.is_finite() && *p > 0.0);
    let step = match (precision, integer_step) {
        (Some(precision), Some(scale)) => precision.max(scale),
        (Some(precision), None) => precision,
        (None, Some(scale)) => scale,
        (None, None) if is_range => 1.0,
        (None, None) => 0.001,
    }
    .max(0.001);
    config.insert("min".into(), json!(min));
    config.insert("max".into(), json!(max));
    config.insert("step".into(), json!(step));
    config.insert(
        "mode".into(),
        json!(if is_range { "slider" } else { "box" }),
    );
}

/// Unit, device class and state class of a read-only numeric control.
fn sensor_fields(channel: &ResolvedChannel, config: &mut Map<String, Value>) {
    let numeric = !matches!(
        channel.control_type.as_str(),
        "text" | "rgb" | "unixtime" | "w1-id" | "switch" | "alarm"
    ) && channel.enum_titles.is_empty();
    if !numeric {
        return;
    }
    let class = units_of(channel).map(unit_class);
    if let Some(class) = &class {
        config.insert("unit_of_measurement".into(), json!(class.ha_unit));
        if let Some(device_class) = class.device_class {
            config.insert("device_class".into(), json!(device_class));
        }
    }
    let total = class.as_ref().is_some_and(|c| c.total_increasing);
    config.insert(
        "state_class".into(),
        json!(if total {
            "total_increasing"
        } else {
            "measurement"
        }),
    );
}

/// The control's unit: `units`, else the unit a deprecated typed value implies.
pub fn units_of(channel: &ResolvedChannel) -> Option<&str> {
    if let Some(units) = channel.units.as_deref().filter(|u| !u.is_empty()) {
        return Some(units);
    }
    Some(match channel.control_type.as_str() {
        "temperature" => "deg C",
        "rel_humidity" => "%, RH",
        "atmospheric_pressure" => "mbar",
        "rainfall" => "mm/h",
        "wind_speed" => "m/s",
        "power" => "W",
        "power_consumption" => "kWh",
        "voltage" => "V",
        "water_flow" => "m^3/h",
        "water_consumption" => "m^3",
        "resistance" => "Ohm",
        "concentration" => "ppm",
        "heat_power" => "Gcal/h",
        "heat_energy" => "Gcal",
        "current" => "A",
        "pressure" => "bar",
        "lux" => "lx",
        "sound_level" => "dB",
        _ => return None,
    })
}

/// How HA spells a WB unit, and the device class it implies.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnitClass {
    pub ha_unit: String,
    pub device_class: Option<&'static str>,
    pub total_increasing: bool,
}

/// WB unit → HA unit and device class (the table of wb-home-assistant's `sensor.py`).
pub fn unit_class(wb_unit: &str) -> UnitClass {
    let (ha_unit, device_class, total_increasing) = match wb_unit {
        "deg C" => ("°C", Some("temperature"), false),
        "%, RH" => ("%", Some("humidity"), false),
        "V" | "mV" => (wb_unit, Some("voltage"), false),
        "A" | "mA" => (wb_unit, Some("current"), false),
        "W" | "kW" => (wb_unit, Some("power"), false),
        "Wh" | "kWh" => (wb_unit, Some("energy"), true),
        "mbar" => ("mbar", Some("atmospheric_pressure"), false),
        "Pa" | "kPa" | "hPa" | "bar" => (wb_unit, Some("pressure"), false),
        "lx" => ("lx", Some("illuminance"), false),
        "ppm" => ("ppm", Some("carbon_dioxide"), false),
        "ppb" => ("ppb", Some("volatile_organic_compounds_parts"), false),
        "dB" => ("dB", Some("sound_pressure"), false),
        "Hz" => ("Hz", Some("frequency"), false),
        "m^3" => ("m³", Some("water"), true),
        "m^3/h" => ("m³/h", Some("volume_flow_rate"), false),
        "m/s" => ("m/s", Some("wind_speed"), false),
        "mm/h" => ("mm/h", Some("precipitation_intensity"), false),
        "s" | "min" | "h" => (wb_unit, Some("duration"), false),
        "var" => ("var", Some("reactive_power"), false),
        "VA" => ("VA", Some("apparent_power"), false),
        "kvarh" => ("kvarh", Some("reactive_energy"), true),
        "Ohm" => ("Ω", None, false),
        "mOhm" => ("mΩ", None, false),
        "deg" => ("°", None, false),
        other => (other, None, false),
    };
    UnitClass {
        ha_unit: ha_unit.to_string(),
        device_class,
        total_increasing,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mqtt::layout::tests::channel;

    #[test]
    fn mapping_follows_the_bridges() {
        let mut ro_switch = channel("In", "switch");
        ro_switch.readonly = true;
        assert_eq!(component_for(&channel("K1", "switch")), Some("switch"));
        assert_eq!(component_for(&ro_switch), Some("binary_sensor"));
        assert_eq!(component_for(&channel("A", "alarm")), Some("binary_sensor"));
        assert_eq!(component_for(&channel("B", "pushbutton")), Some("button"));
        assert_eq!(component_for(&channel("R", "range")), Some("number"));
        let mut ro_value = channel("T", "temperature");
        ro_value.readonly = true;
        assert_eq!(component_for(&ro_value), Some("sensor"));
    }

    #[test]
    fn a_writable_enum_is_a_select_of_its_titles() {
        use crate::device::{EnumTitle, Titles};
        let titled = |pairs: &[(&str, &str)]| -> Vec<EnumTitle> {
            pairs
                .iter()
                .map(|(value, title)| EnumTitle {
                    value: (*value).into(),
                    title: Titles::from([("en".into(), (*title).into())]),
                })
                .collect()
        };
        let mut fan = channel("Fan speed", "value");
        fan.enum_titles = titled(&[("0", "Auto"), ("1", "Low"), ("3", "High \"max\"")]);
        assert_eq!(component_for(&fan), Some("select"));
        let topics = TopicScheme::new("", "rtu2mqtt").unwrap();
        let settings = DiscoverySettings {
            prefix: "homeassistant".into(),
        };
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("templates/rtu2mqtt-climate.json");
        let file = crate::config::TemplateFile::load(&path).unwrap();
        let device =
            crate::device::resolve_template_device(&file, &json!({ "slave_id": 21 })).unwrap();
        let config = control_config(
            &settings,
            &topics,
            &device,
            &DeviceIdentity::default(),
            &fan,
        )
        .unwrap();
        assert_eq!(config.component, "select");
        let payload = &config.payload;
        assert_eq!(payload["options"], json!(["Auto", "Low", "High \"max\""]));
        assert_eq!(
            payload["value_template"],
            r#"{{ {"0":"Auto","1":"Low","3":"High \"max\""}.get(value, 'None') }}"#
        );
        assert_eq!(
            payload["command_template"],
            r#"{{ {"Auto":"0","Low":"1","High \"max\"":"3"}[value] }}"#
        );
        assert!(payload["command_topic"].as_str().unwrap().ends_with("/on"));
        // Read-only, it stays a sensor; two values under one title cannot be told apart.
        let mut shown = fan.clone();
        shown.readonly = true;
        assert_eq!(component_for(&shown), Some("sensor"));
        let sensor = control_config(
            &settings,
            &topics,
            &device,
            &DeviceIdentity::default(),
            &shown,
        )
        .unwrap();
        assert_eq!(
            sensor.payload["value_template"],
            r#"{{ {"0":"Auto","1":"Low","3":"High \"max\""}.get(value, value) }}"#
        );
        let mut clash = fan.clone();
        clash.enum_titles = titled(&[("0", "Off"), ("1", "Off")]);
        assert_eq!(component_for(&clash), Some("number"));
        // HA takes a state rendered "None" (any case) for no option at all.
        let mut none = fan;
        none.enum_titles = titled(&[("0", "none"), ("1", "On")]);
        assert_eq!(component_for(&none), Some("number"));
    }

    #[test]
    fn a_number_steps_by_what_its_register_can_hold() {
        let step = |channel: &ResolvedChannel| {
            let mut config = Map::new();
            number_limits(channel, &mut config);
            config["step"].as_f64().unwrap()
        };
        let mut setpoint = channel("Setpoint", "range");
        assert_eq!(step(&setpoint), 1.0);
        setpoint.registers[0].codec.scale = 0.5;
        assert_eq!(step(&setpoint), 0.5, "22.5 must be settable");
        setpoint.registers[0].codec.scale = 10.0;
        assert_eq!(step(&setpoint), 10.0);
        setpoint.precision = Some(0.1);
        assert_eq!(
            step(&setpoint),
            10.0,
            "a precision finer than the register holds"
        );
        setpoint.registers[0].codec.scale = 0.01;
        assert_eq!(step(&setpoint), 0.1, "a precision coarser than the scale");
        let mut wide = channel("Counter", "value");
        wide.registers.push(wide.registers[0].clone());
        assert_eq!(step(&wide), 1.0, "two integer registers unscaled");
        let mut float = channel("Level", "value");
        float.registers[0].codec.format = crate::config::format::RegisterFormat::Float;
        assert_eq!(step(&float), 0.001);
    }

    #[test]
    fn units_map_to_device_classes() {
        assert_eq!(unit_class("deg C").ha_unit, "°C");
        assert_eq!(unit_class("kWh").device_class, Some("energy"));
        assert!(unit_class("kWh").total_increasing);
        assert_eq!(unit_class("furlong").device_class, None);
        let mut typed = channel("T", "temperature");
        typed.readonly = true;
        assert_eq!(units_of(&typed), Some("deg C"));
    }
}
