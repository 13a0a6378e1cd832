//! The control protocol: one JSON object per line in, one JSON object per line out.
//! Pure: commands run on a [`Bus`] at a given time. The socket and the script feed it.
//!
//! Every command names a device by `"device"` (its Modbus address, or its name) or `"serial"`.
//! Replies are `{"ok": true, …}` or `{"ok": false, "error": "…"}`, echoing `"id"` when given.
//! See docs/sim.md for the list of commands.

use std::time::Duration;

use serde::Deserialize;
use serde_json::{json, Value};

use crate::protocol::frame::MAX_DEVICE_ADDRESS;
use crate::protocol::{RegisterType, RequestPdu};

use super::bus::Bus;
use super::bus_file::{parse_line, parse_register_type, parse_serial};
use super::device::wb;
use super::faults::Faults;
use super::other_master::OtherMaster;

/// The fields any command may carry; which ones matter depends on `cmd`.
#[derive(Debug, Clone, Default, Deserialize)]
pub struct ControlCommand {
    pub cmd: String,
    #[serde(default)]
    pub id: Option<Value>,
    #[serde(default)]
    pub device: Option<Value>,
    #[serde(default)]
    pub serial: Option<Value>,
    #[serde(default, rename = "type")]
    pub register_type: Option<String>,
    #[serde(default)]
    pub address: Option<u16>,
    #[serde(default)]
    pub count: Option<u16>,
    #[serde(default)]
    pub value: Option<Value>,
    #[serde(default)]
    pub new_address: Option<u8>,
    /// `replace`: the serial number of the device put in its place.
    pub new_serial: Option<Value>,
    #[serde(default)]
    pub line: Option<String>,
    #[serde(default)]
    pub drop: Option<f64>,
    #[serde(default)]
    pub corrupt_crc: Option<f64>,
    #[serde(default)]
    pub delay: Option<f64>,
    #[serde(default)]
    pub delay_ms: Option<u64>,
    #[serde(default)]
    pub exception: Option<f64>,
    #[serde(default)]
    pub garbage: Option<f64>,
    #[serde(default)]
    pub flip_bit: Option<f64>,
    #[serde(default)]
    pub truncate: Option<f64>,
    #[serde(default)]
    pub glitch: Option<f64>,
    /// `faults`: they end after hitting this many replies.
    #[serde(default)]
    pub times: Option<u32>,
    /// `other_master`: its pace; left out or 0 stops it.
    #[serde(default)]
    pub every_ms: Option<u64>,
    /// `other_master`: it waits for a frame gap of silence before it talks.
    #[serde(default)]
    pub listen: Option<bool>,
}

/// What the caller should do after replying.
#[derive(Debug, Clone, PartialEq)]
pub struct ControlReply {
    pub reply: Value,
    /// The connection asked to receive the change log.
    pub watch: bool,
}

pub fn register_type_name(register_type: RegisterType) -> &'static str {
    match register_type {
        RegisterType::Coil => "coil",
        RegisterType::DiscreteInput => "discrete",
        RegisterType::Holding => "holding",
        RegisterType::Input => "input",
    }
}

/// Parses and runs one line.
pub fn execute_line(bus: &mut Bus, now: Duration, line: &str) -> ControlReply {
    match serde_json::from_str::<ControlCommand>(line) {
        Ok(command) => execute(bus, now, &command),
        Err(err) => ControlReply {
            reply: json!({"ok": false, "error": format!("bad command: {err}")}),
            watch: false,
        },
    }
}

pub fn execute(bus: &mut Bus, now: Duration, command: &ControlCommand) -> ControlReply {
    bus.outside_acts(now);
    let watch = command.cmd == "watch";
    let mut reply = match run(bus, now, command) {
        Ok(Value::Object(mut fields)) => {
            fields.insert("ok".into(), Value::Bool(true));
            Value::Object(fields)
        }
        Ok(other) => json!({"ok": true, "result": other}),
        Err(error) => json!({"ok": false, "error": error}),
    };
    if let (Some(id), Value::Object(fields)) = (&command.id, &mut reply) {
        fields.insert("id".into(), id.clone());
    }
    ControlReply { reply, watch }
}

fn run(bus: &mut Bus, now: Duration, command: &ControlCommand) -> Result<Value, String> {
    match command.cmd.as_str() {
        "ping" | "watch" => Ok(json!({})),
        "stats" => {
            let stats = bus.stats();
            Ok(json!({
                "t_us": u64::try_from(now.as_micros()).unwrap_or(u64::MAX),
                "requests": stats.requests,
                "classic_requests": stats.classic_requests,
                "registers_read": stats.registers_read,
                "fast_requests": stats.fast_requests,
                "answered": stats.answered,
                "reply_bytes": stats.reply_bytes,
                "event_polls": stats.event_polls,
                "contended_event_polls": stats.contended_event_polls,
                "max_event_contenders": stats.max_event_contenders,
                "other_master_requests": stats.other_master_requests,
                "other_master_answered": stats.other_master_answered,
            }))
        }
        "list" => Ok(json!({
            "devices": list(bus),
            "t_us": u64::try_from(now.as_micros()).unwrap_or(u64::MAX),
        })),
        "get" => {
            let index = find_device(bus, command)?;
            let (register_type, address) = register(command)?;
            let count = command.count.unwrap_or(1);
            let device = bus.devices().get(index).ok_or("no such device")?;
            let values = device
                .registers()
                .read_range(register_type, address, count)
                .ok_or_else(|| {
                    format!(
                        "no {} register {address} (x{count})",
                        register_type_name(register_type)
                    )
                })?;
            match values.as_slice() {
                [one] if command.count.is_none() => Ok(json!({ "value": one })),
                _ => Ok(json!({ "values": values })),
            }
        }
        "set" => {
            let index = find_device(bus, command)?;
            let (register_type, address) = register(command)?;
            let values = match &command.value {
                Some(Value::Array(items)) => {
                    items.iter().map(to_u16).collect::<Result<Vec<_>, _>>()?
                }
                Some(value) => vec![to_u16(value)?],
                None => return Err("\"value\" missing".into()),
            };
            bus.write_register(index, register_type, address, &values, now)
                .map_err(|code| code.to_string())?;
            Ok(json!({}))
        }
        "toggle" => {
            let index = find_device(bus, command)?;
            let (register_type, address) = register(command)?;
            let current = bus
                .devices()
                .get(index)
                .and_then(|d| d.registers().get(register_type, address))
                .ok_or("no such register")?;
            let value = u16::from(current == 0);
            bus.write_register(index, register_type, address, &[value], now)
                .map_err(|code| code.to_string())?;
            Ok(json!({ "value": value }))
        }
        "reboot" => with_device(bus, command, |d| d.reboot()),
        // A replaced device: another serial number, freshly powered on.
        "replace" => {
            let new_serial = parse_serial(
                command
                    .new_serial
                    .as_ref()
                    .ok_or("\"new_serial\" missing")?,
            )?;
            with_device(bus, command, |d| {
                d.set_serial(new_serial);
                d.reboot();
            })
        }
        "unplug" => with_device(bus, command, |d| d.plugged = false),
        "replug" => with_device(bus, command, |d| d.plugged = true),
        "set_address" => {
            let index = find_device(bus, command)?;
            let new_address = command.new_address.ok_or("\"new_address\" missing")?;
            bus.write_register(
                index,
                RegisterType::Holding,
                wb::ADDRESS,
                &[u16::from(new_address)],
                now,
            )
            .map_err(|code| code.to_string())?;
            Ok(json!({}))
        }
        "set_line" => {
            let index = find_device(bus, command)?;
            let line = parse_line(command.line.as_deref().ok_or("\"line\" missing")?)?;
            let values = [
                u16::try_from(line.baud / 100).map_err(|_| "baud rate too high")?,
                match line.parity {
                    crate::protocol::Parity::None => 0,
                    crate::protocol::Parity::Odd => 1,
                    crate::protocol::Parity::Even => 2,
                },
                u16::from(line.stop_bits),
            ];
            bus.write_register(index, RegisterType::Holding, wb::BAUD, &values, now)
                .map_err(|code| code.to_string())?;
            Ok(json!({}))
        }
        "link_down" => {
            bus.cut_links(true);
            Ok(json!({}))
        }
        "link_up" => {
            bus.restore_links();
            Ok(json!({}))
        }
        "link_drop" => {
            bus.cut_links(false);
            Ok(json!({}))
        }
        "faults" => {
            let index = find_device(bus, command)?;
            let device = bus.device_mut(index).ok_or("no such device")?;
            let defaults = Faults::default();
            device.faults = Faults {
                drop_reply: command.drop.unwrap_or(0.0),
                corrupt_crc: command.corrupt_crc.unwrap_or(0.0),
                delay_reply: command.delay.unwrap_or(0.0),
                delay: command
                    .delay_ms
                    .map_or(defaults.delay, Duration::from_millis),
                exception: command.exception.unwrap_or(0.0),
                garbage: command.garbage.unwrap_or(0.0),
                flip_bit: command.flip_bit.unwrap_or(0.0),
                truncate: command.truncate.unwrap_or(0.0),
                glitch: command.glitch.unwrap_or(0.0),
                times: command.times.filter(|&times| times > 0),
            };
            Ok(json!({}))
        }
        "other_master" => {
            let Some(every) = command.every_ms.filter(|&ms| ms > 0) else {
                bus.set_other_master(None);
                return Ok(json!({}));
            };
            // Any address: the other master may ask for a device that is not there.
            let address = match &command.device {
                Some(Value::Number(n)) => n
                    .as_u64()
                    .and_then(|a| u8::try_from(a).ok())
                    .filter(|a| (1..=MAX_DEVICE_ADDRESS).contains(a))
                    .ok_or("bad address (1..247)")?,
                _ => {
                    let index = find_device(bus, command)?;
                    bus.devices().get(index).ok_or("no such device")?.address()
                }
            };
            let (register_type, start) = register(command)?;
            let count = command.count.unwrap_or(1);
            let pdu = match register_type {
                RegisterType::Coil => RequestPdu::ReadCoils { start, count },
                RegisterType::DiscreteInput => RequestPdu::ReadDiscreteInputs { start, count },
                RegisterType::Holding => RequestPdu::ReadHoldingRegisters { start, count },
                RegisterType::Input => RequestPdu::ReadInputRegisters { start, count },
            };
            let mut other = OtherMaster::reading(address, pdu, Duration::from_millis(every), now)?;
            other.listens = command.listen.unwrap_or(false);
            let frame = crate::protocol::hex(other.frame());
            bus.set_other_master(Some(other));
            Ok(json!({ "frame": frame }))
        }
        other => Err(format!(
            "unknown command {other:?} (ping, list, get, set, toggle, reboot, unplug, replug, \
             set_address, set_line, replace, faults, other_master, link_down, link_up, \
             link_drop, stats, watch)"
        )),
    }
}

fn to_u16(value: &Value) -> Result<u16, String> {
    value
        .as_u64()
        .and_then(|v| u16::try_from(v).ok())
        .ok_or_else(|| format!("not a 16-bit value: {value}"))
}

fn register(command: &ControlCommand) -> Result<(RegisterType, u16), String> {
    let register_type =
        parse_register_type(command.register_type.as_deref().ok_or("\"type\" missing")?)?;
    Ok((register_type, command.address.ok_or("\"address\" missing")?))
}

fn with_device(
    bus: &mut Bus,
    command: &ControlCommand,
    f: impl FnOnce(&mut super::VirtualDevice),
) -> Result<Value, String> {
    let index = find_device(bus, command)?;
    f(bus.device_mut(index).ok_or("no such device")?);
    Ok(json!({}))
}

/// The one device a command names.
pub fn find_device(bus: &Bus, command: &ControlCommand) -> Result<usize, String> {
    let matches: Vec<usize> = match (&command.serial, &command.device) {
        (Some(serial), _) => {
            let serial = parse_serial(serial)?;
            indices(bus, |d| d.serial == serial)
        }
        (None, Some(Value::Number(n))) => {
            let address = n
                .as_u64()
                .and_then(|a| u8::try_from(a).ok())
                .ok_or("bad address")?;
            indices(bus, |d| d.address() == address)
        }
        (None, Some(Value::String(name))) => indices(bus, |d| &d.name == name),
        _ => return Err("name the device: \"device\": address or name, or \"serial\"".into()),
    };
    match matches.as_slice() {
        [one] => Ok(*one),
        [] => Err("no such device".into()),
        _ => Err("several devices match (shared address?): use \"serial\"".into()),
    }
}

fn indices(bus: &Bus, predicate: impl Fn(&super::VirtualDevice) -> bool) -> Vec<usize> {
    bus.devices()
        .iter()
        .enumerate()
        .filter(|(_, d)| predicate(d))
        .map(|(i, _)| i)
        .collect()
}

/// The devices as JSON, for `list` and the start-up banner.
pub fn list(bus: &Bus) -> Vec<Value> {
    bus.devices()
        .iter()
        .map(|d| {
            json!({
                "name": d.name,
                "address": d.address(),
                "serial": format!("0x{:08X}", d.serial),
                "line": d.line().to_string(),
                "fast": d.fast,
                "plugged": d.plugged,
                "template": d.template,
                "starts": d.starts,
                "pending_events": d.events().pending_count(),
                "events_enabled": d.events().enabled().count(),
                "events_configured_t_us": d
                    .events_configured_at
                    .map(|at| u64::try_from(at.as_micros()).unwrap_or(u64::MAX)),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{LineSettings, Parity};
    use crate::sim::{DeviceSpec, RegisterMap, VirtualDevice};

    fn bus() -> Bus {
        let mut registers = RegisterMap::new();
        registers.define(RegisterType::Coil, 0, 2, true);
        let spec = |name: &str, address, serial| DeviceSpec {
            name: name.into(),
            template: "-".into(),
            serial,
            address,
            line: LineSettings::new(9600, Parity::None, 2),
            fast: true,
            turnaround: Duration::ZERO,
            model: "M".into(),
            firmware: "1".into(),
            signature: "s".into(),
            registers: registers.clone(),
        };
        Bus::new(
            vec![
                VirtualDevice::new(spec("a", 20, 1)),
                VirtualDevice::new(spec("b", 20, 2)),
                VirtualDevice::new(spec("c", 30, 3)),
            ],
            1,
        )
    }

    fn run_line(bus: &mut Bus, line: &str) -> Value {
        execute_line(bus, Duration::ZERO, line).reply
    }

    #[test]
    fn commands() {
        let mut bus = bus();
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"set","device":30,"type":"coil","address":1,"value":1,"id":7}"#
            ),
            json!({"ok": true, "id": 7})
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"get","device":"c","type":"coil","address":1}"#
            ),
            json!({"ok": true, "value": 1})
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"toggle","device":30,"type":"coil","address":1}"#
            ),
            json!({"ok": true, "value": 0})
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"get","serial":"0x1","type":"holding","address":128,"count":1}"#
            ),
            json!({"ok": true, "values": [20]})
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"get","device":20,"type":"coil","address":0}"#
            )["ok"],
            json!(false)
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"set_address","serial":2,"new_address":21}"#
            )["ok"],
            json!(true)
        );
        assert_eq!(bus.devices()[1].address(), 21);
        // A replaced device: another serial number, in the registers too, and a fresh start.
        let starts = bus.devices()[1].starts;
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"replace","serial":2,"new_serial":"0x00010002"}"#
            )["ok"],
            json!(true)
        );
        assert_eq!(bus.devices()[1].serial, 0x0001_0002);
        assert_eq!(bus.devices()[1].starts, starts + 1);
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"get","serial":"0x00010002","type":"holding","address":270,"count":2}"#
            ),
            json!({"ok": true, "values": [1, 2]})
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"set_address","serial":2,"new_address":0}"#
            )["ok"],
            json!(false)
        );
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"set_line","device":21,"line":"115200 8E1"}"#
            )["ok"],
            json!(true)
        );
        assert_eq!(
            bus.devices()[1].line(),
            LineSettings::new(115_200, Parity::Even, 1)
        );
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"unplug","device":30}"#)["ok"],
            json!(true)
        );
        assert!(!bus.devices()[2].plugged);
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"faults","device":30,"drop":0.5}"#)["ok"],
            json!(true)
        );
        assert_eq!(bus.devices()[2].faults.drop_reply, 0.5);
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"reboot","device":30}"#)["ok"],
            json!(true)
        );
        assert_eq!(bus.devices()[2].starts, 2);
        assert_eq!(run_line(&mut bus, "not json")["ok"], json!(false));
        assert_eq!(run_line(&mut bus, r#"{"cmd":"fly"}"#)["ok"], json!(false));
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"list"}"#)["devices"]
                .as_array()
                .map(Vec::len),
            Some(3)
        );
        assert!(execute_line(&mut bus, Duration::ZERO, r#"{"cmd":"watch"}"#).watch);
        assert!(bus.link().up);
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"link_down"}"#)["ok"],
            json!(true)
        );
        assert_eq!((bus.link().up, bus.link().generation), (false, 1));
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"link_up"}"#)["ok"],
            json!(true)
        );
        assert_eq!((bus.link().up, bus.link().generation), (true, 1));
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"link_drop"}"#)["ok"],
            json!(true)
        );
        assert_eq!((bus.link().up, bus.link().generation), (true, 2));
        assert_eq!(bus.take_changes().len(), 6);
    }

    #[test]
    fn stats_count_requests_and_registers_read() {
        use crate::protocol::{Request, RequestPdu};
        let mut bus = bus();
        let line = crate::sim::MasterLine::exact(LineSettings::new(9600, Parity::None, 2));
        let read = Request::classic(30, RequestPdu::ReadCoils { start: 0, count: 2 });
        bus.exchange(&read.encode().unwrap(), line, Duration::ZERO);
        let nobody = Request::classic(99, RequestPdu::ReadCoils { start: 0, count: 1 });
        bus.exchange(&nobody.encode().unwrap(), line, Duration::from_secs(1));
        let reply = run_line(&mut bus, r#"{"cmd":"stats"}"#);
        assert_eq!(reply["requests"], 2);
        assert_eq!(reply["classic_requests"], 2);
        assert_eq!(reply["registers_read"], 3);
        assert_eq!(reply["fast_requests"], 0);
        assert_eq!(reply["answered"], 1);
        // 30 01 01 <bits> CRC CRC
        assert_eq!(reply["reply_bytes"], 6);
    }

    #[test]
    fn another_master_is_set_paced_and_stopped() {
        let mut bus = bus();
        let reply = execute_line(
            &mut bus,
            Duration::from_secs(2),
            r#"{"cmd":"other_master","device":30,"type":"coil","address":0,"count":2,"every_ms":200}"#,
        )
        .reply;
        assert_eq!(reply["ok"], json!(true), "{reply}");
        let frame = crate::protocol::parse_hex(reply["frame"].as_str().unwrap()).unwrap();
        let read = crate::protocol::Request::classic(
            30,
            crate::protocol::RequestPdu::ReadCoils { start: 0, count: 2 },
        );
        assert_eq!(frame, read.encode().unwrap());
        assert_eq!(
            bus.other_master_due(),
            Some((Duration::from_millis(2200), false))
        );
        assert_eq!(bus.other_master_turn(Duration::from_millis(2100)), None);
        assert_eq!(
            bus.other_master_turn(Duration::from_millis(2200)),
            Some(frame)
        );
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"stats"}"#)["other_master_requests"],
            1
        );
        // An address no device has is a request all the same.
        assert_eq!(
            run_line(
                &mut bus,
                r#"{"cmd":"other_master","device":99,"type":"input","address":0,"every_ms":50,"listen":true}"#
            )["ok"],
            json!(true)
        );
        assert_eq!(
            bus.other_master_due(),
            Some((Duration::from_millis(50), true))
        );
        for bad in [
            r#"{"cmd":"other_master","device":0,"type":"input","address":0,"every_ms":50}"#,
            r#"{"cmd":"other_master","device":30,"address":0,"every_ms":50}"#,
        ] {
            assert_eq!(run_line(&mut bus, bad)["ok"], json!(false), "{bad}");
        }
        assert_eq!(
            run_line(&mut bus, r#"{"cmd":"other_master","every_ms":0}"#)["ok"],
            json!(true)
        );
        assert_eq!(bus.other_master_due(), None);
    }
}
