//! Device identity in the daemon, end to end (`rtu2mqtt sim` on a pty, `rtu2mqtt run`, a real
//! mosquitto): model, serial number and firmware read at setup appear in the device meta and
//! in Home Assistant's device entry; a device replaced by another at the same address (the
//! simulator's `replace`: another serial number, freshly powered on) is noticed, logged and set
//! up afresh, and its new serial number published.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::process::Stdio;

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{retained, wait_for, Mosquitto};
use serde_json::{json, Value};
use sim_support::SimProcess;

async fn retained_json(port: u16, topic: &str) -> Option<Value> {
    let state = retained(port).await?;
    serde_json::from_str(state.get(topic)?).ok()
}

async fn identity_at(line: &str, baud: u32) {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let devices = json!({"devices": [
        {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020",
         "line": line, "model": "WBMR6C", "firmware": "1.26.0"}
    ]});
    std::fs::write(&bus, devices.to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-identity-test"},
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": [
            {"device_type": "rtu2mqtt-relay6", "slave_id": 20}
        ]}]
    });
    let daemon = DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());

    let meta = wait_for("the identity in the device meta", || async {
        let meta = retained_json(port, "/devices/relay6_20/meta").await?;
        meta.get("serial_number").is_some().then_some(meta)
    })
    .await;
    assert_eq!(meta["serial_number"], "4261412896", "{meta}");
    assert_eq!(meta["model"], "WBMR6C", "{meta}");
    assert_eq!(meta["firmware"], "1.26.0", "{meta}");
    let discovery = wait_for("the identity in Home Assistant's device entry", || async {
        let state = retained(port).await?;
        let (_, config) = state.iter().find(|(topic, _)| {
            topic.starts_with("homeassistant/") && topic.contains("relay6_20")
        })?;
        let config: Value = serde_json::from_str(config).ok()?;
        config["device"]
            .get("serial_number")
            .is_some()
            .then_some(config)
    })
    .await;
    assert_eq!(discovery["device"]["serial_number"], "4261412896");
    assert_eq!(discovery["device"]["sw_version"], "1.26.0");
    assert_eq!(discovery["device"]["model"], "WBMR6C");

    // Another relay takes its place at address 20: noticed, logged, and its serial published.
    let replaced = sim.control(json!({"cmd": "replace", "device": 20, "new_serial": "0xFE000099"}));
    assert_eq!(replaced["ok"], true, "{replaced}");
    wait_for("the new serial number in the device meta", || async {
        let meta = retained_json(port, "/devices/relay6_20/meta").await?;
        (meta["serial_number"] == "4261413017").then_some(())
    })
    .await;
    let log = daemon.log();
    assert!(
        log.contains("serial number changed") && log.contains("setting it up afresh"),
        "{log}"
    );

    // Set up afresh: the new device is polled and takes writes.
    sim.control(json!({"cmd": "set", "device": 20, "type": "coil", "address": 4, "value": 1}));
    wait_for("K5 of the new relay on the broker", || async {
        let state = retained(port).await?;
        (state.get("/devices/relay6_20/controls/K5")? == "1").then_some(())
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identity_published_and_a_replaced_device_noticed_at_115200() {
    identity_at("115200 8N2", 115_200).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identity_published_and_a_replaced_device_noticed_at_9600() {
    identity_at("9600 8N2", 9600).await;
}

/// A channel whose template needs newer firmware than the device has (`fw`, as wb-mqtt-serial
/// reads it) is never read and shows the read error; one the firmware has is read as usual.
/// The simulated device has both registers, so reading the newer one would publish its value.
async fn newer_firmware_channels_at(line: &str, baud: u32) {
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    let template = json!({
        "device_type": "fw-gated",
        "title": "Firmware-gated channels",
        "hw": [{"signature": "WBMR6C"}],
        "device": {"name": "FW", "id": "fw", "channels": [
            {"name": "Old", "reg_type": "holding", "address": 100, "type": "value", "fw": "1.20"},
            {"name": "New", "reg_type": "holding", "address": 101, "type": "value", "fw": "1.30.0"},
            {"name": "Plain", "reg_type": "holding", "address": 102, "type": "value"}
        ]}
    });
    std::fs::write(dir.path().join("fw-gated.json"), template.to_string()).unwrap();
    let bus = dir.path().join("bus.json");
    let devices = json!({"devices": [
        {"name": "fw", "template": "fw-gated.json", "address": 30, "serial": "0xFE000030",
         "line": line, "model": "WBMR6C", "firmware": "1.26.0",
         "values": {"holding:100": 42, "holding:101": 7, "holding:102": 9}}
    ]});
    std::fs::write(&bus, devices.to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, dir.path(), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-fw-test"},
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": [
            {"device_type": "fw-gated", "slave_id": 30}
        ]}]
    });
    let templates = dir.path().to_string_lossy().into_owned();
    let _daemon = DaemonProcess::start(
        &config,
        &["--templates", &templates],
        Stdio::null(),
        Stdio::null(),
    );
    // The older channel and the plain one read, the newer one marked: all three retained.
    let state = wait_for("Old, Plain and the error of New", || async {
        let state = retained(port).await?;
        let ready = state.get("/devices/fw_30/controls/New/meta/error")? == "r"
            && state.get("/devices/fw_30/controls/Old")? == "42"
            && state.get("/devices/fw_30/controls/Plain")? == "9";
        ready.then_some(state)
    })
    .await;
    assert_ne!(
        state.get("/devices/fw_30/controls/New").map(String::as_str),
        Some("7"),
        "a channel the firmware does not have was read"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channels_that_need_newer_firmware_are_not_read_at_115200() {
    newer_firmware_channels_at("115200 8N2", 115_200).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channels_that_need_newer_firmware_are_not_read_at_9600() {
    newer_firmware_channels_at("9600 8N2", 9600).await;
}
