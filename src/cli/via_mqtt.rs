//! The site tools through the running service: when the port is busy (the service holds it) or
//! with `--via-mqtt`, `read`, `write` and `scan` send wb-mqtt-serial RPC requests to the
//! service over the broker instead of opening the port. See `docs/rpc.md`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use serde_json::{json, Value};

use crate::config::config_file::MqttConfig;
use crate::config::load::{load_config, DEFAULT_CONFIG_PATH};
use crate::protocol::{LineSettings, Parity};
use crate::rpc::client::{CallError, RpcSession};
use crate::rpc::message::RpcError;
use crate::tools::bus::Answer;
use crate::tools::exit;

/// How to reach the running service.
#[derive(clap::Args, Debug, Clone)]
pub struct ViaMqttArgs {
    /// Go through the running rtu2mqtt service (MQTT RPC) instead of opening the port. Done
    /// automatically when the port is busy and the broker is known.
    #[arg(long)]
    pub via_mqtt: bool,
    /// The service's config file: its `mqtt` section names the broker.
    #[arg(long = "service-config", value_name = "FILE", default_value = DEFAULT_CONFIG_PATH)]
    pub service_config: PathBuf,
    /// The broker (HOST or HOST:PORT), instead of the one in --service-config.
    #[arg(long, value_name = "HOST[:PORT]")]
    pub broker: Option<String>,
}

impl ViaMqttArgs {
    /// The broker settings: `--broker`, else the service's config file.
    pub fn broker_config(&self) -> Result<MqttConfig, String> {
        if let Some(broker) = &self.broker {
            let (host, port) = match broker.rsplit_once(':') {
                Some((host, port)) => (
                    host,
                    port.parse::<u16>()
                        .map_err(|_| format!("--broker {broker:?}: the port is not a number"))?,
                ),
                None => (broker.as_str(), 1883),
            };
            return Ok(MqttConfig {
                host: host.to_owned(),
                port,
                ..MqttConfig::default()
            });
        }
        load_config(&self.service_config)
            .map(|loaded| loaded.config.mqtt)
            .map_err(|errors| {
                format!(
                    "cannot read the broker settings from {} (give --broker HOST:PORT or \
                     --service-config FILE): {}",
                    self.service_config.display(),
                    errors
                        .0
                        .first()
                        .map(ToString::to_string)
                        .unwrap_or_default()
                )
            })
    }

    /// Whether a busy port should be reached through the service: the broker is known.
    pub fn can_reach_service(&self) -> bool {
        self.via_mqtt || self.broker.is_some() || self.service_config.exists()
    }
}

/// What a `port/Load` refusal says of the device, as the port would have said it: silence is
/// -32600, as wb-mqtt-serial answers it (a `total_timeout` that ran out is not), and an
/// unreadable reply is named so; anything else is the service's own trouble (None).
pub fn answer_of_refusal(refused: &RpcError) -> Option<Answer> {
    if refused.is_no_reply() {
        return Some(Answer::NoReply);
    }
    refused
        .message
        .contains("unreadable reply")
        .then_some(Answer::Garbled)
}

/// Why the service could not be asked, for the integrator; the exit code.
pub fn call_failure(err: &CallError) -> ExitCode {
    match err {
        CallError::Refused(_) => {
            eprintln!("{err}");
            ExitCode::from(exit::NOT_FOUND)
        }
        _ => {
            eprintln!("error: {err}");
            ExitCode::from(exit::PORT)
        }
    }
}

/// Connects to the service's broker; `Err` is the exit code (the reason printed).
pub async fn connect_service(args: &ViaMqttArgs) -> Result<RpcSession, ExitCode> {
    let broker = args.broker_config().map_err(|message| {
        eprintln!("{message}");
        ExitCode::from(exit::USAGE)
    })?;
    RpcSession::connect(&broker)
        .await
        .map_err(|err| call_failure(&err))
}

/// A call to the service, errors printed for the integrator; `Err` is the exit code.
pub async fn service_call(
    session: &mut RpcSession,
    service: &str,
    method: &str,
    params: Value,
    total_timeout: Duration,
) -> Result<Value, ExitCode> {
    session
        .call(service, method, params, total_timeout)
        .await
        .map_err(|err| call_failure(&err))
}

/// The settings the service runs `path` at (its `ports/Load` entry).
pub async fn served_line(session: &mut RpcSession, path: &str) -> Result<LineSettings, ExitCode> {
    let has_path = |ports: &Value| {
        ports
            .as_array()
            .is_some_and(|ports| ports.iter().any(|p| p["path"] == path))
    };
    // Each server on the broker lists its own ports: the one with this port is the answer.
    let ports = session
        .call_answered_by(
            "ports",
            "Load",
            json!({}),
            Duration::from_secs(5),
            |outcome| matches!(outcome, Ok(ports) if has_path(ports)),
        )
        .await
        .map_err(|err| call_failure(&err))?;
    let entry = ports
        .as_array()
        .and_then(|ports| ports.iter().find(|p| p["path"] == path));
    if entry.is_some() {
        session.port_is_served();
    }
    let Some(entry) = entry else {
        eprintln!(
            "the rtu2mqtt service does not serve {path} (it serves: {}): check the port name",
            ports
                .as_array()
                .map(|ports| ports
                    .iter()
                    .map(|p| p["path"].as_str().unwrap_or("(tcp)").to_owned())
                    .collect::<Vec<_>>()
                    .join(", "))
                .unwrap_or_default()
        );
        return Err(ExitCode::from(exit::NOT_FOUND));
    };
    let parity = match entry["parity"].as_str() {
        Some("E") => Parity::Even,
        Some("O") => Parity::Odd,
        _ => Parity::None,
    };
    let baud = entry["baud_rate"]
        .as_u64()
        .and_then(|b| u32::try_from(b).ok())
        .unwrap_or(9600);
    let stop_bits = entry["stop_bits"]
        .as_u64()
        .and_then(|b| u8::try_from(b).ok())
        .unwrap_or(1);
    Ok(LineSettings::new(baud, parity, stop_bits))
}

/// How long the service may take over `port/Scan` at `line`: a whole bus of devices, each
/// with its scan step and the reads of its details by serial number (some 300 characters of
/// wire time), within rpc.md's 600 s. A fixed 10 s failed a 40-device bus at 9600 (13.3 s), and
/// its partial results were lost with it (a site tools audit).
pub fn scan_total_timeout(line: &LineSettings) -> Duration {
    let per_device = line.wire_time(300);
    (Duration::from_secs(10) + per_device * u32::from(crate::protocol::frame::MAX_DEVICE_ADDRESS))
        .min(Duration::from_secs(600))
}

/// The params that put a request at `line`.
pub fn line_params(line: &LineSettings) -> Value {
    json!({
        "baud_rate": line.baud,
        "parity": line.parity.letter().to_string(),
        "data_bits": line.data_bits,
        "stop_bits": line.stop_bits,
    })
}

/// One setting scanned through the service (`port/Scan`, which also reads each device's
/// identity by serial number): the devices go into `report`, as the direct scan puts them;
/// returns (serial, address) of each device answering there.
pub async fn scan_setting_via_service(
    session: &mut RpcSession,
    path: &str,
    line: LineSettings,
    report: &mut crate::tools::report::ScanReport,
) -> Result<Vec<(u32, u8)>, crate::tools::bus::PortError> {
    use crate::tools::bus::PortError;
    use crate::tools::report::{Identity, SettingProblem};
    let mut params = line_params(&line);
    params["path"] = json!(path);
    let result = session
        .call("port", "Scan", params, scan_total_timeout(&line))
        .await
        .map_err(|err| PortError::Service(err.to_string()))?;
    if let Some(error) = result["error"].as_str() {
        report.problems.push(SettingProblem {
            line,
            what: error.to_owned(),
        });
    }
    let mut seen = Vec::new();
    for device in result["devices"].as_array().into_iter().flatten() {
        let serial = scanned_serial(device);
        let address = device["cfg"]["slave_id"]
            .as_u64()
            .and_then(|a| u8::try_from(a).ok());
        let (Some(serial), Some(address)) = (serial, address) else {
            continue;
        };
        seen.push((serial, address));
        if report.add_fast(line, serial, address) {
            if let Some(found) = report.devices.last_mut() {
                let text =
                    |value: &Value| value.as_str().filter(|t| !t.is_empty()).map(str::to_owned);
                found.identity = Identity {
                    model: text(&device["device_signature"]),
                    firmware: text(&device["fw"]["version"]),
                    signature: text(&device["fw_signature"]),
                };
                if let Some(settings) = reported_settings(&device["cfg"]) {
                    found.take_reported(settings);
                }
            }
        }
    }
    Ok(seen)
}

/// The serial number a `port/Scan` result names a device by in requests by serial number: its
/// `fast_modbus_sn` where the reported `sn` is not the whole number (a WB-MAP meter's lower 24
/// bits, as wb-mqtt-serial reports it), else `sn`.
pub fn scanned_serial(device: &Value) -> Option<u32> {
    device["fast_modbus_sn"]
        .as_str()
        .or_else(|| device["sn"].as_str())
        .and_then(|sn| sn.parse::<u32>().ok())
}

/// The port settings a device reported (`cfg` of a `port/Scan` result), when it read them.
fn reported_settings(cfg: &Value) -> Option<LineSettings> {
    let baud = cfg["baud_rate"].as_u64()?;
    let words = [
        u16::try_from(baud / 100).ok()?,
        match cfg["parity"].as_str()? {
            "N" => 0,
            "O" => 1,
            "E" => 2,
            _ => return None,
        },
        u16::try_from(cfg["stop_bits"].as_u64()?).ok()?,
    ];
    crate::tools::bus::reported_port_settings(&words)
}

/// Words from a `port/Load` hex response (bits as 0/1 for coils and discrete inputs).
pub fn response_words(response: &str, bits: bool, count: u16) -> Option<Vec<u16>> {
    let bytes = crate::protocol::parse_hex(response).ok()?;
    if bits {
        return Some(
            crate::protocol::pdu::unpack_bits(&bytes, usize::from(count))
                .into_iter()
                .map(u16::from)
                .collect(),
        );
    }
    if bytes.len() % 2 != 0 {
        return None;
    }
    Some(
        bytes
            .chunks_exact(2)
            .map(|pair| u16::from_be_bytes([pair[0], pair[1]]))
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scan through the service may take what a full bus takes at its speed: a 40-device bus
    /// at 9600 took 13.3 s against the 10 s it was given.
    #[test]
    fn a_scan_through_the_service_is_given_what_a_full_bus_takes() {
        use crate::protocol::Parity;
        let at = |baud| scan_total_timeout(&LineSettings::new(baud, Parity::None, 2));
        assert!(at(9600) > Duration::from_secs(80), "{:?}", at(9600));
        assert!(at(115_200) >= Duration::from_secs(15), "{:?}", at(115_200));
        assert_eq!(at(1200), Duration::from_secs(600), "rpc.md's limit");
    }

    #[test]
    fn broker_option_and_hex_responses() {
        let args = ViaMqttArgs {
            via_mqtt: true,
            service_config: PathBuf::from("/nonexistent"),
            broker: Some("10.0.0.2:1884".into()),
        };
        let broker = args.broker_config().unwrap();
        assert_eq!((broker.host.as_str(), broker.port), ("10.0.0.2", 1884));
        let args = ViaMqttArgs {
            broker: None,
            ..args
        };
        assert!(args.broker_config().unwrap_err().contains("--broker"));
        assert_eq!(
            response_words("0866abcd", false, 2),
            Some(vec![0x0866, 0xABCD])
        );
        assert_eq!(response_words("05", true, 3), Some(vec![1, 0, 1]));
        assert_eq!(response_words("086", false, 1), None);
    }
}
