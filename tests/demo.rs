//! `rtu2mqtt demo` as a user runs it: the simulator, the daemon, and a broker (the built-in one
//! here, with no mosquitto on PATH) or none. Values come, the built-in scenario's input clicks
//! arrive by Fast Modbus events, and Ctrl-C stops everything and removes the demo's directory.

use rtu2mqtt::child::StopWithParent;
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
        let mut child = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
            .stop_with_parent()
            .arg("demo")
            .args(args)
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
        if line["device"] == "relay6_20" && line["control"] == "Input 1" && line["event"] == true {
            break line;
        }
    };
    assert!(clicked["value"] == "0" || clicked["value"] == "1");
    assert!(seen
        .iter()
        .any(|l| l["device"] == "climate_21" && l["control"] == "Temperature"));
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
        .subscribe("/devices/climate_21/controls/Temperature", QoS::AtMostOnce)
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
        if line.contains("climate_21") {
            break line;
        }
    };
    assert!(shown.contains(" s "), "{shown}");
    drop(client);
    drop(connection);
    demo.interrupt_and_check(dir);
}
