//! `rtu2mqtt set-address` and `rtu2mqtt fix-addresses`: change Modbus addresses by serial number
//! (Fast Modbus 0x46 0x08), so devices that share an address are told apart without unplugging
//! anything, and check the result with a new scan.

use std::collections::BTreeSet;
use std::process::ExitCode;
use std::time::Duration;

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

/// How long a classic probe of a new address waits for a reply: a device without Fast Modbus
/// (an energy meter, another vendor's module) may take a while to answer.
pub const ADDRESS_PROBE_TIMEOUT: Duration = Duration::from_millis(500);

/// The classic request that tells whether an address is in use: a read of holding 128 (any
/// reply, an exception too, is a device).
pub const ADDRESS_PROBE: RequestPdu = RequestPdu::ReadHoldingRegisters {
    start: ADDRESS_REGISTER,
    count: 1,
};

/// What answered a classic probe of an address, in words; None: nothing (the address is free).
pub fn probe_answer_text(answer: &Answer) -> Option<String> {
    match answer {
        Answer::NoReply => None,
        Answer::Pdu(ResponsePdu::Exception { code, .. }) => Some(format!(
            "a device answered a classic request there with {code}"
        )),
        Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => Some(format!(
            "a device answered a classic request there (holding {ADDRESS_REGISTER} = {})",
            values
                .iter()
                .map(u16::to_string)
                .collect::<Vec<_>>()
                .join(" ")
        )),
        Answer::Pdu(_) => Some("a device answered a classic request there".into()),
        Answer::Garbled => Some(
            "an unreadable reply came to a classic request there (bad CRC: a device, or \
             several, answering)"
                .into(),
        ),
    }
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
    // A device without Fast Modbus does not take part in the scan: ask the address itself.
    if taken_by.is_empty() {
        if let Some(what) = bus.probe(line, args.address).await? {
            if !args.force {
                eprintln!(
                    "address {} is already used at {line}: {what}; choose another (rtu2mqtt scan \
                     --classic lists devices without Fast Modbus) or add --force",
                    args.address
                );
                return Ok(ExitCode::from(exit::NOT_FOUND));
            }
            eprintln!(
                "address {} at {line}: {what}; changing anyway (--force)",
                args.address
            );
        }
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
    /// A classic probe of `address` at `line`: what answered, None when nothing did (free).
    async fn probe(&mut self, line: LineSettings, address: u8) -> Result<Option<String>, ExitCode>;
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

    async fn probe(&mut self, line: LineSettings, address: u8) -> Result<Option<String>, ExitCode> {
        let answer = self
            .classic(line, address, ADDRESS_PROBE, ADDRESS_PROBE_TIMEOUT)
            .await
            .map_err(|err| port_failure(&err))?;
        Ok(probe_answer_text(&answer))
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

    /// Through the service's bus queue, as `read` goes: `port/Load` of holding 128.
    async fn probe(&mut self, line: LineSettings, address: u8) -> Result<Option<String>, ExitCode> {
        let timeout_ms = u64::try_from(ADDRESS_PROBE_TIMEOUT.as_millis()).unwrap_or(500);
        let mut params = super::via_mqtt::line_params(&line);
        params["path"] = serde_json::json!(self.path);
        params["protocol"] = serde_json::json!("modbus");
        params["function"] = serde_json::json!(ADDRESS_PROBE.function());
        params["address"] = serde_json::json!(ADDRESS_REGISTER);
        params["count"] = serde_json::json!(1);
        params["format"] = serde_json::json!("HEX");
        params["msg"] = serde_json::json!("");
        params["response_timeout"] = serde_json::json!(timeout_ms);
        params["slave_id"] = serde_json::json!(address);
        // The service tries twice; then its turn on the bus.
        let total = ADDRESS_PROBE_TIMEOUT * 2 + Duration::from_secs(5);
        match self.session.call("port", "Load", params, total).await {
            Ok(result) => {
                if let Some(exception) = result.get("exception") {
                    return Ok(Some(format!(
                        "a device answered a classic request there with exception {} ({})",
                        exception["code"],
                        exception["msg"].as_str().unwrap_or("?")
                    )));
                }
                let words = result["response"]
                    .as_str()
                    .and_then(|response| super::via_mqtt::response_words(response, false, 1));
                Ok(Some(
                    probe_answer_text(&Answer::Pdu(ResponsePdu::ReadHoldingRegisters {
                        values: words.unwrap_or_default(),
                    }))
                    .unwrap_or_default(),
                ))
            }
            Err(crate::rpc::client::CallError::Refused(refused))
                if refused.message.contains("no reply") =>
            {
                Ok(None)
            }
            Err(crate::rpc::client::CallError::Refused(refused))
                if refused.message.contains("unreadable reply") =>
            {
                Ok(probe_answer_text(&Answer::Garbled))
            }
            Err(err) => {
                eprintln!("error: asking the service whether address {address} is free: {err}");
                Err(ExitCode::from(exit::PORT))
            }
        }
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

/// The address plan, every new address checked with a classic probe at its setting: an address
/// where something answers (a device without Fast Modbus, which the scan does not list) is taken,
/// and the plan is made again without it.
async fn plan_free_addresses(
    bus: &mut impl AddressBus,
    report: &ScanReport,
    range: (u8, u8),
) -> Result<crate::tools::report::AddressPlan, ExitCode> {
    let mut occupied = BTreeSet::new();
    let mut free: Vec<(LineSettings, u8)> = Vec::new();
    // Each round takes at least one more address, so there are at most as many as addresses.
    loop {
        let plan = report.plan_addresses_avoiding(range, &occupied);
        let mut changed = false;
        for change in &plan.changes {
            if free.contains(&(change.line, change.to)) {
                continue;
            }
            match bus.probe(change.line, change.to).await? {
                None => {
                    free.push((change.line, change.to));
                }
                Some(what) => {
                    eprintln!(
                        "address {} at {} is not free: {what}",
                        change.to, change.line
                    );
                    occupied.insert(change.to);
                    changed = true;
                    break;
                }
            }
        }
        if !changed {
            return Ok(plan);
        }
    }
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
    let address_plan = plan_free_addresses(bus, &report, args.range).await?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::pdu::ExceptionCode;

    #[test]
    fn any_answer_to_the_probe_takes_the_address_and_says_what_came() {
        assert_eq!(probe_answer_text(&Answer::NoReply), None);
        let exception = Answer::Pdu(ResponsePdu::Exception {
            function: 3,
            code: ExceptionCode(2),
        });
        assert_eq!(
            probe_answer_text(&exception).as_deref(),
            Some(
                "a device answered a classic request there with exception 2 (illegal data address)"
            )
        );
        let value = Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values: vec![30] });
        assert!(probe_answer_text(&value)
            .unwrap()
            .contains("holding 128 = 30"));
        assert!(probe_answer_text(&Answer::Garbled)
            .unwrap()
            .contains("unreadable reply"));
    }
}

/// Review (branch review-tools): what set-address does when its write is answered by nobody.
/// FAILS on the current code; see /tmp/review-tools.md.
#[cfg(test)]
mod review_tests {
    use super::*;
    use crate::protocol::Parity;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: SetAddressArgs,
    }

    /// One device (serial 5) at 9600 8N2 that takes the new address but whose reply to the
    /// write is lost (noise, a collision, a slow adapter): the write "fails", the device moved.
    struct LostReply {
        address: u8,
        scans: usize,
    }

    impl AddressBus for LostReply {
        async fn scan(
            &mut self,
            lines: &[LineSettings],
            report: &mut ScanReport,
        ) -> Result<(), ExitCode> {
            self.scans += 1;
            for line in lines {
                report.settings_tried.push(*line);
                if line.baud == 9600 && line.parity == Parity::None {
                    report.add_fast(*line, 5, self.address);
                }
            }
            Ok(())
        }

        async fn write_address(
            &mut self,
            change: &AddressChange,
        ) -> Result<Result<(), String>, ExitCode> {
            self.address = change.to;
            Ok(Err("no reply to the write".into()))
        }

        async fn probe(&mut self, _: LineSettings, _: u8) -> Result<Option<String>, ExitCode> {
            Ok(None)
        }
    }

    #[tokio::test]
    async fn review_set_address_checks_the_device_after_an_unanswered_write() {
        let cli = Cli::parse_from([
            "set-address",
            "--port",
            "/dev/null",
            "--serial",
            "5",
            "--address",
            "30",
            "--baud",
            "9600",
            "--parity",
            "N",
        ]);
        let mut bus = LostReply {
            address: 20,
            scans: 0,
        };
        let plan = cli.args.port.plan();
        let code = set_address_steps(&mut bus, &cli.args, &plan)
            .await
            .unwrap_or_else(|code| code);
        // The device now answers at 30, yet the tool printed "the address stays 20" and exited 1
        // without a second scan.
        assert_eq!(
            bus.scans, 2,
            "no scan after the unanswered write: the tool told the integrator the address \
             stays 20 while the device has 30 (exit {code:?})"
        );
    }
}
