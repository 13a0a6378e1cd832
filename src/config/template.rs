//! The wb-mqtt-serial device template format (`config-*.json`), read unchanged.
//!
//! Unknown keys are not errors here: upstream templates carry UI-only keys and new ones appear
//! over time. They are reported as warnings by `check-templates` instead.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::values::{AddressSpec, SerialInt, SerialNumber};
use crate::config::format::{ByteOrder, RegisterFormat, WordOrder};

/// Defines a struct with the device keys that both templates and config devices may set
/// (reference §1.3), so the two stay in step without `#[serde(flatten)]`, which would hide
/// unknown keys and error paths.
macro_rules! with_device_settings {
    ($(#[$meta:meta])* pub struct $name:ident { $($(#[$fmeta:meta])* pub $field:ident : $ty:ty,)* }) => {
        $(#[$meta])*
        pub struct $name {
            $($(#[$fmeta])* pub $field: $ty,)*
            /// Response timeout in ms (the port's value is the minimum). WB templates set 1.
            #[schemars(range(min = -1, max = 60000))]
            pub response_timeout_ms: Option<i64>,
            /// Silence that ends a frame, in ms (default 20; raised to 3.5 characters).
            #[schemars(range(min = -1, max = 10000))]
            pub frame_timeout_ms: Option<i64>,
            /// After a complete frame, also wait for silence and drop extra bytes.
            pub force_frame_timeout: Option<bool>,
            /// Pause before every request, from the last bus activity, in µs (default: port's).
            #[schemars(range(min = -1, max = 1000000))]
            pub guard_interval_us: Option<i64>,
            /// Low-priority reads start no earlier than last read + this, in ms.
            #[schemars(range(min = -1, max = 3600000))]
            pub min_request_interval: Option<i64>,
            /// Disconnect after this long without success (ms, default 3000) …
            #[schemars(range(min = -1, max = 3600000))]
            pub device_timeout_ms: Option<i64>,
            /// … and this many failed cycles (default 2). -1 disables either.
            pub device_max_fail_cycles: Option<i64>,
            /// How long failed writes are retried, in s (default 600).
            #[schemars(range(min = -1, max = 86400))]
            pub max_write_fail_time_s: Option<i64>,
            /// Registers per read request; 0 = protocol maximum (125 / 2000 bits).
            pub max_read_registers: Option<i64>,
            /// Shorter reads are padded up to this many registers.
            pub min_read_registers: Option<i64>,
            /// Registers per merged setup write (1; 123 for WB devices).
            pub max_write_registers: Option<i64>,
            /// Unconfigured registers / bits allowed inside one read.
            pub max_reg_hole: Option<i64>,
            pub max_bit_hole: Option<i64>,
            /// WB: write 1 to holding 114 on connect, so reads may span unused registers.
            pub enable_wb_continuous_read: Option<bool>,
            /// Keep polling registers that answer with exception 1/2/3.
            pub continue_polling_on_illegal_modbus_exception: Option<bool>,
            /// Write setup items in the given order instead of by register.
            pub preserve_setup_order: Option<bool>,
            /// Default minimum interval between reads of a register (deprecated upstream).
            #[schemars(range(min = -1, max = 172800000))]
            pub read_rate_limit_ms: Option<i64>,
            /// Legacy name of `read_rate_limit_ms`.
            #[schemars(range(min = -1, max = 172800000))]
            pub poll_interval: Option<i64>,
            /// wb-mqtt-serial's republish interval of unchanged values, in s, per device or
            /// channel: accepted, not applied (the top-level `max_unchanged_interval` is).
            pub max_publish_interval: Option<i64>,
            /// Not used by Modbus devices (kept so upstream files load).
            pub password: Option<Vec<SerialInt>>,
            pub access_level: Option<i64>,
            pub stride: Option<i64>,
            pub shift: Option<SerialInt>,
            pub protocol: Option<String>,
        }
    };
}
pub(crate) use with_device_settings;

/// One template file.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
pub struct Template {
    /// Unique name that config devices refer to.
    pub device_type: String,
    /// Title, translated through `device.translations`.
    pub title: Option<String>,
    /// UI group such as `g-wb` or `g-power-meter`.
    pub group: Option<String>,
    pub deprecated: Option<bool>,
    /// WB model signatures (and minimum firmware) this template is for.
    pub hw: Option<Vec<HardwareSignature>>,
    pub device: TemplateDevice,
}

#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize, JsonSchema)]
pub struct HardwareSignature {
    pub signature: String,
    pub fw: Option<String>,
}

with_device_settings! {
    /// The `device` object of a template.
    #[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
    pub struct TemplateDevice {
        /// Device title; the config's devices get `name + " " + slave_id`.
        pub name: Option<String>,
        /// MQTT device id prefix; devices get `id + "_" + slave_id`.
        pub id: Option<String>,
        pub groups: Option<Vec<GroupSpec>>,
        pub parameters: Option<Parameters>,
        pub setup: Option<Vec<SetupItemSpec>>,
        pub channels: Option<Vec<ChannelSpec>>,
        pub subdevices: Option<Vec<SubdeviceSpec>>,
        /// `{lang: {english text: translation}}`.
        pub translations: Option<BTreeMap<String, BTreeMap<String, String>>>,
        pub ui_options: Option<serde_json::Value>,
    }
}

/// UI group of parameters and channels (layout only).
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
pub struct GroupSpec {
    pub id: String,
    /// wb-mqtt-serial's library has groups with only an `id` (their title comes from
    /// `translations`); layout only, so a missing title is empty.
    #[serde(default)]
    pub title: String,
    pub order: Option<i64>,
    pub description: Option<String>,
    pub group: Option<String>,
    pub fw: Option<String>,
    pub condition: Option<String>,
    pub ui_options: Option<serde_json::Value>,
}

/// Modbus register table of a channel, as named in templates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize, Serialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RegisterKind {
    Holding,
    Input,
    Coil,
    Discrete,
    /// Holding register always written with function 06.
    HoldingSingle,
    /// Holding register always written with function 16.
    HoldingMulti,
    /// WB press counter: an input register whose 0 after a reboot is not published.
    PressCounter,
}

/// A channel: one MQTT control made of one register (or several with `consists_of`), or a
/// subdevice slot (`device_type`, `oneOf`, `shift`, `stride`).
#[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
pub struct ChannelSpec {
    /// Required for channels; not used in `consists_of` entries.
    #[serde(default)]
    pub name: String,
    /// MQTT control id (default: `name`). In subdevices an empty id drops the name prefix.
    pub id: Option<String>,
    pub reg_type: Option<RegisterKind>,
    pub address: Option<AddressSpec>,
    pub write_address: Option<AddressSpec>,
    pub format: Option<RegisterFormat>,
    pub word_order: Option<WordOrder>,
    pub byte_order: Option<ByteOrder>,
    /// Characters of a `string`/`string8` value.
    pub string_data_size: Option<u32>,
    pub scale: Option<f64>,
    pub offset: Option<f64>,
    pub round_to: Option<f64>,
    /// Control type: value, switch, range, text, pushbutton, rgb, alarm, wo-switch, temperature …
    #[serde(rename = "type")]
    pub control_type: Option<String>,
    pub units: Option<String>,
    pub min: Option<SerialNumber>,
    pub max: Option<SerialNumber>,
    pub readonly: Option<bool>,
    /// Legacy alias of `readonly`.
    pub channel_readonly: Option<bool>,
    pub on_value: Option<SerialInt>,
    pub off_value: Option<SerialInt>,
    pub error_value: Option<SerialInt>,
    pub unsupported_value: Option<SerialInt>,
    /// Fast Modbus events only: the register leaves polling once events are enabled.
    pub sporadic: Option<bool>,
    /// Fast Modbus events and polling.
    #[serde(rename = "semi-sporadic")]
    pub semi_sporadic: Option<bool>,
    /// Fixed read period (high priority), in ms.
    #[schemars(range(min = -1, max = 172800000))]
    pub read_period_ms: Option<i64>,
    #[schemars(range(min = -1, max = 172800000))]
    pub read_rate_limit_ms: Option<i64>,
    #[schemars(range(min = -1, max = 172800000))]
    pub poll_interval: Option<i64>,
    pub enabled: Option<bool>,
    pub hidden: Option<bool>,
    /// Minimum WB firmware version for this channel.
    pub fw: Option<String>,
    /// Expression over parameter values; the channel is dropped when false.
    pub condition: Option<String>,
    #[serde(rename = "enum")]
    pub enum_values: Option<Vec<serde_json::Value>>,
    pub enum_titles: Option<Vec<String>>,
    /// Registers of a multi-register control (value `a;b;c`).
    pub consists_of: Option<Vec<ChannelSpec>>,
    pub group: Option<String>,
    pub order: Option<i64>,
    pub description: Option<String>,
    pub ui_options: Option<serde_json::Value>,
    /// Subdevice slot: the chosen subdevice type.
    pub device_type: Option<String>,
    /// Subdevice slot: the types the user may choose from.
    #[serde(rename = "oneOf")]
    pub one_of: Option<Vec<String>>,
    /// Subdevice slot: added to every address of the subdevice.
    pub shift: Option<SerialInt>,
    /// Subdevice slot: every register moves by `stride` × its own width.
    pub stride: Option<u32>,
    /// Config overrides of a subdevice slot: its channels and setup.
    pub channels: Option<Vec<ChannelSpec>>,
    pub setup: Option<Vec<SetupItemSpec>>,
    /// Where the channel came from (set while merging, for located errors).
    #[serde(rename = "__origin", default, skip_serializing_if = "Option::is_none")]
    #[schemars(skip)]
    pub origin: Option<String>,
}

/// A register written when the device connects.
#[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
pub struct SetupItemSpec {
    pub title: Option<String>,
    pub address: Option<AddressSpec>,
    pub write_address: Option<AddressSpec>,
    pub value: Option<SetupValue>,
    pub reg_type: Option<RegisterKind>,
    pub format: Option<RegisterFormat>,
    pub word_order: Option<WordOrder>,
    pub byte_order: Option<ByteOrder>,
    pub scale: Option<f64>,
    pub offset: Option<f64>,
    pub condition: Option<String>,
    pub id: Option<String>,
    pub fw: Option<String>,
    /// Where the item came from (set while merging, for located errors).
    #[serde(rename = "__origin", default, skip_serializing_if = "Option::is_none")]
    #[schemars(skip)]
    pub origin: Option<String>,
}

/// A setup value: a number, or an integer string (`"0x10"`).
///
/// A JSON integer is kept as its exact text: 1-Wire sensor ids (WB-M1W2 v.3) are u64 values
/// above 2^53, which a double would round.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
#[serde(untagged)]
pub enum SetupValue {
    Number(f64),
    Text(String),
}

impl<'de> Deserialize<'de> for SetupValue {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        match serde_json::Value::deserialize(deserializer)? {
            serde_json::Value::Number(number) => Ok(match number.as_f64() {
                Some(value) if number.is_f64() => SetupValue::Number(value),
                _ => SetupValue::Text(number.to_string()),
            }),
            serde_json::Value::String(text) => Ok(SetupValue::Text(text)),
            other => Err(serde::de::Error::custom(format!(
                "expected a number or an integer string, not {other}"
            ))),
        }
    }
}

/// A device parameter: a value the config may set, written as a setup item.
#[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
pub struct ParameterSpec {
    /// Set for parameters given as an array; the object key otherwise.
    pub id: Option<String>,
    pub title: Option<String>,
    pub description: Option<String>,
    pub address: Option<AddressSpec>,
    pub write_address: Option<AddressSpec>,
    pub reg_type: Option<RegisterKind>,
    pub format: Option<RegisterFormat>,
    pub word_order: Option<WordOrder>,
    pub byte_order: Option<ByteOrder>,
    #[serde(rename = "enum")]
    pub enum_values: Option<Vec<serde_json::Value>>,
    pub enum_titles: Option<Vec<String>>,
    pub default: Option<SerialNumber>,
    pub min: Option<SerialNumber>,
    pub max: Option<SerialNumber>,
    pub scale: Option<f64>,
    pub offset: Option<f64>,
    pub order: Option<i64>,
    pub required: Option<bool>,
    /// UI only: never written.
    pub readonly: Option<bool>,
    pub fw: Option<String>,
    pub group: Option<String>,
    pub condition: Option<String>,
    pub units: Option<String>,
    pub ui_options: Option<serde_json::Value>,
}

/// `parameters`: an object keyed by id, or an array of objects with `id`; kept in file order.
#[derive(Debug, Clone, Default)]
pub struct Parameters(pub Vec<(String, ParameterSpec)>);

/// The declarations of a raw `parameters` value (an object keyed by id, or an array of objects
/// with `id`), in file order: (id, declaration). Entries that are not objects, and array
/// entries without an `id`, are left out.
pub fn parameter_declarations(
    parameters: Option<&serde_json::Value>,
) -> Vec<(String, &serde_json::Map<String, serde_json::Value>)> {
    use serde_json::Value;
    match parameters {
        Some(Value::Object(map)) => map
            .iter()
            .filter_map(|(id, spec)| Some((id.clone(), spec.as_object()?)))
            .collect(),
        Some(Value::Array(items)) => items
            .iter()
            .filter_map(Value::as_object)
            .filter_map(|spec| Some((spec.get("id")?.as_str()?.to_owned(), spec)))
            .collect(),
        _ => Vec::new(),
    }
}

impl Parameters {
    /// Every parameter with its id, in file order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &ParameterSpec)> {
        self.0.iter().map(|(id, spec)| (id.as_str(), spec))
    }

    pub fn get(&self, id: &str) -> Option<&ParameterSpec> {
        self.iter()
            .find(|(key, _)| *key == id)
            .map(|(_, spec)| spec)
    }
}

impl<'de> Deserialize<'de> for Parameters {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct ParametersVisitor;
        impl<'de> serde::de::Visitor<'de> for ParametersVisitor {
            type Value = Parameters;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(
                    "an object of parameters keyed by id, or an array of parameters with `id`",
                )
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut map: A,
            ) -> Result<Parameters, A::Error> {
                let mut list = Vec::new();
                while let Some((id, spec)) = map.next_entry::<String, ParameterSpec>()? {
                    list.push((id, spec));
                }
                Ok(Parameters(list))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Parameters, A::Error> {
                let mut list = Vec::new();
                while let Some(spec) = seq.next_element::<ParameterSpec>()? {
                    let id = spec.id.clone().ok_or_else(|| {
                        serde::de::Error::custom("a parameter in an array needs an `id`")
                    })?;
                    list.push((id, spec));
                }
                Ok(Parameters(list))
            }
        }
        deserializer.deserialize_any(ParametersVisitor)
    }
}

impl Serialize for Parameters {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut map = serializer.serialize_map(Some(self.0.len()))?;
        for (id, spec) in &self.0 {
            map.serialize_entry(id, spec)?;
        }
        map.end()
    }
}

impl JsonSchema for Parameters {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Parameters".into()
    }
    fn json_schema(generator: &mut schemars::SchemaGenerator) -> schemars::Schema {
        let parameter = generator.subschema_for::<ParameterSpec>();
        schemars::json_schema!({
            "description": "Device parameters: an object keyed by id, or an array of parameters with `id`.",
            "anyOf": [
                {"type": "object", "additionalProperties": parameter},
                {"type": "array", "items": parameter}
            ]
        })
    }
}

/// A subdevice type a channel slot can pull in.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
pub struct SubdeviceSpec {
    pub device_type: String,
    pub title: Option<String>,
    pub device: SubdeviceBody,
}

#[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
pub struct SubdeviceBody {
    pub setup: Option<Vec<SetupItemSpec>>,
    pub parameters: Option<Parameters>,
    pub channels: Option<Vec<ChannelSpec>>,
    pub subdevices: Option<Vec<SubdeviceSpec>>,
    pub groups: Option<Vec<GroupSpec>>,
    pub ui_options: Option<serde_json::Value>,
}

/// The template format's JSON Schema as a value (also what `rtu2mqtt schema template` prints).
pub fn template_schema() -> serde_json::Value {
    serde_json::to_value(schemars::schema_for!(Template)).unwrap_or_default()
}
