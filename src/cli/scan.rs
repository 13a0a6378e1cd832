//! `rtu2mqtt scan`: every Fast Modbus device on a port, at every port setting, with its port
//! settings (stop bits from its registers: the wire does not show them), model and firmware;
//! optionally the slow classic scan for devices without the extension. Also the port options and
//! the runtime shared by the other site tools.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::config::TemplateLibrary;
use crate::protocol::{LineSettings, Parity, RequestPdu, ResponsePdu};
use crate::tools::adapter::Adapter;
use crate::tools::bus::{
    port_settings_in, Answer, PortError, ToolBus, ToolPort, KNOWN_DEVICE_TIMEOUT,
    PORT_SETTINGS_READ, TEXT_REGISTERS,
};
use crate::tools::exit;
use crate::tools::plan::{
    parse_baud, parse_parity, parse_range, same_on_the_wire, scan_plan, PlanFilter,
};
use crate::tools::report::same_serial;
use crate::tools::report::{serial_text, FoundDevice, Identity, ScanReport};
use crate::tools::values::standard_text;
use crate::transport::fifo::sysfs_tty;

/// The port and the settings to try, shared by every site tool.
#[derive(clap::Args, Debug, Clone)]
pub struct PortArgs {
    /// The serial port, e.g. /dev/ttyRS485-1 or /dev/ttyUSB0.
    #[arg(long)]
    pub port: String,
    /// Baud rate(s) to try (comma-separated); default: all eight standard rates.
    #[arg(long, value_delimiter = ',', value_parser = parse_baud)]
    pub baud: Vec<u32>,
    /// Parity (N, E, O; comma-separated); default: all three.
    #[arg(long, value_delimiter = ',', value_parser = parse_parity)]
    pub parity: Vec<Parity>,
    /// Stop bits (1, 2; comma-separated); default: both. The stop bits are not visible on the
    /// wire: a scan sends once per baud rate and parity, with 2 stop bits (or the one count
    /// named here), which devices at 1 or 2 hear alike, and lists the devices that report the
    /// stop bits named here (and those that do not report theirs).
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u8).range(1..=2))]
    pub stop_bits: Vec<u8>,
    /// Added to every reply timeout, in ms: what a USB adapter and a busy machine add.
    /// Default: from the kind of port (5 for a native UART, an FTDI adapter's latency timer
    /// + 4, 24 for other USB adapters).
    #[arg(long, value_name = "MS")]
    pub latency: Option<u64>,
    /// How many bytes the port's receive FIFO collects before it hands them over, when the
    /// kernel does not say (it does for a controller's own UARTs:
    /// /sys/class/tty/<port>/rx_trig_bytes, which the tools set to 1 while they run). More than
    /// 1 makes every reply wait as the FIFO may hand it over: slower, never blind.
    #[arg(long, value_name = "BYTES", value_parser = clap::value_parser!(u32).range(1..=256))]
    pub fifo_trigger: Option<u32>,
}

impl PortArgs {
    fn filter(&self) -> PlanFilter {
        PlanFilter {
            bauds: self.baud.clone(),
            parities: self.parity.clone(),
            stop_bits: self.stop_bits.clone(),
        }
    }

    /// The settings to transmit at: one per baud rate and parity (see [`scan_plan`]).
    pub fn plan(&self) -> Vec<LineSettings> {
        scan_plan(&self.filter())
    }

    /// The one setting the options name, when they name one baud rate and one parity: with the
    /// stop bits named, else 2 (which devices at 1 or 2 stop bits understand alike).
    pub fn single_line(&self) -> Option<LineSettings> {
        match self.plan().as_slice() {
            [one] => Some(*one),
            _ => None,
        }
    }

    pub fn open(&self) -> Result<ToolPort, PortError> {
        Ok(
            ToolPort::open(&self.port, self.reply_allowance())?
                .with_receive_fifo(self.fifo_trigger),
        )
    }

    /// `--latency`, or what the kind of port needs.
    pub fn reply_allowance(&self) -> Duration {
        match self.latency {
            Some(ms) => Duration::from_millis(ms),
            None => {
                let adapter = Adapter::detect(Path::new(&self.port), &sysfs_tty());
                tracing::info!(port = %self.port, "{}", adapter.describe());
                adapter.reply_allowance()
            }
        }
    }
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub port: PortArgs,
    /// Also probe addresses one by one with classic Modbus (slow: up to --timeout per address
    /// and setting) for devices without Fast Modbus.
    #[arg(long)]
    pub classic: bool,
    /// Addresses the classic scan probes.
    #[arg(long, default_value = "1-247", value_parser = parse_range)]
    pub range: (u8, u8),
    /// Reply timeout of a classic probe, in ms. 600 finds devices built on libmodbus (a Linux
    /// device's Modbus stack), which take the frame after a request to another address for
    /// that address's reply for 0.5 s and so miss a probe that follows a silent one sooner.
    #[arg(long, default_value_t = 100, value_name = "MS")]
    pub timeout: u64,
    /// Print JSON instead of a table.
    #[arg(long, conflicts_with = "config")]
    pub json: bool,
    /// Print a config snippet (a port per setting, a device per address) instead of a table.
    #[arg(long)]
    pub config: bool,
    /// Extra template directories for choosing `device_type` in --config.
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    #[command(flatten)]
    pub service: super::via_mqtt::ViaMqttArgs,
}

/// A single-threaded runtime for a tool; Ctrl-C ends `work` (its port is restored on drop) and
/// the command with exit code 130.
pub fn block_on_tool<F>(work: F) -> anyhow::Result<ExitCode>
where
    F: std::future::Future<Output = anyhow::Result<ExitCode>>,
{
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        tokio::select! {
            result = work => result,
            _ = tokio::signal::ctrl_c() => {
                eprintln!("interrupted; the port's settings are restored");
                Ok(ExitCode::from(exit::INTERRUPTED))
            }
        }
    })
}

/// Port errors end a tool with exit code 3 and the integrator's explanation.
pub fn port_failure(err: &PortError) -> ExitCode {
    eprintln!("error: {err}");
    ExitCode::from(exit::PORT)
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    // The service scans with Fast Modbus only: a classic scan through it would miss what it was
    // asked for, so it is refused before anything is sent.
    if args.classic {
        let held = args.service.via_mqtt
            || (matches!(args.port.open(), Err(PortError::Busy { .. }))
                && args.service.can_reach_service());
        if held {
            eprintln!(
                "--classic is not available through the service (it scans with Fast Modbus \
                 only): stop the service (systemctl stop rtu2mqtt) and scan {} directly, or \
                 scan without --classic",
                args.port.port
            );
            return Ok(ExitCode::from(exit::USAGE));
        }
    }
    if let Some(note) = unusual_baud_note(&args.port.baud) {
        eprintln!("{note}");
    }
    let mut report = ScanReport::default();
    let started = Instant::now();
    let mut interrupted = false;
    let result = {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        runtime.block_on(async {
            tokio::select! {
                result = scan(&args, &mut report) => result,
                _ = tokio::signal::ctrl_c() => { interrupted = true; Ok(()) }
            }
        })
    };
    if let Err(err) = result {
        return Ok(port_failure(&err));
    }
    let elapsed = started.elapsed();
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&report_json(&report, elapsed))?
        );
    } else if args.config {
        let library = TemplateLibrary::load_standard(&args.templates);
        println!(
            "{}",
            config_snippet(&report, &args.port.port, &library, &args.templates)
        );
    } else {
        print!(
            "{}",
            table(
                &report,
                elapsed,
                &fix_command(&args, report.through_service)
            )
        );
    }
    if interrupted {
        eprintln!(
            "interrupted: the results above are incomplete; the port's settings are restored"
        );
        return Ok(ExitCode::from(exit::INTERRUPTED));
    }
    Ok(if report.devices.is_empty() {
        eprintln!(
            "no device answered at {} setting(s) of {}: check wiring (A/B swapped?), power, and \
             that the devices speak Fast Modbus (else add --classic); behind a slow USB adapter or \
             converter, give replies more time with --latency 40{}",
            report.settings_covered(),
            args.port.port,
            if args.classic && args.timeout < LIBMODBUS_CONFIRMATION_WAIT_MS {
                "; a device built on libmodbus (Linux-based) answers a classic scan only with \
                 --timeout 600"
            } else {
                ""
            }
        );
        ExitCode::from(exit::NOT_FOUND)
    } else {
        ExitCode::SUCCESS
    })
}

/// How long a libmodbus-based device takes the frame after a request to another address for
/// that address's reply (libmodbus's default response timeout, 0.5 s): a classic probe sooner
/// after a silent one goes unheard by it.
const LIBMODBUS_CONFIRMATION_WAIT_MS: u64 = 500;

/// The `fix-addresses` command for the port this scan went to (through the service: with the
/// options that reach it).
fn fix_command(args: &Args, through_service: bool) -> String {
    let mut command = format!(
        "rtu2mqtt fix-addresses --port {}",
        shell_word(&args.port.port)
    );
    if through_service {
        if args.service.via_mqtt {
            command.push_str(" --via-mqtt");
        }
        if let Some(broker) = &args.service.broker {
            command.push_str(&format!(" --broker {}", shell_word(broker)));
        } else if args.service.service_config != Path::new(crate::config::load::DEFAULT_CONFIG_PATH)
        {
            command.push_str(&format!(
                " --service-config {}",
                shell_word(&args.service.service_config.to_string_lossy())
            ));
        }
    }
    command.push_str(" --apply");
    command
}

/// `text` as one shell word: quoted when it holds anything a shell would split or expand.
fn shell_word(text: &str) -> String {
    let plain = !text.is_empty()
        && text
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-:+,=@%".contains(c));
    if plain {
        text.to_owned()
    } else {
        format!("'{}'", text.replace('\'', "'\\''"))
    }
}

/// A baud rate no device is set to is far more often a typo (9601, 96000) than a real setting:
/// said before the scan rather than left to its "no device answered".
fn unusual_baud_note(bauds: &[u32]) -> Option<String> {
    let unusual: Vec<String> = bauds
        .iter()
        .filter(|baud| !crate::protocol::timing::is_usual_baud_rate(**baud))
        .map(u32::to_string)
        .collect();
    (!unusual.is_empty()).then(|| {
        format!(
            "note: --baud {} is not a usual rate (usual: {}); scanning it anyway",
            unusual.join(","),
            crate::protocol::timing::usual_baud_rates_text()
        )
    })
}

/// The scan itself, filling `report` as it goes (an interrupted scan keeps what it found).
pub async fn scan(args: &Args, report: &mut ScanReport) -> Result<(), PortError> {
    let mut port = if args.service.via_mqtt {
        return scan_via_service(args, report).await;
    } else {
        match args.port.open() {
            Err(PortError::Busy { path }) if args.service.can_reach_service() => {
                eprintln!(
                    "{path} is busy: scanning through the running rtu2mqtt service (MQTT RPC)"
                );
                return scan_via_service(args, report).await;
            }
            other => other?,
        }
    };
    let plan = args.port.plan();
    report.stop_bits_covered = args.port.filter().stop_bits_covered();
    fast_scan(&mut port, &plan, report).await?;
    if args.classic {
        classic_scan(
            &mut port,
            &plan,
            args.range,
            Duration::from_millis(args.timeout),
            report,
        )
        .await?;
    }
    port.restore();
    report.keep_stop_bits(&args.port.stop_bits);
    Ok(())
}

/// Fast Modbus scan over `plan`, then port settings, model and firmware of each new device.
pub async fn fast_scan(
    port: &mut ToolPort,
    plan: &[LineSettings],
    report: &mut ScanReport,
) -> Result<(), PortError> {
    for &line in plan {
        let problems_before = report.problems.len();
        report.settings_tried.push(line);
        let seen = port.scan_setting(line, report).await?;
        if !seen.is_empty() {
            tracing::info!("{line}: {} Fast Modbus device(s)", seen.len());
        }
        if report.problems.len() > problems_before && line.stop_bits == 2 {
            // A port whose receiver checks both stop bits (the 16550 and the common adapters
            // check only the first) garbles the replies of devices at 1: hear them at 1.
            let one_stop_bit = LineSettings {
                stop_bits: 1,
                ..line
            };
            report.settings_tried.push(one_stop_bit);
            port.scan_setting(one_stop_bit, report).await?;
        }
    }
    for index in 0..report.devices.len() {
        let Some(device) = report.devices.get(index) else {
            continue;
        };
        if let (Some(serial), true, None) = (device.serial, device.fast, &device.identity.model) {
            let (identity, settings) = port.details(device.line, serial).await?;
            if let Some(device) = report.devices.get_mut(index) {
                device.identity = identity;
                if let Some(settings) = settings {
                    device.take_reported(settings);
                }
            }
        }
    }
    Ok(())
}

/// Classic probes of every address in `range` at every setting of `plan` (addresses with a
/// known device at that setting skipped), with progress and time left on stderr.
async fn classic_scan(
    port: &mut ToolPort,
    plan: &[LineSettings],
    range: (u8, u8),
    timeout: Duration,
    report: &mut ScanReport,
) -> Result<(), PortError> {
    let terminal = std::io::stderr().is_terminal();
    let total = plan.len() * usize::from(range.1 - range.0 + 1);
    let started = Instant::now();
    let mut done = 0usize;
    let probes_before = report.classic_probes;
    for &line in plan {
        // A silent address costs the request, the timeout with the allowance, and the watch
        // for a late reply after it (so that a slow device is not taken for the next address):
        // the estimate until probes have been timed.
        let reply_wait = timeout + port.latency;
        let silent = line.wire_time(8)
            + reply_wait
            + reply_wait.min(crate::protocol::transaction::MAX_LATE_WINDOW);
        // The line was last used by another request (the Fast Modbus scan's broadcast, or
        // probes at another setting, garbage at this one): a silence of a probe's timeout before
        // the first probe, as after every silent one. A device built on libmodbus takes the
        // frame after a request to another address for that address's reply, for 0.5 s, and
        // hears the first probe with `--timeout 600` only so.
        tokio::time::sleep(timeout).await;
        for address in range.0..=range.1 {
            done += 1;
            let known: Vec<(Option<u32>, bool)> = report
                .devices
                .iter()
                .filter(|d| d.address == address && d.answers_at(&line))
                .map(|d| (d.serial, d.fast))
                .collect();
            if let [(serial, true)] = known[..] {
                // A device without Fast Modbus may share the address of one the scan found:
                // asked for the serial number, the two answer differently and collide (a site
                // tools audit: such a clash was invisible to every tool).
                report.classic_probes += 1;
                if let Some(what) =
                    shared_with_a_classic_device(port, line, address, serial, timeout).await?
                {
                    report
                        .problems
                        .push(crate::tools::report::SettingProblem { line, what });
                }
                continue;
            }
            if !known.is_empty() {
                // A device found here already (by a probe at another setting, or several Fast
                // Modbus devices: a duplicate the scan reports).
                continue;
            }
            let probed = report.classic_probes - probes_before;
            let left = time_left(started.elapsed(), probed, total - (done - 1), silent);
            let shown = terminal || probed == 0 || (done - 1) % 50 == 0;
            if shown {
                progress(terminal, line, address, done - 1, total, left);
            }
            let probe = RequestPdu::ReadHoldingRegisters {
                start: 128,
                count: 1,
            };
            report.classic_probes += 1;
            match port.classic(line, address, probe, timeout).await? {
                Answer::Pdu(_) => {
                    let (identity, serial, settings) =
                        classic_identity(port, line, address).await?;
                    if report.add_classic(line, address, serial) {
                        if let Some(device) = report.devices.last_mut() {
                            device.identity = identity;
                            if let Some(settings) = settings {
                                device.take_reported(settings);
                            }
                        }
                        eprintln!(
                            "{}classic device at address {address}, {line}",
                            clear(terminal)
                        );
                    }
                }
                Answer::Garbled => report.problems.push(crate::tools::report::SettingProblem {
                    line,
                    what: format!("address {address}: unreadable reply (bad CRC or a collision)"),
                }),
                Answer::NoReply => {}
            }
        }
    }
    if terminal {
        eprint!("{}", clear(true));
    }
    Ok(())
}

/// Whether a device without Fast Modbus answers at `address` besides the one the Fast Modbus
/// scan found there (`serial`): a read of the serial number (holding 270..271) comes back
/// unreadable (two replies at once) or with another number. Said as a problem of the setting.
async fn shared_with_a_classic_device(
    port: &mut ToolPort,
    line: LineSettings,
    address: u8,
    serial: Option<u32>,
    timeout: Duration,
) -> Result<Option<String>, PortError> {
    // Asked twice, and said only when both answers say so: one reply lost to noise, or not
    // trusted while another master polls, must not pass for a second device.
    let mut unreadable = false;
    for _ in 0..2 {
        let probe = RequestPdu::ReadHoldingRegisters {
            start: 270,
            count: 2,
        };
        match port.classic(line, address, probe, timeout).await? {
            Answer::Garbled => unreadable = true,
            Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => {
                let read = crate::daemon::identity::serial_of(&values);
                match (read, serial) {
                    (Some(read), Some(scanned)) if !same_serial(read, scanned) => {}
                    // The device the scan found, alone.
                    _ => return Ok(None),
                }
            }
            // Refused or silent: the Fast Modbus device alone, without that register.
            Answer::Pdu(_) | Answer::NoReply => return Ok(None),
        }
    }
    let what = if unreadable {
        "an unreadable reply"
    } else {
        "another serial number"
    };
    let scanned = serial.map_or("?".to_owned(), |s| format!("{s} (0x{s:08X})"));
    Ok(Some(format!(
        "address {address}: a classic request got {what} where the Fast Modbus scan found serial \
         {scanned}: a device without Fast Modbus probably shares this address (give one of them \
         another address)"
    )))
}

fn clear(terminal: bool) -> &'static str {
    if terminal {
        "\r\x1b[K"
    } else {
        ""
    }
}

/// Time left for `remaining` probes: at the pace of the `probed` ones so far (`elapsed`), or
/// `silent` each (a probe that waits out its timeout) before any has been timed.
fn time_left(elapsed: Duration, probed: usize, remaining: usize, silent: Duration) -> Duration {
    let per_probe = match u32::try_from(probed) {
        Ok(probed) if probed > 0 => elapsed / probed,
        _ => silent,
    };
    per_probe.saturating_mul(u32::try_from(remaining).unwrap_or(u32::MAX))
}

/// One progress line: `done` addresses of `total` handled before this one.
fn progress(
    terminal: bool,
    line: LineSettings,
    address: u8,
    done: usize,
    total: usize,
    left: Duration,
) {
    let text = format!(
        "classic scan {line}, address {address}: {done}/{total} ({}%), about {} s left",
        done * 100 / total.max(1),
        left.as_secs_f64().ceil()
    );
    if terminal {
        eprint!("{}{text}", clear(true));
    } else {
        eprintln!("{text}");
    }
}

/// Model, firmware, serial and port settings of a classic device from the standard registers, if
/// it has them.
async fn classic_identity(
    port: &mut ToolPort,
    line: LineSettings,
    address: u8,
) -> Result<(Identity, Option<u32>, Option<LineSettings>), PortError> {
    let mut texts = Vec::new();
    for (start, count) in TEXT_REGISTERS {
        let pdu = RequestPdu::ReadHoldingRegisters { start, count };
        texts.push(
            match port
                .classic(line, address, pdu, KNOWN_DEVICE_TIMEOUT)
                .await?
            {
                Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => standard_text(&values),
                _ => None,
            },
        );
    }
    let pdu = RequestPdu::ReadHoldingRegisters {
        start: 270,
        count: 2,
    };
    let serial = match port
        .classic(line, address, pdu, KNOWN_DEVICE_TIMEOUT)
        .await?
    {
        Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => match values.as_slice() {
            [hi, lo] => Some(u32::from(*hi) << 16 | u32::from(*lo)),
            _ => None,
        },
        _ => None,
    };
    let settings = port_settings_in(
        &port
            .classic(line, address, PORT_SETTINGS_READ, KNOWN_DEVICE_TIMEOUT)
            .await?,
    );
    let mut texts = texts.into_iter();
    Ok((
        Identity {
            model: texts.next().flatten(),
            firmware: texts.next().flatten(),
            signature: texts.next().flatten(),
        },
        serial,
        settings,
    ))
}

fn serial_cell(device: &FoundDevice) -> String {
    device.serial.map_or_else(|| "-".into(), serial_text)
}

/// The table an integrator reads, with what needs attention below it.
pub fn table(report: &ScanReport, elapsed: Duration, fix_command: &str) -> String {
    use std::fmt::Write as _;
    let duplicates = report.duplicates();
    let mut out = String::new();
    // A model or firmware text takes up to 20 characters (its registers): the columns widen to
    // what this bus holds rather than push the next column out of line.
    let width = |least: usize, cell: &dyn Fn(&FoundDevice) -> usize| {
        report.devices.iter().map(cell).fold(least, usize::max)
    };
    let text_len = |text: &Option<String>| text.as_deref().map_or(1, |t| t.chars().count());
    let model_width = width(14, &|d| text_len(&d.identity.model));
    let firmware_width = width(10, &|d| text_len(&d.identity.firmware));
    let _ = writeln!(
        out,
        "{:<24} {:>4}  {:<12} {:<5} {:<model_width$} {:<firmware_width$} NOTES",
        "SERIAL", "ADDR", "SETTINGS", "FAST", "MODEL", "FIRMWARE"
    );
    for (index, device) in report.devices.iter().enumerate() {
        let mut notes = Vec::new();
        if duplicates.iter().any(|d| d.devices.contains(&index)) {
            notes.push("DUPLICATE ADDRESS".to_owned());
        }
        if !device.also_at.is_empty() {
            let others: Vec<String> = device.also_at.iter().map(|l| l.to_string()).collect();
            notes.push(format!("also answers at {}", others.join(", ")));
        }
        if !device.stop_bits_known {
            notes.push("stop bits 1 or 2: not reported (holding 112)".to_owned());
        }
        if let Some(registers) = device.registers_say {
            notes.push(format!(
                "its registers say {registers} (applied at its next start?)"
            ));
        }
        let _ = writeln!(
            out,
            "{:<24} {:>4}  {:<12} {:<5} {:<model_width$} {:<firmware_width$} {}",
            serial_cell(device),
            device.address,
            device.settings_text(),
            if device.fast { "yes" } else { "no" },
            device.identity.model.as_deref().unwrap_or("-"),
            device.identity.firmware.as_deref().unwrap_or("-"),
            notes.join("; ")
        );
    }
    let classic = if report.classic_probes > 0 {
        format!(
            " and {} classic probe(s) (an address at a setting each)",
            report.classic_probes
        )
    } else {
        String::new()
    };
    let _ = writeln!(
        out,
        "{} device(s); {} setting(s) covered by {} Fast Modbus transmission(s){classic} in {:.2} s",
        report.devices.len(),
        report.settings_covered(),
        report.settings_tried.len(),
        elapsed.as_secs_f64()
    );
    if report.other_stop_bits > 0 {
        let _ = writeln!(
            out,
            "{} device(s) with other stop bits not listed (--stop-bits)",
            report.other_stop_bits
        );
    }
    for duplicate in &duplicates {
        let serials: Vec<String> = duplicate
            .devices
            .iter()
            .filter_map(|&i| report.devices.get(i))
            .map(serial_cell)
            .collect();
        let _ = writeln!(
            out,
            "duplicate: address {} at {} is used by {} devices ({}); fix with {fix_command}",
            duplicate.address,
            duplicate_settings(report, duplicate),
            duplicate.devices.len(),
            serials.join(", ")
        );
    }
    if report.multi_setting().next().is_some() {
        let _ = writeln!(
            out,
            "note: devices that answer at several settings: on a pseudo-terminal parity N and E \
             cannot be told apart; on a real bus check the device's settings"
        );
    }
    for problem in &report.problems {
        let _ = writeln!(out, "problem at {}: {}", problem.line, problem.what);
    }
    out
}

/// The settings of a duplicate: those of its devices, or without the stop bits when they differ
/// or are not known (the address collides whatever the stop bits).
fn duplicate_settings(report: &ScanReport, duplicate: &crate::tools::report::Duplicate) -> String {
    let members: Vec<&FoundDevice> = duplicate
        .devices
        .iter()
        .filter_map(|&i| report.devices.get(i))
        .collect();
    let alike = members
        .iter()
        .all(|d| d.stop_bits_known && d.line == duplicate.line);
    if alike {
        duplicate.line.to_string()
    } else {
        let line = duplicate.line;
        format!(
            "{} {}{} (any stop bits)",
            line.baud,
            line.data_bits,
            line.parity.letter()
        )
    }
}

pub fn device_json(device: &FoundDevice) -> Value {
    json!({
        "serial": device.serial,
        "serial_hex": device.serial.map(|s| format!("0x{s:08X}")),
        "address": device.address,
        "settings": device.settings_text(),
        "baud_rate": device.line.baud,
        "parity": device.line.parity.letter().to_string(),
        "data_bits": device.line.data_bits,
        // null: not reported by the device, and not visible on the wire (1 or 2).
        "stop_bits": device.stop_bits_known.then_some(device.line.stop_bits),
        "registers_say": device.registers_say.map(|l| l.to_string()),
        "also_at": device.also_at.iter().map(|l| l.to_string()).collect::<Vec<_>>(),
        "fast_modbus": device.fast,
        "model": device.identity.model,
        "firmware": device.identity.firmware,
        "signature": device.identity.signature,
    })
}

pub fn report_json(report: &ScanReport, elapsed: Duration) -> Value {
    let duplicates: Vec<Value> = report
        .duplicates()
        .iter()
        .map(|d| {
            json!({
                "settings": duplicate_settings(report, d),
                "address": d.address,
                "serials": d.devices.iter().filter_map(|&i| report.devices.get(i)).map(|x| x.serial).collect::<Vec<_>>(),
            })
        })
        .collect();
    json!({
        "port_settings_scanned": report.settings_covered(),
        "transmissions": report.settings_tried.len(),
        "classic_probes": report.classic_probes,
        "other_stop_bits": report.other_stop_bits,
        "elapsed_ms": u64::try_from(elapsed.as_millis()).unwrap_or(u64::MAX),
        "devices": report.devices.iter().map(device_json).collect::<Vec<_>>(),
        "duplicates": duplicates,
        "problems": report.problems.iter().map(|p| json!({"settings": p.line.to_string(), "problem": p.what})).collect::<Vec<_>>(),
    })
}

/// The template whose `hw` signature is the device's signature (or model); one from the
/// directories given with --templates wins over the built-in and system ones.
fn matching_template(
    library: &TemplateLibrary,
    preferred_dirs: &[PathBuf],
    identity: &Identity,
) -> Option<String> {
    let wanted: Vec<&str> = [identity.signature.as_deref(), identity.model.as_deref()]
        .into_iter()
        .flatten()
        .collect();
    let matches: Vec<(&str, &crate::config::library::TemplateEntry)> = library
        .entries()
        .filter(|(_, entry)| !entry.deprecated)
        .filter(|(_, entry)| {
            entry
                .signatures
                .iter()
                .any(|signature| wanted.iter().any(|w| w.eq_ignore_ascii_case(signature)))
        })
        // Only a template that loads is offered (read here: the few that match).
        .filter(|(device_type, _)| library.get(device_type).is_some())
        .collect();
    matches
        .iter()
        .find(|(_, entry)| preferred_dirs.iter().any(|d| entry.path().starts_with(d)))
        .or(matches.first())
        .map(|(device_type, _)| (*device_type).to_owned())
}

/// A config snippet: one port per setting devices were found at (stop bits aside: a port hears
/// devices at 1 and 2 alike), one device per address (a duplicate address is listed once, with a
/// comment: fix it first).
pub fn config_snippet(
    report: &ScanReport,
    path: &str,
    library: &TemplateLibrary,
    preferred_dirs: &[PathBuf],
) -> String {
    let mut lines: Vec<LineSettings> = Vec::new();
    for device in &report.devices {
        if !lines.iter().any(|l| same_on_the_wire(l, &device.line)) {
            lines.push(device.line);
        }
    }
    let mut ports = Vec::new();
    let mut comments = Vec::new();
    for line in &lines {
        let members: Vec<&FoundDevice> = report
            .devices
            .iter()
            .filter(|d| same_on_the_wire(&d.line, line))
            .collect();
        let (stop_bits, why) = port_stop_bits(&members);
        let port_line = LineSettings { stop_bits, ..*line };
        if let Some(why) = why {
            comments.push(format!(
                "// {port_line}: stop bits 2, {why}; a port at 2 works with devices at 1 or 2 (a \
                 UART checks only the first stop bit)"
            ));
        }
        let mut devices = Vec::new();
        let mut addresses = Vec::new();
        for device in members {
            if addresses.contains(&device.address) {
                comments.push(format!(
                    "// address {} at {port_line} is used by more than one device: run \
                     rtu2mqtt fix-addresses first",
                    device.address
                ));
                continue;
            }
            addresses.push(device.address);
            let device_type = matching_template(library, preferred_dirs, &device.identity);
            if device_type.is_none() {
                comments.push(format!(
                    "// no template matches address {} at {port_line} (model {}): set \
                     device_type by hand",
                    device.address,
                    device.identity.model.as_deref().unwrap_or("unknown")
                ));
            }
            devices.push(json!({
                "slave_id": device.address,
                "device_type": device_type.unwrap_or_else(|| "FIXME".into()),
            }));
        }
        ports.push(json!({
            "path": path,
            "baud_rate": port_line.baud,
            "parity": port_line.parity.letter().to_string(),
            "data_bits": port_line.data_bits,
            "stop_bits": port_line.stop_bits,
            "devices": devices,
        }));
    }
    if lines.len() > 1 {
        comments.push(format!(
            "// devices use {} different port settings on one port: the daemon talks one \
             setting per port, so set them all alike (keep one \"ports\" entry)",
            lines.len()
        ));
    }
    let body = serde_json::to_string_pretty(&json!({ "ports": ports })).unwrap_or_default();
    let mut out = comments.join("\n");
    if !out.is_empty() {
        out.push('\n');
    }
    out.push_str(&body);
    out
}

/// The stop bits of a port for `devices` (one setting on the wire): theirs when they all
/// reported the same, else 2, with the reason.
fn port_stop_bits(devices: &[&FoundDevice]) -> (u8, Option<String>) {
    if let Some(unknown) = devices.iter().find(|d| !d.stop_bits_known) {
        return (
            2,
            Some(format!(
                "as address {} did not report its stop bits (holding 112)",
                unknown.address
            )),
        );
    }
    let mut reported: Vec<u8> = devices.iter().map(|d| d.line.stop_bits).collect();
    reported.sort_unstable();
    reported.dedup();
    match reported.as_slice() {
        [one] => (*one, None),
        _ => (2, Some("as the devices here use 1 and 2".to_owned())),
    }
}

/// The scan through the running service: `port/Scan` at each setting of the plan (the service
/// reads each device's details by serial number).
async fn scan_via_service(args: &Args, report: &mut ScanReport) -> Result<(), PortError> {
    use crate::rpc::client::RpcSession;
    report.through_service = true;
    let broker = args.service.broker_config().map_err(PortError::Service)?;
    let mut session = RpcSession::connect(&broker)
        .await
        .map_err(|err| PortError::Service(err.to_string()))?;
    // The port is looked up first: a typo is said at once, and the scans wait as long as
    // they take beside another server on the broker.
    super::via_mqtt::served_line(&mut session, &args.port.port)
        .await
        .map_err(|_| {
            PortError::Service(format!(
                "the service does not serve {} (see above)",
                args.port.port
            ))
        })?;
    report.stop_bits_covered = args.port.filter().stop_bits_covered();
    for line in args.port.plan() {
        report.settings_tried.push(line);
        super::via_mqtt::scan_setting_via_service(&mut session, &args.port.port, line, report)
            .await?;
    }
    report.keep_stop_bits(&args.port.stop_bits);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Parity;

    const N2: LineSettings = LineSettings::new(9600, Parity::None, 2);

    /// Two devices at 9600 8N: one reports 1 stop bit, one has no registers 110..112.
    fn report() -> ScanReport {
        let mut report = ScanReport {
            settings_tried: vec![N2],
            ..ScanReport::default()
        };
        report.add_fast(N2, 1, 20);
        report.add_fast(N2, 2, 21);
        report.devices[0].take_reported(LineSettings::new(9600, Parity::None, 1));
        report
    }

    #[test]
    fn the_template_offered_for_a_model_is_one_that_loads() {
        let (system, preferred) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        std::fs::write(
            system.path().join("good.json"),
            r#"{"device_type": "GOOD", "hw": [{"signature": "WBMR6C"}], "device": {"channels": []}}"#,
        )
        .unwrap();
        // Preferred (given with --templates), same signature, but its channel does not load.
        std::fs::write(
            preferred.path().join("broken.json"),
            r#"{"device_type": "BROKEN", "hw": [{"signature": "WBMR6C"}], "device": {"channels": [{"name": "a", "address": 1, "format": "float32"}]}}"#,
        )
        .unwrap();
        let library = TemplateLibrary::load_dirs(&[
            system.path().to_path_buf(),
            preferred.path().to_path_buf(),
        ]);
        let identity = crate::tools::report::Identity {
            signature: Some("WBMR6C".into()),
            ..Default::default()
        };
        assert_eq!(
            matching_template(&library, &[preferred.path().to_path_buf()], &identity).as_deref(),
            Some("GOOD")
        );
    }

    #[test]
    fn unknown_stop_bits_are_said_in_the_table_and_the_json() {
        let report = report();
        let text = table(
            &report,
            Duration::from_millis(700),
            "rtu2mqtt fix-addresses --port /dev/ttyRS485-1 --apply",
        );
        let lines: Vec<&str> = text.lines().collect();
        assert!(lines[1].contains("9600 8N1"), "{text}");
        assert!(!lines[1].contains("not reported"), "{text}");
        assert!(lines[2].contains("9600 8N?"), "{text}");
        assert!(
            lines[2].contains("stop bits 1 or 2: not reported"),
            "{text}"
        );
        assert!(
            text.contains("2 device(s); 2 setting(s) covered by 1 Fast Modbus transmission(s) in"),
            "{text}"
        );
        let json = report_json(&report, Duration::from_millis(700));
        assert_eq!(json["port_settings_scanned"], 2);
        assert_eq!(json["transmissions"], 1);
        assert_eq!(json["devices"][0]["stop_bits"], 1);
        assert_eq!(json["devices"][0]["settings"], "9600 8N1");
        assert_eq!(json["devices"][1]["stop_bits"], Value::Null);
        assert_eq!(json["devices"][1]["settings"], "9600 8N?");
    }

    #[test]
    fn a_long_model_name_widens_its_column_and_keeps_the_others_in_line() {
        let mut report = report();
        report.devices[0].identity.model = Some("rtu2mqtt-energy-mete".into());
        report.devices[0].identity.firmware = Some("1.2.3".into());
        report.devices[1].identity.firmware = Some("10.20.30-rc1".into());
        let text = table(&report, Duration::from_millis(700), "x");
        let lines: Vec<&str> = text.lines().collect();
        let column = |line: &str, what: &str| line.find(what).unwrap_or_else(|| panic!("{text}"));
        let firmware_at = column(lines[0], "FIRMWARE");
        let notes_at = column(lines[0], "NOTES");
        assert_eq!(column(lines[1], "1.2.3"), firmware_at, "{text}");
        assert_eq!(column(lines[2], "10.20.30-rc1"), firmware_at, "{text}");
        assert_eq!(column(lines[2], "stop bits 1 or 2"), notes_at, "{text}");
        assert!(
            column(lines[1], "rtu2mqtt-energy-mete") < firmware_at,
            "{text}"
        );
    }

    #[test]
    fn the_classic_scan_estimates_its_time_from_the_start() {
        let silent = Duration::from_millis(150);
        // Nothing timed yet: every address as a silent one.
        assert_eq!(
            time_left(Duration::from_millis(3), 0, 10, silent),
            Duration::from_millis(1500)
        );
        // Then the pace of the probes made.
        assert_eq!(
            time_left(Duration::from_millis(400), 4, 6, silent),
            Duration::from_millis(600)
        );
        let mut report = report();
        report.classic_probes = 30;
        let text = table(&report, Duration::from_millis(700), "x");
        assert!(
            text.contains("covered by 1 Fast Modbus transmission(s) and 30 classic probe(s)"),
            "{text}"
        );
        assert_eq!(
            report_json(&report, Duration::from_millis(700))["classic_probes"],
            30
        );
    }

    #[test]
    fn an_unusual_baud_rate_is_said_before_the_scan() {
        assert_eq!(unusual_baud_note(&[]), None);
        assert_eq!(unusual_baud_note(&[9600, 115_200]), None);
        let note = unusual_baud_note(&[9600, 9601, 96_000]).unwrap();
        assert!(
            note.starts_with("note: --baud 9601,96000 is not a usual rate (usual: 110, 300"),
            "{note}"
        );
    }

    #[test]
    fn the_fix_command_is_one_to_paste() {
        assert_eq!(shell_word("/dev/ttyRS485-1"), "/dev/ttyRS485-1");
        assert_eq!(shell_word("/tmp/my port"), "'/tmp/my port'");
        assert_eq!(shell_word("it's"), "'it'\\''s'");
    }

    #[test]
    fn a_port_for_devices_of_unknown_stop_bits_gets_two_and_says_why() {
        let snippet = config_snippet(
            &report(),
            "/dev/ttyRS485-1",
            &TemplateLibrary::default(),
            &[],
        );
        assert!(
            snippet
                .contains("// 9600 8N2: stop bits 2, as address 21 did not report its stop bits"),
            "{snippet}"
        );
        let body: Value = serde_json::from_str(&snippet[snippet.find('{').unwrap()..]).unwrap();
        assert_eq!(body["ports"].as_array().unwrap().len(), 1);
        assert_eq!(body["ports"][0]["stop_bits"], 2);
        // All reported alike: theirs, without a comment.
        let mut alike = report();
        alike.devices[1].take_reported(LineSettings::new(9600, Parity::None, 1));
        let snippet = config_snippet(&alike, "/dev/ttyRS485-1", &TemplateLibrary::default(), &[]);
        assert!(!snippet.contains("stop bits 2"), "{snippet}");
        let body: Value = serde_json::from_str(&snippet[snippet.find('{').unwrap()..]).unwrap();
        assert_eq!(body["ports"][0]["stop_bits"], 1);
    }

    #[test]
    fn one_baud_rate_and_parity_is_a_single_line() {
        let args = |stop_bits: Vec<u8>| PortArgs {
            port: "/dev/null".into(),
            baud: vec![9600],
            parity: vec![Parity::Even],
            stop_bits,
            latency: None,
            fifo_trigger: None,
        };
        assert_eq!(
            args(vec![]).single_line(),
            Some(LineSettings::new(9600, Parity::Even, 2))
        );
        assert_eq!(
            args(vec![1]).single_line(),
            Some(LineSettings::new(9600, Parity::Even, 1))
        );
        assert_eq!(
            args(vec![1, 2]).single_line(),
            Some(LineSettings::new(9600, Parity::Even, 2))
        );
    }
}
