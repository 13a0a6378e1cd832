//! `rtu2mqtt read` and `rtu2mqtt write`: one-off register access by address or by serial number,
//! printing raw words and decoded values (mbpoll habits: register numbers as on the wire, from 0).

use std::process::ExitCode;
use std::time::Duration;

use serde_json::json;

use crate::config::format::{RegisterFormat, WordOrder};
use crate::config::values::parse_int_text;
use crate::protocol::pdu::ExceptionCode;
use crate::protocol::{pdu, LineSettings, RegisterType, RequestPdu, ResponsePdu};
use crate::tools::bus::{Answer, PortError, ToolBus, ToolPort};
use crate::tools::exit;
use crate::tools::report::{serial_text, ScanReport};
use crate::tools::values::{
    decode_words, encode_string_field, encode_value, parse_format, value_width,
};

use super::address::{locate, parse_serial};
use super::scan::{block_on_tool, port_failure, PortArgs};
use super::via_mqtt::{
    call_failure, connect_service, line_params, response_words, served_line, ViaMqttArgs,
};
use crate::rpc::client::{CallError, RpcSession};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TypeArg {
    Holding,
    Input,
    Coil,
    Discrete,
}

impl TypeArg {
    pub fn register_type(self) -> RegisterType {
        match self {
            Self::Holding => RegisterType::Holding,
            Self::Input => RegisterType::Input,
            Self::Coil => RegisterType::Coil,
            Self::Discrete => RegisterType::DiscreteInput,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WordOrderArg {
    /// Most significant word first (the Modbus habit).
    Big,
    /// Least significant word first.
    Little,
}

fn parse_register(text: &str) -> Result<u16, String> {
    parse_int_text(text)
        .and_then(|n| u16::try_from(n).ok())
        .ok_or_else(|| format!("register {text:?}: expected 0..65535 (decimal or 0x hex)"))
}

/// Which device, how, and which registers.
#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("target").required(true).args(["address", "serial"])))]
pub struct TargetArgs {
    #[command(flatten)]
    pub port: PortArgs,
    /// The device's Modbus address (classic request).
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=247))]
    pub address: Option<u8>,
    /// The device's serial number (Fast Modbus request by serial number; works at any address,
    /// duplicates included).
    #[arg(long, value_parser = parse_serial)]
    pub serial: Option<u32>,
    /// Register table.
    #[arg(long = "type", value_enum)]
    pub register_type: TypeArg,
    /// First register (decimal or 0x hex), as on the wire.
    #[arg(long, value_parser = parse_register)]
    pub reg: u16,
    /// How to decode the words: u16, s16, u32, s32, u64, s64, float, double, bcd16, string, ...
    #[arg(long, default_value = "u16", value_parser = parse_format)]
    pub format: RegisterFormat,
    /// Word order of values wider than one register.
    #[arg(long, value_enum, default_value = "big")]
    pub word_order: WordOrderArg,
    /// Reply timeout, in ms.
    #[arg(long, default_value_t = 500, value_name = "MS")]
    pub timeout: u64,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub service: ViaMqttArgs,
}

#[derive(clap::Args, Debug)]
pub struct ReadArgs {
    #[command(flatten)]
    pub target: TargetArgs,
    /// Registers (or bits) to read; default: one value of --format.
    #[arg(long)]
    pub count: Option<u16>,
}

#[derive(clap::Args, Debug)]
pub struct WriteArgs {
    #[command(flatten)]
    pub target: TargetArgs,
    /// Value(s) to write: numbers in --format (consecutive values go to consecutive registers);
    /// for coils 0/1 (or on/off).
    #[arg(required = true, num_args = 1.., allow_negative_numbers = true)]
    pub values: Vec<String>,
    /// For a string value: the registers its field takes (20 for a Wiren Board model); the text
    /// is padded with zeros to fill them, as wb-mqtt-serial writes a string channel, so no
    /// character of a longer old text stays. Default: the registers the text needs.
    #[arg(long, value_name = "REGISTERS")]
    pub count: Option<u16>,
    /// Take the device's acknowledgement as the result and read nothing back: for a command
    /// register (a restart, a calibration start) whose device then falls silent or reads it
    /// back as something else.
    #[arg(long)]
    pub no_read_back: bool,
}

/// The device a request goes to, at its port setting.
#[derive(Debug, Clone, Copy)]
pub struct Target {
    pub line: LineSettings,
    pub address: Option<u8>,
    pub serial: Option<u32>,
}

impl Target {
    fn name(&self) -> String {
        match (self.serial, self.address) {
            (Some(serial), _) => format!("serial {}", serial_text(serial)),
            (None, Some(address)) => format!("address {address}"),
            (None, None) => "the device".into(),
        }
    }
}

/// Finds the port setting: the one the options name, else a scan for the serial number or a Fast
/// Modbus device with the address.
async fn resolve(
    port: &mut ToolPort,
    args: &TargetArgs,
) -> Result<Result<Target, String>, PortError> {
    let plan = args.port.plan();
    if let Some(line) = args.port.single_line() {
        return Ok(Ok(Target {
            line,
            address: args.address,
            serial: args.serial,
        }));
    }
    if let Some(serial) = args.serial {
        return Ok(match locate(port, &plan, serial).await? {
            Some((line, _, _)) => Ok(Target {
                line,
                address: None,
                serial: Some(serial),
            }),
            None => Err(format!(
                "no device with serial {} answered a scan at {} port setting(s)",
                serial_text(serial),
                plan.len()
            )),
        });
    }
    let address = args.address.unwrap_or(0);
    // The whole plan: a device with this address at a later setting would otherwise be missed,
    // and the request would go to the first one found without a word about the other.
    let mut scans = Vec::with_capacity(plan.len());
    for &line in &plan {
        let mut report = ScanReport::default();
        let seen = port.scan_setting(line, &mut report).await?;
        let serials = seen
            .iter()
            .filter(|(_, a)| *a == address)
            .map(|(serial, _)| *serial)
            .collect();
        scans.push((line, serials));
    }
    Ok(setting_of_address(address, &scans).map(|line| Target {
        line,
        address: Some(address),
        serial: None,
    }))
}

/// The setting a request by `address` goes to, from the serial numbers a scan of each setting
/// of the plan saw with that address; `Err` says why none is taken.
fn setting_of_address(
    address: u8,
    scans: &[(LineSettings, Vec<u32>)],
) -> Result<LineSettings, String> {
    if let Some((line, serials)) = scans.iter().find(|(_, serials)| serials.len() > 1) {
        return Err(duplicate_address(address, *line, serials));
    }
    // A device that answers at several settings (a parity bit its receiver takes for a stop
    // bit, a pseudo-terminal that has no parity) is one device: its first setting.
    let mut found: Vec<(u32, LineSettings)> = Vec::new();
    for (line, serials) in scans {
        for serial in serials {
            if !found.iter().any(|(s, _)| s == serial) {
                found.push((*serial, *line));
            }
        }
    }
    match found.as_slice() {
        [] => Err(format!(
            "no Fast Modbus device with address {address} answered a scan at {} port setting(s) \
             (a device without Fast Modbus does not answer a scan): for a classic device give \
             --baud, --parity and --stop-bits",
            scans.len()
        )),
        [(_, line)] => Ok(*line),
        several => Err(address_at_several_settings(address, several)),
    }
}

/// Why a request by address is not sent when the scan saw that address at several port
/// settings, on different devices: which one was meant is for the integrator to say.
fn address_at_several_settings(address: u8, found: &[(u32, LineSettings)]) -> String {
    format!(
        "address {address} is used by {} devices at different port settings ({}): nothing was \
         sent. Name one with {}, or give its settings with --baud, --parity and --stop-bits",
        found.len(),
        found
            .iter()
            .map(|(serial, line)| format!("serial {} at {line}", serial_text(*serial)))
            .collect::<Vec<_>>()
            .join(", "),
        found
            .iter()
            .map(|(serial, _)| format!("--serial {serial}"))
            .collect::<Vec<_>>()
            .join(" or ")
    )
}

/// Why a request by address is not sent where the scan has just seen several devices with that
/// address: every one of them would carry it out (a write changes them all) and their replies
/// collide.
fn duplicate_address(address: u8, line: LineSettings, serials: &[u32]) -> String {
    format!(
        "address {address} at {line} is used by {} devices (serial {}): a request by address \
         would reach all of them, so nothing was sent. Name one with {}, or give them distinct \
         addresses first: rtu2mqtt fix-addresses --port …",
        serials.len(),
        serials
            .iter()
            .map(|s| serial_text(*s))
            .collect::<Vec<_>>()
            .join(", "),
        serials
            .iter()
            .map(|s| format!("--serial {s}"))
            .collect::<Vec<_>>()
            .join(" or ")
    )
}

async fn request(
    port: &mut ToolPort,
    target: &Target,
    pdu: RequestPdu,
    timeout: Duration,
) -> Result<Answer, PortError> {
    match (target.serial, target.address) {
        (Some(serial), _) => port.by_serial(target.line, serial, pdu, timeout).await,
        (None, Some(address)) => port.classic(target.line, address, pdu, timeout).await,
        (None, None) => Ok(Answer::NoReply),
    }
}

/// What failed, for the integrator.
fn failure(target: &Target, answer: &Answer, timeout: Duration) -> String {
    match answer {
        Answer::NoReply => format!(
            "no reply from {} at {} within {} ms: check the address/serial, the port settings and \
             the wiring",
            target.name(),
            target.line,
            timeout.as_millis()
        ),
        Answer::Garbled => format!(
            "unreadable reply from {} at {} (bad CRC or two devices answering: a duplicate address?)",
            target.name(),
            target.line
        ),
        Answer::Pdu(ResponsePdu::Exception { code, .. }) => format!(
            "{} at {} refused: {code}",
            target.name(),
            target.line
        ),
        Answer::Pdu(other) => format!("unexpected reply from {}: {other:?}", target.name()),
    }
}

/// [`failure`] of a write, with what it means for the devices: a write whose reply was lost
/// may have been carried out, and an unreadable reply to a write by address is most often two
/// devices answering at once, each of which took it (a site tools audit: both devices of a
/// duplicate address had their coil set, and the tool said only "unreadable reply").
fn failure_of_write(target: &Target, answer: &Answer, timeout: Duration) -> String {
    let mut text = failure(target, answer, timeout);
    match answer {
        Answer::Garbled if target.serial.is_none() => text.push_str(
            "\nif two devices share that address, each of them most likely carried out the \
             write (nothing was verified): `rtu2mqtt scan` lists duplicates, `rtu2mqtt \
             fix-addresses` separates them",
        ),
        Answer::NoReply | Answer::Garbled => text.push_str(
            "\nthe write may have been carried out and only its reply lost: read the register \
             before writing again",
        ),
        Answer::Pdu(_) => {}
    }
    text
}

/// How many registers (or bits) one request may carry, as Modbus allows: reads of 1..=125
/// registers or 1..=2000 bits, writes of 1..=123 registers or 1..=1968 coils.
pub fn span_limit(register_type: RegisterType, write: bool) -> u16 {
    match (register_type.is_bit(), write) {
        (true, false) => 2000,
        (true, true) => 1968,
        (false, false) => 125,
        (false, true) => 123,
    }
}

/// Checks a request's span before the port is opened: a count Modbus allows, and registers that
/// exist (the last one at most 65535).
fn check_span(
    register_type: RegisterType,
    start: u16,
    count: u16,
    write: bool,
) -> Result<(), String> {
    let limit = span_limit(register_type, write);
    let what = if register_type.is_bit() {
        if write {
            "coils"
        } else {
            "bits"
        }
    } else {
        "registers"
    };
    let verb = if write { "write" } else { "read" };
    if !(1..=limit).contains(&count) {
        return Err(format!(
            "{count} {what} to {verb}: one Modbus request carries 1..={limit} {what}"
        ));
    }
    if u32::from(start) + u32::from(count) - 1 > u32::from(u16::MAX) {
        return Err(format!(
            "{count} {what} from {start} go past register 65535"
        ));
    }
    Ok(())
}

fn read_pdu(register_type: RegisterType, start: u16, count: u16) -> RequestPdu {
    match register_type {
        RegisterType::Coil => RequestPdu::ReadCoils { start, count },
        RegisterType::DiscreteInput => RequestPdu::ReadDiscreteInputs { start, count },
        RegisterType::Holding => RequestPdu::ReadHoldingRegisters { start, count },
        RegisterType::Input => RequestPdu::ReadInputRegisters { start, count },
    }
}

/// The words (bits as 0/1) of a read reply.
fn words_of(answer: &Answer, count: u16) -> Option<Vec<u16>> {
    match answer {
        Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values })
        | Answer::Pdu(ResponsePdu::ReadInputRegisters { values }) => Some(values.clone()),
        Answer::Pdu(ResponsePdu::ReadCoils { packed })
        | Answer::Pdu(ResponsePdu::ReadDiscreteInputs { packed }) => Some(
            pdu::unpack_bits(packed, usize::from(count))
                .into_iter()
                .map(u16::from)
                .collect(),
        ),
        _ => None,
    }
}

fn word_order(args: &TargetArgs) -> WordOrder {
    match args.word_order {
        WordOrderArg::Big => WordOrder::BigEndian,
        WordOrderArg::Little => WordOrder::LittleEndian,
    }
}

/// Prints what was read: each register raw, then the decoded values.
fn print_values(args: &TargetArgs, target: &Target, words: &[u16]) -> Result<(), String> {
    let register_type = args.register_type.register_type();
    let bits = register_type.is_bit();
    let decoded = if bits {
        words.iter().map(u16::to_string).collect()
    } else {
        decode_words(args.format, word_order(args), words)?
    };
    let type_name = crate::sim::control::register_type_name(register_type);
    if args.json {
        let body = json!({
            "settings": target.line.to_string(),
            "address": target.address,
            "serial": target.serial,
            "type": type_name,
            "start": args.reg,
            "registers": words,
            "format": if bits { "bit" } else { args.format.name() },
            "values": decoded,
        });
        println!("{body}");
        return Ok(());
    }
    println!(
        "{} at {}, {type_name} {}:",
        target.name(),
        target.line,
        args.reg
    );
    for (offset, word) in words.iter().enumerate() {
        let register = usize::from(args.reg) + offset;
        if bits {
            println!("[{register}]: {word}");
        } else {
            println!("[{register}]: 0x{word:04X}  {word}");
        }
    }
    if !bits && (args.format != RegisterFormat::U16) {
        println!("{}: {}", args.format.name(), decoded.join(" "));
    }
    Ok(())
}

pub fn run_read(args: ReadArgs) -> anyhow::Result<ExitCode> {
    block_on_tool(async move {
        match read(&args).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
}

async fn read(args: &ReadArgs) -> Result<ExitCode, PortError> {
    let target_args = &args.target;
    let register_type = target_args.register_type.register_type();
    let count = args.count.unwrap_or_else(|| {
        if register_type.is_bit() {
            1
        } else {
            value_width(target_args.format, 1)
        }
    });
    if let Err(message) = check_span(register_type, target_args.reg, count, false) {
        eprintln!("{message}");
        return Ok(ExitCode::from(exit::USAGE));
    }
    let Some(mut port) = open_or_service(target_args)? else {
        return Ok(read_via_service(target_args, count).await);
    };
    let target = match resolve(&mut port, target_args).await? {
        Ok(target) => target,
        Err(message) => {
            eprintln!("{message}");
            return Ok(ExitCode::from(exit::NOT_FOUND));
        }
    };
    let timeout = Duration::from_millis(target_args.timeout);
    let answer = request(
        &mut port,
        &target,
        read_pdu(register_type, target_args.reg, count),
        timeout,
    )
    .await?;
    port.restore();
    let Some(words) = words_of(&answer, count) else {
        eprintln!("{}", failure(&target, &answer, timeout));
        return Ok(ExitCode::from(exit::NOT_FOUND));
    };
    if let Err(message) = print_values(target_args, &target, &words) {
        eprintln!("{message}");
        return Ok(ExitCode::from(exit::USAGE));
    }
    Ok(ExitCode::SUCCESS)
}

pub fn run_write(args: WriteArgs) -> anyhow::Result<ExitCode> {
    block_on_tool(async move {
        match write(&args).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
}

/// What `write --no-read-back` says once the device acknowledged the write.
const NOT_READ_BACK: &str = "written: the device acknowledged it (not read back: --no-read-back)";

/// The words `values` encode to in `args`' type and format.
fn encode_all(args: &WriteArgs) -> Result<Vec<u16>, String> {
    let target = &args.target;
    // After `--` (which a negative value needs) everything is a value, options too.
    if let Some(option) = args.values.iter().find(|v| v.starts_with("--")) {
        return Err(format!(
            "{option:?} is not a value: options go before `--` (e.g. `--baud 9600 -- -2`)"
        ));
    }
    if target.register_type.register_type().is_bit() {
        return args
            .values
            .iter()
            .map(|v| match v.to_ascii_lowercase().as_str() {
                "1" | "on" | "true" => Ok(1),
                "0" | "off" | "false" => Ok(0),
                _ => Err(format!("coil value {v:?}: use 0 or 1")),
            })
            .collect();
    }
    let mut words = Vec::new();
    for value in &args.values {
        words.extend(match args.count {
            Some(registers) if target.format.is_string() => {
                encode_string_field(target.format, value, registers)?
            }
            Some(_) => {
                return Err(
                    "--count is for a string value (the registers its field takes); a value of \
                     another format takes its format's registers: give several values for \
                     consecutive registers"
                        .to_owned(),
                )
            }
            None => encode_value(target.format, word_order(target), value)?,
        });
    }
    Ok(words)
}

fn write_pdu(register_type: RegisterType, start: u16, words: &[u16]) -> Option<RequestPdu> {
    Some(match (register_type, words) {
        (RegisterType::Coil, [one]) => RequestPdu::WriteSingleCoil {
            address: start,
            value: *one != 0,
        },
        (RegisterType::Coil, _) => RequestPdu::WriteMultipleCoils {
            start,
            values: words.iter().map(|w| *w != 0).collect(),
        },
        (RegisterType::Holding, [one]) => RequestPdu::WriteSingleRegister {
            address: start,
            value: *one,
        },
        (RegisterType::Holding, _) => RequestPdu::WriteMultipleRegisters {
            start,
            values: words.to_vec(),
        },
        _ => return None,
    })
}

async fn write(args: &WriteArgs) -> Result<ExitCode, PortError> {
    let target_args = &args.target;
    let register_type = target_args.register_type.register_type();
    let words = match encode_all(args) {
        Ok(words) => words,
        Err(message) => {
            eprintln!("{message}");
            return Ok(ExitCode::from(exit::USAGE));
        }
    };
    if target_args.format.is_string() && args.count.is_none() {
        eprintln!(
            "note: only the {} register(s) the text needs are written: characters of a longer \
             old text after them stay (give --count with the field's size to clear them)",
            words.len()
        );
    }
    let Some(pdu) = write_pdu(register_type, target_args.reg, &words) else {
        eprintln!(
            "input registers and discrete inputs are read-only: write holding registers or coils"
        );
        return Ok(ExitCode::from(exit::USAGE));
    };
    let count = u16::try_from(words.len()).unwrap_or(u16::MAX);
    if let Err(message) = check_span(register_type, target_args.reg, count, true) {
        eprintln!("{message}");
        return Ok(ExitCode::from(exit::USAGE));
    }
    let Some(mut port) = open_or_service(target_args)? else {
        return Ok(write_via_service(target_args, &pdu, &words, args.no_read_back).await);
    };
    let target = match resolve(&mut port, target_args).await? {
        Ok(target) => target,
        Err(message) => {
            eprintln!("{message}");
            return Ok(ExitCode::from(exit::NOT_FOUND));
        }
    };
    let timeout = Duration::from_millis(target_args.timeout);
    let answer = request(&mut port, &target, pdu, timeout).await?;
    let written = matches!(
        answer,
        Answer::Pdu(
            ResponsePdu::WriteSingleCoil { .. }
                | ResponsePdu::WriteSingleRegister { .. }
                | ResponsePdu::WriteMultipleCoils { .. }
                | ResponsePdu::WriteMultipleRegisters { .. }
        )
    );
    if !written {
        eprintln!("{}", failure_of_write(&target, &answer, timeout));
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    if args.no_read_back {
        port.restore();
        println!("{NOT_READ_BACK}");
        return Ok(ExitCode::SUCCESS);
    }
    // Read back: what the device holds now (a device may clamp or refuse silently).
    let back = request(
        &mut port,
        &target,
        read_pdu(register_type, target_args.reg, count),
        timeout,
    )
    .await?;
    port.restore();
    match words_of(&back, count) {
        Some(now) => {
            if !target_args.json {
                println!("written; read back:");
            }
            if let Err(message) = print_values(target_args, &target, &now) {
                eprintln!("{message}");
            }
            if now != words {
                eprintln!(
                    "the device holds {now:?} after writing {words:?}: it may clamp or ignore \
                     this value"
                );
                return Ok(ExitCode::from(exit::NOT_FOUND));
            }
            Ok(ExitCode::SUCCESS)
        }
        // The write was answered, but what the device holds now is not known: not verified.
        None => {
            eprintln!(
                "written, but reading back failed: {}",
                failure(&target, &back, timeout)
            );
            Ok(ExitCode::from(exit::NOT_FOUND))
        }
    }
}

/// The port, or `None` when the request goes through the running service: asked for with
/// `--via-mqtt`, or the port is busy and the broker is known.
fn open_or_service(args: &TargetArgs) -> Result<Option<ToolPort>, PortError> {
    if args.service.via_mqtt {
        return Ok(None);
    }
    match args.port.open() {
        Ok(port) => Ok(Some(port)),
        Err(PortError::Busy { path }) if args.service.can_reach_service() => {
            eprintln!("{path} is busy: asking the running rtu2mqtt service over MQTT");
            Ok(None)
        }
        Err(err) => Err(err),
    }
}

/// The device and settings a request through the service goes to: the settings the options
/// name, else the ones the service runs the port at.
async fn service_target(args: &TargetArgs, session: &mut RpcSession) -> Result<Target, ExitCode> {
    // Looked up even with the settings given: a typo in the port is said at once, and beside
    // another RPC server the request waits for the one that serves it (`port_is_served`).
    let served = served_line(session, &args.port.port).await?;
    let line = args.port.single_line().unwrap_or(served);
    Ok(Target {
        line,
        address: args.address,
        serial: args.serial,
    })
}

/// One Modbus request through the service's `port/Load`: the data words of the reply (none for
/// a write), or why there are none in the words the direct path uses (`failure`). `Err` is the
/// exit code when the service itself could not be asked (the reason printed).
async fn load_via_service(
    args: &TargetArgs,
    session: &mut RpcSession,
    target: &Target,
    pdu: &RequestPdu,
    count: u16,
    message: &[u8],
) -> Result<Result<Vec<u16>, String>, ExitCode> {
    let timeout = Duration::from_millis(args.timeout);
    let mut params = line_params(&target.line);
    params["path"] = json!(args.port.port);
    params["protocol"] = json!("modbus");
    params["function"] = json!(pdu.function());
    params["address"] = json!(args.reg);
    params["count"] = json!(count);
    params["format"] = json!("HEX");
    params["msg"] = json!(crate::protocol::hex(message).replace(' ', ""));
    params["response_timeout"] = json!(args.timeout);
    match (target.serial, target.address) {
        (Some(serial), _) => params["sn"] = json!(serial),
        (None, address) => params["slave_id"] = json!(address),
    }
    let called = session
        .call("port", "Load", params, timeout + SERVICE_MARGIN)
        .await;
    let result = match called {
        Ok(result) => result,
        Err(CallError::Refused(refused)) => match super::via_mqtt::answer_of_refusal(&refused) {
            Some(answer) if pdu.is_write() => {
                return Ok(Err(failure_of_write(target, &answer, timeout)))
            }
            Some(answer) => return Ok(Err(failure(target, &answer, timeout))),
            None => return Err(call_failure(&CallError::Refused(refused))),
        },
        Err(err) => return Err(call_failure(&err)),
    };
    if let Some(exception) = result.get("exception") {
        let code = exception["code"]
            .as_u64()
            .and_then(|code| u8::try_from(code).ok())
            .unwrap_or(0);
        let refused = Answer::Pdu(ResponsePdu::Exception {
            function: pdu.function(),
            code: ExceptionCode(code),
        });
        return Ok(Err(failure(target, &refused, timeout)));
    }
    let bits = args.register_type.register_type().is_bit();
    Ok(result["response"]
        .as_str()
        .and_then(|response| response_words(response, bits, count))
        .ok_or_else(|| "the service's reply holds no register data".to_owned()))
}

/// Time a request through the service may take beyond its reply timeout: its turn on the bus.
const SERVICE_MARGIN: Duration = Duration::from_secs(5);

async fn read_via_service(args: &TargetArgs, count: u16) -> ExitCode {
    let mut session = match connect_service(&args.service).await {
        Ok(session) => session,
        Err(code) => return code,
    };
    let target = match service_target(args, &mut session).await {
        Ok(target) => target,
        Err(code) => return code,
    };
    let pdu = read_pdu(args.register_type.register_type(), args.reg, count);
    let words = match load_via_service(args, &mut session, &target, &pdu, count, &[]).await {
        Ok(Ok(words)) => words,
        Ok(Err(why)) => {
            eprintln!("{why}");
            return ExitCode::from(exit::NOT_FOUND);
        }
        Err(code) => return code,
    };
    if let Err(message) = print_values(args, &target, &words) {
        eprintln!("{message}");
        return ExitCode::from(exit::USAGE);
    }
    ExitCode::SUCCESS
}

async fn write_via_service(
    args: &TargetArgs,
    pdu: &RequestPdu,
    words: &[u16],
    no_read_back: bool,
) -> ExitCode {
    let mut session = match connect_service(&args.service).await {
        Ok(session) => session,
        Err(code) => return code,
    };
    let target = match service_target(args, &mut session).await {
        Ok(target) => target,
        Err(code) => return code,
    };
    let count = u16::try_from(words.len()).unwrap_or(u16::MAX);
    let message: Vec<u8> = match pdu {
        RequestPdu::WriteSingleCoil { value, .. } => vec![if *value { 0xFF } else { 0 }, 0],
        RequestPdu::WriteMultipleCoils { values, .. } => {
            let mut packed = vec![0u8; values.len().div_ceil(8)];
            for (i, on) in values.iter().enumerate() {
                if *on {
                    if let Some(byte) = packed.get_mut(i / 8) {
                        *byte |= 1 << (i % 8);
                    }
                }
            }
            packed
        }
        _ => words.iter().flat_map(|w| w.to_be_bytes()).collect(),
    };
    match load_via_service(args, &mut session, &target, pdu, count, &message).await {
        Ok(Ok(_)) => {}
        Ok(Err(why)) => {
            eprintln!("{why}");
            return ExitCode::from(exit::NOT_FOUND);
        }
        Err(code) => return code,
    }
    if no_read_back {
        println!("{NOT_READ_BACK}");
        return ExitCode::SUCCESS;
    }
    let read = read_pdu(args.register_type.register_type(), args.reg, count);
    match load_via_service(args, &mut session, &target, &read, count, &[]).await {
        Ok(Ok(now)) => {
            if !args.json {
                println!("written; read back:");
            }
            if let Err(message) = print_values(args, &target, &now) {
                eprintln!("{message}");
            }
            if now != words {
                eprintln!(
                    "the device holds {now:?} after writing {words:?}: it may clamp or ignore \
                     this value"
                );
                return ExitCode::from(exit::NOT_FOUND);
            }
            ExitCode::SUCCESS
        }
        // The write was answered, but what the device holds now is not known: not verified.
        Ok(Err(why)) => {
            eprintln!("written, but reading back failed: {why}");
            ExitCode::from(exit::NOT_FOUND)
        }
        Err(_) => {
            eprintln!("written, but reading back through the service failed");
            ExitCode::from(exit::NOT_FOUND)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_by_address_goes_where_exactly_one_device_has_it() {
        let n9600 = LineSettings::new(9600, crate::protocol::Parity::None, 2);
        let e9600 = LineSettings::new(9600, crate::protocol::Parity::Even, 2);
        let n115200 = LineSettings::new(115_200, crate::protocol::Parity::None, 2);
        // Seen at two settings, one serial number: one device, at its first setting.
        let scans = [
            (n9600, vec![]),
            (n115200, vec![0xFE00_0020]),
            (e9600, vec![0xFE00_0020]),
        ];
        assert_eq!(setting_of_address(20, &scans), Ok(n115200));
        // Two devices at different settings: neither is picked.
        let scans = [(n9600, vec![0xFE00_0020]), (n115200, vec![0xFE00_0021])];
        let refused = setting_of_address(20, &scans).unwrap_err();
        for words in [
            "address 20 is used by 2 devices at different port settings",
            "serial 4261412896 (0xFE000020) at 9600 8N2",
            "serial 4261412897 (0xFE000021) at 115200 8N2",
            "--serial 4261412896 or --serial 4261412897",
            "--baud, --parity and --stop-bits",
        ] {
            assert!(refused.contains(words), "{words:?} in {refused}");
        }
        // Two devices at one setting: the duplicate refusal, whatever comes later.
        let scans = [
            (n9600, vec![0xFE00_0010, 0xFE00_0011]),
            (n115200, vec![0xFE00_0020]),
        ];
        assert!(setting_of_address(10, &scans)
            .unwrap_err()
            .contains("address 10 at 9600 8N2 is used by 2 devices"));
        let refused = setting_of_address(40, &[(n9600, vec![]), (n115200, vec![])]).unwrap_err();
        assert!(
            refused.contains("at 2 port setting(s)") && refused.contains("without Fast Modbus"),
            "{refused}"
        );
    }

    #[test]
    fn request_spans_are_checked_as_modbus_allows() {
        assert!(check_span(RegisterType::Holding, 0, 125, false).is_ok());
        assert!(check_span(RegisterType::Input, 0, 0, false).is_err());
        assert!(check_span(RegisterType::Holding, 0, 126, false)
            .unwrap_err()
            .contains("1..=125 registers"));
        assert!(check_span(RegisterType::Coil, 0, 2000, false).is_ok());
        assert!(check_span(RegisterType::DiscreteInput, 0, 2001, false).is_err());
        assert!(check_span(RegisterType::Holding, 0, 124, true).is_err());
        assert!(check_span(RegisterType::Coil, 0, 1968, true).is_ok());
        assert!(check_span(RegisterType::Holding, 65535, 1, false).is_ok());
        assert!(check_span(RegisterType::Holding, 65535, 2, false)
            .unwrap_err()
            .contains("past register 65535"));
    }
}
