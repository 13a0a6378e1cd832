//! The MQTT task against a real mosquitto: exact retained topics and payloads, `/on` writes,
//! offline devices, a broker restart, and the clean exit.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::mqtt_support::*;
use rtu2mqtt::device_updates::{ControlWrite, DeviceUpdate};

const RELAY: &str = "relay6_1";
const CLIMATE: &str = "climate_2";

/// A relay module and a climate sensor with a few values, as the bus side would report them.
async fn feed_two_devices(mqtt: &MqttUnderTest) {
    mqtt.send(DeviceUpdate::Added(template_device("rtu2mqtt-relay6", 1)))
        .await;
    mqtt.send(DeviceUpdate::Added(template_device("rtu2mqtt-climate", 2)))
        .await;
    // Their port opened: their topics are this gateway's; and they answered (their models
    // report them online at their first reply).
    for device_id in [RELAY, CLIMATE] {
        mqtt.send(DeviceUpdate::BusServed {
            device_id: device_id.into(),
        })
        .await;
        mqtt.send(DeviceUpdate::Online {
            device_id: device_id.into(),
            online: true,
        })
        .await;
    }
    for (device, control, text) in [
        (RELAY, "K1", "1"),
        (RELAY, "K2", "0"),
        (RELAY, "Input 0", "0"),
        (RELAY, "Input 0 counter", "17"),
        (RELAY, "Serial", "4265607321"),
        (CLIMATE, "Humidity", "41.23"),
        (CLIMATE, "CO2", "612"),
        (CLIMATE, "Sound Level", "38.5"),
        (CLIMATE, "Temperature", "21.5"),
    ] {
        mqtt.send(value(device, control, text)).await;
    }
}

/// The broker's retained state once `topic` holds `payload` and the state has settled (two
/// snapshots in a row agree): a snapshot taken while the client is still publishing misses what
/// arrives live, and a test comparing against it later would wait forever.
async fn state_with(port: u16, topic: &str, payload: &str) -> BTreeMap<String, String> {
    let deadline = std::time::Instant::now() + TIMEOUT;
    let mut previous = None;
    loop {
        let state = retained(port)
            .await
            .filter(|s| s.get(topic).map(String::as_str) == Some(payload));
        if state.is_some() && state == previous {
            return state.unwrap_or_default();
        }
        assert!(
            std::time::Instant::now() < deadline,
            "timed out waiting for {topic} = {payload:?} on the broker (settled)"
        );
        previous = state;
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

async fn state_without(port: u16, topic: &str) -> BTreeMap<String, String> {
    wait_for(&format!("{topic} gone from the broker"), || async {
        retained(port).await.filter(|s| !s.contains_key(topic))
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retained_layout_matches_golden() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    assert_broker_matches_golden(broker.port, "broker-relay-climate").await;
    assert!(mqtt.is_running());
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn writes_go_to_the_bus_side_and_bad_payloads_set_w() {
    let broker = Mosquitto::start();
    // A retained `/on` left by some client is an old command: not replayed at start.
    publish(
        broker.port,
        &format!("/devices/{RELAY}/controls/K4/on"),
        "1",
        true,
    )
    .await;
    let mut mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let k3 = format!("/devices/{RELAY}/controls/K3");
    state_with(broker.port, &format!("{k3}/meta/type"), "switch").await;

    publish(broker.port, &format!("{k3}/on"), "1", false).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert_eq!(
        write,
        ControlWrite {
            device_id: RELAY.into(),
            control_id: "K3".into(),
            payload: "1".into()
        }
    );
    // The bus side wrote it and reports the new value.
    mqtt.send(value(RELAY, "K3", "1")).await;
    state_with(broker.port, &k3, "1").await;

    let mut model = rtu2mqtt::gateway::device_model::DeviceModel::new(
        template_device("rtu2mqtt-relay6", 1),
        0,
        rtu2mqtt::device_updates::Repeats::None,
    );
    assert!(bus_side_takes(&mqtt, &mut model, &write).await);
    // Not a number: the device model refuses it, `w`, nothing written.
    publish(broker.port, &format!("{k3}/on"), "on", false).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert_eq!(write.payload, "on");
    assert!(!bus_side_takes(&mqtt, &mut model, &write).await);
    let state = state_with(broker.port, &format!("{k3}/meta/error"), "w").await;
    assert_eq!(state.get(&k3).map(String::as_str), Some("1"));
    // A read-only control has no `/on` subscription.
    publish(
        broker.port,
        &format!("/devices/{RELAY}/controls/Input 0/on"),
        "1",
        false,
    )
    .await;
    // A later good write goes through and clears `w`.
    publish(broker.port, &format!("{k3}/on"), "0", false).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert_eq!(
        write.control_id, "K3",
        "nothing for the read-only control: {write:?}"
    );
    assert_eq!(write.payload, "0");
    assert!(bus_side_takes(&mqtt, &mut model, &write).await);
    state_without(broker.port, &format!("{k3}/meta/error")).await;
    assert!(mqtt.writes.try_recv().is_err(), "nothing else was written");
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unplugged_device_sets_r_and_clears_it_on_return() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let error = format!("/devices/{CLIMATE}/meta/error");
    let availability = format!("/rtu2mqtt/rtu2mqtt/availability/{CLIMATE}");
    state_with(broker.port, &availability, "online").await;

    mqtt.send(DeviceUpdate::Online {
        device_id: CLIMATE.into(),
        online: false,
    })
    .await;
    let state = wait_for("device error r and availability offline", || async {
        retained(broker.port).await.filter(|s| {
            s.get(&error).map(String::as_str) == Some("r")
                && s.get(&availability).map(String::as_str) == Some("offline")
        })
    })
    .await;
    assert_eq!(
        state
            .get(&format!("/devices/{CLIMATE}/controls/Temperature"))
            .map(String::as_str),
        Some("21.5"),
        "the last good value stays"
    );

    mqtt.send(DeviceUpdate::Online {
        device_id: CLIMATE.into(),
        online: true,
    })
    .await;
    wait_for("device error cleared and availability online", || async {
        retained(broker.port).await.filter(|s| {
            !s.contains_key(&error) && s.get(&availability).map(String::as_str) == Some("online")
        })
    })
    .await;
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn broker_restart_gets_everything_again() {
    let mut broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let temperature = format!("/devices/{CLIMATE}/controls/Temperature");
    let before = state_with(broker.port, &temperature, "21.5").await;

    broker.kill();
    // The bus side goes on while the broker is away: never blocked, the latest value wins.
    for i in 0..2000 {
        mqtt.send(value(CLIMATE, "Temperature", &format!("{}", 20 + i % 5)))
            .await;
    }
    mqtt.send(value(CLIMATE, "Temperature", "22.25")).await;
    broker.restart();

    let mut expected = before;
    expected.insert(temperature, "22.25".into());
    wait_for_retained(broker.port, &expected, "the whole retained state again").await;
    assert!(mqtt.is_running());
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn updates_flow_before_the_broker_exists() {
    let port = free_port();
    let mqtt = MqttUnderTest::start(settings(port));
    let sending = async {
        feed_two_devices(&mqtt).await;
        for i in 0..5000 {
            mqtt.send(value(RELAY, "Input 0 counter", &i.to_string()))
                .await;
        }
    };
    tokio::time::timeout(Duration::from_secs(10), sending)
        .await
        .expect("updates are taken while no broker is there");
    let broker = Mosquitto::start_on(port);
    state_with(
        broker.port,
        &format!("/devices/{RELAY}/controls/Input 0 counter"),
        "4999",
    )
    .await;
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn home_assistant_birth_gets_configs_again() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let configs = wait_for("discovery configs", || async {
        retained(broker.port).await.and_then(|s| {
            let n = s.keys().filter(|t| t.starts_with("homeassistant/")).count();
            (n > 20).then_some(n)
        })
    })
    .await;
    let recorder = Recorder::start(broker.port, "homeassistant/+/+/+/config").await;
    wait_for("retained configs delivered", || async {
        (recorder.count("/config") >= configs).then_some(())
    })
    .await;
    publish(broker.port, "homeassistant/status", "online", false).await;
    wait_for("configs sent again", || async {
        (recorder.count("/config") >= 2 * configs).then_some(())
    })
    .await;
    mqtt.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clean_exit_leaves_no_device_topics() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    state_with(
        broker.port,
        &format!("/devices/{CLIMATE}/controls/Temperature"),
        "21.5",
    )
    .await;
    mqtt.stop().await;
    let state = retained(broker.port).await.expect("broker reachable");
    let left: Vec<&String> = state
        .keys()
        .filter(|t| !t.starts_with("homeassistant/"))
        .collect();
    // The device record stays: it says what an earlier run may have left on the broker.
    assert_eq!(
        left,
        ["/rtu2mqtt/rtu2mqtt/devices", "/rtu2mqtt/rtu2mqtt/status"],
        "{state:#?}"
    );
    assert_eq!(state["/rtu2mqtt/rtu2mqtt/status"], "offline");
    assert!(
        state.keys().any(|t| t.starts_with("homeassistant/")),
        "discovery configs stay by default"
    );

    // With homeassistant.clear_on_exit the configs go too.
    let mut settings = settings(broker.port);
    settings.broker.homeassistant.clear_on_exit = true;
    let mqtt = MqttUnderTest::start(settings);
    feed_two_devices(&mqtt).await;
    state_with(broker.port, "/rtu2mqtt/rtu2mqtt/status", "online").await;
    state_with(
        broker.port,
        &format!("/devices/{CLIMATE}/controls/Temperature"),
        "21.5",
    )
    .await;
    mqtt.stop().await;
    let state = retained(broker.port).await.expect("broker reachable");
    assert_eq!(
        state.into_iter().collect::<Vec<_>>(),
        [
            (
                "/rtu2mqtt/rtu2mqtt/devices".to_string(),
                r#"["climate_2","relay6_1"]"#.to_string()
            ),
            (
                "/rtu2mqtt/rtu2mqtt/status".to_string(),
                "offline".to_string()
            )
        ]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clear_on_exit_off_keeps_the_state() {
    let broker = Mosquitto::start();
    let mut settings = settings(broker.port);
    settings.broker.clear_on_exit = false;
    settings.broker.topic_prefix = "site1".into();
    let mqtt = MqttUnderTest::start(settings);
    feed_two_devices(&mqtt).await;
    let temperature = format!("site1/devices/{CLIMATE}/controls/Temperature");
    state_with(broker.port, &temperature, "21.5").await;
    mqtt.stop().await;
    let state = retained(broker.port).await.expect("broker reachable");
    assert_eq!(state.get(&temperature).map(String::as_str), Some("21.5"));
    assert_eq!(state["site1/rtu2mqtt/rtu2mqtt/status"], "offline");
    assert!(
        !state.keys().any(|t| t.starts_with("/devices")),
        "prefix applies to all"
    );
}

/// Issue 15 defect 5: an `/on` payload over the old 256 KiB packet limit, live or retained,
/// is refused without dropping the connection (which made the broker publish the last will
/// and, for a retained one, made the driver reconnect forever).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_on_payloads_are_refused_without_disconnecting() {
    let broker = Mosquitto::start();
    let huge = "1".repeat(300 * 1024);
    let k4_on = format!("/devices/{RELAY}/controls/K4/on");
    publish(broker.port, &k4_on, &huge, true).await;
    let mut mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let status = "/rtu2mqtt/rtu2mqtt/status";
    state_with(broker.port, status, "online").await;
    let recorder = Recorder::start(broker.port, status).await;

    let k3 = format!("/devices/{RELAY}/controls/K3");
    let mut model = rtu2mqtt::gateway::device_model::DeviceModel::new(
        template_device("rtu2mqtt-relay6", 1),
        0,
        rtu2mqtt::device_updates::Repeats::None,
    );
    publish(broker.port, &format!("{k3}/on"), &huge, false).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert!(!bus_side_takes(&mqtt, &mut model, &write).await);
    state_with(broker.port, &format!("{k3}/meta/error"), "w").await;
    publish(broker.port, &format!("{k3}/on"), "1", false).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert_eq!(
        (write.control_id.as_str(), write.payload.as_str()),
        ("K3", "1")
    );
    // The bus side's answer goes out on the same connection.
    mqtt.send(value(RELAY, "K3", "1")).await;
    state_with(broker.port, &k3, "1").await;
    let seen = recorder.messages.lock().unwrap().clone();
    assert_eq!(
        seen,
        [(status.to_string(), "online".to_string(), true)],
        "no last will, no reconnect"
    );
    mqtt.stop().await;
}

/// Issue 15 defect 9: a retained `/on` published while the driver runs reaches it live
/// (mosquitto clears the retain flag on live delivery, as MQTT 3.1.1 says) and is carried out,
/// as docs/mqtt.md says; clearing it (an empty retained payload) is no bad write.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retained_on_while_running_is_a_write_and_clearing_it_is_nothing() {
    let broker = Mosquitto::start();
    let mut mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let k4 = format!("/devices/{RELAY}/controls/K4");
    state_with(broker.port, &format!("{k4}/meta/type"), "switch").await;
    publish(broker.port, &format!("{k4}/on"), "1", true).await;
    let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
        .await
        .expect("a write within the timeout")
        .expect("writes channel open");
    assert_eq!(
        (write.control_id.as_str(), write.payload.as_str()),
        ("K4", "1")
    );
    publish(broker.port, &format!("{k4}/on"), "", true).await;
    // Published after anything the empty payload could have caused, on the same connection.
    mqtt.send(value(RELAY, "K4", "1")).await;
    let state = state_with(broker.port, &k4, "1").await;
    assert_eq!(state.get(&format!("{k4}/meta/error")), None, "{state:#?}");
    assert!(mqtt.writes.try_recv().is_err(), "nothing else was written");
    mqtt.stop().await;
}

/// Issue 15 defect 8: a device dropped from the config while the daemon was down (here: after
/// a crash, which skips the clean exit) loses its retained topics and discovery configs at the
/// next start; the configured device keeps its own.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_dropped_from_the_config_is_cleared_at_the_next_start() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let temperature = format!("/devices/{CLIMATE}/controls/Temperature");
    let record = "/rtu2mqtt/rtu2mqtt/devices";
    state_with(broker.port, &temperature, "21.5").await;
    state_with(broker.port, record, r#"["climate_2","relay6_1"]"#).await;
    drop(mqtt); // a crash: nothing is cleared

    let stale = |topic: &str| topic.contains("/climate_2/") || topic.contains("rtu2mqtt_climate_2");
    let before = retained(broker.port).await.expect("broker reachable");
    assert!(before.keys().filter(|t| stale(t)).count() > 50);

    let mqtt = MqttUnderTest::start(settings(broker.port));
    mqtt.send(DeviceUpdate::Added(template_device("rtu2mqtt-relay6", 1)))
        .await;
    mqtt.send(value(RELAY, "K1", "1")).await;
    wait_for(
        "the dropped device's topics gone, the kept one's value and discovery there",
        || async {
            retained(broker.port).await.filter(|s| {
                !s.keys().any(|t| stale(t))
                && s.get(record).map(String::as_str) == Some(r#"["relay6_1"]"#)
                // The kept device's value and discovery configs may reach the broker after the
                // sweep: all in one condition (a snapshot taken in between failed under load).
                && s.get(&format!("/devices/{RELAY}/controls/K1")).map(String::as_str) == Some("1")
                && s.keys().any(|t| t.contains("rtu2mqtt_relay6_1"))
            })
        },
    )
    .await;
    mqtt.stop().await;
}

/// Whether `state` has no topic of the relay's control `control` (value, meta, subtopics) nor
/// its discovery config.
fn control_gone(state: &BTreeMap<String, String>, control: &str) -> bool {
    let value = format!("/devices/{RELAY}/controls/{control}");
    let under = format!("{value}/");
    let config = format!(
        "homeassistant/switch/rtu2mqtt_{RELAY}/{}/config",
        control.to_lowercase()
    );
    !state
        .keys()
        .any(|t| *t == value || t.starts_with(&under) || *t == config)
}

/// Whether `state` has the relay's control `control`: its meta and its discovery config.
fn control_there(state: &BTreeMap<String, String>, control: &str) -> bool {
    state.contains_key(&format!("/devices/{RELAY}/controls/{control}/meta"))
        && state.contains_key(&format!(
            "homeassistant/switch/rtu2mqtt_{RELAY}/{}/config",
            control.to_lowercase()
        ))
}

/// The relay without its channel K6 (dropped from the config or template).
fn relay_without_k6() -> DeviceUpdate {
    let mut smaller = (*template_device("rtu2mqtt-relay6", 1)).clone();
    smaller.channels.make_mut().retain(|c| c.id != "K6");
    DeviceUpdate::Added(std::sync::Arc::new(smaller))
}

/// Review F3: a control dropped from a device's config while the daemon was down (stopped
/// with `clear_on_exit: false`, or crashed) loses its retained topics and its discovery config
/// at the next start, as wb-mqtt-serial's `RemoveUnusedControls` deletes them; the device's
/// other controls keep theirs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_control_dropped_while_the_daemon_was_down_is_cleared_at_the_next_start() {
    let broker = Mosquitto::start();
    let mut settings = settings(broker.port);
    settings.broker.clear_on_exit = false;
    let relay = DeviceUpdate::Added(template_device("rtu2mqtt-relay6", 1));
    let mqtt = MqttUnderTest::start_with(settings.clone(), None, vec![relay]);
    mqtt.send(value(RELAY, "K6", "1")).await;
    let k6 = format!("/devices/{RELAY}/controls/K6");
    wait_for("K6 and its discovery config on the broker", || async {
        retained(broker.port)
            .await
            .filter(|s| s.get(&k6).map(String::as_str) == Some("1") && control_there(s, "K6"))
    })
    .await;
    mqtt.stop().await;

    // The device is known when the sweep starts, as the daemon announces its devices before
    // the MQTT task starts.
    let mqtt = MqttUnderTest::start_with(settings, None, vec![relay_without_k6()]);
    mqtt.send(value(RELAY, "K5", "1")).await;
    let k5 = format!("/devices/{RELAY}/controls/K5");
    wait_for("K6 gone, the other controls there", || async {
        retained(broker.port).await.filter(|s| {
            control_gone(s, "K6")
                && s.get(&k5).map(String::as_str) == Some("1")
                && ["K1", "K5"].iter().all(|c| control_there(s, c))
        })
    })
    .await;
    mqtt.stop().await;
}

/// Review F2: a reload that drops a control while the broker is away: the planner's deletions
/// never reached the broker, which kept its retained messages (persistence, as on a Wiren
/// Board controller). The sweep after the reconnect deletes the control's topics and its
/// discovery config.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_control_dropped_while_the_broker_is_away_is_cleared_after_the_reconnect() {
    use rtu2mqtt::service::{BrokerState, ServiceHealth};
    let mut broker = Mosquitto::start_persistent();
    let port = broker.port;
    let health = std::sync::Arc::new(ServiceHealth::new(BrokerState::Connecting));
    let relay = DeviceUpdate::Added(template_device("rtu2mqtt-relay6", 1));
    let mqtt = MqttUnderTest::start_with(settings(port), Some(health.clone()), vec![relay]);
    mqtt.send(value(RELAY, "K6", "1")).await;
    let k6 = format!("/devices/{RELAY}/controls/K6");
    wait_for("K6 and its discovery config on the broker", || async {
        retained(port)
            .await
            .filter(|s| s.get(&k6).map(String::as_str) == Some("1") && control_there(s, "K6"))
    })
    .await;
    let persisted = "rtu2mqtt-test/persisted";
    publish(port, persisted, "x", true).await;

    broker.stop();
    // The client task hears of the disconnect before the health says so: the update sent
    // next is taken while the broker is away.
    wait_for("the client to see the broker gone", || async {
        health
            .status_line()
            .ends_with("MQTT unreachable")
            .then_some(())
    })
    .await;
    mqtt.send(relay_without_k6()).await;
    mqtt.send(value(RELAY, "K5", "1")).await;
    broker.start_again();

    let k5 = format!("/devices/{RELAY}/controls/K5");
    wait_for(
        "K6 gone after the reconnect, the other controls there",
        || async {
            retained(port).await.filter(|s| {
                s.contains_key(persisted)
                    && control_gone(s, "K6")
                    && s.get(&k5).map(String::as_str) == Some("1")
                    && ["K1", "K5"].iter().all(|c| control_there(s, c))
            })
        },
    )
    .await;
    mqtt.stop().await;
}

/// Issue 15 defect 11: a publication the client refuses (here a channel named `Lvl#`, which
/// the config loader should refuse too) is logged and dropped: it no longer blocks every later
/// publication, and the exit flush still gets `offline` out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_topic_the_client_refuses_does_not_block_the_others() {
    let broker = Mosquitto::start();
    let mqtt = MqttUnderTest::start(settings(broker.port));
    let mut relay = (*template_device("rtu2mqtt-relay6", 1)).clone();
    let mut level = relay.channels[0].clone();
    level.id = "Lvl#".into();
    level.readonly = true;
    relay.channels.make_mut().insert(0, level);
    mqtt.send(DeviceUpdate::Added(std::sync::Arc::new(relay)))
        .await;
    mqtt.send(DeviceUpdate::BusServed {
        device_id: RELAY.into(),
    })
    .await;
    mqtt.send(value(RELAY, "Lvl#", "1")).await;
    mqtt.send(value(RELAY, "K1", "1")).await;
    let k1 = format!("/devices/{RELAY}/controls/K1");
    state_with(broker.port, &k1, "1").await;
    mqtt.send(value(RELAY, "K1", "0")).await;
    state_with(broker.port, &k1, "0").await;
    mqtt.stop().await;
    let state = retained(broker.port).await.expect("broker reachable");
    assert_eq!(state["/rtu2mqtt/rtu2mqtt/status"], "offline");
    assert!(!state.contains_key(&k1), "cleared on exit: {state:#?}");
}

/// Writes come faster than the bus side takes them (its queue of 16 is full and nobody reads):
/// none is lost. The latest payload of every control reaches the bus side, in the order the
/// controls were first written, once the bus side reads again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn writes_wait_while_the_bus_side_is_busy_and_the_latest_per_control_arrives() {
    let broker = Mosquitto::start();
    let mut mqtt = MqttUnderTest::start(settings(broker.port));
    feed_two_devices(&mqtt).await;
    let on = |control: &str| format!("/devices/{RELAY}/controls/{control}/on");
    state_with(
        broker.port,
        &format!("/devices/{RELAY}/controls/K6/meta/type"),
        "switch",
    )
    .await;
    let mut published = Vec::new();
    for i in 0..40 {
        published.push(("K3", if i % 2 == 0 { "1" } else { "0" }));
    }
    published.extend([("K1", "1"), ("K3", "1"), ("K1", "0"), ("K6", "1")]);
    for (control, payload) in &published {
        publish(broker.port, &on(control), payload, false).await;
    }
    // Read until the last control written arrives; it was written last, so it comes last.
    let mut received = Vec::new();
    loop {
        let write = tokio::time::timeout(TIMEOUT, mqtt.writes.recv())
            .await
            .expect("every control's latest write reaches the bus side")
            .expect("writes channel open");
        received.push((write.control_id.clone(), write.payload.clone()));
        if write.control_id == "K6" {
            break;
        }
    }
    let last = |control: &str| {
        received
            .iter()
            .rev()
            .find(|(c, _)| c == control)
            .map(|(_, p)| p.as_str())
    };
    assert_eq!(last("K3"), Some("1"), "{received:?}");
    assert_eq!(last("K1"), Some("0"), "{received:?}");
    assert_eq!(received.last(), Some(&("K6".to_string(), "1".to_string())));
    assert!(received.len() <= published.len(), "{received:?}");
    // The first writes went through as they came, in order, before the queue filled.
    let firsts: Vec<&str> = received.iter().take(16).map(|(_, p)| p.as_str()).collect();
    let expected: Vec<&str> = published.iter().take(16).map(|(_, p)| *p).collect();
    assert_eq!(firsts, expected);
    assert!(mqtt.writes.try_recv().is_err(), "nothing else was written");
    mqtt.stop().await;
}
