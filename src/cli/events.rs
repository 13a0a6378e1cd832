//! `rtu2mqtt events`: the live Fast Modbus event stream of a port, decoded and acknowledged, with
//! channel names when a config is given. Ends with Ctrl-C, after --count events or --duration.
//!
//! When the running service holds the port (busy, or `--via-mqtt`), the events are the
//! service's: it polls and acknowledges them, and this command shows the packets it received
//! (RPC `port/EventLog`) instead of polling the bus itself, which would take events away from
//! the service.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use serde_json::json;

use crate::config::format::WordOrder;
use crate::config::load::load_config;
use crate::config::TemplateLibrary;
use crate::device::codec::{Reading, ValueCodec};
use crate::device::configure::resolve_config_checked;
use crate::device::model::EventMode;
use crate::port::TransactionOutcome;
use crate::protocol::fast::{split_event_masks, FastReply};
use crate::protocol::{
    Event, EventPoll, EventPriority, EventRange, EventSource, ExceptionCode, LineSettings,
    RegisterType, Reply, ReplyBody, Request, ResponsePdu,
};
use crate::sim::control::register_type_name;
use crate::tools::bus::{PortError, ToolBus, ToolPort};
use crate::tools::exit;

use super::scan::{block_on_tool, port_failure, PortArgs};
use super::via_mqtt::{connect_service, service_call};
use crate::rpc::client::RpcSession;

/// Most event data a device may put in one reply (wb-mqtt-serial asks for as much).
const MAX_EVENT_DATA: u8 = 100;

/// One `--enable ADDR:TYPE:REG[:PRIO]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EnableSpec {
    pub address: u8,
    pub register_type: RegisterType,
    pub register: u16,
    pub priority: EventPriority,
}

pub fn parse_enable(text: &str) -> Result<EnableSpec, String> {
    let err = |what: &str| {
        format!("--enable {text:?}: {what}; expected ADDR:TYPE:REG[:PRIO], e.g. 20:coil:0:high")
    };
    let parts: Vec<&str> = text.split(':').collect();
    let (address, kind, register, priority) = match parts.as_slice() {
        [a, t, r] => (a, t, r, "high"),
        [a, t, r, p] => (a, t, r, *p),
        _ => return Err(err("wrong number of fields")),
    };
    let address = address
        .parse::<u8>()
        .ok()
        .filter(|a| (1..=247).contains(a))
        .ok_or_else(|| err("the address is 1..247"))?;
    let register_type = match kind.to_ascii_lowercase().as_str() {
        "coil" => RegisterType::Coil,
        "discrete" => RegisterType::DiscreteInput,
        "holding" => RegisterType::Holding,
        "input" => RegisterType::Input,
        _ => return Err(err("the type is coil, discrete, holding or input")),
    };
    let register = crate::config::values::parse_int_text(register)
        .and_then(|n| u16::try_from(n).ok())
        .ok_or_else(|| err("the register is 0..65535"))?;
    let priority = match priority.to_ascii_lowercase().as_str() {
        "high" | "2" => EventPriority::High,
        "low" | "1" => EventPriority::Low,
        "off" | "0" => EventPriority::Disabled,
        _ => return Err(err("the priority is high, low or off")),
    };
    Ok(EnableSpec {
        address,
        register_type,
        register,
        priority,
    })
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub port: PortArgs,
    /// Config file: channel names in the output; its port (by path) gives the port settings, and
    /// without --enable its channels with events are enabled.
    #[arg(long, short = 'c')]
    pub config: Option<PathBuf>,
    /// Extra template directories for --config.
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// Enable events of one register: ADDR:TYPE:REG[:PRIO] (type coil, discrete, holding,
    /// input; priority high (default), low or off). Repeat for more.
    #[arg(long, value_parser = parse_enable)]
    pub enable: Vec<EnableSpec>,
    /// Stop after this many register events.
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop after this many seconds.
    #[arg(long, value_name = "S")]
    pub duration: Option<f64>,
    /// One JSON object per line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub service: super::via_mqtt::ViaMqttArgs,
}

/// What a config says about a register: its channel, and how to read its value.
struct ChannelName {
    device: String,
    channel: String,
    codec: Option<ValueCodec>,
    /// Registers of the value (1 for bits).
    width: u16,
}

/// Names, the port's settings and the event registers of the config's port with this path.
struct ConfigView {
    names: BTreeMap<(u8, RegisterType, u16), ChannelName>,
    line: Option<LineSettings>,
    enable: Vec<EnableSpec>,
}

fn load_view(
    path: &std::path::Path,
    templates: &[PathBuf],
    port: &str,
) -> Result<ConfigView, String> {
    let loaded = load_config(path).map_err(|errors| {
        errors
            .0
            .iter()
            .map(|e| e.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    })?;
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(templates.iter().cloned());
    let library = TemplateLibrary::load_standard(&dirs);
    let (result, _warnings) = resolve_config_checked(&loaded, &library);
    let ports = result.map_err(|errors| {
        errors
            .0
            .iter()
            .map(|e| e.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    })?;
    let mut view = ConfigView {
        names: BTreeMap::new(),
        line: None,
        enable: Vec::new(),
    };
    let Some(resolved) = ports
        .iter()
        .find(|p| p.config.path.as_deref() == Some(port))
    else {
        return Err(format!(
            "{} has no port with path {port}: names are looked up by the port's path",
            path.display()
        ));
    };
    view.line = Some(crate::gateway::port_plan::line_settings(&resolved.config));
    for device in &resolved.devices {
        for channel in &device.channels {
            for register in &channel.registers {
                let Some(read) = &register.read else {
                    continue;
                };
                let width = if read.reg_type.is_bit() {
                    1
                } else {
                    read.count.max(1)
                };
                view.names.insert(
                    (device.slave_id, read.reg_type, read.address),
                    ChannelName {
                        device: device.id.clone(),
                        channel: channel.id.clone(),
                        codec: Some(register.codec.clone()),
                        width,
                    },
                );
                // A value wider than a register is enabled at its first register, as the daemon
                // does: the device reports the whole value there.
                if channel.events != EventMode::Polled {
                    view.enable.push(EnableSpec {
                        address: device.slave_id,
                        register_type: read.reg_type,
                        register: read.address,
                        priority: EventPriority::High,
                    });
                }
            }
        }
    }
    Ok(view)
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.service.via_mqtt {
        return run_via_service(&args);
    }
    // The service holds the port: its events, not ours (polling the bus here would take them
    // away from it).
    // A busy port is said first, whatever else is missing: the settings would not help.
    if let Err(busy @ PortError::Busy { .. }) = args.port.open() {
        if !args.service.can_reach_service() {
            return Ok(port_failure(&busy));
        }
        eprintln!(
            "{} is busy: showing the running rtu2mqtt service's events (MQTT RPC)",
            args.port.port
        );
        return run_via_service(&args);
    }
    let view = match &args.config {
        Some(path) => match load_view(path, &args.templates, &args.port.port) {
            Ok(view) => Some(view),
            Err(message) => {
                eprintln!("{message}");
                return Ok(ExitCode::from(exit::USAGE));
            }
        },
        None => None,
    };
    let Some(line) = args
        .port
        .single_line()
        .or_else(|| view.as_ref().and_then(|v| v.line))
    else {
        eprintln!(
            "events need the port's settings: give --baud, --parity and --stop-bits (or --config)"
        );
        return Ok(ExitCode::from(exit::USAGE));
    };
    block_on_tool(async move {
        match stream(&args, view.as_ref(), line).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
}

/// The service's events of this port, as its port task received them (RPC `port/EventLog`):
/// the service polls and acknowledges them, this command only shows them. Channel names come
/// from `--config`, else from the service's config when it can be read.
fn run_via_service(args: &Args) -> anyhow::Result<ExitCode> {
    let config = args
        .config
        .clone()
        .unwrap_or_else(|| args.service.service_config.clone());
    let view = match load_view(&config, &args.templates, &args.port.port) {
        Ok(view) => Some(view),
        Err(message) if args.config.is_some() => {
            eprintln!("{message}");
            return Ok(ExitCode::from(exit::USAGE));
        }
        Err(message) => {
            eprintln!("no channel names (give --config for them): {message}");
            None
        }
    };
    if !args.enable.is_empty() {
        eprintln!("--enable is ignored through the service: it enables the events of its config");
    }
    if view.as_ref().is_some_and(|view| view.enable.is_empty()) {
        eprintln!(
            "no channel of {} in {} has events (sporadic or semi-sporadic): the service polls \
             none there, nothing to show",
            args.port.port,
            config.display()
        );
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    block_on_tool(async move {
        let mut session = match connect_service(&args.service).await {
            Ok(session) => session,
            Err(code) => return Ok(code),
        };
        Ok(service_stream(args, view.as_ref(), &mut session)
            .await
            .unwrap_or_else(|code| code))
    })
}

/// How long one `port/EventLog` call waits for a packet.
const EVENT_LOG_WAIT: Duration = Duration::from_secs(1);
/// Added to that wait for the call's reply (broker round trips, a busy controller).
const EVENT_LOG_MARGIN: Duration = Duration::from_secs(4);

async fn service_stream(
    args: &Args,
    view: Option<&ConfigView>,
    session: &mut RpcSession,
) -> Result<ExitCode, ExitCode> {
    let path = args.port.port.as_str();
    // A typo in the port is said at once, and beside another RPC server each call waits for
    // the one that serves it.
    super::via_mqtt::served_line(session, path).await?;
    let read = |from: Option<(u64, u64)>, wait: Duration| {
        let mut params = json!({
            "path": path,
            "wait_ms": u64::try_from(wait.as_millis()).unwrap_or(u64::MAX),
        });
        if let Some((from, log)) = from {
            params["from"] = json!(from);
            params["log"] = json!(log);
        }
        params
    };
    // The first call starts the service's recording: every packet after it is shown.
    let first = service_call(
        session,
        "port",
        "EventLog",
        read(None, Duration::ZERO),
        EVENT_LOG_MARGIN,
    )
    .await?;
    let mut from = (
        first["next"].as_u64().unwrap_or(0),
        first["log"].as_u64().unwrap_or(0),
    );
    eprintln!(
        "showing the events the rtu2mqtt service receives on {path} (it polls and acknowledges \
         them; Ctrl-C to stop)"
    );
    let deadline = args
        .duration
        .filter(|d| d.is_finite() && *d >= 0.0)
        .map(|d| tokio::time::Instant::now() + Duration::from_secs_f64(d.min(1e9)));
    let mut events_seen = 0u64;
    let mut repeats = RepeatWatch::default();
    loop {
        if args.count.is_some_and(|c| events_seen >= c) {
            break;
        }
        let wait = match deadline {
            Some(deadline) => {
                let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                if left.is_zero() {
                    break;
                }
                left.min(EVENT_LOG_WAIT)
            }
            None => EVENT_LOG_WAIT,
        };
        let page = service_call(
            session,
            "port",
            "EventLog",
            read(Some(from), wait),
            wait + EVENT_LOG_MARGIN,
        )
        .await?;
        if page["restarted"] == true {
            eprintln!(
                "the service restarted this port (a config reload): events received meanwhile \
                 may be missing"
            );
            repeats = RepeatWatch::default();
        }
        let lost = page["lost"].as_u64().unwrap_or(0);
        if lost > 0 {
            eprintln!("{lost} event packets came faster than shown here and were skipped");
            // A skipped packet may have changed a device's flag.
            repeats = RepeatWatch::default();
        }
        for packet in page["packets"].as_array().into_iter().flatten() {
            let (Some(address), Some(flag)) = (
                packet["slave_id"]
                    .as_u64()
                    .and_then(|a| u8::try_from(a).ok()),
                packet["flag"].as_u64().and_then(|f| u8::try_from(f).ok()),
            ) else {
                continue;
            };
            let events: Vec<Event> = packet["events"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(logged_event)
                .collect();
            let origin = PacketOrigin {
                address,
                via_service: true,
                repeated: repeats.is_repeat(address, flag, &events),
            };
            print_repeat(origin, args.json);
            for event in &events {
                if event.is_reboot() {
                    print_event(origin, event, view, args.json);
                } else if args.count.is_none_or(|c| events_seen < c) {
                    print_event(origin, event, view, args.json);
                    events_seen += 1;
                }
            }
        }
        from = (
            page["next"].as_u64().unwrap_or(from.0),
            page["log"].as_u64().unwrap_or(from.1),
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// An event of a `port/EventLog` reply, back as the bus brought it.
fn logged_event(event: &serde_json::Value) -> Option<Event> {
    Some(Event {
        source: EventSource::from_wire(u8::try_from(event["source"].as_u64()?).ok()?),
        id: u16::try_from(event["id"].as_u64()?).ok()?,
        payload: crate::protocol::parse_hex(event["payload"].as_str()?).ok()?,
    })
}

/// Sends the 0x18 request for one device's registers (once more after silence or noise); prints
/// which were enabled. False when the device took none: it is said, and the others go on.
async fn enable(
    port: &mut ToolPort,
    line: LineSettings,
    address: u8,
    specs: &[&EnableSpec],
    alone: bool,
    json_output: bool,
) -> Result<bool, PortError> {
    let ranges: Vec<EventRange> = specs
        .iter()
        .map(|s| EventRange::registers(s.register_type, s.register, vec![s.priority]))
        .collect();
    let request = Request::configure_events(address, ranges.clone());
    let mut outcome = TransactionOutcome::NoReply;
    let mut garbled = false;
    // Once more after silence or a garbled reply (noise): the request only sets what it names,
    // so a second one does no harm.
    for _ in 0..2 {
        outcome = port
            .fast(
                line,
                request.clone(),
                Duration::from_millis(500),
                Duration::from_millis(600),
            )
            .await?;
        match outcome {
            TransactionOutcome::NoReply => {}
            TransactionOutcome::Garbled => garbled = true,
            _ => break,
        }
    }
    let masks = match &outcome {
        TransactionOutcome::Reply(Reply {
            body:
                ReplyBody::Fast {
                    reply: FastReply::EventsConfigured { masks },
                    ..
                },
            ..
        }) => split_event_masks(masks, &ranges),
        _ => None,
    };
    let Some(masks) = masks else {
        let why = match outcome {
            TransactionOutcome::NoReply if !garbled => {
                "no reply, twice: not connected, or another address?".to_owned()
            }
            TransactionOutcome::NoReply | TransactionOutcome::Garbled => {
                "no readable reply in two tries: noise, or two devices at this address?".to_owned()
            }
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(ResponsePdu::Exception { code, .. }),
                ..
            }) if code == ExceptionCode::ILLEGAL_FUNCTION => format!(
                "the device refused, {code}: it has no Fast Modbus events (the daemon polls such \
                 a device classically)"
            ),
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(ResponsePdu::Exception { code, .. }),
                ..
            }) => format!(
                "the device refused the request, {code}: are these registers its event \
                 sources?"
            ),
            TransactionOutcome::Reply(_) => "a reply that is no answer to it".to_owned(),
        };
        let others = if alone { "" } else { "; watching the others" };
        eprintln!("address {address} at {line}: events not enabled ({why}){others}");
        return Ok(false);
    };
    for (spec, mask) in specs.iter().zip(masks) {
        let on = mask.first().is_some_and(|b| b & 1 == 1);
        let kind = register_type_name(spec.register_type);
        if json_output {
            println!(
                "{}",
                json!({"enabled": on, "address": address, "type": kind, "register": spec.register})
            );
        } else {
            println!(
                "address {address}: events of {kind} {} {}",
                spec.register,
                if on {
                    "enabled"
                } else {
                    "NOT enabled (the device does not support events there)"
                }
            );
        }
    }
    Ok(true)
}

async fn enable_all(
    port: &mut ToolPort,
    line: LineSettings,
    specs: &[EnableSpec],
    only: Option<u8>,
    json_output: bool,
) -> Result<bool, PortError> {
    let mut by_address: BTreeMap<u8, Vec<&EnableSpec>> = BTreeMap::new();
    for spec in specs.iter().filter(|s| only.is_none_or(|a| a == s.address)) {
        by_address.entry(spec.address).or_default().push(spec);
    }
    let mut any = false;
    let alone = by_address.len() == 1;
    for (address, specs) in by_address {
        any |= enable(port, line, address, &specs, alone, json_output).await?;
    }
    Ok(any)
}

/// Where an event came from, for its line.
#[derive(Debug, Clone, Copy)]
struct PacketOrigin {
    address: u8,
    /// The service received it, not this command.
    via_service: bool,
    /// Its packet came again under the same flag (its confirmation was lost): its events may
    /// have been shown already.
    repeated: bool,
}

/// Tells a packet sent again under the same flag (its confirmation was lost) from a new one.
#[derive(Debug, Default)]
struct RepeatWatch {
    last_flag: BTreeMap<u8, u8>,
}

impl RepeatWatch {
    fn is_repeat(&mut self, address: u8, flag: u8, events: &[Event]) -> bool {
        let previous = self.last_flag.insert(address, flag);
        // A restarted device numbers its packets afresh.
        previous == Some(flag) && !events.iter().any(Event::is_reboot)
    }
}

/// Says once per packet sent again that its events may repeat.
fn print_repeat(origin: PacketOrigin, json_output: bool) {
    if origin.repeated && !json_output {
        println!(
            "address {}: packet sent again (its confirmation was lost): events may repeat",
            origin.address
        );
    }
}

/// The words of a channel `width` registers wide, in register order, from an event's payload:
/// the payload is the value's number, little-endian (fast-modbus.md §6: "payload = the
/// register's new value"), and the registers hold it in the channel's word order, most
/// significant word first unless `word_order` is little_endian (the channel's codec then puts
/// them back in order). A payload padded beyond the value gives its low words; one shorter
/// than the value gives None (the daemon reads the rest; this command cannot tell it).
fn value_words(payload: &[u8], width: u16, word_order: WordOrder) -> Option<Vec<u16>> {
    let carried = crate::protocol::event_payload_words(payload);
    let width = usize::from(width.max(1));
    let skip = carried.len().checked_sub(width)?;
    let mut words = carried.get(skip..)?.to_vec();
    if word_order == WordOrder::LittleEndian {
        words.reverse();
    }
    Some(words)
}

/// One event, in words or as JSON.
fn print_event(origin: PacketOrigin, event: &Event, view: Option<&ConfigView>, json_output: bool) {
    let address = origin.address;
    let raw = event.value();
    let kind = event.source.name();
    let register_type = match event.source {
        EventSource::Register(register_type) => Some(register_type),
        _ => None,
    };
    let name = register_type.and_then(|t| view.and_then(|v| v.names.get(&(address, t, event.id))));
    let decoded = name.and_then(|n| {
        let codec = n.codec.as_ref()?;
        let words = value_words(&event.payload, n.width, codec.word_order)?;
        match codec.decode(&words) {
            Ok(Reading::Value(text)) => Some(text),
            _ => None,
        }
    });
    if json_output {
        let mut line = json!({
            "address": address,
            "type": kind,
            "register": event.id,
            "value": raw,
            "reboot": event.is_reboot(),
            "device": name.map(|n| n.device.clone()),
            "channel": name.map(|n| n.channel.clone()),
            "text": decoded,
            "repeated": origin.repeated,
        });
        if origin.via_service {
            line["via"] = json!("service");
        }
        println!("{line}");
        return;
    }
    if event.is_reboot() {
        // Through the service, the service sets the device up again (this tool enables nothing).
        let after = if origin.via_service {
            "the service sets it up again"
        } else {
            "enabled again where asked"
        };
        println!("address {address}: restarted (event settings lost; {after})");
        return;
    }
    let value = raw.map_or_else(|| crate::protocol::hex(&event.payload), |v| v.to_string());
    let channel = name.map_or(String::new(), |n| {
        format!(
            "  {}/{}{}",
            n.device,
            n.channel,
            decoded.map_or(String::new(), |d| format!(" = {d}"))
        )
    });
    println!("address {address}: {kind} {} = {value}{channel}", event.id);
}

async fn stream(
    args: &Args,
    view: Option<&ConfigView>,
    line: LineSettings,
) -> Result<ExitCode, PortError> {
    let mut port = args.port.open()?;
    let specs: Vec<EnableSpec> = if args.enable.is_empty() {
        view.map(|v| v.enable.clone()).unwrap_or_default()
    } else {
        args.enable.clone()
    };
    // A device that cannot take events (a classic one on a mixed bus, one unplugged) is said
    // and left out; the others are watched. Nothing to watch is a failure.
    if !specs.is_empty() && !enable_all(&mut port, line, &specs, None, args.json).await? {
        eprintln!("events were enabled on no device: nothing to watch");
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    if !args.json {
        eprintln!("listening for events at {line} (Ctrl-C to stop)");
    }
    let deadline = args
        .duration
        .filter(|d| d.is_finite() && *d >= 0.0)
        .map(|d| tokio::time::Instant::now() + Duration::from_secs_f64(d.min(1e9)));
    let mut poll = EventPoll {
        min_address: 0,
        max_data_len: MAX_EVENT_DATA,
        ack_address: 0,
        ack_flag: 0,
    };
    let mut events_seen = 0u64;
    let mut repeats = RepeatWatch::default();
    let mut closing_polls = 0;
    let mut round_started = tokio::time::Instant::now();
    let first_byte = line.event_first_byte_timeout();
    let reply = line.event_reply_timeout() + line.wire_time(usize::from(MAX_EVENT_DATA) + 40);
    loop {
        let done = args.count.is_some_and(|c| events_seen >= c)
            || deadline.is_some_and(|d| tokio::time::Instant::now() >= d);
        // After the end, polls only confirm the last packet; a few at most, however busy the bus.
        if done {
            closing_polls += 1;
            if poll.ack_address == 0 || closing_polls > 3 {
                break;
            }
        }
        let outcome = port
            .fast(line, Request::poll_events(poll), first_byte, reply)
            .await?;
        // Only what this poll confirmed is confirmed.
        poll.ack_address = 0;
        poll.ack_flag = 0;
        if let Some((address, packet)) = outcome.event_packet() {
            poll.ack_address = address;
            poll.ack_flag = packet.flag;
            let origin = PacketOrigin {
                address,
                via_service: false,
                repeated: repeats.is_repeat(address, packet.flag, &packet.events),
            };
            print_repeat(origin, args.json);
            for event in &packet.events {
                // Past --count a register event is still confirmed with its packet, not shown.
                let past_count = args.count.is_some_and(|c| events_seen >= c);
                if event.is_reboot() {
                    print_event(origin, event, view, args.json);
                    enable_all(&mut port, line, &specs, Some(address), args.json).await?;
                } else if !past_count {
                    print_event(origin, event, view, args.json);
                    if !done {
                        events_seen += 1;
                    }
                }
            }
            continue;
        }
        if outcome == TransactionOutcome::Garbled {
            tracing::debug!("unreadable reply to an event poll");
        }
        if done {
            break;
        }
        // Rounds (polls until no device has events) start an interval apart, as the daemon's;
        // one that took longer is followed at once.
        let next_round = round_started + line.event_poll_interval();
        let now = tokio::time::Instant::now();
        round_started = if next_round > now {
            tokio::time::sleep_until(next_round).await;
            next_round
        } else {
            now
        };
    }
    port.restore();
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_packet_again_under_the_same_flag_is_a_repeat_until_the_device_restarts() {
        let value = Event {
            source: EventSource::Register(RegisterType::Coil),
            id: 0,
            payload: vec![1],
        };
        let values = std::slice::from_ref(&value);
        let mut repeats = RepeatWatch::default();
        assert!(!repeats.is_repeat(20, 0, values));
        // Another device's packets under the same flag are its own.
        assert!(!repeats.is_repeat(21, 0, values));
        assert!(repeats.is_repeat(20, 0, values));
        assert!(!repeats.is_repeat(20, 1, values));
        // A restart resets the device's flag: not a repeat, whatever the flag.
        assert!(!repeats.is_repeat(20, 1, &[Event::reboot(), value.clone()]));
        assert!(!repeats.is_repeat(20, 0, &[value]));
    }

    #[test]
    fn an_event_value_is_split_into_its_registers_in_their_word_order() {
        let big = WordOrder::BigEndian;
        // 0x0001_0002 little-endian: the high word in the first register.
        let payload = [0x02, 0x00, 0x01, 0x00];
        assert_eq!(value_words(&payload, 2, big), Some(vec![0x0001, 0x0002]));
        // A 16-bit register padded to 32 bits: its low word.
        assert_eq!(value_words(&payload, 1, big), Some(vec![0x0002]));
        // Shorter than the value: not decoded.
        assert_eq!(value_words(&payload[..2], 2, big), None);
        // A bit: one byte.
        assert_eq!(value_words(&[1], 1, big), Some(vec![1]));
    }

    /// A u32 kept least significant word first: the event carries the value 262150
    /// (0x0004_0006, fast-modbus.md §6); its registers are 0x0006, 0x0004, which the channel's
    /// codec decodes back to 262150. Taken high word first, they decoded to 393220.
    #[test]
    fn a_wide_event_value_of_a_low_word_first_channel_decodes_to_the_value() {
        let payload = [0x06, 0x00, 0x04, 0x00];
        let words = value_words(&payload, 2, WordOrder::LittleEndian).unwrap();
        assert_eq!(words, vec![0x0006, 0x0004]);
        let codec = ValueCodec {
            word_order: WordOrder::LittleEndian,
            ..ValueCodec::plain(crate::config::format::RegisterFormat::U32)
        };
        assert_eq!(codec.decode(&words), Ok(Reading::Value("262150".into())));
    }

    #[test]
    fn enable_specs_parse() {
        assert_eq!(
            parse_enable("20:coil:0"),
            Ok(EnableSpec {
                address: 20,
                register_type: RegisterType::Coil,
                register: 0,
                priority: EventPriority::High
            })
        );
        assert_eq!(
            parse_enable("7:input:0x20:low").map(|s| (s.register, s.priority)),
            Ok((32, EventPriority::Low))
        );
        assert!(parse_enable("0:coil:0").is_err());
        assert!(parse_enable("20:relay:0").is_err());
        assert!(parse_enable("20:coil").is_err());
        assert!(parse_enable("20:coil:0:urgent").is_err());
    }
}
