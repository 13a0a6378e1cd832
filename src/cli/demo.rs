//! `rtu2mqtt demo`: a virtual bus of five devices (the simulator), a broker (the one already
//! listening on 127.0.0.1:1883, else a built-in one) and the daemon, with nothing to set up. Everything it needs is built in; it runs
//! in a temporary directory and stops everything on Ctrl-C.

use crate::child::StopWithParent;
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use anyhow::Context;
use serde_json::Value;

use crate::config::jsonc::strip_comments;
use crate::embedded_broker::EmbeddedBroker;

const BUS: &str = include_str!("../../config/examples/sim-bus.json");
const DAEMON_CONFIG: &str = include_str!("../../config/examples/sim-daemon.json");
const SCENARIO: &str = include_str!("../../config/demo/scenario.script");

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Don't start a broker: print device updates as JSON lines instead.
    #[arg(long)]
    pub no_broker: bool,
    /// MQTT port on 127.0.0.1 (default 1883): a broker already listening there is used,
    /// otherwise a built-in one is started on it.
    #[arg(long)]
    pub mqtt_port: Option<u16>,
    /// Port of the status page on 127.0.0.1 (default 8080, or a free one when 8080 is taken).
    #[arg(long)]
    pub http_port: Option<u16>,
}

/// The demo's scratch directory: private (0700), under a fresh random name, removed at the end.
/// A predictable path would let another local user plant links the demo then writes through.
fn create_demo_dir() -> anyhow::Result<tempfile::TempDir> {
    tempfile::Builder::new()
        .prefix("rtu2mqtt-demo-")
        .tempdir()
        .context("cannot create the demo's directory")
}

/// Writes a new file; never follows or replaces anything already there.
fn write_new(path: &Path, text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .with_context(|| format!("cannot create {}", path.display()))?;
    file.write_all(text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
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
    let dir = create_demo_dir()?;
    let templates = dir.path().join("templates");
    std::fs::create_dir(&templates)?;
    for (name, text) in crate::config::library::BUILT_IN_TEMPLATES {
        write_new(&templates.join(name), text)?;
    }
    let bus = dir.path().join("bus.json");
    write_new(&bus, BUS)?;
    let scenario = dir.path().join("scenario.script");
    write_new(&scenario, SCENARIO)?;
    let pty = dir.path().join("ttyRS485-demo");
    let control = dir.path().join("sim.sock");

    let broker = if args.no_broker {
        None
    } else {
        Some(choose_broker(args.mqtt_port)?)
    };
    let _sim = start_simulator(&bus, &templates, &pty, &control, &scenario)?;

    let config = dir.path().join("config.json");
    let mut daemon_config: Value = serde_json::from_str(&strip_comments(DAEMON_CONFIG))
        .context("the built-in demo config is not JSON")?;
    daemon_config["ports"][0]["path"] = Value::from(pty.display().to_string());
    daemon_config["mqtt"]["host"] = Value::from("127.0.0.1");
    daemon_config["mqtt"]["client_id"] = Value::from("rtu2mqtt-demo");
    if let Some(broker) = &broker {
        daemon_config["mqtt"]["port"] = Value::from(broker.port());
    }
    let http_listener = bind_http_port(args.http_port)?;
    let http_port = http_listener.local_addr()?.port();
    daemon_config["http"] = serde_json::json!({"listen": format!("127.0.0.1:{http_port}")});
    write_new(&config, &serde_json::to_string_pretty(&daemon_config)?)?;

    eprintln!("rtu2mqtt demo: five simulated devices on a virtual RS-485 bus at 115200 8N2 (Fast Modbus events on)");
    eprintln!(
        "  bus:        {} (simulator control socket: {})",
        pty.display(),
        control.display()
    );
    eprintln!("  files:      {}", dir.path().display());
    eprintln!("  status:     http://127.0.0.1:{http_port}/  (live page; /metrics for Prometheus)");
    match &broker {
        Some(broker) => {
            let port = broker.port();
            match broker {
                DemoBroker::Embedded(_) => {
                    eprintln!("  broker:     built-in MQTT broker on 127.0.0.1:{port}")
                }
                DemoBroker::Existing(_) => eprintln!(
                    "  broker:     the broker already listening on 127.0.0.1:{port} (use --mqtt-port for another)"
                ),
            }
            eprintln!("  watch:      mosquitto_sub -h 127.0.0.1 -p {port} -t '/devices/#' -v");
            eprintln!("  switch K2:  mosquitto_pub -h 127.0.0.1 -p {port} -t /devices/relay6_20/controls/K2/on -m 1");
        }
        None => eprintln!("  no broker:  device updates follow as JSON lines"),
    }
    eprintln!("  Ctrl-C stops everything.");
    let run_args = super::run::Args {
        config,
        templates: vec![templates],
        stdio: broker.is_none(),
        http_listener: Some(std::sync::Arc::new(http_listener)),
    };
    let _live_view = broker.as_ref().map(|b| live_view(b.port()));
    let code = super::run::run(run_args)?;
    // Stop the simulator and the broker before the directory they use goes.
    drop(_sim);
    drop(broker);
    drop(dir);
    Ok(code)
}

/// The status page's socket: on the port asked for, else 8080 when free, else any free one.
/// Bound here and handed to the daemon, so the URL printed is the one served.
fn bind_http_port(wanted: Option<u16>) -> anyhow::Result<std::net::TcpListener> {
    let bind = |port: u16| std::net::TcpListener::bind(("127.0.0.1", port));
    if let Some(port) = wanted {
        return bind(port).with_context(|| {
            format!("the status page cannot listen on 127.0.0.1:{port}: is another program using the port? Pick another with --http-port")
        });
    }
    bind(8080)
        .or_else(|_| bind(0))
        .context("no free TCP port on 127.0.0.1 for the status page")
}

/// Where the demo's daemon publishes.
enum DemoBroker {
    /// Nothing listened on the port: our own, stopped with the demo.
    Embedded(EmbeddedBroker),
    /// Something already listens there (say the machine's mosquitto): use it.
    Existing(u16),
}

impl DemoBroker {
    fn port(&self) -> u16 {
        match self {
            Self::Embedded(broker) => broker.port(),
            Self::Existing(port) => *port,
        }
    }
}

/// The broker on `wanted` (1883 by default) if one listens there, else the built-in one on that
/// port (or on any free port when 1883 cannot be had).
fn choose_broker(wanted: Option<u16>) -> anyhow::Result<DemoBroker> {
    let port = wanted.unwrap_or(1883);
    if std::net::TcpStream::connect_timeout(
        &std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        Duration::from_millis(500),
    )
    .is_ok()
    {
        return Ok(DemoBroker::Existing(port));
    }
    match EmbeddedBroker::start(port) {
        Ok(broker) => Ok(DemoBroker::Embedded(broker)),
        Err(_) if wanted.is_none() => Ok(DemoBroker::Embedded(
            EmbeddedBroker::start(0).context("cannot start the built-in MQTT broker")?,
        )),
        Err(err) => Err(err).with_context(|| format!("cannot listen on 127.0.0.1:{port} for MQTT")),
    }
}

/// Prints each control value as it reaches the broker, one compact line per change, on stdout
/// (the daemon's log goes to stderr). Runs on its own thread until the demo ends.
fn live_view(port: u16) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        else {
            return;
        };
        runtime.block_on(async move {
            use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
            let options = MqttOptions::new(
                format!("rtu2mqtt-demo-view-{}", std::process::id()),
                "127.0.0.1",
                port,
            );
            let (client, mut eventloop) = AsyncClient::new(options, 16);
            let _ = client
                .subscribe("/devices/+/controls/+", QoS::AtMostOnce)
                .await;
            let started = std::time::Instant::now();
            loop {
                match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::Publish(p))) if !p.retain => {
                        let parts: Vec<&str> = p.topic.split('/').collect();
                        if let [_, _, device, _, control] = parts.as_slice() {
                            println!(
                                "{:>9.3} s  {device:<14} {control:<24} {}",
                                started.elapsed().as_secs_f64(),
                                String::from_utf8_lossy(&p.payload)
                            );
                        }
                    }
                    Ok(_) => {}
                    // The broker went away: the demo is ending.
                    Err(_) => return,
                }
            }
        });
    })
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
        .stop_with_parent()
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
