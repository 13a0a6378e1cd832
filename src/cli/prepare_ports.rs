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
    /// A process not to name as another master on the ports: the service's own daemon, which
    /// has them open when a reload runs this (`--except-pid $MAINPID` in the unit).
    #[arg(long = "except-pid", value_name = "PID")]
    pub except_pid: Vec<u32>,
}

/// Prints one line per serial port. Fails only when the config cannot be read: a port that
/// cannot be prepared still works (the daemon allows for its FIFO), so the service must start.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let Some(loaded) = load_or_print_errors(&args.config) else {
        return Ok(ExitCode::FAILURE);
    };
    let paths: Vec<&str> = loaded.config.serial_port_paths().collect();
    let openers = OpenFiles::of_other_processes(&args.except_pid);
    for path in &paths {
        println!("{path}: {}", prepare(Path::new(path), &args.sysfs_tty));
        for (pid, name) in openers.holding(Path::new(path)) {
            println!(
                "{path}: warning: also open in {name} (pid {pid}): two masters on one bus garble \
                 each other's requests and answer each other's reads; stop it on this port first \
                 (for wb-mqtt-serial: take the port out of /etc/wb-mqtt-serial.conf and restart \
                 it, or stop it altogether with systemctl mask --now wb-mqtt-serial)"
            );
        }
    }
    if openers.unreadable > 0 && !paths.is_empty() {
        println!(
            "note: {} processes could not be looked into (not root), so another master on these \
             ports may have gone unseen",
            openers.unreadable
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// What the other processes have open, from `/proc/<pid>/fd` (as root, which the unit runs
/// this as, every process is seen). wb-mqtt-serial takes no lock on its ports, so the daemon's
/// own open cannot tell that it still holds one: this is where that shows.
struct OpenFiles {
    /// Each process looked into: its pid, its name and what its descriptors point to.
    processes: Vec<(u32, String, Vec<PathBuf>)>,
    /// Processes whose descriptors this user may not read.
    unreadable: usize,
}

impl OpenFiles {
    /// Every process but this one and `except` (the service's own daemon, at a reload).
    fn of_other_processes(except: &[u32]) -> Self {
        let mut open = OpenFiles {
            processes: Vec::new(),
            unreadable: 0,
        };
        let Ok(entries) = std::fs::read_dir("/proc") else {
            return open;
        };
        let me = std::process::id();
        for entry in entries.flatten() {
            let Some(pid) = entry
                .file_name()
                .to_str()
                .and_then(|name| name.parse::<u32>().ok())
            else {
                continue;
            };
            if pid == me || except.contains(&pid) {
                continue;
            }
            let descriptors = match std::fs::read_dir(entry.path().join("fd")) {
                Ok(descriptors) => descriptors,
                Err(err) if err.kind() == std::io::ErrorKind::PermissionDenied => {
                    open.unreadable += 1;
                    continue;
                }
                // Gone since /proc was listed.
                Err(_) => continue,
            };
            let targets = descriptors
                .flatten()
                .filter_map(|fd| std::fs::read_link(fd.path()).ok())
                .collect();
            let name = std::fs::read_to_string(entry.path().join("comm"))
                .map(|comm| comm.trim().to_owned())
                .unwrap_or_else(|_| "another process".into());
            open.processes.push((pid, name, targets));
        }
        open
    }

    /// The processes that have `path` open.
    fn holding(&self, path: &Path) -> Vec<(u32, &str)> {
        let Ok(target) = std::fs::canonicalize(path) else {
            return Vec::new();
        };
        self.processes
            .iter()
            .filter(|(_, _, targets)| targets.contains(&target))
            .map(|(pid, name, _)| (*pid, name.as_str()))
            .collect()
    }
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
