//! Adversarial review of the MQTT side (branch review-mq). Each test shows a suspected defect
//! and FAILS on the code as it was reviewed; see /tmp/review-mq.md for the findings.

#[path = "mqtt_support/mod.rs"]
mod mqtt_support;

use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mqtt_support::*;
use rtu2mqtt::device_updates::DeviceUpdate;

/// A mosquitto that keeps its retained messages across a restart (persistence on, as on a
/// Wiren Board controller): stopped with SIGTERM it saves them, started again it loads them.
struct PersistentBroker {
    dir: tempfile::TempDir,
    port: u16,
    child: Option<Child>,
}

impl PersistentBroker {
    fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        // Run as root, mosquitto drops to its own user: let it write its database.
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o777)).unwrap();
        let mut broker = Self {
            dir,
            port: free_port(),
            child: None,
        };
        broker.launch();
        broker
    }

    fn launch(&mut self) {
        let config = self.dir.path().join("mosquitto.conf");
        std::fs::write(
            &config,
            format!(
                "listener {} 127.0.0.1\nallow_anonymous true\npersistence true\npersistence_location {}/\n",
                self.port,
                self.dir.path().display()
            ),
        )
        .unwrap();
        let child = Command::new(mosquitto_program("mosquitto"))
            .arg("-c")
            .arg(&config)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < deadline, "mosquitto did not listen");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGTERM: mosquitto writes its retained messages to disk and exits.
    fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            )
            .unwrap();
            let _ = child.wait();
        }
    }
}

impl Drop for PersistentBroker {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// SIGHUP drops a channel (or a control changes type, a device's channels shrink) while the
/// broker is unreachable: `run_mqtt` hands the `Added` to the planner and throws its actions
/// away (`if !connected { planner.handle(update, now); continue; }`), the deletions of the
/// dropped control included. After the reconnect only the current controls are republished
/// and the sweep looks at whole devices only, so the dropped control stays on a broker that
/// kept its retained messages: a phantom control with its last value in homeui and rules.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_control_dropped_while_the_broker_is_away_is_cleared_after_the_reconnect() {
    let mut broker = PersistentBroker::start();
    let port = broker.port;
    let mqtt = MqttUnderTest::start(settings(port));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    mqtt.send(DeviceUpdate::Added(relay.clone())).await;
    mqtt.send(value(&id, "K6", "1")).await;
    let k6 = format!("/devices/{id}/controls/K6");
    wait_for("K6 on the broker", || async {
        retained(port)
            .await
            .filter(|s| s.get(&k6).map(String::as_str) == Some("1"))
    })
    .await;

    publish(port, "/review/persisted", "x", true).await;
    broker.stop();
    // The client has seen the connection go.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let mut smaller = (*relay).clone();
    smaller.channels.make_mut().retain(|c| c.id != "K6");
    mqtt.send(DeviceUpdate::Added(Arc::new(smaller))).await;
    broker.launch();

    mqtt.send(value(&id, "K5", "1")).await;
    let k5 = format!("/devices/{id}/controls/K5");
    let state = wait_for("the reconnect's republished state", || async {
        retained(port)
            .await
            .filter(|s| s.get(&k5).map(String::as_str) == Some("1"))
    })
    .await;
    // Let the snapshot finish.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let state = retained(port).await.unwrap_or(state);
    assert!(
        state.contains_key("/review/persisted"),
        "the broker kept its retained messages across the restart"
    );
    let left: Vec<&String> = state.keys().filter(|t| t.starts_with(&k6)).collect();
    assert!(
        left.is_empty(),
        "the dropped control K6 is still on the broker: {left:?}"
    );
    mqtt.stop().await;
}

/// The same at a start after a crash (or with `clear_on_exit: false`): the template or config
/// lost a channel while the daemon was down. wb-mqtt-serial creates its devices with
/// `SetDoLoadPrevious(true)` and calls `RemoveUnusedControls` (src/serial_port_driver.cpp,
/// `SetUpDevices`), which deletes the retained controls of its devices that the config no
/// longer has; rtu2mqtt's sweep clears only devices missing from its record.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_control_dropped_while_the_daemon_was_down_is_cleared_at_the_next_start() {
    let broker = PersistentBroker::start();
    let port = broker.port;
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let k6 = format!("/devices/{id}/controls/K6");
    {
        let crashed = MqttUnderTest::start(settings(port));
        crashed.send(DeviceUpdate::Added(relay.clone())).await;
        crashed.send(value(&id, "K6", "1")).await;
        wait_for("K6 on the broker", || async {
            retained(port)
                .await
                .filter(|s| s.get(&k6).map(String::as_str) == Some("1"))
        })
        .await;
        // Dropped without a clean stop: the task is aborted, nothing is cleared.
    }
    let mut smaller = (*relay).clone();
    smaller.channels.make_mut().retain(|c| c.id != "K6");
    let mqtt = MqttUnderTest::start(settings(port));
    mqtt.send(DeviceUpdate::Added(Arc::new(smaller))).await;
    mqtt.send(value(&id, "K5", "1")).await;
    let k5 = format!("/devices/{id}/controls/K5");
    wait_for("the new run's state", || async {
        retained(port)
            .await
            .filter(|s| s.get(&k5).map(String::as_str) == Some("1"))
    })
    .await;
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let state = retained(port).await.unwrap();
    let left: Vec<&String> = state.keys().filter(|t| t.starts_with(&k6)).collect();
    assert!(
        left.is_empty(),
        "the dropped control K6 is still on the broker: {left:?}"
    );
    mqtt.stop().await;
}
