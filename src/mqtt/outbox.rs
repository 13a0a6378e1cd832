//! Actions waiting for the MQTT client: one entry per topic, the latest wins, and an updated
//! entry moves to the back so the broker sees the last changes in the order they were made
//! (an error cleared before the value that follows it). Its size is bounded by the number of
//! topics the devices have.
//!
//! The retained state of every device, republished after each connect, waits in a
//! [`Backlog`] of device ids instead: a device's actions are built from its current state only
//! when the outbox has drained, so one device's actions are held at a time, not every device's
//! (13,000 actions, some 7 MB, at 32 devices of 68 controls). [`Waiting`] is the two together,
//! as the client task drives them.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::time::Instant;

use tracing::warn;

use super::layout;
use super::planner::PublicationPlanner;
use super::MqttAction;
use crate::device_updates::DeviceUpdate;

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
    /// it meanwhile goes out with it, from the state at that time ([`carried_by_backlog`]).
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

/// True when a device's state, republished from the [`Backlog`], carries what `action` does,
/// so that it can be left out while the device waits there: a subscription, or a retained
/// payload on one of its topics (values, errors, meta, discovery configs are published from
/// the state then). `added_topics`, for the actions of a device (re)added with a new config,
/// are its new topics: the deletions of those it no longer has must still go out. Transient
/// messages (pushbutton presses) and unsubscriptions are never carried.
fn carried_by_backlog(action: &MqttAction, added_topics: Option<&HashSet<String>>) -> bool {
    match action {
        MqttAction::Publish(p) if !p.retain => false,
        MqttAction::Publish(p) => {
            added_topics.is_none_or(|topics| !p.payload.is_empty() || topics.contains(&p.topic))
        }
        MqttAction::Subscribe(_) => true,
        MqttAction::Unsubscribe(_) => false,
    }
}

/// The device an update is about.
fn device_of(update: &DeviceUpdate) -> &str {
    match update {
        DeviceUpdate::Added(device) => &device.id,
        DeviceUpdate::Value { device_id, .. } => device_id,
        DeviceUpdate::Identity { device_id, .. }
        | DeviceUpdate::Removed { device_id }
        | DeviceUpdate::ControlError { device_id, .. }
        | DeviceUpdate::Online { device_id, .. }
        | DeviceUpdate::BusServed { device_id } => device_id,
    }
}

/// The actions of the next device in the backlog that has any (a device removed meanwhile has
/// none), built from its state now.
pub fn next_from_backlog(
    backlog: &mut Backlog,
    planner: &mut PublicationPlanner,
) -> Option<Vec<MqttAction>> {
    while let Some((id, owed)) = backlog.pop() {
        let actions = match owed {
            Owed::Everything => planner.device_snapshot(&id),
            Owed::Discovery => planner.device_discovery(&id),
        };
        if !actions.is_empty() {
            return Some(actions);
        }
    }
    None
}

/// What waits for the client while connected: actions, one per topic, and the devices whose
/// retained state is still owed, built one device at a time as the client takes them.
#[derive(Debug, Default)]
pub struct Waiting {
    pub outbox: Outbox,
    pub backlog: Backlog,
}

impl Waiting {
    /// After a connect: `first`, then every device's retained state.
    pub fn connected(&mut self, first: Vec<MqttAction>, devices: Vec<String>) {
        self.clear();
        self.outbox.extend(first);
        for id in devices {
            self.backlog.add(&id, Owed::Everything);
        }
    }

    pub fn clear(&mut self) {
        self.outbox.clear();
        self.backlog.clear();
    }

    pub fn is_empty(&self) -> bool {
        self.outbox.is_empty() && self.backlog.is_empty()
    }

    /// The planner's actions for `update`, while connected. A device added now waits in the
    /// backlog like the others; for a device waiting there, only what its republished state
    /// will not carry goes out now (deletions, a pushbutton press): its meta still comes
    /// before its values, and those are the latest when it is built.
    pub fn update(&mut self, planner: &mut PublicationPlanner, update: DeviceUpdate, now: Instant) {
        if let DeviceUpdate::Added(device) = &update {
            self.backlog.add(&device.id, Owed::Everything);
        }
        let in_backlog = !self.backlog.is_empty()
            && !matches!(update, DeviceUpdate::Removed { .. })
            && self.backlog.owes_everything(device_of(&update));
        if !in_backlog {
            self.outbox.extend(planner.handle(update, now));
            return;
        }
        let added_topics = match &update {
            DeviceUpdate::Added(device) => Some(
                layout::device_topics(planner.topics(), device)
                    .into_iter()
                    .collect::<HashSet<_>>(),
            ),
            _ => None,
        };
        let actions = planner.handle(update, now);
        self.outbox.extend(
            actions
                .into_iter()
                .filter(|a| !carried_by_backlog(a, added_topics.as_ref())),
        );
    }

    /// Gives `take` (the client, without waiting) as many actions as it takes, then the
    /// backlog's devices one at a time while it takes them all. `take` returns false when it
    /// takes no more. What the client or broker would refuse whatever happens is logged and
    /// dropped, never retried.
    pub fn offer(
        &mut self,
        planner: &mut PublicationPlanner,
        max_packet: usize,
        mut take: impl FnMut(&MqttAction) -> bool,
    ) {
        loop {
            while let Some(action) = self.outbox.pop() {
                if let Some(reason) = unsendable(&action, max_packet) {
                    log_unsendable(&action, reason);
                    continue;
                }
                if !take(&action) {
                    self.outbox.push_front(action);
                    return;
                }
            }
            match next_from_backlog(&mut self.backlog, planner) {
                Some(actions) => self.outbox.extend(actions),
                None => return,
            }
        }
    }
}

pub fn log_unsendable(action: &MqttAction, reason: &str) {
    let (what, topic) = match action {
        MqttAction::Publish(p) => ("publication", p.topic.as_str()),
        MqttAction::Subscribe(t) => ("subscription", t.as_str()),
        MqttAction::Unsubscribe(t) => ("unsubscription", t.as_str()),
    };
    let shown: String = topic.escape_debug().take(200).collect();
    warn!(
        topic = %shown,
        reason,
        "dropped an MQTT {what}: check the device and channel names in the config and templates"
    );
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
    fn the_backlog_keeps_each_device_once_in_its_place() {
        let mut backlog = Backlog::default();
        backlog.add("b", Owed::Discovery);
        backlog.add("a", Owed::Everything);
        backlog.add("b", Owed::Everything);
        backlog.add("a", Owed::Discovery);
        backlog.add("c", Owed::Discovery);
        assert!(backlog.owes_everything("a") && backlog.owes_everything("b"));
        assert!(!backlog.owes_everything("c") && !backlog.owes_everything("d"));
        let mut exiting = std::mem::take(&mut backlog);
        exiting.before_clearing(true);
        let order: Vec<_> = std::iter::from_fn(|| exiting.pop()).collect();
        assert_eq!(
            order,
            [
                ("b".to_string(), Owed::Discovery),
                ("a".to_string(), Owed::Discovery),
                ("c".to_string(), Owed::Discovery)
            ]
        );
        backlog.add("a", Owed::Everything);
        backlog.before_clearing(false);
        assert!(backlog.is_empty());
    }

    #[test]
    fn what_a_waiting_device_still_sends_at_once() {
        let transient = MqttAction::Publish(Publication::transient("/devices/d/controls/b", "1"));
        let deletion = MqttAction::Publish(Publication::removal("/devices/d/controls/x/meta"));
        let cleared = MqttAction::Publish(Publication::removal("/devices/d/meta/error"));
        let retained = publish("/devices/d/controls/v", "1");
        let unsubscribe = MqttAction::Unsubscribe("/devices/d/controls/x/on".into());
        let subscribe = MqttAction::Subscribe("/devices/d/controls/v/on".into());
        let new_topics: HashSet<String> = ["/devices/d/meta/error", "/devices/d/controls/v"]
            .map(String::from)
            .into();
        for added in [None, Some(&new_topics)] {
            assert!(!carried_by_backlog(&transient, added));
            assert!(!carried_by_backlog(&unsubscribe, added));
            assert!(carried_by_backlog(&retained, added));
            assert!(carried_by_backlog(&subscribe, added));
            assert!(carried_by_backlog(&cleared, added));
        }
        // A config change deletes the topics the device no longer has.
        assert!(!carried_by_backlog(&deletion, Some(&new_topics)));
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
