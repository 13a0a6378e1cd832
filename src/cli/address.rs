//! `rtu2mqtt set-address` and `rtu2mqtt fix-addresses`: change Modbus addresses by serial number
//! (Fast Modbus 0x46 0x08), so devices that share an address are told apart without unplugging
//! anything, and check the result with a new scan. When the port is busy (the service holds
//! it) or with `--via-mqtt`, the same goes through the running service: `port/Scan` to find
//! the devices, `port/Setup` by serial number (`sn`) to write the address, `port/Load` by
//! serial number (rtu2mqtt's `sn` extension) to read it back.

use std::process::ExitCode;

use anyhow::Context as _;

use crate::config::values::parse_int_text;
use crate::protocol::{LineSettings, RequestPdu, ResponsePdu};
use crate::tools::bus::{Answer, PortError, ToolBus, ToolPort, KNOWN_DEVICE_TIMEOUT};
use crate::tools::exit;
use crate::tools::plan::parse_range;
use crate::tools::report::{serial_text, AddressChange, ScanReport};

use super::scan::{block_on_tool, port_failure, PortArgs};
use super::via_mqtt::{line_params, response_words, scan_setting_via_service, ViaMqttArgs};
use crate::rpc::client::RpcSession;

/// The Wiren Board holding register with the device's Modbus address.
pub const ADDRESS_REGISTER: u16 = 128;

/// A serial number as printed on the device (decimal) or in hex (`0xFE4000AC`).
pub fn parse_serial(text: &str) -> Result<u32, String> {
    parse_int_text(text)
        .and_then(|n| u32::try_from(n).ok())
        .ok_or_else(|| format!("serial number {text:?}: expected e.g. 4265607340 or 0xFE4000AC"))
}

fn parse_address(text: &str) -> Result<u8, String> {
    text.parse::<u8>()
        .ok()
        .filter(|a| (1..=247).contains(a))
        .ok_or_else(|| format!("address {text:?}: Modbus addresses are 1..247"))
}

#[derive(clap::Args, Debug)]
pub struct SetAddressArgs {
    #[command(flatten)]
    pub port: PortArgs,
    /// The device's serial number (decimal, or hex with 0x).
    #[arg(long, value_parser = parse_serial)]
    pub serial: u32,
    /// The new Modbus address (1..247).
    #[arg(long, value_parser = parse_address)]
    pub address: u8,
    /// Change it even when another device already uses that address at the same setting.
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub service: ViaMqttArgs,
}

#[derive(clap::Args, Debug)]
pub struct FixAddressesArgs {
    #[command(flatten)]
    pub port: PortArgs,
    /// Addresses the free ones are chosen from.
    #[arg(long, default_value = "1-247", value_parser = parse_range)]
    pub range: (u8, u8),
    /// Write the new addresses (without it: only show the plan).
    #[arg(long)]
    pub apply: bool,
    #[command(flatten)]
    pub service: ViaMqttArgs,
}

/// The bus the address tools work on: the port itself, or the running service holding it.
pub enum AddressBus {
    Direct(Box<ToolPort>),
    Service { session: RpcSession, path: String },
}

impl AddressBus {
    /// The port, or the service when `--via-mqtt` is given or the port is busy and the broker
    /// is known.
    pub async fn open(port: &PortArgs, service: &ViaMqttArgs) -> Result<Self, PortError> {
        if !service.via_mqtt {
            match port.open() {
                Err(PortError::Busy { path }) if service.can_reach_service() => {
                    eprintln!(
                        "{path} is busy: going through the running rtu2mqtt service (MQTT RPC)"
                    );
                }
                other => return other.map(|port| Self::Direct(Box::new(port))),
            }
        }
        let broker = service.broker_config().map_err(PortError::Service)?;
        let session = RpcSession::connect(&broker)
            .await
            .map_err(|err| PortError::Service(err.to_string()))?;
        Ok(Self::Service {
            session,
            path: port.port.clone(),
        })
    }

    async fn scan_setting(
        &mut self,
        line: LineSettings,
        report: &mut ScanReport,
    ) -> Result<Vec<(u32, u8)>, PortError> {
        match self {
            Self::Direct(port) => port.scan_setting(line, report).await,
            Self::Service { session, path } => {
                scan_setting_via_service(session, path, line, report).await
            }
        }
    }

    /// Every setting of `plan`, with each device's identity (the service reads it with its
    /// scan).
    async fn fast_scan(
        &mut self,
        plan: &[LineSettings],
        report: &mut ScanReport,
    ) -> Result<(), PortError> {
        match self {
            Self::Direct(port) => super::scan::fast_scan(port, plan, report).await,
            Self::Service { session, path } => {
                for &line in plan {
                    report.settings_tried.push(line);
                    scan_setting_via_service(session, path, line, report).await?;
                }
                Ok(())
            }
        }
    }

    fn restore(&mut self) {
        if let Self::Direct(port) = self {
            port.restore();
        }
    }
}

/// Scans setting after setting until the device with `serial` answers; the report of that
/// setting (every Fast Modbus device there) comes with it.
pub async fn locate(
    port: &mut ToolPort,
    plan: &[LineSettings],
    serial: u32,
) -> Result<Option<(LineSettings, u8, ScanReport)>, PortError> {
    for &line in plan {
        let mut report = ScanReport::default();
        report.settings_tried.push(line);
        let seen = port.scan_setting(line, &mut report).await?;
        if let Some((_, address)) = seen.iter().find(|(s, _)| *s == serial) {
            return Ok(Some((line, *address, report)));
        }
    }
    Ok(None)
}

/// [`locate`], on the port or through the service.
async fn locate_on_bus(
    port: &mut AddressBus,
    plan: &[LineSettings],
    serial: u32,
) -> Result<Option<(LineSettings, u8, ScanReport)>, PortError> {
    for &line in plan {
        let mut report = ScanReport::default();
        report.settings_tried.push(line);
        let seen = port.scan_setting(line, &mut report).await?;
        if let Some((_, address)) = seen.iter().find(|(s, _)| *s == serial) {
            return Ok(Some((line, *address, report)));
        }
    }
    Ok(None)
}

/// Writes the address register by serial number; Err with the reason when the device refuses.
/// Through the service: `port/Setup` with `sn` (as Wiren Board's device manager does it).
async fn write_address(
    bus: &mut AddressBus,
    line: LineSettings,
    serial: u32,
    from: u8,
    address: u8,
) -> Result<Result<(), String>, PortError> {
    let port = match bus {
        AddressBus::Direct(port) => port,
        AddressBus::Service { session, path } => {
            let mut item = line_params(&line);
            item["slave_id"] = serde_json::json!(from);
            item["sn"] = serde_json::json!(serial);
            item["cfg"] = serde_json::json!({ "slave_id": address });
            let params = serde_json::json!({ "path": path, "items": [item] });
            return Ok(
                match session
                    .call("port", "Setup", params, std::time::Duration::from_secs(10))
                    .await
                {
                    Ok(_) => Ok(()),
                    Err(crate::rpc::client::CallError::Refused(why)) => Err(why.message),
                    Err(err) => return Err(PortError::Service(err.to_string())),
                },
            );
        }
    };
    let pdu = RequestPdu::WriteSingleRegister {
        address: ADDRESS_REGISTER,
        value: u16::from(address),
    };
    Ok(
        match port
            .by_serial(line, serial, pdu, KNOWN_DEVICE_TIMEOUT)
            .await?
        {
            Answer::Pdu(ResponsePdu::WriteSingleRegister { value, .. })
                if value == u16::from(address) =>
            {
                Ok(())
            }
            Answer::Pdu(ResponsePdu::Exception { code, .. }) => Err(format!(
                "the device refused to change its address: {}",
                code.description()
            )),
            Answer::Pdu(other) => Err(format!("unexpected reply: {other:?}")),
            Answer::NoReply => Err("no reply to the write".into()),
            Answer::Garbled => Err("unreadable reply to the write (bad CRC)".into()),
        },
    )
}

/// The address the device with `serial` reports now, read back by serial number.
async fn read_address(
    bus: &mut AddressBus,
    line: LineSettings,
    serial: u32,
) -> Result<Option<u16>, PortError> {
    let port = match bus {
        AddressBus::Direct(port) => port,
        AddressBus::Service { session, path } => {
            let mut params = line_params(&line);
            params["path"] = serde_json::json!(path);
            params["protocol"] = serde_json::json!("modbus");
            params["sn"] = serde_json::json!(serial);
            params["function"] = serde_json::json!(3);
            params["address"] = serde_json::json!(ADDRESS_REGISTER);
            params["count"] = serde_json::json!(1);
            params["format"] = serde_json::json!("HEX");
            return Ok(
                match session
                    .call("port", "Load", params, std::time::Duration::from_secs(10))
                    .await
                {
                    Ok(result) => result["response"]
                        .as_str()
                        .and_then(|hex| response_words(hex, false, 1))
                        .and_then(|words| words.first().copied()),
                    Err(crate::rpc::client::CallError::Refused(_)) => None,
                    Err(err) => return Err(PortError::Service(err.to_string())),
                },
            );
        }
    };
    let pdu = RequestPdu::ReadHoldingRegisters {
        start: ADDRESS_REGISTER,
        count: 1,
    };
    Ok(
        match port
            .by_serial(line, serial, pdu, KNOWN_DEVICE_TIMEOUT)
            .await?
        {
            Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => values.first().copied(),
            _ => None,
        },
    )
}

pub fn run_set_address(args: SetAddressArgs) -> anyhow::Result<ExitCode> {
    block_on_tool(async move {
        match set_address(&args).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
}

async fn set_address(args: &SetAddressArgs) -> Result<ExitCode, PortError> {
    let mut port = AddressBus::open(&args.port, &args.service).await?;
    let plan = args.port.plan();
    let serial = serial_text(args.serial);
    let Some((line, old, report)) = locate_on_bus(&mut port, &plan, args.serial).await? else {
        eprintln!(
            "no device with serial {serial} answered a Fast Modbus scan at {} port setting(s) of \
             {}: check the number (decimal or 0x hex) and the wiring",
            plan.len(),
            args.port.port
        );
        return Ok(ExitCode::from(exit::NOT_FOUND));
    };
    if old == args.address {
        println!("serial {serial} already has address {old} ({line}); nothing to do");
        return Ok(ExitCode::SUCCESS);
    }
    let taken_by: Vec<String> = report
        .devices
        .iter()
        .filter(|d| d.address == args.address && d.serial != Some(args.serial))
        .filter_map(|d| d.serial.map(serial_text))
        .collect();
    if !taken_by.is_empty() && !args.force {
        eprintln!(
            "address {} is already used at {line} by serial {}: choose another (rtu2mqtt scan \
             lists the used ones) or add --force",
            args.address,
            taken_by.join(", ")
        );
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    if let Err(reason) = write_address(&mut port, line, args.serial, old, args.address).await? {
        eprintln!("serial {serial} at {line}: {reason}; the address stays {old}");
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    let read_back = read_address(&mut port, line, args.serial).await?;
    let mut check = ScanReport::default();
    let seen = port.scan_setting(line, &mut check).await?;
    port.restore();
    let scanned = seen
        .iter()
        .find(|(s, _)| *s == args.serial)
        .map(|(_, a)| *a);
    if read_back == Some(u16::from(args.address)) && scanned == Some(args.address) {
        println!(
            "serial {serial} at {line}: address {old} -> {} (read back and confirmed by a scan)",
            args.address
        );
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!(
            "serial {serial} at {line}: wrote address {} but the device reports {} and the scan \
             shows {}",
            args.address,
            read_back.map_or("nothing".into(), |a| a.to_string()),
            scanned.map_or("nothing".into(), |a| a.to_string())
        );
        Ok(ExitCode::from(exit::NOT_FOUND))
    }
}

pub fn run_fix_addresses(args: FixAddressesArgs) -> anyhow::Result<ExitCode> {
    block_on_tool(async move {
        match fix_addresses(&args).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
    .context("fix-addresses")
}

fn print_changes(changes: &[AddressChange], applied: bool) {
    for change in changes {
        println!(
            "serial {} at {}: address {} -> {}{}",
            serial_text(change.serial),
            change.line,
            change.from,
            change.to,
            if applied { "" } else { " (planned)" }
        );
    }
}

async fn fix_addresses(args: &FixAddressesArgs) -> Result<ExitCode, PortError> {
    let mut port = AddressBus::open(&args.port, &args.service).await?;
    let plan = args.port.plan();
    let mut report = ScanReport::default();
    port.fast_scan(&plan, &mut report).await?;
    let duplicates = report.duplicates();
    if duplicates.is_empty() {
        println!(
            "no duplicate addresses among {} Fast Modbus device(s) at {} setting(s)",
            report.devices.len(),
            plan.len()
        );
        return Ok(ExitCode::SUCCESS);
    }
    let address_plan = report.plan_addresses(args.range);
    for problem in &address_plan.unresolved {
        eprintln!("cannot fix: {problem}");
    }
    if !args.apply {
        print_changes(&address_plan.changes, false);
        println!("dry run: nothing written; add --apply to write these addresses");
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    let mut failed = false;
    for change in &address_plan.changes {
        if let Err(reason) = write_address(
            &mut port,
            change.line,
            change.serial,
            change.from,
            change.to,
        )
        .await?
        {
            failed = true;
            eprintln!(
                "serial {} at {}: {reason}",
                serial_text(change.serial),
                change.line
            );
        }
    }
    // Verify with a new scan of the settings that had duplicates.
    let mut lines: Vec<LineSettings> = duplicates.iter().map(|d| d.line).collect();
    lines.dedup();
    let mut check = ScanReport::default();
    port.fast_scan(&lines, &mut check).await?;
    port.restore();
    for change in &address_plan.changes {
        let now = check
            .devices
            .iter()
            .find(|d| d.serial == Some(change.serial))
            .map(|d| d.address);
        if now == Some(change.to) {
            println!(
                "serial {} at {}: address {} -> {} (confirmed by a new scan)",
                serial_text(change.serial),
                change.line,
                change.from,
                change.to
            );
        } else {
            failed = true;
            eprintln!(
                "serial {} at {}: expected address {} after the change, the scan shows {}",
                serial_text(change.serial),
                change.line,
                change.to,
                now.map_or("no device".into(), |a| a.to_string())
            );
        }
    }
    let left = check.duplicates();
    for duplicate in &left {
        eprintln!(
            "still duplicate: address {} at {}",
            duplicate.address, duplicate.line
        );
    }
    Ok(
        if failed || !left.is_empty() || !address_plan.unresolved.is_empty() {
            ExitCode::from(exit::NOT_FOUND)
        } else {
            ExitCode::SUCCESS
        },
    )
}
