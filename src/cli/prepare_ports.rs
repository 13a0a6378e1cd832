//! `rtu2mqtt prepare-ports`: what the daemon needs of its serial ports and cannot do itself
//! once its privileges are dropped (the systemd unit runs it as root before the daemon):
//! each UART's receive FIFO set to hand bytes over one at a time (`rx_trig_bytes` = 1), as
//! wb-mqtt-serial sets it. With the kernel's default (8 bytes on a 16550A) a reply's end
//! reaches the daemon 4 characters late on every transaction. It also says which other
//! processes have a port open (wb-mqtt-serial still running on it: two masters on one bus).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use super::check::load_or_print_errors;
use crate::config::load::DEFAULT_CONFIG_PATH;
use crate::transport::fifo::{self, TriggerChange};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Config file: its enabled serial ports are prepared.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// Where the kernel shows tty devices (for tests).
    #[arg(long, hide = true, default_value = "/sys/class/tty")]
    pub sysfs_tty: PathBuf,
}

/// Prints one line per serial port. Fails only when the config cannot be read: a port that
/// cannot be prepared still works (the daemon allows for its FIFO), so the service must start.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let Some(loaded) = load_or_print_errors(&args.config) else {
        return Ok(ExitCode::FAILURE);
    };
    for path in loaded.config.serial_port_paths() {
        println!("{path}: {}", prepare(Path::new(path), &args.sysfs_tty));
        for (pid, name) in other_openers(Path::new(path)) {
            println!(
                "{path}: warning: also open in {name} (pid {pid}): two masters on one bus garble \
                 each other's requests and answer each other's reads; stop it first (for \
                 wb-mqtt-serial: systemctl mask --now wb-mqtt-serial)"
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The processes besides this one that have `path` open, from `/proc/<pid>/fd` (as root, which
/// the unit runs this as, every process is seen). wb-mqtt-serial takes no lock on its ports, so
/// the daemon's own open cannot tell that it still holds one: this is where that shows.
fn other_openers(path: &Path) -> Vec<(u32, String)> {
    let Ok(target) = std::fs::canonicalize(path) else {
        return Vec::new();
    };
    let Ok(processes) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let me = std::process::id();
    let mut openers = Vec::new();
    for process in processes.flatten() {
        let Some(pid) = process
            .file_name()
            .to_str()
            .and_then(|name| name.parse::<u32>().ok())
        else {
            continue;
        };
        if pid == me {
            continue;
        }
        // A process that is gone, or one this user may not look into, is skipped.
        let Ok(descriptors) = std::fs::read_dir(process.path().join("fd")) else {
            continue;
        };
        let holds = descriptors
            .flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|open| open == target));
        if holds {
            let name = std::fs::read_to_string(process.path().join("comm"))
                .map(|comm| comm.trim().to_owned())
                .unwrap_or_else(|_| "another process".into());
            openers.push((pid, name));
        }
    }
    openers
}

fn prepare(path: &Path, sysfs_tty: &Path) -> String {
    if !path.exists() {
        return "does not exist (a USB adapter not plugged in, or a typo in the config?); \
                nothing to set"
            .into();
    }
    match fifo::lower_to_one_byte(path, sysfs_tty) {
        TriggerChange::NotReported => {
            "no receive FIFO trigger to set (USB adapter, or not a UART the kernel reports)".into()
        }
        TriggerChange::AlreadyOne => "receive FIFO hands bytes over one at a time".into(),
        TriggerChange::Lowered { previous, .. } => {
            format!("receive FIFO set to hand bytes over one at a time (it collected {previous})")
        }
        TriggerChange::Holds { trigger, why } => format!(
            "receive FIFO collects {trigger} bytes and could not be set to 1 ({why}; run as root)"
        ),
    }
}
