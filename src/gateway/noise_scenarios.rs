//! Issue 15's noise scenario on virtual time: the bus of tests/fault_suite.rs (odd addresses
//! Fast Modbus, even ones classic; 2 event inputs and 4 input registers each, a setup register),
//! the simulator's noise faults on every reply, one register changing every 10 ms and every
//! event input toggled as soon as its last toggle was published. Exact and reproducible: the
//! recovery after the faults is a fact of the virtual wire, so it can be asserted here (the
//! real-process suite only reports it), and many seeds cost seconds.
//!
//! Checked on every run: each published register value is one the register held at or before
//! the publication and newer than the last one published; each event toggle is published exactly
//! once; after the faults the broker's retained state converges on the simulator's.
//!
//! `cargo test --lib noise_figures -- --ignored --nocapture` prints the figures
//! docs/reliability.md records (`NOISE_SEEDS` runs per bus).

use std::collections::BTreeMap;
use std::time::Duration;

use super::virtual_gateway::{OtherMaster, VirtualGateway};
use crate::bench::harness::{Change, Publication};
use crate::bench::history::{check_held_values, value_histories, RegisterKey};
use crate::bench::layout::{BenchLayout, FaultSlot, FAULT_BUS_EVENTS as EVENTS, FAULT_BUS_WIDE};
use crate::bench::matching::{match_expected, ExpectedChange, MatchReport};
use crate::device_updates::{DeviceUpdate, Repeats};
use crate::protocol::RegisterType;
use crate::sim::bus::{BusStats, ChangeOrigin};
use crate::sim::control::register_type_name;
use crate::sim::faults::Faults;

const TICK: Duration = Duration::from_millis(10);
const FAULT_TIME: Duration = Duration::from_secs(25);
/// Issue 15: the broker shows the simulator's values within 2 s of the faults ending.
const RECOVERY_TARGET: Duration = Duration::from_secs(2);

/// The noise of tests/fault_suite.rs: lost and corrupted replies, replies later than any
/// timeout, busy exceptions, garbage.
fn noise() -> Faults {
    Faults {
        drop_reply: 0.05,
        corrupt_crc: 0.05,
        delay_reply: 0.03,
        delay: Duration::from_millis(700),
        exception: 0.02,
        garbage: 0.02,
        ..Faults::default()
    }
}

/// The simulator's change log since the last call, as the harness's `watch` records it.
pub(super) fn taken_changes(gateway: &mut VirtualGateway) -> Vec<Change> {
    gateway
        .bus
        .take_changes()
        .into_iter()
        .map(|change| Change {
            mono_ns: nanos(change.at),
            address: change.address,
            register_type: register_type_name(change.change.register_type).to_string(),
            register: change.change.address,
            value: change.change.new,
            origin: match change.origin {
                ChangeOrigin::Master => "master",
                ChangeOrigin::Control => "control",
            }
            .to_string(),
        })
        .collect()
}

pub(super) fn nanos(at: Duration) -> u64 {
    u64::try_from(at.as_nanos()).unwrap_or(u64::MAX)
}

struct NoiseBus {
    gateway: VirtualGateway,
    layout: BenchLayout,
    /// Values per slot (see [`FaultSlot::words_for`]).
    span: u16,
    /// Values changed one per tick, round robin.
    round_robin: Vec<FaultSlot>,
    /// Wide values whose next change waits until the last one is published.
    awaited_slots: Vec<FaultSlot>,
    /// Per slot index: values taken so far.
    sequence: Vec<u16>,
    next_slot: usize,
    /// Every value topic and its value.
    topics: BTreeMap<String, RegisterKey>,
    /// Every single register's value before the first change.
    initial: BTreeMap<RegisterKey, u16>,
    /// The simulator's change log so far.
    changes: Vec<Change>,
    /// Event topics (and awaited wide values) changed whose new value is not yet published.
    awaiting: BTreeMap<String, String>,
    toggles: usize,
    /// Every event input toggle: when, topic, new value.
    toggle_log: Vec<(Duration, String, String)>,
    /// Configured devices that never answer (left out of every check).
    absent: Vec<u8>,
    _templates: tempfile::TempDir,
}

impl NoiseBus {
    /// `devices` at `baud`, up and converged on their first values; the devices at `absent`
    /// are configured but unplugged for good.
    fn start(devices: u8, baud: u32, seed: u64, absent: &[u8]) -> Self {
        Self::start_with(devices, baud, seed, absent, false, Repeats::All)
    }

    /// As [`Self::start`]; with `word_events`, the Fast Modbus devices send the words of their
    /// wide event values by separate events, a register each (2-byte payloads), as the
    /// independent bus emulator of issue 15 did, instead of the whole value at its first
    /// register.
    /// `repeats`: what the device models report besides the changes (every value, unless a
    /// test compares).
    fn start_with(
        devices: u8,
        baud: u32,
        seed: u64,
        absent: &[u8],
        word_events: bool,
        repeats: Repeats,
    ) -> Self {
        let layout = BenchLayout::fault_bus(devices, baud);
        let dir = tempfile::tempdir().expect("a template directory");
        let (name, template, mut entries) = layout.fault_bus_files();
        if word_events {
            let blocks: Vec<serde_json::Value> = FAULT_BUS_WIDE
                .iter()
                .filter(|wide| wide.sporadic)
                .map(|wide| {
                    serde_json::json!({"type": "input", "address": wide.address,
                        "count": wide.words, "events": true, "writable": false})
                })
                .collect();
            for entry in entries.iter_mut().filter(|e| e["fast"] == true) {
                entry["registers"] = serde_json::json!(blocks);
            }
        }
        std::fs::write(dir.path().join(name), template.to_string()).expect("template written");
        let gateway = VirtualGateway::from_bus(
            &layout.line(),
            &entries,
            dir.path(),
            true,
            seed.max(1),
            repeats,
        );
        let (round_robin, awaited_slots) = layout.fault_slots();
        let topics = layout.fault_topics();
        let mut bus = Self {
            gateway,
            span: layout.fault_span(),
            sequence: vec![0; round_robin.len() + awaited_slots.len()],
            round_robin,
            awaited_slots,
            layout,
            next_slot: 0,
            topics,
            initial: BTreeMap::new(),
            changes: Vec::new(),
            awaiting: BTreeMap::new(),
            toggles: 0,
            toggle_log: Vec::new(),
            absent: absent.to_vec(),
            _templates: dir,
        };
        for key in bus.topics.values() {
            for register in key.registers() {
                let value = bus.sim_register(&register).unwrap_or(0);
                bus.initial.insert(register, value);
            }
        }
        for _ in 0..bus.round_robin.len() {
            bus.change_next_register();
        }
        for slot in bus.awaited_slots.clone() {
            bus.change_slot(slot);
        }
        for &address in absent {
            bus.gateway.set_plugged(address, false);
        }
        let first = bus.run_until_converged(Duration::from_secs(60));
        assert!(first.is_some(), "no first values: {:?}", bus.disagreement());
        bus
    }

    fn sim_register(&self, key: &RegisterKey) -> Option<u16> {
        let register_type = match key.register_type.as_str() {
            "discrete" => RegisterType::DiscreteInput,
            _ => RegisterType::Input,
        };
        self.gateway
            .register(key.address, register_type, key.register)
    }

    /// The payload the broker should show for `key` now.
    fn sim_payload(&self, key: &RegisterKey) -> Option<String> {
        let words: Option<Vec<u16>> = key.registers().map(|r| self.sim_register(&r)).collect();
        let value = crate::bench::layout::join_words(&words?);
        Some(BenchLayout::fault_payload(key, value))
    }

    /// `slot` takes its next value of its own (all its words at once); false when it has used
    /// up its values.
    fn change_slot(&mut self, slot: FaultSlot) -> bool {
        let Some(sequence) = self.sequence.get_mut(slot.index) else {
            return false;
        };
        if *sequence + 1 >= self.span {
            return false;
        }
        *sequence += 1;
        let words = slot.words_for(self.span, *sequence);
        self.gateway
            .change(slot.address, RegisterType::Input, slot.register, &words);
        self.collect_changes();
        true
    }

    /// The next register or wide value (round robin) takes its next value of its own.
    fn change_next_register(&mut self) {
        let Some(&slot) = self
            .round_robin
            .get(self.next_slot % self.round_robin.len().max(1))
        else {
            return;
        };
        self.next_slot += 1;
        self.change_slot(slot);
    }

    /// Moves the simulator's change log into [`Self::changes`], as the harness's `watch` does.
    fn collect_changes(&mut self) {
        self.changes.extend(taken_changes(&mut self.gateway));
    }

    fn topic(&self, address: u8, register_type: &str, register: u16) -> String {
        self.layout
            .topic_of(address, register_type, register, 0)
            .expect("a register of the layout")
            .0
    }

    /// Toggles every event input, and changes every awaited wide value, whose last change has
    /// been published.
    fn toggle_published_events(&mut self) {
        let retained = &self.gateway.retained;
        self.awaiting
            .retain(|topic, value| retained.get(topic) != Some(value));
        for address in 1..=self.layout.devices {
            if self.absent.contains(&address) {
                continue;
            }
            for event in 0..EVENTS {
                let topic = self.topic(address, "discrete", event);
                if self.awaiting.contains_key(&topic) {
                    continue;
                }
                let value = self
                    .gateway
                    .register(address, RegisterType::DiscreteInput, event)
                    .unwrap_or(0);
                let toggled = u16::from(value == 0);
                self.gateway
                    .change(address, RegisterType::DiscreteInput, event, &[toggled]);
                self.collect_changes();
                self.toggle_log
                    .push((self.gateway.now, topic.clone(), toggled.to_string()));
                self.awaiting.insert(topic, toggled.to_string());
                self.toggles += 1;
            }
        }
        for slot in self.awaited_slots.clone() {
            if self.absent.contains(&slot.address) {
                continue;
            }
            let key = slot.key();
            let Some(topic) = self
                .topics
                .iter()
                .find(|(_, k)| **k == key)
                .map(|(t, _)| t.clone())
            else {
                continue;
            };
            if self.awaiting.contains_key(&topic) || !self.change_slot(slot) {
                continue;
            }
            let payload = self.sim_payload(&key).unwrap_or_default();
            self.awaiting.insert(topic, payload);
            self.toggles += 1;
        }
    }

    /// The world changes for `length`: a register per tick, events toggled once published.
    fn drive(&mut self, length: Duration) {
        let end = self.gateway.now + length;
        let mut tick = 0_u32;
        while self.gateway.now < end {
            self.change_next_register();
            if tick % 10 == 0 {
                self.toggle_published_events();
            }
            tick += 1;
            self.gateway.run_for(TICK);
        }
    }

    fn faults_on_all(&mut self, faults: Faults) {
        for address in 1..=self.layout.devices {
            self.gateway.set_faults(address, faults);
        }
    }

    /// What still differs between the broker and the simulator (None: converged).
    fn disagreement(&self) -> Option<String> {
        for (topic, key) in &self.topics {
            if self.absent.contains(&key.address) {
                continue;
            }
            let value = self.sim_payload(key);
            let published = self.gateway.retained.get(topic);
            if published != value.as_ref() {
                return Some(format!("{topic}: {published:?}, simulator {value:?}"));
            }
        }
        self.gateway
            .retained
            .keys()
            .find(|topic| {
                topic.ends_with("/meta/error")
                    && !self
                        .absent
                        .iter()
                        .any(|a| topic.starts_with(&format!("/devices/bench_{a}/")))
            })
            .map(|topic| format!("{topic} is set"))
    }

    /// Runs until the broker shows the simulator's values (checked every 10 ms of virtual
    /// time); how long it took.
    fn run_until_converged(&mut self, limit: Duration) -> Option<Duration> {
        let start = self.gateway.now;
        while self.gateway.now < start + limit {
            if self.disagreement().is_none() {
                return Some(self.gateway.now - start);
            }
            self.gateway.run_for(TICK);
        }
        None
    }

    fn publications(&self) -> Vec<Publication> {
        self.gateway.publications()
    }

    /// Every value publication since `since` checked against what the value held (all its
    /// words at one instant): (publications checked, what was wrong).
    fn check_published(&self, since: Duration) -> (usize, Vec<String>) {
        let report = check_held_values(
            &self.initial,
            &self.changes,
            &self.publications(),
            nanos(since),
            &self.topics,
            BenchLayout::fault_payload,
        );
        let wrong = report
            .bad
            .iter()
            .map(|bad| {
                format!(
                    "{} = {} at {:?}: {} (held {:?})",
                    bad.publication.topic,
                    bad.publication.payload,
                    Duration::from_nanos(bad.publication.mono_ns),
                    bad.reason,
                    bad.held
                )
            })
            .collect();
        (report.checked, wrong)
    }

    /// The changes of event inputs and awaited wide values since `since` matched with their
    /// publications: each must be published exactly once.
    fn awaited_matching(&self, since: Duration) -> MatchReport {
        let awaited: Vec<RegisterKey> = self
            .awaited_slots
            .iter()
            .map(FaultSlot::key)
            .chain(
                self.topics
                    .values()
                    .filter(|k| k.register_type == "discrete")
                    .cloned(),
            )
            .filter(|k| !self.absent.contains(&k.address))
            .collect();
        let topic_of: BTreeMap<&RegisterKey, &String> =
            self.topics.iter().map(|(t, k)| (k, t)).collect();
        let (_, changes) = value_histories(&self.initial, &self.changes, &awaited);
        let expected: Vec<ExpectedChange> = changes
            .into_iter()
            .filter(|c| c.mono_ns >= nanos(since) && c.origin == "control")
            .filter_map(|c| {
                Some(ExpectedChange {
                    mono_ns: c.mono_ns,
                    topic: topic_of.get(&c.key)?.to_string(),
                    payload: BenchLayout::fault_payload(&c.key, c.value),
                })
            })
            .collect();
        // A publication at `since` itself came before the changes made at that instant (the
        // world changes between two runs of the gateway): it counts as earlier.
        match_expected(&expected, &self.publications(), nanos(since) + 1)
    }

    /// Publications on event input and awaited wide value topics since `since`.
    fn event_publications(&self, since: Duration) -> usize {
        let awaited: Vec<String> = FAULT_BUS_WIDE
            .iter()
            .filter(|w| w.awaited)
            .map(|w| format!("/controls/{}", w.name))
            .collect();
        self.gateway
            .published
            .iter()
            .filter(|p| {
                // A publication at `since` itself answers a change made before it (counted
                // in the toggles before), not one of the run's.
                p.at > since
                    && !p.topic.contains("/meta")
                    && (p.topic.contains("/controls/E")
                        || awaited.iter().any(|a| p.topic.ends_with(a.as_str())))
            })
            .count()
    }

    /// Every change made since `since` (`changes` of them) was published once, with its value.
    fn assert_every_change_matched(&self, since: Duration, changes: usize, case: &str) {
        let matched = self.awaited_matching(since);
        assert_eq!(
            (
                matched.changes,
                matched.lost,
                matched.wrong,
                matched.duplicates
            ),
            (changes, 0, 0, 0),
            "{case}: {matched:?}"
        );
    }

    /// How many times a device was marked offline since `since`.
    fn marked_offline(&self, since: Duration) -> usize {
        self.gateway
            .updates
            .iter()
            .filter(|(at, u)| {
                *at >= since && matches!(u, DeviceUpdate::Online { online: false, .. })
            })
            .count()
    }

    /// Reads of the input registers of `devices` reported since `since`.
    fn reads_of(&self, devices: &[u8], since: Duration) -> usize {
        let ids: Vec<String> = devices.iter().map(|a| format!("bench_{a}")).collect();
        self.gateway
            .updates
            .iter()
            .filter(|(at, update)| {
                *at >= since
                    && matches!(update, DeviceUpdate::Value { device_id, control_id, .. }
                        if ids.iter().any(|id| **id == **device_id) && control_id.starts_with('R'))
            })
            .count()
    }

    /// Toggle-to-publication latencies of the event inputs of `devices` toggled since `since`,
    /// sorted (toggles not yet published are left out).
    fn event_latencies(&self, devices: &[u8], since: Duration) -> Vec<Duration> {
        let prefixes: Vec<String> = devices
            .iter()
            .map(|a| format!("/devices/bench_{a}/controls/"))
            .collect();
        let mut latencies: Vec<Duration> = self
            .toggle_log
            .iter()
            .filter(|(at, topic, _)| *at >= since && prefixes.iter().any(|p| topic.starts_with(p)))
            .filter_map(|(at, topic, value)| {
                self.gateway
                    .published
                    .iter()
                    .find(|p| p.at >= *at && &p.topic == topic && &p.payload == value)
                    .map(|p| p.at - *at)
            })
            .collect();
        latencies.sort();
        latencies
    }
}

/// Figures of one noise run.
#[derive(Debug)]
#[allow(dead_code)] // printed
struct NoiseFigures {
    recovery: Duration,
    checked: usize,
    /// Event input toggles and awaited wide value changes, each published exactly once.
    toggles: usize,
    marked_offline: usize,
    /// Event polls in which two devices or more had events and arbitrated (the simulator's
    /// count), and the most that did in one poll.
    contended_event_polls: u64,
    max_event_contenders: u64,
}

/// `fault_time` of `faults` on `devices` at `baud`, then the recovery; asserts that nothing
/// wrong was published and no event lost.
fn noise_run(devices: u8, baud: u32, seed: u64, faults: Faults) -> NoiseFigures {
    noise_run_bus(devices, baud, seed, faults).0
}

/// [`noise_run`], with the bus after it and when the faults ended.
fn noise_run_bus(
    devices: u8,
    baud: u32,
    seed: u64,
    faults: Faults,
) -> (NoiseFigures, NoiseBus, Duration) {
    let mut bus = NoiseBus::start(devices, baud, seed, &[]);
    let since = bus.gateway.now;
    let toggles_before = bus.toggles;
    let stats_before: BusStats = bus.gateway.bus.stats();
    bus.faults_on_all(faults);
    bus.drive(FAULT_TIME);
    bus.faults_on_all(Faults::default());
    let faults_ended = bus.gateway.now;
    let stats = bus.gateway.bus.stats();
    let case = format!("{devices} devices at {baud}, seed {seed}");
    let Some(recovery) = bus.run_until_converged(Duration::from_secs(90)) else {
        panic!("{case}: never converged: {:?}", bus.disagreement());
    };
    let (checked, wrong) = bus.check_published(since);
    assert!(checked > 0, "{case}: nothing checked");
    assert!(wrong.is_empty(), "{case}: {wrong:#?}");
    let toggles = bus.toggles - toggles_before;
    assert_eq!(
        bus.event_publications(since),
        toggles,
        "{case}: every toggle published exactly once"
    );
    bus.assert_every_change_matched(since, toggles, &case);
    let figures = NoiseFigures {
        recovery,
        checked,
        toggles,
        marked_offline: bus.marked_offline(since),
        contended_event_polls: stats.contended_event_polls - stats_before.contended_event_polls,
        max_event_contenders: stats.max_event_contenders,
    };
    (figures, bus, faults_ended)
}

/// Issue 14: device models that report changes only (what MQTT asks for by default) make the
/// planner publish exactly what models reporting every value do, at the same instants, through
/// noise, recovery, event toggles and changing registers; and the sinks are handed the same
/// updates less the repeats.
#[test]
fn models_reporting_changes_only_publish_what_every_value_publishes() {
    for seed in 1..=2 {
        let run = |repeats| {
            let mut bus = NoiseBus::start_with(8, 115_200, seed, &[], false, repeats);
            bus.faults_on_all(noise());
            bus.drive(Duration::from_secs(4));
            bus.faults_on_all(Faults::default());
            bus.drive(Duration::from_secs(2));
            let published: Vec<(Duration, String, String)> = bus
                .gateway
                .published
                .iter()
                .map(|p| (p.at, p.topic.clone(), p.payload.clone()))
                .collect();
            let updates: Vec<String> = bus
                .gateway
                .updates
                .iter()
                .filter(|(_, update)| !matches!(update, DeviceUpdate::Value { changed: false, .. }))
                .map(|(at, update)| format!("{at:?} {update:?}"))
                .collect();
            (published, updates)
        };
        let (every_value, every_update) = run(Repeats::All);
        let (changes_only, change_updates) = run(Repeats::None);
        assert!(
            every_value.len() > 500,
            "{} publications",
            every_value.len()
        );
        assert_eq!(changes_only, every_value, "seed {seed}");
        assert_eq!(change_updates, every_update, "seed {seed}");
    }
}

/// What 6 healthy devices at `baud` get over `length` with `dead` more devices configured that
/// never answer: (reads of their registers, event latency p50, p90, max).
fn healthy_rate(baud: u32, dead: u8, length: Duration) -> (usize, Duration, Duration, Duration) {
    let absent: Vec<u8> = (7..7 + dead).collect();
    let mut bus = NoiseBus::start(6 + dead, baud, 1, &absent);
    let since = bus.gateway.now;
    bus.drive(length);
    let healthy: Vec<u8> = (1..=6).collect();
    let reads = bus.reads_of(&healthy, since);
    let latencies = bus.event_latencies(&healthy, since);
    let at = |q: usize| {
        latencies
            .get(latencies.len() * q / 100)
            .copied()
            .unwrap_or_default()
    };
    (
        reads,
        at(50),
        at(90),
        latencies.last().copied().unwrap_or_default(),
    )
}

/// What a device that a late reply taught the longer timeout costs the others once it dies.
#[derive(Debug)]
#[allow(dead_code)] // printed
struct LateThenDead {
    /// Its transactions after it was marked offline, and the longest and total bus time they took.
    retries: usize,
    longest_retry: Duration,
    retry_time: Duration,
    /// Reads of the six healthy devices' registers, their longest event wait.
    healthy_reads: usize,
    event_max: Duration,
}

/// Six healthy devices and device 7 (Fast Modbus), which answers every request 700 ms late
/// for 10 s (past its 524 ms timeout: it learns the longer one, about 1.05 s, and is read with
/// it), then answers in time for 2 s, then dies; `length` after it died.
fn late_then_dead(baud: u32, length: Duration) -> LateThenDead {
    late_then_dead_bus(baud, length).1
}

/// [`late_then_dead`], with the bus.
fn late_then_dead_bus(baud: u32, length: Duration) -> (NoiseBus, LateThenDead) {
    let mut bus = NoiseBus::start(7, baud, 1, &[]);
    bus.gateway.set_faults(
        7,
        Faults {
            delay_reply: 1.0,
            delay: Duration::from_millis(700),
            ..Faults::default()
        },
    );
    bus.drive(Duration::from_secs(10));
    bus.gateway.set_faults(7, Faults::default());
    bus.drive(Duration::from_secs(2));
    bus.gateway.set_plugged(7, false);
    bus.absent.push(7);
    let died = bus.gateway.now;
    bus.drive(length);
    let offline_at = bus
        .gateway
        .updates
        .iter()
        .find(|(at, u)| {
            *at >= died
                && matches!(u, DeviceUpdate::Online { device_id, online: false } if device_id == "bench_7")
        })
        .map_or(bus.gateway.now, |(at, _)| *at);
    let retries: Vec<Duration> = bus
        .gateway
        .wire_log
        .iter()
        .filter(|r| r.address == 7 && r.at >= offline_at)
        .map(|r| r.ended - r.at)
        .collect();
    let healthy: Vec<u8> = (1..=6).collect();
    let figures = LateThenDead {
        retries: retries.len(),
        longest_retry: retries.iter().max().copied().unwrap_or_default(),
        retry_time: retries.iter().sum(),
        healthy_reads: bus.reads_of(&healthy, died),
        event_max: bus
            .event_latencies(&healthy, died)
            .last()
            .copied()
            .unwrap_or_default(),
    };
    (bus, figures)
}

/// A late reply raises a device's response timeout for 5 minutes (about 1.05 s here), and its
/// slow answers raise the smoothed time. Once the device is dead, silence through that timeout
/// and the late window after it shows it is not slow: its retries go back to its normal timeout
/// (524 ms, and as long again watching for a late reply), instead of holding the bus 2.1 s
/// (115200) or 3.3 s (9600) each.
#[test]
fn a_dead_device_is_retried_at_its_normal_timeout_though_it_once_answered_late() {
    for baud in [115_200, 9600] {
        let (mut bus, figures) = late_then_dead_bus(baud, Duration::from_secs(60));
        assert!(figures.retries > 0, "{baud}: {figures:?}");
        assert!(
            figures.longest_retry < Duration::from_millis(1100),
            "{baud}: {figures:?}"
        );
        // It comes back as slow as it was: its late reply, caught in a retry's late window,
        // teaches it the longer timeout again, and its values come back.
        bus.gateway.set_faults(
            7,
            Faults {
                delay_reply: 1.0,
                delay: Duration::from_millis(700),
                ..Faults::default()
            },
        );
        bus.gateway.set_plugged(7, true);
        bus.absent.clear();
        bus.drive(Duration::from_secs(5));
        assert!(
            bus.run_until_converged(Duration::from_secs(30)).is_some(),
            "{baud}: back slow, never read again: {:?}",
            bus.disagreement()
        );
    }
}

/// Issue 15, defect 1 with a device that reports a wide value's words by separate events (2-byte
/// payloads) while the daemon enables the value at its first register only: the event carries
/// the first word of an update of all words. Joined with the other words as last read it would
/// be a value the device never held; the value is read instead, and every change still comes
/// through.
#[test]
fn a_wide_value_reported_a_word_at_a_time_is_never_published_half_updated() {
    for faults in [Faults::default(), noise()] {
        let mut bus = NoiseBus::start_with(4, 115_200, 1, &[], true, Repeats::All);
        let since = bus.gateway.now;
        let toggles_before = bus.toggles;
        bus.faults_on_all(faults);
        bus.drive(Duration::from_secs(10));
        bus.faults_on_all(Faults::default());
        assert!(
            bus.run_until_converged(Duration::from_secs(30)).is_some(),
            "{:?}",
            bus.disagreement()
        );
        let (checked, wrong) = bus.check_published(since);
        assert!(checked > 0);
        assert!(wrong.is_empty(), "{faults:?}: {wrong:#?}");
        bus.assert_every_change_matched(
            since,
            bus.toggles - toggles_before,
            &format!("{faults:?}"),
        );
    }
}

/// A reply later than its timeout stays on the line as on a real port, and may land in the
/// next transaction's window. When another device's such reply lands early in a device's own
/// window, its transaction ends garbled there and then, while its own reply may still come:
/// taken as the reply to its next request of the same function and length (the fault bus's
/// classic devices read 6 registers at 0 and at 10), it would publish one read's values as the
/// other's. Replies 1.1 s and 1.3 s late (past the 524 ms timeout, within the 1 s hold-off
/// after it), 15 % of them: nothing wrong is published, every toggle once. (Before the hold-off
/// counted from the timeout, seed 1 at 1.3 s published device 6's inputs 10–15 as R0–R3 and L0.)
/// A second master on the bus (wb-mqtt-serial started again beside rtu2mqtt) reads registers
/// 0–15 of random devices; the devices answer it, and such an answer is a valid reply by
/// address, function and length to this master's read of other registers of the same device.
/// No such answer may be published as this master's values, with the other master polling now
/// and then or all the time (under noise), at 115200 and at 9600; once it stops, everything
/// converges. (Before replies near another master's request were distrusted, seeds 1–4 at
/// 115200 published values the registers never held.)
#[test]
fn another_masters_replies_are_never_published_as_this_masters_values() {
    for mix in sweep_mixes()
        .into_iter()
        .filter(|mix| mix.other_master.is_some())
    {
        for (devices, baud) in [(8, 115_200), (8, 9600)] {
            for seed in 1..=4 {
                let (violations, figures) = sweep_run(devices, baud, seed, &mix);
                assert!(
                    violations.is_empty(),
                    "{} {devices}x{baud} seed {seed}: {violations:#?} ({figures})",
                    mix.name
                );
            }
        }
    }
}

#[test]
fn a_late_reply_is_never_taken_for_the_next_request_after_another_devices_bytes() {
    for delay in [1100, 1300] {
        let mix = SweepMix {
            name: format!("late{delay}"),
            faults: Box::new(move |_, _| Faults {
                delay_reply: 0.15,
                delay: Duration::from_millis(delay),
                ..Faults::default()
            }),
            carry_late_bytes: true,
            other_master: None,
        };
        for seed in 1..=8 {
            let (violations, figures) = sweep_run(8, 115_200, seed, &mix);
            assert!(
                violations.is_empty(),
                "{} seed {seed}: {violations:#?} ({figures})",
                mix.name
            );
        }
    }
}

/// Issue 15: within 2 s of the noise ending the broker shows the simulator's values, over 20
/// seeds per bus at 115200. The floor is a safety rule: a device whose request failed just
/// before the end is left alone for its late-reply holdoff (1 s, plus the late window it skipped
/// at its configured timeout: 1.52 s). Three seeds took 2.06–2.30 s before 25 Nov 2026 (8
/// devices seed 3, 32 devices seeds 7 and 17): the window added after a reply that came in time
/// (CRC error), the window counted at a timeout a late reply had raised to 1.05 s, and an
/// offline device's retry delay grown to 2 s. The 8 devices at 9600 are held to 2 s too (10
/// seeds; 20 seeds measured 0.40–1.70 s). With 32 devices at 9600 the bus needs a whole poll
/// cycle (about 3.2 s with this load, the bus busy all along: reads and event polls) to bring
/// every value up to date after the load stops even without any fault ([`noise_figures`]
/// prints both): there the noise may add at most 0.5 s to the fault-free run.
#[test]
fn after_the_noise_the_values_are_back_within_the_holdoff_of_the_last_failure() {
    let slow_line_cycle = noise_run(32, 9600, 1, Faults::default()).recovery;
    for (devices, baud, seeds, bound) in [
        (8, 115_200, 1..=20, RECOVERY_TARGET),
        (8, 9600, 1..=10, RECOVERY_TARGET),
        (32, 115_200, 1..=20, RECOVERY_TARGET),
        (
            32,
            9600,
            1..=2,
            slow_line_cycle + Duration::from_millis(500),
        ),
    ] {
        for seed in seeds {
            let figures = noise_run(devices, baud, seed, noise());
            assert!(
                figures.recovery <= bound,
                "{devices} devices at {baud}, seed {seed}: {figures:?} (bound {bound:?})"
            );
        }
    }
}

/// Issue 15, defect 7 through the whole gateway: two or four configured devices that never
/// answer cost the six healthy ones less than a fifth of their reads over 3 minutes, their
/// events stay as quick (p90), and no event waits longer than one retry of a dead device.
#[test]
fn dead_devices_cost_the_healthy_ones_under_a_fifth() {
    let length = Duration::from_secs(180);
    let (clean, _, clean_p90, _) = healthy_rate(115_200, 0, length);
    for dead in [2, 4] {
        let (reads, _, p90, max) = healthy_rate(115_200, dead, length);
        assert!(
            reads * 10 >= clean * 8,
            "{dead} dead devices: {reads} reads, {clean} without"
        );
        assert!(
            p90 <= clean_p90 + clean_p90 / 5,
            "{dead} dead devices: event p90 {p90:?}, {clean_p90:?} without"
        );
        assert!(
            max < Duration::from_millis(1200),
            "{dead} dead devices: {max:?}"
        );
    }
}

/// Prints the figures of many runs.
#[test]
#[ignore = "measurement: prints recovery and dead-device figures"]
fn noise_figures() {
    let seeds: u64 = std::env::var("NOISE_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    for baud in [115_200, 9600] {
        for dead in [0, 2, 4] {
            for length in [60, 300] {
                let (reads, p50, p90, max) = healthy_rate(baud, dead, Duration::from_secs(length));
                eprintln!(
                    "FIGURES virtual dead_devices={dead} besides 6 baud={baud} \
                     healthy_reads/{length}s={reads} event p50={p50:?} p90={p90:?} max={max:?}"
                );
            }
        }
    }
    for baud in [115_200, 9600] {
        let figures = late_then_dead(baud, Duration::from_secs(60));
        eprintln!("FIGURES virtual late_then_dead baud={baud} 60s after it died: {figures:?}");
    }
    for (devices, baud) in [(8, 115_200), (32, 115_200), (32, 9600)] {
        let clean = noise_run(devices, baud, 1, Faults::default()).recovery;
        eprintln!(
            "FIGURES virtual clean devices={devices} baud={baud} converged {clean:?} after the load"
        );
        let mut recoveries = Vec::new();
        for seed in 1..=seeds {
            let figures = noise_run(devices, baud, seed, noise());
            eprintln!(
                "FIGURES virtual noise devices={devices} baud={baud} seed={seed} {figures:?}"
            );
            recoveries.push(figures.recovery);
        }
        recoveries.sort();
        if let (Some(min), Some(max)) = (recoveries.first(), recoveries.last()) {
            let over = recoveries.iter().filter(|r| **r > RECOVERY_TARGET).count();
            eprintln!(
                "FIGURES virtual noise devices={devices} baud={baud} runs={seeds} recovery \
                 min={min:?} median={:?} max={max:?} over_2s={over}",
                recoveries[recoveries.len() / 2]
            );
        }
    }
}

/// Why a noise run recovers slowly: each seed's recovery at 115200 (8 and 32 devices,
/// `NOISE_SEEDS` each, `NOISE_DEVICES` to pick one bus) and, for those over 1.6 s, the topics
/// published last and every transaction but answered event polls from `TRACE_BACK_S` (3) before
/// the end of the noise. `cargo test --lib recovery_trace -- --ignored --nocapture`.
#[test]
#[ignore = "diagnosis: prints the slow seeds' wire"]
fn recovery_trace() {
    let seeds: u64 = std::env::var("NOISE_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let only: Option<u8> = std::env::var("NOISE_DEVICES")
        .ok()
        .and_then(|s| s.parse().ok());
    for devices in [8u8, 32] {
        if only.is_some_and(|o| o != devices) {
            continue;
        }
        for seed in 1..=seeds {
            let (figures, bus, ended) = noise_run_bus(devices, 115_200, seed, noise());
            eprintln!(
                "TRACE devices={devices} seed={seed} recovery={:?}",
                figures.recovery
            );
            if figures.recovery <= Duration::from_millis(1600) {
                continue;
            }
            // Replay: which topic converged last, and when.
            let mut last: BTreeMap<String, Duration> = BTreeMap::new();
            for p in bus.gateway.published.iter().filter(|p| p.at >= ended) {
                last.insert(p.topic.clone(), p.at - ended);
            }
            let mut late: Vec<_> = last
                .iter()
                .filter(|(_, at)| **at > Duration::from_millis(1000))
                .collect();
            late.sort_by_key(|(_, at)| **at);
            for (topic, at) in late.iter().rev().take(6) {
                eprintln!("  late publication {topic} at +{at:?}");
            }
            let back: u64 = std::env::var("TRACE_BACK_S")
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(3);
            for r in bus.gateway.wire_log.iter().filter(|r| {
                r.ended + Duration::from_secs(back) >= ended && r.at <= ended + figures.recovery
            }) {
                if r.fast && r.address == 0xFD && r.answered {
                    continue;
                }
                let t = |d: Duration| d.as_secs_f64() - ended.as_secs_f64();
                eprintln!(
                    "  wire {:+.4}..{:+.4} addr {} fast {} answered {}",
                    t(r.at),
                    t(r.ended),
                    r.address,
                    r.fast,
                    r.answered
                );
            }
        }
    }
}

/// A fault mix of [`fault_sweep`]: the faults of each device (by address and seed), and whether
/// late bytes stay on the line for the next transactions.
pub(super) struct SweepMix {
    pub(super) name: String,
    pub(super) faults: Box<dyn Fn(u8, u64) -> Faults>,
    pub(super) carry_late_bytes: bool,
    /// A second master on the bus during the faults, reading every this often or so.
    pub(super) other_master: Option<Duration>,
}

fn scaled(faults: Faults, by: f64) -> Faults {
    Faults {
        drop_reply: faults.drop_reply * by,
        corrupt_crc: faults.corrupt_crc * by,
        delay_reply: faults.delay_reply * by,
        exception: faults.exception * by,
        garbage: faults.garbage * by,
        ..faults
    }
}

/// Delays that fall before, at and after a device's timeout (524 ms here), its late window
/// (as long again) and its hold-off after a failure (1 s more), picked per device and seed.
fn spread_delay(address: u8, seed: u64) -> Duration {
    const DELAYS_MS: [u64; 8] = [150, 400, 520, 530, 700, 1000, 1060, 1300];
    let pick = (u64::from(address) * 7 + seed * 3) % DELAYS_MS.len() as u64;
    Duration::from_millis(DELAYS_MS[pick as usize])
}

pub(super) fn sweep_mixes() -> Vec<SweepMix> {
    let mix = |name: &str, carry: bool, faults: Box<dyn Fn(u8, u64) -> Faults>| SweepMix {
        name: name.to_string(),
        faults,
        carry_late_bytes: carry,
        other_master: None,
    };
    let with_other_master = |every_ms: u64, mix: SweepMix| SweepMix {
        other_master: Some(Duration::from_millis(every_ms)),
        ..mix
    };
    let mut mixes = vec![
        mix("noise", false, Box::new(|_, _| noise())),
        mix("noise_carry", true, Box::new(|_, _| noise())),
        mix(
            "noise_x3_carry",
            true,
            Box::new(|_, _| scaled(noise(), 3.0)),
        ),
        mix(
            "garble_late_carry",
            true,
            Box::new(|address, seed| Faults {
                drop_reply: 0.02,
                corrupt_crc: 0.12,
                delay_reply: 0.08,
                delay: spread_delay(address, seed),
                exception: 0.02,
                garbage: 0.12,
                ..Faults::default()
            }),
        ),
        mix(
            "line_errors_carry",
            true,
            Box::new(|_, _| Faults {
                flip_bit: 0.08,
                truncate: 0.04,
                glitch: 0.08,
                ..Faults::default()
            }),
        ),
        with_other_master(
            200,
            mix(
                "other_master_carry",
                true,
                Box::new(|_, _| Faults::default()),
            ),
        ),
        with_other_master(
            25,
            mix("other_master_busy_carry", true, Box::new(|_, _| noise())),
        ),
        mix(
            "line_errors_late_carry",
            true,
            Box::new(|address, seed| Faults {
                delay_reply: 0.05,
                delay: spread_delay(address, seed),
                garbage: 0.03,
                flip_bit: 0.08,
                truncate: 0.04,
                glitch: 0.08,
                ..Faults::default()
            }),
        ),
    ];
    let delays: Vec<u64> = std::env::var("SWEEP_DELAYS")
        .ok()
        .map(|s| s.split(',').filter_map(|d| d.parse().ok()).collect())
        .unwrap_or_else(|| vec![300, 520, 530, 700, 1000, 1100, 1300]);
    for delay in delays {
        mixes.push(mix(
            &format!("late{delay}_carry"),
            true,
            Box::new(move |_, _| Faults {
                delay_reply: 0.15,
                delay: Duration::from_millis(delay),
                ..Faults::default()
            }),
        ));
    }
    mixes
}

/// The mix's second master, if it has one; with it the devices take 0.5, 3, 15 or 40 ms to
/// answer (picked per device and seed): the answer to the other master's request falls into
/// this master's next reply window when the device is slower than the silence before a request
/// and the request together, as slow meters are at any baud rate.
fn start_other_master(bus: &mut NoiseBus, mix: &SweepMix, seed: u64) {
    start_other_master_on(&mut bus.gateway, mix, seed);
}

/// [`start_other_master`] on any virtual gateway.
pub(super) fn start_other_master_on(gateway: &mut VirtualGateway, mix: &SweepMix, seed: u64) {
    let Some(every) = mix.other_master else {
        return;
    };
    const TURNAROUNDS_US: [u64; 4] = [500, 3_000, 15_000, 40_000];
    for index in 0..gateway.bus.devices().len() {
        let pick = (index as u64 * 5 + seed) % TURNAROUNDS_US.len() as u64;
        if let Some(device) = gateway.bus.device_mut(index) {
            device.turnaround = Duration::from_micros(TURNAROUNDS_US[pick as usize]);
        }
    }
    gateway.other_master = Some(OtherMaster::new(every, gateway.now, seed));
}

/// One sweep run: what the noise run's checks found wrong (every wrong or stale publication,
/// event toggles not published exactly once, no convergence), and its figures.
fn sweep_run(devices: u8, baud: u32, seed: u64, mix: &SweepMix) -> (Vec<String>, String) {
    let mut bus = NoiseBus::start(devices, baud, seed, &[]);
    bus.gateway.carry_late_bytes = mix.carry_late_bytes;
    let since = bus.gateway.now;
    let toggles_before = bus.toggles;
    for address in 1..=devices {
        bus.gateway.set_faults(address, (mix.faults)(address, seed));
    }
    start_other_master(&mut bus, mix, seed);
    bus.drive(FAULT_TIME);
    bus.gateway.other_master = None;
    bus.faults_on_all(Faults::default());
    let recovery = bus.run_until_converged(Duration::from_secs(90));
    let mut violations = Vec::new();
    if recovery.is_none() {
        violations.push(format!("never converged: {:?}", bus.disagreement()));
    }
    let (checked, wrong) = bus.check_published(since);
    violations.extend(wrong.into_iter().map(|w| format!("wrong: {w}")));
    let toggles = bus.toggles - toggles_before;
    let event_publications = bus.event_publications(since);
    if event_publications != toggles {
        violations.push(format!(
            "{event_publications} event publications for {toggles} toggles"
        ));
    }
    if bus.gateway.spins > 0 {
        violations.push(format!(
            "the scheduler said to wait until a time already come {} times (the port spins)",
            bus.gateway.spins
        ));
    }
    let matched = bus.awaited_matching(since);
    if (
        matched.changes,
        matched.lost,
        matched.wrong,
        matched.duplicates,
    ) != (toggles, 0, 0, 0)
    {
        violations.push(format!("toggles {toggles}: {matched:?}"));
    }
    let figures = format!(
        "recovery={recovery:?} checked={checked} toggles={toggles} offline={} wire={} now={:?} \
         spins={}",
        bus.marked_offline(since),
        bus.gateway.wire_log.len(),
        bus.gateway.now,
        bus.gateway.spins
    );
    (violations, figures)
}

/// Sweeps the noise run over many seeds, buses (8 and 32 devices at 115200, 8 at 9600) and fault
/// mixes, printing every violation of the value and event checks (a value published that the
/// register never held or older than one already published, an event toggle not published
/// exactly once, no convergence within 90 s, the scheduler telling the port to wait until a
/// time already come) and every panic, with its seed; the recovery time is printed, not
/// checked. Mixes: the suite's noise; the same with late bytes left on the line for the next
/// transactions ([`VirtualGateway::carry_late_bytes`], as on a real port); every probability
/// tripled; one heavy on corruption, garbage and replies late by 150 ms to 1.3 s; line errors
/// (a flipped bit anywhere in a reply, a reply cut short, a stray byte beside it), alone and
/// with late replies and garbage; a second master on the bus reading a few registers of a
/// random device every 200 ms or so, and every 25 ms with the suite's noise (no reply near its
/// requests may pass for this master's); and one per
/// delay of `SWEEP_DELAYS` (ms, comma-separated) with 15 % of replies that late.
/// `SWEEP_SEEDS` (default 300) runs per bus and mix from seed `SWEEP_FROM` (1); `SWEEP_MIX`
/// (a name prefix) and `SWEEP_BUS` (`8x115200`; any devices and baud rate, `32x9600` too) pick
/// some. About 5 minutes for everything in
/// release: `cargo test --release --lib gateway::noise_scenarios::fault_sweep -- --exact
/// --ignored --nocapture --test-threads=1`.
#[test]
#[ignore = "long: many seeds of the noise run"]
fn fault_sweep() {
    sweep_seeds("SWEEP", 300, sweep_run);
}

/// One run of [`fault_sweep`] (`SWEEP_BUS`, `SWEEP_MIX` its exact name, `SWEEP_FROM` the seed,
/// `SWEEP_DELAYS`), every transaction and publication printed, then what was wrong.
#[test]
#[ignore = "diagnosis: prints one sweep run's wire"]
fn fault_sweep_trace() {
    let env = |name: &str| std::env::var(name).ok();
    let seed: u64 = env("SWEEP_FROM").and_then(|s| s.parse().ok()).unwrap_or(1);
    let bus_name = env("SWEEP_BUS").unwrap_or_else(|| "8x115200".into());
    let (devices, baud) = bus_name.split_once('x').expect("8x115200");
    let (devices, baud): (u8, u32) = (devices.parse().unwrap(), baud.parse().unwrap());
    let mix_name = env("SWEEP_MIX").unwrap_or_else(|| "noise".into());
    let mixes = sweep_mixes();
    let mix = mixes.iter().find(|m| m.name == mix_name).expect("a mix");
    let mut bus = NoiseBus::start(devices, baud, seed, &[]);
    bus.gateway.carry_late_bytes = mix.carry_late_bytes;
    bus.gateway.trace = true;
    for address in 1..=devices {
        bus.gateway.set_faults(address, (mix.faults)(address, seed));
    }
    start_other_master(&mut bus, mix, seed);
    let since = bus.gateway.now;
    bus.drive(FAULT_TIME);
    bus.gateway.other_master = None;
    bus.faults_on_all(Faults::default());
    let ended = bus.gateway.now;
    let recovery = bus.run_until_converged(Duration::from_secs(90));
    eprintln!(
        "FAULTS ENDED {:.6} recovery {recovery:?}",
        ended.as_secs_f64()
    );
    for p in bus.gateway.published.iter().filter(|p| p.at >= since) {
        eprintln!("PUB {:.6} {} = {}", p.at.as_secs_f64(), p.topic, p.payload);
    }
    let (_, wrong) = bus.check_published(since);
    for w in wrong {
        eprintln!("WRONG {w}");
    }
}

/// Writes under noise: `devices` at `baud` (odd addresses Fast Modbus) with four writable
/// holding registers each (`W0`..`W3`) and one polled input register; for 20 s a client
/// writes a new value (increasing across the run, so every write's value is its own) every
/// 20 ms to a register picked at random, under `faults(address)`; then 10 s without faults.
/// What was wrong: a value written to the device that no client asked for that register, or
/// an older one after a newer (a stale write retried late); a published value the register
/// never held or older than one published before; after the faults, a register that does not
/// hold the last value asked for while its control shows no write error (a write lost
/// silently); the scheduler telling the port to wait until a time already come (it spins).
fn write_run(
    devices: u8,
    baud: u32,
    seed: u64,
    faults: &dyn Fn(u8, u64) -> Faults,
    carry_late_bytes: bool,
) -> (Vec<String>, String) {
    const REGISTERS: u16 = 4;
    let dir = tempfile::tempdir().expect("a template directory");
    let mut channels: Vec<serde_json::Value> = (0..REGISTERS)
        .map(|r| {
            serde_json::json!({"name": format!("W{r}"), "reg_type": "holding", "address": r,
                "type": "value"})
        })
        .collect();
    channels.push(
        serde_json::json!({"name": "R0", "reg_type": "input", "address": 0,
        "type": "value", "readonly": true}),
    );
    let template = serde_json::json!({"title": "write sweep", "device_type": "write-sweep",
        "device": {"name": "Write sweep", "id": "ws", "max_read_registers": 0,
            "channels": channels}});
    std::fs::write(dir.path().join("write-sweep.json"), template.to_string())
        .expect("template written");
    let line = format!("{baud} 8N2");
    let entries: Vec<serde_json::Value> = (1..=devices)
        .map(|address| {
            serde_json::json!({"name": format!("d{address}"), "template": "write-sweep",
                "address": address, "serial": 0xFE00_0000_u32 + u32::from(address),
                "line": line, "fast": address % 2 == 1, "turnaround_us": 500})
        })
        .collect();
    let mut gateway =
        VirtualGateway::from_bus(&line, &entries, dir.path(), true, seed, Repeats::All);
    gateway.carry_late_bytes = carry_late_bytes;
    gateway.trace = std::env::var("WRITE_TRACE").is_ok();
    gateway.run_for(Duration::from_secs(5));
    let mut initial = BTreeMap::new();
    let mut topics = BTreeMap::new();
    for address in 1..=devices {
        for register in 0..REGISTERS {
            let key = RegisterKey::new(address, "holding", register);
            let value = gateway
                .register(address, RegisterType::Holding, register)
                .unwrap_or(0);
            initial.insert(key.clone(), value);
            topics.insert(format!("/devices/ws_{address}/controls/W{register}"), key);
        }
    }
    gateway.bus.take_changes();
    let since = gateway.now;
    for address in 1..=devices {
        gateway.set_faults(address, faults(address, seed));
    }
    let mut rng = crate::sim::faults::XorShift64::new(seed.wrapping_mul(0x9E37_79B9) | 1);
    // Per register, the values asked for, in order.
    let mut asked: BTreeMap<(u8, u16), Vec<u16>> = BTreeMap::new();
    let mut next_value: u16 = 1000;
    let mut changes = Vec::new();
    let collect = |gateway: &mut VirtualGateway, changes: &mut Vec<Change>| {
        changes.extend(taken_changes(gateway));
    };
    let end = gateway.now + Duration::from_secs(20);
    while gateway.now < end {
        let address = u8::try_from(rng.next_u64() % u64::from(devices)).unwrap_or(0) + 1;
        let register = u16::try_from(rng.next_u64() % u64::from(REGISTERS)).unwrap_or(0);
        next_value += 1;
        asked
            .entry((address, register))
            .or_default()
            .push(next_value);
        gateway.publish_on(
            &format!("ws_{address}"),
            &format!("W{register}"),
            next_value.to_string().as_bytes(),
        );
        gateway.run_for(Duration::from_millis(20));
        collect(&mut gateway, &mut changes);
    }
    for address in 1..=devices {
        gateway.set_faults(address, Faults::default());
    }
    gateway.run_for(Duration::from_secs(10));
    collect(&mut gateway, &mut changes);
    let mut violations = Vec::new();
    // What reached the devices.
    let mut last_written: BTreeMap<(u8, u16), u16> = BTreeMap::new();
    for change in changes.iter().filter(|c| c.register_type == "holding") {
        let key = (change.address, change.register);
        let Some(values) = asked.get(&key) else {
            violations.push(format!("written, never asked: {change:?}"));
            continue;
        };
        if !values.contains(&change.value) {
            violations.push(format!("a value asked for another register: {change:?}"));
        }
        if let Some(&last) = last_written.get(&key) {
            if change.value < last {
                violations.push(format!("older than {last} written after it: {change:?}"));
            }
        }
        last_written.insert(key, change.value);
    }
    // What was published.
    let publications: Vec<Publication> = gateway.publications();
    let report = check_held_values(
        &initial,
        &changes,
        &publications,
        nanos(since),
        &topics,
        |_, value| value.to_string(),
    );
    for bad in &report.bad {
        violations.push(format!(
            "published {} = {} at {:?}: {} (held {:?})",
            bad.publication.topic,
            bad.publication.payload,
            Duration::from_nanos(bad.publication.mono_ns),
            bad.reason,
            bad.held
        ));
    }
    if gateway.spins > 0 {
        violations.push(format!(
            "the scheduler said to wait until a time already come {} times (the port spins)",
            gateway.spins
        ));
    }
    // Lost silently.
    let mut lost_with_error = 0;
    for ((address, register), values) in &asked {
        let Some(&last) = values.last() else {
            continue;
        };
        let held = gateway.register(*address, RegisterType::Holding, *register);
        if held == Some(last) {
            continue;
        }
        let error = gateway
            .retained
            .get(&format!(
                "/devices/ws_{address}/controls/W{register}/meta/error"
            ))
            .cloned()
            .unwrap_or_default();
        if error.contains('w') {
            lost_with_error += 1;
        } else {
            violations.push(format!(
                "ws_{address} W{register} holds {held:?}, {last} asked last, error {error:?}"
            ));
        }
    }
    let writes: usize = asked.values().map(Vec::len).sum();
    let figures = format!(
        "writes={writes} reached={} checked={} lost_with_error={lost_with_error} wire={} \
         now={:?} since={since:?} spins={}",
        changes
            .iter()
            .filter(|c| c.register_type == "holding")
            .count(),
        report.checked,
        gateway.wire_log.len(),
        gateway.now,
        gateway.spins
    );
    (violations, figures)
}

/// Writes under three times the suite's noise, late bytes left on the line, on a bus whose
/// devices send no events: every value written is one a client asked for that register, never
/// an older one after a newer; nothing published the register never held; no write lost
/// without its error; and the port never told to wait until a time already come (with no event
/// poll to fill the bus, a device held off after a failure had it spin until the hold-off
/// ended: 2 million 1 µs steps over seed 1's 20 s).
#[test]
fn writes_under_noise_reach_the_devices_in_order_and_the_port_never_spins() {
    let mixes = sweep_mixes();
    let mix = mixes
        .iter()
        .find(|m| m.name == "noise_x3_carry")
        .expect("the mix");
    for seed in 1..=2 {
        let (violations, figures) = write_run(8, 115_200, seed, &*mix.faults, true);
        assert!(
            violations.is_empty(),
            "seed {seed}: {violations:#?} ({figures})"
        );
    }
}

/// [`write_run`] over seeds, buses and the mixes of [`fault_sweep`] (same variables, and
/// `SWEEP_SEEDS` defaults to 100). `cargo test --release --lib
/// gateway::noise_scenarios::write_sweep -- --exact --ignored --nocapture --test-threads=1`.
#[test]
#[ignore = "long: many seeds of writes under noise"]
fn write_sweep() {
    sweep_seeds("WRITES", 100, |devices, baud, seed, mix| {
        write_run(devices, baud, seed, &*mix.faults, mix.carry_late_bytes)
    });
}

/// Runs `run` over seeds, buses and the mixes of [`sweep_mixes`] as the environment picks them
/// (`SWEEP_SEEDS`, default `default_seeds`; `SWEEP_FROM`, `SWEEP_MIX`, `SWEEP_BUS`: see
/// [`fault_sweep`]), printing each run's violations or panic under `label`; fails if any run had
/// either.
fn sweep_seeds(
    label: &str,
    default_seeds: u64,
    run: impl Fn(u8, u32, u64, &SweepMix) -> (Vec<String>, String),
) {
    let env = |name: &str| std::env::var(name).ok();
    let seeds: u64 = env("SWEEP_SEEDS")
        .and_then(|s| s.parse().ok())
        .unwrap_or(default_seeds);
    let from: u64 = env("SWEEP_FROM").and_then(|s| s.parse().ok()).unwrap_or(1);
    let only_mix = env("SWEEP_MIX");
    // One bus when asked for (any `<devices>x<baud>`, 32x9600 too), else the usual three.
    let buses: Vec<(u8, u32)> = match env("SWEEP_BUS") {
        Some(bus) => {
            let parsed = bus
                .split_once('x')
                .and_then(|(devices, baud)| Some((devices.parse().ok()?, baud.parse().ok()?)));
            vec![parsed.unwrap_or_else(|| panic!("SWEEP_BUS={bus:?}: write e.g. 8x115200"))]
        }
        None => vec![(8, 115_200), (32, 115_200), (8, 9600)],
    };
    let mut total = 0;
    for (devices, baud) in buses {
        for mix in &sweep_mixes() {
            if only_mix
                .as_ref()
                .is_some_and(|m| !mix.name.starts_with(m.as_str()))
            {
                continue;
            }
            let started = std::time::Instant::now();
            let mut bad_runs = 0;
            for seed in from..from + seeds {
                let case = format!("{label} {devices}x{baud} {} seed={seed}", mix.name);
                bad_runs += usize::from(!report_run(&case, || run(devices, baud, seed, mix)));
            }
            total += bad_runs;
            eprintln!(
                "{label} SUMMARY {devices}x{baud} {} seeds {from}..{} bad_runs={bad_runs} in {:?}",
                mix.name,
                from + seeds,
                started.elapsed()
            );
        }
    }
    assert_eq!(total, 0, "runs with violations or panics");
}

/// Runs one sweep case, printing its figures and violations, or its panic, under `case`;
/// true when it had neither.
pub(super) fn report_run(case: &str, run: impl FnOnce() -> (Vec<String>, String)) -> bool {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(run)) {
        Ok((violations, figures)) => {
            eprintln!("{case} violations={} {figures}", violations.len());
            for violation in violations.iter().take(20) {
                eprintln!("  VIOLATION {case}: {violation}");
            }
            violations.is_empty()
        }
        Err(panic) => {
            let message = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            eprintln!("  PANIC {case}: {message}");
            false
        }
    }
}
