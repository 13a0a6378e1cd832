//! Clearing what an earlier run left on the broker for devices that are no longer configured
//! (removed from the config while the daemon was down, or after a crash that skipped the clean
//! exit). Pure: MQTT messages in, [`MqttAction`]s out.
//!
//! The driver keeps a retained record of its device ids. After each connect it subscribes to
//! that record and to a marker topic, then publishes a marker: the broker sends the retained
//! record before the marker (it handles one client's packets in order), so when the marker
//! comes back the record has been seen, or there was none. Devices in the record but not in
//! the config are stale: the driver subscribes to their topics (WB tree and discovery configs),
//! deletes every retained message it receives there, and sends a second marker; when that one
//! returns, the sweep is done and the record is replaced by the configured devices.

use std::collections::BTreeSet;

use super::topics::{topic_level, TopicScheme};
use super::{MqttAction, Publication};

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
    /// Clearing these devices' retained topics until the second marker.
    Sweeping {
        stale: Vec<String>,
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
        configured: &BTreeSet<String>,
    ) -> Option<Vec<MqttAction>> {
        if topic == self.topics.driver_devices() {
            if let (Phase::ReadingRecord { recorded }, true) = (&mut self.phase, retain) {
                *recorded = parse_record(payload);
            }
            return Some(Vec::new());
        }
        if topic == self.topics.driver_sweep_marker() {
            return Some(self.marker(payload, configured));
        }
        let Phase::Sweeping { stale } = &self.phase else {
            return None;
        };
        if !stale.iter().any(|id| self.is_stale_topic(topic, id)) {
            return None;
        }
        // Our own deletions come back live and empty: nothing to do.
        if retain && !payload.is_empty() {
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
                if stale.is_empty() {
                    self.phase = Phase::Done;
                    return vec![MqttAction::Publish(self.record(configured))];
                }
                tracing::info!(
                    devices = ?stale,
                    "clearing the broker's retained topics of devices no longer in the config"
                );
                let mut out = Vec::new();
                for id in &stale {
                    out.extend(
                        self.filters(id, configured)
                            .into_iter()
                            .map(MqttAction::Subscribe),
                    );
                    out.push(MqttAction::Publish(Publication::removal(
                        self.topics.device_availability(id),
                    )));
                }
                out.push(MqttAction::Publish(Publication::transient(
                    self.topics.driver_sweep_marker(),
                    SWEPT,
                )));
                self.phase = Phase::Sweeping { stale };
                out
            }
            (Phase::Sweeping { stale }, p) if p == SWEPT.as_bytes() => {
                let mut out: Vec<MqttAction> = stale
                    .iter()
                    .flat_map(|id| self.filters(id, configured))
                    .map(MqttAction::Unsubscribe)
                    .collect();
                out.push(MqttAction::Publish(self.record(configured)));
                self.phase = Phase::Done;
                out
            }
            _ => Vec::new(),
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
    ids.into_iter()
        .filter(|id| {
            !id.is_empty()
                && id.len() <= MAX_ID_LEN
                && !id.contains(['/', '+', '#'])
                && !id.chars().any(char::is_control)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweeper() -> Sweeper {
        Sweeper::new(
            TopicScheme::new("", "rtu2mqtt").unwrap(),
            Some("homeassistant".into()),
        )
    }

    fn configured(ids: &[&str]) -> BTreeSet<String> {
        ids.iter().map(|s| s.to_string()).collect()
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

    const RECORD: &str = "/rtu2mqtt/rtu2mqtt/devices";
    const MARKER: &str = "/rtu2mqtt/rtu2mqtt/sweep";

    /// Issue 15 defect 8: a device in the record but not in the config has its retained
    /// topics and discovery configs deleted, and nothing else is touched.
    #[test]
    fn a_device_dropped_from_the_config_is_cleared() {
        let mut sweeper = sweeper();
        let now = configured(&["relay6_1"]);
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
    fn no_record_or_nothing_stale_just_writes_the_record() {
        let mut sweeper = sweeper();
        let now = configured(&["relay6_1"]);
        sweeper.connected();
        let actions = sweeper
            .on_message(MARKER, RECORD_READ.as_bytes(), false, &now)
            .unwrap();
        assert_eq!(
            publications(&actions),
            [(RECORD.to_string(), r#"["relay6_1"]"#.to_string(), true)]
        );
        assert!(sweeper.is_done());
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
