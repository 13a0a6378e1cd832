//! The whole chain with real processes: `rtu2mqtt sim` on a pty, `rtu2mqtt run`, and mosquitto.
//! Writes on `/on` reach the device's register and come back as the published value; a bad
//! payload sets `w` and writes nothing; an unplugged device gets device `meta/error` "r", cleared
//! on return; SIGTERM leaves no retained device topic behind.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{publish, retained, wait_for, Mosquitto, Recorder};
use serde_json::json;
use sim_support::SimProcess;
use std::process::Stdio;

const BUS: &str = r#"{"devices": [
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "115200 8N2"},
  {"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021", "line": "115200 8N2",
   "values": {"input:4": 2150}}
]}"#;

fn start_daemon(pty: &std::path::Path, mqtt_port: u16) -> DaemonProcess {
    let devices = json!([
        {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
        {"device_type": "rtu2mqtt-climate", "slave_id": 21}
    ]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": mqtt_port, "client_id": "rtu2mqtt-e2e"},
        "ports": [{"path": pty, "baud_rate": 115200, "stop_bits": 2, "devices": devices}]
    });
    DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null())
}

fn start() -> (Mosquitto, SimProcess, DaemonProcess) {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(&bus, BUS).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let daemon = start_daemon(&sim.pty, broker.port);
    (broker, sim, daemon)
}

async fn retained_value(port: u16, topic: &str) -> Option<String> {
    retained(port)
        .await
        .and_then(|state| state.get(topic).cloned())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn writes_errors_and_clean_exit_through_a_real_broker() {
    let (broker, sim, mut daemon) = start();
    let port = broker.port;
    wait_for("the temperature on the broker", || async {
        (retained_value(port, "/devices/climate_21/controls/Temperature").await? == "21.5")
            .then_some(())
    })
    .await;
    wait_for("K3 off on the broker", || async {
        (retained_value(port, "/devices/relay6_20/controls/K3").await? == "0").then_some(())
    })
    .await;

    // A write on /on reaches the device, and the new value is published.
    publish(port, "/devices/relay6_20/controls/K3/on", "1", false).await;
    wait_for("K3 on in the simulator", || async {
        let reply = sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
        (reply["value"] == 1).then_some(())
    })
    .await;
    wait_for("K3 on on the broker", || async {
        (retained_value(port, "/devices/relay6_20/controls/K3").await? == "1").then_some(())
    })
    .await;

    // A bad payload sets `w` and writes nothing.
    publish(port, "/devices/relay6_20/controls/K4/on", "maybe", false).await;
    wait_for("K4 meta/error w", || async {
        (retained_value(port, "/devices/relay6_20/controls/K4/meta/error").await? == "w")
            .then_some(())
    })
    .await;
    let k4 = sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 3}));
    assert_eq!(k4["value"], 0, "nothing was written");

    // An unplugged device: device meta/error "r", cleared when it is back.
    sim.control(json!({"cmd": "unplug", "device": 21}));
    wait_for("climate meta/error r", || async {
        (retained_value(port, "/devices/climate_21/meta/error").await? == "r").then_some(())
    })
    .await;
    sim.control(json!({"cmd": "replug", "device": 21}));
    wait_for("climate meta/error cleared", || async {
        let state = retained(port).await?;
        // An empty payload is not retained: a cleared error has no retained topic.
        (!state.contains_key("/devices/climate_21/meta/error")).then_some(())
    })
    .await;

    // A press counter back at 0 after its device was away is not published (a `whenChanged`
    // rule on it would fire by itself after every bus or power glitch, as wb-mqtt-serial
    // holds that 0 back); the next press is.
    let counter = "/devices/relay6_20/controls/Input 0 single press counter";
    assert_eq!(
        retained_value(port, counter).await.as_deref(),
        Some("0"),
        "published at 0 at the start, as wb-mqtt-serial publishes it"
    );
    let recorder = Recorder::start(port, counter).await;
    let set_counter = |value: u16| {
        sim.control(
            json!({"cmd": "set", "device": 20, "type": "input", "address": 464, "value": value}),
        );
    };
    set_counter(3);
    wait_for("the press counter at 3", || async {
        (retained_value(port, counter).await? == "3").then_some(())
    })
    .await;
    sim.control(json!({"cmd": "unplug", "device": 20}));
    let counter_error = format!("{counter}/meta/error");
    wait_for("the press counter marked r", || async {
        (retained_value(port, &counter_error).await? == "r").then_some(())
    })
    .await;
    set_counter(0);
    sim.control(json!({"cmd": "replug", "device": 20}));
    // Its `r` is cleared by its first read after the return: the 0 has been read.
    wait_for("the press counter read again", || async {
        (!retained(port).await?.contains_key(&counter_error)).then_some(())
    })
    .await;
    set_counter(1);
    wait_for("the next press published", || async {
        (retained_value(port, counter).await? == "1").then_some(())
    })
    .await;
    let published: Vec<String> = recorder
        .messages
        .lock()
        .unwrap()
        .iter()
        .filter(|(topic, _, retained)| topic == counter && !retained)
        .map(|(_, payload, _)| payload.clone())
        .collect();
    assert_eq!(
        published,
        ["3", "1"],
        "the counter as published since it was 0 at the start"
    );

    // SIGTERM: a clean exit that leaves no retained device topic.
    let status = daemon.terminate();
    assert!(status.success(), "exit status {status}");
    let state = retained(port).await.expect("broker reachable");
    let stale: Vec<&String> = state
        .keys()
        .filter(|topic| topic.starts_with("/devices/"))
        .collect();
    assert!(
        stale.is_empty(),
        "retained device topics after exit: {stale:?}"
    );
}
