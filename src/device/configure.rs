//! The whole config resolved against the templates: every enabled device of every enabled port,
//! with errors located in the config file or in the template file they come from.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{json, Map, Value};

use super::merge::{merge_device, DeviceMergeInput, MergeError};
use super::model::{ResolvedDevice, ResolvedPort};
use super::resolve::{
    resolve_device, topic_level_problem, ResolveError, ResolveInput, SharedResolutions,
};
use crate::config::config_file::{DeviceConfig, PortConfig};
use crate::config::error::{ErrorList, LocatedError, Problem};
use crate::config::json_path::JsonPath;
use crate::config::load::LoadedConfig;
use crate::config::parse::{value_at, SourceText};
use crate::config::values::SlaveId;
use crate::config::{TemplateFile, TemplateLibrary};

/// Resolves every enabled device; all errors are collected, warnings are logged.
pub fn resolve_config(
    loaded: &LoadedConfig,
    library: &TemplateLibrary,
) -> Result<Vec<ResolvedPort>, ErrorList> {
    let (result, warnings) = resolve_config_checked(loaded, library);
    for warning in &warnings {
        tracing::warn!("{warning}");
    }
    result
}

/// Resolves every enabled device, returning the warnings too (settings that do nothing: a
/// misspelt key, an override of a protected field), for `check-config` to show.
pub fn resolve_config_checked(
    loaded: &LoadedConfig,
    library: &TemplateLibrary,
) -> (Result<Vec<ResolvedPort>, ErrorList>, Vec<LocatedError>) {
    let mut warnings = loaded.warnings.clone();
    let mut used_templates: Vec<&TemplateFile> = Vec::new();
    let mut errors = Vec::new();
    let mut ports = Vec::new();
    let mut device_ids: BTreeMap<String, JsonPath> = BTreeMap::new();
    let mut shared = SharedResolutions::default();
    for (port_index, port) in loaded.config.ports.iter().enumerate() {
        if !port.enabled {
            continue;
        }
        let mut devices = Vec::new();
        for (device_index, device) in port.devices.iter().enumerate() {
            if device.enabled == Some(false) {
                continue;
            }
            let path = JsonPath::root()
                .key("ports")
                .index(port_index)
                .key("devices")
                .index(device_index);
            let Some(object) = value_at(&loaded.raw, &path).and_then(Value::as_object) else {
                continue;
            };
            let slave_id = device
                .slave_id
                .map(|s| s.value())
                .unwrap_or(0)
                .clamp(0, 255) as u8;
            let module = device.slave_id.and_then(|s| s.module);
            let template = match &device.device_type {
                Some(device_type) => match library.get(device_type) {
                    Some(template) => {
                        if !used_templates
                            .iter()
                            .any(|t| t.device_type() == template.device_type())
                        {
                            used_templates.push(template);
                            warnings.extend(template_key_warnings(template));
                        }
                        Some(template)
                    }
                    None => {
                        // A template of another protocol is there, but left out: say that, not
                        // "no template".
                        if let Some((protocol, at)) = library.unsupported_protocol(device_type) {
                            errors.push(loaded.error(
                                path.key("device_type"),
                                Problem::UnsupportedDevice {
                                    device_type: Some(device_type.clone()),
                                    protocol: protocol.to_string(),
                                    template: Some(at.location()),
                                },
                            ));
                            continue;
                        }
                        if let Some((cause, entry)) = library.broken(device_type) {
                            errors.push(
                                loaded.error(
                                    path.key("device_type"),
                                    Problem::BrokenTemplate {
                                        device_type: device_type.clone(),
                                        file: entry.path().display().to_string(),
                                        shadowed: entry
                                            .shadowed
                                            .iter()
                                            .map(|p| p.display().to_string())
                                            .collect(),
                                    },
                                ),
                            );
                            errors.push(cause.clone());
                            continue;
                        }
                        errors.push(loaded.error(
                            path.key("device_type"),
                            Problem::MissingTemplate {
                                device_type: device_type.clone(),
                                similar: library.similar(device_type),
                                searched: library.searched(),
                            },
                        ));
                        if let Some(cause) = library.load_error_for(device_type) {
                            errors.push(cause.clone());
                        }
                        continue;
                    }
                },
                None => None,
            };
            match resolve_one(
                loaded.source.clone(),
                object,
                &path,
                template,
                port,
                (slave_id, module),
                true,
                &mut warnings,
                &mut shared,
            ) {
                Ok(mut resolved) => {
                    if resolved.id.is_empty() {
                        resolved.id = format!("wb-modbus-{port_index}-{device_index}");
                    }
                    // Only a device with nothing to go on: one whose config turns off every
                    // channel of its template (kept for its setup writes, say) is left as asked,
                    // as wb-mqtt-serial leaves it.
                    if resolved.channels.is_empty() && device.device_type.is_none() {
                        warnings.push(loaded.error(
                            path.clone(),
                            Problem::Warning(no_channels_warning(port, device)),
                        ));
                    }
                    if let Some(message) = topic_level_problem("device id", &resolved.id) {
                        errors.push(loaded.error(
                            if device.id.is_some() {
                                path.key("id")
                            } else {
                                path.clone()
                            },
                            Problem::Invalid(message),
                        ));
                        continue;
                    }
                    match device_ids.get(&resolved.id) {
                        Some(other) => errors.push(loaded.error(
                            if device.id.is_some() {
                                path.key("id")
                            } else {
                                path.clone()
                            },
                            Problem::DuplicateDeviceId {
                                id: resolved.id.clone(),
                                other: other.to_string(),
                            },
                        )),
                        None => {
                            device_ids.insert(resolved.id.clone(), path.clone());
                        }
                    }
                    devices.push(resolved);
                }
                Err(mut more) => errors.append(&mut more),
            }
        }
        ports.push(ResolvedPort {
            index: port_index,
            config: port.clone(),
            devices,
            low_priority_read_limit: None,
        });
    }
    if let Some(limit) = loaded.config.rate_limit {
        share_rate_limit(&mut ports, limit);
    }
    let result = if errors.is_empty() {
        Ok(ports)
    } else {
        Err(ErrorList(errors))
    };
    // A template's channel left out is reported by every device made from it: say it once.
    let mut seen = std::collections::BTreeSet::new();
    warnings.retain(|w| seen.insert(w.to_string()));
    (result, warnings)
}

/// A device that resolves to no channel is accepted, as wb-mqtt-serial accepts it (its schema
/// of a device without template requires only `slave_id`; loading it logs "the device has no
/// channels"), but nothing is ever read from it: most often `device_type` was left out.
fn no_channels_warning(port: &PortConfig, device: &DeviceConfig) -> String {
    format!(
        "the device with slave_id {} on port {} has neither `device_type` nor `channels`: \
         nothing will be polled for it. `device_type` (the name of its template, e.g. \
         \"WB-MR6C\") is probably missing.",
        device
            .slave_id
            .map(|id| id.to_string())
            .unwrap_or_else(|| "(none)".into()),
        port.describe()
    )
}

/// Splits `rate_limit` (low-priority channel reads per second, all ports together) across the
/// ports in proportion to their channels, at least 1 each, as wb-mqtt-serial does.
fn share_rate_limit(ports: &mut [ResolvedPort], limit: u32) {
    let channels =
        |port: &ResolvedPort| -> u64 { port.devices.iter().map(|d| d.channels.len() as u64).sum() };
    let total: u64 = ports.iter().map(channels).sum();
    for port in ports.iter_mut() {
        let share = u64::from(limit)
            .saturating_mul(channels(port))
            .checked_div(total)
            .unwrap_or(u64::from(limit));
        port.low_priority_read_limit = Some(u32::try_from(share).unwrap_or(u32::MAX).max(1));
    }
}

/// Keys of a template that no setting reads and that look like a misspelt valid key (`scal`,
/// `read_period`). Keys close to nothing are UI-only keys of the wb format: not reported.
pub fn template_key_warnings(template: &TemplateFile) -> Vec<LocatedError> {
    let schema = crate::config::template::template_schema();
    let mut out = Vec::new();
    for path in &template.unknown_keys {
        let segments = path.segments();
        let Some(crate::config::json_path::PathSegment::Key(key)) = segments.last() else {
            continue;
        };
        let parent = JsonPath(segments[..segments.len() - 1].to_vec());
        let valid = crate::config::parse::schema_keys_at(&schema, &parent);
        let suggestions =
            crate::config::library::suggest_keys(key, valid.iter().map(String::as_str));
        if suggestions.is_empty() {
            continue;
        }
        out.push(template.source.error(
            path.clone(),
            Problem::Warning(crate::config::library::unknown_key_warning(
                "key",
                key,
                &suggestions,
                parent.find(&template.raw),
            )),
        ));
    }
    out
}

// One call site per use (config, check-templates, single template): a struct would only rename them.
#[allow(clippy::too_many_arguments)]
fn resolve_one(
    config_source: SourceText,
    object: &Map<String, Value>,
    path: &JsonPath,
    template: Option<&TemplateFile>,
    port: &PortConfig,
    (slave_id, module): (u8, Option<i128>),
    check_required: bool,
    warnings: &mut Vec<LocatedError>,
    shared: &mut SharedResolutions,
) -> Result<ResolvedDevice, Vec<LocatedError>> {
    let locate = |origin: &str, problem: Problem| {
        locate_origin(&config_source, template, path, origin, problem)
    };
    let slave_text = object.get("slave_id").map(|v| match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    });
    let input = DeviceMergeInput {
        template: template.map(|t| &t.raw),
        device: object,
        device_path: path.clone(),
        slave_id: slave_text.unwrap_or_else(|| slave_id.to_string()),
        check_required,
    };
    let (merged, merge_warnings) = merge_device(&input).map_err(|errors| {
        errors
            .into_iter()
            .map(|MergeError { origin, problem }| locate(&origin, problem))
            .collect::<Vec<_>>()
    })?;
    warnings.extend(
        merge_warnings
            .into_iter()
            .map(|MergeError { origin, problem }| locate(&origin, problem)),
    );
    let resolve_input = ResolveInput {
        merged: &merged,
        port,
        slave_id,
        module,
        is_wb_template: template
            .is_some_and(|t| t.template.hw.as_ref().is_some_and(|hw| !hw.is_empty())),
        hw: template
            .and_then(|t| t.template.hw.clone())
            .unwrap_or_default(),
        device_type: template.map(|t| t.device_type().to_string()),
    };
    let (device, resolve_warnings) = resolve_device(&resolve_input, shared).map_err(|errors| {
        errors
            .into_iter()
            .map(|ResolveError { origin, problem }| locate(&origin, problem))
            .collect::<Vec<_>>()
    })?;
    warnings.extend(
        resolve_warnings
            .into_iter()
            .map(|warning| locate(&warning.origin, Problem::Warning(warning.message))),
    );
    Ok(device)
}

/// Turns an `__origin` (`t:` template path, `c:` config path) into a located error.
fn locate_origin(
    config: &SourceText,
    template: Option<&TemplateFile>,
    device_path: &JsonPath,
    origin: &str,
    problem: Problem,
) -> LocatedError {
    if let (Some(rest), Some(template)) = (origin.strip_prefix("t:"), template) {
        let mut error = template.source.error(JsonPath::parse(rest), problem);
        // Which device brought the template in, when there is one (not for `check-templates`).
        if !device_path.is_root() {
            if let Problem::Invalid(message) = &mut error.problem {
                *message = format!(
                    "{message} (in the template, as used by the device at {device_path} of {})",
                    config.path.display()
                );
            }
        }
        return error;
    }
    let path = origin
        .strip_prefix("c:")
        .map(JsonPath::parse)
        .unwrap_or_else(|| device_path.clone());
    config.error(path, problem)
}

/// Resolves a template on its own, as a device at slave 1 with default choices, and once for
/// every choice of every subdevice slot: what `check-templates` runs to find errors that only
/// show when the template is used.
pub fn check_template(template: &TemplateFile) -> Vec<LocatedError> {
    let port = default_port();
    let mut errors = Vec::new();
    let is_modbus_io = template
        .template
        .device
        .protocol
        .as_deref()
        .is_some_and(|p| p.starts_with("modbus_io"));
    let (slave_id, module) = if is_modbus_io {
        (json!("1:1"), Some(1))
    } else {
        (json!(1), None)
    };
    let mut configs = vec![json!({"slave_id": slave_id, "device_type": template.device_type()})];
    let slots = template
        .raw
        .pointer("/device/channels")
        .and_then(Value::as_array)
        .cloned()
        .unwrap_or_default();
    let mut tried = std::collections::BTreeSet::new();
    for slot in &slots {
        let (Some(name), Some(choices)) = (
            slot.get("name"),
            slot.get("oneOf").and_then(Value::as_array),
        ) else {
            continue;
        };
        // Each choice once, in the first slot that offers it: enough to load every subdevice.
        for choice in choices.iter().filter(|c| tried.insert(c.to_string())) {
            configs.push(json!({
                "slave_id": slave_id,
                "device_type": template.device_type(),
                "channels": [{"name": name, "device_type": choice}],
            }));
        }
    }
    let config_source = SourceText::from_text(Path::new("(check)"), "{}");
    for config in configs {
        let Some(object) = config.as_object() else {
            continue;
        };
        // Resolve warnings (channels left out, enum titles dropped) come back as
        // `Problem::Warning` entries.
        let mut warnings = Vec::new();
        let result = resolve_one(
            config_source.clone(),
            object,
            &JsonPath::root(),
            Some(template),
            &port,
            (1, module),
            false,
            &mut warnings,
            &mut SharedResolutions::default(),
        );
        let warnings = warnings
            .into_iter()
            .filter(|w| matches!(w.problem, Problem::Warning(_)));
        for error in warnings.chain(result.err().unwrap_or_default()) {
            if !errors.contains(&error) {
                errors.push(error);
            }
        }
    }
    errors
}

fn default_port() -> PortConfig {
    serde_json::from_value(json!({"path": "/dev/null"})).unwrap_or_else(|_| PortConfig {
        port_type: Default::default(),
        enabled: true,
        path: None,
        baud_rate: 9600,
        parity: crate::protocol::Parity::None,
        data_bits: 8,
        stop_bits: 1,
        address: None,
        port: None,
        connected_to_mge: false,
        fast_modbus: None,
        response_timeout_ms: None,
        frame_timeout_ms: None,
        guard_interval_us: None,
        read_rate_limit_ms: None,
        event_interval_ms: None,
        poll_interval: None,
        connect_timeout_ms: 5000,
        connection_timeout_ms: 5000,
        connection_max_fail_cycles: 2,
        devices: Vec::new(),
    })
}

/// Resolves a single template as a device (tests, simulator): `device` is the config device
/// object (at least `slave_id`), merged with the template as in a config file.
pub fn resolve_template_device(
    template: &TemplateFile,
    device: &Value,
) -> Result<ResolvedDevice, ErrorList> {
    resolve_single(template, device, true, &mut Vec::new())
}

/// As [`resolve_template_device`], with the warnings (settings that do nothing, channels left
/// out) as `check-config` shows them.
pub fn resolve_template_device_with_warnings(
    template: &TemplateFile,
    device: &Value,
) -> Result<(ResolvedDevice, Vec<LocatedError>), ErrorList> {
    let mut warnings = Vec::new();
    let device = resolve_single(template, device, true, &mut warnings)?;
    Ok((device, warnings))
}

/// As [`resolve_template_device_with_warnings`], without asking for the `required`
/// parameters: what the hardware has does not depend on what a config must give (the simulator
/// builds a WB-LED or a WB-MAI6, whose templates require a mode, from its template alone).
pub fn resolve_template_device_unconfigured(
    template: &TemplateFile,
    device: &Value,
) -> Result<(ResolvedDevice, Vec<LocatedError>), ErrorList> {
    let mut warnings = Vec::new();
    let device = resolve_single(template, device, false, &mut warnings)?;
    Ok((device, warnings))
}

fn resolve_single(
    template: &TemplateFile,
    device: &Value,
    check_required: bool,
    warnings: &mut Vec<LocatedError>,
) -> Result<ResolvedDevice, ErrorList> {
    let object = device.as_object().cloned().unwrap_or_default();
    let parsed: Option<SlaveId> = object
        .get("slave_id")
        .and_then(|v| serde_json::from_value(v.clone()).ok());
    let slave_id = parsed.map(|s| s.value()).unwrap_or(1).clamp(0, 255) as u8;
    let module = parsed.and_then(|s| s.module);
    let text = serde_json::to_string_pretty(device).unwrap_or_default();
    let source = SourceText::from_text(Path::new("(device)"), &text);
    resolve_one(
        source,
        &object,
        &JsonPath::root(),
        Some(template),
        &default_port(),
        (slave_id, module),
        check_required,
        warnings,
        &mut SharedResolutions::default(),
    )
    .map_err(ErrorList)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use serde_json::json;

    use super::*;
    use crate::device::SharedVec;

    /// The devices of a config's ports (templates from the repository's `templates` and the
    /// WBIO test template), in config order.
    fn resolve(ports: Value) -> Vec<ResolvedDevice> {
        let config = json!({ "ports": ports });
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let library =
            TemplateLibrary::load_dirs(&[root.join("templates"), root.join("tests/data/wb-rules")]);
        resolve_config(&loaded, &library)
            .unwrap_or_else(|errors| panic!("{errors}"))
            .into_iter()
            .flat_map(|port| port.devices)
            .collect()
    }

    /// `rate_limit` is shared by the ports in proportion to their channels, at least 1 each.
    #[test]
    fn rate_limit_is_split_across_ports_by_their_channels() {
        let config = json!({
            "rate_limit": 100,
            "ports": [
                {"path": "/dev/ttyA", "devices": [
                    {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
                    {"device_type": "rtu2mqtt-relay6", "slave_id": 21},
                    {"device_type": "rtu2mqtt-relay6", "slave_id": 22},
                ]},
                {"path": "/dev/ttyB", "devices": [
                    {"device_type": "rtu2mqtt-relay6", "slave_id": 23},
                ]},
                {"path": "/dev/ttyC", "devices": []},
            ]
        });
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let library = TemplateLibrary::load_dirs(&[root.join("templates")]);
        let ports = resolve_config(&loaded, &library).unwrap_or_else(|errors| panic!("{errors}"));
        let limits: Vec<Option<u32>> = ports.iter().map(|p| p.low_priority_read_limit).collect();
        assert_eq!(limits, [Some(75), Some(25), Some(1)]);
        let unlimited = crate::config::load::load_config_source(
            SourceText::from_text(
                Path::new("c.json"),
                &json!({"ports": [{"path": "/dev/ttyA", "devices": []}]}).to_string(),
            ),
            false,
        )
        .unwrap();
        let ports = resolve_config(&unlimited, &library).unwrap();
        assert_eq!(ports[0].low_priority_read_limit, None);
    }

    fn shares(a: &ResolvedDevice, b: &ResolvedDevice) -> bool {
        let channels = SharedVec::ptr_eq(&a.channels, &b.channels);
        assert_eq!(channels, SharedVec::ptr_eq(&a.setup, &b.setup));
        channels
    }

    /// Identical devices hold one copy of their template's channels and setup, and only their
    /// own id, name and address — also across ports (only the timing depends on the port).
    #[test]
    fn devices_of_one_template_share_its_resolution() {
        let devices = resolve(json!([
            {"path": "/dev/ttyA", "devices": [
                {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
                {"device_type": "rtu2mqtt-relay6", "slave_id": 21},
            ]},
            {"path": "/dev/ttyB", "response_timeout_ms": 700, "devices": [
                {"device_type": "rtu2mqtt-relay6", "slave_id": 22},
            ]},
        ]));
        let [a, b, c] = &devices[..] else {
            panic!("3 devices expected")
        };
        assert!(shares(a, b) && shares(a, c));
        assert!(!a.channels.is_empty() && !a.setup.is_empty());
        assert_eq!(
            [&a.id, &b.id, &c.id].map(String::as_str),
            ["relay6_20", "relay6_21", "relay6_22"]
        );
        assert_eq!([a.slave_id, b.slave_id, c.slave_id], [20, 21, 22]);
        assert_eq!(c.timing.response_timeout.as_millis(), 700);
        assert_ne!(a.timing, c.timing);
    }

    /// A device with its own overrides or parameters gets its own channels and setup; devices
    /// with the same overrides share theirs, although the overrides sit at different places in
    /// the config (which error messages would name).
    #[test]
    fn devices_with_other_overrides_do_not_share() {
        let override_k1 = json!([{"name": "K1", "read_period_ms": 100}]);
        let devices = resolve(json!([
            {"path": "/dev/ttyA", "devices": [
                {"device_type": "rtu2mqtt-relay6", "slave_id": 1},
                {"device_type": "rtu2mqtt-relay6", "slave_id": 2, "channels": override_k1},
                {"device_type": "rtu2mqtt-relay6", "slave_id": 3, "channels": override_k1},
                {"device_type": "rtu2mqtt-relay6", "slave_id": 4, "baud_rate": 1152},
                {"device_type": "rtu2mqtt-relay6", "slave_id": 5, "id": "hall", "name": "Hall"},
            ]},
        ]));
        let [plain, k1, k1_again, baud, named] = &devices[..] else {
            panic!("5 devices expected")
        };
        assert!(!shares(plain, k1));
        assert!(shares(k1, k1_again));
        assert!(!shares(plain, baud));
        assert!(!shares(k1, baud));
        assert!(shares(plain, named), "an own id and name change no channel");
        assert_eq!((named.id.as_str(), named.name.as_str()), ("hall", "Hall"));
        let period = |device: &ResolvedDevice| device.channel("K1").unwrap().read_period;
        assert_eq!(period(plain), None);
        assert_eq!(period(k1), Some(std::time::Duration::from_millis(100)));
        let baud_value = |device: &ResolvedDevice| {
            device
                .setup
                .iter()
                .find(|s| s.parameter_id.as_deref() == Some("baud_rate"))
                .map(|s| s.value.clone())
        };
        assert_eq!(baud_value(baud).as_deref(), Some("1152"));
        assert_ne!(baud_value(plain), baud_value(baud));
    }

    /// WBIO modules behind one WB-MIO differ in their addresses only through the module number:
    /// those in the same register window share, the others do not.
    #[test]
    fn modbus_io_modules_in_other_windows_do_not_share() {
        let devices = resolve(json!([
            {"path": "/dev/ttyA", "devices": [
                {"device_type": "TEST-WBIO", "slave_id": "1:1"},
                {"device_type": "TEST-WBIO", "slave_id": "1:2"},
                {"device_type": "TEST-WBIO", "slave_id": "2:1"},
            ]},
        ]));
        let [first, second, other_mio] = &devices[..] else {
            panic!("3 devices expected")
        };
        assert!(!shares(first, second));
        assert!(shares(first, other_mio));
        let k1 = |device: &ResolvedDevice| device.channel("K1").unwrap().registers[0].read;
        assert_eq!(k1(first).unwrap().address, 1016);
        assert_eq!(k1(second).unwrap().address, 1032);
    }
}
