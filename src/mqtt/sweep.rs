//! Clearing what an earlier run left on the broker that the config no longer has: devices
//! (removed from the config while the daemon was down, or after a crash that skipped the clean
//! exit), and controls of the configured devices (dropped from a device's config or template
//! while the daemon was down, or by a reload while the broker was away: what the planner
//! deleted then never reached the broker), as wb-mqtt-serial's `RemoveUnusedControls` does at
//! its start. Pure: MQTT messages in, [`MqttAction`]s out.
//!
//! The driver keeps a retained record of its device ids. After each connect it subscribes to
//! that record and to a marker topic, then publishes a marker: the broker sends the retained
//! record before the marker (it handles one client's packets in order), so when the marker
//! comes back the record has been seen, or there was none. Devices in the record but not in
//! the config are stale: the driver subscribes to their topics (WB tree and discovery configs).
//! For each configured device it subscribes to its controls' `meta` (one retained message per
//! control) and, with discovery on, to its discovery configs. It deletes every retained message
//! it receives of a stale device, and every topic of a control (or discovery config) that the
//! configured device does not have, asked at that moment (a reload meanwhile counts), then
//! sends a second marker; when that one returns, the sweep is done and the record is replaced
//! by the configured devices.

use std::collections::BTreeSet;

use super::layout;
use super::topics::{topic_level, TopicScheme};
use super::{MqttAction, Publication};

/// What the sweep asks about the devices served, at the moment it needs the answer (the
/// planner's state: a reload during the sweep counts).
pub trait Served {
    /// The ids of the devices served.
    fn device_ids(&self) -> BTreeSet<String>;
    /// Whether `device_id` is served and has the control `control_id`.
    fn has_control(&self, device_id: &str, control_id: &str) -> bool;
    /// Whether `topic` is the discovery config of one of `device_id`'s controls.
    fn has_discovery_config(&self, device_id: &str, topic: &str) -> bool;
}

const RECORD_READ: &str = "record-read";
const SWEPT: &str = "swept";

/// Longest device id taken from a record (a record is any client's to write).
const MAX_ID_LEN: usize = 256;

#[derive(Debug, Clone, PartialEq, Eq)]
enum Phase {
    /// Not connected, or connected before `connected` was called.
    Idle,
    /// Waiting for the first marker; the record seen so far.
    ReadingRecord {
        recorded: Vec<String>,
    },
    /// Until the second marker: clearing these devices' retained topics (`stale`), and the
    /// controls and discovery configs that the configured devices (`kept`, with their HA
    /// nodes) do not have; `filters` are unsubscribed at the end.
    Sweeping {
        stale: Vec<String>,
        kept: Vec<(String, String)>,
        filters: Vec<String>,
    },
    Done,
}

#[derive(Debug)]
pub struct Sweeper {
    topics: TopicScheme,
    /// Home Assistant discovery prefix, when discovery is on.
    discovery_prefix: Option<String>,
    phase: Phase,
}

impl Sweeper {
    pub fn new(topics: TopicScheme, discovery_prefix: Option<String>) -> Self {
        Self {
            topics,
            discovery_prefix,
            phase: Phase::Idle,
        }
    }

    /// True once the record on the broker names exactly the configured devices.
    pub fn is_done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// After a connect: subscribe to the record and the marker, then send the first marker.
    pub fn connected(&mut self) -> Vec<MqttAction> {
        self.phase = Phase::ReadingRecord {
            recorded: Vec::new(),
        };
        vec![
            MqttAction::Subscribe(self.topics.driver_devices()),
            MqttAction::Subscribe(self.topics.driver_sweep_marker()),
            MqttAction::Publish(Publication::transient(
                self.topics.driver_sweep_marker(),
                RECORD_READ,
            )),
        ]
    }

    pub fn disconnected(&mut self) {
        self.phase = Phase::Idle;
    }

    /// The record of the configured devices.
    pub fn record(&self, configured: &BTreeSet<String>) -> Publication {
        let ids: Vec<&String> = configured.iter().collect();
        Publication::retained(
            self.topics.driver_devices(),
            serde_json::to_string(&ids).unwrap_or_else(|_| "[]".into()),
        )
    }

    /// A message on one of the sweep's topics: what to do. None when the topic is not the
    /// sweep's (an `/on` write, HA's status).
    pub fn on_message(
        &mut self,
        topic: &str,
        payload: &[u8],
        retain: bool,
        served: &impl Served,
    ) -> Option<Vec<MqttAction>> {
        if topic == self.topics.driver_devices() {
            if let (Phase::ReadingRecord { recorded }, true) = (&mut self.phase, retain) {
                *recorded = parse_record(payload);
            }
            return Some(Vec::new());
        }
        if topic == self.topics.driver_sweep_marker() {
            return Some(self.marker(payload, &served.device_ids()));
        }
        let Phase::Sweeping { stale, kept, .. } = &self.phase else {
            return None;
        };
        // Our own deletions and publications come back live (not retained): nothing to do.
        let retained = retain && !payload.is_empty();
        if let Some((device_id, control_id)) = self.control_meta_of(topic, kept) {
            if retained && !served.has_control(device_id, control_id) {
                return Some(
                    layout::any_control_topics(&self.topics, device_id, control_id)
                        .into_iter()
                        .map(|t| MqttAction::Publish(Publication::removal(t)))
                        .collect(),
                );
            }
            return Some(Vec::new());
        }
        if let Some(node) = self.discovery_node_of(topic) {
            let mut owners = kept.iter().filter(|(_, n)| n == node).peekable();
            if owners.peek().is_some() {
                if retained && !owners.any(|(id, _)| served.has_discovery_config(id, topic)) {
                    return Some(vec![MqttAction::Publish(Publication::removal(topic))]);
                }
                return Some(Vec::new());
            }
        }
        if !stale.iter().any(|id| self.is_stale_topic(topic, id)) {
            return None;
        }
        if retained {
            return Some(vec![MqttAction::Publish(Publication::removal(topic))]);
        }
        Some(Vec::new())
    }

    fn marker(&mut self, payload: &[u8], configured: &BTreeSet<String>) -> Vec<MqttAction> {
        match (&self.phase, payload) {
            (Phase::ReadingRecord { recorded }, p) if p == RECORD_READ.as_bytes() => {
                let stale: Vec<String> = recorded
                    .iter()
                    .filter(|id| !configured.contains(*id))
                    .cloned()
                    .collect();
                let kept: Vec<(String, String)> = configured
                    .iter()
                    .filter(|id| usable_id(id))
                    .map(|id| (id.clone(), self.discovery_node(id)))
                    .collect();
                if stale.is_empty() && kept.is_empty() {
                    self.phase = Phase::Done;
                    return vec![MqttAction::Publish(self.record(configured))];
                }
                if !stale.is_empty() {
                    tracing::info!(
                        devices = ?stale,
                        "clearing the broker's retained topics of devices no longer in the config"
                    );
                }
                let mut filters: Vec<String> = stale
                    .iter()
                    .flat_map(|id| self.filters(id, configured))
                    .collect();
                filters.extend(self.kept_filters(&kept));
                let mut out: Vec<MqttAction> =
                    filters.iter().cloned().map(MqttAction::Subscribe).collect();
                if stale.is_empty() {
                    // The record is right already: written now, as before the controls were
                    // swept too, rather than lost if the driver stops before the sweep ends.
                    out.push(MqttAction::Publish(self.record(configured)));
                }
                for id in &stale {
                    out.push(MqttAction::Publish(Publication::removal(
                        self.topics.device_availability(id),
                    )));
                }
                out.push(MqttAction::Publish(Publication::transient(
                    self.topics.driver_sweep_marker(),
                    SWEPT,
                )));
                self.phase = Phase::Sweeping {
                    stale,
                    kept,
                    filters,
                };
                out
            }
            (Phase::Sweeping { filters, .. }, p) if p == SWEPT.as_bytes() => {
                let mut out: Vec<MqttAction> = filters
                    .iter()
                    .cloned()
                    .map(MqttAction::Unsubscribe)
                    .collect();
                out.push(MqttAction::Publish(self.record(configured)));
                self.phase = Phase::Done;
                out
            }
            _ => Vec::new(),
        }
    }

    /// The subscriptions that bring back what the configured devices left: each control's
    /// `meta` (one retained message per control, every control of ours has one), and, with
    /// discovery on, the discovery configs of their HA nodes (once per node).
    fn kept_filters(&self, kept: &[(String, String)]) -> Vec<String> {
        let mut filters: Vec<String> = kept
            .iter()
            .map(|(id, _)| format!("{}/controls/+/meta", self.topics.device(id)))
            .collect();
        if let Some(prefix) = &self.discovery_prefix {
            let nodes: BTreeSet<&str> = kept.iter().map(|(_, node)| node.as_str()).collect();
            filters.extend(
                nodes
                    .into_iter()
                    .map(|node| format!("{prefix}/+/{node}/+/config")),
            );
        }
        filters
    }

    /// The device and control of `<prefix>/devices/<device>/controls/<control>/meta` for a
    /// configured device.
    fn control_meta_of<'a>(
        &self,
        topic: &'a str,
        kept: &[(String, String)],
    ) -> Option<(&'a str, &'a str)> {
        let rest = topic
            .strip_prefix(self.topics.device("").as_str())?
            .strip_suffix("/meta")?;
        let (device_id, control_id) = rest.split_once("/controls/")?;
        let single_levels = !device_id.contains('/') && !control_id.contains('/');
        (single_levels && kept.iter().any(|(id, _)| id == device_id))
            .then_some((device_id, control_id))
    }

    /// The HA node of `<discovery prefix>/<component>/<node>/<object>/config`.
    fn discovery_node_of<'a>(&self, topic: &'a str) -> Option<&'a str> {
        let prefix = self.discovery_prefix.as_deref()?;
        let rest = topic.strip_prefix(prefix)?.strip_prefix('/')?;
        match rest.split('/').collect::<Vec<_>>().as_slice() {
            [_, node, _, "config"] => Some(node),
            _ => None,
        }
    }

    /// The subscriptions that bring back a stale device's retained topics.
    fn filters(&self, id: &str, configured: &BTreeSet<String>) -> Vec<String> {
        let mut filters = vec![format!("{}/#", self.topics.device(id))];
        if let Some(prefix) = &self.discovery_prefix {
            let node = self.discovery_node(id);
            // Ids that reduce to the same HA node as a configured device keep their configs.
            if !configured.iter().any(|c| self.discovery_node(c) == node) {
                filters.push(format!("{prefix}/+/{node}/+/config"));
            }
        }
        filters
    }

    fn discovery_node(&self, id: &str) -> String {
        format!("{}_{}", self.topics.driver_node(), topic_level(id))
    }

    fn is_stale_topic(&self, topic: &str, id: &str) -> bool {
        if topic
            .strip_prefix(&self.topics.device(id))
            .is_some_and(|rest| rest.starts_with('/'))
        {
            return true;
        }
        let Some(prefix) = &self.discovery_prefix else {
            return false;
        };
        let Some(rest) = topic
            .strip_prefix(prefix.as_str())
            .and_then(|r| r.strip_prefix('/'))
        else {
            return false;
        };
        let levels: Vec<&str> = rest.split('/').collect();
        matches!(levels.as_slice(), [_, node, _, "config"] if *node == self.discovery_node(id))
    }
}

/// The device ids of a record; what cannot be a device id (wildcards, `/`, control
/// characters: the record is any client's to write) is left out.
fn parse_record(payload: &[u8]) -> Vec<String> {
    let ids: Vec<String> = serde_json::from_slice(payload).unwrap_or_default();
    ids.into_iter().filter(|id| usable_id(id)).collect()
}

/// An id that can go into a subscription as one topic level without widening it.
fn usable_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && !id.contains(['/', '+', '#'])
        && !id.chars().any(char::is_control)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    fn sweeper() -> Sweeper {
        Sweeper::new(
            TopicScheme::new("", "rtu2mqtt").unwrap(),
            Some("homeassistant".into()),
        )
    }

    /// Devices served, with their controls; a control's discovery config is
    /// `homeassistant/switch/rtu2mqtt_<device>/<control lower case>/config`.
    #[derive(Default)]
    struct Fake(BTreeMap<String, Vec<String>>);

    impl Fake {
        fn with(devices: &[(&str, &[&str])]) -> Self {
            Self(
                devices
                    .iter()
                    .map(|(id, controls)| {
                        (
                            id.to_string(),
                            controls.iter().map(|c| c.to_string()).collect(),
                        )
                    })
                    .collect(),
            )
        }
    }

    impl Served for Fake {
        fn device_ids(&self) -> BTreeSet<String> {
            self.0.keys().cloned().collect()
        }

        fn has_control(&self, device_id: &str, control_id: &str) -> bool {
            self.0
                .get(device_id)
                .is_some_and(|c| c.iter().any(|c| c == control_id))
        }

        fn has_discovery_config(&self, device_id: &str, topic: &str) -> bool {
            self.0.get(device_id).is_some_and(|controls| {
                controls.iter().any(|c| {
                    topic
                        == format!(
                            "homeassistant/switch/rtu2mqtt_{device_id}/{}/config",
                            c.to_lowercase()
                        )
                })
            })
        }
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

    fn removals(topics: &[String]) -> Vec<MqttAction> {
        topics
            .iter()
            .map(|t| MqttAction::Publish(Publication::removal(t.as_str())))
            .collect()
    }

    const RECORD: &str = "/rtu2mqtt/rtu2mqtt/devices";
    const MARKER: &str = "/rtu2mqtt/rtu2mqtt/sweep";

    /// Issue 15 defect 8: a device in the record but not in the config has its retained
    /// topics and discovery configs deleted, and nothing else is touched.
    #[test]
    fn a_device_dropped_from_the_config_is_cleared() {
        let mut sweeper = sweeper();
        let now = Fake::with(&[("relay6_1", &["K1"])]);
        sweeper.connected();
        let record = br#"["climate_2","relay6_1"]"#;
        assert_eq!(sweeper.on_message(RECORD, record, true, &now), Some(vec![]));
        let actions = sweeper
            .on_message(MARKER, RECORD_READ.as_bytes(), false, &now)
            .unwrap();
        assert!(actions.contains(&MqttAction::Subscribe("/devices/climate_2/#".into())));
        assert!(actions.contains(&MqttAction::Subscribe(
            "homeassistant/+/rtu2mqtt_climate_2/+/config".into()
        )));
        assert!(!sweeper.is_done());
        for topic in [
            "/devices/climate_2/controls/CO2",
            "homeassistant/sensor/rtu2mqtt_climate_2/co2/config",
        ] {
            assert_eq!(
                sweeper.on_message(topic, b"612", true, &now),
                Some(vec![MqttAction::Publish(Publication::removal(topic))])
            );
            // Our own deletion coming back.
            assert_eq!(sweeper.on_message(topic, b"", false, &now), Some(vec![]));
        }
        // Not the stale device's: left to the caller.
        assert_eq!(
            sweeper.on_message("/devices/relay6_1/controls/K1/on", b"1", false, &now),
            None
        );
        assert_eq!(
            sweeper.on_message("/devices/climate_20/controls/CO2", b"1", true, &now),
            None
        );
        let done = sweeper
            .on_message(MARKER, SWEPT.as_bytes(), false, &now)
            .unwrap();
        assert_eq!(
            publications(&done),
            [(RECORD.to_string(), r#"["relay6_1"]"#.to_string(), true)]
        );
        assert!(sweeper.is_done());
        assert_eq!(
            sweeper.on_message("/devices/climate_2/controls/CO2", b"1", true, &now),
            None
        );
    }

    #[test]
    fn no_record_and_no_device_just_writes_the_record() {
        let mut sweeper = sweeper();
        let now = Fake::default();
        sweeper.connected();
        let actions = sweeper
            .on_message(MARKER, RECORD_READ.as_bytes(), false, &now)
            .unwrap();
        assert_eq!(
            publications(&actions),
            [(RECORD.to_string(), "[]".to_string(), true)]
        );
        assert!(sweeper.is_done());
    }

    /// Review F2/F3: a control of a configured device that the config no longer has (dropped
    /// while the daemon was down, or by a reload while the broker was away) loses its retained
    /// topics and its discovery config, as wb-mqtt-serial's `RemoveUnusedControls` does at
    /// start; the device's other controls are not touched.
    #[test]
    fn controls_the_config_no_longer_has_are_cleared_and_the_others_kept() {
        let mut sweeper = sweeper();
        let now = Fake::with(&[("relay6_1", &["K1", "K5"])]);
        sweeper.connected();
        let actions = sweeper
            .on_message(MARKER, RECORD_READ.as_bytes(), false, &now)
            .unwrap();
        let subscribed: Vec<&MqttAction> = actions
            .iter()
            .filter(|a| matches!(a, MqttAction::Subscribe(_)))
            .collect();
        assert_eq!(
            subscribed,
            [
                &MqttAction::Subscribe("/devices/relay6_1/controls/+/meta".into()),
                &MqttAction::Subscribe("homeassistant/+/rtu2mqtt_relay6_1/+/config".into()),
            ]
        );
        // The marker goes after the subscriptions: their retained messages come before it.
        assert!(matches!(actions.last(), Some(MqttAction::Publish(p)) if p.topic == MARKER));
        // Nothing stale: the record is written at once.
        assert!(publications(&actions).contains(&(
            RECORD.to_string(),
            r#"["relay6_1"]"#.to_string(),
            true
        )));

        let k6 = "/devices/relay6_1/controls/K6/meta";
        let cleared = sweeper.on_message(k6, br#"{"type":"switch"}"#, true, &now);
        let expected = layout::any_control_topics(&sweeper.topics, "relay6_1", "K6");
        assert!(expected.contains(&"/devices/relay6_1/controls/K6".to_string()));
        assert_eq!(cleared, Some(removals(&expected)));
        // Configured controls, and our own publications and deletions coming back live.
        for (topic, payload, retain) in [
            (
                "/devices/relay6_1/controls/K1/meta",
                &br#"{"type":"switch"}"#[..],
                true,
            ),
            (k6, b"", false),
            (
                "/devices/relay6_1/controls/K5/meta",
                br#"{"type":"switch"}"#,
                false,
            ),
        ] {
            assert_eq!(
                sweeper.on_message(topic, payload, retain, &now),
                Some(vec![]),
                "{topic}"
            );
        }
        let config = |c: &str| format!("homeassistant/switch/rtu2mqtt_relay6_1/{c}/config");
        assert_eq!(
            sweeper.on_message(&config("k6"), b"{}", true, &now),
            Some(removals(&[config("k6")]))
        );
        assert_eq!(
            sweeper.on_message(&config("k1"), b"{}", true, &now),
            Some(vec![])
        );
        // Other topics of the device are the caller's (`/on` writes).
        assert_eq!(
            sweeper.on_message("/devices/relay6_1/controls/K6/on", b"1", false, &now),
            None
        );
        let done = sweeper
            .on_message(MARKER, SWEPT.as_bytes(), false, &now)
            .unwrap();
        assert!(done.contains(&MqttAction::Unsubscribe(
            "/devices/relay6_1/controls/+/meta".into()
        )));
        assert!(done.contains(&MqttAction::Unsubscribe(
            "homeassistant/+/rtu2mqtt_relay6_1/+/config".into()
        )));
        assert!(sweeper.is_done());
    }

    /// The controls are looked up when their retained message arrives: one that a reload
    /// added meanwhile is kept.
    #[test]
    fn a_control_added_by_a_reload_during_the_sweep_is_kept() {
        let mut sweeper = sweeper();
        sweeper.connected();
        let before = Fake::with(&[("relay6_1", &["K1"])]);
        sweeper.on_message(MARKER, RECORD_READ.as_bytes(), false, &before);
        let after = Fake::with(&[("relay6_1", &["K1", "K6"])]);
        let k6 = "/devices/relay6_1/controls/K6/meta";
        assert_eq!(sweeper.on_message(k6, b"{}", true, &after), Some(vec![]));
    }

    /// A configured id that could widen a subscription is not swept.
    #[test]
    fn configured_ids_that_would_widen_a_subscription_are_not_swept() {
        let mut sweeper = sweeper();
        sweeper.connected();
        let now = Fake::with(&[("a+b", &["K1"]), ("ok", &["K1"])]);
        let actions = sweeper
            .on_message(MARKER, RECORD_READ.as_bytes(), false, &now)
            .unwrap();
        assert!(!actions
            .iter()
            .any(|a| matches!(a, MqttAction::Subscribe(f) if f.contains("a+b"))));
        assert!(actions.contains(&MqttAction::Subscribe("/devices/ok/controls/+/meta".into())));
    }

    /// The record is any client's to write: ids that would widen a subscription are ignored.
    #[test]
    fn hostile_records_cannot_widen_the_sweep() {
        assert_eq!(
            parse_record(br##"["+","#","a/b","","ok","x\u0000"]"##),
            ["ok"]
        );
        assert!(parse_record(b"not json").is_empty());
        assert!(parse_record(&[0xFF; 10]).is_empty());
    }
}
