//! `rtu2mqtt sim`: runs a virtual bus until killed (SIGINT/SIGTERM remove the pty symlink and the
//! control socket). Prints where it listens and which devices are on the bus, then `ready`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context};
use nix::sys::signal::{sigaction, SaFlags, SigAction, SigHandler, SigSet, Signal};

use crate::protocol::LineSettings;
use crate::sim::bus_file::{load_bus, parse_line};
use crate::sim::control_socket::{spawn_control_socket, spawn_stdin_control};
use crate::sim::pty::PtyLink;
use crate::sim::runtime::{ChangeLog, SimRuntime};
use crate::sim::script::{parse_script, spawn_script};
use crate::sim::tcp::TcpMode;
use crate::sim::Bus;

/// Run a virtual RS-485 bus of classic and Fast Modbus devices (see docs/sim.md).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Bus description file (JSON): the devices on the bus.
    #[arg(long, value_name = "FILE")]
    pub bus: PathBuf,
    /// Create a pseudo-terminal and publish its path as this symlink (e.g. /tmp/ttyRS485-sim).
    #[arg(long, value_name = "PATH")]
    pub pty: Option<PathBuf>,
    /// Listen for RTU-over-TCP connections (e.g. 127.0.0.1:5020; port 0 picks a free one).
    #[arg(long, value_name = "ADDR")]
    pub tcp: Option<String>,
    /// Listen for Modbus TCP (MBAP) connections: a gateway in front of the bus, unit id = slave
    /// address (e.g. 127.0.0.1:5502; port 0 picks a free one).
    #[arg(long, value_name = "ADDR")]
    pub modbus_tcp: Option<String>,
    /// Port settings of the TCP listeners' virtual line (RTU over TCP and Modbus TCP).
    #[arg(long, value_name = "SETTINGS", default_value = "9600 8N2")]
    pub tcp_line: String,
    /// Unix socket for JSON-lines control commands.
    #[arg(long, value_name = "SOCKET")]
    pub control: Option<PathBuf>,
    /// Also read control commands from stdin (replies on stdout).
    #[arg(long)]
    pub stdin_control: bool,
    /// Write every register change as a JSON line to FILE, or to stdout with "-".
    #[arg(long, value_name = "FILE|-")]
    pub log_changes: Option<String>,
    /// Run a timed scenario of control commands (JSON lines with at_ms / every_ms / count).
    #[arg(long, value_name = "FILE")]
    pub script: Option<PathBuf>,
    /// Deliver the pty's bytes this many ms after they end on the wire, as a USB-RS485 adapter
    /// does (an FTDI chip holds bytes up to its 16 ms latency timer); 0 = a native UART.
    #[arg(long, value_name = "MS", default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=1000))]
    pub adapter_latency_ms: u64,
    /// Hand the pty's bytes over as a 16550 UART whose receive FIFO collects this many before
    /// handing them over (Linux sets 8 on a 16550A), or once the line has been quiet for 4
    /// characters; 1: every byte as it comes, a frame's end too (the trigger rtu2mqtt and
    /// wb-mqtt-serial set on a controller's UART). Default: bytes as they come, a frame's end
    /// 4 characters late (a UART left at the kernel's trigger).
    #[arg(long, value_name = "BYTES", value_parser = clap::value_parser!(u16).range(1..=256))]
    pub rx_fifo_trigger: Option<u16>,
    /// Where templates named by device_type are looked up (default: ./templates, else the
    /// repository's templates/).
    #[arg(long, value_name = "DIR")]
    pub templates: Option<PathBuf>,
}

static STOP_REQUESTED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_stop_signal(_: nix::libc::c_int) {
    STOP_REQUESTED.store(true, Ordering::SeqCst);
}

fn install_signal_handlers() -> anyhow::Result<()> {
    let action = SigAction::new(
        SigHandler::Handler(on_stop_signal),
        SaFlags::empty(),
        SigSet::empty(),
    );
    for signal in [Signal::SIGINT, Signal::SIGTERM, Signal::SIGHUP] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        unsafe { sigaction(signal, &action) }
            .with_context(|| format!("installing a {signal} handler"))?;
    }
    Ok(())
}

fn templates_dir(args: &Args) -> PathBuf {
    if let Some(dir) = &args.templates {
        return dir.clone();
    }
    let local = Path::new("templates");
    if local.is_dir() {
        local.to_path_buf()
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("templates")
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .try_init();
    if args.pty.is_none() && args.tcp.is_none() && args.modbus_tcp.is_none() {
        bail!("nothing to serve: give --pty PATH, --tcp ADDR and/or --modbus-tcp ADDR");
    }
    let (bus_file, devices) = load_bus(&args.bus, &templates_dir(&args))?;
    let sink: Option<Box<dyn Write + Send>> = match args.log_changes.as_deref() {
        None => None,
        Some("-") => Some(Box::new(std::io::stdout())),
        Some(path) => Some(Box::new(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .with_context(|| format!("opening the change log {path}"))?,
        )),
    };
    let mut runtime = SimRuntime::new(Bus::new(devices, bus_file.seed), ChangeLog::new(sink))
        .with_adapter_latency(Duration::from_millis(args.adapter_latency_ms));
    if let Some(trigger) = args.rx_fifo_trigger {
        runtime = runtime.with_fifo_trigger(usize::from(trigger));
    }
    let runtime = Arc::new(runtime);
    install_signal_handlers()?;
    let mut out = std::io::stdout().lock();
    let mut threads = Vec::new();
    let mut pty_link = None;
    if let Some(link) = &args.pty {
        let pty = PtyLink::open(link, LineSettings::WIREN_BOARD_DEFAULT)
            .with_context(|| format!("creating the pseudo-terminal {}", link.display()))?;
        writeln!(
            out,
            "pty {} -> {}",
            link.display(),
            pty.slave_path.display()
        )?;
        pty_link = Some((pty.link.clone(), pty.slave_path.clone()));
        threads.push(pty.spawn(Arc::clone(&runtime))?);
    }
    if let Some(address) = &args.tcp {
        let line = parse_line(&args.tcp_line).map_err(anyhow::Error::msg)?;
        let (local, handle) = crate::sim::tcp::spawn_listener(address, line, Arc::clone(&runtime))
            .with_context(|| format!("listening on {address}"))?;
        writeln!(out, "tcp {local} ({line})")?;
        threads.push(handle);
    }
    if let Some(address) = &args.modbus_tcp {
        let line = parse_line(&args.tcp_line).map_err(anyhow::Error::msg)?;
        let (local, handle) =
            crate::sim::tcp::spawn(address, line, Arc::clone(&runtime), TcpMode::ModbusTcp)
                .with_context(|| format!("listening on {address}"))?;
        writeln!(out, "modbus-tcp {local} ({line})")?;
        threads.push(handle);
    }
    if let Some(path) = &args.control {
        threads.push(
            spawn_control_socket(path, Arc::clone(&runtime))
                .with_context(|| format!("control socket {}", path.display()))?,
        );
        writeln!(out, "control {}", path.display())?;
    }
    let listing: Vec<String> = runtime.with_bus(|bus, _| {
        bus.devices()
            .iter()
            .map(|device| {
                format!(
                    "device {:>3}  serial 0x{:08X}  {}  {}  {}  {}",
                    device.address(),
                    device.serial,
                    device.line(),
                    if device.fast { "fast   " } else { "classic" },
                    device.name,
                    device.template,
                )
            })
            .collect()
    });
    for line in listing {
        writeln!(out, "{line}")?;
    }
    if let Some(path) = &args.script {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let steps = parse_script(&text).map_err(anyhow::Error::msg)?;
        writeln!(out, "script {} ({} steps)", path.display(), steps.len())?;
        threads.push(spawn_script(steps, Arc::clone(&runtime))?);
    }
    writeln!(out, "ready")?;
    out.flush()?;
    drop(out);
    if args.stdin_control {
        spawn_stdin_control(Arc::clone(&runtime))?;
    }
    while !STOP_REQUESTED.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
    }
    runtime.stop();
    for thread in threads {
        let _ = thread.join();
    }
    if let Some((link, target)) = pty_link {
        crate::sim::pty::remove_link(&link, &target);
    }
    if let Some(path) = &args.control {
        // Only the socket we bound: the path may have been replaced meanwhile.
        if std::fs::symlink_metadata(path)
            .is_ok_and(|m| std::os::unix::fs::FileTypeExt::is_socket(&m.file_type()))
        {
            let _ = std::fs::remove_file(path);
        }
    }
    Ok(ExitCode::SUCCESS)
}
