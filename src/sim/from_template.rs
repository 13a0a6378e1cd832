//! A device template as the simulator's registers, read through the shared template loader
//! (`config::TemplateFile`, `device::resolve_template_device_unconfigured`): the simulator and the daemon
//! cannot disagree on what a template means.
//!
//! A real device has every register of its template, whatever a master configures, so the
//! template is resolved twice: as configured by default (`{"slave_id": N}`; its errors are the
//! ones reported), and "opened": channels and subdevice slots with `enabled: false` enabled,
//! `condition`s of channels and setup items dropped, and every parameter (of the device and of
//! the default subdevices) added as a channel on its register. The registers of both are kept.

use std::path::Path;

use serde_json::{json, Map, Value};

use crate::config::format::WordOrder;
use crate::config::parse::SourceText;
use crate::config::template::parameter_declarations;
use crate::config::{TemplateFile, TemplateLibrary};
use crate::device::{resolve_template_device_unconfigured, EventMode, RegisterRef, ResolvedDevice};

use super::registers::RegisterMap;
use super::SimError;

/// What a template contributes to a virtual device.
#[derive(Debug, Clone)]
pub struct TemplateRegisters {
    pub device_type: String,
    /// The first `hw[].signature`, when there is one (the model string of WB devices).
    pub signature: Option<String>,
    pub registers: RegisterMap,
    /// Set (to the reason) when the opened template did not resolve: only the registers of the
    /// default configuration are simulated.
    pub limited: Option<String>,
}

/// Loads a template file with the shared loader.
pub fn load_template_file(path: &Path) -> Result<TemplateFile, SimError> {
    TemplateFile::load(path).map_err(|err| SimError::Template(err.to_string()))
}

/// The template of `device_type` in `library`, with a hint when it is missing.
pub fn find_template<'a>(
    library: &'a TemplateLibrary,
    device_type: &str,
) -> Result<&'a TemplateFile, SimError> {
    library.get(device_type).ok_or_else(|| {
        let mut hint = String::new();
        let similar = library.similar(device_type);
        if !similar.is_empty() {
            hint = format!("; did you mean {}?", similar.join(" or "));
        }
        if let Some(cause) = library.load_error_for(device_type) {
            hint.push_str(&format!("; a file failed to load: {cause}"));
        }
        SimError::TemplateNotFound {
            device_type: device_type.to_string(),
            dirs: library
                .dirs
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            hint,
        }
    })
}

/// The registers of `template` for a device at Modbus address `address`.
pub fn template_registers(
    template: &TemplateFile,
    address: u8,
) -> Result<TemplateRegisters, SimError> {
    let config = json!({ "slave_id": address });
    let (configured, warnings) = resolve_template_device_unconfigured(template, &config)
        .map_err(|errors| SimError::Template(errors.to_string()))?;
    // A channel whose register cannot be built is left out, as the daemon and wb-mqtt-serial
    // leave it out: the device is simulated without it, and the log says so.
    for warning in &warnings {
        tracing::warn!("{warning}");
    }
    let mut registers = RegisterMap::new();
    add_device(&mut registers, &configured);
    let limited = match opened(template).and_then(|open| {
        resolve_template_device_unconfigured(&open, &config).map_err(|errors| errors.to_string())
    }) {
        Ok((open, _)) => {
            add_device(&mut registers, &open);
            None
        }
        Err(message) => {
            tracing::warn!(
                "{}: only the registers of the default configuration are simulated: {message}",
                template.source.path.display()
            );
            Some(message)
        }
    };
    Ok(TemplateRegisters {
        device_type: template.device_type().to_string(),
        signature: template
            .template
            .hw
            .as_ref()
            .and_then(|hw| hw.first())
            .map(|hw| hw.signature.clone()),
        registers,
        limited,
    })
}

/// Every register a resolved device reads or writes. A register is writable when some channel,
/// setup item or parameter writes it; event-capable when a sporadic or semi-sporadic channel reads
/// it (the whole value: `count` registers).
pub fn add_device(registers: &mut RegisterMap, device: &ResolvedDevice) {
    let mut define = |register: &RegisterRef, writable: bool| {
        registers.define(
            register.reg_type,
            register.address,
            register.count,
            writable,
        );
    };
    for channel in &device.channels {
        for register in &channel.registers {
            if let Some(read) = &register.read {
                define(read, false);
            }
            if let Some(write) = &register.write {
                define(write, true);
            }
        }
    }
    if let Some(read) = device.serial_number.as_ref().and_then(|s| s.read.as_ref()) {
        define(read, false);
    }
    for item in &device.setup {
        define(&item.register, true);
    }
    for channel in device
        .channels
        .iter()
        .filter(|c| c.events != EventMode::Polled)
    {
        for register in &channel.registers {
            let Some(read) = register.read.as_ref() else {
                continue;
            };
            let width = u8::try_from(read.count).unwrap_or(u8::MAX);
            registers.mark_event_source(read.reg_type, read.address, width);
            if width > 1 && register.codec.word_order == WordOrder::LittleEndian {
                registers.mark_low_word_first(read.reg_type, read.address);
            }
        }
    }
}

/// The template with everything a master could configure switched on (see the module docs), as
/// a template file of the shared loader.
fn opened(template: &TemplateFile) -> Result<TemplateFile, String> {
    let mut raw = template.raw.clone();
    if let Some(device) = raw.get_mut("device") {
        open_level(device);
    }
    let text = serde_json::to_string_pretty(&raw).map_err(|err| err.to_string())?;
    TemplateFile::from_source(SourceText::from_text(&template.source.path, &text))
        .map_err(|err| err.to_string())
}

/// One level: the device, or a subdevice's `device` body.
fn open_level(body: &mut Value) {
    let Some(body) = body.as_object_mut() else {
        return;
    };
    let parameters = parameter_channels(body.get("parameters"));
    if let Some(Value::Array(channels)) = body.get_mut("channels") {
        for channel in channels.iter_mut().filter_map(Value::as_object_mut) {
            channel.remove("enabled");
            channel.remove("condition");
        }
    }
    if !parameters.is_empty() {
        match body.get_mut("channels") {
            Some(Value::Array(channels)) => channels.extend(parameters),
            _ => {
                body.insert("channels".into(), Value::Array(parameters));
            }
        }
    }
    if let Some(Value::Array(setup)) = body.get_mut("setup") {
        for item in setup.iter_mut().filter_map(Value::as_object_mut) {
            item.remove("condition");
        }
    }
    if let Some(Value::Array(subdevices)) = body.get_mut("subdevices") {
        for subdevice in subdevices {
            if let Some(device) = subdevice.get_mut("device") {
                open_level(device);
            }
        }
    }
}

/// Keys of a parameter that say where and how its value is stored.
const PARAMETER_REGISTER_KEYS: [&str; 6] = [
    "reg_type",
    "address",
    "write_address",
    "format",
    "word_order",
    "byte_order",
];

/// A channel per parameter that has an address: the resolver places it (shift, stride, width).
fn parameter_channels(parameters: Option<&Value>) -> Vec<Value> {
    parameter_declarations(parameters)
        .into_iter()
        .filter(|(_, spec)| spec.contains_key("address") || spec.contains_key("write_address"))
        .map(|(id, spec)| {
            let mut channel = Map::new();
            channel.insert("name".into(), Value::String(format!("parameter {id}")));
            for key in PARAMETER_REGISTER_KEYS {
                if let Some(value) = spec.get(key) {
                    channel.insert(key.into(), value.clone());
                }
            }
            Value::Object(channel)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::RegisterType;

    fn registers(text: &str) -> TemplateRegisters {
        let source = SourceText::from_text(Path::new("test.json"), text);
        let template = TemplateFile::from_source(source).unwrap();
        template_registers(&template, 1).unwrap()
    }

    /// A sporadic u32 kept least significant word first sends its value (fast-modbus.md §6,
    /// "payload = the register's new value", little-endian), whatever its word order; one
    /// kept most significant word first sends the same bytes for the same value.
    #[test]
    fn wide_event_payloads_are_the_value_in_either_word_order() {
        let mut t = registers(
            r#"{"device_type": "t", "device": {"name": "T", "channels": [
                {"name": "BE", "reg_type": "input", "address": 7, "format": "u32", "sporadic": true},
                {"name": "LE", "reg_type": "input", "address": 9, "format": "u32",
                 "word_order": "little_endian", "sporadic": true}
            ]}}"#,
        );
        let r = &mut t.registers;
        // 0x0004_0006 in both
        r.set(RegisterType::Input, 7, 0x0004);
        r.set(RegisterType::Input, 8, 0x0006);
        r.set(RegisterType::Input, 9, 0x0006);
        r.set(RegisterType::Input, 10, 0x0004);
        let value = vec![0x06, 0x00, 0x04, 0x00];
        assert_eq!(r.event_payload(RegisterType::Input, 7), value);
        assert_eq!(r.event_payload(RegisterType::Input, 9), value);
    }

    #[test]
    fn channels_setup_parameters_and_subdevices() {
        let t = registers(
            r#"{
            // a comment, and a URL in a string: "http://x"
            "device_type": "t", "hw": [{"signature": "WBMR6C"}],
            "device": {
                "name": "T",
                "channels": [
                    {"name": "K1", "reg_type": "coil", "address": 0, "sporadic": true},
                    {"name": "C", "reg_type": "input", "address": "0x3C", "format": "u32", "semi-sporadic": true},
                    {"name": "B", "reg_type": "holding", "address": "9:4:2"},
                    {"name": "B2", "reg_type": "holding", "address": "9:0:4", "readonly": true},
                    {"name": "S", "reg_type": "holding", "address": 300, "format": "string", "string_data_size": 6, "readonly": true},
                    {"name": "W", "reg_type": "holding", "address": 400, "write_address": 401},
                    {"name": "off", "reg_type": "input", "address": 1, "enabled": false, "sporadic": true},
                    {"name": "cond", "reg_type": "holding", "address": 500, "condition": "mode==7"},
                    {"name": "Slot", "oneOf": ["sub"], "device_type": "sub", "shift": 1000}
                ],
                "setup": [{"title": "x", "address": 5, "value": 0}],
                "parameters": {"mode": {"title": "m", "address": 16, "reg_type": "holding", "default": 0},
                               "wide": {"title": "w", "address": 17, "format": "u32", "default": 0}},
                "subdevices": [{"device_type": "sub", "device": {
                    "channels": [{"name": "Sub value", "reg_type": "input", "address": 2, "sporadic": true}],
                    "parameters": [{"id": "sub_mode", "title": "s", "address": 3, "default": 0}]
                }}]
            }
        }"#,
        );
        assert_eq!(t.signature.as_deref(), Some("WBMR6C"));
        assert_eq!(t.device_type, "t");
        assert_eq!(t.limited, None);
        let r = &t.registers;
        assert_eq!(r.event_width(RegisterType::Coil, 0), Some(1));
        assert!(r.cell(RegisterType::Coil, 0).unwrap().writable);
        assert_eq!(r.event_width(RegisterType::Input, 60), Some(2));
        assert!(r.get(RegisterType::Input, 61).is_some());
        assert!(r.get(RegisterType::Input, 62).is_none());
        // A bit field written by one channel is writable, even if another one is read-only.
        assert!(r.cell(RegisterType::Holding, 9).unwrap().writable);
        assert!(r.get(RegisterType::Holding, 10).is_none());
        // One character per register.
        assert!(!r.cell(RegisterType::Holding, 305).unwrap().writable);
        assert!(r.get(RegisterType::Holding, 306).is_none());
        assert!(!r.cell(RegisterType::Holding, 400).unwrap().writable);
        assert!(r.cell(RegisterType::Holding, 401).unwrap().writable);
        assert!(r.cell(RegisterType::Holding, 5).unwrap().writable);
        assert!(r.cell(RegisterType::Holding, 16).unwrap().writable);
        assert!(r.cell(RegisterType::Holding, 18).unwrap().writable);
        // Disabled and conditional channels exist: a master may enable them.
        assert_eq!(r.event_width(RegisterType::Input, 1), Some(1));
        assert!(r.cell(RegisterType::Holding, 500).unwrap().writable);
        // The default subdevice, shifted, with its parameters.
        assert_eq!(r.event_width(RegisterType::Input, 1002), Some(1));
        assert!(r.cell(RegisterType::Holding, 1003).unwrap().writable);
    }

    /// A WB-LED or WB-MAI6 template requires a mode the config must give; the hardware has
    /// its registers whatever the mode, so the simulator builds it from the template alone.
    #[test]
    fn a_template_with_a_required_parameter_is_simulated() {
        let t = registers(
            r#"{"device_type": "t", "device": {
                "parameters": {"mode": {"title": "m", "address": 16, "reg_type": "holding",
                                        "enum": [1, 2], "required": true}},
                "channels": [
                    {"name": "A", "reg_type": "input", "address": 1},
                    {"name": "B", "reg_type": "input", "address": 2, "condition": "mode==2"}]}}"#,
        );
        assert_eq!(t.limited, None);
        assert!(t.registers.get(RegisterType::Input, 1).is_some());
        assert!(t.registers.get(RegisterType::Input, 2).is_some());
        assert!(
            t.registers
                .cell(RegisterType::Holding, 16)
                .unwrap()
                .writable
        );
    }

    #[test]
    fn errors_of_the_shared_loader_are_reported() {
        let source = SourceText::from_text(
            Path::new("bad.json"),
            r#"{"device_type": "t", "device": {"channels": [
                {"name": "S", "address": 70000, "reg_type": "input"}]}}"#,
        );
        let template = TemplateFile::from_source(source).unwrap();
        let err = template_registers(&template, 1).unwrap_err().to_string();
        assert!(
            err.contains("bad.json") && err.contains("70000 is out of range"),
            "{err}"
        );
    }

    /// A channel whose register cannot be built is left out, as the daemon leaves it out: the
    /// rest of the device is simulated.
    #[test]
    fn a_channel_the_daemon_leaves_out_is_not_simulated() {
        let t = registers(
            r#"{"device_type": "t", "device": {"channels": [
                {"name": "A", "reg_type": "input", "address": 1},
                {"name": "S", "reg_type": "holding", "address": 2, "format": "string"}]}}"#,
        );
        assert!(t.registers.get(RegisterType::Input, 1).is_some());
        assert!(t.registers.get(RegisterType::Holding, 2).is_none());
        assert_eq!(t.limited, None);
    }

    #[test]
    fn a_broken_disabled_channel_leaves_the_default_registers() {
        let t = registers(
            r#"{"device_type": "t", "device": {"channels": [
                {"name": "A", "reg_type": "input", "address": 1},
                {"name": "S", "address": 70000, "enabled": false}]}}"#,
        );
        assert!(t.limited.as_deref().unwrap().contains("70000"));
        assert!(t.registers.get(RegisterType::Input, 1).is_some());
        assert!(t.registers.get(RegisterType::Holding, 2).is_none());
    }
}
