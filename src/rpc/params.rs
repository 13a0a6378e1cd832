//! The params of each method, read and checked before anything touches a bus. Field names and
//! meanings are wb-mqtt-serial's; every refusal says which field is wrong and why. Pure.

use std::time::Duration;

use serde_json::{Map, Value};

use super::message::RpcError;
use crate::protocol::{LineSettings, Parity, RequestPdu};

/// `total_timeout` when the request gives none (wb-mqtt-serial's default).
pub const DEFAULT_TOTAL_TIMEOUT: Duration = Duration::from_secs(10);
/// `response_timeout` of `port/Load` when the request gives none.
pub const DEFAULT_RESPONSE_TIMEOUT: Duration = Duration::from_millis(500);
/// The longest `total_timeout` taken: an RPC holds a slot of the server while it runs.
pub const MAX_TOTAL_TIMEOUT: Duration = Duration::from_secs(600);

/// The methods served, and those known but not served (their requests get a clear error).
pub const SERVED: &[(&str, &str)] = &[
    ("ports", "Load"),
    ("port", "Load"),
    ("port", "Scan"),
    ("device", "Probe"),
    ("port", "Setup"),
    ("device", "LoadConfig"),
    ("port", "EventLog"),
    ("device", "Load"),
    ("device", "Set"),
    ("device", "SetPoll"),
    ("config", "Load"),
];
pub const NOT_SERVED: &[(&str, &str)] = &[
    ("config", "GetSchema"),
    ("templates", "Upload"),
    ("templates", "Delete"),
    ("fw-update", "GetFirmwareInfo"),
    ("fw-update", "Update"),
    ("fw-update", "ClearError"),
    ("fw-update", "Restore"),
    ("metrics", "Load"),
];

/// Which configured port a request means: `path` (serial), `ip` + `port` (TCP), or the port of
/// a configured `device_id`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PortSelector {
    Path(String),
    Tcp { ip: String, port: u16 },
    Device(String),
}

/// Serial settings a request asks for; what it leaves out stays as the port has it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LineOverride {
    pub baud_rate: Option<u32>,
    pub parity: Option<Parity>,
    pub data_bits: Option<u8>,
    pub stop_bits: Option<u8>,
}

impl LineOverride {
    pub fn apply(&self, home: LineSettings) -> LineSettings {
        LineSettings {
            baud: self.baud_rate.unwrap_or(home.baud),
            parity: self.parity.unwrap_or(home.parity),
            data_bits: self.data_bits.unwrap_or(home.data_bits),
            stop_bits: self.stop_bits.unwrap_or(home.stop_bits),
        }
    }
}

/// How `msg` and `response` are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MessageFormat {
    /// Two lowercase hex digits per byte.
    Hex,
    /// The bytes as they are (wb-mqtt-serial's default).
    Str,
}

/// `port/Load` with `protocol` `modbus` or `modbus-tcp`: one Modbus request.
#[derive(Debug, Clone, PartialEq)]
pub struct PortLoad {
    pub port: PortSelector,
    pub line: LineOverride,
    /// The device's address (a `device_id` selector supplies it when the request does not).
    pub slave_id: Option<u8>,
    /// rtu2mqtt extension: address the device by serial number (Fast Modbus 0x46 0x08).
    pub serial: Option<u32>,
    pub pdu: RequestPdu,
    pub format: MessageFormat,
    pub response_timeout: Duration,
    pub total_timeout: Duration,
}

/// `port/Load` without `protocol`: bytes out as they are, and what comes back.
#[derive(Debug, Clone, PartialEq)]
pub struct PortLoadRaw {
    pub port: PortSelector,
    pub line: LineOverride,
    pub message: Vec<u8>,
    pub format: MessageFormat,
    /// Bytes to wait for at most.
    pub response_size: usize,
    pub response_timeout: Duration,
    pub frame_timeout: Duration,
    pub total_timeout: Duration,
}

/// Silence after a byte that ends a raw answer when the request does not say (wb-mqtt-serial's
/// default frame timeout).
pub const DEFAULT_RAW_FRAME_TIMEOUT: Duration = Duration::from_millis(20);
/// The longest raw answer taken (a whole frame of any protocol on a serial bus fits).
pub const MAX_RAW_RESPONSE: u64 = 4096;

/// `port/Scan`'s modes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanMode {
    /// Start, then continue until the end of the scan.
    All,
    /// Only the scan start: the first device.
    Start,
    /// One continue: the next device.
    Next,
}

#[derive(Debug, Clone, PartialEq)]
pub struct PortScan {
    pub port: PortSelector,
    pub line: LineOverride,
    pub mode: ScanMode,
    /// The Fast Modbus function code of the scan and its requests by serial number: 0x46, or
    /// 0x60 (`"command": 96`, the deprecated one wb-device-manager sends for every scan).
    pub command: u8,
    pub total_timeout: Duration,
}

#[derive(Debug, Clone, PartialEq)]
pub struct DeviceProbe {
    pub port: PortSelector,
    pub line: LineOverride,
    pub slave_id: u8,
    pub total_timeout: Duration,
}

/// New port settings and address of one Wiren Board device (`port/Setup`'s `cfg`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DeviceSettings {
    pub slave_id: Option<u8>,
    /// In bit/s (the register holds it / 100).
    pub baud_rate: Option<u32>,
    pub parity: Option<Parity>,
    pub stop_bits: Option<u8>,
}

/// One device of `port/Setup`: where it is now (address or serial number, port settings) and
/// what to set.
#[derive(Debug, Clone, PartialEq)]
pub struct SetupItem {
    pub slave_id: u8,
    pub serial: Option<u32>,
    pub line: LineOverride,
    pub cfg: DeviceSettings,
}

#[derive(Debug, Clone, PartialEq)]
pub struct PortSetup {
    pub port: PortSelector,
    pub items: Vec<SetupItem>,
    pub total_timeout: Duration,
}

/// `device/Load`: channels (by template name) of a configured device, read and decoded as the
/// daemon decodes them.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceLoad {
    pub port: PortSelector,
    /// The device's address when the port is named by `path`/`ip` (not by `device_id`).
    pub slave_id: Option<u8>,
    /// The template the caller means (homeui always sends it): refused unless it is the
    /// configured device's.
    pub device_type: Option<String>,
    pub channels: Vec<String>,
    pub parameters: Vec<String>,
    pub total_timeout: Duration,
}

/// `device/Set`: values to write to channels (by template name) of a configured device, each
/// as its `/on` payload.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceSet {
    pub port: PortSelector,
    pub slave_id: Option<u8>,
    pub device_type: Option<String>,
    pub channels: Vec<(String, String)>,
    pub parameters: Vec<(String, String)>,
    pub total_timeout: Duration,
}

/// How long `device/SetPoll` with `poll` false holds a device's polling (wb-mqtt-serial's 10
/// minutes; asking again holds it 10 minutes from then).
pub const POLL_HOLD: Duration = Duration::from_secs(600);

/// `device/SetPoll`: hold (for [`POLL_HOLD`]) or resume the polling of a configured device,
/// named by `device_id` or by its port and `slave_id`.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceSetPoll {
    pub port: PortSelector,
    pub slave_id: Option<u8>,
    pub poll: bool,
}

/// `device/LoadConfig`: a configured device's parameters, and its model and firmware.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceLoadConfig {
    pub port: PortSelector,
    pub slave_id: Option<u8>,
    pub device_type: Option<String>,
    pub total_timeout: Duration,
}

/// `port/EventLog` (rtu2mqtt's own): the port's Fast Modbus event packets as they came.
#[derive(Debug, Clone, PartialEq)]
pub struct PortEventLog {
    pub port: PortSelector,
    /// The first packet wanted (`next` of the previous reply); none: only those to come.
    pub from: Option<u64>,
    /// The log `from` counts in (`log` of the previous reply): a restarted port has another.
    pub log: Option<u64>,
    /// How long to wait for a packet when there is none yet.
    pub wait: Duration,
    pub total_timeout: Duration,
}

/// `port/EventLog`'s wait when the request gives none.
pub const DEFAULT_EVENT_LOG_WAIT: Duration = Duration::from_secs(1);
/// What of `total_timeout` a `port/EventLog` wait leaves for the reply to go out.
const EVENT_LOG_REPLY_ROOM: Duration = Duration::from_millis(500);

/// A request, read.
#[derive(Debug, Clone, PartialEq)]
pub enum Method {
    PortsLoad,
    PortLoad(PortLoad),
    PortLoadRaw(PortLoadRaw),
    PortScan(PortScan),
    DeviceProbe(DeviceProbe),
    PortSetup(PortSetup),
    DeviceLoad(DeviceLoad),
    DeviceSet(DeviceSet),
    DeviceSetPoll(DeviceSetPoll),
    DeviceLoadConfig(DeviceLoadConfig),
    PortEventLog(PortEventLog),
    /// `config/Load` in `lang` (titles and group names).
    ConfigLoad {
        lang: String,
    },
}

impl Method {
    /// The time the request may take at most, reply included.
    pub fn total_timeout(&self) -> Duration {
        match self {
            Self::PortsLoad => DEFAULT_TOTAL_TIMEOUT,
            Self::PortLoad(p) => p.total_timeout,
            Self::PortLoadRaw(p) => p.total_timeout,
            Self::PortScan(p) => p.total_timeout,
            Self::DeviceProbe(p) => p.total_timeout,
            Self::PortSetup(p) => p.total_timeout,
            Self::DeviceLoad(p) => p.total_timeout,
            Self::DeviceSet(p) => p.total_timeout,
            Self::DeviceSetPoll(_) => DEFAULT_TOTAL_TIMEOUT,
            Self::DeviceLoadConfig(p) => p.total_timeout,
            Self::PortEventLog(p) => p.total_timeout,
            Self::ConfigLoad { .. } => DEFAULT_TOTAL_TIMEOUT,
        }
    }
}

/// Reads the params of `service/method`.
pub fn parse_method(service: &str, method: &str, params: &Value) -> Result<Method, RpcError> {
    let empty = Map::new();
    let fields = params.as_object().unwrap_or(&empty);
    match (service, method) {
        ("ports", "Load") => Ok(Method::PortsLoad),
        ("config", "Load") => Ok(Method::ConfigLoad {
            lang: language(fields)?,
        }),
        // A configured device named by `device_id` is asked in its own protocol, whatever
        // `protocol` says (wb-mqtt-serial's `PortLoad`): wb-mqtt-dali writes to its WB-MDALI
        // gateways with `device_id`, `function` and `msg`, and no `protocol`.
        ("port", "Load") if names_a_device(fields) => {
            parse_port_load(fields, true).map(Method::PortLoad)
        }
        ("port", "Load") => match optional_str(fields, "protocol")? {
            None => parse_port_load_raw(fields).map(Method::PortLoadRaw),
            Some(_) => parse_port_load(fields, false).map(Method::PortLoad),
        },
        ("port", "Scan") => Ok(Method::PortScan(PortScan {
            port: port_selector(fields)?,
            line: line_override(fields)?,
            mode: match optional_str(fields, "mode")? {
                None | Some("all") => ScanMode::All,
                Some("start") => ScanMode::Start,
                Some("next") => ScanMode::Next,
                Some(other) => {
                    return Err(bad("mode", format!("{other:?}: use all, start or next")))
                }
            },
            command: match optional_uint(fields, "command")? {
                None | Some(0x46) => crate::protocol::fast::FUNCTION,
                Some(0x60) => crate::protocol::fast::LEGACY_FUNCTION,
                Some(other) => {
                    return Err(bad(
                        "command",
                        format!("{other}: use 70 (0x46) or 96 (0x60, the deprecated one)"),
                    ))
                }
            },
            total_timeout: total_timeout(fields)?,
        })),
        ("device", "Probe") => Ok(Method::DeviceProbe(DeviceProbe {
            port: port_selector(fields)?,
            line: line_override(fields)?,
            slave_id: slave_id(fields)?.ok_or_else(|| bad("slave_id", "missing"))?,
            total_timeout: total_timeout(fields)?,
        })),
        ("port", "Setup") => Ok(Method::PortSetup(PortSetup {
            port: port_selector(fields)?,
            items: setup_items(fields)?,
            total_timeout: total_timeout(fields)?,
        })),
        ("device", "Load") => Ok(Method::DeviceLoad(DeviceLoad {
            port: port_selector(fields)?,
            slave_id: slave_id(fields)?,
            device_type: optional_str(fields, "device_type")?.map(str::to_owned),
            channels: name_list(fields, "channels")?,
            parameters: name_list(fields, "parameters")?,
            total_timeout: total_timeout(fields)?,
        })),
        ("device", "Set") => Ok(Method::DeviceSet(DeviceSet {
            port: port_selector(fields)?,
            slave_id: slave_id(fields)?,
            device_type: optional_str(fields, "device_type")?.map(str::to_owned),
            channels: value_map(fields, "channels")?,
            parameters: value_map(fields, "parameters")?,
            total_timeout: total_timeout(fields)?,
        })),
        ("device", "SetPoll") => {
            let port = port_selector(fields)?;
            let slave_id = slave_id(fields)?;
            if slave_id.is_none() && !matches!(port, PortSelector::Device(_)) {
                return Err(bad("slave_id", "missing (or give \"device_id\")"));
            }
            let poll = match fields.get("poll") {
                Some(Value::Bool(poll)) => *poll,
                Some(other) => return Err(bad("poll", format!("{other}: use true or false"))),
                None => return Err(bad("poll", "missing: true resumes polling, false holds it")),
            };
            Ok(Method::DeviceSetPoll(DeviceSetPoll {
                port,
                slave_id,
                poll,
            }))
        }
        ("device", "LoadConfig") => Ok(Method::DeviceLoadConfig(DeviceLoadConfig {
            port: port_selector(fields)?,
            slave_id: slave_id(fields)?,
            device_type: optional_str(fields, "device_type")?.map(str::to_owned),
            total_timeout: total_timeout(fields)?,
        })),
        ("port", "EventLog") => {
            let total_timeout = total_timeout(fields)?;
            let wait = optional_millis(fields, "wait_ms")?.unwrap_or(DEFAULT_EVENT_LOG_WAIT);
            Ok(Method::PortEventLog(PortEventLog {
                port: port_selector(fields)?,
                from: optional_uint(fields, "from")?,
                log: optional_uint(fields, "log")?,
                // The reply must leave before the caller stops waiting for it.
                wait: wait.min(total_timeout.saturating_sub(EVENT_LOG_REPLY_ROOM)),
                total_timeout,
            }))
        }
        _ if NOT_SERVED.contains(&(service, method)) => Err(RpcError::server(format!(
            "{service}/{method} is not served by rtu2mqtt yet; served: {}",
            served_list()
        ))),
        _ => Err(RpcError::server(format!(
            "unknown method {service}/{method}; served: {}",
            served_list()
        ))),
    }
}

/// `device/Load`'s `channels`/`parameters`: a list of names (duplicates read once).
fn name_list(fields: &Map<String, Value>, name: &str) -> Result<Vec<String>, RpcError> {
    let Some(value) = fields.get(name) else {
        return Ok(Vec::new());
    };
    let items = value
        .as_array()
        .ok_or_else(|| bad(name, "not a list of names"))?;
    let mut names: Vec<String> = Vec::new();
    for item in items {
        let text = item
            .as_str()
            .filter(|t| !t.is_empty())
            .ok_or_else(|| bad(name, format!("{item} is not a name")))?;
        if !names.iter().any(|n| n == text) {
            names.push(text.to_owned());
        }
    }
    Ok(names)
}

/// `device/Set`'s `channels`/`parameters`: an object of name → value (number, string or
/// boolean; wb-mqtt-serial takes each value as its text).
fn value_map(fields: &Map<String, Value>, name: &str) -> Result<Vec<(String, String)>, RpcError> {
    let Some(value) = fields.get(name) else {
        return Ok(Vec::new());
    };
    let items = value
        .as_object()
        .ok_or_else(|| bad(name, "not an object of name: value"))?;
    items
        .iter()
        .map(|(key, value)| {
            let text = match value {
                Value::String(text) => text.clone(),
                Value::Number(number) => number.to_string(),
                Value::Bool(flag) => u8::from(*flag).to_string(),
                other => return Err(bad(name, format!("{key:?}: {other} is no value"))),
            };
            Ok((key.clone(), text))
        })
        .collect()
}

/// The baud rates `port/Setup` writes (wb-mqtt-serial-rpc-port-setup-request.schema.json's
/// `cfg.baud_rate` enum).
pub const SETUP_BAUD_RATES: [u32; 12] = [
    110, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115_200, 230_400,
];

fn setup_items(fields: &Map<String, Value>) -> Result<Vec<SetupItem>, RpcError> {
    let Some(Value::Array(items)) = fields.get("items") else {
        return Err(bad("items", "missing: a list of {slave_id, sn?, cfg: {…}}"));
    };
    items
        .iter()
        .map(|item| {
            let item = item
                .as_object()
                .ok_or_else(|| bad("items", "each item is an object"))?;
            let cfg = match item.get("cfg") {
                None | Some(Value::Null) => Map::new(),
                Some(Value::Object(cfg)) => cfg.clone(),
                Some(_) => return Err(bad("cfg", "an object")),
            };
            let mut cfg_line = cfg.clone();
            if cfg.get("parity").is_some_and(Value::is_number) {
                cfg_line.remove("parity");
            }
            let settings = line_override(&cfg_line)?;
            if let Some(baud) = settings.baud_rate {
                // Holding 110 takes baud / 100: only rates a device can be set to, as
                // wb-mqtt-serial's schema lists them (checked before anything is written).
                if !SETUP_BAUD_RATES.contains(&baud) {
                    return Err(bad(
                        "cfg.baud_rate",
                        format!(
                            "{baud}: a device can be set to {}",
                            SETUP_BAUD_RATES.map(|b| b.to_string()).join(", ")
                        ),
                    ));
                }
            }
            let cfg_parity = match cfg.get("parity") {
                // The register's own numbers are taken too: 0 N, 1 O, 2 E.
                Some(Value::Number(n)) => match n.as_u64() {
                    Some(0) => Some(Parity::None),
                    Some(1) => Some(Parity::Odd),
                    Some(2) => Some(Parity::Even),
                    _ => return Err(bad("parity", format!("{n}: use N, E, O (or 0, 2, 1)"))),
                },
                _ => settings.parity,
            };
            let serial = match optional_uint(item, "sn")? {
                None => None,
                Some(sn) => Some(u32::try_from(sn).map_err(|_| bad("sn", "above 4294967295"))?),
            };
            Ok(SetupItem {
                slave_id: slave_id(item)?.ok_or_else(|| bad("slave_id", "missing"))?,
                serial,
                line: line_override(item)?,
                cfg: DeviceSettings {
                    slave_id: slave_id(&cfg)?,
                    baud_rate: settings.baud_rate,
                    parity: cfg_parity,
                    stop_bits: settings.stop_bits,
                },
            })
        })
        .collect()
}

fn served_list() -> String {
    SERVED
        .iter()
        .map(|(s, m)| format!("{s}/{m}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn bad(field: &str, why: impl std::fmt::Display) -> RpcError {
    RpcError::server(format!("bad \"{field}\": {why}"))
}

/// `format` and `msg`, as wb-mqtt-serial reads them (`HEX`: two hex digits per byte; anything
/// else: the string's bytes).
fn message(fields: &Map<String, Value>) -> Result<(MessageFormat, Vec<u8>), RpcError> {
    let format = match optional_str(fields, "format")? {
        Some("HEX") => MessageFormat::Hex,
        _ => MessageFormat::Str,
    };
    let message = match optional_str(fields, "msg")? {
        None => Vec::new(),
        Some(text) => match format {
            MessageFormat::Str => text.as_bytes().to_vec(),
            MessageFormat::Hex => parse_hex_message(text)?,
        },
    };
    Ok((format, message))
}

fn parse_port_load_raw(fields: &Map<String, Value>) -> Result<PortLoadRaw, RpcError> {
    let (format, message) = message(fields)?;
    if message.is_empty() {
        return Err(bad("msg", "missing or empty: the bytes to send"));
    }
    let response_size = optional_uint(fields, "response_size")?.ok_or_else(|| {
        bad(
            "response_size",
            "missing: how many bytes to wait for at most",
        )
    })?;
    if response_size > MAX_RAW_RESPONSE {
        return Err(bad(
            "response_size",
            format!("{response_size} is above {MAX_RAW_RESPONSE}"),
        ));
    }
    Ok(PortLoadRaw {
        port: port_selector(fields)?,
        line: line_override(fields)?,
        message,
        format,
        response_size: usize::try_from(response_size).unwrap_or(0),
        response_timeout: optional_millis(fields, "response_timeout")?
            .unwrap_or(DEFAULT_RESPONSE_TIMEOUT),
        frame_timeout: optional_millis(fields, "frame_timeout")?
            .unwrap_or(DEFAULT_RAW_FRAME_TIMEOUT),
        total_timeout: total_timeout(fields)?,
    })
}

/// `device_id` names the port (it comes before `path` and `ip`: see [`port_selector`]).
fn names_a_device(fields: &Map<String, Value>) -> bool {
    matches!(port_selector(fields), Ok(PortSelector::Device(_)))
}

/// The Modbus form of `port/Load`; `by_device`: the port is named by a configured device,
/// whose own protocol (Modbus, every device rtu2mqtt drives) is used whatever `protocol` says.
fn parse_port_load(fields: &Map<String, Value>, by_device: bool) -> Result<PortLoad, RpcError> {
    match optional_str(fields, "protocol")? {
        _ if by_device => {}
        Some("modbus" | "modbus-tcp") => {}
        None => {
            return Err(bad("protocol", "missing"));
        }
        Some(other) => {
            return Err(bad(
                "protocol",
                format!("{other:?}: use \"modbus\" or \"modbus-tcp\""),
            ))
        }
    }
    let (format, message) = message(fields)?;
    let function = optional_uint(fields, "function")?.ok_or_else(|| bad("function", "missing"))?;
    let address = optional_uint(fields, "address")?.unwrap_or(0);
    let address = u16::try_from(address).map_err(|_| bad("address", "above 65535"))?;
    let count = optional_uint(fields, "count")?.unwrap_or(1);
    let count = u16::try_from(count).map_err(|_| bad("count", "above 65535"))?;
    let pdu = modbus_pdu(function, address, count, &message)?;
    let serial = match optional_uint(fields, "sn")? {
        None => None,
        Some(sn) => Some(u32::try_from(sn).map_err(|_| bad("sn", "above 4294967295"))?),
    };
    let slave_id = slave_id(fields)?;
    let port = port_selector(fields)?;
    if slave_id.is_none() && serial.is_none() && !matches!(port, PortSelector::Device(_)) {
        return Err(bad("slave_id", "missing (or give \"sn\" or \"device_id\")"));
    }
    Ok(PortLoad {
        port,
        line: line_override(fields)?,
        slave_id,
        serial,
        pdu,
        format,
        response_timeout: optional_millis(fields, "response_timeout")?
            .unwrap_or(DEFAULT_RESPONSE_TIMEOUT),
        total_timeout: total_timeout(fields)?,
    })
}

/// The request PDU of a Modbus function, its data taken from `msg` (wb-mqtt-serial's layout:
/// 5: `ff00`/`0000`; 6: one word; 15: coils packed LSB first; 16: `count` words).
pub fn modbus_pdu(
    function: u64,
    address: u16,
    count: u16,
    message: &[u8],
) -> Result<RequestPdu, RpcError> {
    let check_count = |max: u16| {
        if count == 0 || count > max {
            Err(bad(
                "count",
                format!("{count}: function {function} takes 1..{max}"),
            ))
        } else {
            Ok(())
        }
    };
    let words = |message: &[u8]| -> Vec<u16> {
        message
            .chunks_exact(2)
            .map(|pair| u16::from_be_bytes([pair[0], pair[1]]))
            .collect()
    };
    Ok(match function {
        1 | 2 => {
            check_count(2000)?;
            if function == 1 {
                RequestPdu::ReadCoils {
                    start: address,
                    count,
                }
            } else {
                RequestPdu::ReadDiscreteInputs {
                    start: address,
                    count,
                }
            }
        }
        3 | 4 => {
            check_count(125)?;
            if function == 3 {
                RequestPdu::ReadHoldingRegisters {
                    start: address,
                    count,
                }
            } else {
                RequestPdu::ReadInputRegisters {
                    start: address,
                    count,
                }
            }
        }
        5 => match message {
            [0xFF, 0x00] => RequestPdu::WriteSingleCoil {
                address,
                value: true,
            },
            [0x00, 0x00] => RequestPdu::WriteSingleCoil {
                address,
                value: false,
            },
            _ => return Err(bad("msg", "function 5 writes ff00 (on) or 0000 (off)")),
        },
        6 => match message {
            [high, low] => RequestPdu::WriteSingleRegister {
                address,
                value: u16::from_be_bytes([*high, *low]),
            },
            _ => return Err(bad("msg", "function 6 writes one word: 4 hex digits")),
        },
        15 => {
            check_count(1968)?;
            let needed = usize::from(count).div_ceil(8);
            if message.len() != needed {
                return Err(bad(
                    "msg",
                    format!("{count} coils take {needed} byte(s), packed LSB first"),
                ));
            }
            RequestPdu::WriteMultipleCoils {
                start: address,
                values: (0..usize::from(count))
                    .map(|i| message.get(i / 8).is_some_and(|b| b & (1 << (i % 8)) != 0))
                    .collect(),
            }
        }
        16 => {
            check_count(123)?;
            if message.len() != usize::from(count) * 2 {
                return Err(bad(
                    "msg",
                    format!(
                        "{count} register(s) take {} hex digits",
                        usize::from(count) * 4
                    ),
                ));
            }
            RequestPdu::WriteMultipleRegisters {
                start: address,
                values: words(message),
            }
        }
        other => {
            return Err(bad(
                "function",
                format!("{other}: supported are 1, 2, 3, 4, 5, 6, 15, 16"),
            ))
        }
    })
}

fn parse_hex_message(text: &str) -> Result<Vec<u8>, RpcError> {
    let text: String = text.chars().filter(|c| !c.is_whitespace()).collect();
    if text.len() % 2 != 0 {
        return Err(bad("msg", "hex message has an odd number of digits"));
    }
    (0..text.len())
        .step_by(2)
        .map(|i| {
            text.get(i..i + 2)
                .and_then(|pair| u8::from_str_radix(pair, 16).ok())
                .ok_or_else(|| bad("msg", format!("{text:?} is not hex")))
        })
        .collect()
}

/// `device_id` first, as wb-mqtt-serial looks the device up before the port.
fn port_selector(fields: &Map<String, Value>) -> Result<PortSelector, RpcError> {
    if let Some(device) = optional_str(fields, "device_id")? {
        return Ok(PortSelector::Device(device.to_owned()));
    }
    if let Some(path) = optional_str(fields, "path")? {
        return Ok(PortSelector::Path(path.to_owned()));
    }
    if let Some(ip) = optional_str(fields, "ip")? {
        let port = optional_uint(fields, "port")?.ok_or_else(|| bad("port", "missing"))?;
        let port = u16::try_from(port).map_err(|_| bad("port", "above 65535"))?;
        return Ok(PortSelector::Tcp {
            ip: ip.to_owned(),
            port,
        });
    }
    Err(RpcError::server(
        "Port is not defined: give \"path\" (serial), \"ip\" and \"port\" (TCP), or \"device_id\"",
    ))
}

fn line_override(fields: &Map<String, Value>) -> Result<LineOverride, RpcError> {
    let baud_rate = match optional_uint(fields, "baud_rate")? {
        None => None,
        Some(baud @ 110..=1_000_000) => Some(u32::try_from(baud).unwrap_or(9600)),
        Some(other) => return Err(bad("baud_rate", format!("{other}: use 1200..115200"))),
    };
    let parity = match optional_str(fields, "parity")? {
        None => None,
        Some(text) => Some(match text.chars().next() {
            Some('N' | 'n') => Parity::None,
            Some('E' | 'e') => Parity::Even,
            Some('O' | 'o') => Parity::Odd,
            _ => return Err(bad("parity", format!("{text:?}: use N, E or O"))),
        }),
    };
    let data_bits = match optional_uint(fields, "data_bits")? {
        None => None,
        Some(bits @ 5..=8) => Some(u8::try_from(bits).unwrap_or(8)),
        Some(other) => return Err(bad("data_bits", format!("{other}: use 5..8"))),
    };
    let stop_bits = match optional_uint(fields, "stop_bits")? {
        None => None,
        Some(bits @ 1..=2) => Some(u8::try_from(bits).unwrap_or(1)),
        Some(other) => return Err(bad("stop_bits", format!("{other}: use 1 or 2"))),
    };
    Ok(LineOverride {
        baud_rate,
        parity,
        data_bits,
        stop_bits,
    })
}

fn slave_id(fields: &Map<String, Value>) -> Result<Option<u8>, RpcError> {
    match optional_uint(fields, "slave_id")? {
        None => Ok(None),
        Some(id @ 1..=247) => Ok(Some(u8::try_from(id).unwrap_or(1))),
        Some(other) => Err(bad("slave_id", format!("{other}: use 1..247"))),
    }
}

fn total_timeout(fields: &Map<String, Value>) -> Result<Duration, RpcError> {
    Ok(optional_millis(fields, "total_timeout")?
        .unwrap_or(DEFAULT_TOTAL_TIMEOUT)
        .min(MAX_TOTAL_TIMEOUT))
}

fn optional_millis(fields: &Map<String, Value>, name: &str) -> Result<Option<Duration>, RpcError> {
    Ok(optional_uint(fields, name)?.map(Duration::from_millis))
}

fn optional_str<'a>(
    fields: &'a Map<String, Value>,
    name: &str,
) -> Result<Option<&'a str>, RpcError> {
    match fields.get(name) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(text)) => Ok(Some(text)),
        Some(other) => Err(bad(name, format!("{other} is not a string"))),
    }
}

/// `config/Load`'s `lang`, read as wb-mqtt-serial reads it (JSON's `asString`): a number or a
/// boolean as its text, null as no language (titles fall back to English), "en" when absent.
fn language(fields: &Map<String, Value>) -> Result<String, RpcError> {
    match fields.get("lang") {
        None => Ok("en".to_owned()),
        Some(Value::Null) => Ok(String::new()),
        Some(Value::String(text)) => Ok(text.clone()),
        Some(scalar @ (Value::Number(_) | Value::Bool(_))) => Ok(scalar.to_string()),
        Some(other) => Err(bad("lang", format!("{other} is not a language code"))),
    }
}

/// A non-negative integer, as a number or a decimal / `0x` hex string.
fn optional_uint(fields: &Map<String, Value>, name: &str) -> Result<Option<u64>, RpcError> {
    match fields.get(name) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Number(number)) => number
            .as_u64()
            .map(Some)
            .ok_or_else(|| bad(name, format!("{number} is not a non-negative integer"))),
        Some(Value::String(text)) => {
            let text = text.trim();
            let parsed = match text.strip_prefix("0x").or_else(|| text.strip_prefix("0X")) {
                Some(hex) => u64::from_str_radix(hex, 16).ok(),
                None => text.parse().ok(),
            };
            parsed
                .map(Some)
                .ok_or_else(|| bad(name, format!("{text:?} is not a non-negative integer")))
        }
        Some(other) => Err(bad(name, format!("{other} is not a number"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn parse(service: &str, method: &str, params: Value) -> Result<Method, RpcError> {
        parse_method(service, method, &params)
    }

    #[test]
    fn wb_mqtt_serial_methods_not_served_say_so() {
        for (service, method) in NOT_SERVED {
            let err = parse(service, method, json!({})).unwrap_err();
            assert!(
                err.message
                    .starts_with(&format!("{service}/{method} is not served by rtu2mqtt yet")),
                "{}",
                err.message
            );
        }
        let err = parse("fw-update", "Flash", json!({})).unwrap_err();
        assert!(
            err.message.starts_with("unknown method fw-update/Flash"),
            "{}",
            err.message
        );
    }

    #[test]
    fn an_event_log_read_waits_no_longer_than_its_reply_can() {
        assert_eq!(
            parse(
                "port",
                "EventLog",
                json!({"path": "/dev/ttyRS485-1", "from": 7})
            ),
            Ok(Method::PortEventLog(PortEventLog {
                port: PortSelector::Path("/dev/ttyRS485-1".into()),
                from: Some(7),
                log: None,
                wait: DEFAULT_EVENT_LOG_WAIT,
                total_timeout: DEFAULT_TOTAL_TIMEOUT,
            }))
        );
        let Ok(Method::PortEventLog(read)) = parse(
            "port",
            "EventLog",
            json!({"device_id": "relay", "wait_ms": 5000, "total_timeout": 2000}),
        ) else {
            panic!("not read")
        };
        assert_eq!((read.from, read.wait), (None, Duration::from_millis(1500)));
        let err = parse("port", "EventLog", json!({"path": "/dev/x", "from": -1})).unwrap_err();
        assert!(err.message.contains("\"from\""), "{}", err.message);
    }

    #[test]
    fn a_modbus_read_as_wb_tools_send_it() {
        let method = parse(
            "port",
            "Load",
            json!({"path": "/dev/ttyRS485-1", "baud_rate": 9600, "parity": "N", "data_bits": 8,
                   "stop_bits": 2, "slave_id": 12, "function": 3, "address": 200, "count": 20,
                   "format": "HEX", "msg": "", "total_timeout": 1000, "protocol": "modbus"}),
        )
        .unwrap();
        let Method::PortLoad(load) = method else {
            panic!("{method:?}")
        };
        assert_eq!(load.port, PortSelector::Path("/dev/ttyRS485-1".into()));
        assert_eq!(load.slave_id, Some(12));
        assert_eq!(
            load.pdu,
            RequestPdu::ReadHoldingRegisters {
                start: 200,
                count: 20
            }
        );
        assert_eq!(load.format, MessageFormat::Hex);
        assert_eq!(load.total_timeout, Duration::from_millis(1000));
        assert_eq!(load.response_timeout, DEFAULT_RESPONSE_TIMEOUT);
        assert_eq!(
            load.line.apply(LineSettings::new(115_200, Parity::Even, 1)),
            LineSettings::new(9600, Parity::None, 2)
        );
    }

    #[test]
    fn writes_take_their_data_from_msg() {
        let pdu = |function, count, msg: &[u8]| modbus_pdu(function, 10, count, msg);
        assert_eq!(
            pdu(5, 1, &[0xFF, 0]),
            Ok(RequestPdu::WriteSingleCoil {
                address: 10,
                value: true
            })
        );
        assert_eq!(
            pdu(6, 1, &[0x12, 0x34]),
            Ok(RequestPdu::WriteSingleRegister {
                address: 10,
                value: 0x1234
            })
        );
        assert_eq!(
            pdu(15, 3, &[0b101]),
            Ok(RequestPdu::WriteMultipleCoils {
                start: 10,
                values: vec![true, false, true]
            })
        );
        assert_eq!(
            pdu(16, 2, &[0, 1, 0xAB, 0xCD]),
            Ok(RequestPdu::WriteMultipleRegisters {
                start: 10,
                values: vec![1, 0xABCD]
            })
        );
        assert!(pdu(5, 1, &[1]).is_err());
        assert!(pdu(16, 2, &[0, 1]).is_err());
        assert!(pdu(15, 9, &[0xFF]).is_err());
    }

    #[test]
    fn lang_is_read_as_wb_mqtt_serial_reads_it() {
        let lang = |params: Value| match parse_method("config", "Load", &params) {
            Ok(Method::ConfigLoad { lang }) => Ok(lang),
            Ok(other) => panic!("{other:?}"),
            Err(error) => Err(error.message),
        };
        assert_eq!(lang(json!({})), Ok("en".to_owned()));
        assert_eq!(lang(json!({"lang": "ru"})), Ok("ru".to_owned()));
        assert_eq!(lang(json!({"lang": 7})), Ok("7".to_owned()));
        assert_eq!(lang(json!({"lang": true})), Ok("true".to_owned()));
        assert_eq!(lang(json!({"lang": null})), Ok(String::new()));
        assert!(lang(json!({"lang": ["ru"]})).unwrap_err().contains("lang"));
    }

    #[test]
    fn set_poll_takes_a_device_id_or_a_port_and_slave_id() {
        assert_eq!(
            parse_method(
                "device",
                "SetPoll",
                &json!({"device_id": "climate_21", "poll": false})
            )
            .unwrap(),
            Method::DeviceSetPoll(DeviceSetPoll {
                port: PortSelector::Device("climate_21".into()),
                slave_id: None,
                poll: false
            })
        );
        assert_eq!(
            parse_method(
                "device",
                "SetPoll",
                &json!({"path": "/dev/ttyRS485-1", "slave_id": 21, "poll": true})
            )
            .unwrap(),
            Method::DeviceSetPoll(DeviceSetPoll {
                port: PortSelector::Path("/dev/ttyRS485-1".into()),
                slave_id: Some(21),
                poll: true
            })
        );
        for (params, field) in [
            (json!({"path": "/dev/x", "poll": true}), "slave_id"),
            (json!({"device_id": "d"}), "poll"),
            (json!({"device_id": "d", "poll": "no"}), "poll"),
        ] {
            let err = parse_method("device", "SetPoll", &params).unwrap_err();
            assert!(err.message.contains(field), "{params}: {}", err.message);
        }
    }

    #[test]
    fn port_load_by_device_id_is_modbus_whatever_protocol_says() {
        // wb-mqtt-dali's write to a WB-MDALI gateway's queue pointer, as it sends it.
        let dali = json!({"device_id": "wb-mdali_1", "function": 6, "address": 1432,
                          "count": 1, "total_timeout": 1000, "frame_timeout": 0,
                          "format": "HEX", "msg": "0000"});
        let Method::PortLoad(load) = parse("port", "Load", dali.clone()).unwrap() else {
            panic!("not Modbus");
        };
        assert_eq!(load.port, PortSelector::Device("wb-mdali_1".into()));
        assert_eq!(load.slave_id, None, "the device's own address is used");
        assert_eq!(
            load.pdu,
            RequestPdu::WriteSingleRegister {
                address: 1432,
                value: 0
            }
        );
        assert_eq!(load.total_timeout, Duration::from_millis(1000));
        // As wb-mqtt-serial, the device's protocol wins over the request's.
        for protocol in ["raw", "modbus"] {
            let mut request = dali.clone();
            request["protocol"] = json!(protocol);
            assert!(
                matches!(parse("port", "Load", request), Ok(Method::PortLoad(_))),
                "{protocol}"
            );
        }
        // The device comes before a path (wb-mqtt-serial looks it up first); a port named by
        // its path alone is still a raw transfer without "protocol".
        let mut with_path = dali;
        with_path["path"] = json!("/dev/ttyRS485-1");
        with_path["response_size"] = json!(8);
        let Ok(Method::PortLoad(load)) = parse("port", "Load", with_path.clone()) else {
            panic!("not Modbus");
        };
        assert_eq!(load.port, PortSelector::Device("wb-mdali_1".into()));
        with_path.as_object_mut().unwrap().remove("device_id");
        assert!(matches!(
            parse("port", "Load", with_path),
            Ok(Method::PortLoadRaw(_))
        ));
    }

    #[test]
    fn port_load_without_protocol_is_a_raw_transfer() {
        let method = parse(
            "port",
            "Load",
            json!({"path": "/dev/ttyRS485-1", "baud_rate": 9600, "format": "HEX",
                   "msg": "0103000000018 40A".replace(' ', ""), "response_size": 7,
                   "response_timeout": 200, "frame_timeout": 30, "total_timeout": 3000}),
        )
        .unwrap();
        let Method::PortLoadRaw(raw) = method else {
            panic!("{method:?}");
        };
        assert_eq!(raw.port, PortSelector::Path("/dev/ttyRS485-1".into()));
        assert_eq!(
            raw.message,
            [0x01, 0x03, 0x00, 0x00, 0x00, 0x01, 0x84, 0x0A]
        );
        assert_eq!(raw.format, MessageFormat::Hex);
        assert_eq!(raw.response_size, 7);
        assert_eq!(raw.response_timeout, Duration::from_millis(200));
        assert_eq!(raw.frame_timeout, Duration::from_millis(30));
        assert_eq!(raw.total_timeout, Duration::from_millis(3000));
        // A string message is sent as its bytes; the timeouts default as wb-mqtt-serial's.
        let Method::PortLoadRaw(text) = parse(
            "port",
            "Load",
            json!({"path": "/dev/ttyRS485-1", "msg": "#01RD\r", "response_size": 16}),
        )
        .unwrap() else {
            panic!("not raw");
        };
        assert_eq!(text.message, b"#01RD\r");
        assert_eq!(text.format, MessageFormat::Str);
        assert_eq!(text.response_timeout, DEFAULT_RESPONSE_TIMEOUT);
        assert_eq!(text.frame_timeout, DEFAULT_RAW_FRAME_TIMEOUT);
    }

    #[test]
    fn bad_params_say_which_field_and_why() {
        let cases = [
            // Without "protocol": a raw transfer.
            (
                json!({"path": "/dev/x", "slave_id": 1, "function": 3, "address": 1, "count": 1}),
                "msg",
            ),
            (json!({"path": "/dev/x", "msg": "hello"}), "response_size"),
            (
                json!({"path": "/dev/x", "msg": "01", "format": "HEX", "response_size": 5000}),
                "response_size",
            ),
            (
                json!({"path": "/dev/x", "msg": "010", "format": "HEX", "response_size": 8}),
                "msg",
            ),
            // A configured device is asked in Modbus, with or without "protocol".
            (
                json!({"device_id": "relay", "msg": "x", "response_size": 8}),
                "function",
            ),
            (
                json!({"path": "/dev/x", "protocol": "dlms", "slave_id": 1, "function": 3}),
                "protocol",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 7}),
                "function",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 0, "function": 3}),
                "slave_id",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "function": 3}),
                "slave_id",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3, "count": 200}),
                "count",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3, "address": -1}),
                "address",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3, "address": 70000}),
                "address",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 6, "format": "HEX", "msg": "12G4"}),
                "msg",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3, "parity": "X"}),
                "parity",
            ),
            (
                json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3, "baud_rate": "fast"}),
                "baud_rate",
            ),
            (
                json!({"path": 5, "protocol": "modbus", "slave_id": 1, "function": 3}),
                "path",
            ),
            (
                json!({"protocol": "modbus", "slave_id": 1, "function": 3}),
                "Port is not defined",
            ),
        ];
        for (params, field) in cases {
            let error = parse("port", "Load", params.clone()).unwrap_err();
            assert_eq!(error.code, super::super::message::code::SERVER_ERROR);
            assert!(error.message.contains(field), "{params}: {}", error.message);
        }
    }

    #[test]
    fn unknown_and_unserved_methods_are_named() {
        let unknown = parse("port", "Explode", json!({})).unwrap_err();
        assert!(unknown.message.contains("unknown method port/Explode"));
        assert!(unknown.message.contains("port/Scan"));
        let later = parse("config", "GetSchema", json!({"type": "WB-MR6C"})).unwrap_err();
        assert!(later.message.contains("not served"), "{}", later.message);
    }

    #[test]
    fn odd_values_in_any_field_are_refused_without_panic() {
        let odd = [
            json!(null),
            json!(-1),
            json!(1.5),
            json!(u64::MAX),
            json!("0x"),
            json!("ffffffffffffffffffffff"),
            json!([1, [2]]),
            json!({"a": {}}),
            json!(""),
            json!(true),
        ];
        let fields = [
            "path",
            "ip",
            "port",
            "device_id",
            "protocol",
            "slave_id",
            "sn",
            "function",
            "address",
            "count",
            "format",
            "msg",
            "response_timeout",
            "total_timeout",
            "baud_rate",
            "parity",
            "data_bits",
            "stop_bits",
            "mode",
            "command",
            "items",
        ];
        let base = json!({"path": "/dev/x", "protocol": "modbus", "slave_id": 1, "function": 3,
                          "items": [{"slave_id": 1, "cfg": {"slave_id": 2}}]});
        for (service, method) in SERVED.iter().chain(NOT_SERVED) {
            for field in fields {
                for value in &odd {
                    let mut params = base.clone();
                    params[field] = value.clone();
                    // Whatever the outcome, it is a value or an error: no panic.
                    let _ = parse_method(service, method, &params);
                    let mut item = base.clone();
                    item["items"][0]["cfg"][field] = value.clone();
                    let _ = parse_method(service, method, &item);
                }
            }
            for params in &odd {
                let _ = parse_method(service, method, params);
            }
        }
    }

    #[test]
    fn setup_items() {
        let setup = parse(
            "port",
            "Setup",
            json!({"path": "/dev/x", "items": [
                {"slave_id": 21, "sn": 4261412897u64, "baud_rate": 9600,
                 "cfg": {"slave_id": 31, "baud_rate": 115200, "parity": "N", "stop_bits": 2}},
                {"slave_id": 5, "cfg": {"parity": 2}}
            ]}),
        )
        .unwrap();
        let Method::PortSetup(setup) = setup else {
            panic!()
        };
        assert_eq!(setup.items.len(), 2);
        assert_eq!(setup.items[0].serial, Some(4_261_412_897));
        assert_eq!(setup.items[0].line.baud_rate, Some(9600));
        assert_eq!(
            setup.items[0].cfg,
            DeviceSettings {
                slave_id: Some(31),
                baud_rate: Some(115_200),
                parity: Some(Parity::None),
                stop_bits: Some(2)
            }
        );
        assert_eq!(setup.items[1].cfg.parity, Some(Parity::Even));
        for bad_items in [
            json!({"path": "/dev/x"}),
            json!({"path": "/dev/x", "items": [{"cfg": {}}]}),
            json!({"path": "/dev/x", "items": [{"slave_id": 1, "cfg": {"slave_id": 300}}]}),
            json!({"path": "/dev/x", "items": [{"slave_id": 1, "cfg": {"parity": 7}}]}),
        ] {
            assert!(
                parse("port", "Setup", bad_items.clone()).is_err(),
                "{bad_items}"
            );
        }
    }

    #[test]
    fn scan_and_probe_params() {
        let scan = parse(
            "port",
            "Scan",
            json!({"path": "/dev/x", "baud_rate": 115200, "mode": "start", "command": 70}),
        )
        .unwrap();
        let Method::PortScan(scan) = scan else {
            panic!()
        };
        assert_eq!(scan.mode, ScanMode::Start);
        assert_eq!(scan.total_timeout, DEFAULT_TOTAL_TIMEOUT);
        assert_eq!(scan.command, 0x46);
        assert!(parse("port", "Scan", json!({"path": "/dev/x", "command": 71})).is_err());
        assert!(parse("port", "Scan", json!({"path": "/dev/x", "mode": "some"})).is_err());
        let probe = parse(
            "device",
            "Probe",
            json!({"ip": "10.0.0.5", "port": 502, "slave_id": "0x10"}),
        )
        .unwrap();
        assert_eq!(
            probe,
            Method::DeviceProbe(DeviceProbe {
                port: PortSelector::Tcp {
                    ip: "10.0.0.5".into(),
                    port: 502
                },
                line: LineOverride::default(),
                slave_id: 16,
                total_timeout: DEFAULT_TOTAL_TIMEOUT,
            })
        );
        assert!(parse("device", "Probe", json!({"path": "/dev/x"})).is_err());
    }

    /// wb-device-manager (the web UI's scan) sends every Fast Modbus `port/Scan` with
    /// `"command": 96` (fast_modbus_scan.py / main.py: "Use 0x60 for scanning as the last device
    /// with deprecated command only was sold 18.12.24"); wb-mqtt-serial serves it
    /// (rpc_port_scan_serial_client_task.cpp: `ModbusExt::Scan(port, rpcRequest->ModbusExtCommand, …)`).
    #[test]
    fn port_scan_takes_command_96_as_wb_device_manager_sends_it() {
        let params = json!({"path": "/dev/ttyRS485-1", "baud_rate": 9600, "parity": "N",
                            "data_bits": 8, "stop_bits": 2, "command": 96,
                            "total_timeout": 10000});
        let parsed = parse_method("port", "Scan", &params);
        assert!(
            matches!(parsed, Ok(Method::PortScan(PortScan { command: 0x60, .. }))),
            "wb-device-manager's scan request refused: {parsed:?}"
        );
    }

    /// wb-mqtt-serial-rpc-port-setup-request.schema.json: `cfg.baud_rate` is one of
    /// 110..230400 (enum), validated before anything is written; holding 110 gets `baud / 100`,
    /// so 12345 would become 123 (the device then talks at 12300 baud and is lost). The line
    /// override beside `slave_id` keeps its own range.
    #[test]
    fn port_setup_refuses_a_baud_rate_no_device_can_take() {
        for baud in [12_345_u32, 9601, 250_000, 1_000_000, 150] {
            let params = json!({"path": "/dev/x",
                                "items": [{"slave_id": 1, "cfg": {"baud_rate": baud}}]});
            let parsed = parse_method("port", "Setup", &params);
            assert!(
                parsed.is_err(),
                "cfg.baud_rate {baud} accepted (holding 110 would get {}): {parsed:?}",
                baud / 100
            );
        }
        let ok = parse_method(
            "port",
            "Setup",
            &json!({"path": "/dev/x", "baud_rate": 250_000,
                    "items": [{"slave_id": 1, "baud_rate": 250_000,
                               "cfg": {"baud_rate": 230_400}}]}),
        );
        assert!(matches!(ok, Ok(Method::PortSetup(_))), "{ok:?}");
        let refused = parse_method(
            "port",
            "Setup",
            &json!({"path": "/dev/x", "items": [{"slave_id": 1, "cfg": {"baud_rate": 12345}}]}),
        )
        .unwrap_err();
        assert!(
            refused.message.contains("cfg.baud_rate") && refused.message.contains("115200"),
            "{refused:?}"
        );
    }
}
