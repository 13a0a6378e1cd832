//! Adversarial review of the MQTT side (branch review-mq). Each test shows a suspected defect
//! and FAILS on the code as it was reviewed; see /tmp/review-mq.md for the findings.

#[path = "mqtt_support/mod.rs"]
mod mqtt_support;

use std::collections::BTreeMap;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mqtt_support::*;
use rtu2mqtt::device::ResolvedDevice;
use rtu2mqtt::device_updates::{DeviceUpdate, Repeats};
use rtu2mqtt::gateway::device_model::DeviceModel;
use rtu2mqtt::mqtt::{MqttAction, PlannerSettings, PublicationPlanner, TopicScheme, UnchangedPolicy};
use rtu2mqtt::port::{PortEvent, RegisterSpan};
use rtu2mqtt::protocol::fast::RegisterType;

fn planner() -> PublicationPlanner {
    PublicationPlanner::new(PlannerSettings {
        topics: TopicScheme::new("", "rtu2mqtt").unwrap(),
        unchanged: UnchangedPolicy::OnChange,
        discovery: None,
        clear_discovery_on_exit: false,
    })
}

/// Feeds the model's updates to the planner; returns the (topic, payload) publications.
fn feed(planner: &mut PublicationPlanner, updates: Vec<DeviceUpdate>) -> Vec<(String, String)> {
    let mut out = Vec::new();
    for update in updates {
        for action in planner.handle(update, Instant::now()) {
            if let MqttAction::Publish(p) = action {
                out.push((p.topic, p.payload));
            }
        }
    }
    out
}

/// The retained state the planner has left on a broker that saw `publications` (last wins,
/// empty payload deletes).
fn apply(state: &mut BTreeMap<String, String>, publications: &[(String, String)]) {
    for (topic, payload) in publications {
        if payload.is_empty() {
            state.remove(topic);
        } else {
            state.insert(topic.clone(), payload.clone());
        }
    }
}

/// What the daemon does on SIGHUP for a port whose config changed (`BusControl::reload`): the
/// port task stops, a NEW `DeviceModel` is built for each of its devices (clean error flags) and
/// every device is announced again with `DeviceUpdate::Added`. The planner keeps the control's
/// old published `w`; the new model never saw it set, so the next good write (which clears `w`
/// only when the model's own flag was set) reports nothing and `w` stays on the broker for good.
#[test]
fn a_w_flag_set_before_a_port_restart_is_cleared_by_the_next_good_write() {
    let mut planner = planner();
    let relay: Arc<ResolvedDevice> = template_device("rtu2mqtt-relay6", 1);
    let error_topic = format!("/devices/{}/controls/K1/meta/error", relay.id);
    let mut broker = BTreeMap::new();
    apply(&mut broker, &feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]));

    // A refused payload: `w`.
    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    assert!(model.take_write("K1", "not a number", &mut out).is_err());
    apply(&mut broker, &feed(&mut planner, out));
    assert_eq!(broker.get(&error_topic).map(String::as_str), Some("w"));

    // SIGHUP with a change on that port: new model, the device announced again.
    apply(&mut broker, &feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]));
    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None);

    // A good write, done by the device.
    let mut out = Vec::new();
    let writes = model.take_write("K1", "1", &mut out).expect("accepted");
    for w in writes {
        model.apply(
            PortEvent::WriteDone {
                device: w.device,
                register_type: w.register_type,
                address: w.address,
            },
            &mut out,
        );
    }
    apply(&mut broker, &feed(&mut planner, out));
    assert_eq!(
        broker.get(&error_topic).map(String::as_str),
        None,
        "a successful write must clear `w` (mqtt.md: `w` stays until a write succeeds)"
    );
}

/// The same for `r`: a control whose read failed just before the port restarted keeps `r` on
/// the broker although its reads succeed and its values are published again.
#[test]
fn an_r_flag_set_before_a_port_restart_is_cleared_by_the_next_good_read() {
    let mut planner = planner();
    let relay: Arc<ResolvedDevice> = template_device("rtu2mqtt-relay6", 1);
    let error_topic = format!("/devices/{}/controls/K1/meta/error", relay.id);
    let mut broker = BTreeMap::new();
    apply(&mut broker, &feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]));
    let coils = RegisterSpan::new(RegisterType::Coil, 0, 6);

    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    model.apply(
        PortEvent::ReadFailed {
            device: 0,
            span: coils,
            unsupported: false,
        },
        &mut out,
    );
    apply(&mut broker, &feed(&mut planner, out));
    assert_eq!(broker.get(&error_topic).map(String::as_str), Some("r"));

    apply(&mut broker, &feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]));
    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    model.apply(
        PortEvent::Values {
            device: 0,
            span: coils,
            values: vec![1, 0, 0, 0, 0, 0].into(),
        },
        &mut out,
    );
    apply(&mut broker, &feed(&mut planner, out));
    assert_eq!(
        broker
            .get(&format!("/devices/{}/controls/K1", relay.id))
            .map(String::as_str),
        Some("1")
    );
    assert_eq!(
        broker.get(&error_topic).map(String::as_str),
        None,
        "a good read must clear `r`"
    );
}

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

/// wb-mqtt-serial converts an `/on` payload starting with `0x` as hexadecimal for every integer
/// format (`FromScaledTextValue` in src/register.cpp: `StringStartsWith(str, "0x")` → base
/// 16), and the codec here does too (`parse_int_text`), but the type check before it
/// (`check_payload` in src/gateway/device_model.rs) parses with `str::parse::<f64>`, which
/// refuses `0x1`: the write is refused and the control gets `w`.
#[test]
fn a_hexadecimal_on_payload_is_written_as_wb_mqtt_serial_writes_it() {
    let relay = template_device("rtu2mqtt-relay6", 1);
    let mut model = DeviceModel::new(relay, 0, Repeats::None);
    let mut out = Vec::new();
    let result = model.take_write("K1", "0x1", &mut out);
    assert!(result.is_ok(), "`0x1` refused: {:?}", result.err());
}
