//! Matches the simulator's register changes with the daemon's publications (pure).
//!
//! Per topic, publications are taken in arrival order. A publication reports the latest change
//! before it whose value it carries; changes pending before that one were never published on
//! their own (lost: a short pulse a poll cycle did not see, or an event overwritten). A
//! publication that carries no pending change's value is a duplicate when it repeats the last
//! published value, else a wrong value (a topic's very first publication is its initial value,
//! neither). Changes still pending at the end are lost.

use std::collections::{BTreeMap, VecDeque};

use super::harness::{Change, Publication};

/// The outcome of matching one run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MatchReport {
    /// Change → arrival at the subscriber, in nanoseconds, one per matched change.
    pub latencies_ns: Vec<u64>,
    /// Changes considered (those with a topic).
    pub changes: usize,
    pub matched: usize,
    pub lost: usize,
    /// Publications that carried a value no pending change had (and not the last one again).
    pub wrong: usize,
    /// Publications that repeated the last published value with no change to report.
    pub duplicates: usize,
    /// Changes with no topic (registers outside the layout).
    pub unmapped: usize,
    /// A topic's first publication, with no change to report: its initial value (the daemon's
    /// first read finished after the run started).
    pub initial: usize,
}

/// Matches `changes` with the `publications` received at or after `since_ns`. `topic_of` names
/// the topic where a change must appear and the payload it must carry; earlier publications
/// only set each topic's last published value.
pub fn match_changes(
    changes: &[Change],
    publications: &[Publication],
    since_ns: u64,
    topic_of: impl Fn(&Change) -> Option<(String, String)>,
) -> MatchReport {
    let mut unmapped = 0;
    let expected: Vec<ExpectedChange> = changes
        .iter()
        .filter_map(|change| {
            let mapped = topic_of(change).map(|(topic, payload)| ExpectedChange {
                mono_ns: change.mono_ns,
                topic,
                payload,
            });
            unmapped += usize::from(mapped.is_none());
            mapped
        })
        .collect();
    MatchReport {
        unmapped,
        ..match_expected(&expected, publications, since_ns)
    }
}

/// A change as it must be published: when it happened, its topic and payload (for values that
/// are not one register: see `history::value_histories`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExpectedChange {
    pub mono_ns: u64,
    pub topic: String,
    pub payload: String,
}

/// [`match_changes`] for changes already mapped to their topics.
pub fn match_expected(
    changes: &[ExpectedChange],
    publications: &[Publication],
    since_ns: u64,
) -> MatchReport {
    let mut report = MatchReport::default();
    // topic → changes in time order, (time, expected payload).
    let mut by_topic: BTreeMap<&str, VecDeque<(u64, String)>> = BTreeMap::new();
    let mut ordered: Vec<&ExpectedChange> = changes.iter().collect();
    ordered.sort_by_key(|c| c.mono_ns);
    for change in ordered {
        report.changes += 1;
        by_topic
            .entry(change.topic.as_str())
            .or_default()
            .push_back((change.mono_ns, change.payload.clone()));
    }
    let mut last_value: BTreeMap<&str, &str> = BTreeMap::new();
    let mut ordered: Vec<&Publication> = publications.iter().collect();
    ordered.sort_by_key(|p| p.mono_ns);
    // Pending changes per topic: those already made when the publication arrived.
    let mut pending: BTreeMap<&str, Vec<(u64, String)>> = BTreeMap::new();
    for publication in ordered {
        let topic = publication.topic.as_str();
        if publication.mono_ns < since_ns {
            last_value.insert(topic, publication.payload.as_str());
            continue;
        }
        let Some(upcoming) = by_topic.get_mut(topic) else {
            continue;
        };
        let waiting = pending.entry(topic).or_default();
        while upcoming
            .front()
            .is_some_and(|(at, _)| *at <= publication.mono_ns)
        {
            if let Some(change) = upcoming.pop_front() {
                waiting.push(change);
            }
        }
        match waiting
            .iter()
            .rposition(|(_, payload)| *payload == publication.payload)
        {
            Some(position) => {
                let reported = waiting.get(position).map_or(0, |(at, _)| *at);
                report
                    .latencies_ns
                    .push(publication.mono_ns.saturating_sub(reported));
                report.matched += 1;
                report.lost += position;
                waiting.drain(..=position);
            }
            None if last_value.get(topic) == Some(&publication.payload.as_str()) => {
                report.duplicates += 1;
            }
            None if waiting.is_empty() && !last_value.contains_key(topic) => {
                report.initial += 1;
            }
            None => report.wrong += 1,
        }
        last_value.insert(topic, publication.payload.as_str());
    }
    report.lost += pending.values().map(Vec::len).sum::<usize>();
    report.lost += by_topic.values().map(VecDeque::len).sum::<usize>();
    report
}

/// Nearest-rank percentile of sorted values (`p` in 0..=1); None when empty.
pub fn percentile(sorted: &[u64], p: f64) -> Option<u64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = (p.clamp(0.0, 1.0) * sorted.len() as f64).ceil() as usize;
    sorted
        .get(rank.saturating_sub(1).min(sorted.len() - 1))
        .copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn change(ms: u64, register: u16, value: u16) -> Change {
        Change {
            mono_ns: ms * 1_000_000,
            address: 1,
            register_type: "discrete".into(),
            register,
            value,
            origin: "control".into(),
        }
    }

    fn publication(ms: u64, register: u16, payload: &str) -> Publication {
        Publication {
            mono_ns: ms * 1_000_000,
            topic: format!("/devices/d/controls/E{register}"),
            payload: payload.into(),
            retain: true,
        }
    }

    fn topic(change: &Change) -> Option<(String, String)> {
        (change.register < 8).then(|| {
            (
                format!("/devices/d/controls/E{}", change.register),
                change.value.to_string(),
            )
        })
    }

    #[test]
    fn each_change_is_matched_lost_wrong_or_duplicated() {
        let changes = [
            change(100, 0, 1),
            change(200, 0, 0),
            // A pulse nobody saw: 1 then back to 0 before the next publication.
            change(300, 0, 1),
            change(310, 0, 0),
            change(400, 1, 1),
            change(500, 9, 1),
            // Never published.
            change(600, 2, 1),
        ];
        let publications = [
            // Before the run: only the last value counts.
            publication(50, 0, "0"),
            publication(120, 0, "1"),
            // The same value again, nothing new to report: a duplicate.
            publication(205, 0, "1"),
            publication(230, 0, "0"),
            publication(350, 0, "0"),
            publication(420, 1, "7"),
            publication(450, 1, "1"),
            // E2's initial value, read after the run started.
            publication(460, 2, "0"),
        ];
        let report = match_changes(&changes, &publications, 100_000_000, topic);
        assert_eq!(report.changes, 6);
        assert_eq!(report.unmapped, 1);
        assert_eq!(report.matched, 4);
        assert_eq!(
            report.latencies_ns,
            vec![20_000_000, 30_000_000, 40_000_000, 50_000_000]
        );
        // 300 ms (superseded by 310 ms) and 600 ms (never published).
        assert_eq!(report.lost, 2);
        assert_eq!(report.duplicates, 1);
        assert_eq!(report.wrong, 1);
        assert_eq!(report.initial, 1);
    }

    #[test]
    fn percentiles_by_nearest_rank() {
        let sorted: Vec<u64> = (1..=100).collect();
        assert_eq!(percentile(&sorted, 0.5), Some(50));
        assert_eq!(percentile(&sorted, 0.99), Some(99));
        assert_eq!(percentile(&sorted, 1.0), Some(100));
        assert_eq!(percentile(&[], 0.5), None);
    }
}
