//! What each method does on a running port: every bus exchange goes through the port's
//! [`BusQueue`], one transaction at a time, between the port's own transactions.

use std::cmp::Ordering;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde_json::{json, Map, Value};

use super::config_load::{
    config_for_clients, device_types, device_types_used, TemplateShape, WB_GROUP_NAMES,
    WB_PORTS_SCHEMA,
};
use super::message::RpcError;
use super::params::{
    DeviceLoad, DeviceLoadConfig, DeviceProbe, DeviceSet, DeviceSetPoll, MessageFormat, Method,
    PortEventLog, PortLoad, PortLoadRaw, PortScan, PortSelector, PortSetup, ScanMode, POLL_HOLD,
};
use crate::config::config_file::PortType;
use crate::config::library::ListedTemplate;
use crate::config::parse::SourceText;
use crate::config::{TemplateFile, TemplateLibrary};
use crate::daemon::bus_queue::BusQueue;
use crate::daemon::{PortAccess, PortDirectory};
use crate::device::firmware::compare_versions;
use crate::gateway::port_plan::line_settings;
use crate::port::{Transaction, TransactionOutcome};
use crate::protocol::fast::FastReply;
use crate::protocol::timing::ADAPTER_LATENCY_ALLOWANCE;
use crate::protocol::{LineSettings, Reply, ReplyBody, Request, RequestPdu, ResponsePdu};
use crate::tools::adapter::Adapter;
use crate::tools::bus::{scan_transaction, Answer, PortError, ToolBus};
use crate::tools::report::{same_serial, ScanReport};
use crate::tools::values::standard_text;
use crate::transport::fifo::sysfs_tty;
use crate::transport::raw::RawRequest;

/// A running port's bus as the site tools' exchanges see it.
pub struct QueuedBus {
    queue: BusQueue,
    /// The port's own settings; `None` for TCP gateways (settings do not apply).
    home: Option<LineSettings>,
    latency: Duration,
    /// What the serial port is (a USB adapter or not), for requests at other settings.
    adapter: Option<Adapter>,
    /// The function code of scans and requests by serial number (0x46, or 0x60 when asked).
    fast_function: u8,
}

impl QueuedBus {
    pub fn new(access: &PortAccess) -> Self {
        let adapter = access
            .resolved
            .config
            .path
            .as_deref()
            .map(|path| Adapter::detect(Path::new(path), &sysfs_tty()));
        Self {
            queue: access.queue.clone(),
            home: access.line,
            latency: RPC_LATENCY,
            adapter,
            fast_function: crate::protocol::fast::FUNCTION,
        }
    }

    /// Scans and requests by serial number under `function` (0x46 or 0x60).
    fn with_fast_function(mut self, function: u8) -> Self {
        self.fast_function = function;
        self
    }

    /// Timeouts for requests at `line`: at other settings than the port's own (a client
    /// scanning all 24, where every empty setting costs this once) what the kind of port
    /// needs, as the site tools use it.
    fn for_line(mut self, line: LineSettings) -> Self {
        if self.home.is_some_and(|home| home != line) {
            self.latency = self
                .adapter
                .map_or(ADAPTER_LATENCY_ALLOWANCE, Adapter::reply_allowance);
        }
        self
    }
}

/// Added to the timeouts of RPC requests at the port's own settings: the USB adapter's
/// allowance, and more for a controller busy with the daemon's own work (an RPC is never in a
/// hurry, and a reply taken for silence would be a wrong answer).
const RPC_LATENCY: Duration = Duration::from_millis(50);

impl ToolBus for QueuedBus {
    fn latency(&self) -> Duration {
        self.latency
    }

    fn fast_function(&self) -> u8 {
        self.fast_function
    }

    async fn transact(
        &mut self,
        line: LineSettings,
        transaction: Transaction,
    ) -> Result<TransactionOutcome, PortError> {
        let line = self.home.map(|_| line);
        Ok(self.queue.transact(line, transaction).await?)
    }
}

/// What the RPC knows of the service's files: the templates the running config was resolved
/// with (those its devices use; `device/LoadConfig` reads a template's parameter list from
/// them), the device types of the whole library, and the config file (`config/Load` reads it
/// at each request, as wb-mqtt-serial). Replaced on a reload.
#[derive(Debug, Clone, Default)]
pub struct DeviceTemplates(Arc<std::sync::RwLock<ServiceFiles>>);

#[derive(Debug, Default)]
struct ServiceFiles {
    used: TemplateLibrary,
    types: Vec<ListedTemplate>,
    config: Option<PathBuf>,
}

impl DeviceTemplates {
    pub fn new(used: TemplateLibrary, types: Vec<ListedTemplate>, config: PathBuf) -> Self {
        Self(Arc::new(std::sync::RwLock::new(ServiceFiles {
            used,
            types,
            config: Some(config),
        })))
    }

    pub fn replace(&self, used: TemplateLibrary, types: Vec<ListedTemplate>) {
        let mut files = self
            .0
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        files.used = used;
        files.types = types;
    }

    fn files(&self) -> std::sync::RwLockReadGuard<'_, ServiceFiles> {
        self.0
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn get(&self, device_type: &str) -> Option<TemplateFile> {
        self.files().used.get(device_type).cloned()
    }
}

/// `config/Load`: the config file as wb-mqtt-serial hands it out, its ports schema when its
/// package is installed (else `{}`), and the device types of the library.
fn config_load(templates: &DeviceTemplates, lang: &str) -> Result<Value, RpcError> {
    let files = templates.files();
    let path = files
        .config
        .as_deref()
        .ok_or_else(|| RpcError::server("this service has no config file"))?;
    let source = SourceText::read(path).map_err(|err| RpcError::server(err.to_string()))?;
    let root = source
        .parse_json()
        .map_err(|err| RpcError::server(err.to_string()))?;
    if !root.is_object() {
        return Err(RpcError::server(format!(
            "{}: the config is not a JSON object",
            path.display()
        )));
    }
    // Every device's template, the running config's or not (a disabled device, one added
    // since the last reload): the ones in use as loaded, the others read again, not kept.
    let mut shapes = BTreeMap::new();
    for device_type in device_types_used(&root) {
        if shapes.contains_key(device_type) {
            continue;
        }
        let shape = match files.used.get(device_type) {
            Some(template) => Some(TemplateShape::of(&template.raw)),
            None => files
                .types
                .iter()
                .find(|listed| listed.device_type == device_type)
                .and_then(ListedTemplate::read_json)
                .map(|raw| TemplateShape::of(&raw)),
        };
        if let Some(shape) = shape {
            shapes.insert(device_type.to_owned(), shape);
        }
    }
    let installed = |file: &str| SourceText::read(Path::new(file)).ok()?.parse_json().ok();
    let group_names = installed(WB_GROUP_NAMES).unwrap_or(Value::Null);
    let types = device_types(&files.types, &group_names, lang);
    Ok(json!({
        "config": config_for_clients(root, &shapes),
        "schema": installed(WB_PORTS_SCHEMA).unwrap_or_else(|| json!({})),
        "types": types,
    }))
}

/// Runs a request that needs no template (the status page's scan); `Err` is the JSON-RPC error
/// to send back.
pub async fn execute(ports: &PortDirectory, method: Method) -> Result<Value, RpcError> {
    execute_with_templates(ports, &DeviceTemplates::default(), method).await
}

/// Runs a request; `Err` is the JSON-RPC error to send back.
pub async fn execute_with_templates(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    method: Method,
) -> Result<Value, RpcError> {
    match method {
        Method::PortsLoad => Ok(ports_load(ports)),
        Method::PortLoad(load) => port_load(ports, load).await,
        Method::PortLoadRaw(raw) => port_load_raw(ports, raw).await,
        Method::PortScan(scan) => port_scan(ports, scan).await,
        Method::DeviceProbe(probe) => device_probe(ports, probe).await,
        Method::PortSetup(setup) => port_setup(ports, setup).await,
        Method::DeviceLoad(load) => device_load(ports, templates, load).await,
        Method::DeviceSet(set) => device_set(ports, templates, set).await,
        Method::DeviceSetPoll(set_poll) => device_set_poll(ports, set_poll).await,
        Method::DeviceLoadConfig(load) => device_load_config(ports, templates, load).await,
        Method::PortEventLog(read) => port_event_log(ports, read).await,
        Method::ConfigLoad { lang } => {
            // Files are read (the config, templates not in use): off the async workers.
            let templates = templates.clone();
            tokio::task::spawn_blocking(move || config_load(&templates, &lang))
                .await
                .map_err(|err| RpcError::server(format!("config/Load failed: {err}")))?
        }
    }
}

fn snapshot(ports: &PortDirectory) -> Vec<PortAccess> {
    ports
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .values()
        .cloned()
        .collect()
}

/// `params` as the request is to be read: a `device_id` that names no configured device is
/// left out when the request also names a port by `path` or `ip`, which then decides (as
/// wb-mqtt-serial does: it looks the device up first and goes on with the port when there is
/// none). Without a port to fall back on, the `device_id` stays and is reported as unknown.
pub fn without_unknown_device_id(ports: &PortDirectory, params: &Value) -> Option<Value> {
    let fields = params.as_object()?;
    let id = fields.get("device_id")?.as_str()?;
    if !(fields.contains_key("path") || fields.contains_key("ip")) {
        return None;
    }
    let configured = snapshot(ports)
        .iter()
        .any(|access| access.resolved.devices.iter().any(|d| d.id == id));
    if configured {
        return None;
    }
    let mut fields = fields.clone();
    fields.remove("device_id");
    Some(Value::Object(fields))
}

/// `ports/Load`: the configured ports, as wb-mqtt-serial lists them.
fn ports_load(ports: &PortDirectory) -> Value {
    // In the config's order, as wb-mqtt-serial lists them (the directory is keyed by name).
    let mut running = snapshot(ports);
    running.sort_by_key(|access| access.resolved.index);
    let list: Vec<Value> = running
        .iter()
        .map(|access| {
            let config = &access.resolved.config;
            match config.port_type {
                PortType::Serial => {
                    let line = line_settings(config);
                    json!({
                        "path": config.path,
                        "baud_rate": line.baud,
                        "data_bits": line.data_bits,
                        "parity": line.parity.letter().to_string(),
                        "stop_bits": line.stop_bits,
                    })
                }
                PortType::Tcp => json!({ "address": config.address, "port": config.port }),
                PortType::ModbusTcp => json!({
                    "address": config.address,
                    "port": config.port,
                    "protocol": "modbus-tcp",
                }),
            }
        })
        .collect();
    Value::Array(list)
}

/// The running port a request names, and the index among its devices of the device it names
/// (if it names one by `device_id`).
fn find_port(
    ports: &PortDirectory,
    selector: &PortSelector,
) -> Result<(PortAccess, Option<usize>), RpcError> {
    let running = snapshot(ports);
    let found = running.iter().find_map(|access| {
        let config = &access.resolved.config;
        match selector {
            PortSelector::Path(path) => {
                (config.path.as_deref() == Some(path.as_str())).then(|| (access.clone(), None))
            }
            PortSelector::Tcp { ip, port } => (config.address.as_deref() == Some(ip.as_str())
                && config.port == Some(*port))
            .then(|| (access.clone(), None)),
            PortSelector::Device(id) => access
                .resolved
                .devices
                .iter()
                .position(|d| d.id == *id)
                .map(|index| (access.clone(), Some(index))),
        }
    });
    found.ok_or_else(|| {
        let served: Vec<&str> = running.iter().map(|a| a.name.as_str()).collect();
        let what = match selector {
            PortSelector::Path(path) => format!("port {path}"),
            PortSelector::Tcp { ip, port } => format!("port {ip}:{port}"),
            PortSelector::Device(id) => format!("device {id:?}"),
        };
        RpcError::server(format!(
            "{what} is not served by this rtu2mqtt (it serves: {}); add it to the config, or use \
             the site tools directly on a port the service does not hold",
            if served.is_empty() {
                "no port".to_owned()
            } else {
                served.join(", ")
            }
        ))
    })
}

/// The settings a request runs at: the port's own with what the request changes. TCP gateways
/// are timed as 9600 8N2, as wb-mqtt-serial does.
fn request_line(access: &PortAccess, line: &super::params::LineOverride) -> LineSettings {
    let home = access
        .line
        .unwrap_or_else(|| line_settings(&access.resolved.config));
    match access.line {
        Some(_) => line.apply(home),
        None => home,
    }
}

fn io_error(err: PortError) -> RpcError {
    RpcError::server(format!("Port IO error: {err}"))
}

/// `port/Load` with a Modbus protocol: one request, the reply's data as wb-mqtt-serial gives it.
async fn port_load(ports: &PortDirectory, load: PortLoad) -> Result<Value, RpcError> {
    let (access, named_device) = find_port(ports, &load.port)?;
    let named_device = named_device.and_then(|index| access.resolved.devices.get(index));
    if load.serial.is_some() {
        refuse_if_the_config_forbids_fast_modbus(&access, "request by serial number")?;
    }
    if let Some(device) = named_device.filter(|device| device.modbus_io) {
        // wb-mqtt-serial asks a device named by `device_id` in its own protocol and refuses
        // the others; a WBIO module's registers are not the host's at these addresses.
        return Err(RpcError::server(format!(
            "The device's protocol is not supported: {:?} is a modbus_io module; name its \
             WB-MIO's port and address instead",
            device.id
        )));
    }
    let line = request_line(&access, &load.line);
    let mut bus = QueuedBus::new(&access);
    // A device named by `device_id` is asked at its own address, as wb-mqtt-serial does.
    let slave_id = named_device.map(|device| device.slave_id).or(load.slave_id);
    // A read that meets a garbled reply is tried once more: between the port's own
    // transactions, a late reply to one of them can spoil the first try on a loaded line.
    // Silence is not: a scan (wb-device-manager's bootloader scan reads 246 addresses at 48
    // settings with an 8 ms timeout) must pay one timeout per empty address, as with
    // wb-mqtt-serial, which sends once. A write is sent once, as wb-mqtt-serial sends it: its
    // reply lost is no proof that it was not carried out, and a device's queue or command
    // register would carry it out twice.
    let tries = if load.pdu.is_write() { 1 } else { 2 };
    let mut answer = Answer::NoReply;
    let mut tried = 0;
    while tried < tries {
        tried += 1;
        answer = match (load.serial, slave_id) {
            (Some(serial), _) => bus
                .by_serial(line, serial, load.pdu.clone(), load.response_timeout)
                .await
                .map_err(io_error)?,
            (None, Some(address)) => bus
                .classic(line, address, load.pdu.clone(), load.response_timeout)
                .await
                .map_err(io_error)?,
            (None, None) => return Err(RpcError::server("bad \"slave_id\": missing")),
        };
        if !matches!(answer, Answer::Garbled) {
            break;
        }
    }
    let target = match (load.serial, slave_id) {
        (Some(serial), _) => format!("serial {serial}"),
        (None, Some(address)) => format!("slave {address}"),
        (None, None) => String::new(),
    };
    load_result(&answer, load.format).map_err(|why| {
        let message = format!(
            "Port IO error: {why} from {target} on {} at {line} (response_timeout {} ms{})",
            access.name,
            load.response_timeout.as_millis(),
            if tried > 1 { ", tried twice" } else { "" }
        );
        // wb-mqtt-serial answers silence with E_RPC_REQUEST_TIMEOUT (its
        // TResponseTimeoutException), which wb-device-manager's bootloader scan relies on; any
        // other failure is a server error.
        match answer {
            Answer::NoReply => RpcError::timeout(message),
            _ => RpcError::server(message),
        }
    })
}

/// `port/Load` without a protocol: the bytes out as given, then `{"response": …}` with what
/// came back. Nothing at all, when a reply was asked for, is wb-mqtt-serial's server error
/// "Port IO error: request timed out" (its `ReadFrame`), which scanners such as
/// modbus-utils-rpc's take for an empty setting.
async fn port_load_raw(ports: &PortDirectory, raw: PortLoadRaw) -> Result<Value, RpcError> {
    let (access, _) = find_port(ports, &raw.port)?;
    let line = access.line.map(|_| request_line(&access, &raw.line));
    let request = RawRequest {
        bytes: raw.message,
        response_size: raw.response_size,
        response_timeout: raw.response_timeout + RPC_LATENCY,
        frame_timeout: raw.frame_timeout,
    };
    let answer = access
        .queue
        .transfer_raw(line, request)
        .await
        .map_err(|err| RpcError::server(format!("Port IO error: {err}")))?;
    if answer.is_empty() && raw.response_size > 0 {
        return Err(RpcError::server("Port IO error: request timed out"));
    }
    Ok(json!({ "response": format_response(&answer, raw.format) }))
}

/// `response` as wb-mqtt-serial writes it: two lowercase hex digits per byte, or the bytes as
/// a string.
fn format_response(data: &[u8], format: MessageFormat) -> String {
    match format {
        MessageFormat::Hex => data.iter().map(|b| format!("{b:02x}")).collect(),
        MessageFormat::Str => String::from_utf8_lossy(data).into_owned(),
    }
}

/// The result of `port/Load` for a reply: `{"response": data}` or `{"exception": …}`.
pub fn load_result(answer: &Answer, format: MessageFormat) -> Result<Value, &'static str> {
    let data: Vec<u8> = match answer {
        Answer::NoReply => return Err("no reply"),
        Answer::Garbled => return Err("unreadable reply (bad CRC, or two devices answering)"),
        Answer::Pdu(ResponsePdu::Exception { code, .. }) => {
            return Ok(json!({
                "exception": { "code": code.0, "msg": code.description() }
            }))
        }
        Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values })
        | Answer::Pdu(ResponsePdu::ReadInputRegisters { values }) => {
            values.iter().flat_map(|w| w.to_be_bytes()).collect()
        }
        Answer::Pdu(ResponsePdu::ReadCoils { packed })
        | Answer::Pdu(ResponsePdu::ReadDiscreteInputs { packed }) => packed.clone(),
        Answer::Pdu(_) => Vec::new(),
    };
    Ok(json!({ "response": format_response(&data, format) }))
}

/// `port/Scan`: the Fast Modbus scan at one setting, then each device's details.
async fn port_scan(ports: &PortDirectory, scan: PortScan) -> Result<Value, RpcError> {
    let (access, _) = find_port(ports, &scan.port)?;
    if tcp_without_mge(&access) {
        // wb-mqtt-serial: Modbus TCP without a WB-MGE gateway finds nothing.
        return Ok(json!({ "devices": [] }));
    }
    refuse_if_the_config_forbids_fast_modbus(&access, "scan")?;
    let line = request_line(&access, &scan.line);
    let mut bus = QueuedBus::new(&access)
        .for_line(line)
        .with_fast_function(scan.command);
    // The whole scan (start … end, and the reads by serial number of what it found) is one
    // turn on the port: another scan's start would make our devices un-scanned again.
    let _lease = access.queue.scan_lease().await;
    let mut error = None;
    let found = match scan.mode {
        ScanMode::All => {
            let mut report = ScanReport::default();
            let mut seen = bus
                .scan_setting(line, &mut report)
                .await
                .map_err(io_error)?;
            if seen.is_empty() && report.problems.is_empty() && access.line == Some(line) {
                // Silence after a scan start at the port's own settings means nobody there,
                // unless the reply was late (a loaded machine): a second start costs one more
                // short timeout. Other settings are usually empty; a client scanning all of
                // them would pay it 47 times.
                seen = bus
                    .scan_setting(line, &mut report)
                    .await
                    .map_err(io_error)?;
            }
            if let Some(problem) = report.problems.first() {
                error = Some(problem.what.clone());
            }
            seen
        }
        ScanMode::Start | ScanMode::Next => {
            let start = scan.mode == ScanMode::Start;
            let request = if start {
                Request::scan_start()
            } else {
                Request::scan_continue()
            }
            .with_fast_function(scan.command);
            let transaction = scan_transaction(&line, request, start, bus.latency());
            match bus.transact(line, transaction).await.map_err(io_error)? {
                TransactionOutcome::Reply(Reply {
                    body:
                        ReplyBody::Fast {
                            reply:
                                FastReply::ScanFound {
                                    serial,
                                    modbus_address,
                                },
                            ..
                        },
                    ..
                }) => vec![(serial, modbus_address)],
                TransactionOutcome::Reply(Reply {
                    body:
                        ReplyBody::Fast {
                            reply: FastReply::ScanEnd,
                            ..
                        },
                    ..
                })
                | TransactionOutcome::NoReply => Vec::new(),
                TransactionOutcome::Reply(_) | TransactionOutcome::Garbled => {
                    error = Some("unreadable reply to the scan (bad CRC or a collision)".into());
                    Vec::new()
                }
            }
        }
    };
    let mut devices = Vec::new();
    for (serial, address) in found {
        let mut reader = Reader::BySerial(serial);
        let mut details = device_details(&mut bus, line, &mut reader, address, serial).await?;
        insert_configured(&mut details, &access, address, serial);
        devices.push(Value::Object(details));
    }
    let mut result = json!({ "devices": devices });
    if let Some(error) = error {
        result["error"] = json!(error);
    }
    Ok(result)
}

fn tcp_without_mge(access: &PortAccess) -> bool {
    let config = &access.resolved.config;
    config.port_type == PortType::ModbusTcp && !config.connected_to_mge
}

/// The config's own switch (the site's or the port's `"fast_modbus": false`: a site that
/// forbids the extension, or a bus with a device Fast Modbus frames throw out of step) holds
/// for what is asked of the service too: no Fast Modbus frame is sent on such a port.
fn refuse_if_the_config_forbids_fast_modbus(
    access: &PortAccess,
    what: &str,
) -> Result<(), RpcError> {
    if access.fast_modbus || tcp_without_mge(access) {
        return Ok(());
    }
    Err(RpcError::server(format!(
        "Fast Modbus is off for {} in the service's config (\"fast_modbus\": false): no Fast \
         Modbus {what} is sent there; use classic Modbus (by address), or turn the switch on",
        access.name
    )))
}

/// What a scan or probe result says of the configured device at `address` of a device found
/// there with `serial`:
/// - `configured_device_type`, as wb-mqtt-serial: the configured device's type, unless the
///   service has read that device's serial number and it is another one;
/// - `configured_device` (rtu2mqtt's own): `{"id": …, "sn": …}`, the configured device at this
///   address and the serial number the service read from it (left out while unknown), so that
///   `rtu2mqtt fix-addresses` keeps the address of the device the service polls.
fn insert_configured(
    details: &mut Map<String, Value>,
    access: &PortAccess,
    address: u8,
    serial: u32,
) {
    let Some(index) = access
        .resolved
        .devices
        .iter()
        .position(|d| d.slave_id == address)
    else {
        return;
    };
    let device = &access.resolved.devices[index];
    let identified = access.queue.identified_serial(index);
    let mut configured = json!({ "id": device.id });
    if let Some(known) = identified {
        configured["sn"] = json!(known.to_string());
    }
    details.insert("configured_device".into(), configured);
    let this_one = identified.is_none_or(|known| same_serial(known, serial));
    if let (Some(device_type), true) = (&device.device_type, this_one) {
        details.insert("configured_device_type".into(), json!(device_type));
    }
}

/// `device/Probe`: a Wiren Board device at a given address (classic requests): its serial
/// number first; silence means "nobody there" (`{}`).
/// Holds or resumes a configured device's polling; `{}` as wb-mqtt-serial answers.
/// `port/EventLog`: the event packets the port received from `from` on, each event with its
/// source byte as on the wire (and in words), register or system event number, and payload.
async fn port_event_log(ports: &PortDirectory, read: PortEventLog) -> Result<Value, RpcError> {
    let (access, _) = find_port(ports, &read.port)?;
    let page = access.events.read(read.from, read.log, read.wait).await;
    let packets: Vec<Value> = page
        .packets
        .iter()
        .map(|packet| {
            let events: Vec<Value> = packet
                .events
                .iter()
                .map(|event| {
                    json!({
                        "source": event.source.to_wire(),
                        "type": event.source.name(),
                        "id": event.id,
                        "payload": crate::protocol::hex(&event.payload),
                    })
                })
                .collect();
            json!({
                "seq": packet.seq,
                "time_ms": packet.unix_ms,
                "slave_id": packet.address,
                "flag": packet.flag,
                "events": events,
            })
        })
        .collect();
    Ok(json!({
        "packets": packets,
        "next": page.next,
        "lost": page.lost,
        "log": page.log,
        "restarted": page.restarted,
    }))
}

async fn device_set_poll(ports: &PortDirectory, request: DeviceSetPoll) -> Result<Value, RpcError> {
    // wb-mqtt-serial's words for any device it does not poll.
    let (access, index) = find_device(
        ports,
        &request.port,
        request.slave_id,
        ("device/SetPoll", None),
    )
    .map_err(|_| RpcError::server("Port or device not found"))?;
    let hold_for = (!request.poll).then_some(POLL_HOLD);
    access
        .queue
        .hold_polling(index, hold_for)
        .await
        .map_err(|err| RpcError::server(err.to_string()))?;
    Ok(Value::Object(Map::new()))
}

async fn device_probe(ports: &PortDirectory, probe: DeviceProbe) -> Result<Value, RpcError> {
    let (access, _) = find_port(ports, &probe.port)?;
    let line = request_line(&access, &probe.line);
    let mut bus = QueuedBus::new(&access);
    let mut reader = Reader::Address(probe.slave_id);
    // wb-device-manager's standard scan probes 246 addresses at 48 settings, most of them
    // silent: the first read waits 3.5 characters (wb-mqtt-serial's frame timeout) on top of
    // the RPC latency, not the 500 ms kept for a device that answered.
    let first_read_timeout = line.frame_gap();
    let serial = match reader
        .read_within(&mut bus, line, wb_register::SERIAL, 2, first_read_timeout)
        .await
        .map_err(io_error)?
    {
        Ok(words) => (u32::from(words[0]) << 16) | u32::from(words[1]),
        Err(Answer::NoReply) => return Ok(json!({})),
        Err(answer) => {
            return Ok(json!({ "errors": [error_entry("read_sn", &describe(&answer))] }));
        }
    };
    let mut details = device_details(&mut bus, line, &mut reader, probe.slave_id, serial).await?;
    insert_configured(&mut details, &access, probe.slave_id, serial);
    Ok(Value::Object(details))
}

/// `port/Setup`: new address and port settings of Wiren Board devices, by address or serial
/// number. The result is `null`, as wb-mqtt-serial's.
async fn port_setup(ports: &PortDirectory, setup: PortSetup) -> Result<Value, RpcError> {
    let (access, _) = find_port(ports, &setup.port)?;
    if setup.items.iter().any(|item| item.serial.is_some()) {
        refuse_if_the_config_forbids_fast_modbus(&access, "request by serial number")?;
    }
    let mut bus = QueuedBus::new(&access);
    for item in &setup.items {
        let line = request_line(&access, &item.line);
        let mut target = match item.serial {
            Some(serial) => Reader::BySerial(serial),
            None => Reader::Address(item.slave_id),
        };
        // The address first: by serial number it does not matter, by address the following
        // writes go to the new one.
        if let Some(new_address) = item.cfg.slave_id {
            setup_write(
                &mut bus,
                line,
                &target,
                wb_register::ADDRESS,
                &[u16::from(new_address)],
            )
            .await?;
            if let Reader::Address(address) = &mut target {
                *address = new_address;
            }
        }
        // The port settings last and in one write where they are contiguous: the device takes
        // them at once and would not hear a second write at its old settings.
        let mut registers: Vec<(u16, u16)> = Vec::new();
        if let Some(baud) = item.cfg.baud_rate {
            registers.push((
                wb_register::BAUD,
                u16::try_from(baud / 100).unwrap_or(u16::MAX),
            ));
        }
        if let Some(parity) = item.cfg.parity {
            let value = match parity {
                crate::protocol::Parity::None => 0,
                crate::protocol::Parity::Odd => 1,
                crate::protocol::Parity::Even => 2,
            };
            registers.push((wb_register::PARITY, value));
        }
        if let Some(stop_bits) = item.cfg.stop_bits {
            registers.push((wb_register::STOP_BITS, u16::from(stop_bits)));
        }
        let contiguous = registers.windows(2).all(|pair| pair[1].0 == pair[0].0 + 1);
        if contiguous && !registers.is_empty() {
            let values: Vec<u16> = registers.iter().map(|(_, v)| *v).collect();
            setup_write(&mut bus, line, &target, registers[0].0, &values).await?;
        } else {
            for (register, value) in registers {
                setup_write(&mut bus, line, &target, register, &[value]).await?;
            }
        }
    }
    Ok(Value::Null)
}

async fn setup_write(
    bus: &mut QueuedBus,
    line: LineSettings,
    target: &Reader,
    start: u16,
    values: &[u16],
) -> Result<(), RpcError> {
    let pdu = match values {
        [value] => RequestPdu::WriteSingleRegister {
            address: start,
            value: *value,
        },
        _ => RequestPdu::WriteMultipleRegisters {
            start,
            values: values.to_vec(),
        },
    };
    let timeout = crate::tools::bus::KNOWN_DEVICE_TIMEOUT;
    let (answer, who) = match target {
        Reader::BySerial(serial) => (
            bus.by_serial(line, *serial, pdu, timeout).await,
            format!("serial {serial}"),
        ),
        Reader::Address(address) => (
            bus.classic(line, *address, pdu, timeout).await,
            format!("slave {address}"),
        ),
    };
    match answer.map_err(io_error)? {
        Answer::Pdu(
            ResponsePdu::WriteSingleRegister { .. } | ResponsePdu::WriteMultipleRegisters { .. },
        ) => Ok(()),
        other => Err(RpcError::server(format!(
            "Port IO error: writing holding {start} of {who} at {line}: {}",
            describe(&other)
        ))),
    }
}

/// The configured device a `device/…` request names: by `device_id`, or by the port and its
/// `slave_id`. wb-mqtt-serial also serves devices that are not configured (from a
/// `device_type` alone); rtu2mqtt serves the configured ones only.
fn find_device(
    ports: &PortDirectory,
    selector: &PortSelector,
    slave_id: Option<u8>,
    (method, device_type): (&str, Option<&str>),
) -> Result<(PortAccess, usize), RpcError> {
    let (access, named_device) = find_port(ports, selector)?;
    let index = match named_device {
        Some(index) => index,
        None => {
            let address = slave_id.ok_or_else(|| RpcError::server("bad \"slave_id\": missing"))?;
            access
                .resolved
                .devices
                .iter()
                .position(|d| d.slave_id == address)
                .ok_or_else(|| {
                    RpcError::server(format!(
                        "no configured device at slave_id {address} on {}: rtu2mqtt serves \
                         {method} for configured devices only (add the device to the config \
                         first, or give the \"device_id\" or \"slave_id\" of one)",
                        access.name
                    ))
                })?
        }
    };
    // Another template's registers must never be read or written as this device's: the caller
    // (homeui, after the type was changed and not saved yet) means another device.
    if let (Some(wanted), Some(device)) = (device_type, access.resolved.devices.get(index)) {
        let configured = device.device_type.as_deref().unwrap_or("");
        if configured != wanted {
            return Err(RpcError::server(format!(
                "slave_id {} on {} is configured as \"{configured}\", not \"{wanted}\": \
                 rtu2mqtt serves {method} with the configured template only (save the config \
                 with the new type first)",
                device.slave_id, access.name
            )));
        }
    }
    Ok((access, index))
}

/// A channel of a device by its template name (as wb-mqtt-serial names it), or by its MQTT
/// control id.
fn channel_named<'a>(
    device: &'a crate::device::model::ResolvedDevice,
    name: &str,
) -> Option<&'a crate::device::model::ResolvedChannel> {
    device
        .channels
        .iter()
        .find(|c| c.name == name)
        .or_else(|| device.channel(name))
}

/// A decoded value as wb-mqtt-serial gives it: a number where the text is one, else the text.
fn value_json(text: &str) -> Value {
    match text.trim().parse::<f64>() {
        // Whole numbers as integers (wb-mqtt-serial's JSON writes 21, not 21.0).
        Ok(number) if number.is_finite() && number.fract() == 0.0 && number.abs() < 9.0e15 => {
            json!(number as i64)
        }
        Ok(number) if number.is_finite() => json!(number),
        _ => json!(text),
    }
}

/// `device/Load`: reads the named channels and template parameters of a configured device,
/// each through the bus queue (tried three times, as wb-mqtt-serial does), and decodes them as
/// the daemon does. Result `{"channels": {"name": value}, "parameters": {"id": value}}`.
async fn device_load(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    load: DeviceLoad,
) -> Result<Value, RpcError> {
    let (access, index) = find_device(
        ports,
        &load.port,
        load.slave_id,
        ("device/Load", load.device_type.as_deref()),
    )?;
    let device = &access.resolved.devices[index];
    let parameters = if load.parameters.is_empty() {
        Vec::new()
    } else {
        let template = device_template(templates, device)?;
        super::parameters::named_parameters(&template, device.slave_id, &load.parameters)
            .map_err(RpcError::server)?
    };
    let mut wanted = Vec::new();
    for name in &load.channels {
        match channel_named(device, name) {
            Some(channel) if !channel.write_only => wanted.push((name, channel)),
            _ => {
                return Err(RpcError::server(format!(
                    "Channel \"{name}\" is write only or not found in \"{}\" device template",
                    device.device_type.as_deref().unwrap_or(&device.id)
                )))
            }
        }
    }
    let line = request_line(&access, &super::params::LineOverride::default());
    let mut bus = QueuedBus::new(&access);
    let mut channels = Map::new();
    for (name, channel) in wanted {
        let mut words: Vec<Vec<u16>> = Vec::new();
        for register in &channel.registers {
            let Some(target) = register.read else {
                continue;
            };
            words.push(read_words(&mut bus, line, device.slave_id, target).await?);
        }
        let refs: Vec<&[u16]> = words.iter().map(Vec::as_slice).collect();
        let value = match channel.decode(&refs) {
            Ok(crate::device::Reading::Value(text)) => value_json(&text),
            Ok(crate::device::Reading::DeviceError) => {
                return Err(RpcError::server(format!(
                    "Channel \"{name}\": the device reports an error value"
                )))
            }
            Ok(crate::device::Reading::Unsupported) => json!("unsupported"),
            Err(err) => {
                return Err(RpcError::server(format!(
                    "Channel \"{name}\": cannot decode: {err}"
                )))
            }
        };
        channels.insert(name.clone(), value);
    }
    let mut values = Map::new();
    for parameter in &parameters {
        let Some(target) = parameter.register.read else {
            continue;
        };
        let words = read_words(&mut bus, line, device.slave_id, target).await?;
        let value = match parameter.register.codec.decode(&words) {
            Ok(crate::device::Reading::Value(text)) => value_json(&text),
            Ok(_) => json!("unsupported"),
            Err(err) => {
                return Err(RpcError::server(format!(
                    "Parameter \"{}\": cannot decode: {err}",
                    parameter.id
                )))
            }
        };
        values.insert(parameter.id.clone(), value);
    }
    let mut result = Map::new();
    if !channels.is_empty() {
        result.insert("channels".into(), Value::Object(channels));
    }
    if !values.is_empty() {
        result.insert("parameters".into(), Value::Object(values));
    }
    Ok(Value::Object(result))
}

/// The template a configured device was resolved with, for its parameters; templates with
/// subdevices are refused, as wb-mqtt-serial's device methods refuse them.
fn device_template(
    templates: &DeviceTemplates,
    device: &crate::device::model::ResolvedDevice,
) -> Result<TemplateFile, RpcError> {
    let device_type = device.device_type.as_deref().ok_or_else(|| {
        RpcError::server(format!(
            "device \"{}\" has no template, hence no parameters",
            device.id
        ))
    })?;
    let template = templates.get(device_type).ok_or_else(|| {
        RpcError::server(format!(
            "the template \"{device_type}\" is not loaded (reload the service after adding it)"
        ))
    })?;
    if super::parameters::has_subdevices(&template) {
        return Err(RpcError::server(format!(
            "Device \"{device_type}\" is not supported by this RPC"
        )));
    }
    Ok(template)
}

/// Tries of a `device/Load` read or a `device/Set` write (wb-mqtt-serial: 1 + 2 retries).
const DEVICE_TRIES: usize = 3;

/// A read of a configured device's registers: their words (one per bit for coils and discrete
/// inputs), or the device's refusal.
enum SpanRead {
    Words(Vec<u16>),
    Refused(Answer),
}

/// Reads `span` of the device at `address` through the bus queue, tried [`DEVICE_TRIES`] times
/// (a refusal is final); silence or garbage every time is the error.
async fn read_span(
    bus: &mut QueuedBus,
    line: LineSettings,
    address: u8,
    span: crate::port::RegisterSpan,
) -> Result<SpanRead, RpcError> {
    let count = span.count.max(1);
    let pdu = crate::port::RegisterSpan { count, ..span }.read_request();
    let bits = |packed: &[u8]| -> Vec<u16> {
        (0..usize::from(count))
            .map(|i| u16::from(packed.get(i / 8).is_some_and(|b| b & (1 << (i % 8)) != 0)))
            .collect()
    };
    let mut answer = Answer::NoReply;
    for _ in 0..DEVICE_TRIES {
        answer = bus
            .classic(
                line,
                address,
                pdu.clone(),
                crate::tools::bus::KNOWN_DEVICE_TIMEOUT,
            )
            .await
            .map_err(io_error)?;
        match &answer {
            Answer::Pdu(
                ResponsePdu::ReadHoldingRegisters { values }
                | ResponsePdu::ReadInputRegisters { values },
            ) if values.len() == usize::from(count) => return Ok(SpanRead::Words(values.clone())),
            Answer::Pdu(
                ResponsePdu::ReadCoils { packed } | ResponsePdu::ReadDiscreteInputs { packed },
            ) => return Ok(SpanRead::Words(bits(packed))),
            Answer::Pdu(ResponsePdu::Exception { .. }) => return Ok(SpanRead::Refused(answer)),
            _ => {}
        }
    }
    Err(read_failed(span, address, line, &answer))
}

fn read_failed(
    span: crate::port::RegisterSpan,
    address: u8,
    line: LineSettings,
    answer: &Answer,
) -> RpcError {
    RpcError::server(format!(
        "Failed to read {} registers starting from <{:?} {}> of slave {address} at {line}: {}",
        span.count.max(1),
        span.register_type,
        span.start,
        describe(answer)
    ))
}

/// The words of `target`; a refusal is an error too.
async fn read_words(
    bus: &mut QueuedBus,
    line: LineSettings,
    address: u8,
    target: crate::device::model::RegisterRef,
) -> Result<Vec<u16>, RpcError> {
    let span = target.span();
    match read_span(bus, line, address, span).await? {
        SpanRead::Words(words) => Ok(words),
        SpanRead::Refused(answer) => Err(read_failed(span, address, line, &answer)),
    }
}

/// `device/Set`: writes the named channels and template parameters of a configured device.
/// Each value is checked as its `/on` payload would be (the device model's write check: control
/// type, limits, register format, read-only; see [`checked_writes`]), then written through the
/// bus queue, channels first. Nothing is written if one value is refused. Result `{}`.
async fn device_set(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    set: DeviceSet,
) -> Result<Value, RpcError> {
    use crate::device_updates::Repeats;
    use crate::gateway::device_model::DeviceModel;
    let (access, index) = find_device(
        ports,
        &set.port,
        set.slave_id,
        ("device/Set", set.device_type.as_deref()),
    )?;
    let device = Arc::new(access.resolved.devices[index].clone());
    let template = device
        .device_type
        .as_deref()
        .unwrap_or(&device.id)
        .to_owned();
    // The channels as the device model knows them; the parameters as a device of their own
    // (one channel per parameter), so the same model checks and encodes them.
    // Only writes go through these models: no value is read, none repeats.
    let mut channels_model = DeviceModel::new(Arc::clone(&device), index, Repeats::None);
    let mut parameters_model = None;
    if !set.parameters.is_empty() {
        let file = device_template(templates, &device)?;
        let ids: Vec<&str> = set.parameters.iter().map(|(id, _)| id.as_str()).collect();
        let (parameters_device, controls) =
            super::parameters::writable_parameters(&file, device.slave_id, &ids)
                .map_err(RpcError::server)?;
        parameters_model = Some((
            DeviceModel::new(Arc::new(parameters_device), index, Repeats::None),
            controls,
        ));
    }
    let line = request_line(&access, &super::params::LineOverride::default());
    let mut bus = QueuedBus::new(&access);
    // Every value is checked before anything is written.
    let mut writes = Vec::new();
    for (name, payload) in &set.channels {
        let channel = channel_named(&device, name)
            .filter(|c| !c.readonly)
            .ok_or_else(|| {
                RpcError::server(format!(
                    "Channel \"{name}\" is read only or not found in \"{template}\" device \
                     template"
                ))
            })?;
        let control = channel.id.clone();
        let checked = checked_writes(
            &mut bus,
            line,
            (&mut channels_model, index),
            (&control, payload),
            &writes,
        )
        .await
        .map_err(|why| RpcError::server(format!("Channel \"{name}\": {why}")))?;
        writes.extend(checked);
    }
    if let Some((model, controls)) = &mut parameters_model {
        for ((id, payload), control) in set.parameters.iter().zip(controls.iter()) {
            let checked =
                checked_writes(&mut bus, line, (model, index), (control, payload), &writes)
                    .await
                    .map_err(|why| RpcError::server(format!("Parameter \"{id}\": {why}")))?;
            writes.extend(checked);
        }
    }
    let requests = writes.iter().flat_map(|write| {
        (0..write.request_count()).map(move |sent| {
            let (address, values) = write.request(sent);
            let pdu = crate::port::plan::write_pdu(
                write.register_type,
                address,
                values,
                write.force_multiple,
            );
            (write.register_type, address, pdu)
        })
    });
    for (register_type, address, pdu) in requests {
        let mut answer = Answer::NoReply;
        for _ in 0..DEVICE_TRIES {
            answer = bus
                .classic(
                    line,
                    device.slave_id,
                    pdu.clone(),
                    crate::tools::bus::KNOWN_DEVICE_TIMEOUT,
                )
                .await
                .map_err(io_error)?;
            if matches!(answer, Answer::Pdu(_)) {
                break;
            }
        }
        match answer {
            Answer::Pdu(
                ResponsePdu::WriteSingleCoil { .. }
                | ResponsePdu::WriteSingleRegister { .. }
                | ResponsePdu::WriteMultipleCoils { .. }
                | ResponsePdu::WriteMultipleRegisters { .. },
            ) => {}
            other => {
                return Err(RpcError::server(format!(
                    "Failed to write <{:?} {}> of slave {} at {line}: {}",
                    register_type,
                    address,
                    device.slave_id,
                    describe(&other)
                )))
            }
        }
    }
    Ok(json!({}))
}

/// The register writes of one value for control `control` of `model`, checked and encoded by
/// the device model as an `/on` payload. A bit field's register is read first and handed to
/// the model as the daemon's reads hand it over, then the writes of this request before it
/// (`pending`, which land first), so the model keeps the other bits as the device will hold
/// them. `Err` is why (the model's words, or the read that failed).
async fn checked_writes(
    bus: &mut QueuedBus,
    line: LineSettings,
    (model, index): (&mut crate::gateway::device_model::DeviceModel, usize),
    (control, payload): (&str, &str),
    pending: &[crate::port::RegisterWrite],
) -> Result<Vec<crate::port::RegisterWrite>, String> {
    let device = Arc::clone(&model.device);
    let learn = |model: &mut crate::gateway::device_model::DeviceModel,
                 span: crate::port::RegisterSpan,
                 values: Vec<u16>| {
        model.apply(
            crate::port::PortEvent::Values {
                device: index,
                span,
                values: values.into(),
            },
            &mut Vec::new(),
        );
    };
    if let Some(channel) = device.channel(control) {
        for register in channel.registers.iter().filter(|r| r.codec.is_partial()) {
            let Some(target) = register.write.or(register.read) else {
                continue;
            };
            // A register the model would refuse to write is not worth a read, nor one no
            // channel reads: the model writes over what the setup leaves there, or zeros, as
            // wb-mqtt-serial writes over its cache (the device may refuse to read it).
            let read_by_a_channel = (0..target.count.max(1)).any(|offset| {
                model.reads_register(target.reg_type, target.address.wrapping_add(offset))
            });
            if target.reg_type.is_writable() && read_by_a_channel {
                let words = read_words(bus, line, device.slave_id, target)
                    .await
                    .map_err(|err| err.message)?;
                learn(model, target.span(), words);
            }
        }
    }
    for write in pending {
        let count = u16::try_from(write.values.len()).unwrap_or(u16::MAX);
        learn(
            model,
            crate::port::RegisterSpan::new(write.register_type, write.address, count),
            write.values.clone(),
        );
    }
    model.write(control, payload).map_err(|why| why.to_string())
}

/// `device/LoadConfig`, as wb-mqtt-serial answers it: the template's parameters, those the
/// config sets as it sets them and the others read from the device now (see
/// [`super::parameters`]), and for a Wiren Board device its model and firmware, read now and
/// checked against the template's `hw` list (as wb-mqtt-serial refuses a device the template
/// does not fit). A template without parameters gives `{}`.
async fn device_load_config(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    load: DeviceLoadConfig,
) -> Result<Value, RpcError> {
    use super::parameters::{
        group_reads, has_parameters, parameter_registers, reported, words_of, ReadWords,
    };
    let (access, index) = find_device(
        ports,
        &load.port,
        load.slave_id,
        ("device/LoadConfig", load.device_type.as_deref()),
    )?;
    let device = &access.resolved.devices[index];
    if device.device_type.is_none() {
        return Ok(json!({}));
    }
    let template = device_template(templates, device)?;
    if !has_parameters(&template) {
        return Ok(json!({}));
    }
    let mut known = Map::new();
    for item in &device.setup {
        if let Some(id) = &item.parameter_id {
            known
                .entry(id.clone())
                .or_insert_with(|| value_json(&item.value));
        }
    }
    let line = request_line(&access, &super::params::LineOverride::default());
    let mut bus = QueuedBus::new(&access);
    let identity = if device.is_wb {
        Some(wb_identity(&mut bus, line, device).await?)
    } else {
        None
    };
    let firmware = identity.as_ref().map(|(_, fw)| fw.as_str());
    let registers = parameter_registers(&template, device.slave_id, &known, firmware)
        .map_err(RpcError::server)?;
    let spans: Vec<crate::port::RegisterSpan> = registers.iter().filter_map(|r| r.span()).collect();
    // A device with continuous read (which the port task switches on) answers a register it
    // lacks as 0xFFFE in a read that covers others: each parameter is read on its own there,
    // so that one it lacks is refused, not reported as 65534.
    let limits = if device.timing.enable_wb_continuous_read {
        crate::port::MergeLimits {
            min_read_registers: device.timing.min_read_registers,
            ..crate::port::MergeLimits::default()
        }
    } else {
        crate::port::MergeLimits {
            max_read_registers: device.timing.max_read_registers,
            max_register_hole: device.timing.max_reg_hole,
            max_bit_hole: device.timing.max_bit_hole,
            min_read_registers: device.timing.min_read_registers,
        }
    };
    let mut words = ReadWords::new();
    // Only the words of the parameters' own span: those `min_read_registers` adds past it may
    // be registers the device lacks (0xFFFE in continuous read), and would stand in for a
    // parameter whose own read is refused.
    let keep = |words: &mut ReadWords, span: crate::port::RegisterSpan, values: Vec<u16>| {
        for (offset, value) in (0..span.count).zip(values) {
            words.insert((span.register_type, span.start.wrapping_add(offset)), value);
        }
    };
    for read in group_reads(&spans, limits) {
        let asked = limits.at_least_min(read);
        match read_span(&mut bus, line, device.slave_id, asked).await? {
            SpanRead::Words(values) => keep(&mut words, read, values),
            SpanRead::Refused(_) => {
                // A refused parameter is left out, as wb-mqtt-serial leaves it; one the device
                // does not have must not hide the others read with it.
                let members: Vec<_> = spans.iter().filter(|s| read.contains(s)).copied().collect();
                let one_by_one = crate::port::MergeLimits {
                    min_read_registers: limits.min_read_registers,
                    ..crate::port::MergeLimits::default()
                };
                for member in group_reads(&members, one_by_one) {
                    if member == read {
                        continue;
                    }
                    let asked = one_by_one.at_least_min(member);
                    if let SpanRead::Words(values) =
                        read_span(&mut bus, line, device.slave_id, asked).await?
                    {
                        keep(&mut words, member, values);
                    }
                }
            }
        }
    }
    let values: Vec<Option<Value>> = registers
        .iter()
        .map(|parameter| {
            let read = words_of(&words, parameter.span()?)?;
            match parameter.register.codec.decode(&read) {
                Ok(crate::device::Reading::Value(text)) => Some(value_json(&text)),
                _ => None,
            }
        })
        .collect();
    let mut result = Map::new();
    result.insert(
        "parameters".into(),
        Value::Object(reported(&registers, &values, &known)),
    );
    if let Some((model, fw)) = identity {
        result.insert("model".into(), json!(model));
        if !fw.is_empty() {
            result.insert("fw".into(), json!(fw));
        }
    }
    Ok(Value::Object(result))
}

/// A Wiren Board device's model (holding 200) and firmware version (250), checked against the
/// template's `hw` list with wb-mqtt-serial's words.
async fn wb_identity(
    bus: &mut QueuedBus,
    line: LineSettings,
    device: &crate::device::model::ResolvedDevice,
) -> Result<(String, String), RpcError> {
    let mut reader = Reader::Address(device.slave_id);
    let text = |words: Vec<u16>| standard_text(&words).unwrap_or_default();
    let model = match read_model(bus, line, &mut reader).await? {
        Ok(words) => text(words),
        Err(answer) => {
            return Err(RpcError::server(format!(
                "Port IO error: reading the model (holding 200) of slave {} at {line}: {}",
                device.slave_id,
                describe(&answer)
            )))
        }
    };
    let fw = match reader
        .read(bus, line, wb_register::FIRMWARE, 16)
        .await
        .map_err(io_error)?
    {
        Ok(words) => text(words),
        Err(answer) => {
            return Err(RpcError::server(format!(
                "Port IO error: reading the firmware version (holding 250) of slave {} at \
                 {line}: {}",
                device.slave_id,
                describe(&answer)
            )))
        }
    };
    if !device.hw.is_empty() {
        match device.hw.iter().find(|hw| hw.signature == model) {
            Some(hw) => {
                let too_old = |min: &&str| compare_versions(&fw, min) == Ordering::Less;
                if let Some(min) = hw.fw.as_deref().filter(too_old) {
                    return Err(RpcError::server(format!(
                        "Device \"{model}\" firmware version {fw} is lower than selected \
                         template minimal supported version {min}"
                    )));
                }
            }
            None => {
                return Err(RpcError::server(format!(
                    "Device \"{model}\" with firmware version {fw} is incompatible with selected \
                     template device models"
                )))
            }
        }
    }
    Ok((model, fw))
}

/// Wiren Board's standard registers (holding).
mod wb_register {
    pub const BAUD: u16 = 110;
    pub const PARITY: u16 = 111;
    pub const STOP_BITS: u16 = 112;
    pub const ADDRESS: u16 = 128;
    /// 20 characters, or 6 on older devices.
    pub const MODEL: u16 = 200;
    pub const FIRMWARE: u16 = 250;
    pub const SERIAL: u16 = 270;
    pub const SIGNATURE: u16 = 290;
}

/// How a device's registers are read: by serial number (found by a scan) or by address.
enum Reader {
    BySerial(u32),
    Address(u8),
}

impl Reader {
    /// Holding registers; `Err` is what came instead of them.
    async fn read(
        &mut self,
        bus: &mut QueuedBus,
        line: LineSettings,
        start: u16,
        count: u16,
    ) -> Result<Result<Vec<u16>, Answer>, PortError> {
        // wb-mqtt-serial waits 3.5 characters and retries; a queued read of a device that just
        // answered gets the tools' timeout once.
        self.read_within(
            bus,
            line,
            start,
            count,
            crate::tools::bus::KNOWN_DEVICE_TIMEOUT,
        )
        .await
    }

    /// [`Self::read`] with its own response timeout (the RPC latency comes on top).
    async fn read_within(
        &mut self,
        bus: &mut QueuedBus,
        line: LineSettings,
        start: u16,
        count: u16,
        timeout: Duration,
    ) -> Result<Result<Vec<u16>, Answer>, PortError> {
        let pdu = RequestPdu::ReadHoldingRegisters { start, count };
        let answer = match self {
            Self::BySerial(serial) => bus.by_serial(line, *serial, pdu, timeout).await?,
            Self::Address(address) => bus.classic(line, *address, pdu, timeout).await?,
        };
        Ok(match answer {
            Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values })
                if values.len() == usize::from(count) =>
            {
                Ok(values)
            }
            other => Err(other),
        })
    }
}

fn describe(answer: &Answer) -> String {
    match answer {
        Answer::NoReply => "request timed out".into(),
        Answer::Garbled => "unreadable reply (bad CRC)".into(),
        Answer::Pdu(ResponsePdu::Exception { code, .. }) => {
            format!("the device refused: {}", code.description())
        }
        Answer::Pdu(other) => format!("unexpected reply {other:?}"),
    }
}

fn error_entry(what: &str, message: &str) -> Value {
    json!({ "id": format!("com.wb.device_manager.device.{what}_error"), "message": message })
}

/// What wb-mqtt-serial reports of a found device: `sn`, `device_signature`, `fw_signature`,
/// `cfg` (address and port settings), `fw.version`, and `errors` for what could not be read.
/// The model string (holding 200): 20 characters, else 6, as wb-mqtt-serial reads it.
async fn read_model(
    bus: &mut QueuedBus,
    line: LineSettings,
    reader: &mut Reader,
) -> Result<Result<Vec<u16>, Answer>, RpcError> {
    match reader
        .read(bus, line, wb_register::MODEL, 20)
        .await
        .map_err(io_error)?
    {
        Ok(words) => Ok(Ok(words)),
        Err(_) => reader
            .read(bus, line, wb_register::MODEL, 6)
            .await
            .map_err(io_error),
    }
}

/// The serial number a device is reported by, as wb-mqtt-serial reports it
/// (`GetSnFromRegister`): a WB-MAP energy meter's (signature `^MAP[0-9]{1,2}.*`) lower 24 bits,
/// the number on its label; every other device's whole number. Requests by serial number
/// still carry all 32 bits.
pub fn reported_sn(serial: u32, signature: Option<&str>) -> u32 {
    let map_meter = signature
        .and_then(|signature| signature.strip_prefix("MAP"))
        .is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_digit()));
    if map_meter {
        serial & 0x00FF_FFFF
    } else {
        serial
    }
}

async fn device_details(
    bus: &mut QueuedBus,
    line: LineSettings,
    reader: &mut Reader,
    address: u8,
    serial: u32,
) -> Result<Map<String, Value>, RpcError> {
    let mut details = Map::new();
    let mut errors = Vec::new();
    let text = |words: Result<Vec<u16>, Answer>| match words {
        Ok(words) => Ok(standard_text(&words).unwrap_or_default()),
        Err(answer) => Err(describe(&answer)),
    };
    let model = text(read_model(bus, line, reader).await?);
    let reported = reported_sn(serial, model.as_deref().ok());
    match model {
        Ok(model) => {
            details.insert("device_signature".into(), json!(model));
        }
        Err(why) => errors.push(error_entry("read_device_signature", &why)),
    }
    details.insert("sn".into(), json!(reported.to_string()));
    if reported != serial {
        // rtu2mqtt's own: the whole number, which requests by serial number (`sn` of
        // port/Load and port/Setup) need.
        details.insert("fast_modbus_sn".into(), json!(serial.to_string()));
    }
    match text(
        reader
            .read(bus, line, wb_register::SIGNATURE, 12)
            .await
            .map_err(io_error)?,
    ) {
        Ok(signature) => {
            details.insert("fw_signature".into(), json!(signature));
        }
        Err(why) => errors.push(error_entry("read_fw_signature", &why)),
    }
    let mut cfg = json!({ "slave_id": address, "data_bits": 8 });
    match reader
        .read(bus, line, wb_register::BAUD, 3)
        .await
        .map_err(io_error)?
    {
        Ok(words) => {
            cfg["baud_rate"] = json!(u32::from(words[0]) * 100);
            cfg["parity"] = json!(match words[1] {
                0 => "N",
                1 => "O",
                2 => "E",
                _ => "U",
            });
            cfg["stop_bits"] = json!(words[2]);
        }
        Err(answer) => errors.push(error_entry("read_serial_params", &describe(&answer))),
    }
    details.insert("cfg".into(), cfg);
    match text(
        reader
            .read(bus, line, wb_register::FIRMWARE, 16)
            .await
            .map_err(io_error)?,
    ) {
        Ok(version) => {
            details.insert("fw".into(), json!({ "version": version }));
        }
        Err(why) => errors.push(error_entry("read_fw_version", &why)),
    }
    if !errors.is_empty() {
        details.insert("errors".into(), Value::Array(errors));
    }
    Ok(details)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::ExceptionCode;

    #[test]
    fn a_map_meter_is_reported_by_its_lower_24_bits_as_wb_mqtt_serial_does() {
        assert_eq!(reported_sn(0xFE12_3456, Some("MAP12E")), 0x12_3456);
        assert_eq!(reported_sn(0xFE12_3456, Some("MAP3EV")), 0x12_3456);
        assert_eq!(reported_sn(0xFE12_3456, Some("MAP6S")), 0x12_3456);
        for other in [
            Some("WBMR6C"),
            Some("MAP"),
            Some("MAPX"),
            Some("WB-MAP12E"),
            None,
        ] {
            assert_eq!(reported_sn(0xFE12_3456, other), 0xFE12_3456, "{other:?}");
        }
    }

    /// The directory is keyed by port name; `ports/Load` lists the ports as the config does.
    #[test]
    fn ports_are_listed_in_the_configs_order() {
        let access = |index: usize, config: Value| {
            let config: crate::config::config_file::PortConfig =
                serde_json::from_value(config).unwrap();
            let (queue, _receiver) = crate::daemon::bus_queue::BusQueue::new();
            crate::daemon::PortAccess {
                name: format!("port {index}"),
                resolved: Arc::new(crate::device::ResolvedPort {
                    index,
                    config,
                    devices: Vec::new(),
                    low_priority_read_limit: None,
                }),
                line: None,
                queue,
                events: Arc::default(),
                fast_modbus: false,
            }
        };
        let directory: PortDirectory = Arc::default();
        {
            let mut ports = directory.lock().unwrap();
            // Names that sort against the config's order.
            ports.insert(
                "a".into(),
                access(
                    1,
                    json!({"port_type": "tcp", "address": "10.0.0.5", "port": 502}),
                ),
            );
            ports.insert(
                "b".into(),
                access(0, json!({"path": "/dev/ttyRS485-2", "devices": []})),
            );
        }
        let listed = ports_load(&directory);
        assert_eq!(listed[0]["path"], "/dev/ttyRS485-2", "{listed}");
        assert_eq!(listed[1]["address"], "10.0.0.5", "{listed}");
    }

    /// Serves `jobs` as a device answering each classic request with `answer` (Fast Modbus
    /// requests get no reply): the requests it was asked, in order.
    fn answer_classic(
        mut jobs: crate::daemon::bus_queue::BusQueueReceiver,
        answer: impl Fn(RequestPdu) -> ResponsePdu + Send + 'static,
    ) -> Arc<std::sync::Mutex<Vec<RequestPdu>>> {
        use crate::daemon::bus_queue::QueuedJob;
        let asked = Arc::new(std::sync::Mutex::new(Vec::new()));
        let seen = Arc::clone(&asked);
        tokio::spawn(async move {
            while let Some(job) = jobs.recv().await {
                let QueuedJob::Transaction(job) = job else {
                    continue;
                };
                let request = &job.transaction.request;
                let crate::protocol::RequestBody::Classic(pdu) = &request.body else {
                    let _ = job.reply.send(Ok(TransactionOutcome::NoReply));
                    continue;
                };
                seen.lock().unwrap().push(pdu.clone());
                let reply = Reply::classic(request.address, answer(pdu.clone()));
                let _ = job.reply.send(Ok(TransactionOutcome::Reply(reply)));
            }
        });
        asked
    }

    /// A library of one template, `template` as the file `name`.
    fn library_of(name: &str, template: &Value) -> TemplateLibrary {
        let mut library = TemplateLibrary::default();
        library.insert(
            TemplateFile::from_source(SourceText::from_text(
                Path::new(name),
                &template.to_string(),
            ))
            .unwrap(),
        );
        library
    }

    /// The first port of `config`, resolved with `library` as the daemon resolves it.
    fn first_port(config: &Value, library: &TemplateLibrary) -> crate::device::model::ResolvedPort {
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        crate::device::resolve_config(&loaded, library)
            .unwrap()
            .remove(0)
    }

    /// A directory holding `port` at `path`, at `line`, whose bus queue is served by the
    /// test: its jobs come out of the receiver returned.
    fn served_port(
        path: &str,
        port: crate::device::model::ResolvedPort,
        line: LineSettings,
    ) -> (PortDirectory, crate::daemon::bus_queue::BusQueueReceiver) {
        let (queue, jobs) = BusQueue::new();
        let directory: PortDirectory = Arc::default();
        directory.lock().unwrap().insert(
            path.into(),
            PortAccess {
                name: path.into(),
                resolved: Arc::new(port),
                line: Some(line),
                queue,
                events: Arc::default(),
                fast_modbus: false,
            },
        );
        (directory, jobs)
    }

    /// A device whose template sets `enable_wb_continuous_read` (the port task has switched it
    /// on): a read that covers a register the device has answers the others as 0xFFFE. With
    /// `min_read_registers: 2` the read of parameter `present` (holding 9) asks 9..=10, and 10
    /// comes back as 0xFFFE; parameter `missing` (holding 10) is refused on its own read. Only
    /// the parameters' own words are kept: `missing` is left out, not reported as 65534. (The
    /// template's `max_read_registers: 10` would merge the two: they are read one by one.)
    #[tokio::test]
    async fn load_config_of_a_continuous_read_device_keeps_only_its_parameters_words() {
        let template = json!({
            "device_type": "s35-continuous",
            "device": {
                "name": "Continuous", "id": "continuous",
                "enable_wb_continuous_read": true,
                "min_read_registers": 2,
                "max_read_registers": 10,
                "parameters": {
                    "present": {"title": "Present", "address": 9},
                    "missing": {"title": "Missing", "address": 10}
                },
                "channels": [{"name": "Value", "reg_type": "holding", "address": 20,
                              "type": "value"}]
            }
        });
        let library = library_of("config-s35-continuous.json", &template);
        let path = "/dev/rtu2mqtt-s35-no-such-port";
        let config = json!({"ports": [{"path": path, "baud_rate": 115200, "stop_bits": 2,
            "devices": [{"device_type": "s35-continuous", "slave_id": 7}]}]});
        let port = first_port(&config, &library);
        assert!(port.devices[0].timing.enable_wb_continuous_read);
        let (directory, jobs) = served_port(
            path,
            port,
            LineSettings::new(115_200, crate::protocol::Parity::None, 2),
        );
        // The device: holding 9 and 20, its model and firmware; continuous read on.
        let mut holding: BTreeMap<u16, u16> = BTreeMap::from([(9, 1234), (20, 5)]);
        for (offset, byte) in b"S35CR".iter().enumerate() {
            holding.insert(200 + offset as u16, u16::from(*byte));
        }
        for address in 205..220 {
            holding.insert(address, 0);
        }
        for (offset, byte) in b"1.2.3".iter().enumerate() {
            holding.insert(250 + offset as u16, u16::from(*byte));
        }
        for address in 255..266 {
            holding.insert(address, 0);
        }
        let asked = answer_classic(jobs, move |pdu| match pdu {
            RequestPdu::ReadHoldingRegisters { start, count } => {
                let values: Vec<Option<u16>> = (start..start + count)
                    .map(|address| holding.get(&address).copied())
                    .collect();
                if values.iter().any(Option::is_some) {
                    ResponsePdu::ReadHoldingRegisters {
                        values: values.iter().map(|v| v.unwrap_or(0xFFFE)).collect(),
                    }
                } else {
                    ResponsePdu::Exception {
                        function: 3,
                        code: ExceptionCode::ILLEGAL_DATA_ADDRESS,
                    }
                }
            }
            other => ResponsePdu::Exception {
                function: other.function(),
                code: ExceptionCode::ILLEGAL_FUNCTION,
            },
        });
        let method = super::super::params::parse_method(
            "device",
            "LoadConfig",
            &json!({"path": path, "slave_id": 7}),
        )
        .unwrap();
        let result = execute_with_templates(
            &directory,
            &DeviceTemplates::new(library, Vec::new(), PathBuf::from("c.json")),
            method,
        )
        .await
        .unwrap();
        let asked = asked.lock().unwrap().clone();
        assert!(
            asked.contains(&RequestPdu::ReadHoldingRegisters { start: 9, count: 2 }),
            "{asked:?}"
        );
        assert_eq!(
            result,
            json!({"parameters": {"present": 1234}, "model": "S35CR", "fw": "1.2.3"}),
            "{asked:?}"
        );
    }

    /// wb-device-manager's standard scan probes 246 addresses at 48 settings, most of them
    /// silent: `device/Probe`'s first read waits 3.5 characters past the RPC latency (as
    /// wb-mqtt-serial waits its frame timeout), not the 500 ms kept for devices that answered
    /// (a silent probe took 0.66 s: 2.2 hours per port).
    #[tokio::test]
    async fn a_silent_device_probe_waits_a_frame_gap_not_half_a_second() {
        use crate::daemon::bus_queue::QueuedJob;
        let path = "/dev/rtu2mqtt-probe-no-such-port";
        let config = json!({"ports": [{"path": path, "baud_rate": 9600, "stop_bits": 2,
            "devices": []}]});
        let port = first_port(&config, &TemplateLibrary::default());
        let line = LineSettings::new(9600, crate::protocol::Parity::None, 2);
        let (directory, mut jobs) = served_port(path, port, line);
        let waits = Arc::new(std::sync::Mutex::new(Vec::new()));
        let seen = Arc::clone(&waits);
        tokio::spawn(async move {
            while let Some(job) = jobs.recv().await {
                let QueuedJob::Transaction(job) = job else {
                    continue;
                };
                seen.lock()
                    .unwrap()
                    .push(job.transaction.first_byte_timeout);
                let _ = job.reply.send(Ok(TransactionOutcome::NoReply));
            }
        });
        let method = super::super::params::parse_method(
            "device",
            "Probe",
            &json!({"path": path, "slave_id": 9, "baud_rate": 9600, "parity": "N",
                    "data_bits": 8, "stop_bits": 2}),
        )
        .unwrap();
        let result = execute_with_templates(
            &directory,
            &DeviceTemplates::new(
                TemplateLibrary::default(),
                Vec::new(),
                PathBuf::from("c.json"),
            ),
            method,
        )
        .await;
        assert_eq!(result.unwrap(), json!({}));
        let waits = waits.lock().unwrap().clone();
        let allowed = line.frame_gap() + RPC_LATENCY + Duration::from_millis(10);
        assert!(
            !waits.is_empty() && waits.iter().all(|wait| wait.is_some_and(|w| w <= allowed)),
            "{waits:?}, allowed {allowed:?}"
        );
    }

    /// `device/Set` of a write-only `u8` (a `write_address` no channel reads) on a device that
    /// refuses reads of that register: written over zeros, as the daemon and wb-mqtt-serial
    /// write it (a narrow format keeps its register's other bits only where they are read); no
    /// read goes first that would fail the whole Set.
    #[tokio::test]
    async fn device_set_of_a_write_only_narrow_value_reads_nothing_first() {
        let template = json!({
            "device_type": "write-only-u8",
            "device": {
                "name": "WO", "id": "wo",
                "channels": [
                    {"name": "Value", "reg_type": "holding", "address": 20, "type": "value"},
                    {"name": "Cmd", "reg_type": "holding", "write_address": 30, "format": "u8", "type": "value"}
                ]
            }
        });
        let library = library_of("config-write-only-u8.json", &template);
        let path = "/dev/rtu2mqtt-write-only-no-such-port";
        let config = json!({"ports": [{"path": path, "baud_rate": 115200, "stop_bits": 2,
            "devices": [{"device_type": "write-only-u8", "slave_id": 7}]}]});
        let port = first_port(&config, &library);
        let (directory, jobs) = served_port(
            path,
            port,
            LineSettings::new(115_200, crate::protocol::Parity::None, 2),
        );
        let asked = answer_classic(jobs, move |pdu| match pdu {
            RequestPdu::WriteSingleRegister { address, value } => {
                ResponsePdu::WriteSingleRegister { address, value }
            }
            other => ResponsePdu::Exception {
                function: other.function(),
                code: ExceptionCode::ILLEGAL_DATA_ADDRESS,
            },
        });
        let method = super::super::params::parse_method(
            "device",
            "Set",
            &json!({"path": path, "slave_id": 7, "channels": {"Cmd": 5}}),
        )
        .unwrap();
        let result = execute_with_templates(
            &directory,
            &DeviceTemplates::new(library, Vec::new(), PathBuf::from("c.json")),
            method,
        )
        .await;
        let asked = asked.lock().unwrap().clone();
        assert!(result.is_ok(), "{result:?}; requests {asked:?}");
        assert_eq!(
            asked,
            [RequestPdu::WriteSingleRegister {
                address: 30,
                value: 5
            }]
        );
    }

    #[test]
    fn values_are_numbers_where_the_text_is_one() {
        assert_eq!(value_json("21.5"), json!(21.5));
        assert_eq!(value_json("1"), json!(1));
        assert_eq!(value_json("4261412897"), json!(4_261_412_897_u64));
        assert_eq!(value_json("-3"), json!(-3));
        assert_eq!(value_json("on"), json!("on"));
        assert_eq!(value_json("NaN"), json!("NaN"));
    }

    #[test]
    fn load_results_as_wb_mqtt_serial_gives_them() {
        let read = Answer::Pdu(ResponsePdu::ReadHoldingRegisters {
            values: vec![0x0102, 0xABCD],
        });
        assert_eq!(
            load_result(&read, MessageFormat::Hex),
            Ok(json!({"response": "0102abcd"}))
        );
        let coils = Answer::Pdu(ResponsePdu::ReadCoils { packed: vec![0x05] });
        assert_eq!(
            load_result(&coils, MessageFormat::Hex),
            Ok(json!({"response": "05"}))
        );
        let written = Answer::Pdu(ResponsePdu::WriteSingleRegister {
            address: 1,
            value: 2,
        });
        assert_eq!(
            load_result(&written, MessageFormat::Hex),
            Ok(json!({"response": ""}))
        );
        let refused = Answer::Pdu(ResponsePdu::Exception {
            function: 3,
            code: ExceptionCode::ILLEGAL_DATA_ADDRESS,
        });
        assert_eq!(
            load_result(&refused, MessageFormat::Hex),
            Ok(json!({"exception": {"code": 2, "msg": "illegal data address"}}))
        );
        assert!(load_result(&Answer::NoReply, MessageFormat::Hex).is_err());
        assert!(load_result(&Answer::Garbled, MessageFormat::Str).is_err());
    }
}
