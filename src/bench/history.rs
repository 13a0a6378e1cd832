//! Was each published value one the simulator really held? (pure)
//!
//! Each value's history is its value when the run started followed by its logged changes; a value
//! of several registers changes once per instant at which any of its words changed (the
//! simulator logs the words of one update with one time), and holds only the words of such
//! instants joined. A publication at time t is right when its payload is a value the register
//! held at some instant up to t, and not older than the value the topic last published (a reply credited to
//! the wrong request, a stale read published after a newer one, or a half-updated multi-register
//! value all fail one of the two). The runs that use it give every register values that no other
//! register ever holds, so that a value read from the wrong register or device is caught too.

use std::collections::BTreeMap;

use super::harness::{Change, Publication};

/// One value of one device: a register, or `words` registers from `register` (high word first).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RegisterKey {
    pub address: u8,
    /// `coil`, `discrete`, `holding` or `input`, as in the change log.
    pub register_type: String,
    pub register: u16,
    /// Registers the value spans (1 for a plain register or bit).
    pub words: u16,
}

impl RegisterKey {
    pub fn new(address: u8, register_type: &str, register: u16) -> Self {
        Self::wide(address, register_type, register, 1)
    }

    /// A value of `words` registers from `register`.
    pub fn wide(address: u8, register_type: &str, register: u16, words: u16) -> Self {
        Self {
            address,
            register_type: register_type.to_string(),
            register,
            words: words.max(1),
        }
    }

    pub fn of(change: &Change) -> Self {
        Self::new(change.address, &change.register_type, change.register)
    }

    /// The single registers of the value, first to last.
    pub fn registers(&self) -> impl Iterator<Item = RegisterKey> + '_ {
        (0..self.words).filter_map(|offset| {
            Some(Self::new(
                self.address,
                &self.register_type,
                self.register.checked_add(offset)?,
            ))
        })
    }
}

/// A publication that fails the check, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadPublication {
    pub publication: Publication,
    /// The values the register had held up to then, oldest first (the last ten).
    pub held: Vec<u64>,
    /// `never held` or `older than the last published value`.
    pub reason: &'static str,
}

/// The outcome of one check.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct HistoryReport {
    /// Publications on a checked topic at or after `since_ns`.
    pub checked: usize,
    pub bad: Vec<BadPublication>,
}

/// One value taking a new value: every register of the value changed at the same instant is
/// one change (a device updates a wide value at once; the simulator logs its words with one
/// time).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ValueChange {
    pub mono_ns: u64,
    pub key: RegisterKey,
    /// The words joined, high first.
    pub value: u64,
    /// The origin of the change log entries (`control` or `master`).
    pub origin: String,
}

/// The values `keys` held: each key's value at the start (from `initial`, a value per single
/// register; a register missing there counts as 0) at time 0, then every change, in time order.
pub fn value_histories<'k>(
    initial: &BTreeMap<RegisterKey, u16>,
    changes: &[Change],
    keys: impl IntoIterator<Item = &'k RegisterKey>,
) -> (BTreeMap<RegisterKey, u64>, Vec<ValueChange>) {
    // Single register → (its value, the position of its word in it).
    let mut word_of: BTreeMap<RegisterKey, Vec<(RegisterKey, usize)>> = BTreeMap::new();
    let mut words: BTreeMap<RegisterKey, Vec<u16>> = BTreeMap::new();
    for key in keys {
        let current: Vec<u16> = key
            .registers()
            .map(|register| initial.get(&register).copied().unwrap_or(0))
            .collect();
        for (position, register) in key.registers().enumerate() {
            word_of
                .entry(register)
                .or_default()
                .push((key.clone(), position));
        }
        words.insert(key.clone(), current);
    }
    let start: BTreeMap<RegisterKey, u64> = words
        .iter()
        .map(|(key, w)| (key.clone(), join(w)))
        .collect();
    let mut ordered: Vec<&Change> = changes.iter().collect();
    ordered.sort_by_key(|c| c.mono_ns);
    let mut out = Vec::new();
    let mut index = 0;
    while let Some(first) = ordered.get(index) {
        let at = first.mono_ns;
        // Keys touched at this instant, with the origin of their first entry.
        let mut touched: Vec<(RegisterKey, String)> = Vec::new();
        while let Some(change) = ordered.get(index).filter(|c| c.mono_ns == at) {
            index += 1;
            for (key, position) in word_of.get(&RegisterKey::of(change)).into_iter().flatten() {
                if let Some(word) = words.get_mut(key).and_then(|w| w.get_mut(*position)) {
                    *word = change.value;
                }
                if !touched.iter().any(|(k, _)| k == key) {
                    touched.push((key.clone(), change.origin.clone()));
                }
            }
        }
        for (key, origin) in touched {
            let value = words.get(&key).map_or(0, |w| join(w));
            out.push(ValueChange {
                mono_ns: at,
                key,
                value,
                origin,
            });
        }
    }
    (start, out)
}

fn join(words: &[u16]) -> u64 {
    words
        .iter()
        .fold(0u64, |acc, &word| (acc << 16) | u64::from(word))
}

/// Checks every publication on a topic of `topics` (topic → its value and how a value is
/// written as a payload) at or after `since_ns`. `initial` holds each single register's value
/// before the first change in `changes`.
pub fn check_held_values(
    initial: &BTreeMap<RegisterKey, u16>,
    changes: &[Change],
    publications: &[Publication],
    since_ns: u64,
    topics: &BTreeMap<String, RegisterKey>,
    payload_of: impl Fn(&RegisterKey, u64) -> String,
) -> HistoryReport {
    check_held_values_by_topic(
        initial,
        changes,
        publications,
        since_ns,
        topics,
        |_, key, value| payload_of(key, value),
    )
}

/// [`check_held_values`] where the payload depends on the topic too (`payload_of(topic, key,
/// value)`): several controls on one register (bit fields) show the same words differently.
pub fn check_held_values_by_topic(
    initial: &BTreeMap<RegisterKey, u16>,
    changes: &[Change],
    publications: &[Publication],
    since_ns: u64,
    topics: &BTreeMap<String, RegisterKey>,
    payload_of: impl Fn(&str, &RegisterKey, u64) -> String,
) -> HistoryReport {
    // Value → [(from when, value)], in time order.
    let (start, value_changes) = value_histories(initial, changes, topics.values());
    let mut history: BTreeMap<RegisterKey, Vec<(u64, u64)>> = start
        .into_iter()
        .map(|(key, value)| (key, vec![(0, value)]))
        .collect();
    for change in value_changes {
        history
            .entry(change.key)
            .or_default()
            .push((change.mono_ns, change.value));
    }
    let mut report = HistoryReport::default();
    // Topic → index in its value's history of the value it last published.
    let mut last_published: BTreeMap<&str, usize> = BTreeMap::new();
    let mut ordered: Vec<&Publication> = publications.iter().collect();
    ordered.sort_by_key(|p| p.mono_ns);
    for publication in ordered {
        let Some(key) = topics.get(&publication.topic) else {
            continue;
        };
        let held: &[(u64, u64)] = history.get(key).map_or(&[], Vec::as_slice);
        let until = held.partition_point(|(from, _)| *from <= publication.mono_ns);
        let held_until_then = held.get(..until).unwrap_or(&[]);
        let index = held_until_then.iter().rposition(|(_, value)| {
            payload_of(&publication.topic, key, *value) == publication.payload
        });
        if publication.mono_ns < since_ns {
            if let Some(index) = index {
                last_published.insert(publication.topic.as_str(), index);
            }
            continue;
        }
        report.checked += 1;
        let reason = match (index, last_published.get(publication.topic.as_str())) {
            (None, _) => Some("never held"),
            (Some(index), Some(&last)) if index < last => {
                Some("older than the last published value")
            }
            (Some(index), _) => {
                last_published.insert(publication.topic.as_str(), index);
                None
            }
        };
        if let Some(reason) = reason {
            let recent = held_until_then.len().saturating_sub(10);
            report.bad.push(BadPublication {
                publication: publication.clone(),
                held: held_until_then
                    .get(recent..)
                    .unwrap_or(&[])
                    .iter()
                    .map(|(_, v)| *v)
                    .collect(),
                reason,
            });
        }
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    fn change(ms: u64, value: u16) -> Change {
        Change {
            mono_ns: ms * 1_000_000,
            address: 3,
            register_type: "input".into(),
            register: 1,
            value,
            origin: "control".into(),
        }
    }

    fn publication(ms: u64, payload: &str) -> Publication {
        Publication {
            mono_ns: ms * 1_000_000,
            topic: "/devices/d_3/controls/R1".into(),
            payload: payload.into(),
            retain: true,
        }
    }

    #[test]
    fn values_never_held_or_older_than_published_ones_are_bad() {
        let key = RegisterKey::new(3, "input", 1);
        let initial = BTreeMap::from([(key.clone(), 100)]);
        let topics = BTreeMap::from([("/devices/d_3/controls/R1".to_string(), key)]);
        let changes = [change(100, 101), change(200, 102), change(300, 103)];
        let publications = [
            publication(50, "100"),
            // 101 was held from 100 ms: right, even if 102 is current.
            publication(210, "101"),
            publication(220, "102"),
            // Not yet held at 250 ms (it is at 300 ms): a value from the future is wrong.
            publication(250, "103"),
            // Held, but older than 102 already published.
            publication(260, "101"),
            // Never held at all.
            publication(400, "7"),
            publication(410, "103"),
        ];
        let report = check_held_values(
            &initial,
            &changes,
            &publications,
            60_000_000,
            &topics,
            |_, v| v.to_string(),
        );
        assert_eq!(report.checked, 6);
        let bad: Vec<(&str, &str)> = report
            .bad
            .iter()
            .map(|b| (b.publication.payload.as_str(), b.reason))
            .collect();
        assert_eq!(
            bad,
            [
                ("103", "never held"),
                ("101", "older than the last published value"),
                ("7", "never held"),
            ]
        );
        assert_eq!(report.bad[2].held, [100, 101, 102, 103]);
    }

    fn word_change(ms: u64, register: u16, value: u16) -> Change {
        Change {
            register,
            ..change(ms, value)
        }
    }

    #[test]
    fn a_wide_value_holds_only_words_of_one_instant() {
        // A u32 at input 10..11 (high word first): 1:2, then both words at 100 ms (3:4), then
        // only the low word at 200 ms (3:5).
        let key = RegisterKey::wide(3, "input", 10, 2);
        let initial = BTreeMap::from([
            (RegisterKey::new(3, "input", 10), 1),
            (RegisterKey::new(3, "input", 11), 2),
        ]);
        let topic = "/devices/d_3/controls/R1".to_string();
        let topics = BTreeMap::from([(topic, key.clone())]);
        let changes = [
            word_change(100, 10, 3),
            word_change(100, 11, 4),
            word_change(200, 11, 5),
        ];
        let value = |hi: u64, lo: u64| ((hi << 16) | lo).to_string();
        let publications = [
            publication(150, &value(3, 4)),
            // Half updated: the new high word with the old low one.
            publication(160, &value(3, 2)),
            publication(250, &value(3, 5)),
            // The old high word with the newest low word: never held together.
            publication(260, &value(1, 5)),
        ];
        let report = check_held_values(&initial, &changes, &publications, 0, &topics, |_, v| {
            v.to_string()
        });
        assert_eq!(report.checked, 4);
        let bad: Vec<&str> = report
            .bad
            .iter()
            .map(|b| b.publication.payload.as_str())
            .collect();
        assert_eq!(bad, [value(3, 2), value(1, 5)]);
        let (start, changed) = value_histories(&initial, &changes, [&key]);
        assert_eq!(start.get(&key), Some(&0x0001_0002));
        let values: Vec<u64> = changed.iter().map(|c| c.value).collect();
        assert_eq!(values, [0x0003_0004, 0x0003_0005]);
    }

    /// Two bit fields of one register: each topic shows its own bits of the same words, and a
    /// value is right for one topic only if those bits were held.
    #[test]
    fn bit_fields_of_one_register_are_checked_by_topic() {
        let key = RegisterKey::new(3, "input", 1);
        let initial = BTreeMap::from([(key.clone(), 0x0000)]);
        let topics = BTreeMap::from([
            ("/low".to_string(), key.clone()),
            ("/high".to_string(), key),
        ]);
        let changes = [change(100, 0x1203)];
        let at = |ms: u64, topic: &str, payload: &str| Publication {
            topic: topic.into(),
            ..publication(ms, payload)
        };
        let publications = [
            at(150, "/low", "3"),
            at(150, "/high", "18"),
            // The low byte under the high byte's topic: never held there.
            at(160, "/high", "3"),
        ];
        let report = check_held_values_by_topic(
            &initial,
            &changes,
            &publications,
            0,
            &topics,
            |topic, _, value| match topic {
                "/low" => (value & 0xFF).to_string(),
                _ => (value >> 8).to_string(),
            },
        );
        assert_eq!(report.checked, 3);
        let bad: Vec<(&str, &str)> = report
            .bad
            .iter()
            .map(|b| (b.publication.topic.as_str(), b.publication.payload.as_str()))
            .collect();
        assert_eq!(bad, [("/high", "3")]);
    }
}
