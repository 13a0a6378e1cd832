//! `rtu2mqtt set-address` and `rtu2mqtt fix-addresses`: change Modbus addresses by serial number
//! (Fast Modbus 0x46 0x08), so devices that share an address are told apart without unplugging
//! anything, and check the result with a new scan.

use std::process::ExitCode;

use anyhow::Context as _;

use crate::config::values::parse_int_text;
use crate::protocol::{LineSettings, RequestPdu, ResponsePdu};
use crate::tools::bus::{Answer, PortError, ToolBus, ToolPort, KNOWN_DEVICE_TIMEOUT};
use crate::tools::exit;
use crate::tools::plan::parse_range;
use crate::tools::report::{serial_text, AddressChange, ScanReport};

use super::scan::{block_on_tool, port_failure, PortArgs};

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
    pub service: super::via_mqtt::ViaMqttArgs,
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
    pub service: super::via_mqtt::ViaMqttArgs,
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

/// Writes the address register by serial number; Err with the reason when the device refuses.
async fn write_address(
    port: &mut ToolPort,
    line: LineSettings,
    serial: u32,
    address: u8,
) -> Result<Result<(), String>, PortError> {
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

pub fn run_set_address(args: SetAddressArgs) -> anyhow::Result<ExitCode> {
    block_on_tool(async move {
        match set_address(&args).await {
            Ok(code) => Ok(code),
            Err(err) => Ok(port_failure(&err)),
        }
    })
}

async fn set_address(args: &SetAddressArgs) -> Result<ExitCode, PortError> {
    if !args.service.via_mqtt {
        match args.port.open() {
            Err(PortError::Busy { path }) if args.service.can_reach_service() => {
                eprintln!(
                    "{path} is busy: changing the address through the running rtu2mqtt service \
                     (MQTT RPC)"
                );
            }
            other => {
                let mut port = other?;
                let code = set_address_on(&mut port, args, args.port.plan()).await;
                port.restore();
                return Ok(code);
            }
        }
    }
    let (mut service, home) = match ServiceBus::connect(&args.service, &args.port.port).await {
        Ok(connected) => connected,
        Err(code) => return Ok(code),
    };
    // The service's own settings first: where its devices most likely are (the plan's setting
    // that differs from them only in stop bits is the same one on the wire).
    let mut plan = args.port.plan();
    if let Some(index) = plan
        .iter()
        .position(|l| crate::tools::plan::same_on_the_wire(l, &home))
    {
        plan.remove(index);
        plan.insert(0, home);
    }
    let code = set_address_on(&mut service, args, plan).await;
    if code == ExitCode::SUCCESS {
        eprintln!(
            "if the service polls this device, change its slave_id in the service's config too"
        );
    }
    Ok(code)
}

/// Finds the device by serial number (setting after setting), writes its new address and
/// confirms it with a new scan of that setting.
async fn set_address_on(
    bus: &mut impl AddressBus,
    args: &SetAddressArgs,
    plan: Vec<LineSettings>,
) -> ExitCode {
    set_address_steps(bus, args, &plan)
        .await
        .unwrap_or_else(|code| code)
}

async fn set_address_steps(
    bus: &mut impl AddressBus,
    args: &SetAddressArgs,
    plan: &[LineSettings],
) -> Result<ExitCode, ExitCode> {
    let serial = serial_text(args.serial);
    let address_at = |report: &ScanReport| {
        report
            .devices
            .iter()
            .find(|d| d.serial == Some(args.serial))
            .map(|d| d.address)
    };
    let mut found = None;
    for &line in plan {
        let mut report = ScanReport::default();
        bus.scan(&[line], &mut report).await?;
        if let Some(address) = address_at(&report) {
            found = Some((line, address, report));
            break;
        }
    }
    let Some((line, old, report)) = found else {
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
    let change = AddressChange {
        serial: args.serial,
        line,
        from: old,
        to: args.address,
    };
    if let Err(reason) = bus.write_address(&change).await? {
        eprintln!("serial {serial} at {line}: {reason}; the address stays {old}");
        return Ok(ExitCode::from(exit::NOT_FOUND));
    }
    let mut check = ScanReport::default();
    bus.scan(&[line], &mut check).await?;
    let scanned = address_at(&check);
    if scanned == Some(args.address) {
        println!(
            "serial {serial} at {line}: address {old} -> {} (confirmed by a scan)",
            args.address
        );
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!(
            "serial {serial} at {line}: wrote address {} but the scan shows {}",
            args.address,
            scanned.map_or("nothing".into(), |a| a.to_string())
        );
        Ok(ExitCode::from(exit::NOT_FOUND))
    }
}

/// The Fast Modbus devices at one setting of a port the service holds, as (serial, address).
async fn scan_via_service(
    session: &mut crate::rpc::client::RpcSession,
    path: &str,
    line: &LineSettings,
) -> Result<Vec<(u32, u8)>, ExitCode> {
    let mut params = super::via_mqtt::line_params(line);
    params["path"] = serde_json::json!(path);
    let result = super::via_mqtt::service_call(
        session,
        "port",
        "Scan",
        params,
        std::time::Duration::from_secs(10),
    )
    .await?;
    if let Some(error) = result["error"].as_str() {
        eprintln!("{line}: {error}");
    }
    Ok(result["devices"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|device| {
            let serial = device["sn"].as_str()?.parse::<u32>().ok()?;
            let address = u8::try_from(device["cfg"]["slave_id"].as_u64()?).ok()?;
            Some((serial, address))
        })
        .collect())
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

/// What `fix-addresses` needs of a port: the port itself, or the running service that holds it.
#[allow(async_fn_in_trait)]
trait AddressBus {
    /// Fast Modbus scan of `lines` into `report`.
    async fn scan(
        &mut self,
        lines: &[LineSettings],
        report: &mut ScanReport,
    ) -> Result<(), ExitCode>;
    /// Writes the address register of the device with `serial` (now at `change.from`); Err
    /// with the reason.
    async fn write_address(
        &mut self,
        change: &AddressChange,
    ) -> Result<Result<(), String>, ExitCode>;
}

impl AddressBus for ToolPort {
    async fn scan(
        &mut self,
        lines: &[LineSettings],
        report: &mut ScanReport,
    ) -> Result<(), ExitCode> {
        // The address tools need serials and addresses only: no model or firmware reads.
        for &line in lines {
            report.settings_tried.push(line);
            self.scan_setting(line, report)
                .await
                .map_err(|err| port_failure(&err))?;
        }
        Ok(())
    }

    async fn write_address(
        &mut self,
        change: &AddressChange,
    ) -> Result<Result<(), String>, ExitCode> {
        write_address(self, change.line, change.serial, change.to)
            .await
            .map_err(|err| port_failure(&err))
    }
}

/// The running service, through `port/Scan` and `port/Setup`.
struct ServiceBus {
    session: crate::rpc::client::RpcSession,
    path: String,
}

impl ServiceBus {
    /// Connects to the service holding `path`; with the port's settings there.
    async fn connect(
        args: &super::via_mqtt::ViaMqttArgs,
        path: &str,
    ) -> Result<(Self, LineSettings), ExitCode> {
        let mut session = super::via_mqtt::connect_service(args).await?;
        let home = super::via_mqtt::served_line(&mut session, path).await?;
        Ok((
            Self {
                session,
                path: path.to_owned(),
            },
            home,
        ))
    }
}

impl AddressBus for ServiceBus {
    async fn scan(
        &mut self,
        lines: &[LineSettings],
        report: &mut ScanReport,
    ) -> Result<(), ExitCode> {
        for line in lines {
            report.settings_tried.push(*line);
            for (serial, address) in scan_via_service(&mut self.session, &self.path, line).await? {
                report.add_fast(*line, serial, address);
            }
        }
        Ok(())
    }

    async fn write_address(
        &mut self,
        change: &AddressChange,
    ) -> Result<Result<(), String>, ExitCode> {
        let mut item = super::via_mqtt::line_params(&change.line);
        item["slave_id"] = serde_json::json!(change.from);
        item["sn"] = serde_json::json!(change.serial);
        item["cfg"] = serde_json::json!({"slave_id": change.to});
        let setup = serde_json::json!({"path": self.path, "items": [item]});
        Ok(
            match self
                .session
                .call("port", "Setup", setup, std::time::Duration::from_secs(10))
                .await
            {
                Ok(_) => Ok(()),
                Err(err) => Err(err.to_string()),
            },
        )
    }
}

async fn fix_addresses(args: &FixAddressesArgs) -> Result<ExitCode, PortError> {
    if !args.service.via_mqtt {
        match args.port.open() {
            Err(PortError::Busy { path }) if args.service.can_reach_service() => {
                eprintln!("{path} is busy: fixing addresses through the running rtu2mqtt service (MQTT RPC)");
            }
            other => {
                let mut port = other?;
                let code = fix_addresses_on(&mut port, args).await;
                port.restore();
                return Ok(code);
            }
        }
    }
    let mut service = match ServiceBus::connect(&args.service, &args.port.port).await {
        Ok((service, _home)) => service,
        Err(code) => return Ok(code),
    };
    Ok(fix_addresses_on(&mut service, args).await)
}

/// Finds duplicate addresses over the plan, proposes or writes free ones, and checks them with
/// a new scan. The error side is an exit code already explained to the integrator.
async fn fix_addresses_on(bus: &mut impl AddressBus, args: &FixAddressesArgs) -> ExitCode {
    fix_addresses_steps(bus, args)
        .await
        .unwrap_or_else(|code| code)
}

async fn fix_addresses_steps(
    bus: &mut impl AddressBus,
    args: &FixAddressesArgs,
) -> Result<ExitCode, ExitCode> {
    let plan = args.port.plan();
    let mut report = ScanReport::default();
    bus.scan(&plan, &mut report).await?;
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
        if let Err(reason) = bus.write_address(change).await? {
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
    bus.scan(&lines, &mut check).await?;
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
