//! SIGHUP reloads the config with real processes (two simulated buses, the daemon, mosquitto):
//! a device removed from one port loses its retained topics, a device added there is set up and
//! published, the other port keeps running untouched (its task is not restarted and still takes
//! writes), and a config that does not load leaves everything running as it was. Also what
//! becomes of a write while its port is away: carried over a reload that restarts the port,
//! given up after the device's write retry time.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use rtu2mqtt::child::StopWithParent;
use std::path::Path;
use std::process::{Child, Command, Stdio};

use daemon_support::repo;
use mqtt_support::{publish, retained, rpc, wait_for, Mosquitto, Recorder};
use serde_json::{json, Value};
use sim_support::SimProcess;

const BUS_A: &str = r#"{"devices": [
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "115200 8N2"}
]}"#;
const BUS_B: &str = r#"{"devices": [
  {"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021", "line": "115200 8N2",
   "values": {"input:4": 2150}},
  {"name": "counter", "template": "rtu2mqtt-counter8", "address": 22, "serial": "0xFE000022", "line": "115200 8N2",
   "values": {"input:60": [0, 1234]}}
]}"#;

const BUS_RELAY_METER: &str = r#"{"devices": [
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "115200 8N2"},
  {"name": "meter", "template": "rtu2mqtt-energy-meter", "address": 30, "serial": "0x0D000030", "line": "115200 8N2",
   "fast": false, "values": {"input:0": [32768, 17254]}}
]}"#;

fn sim(dir: &Path, name: &str, bus: &str) -> SimProcess {
    let path = dir.join(name);
    std::fs::write(&path, bus).unwrap();
    SimProcess::start_with(&path, &repo("templates"), &[])
}

fn config(mqtt_port: u16, a: &Path, b: &Path, b_devices: Value) -> Value {
    json!({
        "mqtt": {"host": "127.0.0.1", "port": mqtt_port, "client_id": "rtu2mqtt-reload"},
        "ports": [
            {"path": a, "baud_rate": 115200, "stop_bits": 2,
             "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]},
            {"path": b, "baud_rate": 115200, "stop_bits": 2, "devices": b_devices}
        ]
    })
}

struct Daemon {
    child: Child,
    log: std::path::PathBuf,
}

impl Daemon {
    /// `rtu2mqtt run` with the repository's templates, logging at `filter` to `dir`/daemon.log.
    fn start(dir: &Path, config_path: &Path, filter: &str) -> Self {
        let log = dir.join("daemon.log");
        Daemon {
            child: Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
                .stop_with_parent()
                .arg("run")
                .arg("--templates")
                .arg(repo("templates"))
                .arg("-c")
                .arg(config_path)
                .env("RUST_LOG", filter)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(std::fs::File::create(&log).unwrap())
                .spawn()
                .unwrap(),
            log,
        }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn signal(&self, signal: nix::sys::signal::Signal) {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(self.child.id() as i32), signal).unwrap();
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if std::thread::panicking() {
            eprintln!("--- daemon log ---\n{}", self.log());
        }
    }
}

async fn topic_value(port: u16, topic: &str) -> Option<String> {
    retained(port).await?.get(topic).cloned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_applies_the_new_config_port_by_port() {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let sim_a = sim(dir.path(), "a.json", BUS_A);
    let sim_b = sim(dir.path(), "b.json", BUS_B);
    let config_path = dir.path().join("config.json");
    let write_config = |b_devices: Value| {
        let text = config(port, &sim_a.pty, &sim_b.pty, b_devices).to_string();
        std::fs::write(&config_path, text).unwrap();
    };
    write_config(json!([{"device_type": "rtu2mqtt-climate", "slave_id": 21}]));
    let daemon = Daemon::start(dir.path(), &config_path, "info");
    let temperature = "/devices/climate_21/controls/Temperature";
    wait_for("the climate sensor's temperature", || async {
        (topic_value(port, temperature).await? == "21.5").then_some(())
    })
    .await;
    wait_for("the relay's K1", || async {
        topic_value(port, "/devices/relay6_20/controls/K1").await
    })
    .await;

    // Port B: the climate sensor goes, the counter comes.
    write_config(json!([{"device_type": "rtu2mqtt-counter8", "slave_id": 22}]));
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the counter's value after the reload", || async {
        (topic_value(port, "/devices/counter8_22/controls/Input 1 counter").await? == "1234")
            .then_some(())
    })
    .await;
    let state = wait_for("the climate sensor's topics cleared", || async {
        retained(port).await.filter(|state| {
            !state
                .keys()
                .any(|t| t.starts_with("/devices/climate_21/") || t.contains("climate_21/"))
        })
    })
    .await;
    assert!(
        state.contains_key("/devices/relay6_20/controls/K1"),
        "the relay's topics must stay"
    );

    // Port A was not restarted, and its task still serves writes.
    publish(port, "/devices/relay6_20/controls/K3/on", "1", false).await;
    wait_for("K3 switched on port A", || async {
        let reply =
            sim_a.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
        (reply["value"] == 1).then_some(())
    })
    .await;
    let log = daemon.log();
    let a_name = sim_a.pty.display().to_string();
    let opens_of_a = |log: &str| {
        log.lines()
            .filter(|l| l.contains("port open") && l.contains(&a_name))
            .count()
    };
    assert_eq!(
        opens_of_a(&log),
        1,
        "port A must not be reopened by the reload:\n{log}"
    );
    assert!(log.contains("reload applied"), "{log}");

    // The config as it stands now (the counter on port B), for the changes below.
    let current_config = || {
        config(
            port,
            &sim_a.pty,
            &sim_b.pty,
            json!([{"device_type": "rtu2mqtt-counter8", "slave_id": 22}]),
        )
    };

    // The same ports in the other order: nothing restarts, and `ports/Load` lists them as the
    // config now does (it kept the order of the config they were started from).
    let applied = |log: &str| log.matches("reload applied").count();
    let before = applied(&daemon.log());
    let mut reordered = current_config();
    reordered["ports"].as_array_mut().unwrap().reverse();
    std::fs::write(&config_path, reordered.to_string()).unwrap();
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the reordered config applied", || async {
        (applied(&daemon.log()) > before).then_some(())
    })
    .await;
    let listed = rpc(port, "ports", "Load", json!({})).await;
    let paths: Vec<&str> = listed["result"]
        .as_array()
        .unwrap_or_else(|| panic!("{listed}"))
        .iter()
        .filter_map(|port| port["path"].as_str())
        .collect();
    assert_eq!(
        paths,
        [sim_b.pty.to_str().unwrap(), sim_a.pty.to_str().unwrap()],
        "{listed}"
    );
    assert_eq!(opens_of_a(&daemon.log()), 1, "{}", daemon.log());

    // A new `rate_limit` changes every port's share: both restart with it.
    let mut limited = current_config();
    limited["rate_limit"] = json!(1000);
    std::fs::write(&config_path, limited.to_string()).unwrap();
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("port A restarted with its share of rate_limit", || async {
        (opens_of_a(&daemon.log()) == 2).then_some(())
    })
    .await;

    // What only a restart applies is named in the log, not silently ignored.
    let mut publishing_changed = current_config();
    publishing_changed["max_unchanged_interval"] = json!(0);
    std::fs::write(&config_path, publishing_changed.to_string()).unwrap();
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the restart-only change in the log", || async {
        daemon
            .log()
            .contains("max_unchanged_interval changed: it takes effect when the service restarts")
            .then_some(())
    })
    .await;
    assert!(
        !daemon.log().contains("the mqtt section changed"),
        "{}",
        daemon.log()
    );

    // A broken config: the daemon says why and keeps serving the old one.
    std::fs::write(&config_path, "{ \"ports\": [ ").unwrap();
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the reload failure in the log", || async {
        daemon.log().contains("reload failed").then_some(())
    })
    .await;
    publish(port, "/devices/relay6_20/controls/K3/on", "0", false).await;
    wait_for("K3 switched off after the failed reload", || async {
        let reply =
            sim_a.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
        (reply["value"] == 0).then_some(())
    })
    .await;

    let mut daemon = daemon;
    daemon.signal(nix::sys::signal::Signal::SIGTERM);
    let status = daemon.child.wait().unwrap();
    assert!(status.success(), "exit status {status}");
}

/// Once the daemon has announced relay6_20's K3 and found its port missing, `/on` 1 to K3.
/// Subscriptions go before a device's meta: once K3's meta is there, its `/on` is heard.
async fn switch_k3_on_while_the_port_is_missing(port: u16, daemon: &Daemon) {
    wait_for("K3 announced", || async {
        topic_value(port, "/devices/relay6_20/controls/K3/meta").await
    })
    .await;
    wait_for("the port found missing", || async {
        daemon.log().contains("cannot open the port").then_some(())
    })
    .await;
    publish(port, "/devices/relay6_20/controls/K3/on", "1", false).await;
}

/// A write that waits for its port (which cannot be opened yet) is not lost when a reload
/// restarts that port: the stopping task hands it to the new one, which sends it once the port
/// opens. (Without that, the write died with the old task's queue.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_write_waiting_for_its_port_survives_a_reload_that_restarts_the_port() {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let tty = dir.path().join("ttyRS485-later");
    let config_path = dir.path().join("config.json");
    let write_config = |response_timeout_ms: u64| {
        let config = json!({
            "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-reload-write"},
            "ports": [{"path": &tty, "baud_rate": 115200, "stop_bits": 2,
                       "response_timeout_ms": response_timeout_ms,
                       "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
        });
        std::fs::write(&config_path, config.to_string()).unwrap();
    };
    write_config(500);
    let daemon = Daemon::start(
        dir.path(),
        &config_path,
        "info,rtu2mqtt::mqtt::client=debug",
    );
    switch_k3_on_while_the_port_is_missing(port, &daemon).await;
    wait_for("the write taken for the bus", || async {
        daemon
            .log()
            .lines()
            .any(|l| l.contains("write") && l.contains("control_id=K3"))
            .then_some(())
    })
    .await;

    write_config(600);
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the port restarted by the reload", || async {
        daemon
            .log()
            .lines()
            .any(|l| l.contains("reload applied") && l.contains("ttyRS485-later"))
            .then_some(())
    })
    .await;

    let sim = sim(dir.path(), "bus.json", BUS_A);
    std::os::unix::fs::symlink(&sim.pty, &tty).unwrap();
    wait_for("K3 switched once the port opened", || async {
        let reply = sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
        (reply["value"] == 1).then_some(())
    })
    .await;
}

/// A write asked for while its port is unavailable is given up once the device's
/// `max_write_fail_time_s` is over (flagged `w`), as a write the device never answered is, and
/// is not sent when the port comes back: a relay switched at 10:00 must not click at 14:00,
/// when the adapter is plugged in again. (It waited in the port's queue for as long as the port
/// was away, and went out first thing once it opened.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_write_its_port_could_not_take_in_time_is_given_up_not_sent_late() {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let tty = dir.path().join("ttyRS485-away");
    let config_path = dir.path().join("config.json");
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-write-away"},
        "ports": [{"path": &tty, "baud_rate": 115200, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20,
                                "max_write_fail_time_s": 1}]}]
    });
    std::fs::write(&config_path, config.to_string()).unwrap();
    // Home Assistant's view: the relay is never available while its port is missing (it was
    // `online` at start, then `offline` once the port had been missing for the device timeout).
    let availability = "/rtu2mqtt/rtu2mqtt-write-away/availability/relay6_20";
    let recorder = Recorder::start(port, availability).await;
    let availabilities = || -> Vec<String> {
        let messages = recorder.messages.lock().unwrap();
        messages
            .iter()
            .map(|(_, payload, _)| payload.clone())
            .collect()
    };
    let daemon = Daemon::start(dir.path(), &config_path, "info");
    switch_k3_on_while_the_port_is_missing(port, &daemon).await;
    // Flagged `w` at once (the write waits for the port), given up after its retry time.
    wait_for("the write flagged", || async {
        topic_value(port, "/devices/relay6_20/controls/K3/meta/error")
            .await
            .filter(|flags| flags.contains('w'))
    })
    .await;
    wait_for("the write given up", || async {
        daemon
            .log()
            .contains("write given up: the port has been unavailable")
            .then_some(())
    })
    .await;
    let flags = topic_value(port, "/devices/relay6_20/controls/K3/meta/error").await;
    assert!(
        flags.as_deref().is_some_and(|f| f.contains('w')),
        "still flagged once given up: {flags:?}"
    );
    wait_for("the relay marked offline", || async {
        daemon.log().contains("device marked offline").then_some(())
    })
    .await;
    assert_eq!(availabilities(), ["offline"]);

    let sim = sim(dir.path(), "bus.json", BUS_A);
    std::os::unix::fs::symlink(&sim.pty, &tty).unwrap();
    // Set up, then read: a write still queued would have gone before the first read.
    wait_for("K3 read once the port opened", || async {
        (topic_value(port, "/devices/relay6_20/controls/K3").await? == "0").then_some(())
    })
    .await;
    let reply = sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
    assert_eq!(reply["value"], 0, "the given-up write went out late");
    wait_for("the relay available once it answered", || async {
        (availabilities().len() > 1).then_some(())
    })
    .await;
    assert_eq!(availabilities(), ["offline", "online"]);
}

/// Operator audit: two devices on one port, the meter unplugged and flagged `r`; a reload that
/// changes only the relay restarts the port. The broker saw, at once, an empty `meta/error` on
/// every control of the meter and its minutes-old values sent again, and `r` only a second
/// later. Now, until the meter is plugged back, none of its controls gets an empty
/// `meta/error` or a value; once it is back, `r` is cleared and its values come.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reload_keeps_r_on_an_offline_device_until_it_answers_again() {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let sim = sim(dir.path(), "bus.json", BUS_RELAY_METER);
    let config_path = dir.path().join("config.json");
    let write_config = |relay: Value| {
        let config = json!({
            "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-reload-offline"},
            "ports": [{"path": &sim.pty, "baud_rate": 115200, "stop_bits": 2,
                       "devices": [relay, {"device_type": "rtu2mqtt-energy-meter", "slave_id": 30}]}]
        });
        std::fs::write(&config_path, config.to_string()).unwrap();
    };
    write_config(json!({"device_type": "rtu2mqtt-relay6", "slave_id": 20}));
    let daemon = Daemon::start(dir.path(), &config_path, "info");
    let meter = "/devices/energy_meter_30";
    let voltage = format!("{meter}/controls/Voltage");
    let voltage_error = format!("{voltage}/meta/error");
    let availability = "/rtu2mqtt/rtu2mqtt-reload-offline/availability/energy_meter_30";
    wait_for("the meter's voltage", || async {
        (topic_value(port, &voltage).await? == "230.5").then_some(())
    })
    .await;

    sim.control(json!({"cmd": "unplug", "device": 30}));
    wait_for("the meter flagged r", || async {
        let state = retained(port).await?;
        (state.get(&voltage_error)? == "r"
            && state.get(&format!("{meter}/meta/error"))? == "r"
            && state.get(availability)? == "offline")
            .then_some(())
    })
    .await;
    let marked_offline = |log: &str| {
        log.lines()
            .filter(|l| l.contains("marked offline") && l.contains("energy_meter"))
            .count()
    };
    let offline_before = marked_offline(&daemon.log());
    assert!(offline_before > 0, "{}", daemon.log());

    // Live messages only: the retained ones a subscription starts with come with the flag.
    let recorder = Recorder::start(port, &format!("{meter}/#")).await;
    let live = |recorder: &Recorder| -> Vec<(String, String)> {
        recorder
            .messages
            .lock()
            .unwrap()
            .iter()
            .filter(|(_, _, retained)| !retained)
            .map(|(topic, payload, _)| (topic.clone(), payload.clone()))
            .collect()
    };
    let is_value = |topic: &str| {
        topic
            .strip_prefix(&format!("{meter}/controls/"))
            .is_some_and(|control| !control.contains('/'))
    };
    write_config(json!({"device_type": "rtu2mqtt-relay6", "slave_id": 20,
                        "max_write_fail_time_s": 30}));
    daemon.signal(nix::sys::signal::Signal::SIGHUP);
    wait_for("the port restarted by the reload", || async {
        daemon
            .log()
            .lines()
            .any(|l| l.contains("reload applied") && l.contains("restarted"))
            .then_some(())
    })
    .await;
    // The meter announced again (its meta sent again), then found offline by the new task.
    wait_for("the meter announced again and found offline", || async {
        let announced = live(&recorder)
            .iter()
            .any(|(topic, _)| *topic == format!("{voltage}/meta"));
        (announced && marked_offline(&daemon.log()) > offline_before).then_some(())
    })
    .await;
    // What the new task's first failure would send (in the audit ~1 s after the reload).
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    for (topic, payload) in live(&recorder) {
        assert!(
            !(topic.ends_with("/meta/error") && payload.is_empty()),
            "{topic} cleared while the meter is unplugged:\n{:?}",
            live(&recorder)
        );
        assert!(
            !is_value(&topic),
            "{topic} = {payload} sent again while the meter is unplugged"
        );
    }
    assert_eq!(
        topic_value(port, &voltage_error).await.as_deref(),
        Some("r")
    );

    let before_replug = live(&recorder).len();
    sim.control(json!({"cmd": "replug", "device": 30}));
    wait_for("the meter's voltage after the replug", || async {
        let after: Vec<(String, String)> = live(&recorder).split_off(before_replug);
        let cleared = after
            .iter()
            .position(|(t, p)| *t == voltage_error && p.is_empty())?;
        let value = after
            .iter()
            .position(|(t, p)| *t == voltage && p == "230.5")?;
        assert!(
            cleared < value,
            "the value before its r was cleared: {after:?}"
        );
        Some(())
    })
    .await;
    wait_for("no r left on the meter, and it is available", || async {
        let state = retained(port).await?;
        let flagged = state
            .iter()
            .any(|(t, p)| t.starts_with(meter) && t.ends_with("/meta/error") && p.contains('r'));
        (!flagged && state.get(availability)? == "online").then_some(())
    })
    .await;
}
