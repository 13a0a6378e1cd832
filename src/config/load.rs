//! Loading the config file: JSON with comments, then `RTU2MQTT_*` environment overrides
//! (figment), then the checks that need no templates.

use std::collections::BTreeMap;
use std::path::Path;

use figment::providers::{Env, Serialized};
use figment::Figment;
use serde_json::Value;

use super::config_file::{Config, PortType, MAX_BAUD_RATE, MIN_BAUD_RATE};
use super::error::{ErrorList, LocatedError, Problem};
use super::json_path::JsonPath;
use super::parse::{deserialize_at, schema_keys_at, value_at, SourceText};
use super::values::SlaveId;
use crate::protocol::timing::{is_usual_baud_rate, usual_baud_rates_text};

/// Default config path of the Debian package.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/rtu2mqtt/config.json";
/// Prefix of environment overrides: `RTU2MQTT_MQTT__HOST=broker` sets `mqtt.host`.
pub const ENV_PREFIX: &str = "RTU2MQTT_";

/// A parsed config and what is needed to report later errors in it.
#[derive(Debug, Clone)]
pub struct LoadedConfig {
    pub config: Config,
    pub source: SourceText,
    pub raw: Value,
    /// Device-level keys that are no device setting: values of template parameters, or typos
    /// (decided against the template when devices are resolved).
    pub device_extra_keys: Vec<JsonPath>,
    /// Settings that do nothing (unknown keys at the top level or on a port, which
    /// wb-mqtt-serial ignores too): reported with the resolve warnings.
    pub warnings: Vec<LocatedError>,
}

impl LoadedConfig {
    pub fn error(&self, path: JsonPath, problem: Problem) -> LocatedError {
        self.source.error(path, problem)
    }
}

/// Loads `path`, applies the process's `RTU2MQTT_*` environment, checks ports and devices.
pub fn load_config(path: &Path) -> Result<LoadedConfig, ErrorList> {
    let source = SourceText::read(path)?;
    let env: Vec<(String, String)> = std::env::vars()
        .filter(|(k, _)| k.starts_with(ENV_PREFIX))
        .collect();
    load_config_source(source, !env.is_empty())
}

/// Loads config text already read (tests; `apply_env` merges the process environment).
pub fn load_config_source(source: SourceText, apply_env: bool) -> Result<LoadedConfig, ErrorList> {
    let mut raw = source.parse_json()?;
    let foreign = foreign_protocol_errors(&source, &raw);
    // Validate the file on its own first, so its errors point into it.
    let typed =
        deserialize_at::<Config>(&source, &without_foreign_devices(&raw), &JsonPath::root())?;
    let mut config = typed.value;
    let mut ignored = typed.ignored;
    if apply_env {
        let file_raw = raw.clone();
        raw = Figment::from(Serialized::defaults(&raw))
            .merge(Env::prefixed(ENV_PREFIX).split("__"))
            .extract::<Value>()
            .map_err(|err| {
                LocatedError::file_level(
                    &source.path,
                    Problem::Invalid(format!("environment override: {err}")),
                )
            })?;
        let merged =
            deserialize_at::<Config>(&source, &without_foreign_devices(&raw), &JsonPath::root())
                .map_err(|err| env_error(err, &file_raw))?;
        config = merged.value;
        ignored = merged.ignored;
    }
    let loaded = LoadedConfig {
        config,
        source,
        raw,
        device_extra_keys: Vec::new(),
        warnings: Vec::new(),
    };
    let (device_extra_keys, mut warnings, mut errors) = split_ignored(&loaded, ignored);
    warnings.extend(unusual_baud_rates(&loaded));
    errors.splice(0..0, foreign);
    errors.extend(check_mqtt(&loaded));
    errors.extend(check_ports(&loaded));
    errors.extend(check_http(&loaded));
    if errors.is_empty() {
        Ok(LoadedConfig {
            device_extra_keys,
            warnings,
            ..loaded
        })
    } else {
        Err(ErrorList(errors))
    }
}

/// An error in the config once the `RTU2MQTT_*` environment is applied: it comes from the
/// variables that set that place (the file alone loaded), so they are named, and no line and
/// column of the file are given.
fn env_error(err: LocatedError, file_raw: &Value) -> LocatedError {
    let variables: Vec<(String, Vec<String>)> = std::env::vars()
        .filter_map(|(key, _)| {
            let rest = key.strip_prefix(ENV_PREFIX)?;
            let segments = rest.split("__").map(str::to_lowercase).collect();
            Some((key, segments))
        })
        .collect();
    let error_segments: Vec<String> = err
        .path
        .segments()
        .iter()
        .map(|segment| match segment {
            super::json_path::PathSegment::Key(key) => key.to_lowercase(),
            super::json_path::PathSegment::Index(index) => index.to_string(),
        })
        .collect();
    let common = |env: &[String]| {
        let n = env.len().min(error_segments.len());
        env[..n] == error_segments[..n]
    };
    let named: Vec<&(String, Vec<String>)> =
        variables.iter().filter(|(_, env)| common(env)).collect();
    let names: Vec<&str> = named.iter().map(|(key, _)| key.as_str()).collect();
    let by = match names.as_slice() {
        [] => format!("an {ENV_PREFIX}* environment variable"),
        [one] => format!("the environment variable {one}"),
        several => format!("the environment variables {}", several.join(", ")),
    };
    // A variable that reaches inside a list (`RTU2MQTT_PORTS__0__BAUD_RATE`) replaces the list.
    let into_a_list = named
        .iter()
        .any(|(_, env)| env.len() > error_segments.len())
        && value_at(file_raw, &err.path).is_some_and(Value::is_array);
    let hint = if into_a_list {
        format!(
            "; the environment sets only scalar settings (such as {ENV_PREFIX}MQTT__HOST), \
             not entries of lists such as `{}`: change those in the file",
            err.path
        )
    } else {
        String::new()
    };
    LocatedError {
        problem: Problem::Invalid(format!("{} (set by {by}{hint})", err.problem)),
        line_column: None,
        ..err
    }
}

/// The config devices that name a protocol other than Modbus (`"protocol": "milur"`, with
/// channels of that protocol's register types), by path.
fn foreign_protocol_devices(raw: &Value) -> Vec<(usize, usize, String, bool)> {
    let mut out = Vec::new();
    let Some(ports) = raw.get("ports").and_then(Value::as_array) else {
        return out;
    };
    for (p, port) in ports.iter().enumerate() {
        let port_enabled = port.get("enabled").and_then(Value::as_bool) != Some(false);
        let Some(devices) = port.get("devices").and_then(Value::as_array) else {
            continue;
        };
        for (d, device) in devices.iter().enumerate() {
            if let Some(protocol) = device
                .get("protocol")
                .and_then(Value::as_str)
                .filter(|p| !super::library::is_modbus_protocol(p))
            {
                let enabled =
                    port_enabled && device.get("enabled").and_then(Value::as_bool) != Some(false);
                out.push((p, d, protocol.to_string(), enabled));
            }
        }
    }
    out
}

/// An enabled device of another protocol cannot be served: said once, at its `protocol`,
/// rather than at the first of its channels whose register type Modbus does not know.
fn foreign_protocol_errors(source: &SourceText, raw: &Value) -> Vec<LocatedError> {
    foreign_protocol_devices(raw)
        .into_iter()
        .filter(|(_, _, _, enabled)| *enabled)
        .map(|(port, device, protocol, _)| {
            source.error(
                JsonPath::root()
                    .key("ports")
                    .index(port)
                    .key("devices")
                    .index(device)
                    .key("protocol"),
                Problem::UnsupportedDevice {
                    device_type: None,
                    protocol,
                    template: None,
                },
            )
        })
        .collect()
}

/// `raw` with every device of another protocol replaced by a disabled stub (indices kept), so
/// that the typed check does not read their channels and a disabled one costs nothing.
fn without_foreign_devices(raw: &Value) -> std::borrow::Cow<'_, Value> {
    let foreign = foreign_protocol_devices(raw);
    if foreign.is_empty() {
        return std::borrow::Cow::Borrowed(raw);
    }
    let mut out = raw.clone();
    for (port, device, _, _) in foreign {
        if let Some(slot) = out.pointer_mut(&format!("/ports/{port}/devices/{device}")) {
            *slot = serde_json::json!({"enabled": false});
        }
    }
    std::borrow::Cow::Owned(out)
}

/// Unknown keys: at device level (and in channel overrides) they may be parameter values; at the
/// top level and on a port they are ignored with a warning, as wb-mqtt-serial ignores them (its
/// ports schema, `wb-mqtt-serial-ports.schema.json`, has no `additionalProperties`, and
/// `LoadConfig`/`LoadPort` read only the keys they know); anywhere else they are typos.
fn split_ignored(
    loaded: &LoadedConfig,
    ignored: Vec<JsonPath>,
) -> (Vec<JsonPath>, Vec<LocatedError>, Vec<LocatedError>) {
    use super::json_path::PathSegment;
    let schema = config_schema();
    let mut device_keys = Vec::new();
    let mut warnings = Vec::new();
    let mut errors = Vec::new();
    for path in ignored {
        let segments = path.segments();
        let in_ports = matches!(segments.first(), Some(PathSegment::Key(k)) if k == "ports");
        let is_device_level = segments.len() >= 5
            && in_ports
            && matches!(&segments[2], PathSegment::Key(k) if k == "devices");
        if is_device_level {
            device_keys.push(path);
            continue;
        }
        let parent = JsonPath(segments[..segments.len().saturating_sub(1)].to_vec());
        let key = match segments.last() {
            Some(PathSegment::Key(k)) => k.clone(),
            _ => continue,
        };
        let valid = schema_keys_at(&schema, &parent);
        let what = match segments.len() {
            1 => "top-level key",
            3 if in_ports => "port key",
            _ => {
                errors.push(loaded.error(path, Problem::UnknownKey { key, valid }));
                continue;
            }
        };
        let suggestions = super::library::suggest_keys(&key, valid.iter().map(String::as_str));
        let mut message =
            super::library::unknown_key_warning(what, &key, &suggestions, parent.find(&loaded.raw));
        message.push_str(if message.ends_with(['.', '?']) {
            " wb-mqtt-serial ignores it too."
        } else {
            "; wb-mqtt-serial ignores it too"
        });
        warnings.push(loaded.error(path, Problem::Warning(message)));
    }
    (device_keys, warnings, errors)
}

/// Why a `slave_id` cannot be used, if it cannot. 0 is the broadcast address (every device of
/// the bus would carry out a write to it) and 248…255 are reserved on a serial line; a Modbus
/// TCP server may use 248…255 as its unit id (255 is common), never 0.
fn slave_id_problem(slave_id: SlaveId, port_type: PortType) -> Option<String> {
    let highest = if port_type == PortType::ModbusTcp {
        255
    } else {
        247
    };
    if slave_id.address == 0 {
        return Some(
            "slave_id 0 is the Modbus broadcast address: every device of the bus would carry out \
             writes to it; use the device's own address (1…247)"
                .to_string(),
        );
    }
    if !(1..=highest).contains(&slave_id.address) {
        return Some(format!(
            "slave_id {} is out of range: devices on {} use 1…{highest}",
            slave_id.address,
            if port_type == PortType::ModbusTcp {
                "Modbus TCP"
            } else {
                "a serial line (248…255 are reserved)"
            }
        ));
    }
    if let Some(module) = slave_id.module {
        if !(1..=255).contains(&module) {
            return Some(format!(
                "the module number in slave_id `{slave_id}` must be 1…255 (its place behind the WB-MIO)"
            ));
        }
    }
    None
}

/// The longest value each duration key may have. A larger one is surely a mistake (a unit
/// mix-up, a typo) and would make the daemon wait for hours or days on the bus.
pub const DURATION_LIMITS: [(&str, i64, &str); 12] = [
    ("response_timeout_ms", 60_000, "1 minute"),
    ("frame_timeout_ms", 10_000, "10 s"),
    ("guard_interval_us", 1_000_000, "1 s"),
    ("min_request_interval", 3_600_000, "1 hour"),
    ("device_timeout_ms", 3_600_000, "1 hour"),
    ("max_write_fail_time_s", 86_400, "1 day"),
    // 2 days: the longest period wb-mqtt-serial's web UI saves (`tableChannelSettings.period`,
    // as `read_period_ms` or `read_rate_limit_ms`).
    ("read_rate_limit_ms", 172_800_000, "2 days"),
    ("poll_interval", 172_800_000, "2 days"),
    ("read_period_ms", 172_800_000, "2 days"),
    ("connection_timeout_ms", 3_600_000, "1 hour"),
    ("event_interval_ms", 86_400_000, "1 day"),
    ("connect_timeout_ms", 3_600_000, "1 hour"),
];

/// Whether a duration is out of bounds: -1 (or any negative, "not set" upstream) is allowed,
/// and values up to the key's limit.
pub fn duration_problem(key: &str, value: i64) -> Option<Problem> {
    let (_, limit, words) = DURATION_LIMITS.iter().find(|(k, _, _)| *k == key)?;
    (value > *limit || value < -1).then(|| {
        Problem::Invalid(format!(
            "`{key}` {value} is out of range: use -1 (unset) or 0…{limit} ({words} at most)"
        ))
    })
}

fn port_durations(port: &super::config_file::PortConfig) -> Vec<(&'static str, i64)> {
    let mut out = vec![
        ("connection_timeout_ms", port.connection_timeout_ms),
        (
            "connect_timeout_ms",
            i64::try_from(port.connect_timeout_ms).unwrap_or(i64::MAX),
        ),
    ];
    let optional = [
        ("response_timeout_ms", port.response_timeout_ms),
        ("frame_timeout_ms", port.frame_timeout_ms),
        ("guard_interval_us", port.guard_interval_us),
        ("read_rate_limit_ms", port.read_rate_limit_ms),
        ("poll_interval", port.poll_interval),
        (
            "event_interval_ms",
            port.event_interval_ms
                .map(|v| i64::try_from(v).unwrap_or(i64::MAX)),
        ),
    ];
    out.extend(optional.into_iter().filter_map(|(k, v)| v.map(|v| (k, v))));
    out
}

/// TLS files must exist now, not fail at the first connection; a certificate needs its key.
fn check_tls(loaded: &LoadedConfig) -> Vec<LocatedError> {
    let mut errors = Vec::new();
    let Some(tls) = &loaded.config.mqtt.tls else {
        return errors;
    };
    let at = JsonPath::root().key("mqtt").key("tls");
    for (key, file) in [
        ("ca_file", &tls.ca_file),
        ("cert_file", &tls.cert_file),
        ("key_file", &tls.key_file),
    ] {
        if let Some(file) = file {
            if let Err(err) = std::fs::File::open(file) {
                errors.push(loaded.error(
                    at.key(key),
                    Problem::Invalid(format!(
                        "cannot read {}: {err}; give the path of the PEM file on this machine",
                        file.display()
                    )),
                ));
            }
        }
    }
    match (&tls.cert_file, &tls.key_file) {
        (Some(_), None) => errors.push(loaded.error(
            at.key("cert_file"),
            Problem::Invalid("a client certificate needs its private key: add `key_file`".into()),
        )),
        (None, Some(_)) => errors.push(loaded.error(
            at.key("key_file"),
            Problem::Invalid("a private key needs its certificate: add `cert_file`".into()),
        )),
        _ => {}
    }
    errors
}

/// A broker address that cannot work is refused here: `run` would otherwise retry it forever
/// with a resolver error that does not say what is wrong in the config.
fn check_mqtt(loaded: &LoadedConfig) -> Vec<LocatedError> {
    let mqtt = &loaded.config.mqtt;
    let at = JsonPath::root().key("mqtt");
    let mut errors = Vec::new();
    if let Some(message) = broker_host_problem(&mqtt.host, mqtt.tls.is_some()) {
        errors.push(loaded.error(at.key("host"), Problem::Invalid(message)));
    }
    if mqtt.port == 0 {
        errors.push(loaded.error(
            at.key("port"),
            Problem::Invalid(format!(
                "port 0 is no port a broker listens on: write the broker's TCP port, \"port\": {}",
                if mqtt.tls.is_some() {
                    "8883 (the usual MQTT port with TLS)"
                } else {
                    "1883 (the usual MQTT port; 8883 with TLS)"
                }
            )),
        ));
    }
    errors
}

/// What is wrong with `host` as the broker's address, if anything. A host name or an IP address
/// has no `/`, and no single `:` (an IPv6 address has several).
fn broker_host_problem(host: &str, tls: bool) -> Option<String> {
    if host.trim().is_empty() {
        return Some(
            "the broker's host is empty: write its host name or IP address, e.g. \"host\": \
             \"localhost\""
                .into(),
        );
    }
    if let Some((scheme, rest)) = host.split_once("://") {
        let address = rest.split('/').next().unwrap_or_default();
        let (name, port) = split_port(address);
        let name = if name.is_empty() { "localhost" } else { name };
        let port_hint = port
            .map(|port| format!(" and \"port\": {port}"))
            .unwrap_or_default();
        let tls_scheme = matches!(
            scheme.to_ascii_lowercase().as_str(),
            "mqtts" | "ssl" | "tls" | "wss"
        );
        let tls_hint = match (tls_scheme && !tls, port) {
            (false, _) => "",
            (true, Some(_)) => {
                "; TLS is set apart: add \"tls\": {} to the `mqtt` section (with `ca_file` … \
                 as docs/mqtt.md says)"
            }
            (true, None) => {
                "; TLS is set apart: add \"tls\": {} to the `mqtt` section (with `ca_file` … \
                 as docs/mqtt.md says) and the broker's TLS port, usually \"port\": 8883"
            }
        };
        return Some(format!(
            "`{host}` is a URL, not a host: write the host name or IP address alone, \
             \"host\": \"{name}\"{port_hint}{tls_hint}"
        ));
    }
    if host.contains('/') {
        return Some(format!(
            "`{host}` is not a host name or IP address (no `/` in one): write e.g. \"host\": \
             \"localhost\" or \"192.168.1.10\""
        ));
    }
    if let (name, Some(port)) = split_port(host) {
        return Some(format!(
            "`{host}` has the port in it: write \"host\": \"{name}\" and \"port\": {port}"
        ));
    }
    if host.trim() != host || host.contains(char::is_whitespace) {
        return Some(format!(
            "`{host}` has spaces in it: write the host name or IP address alone, \
             \"host\": \"{}\"",
            host.trim()
        ));
    }
    // The resolver takes a bare IPv6 address, not the bracketed form of a URL.
    if let Some(inner) = host
        .strip_prefix('[')
        .and_then(|rest| rest.strip_suffix(']'))
    {
        return Some(format!(
            "`{host}`: write an IPv6 address without brackets, \"host\": \"{inner}\""
        ));
    }
    if host.matches(':').count() == 1 {
        return Some(format!(
            "`{host}` is not a host name or IP address (one `:` in it): write the host alone, \
             and the port in `port`"
        ));
    }
    None
}

/// `name:port` or `[v6]:port` as (name, port); an address without a port (an IPv6 one has
/// several `:`) as (address, None).
fn split_port(address: &str) -> (&str, Option<u16>) {
    if let Some(rest) = address.strip_prefix('[') {
        if let Some((name, tail)) = rest.split_once(']') {
            let port = tail.strip_prefix(':').and_then(|p| p.parse().ok());
            return (name, port);
        }
    }
    match address.split_once(':') {
        Some((name, port)) if !port.contains(':') => match port.parse() {
            Ok(port) => (name, Some(port)),
            Err(_) => (address, None),
        },
        _ => (address, None),
    }
}

/// An enabled serial port at a speed none of its devices is likely set to: a typo (9601, 96000)
/// would otherwise show only as devices that do not answer. Not refused: some devices do use
/// odd rates.
fn unusual_baud_rates(loaded: &LoadedConfig) -> Vec<LocatedError> {
    loaded
        .config
        .ports
        .iter()
        .enumerate()
        .filter(|(_, port)| port.enabled && port.port_type == PortType::Serial)
        .filter(|(_, port)| {
            (MIN_BAUD_RATE..=MAX_BAUD_RATE).contains(&port.baud_rate)
                && !is_usual_baud_rate(port.baud_rate)
        })
        .map(|(index, port)| {
            loaded.error(
                JsonPath::root().key("ports").index(index).key("baud_rate"),
                Problem::Warning(format!(
                    "baud_rate {} of port {} is not a usual serial speed ({}): a typo? Devices \
                     set to another speed do not answer. If they really use {}, leave it.",
                    port.baud_rate,
                    port.describe(),
                    usual_baud_rates_text(),
                    port.baud_rate
                )),
            )
        })
        .collect()
}

/// The status page may only be reachable from other machines behind a password.
fn check_http(loaded: &LoadedConfig) -> Vec<LocatedError> {
    let Some(http) = &loaded.config.http else {
        return Vec::new();
    };
    let at = JsonPath::root().key("http");
    http.problems()
        .into_iter()
        .map(|(key, message)| loaded.error(at.key(key), Problem::Invalid(message)))
        .collect()
}

/// The config's JSON Schema as a value (also what `rtu2mqtt schema config` prints).
pub fn config_schema() -> Value {
    serde_json::to_value(schemars::schema_for!(Config)).unwrap_or(Value::Null)
}

/// Checks that need only the config: required port keys, ranges, duplicate ports and
/// duplicate slave ids on one port.
fn check_ports(loaded: &LoadedConfig) -> Vec<LocatedError> {
    let mut errors = Vec::new();
    let mut seen_ports: BTreeMap<String, JsonPath> = BTreeMap::new();
    let ports_path = JsonPath::root().key("ports");
    for (port_index, port) in loaded.config.ports.iter().enumerate() {
        let at = ports_path.index(port_index);
        let mut invalid = |key: &str, message: String| {
            errors.push(loaded.error(at.key(key), Problem::Invalid(message)))
        };
        match port.port_type {
            PortType::Serial => {
                if port.path.as_deref().unwrap_or("").is_empty() {
                    invalid(
                        "path",
                        "a serial port needs `path`, e.g. \"/dev/ttyRS485-1\"".into(),
                    );
                }
                if !(5..=8).contains(&port.data_bits) {
                    invalid(
                        "data_bits",
                        format!("data_bits {} is not 5, 6, 7 or 8", port.data_bits),
                    );
                }
                if !(1..=2).contains(&port.stop_bits) {
                    invalid(
                        "stop_bits",
                        format!("stop_bits {} is not 1 or 2", port.stop_bits),
                    );
                }
                if !(MIN_BAUD_RATE..=MAX_BAUD_RATE).contains(&port.baud_rate) {
                    invalid(
                        "baud_rate",
                        format!(
                            "baud_rate {} is not a serial speed: the usual ones are {}",
                            port.baud_rate,
                            usual_baud_rates_text()
                        ),
                    );
                }
            }
            PortType::Tcp | PortType::ModbusTcp => {
                if port.address.as_deref().unwrap_or("").is_empty() {
                    invalid(
                        "address",
                        "a TCP port needs `address` (host name or IP of the gateway)".into(),
                    );
                }
                if port.port.is_none() {
                    invalid(
                        "port",
                        "a TCP port needs `port` (TCP port of the gateway, e.g. 502)".into(),
                    );
                }
            }
        }
        if !port.enabled {
            continue;
        }
        let description = port.describe();
        if let Some(other) = seen_ports.get(&description) {
            errors.push(loaded.error(
                at.clone(),
                Problem::DuplicatePort {
                    port: description.clone(),
                    other: other.to_string(),
                },
            ));
        } else {
            seen_ports.insert(description, at.clone());
        }
        for (key, value) in port_durations(port) {
            if let Some(problem) = duration_problem(key, value) {
                errors.push(loaded.error(at.key(key), problem));
            }
        }
        let mut slave_ids: BTreeMap<(i128, Option<i128>), JsonPath> = BTreeMap::new();
        for (device_index, device) in port.devices.iter().enumerate() {
            let device_at = at.key("devices").index(device_index);
            if device.enabled == Some(false) {
                continue;
            }
            for (key, value) in crate::config::device_durations!(device) {
                if let Some(problem) = duration_problem(key, value) {
                    errors.push(loaded.error(device_at.key(key), problem));
                }
            }
            let Some(slave_id) = device.slave_id else {
                errors.push(loaded.error(
                    device_at.key("slave_id"),
                    Problem::Invalid(
                        "a device needs `slave_id` (its Modbus address, 1…247)".into(),
                    ),
                ));
                continue;
            };
            if let Some(message) = slave_id_problem(slave_id, port.port_type) {
                errors.push(loaded.error(device_at.key("slave_id"), Problem::Invalid(message)));
                continue;
            }
            match slave_ids.get(&(slave_id.address, slave_id.module)) {
                Some(other) => errors.push(loaded.error(
                    device_at.key("slave_id"),
                    Problem::DuplicateSlaveId {
                        slave_id: slave_id.to_string(),
                        other: other.to_string(),
                    },
                )),
                None => {
                    slave_ids.insert((slave_id.address, slave_id.module), device_at);
                }
            }
        }
    }
    errors.extend(check_tls(loaded));
    errors
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(text: &str) -> Result<LoadedConfig, ErrorList> {
        load_config_source(SourceText::from_text(Path::new("c.json"), text), false)
    }

    #[test]
    fn defaults_and_comments() {
        let loaded =
            load("// site config\n{\"ports\": [{\"path\": \"/dev/ttyRS485-1\"}]}").unwrap();
        let config = loaded.config;
        assert_eq!(config.mqtt.host, "localhost");
        assert_eq!(config.mqtt.port, 1883);
        assert!(config.fast_modbus);
        assert_eq!(config.max_unchanged_interval, -1);
        assert_eq!(config.ports[0].baud_rate, 9600);
        assert_eq!(config.ports[0].stop_bits, 1);
    }

    #[test]
    fn duplicate_slave_id_on_a_port() {
        let text = r#"{"ports": [{"path": "/dev/x", "devices": [
            {"slave_id": 5, "device_type": "A"},
            {"slave_id": "0x05", "device_type": "B"}]}]}"#;
        let errors = load(text).unwrap_err().0;
        assert_eq!(errors.len(), 1);
        assert!(matches!(
            errors[0].problem,
            Problem::DuplicateSlaveId { .. }
        ));
        assert_eq!(errors[0].path.to_string(), "ports[0].devices[1].slave_id");
        assert_eq!(errors[0].line_column.map(|(l, _)| l), Some(3));
        assert!(
            errors[0].to_string().contains("ports[0].devices[0]"),
            "{}",
            errors[0]
        );
    }

    #[test]
    fn the_status_page_is_off_unless_configured_and_loopback_unless_password_protected() {
        assert_eq!(load("{}").unwrap().config.http, None);
        let http = load(r#"{"http": {}}"#).unwrap().config.http.unwrap();
        assert_eq!(http.listen, "127.0.0.1:8080");
        assert!(load(r#"{"http": {"listen": "[::1]:9000"}}"#).is_ok());
        let hash = "$2b$05$dCQ30UB4jly1BFDuIxBRAuNZQfUjMqCDKeE1BLR1sstX/KO5QMpFK";
        let open_to_all = load(r#"{"http": {"listen": "0.0.0.0:8080"}}"#)
            .unwrap_err()
            .0;
        assert_eq!(open_to_all.len(), 1);
        assert_eq!(open_to_all[0].path.to_string(), "http.listen");
        assert!(
            open_to_all[0].to_string().contains("password_hash"),
            "{}",
            open_to_all[0]
        );
        let guarded = format!(
            r#"{{"http": {{"listen": "0.0.0.0:8080", "user": "admin", "password_hash": "{hash}"}}}}"#
        );
        assert!(load(&guarded).is_ok());
        // A password in clear where its hash belongs, an address without a port.
        let plain = load(
            r#"{"http": {"listen": "127.0.0.1", "user": "admin", "password_hash": "s3cret"}}"#,
        )
        .unwrap_err()
        .0;
        let paths: Vec<String> = plain.iter().map(|e| e.path.to_string()).collect();
        assert_eq!(paths, ["http.listen", "http.password_hash"]);
        let no_user = load(&format!(r#"{{"http": {{"password_hash": "{hash}"}}}}"#)).unwrap_err();
        assert_eq!(no_user.0[0].path.to_string(), "http.password_hash");
    }

    #[test]
    fn same_slave_id_on_two_ports_is_fine() {
        let text = r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 5}]},
                                  {"path": "/dev/y", "devices": [{"slave_id": 5}]}]}"#;
        assert!(load(text).is_ok());
    }

    #[test]
    fn port_problems() {
        let text = r#"{"ports": [{"port_type": "tcp", "address": "10.0.0.2"},
                                  {"path": "/dev/x", "stop_bits": 3},
                                  {"path": "/dev/x"}]}"#;
        let errors = load(text).unwrap_err().0;
        let paths: Vec<String> = errors.iter().map(|e| e.path.to_string()).collect();
        assert_eq!(
            paths,
            vec!["ports[0].port", "ports[1].stop_bits", "ports[2]"]
        );
    }

    #[test]
    fn a_broker_host_is_a_name_or_an_address_alone() {
        for fine in [
            "localhost",
            "192.168.1.10",
            "broker.example.com",
            "::1",
            "fe80::1",
        ] {
            assert_eq!(broker_host_problem(fine, false), None, "{fine}");
        }
        let problem = |host: &str, tls: bool| broker_host_problem(host, tls).unwrap();
        let url = problem("mqtt://localhost", false);
        assert!(
            url.contains(r#""host": "localhost""#) && !url.contains("tls"),
            "{url}"
        );
        let with_port = problem("tcp://10.0.0.5:1884/", false);
        assert!(
            with_port.contains(r#""host": "10.0.0.5" and "port": 1884"#),
            "{with_port}"
        );
        let tls = problem("mqtts://broker.lan", false);
        assert!(
            tls.contains(r#"add "tls": {}"#) && tls.contains(r#""port": 8883"#),
            "{tls}"
        );
        // TLS already set: only the host is to fix.
        assert!(!problem("mqtts://broker.lan", true).contains("tls"));
        let v6 = problem("mqtt://[::1]:1883", false);
        assert!(v6.contains(r#""host": "::1" and "port": 1883"#), "{v6}");
        let glued = problem("localhost:1883", false);
        assert!(
            glued.contains(r#"write "host": "localhost" and "port": 1883"#),
            "{glued}"
        );
        assert!(problem("", false).contains("empty"));
        assert!(problem("broker/mqtt", false).contains("no `/`"));
        assert!(problem(" localhost", false).contains(
            r#"has spaces in it: write the host name or IP address alone, "host": "localhost""#
        ));
        assert!(problem("broker lan", false).contains("has spaces in it"));
        assert!(problem("[::1]", false).contains(r#"without brackets, "host": "::1""#));
    }

    #[test]
    fn unknown_port_type_lists_the_valid_ones() {
        let err = load(r#"{"ports": [{"port_type": "rtu"}]}"#)
            .unwrap_err()
            .0
            .remove(0);
        assert!(err.to_string().contains("serial, tcp, modbus tcp"), "{err}");
    }

    #[test]
    fn device_level_unknown_keys_are_kept_for_the_template_check() {
        let loaded =
            load(r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 1, "in1_mode": 2}]}]}"#)
                .unwrap();
        assert_eq!(
            loaded.device_extra_keys[0].to_string(),
            "ports[0].devices[0].in1_mode"
        );
    }
}
