//! Registers of a device template, read by the simulator.
//!
//! STOPGAP, TO BE REPLACED BY THE SHARED TEMPLATE LOADER (`src/config/`, `src/device/`) AT MERGE.
//! Reads only what the simulator needs from a wb-mqtt-serial template: the channels' `reg_type`,
//! `address` (number, `"0x.."` or `"reg:shift:width"`), `format` (→ number of registers),
//! `string_data_size`, `readonly`, `sporadic`/`semi-sporadic` (→ can send events); the addresses
//! of `setup` items and `parameters` (the master writes them); `write_address`; `consists_of`.
//! Subdevices are ignored. `//` comments are allowed, as in the templates.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::protocol::RegisterType;

use super::registers::RegisterMap;
use super::SimError;

/// What a template contributes to a virtual device.
#[derive(Debug, Clone)]
pub struct TemplateRegisters {
    pub device_type: String,
    /// The first `hw[].signature`, when there is one (the model string of WB devices).
    pub signature: Option<String>,
    pub registers: RegisterMap,
}

/// Removes `//` line comments outside strings.
pub fn strip_comments(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars().peekable();
    let mut in_string = false;
    while let Some(c) = chars.next() {
        if in_string {
            out.push(c);
            match c {
                '\\' => out.extend(chars.next()),
                '"' => in_string = false,
                _ => {}
            }
        } else if c == '/' && chars.peek() == Some(&'/') {
            for skipped in chars.by_ref() {
                if skipped == '\n' {
                    out.push('\n');
                    break;
                }
            }
        } else {
            in_string = c == '"';
            out.push(c);
        }
    }
    out
}

pub fn load_template(path: &Path) -> Result<TemplateRegisters, SimError> {
    let text = std::fs::read_to_string(path).map_err(|source| SimError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let json: Value =
        serde_json::from_str(&strip_comments(&text)).map_err(|err| SimError::Json {
            path: path.to_path_buf(),
            message: err.to_string(),
        })?;
    registers_from_template(&json).map_err(|message| SimError::Json {
        path: path.to_path_buf(),
        message,
    })
}

/// The template in `dir` (not recursive) whose `device_type` is `device_type`.
pub fn find_template(dir: &Path, device_type: &str) -> Result<PathBuf, SimError> {
    let entries = std::fs::read_dir(dir).map_err(|source| SimError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|entry| entry.path())
        .filter(|path| path.extension().is_some_and(|ext| ext == "json"))
        .collect();
    paths.sort();
    for path in paths {
        let Ok(text) = std::fs::read_to_string(&path) else {
            continue;
        };
        let Ok(json) = serde_json::from_str::<Value>(&strip_comments(&text)) else {
            continue;
        };
        if json.get("device_type").and_then(Value::as_str) == Some(device_type) {
            return Ok(path);
        }
    }
    Err(SimError::TemplateNotFound {
        device_type: device_type.to_string(),
        dir: dir.to_path_buf(),
    })
}

pub fn registers_from_template(json: &Value) -> Result<TemplateRegisters, String> {
    let device = json.get("device").ok_or("no \"device\" object")?;
    let mut registers = RegisterMap::new();
    for channel in device
        .get("channels")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
    {
        add_channel(&mut registers, channel);
        for part in channel
            .get("consists_of")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            add_channel(&mut registers, part);
        }
    }
    for item in device
        .get("setup")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
    {
        add_writable(&mut registers, item);
    }
    match device.get("parameters") {
        Some(Value::Array(items)) => items.iter().for_each(|i| add_writable(&mut registers, i)),
        Some(Value::Object(items)) => items.values().for_each(|i| add_writable(&mut registers, i)),
        _ => {}
    }
    Ok(TemplateRegisters {
        device_type: json
            .get("device_type")
            .and_then(Value::as_str)
            .unwrap_or("unknown")
            .to_string(),
        signature: json
            .get("hw")
            .and_then(Value::as_array)
            .and_then(|hw| hw.first())
            .and_then(|hw| hw.get("signature"))
            .and_then(Value::as_str)
            .map(str::to_string),
        registers,
    })
}

fn register_type(item: &Value) -> Option<RegisterType> {
    match item
        .get("reg_type")
        .and_then(Value::as_str)
        .unwrap_or("holding")
    {
        "coil" => Some(RegisterType::Coil),
        "discrete" => Some(RegisterType::DiscreteInput),
        "holding" | "holding_single" | "holding_multi" => Some(RegisterType::Holding),
        "input" | "press_counter" => Some(RegisterType::Input),
        _ => None,
    }
}

/// `123`, `"123"`, `"0x7B"`, or `"reg:shift:width"` (the register part).
pub fn parse_address(value: &Value) -> Option<u16> {
    match value {
        Value::Number(n) => n.as_u64().and_then(|n| u16::try_from(n).ok()),
        Value::String(text) => {
            let register = text.split(':').next()?.trim();
            match register
                .strip_prefix("0x")
                .or_else(|| register.strip_prefix("0X"))
            {
                Some(hex) => u16::from_str_radix(hex, 16).ok(),
                None => register.parse().ok(),
            }
        }
        _ => None,
    }
}

/// Registers a value of this format occupies.
fn register_count(item: &Value, register_type: RegisterType) -> u16 {
    if register_type.is_bit() {
        return 1;
    }
    let size = || {
        item.get("string_data_size")
            .and_then(Value::as_u64)
            .and_then(|n| u16::try_from(n).ok())
            .unwrap_or(1)
    };
    match item.get("format").and_then(Value::as_str).unwrap_or("u16") {
        "u24" | "s24" | "u32" | "s32" | "float" | "bcd24" | "bcd32" => 2,
        "u64" | "s64" | "double" => 4,
        "string" => size().max(1),
        "string8" => size().div_ceil(2).max(1),
        _ => 1,
    }
}

fn flag(item: &Value, key: &str) -> bool {
    item.get(key).is_some_and(|v| v.as_bool() == Some(true))
}

fn add_channel(registers: &mut RegisterMap, channel: &Value) {
    let Some(register_type) = register_type(channel) else {
        return;
    };
    let count = register_count(channel, register_type);
    let writable = !flag(channel, "readonly") && !flag(channel, "channel_readonly");
    if let Some(address) = channel.get("address").and_then(parse_address) {
        registers.define(register_type, address, count, writable);
        if flag(channel, "sporadic") || flag(channel, "semi-sporadic") {
            registers.mark_event_source(register_type, address, u8::try_from(count).unwrap_or(4));
        }
    }
    if let Some(address) = channel.get("write_address").and_then(parse_address) {
        registers.define(register_type, address, count, true);
    }
}

fn add_writable(registers: &mut RegisterMap, item: &Value) {
    let Some(register_type) = register_type(item) else {
        return;
    };
    if let Some(address) = item.get("address").and_then(parse_address) {
        registers.define(
            register_type,
            address,
            register_count(item, register_type),
            true,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_channels_setup_and_parameters() {
        let text = r#"{
            // a comment, and a URL in a string: "http://x"
            "device_type": "t", "hw": [{"signature": "WBMR6C"}],
            "device": {
                "channels": [
                    {"name": "K1", "reg_type": "coil", "address": 0, "sporadic": true},
                    {"name": "C", "reg_type": "input", "address": "0x3C", "format": "u32", "semi-sporadic": true},
                    {"name": "B", "reg_type": "holding", "address": "9:4:2"},
                    {"name": "S", "reg_type": "holding", "address": 300, "format": "string", "string_data_size": 3, "readonly": true},
                    {"name": "url", "reg_type": "input", "address": 1, "description": "see http://wb//x"}
                ],
                "setup": [{"title": "x", "address": 5, "value": 0}],
                "parameters": {"mode": {"address": 16, "reg_type": "holding"}}
            }
        }"#;
        let json: Value = serde_json::from_str(&strip_comments(text)).unwrap();
        let t = registers_from_template(&json).unwrap();
        assert_eq!(t.signature.as_deref(), Some("WBMR6C"));
        let r = &t.registers;
        assert_eq!(r.event_width(RegisterType::Coil, 0), Some(1));
        assert_eq!(r.event_width(RegisterType::Input, 60), Some(2));
        assert!(r.get(RegisterType::Input, 61).is_some());
        assert!(r.cell(RegisterType::Holding, 9).unwrap().writable);
        assert!(!r.cell(RegisterType::Holding, 302).unwrap().writable);
        assert!(r.get(RegisterType::Holding, 303).is_none());
        assert!(r.cell(RegisterType::Holding, 5).unwrap().writable);
        assert!(r.cell(RegisterType::Holding, 16).unwrap().writable);
        assert!(r.get(RegisterType::Input, 1).is_some());
    }

    #[test]
    fn real_templates_load() {
        let dir = Path::new("/work/shared/compat/wb-templates");
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for entry in entries.flatten() {
            let t = load_template(&entry.path()).unwrap();
            assert!(
                t.registers.iter(RegisterType::Holding).count()
                    + t.registers.iter(RegisterType::Input).count()
                    + t.registers.iter(RegisterType::Coil).count()
                    + t.registers.iter(RegisterType::DiscreteInput).count()
                    > 0,
                "{:?}",
                entry.path()
            );
        }
    }
}
