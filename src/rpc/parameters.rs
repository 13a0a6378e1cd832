//! Template parameters in the device methods, as wb-mqtt-serial takes them: which declarations
//! `device/LoadConfig` reads (an `address`, not `readonly`, not set by the config, within the
//! device's firmware), `device/Load` reads and `device/Set` writes; their registers and formats
//! (resolved by the template resolver itself, each parameter as a channel of a device of their
//! own); how reads are grouped; which values `device/LoadConfig` reports (each declaration's
//! `condition` on the values known so far). Pure: the bus work is `methods.rs`'s.

use std::collections::{BTreeMap, HashMap};

use serde_json::{json, Map, Value};

use crate::config::condition::Condition;
use crate::config::parse::SourceText;
use crate::config::template::parameter_declarations;
use crate::config::TemplateFile;
use crate::device::firmware::firmware_has;
use crate::device::model::{ChannelRegister, ResolvedDevice};
use crate::device::resolve_template_device;
use crate::port::{MergeLimits, RegisterSpan};
use crate::protocol::RegisterType;

/// One declaration of a template parameter (a template may declare an id several times, with
/// other registers under other conditions).
#[derive(Debug, Clone)]
pub struct ParameterRegister {
    pub id: String,
    pub register: ChannelRegister,
    /// None: always reported.
    pub condition: Option<Condition>,
}

impl ParameterRegister {
    /// The registers (or bits) its value is read from.
    pub fn span(&self) -> Option<RegisterSpan> {
        self.register.read.map(|read| read.span())
    }
}

/// Keys of a parameter that say where its value is and how it is encoded.
const REGISTER_KEYS: [&str; 9] = [
    "reg_type",
    "address",
    "write_address",
    "format",
    "word_order",
    "byte_order",
    "scale",
    "offset",
    "string_data_size",
];

/// The template's parameter declarations in file order: (id, declaration).
fn declarations(template: &TemplateFile) -> Vec<(String, &Map<String, Value>)> {
    parameter_declarations(template.raw.get("device").and_then(|d| d.get("parameters")))
}

/// The template declares parameters (wb-mqtt-serial answers `{}` for a template without).
pub fn has_parameters(template: &TemplateFile) -> bool {
    !declarations(template).is_empty()
}

/// The template pulls in subdevices (wb-mqtt-serial's device RPCs refuse such templates).
pub fn has_subdevices(template: &TemplateFile) -> bool {
    template
        .raw
        .get("device")
        .and_then(|d| d.get("subdevices"))
        .and_then(Value::as_array)
        .is_some_and(|list| !list.is_empty())
}

/// What wb-mqtt-serial reads for `device/LoadConfig`: every declaration with an `address`, not
/// `readonly`, whose id the config does not set (`known`), and whose `fw` the device's firmware
/// reaches (when it is known).
pub fn parameter_registers(
    template: &TemplateFile,
    slave_id: u8,
    known: &Map<String, Value>,
    firmware: Option<&str>,
) -> Result<Vec<ParameterRegister>, String> {
    let mut wanted = Vec::new();
    for (id, spec) in declarations(template) {
        if !spec.contains_key("address") || is_readonly(spec) || known.contains_key(&id) {
            continue;
        }
        // As wb-mqtt-serial's device tools (`IsSupportedByFw`): a parameter newer than the
        // firmware is left out; unknown firmware has them all.
        let needs = spec.get("fw").and_then(Value::as_str).unwrap_or("");
        if !needs.is_empty() && !firmware_has(firmware, needs) {
            continue;
        }
        wanted.push((id, spec));
    }
    resolve(template, slave_id, wanted)
}

/// What `device/Load` reads for its `parameters`: the first declaration of each id with an
/// `address`, as wb-mqtt-serial takes it (conditions do not apply); `Err` names an id the
/// template has no readable declaration of, in wb-mqtt-serial's words.
pub fn named_parameters(
    template: &TemplateFile,
    slave_id: u8,
    ids: &[String],
) -> Result<Vec<ParameterRegister>, String> {
    let all = declarations(template);
    let mut wanted = Vec::new();
    for id in ids {
        let declaration = all
            .iter()
            .find(|(declared, spec)| declared == id && spec.contains_key("address"))
            .ok_or_else(|| {
                format!(
                    "Parameter \"{id}\" is write only or not found in \"{}\" device template",
                    template.device_type()
                )
            })?;
        wanted.push((declaration.0.clone(), declaration.1));
    }
    let mut registers = resolve(template, slave_id, wanted)?;
    for register in &mut registers {
        register.condition = None;
    }
    Ok(registers)
}

/// The registers of `wanted` declarations, from the template resolver: the device's own keys
/// (shift, protocol) with one channel per declaration.
fn resolve(
    template: &TemplateFile,
    slave_id: u8,
    wanted: Vec<(String, &Map<String, Value>)>,
) -> Result<Vec<ParameterRegister>, String> {
    if wanted.is_empty() {
        return Ok(Vec::new());
    }
    Ok(resolve_as_device(template, slave_id, wanted)?.0)
}

/// [`resolve`], with the device the declarations resolve to: one channel per declaration,
/// named [`channel_name`] of its index.
fn resolve_as_device(
    template: &TemplateFile,
    slave_id: u8,
    wanted: Vec<(String, &Map<String, Value>)>,
) -> Result<(Vec<ParameterRegister>, ResolvedDevice), String> {
    let channels: Vec<Value> = wanted
        .iter()
        .enumerate()
        .map(|(index, (_, spec))| {
            let mut channel = Map::new();
            channel.insert("name".into(), json!(channel_name(index)));
            for key in REGISTER_KEYS {
                if let Some(value) = spec.get(key) {
                    channel.insert(key.into(), value.clone());
                }
            }
            Value::Object(channel)
        })
        .collect();
    let mut raw = template.raw.clone();
    if let Some(device) = raw.get_mut("device").and_then(Value::as_object_mut) {
        for key in ["channels", "setup", "parameters", "subdevices", "groups"] {
            device.remove(key);
        }
        device.insert("channels".into(), Value::Array(channels));
    }
    let text = serde_json::to_string(&raw).map_err(|err| err.to_string())?;
    let file = TemplateFile::from_source(SourceText::from_text(&template.source.path, &text))
        .map_err(|err| err.to_string())?;
    let resolved = resolve_template_device(&file, &json!({ "slave_id": slave_id }))
        .map_err(|errors| format!("the template's parameters do not resolve: {errors}"))?;
    let mut registers = Vec::new();
    for (index, (id, spec)) in wanted.into_iter().enumerate() {
        let name = channel_name(index);
        let register = resolved
            .channels
            .iter()
            .find(|c| c.name == name)
            .and_then(|c| c.registers.first())
            .filter(|r| r.read.is_some() || r.write.is_some())
            .ok_or_else(|| format!("parameter \"{id}\" has no register"))?;
        let condition = match spec.get("condition").and_then(Value::as_str) {
            Some(text) if !text.trim().is_empty() => {
                Some(Condition::parse(text).map_err(|err| {
                    format!("parameter \"{id}\": condition {text:?}: {}", err.message)
                })?)
            }
            _ => None,
        };
        registers.push(ParameterRegister {
            id,
            register: register.clone(),
            condition,
        });
    }
    Ok((registers, resolved))
}

/// What `device/Set` writes for its `parameters`, as wb-mqtt-serial takes them: the first
/// declaration of each id that is not `readonly`, resolved as a device whose channels are the
/// parameters (so the device model checks, encodes and merges bit fields as for `/on`). Returns
/// that device and each id's control id in it; `Err` names an id it cannot write, in
/// wb-mqtt-serial's words.
pub fn writable_parameters(
    template: &TemplateFile,
    slave_id: u8,
    ids: &[&str],
) -> Result<(ResolvedDevice, Vec<String>), String> {
    let all = declarations(template);
    let mut wanted = Vec::new();
    for id in ids {
        let declaration = all
            .iter()
            .find(|(declared, spec)| declared == id && !is_readonly(spec))
            .filter(|(_, spec)| spec.contains_key("address") || spec.contains_key("write_address"))
            .ok_or_else(|| {
                format!(
                    "Parameter \"{id}\" is read only or not found in \"{}\" device template",
                    template.device_type()
                )
            })?;
        wanted.push((declaration.0.clone(), declaration.1));
    }
    let count = wanted.len();
    let (_, device) = resolve_as_device(template, slave_id, wanted)?;
    Ok((device, (0..count).map(channel_name).collect()))
}

/// `readonly` (UI only: never written, not read by `device/LoadConfig`).
fn is_readonly(spec: &Map<String, Value>) -> bool {
    spec.get("readonly").and_then(Value::as_bool) == Some(true)
}

fn channel_name(index: usize) -> String {
    format!("parameter {index}")
}

/// The reads that cover `spans`: ascending by table and address, merged as far as the device
/// lets reads be merged (its `max_read_registers` and holes), each register read once.
pub fn group_reads(spans: &[RegisterSpan], limits: MergeLimits) -> Vec<RegisterSpan> {
    let mut sorted = spans.to_vec();
    sorted.sort();
    sorted.dedup();
    let mut reads: Vec<RegisterSpan> = Vec::new();
    for span in sorted {
        if let Some(last) = reads.last_mut() {
            if last.contains(&span) {
                continue;
            }
            if let Some(merged) = limits.extend(*last, span) {
                *last = merged;
                continue;
            }
        }
        reads.push(span);
    }
    reads
}

/// Register contents read so far, by table and address.
pub type ReadWords = HashMap<(RegisterType, u16), u16>;

/// The words of `span`, if every one was read.
pub fn words_of(read: &ReadWords, span: RegisterSpan) -> Option<Vec<u16>> {
    (0..span.count)
        .map(|offset| {
            read.get(&(span.register_type, span.start.wrapping_add(offset)))
                .copied()
        })
        .collect()
}

/// The reported parameters: `known` (the config's values), then each value read whose
/// declaration's condition holds on the values reported so far, again until nothing more is
/// added (as wb-mqtt-serial: a condition may name a parameter that is read). `values` are the
/// decoded values, by index in `registers`.
pub fn reported(
    registers: &[ParameterRegister],
    values: &[Option<Value>],
    known: &Map<String, Value>,
) -> Map<String, Value> {
    let mut result: BTreeMap<String, Value> = known
        .iter()
        .map(|(id, value)| (id.clone(), value.clone()))
        .collect();
    loop {
        let numbers: BTreeMap<String, f64> = result
            .iter()
            .filter_map(|(id, value)| Some((id.clone(), value.as_f64()?)))
            .collect();
        let next = registers.iter().zip(values).find(|(register, value)| {
            value.is_some()
                && !result.contains_key(&register.id)
                && register
                    .condition
                    .as_ref()
                    .is_none_or(|condition| condition.holds(&numbers))
        });
        match next {
            Some((register, Some(value))) => {
                result.insert(register.id.clone(), value.clone());
            }
            _ => break,
        }
    }
    result.into_iter().collect()
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    fn template(parameters: Value) -> TemplateFile {
        let raw = json!({
            "device_type": "t",
            "device": {
                "name": "T", "id": "t",
                "parameters": parameters,
                "channels": [{"name": "C", "reg_type": "input", "address": 1}]
            }
        });
        TemplateFile::from_source(SourceText::from_text(Path::new("t.json"), &raw.to_string()))
            .unwrap()
    }

    fn holding(start: u16, count: u16) -> RegisterSpan {
        RegisterSpan::new(RegisterType::Holding, start, count)
    }

    #[test]
    fn which_parameters_are_read() {
        let template = template(json!({
            "mode": {"title": "m", "address": 9, "reg_type": "holding"},
            "ui_only": {"title": "u", "address": 10, "readonly": true},
            "no_register": {"title": "n"},
            "newer": {"title": "f", "address": 11, "fw": "1.30.0"},
            "configured": {"title": "c", "address": 12},
            "temp": {"title": "t", "address": "0x20", "format": "s16", "scale": 0.1,
                     "condition": "mode==2"},
            "flag": {"title": "b", "address": "13:4:2"},
            "coil": {"title": "k", "address": 3, "reg_type": "coil"}
        }));
        let known = Map::from_iter([("configured".to_owned(), json!(1))]);
        let registers = parameter_registers(&template, 5, &known, Some("1.26.0")).unwrap();
        let ids: Vec<&str> = registers.iter().map(|r| r.id.as_str()).collect();
        assert_eq!(ids, ["mode", "temp", "flag", "coil"]);
        assert_eq!(registers[0].span(), Some(holding(9, 1)));
        assert_eq!(registers[1].span(), Some(holding(0x20, 1)));
        assert_eq!(
            registers[1].register.codec.decode(&[0xFF9C]).unwrap(),
            crate::device::Reading::Value("-10".into())
        );
        assert_eq!(
            registers[2].register.codec.decode(&[0b0010_0000]).unwrap(),
            crate::device::Reading::Value("2".into())
        );
        assert_eq!(
            registers[3].span(),
            Some(RegisterSpan::new(RegisterType::Coil, 3, 1))
        );
        assert!(registers[1].condition.is_some());
        // Firmware unknown: `fw` does not filter.
        let all = parameter_registers(&template, 5, &known, None).unwrap();
        assert!(all.iter().any(|r| r.id == "newer"));
        // Versions order as wb-mqtt-serial orders them: a release candidate is older.
        let has_newer = |firmware| {
            parameter_registers(&template, 5, &known, Some(firmware))
                .unwrap()
                .iter()
                .any(|r| r.id == "newer")
        };
        assert!(!has_newer("1.30.0-rc2"));
        assert!(has_newer("1.30.0+wb1"));
        assert!(has_newer("1.30"));
    }

    #[test]
    fn parameters_as_an_array_with_repeated_ids() {
        let template = template(json!([
            {"id": "range", "title": "r", "address": 20, "condition": "kind==1"},
            {"id": "range", "title": "r", "address": 21, "condition": "kind==2"},
            {"id": "kind", "title": "k", "address": 19}
        ]));
        let registers = parameter_registers(&template, 1, &Map::new(), None).unwrap();
        let spans: Vec<_> = registers
            .iter()
            .map(|r| (r.id.as_str(), r.span()))
            .collect();
        assert_eq!(
            spans,
            [
                ("range", Some(holding(20, 1))),
                ("range", Some(holding(21, 1))),
                ("kind", Some(holding(19, 1)))
            ]
        );
        // The declaration whose condition holds on the value read gives the value.
        let values = [Some(json!(7)), Some(json!(8)), Some(json!(2))];
        let result = reported(&registers, &values, &Map::new());
        assert_eq!(Value::Object(result), json!({"kind": 2, "range": 8}));
    }

    #[test]
    fn conditions_see_config_values_and_values_read() {
        let template = template(json!({
            "mode": {"title": "m", "address": 9},
            "extra": {"title": "e", "address": 10, "condition": "mode==3"},
            "other": {"title": "o", "address": 11, "condition": "set==1"}
        }));
        let registers = parameter_registers(&template, 1, &Map::new(), None).unwrap();
        let values = [Some(json!(3)), Some(json!(40)), Some(json!(50))];
        let result = reported(&registers, &values, &Map::new());
        assert_eq!(Value::Object(result), json!({"extra": 40, "mode": 3}));
        let known = Map::from_iter([("set".to_owned(), json!(1))]);
        let result = reported(&registers, &values, &known);
        assert_eq!(
            Value::Object(result),
            json!({"extra": 40, "mode": 3, "other": 50, "set": 1})
        );
        // A value that could not be read is left out, and so is what depends on it.
        let result = reported(&registers, &[None, Some(json!(40)), None], &Map::new());
        assert_eq!(Value::Object(result), json!({}));
    }

    #[test]
    fn parameters_named_by_device_load() {
        let template = template(json!([
            {"id": "range", "title": "r", "address": 20, "condition": "kind==1", "readonly": true},
            {"id": "range", "title": "r", "address": 21, "condition": "kind==2"},
            {"id": "write_only", "title": "w", "write_address": 22}
        ]));
        let ids = ["range".to_owned()];
        let registers = named_parameters(&template, 1, &ids).unwrap();
        assert_eq!(registers.len(), 1);
        assert_eq!(registers[0].span(), Some(holding(20, 1)));
        assert!(registers[0].condition.is_none());
        for missing in ["write_only", "nope"] {
            assert_eq!(
                named_parameters(&template, 1, &[missing.to_owned()]).unwrap_err(),
                format!(
                    "Parameter \"{missing}\" is write only or not found in \"t\" device template"
                )
            );
        }
    }

    #[test]
    fn parameters_written_by_device_set() {
        let template = template(json!([
            {"id": "mode", "title": "m", "address": 20, "readonly": true},
            {"id": "mode", "title": "m", "address": 21, "format": "s16", "scale": 0.1},
            {"id": "flag", "title": "f", "write_address": "22:4:1"},
            {"id": "shown", "title": "s", "address": 23, "readonly": true}
        ]));
        let (device, controls) = writable_parameters(&template, 1, &["flag", "mode"]).unwrap();
        let register = |control: &str| device.channel(control).unwrap().registers[0].clone();
        let flag = register(&controls[0]);
        assert_eq!(flag.read, None);
        assert_eq!(flag.write.map(|w| (w.address, w.bit_shift)), Some((22, 4)));
        let mode = register(&controls[1]);
        assert_eq!(mode.write.map(|w| w.address), Some(21));
        assert_eq!(mode.codec.encode("-1.5", None).unwrap(), [0xFFF1]);
        assert_eq!(
            writable_parameters(&template, 1, &["shown"]).unwrap_err(),
            "Parameter \"shown\" is read only or not found in \"t\" device template"
        );
    }

    #[test]
    fn no_parameters_and_subdevices() {
        let plain = template(json!({}));
        assert!(!has_parameters(&plain));
        assert!(!has_subdevices(&plain));
        assert!(parameter_registers(&plain, 1, &Map::new(), None)
            .unwrap()
            .is_empty());
    }

    #[test]
    fn reads_are_grouped_as_the_device_allows() {
        let spans = [
            holding(16, 1),
            holding(9, 1),
            holding(10, 1),
            holding(11, 1),
            holding(110, 1),
            holding(10, 1),
            RegisterSpan::new(RegisterType::Coil, 3, 1),
        ];
        let no_holes = MergeLimits {
            max_read_registers: 0,
            max_register_hole: 0,
            max_bit_hole: 0,
            min_read_registers: 1,
        };
        assert_eq!(
            group_reads(&spans, no_holes),
            [
                RegisterSpan::new(RegisterType::Coil, 3, 1),
                holding(9, 3),
                holding(16, 1),
                holding(110, 1)
            ]
        );
        let holes = MergeLimits {
            max_register_hole: 10,
            ..no_holes
        };
        assert_eq!(
            group_reads(&spans, holes)[1..],
            [holding(9, 8), holding(110, 1)]
        );
        let one_at_a_time = MergeLimits::default();
        assert_eq!(group_reads(&spans, one_at_a_time).len(), 6);
    }
}
