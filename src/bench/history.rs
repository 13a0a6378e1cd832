//! Was each published value one the simulator really held? (pure)
//!
//! Each register's history is its value when the run started followed by its logged changes.
//! A publication at time t is right when its payload is a value the register held at some
//! instant up to t, and not older than the value the topic last published (a reply credited to
//! the wrong request, a stale read published after a newer one, or a half-updated multi-register
//! value all fail one of the two). The runs that use it give every register values that no other
//! register ever holds, so that a value read from the wrong register or device is caught too.

use std::collections::BTreeMap;

use super::harness::{Change, Publication};

/// One register of one device.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RegisterKey {
    pub address: u8,
    /// `coil`, `discrete`, `holding` or `input`, as in the change log.
    pub register_type: String,
    pub register: u16,
}

impl RegisterKey {
    pub fn new(address: u8, register_type: &str, register: u16) -> Self {
        Self {
            address,
            register_type: register_type.to_string(),
            register,
        }
    }

    pub fn of(change: &Change) -> Self {
        Self::new(change.address, &change.register_type, change.register)
    }
}

/// A publication that fails the check, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadPublication {
    pub publication: Publication,
    /// The values the register had held up to then, oldest first (the last ten).
    pub held: Vec<u16>,
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

/// Checks every publication on a topic of `topics` (topic → its register and how a value is
/// written as a payload) at or after `since_ns`. `initial` holds each register's value before
/// the first change in `changes`.
pub fn check_held_values(
    initial: &BTreeMap<RegisterKey, u16>,
    changes: &[Change],
    publications: &[Publication],
    since_ns: u64,
    topics: &BTreeMap<String, RegisterKey>,
    payload_of: impl Fn(&RegisterKey, u16) -> String,
) -> HistoryReport {
    // Register → [(from when, value)], in time order.
    let mut history: BTreeMap<&RegisterKey, Vec<(u64, u16)>> = BTreeMap::new();
    for (key, value) in initial {
        history.entry(key).or_default().push((0, *value));
    }
    let mut ordered: Vec<&Change> = changes.iter().collect();
    ordered.sort_by_key(|c| c.mono_ns);
    let keys: BTreeMap<RegisterKey, &RegisterKey> =
        topics.values().map(|key| (key.clone(), key)).collect();
    for change in ordered {
        if let Some(key) = keys.get(&RegisterKey::of(change)) {
            history
                .entry(key)
                .or_default()
                .push((change.mono_ns, change.value));
        }
    }
    let mut report = HistoryReport::default();
    // Topic → index in its register's history of the value it last published.
    let mut last_published: BTreeMap<&str, usize> = BTreeMap::new();
    let mut ordered: Vec<&Publication> = publications.iter().collect();
    ordered.sort_by_key(|p| p.mono_ns);
    for publication in ordered {
        let Some(key) = topics.get(&publication.topic) else {
            continue;
        };
        let held: &[(u64, u16)] = history.get(key).map_or(&[], Vec::as_slice);
        let until = held.partition_point(|(from, _)| *from <= publication.mono_ns);
        let held_until_then = held.get(..until).unwrap_or(&[]);
        let index = held_until_then
            .iter()
            .rposition(|(_, value)| payload_of(key, *value) == publication.payload);
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
}
