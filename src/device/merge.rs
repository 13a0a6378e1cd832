//! Merging a config device with its template, as wb-mqtt-serial does (reference §2.5–2.7), on
//! JSON values: config keys override template keys, channels merge by `name`, subdevice slots
//! are replaced by the chosen subdevice, parameters become setup items, and channels whose
//! `condition` is false are dropped.
//!
//! Every channel and setup item gets an `__origin` (`t:` template or `c:` config, and a JSON
//! path), so that later errors can still point into the right file.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use serde_json::{Map, Value};

use crate::config::condition::Condition;
use crate::config::error::Problem;
use crate::config::json_path::JsonPath;
use crate::config::load::{config_schema, duration_problem};
use crate::config::parse::schema_keys_at;

/// An error found while merging, before it is turned into a located error.
#[derive(Debug, Clone)]
pub struct MergeError {
    /// `t:` or `c:` followed by a JSON path.
    pub origin: String,
    pub problem: Problem,
}

/// Channel keys a config override may not change (they define the register).
const FORBIDDEN_CHANNEL_OVERRIDES: [&str; 16] = [
    "id",
    "type",
    "reg_type",
    "address",
    "format",
    "max",
    "scale",
    "offset",
    "round_to",
    "on_value",
    "off_value",
    "error_value",
    "unsupported_value",
    "word_order",
    "byte_order",
    "consists_of",
];

/// Device keys that are not copied from the config as plain overrides.
const SPECIAL_DEVICE_KEYS: [&str; 4] = ["channels", "setup", "name", "protocol"];

/// Device keys that stay what they are even if the template declares a parameter of that name
/// (which would take the device's address, type, name or channels away in wb-mqtt-serial).
const DEVICE_IDENTITY_KEYS: [&str; 8] = [
    "slave_id",
    "device_type",
    "id",
    "name",
    "enabled",
    "protocol",
    "channels",
    "setup",
];

fn known_device_keys() -> &'static Vec<String> {
    static KEYS: OnceLock<Vec<String>> = OnceLock::new();
    KEYS.get_or_init(|| schema_keys_at(&config_schema(), &JsonPath::parse("ports[0].devices[0]")))
}

fn known_channel_keys() -> &'static Vec<String> {
    static KEYS: OnceLock<Vec<String>> = OnceLock::new();
    KEYS.get_or_init(|| {
        schema_keys_at(
            &config_schema(),
            &JsonPath::parse("ports[0].devices[0].channels[0]"),
        )
    })
}

/// A config channel object that overrides a template channel, and its path in the config.
type ConfigOverride = (Map<String, Value>, JsonPath);

/// Subdevice bodies by `device_type`, from every nesting level, with their paths.
type SubdeviceMap = BTreeMap<String, (Value, JsonPath)>;

fn collect_subdevices(body: &Value, at: &JsonPath, out: &mut SubdeviceMap) {
    let Some(list) = body.get("subdevices").and_then(Value::as_array) else {
        return;
    };
    for (i, sub) in list.iter().enumerate() {
        let sub_at = at.key("subdevices").index(i).key("device");
        if let (Some(device_type), Some(device)) = (
            sub.get("device_type").and_then(Value::as_str),
            sub.get("device"),
        ) {
            out.entry(device_type.to_string())
                .or_insert_with(|| (device.clone(), sub_at.clone()));
            collect_subdevices(device, &sub_at, out);
        }
    }
}

/// Inputs of one device merge.
pub struct DeviceMergeInput<'a> {
    /// The template's raw JSON (None for a device defined entirely in the config).
    pub template: Option<&'a Value>,
    /// The config device object and its path in the config file.
    pub device: &'a Map<String, Value>,
    pub device_path: JsonPath,
    pub slave_id: String,
    /// Enforce `required` parameters (off when `check-templates` tries a template on its own).
    pub check_required: bool,
}

/// Merges; returns the device object to resolve and the warnings (settings that do nothing),
/// or every problem found.
pub fn merge_device(input: &DeviceMergeInput) -> Result<(Value, Vec<MergeError>), Vec<MergeError>> {
    let mut errors = Vec::new();
    let empty = Value::Object(Map::new());
    let template_device = input
        .template
        .and_then(|t| t.get("device"))
        .unwrap_or(&empty);
    let mut subdevices = SubdeviceMap::new();
    collect_subdevices(
        template_device,
        &JsonPath::root().key("device"),
        &mut subdevices,
    );

    let mut result = template_device.as_object().cloned().unwrap_or_default();
    result.remove("subdevices");
    result.remove("parameters");
    let template_name = template_device
        .get("name")
        .and_then(Value::as_str)
        .unwrap_or("");
    let name = match input.device.get("name").and_then(Value::as_str) {
        Some(name) => name.to_string(),
        None => format!("{template_name} {}", input.slave_id)
            .trim()
            .to_string(),
    };
    result.insert("name".into(), Value::String(name));
    if let Some(id) = template_device.get("id").and_then(Value::as_str) {
        result.insert(
            "id".into(),
            Value::String(format!("{id}_{}", input.slave_id)),
        );
    }

    // Config device keys: settings override, anything else must be a template parameter.
    let parameters = template_device.get("parameters");
    let mut values = BTreeMap::new();
    let mut not_numbers = Vec::new();
    for (key, value) in input.device {
        // A key named like a parameter of the template is that parameter's value, even where
        // it is a device setting too (a `stride` or a timing): wb-mqtt-serial's
        // `MergeDeviceConfigWithTemplate` copies the key into the device, then `AppendSetupItems`
        // makes a setup item of it and removes it from the device (`removeMember`), so it is
        // no setting there. The keys that make the device what it is stay settings.
        let is_parameter = parameter_spec(parameters, key).is_some()
            && !DEVICE_IDENTITY_KEYS.contains(&key.as_str());
        if known_device_keys().contains(key) && !is_parameter {
            if key == "max_publish_interval" {
                errors.push(warning(
                    format!("c:{}", input.device_path.key(key)),
                    "max_publish_interval is not applied per device: unchanged values are \
                     published again by the top-level max_unchanged_interval"
                        .into(),
                ));
            }
            if !SPECIAL_DEVICE_KEYS.contains(&key.as_str()) {
                result.insert(key.clone(), value.clone());
            }
            continue;
        }
        if is_parameter {
            // The template's own setting of that name goes too, as `removeMember` takes it.
            result.remove(key);
        }
        match parameter_spec(parameters, key) {
            Some(_) => match value.as_f64() {
                Some(number) => {
                    values.insert(key.clone(), number);
                }
                None => not_numbers.push((key, value)),
            },
            // wb-mqtt-serial's device schema has no `additionalProperties` and its merge copies
            // the key into the device, where nothing reads it (a parameter a newer template
            // dropped, kept in a config the web UI saved): the device runs there, so here too.
            None => {
                let mut valid: Vec<String> = known_device_keys()
                    .iter()
                    .filter(|k| !SPECIAL_DEVICE_KEYS.contains(&k.as_str()))
                    .cloned()
                    .collect();
                valid.extend(["channels", "setup", "name"].map(String::from));
                valid.extend(parameter_ids(parameters));
                errors.push(unknown_key(
                    format!("c:{}", input.device_path.key(key)),
                    "a device setting nor a parameter of the template",
                    key,
                    &valid,
                ));
            }
        }
    }

    // wb-mqtt-serial's device schema has an entry (type number) only for the declarations whose
    // condition holds over the config's values (`MakeDeviceParametersSchema`); for another,
    // `AppendSetupItems` logs "… is not an integer" and writes nothing.
    for (key, value) in not_numbers {
        let origin = format!("c:{}", input.device_path.key(key));
        let in_effect = parameter_declarations(parameters, key)
            .iter()
            .any(|(_, p)| condition_true(p, &values));
        errors.push(match in_effect {
            true => MergeError {
                origin,
                problem: Problem::Invalid(format!("parameter `{key}` needs a number, not {value}")),
            },
            false => warning(
                origin,
                format!(
                    "parameter `{key}` is {value}, not a number, and its condition does not \
                     hold: ignored, as wb-mqtt-serial ignores it"
                ),
            ),
        });
    }
    let level = Level {
        parameters,
        values: &values,
        config: input.device,
        config_setup: input.device.get("setup"),
        config_setup_path: input.device_path.key("setup"),
        value_path: input.device_path.clone(),
        template_setup: template_device.get("setup"),
        template_path: JsonPath::root().key("device"),
        evaluate_conditions: true,
    };
    level.check_rules(input.check_required, &mut errors);
    let setup = level.setup_items(&mut errors);
    result.insert("setup".into(), Value::Array(setup));

    let channels = merge_channels(
        template_device.get("channels"),
        &JsonPath::root().key("device").key("channels"),
        input.device.get("channels"),
        &input.device_path.key("channels"),
        &Scope {
            subdevices: &subdevices,
            check_required: input.check_required,
        },
        Some(&level.condition_values()),
        &mut errors,
        0,
    );
    result.insert("channels".into(), Value::Array(channels));
    let (warnings, errors): (Vec<MergeError>, Vec<MergeError>) = errors
        .into_iter()
        .partition(|e| matches!(e.problem, Problem::Warning(_)));
    if errors.is_empty() {
        Ok((Value::Object(result), warnings))
    } else {
        Err(errors)
    }
}

/// A config key that is neither a setting nor a parameter (`neither`: what it is not, "a device
/// setting nor a parameter of the template"): a warning that it is ignored, as wb-mqtt-serial
/// ignores it, with the closest valid keys for a typo.
fn unknown_key(origin: String, neither: &str, key: &str, valid: &[String]) -> MergeError {
    let suggestions = crate::config::library::suggest_keys(key, valid.iter().map(String::as_str));
    let hint = match suggestions.as_slice() {
        [] => String::new(),
        some => format!(" (did you mean `{}`?)", some.join("` or `")),
    };
    warning(
        origin,
        format!("`{key}` is neither {neither}{hint}: ignored, as wb-mqtt-serial ignores it"),
    )
}

fn warning(origin: String, message: String) -> MergeError {
    MergeError {
        origin,
        problem: Problem::Warning(message),
    }
}

/// A config channel's keys that no channel setting reads: a typo makes a setting silently do
/// nothing, so say so (an error under `check-config --strict`).
fn warn_unknown_channel_keys(
    object: &Map<String, Value>,
    at: &JsonPath,
    errors: &mut Vec<MergeError>,
) {
    for key in object.keys() {
        if known_channel_keys().contains(key) || key.starts_with("__") {
            continue;
        }
        let suggestions = crate::config::library::suggest_keys(
            key,
            known_channel_keys().iter().map(String::as_str),
        );
        // A config channel overrides the template's channel of its name: what it leaves out
        // comes from there, not from a default, so only the misspelling is said.
        errors.push(warning(
            format!("c:{}", at.key(key)),
            crate::config::library::unknown_key_warning("channel key", key, &suggestions, None),
        ));
    }
}

fn parameter_spec<'a>(parameters: Option<&'a Value>, id: &str) -> Option<&'a Value> {
    match parameters? {
        Value::Object(map) => map.get(id),
        Value::Array(list) => list
            .iter()
            .find(|p| p.get("id").and_then(Value::as_str) == Some(id)),
        _ => None,
    }
}

/// Parameter ids in template order, each once (an array may declare one id several times,
/// under exclusive conditions).
fn parameter_ids(parameters: Option<&Value>) -> Vec<String> {
    let mut ids: Vec<String> = Vec::new();
    let all: Vec<String> = match parameters {
        Some(Value::Object(map)) => map.keys().cloned().collect(),
        Some(Value::Array(list)) => list
            .iter()
            .filter_map(|p| p.get("id").and_then(Value::as_str))
            .map(String::from)
            .collect(),
        _ => Vec::new(),
    };
    for id in all {
        if !ids.contains(&id) {
            ids.push(id);
        }
    }
    ids
}

/// Parameter ids in the order wb-mqtt-serial turns them into setup items
/// (`AppendSetupItems` in `src/config_merge_template.cpp` walks the `parameters` value with
/// jsoncpp's iterator): an array in declaration order, an object in the byte order of its keys,
/// as jsoncpp keeps object members in a sorted map. Of two parameters on one address the first
/// is written, and `preserve_setup_order` writes them in this order.
fn setup_parameter_order(parameters: Option<&Value>) -> Vec<String> {
    let mut ids = parameter_ids(parameters);
    if matches!(parameters, Some(Value::Object(_))) {
        ids.sort();
    }
    ids
}

/// Every declaration of parameter `id` with its index in an array (None in an object).
fn parameter_declarations<'a>(
    parameters: Option<&'a Value>,
    id: &str,
) -> Vec<(Option<usize>, &'a Value)> {
    match parameters {
        Some(Value::Object(map)) => map.get(id).map(|p| (None, p)).into_iter().collect(),
        Some(Value::Array(list)) => list
            .iter()
            .enumerate()
            .filter(|(_, p)| p.get("id").and_then(Value::as_str) == Some(id))
            .map(|(i, p)| (Some(i), p))
            .collect(),
        _ => Vec::new(),
    }
}

/// Whether parameter declarations are firmware variants of one parameter: the same register
/// and `condition`, each for another minimum firmware (`fw`; none is the oldest).
/// wb-mqtt-serial takes them as one parameter whose values are those of the newest variant
/// (`TConfigParserTest.ParametersFwVariants`: a firmware update widens what it allows); two
/// whose conditions differ and both hold are a duplicate (its unsuccessful-17).
fn are_fw_variants(declarations: &[&Value]) -> bool {
    let Some(first) = declarations.first() else {
        return false;
    };
    let same_register = declarations.iter().all(|p| {
        ["address", "reg_type", "condition"]
            .iter()
            .all(|key| p.get(*key) == first.get(*key))
    });
    let mut versions: Vec<Vec<u64>> = declarations.iter().map(|p| fw_of(p)).collect();
    versions.sort();
    versions.dedup();
    same_register && versions.len() == declarations.len()
}

/// A declaration's `fw` as comparable numbers ("2.4.0" → [2, 4, 0]); none (no `fw`) sorts first.
fn fw_of(declaration: &Value) -> Vec<u64> {
    declaration
        .get("fw")
        .and_then(Value::as_str)
        .map(|fw| {
            fw.split(['.', '-', '+'])
                .map_while(|part| part.parse::<u64>().ok())
                .collect()
        })
        .unwrap_or_default()
}

/// Whether an item's `condition` holds; an unparsable condition counts as false (it is
/// reported where the item is used).
fn condition_true(item: &Value, values: &BTreeMap<String, f64>) -> bool {
    match item
        .get("condition")
        .and_then(Value::as_str)
        .filter(|t| !t.trim().is_empty())
    {
        None => true,
        Some(text) => Condition::parse(text).is_ok_and(|c| c.holds(values)),
    }
}

/// The numbers an `enum` allows, if the parameter has one.
fn allowed_values(spec: &Value) -> Option<Vec<f64>> {
    let list = spec.get("enum")?.as_array()?;
    Some(
        list.iter()
            .filter_map(|v| {
                v.as_f64().or_else(|| {
                    v.as_str()
                        .and_then(crate::config::values::parse_int_text)
                        .map(|i| i as f64)
                })
            })
            .collect(),
    )
}

fn number_of(spec: &Value, key: &str) -> Option<f64> {
    let value = spec.get(key)?;
    value.as_f64().or_else(|| {
        value
            .as_str()
            .and_then(crate::config::values::parse_int_text)
            .map(|i| i as f64)
    })
}

/// One level of parameters and setup: the device, or one subdevice slot.
struct Level<'a> {
    parameters: Option<&'a Value>,
    /// Parameter values given in the config.
    values: &'a BTreeMap<String, f64>,
    /// The config object that gave them (their exact JSON numbers).
    config: &'a Map<String, Value>,
    config_setup: Option<&'a Value>,
    config_setup_path: JsonPath,
    /// Where the config gives parameter values (for errors on them).
    value_path: JsonPath,
    template_setup: Option<&'a Value>,
    template_path: JsonPath,
    /// Whether `condition`s choose the parameters and setup items written. wb-mqtt-serial
    /// evaluates them for the device only: `MergeChannelConfigWithTemplate`
    /// (`src/config_merge_template.cpp`) calls `AppendSetupItems` for a subdevice without an
    /// expression cache, and `CheckCondition` holds without one.
    evaluate_conditions: bool,
}

impl Level<'_> {
    /// The declaration of `id` in effect: the one whose condition holds (reported when several
    /// do, unless they are firmware variants of one parameter: then the newest), else the
    /// first.
    fn active_spec(&self, id: &str, conditions: &BTreeMap<String, f64>) -> Option<&Value> {
        let declarations = parameter_declarations(self.parameters, id);
        let holding: Vec<&Value> = declarations
            .iter()
            .filter(|(_, p)| condition_true(p, conditions))
            .map(|(_, p)| *p)
            .collect();
        if holding.len() > 1 && are_fw_variants(&holding) {
            return holding.into_iter().max_by(|a, b| fw_of(a).cmp(&fw_of(b)));
        }
        holding
            .first()
            .copied()
            .or(declarations.first().map(|(_, p)| *p))
    }

    /// wb-mqtt-serial's parameter rules: one declaration in effect per id, values within
    /// `enum` / `min`…`max`, and every `required` parameter in effect given (checked only where
    /// the config chose this level: `check_required`).
    ///
    /// wb-mqtt-serial's validator decides "in effect" over the config's own values, without
    /// defaults: `MakeDeviceParametersSchema` (`src/config_schema_generator.cpp`) evaluates each
    /// declaration's condition over `TJsonParams(config)` (the device config as written) and puts
    /// only those that hold into the schema, with their `enum`, `minimum`, `maximum` and
    /// `required`; `default` is not part of it. Defaults are added later, by
    /// `MergeDeviceConfigWithTemplate`, for what is written and polled. A value is checked here
    /// both ways: against the declaration wb-mqtt-serial's validator sees (so the configs it
    /// refuses are refused) and against the one in effect once the defaults are in, which is the
    /// one written (so no value outside its declaration's bounds reaches a device, where
    /// wb-mqtt-serial writes one whose condition holds only through a default unchecked). In a
    /// subdevice every declaration given is written whatever its condition: a lone declaration
    /// is checked whatever its condition too.
    fn check_rules(&self, check_required: bool, errors: &mut Vec<MergeError>) {
        let with_defaults = self.condition_values();
        for id in parameter_ids(self.parameters) {
            let declarations = parameter_declarations(self.parameters, &id);
            let as_validated = self.check_value(&id, &declarations, self.values);
            // Only a value given is written: a parameter left out whose declarations hold two at
            // once only with the defaults in is nothing to choose between (wb-mqtt-serial's
            // validator does not see them either).
            let as_written = if self.values.contains_key(&id) {
                self.check_value(&id, &declarations, &with_defaults)
            } else {
                None
            };
            // A subdevice's parameter is written whatever its condition (`setup_items`, as
            // wb-mqtt-serial's `AppendSetupItems` without an expression cache): a lone
            // declaration's bounds apply whatever its condition.
            let in_subdevice = match (declarations.as_slice(), self.values.get(&id)) {
                ([(_, spec)], Some(value)) if !self.evaluate_conditions => {
                    self.bounds_error(&id, spec, *value)
                }
                _ => None,
            };
            // Both said when they differ: the first alone would send the user to a value the
            // other refuses (two declarations of one id, each with its own `enum`).
            let mut found: Vec<MergeError> = Vec::new();
            for error in [as_validated, as_written, in_subdevice]
                .into_iter()
                .flatten()
            {
                if !found.iter().any(|e| e.problem == error.problem) {
                    found.push(error);
                }
            }
            if !found.is_empty() {
                errors.extend(found);
                continue;
            }
            if self.values.contains_key(&id) || !check_required {
                continue;
            }
            // Over the config's own values too: a leak controller's `zone1_type` is required
            // only once the config gives `zone1_enable`, whose default would make its condition
            // hold. A `default` does not stand in for a `required` parameter whose condition
            // holds (WB-MAO4's `ls_1_ch_1_fading_off` once `ls_1_ch_1_action_off` is given):
            // `IsRequiredSetupRegister` reads `required` alone.
            let Some(required) = declarations.iter().map(|(_, p)| *p).find(|p| {
                p.get("required").and_then(Value::as_bool) == Some(true)
                    && condition_true(p, self.values)
            }) else {
                continue;
            };
            let choices = allowed_values(required)
                .filter(|a| !a.is_empty())
                .map(|a| format!(" (one of {})", describe_choices(required, &a)))
                .unwrap_or_default();
            errors.push(MergeError {
                origin: format!("c:{}", self.value_path),
                problem: Problem::Invalid(format!(
                    "the template requires parameter `{id}`: add `\"{id}\": <value>`{choices}"
                )),
            });
        }
    }

    /// One declaration of `id` in effect over `conditions`, and the config's value of `id`
    /// within that declaration's `enum` and `min`…`max`; the first rule broken, if any.
    fn check_value(
        &self,
        id: &str,
        declarations: &[(Option<usize>, &Value)],
        conditions: &BTreeMap<String, f64>,
    ) -> Option<MergeError> {
        let active: Vec<&(Option<usize>, &Value)> = declarations
            .iter()
            .filter(|(_, p)| condition_true(p, conditions))
            .collect();
        let specs: Vec<&Value> = active.iter().map(|(_, p)| *p).collect();
        if active.len() > 1 && !are_fw_variants(&specs) {
            let at = match active[1].0 {
                Some(i) => self.template_path.key("parameters").index(i),
                None => self.template_path.key("parameters").key(id),
            };
            return Some(MergeError {
                origin: format!("t:{at}"),
                problem: Problem::Invalid(format!(
                    "parameter `{id}` is declared {} times and more than one applies; give each declaration a `condition` that excludes the others",
                    declarations.len()
                )),
            });
        }
        let spec = self.active_spec(id, conditions)?;
        let value = self.values.get(id)?;
        // No declaration in effect: nothing is checked (WB-LED declares one id per dimmer mode,
        // each with its own `enum`), and, with the defaults in, nothing is written.
        if !condition_true(spec, conditions) {
            return None;
        }
        self.bounds_error(id, spec, *value)
    }

    /// The value of `id` within its declaration `spec`'s `enum` and `min`…`max`, or the error.
    fn bounds_error(&self, id: &str, spec: &Value, value: f64) -> Option<MergeError> {
        let value = &value;
        let origin = format!("c:{}", self.value_path.key(id));
        if let Some(allowed) = allowed_values(spec) {
            if !allowed.is_empty() && !allowed.contains(value) {
                return Some(MergeError {
                    origin,
                    problem: Problem::Invalid(format!(
                        "parameter `{id}` cannot be {value}; allowed: {}",
                        describe_choices(spec, &allowed)
                    )),
                });
            }
        }
        let min = number_of(spec, "min");
        let max = number_of(spec, "max");
        if min.is_some_and(|m| *value < m) || max.is_some_and(|m| *value > m) {
            return Some(MergeError {
                origin,
                problem: Problem::Invalid(format!(
                    "parameter `{id}` is {value}, outside its range {}…{}",
                    min.map(|m| m.to_string()).unwrap_or_default(),
                    max.map(|m| m.to_string()).unwrap_or_default()
                )),
            });
        }
        None
    }

    /// Parameter values for conditions: defaults, then the config's values.
    fn condition_values(&self) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        for id in parameter_ids(self.parameters) {
            // The first declaration that has a `default`, as `MergeDeviceConfigWithTemplate`
            // fills a missing value in (an earlier declaration without one does not stop it).
            if let Some(default) = parameter_declarations(self.parameters, &id)
                .into_iter()
                .find_map(|(_, p)| p.get("default"))
                .and_then(Value::as_f64)
            {
                out.insert(id, default);
            }
        }
        out.extend(self.values.iter().map(|(k, v)| (k.clone(), *v)));
        out
    }

    /// Config setup, then parameters set in the config, then template setup whose condition
    /// holds. In a subdevice no `condition` is looked at, as wb-mqtt-serial builds it
    /// (`AppendSetupItems` without an expression cache): every declaration of a parameter the
    /// config gives (unless `readonly`, in the order jsoncpp walks `parameters`) and every
    /// template setup item.
    fn setup_items(&self, errors: &mut Vec<MergeError>) -> Vec<Value> {
        let conditions = self.evaluate_conditions.then(|| self.condition_values());
        let mut items: Vec<Value> = self
            .config_setup
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .enumerate()
            .map(|(i, item)| with_origin(item, &format!("c:{}", self.config_setup_path.index(i))))
            .collect();
        let writable = |spec: &Value| spec.get("readonly").and_then(Value::as_bool) != Some(true);
        for id in setup_parameter_order(self.parameters) {
            let Some(value) = self.values.get(&id) else {
                continue;
            };
            let origin = format!("c:{}", self.value_path.key(&id));
            match &conditions {
                Some(conditions) => {
                    let Some(spec) = self.active_spec(&id, conditions) else {
                        continue;
                    };
                    if writable(spec) && condition_holds(spec, conditions, &origin, errors) {
                        items.push(self.parameter_item(&id, *value, spec, &origin));
                    }
                }
                None => {
                    for (_, spec) in parameter_declarations(self.parameters, &id) {
                        if writable(spec) {
                            items.push(self.parameter_item(&id, *value, spec, &origin));
                        }
                    }
                }
            }
        }
        for (i, item) in self
            .template_setup
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .enumerate()
        {
            let origin = format!("t:{}", self.template_path.key("setup").index(i));
            let holds = conditions
                .as_ref()
                .is_none_or(|conditions| condition_holds(item, conditions, &origin, errors));
            if holds {
                items.push(with_origin(item, &origin));
            }
        }
        items
    }

    /// The setup item that writes parameter `id`'s config value with declaration `spec`.
    fn parameter_item(&self, id: &str, value: f64, spec: &Value, origin: &str) -> Value {
        let mut item = with_origin(spec, origin);
        if let Some(object) = item.as_object_mut() {
            // The config's own number: an integer stays exact (u64 sensor ids above 2^53).
            let exact = self
                .config
                .get(id)
                .filter(|v| v.is_u64() || v.is_i64())
                .cloned()
                .unwrap_or_else(|| serde_json::json!(value));
            object.insert("value".into(), exact);
            object.insert("id".into(), Value::String(id.to_string()));
            object
                .entry("title")
                .or_insert_with(|| Value::String(id.to_string()));
        }
        item
    }
}

/// `0 (Button), 1 (Counter)` from an `enum` and its `enum_titles`.
fn describe_choices(spec: &Value, allowed: &[f64]) -> String {
    let titles = spec.get("enum_titles").and_then(Value::as_array);
    allowed
        .iter()
        .enumerate()
        .map(
            |(i, v)| match titles.and_then(|t| t.get(i)).and_then(Value::as_str) {
                Some(title) => format!("{v} ({title})"),
                None => v.to_string(),
            },
        )
        .collect::<Vec<_>>()
        .join(", ")
}

fn with_origin(item: &Value, origin: &str) -> Value {
    let mut item = item.clone();
    if let Some(object) = item.as_object_mut() {
        object
            .entry("__origin")
            .or_insert_with(|| Value::String(origin.to_string()));
    }
    item
}

fn condition_holds(
    item: &Value,
    values: &BTreeMap<String, f64>,
    origin: &str,
    errors: &mut Vec<MergeError>,
) -> bool {
    let Some(text) = item
        .get("condition")
        .and_then(Value::as_str)
        .filter(|t| !t.trim().is_empty())
    else {
        return true;
    };
    match Condition::parse(text) {
        Ok(condition) => condition.holds(values),
        Err(err) => {
            errors.push(MergeError {
                origin: format!("{origin}.condition"),
                problem: Problem::Invalid(err.to_string()),
            });
            false
        }
    }
}

/// Merges config channel overrides into template channels, expands subdevice slots and drops
/// channels whose condition is false (`conditions`: the device's values; None inside a
/// subdevice, whose channels wb-mqtt-serial keeps whatever their condition, as its
/// `RemoveDisabledChannels` looks at the device's own channels only).
#[allow(clippy::too_many_arguments)]
fn merge_channels(
    template_channels: Option<&Value>,
    template_path: &JsonPath,
    overrides: Option<&Value>,
    overrides_path: &JsonPath,
    scope: &Scope,
    conditions: Option<&BTreeMap<String, f64>>,
    errors: &mut Vec<MergeError>,
    depth: usize,
) -> Vec<Value> {
    let mut channels: Vec<(Value, Option<ConfigOverride>)> = Vec::new();
    for (i, channel) in template_channels
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .enumerate()
    {
        channels.push((
            with_origin(channel, &format!("t:{}", template_path.index(i))),
            None,
        ));
    }
    for (i, item) in overrides
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .enumerate()
    {
        let at = overrides_path.index(i);
        let Some(object) = item.as_object() else {
            continue;
        };
        let name = object.get("name").and_then(Value::as_str).unwrap_or("");
        // Every template channel of that name, as wb-mqtt-serial does: templates declare one
        // channel several times under conditions (one per input mode, firmware …), and an
        // override must reach whichever of them is in effect.
        let mut matched = false;
        let overrides_a_slot = channels.iter().any(|(c, _)| {
            c.get("name").and_then(Value::as_str) == Some(name)
                && (c.get("device_type").is_some() || c.get("oneOf").is_some())
        });
        if !overrides_a_slot && !object.contains_key("device_type") {
            warn_unknown_channel_keys(object, &at, errors);
        }
        for (channel, slot) in channels
            .iter_mut()
            .filter(|(c, _)| c.get("name").and_then(Value::as_str) == Some(name))
        {
            override_channel(channel, object, &at, errors);
            *slot = Some((object.clone(), at.clone()));
            matched = true;
        }
        match matched {
            true => {}
            false if object.contains_key("device_type") => errors.push(MergeError {
                origin: format!("c:{}", at.key("device_type")),
                problem: Problem::Invalid(format!(
                    "there is no subdevice slot named `{name}` in the template, so this channel cannot set `device_type`"
                )),
            }),
            // A channel of the config's own needs a register. One that has none names a
            // channel the template does not have (a typo, or one an update of the template
            // renamed): wb-mqtt-serial loads it, fails, and ignores it with a warning
            // (`LoadSimpleChannel`), so a config that runs there must not stop here.
            false if !["address", "write_address", "consists_of"]
                .iter()
                .any(|key| object.contains_key(*key)) =>
            {
                let names = channels
                    .iter()
                    .filter_map(|(c, _)| c.get("name").and_then(Value::as_str));
                let suggestions = crate::config::library::suggest_keys(name, names);
                let hint = match suggestions.as_slice() {
                    [] => String::new(),
                    [one] => format!(" (did you mean `{one}`?)"),
                    many => format!(" (did you mean one of `{}`?)", many.join("`, `")),
                };
                errors.push(warning(
                    format!("c:{}", at.key("name")),
                    format!(
                        "the template has no channel `{name}`{hint}, and without `address` it \
                         cannot be a channel of its own: ignored, as wb-mqtt-serial ignores it"
                    ),
                ));
            }
            false => channels.push((with_origin(item, &format!("c:{at}")), None)),
        }
    }
    let mut out = Vec::new();
    for (channel, config) in channels {
        let origin = channel
            .get("__origin")
            .and_then(Value::as_str)
            .unwrap_or("")
            .to_string();
        if let Some(conditions) = conditions {
            if !condition_holds(&channel, conditions, &origin, errors) {
                continue;
            }
        }
        if channel.get("device_type").is_some() {
            // Overridden without naming its subdevice: refused (`slot_without_device_type`), and
            // the template's default is not expanded with settings meant for another one.
            if config
                .as_ref()
                .is_some_and(|(object, _)| !object.contains_key("device_type"))
            {
                continue;
            }
            if depth > 8 {
                errors.push(MergeError {
                    origin,
                    problem: Problem::Invalid("subdevices nest too deep (a loop?)".into()),
                });
                continue;
            }
            if let Some(expanded) = expand_subdevice(channel, config, scope, errors, depth) {
                out.push(expanded);
            }
        } else {
            out.push(channel);
        }
    }
    out
}

fn override_channel(
    channel: &mut Value,
    config: &Map<String, Value>,
    at: &JsonPath,
    errors: &mut Vec<MergeError>,
) {
    let is_slot = channel.get("device_type").is_some() || channel.get("oneOf").is_some();
    let Some(target) = channel.as_object_mut() else {
        return;
    };
    if let Some(chosen) = config.get("device_type") {
        let allowed: Vec<&Value> = match (
            target.get("oneOf").and_then(Value::as_array),
            target.get("device_type"),
        ) {
            (Some(list), _) => list.iter().collect(),
            (None, Some(only)) => vec![only],
            (None, None) => Vec::new(),
        };
        let chosen_text = chosen
            .as_str()
            .map(String::from)
            .unwrap_or_else(|| chosen.to_string());
        if allowed.is_empty() {
            errors.push(MergeError {
                origin: format!("c:{}", at.key("device_type")),
                problem: Problem::Invalid(format!(
                    "the template's channel `{}` is not a subdevice slot, so it cannot take `device_type` `{chosen_text}`; remove `device_type` here",
                    target.get("name").and_then(Value::as_str).unwrap_or("")
                )),
            });
        } else if allowed.contains(&chosen) {
            target.insert("device_type".into(), chosen.clone());
        } else {
            let names: Vec<String> = allowed
                .iter()
                .filter_map(|v| v.as_str())
                .map(String::from)
                .collect();
            errors.push(MergeError {
                origin: format!("c:{}", at.key("device_type")),
                problem: Problem::Invalid(format!(
                    "`{chosen_text}` is not a choice of this slot; valid: {}",
                    names.join(", ")
                )),
            });
        }
    }
    for (key, value) in config {
        let forbidden = if is_slot {
            ["id", "oneOf"].contains(&key.as_str())
        } else {
            FORBIDDEN_CHANNEL_OVERRIDES.contains(&key.as_str())
        };
        match key.as_str() {
            "name" | "device_type" | "channels" | "setup" => {}
            "readonly"
                if target.get("readonly") == Some(&Value::Bool(true))
                    && value != &Value::Bool(true) =>
            {
                errors.push(warning(
                    format!("c:{}", at.key(key)),
                    "the template makes this channel read-only; `readonly` cannot be turned off here (ignored)".into(),
                ));
            }
            _ if forbidden => errors.push(warning(
                format!("c:{}", at.key(key)),
                format!(
                    "the template's `{key}` defines the register and cannot be overridden in the config (ignored); for a different register, add a channel with another name"
                ),
            )),
            _ if is_slot && !known_channel_keys().contains(key) => {} // a subdevice parameter value
            _ => {
                // A duration out of range is the config's mistake: said where the config has it,
                // not at the template's channel it lands on.
                if let Some(problem) = value
                    .as_i64()
                    .and_then(|duration| duration_problem(key, duration))
                {
                    errors.push(MergeError {
                        origin: format!("c:{}", at.key(key)),
                        problem,
                    });
                    continue;
                }
                target.insert(key.clone(), value.clone());
            }
        }
    }
    if is_slot && !config.contains_key("device_type") {
        errors.push(slot_without_device_type(target, at));
    }
}

/// A config channel that overrides a subdevice slot without naming its `device_type`: refused,
/// as wb-mqtt-serial refuses it (`CheckDeviceType` in `src/config_merge_template.cpp`,
/// called by `MergeChannelProperties` for every override of a slot: "'… channel "Input 2"' must
/// contain device_type" over a `oneOf` slot, "… device_type must be '4_20ma'" over a slot of
/// one subdevice). Nothing between there and `main` catches the exception: the whole config is
/// refused, not the device alone. Even `{"name": …, "enabled": false}` needs it there.
fn slot_without_device_type(slot: &Map<String, Value>, at: &JsonPath) -> MergeError {
    let name = slot.get("name").and_then(Value::as_str).unwrap_or("");
    let default = slot.get("device_type").and_then(Value::as_str);
    let choices: Vec<&str> = slot
        .get("oneOf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .collect();
    let quoted = |names: &[&str]| {
        names
            .iter()
            .map(|n| format!("\"{n}\""))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let what_to_add = match (choices.as_slice(), default) {
        ([], Some(only)) => {
            format!("add \"device_type\": \"{only}\" (the only subdevice this slot takes)")
        }
        (_, Some(default)) => format!(
            "add \"device_type\": one of {} (the template's default is \"{default}\")",
            quoted(&choices)
        ),
        (_, None) => format!("add \"device_type\": one of {}", quoted(&choices)),
    };
    MergeError {
        origin: format!("c:{at}"),
        problem: Problem::Invalid(format!(
            "this channel overrides subdevice slot `{name}` without saying which subdevice it \
             holds (wb-mqtt-serial refuses such a config too): {what_to_add}"
        )),
    }
}

/// What every level of one device merge shares.
struct Scope<'a> {
    subdevices: &'a SubdeviceMap,
    check_required: bool,
}

fn expand_subdevice(
    slot: Value,
    config: Option<ConfigOverride>,
    scope: &Scope,
    errors: &mut Vec<MergeError>,
    depth: usize,
) -> Option<Value> {
    let origin = slot
        .get("__origin")
        .and_then(Value::as_str)
        .unwrap_or("")
        .to_string();
    let device_type = slot
        .get("device_type")
        .and_then(Value::as_str)
        .unwrap_or("")
        .to_string();
    let Some((body, body_path)) = scope.subdevices.get(&device_type) else {
        errors.push(MergeError {
            origin: format!("{origin}.device_type"),
            problem: Problem::Invalid(format!(
                "subdevice type `{device_type}` is not in the template's `subdevices`"
            )),
        });
        return None;
    };
    let chosen_in_config = config.is_some();
    let (config_object, config_path) = match config {
        Some((object, path)) => (object, path),
        None => (Map::new(), JsonPath::root()),
    };
    let parameters = body.get("parameters");
    let mut values = BTreeMap::new();
    // A key named like one of the subdevice's parameters is that parameter's value, whatever
    // else the key means on a channel (the legacy WB-MAI11's `min` and `max`, the measuring
    // range of an input): wb-mqtt-serial's `MergeChannelProperties` copies every key of the
    // slot's override but `id` and `oneOf` into the slot, and `MergeChannelConfigWithTemplate`
    // hands the slot to `AppendSetupItems`, which makes a setup item of every member named like
    // a parameter. Nothing else of the slot's own keys reaches its channels there (the
    // subdevice is built from the subdevice's body, with only `name`, `shift`, `stride` and
    // `id` of the slot), so such a key is no channel property either.
    for (key, value) in &config_object {
        match (parameter_spec(parameters, key), value.as_f64()) {
            (Some(_), Some(number)) => {
                values.insert(key.clone(), number);
            }
            (Some(_), None) => errors.push(MergeError {
                origin: format!("c:{}", config_path.key(key)),
                problem: Problem::Invalid(format!("parameter `{key}` needs a number, not {value}")),
            }),
            (None, _) if known_channel_keys().contains(key) => {}
            // Ignored by wb-mqtt-serial's `MergeChannelConfigWithTemplate`, as on a device.
            (None, _) => {
                let mut valid = known_channel_keys().clone();
                valid.extend(parameter_ids(parameters));
                errors.push(unknown_key(
                    format!("c:{}", config_path.key(key)),
                    &format!("a setting of a subdevice slot nor a parameter of subdevice `{device_type}`"),
                    key,
                    &valid,
                ));
            }
        }
    }
    let level = Level {
        parameters,
        values: &values,
        config: &config_object,
        config_setup: config_object.get("setup"),
        config_setup_path: config_path.key("setup"),
        value_path: config_path.clone(),
        template_setup: body.get("setup"),
        template_path: body_path.clone(),
        evaluate_conditions: false,
    };
    level.check_rules(chosen_in_config && scope.check_required, errors);
    let setup = level.setup_items(errors);
    let channels = merge_channels(
        body.get("channels"),
        &body_path.key("channels"),
        config_object.get("channels"),
        &config_path.key("channels"),
        scope,
        None,
        errors,
        depth + 1,
    );
    let mut result = slot.as_object().cloned().unwrap_or_default();
    result.remove("oneOf");
    result.insert("setup".into(), Value::Array(setup));
    result.insert("channels".into(), Value::Array(channels));
    Some(Value::Object(result))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn merge(template: Value, device: Value) -> Result<(Value, Vec<MergeError>), Vec<MergeError>> {
        let device = device.as_object().unwrap().clone();
        merge_device(&DeviceMergeInput {
            template: Some(&template),
            device: &device,
            device_path: JsonPath::parse("ports[0].devices[0]"),
            slave_id: "1".into(),
            check_required: true,
        })
    }

    /// (title, value) of each setup item of `object`.
    fn setup_of(object: &Value) -> Vec<(String, Value)> {
        object["setup"]
            .as_array()
            .unwrap()
            .iter()
            .map(|item| {
                (
                    item["title"].as_str().unwrap().to_string(),
                    item["value"].clone(),
                )
            })
            .collect()
    }

    /// A device key that the template also declares as a parameter is that parameter's value,
    /// as wb-mqtt-serial's `MergeDeviceConfigWithTemplate` → `AppendSetupItems` makes it (a
    /// setup item, and the key removed from the device, the template's own value too); without
    /// the parameter it stays a device setting.
    #[test]
    fn a_device_parameter_named_like_a_device_setting_is_written() {
        let template = json!({"device_type": "t", "device": {"name": "T",
            "max_read_registers": 10,
            "parameters": {"max_read_registers": {"title": "Block size", "address": 5}},
            "channels": []}});
        let (merged, warnings) =
            merge(template, json!({"slave_id": 1, "max_read_registers": 3})).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(setup_of(&merged), vec![("Block size".into(), json!(3))]);
        assert!(merged.get("max_read_registers").is_none(), "{merged}");

        let template = json!({"device_type": "t", "device": {"name": "T", "channels": []}});
        let (merged, _) = merge(template, json!({"slave_id": 1, "max_read_registers": 3})).unwrap();
        assert_eq!(merged["max_read_registers"], 3);
        assert!(setup_of(&merged).is_empty());
    }

    /// A subdevice parameter named like a channel key (`min`, `max`, `units`) is written; it
    /// was skipped as a channel key. An unknown key names the subdevice it is no parameter of.
    #[test]
    fn a_subdevice_parameter_named_like_a_channel_key_is_written() {
        let template = json!({"device_type": "t", "device": {"name": "T",
            "channels": [{"name": "In", "oneOf": ["a"], "device_type": "a"}],
            "subdevices": [{"device_type": "a", "device": {
                "parameters": {
                    "min": {"title": "Minimum", "address": 8},
                    "max": {"title": "Maximum", "address": 10},
                    "units": {"title": "Unit code", "address": 12}},
                "channels": [{"name": "Value", "address": 4}]}}]}});
        let (merged, warnings) = merge(
            template,
            json!({"slave_id": 1, "channels": [{"name": "In", "device_type": "a",
                "min": 5, "max": 2000, "units": 2, "rate": 1}]}),
        )
        .unwrap();
        let slot = &merged["channels"][0];
        assert_eq!(
            setup_of(slot),
            vec![
                ("Maximum".into(), json!(2000)),
                ("Minimum".into(), json!(5)),
                ("Unit code".into(), json!(2)),
            ]
        );
        // The slot's channels do not take them as channel properties.
        assert!(slot["channels"][0].get("max").is_none(), "{slot}");
        let texts: Vec<String> = warnings.iter().map(|w| w.problem.to_string()).collect();
        assert_eq!(texts.len(), 1, "{texts:?}");
        assert!(
            texts[0].contains(
                "`rate` is neither a setting of a subdevice slot nor a parameter of subdevice `a`"
            ),
            "{texts:?}"
        );
    }
}
