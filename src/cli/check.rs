//! `rtu2mqtt check-config` and `rtu2mqtt check-templates`: validate files before a restart,
//! printing "ok" or each error with file, line:column and JSON path.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::config::error::Problem;
use crate::config::library::TemplateLibrary;
use crate::config::load::{load_config, LoadedConfig, DEFAULT_CONFIG_PATH};
use crate::config::values::parse_int_text;
use crate::config::{LocatedError, TemplateFile};
use crate::device::check_template;
use crate::device::configure::{resolve_config_checked, template_key_warnings};
use crate::device::model::{EventMode, RegisterRef, RegisterType, ResolvedDevice, ResolvedPort};
use crate::device::number_text::format_g;
use crate::gateway::port_plan::{fast_modbus_on, line_settings, response_lag};
use crate::protocol::timing::ADAPTER_LATENCY_ALLOWANCE;

#[derive(Debug, clap::Args)]
pub struct CheckConfigArgs {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// Treat warnings (misspelt keys, overrides the template does not allow, a device without
    /// channels, an unusual baud rate) as errors.
    #[arg(long)]
    pub strict: bool,
    /// Also take the `RTU2MQTT_*` settings of this file (KEY=value lines, `#` comments), as the
    /// service takes its secrets from /etc/rtu2mqtt/environment.
    #[arg(long = "env-file", value_name = "FILE")]
    pub env_file: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct CheckTemplatesArgs {
    /// Template files or directories (default: the template search path).
    pub paths: Vec<PathBuf>,
}

/// The config at `path`, or its errors printed (file, line:column, JSON path) and `None`.
pub fn load_or_print_errors(path: &Path) -> Option<LoadedConfig> {
    match load_config(path) {
        Ok(loaded) => Some(loaded),
        Err(errors) => {
            for error in &errors.0 {
                println!("{error}");
            }
            None
        }
    }
}

/// The `RTU2MQTT_*` assignments of a systemd environment file (`KEY=value` lines, `#` and `;`
/// comments, one pair of quotes around a value taken off); other variables are the service's
/// own business (`RUST_LOG`) and do not change the config.
fn service_settings(text: &str) -> Vec<(&str, &str)> {
    text.lines()
        .map(str::trim)
        .filter(|line| !line.is_empty() && !line.starts_with('#') && !line.starts_with(';'))
        .filter_map(|line| line.split_once('='))
        .map(|(name, value)| (name.trim(), unquoted(value.trim())))
        .filter(|(name, _)| name.starts_with(crate::config::load::ENV_PREFIX))
        .collect()
}

fn unquoted(value: &str) -> &str {
    for quote in ['"', '\''] {
        if let Some(inner) = value
            .strip_prefix(quote)
            .and_then(|rest| rest.strip_suffix(quote))
        {
            return inner;
        }
    }
    value
}

/// The enabled serial ports of `config` whose device file is not there.
fn missing_serial_ports(config: &crate::config::config_file::Config) -> Vec<&str> {
    config
        .serial_port_paths()
        .filter(|path| !Path::new(path).exists())
        .collect()
}

pub fn run_check_config(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    if let Some(path) = &args.env_file {
        let text = std::fs::read_to_string(path)
            .map_err(|err| anyhow::anyhow!("cannot read {}: {err}", path.display()))?;
        // Before anything else runs: this command has no other thread to see the change.
        for (name, value) in service_settings(&text) {
            std::env::set_var(name, value);
        }
    }
    let Some(loaded) = load_or_print_errors(&args.config) else {
        return Ok(ExitCode::FAILURE);
    };
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(args.templates.iter().cloned());
    let library = TemplateLibrary::load_standard(&dirs);
    let (result, warnings) = resolve_config_checked(&loaded, &library);
    for warning in &warnings {
        println!("{warning}");
    }
    if args.strict && !warnings.is_empty() && result.is_ok() {
        println!(
            "{}: {} warning(s), which --strict counts as errors",
            args.config.display(),
            warnings.len()
        );
        return Ok(ExitCode::FAILURE);
    }
    match result {
        Ok(ports) => {
            if (1..5).contains(&loaded.config.max_unchanged_interval) {
                println!(
                    "note: max_unchanged_interval {} is raised to 5 s, the shortest the service \
                     republishes unchanged values at",
                    loaded.config.max_unchanged_interval
                );
            }
            // Not a warning (`--strict` passes): a USB adapter may be plugged in later.
            for path in missing_serial_ports(&loaded.config) {
                println!(
                    "note: the serial port {path} does not exist on this machine (yet): a USB \
                     adapter not plugged in, or a typo? The service retries it until it appears."
                );
            }
            let devices: usize = ports.iter().map(|p| p.devices.len()).sum();
            let channels: usize = ports
                .iter()
                .flat_map(|p| &p.devices)
                .map(|d| d.channels.len())
                .sum();
            let count =
                |n: usize, what: &str| format!("{n} {what}{}", if n == 1 { "" } else { "s" });
            println!(
                "{}: ok ({}, {}, {}; {} in the library)",
                args.config.display(),
                count(ports.len(), "port"),
                count(devices, "device"),
                count(channels, "channel"),
                count(library.len(), "template")
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(errors) => {
            for error in &errors.0 {
                println!("{error}");
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

pub fn run_check_templates(args: CheckTemplatesArgs) -> anyhow::Result<ExitCode> {
    let paths = if args.paths.is_empty() {
        TemplateLibrary::standard_dirs(&[])
    } else {
        args.paths
    };
    let mut files = Vec::new();
    for path in &paths {
        if path.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(path)?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "json"))
                .collect();
            found.sort();
            files.extend(found);
        } else if path.exists() || !args_is_default(path) {
            files.push(path.clone());
        }
    }
    let mut failed = false;
    let mut other_protocols = 0;
    // device_type → the file last seen with it.
    let mut seen: std::collections::BTreeMap<String, PathBuf> = Default::default();
    for file in &files {
        let (template, errors) = check_file(file);
        if errors.is_empty() {
            println!("{}: ok", file.display());
        } else if let [error] = errors.as_slice() {
            if matches!(error.problem, Problem::UnsupportedProtocol { .. }) {
                // wb-mqtt-serial's library ships a few dozen of them: listed, but not a failure,
                // so that the exit status tells whether a Modbus template has an error.
                other_protocols += 1;
                println!("{error}");
            } else {
                failed = true;
                println!("{error}");
            }
        } else {
            failed = true;
            for error in errors {
                println!("{error}");
            }
        }
        let Some(template) = template else {
            continue;
        };
        let device_type = template.device_type().to_string();
        if let Some(first) = seen.insert(device_type.clone(), file.clone()) {
            println!(
                "{}: note: device_type `{device_type}` is also defined in {}; {} is used (the \
                 last loaded, as by wb-mqtt-serial: later directories, later names)",
                file.display(),
                first.display(),
                file.display()
            );
        }
    }
    if other_protocols > 0 {
        println!(
            "{other_protocols} template(s) of other protocols than Modbus were not checked (not \
             an error: rtu2mqtt cannot use them, their devices stay on wb-mqtt-serial)"
        );
    }
    if files.is_empty() {
        // Nothing checked is not a success: a wrong path must not look like a clean library.
        failed = true;
        println!(
            "no template files (*.json) found in {}",
            paths
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

fn args_is_default(path: &Path) -> bool {
    TemplateLibrary::standard_dirs(&[])
        .iter()
        .any(|d| d == path)
}

fn check_file(path: &Path) -> (Option<TemplateFile>, Vec<LocatedError>) {
    match TemplateFile::load(path) {
        Ok(template) => {
            // Warnings (misspelt keys, a channel left out as wb-mqtt-serial leaves it out) are
            // reported, but do not fail the check: upstream files carry some.
            let (warnings, errors): (Vec<LocatedError>, Vec<LocatedError>) =
                check_template(&template)
                    .into_iter()
                    .partition(|e| matches!(e.problem, Problem::Warning(_)));
            for warning in template_key_warnings(&template).iter().chain(&warnings) {
                println!("{warning}");
            }
            (Some(template), errors)
        }
        Err(error) => (None, vec![error]),
    }
}

#[derive(Debug, clap::Args)]
pub struct DescribeArgs {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// Only this device: its MQTT id, its name or its slave_id (16 or 0x10).
    pub device: Option<String>,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// `rtu2mqtt describe`: what rtu2mqtt resolved for each device — its channels with register,
/// format, scale, period and event mode, and its setup writes in the order they are written —
/// so a user sees what a template and their overrides really do.
pub fn run_describe(args: DescribeArgs) -> anyhow::Result<ExitCode> {
    let Some(loaded) = load_or_print_errors(&args.config) else {
        return Ok(ExitCode::FAILURE);
    };
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(args.templates.iter().cloned());
    let library = TemplateLibrary::load_standard(&dirs);
    let (result, warnings) = resolve_config_checked(&loaded, &library);
    for warning in &warnings {
        eprintln!("{warning}");
    }
    let ports = match result {
        Ok(ports) => ports,
        Err(errors) => {
            for error in &errors.0 {
                println!("{error}");
            }
            return Ok(ExitCode::FAILURE);
        }
    };
    let devices: Vec<(&ResolvedPort, &ResolvedDevice)> = ports
        .iter()
        .flat_map(|port| port.devices.iter().map(move |device| (port, device)))
        .filter(|(_, device)| {
            args.device.as_deref().is_none_or(|wanted| {
                device.id == wanted
                    || device.name == wanted
                    || device.slave_id.to_string() == wanted
                    // As the config may write it: "0x10", "016".
                    || parse_int_text(wanted) == Some(i128::from(device.slave_id))
            })
        })
        .collect();
    if devices.is_empty() {
        println!(
            "{}: no device {}; devices: {}",
            args.config.display(),
            args.device.as_deref().unwrap_or(""),
            ports
                .iter()
                .flat_map(|p| &p.devices)
                .map(|d| d.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
        return Ok(ExitCode::FAILURE);
    }
    if args.json {
        let json: Vec<serde_json::Value> = devices
            .iter()
            .map(|(port, device)| describe_json(port, device, loaded.config.fast_modbus))
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({ "devices": json }))?
        );
    } else {
        for (i, (port, device)) in devices.iter().enumerate() {
            if i > 0 {
                println!();
            }
            print!(
                "{}",
                describe_table(port, device, loaded.config.fast_modbus)
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn table_name(reg_type: RegisterType) -> &'static str {
    match reg_type {
        RegisterType::Coil => "coil",
        RegisterType::DiscreteInput => "discrete",
        RegisterType::Holding => "holding",
        RegisterType::Input => "input",
    }
}

fn events_name(events: EventMode) -> &'static str {
    match events {
        EventMode::Polled => "polled",
        EventMode::Sporadic => "sporadic",
        EventMode::SemiSporadic => "semi-sporadic",
    }
}

/// `holding 16` / `input 9..10` / `holding 55:4:1`.
fn register_text(register: &RegisterRef) -> String {
    let mut text = format!("{} {}", table_name(register.reg_type), register.address);
    if register.count > 1 && !register.reg_type.is_bit() {
        text.push_str(&format!("..{}", register.last_address()));
    }
    let whole = register.bit_shift == 0 && register.bit_width >= u32::from(register.count) * 16;
    if !register.reg_type.is_bit() && !whole {
        text.push_str(&format!(":{}:{}", register.bit_shift, register.bit_width));
    }
    text
}

/// The timeout the port task starts from (what the status page shows before the device's
/// response time is learned): the configured one, a TCP gateway's lag, the adapter allowance and
/// a character.
fn response_timeout_in_force_ms(port: &ResolvedPort, device: &ResolvedDevice) -> f64 {
    let floor = line_settings(&port.config)
        .response_timeout_floor(device.timing.response_timeout + response_lag(&port.config));
    (floor.as_secs_f64() * 10_000.0).round() / 10.0
}

fn port_text(port: &ResolvedPort) -> String {
    port.config.describe()
}

fn describe_table(port: &ResolvedPort, device: &ResolvedDevice, site_fast_modbus: bool) -> String {
    let mut out = format!(
        "{} \"{}\" (slave_id {}, template {}, {})\n",
        device.id,
        device.name,
        device.slave_id,
        device.device_type.as_deref().unwrap_or("none"),
        port_text(port)
    );
    if !fast_modbus_on(&port.config, site_fast_modbus) {
        out.push_str(
            "  Fast Modbus is off on this port: every channel is polled, sporadic and \
             semi-sporadic ones too (EVENTS shows the template's mode)\n",
        );
    }
    let lag = response_lag(&port.config);
    let gateway = if lag.is_zero() {
        String::new()
    } else {
        format!("the TCP gateway's {} ms, ", lag.as_millis())
    };
    out.push_str(&format!(
        "  response timeout: {} ms configured, {} ms in force ({gateway}the adapter allowance \
         of {} ms and one character are added, as wb-mqtt-serial does; a slow device's learned \
         response time may raise it)\n",
        device.timing.response_timeout.as_millis(),
        format_g(response_timeout_in_force_ms(port, device), 4),
        ADAPTER_LATENCY_ALLOWANCE.as_millis(),
    ));
    let mut rows = vec![[
        "CHANNEL".to_string(),
        "REGISTER".into(),
        "FORMAT".into(),
        "SCALE".into(),
        "PERIOD".into(),
        "EVENTS".into(),
        "ACCESS".into(),
    ]];
    for channel in &device.channels {
        for (i, register) in channel.registers.iter().enumerate() {
            let Some(place) = register.read.as_ref().or(register.write.as_ref()) else {
                continue;
            };
            let access = match (register.read.is_some(), register.write.is_some()) {
                (true, true) => "read/write",
                (true, false) => "read-only",
                (false, true) => "write-only",
                (false, false) => "-",
            };
            rows.push([
                if i == 0 {
                    channel.id.clone()
                } else {
                    format!("  + part {}", i + 1)
                },
                register_text(place),
                register.codec.format.name().to_string(),
                format_g(register.codec.scale, 6),
                match (channel.read_period, device.read_rate_limit(channel)) {
                    (Some(period), _) => format!("{} ms", period.as_millis()),
                    (None, Some(limit)) => format!(">= {} ms", limit.as_millis()),
                    (None, None) => "-".into(),
                },
                events_name(channel.events).into(),
                access.into(),
            ]);
        }
    }
    let widths: Vec<usize> = (0..7)
        .map(|c| rows.iter().map(|r| r[c].chars().count()).max().unwrap_or(0))
        .collect();
    for row in &rows {
        let line: Vec<String> = row
            .iter()
            .zip(&widths)
            .map(|(cell, width)| format!("{cell:<width$}"))
            .collect();
        out.push_str(&format!("  {}\n", line.join("  ").trim_end()));
    }
    if device.setup.is_empty() {
        out.push_str("  setup: none\n");
    } else {
        out.push_str("  setup (written in this order on connect):\n");
        for (i, write) in device.setup.iter().enumerate() {
            out.push_str(&format!(
                "  {:>3}. {} = {}  ({})\n",
                i + 1,
                register_text(&write.register),
                write.value,
                write.title
            ));
        }
    }
    out
}

fn register_json(register: &RegisterRef) -> serde_json::Value {
    serde_json::json!({
        "type": table_name(register.reg_type),
        "address": register.address,
        "count": register.count,
        "bit_shift": register.bit_shift,
        "bit_width": register.bit_width,
    })
}

fn describe_json(
    port: &ResolvedPort,
    device: &ResolvedDevice,
    site_fast_modbus: bool,
) -> serde_json::Value {
    let channels: Vec<serde_json::Value> = device
        .channels
        .iter()
        .map(|channel| {
            let registers: Vec<serde_json::Value> = channel
                .registers
                .iter()
                .map(|r| {
                    serde_json::json!({
                        "read": r.read.as_ref().map(register_json),
                        "write": r.write.as_ref().map(register_json),
                        "format": r.codec.format.name(),
                        "scale": r.codec.scale,
                        "offset": r.codec.offset,
                    })
                })
                .collect();
            serde_json::json!({
                "id": channel.id,
                "name": channel.name,
                "type": channel.control_type,
                "units": channel.units,
                "registers": registers,
                "read_period_ms": channel.read_period.map(|p| p.as_millis() as u64),
                "read_rate_limit_ms": device.read_rate_limit(channel).map(|l| l.as_millis() as u64),
                "events": events_name(channel.events),
                "readonly": channel.readonly,
                "write_only": channel.write_only,
            })
        })
        .collect();
    let setup: Vec<serde_json::Value> = device
        .setup
        .iter()
        .map(|write| {
            serde_json::json!({
                "title": write.title,
                "register": register_json(&write.register),
                "value": write.value,
                "words": write.words,
            })
        })
        .collect();
    serde_json::json!({
        "id": device.id,
        "name": device.name,
        "device_type": device.device_type,
        "slave_id": device.slave_id,
        "port": port_text(port),
        // Off: every channel is polled, whatever its `events`.
        "fast_modbus": fast_modbus_on(&port.config, site_fast_modbus),
        "response_timeout_ms": device.timing.response_timeout.as_millis() as u64,
        "response_timeout_in_force_ms": response_timeout_in_force_ms(port, device),
        "channels": channels,
        "setup": setup,
    })
}
