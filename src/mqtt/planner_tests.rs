//! Planner tests: golden publications for the relay and climate templates, and every rule of
//! the layout (dedup, intervals, error order, writes, removal, reconnect snapshot).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::json;

use super::*;
use crate::config::TemplateFile;
use crate::device::resolve_template_device;

/// Announces `device` and marks its bus served (its port opened): what the daemon sends for a
/// device whose topics are the gateway's to delete. Returns the announcement's actions.
fn add_served(
    planner: &mut PublicationPlanner,
    device: Arc<ResolvedDevice>,
    now: Instant,
) -> Vec<MqttAction> {
    let device_id = device.id.clone();
    let out = planner.handle(DeviceUpdate::Added(device), now);
    planner.handle(DeviceUpdate::BusServed { device_id }, now);
    out
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

pub(crate) fn template_device(template: &str, slave_id: u8) -> Arc<ResolvedDevice> {
    let file = TemplateFile::load(&repo(&format!("templates/{template}.json")))
        .unwrap_or_else(|e| panic!("{e}"));
    Arc::new(
        resolve_template_device(&file, &json!({ "slave_id": slave_id }))
            .unwrap_or_else(|e| panic!("{e}")),
    )
}

fn settings(discovery: bool) -> PlannerSettings {
    PlannerSettings {
        topics: TopicScheme::new("", "rtu2mqtt").unwrap(),
        unchanged: UnchangedPolicy::OnChange,
        discovery: discovery.then(|| DiscoverySettings {
            prefix: "homeassistant".into(),
        }),
        clear_discovery_on_exit: false,
    }
}

/// One line per action: `publish <retain|transient> q<qos> <topic> <payload>` (tab-separated).
pub(crate) fn render(actions: &[MqttAction]) -> String {
    let mut text = String::new();
    for action in actions {
        let line = match action {
            MqttAction::Publish(p) => format!(
                "publish\t{}\tq{}\t{}\t{}",
                if p.retain { "retain" } else { "transient" },
                p.qos as u8,
                p.topic,
                p.payload
            ),
            MqttAction::Subscribe(t) => format!("subscribe\t{t}"),
            MqttAction::Unsubscribe(t) => format!("unsubscribe\t{t}"),
        };
        text.push_str(&line);
        text.push('\n');
    }
    text
}

/// Compares with the snapshot `tests/golden/<name>.snap`. A change is reviewed, never written
/// by the test: `cargo insta review` (or `INSTA_UPDATE=new`, then compare the `.snap.new` file).
pub(crate) fn assert_golden(name: &str, actual: &str) {
    insta::with_settings!({
        snapshot_path => repo("tests/golden"),
        prepend_module_to_snapshot => false,
        omit_expression => true,
    }, {
        insta::assert_snapshot!(name, actual);
    });
}

fn publications(actions: &[MqttAction]) -> Vec<(String, String, bool)> {
    actions
        .iter()
        .filter_map(|a| match a {
            MqttAction::Publish(p) => Some((p.topic.clone(), p.payload.clone(), p.retain)),
            _ => None,
        })
        .collect()
}

/// A value that changed, as the device model reports it.
fn value(device: &str, control: &str, text: &str) -> DeviceUpdate {
    DeviceUpdate::Value {
        device_id: device.into(),
        control_id: control.into(),
        value: text.into(),
        from_event: false,
        changed: true,
    }
}

/// A value read again unchanged, as the device model reports it.
fn repeat(device: &str, control: &str, text: &str) -> DeviceUpdate {
    DeviceUpdate::Value {
        device_id: device.into(),
        control_id: control.into(),
        value: text.into(),
        from_event: false,
        changed: false,
    }
}

#[test]
fn relay_module_added_golden() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let actions = planner.handle(DeviceUpdate::Added(relay), Instant::now());
    assert_golden("relay6-added", &render(&actions));
}

#[test]
fn climate_sensor_added_golden() {
    let mut planner = PublicationPlanner::new(settings(true));
    let climate = template_device("rtu2mqtt-climate", 2);
    let actions = planner.handle(DeviceUpdate::Added(climate), Instant::now());
    assert_golden("climate-added", &render(&actions));
}

#[test]
fn writable_controls_only_are_subscribed() {
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    planner.handle(DeviceUpdate::Added(relay), Instant::now());
    let subscribed = planner.subscriptions();
    assert!(subscribed.contains(&format!("/devices/{id}/controls/K1/on")));
    assert!(!subscribed.iter().any(|t| t.contains("Input 0")));
    assert_eq!(subscribed.len(), 6, "{subscribed:?}");
}

#[test]
fn values_publish_on_change_only() {
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let t0 = Instant::now();
    planner.handle(DeviceUpdate::Added(relay), t0);
    let first = planner.handle(value(&id, "K1", "1"), t0);
    assert_eq!(
        publications(&first),
        [(format!("/devices/{id}/controls/K1"), "1".into(), true)]
    );
    assert!(planner.handle(repeat(&id, "K1", "1"), t0).is_empty());
    assert_eq!(planner.handle(value(&id, "K1", "0"), t0).len(), 1);
    // Issue 15 defect 9: a value read by the poll and then reported by an event (or an event
    // repeated by the device) is published once, as wb-mqtt-serial publishes on change.
    let event = DeviceUpdate::Value {
        device_id: id.as_str().into(),
        control_id: "K1".into(),
        value: "0".into(),
        from_event: true,
        changed: false,
    };
    assert!(
        planner.handle(event, t0).is_empty(),
        "an event of the published value is no change"
    );
    assert!(planner.handle(value("nope", "K1", "1"), t0).is_empty());
    assert!(planner.handle(value(&id, "nope", "1"), t0).is_empty());
}

#[test]
fn unchanged_values_come_back_after_the_interval() {
    assert_eq!(UnchangedPolicy::from_config(-1), UnchangedPolicy::OnChange);
    assert_eq!(UnchangedPolicy::from_config(0), UnchangedPolicy::EveryRead);
    assert_eq!(
        UnchangedPolicy::from_config(2),
        UnchangedPolicy::After(Duration::from_secs(5))
    );
    let mut planner = PublicationPlanner::new(PlannerSettings {
        unchanged: UnchangedPolicy::from_config(10),
        ..settings(false)
    });
    let climate = template_device("rtu2mqtt-climate", 2);
    let id = climate.id.clone();
    let t0 = Instant::now();
    planner.handle(DeviceUpdate::Added(climate), t0);
    assert_eq!(
        planner.handle(value(&id, "Temperature", "21.5"), t0).len(),
        1
    );
    let at = |s| t0 + Duration::from_secs(s);
    assert!(planner
        .handle(repeat(&id, "Temperature", "21.5"), at(9))
        .is_empty());
    assert_eq!(
        planner
            .handle(repeat(&id, "Temperature", "21.5"), at(10))
            .len(),
        1
    );
    assert!(planner
        .handle(repeat(&id, "Temperature", "21.5"), at(15))
        .is_empty());
}

/// The flags are the device model's: the planner publishes them as they come, on change.
#[test]
fn error_flags_publish_as_given_on_change() {
    let mut planner = PublicationPlanner::new(settings(false));
    let climate = template_device("rtu2mqtt-climate", 2);
    let id = climate.id.clone();
    let t0 = Instant::now();
    planner.handle(DeviceUpdate::Added(climate), t0);
    let flags = |read, period_missed| DeviceUpdate::ControlError {
        device_id: id.clone(),
        control_id: "Temperature".into(),
        errors: ErrorFlags {
            read,
            period_missed,
            ..Default::default()
        },
    };
    let error_topic = format!("/devices/{id}/controls/Temperature/meta/error");
    assert_eq!(
        publications(&planner.handle(flags(true, false), t0)),
        [(error_topic.clone(), "r".into(), true)]
    );
    assert!(
        planner.handle(flags(true, false), t0).is_empty(),
        "unchanged"
    );
    assert_eq!(
        publications(&planner.handle(flags(false, true), t0)),
        [(error_topic, "p".into(), true)]
    );
    // A value leaves the flags alone (the model clears `r` before it).
    assert_eq!(
        publications(&planner.handle(value(&id, "Temperature", "21.5"), t0)),
        [(
            format!("/devices/{id}/controls/Temperature"),
            "21.5".into(),
            true
        )]
    );
}

#[test]
fn pushbutton_presses_always_publish_and_are_not_retained() {
    let mut planner = PublicationPlanner::new(settings(false));
    let mut device = (*template_device("rtu2mqtt-relay6", 1)).clone();
    let mut button = device.channels[0].clone();
    button.id = "Reset".into();
    button.control_type = "pushbutton".into();
    device.channels.make_mut().push(button);
    let id = device.id.clone();
    planner.handle(DeviceUpdate::Added(Arc::new(device)), Instant::now());
    // A press repeating the last one (the device model says it did not change) too.
    for update in [value(&id, "Reset", "1"), repeat(&id, "Reset", "1")] {
        let out = planner.handle(update, Instant::now());
        assert_eq!(
            publications(&out),
            [(format!("/devices/{id}/controls/Reset"), "1".into(), false)]
        );
    }
    // Not part of the retained snapshot.
    let snapshot = render(&planner.snapshot());
    assert!(!snapshot.contains("controls/Reset\t1"), "{snapshot}");
}

/// The availability says `offline` until the device has answered once: a device whose port is
/// missing, or that never answers, is never `online` for Home Assistant (it was at start, then
/// `offline` a few seconds later). Its `meta/error` is empty until it is found offline, as
/// wb-mqtt-serial starts it.
#[test]
fn a_device_is_unavailable_until_it_first_answers() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let availability = format!("/rtu2mqtt/rtu2mqtt/availability/{id}");
    let device_error = format!("/devices/{id}/meta/error");
    let added = publications(&planner.handle(DeviceUpdate::Added(relay.clone()), Instant::now()));
    assert!(added.contains(&(availability.clone(), "offline".into(), true)));
    assert!(added.contains(&(device_error.clone(), "".into(), true)));
    let snapshot = publications(&planner.snapshot());
    assert!(snapshot.contains(&(availability.clone(), "offline".into(), true)));
    // Its first reply: available; its `meta/error` was empty already.
    let answered = planner.handle(
        DeviceUpdate::Online {
            device_id: id.clone(),
            online: true,
        },
        Instant::now(),
    );
    assert_eq!(
        publications(&answered),
        [(availability.clone(), "online".into(), true)]
    );
    let snapshot = publications(&planner.snapshot());
    assert!(snapshot.contains(&(availability.clone(), "online".into(), true)));
    // Announced again by a reload: still available.
    let again = publications(&planner.handle(DeviceUpdate::Added(relay), Instant::now()));
    assert!(again.contains(&(availability, "online".into(), true)));
}

#[test]
fn offline_device_sets_r_and_availability() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let availability = format!("/rtu2mqtt/rtu2mqtt/availability/{id}");
    let device_error = format!("/devices/{id}/meta/error");
    planner.handle(DeviceUpdate::Added(relay), Instant::now());
    let state = |online: bool| DeviceUpdate::Online {
        device_id: id.clone(),
        online,
    };
    // Never heard from, it fails: `r`; its availability was `offline` from the start.
    assert_eq!(
        publications(&planner.handle(state(false), Instant::now())),
        [(device_error.clone(), "r".into(), true)]
    );
    assert!(planner.handle(state(false), Instant::now()).is_empty());
    assert_eq!(
        publications(&planner.handle(state(true), Instant::now())),
        [
            (device_error.clone(), "".into(), true),
            (availability.clone(), "online".into(), true),
        ]
    );
    assert!(planner.handle(state(true), Instant::now()).is_empty());
    assert_eq!(
        publications(&planner.handle(state(false), Instant::now())),
        [
            (device_error, "r".into(), true),
            (availability, "offline".into(), true),
        ]
    );
}

/// `/on` topics map to writes; checking the payload (and `w`) is the device model's.
#[test]
fn on_messages_map_to_writes() {
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    planner.handle(DeviceUpdate::Added(relay), Instant::now());
    let on = format!("/devices/{id}/controls/K1/on");
    let write = |payload: &str| {
        WriteOutcome::Accepted(ControlWrite {
            device_id: id.clone(),
            control_id: "K1".into(),
            payload: payload.into(),
        })
    };
    assert_eq!(planner.on_message(&on, b" 1", false), write(" 1"));
    // Not UTF-8: the model refuses U+FFFD (and sets `w`).
    assert_eq!(planner.on_message(&on, b"1\xff", false), write("1\u{FFFD}"));
    assert_eq!(
        planner.on_message(&on, b"1", true),
        WriteOutcome::IgnoredRetained
    );
    // Issue 15 defect 9: a client clearing a retained `/on` (empty payload, delivered live) is
    // no bad write: nothing for the bus, no `w`.
    assert_eq!(
        planner.on_message(&on, b"", false),
        WriteOutcome::IgnoredEmpty
    );
    let input_on = format!("/devices/{id}/controls/Input 0/on");
    assert_eq!(
        planner.on_message(&input_on, b"1", false),
        WriteOutcome::NotOurs
    );
}

#[test]
fn removal_clears_every_topic_it_published() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let added = add_served(&mut planner, relay, Instant::now());
    planner.handle(value(&id, "K1", "1"), Instant::now());
    let removed = planner.handle(
        DeviceUpdate::Removed {
            device_id: id.clone(),
        },
        Instant::now(),
    );
    let cleared: std::collections::BTreeSet<String> = publications(&removed)
        .into_iter()
        .map(|(topic, payload, retain)| {
            assert!(payload.is_empty() && retain, "{topic}");
            topic
        })
        .collect();
    for (topic, _, _) in publications(&added) {
        assert!(cleared.contains(&topic), "{topic} not cleared");
    }
    assert!(cleared.contains(&format!("/devices/{id}/controls/K1")));
    let unsubscribed = removed
        .iter()
        .filter(|a| matches!(a, MqttAction::Unsubscribe(_)))
        .count();
    assert_eq!(unsubscribed, 6);
    assert!(planner.snapshot().is_empty());
    assert!(planner.subscriptions().is_empty());
}

#[test]
fn config_change_drops_removed_controls() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    add_served(&mut planner, relay.clone(), Instant::now());
    let mut smaller = (*relay).clone();
    smaller.channels.make_mut().retain(|c| c.id != "K6");
    let out = planner.handle(DeviceUpdate::Added(Arc::new(smaller)), Instant::now());
    let text = render(&out);
    assert!(text.contains(&format!(
        "publish\tretain\tq1\t/devices/{id}/controls/K6/meta\t\n"
    )));
    assert!(text.contains(&format!("unsubscribe\t/devices/{id}/controls/K6/on")));
    assert!(text.contains(&format!(
        "publish\tretain\tq1\thomeassistant/switch/rtu2mqtt_{id}/k6/config\t\n"
    )));
    assert!(!text.contains(&format!("/devices/{id}/controls/K5/meta\t\n")));
}

/// Feeds the device model's updates to the planner; returns the publications.
fn feed(planner: &mut PublicationPlanner, updates: Vec<DeviceUpdate>) -> Vec<(String, String)> {
    updates
        .into_iter()
        .flat_map(|update| publications(&planner.handle(update, Instant::now())))
        .map(|(topic, payload, _)| (topic, payload))
        .collect()
}

/// The payload `topic` last got in `published` (None: never published).
fn last_of<'a>(published: &'a [(String, String)], topic: &str) -> Option<&'a str> {
    published
        .iter()
        .rev()
        .find(|(t, _)| t == topic)
        .map(|(_, p)| p.as_str())
}

/// What the daemon does on SIGHUP for a port whose config changed: the port restarts with a
/// new device model per device (flags clear) and every device is announced again (`Added`).
fn restart_port(
    planner: &mut PublicationPlanner,
    device: &Arc<ResolvedDevice>,
    published: &mut Vec<(String, String)>,
) -> crate::gateway::device_model::DeviceModel {
    published.extend(feed(planner, vec![DeviceUpdate::Added(device.clone())]));
    crate::gateway::device_model::DeviceModel::new(device.clone(), 0, Repeats::None)
}

/// Review F1: the planner kept a control's `w` when its device was announced again, and the
/// new model (which never saw `w` set) reports nothing when its first write succeeds: the `w`
/// stayed on the broker for good. The control starts over with an empty `meta/error`.
#[test]
fn a_w_flag_set_before_a_port_restart_is_cleared_by_the_next_good_write() {
    use crate::port::PortEvent;
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let error = format!("/devices/{}/controls/K1/meta/error", relay.id);
    let mut published = feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    let mut model = crate::gateway::device_model::DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    assert!(model.take_write("K1", "not a number", &mut out).is_err());
    published.extend(feed(&mut planner, out));
    assert_eq!(last_of(&published, &error), Some("w"));

    let mut model = restart_port(&mut planner, &relay, &mut published);
    assert_eq!(last_of(&published, &error), Some(""));
    let mut out = Vec::new();
    for write in model.take_write("K1", "1", &mut out).expect("accepted") {
        let done = PortEvent::WriteDone {
            device: write.device,
            register_type: write.register_type,
            address: write.address,
        };
        model.apply(done, &mut out);
    }
    published.extend(feed(&mut planner, out));
    assert_eq!(last_of(&published, &error), Some(""));
    // And the new model's `w` goes out as before.
    let mut out = Vec::new();
    assert!(model.take_write("K1", "x", &mut out).is_err());
    assert_eq!(feed(&mut planner, out), [(error, "w".to_string())]);
}

/// Review F1, for `r`: a control whose read failed before its port restarted loses `r` when
/// its device is announced again; the new model's good reads publish the values.
#[test]
fn an_r_flag_set_before_a_port_restart_is_cleared_by_the_next_good_read() {
    use crate::port::{PortEvent, RegisterSpan};
    use crate::protocol::fast::RegisterType;
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let error = format!("/devices/{id}/controls/K1/meta/error");
    let coils = RegisterSpan::new(RegisterType::Coil, 0, 6);
    let mut published = feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    let mut model = crate::gateway::device_model::DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    let failed = PortEvent::ReadFailed {
        device: 0,
        span: coils,
        unsupported: false,
    };
    model.apply(failed, &mut out);
    published.extend(feed(&mut planner, out));
    assert_eq!(last_of(&published, &error), Some("r"));

    let mut model = restart_port(&mut planner, &relay, &mut published);
    let mut out = Vec::new();
    let read = PortEvent::Values {
        device: 0,
        span: coils,
        values: vec![1, 0, 0, 0, 0, 0].into(),
    };
    model.apply(read, &mut out);
    published.extend(feed(&mut planner, out));
    assert_eq!(
        last_of(&published, &format!("/devices/{id}/controls/K1")),
        Some("1")
    );
    assert_eq!(last_of(&published, &error), Some(""));
}

/// The topics of `device`'s readable controls' `meta/error`.
fn readable_error_topics(device: &ResolvedDevice) -> Vec<String> {
    device
        .channels
        .iter()
        .filter(|c| c.is_read())
        .map(|c| format!("/devices/{}/controls/{}/meta/error", device.id, c.id))
        .collect()
}

/// Operator audit: a reload that restarted the port of an offline device published, at once,
/// an empty `meta/error` on every control and the values read before it went away (republished
/// from the planner's state as the device was announced again), and `r` only at the new
/// model's first failure a second later: for that second rules saw old readings without an
/// error flag. A device known offline keeps `r` on its readable controls, and its old values
/// are not sent again, until a read succeeds; its new model (built as the daemon builds it,
/// known offline) clears `r` at that read, before the value.
#[test]
fn an_offline_device_whose_port_restarts_keeps_r_until_a_read_succeeds() {
    use crate::gateway::device_model::DeviceModel;
    use crate::port::{PortEvent, RegisterSpan};
    use crate::protocol::fast::RegisterType;
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let device_error = format!("/devices/{id}/meta/error");
    let k1 = format!("/devices/{id}/controls/K1");
    let k1_error = format!("{k1}/meta/error");
    let readable = readable_error_topics(&relay);
    assert!(readable.len() > 6);
    let coils = RegisterSpan::new(RegisterType::Coil, 0, 6);
    let read_coils = PortEvent::Values {
        device: 0,
        span: coils,
        values: vec![1, 0, 0, 0, 0, 0].into(),
    };
    let mut published = feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None);
    let mut out = Vec::new();
    model.apply(PortEvent::Online { device: 0 }, &mut out);
    model.apply(read_coils.clone(), &mut out);
    model.apply(PortEvent::Offline { device: 0 }, &mut out);
    published.extend(feed(&mut planner, out));
    assert_eq!(last_of(&published, &k1), Some("1"));
    assert!(readable.iter().all(|t| last_of(&published, t) == Some("r")));
    assert!(model.is_offline());

    // The reload: announced again, and its state republished (the client does it from the
    // backlog when the device is announced while connected).
    let restarted = feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    let republished: Vec<(String, String)> = publications(&planner.device_snapshot(&id))
        .into_iter()
        .map(|(topic, payload, _)| (topic, payload))
        .collect();
    for after_restart in [&restarted, &republished] {
        assert_eq!(last_of(after_restart, &device_error), Some("r"));
        for topic in &readable {
            assert_eq!(last_of(after_restart, topic), Some("r"), "{topic}");
        }
        assert!(
            !after_restart
                .iter()
                .any(|(t, p)| t.ends_with("/meta/error") && p.is_empty()),
            "{after_restart:?}"
        );
        assert_eq!(last_of(after_restart, &k1), None, "an old value sent again");
    }
    published.extend(restarted);

    // The new model, as the daemon builds it for a device its old port knew offline: its
    // first failure changes nothing, its first good read clears `r` before the value.
    let mut model = DeviceModel::new(relay.clone(), 0, Repeats::None).known_offline();
    let mut out = Vec::new();
    model.apply(PortEvent::Offline { device: 0 }, &mut out);
    assert_eq!(feed(&mut planner, out), []);
    let mut out = Vec::new();
    model.apply(PortEvent::Online { device: 0 }, &mut out);
    model.apply(read_coils, &mut out);
    let back = feed(&mut planner, out);
    let position = |topic: &str, payload: &str| {
        back.iter()
            .position(|(t, p)| t == topic && p == payload)
            .unwrap_or_else(|| panic!("no {topic} {payload:?} in {back:?}"))
    };
    assert!(position(&device_error, "") < position(&k1_error, ""));
    assert!(position(&k1_error, "") < position(&k1, "1"));
    // Controls not read yet keep `r`.
    let input_0_error = format!("/devices/{id}/controls/Input 0/meta/error");
    assert_eq!(last_of(&back, &input_0_error), None);
    // A reconnect now republishes the value read since.
    let republished = publications(&planner.device_snapshot(&id));
    assert!(republished.iter().any(|(t, p, _)| *t == k1 && p == "1"));
}

/// Should the new model not hold the `r` the planner kept (it was built with clear flags), the
/// control's first value clears it before going out: a value is a good read.
#[test]
fn a_kept_r_is_cleared_by_the_first_value_after_the_restart() {
    let mut planner = PublicationPlanner::new(settings(false));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let k1 = format!("/devices/{id}/controls/K1");
    let k1_error = format!("{k1}/meta/error");
    feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    let offline = DeviceUpdate::Online {
        device_id: id.clone(),
        online: false,
    };
    let r = |control: &str| DeviceUpdate::ControlError {
        device_id: id.clone(),
        control_id: control.into(),
        errors: ErrorFlags {
            read: true,
            ..Default::default()
        },
    };
    feed(&mut planner, vec![offline, r("K1"), r("K2")]);
    let restarted = feed(&mut planner, vec![DeviceUpdate::Added(relay.clone())]);
    assert_eq!(last_of(&restarted, &k1_error), Some("r"));
    assert_eq!(
        feed(&mut planner, vec![value(&id, "K1", "0")]),
        [(k1_error, String::new()), (k1, "0".into())]
    );
}

#[test]
fn snapshot_republishes_state_with_errors_before_values() {
    let mut planner = PublicationPlanner::new(settings(false));
    let climate = template_device("rtu2mqtt-climate", 2);
    let id = climate.id.clone();
    planner.handle(DeviceUpdate::Added(climate), Instant::now());
    planner.handle(value(&id, "Temperature", "21.5"), Instant::now());
    planner.handle(
        DeviceUpdate::ControlError {
            device_id: id.clone(),
            control_id: "Humidity".into(),
            errors: ErrorFlags {
                read: true,
                ..Default::default()
            },
        },
        Instant::now(),
    );
    let snapshot = publications(&planner.snapshot());
    let position = |topic: String| snapshot.iter().position(|(t, _, _)| *t == topic);
    let error = position(format!("/devices/{id}/controls/Temperature/meta/error")).unwrap();
    let value = position(format!("/devices/{id}/controls/Temperature")).unwrap();
    assert!(error < value);
    assert_eq!(snapshot[value].1, "21.5");
    let humidity = position(format!("/devices/{id}/controls/Humidity/meta/error")).unwrap();
    assert_eq!(snapshot[humidity].1, "r");
}

#[test]
fn clear_on_exit_keeps_discovery_unless_asked() {
    let relay = template_device("rtu2mqtt-relay6", 1);
    for clear_discovery in [false, true] {
        let mut planner = PublicationPlanner::new(PlannerSettings {
            clear_discovery_on_exit: clear_discovery,
            ..settings(true)
        });
        add_served(&mut planner, relay.clone(), Instant::now());
        let text = render(&planner.clear_all());
        assert!(text.contains("/meta/error\t\n"));
        assert_eq!(text.contains("homeassistant/"), clear_discovery);
    }
}

#[test]
fn identity_updates_discovery_device_block() {
    let mut planner = PublicationPlanner::new(settings(true));
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    planner.handle(DeviceUpdate::Added(relay), Instant::now());
    let identity = DeviceIdentity {
        model: Some("WBMR6C".into()),
        serial_number: Some("4265607321".into()),
        firmware: Some("1.17.3".into()),
    };
    let update = DeviceUpdate::Identity {
        device_id: id,
        identity,
    };
    let out = planner.handle(update.clone(), Instant::now());
    assert!(!out.is_empty());
    let text = render(&out);
    assert!(text.contains(r#""serial_number":"4265607321""#), "{text}");
    assert!(text.contains(r#""sw_version":"1.17.3""#));
    // The device meta JSON carries it too, and keeps it after a reconnect.
    let meta = "/devices/relay6_1/meta\t{\"driver\":\"rtu2mqtt\",\"title\":{\"en\":\"Relay 6 1\"},\
                \"model\":\"WBMR6C\",\"serial_number\":\"4265607321\",\"firmware\":\"1.17.3\"}\n";
    assert!(text.contains(meta), "{text}");
    let snapshot = render(&planner.snapshot());
    assert!(
        snapshot.contains(r#""serial_number":"4265607321","firmware""#),
        "{snapshot}"
    );
    assert!(planner.handle(update, Instant::now()).is_empty());
}

/// Whatever the order devices were announced in, what is published for all of them (after a
/// reconnect, for Home Assistant, on a clean exit) goes in the order of their ids.
#[test]
fn everything_published_for_all_devices_goes_in_the_order_of_their_ids() {
    let mut planner = PublicationPlanner::new(settings(true));
    let now = Instant::now();
    let slaves = [7, 3, 12, 1, 9];
    for slave in slaves {
        add_served(&mut planner, template_device("rtu2mqtt-relay6", slave), now);
    }
    let mut ids: Vec<String> = slaves
        .iter()
        .map(|&slave| template_device("rtu2mqtt-relay6", slave).id.clone())
        .collect();
    ids.sort();
    // The device a topic belongs to, in the order topics are published.
    let order = |actions: &[MqttAction]| {
        let mut seen: Vec<String> = Vec::new();
        for (topic, _, _) in publications(actions) {
            // `/devices/<id>/…`, or Home Assistant's `…/rtu2mqtt_<id>/…`.
            let Some(id) = ids.iter().find(|id| {
                topic.contains(&format!("/{id}/")) || topic.contains(&format!("_{id}/"))
            }) else {
                continue;
            };
            if seen.last() != Some(id) {
                seen.push(id.clone());
            }
        }
        seen
    };
    assert_eq!(order(&planner.snapshot()), ids);
    assert_eq!(order(&planner.discovery_snapshot()), ids);
    assert_eq!(order(&planner.clear_all()), ids);
    assert_eq!(planner.device_ids().into_iter().collect::<Vec<_>>(), ids);
}

/// Values go to their control however the device's channels are ordered, and an unknown
/// control or device changes nothing.
#[test]
fn values_find_their_control_and_unknown_ones_are_ignored() {
    let mut planner = PublicationPlanner::new(settings(false));
    let now = Instant::now();
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    planner.handle(DeviceUpdate::Added(relay.clone()), now);
    for channel in relay.channels.iter().rev() {
        let actions = planner.handle(value(&id, &channel.id, "1"), now);
        assert_eq!(
            publications(&actions)
                .into_iter()
                .map(|(topic, payload, _)| (topic, payload))
                .collect::<Vec<_>>(),
            [(format!("/devices/{id}/controls/{}", channel.id), "1".into())]
        );
    }
    assert!(planner.handle(value(&id, "nonesuch", "1"), now).is_empty());
    assert!(planner.handle(value("nonesuch", "K1", "1"), now).is_empty());
}

/// After a reconnect the client is handed one device's retained state at a time, built when it
/// has taken everything before: values changed meanwhile go out as they are then (never the
/// ones from before the reconnect), a device removed meanwhile publishes nothing but its
/// deletions, a device added meanwhile waits its turn, each device's subscriptions and meta
/// come before its values, and the outbox never holds much more than one device's actions.
#[test]
fn after_a_reconnect_devices_are_built_one_at_a_time_from_their_latest_state() {
    use crate::mqtt::outbox::Waiting;
    use std::collections::BTreeMap;
    let now = Instant::now();
    let relay = |slave| template_device("rtu2mqtt-relay6", slave);
    let ids: Vec<String> = (1..=5).map(|slave| relay(slave).id.clone()).collect();
    let mut planner = PublicationPlanner::new(settings(true));
    for (slave, id) in (1..=4).zip(&ids) {
        planner.handle(DeviceUpdate::Added(relay(slave)), now);
        planner.handle(value(id, "K1", "1"), now);
    }
    // What one device sends after a reconnect, and when it is removed.
    let (one_device, one_removal) = {
        let mut single = PublicationPlanner::new(settings(true));
        single.handle(DeviceUpdate::Added(relay(1)), now);
        single.handle(value(&ids[0], "K1", "1"), now);
        let snapshot = single.snapshot().len();
        let removed = DeviceUpdate::Removed {
            device_id: ids[0].clone(),
        };
        (snapshot, single.handle(removed, now).len())
    };

    let mut waiting = Waiting::default();
    let online = MqttAction::Publish(Publication::retained("/rtu2mqtt/status", "online"));
    waiting.connected(vec![online], planner.device_order());
    let mut sent: Vec<MqttAction> = Vec::new();
    let mut most_waiting = 0;
    let mut offer = |waiting: &mut Waiting, planner: &mut PublicationPlanner| {
        let mut room = 25;
        waiting.offer(planner, usize::MAX, |action| {
            if room == 0 {
                return false;
            }
            room -= 1;
            sent.push(action.clone());
            true
        });
        most_waiting = most_waiting.max(waiting.outbox.len());
    };
    let mut rounds = 0;
    while !waiting.is_empty() {
        offer(&mut waiting, &mut planner);
        rounds += 1;
        match rounds {
            // Device 1 is being sent, the others wait.
            1 => {
                waiting.update(&mut planner, value(&ids[0], "K2", "1"), now);
                waiting.update(&mut planner, value(&ids[1], "K1", "0"), now);
                waiting.update(&mut planner, DeviceUpdate::Added(relay(5)), now);
                waiting.update(&mut planner, value(&ids[4], "K3", "1"), now);
            }
            2 => {
                let removed = DeviceUpdate::Removed {
                    device_id: ids[2].clone(),
                };
                waiting.update(&mut planner, removed, now);
            }
            _ => {}
        }
        assert!(rounds < 1000, "the backlog never drains");
    }
    // The device being sent, the deletions of the removed one, the values.
    assert!(
        most_waiting <= one_device + one_removal + 3,
        "{most_waiting} actions waited at once; one device has {one_device}"
    );

    let sent_publications = publications(&sent);
    let payloads = |topic: &str| -> Vec<&str> {
        sent_publications
            .iter()
            .filter(|(t, _, _)| t == topic)
            .map(|(_, p, _)| p.as_str())
            .collect()
    };
    let control = |id: &str, control: &str| format!("/devices/{id}/controls/{control}");
    assert_eq!(payloads(&control(&ids[0], "K2")), ["1"]);
    assert_eq!(
        payloads(&control(&ids[1], "K1")),
        ["0"],
        "the latest value only"
    );
    assert_eq!(payloads(&control(&ids[4], "K3")), ["1"]);
    let removed = &ids[2];
    for (topic, payload, _) in &sent_publications {
        if topic.contains(&format!("/{removed}/")) || topic.contains(&format!("_{removed}/")) {
            assert_eq!(payload, "", "{topic} published for a removed device");
        }
    }
    assert!(sent.iter().any(|a| matches!(a, MqttAction::Unsubscribe(t)
        if *t == format!("{}/on", control(removed, "K1")))));
    for id in [&ids[0], &ids[1], &ids[3], &ids[4]] {
        let position = |wanted: &dyn Fn(&MqttAction) -> bool| sent.iter().position(wanted);
        let subscribed = position(
            &|a| matches!(a, MqttAction::Subscribe(t) if *t == format!("{}/on", control(id, "K1"))),
        );
        let meta = position(
            &|a| matches!(a, MqttAction::Publish(p) if p.topic == format!("/devices/{id}/meta")),
        );
        let first_value = position(&|a| {
            matches!(a, MqttAction::Publish(p)
                if p.topic.starts_with(&format!("/devices/{id}/controls/"))
                    && !p.topic.contains("/meta"))
        });
        assert!(subscribed < meta && meta < first_value, "{id}");
        assert!(subscribed.is_some());
    }
    // What the broker holds in the end is the state at the end, as one snapshot would send it.
    let mut retained = BTreeMap::new();
    for (topic, payload, retain) in &sent_publications {
        if *retain && payload.is_empty() {
            retained.remove(topic);
        } else if *retain {
            retained.insert(topic.clone(), payload.clone());
        }
    }
    retained.remove("/rtu2mqtt/status");
    let expected: BTreeMap<String, String> = publications(&planner.snapshot())
        .into_iter()
        .filter(|(_, payload, _)| !payload.is_empty())
        .map(|(topic, payload, _)| (topic, payload))
        .collect();
    assert_eq!(retained, expected);
}

/// A device re-announced with a smaller config while it waits for its turn after a reconnect:
/// the deletions of what it no longer has go out at once, the rest with its turn.
#[test]
fn a_config_change_while_waiting_deletes_dropped_topics_at_once() {
    use crate::mqtt::outbox::Waiting;
    let now = Instant::now();
    let mut planner = PublicationPlanner::new(settings(true));
    let first = template_device("rtu2mqtt-relay6", 1);
    let relay = template_device("rtu2mqtt-relay6", 2);
    let id = relay.id.clone();
    add_served(&mut planner, first, now);
    add_served(&mut planner, relay.clone(), now);
    let mut waiting = Waiting::default();
    waiting.connected(Vec::new(), planner.device_order());
    let mut smaller = (*relay).clone();
    smaller.channels.make_mut().retain(|c| c.id != "K6");
    waiting.update(&mut planner, DeviceUpdate::Added(Arc::new(smaller)), now);
    waiting.update(&mut planner, value(&id, "K1", "1"), now);
    let mut at_once = Vec::new();
    while let Some(action) = waiting.outbox.pop() {
        at_once.push(action);
    }
    let text = render(&at_once);
    assert!(text.contains(&format!(
        "publish\tretain\tq1\t/devices/{id}/controls/K6/meta\t\n"
    )));
    assert!(text.contains(&format!("unsubscribe\t/devices/{id}/controls/K6/on")));
    assert!(text.contains(&format!(
        "publish\tretain\tq1\thomeassistant/switch/rtu2mqtt_{id}/k6/config\t\n"
    )));
    // Nothing of what it still has: no meta, no cleared error, no value before its turn.
    assert!(!text.contains(&format!("/devices/{id}/meta")), "{text}");
    assert!(
        !text.contains(&format!("/devices/{id}/controls/K5")),
        "{text}"
    );
    assert!(
        !text.contains(&format!("/devices/{id}/controls/K1\t")),
        "{text}"
    );
    let mut later = Vec::new();
    waiting.offer(&mut planner, usize::MAX, |action| {
        later.push(action.clone());
        true
    });
    let text = render(&later);
    assert!(
        text.contains(&format!("/devices/{id}/controls/K1\t1\n")),
        "{text}"
    );
    assert!(!text.contains(&format!("/devices/{id}/controls/K6/meta\t{{")));
}

/// Issue 14: the policy asks the device models for the repeats it publishes, no more.
#[test]
fn the_policy_asks_the_models_for_the_repeats_it_publishes() {
    assert_eq!(UnchangedPolicy::OnChange.repeats(), Repeats::None);
    assert_eq!(UnchangedPolicy::EveryRead.repeats(), Repeats::All);
    assert_eq!(
        UnchangedPolicy::After(Duration::from_secs(10)).repeats(),
        Repeats::All
    );
}

/// (topic, payload, retained) of each publication.
type Publications = Vec<(String, String, bool)>;

/// Issue 14, from register words to publications: a device model built with the policy's
/// repeats and the planner with that policy publish, for a coil read four times as 1 (at 0, 5,
/// 10 and 11 s), what each `max_unchanged_interval` says; a pushbutton every read, whatever
/// the policy. Returns (updates the model handed over, publications) per read.
fn reads_of_an_unchanged_coil(
    max_unchanged_interval: i64,
    pushbutton: bool,
) -> Vec<(usize, Publications)> {
    use crate::gateway::device_model::DeviceModel;
    use crate::port::{PortEvent, RegisterSpan};
    use crate::protocol::RegisterType;

    let policy = UnchangedPolicy::from_config(max_unchanged_interval);
    let mut device = (*template_device("rtu2mqtt-relay6", 1)).clone();
    if pushbutton {
        device.channels.make_mut()[0].control_type = "pushbutton".into();
    }
    let device = Arc::new(device);
    let mut model = DeviceModel::new(Arc::clone(&device), 0, policy.repeats());
    let mut planner = PublicationPlanner::new(PlannerSettings {
        unchanged: policy,
        ..settings(false)
    });
    let t0 = Instant::now();
    planner.handle(DeviceUpdate::Added(device), t0);
    [0, 5, 10, 11]
        .into_iter()
        .map(|second| {
            let mut updates = Vec::new();
            model.apply(
                PortEvent::Values {
                    device: 0,
                    span: RegisterSpan::new(RegisterType::Coil, 0, 1),
                    values: vec![1].into(),
                },
                &mut updates,
            );
            let count = updates.len();
            let published = updates
                .into_iter()
                .flat_map(|u| planner.handle(u, t0 + Duration::from_secs(second)))
                .collect::<Vec<_>>();
            (count, publications(&published))
        })
        .collect()
}

#[test]
fn an_unchanged_value_goes_out_as_max_unchanged_interval_says() {
    let k1 = |retained| {
        vec![(
            "/devices/relay6_1/controls/K1".to_owned(),
            "1".to_owned(),
            retained,
        )]
    };
    let none = Vec::new();
    // -1: published once; the repeats are not even handed over.
    assert_eq!(
        reads_of_an_unchanged_coil(-1, false),
        [
            (1, k1(true)),
            (0, none.clone()),
            (0, none.clone()),
            (0, none.clone())
        ]
    );
    // 0: every read.
    assert_eq!(
        reads_of_an_unchanged_coil(0, false),
        [(1, k1(true)), (1, k1(true)), (1, k1(true)), (1, k1(true))]
    );
    // 10 s: again once 10 s have passed since the last publication.
    assert_eq!(
        reads_of_an_unchanged_coil(10, false),
        [
            (1, k1(true)),
            (1, none.clone()),
            (1, k1(true)),
            (1, none.clone())
        ]
    );
    // A pushbutton: every read, under -1 too.
    assert_eq!(
        reads_of_an_unchanged_coil(-1, true),
        [
            (1, k1(false)),
            (1, k1(false)),
            (1, k1(false)),
            (1, k1(false))
        ]
    );
}

/// A device whose port never opened here (another program holds it: wb-mqtt-serial still
/// running) may be that program's on the broker: its Wiren Board topics are not deleted at exit
/// nor when a reload drops it; only this gateway's own (discovery configs, availability) are.
/// Once its bus is served, all of them are.
#[test]
fn a_device_whose_bus_was_never_served_keeps_its_wiren_board_topics() {
    let relay = template_device("rtu2mqtt-relay6", 1);
    let id = relay.id.clone();
    let settings = || PlannerSettings {
        clear_discovery_on_exit: true,
        ..settings(true)
    };
    let wb_topics = |actions: &[MqttAction]| -> Vec<String> {
        publications(actions)
            .into_iter()
            .map(|(topic, _, _)| topic)
            .filter(|topic| topic.starts_with("/devices/"))
            .collect()
    };
    let mut planner = PublicationPlanner::new(settings());
    planner.handle(DeviceUpdate::Added(relay.clone()), Instant::now());
    let cleared = planner.clear_all();
    assert!(wb_topics(&cleared).is_empty(), "{}", render(&cleared));
    assert!(
        render(&cleared).contains("homeassistant/"),
        "{}",
        render(&cleared)
    );
    let removed = planner.handle(
        DeviceUpdate::Removed {
            device_id: id.clone(),
        },
        Instant::now(),
    );
    assert!(wb_topics(&removed).is_empty(), "{}", render(&removed));

    let mut planner = PublicationPlanner::new(settings());
    add_served(&mut planner, relay.clone(), Instant::now());
    // Announced again by a reload: still served.
    planner.handle(DeviceUpdate::Added(relay), Instant::now());
    let cleared = wb_topics(&planner.clear_all());
    assert!(
        cleared.contains(&format!("/devices/{id}/meta/name")),
        "{cleared:?}"
    );
    assert!(
        cleared.contains(&format!("/devices/{id}/controls/K1")),
        "{cleared:?}"
    );
}
