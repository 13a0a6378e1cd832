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
