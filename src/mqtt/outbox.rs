//! Actions waiting for the MQTT client: one entry per topic, the latest wins, and an updated
//! entry moves to the back so the broker sees the last changes in the order they were made
//! (an error cleared before the value that follows it). Its size is bounded by the number of
//! topics the devices have.
//!
//! The retained state of every device, republished after each connect, waits in a
//! [`Backlog`] of device ids instead: a device's actions are built from its current state only
//! when the outbox has drained, so one device's actions are held at a time, not every device's
//! (13,000 actions, some 7 MB, at 32 devices of 68 controls).

use std::collections::{BTreeMap, HashMap, VecDeque};

use super::MqttAction;

#[derive(Debug, Default)]
pub struct Outbox {
    next_seq: i64,
    /// Where each topic's publish waits in `queue`.
    publish_seq: HashMap<String, i64>,
    /// Where each topic's subscribe or unsubscribe waits: the two replace each other.
    filter_seq: HashMap<String, i64>,
    queue: BTreeMap<i64, MqttAction>,
}

/// The topic of an action, and whether it is a publish.
fn topic(action: &MqttAction) -> (&str, bool) {
    match action {
        MqttAction::Publish(p) => (&p.topic, true),
        MqttAction::Subscribe(t) | MqttAction::Unsubscribe(t) => (t, false),
    }
}

impl Outbox {
    fn seqs(&mut self, publish: bool) -> &mut HashMap<String, i64> {
        if publish {
            &mut self.publish_seq
        } else {
            &mut self.filter_seq
        }
    }

    pub fn push(&mut self, action: MqttAction) {
        let seq = self.next_seq;
        self.next_seq += 1;
        let (topic, publish) = topic(&action);
        let seqs = if publish {
            &mut self.publish_seq
        } else {
            &mut self.filter_seq
        };
        // The topic is copied only when it is new to the queue.
        match seqs.get_mut(topic) {
            Some(old) => {
                self.queue.remove(old);
                *old = seq;
            }
            None => {
                seqs.insert(topic.to_owned(), seq);
            }
        }
        self.queue.insert(seq, action);
    }

    pub fn extend(&mut self, actions: impl IntoIterator<Item = MqttAction>) {
        for action in actions {
            self.push(action);
        }
    }

    pub fn pop(&mut self) -> Option<MqttAction> {
        let (_, action) = self.queue.pop_first()?;
        let (topic, publish) = topic(&action);
        self.seqs(publish).remove(topic);
        Some(action)
    }

    /// Puts back an action the client could not take, ahead of everything else, unless a newer
    /// one for its topic arrived meanwhile.
    pub fn push_front(&mut self, action: MqttAction) {
        let (topic, publish) = topic(&action);
        if self.seqs(publish).contains_key(topic) {
            return;
        }
        // Below the first entry (sequence numbers may go negative), or just below the next one when empty.
        let seq = self
            .queue
            .first_key_value()
            .map_or(self.next_seq - 1, |(s, _)| s - 1);
        let owned = topic.to_owned();
        self.seqs(publish).insert(owned, seq);
        self.queue.insert(seq, action);
    }

    pub fn clear(&mut self) {
        self.publish_seq.clear();
        self.filter_seq.clear();
        self.queue.clear();
    }

    pub fn len(&self) -> usize {
        self.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

/// What of a device's retained state the backlog still owes the broker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Owed {
    /// Subscriptions, meta, errors, values and discovery configs (after a connect, or for a
    /// device added while connected).
    Everything,
    /// Only the discovery configs (Home Assistant came back online).
    Discovery,
}

/// Devices whose retained state is still to be published, in order. Their actions are built
/// from the planner's state when the client pulls them, so they carry the latest values; a
/// device removed meanwhile has none.
#[derive(Debug, Default)]
pub struct Backlog {
    devices: VecDeque<(String, Owed)>,
}

impl Backlog {
    /// Owes `owed` for `device_id`, behind the devices already waiting; a device already
    /// owed everything keeps its place.
    pub fn add(&mut self, device_id: &str, owed: Owed) {
        match self.devices.iter_mut().find(|(id, _)| id == device_id) {
            Some((_, waiting)) => {
                if owed == Owed::Everything {
                    *waiting = Owed::Everything;
                }
            }
            None => self.devices.push_back((device_id.to_owned(), owed)),
        }
    }

    /// True while `device_id`'s whole retained state waits here: what the planner decides for
    /// it meanwhile goes out with it, from the state at that time ([`covered_by_backlog`]).
    pub fn owes_everything(&self, device_id: &str) -> bool {
        self.devices
            .iter()
            .any(|(id, owed)| id == device_id && *owed == Owed::Everything)
    }

    pub fn pop(&mut self) -> Option<(String, Owed)> {
        self.devices.pop_front()
    }

    /// Keeps only what a clean exit that deletes the devices' topics still has to send: their
    /// discovery configs when those stay on the broker, else nothing.
    pub fn before_clearing(&mut self, keep_discovery: bool) {
        if !keep_discovery {
            self.devices.clear();
        }
        for (_, owed) in &mut self.devices {
            *owed = Owed::Discovery;
        }
    }

    pub fn clear(&mut self) {
        self.devices.clear();
    }

    pub fn len(&self) -> usize {
        self.devices.len()
    }

    pub fn is_empty(&self) -> bool {
        self.devices.is_empty()
    }
}

/// True when a device's republished state carries what `action` would do (a retained payload
/// or a subscription), so that it can be left out while the device waits in the [`Backlog`].
/// Deletions (empty retained payloads), unsubscriptions and transient messages (pushbutton
/// presses) are not carried and must go out.
pub fn covered_by_backlog(action: &MqttAction) -> bool {
    match action {
        MqttAction::Publish(p) => p.retain && !p.payload.is_empty(),
        MqttAction::Subscribe(_) => true,
        MqttAction::Unsubscribe(_) => false,
    }
}

/// Longest topic MQTT can carry (a two-byte length).
const MAX_TOPIC_LEN: usize = 65_535;

/// Why the client or the broker would refuse `action`: a topic made from a name that is no
/// valid topic, or a packet over `max_packet` bytes. The client refuses such a request every
/// time (or the broker drops the connection for it), so it is logged and dropped, never
/// retried. None when it can be sent.
pub fn unsendable(action: &MqttAction, max_packet: usize) -> Option<&'static str> {
    let (topic, filter, payload_len) = match action {
        MqttAction::Publish(p) => (p.topic.as_str(), false, p.payload.len()),
        MqttAction::Subscribe(t) | MqttAction::Unsubscribe(t) => (t.as_str(), true, 0),
    };
    if topic.is_empty() {
        return Some("the topic is empty");
    }
    if topic.len() > MAX_TOPIC_LEN {
        return Some("the topic is longer than MQTT allows (65535 bytes)");
    }
    // The broker closes the connection on these (MQTT 3.1.1 §1.5.3).
    if holds_control_character(topic) {
        return Some("the topic holds a NUL or another control character");
    }
    if !filter && topic.bytes().any(|b| b == b'+' || b == b'#') {
        return Some("the topic holds a wildcard (`+` or `#`)");
    }
    if filter && !rumqttc::valid_filter(topic) {
        return Some("the subscription is no valid topic filter");
    }
    // Fixed header (up to 5), topic length (2), packet id (2).
    if topic.len() + payload_len + 9 > max_packet {
        return Some("the message is larger than the client's packet limit");
    }
    None
}

/// A control character (Unicode `Cc`), U+FFFE or U+FFFF. Topics are ASCII nearly always: those
/// are checked byte by byte.
fn holds_control_character(topic: &str) -> bool {
    if topic.is_ascii() {
        return topic.bytes().any(|b| b < 0x20 || b == 0x7f);
    }
    topic
        .chars()
        .any(|c| c.is_control() || matches!(c, '\u{FFFE}' | '\u{FFFF}'))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mqtt::Publication;

    fn publish(topic: &str, payload: &str) -> MqttAction {
        MqttAction::Publish(Publication::retained(topic, payload))
    }

    #[test]
    fn latest_wins_and_moves_back() {
        let mut outbox = Outbox::default();
        outbox.push(publish("v", "1"));
        outbox.push(publish("e", "r"));
        outbox.push(publish("e", ""));
        outbox.push(publish("v", "2"));
        assert_eq!(outbox.len(), 2);
        assert_eq!(outbox.pop(), Some(publish("e", "")));
        assert_eq!(outbox.pop(), Some(publish("v", "2")));
        assert_eq!(outbox.pop(), None);
    }

    #[test]
    fn push_front_goes_first_unless_superseded() {
        let mut outbox = Outbox::default();
        outbox.push(publish("a", "1"));
        outbox.push(publish("b", "1"));
        let first = outbox.pop().unwrap();
        outbox.push_front(first.clone());
        assert_eq!(outbox.pop(), Some(first));
        let b = outbox.pop().unwrap();
        outbox.push(publish("b", "2"));
        outbox.push_front(b);
        assert_eq!(outbox.pop(), Some(publish("b", "2")));
        assert!(outbox.is_empty());
    }

    #[test]
    fn invalid_topics_and_oversized_packets_are_unsendable() {
        let max = 1024;
        assert_eq!(
            unsendable(&publish("/devices/a/controls/b", "1"), max),
            None
        );
        for topic in [
            "",
            "/devices/+/controls/b",
            "/devices/a/controls/Lvl#",
            "/devices/a\0b/controls/c",
        ] {
            assert!(
                unsendable(&publish(topic, "1"), max).is_some(),
                "{topic:?} must be refused"
            );
        }
        let long = "x".repeat(70_000);
        assert!(unsendable(&publish(&long, "1"), usize::MAX).is_some());
        assert!(unsendable(&publish("t", &"x".repeat(2000)), max).is_some());
        assert_eq!(
            unsendable(&MqttAction::Subscribe("/devices/+/meta".into()), max),
            None
        );
        assert!(unsendable(&MqttAction::Subscribe("/devices/#/x".into()), max).is_some());
    }

    #[test]
    fn control_characters_are_found_in_ascii_and_beyond() {
        for topic in [
            "a\u{7f}b",
            "a\u{1f}",
            "\u{85}x",
            "é\u{9f}",
            "x\u{FFFE}",
            "é\u{FFFF}",
        ] {
            assert!(holds_control_character(topic), "{topic:?}");
        }
        for topic in ["/devices/a/controls/b", "/devices/é/controls/Température ~"] {
            assert!(!holds_control_character(topic), "{topic:?}");
        }
    }

    #[test]
    fn a_subscribe_and_an_unsubscribe_replace_each_other_not_a_publish() {
        let mut outbox = Outbox::default();
        outbox.push(MqttAction::Subscribe("t".into()));
        outbox.push(publish("t", "1"));
        outbox.push(MqttAction::Unsubscribe("t".into()));
        assert_eq!(outbox.len(), 2);
        assert_eq!(outbox.pop(), Some(publish("t", "1")));
        assert_eq!(outbox.pop(), Some(MqttAction::Unsubscribe("t".into())));
        assert!(outbox.is_empty());
    }

    #[test]
    fn bounded_by_topics() {
        let mut outbox = Outbox::default();
        for i in 0..10_000 {
            outbox.push(publish(&format!("t{}", i % 7), &i.to_string()));
        }
        assert_eq!(outbox.len(), 7);
    }
}
