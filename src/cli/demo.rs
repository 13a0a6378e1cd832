//! `rtu2mqtt demo`: a virtual bus of five devices (the simulator), a broker (mosquitto when
//! installed) and the daemon, with nothing to set up. Everything it needs is built in; it runs
//! in a temporary directory and stops everything on Ctrl-C.

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{bail, Context};
use serde_json::Value;

use crate::config::jsonc::strip_comments;

const BUS: &str = include_str!("../../config/examples/sim-bus.json");
const DAEMON_CONFIG: &str = include_str!("../../config/examples/sim-daemon.json");
const SCENARIO: &str = include_str!("../../config/demo/scenario.script");
const TEMPLATES: [(&str, &str); 6] = [
    (
        "rtu2mqtt-relay6.json",
        include_str!("../../templates/rtu2mqtt-relay6.json"),
    ),
    (
        "rtu2mqtt-climate.json",
        include_str!("../../templates/rtu2mqtt-climate.json"),
    ),
    (
        "rtu2mqtt-counter8.json",
        include_str!("../../templates/rtu2mqtt-counter8.json"),
    ),
    (
        "rtu2mqtt-dimmer.json",
        include_str!("../../templates/rtu2mqtt-dimmer.json"),
    ),
    (
        "rtu2mqtt-energy-meter.json",
        include_str!("../../templates/rtu2mqtt-energy-meter.json"),
    ),
    (
        "rtu2mqtt-generic.json",
        include_str!("../../templates/rtu2mqtt-generic.json"),
    ),
];

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Don't start a broker: print device updates as JSON lines instead.
    #[arg(long)]
    pub no_broker: bool,
    /// Port for the demo's broker (default 1883 if free, else any free port).
    #[arg(long)]
    pub mqtt_port: Option<u16>,
}

/// The demo's scratch directory, removed at the end.
struct DemoDir(PathBuf);

impl DemoDir {
    fn create() -> anyhow::Result<Self> {
        let path = std::env::temp_dir().join(format!("rtu2mqtt-demo-{}", std::process::id()));
        std::fs::create_dir_all(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        Ok(Self(path))
    }

    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for DemoDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A child process that is killed when the demo ends.
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let dir = DemoDir::create()?;
    let templates = dir.path().join("templates");
    std::fs::create_dir(&templates)?;
    for (name, text) in TEMPLATES {
        std::fs::write(templates.join(name), text)?;
    }
    let bus = dir.path().join("bus.json");
    std::fs::write(&bus, BUS)?;
    let scenario = dir.path().join("scenario.script");
    std::fs::write(&scenario, SCENARIO)?;
    let pty = dir.path().join("ttyRS485-demo");
    let control = dir.path().join("sim.sock");

    let broker = if args.no_broker {
        None
    } else {
        start_broker(dir.path(), args.mqtt_port)?
    };
    let _sim = start_simulator(&bus, &templates, &pty, &control, &scenario)?;

    let config = dir.path().join("config.json");
    let mut daemon_config: Value = serde_json::from_str(&strip_comments(DAEMON_CONFIG))
        .context("the built-in demo config is not JSON")?;
    daemon_config["ports"][0]["path"] = Value::from(pty.display().to_string());
    daemon_config["mqtt"]["host"] = Value::from("127.0.0.1");
    daemon_config["mqtt"]["client_id"] = Value::from("rtu2mqtt-demo");
    if let Some((_, port)) = &broker {
        daemon_config["mqtt"]["port"] = Value::from(*port);
    }
    std::fs::write(&config, serde_json::to_string_pretty(&daemon_config)?)?;

    eprintln!("rtu2mqtt demo: five simulated devices on a virtual RS-485 bus at 115200 8N2 (Fast Modbus events on)");
    eprintln!(
        "  bus:        {} (simulator control socket: {})",
        pty.display(),
        control.display()
    );
    match &broker {
        Some((_, port)) => {
            eprintln!("  broker:     mosquitto on 127.0.0.1:{port}");
            eprintln!("  watch:      mosquitto_sub -h 127.0.0.1 -p {port} -t '/devices/#' -v");
            eprintln!("  switch K2:  mosquitto_pub -h 127.0.0.1 -p {port} -t /devices/relay6_20/controls/K2/on -m 1");
        }
        None => eprintln!(
            "  no broker:  device updates follow as JSON lines (install mosquitto for MQTT)"
        ),
    }
    eprintln!("  Ctrl-C stops everything.");
    let run_args = super::run::Args {
        config,
        templates: vec![templates],
        stdio: broker.is_none(),
    };
    let code = super::run::run(run_args)?;
    // Stop the simulator and the broker before the directory they use goes.
    drop(_sim);
    drop(broker);
    drop(dir);
    Ok(code)
}

fn find_mosquitto() -> Option<PathBuf> {
    let from_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|paths| std::env::split_paths(&paths).collect::<Vec<_>>())
        .map(|dir| dir.join("mosquitto"));
    from_path
        .chain([PathBuf::from("/usr/sbin/mosquitto")])
        .find(|path| path.is_file())
}

fn port_is_free(port: u16) -> bool {
    TcpListener::bind(("127.0.0.1", port)).is_ok()
}

/// mosquitto on loopback, or None (with a note) when it is not installed.
fn start_broker(dir: &Path, wanted: Option<u16>) -> anyhow::Result<Option<(Guard, u16)>> {
    let Some(mosquitto) = find_mosquitto() else {
        eprintln!("mosquitto is not installed (apt-get install mosquitto mosquitto-clients): running without a broker");
        return Ok(None);
    };
    let port = match wanted {
        Some(port) => port,
        None if port_is_free(1883) => 1883,
        None => TcpListener::bind("127.0.0.1:0")?.local_addr()?.port(),
    };
    let config = dir.join("mosquitto.conf");
    std::fs::write(
        &config,
        format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
    )?;
    let child = Command::new(&mosquitto)
        // Its own process group: Ctrl-C reaches the demo only, which stops the daemon first
        // (it clears its retained topics) and then the broker.
        .process_group(0)
        .arg("-c")
        .arg(&config)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("cannot start {}", mosquitto.display()))?;
    let mut guard = Guard(child);
    for _ in 0..100 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Ok(Some((guard, port)));
        }
        if let Ok(Some(status)) = guard.0.try_wait() {
            bail!("mosquitto stopped at start ({status}); is port {port} taken? Try --mqtt-port");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    bail!("mosquitto did not start listening on 127.0.0.1:{port}")
}

/// `rtu2mqtt sim` as a child process; returns once it printed "ready".
fn start_simulator(
    bus: &Path,
    templates: &Path,
    pty: &Path,
    control: &Path,
    scenario: &Path,
) -> anyhow::Result<Guard> {
    let exe = std::env::current_exe().context("cannot find the rtu2mqtt binary")?;
    let mut child = Command::new(exe)
        .process_group(0)
        .arg("sim")
        .arg("--bus")
        .arg(bus)
        .arg("--templates")
        .arg(templates)
        .arg("--pty")
        .arg(pty)
        .arg("--control")
        .arg(control)
        .arg("--script")
        .arg(scenario)
        .stdout(Stdio::piped())
        .stdin(Stdio::null())
        .spawn()
        .context("cannot start the simulator")?;
    let stdout = child.stdout.take().context("no simulator output")?;
    let guard = Guard(child);
    let (ready_tx, ready_rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if line == "ready" {
                let _ = ready_tx.send(());
            }
        }
    });
    ready_rx
        .recv_timeout(Duration::from_secs(15))
        .context("the simulator did not get ready within 15 s")?;
    Ok(guard)
}
