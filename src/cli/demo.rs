//! `rtu2mqtt demo`: a virtual bus of five devices (the simulator), a broker (the one already
//! listening on 127.0.0.1:1883, else a built-in one) and the daemon, with nothing to set up. Everything it needs is built in; it runs
//! in a temporary directory and stops everything on Ctrl-C.
//!
//! The broker may be shared with a real installation (the machine's mosquitto, watched by Home
//! Assistant), so the demo keeps to its own topics: every device id starts with `demo_` (a real
//! daemon serving the same device types has `counter8_22`, never `demo_counter8_22`), the daemon
//! clears its device topics and discovery configs on exit, and the demo then deletes its driver
//! topics (`/rtu2mqtt/rtu2mqtt-demo/…`). One demo at a time per broker: see [`tidy_broker`].

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

/// Put before every device id of the demo, so that its topics (`/devices/demo_counter8_22/…`)
/// and Home Assistant ids never meet those of a real daemon on the same broker: the daemon's
/// clear on exit deletes every topic of its device ids, whoever published them.
const DEVICE_ID_PREFIX: &str = "demo_";

/// The demo daemon's MQTT client id (its driver topics are `/rtu2mqtt/rtu2mqtt-demo/…`, its HA
/// ids `rtu2mqtt-demo_<device>`). Unlike the daemon's default (`rtu2mqtt`) or the simulator
/// example's (`rtu2mqtt-sim`), so it does not take over a running daemon's connection (a broker
/// drops the older of two clients with one id). Fixed rather than one per run, on purpose: two
/// demos on one broker would still publish the same `demo_*` devices and each clear the
/// other's on exit, so a second demo is refused instead ([`tidy_broker`] finds the first one's
/// retained `online` status); and a fixed id means a demo that was killed leaves its discovery
/// configs under the same topics the next run overwrites and clears, not under a new id each
/// time.
const CLIENT_ID: &str = "rtu2mqtt-demo";

/// The demo's Home Assistant discovery prefix (HA's default).
const HA_PREFIX: &str = "homeassistant";

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

    let config = dir.path().join("config.json");
    let mut daemon_config: Value = serde_json::from_str(&strip_comments(DAEMON_CONFIG))
        .context("the built-in demo config is not JSON")?;
    daemon_config["ports"][0]["path"] = Value::from(pty.display().to_string());
    daemon_config["mqtt"]["host"] = Value::from("127.0.0.1");
    daemon_config["mqtt"]["client_id"] = Value::from(CLIENT_ID);
    // Leave nothing on the broker: the device topics (the daemon's default too) and, unlike
    // the daemon's default, the discovery configs. A daemon keeps those on a restart so HA
    // keeps its entities' names, areas and dashboards; the demo's devices go away for good
    // with it, and configs left behind are phantom HA devices.
    daemon_config["mqtt"]["clear_on_exit"] = Value::from(true);
    daemon_config["mqtt"]["homeassistant"] = serde_json::json!({
        "enabled": true,
        "prefix": HA_PREFIX,
        "clear_on_exit": true,
    });
    let base_ids = demo_device_ids(&mut daemon_config)?;

    let mut rpc_advertised_before = false;
    let broker = if args.no_broker {
        None
    } else {
        Some(choose_broker(args.mqtt_port)?)
    };
    if let Some(DemoBroker::Existing(port)) = &broker {
        rpc_advertised_before = tidy_broker(*port, &base_ids, Tidy::BeforeStart)?;
    }
    let _sim = start_simulator(&bus, &templates, &pty, &control, &scenario)?;

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
            eprintln!(
                "  devices:    {} (the {DEVICE_ID_PREFIX} prefix keeps them apart from a real gateway's on the same broker)",
                demo_ids(&base_ids).join(", ")
            );
            eprintln!("  watch:      mosquitto_sub -h 127.0.0.1 -p {port} -t '/devices/#' -v");
            eprintln!("  switch K2:  mosquitto_pub -h 127.0.0.1 -p {port} -t /devices/{DEVICE_ID_PREFIX}relay6_20/controls/K2/on -m 1");
        }
        None => eprintln!("  no broker:  device updates follow as JSON lines"),
    }
    match &broker {
        Some(_) => eprintln!(
            "  Ctrl-C stops everything and deletes the demo's retained topics and Home Assistant configs."
        ),
        None => eprintln!("  Ctrl-C stops everything."),
    }
    let run_args = super::run::Args {
        config,
        templates: vec![templates],
        stdio: broker.is_none(),
        http_listener: Some(std::sync::Arc::new(http_listener)),
    };
    let _live_view = broker.as_ref().map(|b| live_view(b.port()));
    let code = super::run::run(run_args)?;
    // The daemon has deleted its devices' topics and discovery configs; what is left is its
    // driver status (`offline`) and device record.
    if let Some(DemoBroker::Existing(port)) = &broker {
        let after = Tidy::AfterExit {
            rpc_advertised_before,
        };
        if let Err(err) = tidy_broker(*port, &base_ids, after) {
            eprintln!("rtu2mqtt demo: the demo's driver topics may be left on the broker: {err:#}");
        }
    }
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
                        if let Some(line) = view_line(started.elapsed(), &p.topic, &p.payload) {
                            println!("{line}");
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

/// The live view's line for a publication: a value of one of the demo's controls. An empty
/// payload deletes a retained topic (the daemon tidying up as the demo ends): not a value to
/// show. The broker may serve a real gateway too, whose devices are not the demo's.
fn view_line(elapsed: Duration, topic: &str, payload: &[u8]) -> Option<String> {
    let [_, _, device, _, control] = topic.split('/').collect::<Vec<_>>()[..] else {
        return None;
    };
    if !device.starts_with(DEVICE_ID_PREFIX) || payload.is_empty() {
        return None;
    }
    Some(format!(
        "{:>9.3} s  {device:<20} {control:<24} {}",
        elapsed.as_secs_f64(),
        String::from_utf8_lossy(payload)
    ))
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

/// Gives every device of the demo config the id `demo_<its usual id>` (the template's id and
/// the slave id, as the daemon would name it); returns the usual ids, in config order.
fn demo_device_ids(config: &mut Value) -> anyhow::Result<Vec<String>> {
    let mut base_ids = Vec::new();
    let ports = config["ports"]
        .as_array_mut()
        .context("the built-in demo config has no ports")?;
    for device in ports
        .iter_mut()
        .filter_map(|port| port["devices"].as_array_mut())
        .flatten()
    {
        let base = match device.get("id").and_then(Value::as_str) {
            Some(id) => id.to_string(),
            None => {
                let device_type = device["device_type"]
                    .as_str()
                    .context("a device of the built-in demo config has no device_type")?;
                let slave_id = match &device["slave_id"] {
                    Value::String(text) => text.clone(),
                    other => other.to_string(),
                };
                format!("{}_{slave_id}", template_id(device_type)?)
            }
        };
        device["id"] = Value::from(format!("{DEVICE_ID_PREFIX}{base}"));
        base_ids.push(base);
    }
    Ok(base_ids)
}

/// The ids the demo's devices have on the broker.
fn demo_ids(base_ids: &[String]) -> Vec<String> {
    base_ids
        .iter()
        .map(|id| format!("{DEVICE_ID_PREFIX}{id}"))
        .collect()
}

/// The `device.id` of a built-in template (the prefix of its devices' default ids).
fn template_id(device_type: &str) -> anyhow::Result<String> {
    let file = format!("{device_type}.json");
    let (_, text) = crate::config::library::BUILT_IN_TEMPLATES
        .iter()
        .find(|(name, _)| *name == file)
        .with_context(|| format!("no built-in template {device_type}"))?;
    let template: Value = serde_json::from_str(&strip_comments(text))
        .with_context(|| format!("the built-in template {device_type} is not JSON"))?;
    template["device"]["id"]
        .as_str()
        .map(str::to_string)
        .with_context(|| format!("the built-in template {device_type} has no device.id"))
}

/// How long the demo waits for a shared broker to show and delete its retained topics.
const TIDY_TIMEOUT: Duration = Duration::from_secs(10);

/// When [`tidy_broker`] runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Tidy {
    /// Before the daemon starts: refuse if another demo is online; delete the driver topics
    /// and the discovery configs an earlier demo left.
    BeforeStart,
    /// After the daemon has exited (and deleted its devices' topics and discovery configs
    /// itself): delete its driver topics, and the RPC method topics unless another server
    /// advertised them before the demo started (they are shared: the daemon leaves them).
    AfterExit { rpc_advertised_before: bool },
}

/// Deletes what the demo keeps retained on a shared broker, besides what its daemon deletes
/// itself, by exact topic (nothing of another gateway is even read):
/// - the driver topics `/rtu2mqtt/rtu2mqtt-demo/…`: status, availability, and the device
///   record, which an older demo wrote with unprefixed ids such as `counter8_22`: the daemon's
///   start-up sweep would delete those devices' topics, a real gateway's;
/// - before the start, the discovery configs of the demo's HA devices, by exact node
///   (`rtu2mqtt-demo_demo_counter8_22`, left by a demo that was killed, and
///   `rtu2mqtt-demo_counter8_22`, left by the demos before the `demo_` ids).
///
/// Before the start it first checks that no other demo (or client with the demo's client id)
/// is online there: two would take each other's connection and clear each other's devices.
/// Returns whether wb-mqtt-serial's RPC methods were advertised on the broker (another server
/// of them runs, or ran).
fn tidy_broker(port: u16, base_ids: &[String], when: Tidy) -> anyhow::Result<bool> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the demo's MQTT client")?;
    runtime.block_on(async {
        tokio::time::timeout(TIDY_TIMEOUT, tidy(port, base_ids, when))
            .await
            .with_context(|| format!("the broker on 127.0.0.1:{port} did not answer in time"))?
    })
}

async fn tidy(port: u16, base_ids: &[String], when: Tidy) -> anyhow::Result<bool> {
    use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS, SubscribeFilter};
    use std::collections::BTreeSet;

    let node = crate::mqtt::topics::topic_level(CLIENT_ID);
    let driver = format!("/rtu2mqtt/{node}/");
    let status = format!("{driver}status");
    let discovery_nodes: BTreeSet<String> = base_ids
        .iter()
        .filter(|_| when == Tidy::BeforeStart)
        .flat_map(|id| [id.clone(), format!("{DEVICE_ID_PREFIX}{id}")])
        .map(|id| format!("{node}_{}", crate::mqtt::topics::topic_level(&id)))
        .collect();
    let id = format!("{CLIENT_ID}-tidy-{}", std::process::id());
    let mut options = MqttOptions::new(id, "127.0.0.1", port);
    options.set_max_packet_size(1 << 20, 1 << 20);
    let (client, mut eventloop) = AsyncClient::new(options, 64);
    // The advertised methods only: a request topic has one level more (its client).
    let rpc_methods = format!("{}/+/+", crate::rpc::message::TOPIC_ROOT);
    let filters: Vec<SubscribeFilter> = [format!("{driver}#"), rpc_methods]
        .into_iter()
        .chain(
            discovery_nodes
                .iter()
                .map(|node| format!("{HA_PREFIX}/+/{node}/+/config")),
        )
        .map(|filter| SubscribeFilter::new(filter, QoS::AtLeastOnce))
        .collect();
    // Sent to ourselves after subscribing: the broker delivers the retained messages of a
    // subscription before a later publication of the same client, so when the marker comes
    // back every retained topic there has been seen.
    let marker = format!("{driver}tidy-{}", std::process::id());
    let mut found = Vec::new();
    // The marker back, and its acknowledgement (which must not count as a deletion's).
    let (mut marker_back, mut marker_acked) = (false, false);
    let mut connected = false;
    while !(marker_back && marker_acked) {
        let event = match eventloop.poll().await {
            Ok(event) => event,
            // A broker that answered, and said no (a password required, say).
            Err(rumqttc::ConnectionError::ConnectionRefused(code)) => anyhow::bail!(
                "the MQTT broker on 127.0.0.1:{port} refused the demo's connection ({code:?}): \
                 it may take no anonymous clients. Give the demo a free port with --mqtt-port \
                 (it starts its own broker there)"
            ),
            // Something took the TCP connection but never answered MQTT's CONNECT.
            Err(err) if !connected => anyhow::bail!(
                "127.0.0.1:{port} takes connections but does not answer as an MQTT broker \
                 ({err}): is another program listening there? Give the demo a free port with \
                 --mqtt-port (it starts its own broker there) or a running broker's"
            ),
            Err(err) => return Err(anyhow::Error::new(err).context("MQTT")),
        };
        match event {
            Event::Incoming(Packet::ConnAck(_)) => {
                connected = true;
                client.subscribe_many(filters.clone()).await?;
            }
            Event::Incoming(Packet::SubAck(_)) => {
                client
                    .publish(marker.as_str(), QoS::AtLeastOnce, false, "x")
                    .await?;
            }
            Event::Incoming(Packet::Publish(p)) if p.topic == marker => marker_back = true,
            Event::Incoming(Packet::PubAck(_)) => marker_acked = true,
            Event::Incoming(Packet::Publish(p)) if p.retain && !p.payload.is_empty() => {
                found.push((p.topic, p.payload));
            }
            _ => {}
        }
    }
    if when == Tidy::BeforeStart
        && found
            .iter()
            .any(|(topic, payload)| *topic == status && payload.as_ref() == b"online")
    {
        let _ = client.disconnect().await;
        anyhow::bail!(
            "another rtu2mqtt demo (MQTT client id {CLIENT_ID}) is running on the broker at \
             127.0.0.1:{port} ({status} is `online`): stop it first, or give this one its own \
             broker with --mqtt-port. If none runs (a broker restored a stale status), delete \
             the status: mosquitto_pub -h 127.0.0.1 -p {port} -r -n -t {status}"
        );
    }
    let is_rpc = |topic: &str| topic.starts_with(crate::rpc::message::TOPIC_ROOT);
    let rpc_advertised = found.iter().any(|(topic, _)| is_rpc(topic));
    found.retain(|(topic, _)| {
        !is_rpc(topic)
            || matches!(
                when,
                Tidy::AfterExit {
                    rpc_advertised_before: false
                }
            )
    });
    // Deleted (empty retained payloads) while the event loop runs: the client's queue is
    // bounded. Done when the broker has acknowledged every deletion.
    let count = found.len();
    let delete = async {
        for (topic, _) in found {
            client.publish(topic, QoS::AtLeastOnce, true, "").await?;
        }
        anyhow::Ok(())
    };
    let acknowledged = async {
        let mut acks = 0;
        while acks < count {
            if let Event::Incoming(Packet::PubAck(_)) = eventloop.poll().await.context("MQTT")? {
                acks += 1;
            }
        }
        anyhow::Ok(())
    };
    let (deleted, acknowledged) = tokio::join!(delete, acknowledged);
    deleted?;
    acknowledged?;
    client.disconnect().await?;
    loop {
        match eventloop.poll().await {
            Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => {
                return Ok(rpc_advertised)
            }
            Ok(_) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_live_view_shows_the_demos_values_and_not_the_deletions_at_its_end() {
        let at = Duration::from_millis(1500);
        let line = view_line(at, "/devices/demo_relay6_20/controls/K2", b"1").unwrap();
        assert!(
            line.contains("demo_relay6_20") && line.contains("K2"),
            "{line}"
        );
        assert!(
            line.starts_with("    1.500 s") && line.ends_with(" 1"),
            "{line}"
        );
        assert_eq!(
            view_line(at, "/devices/demo_relay6_20/controls/K2", b""),
            None
        );
        assert_eq!(view_line(at, "/devices/relay6_20/controls/K2", b"1"), None);
        assert_eq!(view_line(at, "/devices/demo_relay6_20/meta", b"{}"), None);
    }
}
