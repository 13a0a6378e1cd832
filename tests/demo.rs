//! `rtu2mqtt demo` as a user runs it: the simulator, the daemon, and a broker (the built-in one
//! here, with no mosquitto on PATH) or none. Values come, the built-in scenario's input clicks
//! arrive by Fast Modbus events, and Ctrl-C stops everything and removes the demo's directory.
//! On a broker it shares with a real gateway (a mosquitto here), it keeps to its own topics and
//! leaves none of them behind.

#[path = "mqtt_support/mod.rs"]
mod mqtt_support;

use mqtt_support::{publish, retained, wait_for, Mosquitto};
use rtu2mqtt::child::StopWithParent;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read};
use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use rumqttc::{Client, Event, MqttOptions, Packet, QoS};
use serde_json::Value;

/// However many lines come, a demo test gives up after this long in all.
const OVERALL: Duration = Duration::from_secs(60);

struct Demo {
    child: Child,
    stdout: mpsc::Receiver<String>,
    stderr: mpsc::Receiver<String>,
    deadline: Instant,
}

fn lines(source: impl Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(source).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    rx
}

impl Demo {
    fn start(args: &[&str]) -> Self {
        Self::start_with_tmpdir(args, &std::env::temp_dir())
    }

    /// Its scratch files in `tmpdir` (TMPDIR).
    fn start_with_tmpdir(args: &[&str], tmpdir: &std::path::Path) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
            .stop_with_parent()
            .arg("demo")
            .args(args)
            .env("TMPDIR", tmpdir)
            // No mosquitto to be found: the demo must not need one.
            .env("PATH", "/nonexistent")
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stdout = lines(child.stdout.take().unwrap());
        let stderr = lines(child.stderr.take().unwrap());
        Self {
            child,
            stdout,
            stderr,
            deadline: Instant::now() + OVERALL,
        }
    }

    /// The next stdout line, or None once the overall deadline has passed.
    fn next_stdout(&self) -> Option<String> {
        let left = self.deadline.checked_duration_since(Instant::now())?;
        self.stdout.recv_timeout(left).ok()
    }

    /// The demo's scratch directory, from its banner.
    fn files_dir(&self) -> PathBuf {
        loop {
            let left = self.deadline.saturating_duration_since(Instant::now());
            let line = self
                .stderr
                .recv_timeout(left)
                .expect("the demo's banner names its files directory");
            if let Some(dir) = line.trim().strip_prefix("files:") {
                return PathBuf::from(dir.trim());
            }
        }
    }

    /// Ctrl-C, then a clean exit that leaves no directory behind.
    fn interrupt_and_check(mut self, dir: PathBuf) {
        nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.child.id() as i32),
            nix::sys::signal::Signal::SIGINT,
        )
        .unwrap();
        let status = self.child.wait().unwrap();
        assert!(status.success(), "demo exit status {status}");
        assert!(!dir.exists(), "{} is left behind", dir.display());
    }
}

impl Drop for Demo {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn demo_without_a_broker_shows_events_and_stops_cleanly() {
    let demo = Demo::start(&["--no-broker"]);
    let dir = demo.files_dir();
    assert!(dir.is_dir(), "{}", dir.display());
    let mut seen = Vec::new();
    let clicked = loop {
        let line = demo
            .next_stdout()
            .unwrap_or_else(|| panic!("no event from the demo's scenario; got: {seen:?}"));
        let Ok(line) = serde_json::from_str::<Value>(&line) else {
            continue;
        };
        seen.push(line.clone());
        // The scenario toggles the relay's input 1 every 3 s.
        if line["device"] == "demo_relay6_20"
            && line["control"] == "Input 1"
            && line["event"] == true
        {
            break line;
        }
    };
    assert!(clicked["value"] == "0" || clicked["value"] == "1");
    assert!(seen
        .iter()
        .any(|l| l["device"] == "demo_climate_21" && l["control"] == "Temperature"));
    demo.interrupt_and_check(dir);
}

#[test]
fn demo_speaks_mqtt_through_its_built_in_broker() {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let demo = Demo::start(&["--mqtt-port", &port.to_string()]);
    let dir = demo.files_dir();
    assert!(dir.is_dir(), "{}", dir.display());

    // A client of the demo's broker, as mosquitto_sub or Home Assistant would be.
    let mut options = MqttOptions::new("demo-test", "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(5));
    let (client, mut connection) = Client::new(options, 16);
    client
        .subscribe(
            "/devices/demo_climate_21/controls/Temperature",
            QoS::AtMostOnce,
        )
        .unwrap();
    let mut temperature = None;
    for event in connection.iter() {
        assert!(
            Instant::now() < demo.deadline,
            "no Temperature over MQTT in time"
        );
        match event {
            Ok(Event::Incoming(Packet::Publish(p))) => {
                temperature = Some(String::from_utf8_lossy(&p.payload).into_owned());
                break;
            }
            Ok(_) => {}
            // The broker starts with the demo: retry until it listens.
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    }
    let temperature = temperature.expect("a Temperature value over MQTT");
    let celsius: f64 = temperature
        .parse()
        .unwrap_or_else(|_| panic!("Temperature {temperature:?} is not a number"));
    assert!((-40.0..=85.0).contains(&celsius), "{celsius}");

    // The live view shows values as they reach the broker.
    let shown = loop {
        let line = demo
            .next_stdout()
            .expect("the live view prints value lines");
        if line.contains("demo_climate_21") {
            break line;
        }
    };
    assert!(shown.contains(" s "), "{shown}");
    drop(client);
    drop(connection);
    demo.interrupt_and_check(dir);
}

/// What a real rtu2mqtt daemon keeps retained on the broker while serving the same device types
/// at the same addresses as the demo (so the same device ids), with the default client id. It
/// publishes on change only: a topic deleted under it stays missing.
const OTHER_GATEWAY: &[(&str, &str)] = &[
    ("/devices/counter8_22/meta", r#"{"driver":"rtu2mqtt"}"#),
    ("/devices/counter8_22/controls/Input 1", "1"),
    (
        "/devices/counter8_22/controls/Input 1/meta",
        r#"{"type":"switch","readonly":true}"#,
    ),
    ("/devices/energy_meter_30/controls/Voltage", "231.2"),
    ("/devices/relay6_20/controls/K1", "0"),
    ("/devices/climate_21/controls/Temperature", "19.5"),
    ("/devices/dimmer_23/controls/K1", "0"),
    (
        "homeassistant/sensor/rtu2mqtt_energy_meter_30/voltage/config",
        r#"{"name":"Voltage"}"#,
    ),
    (
        "homeassistant/switch/rtu2mqtt_relay6_20/k1/config",
        r#"{"name":"K1"}"#,
    ),
    ("/rtu2mqtt/rtu2mqtt/status", "online"),
    (
        "/rtu2mqtt/rtu2mqtt/devices",
        r#"["climate_21","counter8_22","dimmer_23","energy_meter_30","relay6_20"]"#,
    ),
];

/// What a demo before the `demo_` ids left after its clean exit: its record of the devices it
/// served (which its daemon's start-up sweep reads: ids in it that the config lacks get their
/// topics deleted), its status, and a discovery config of a phantom HA device.
const OLDER_DEMO: &[(&str, &str)] = &[
    (
        "/rtu2mqtt/rtu2mqtt-demo/devices",
        r#"["climate_21","counter8_22","dimmer_23","energy_meter_30","relay6_20"]"#,
    ),
    ("/rtu2mqtt/rtu2mqtt-demo/status", "offline"),
    (
        "homeassistant/sensor/rtu2mqtt-demo_counter8_22/input_1_counter/config",
        r#"{"name":"Input 1 counter"}"#,
    ),
];

/// The demo's record of its devices, once its daemon has swept and rewritten it.
const DEMO_RECORD: &str = r#"["demo_climate_21","demo_counter8_22","demo_dimmer_23","demo_energy_meter_30","demo_relay6_20"]"#;

/// Every topic of `state` that is not the other gateway's.
fn demo_topics(state: &BTreeMap<String, String>) -> Vec<&String> {
    state
        .keys()
        .filter(|topic| !OTHER_GATEWAY.iter().any(|(other, _)| other == topic))
        .collect()
}

fn assert_other_gateway_intact(state: &BTreeMap<String, String>) {
    for (topic, payload) in OTHER_GATEWAY {
        assert_eq!(
            state.get(*topic).map(String::as_str),
            Some(*payload),
            "the other gateway's {topic}"
        );
    }
}

#[test]
fn demo_on_a_shared_broker_keeps_off_another_gateways_topics_and_leaves_nothing() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let broker = Mosquitto::start();
    let port = broker.port;
    runtime.block_on(async {
        for (topic, payload) in OTHER_GATEWAY.iter().chain(OLDER_DEMO) {
            publish(port, topic, payload, true).await;
        }
    });

    let demo = Demo::start(&["--mqtt-port", &port.to_string()]);
    let dir = demo.files_dir();
    // Serving: online, and for every device in the record its daemon writes (rewritten once its
    // start-up sweep is over, so whatever that sweep deletes has been deleted), values and
    // discovery configs. Whatever the ids are: the test tells the demo's own topics from the
    // other gateway's by payload and by what is left, not by trusting the naming.
    let running = runtime.block_on(wait_for("the demo serving its devices", || async {
        let state = retained(port).await?;
        let ids: Vec<String> =
            serde_json::from_str(state.get("/rtu2mqtt/rtu2mqtt-demo/devices")?).ok()?;
        let served = state.get("/rtu2mqtt/rtu2mqtt-demo/status")? == "online"
            && ids.len() == 5
            && ids.iter().all(|id| {
                let values = format!("/devices/{id}/controls/");
                let discovery = format!("/rtu2mqtt-demo_{id}/");
                state.keys().any(|t| t.starts_with(&values))
                    && state
                        .keys()
                        .any(|t| t.starts_with("homeassistant/") && t.contains(&discovery))
            });
        served.then_some(state)
    }));
    assert_other_gateway_intact(&running);
    assert_eq!(
        running["/rtu2mqtt/rtu2mqtt-demo/devices"], DEMO_RECORD,
        "the demo's own device ids"
    );
    assert!(
        !running
            .contains_key("homeassistant/sensor/rtu2mqtt-demo_counter8_22/input_1_counter/config"),
        "an older demo's phantom HA device is cleared at start"
    );

    demo.interrupt_and_check(dir);
    // The demo has exited; the broker may still be taking its daemon's last deletions.
    let deadline = Instant::now() + mqtt_support::TIMEOUT;
    let after = loop {
        let state = runtime
            .block_on(retained(port))
            .expect("the broker's state");
        if demo_topics(&state).is_empty() || Instant::now() >= deadline {
            break state;
        }
        // A condition poll: each round reads the broker again; the pause only paces it.
        std::thread::sleep(Duration::from_millis(25));
    };
    assert_other_gateway_intact(&after);
    assert_eq!(
        demo_topics(&after),
        Vec::<&String>::new(),
        "the demo left these on the broker"
    );
}

#[test]
fn a_second_demo_on_the_same_broker_is_refused() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let broker = Mosquitto::start();
    let port = broker.port;
    let first = Demo::start(&["--mqtt-port", &port.to_string()]);
    let dir = first.files_dir();
    runtime.block_on(wait_for("the first demo online", || async {
        let state = retained(port).await?;
        (state.get("/rtu2mqtt/rtu2mqtt-demo/status")? == "online"
            && state.get("/rtu2mqtt/rtu2mqtt-demo/devices")? == DEMO_RECORD
            && state
                .keys()
                .any(|t| t.starts_with("/devices/demo_counter8_22/controls/")))
        .then_some(())
    }));

    // Same client id and device ids: it would take over the first one's connection, and
    // each would clear the other's devices on exit.
    let mut second = Demo::start(&["--mqtt-port", &port.to_string()]);
    let mut said = Vec::new();
    loop {
        let left = second
            .deadline
            .checked_duration_since(Instant::now())
            .unwrap_or_else(|| panic!("the second demo did not refuse; it said {said:?}"));
        match second.stderr.recv_timeout(left) {
            Ok(line) if line.contains("another rtu2mqtt demo") => break,
            Ok(line) => said.push(line),
            Err(_) => panic!("the second demo did not refuse; it said {said:?}"),
        }
    }
    let status = second.child.wait().unwrap();
    assert!(!status.success(), "{status}");

    // The first one still serves: nothing of it was taken over or cleared.
    let state = runtime
        .block_on(retained(port))
        .expect("the broker's state");
    assert_eq!(
        state
            .get("/rtu2mqtt/rtu2mqtt-demo/status")
            .map(String::as_str),
        Some("online")
    );
    assert_eq!(
        state
            .get("/rtu2mqtt/rtu2mqtt-demo/devices")
            .map(String::as_str),
        Some(DEMO_RECORD)
    );
    assert!(state
        .keys()
        .any(|t| t.starts_with("/devices/demo_counter8_22/controls/")));
    first.interrupt_and_check(dir);
}

/// wb-mqtt-serial's RPC method topics are shared by every server of them on the broker: the
/// demo deletes them on exit only when nobody advertised them before it started (the test
/// above), and leaves another server's (a real gateway, or wb-mqtt-serial kept for a meter).
#[test]
fn the_demo_leaves_the_rpc_methods_another_server_advertised() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let broker = Mosquitto::start();
    let port = broker.port;
    let advertised = "/rpc/v1/wb-mqtt-serial/ports/Load";
    runtime.block_on(publish(port, advertised, "1", true));
    let demo = Demo::start(&["--mqtt-port", &port.to_string()]);
    let dir = demo.files_dir();
    runtime.block_on(wait_for("the demo online", || async {
        let state = retained(port).await?;
        (state.get("/rtu2mqtt/rtu2mqtt-demo/status")? == "online").then_some(())
    }));
    demo.interrupt_and_check(dir);
    let deadline = Instant::now() + mqtt_support::TIMEOUT;
    let after = loop {
        let state = runtime
            .block_on(retained(port))
            .expect("the broker's state");
        let demo_gone = !state
            .keys()
            .any(|t| t.starts_with("/rtu2mqtt/rtu2mqtt-demo/"));
        if demo_gone || Instant::now() >= deadline {
            break state;
        }
        // A condition poll: each round reads the broker again; the pause only paces it.
        std::thread::sleep(Duration::from_millis(25));
    };
    assert_eq!(after.get(advertised).map(String::as_str), Some("1"));
    assert_eq!(
        after
            .get("/rpc/v1/wb-mqtt-serial/port/Load")
            .map(String::as_str),
        Some("1"),
        "the demo's own advertisement of the same methods stays with the other server's"
    );
}

/// A port where something that is not a broker listens (a web server, a stale tunnel): the demo
/// says so instead of a bare "Network timeout", before it starts anything.
#[test]
fn a_demo_pointed_at_a_port_that_is_not_a_broker_says_so() {
    // Accepts the TCP connection (the listen backlog does) and never answers MQTT's CONNECT.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let scratch = tempfile::tempdir().unwrap();
    let mut demo = Demo::start_with_tmpdir(&["--mqtt-port", &port.to_string()], scratch.path());
    let mut said = Vec::new();
    let status = demo.child.wait().unwrap();
    while let Ok(line) = demo.stderr.recv_timeout(Duration::from_secs(5)) {
        said.push(line);
    }
    assert!(!status.success(), "{status}; it said {said:?}");
    let said = said.join("\n");
    assert!(
        said.contains(&format!(
            "127.0.0.1:{port} takes connections but does not answer as an MQTT broker"
        )) && said.contains("--mqtt-port"),
        "{said}"
    );
    // Refused before it started anything (no banner), and nothing left behind.
    assert!(!said.contains("files:"), "{said}");
    let left: Vec<_> = std::fs::read_dir(scratch.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
    drop(listener);
}

/// A broker that takes no anonymous client: the demo says it was refused, not that nothing
/// answered.
#[test]
fn a_demo_refused_by_a_broker_says_so() {
    let broker = Mosquitto::start_with_password("site", "secret");
    let mut demo = Demo::start(&["--mqtt-port", &broker.port.to_string()]);
    let status = demo.child.wait().unwrap();
    let mut said = Vec::new();
    while let Ok(line) = demo.stderr.recv_timeout(Duration::from_secs(5)) {
        said.push(line);
    }
    let said = said.join("\n");
    assert!(!status.success(), "{status}; it said {said}");
    assert!(
        said.contains(&format!(
            "the MQTT broker on 127.0.0.1:{} refused the demo's connection",
            broker.port
        )) && !said.contains("does not answer as an MQTT broker"),
        "{said}"
    );
}
