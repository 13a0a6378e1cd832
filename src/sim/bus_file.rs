//! The bus description file (JSON): which devices are on the virtual bus.
//!
//! ```json
//! { "seed": 1,
//!   "devices": [
//!     { "name": "relay", "template": "wb-mr6c", "address": 20, "serial": "0xFED2A3A6",
//!       "line": "115200 8N2", "fast": true, "turnaround_us": 500,
//!       "model": "WBMR6C", "firmware": "1.26.0",
//!       "registers": [{"type": "holding", "address": 0, "count": 4, "events": false}],
//!       "values": {"coil:0": 1, "holding:0": [1, 2, 3]} } ] }
//! ```
//! `template` is a path (relative to the bus file) when it contains `/` or ends in `.json`, else a
//! `device_type` looked up in the templates directory. See docs/sim.md.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

use crate::protocol::{LineSettings, Parity, RegisterType};

use crate::config::jsonc::strip_comments;
use crate::config::values::parse_int_text;
use crate::config::TemplateLibrary;

use super::device::{DeviceSpec, VirtualDevice};
use super::from_template::{
    find_template, load_template_file, template_registers, TemplateRegisters,
};
use super::registers::RegisterMap;
use super::SimError;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusFile {
    /// Seed of the fault generator.
    #[serde(default)]
    pub seed: u64,
    pub devices: Vec<DeviceEntry>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeviceEntry {
    pub name: Option<String>,
    pub template: Option<String>,
    pub address: u8,
    pub serial: SerialNumber,
    /// `"9600 8N2"` (the default), `"115200 8E1"`, …
    #[serde(default = "default_line")]
    pub line: String,
    #[serde(default = "default_true")]
    pub fast: bool,
    #[serde(default = "default_turnaround_us")]
    pub turnaround_us: u64,
    /// A slow device: the silence in the middle of each of its addressed replies.
    #[serde(default)]
    pub reply_pause_us: u64,
    pub model: Option<String>,
    pub firmware: Option<String>,
    pub signature: Option<String>,
    #[serde(default)]
    pub registers: Vec<RegisterBlock>,
    /// `"type:address"` → a value, or values for consecutive registers.
    #[serde(default)]
    pub values: BTreeMap<String, Values>,
}

/// Registers beyond the template's (or without a template).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterBlock {
    #[serde(rename = "type")]
    pub register_type: String,
    pub address: u16,
    #[serde(default = "default_count")]
    pub count: u16,
    /// Each register can send events (1-register values).
    #[serde(default)]
    pub events: bool,
    #[serde(default = "default_true")]
    pub writable: bool,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum Values {
    One(u16),
    Many(Vec<u16>),
}

/// A serial number as a JSON number or a string (`"0xFE4000AC"` or decimal).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "serde_json::Value")]
pub struct SerialNumber(pub u32);

impl TryFrom<serde_json::Value> for SerialNumber {
    type Error = String;

    fn try_from(value: serde_json::Value) -> Result<Self, Self::Error> {
        parse_serial(&value).map(SerialNumber)
    }
}

pub fn parse_serial(value: &serde_json::Value) -> Result<u32, String> {
    let parsed = match value {
        serde_json::Value::Number(n) => n.as_u64().and_then(|n| u32::try_from(n).ok()),
        serde_json::Value::String(text) => parse_int_text(text).and_then(|n| u32::try_from(n).ok()),
        _ => None,
    };
    parsed.ok_or_else(|| format!("not a 32-bit serial number: {value}"))
}

fn default_line() -> String {
    "9600 8N2".into()
}
fn default_true() -> bool {
    true
}
fn default_turnaround_us() -> u64 {
    500
}
fn default_count() -> u16 {
    1
}

/// `"9600 8N2"`, `"115200-8E1"`, `"19200 8O1"`.
pub fn parse_line(text: &str) -> Result<LineSettings, String> {
    let err = || format!("port settings {text:?}: expected e.g. \"9600 8N2\"");
    let (baud, framing) = text.trim().split_once([' ', '-', ',']).ok_or_else(err)?;
    let baud: u32 = baud.trim().parse().map_err(|_| err())?;
    let framing: Vec<char> = framing.trim().chars().collect();
    let [data, parity, stop] = framing.as_slice() else {
        return Err(err());
    };
    let parity = match parity.to_ascii_uppercase() {
        'N' => Parity::None,
        'E' => Parity::Even,
        'O' => Parity::Odd,
        _ => return Err(err()),
    };
    let stop_bits = match stop {
        '1' => 1,
        '2' => 2,
        _ => return Err(err()),
    };
    if *data != '8' || baud == 0 {
        return Err(err());
    }
    Ok(LineSettings::new(baud, parity, stop_bits))
}

/// `"coil"`, `"discrete"`, `"holding"`, `"input"`.
pub fn parse_register_type(text: &str) -> Result<RegisterType, String> {
    match text {
        "coil" | "coils" => Ok(RegisterType::Coil),
        "discrete" | "discrete_input" => Ok(RegisterType::DiscreteInput),
        "holding" => Ok(RegisterType::Holding),
        "input" => Ok(RegisterType::Input),
        other => Err(format!(
            "unknown register type {other:?} (coil, discrete, holding, input)"
        )),
    }
}

/// `"holding:128"`, `"coil:0x10"` → (type, address).
fn parse_register_key(key: &str) -> Result<(RegisterType, u16), String> {
    let (kind, address) = key
        .split_once(':')
        .ok_or_else(|| format!("register {key:?}: expected \"type:address\""))?;
    let address = parse_int_text(address)
        .and_then(|a| u16::try_from(a).ok())
        .ok_or_else(|| format!("register {key:?}: the address must be 0..=65535 (or \"0x..\")"))?;
    Ok((parse_register_type(kind)?, address))
}

/// Where the `template` of a device entry is found: a file relative to the bus file, or a
/// `device_type` in the templates directory (loaded with the shared loader on first use).
pub struct TemplateSource {
    base: PathBuf,
    dir: PathBuf,
    library: Option<TemplateLibrary>,
}

impl TemplateSource {
    /// `base`: the bus file's directory; `dir`: where `device_type` names are looked up.
    pub fn new(base: &Path, dir: &Path) -> Self {
        Self {
            base: base.to_path_buf(),
            dir: dir.to_path_buf(),
            library: None,
        }
    }

    /// The registers of the template `reference` for a device at `address`.
    pub fn registers(
        &mut self,
        reference: &str,
        address: u8,
    ) -> Result<TemplateRegisters, SimError> {
        if reference.contains('/') || reference.ends_with(".json") {
            let template = load_template_file(&self.base.join(reference))?;
            return template_registers(&template, address);
        }
        let dir = &self.dir;
        let library = self
            .library
            .get_or_insert_with(|| TemplateLibrary::load_dirs(std::slice::from_ref(dir)));
        template_registers(find_template(library, reference)?, address)
    }
}

/// Reads a bus file and builds its devices.
pub fn load_bus(
    path: &Path,
    templates_dir: &Path,
) -> Result<(BusFile, Vec<VirtualDevice>), SimError> {
    let text = std::fs::read_to_string(path).map_err(|reason| SimError::Io {
        path: path.to_path_buf(),
        reason,
    })?;
    let file: BusFile =
        serde_json::from_str(&strip_comments(&text)).map_err(|err| SimError::Json {
            path: path.to_path_buf(),
            message: err.to_string(),
        })?;
    let mut templates = TemplateSource::new(path.parent().unwrap_or(Path::new(".")), templates_dir);
    let devices = file
        .devices
        .iter()
        .map(|entry| build_device(entry, &mut templates))
        .collect::<Result<Vec<VirtualDevice>, _>>()?;
    check_serials_differ(&devices)?;
    Ok((file, devices))
}

/// Fast Modbus arbitration tells devices apart by the low 28 bits of their serial numbers:
/// two devices alike there would answer a scan or an event poll as one, garbled.
fn check_serials_differ(devices: &[VirtualDevice]) -> Result<(), SimError> {
    const ARBITRATED: u32 = 0x0FFF_FFFF;
    for (i, device) in devices.iter().enumerate() {
        if let Some(other) = devices[..i]
            .iter()
            .find(|other| other.serial & ARBITRATED == device.serial & ARBITRATED)
        {
            return Err(SimError::BusFile(format!(
                "devices {:?} and {:?}: serial numbers {:#010X} and {:#010X} have the same low                  28 bits, which Fast Modbus scans and event polls tell devices apart by; give                  one another serial",
                other.name, device.name, other.serial, device.serial
            )));
        }
    }
    Ok(())
}

pub fn build_device(
    entry: &DeviceEntry,
    templates: &mut TemplateSource,
) -> Result<VirtualDevice, SimError> {
    let name = entry
        .name
        .clone()
        .unwrap_or_else(|| format!("device{}", entry.address));
    let bad = |message: String| SimError::BusFile(format!("device {name:?}: {message}"));
    if !(1..=247).contains(&entry.address) {
        return Err(bad(format!("address {} is not 1..=247", entry.address)));
    }
    let (registers, template_name, signature) = match &entry.template {
        Some(reference) => {
            let template = templates
                .registers(reference, entry.address)
                .map_err(|err| bad(err.to_string()))?;
            (template.registers, template.device_type, template.signature)
        }
        None => (RegisterMap::new(), "-".to_string(), None),
    };
    let mut registers = registers;
    for block in &entry.registers {
        let register_type = parse_register_type(&block.register_type).map_err(bad)?;
        registers.define(register_type, block.address, block.count, block.writable);
        if block.events {
            for offset in 0..block.count {
                if let Some(address) = block.address.checked_add(offset) {
                    registers.mark_event_source(register_type, address, 1);
                }
            }
        }
    }
    let model = entry
        .model
        .clone()
        .or(signature)
        .unwrap_or_else(|| template_name.clone());
    let mut device = VirtualDevice::new(DeviceSpec {
        name: name.clone(),
        template: template_name,
        serial: entry.serial.0,
        address: entry.address,
        line: parse_line(&entry.line).map_err(bad)?,
        fast: entry.fast,
        turnaround: Duration::from_micros(entry.turnaround_us),
        signature: entry.signature.clone().unwrap_or_else(|| model.clone()),
        model,
        firmware: entry.firmware.clone().unwrap_or_else(|| "1.0.0".into()),
        registers,
    });
    device.reply_pause = Duration::from_micros(entry.reply_pause_us);
    for (key, values) in &entry.values {
        let (register_type, address) = parse_register_key(key).map_err(bad)?;
        let values = match values {
            Values::One(value) => vec![*value],
            Values::Many(values) => values.clone(),
        };
        device
            .write(register_type, address, &values, false)
            .map_err(|code| bad(format!("initial value of {key}: {code}")))?;
    }
    Ok(device)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_settings_parse() {
        assert_eq!(
            parse_line("9600 8N2"),
            Ok(LineSettings::new(9600, Parity::None, 2))
        );
        assert_eq!(
            parse_line("115200-8e1"),
            Ok(LineSettings::new(115_200, Parity::Even, 1))
        );
        assert!(parse_line("9600 7N1").is_err());
        assert!(parse_line("fast").is_err());
    }

    #[test]
    fn serials_alike_in_their_arbitrated_bits_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let bus = dir.path().join("bus.json");
        let write = |second: &str| {
            std::fs::write(
                &bus,
                format!(
                    r#"{{"devices": [{{"name": "a", "address": 1, "serial": "0xFE000001"}},
                                    {{"name": "b", "address": 2, "serial": "{second}"}}]}}"#
                ),
            )
            .unwrap();
        };
        write("0x0E000001");
        let err = load_bus(&bus, dir.path()).map(|_| ()).unwrap_err();
        assert!(err.to_string().contains(r#"devices "a" and "b""#), "{err}");
        write("0xFE000002");
        assert!(load_bus(&bus, dir.path()).is_ok());
    }

    #[test]
    fn a_device_without_template() {
        let entry: DeviceEntry = serde_json::from_str(
            r#"{"address": 7, "serial": "0x0D000007", "line": "19200 8O1",
                "registers": [{"type": "coil", "address": 0, "count": 2, "events": true}],
                "values": {"coil:1": 1, "holding:128": 9}}"#,
        )
        .unwrap();
        let mut templates = TemplateSource::new(Path::new("."), Path::new("."));
        let device = build_device(&entry, &mut templates).unwrap();
        assert_eq!(device.address(), 9);
        assert_eq!(device.serial, 0x0D00_0007);
        assert_eq!(device.registers().get(RegisterType::Coil, 1), Some(1));
        assert_eq!(device.line(), LineSettings::new(19200, Parity::Odd, 1));
        assert_eq!(
            device.registers().event_width(RegisterType::Coil, 0),
            Some(1)
        );
    }

    #[test]
    fn hex_keys_and_serials() {
        assert_eq!(
            parse_register_key("coil:0x10"),
            Ok((RegisterType::Coil, 16))
        );
        assert!(parse_register_key("holding:70000").is_err());
        assert!(parse_register_key("holding:-1").is_err());
        assert!(parse_register_key("holding").is_err());
        assert_eq!(
            parse_serial(&serde_json::json!("0xFE4000AC")),
            Ok(0xFE40_00AC)
        );
        assert_eq!(
            parse_serial(&serde_json::json!("233000005")),
            Ok(233_000_005)
        );
        assert!(parse_serial(&serde_json::json!("-1")).is_err());
        assert!(parse_serial(&serde_json::json!("0x1FFFFFFFF")).is_err());
    }

    #[test]
    fn template_errors_name_the_device() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("broken.json"), "{\"device_type\": 1}").unwrap();
        std::fs::write(dir.path().join("my-relay.json"), "{").unwrap();
        let mut templates = TemplateSource::new(dir.path(), dir.path());
        let entry = |template: &str| -> DeviceEntry {
            serde_json::from_value(serde_json::json!(
                {"name": "d", "template": template, "address": 7, "serial": 7}
            ))
            .unwrap()
        };
        let err = build_device(&entry("missing.json"), &mut templates)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("\"d\"") && err.contains("missing.json"),
            "{err}"
        );
        let err = build_device(&entry("broken.json"), &mut templates)
            .unwrap_err()
            .to_string();
        assert!(err.contains("broken.json"), "{err}");
        let err = build_device(&entry("my-relay"), &mut templates)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("my-relay") && err.contains("my-relay.json"),
            "{err}"
        );
    }
}
