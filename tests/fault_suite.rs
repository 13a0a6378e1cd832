//! The fault suite (issue 15): the real daemon against the simulator on a pty and a real
//! mosquitto, each a separate process (src/bench/harness.rs), under injected faults. It asserts
//! values, bytes and topics, never timings: every published value is one the simulator really
//! held at that time (its change log, src/bench/history.rs), no event change is lost, and once
//! the faults end the broker converges on the simulator's values. Waits are bounded by a
//! generous patience, never by a latency threshold.
//!
//! Each scenario runs 20–40 s of faults. `FAULT_SUITE_LONG=1 cargo test --test fault_suite --
//! --nocapture` runs the long variants (5 minutes of noise, a 30-minute soak) and prints the
//! figures docs/reliability.md records.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use rtu2mqtt::bench::harness::{
    monotonic_ns, wait_until, BrokerTls, Change, Harness, HarnessOptions, Publication,
};
use rtu2mqtt::bench::history::{check_held_values, value_histories, HistoryReport, RegisterKey};
use rtu2mqtt::bench::layout::{
    join_words, BenchLayout, FaultSlot, FAULT_BUS_EVENTS as EVENTS,
    FAULT_BUS_REGISTERS as REGISTERS, FAULT_BUS_SETUP_REGISTER as SETUP_REGISTER,
    FAULT_BUS_SETUP_VALUE as SETUP_VALUE, FAULT_BUS_WIDE,
};
use rtu2mqtt::bench::matching::{match_expected, ExpectedChange, MatchReport};
use serde_json::{json, Value};

/// How long anything may take to show up (a deadline against hanging, not a latency bound).
const PATIENCE: Duration = Duration::from_secs(90);
const EVERY: Duration = Duration::from_millis(50);
/// Pace of the simulated world: one register change per tick.
const TICK: Duration = Duration::from_millis(10);

/// The serial number the benchmark layout gives the device at `address` (control commands name
/// devices by serial, so that they still work while two devices share an address).
fn serial(address: u8) -> u32 {
    0xFE00_0000 + u32::from(address)
}

fn long_variant() -> bool {
    std::env::var_os("FAULT_SUITE_LONG").is_some_and(|v| !v.is_empty() && v != "0")
}

/// The noise a bad cable makes: lost and corrupted replies, replies later than any timeout,
/// busy exceptions, garbage where a reply should be.
fn noise() -> Value {
    json!({"drop": 0.05, "corrupt_crc": 0.05, "delay": 0.03, "delay_ms": 700,
           "exception": 0.02, "garbage": 0.02})
}

/// Every single register of the fault bus's values on the device at `address`, as the
/// simulator holds them now.
fn sim_registers(harness: &Harness, address: u8) -> BTreeMap<RegisterKey, u16> {
    let mut ranges = vec![("discrete", 0, EVENTS), ("input", 0, REGISTERS)];
    ranges.extend(FAULT_BUS_WIDE.iter().map(|w| ("input", w.address, w.words)));
    let mut registers = BTreeMap::new();
    for (register_type, start, count) in ranges {
        let values = harness
            .registers(address, register_type, start, count)
            .expect("registers");
        for (register, value) in (start..).zip(values) {
            registers.insert(RegisterKey::new(address, register_type, register), value);
        }
    }
    registers
}

/// One run: the harness, the bus layout and what the test knows of the simulated world.
struct Run {
    harness: Harness,
    layout: BenchLayout,
    /// Every value topic → its value (a register, or several: the wide values).
    topics: BTreeMap<String, RegisterKey>,
    /// Each single register's value before any change.
    initial: BTreeMap<RegisterKey, u16>,
    /// Values a slot may take: slot × span + sequence (no two values share one; a wide value's
    /// other words are functions of it, see `bench::layout::wide_words`).
    span: u16,
    /// Values changed one per tick, round robin (registers and wide values).
    round_robin: Vec<FaultSlot>,
    /// Wide values whose next change waits until the last one is published.
    awaited_slots: Vec<FaultSlot>,
    /// Per slot index: values taken so far.
    sequence: Vec<u16>,
    next_slot: usize,
    /// Last payload per topic, from the publications read so far.
    last_payload: BTreeMap<String, String>,
    publications_read: usize,
    /// Event inputs toggled (and awaited wide values changed) whose new value is not yet
    /// published: topic → payload.
    awaiting: BTreeMap<String, String>,
    toggles: usize,
    /// The test CA and certificates of a TLS run (removed with the run).
    _pki: Option<tempfile::TempDir>,
}

/// How the daemon reaches the simulated bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Link {
    /// A pty, as a serial port.
    Pty,
    /// RTU frames over TCP (`sim --tcp`), as through a serial-to-Ethernet converter.
    RtuOverTcp,
    /// A Modbus TCP gateway (`sim --modbus-tcp`).
    ModbusTcp,
}

/// A test CA, the broker's certificate for 127.0.0.1 and a client certificate (openssl), as in
/// tests/mqtt/tls.rs.
fn make_pki(dir: &std::path::Path) {
    let openssl = |args: &[&str]| {
        let out = std::process::Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .output()
            .expect("this test needs openssl (apt-get install openssl; scripts/test does it)");
        assert!(
            out.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    openssl(&[
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-subj",
        "/CN=rtu2mqtt fault suite CA",
        "-keyout",
        "ca.key",
        "-out",
        "ca.crt",
    ]);
    // Extensions make v3 certificates; webpki refuses v1 ones.
    std::fs::write(dir.join("server.ext"), "subjectAltName=IP:127.0.0.1\n").expect("server.ext");
    std::fs::write(dir.join("client.ext"), "extendedKeyUsage=clientAuth\n").expect("client.ext");
    for name in ["server", "client"] {
        let (key, csr, crt, ext) = (
            format!("{name}.key"),
            format!("{name}.csr"),
            format!("{name}.crt"),
            format!("{name}.ext"),
        );
        openssl(&[
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            &format!("/CN={name}"),
            "-keyout",
            &key,
            "-out",
            &csr,
        ]);
        openssl(&[
            "x509",
            "-req",
            "-in",
            &csr,
            "-CA",
            "ca.crt",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "2",
            "-out",
            &crt,
            "-extfile",
            &ext,
        ]);
    }
}

impl Run {
    /// `devices` at `baud` on a pty; odd addresses speak Fast Modbus, even ones are classic.
    fn start(devices: u8, baud: u32) -> Self {
        Self::start_on(devices, baud, Link::Pty)
    }

    /// As [`Run::start`], the daemon reaching the bus through `link`.
    fn start_on(devices: u8, baud: u32, link: Link) -> Self {
        Self::start_with(devices, baud, link, false, false)
    }

    /// As [`Run::start_on`]; with `tls`, the daemon reaches the broker over TLS with a client
    /// certificate (the harness's subscriber keeps a plain listener of the same broker). With
    /// `word_events`, the Fast Modbus device at address 3 sends the words of its wide event
    /// values by separate events (2-byte payloads), as the independent bus emulator of issue 15
    /// did, where the others send each value whole at its first register.
    fn start_with(devices: u8, baud: u32, link: Link, tls: bool, word_events: bool) -> Self {
        Self::start_edited(devices, baud, link, tls, &json!({}), |entries| {
            if !word_events {
                return;
            }
            let blocks: Vec<Value> = FAULT_BUS_WIDE
                .iter()
                .filter(|wide| wide.sporadic)
                .map(|wide| {
                    json!({"type": "input", "address": wide.address, "count": wide.words,
                           "events": true, "writable": false})
                })
                .collect();
            for entry in entries.iter_mut().filter(|e| e["address"] == 3) {
                entry["registers"] = json!(blocks);
            }
        })
    }

    /// As [`Run::start_with`], the simulator's device entries (its bus file) edited first, and
    /// `port_extra`'s settings added to the daemon's port.
    fn start_edited(
        devices: u8,
        baud: u32,
        link: Link,
        tls: bool,
        port_extra: &Value,
        edit_devices: impl FnOnce(&mut [Value]),
    ) -> Self {
        let layout = BenchLayout::fault_bus(devices, baud);
        let (name, template, mut entries) = layout.fault_bus_files();
        edit_devices(&mut entries);
        let mut bus = layout.bus();
        bus["devices"] = json!(entries);
        let mut options =
            HarnessOptions::new(env!("CARGO_BIN_EXE_rtu2mqtt"), bus, vec![(name, template)]);
        let line = format!("{baud} 8N2");
        let listen = match link {
            Link::Pty => None,
            Link::RtuOverTcp => Some("tcp"),
            Link::ModbusTcp => Some("modbus-tcp"),
        };
        if let Some(kind) = listen {
            options.sim_args = vec![
                format!("--{kind}"),
                "127.0.0.1:0".into(),
                "--tcp-line".into(),
                line,
            ];
        }
        let pki = tls.then(|| {
            let dir = tempfile::tempdir().expect("a directory for the test CA");
            make_pki(dir.path());
            options.broker_tls = Some(BrokerTls {
                ca_file: dir.path().join("ca.crt"),
                cert_file: dir.path().join("server.crt"),
                key_file: dir.path().join("server.key"),
            });
            dir
        });
        let harness = Harness::start(&options).expect("harness starts");
        let topics = layout.fault_topics();
        let mut initial = BTreeMap::new();
        for address in 1..=devices {
            initial.extend(sim_registers(&harness, address));
        }
        let (round_robin, awaited_slots) = layout.fault_slots();
        let mut run = Self {
            harness,
            span: layout.fault_span(),
            sequence: vec![0; round_robin.len() + awaited_slots.len()],
            round_robin,
            awaited_slots,
            layout,
            topics,
            initial,
            next_slot: 0,
            last_payload: BTreeMap::new(),
            publications_read: 0,
            awaiting: BTreeMap::new(),
            toggles: 0,
            _pki: pki,
        };
        // Give every value one of its own before the daemon reads anything.
        for _ in 0..run.round_robin.len() {
            run.change_next_register();
        }
        for slot in run.awaited_slots.clone() {
            run.change_slot(slot);
        }
        let mut ports = run.layout.ports(run.harness.pty(), port_extra);
        if let Some(kind) = listen {
            let listening = run
                .harness
                .sim_listening(kind)
                .expect("the simulator's banner names its TCP listener");
            let (host, port) = listening.rsplit_once(':').expect("host:port");
            ports = json!([{
                "port_type": if link == Link::ModbusTcp { "modbus tcp" } else { "tcp" },
                "address": host,
                "port": port.parse::<u16>().expect("a port number"),
                "devices": ports[0]["devices"].clone(),
            }]);
        }
        let mut extra = json!({});
        if let (Some(pki), Some(tls_port)) = (&run._pki, run.harness.mqtt_tls_port()) {
            let file = |name: &str| pki.path().join(name);
            extra = json!({"mqtt": {
                "host": "127.0.0.1", "port": tls_port, "client_id": "rtu2mqtt-harness",
                "tls": {"ca_file": file("ca.crt"), "cert_file": file("client.crt"),
                        "key_file": file("client.key")},
            }});
        }
        let config = run.harness.daemon_config(ports, extra);
        run.harness.start_daemon(&config).expect("daemon starts");
        run.wait_converged("the first values");
        run
    }

    fn devices(&self) -> u8 {
        self.layout.devices
    }

    /// `slot` takes its next value of its own, all its words at once (false: it has used up
    /// its values; a run never gets there).
    fn change_slot(&mut self, slot: FaultSlot) -> bool {
        let Some(sequence) = self.sequence.get_mut(slot.index) else {
            return false;
        };
        if *sequence + 1 >= self.span {
            return false;
        }
        *sequence += 1;
        let words = slot.words_for(self.span, *sequence);
        self.harness
            .control(
                &json!({"cmd": "set", "serial": serial(slot.address), "type": "input",
                             "address": slot.register, "value": words}),
            )
            .expect("set");
        true
    }

    /// Sets the next register or wide value (round robin) to its next value of its own.
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

    fn set(&self, address: u8, register_type: &str, register: u16, value: u16) {
        self.harness
            .control(
                &json!({"cmd": "set", "serial": serial(address), "type": register_type,
                             "address": register, "value": value}),
            )
            .expect("set");
    }

    /// Reads the publications that arrived since the last call.
    fn read_publications(&mut self) {
        let fresh: Vec<Publication> = self
            .harness
            .with_publications(|seen| seen.get(self.publications_read..).unwrap_or(&[]).to_vec());
        self.publications_read += fresh.len();
        for publication in fresh {
            self.last_payload
                .insert(publication.topic, publication.payload);
        }
    }

    /// Toggles every event input (and changes every awaited wide value) whose last change has
    /// been published (so that no change can be legitimately overwritten by the next one: each
    /// must be published).
    fn toggle_published_events(&mut self) {
        self.read_publications();
        let published: Vec<String> = self
            .awaiting
            .iter()
            .filter(|(topic, payload)| self.last_payload.get(*topic) == Some(*payload))
            .map(|(topic, _)| topic.clone())
            .collect();
        for topic in published {
            self.awaiting.remove(&topic);
        }
        for address in 1..=self.devices() {
            for event in 0..EVENTS {
                let (topic, _) = self
                    .layout
                    .topic_of(address, "discrete", event, 0)
                    .expect("an event input");
                if self.awaiting.contains_key(&topic) {
                    continue;
                }
                let reply = self
                    .harness
                    .control(
                        &json!({"cmd": "toggle", "serial": serial(address), "type": "discrete",
                                     "address": event}),
                    )
                    .expect("toggle");
                let value = reply["value"].as_u64().unwrap_or(0);
                self.awaiting.insert(topic, value.to_string());
                self.toggles += 1;
            }
        }
        for slot in self.awaited_slots.clone() {
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
            let words = slot.words_for(self.span, self.sequence[slot.index]);
            let payload = BenchLayout::fault_payload(&key, join_words(&words));
            self.awaiting.insert(topic, payload);
            self.toggles += 1;
        }
    }

    /// The simulated world changes for `length`: one register per tick, event inputs toggled
    /// as soon as their last change was published.
    fn drive(&mut self, length: Duration) {
        let end = Instant::now() + length;
        let mut tick = 0_u32;
        while Instant::now() < end {
            self.change_next_register();
            if tick % 10 == 0 {
                self.toggle_published_events();
            }
            tick += 1;
            // Pacing of the simulated world, not a wait for the daemon.
            std::thread::sleep(TICK);
        }
    }

    fn faults_on_all(&self, faults: &Value) {
        for address in 1..=self.devices() {
            self.faults(address, faults);
        }
    }

    fn faults(&self, address: u8, faults: &Value) {
        let mut command = json!({"cmd": "faults", "device": address});
        if let (Some(fields), Some(extra)) = (command.as_object_mut(), faults.as_object()) {
            fields.extend(extra.clone());
        }
        self.harness.control(&command).expect("faults");
    }

    /// What the broker should show now: topic → payload, from the simulator's registers.
    fn expected(&self) -> BTreeMap<String, String> {
        let mut registers = BTreeMap::new();
        for address in 1..=self.devices() {
            registers.extend(sim_registers(&self.harness, address));
        }
        self.topics
            .iter()
            .map(|(topic, key)| {
                let words: Vec<u16> = key
                    .registers()
                    .map(|r| registers.get(&r).copied().unwrap_or(0))
                    .collect();
                (
                    topic.clone(),
                    BenchLayout::fault_payload(key, join_words(&words)),
                )
            })
            .collect()
    }

    /// The last published value of every topic and the simulator's disagree, or an error flag
    /// is still set, or a toggled event is not yet published: what (for the failure message).
    fn disagreement(&mut self) -> Option<String> {
        self.read_publications();
        for (topic, payload) in self.expected() {
            let published = self.last_payload.get(&topic);
            if published != Some(&payload) {
                return Some(format!(
                    "{topic}: published {published:?}, simulator {payload}"
                ));
            }
        }
        for (topic, payload) in &self.last_payload {
            if topic.ends_with("/meta/error") && !payload.is_empty() {
                return Some(format!("{topic} is still {payload:?}"));
            }
            if topic.contains("/availability/") && payload != "online" {
                return Some(format!("{topic} is still {payload:?}"));
            }
        }
        None
    }

    /// Waits until the broker shows the simulator's values with no error flag; how long that
    /// took (a figure for the report, never asserted).
    fn wait_converged(&mut self, what: &str) -> Duration {
        let started = Instant::now();
        let mut last = String::new();
        let converged = wait_until(PATIENCE, EVERY, || match self.disagreement() {
            None => Some(()),
            Some(why) => {
                last = why;
                None
            }
        });
        assert!(
            converged.is_some(),
            "{what}: the broker never showed the simulator's values ({last})\n{}",
            self.log_tail()
        );
        started.elapsed()
    }

    fn log_tail(&self) -> String {
        let log = self.harness.daemon_log();
        let lines: Vec<&str> = log.lines().collect();
        lines[lines.len().saturating_sub(40)..].join("\n")
    }

    fn changes(&self) -> Vec<Change> {
        self.harness.changes()
    }

    /// Every publication since `since_ns` checked against the registers' histories.
    fn history(&self, since_ns: u64) -> HistoryReport {
        check_held_values(
            &self.initial,
            &self.changes(),
            &self.harness.publications(),
            since_ns,
            &self.topics,
            BenchLayout::fault_payload,
        )
    }

    /// The changes of the values `keep` selects since `since_ns` (a wide value's words of one
    /// instant are one change) matched with their publications.
    fn matching(&self, since_ns: u64, keep: impl Fn(&RegisterKey) -> bool) -> MatchReport {
        let keys: Vec<(&String, &RegisterKey)> =
            self.topics.iter().filter(|(_, k)| keep(k)).collect();
        let topic_of: BTreeMap<&RegisterKey, &String> =
            keys.iter().map(|(t, k)| (*k, *t)).collect();
        let (_, changes) =
            value_histories(&self.initial, &self.changes(), keys.iter().map(|(_, k)| *k));
        let expected: Vec<ExpectedChange> = changes
            .into_iter()
            .filter(|c| c.mono_ns >= since_ns && c.origin == "control")
            .filter_map(|c| {
                Some(ExpectedChange {
                    mono_ns: c.mono_ns,
                    topic: topic_of.get(&c.key)?.to_string(),
                    payload: BenchLayout::fault_payload(&c.key, c.value),
                })
            })
            .collect();
        match_expected(&expected, &self.harness.publications(), since_ns)
    }

    /// The changes of event inputs and awaited wide values matched with their publications:
    /// each must be published exactly once.
    fn event_matching(&self, since_ns: u64) -> MatchReport {
        let awaited: Vec<RegisterKey> = self.awaited_slots.iter().map(FaultSlot::key).collect();
        self.matching(since_ns, |k| {
            k.register_type == "discrete" || awaited.contains(k)
        })
    }

    /// All value changes matched with publications (for the figures: lost counts values that
    /// changed twice between two reads, which no poller can see).
    fn value_matching(&self, since_ns: u64) -> MatchReport {
        self.matching(since_ns, |_| true)
    }

    fn assert_no_bad_value(&self, since_ns: u64, what: &str) -> usize {
        let report = self.history(since_ns);
        assert!(
            report.checked > 0,
            "{what}: no publication was checked (the check cannot fail)"
        );
        let shown: Vec<String> = report
            .bad
            .iter()
            .take(10)
            .map(|bad| {
                format!(
                    "{} = {:?} at +{} ms ({}; held {:?})",
                    bad.publication.topic,
                    bad.publication.payload,
                    bad.publication.mono_ns.saturating_sub(since_ns) / 1_000_000,
                    bad.reason,
                    bad.held
                )
            })
            .collect();
        assert!(
            report.bad.is_empty(),
            "{what}: {} of {} publications carried a value the simulator did not hold:\n{}\n{}",
            report.bad.len(),
            report.checked,
            shown.join("\n"),
            self.log_tail()
        );
        report.checked
    }
}

/// Scenario 1: noise on a bus of fast and classic devices whose values change all the time;
/// device 3 reports its wide values a word at a time (issue 15's independent emulator did).
fn noise_scenario(devices: u8, baud: u32) {
    let fault_time = if long_variant() {
        Duration::from_secs(300)
    } else {
        Duration::from_secs(25)
    };
    let mut run = Run::start_with(devices, baud, Link::Pty, false, true);
    let since = monotonic_ns();
    let stats_before = run.harness.bus_stats().expect("stats");
    let requests_before = stats_before["requests"].as_u64().unwrap_or(0);
    let contended_before = stats_before["contended_event_polls"].as_u64().unwrap_or(0);
    run.faults_on_all(&noise());
    run.drive(fault_time);
    run.faults_on_all(&json!({}));
    let faults_ended = Instant::now();
    // Convergence includes every toggled event input: each must come through.
    let recovery = run.wait_converged("after the faults");
    let recovery_from_end = faults_ended.elapsed();

    let checked = run.assert_no_bad_value(since, &format!("noise at {baud}"));
    let events = run.event_matching(since);
    assert!(events.changes > 0, "no event input changed");
    assert_eq!(
        (events.lost, events.wrong, events.duplicates),
        (0, 0, 0),
        "noise at {baud}: event changes lost, wrong or published twice: {events:?}\n{}",
        run.log_tail()
    );
    let values = run.value_matching(since);
    assert_eq!(values.wrong, 0, "{values:?}");
    let stats = run.harness.bus_stats().expect("stats");
    let requests = stats["requests"].as_u64().unwrap_or(0) - requests_before;
    // Several Fast Modbus devices with events answering the same poll (arbitration) under the
    // noise: the bus must really produce it for the run to prove anything about it.
    let contended = stats["contended_event_polls"].as_u64().unwrap_or(0) - contended_before;
    let max_contenders = stats["max_event_contenders"].as_u64().unwrap_or(0);
    assert!(
        contended > 0 && max_contenders >= 2,
        "no event poll had two devices with events: {stats}"
    );
    // Devices the noise made look dead for a while (their back-off is most of the recovery).
    let marked_offline = run.harness.daemon_log().matches("marked offline").count();
    eprintln!(
        "FIGURES noise devices={devices} baud={baud} faults_s={} requests={requests} \
         devices_marked_offline={marked_offline} contended_event_polls={contended} \
         max_event_contenders={max_contenders} value_changes={} publications_checked={checked} wrong_values=0 \
         event_changes={} events_lost={} event_duplicates={} value_duplicates={} \
         value_changes_unseen_between_reads={} recovery_after_faults_ms={} (converged {} ms)",
        fault_time.as_secs(),
        values.changes,
        events.changes,
        events.lost,
        events.duplicates,
        values.duplicates,
        values.lost,
        recovery_from_end.as_millis(),
        recovery.as_millis(),
    );
}

#[test]
fn noise_at_115200_publishes_only_held_values_and_every_event() {
    noise_scenario(8, 115_200);
}

#[test]
fn noise_at_9600_publishes_only_held_values_and_every_event() {
    noise_scenario(32, 9600);
}

#[test]
fn noise_at_115200_with_32_devices_publishes_only_held_values_and_every_event() {
    noise_scenario(32, 115_200);
}

fn control_error(run: &mut Run, address: u8, control: &str) -> Option<String> {
    run.read_publications();
    run.last_payload
        .get(&format!(
            "{}{control}/meta/error",
            BenchLayout::topic_prefix(address)
        ))
        .cloned()
}

fn device_error(run: &mut Run, address: u8) -> Option<String> {
    run.read_publications();
    run.last_payload
        .get(&format!("/devices/bench_{address}/meta/error"))
        .cloned()
}

fn wait_for(run: &mut Run, what: &str, mut check: impl FnMut(&mut Run) -> bool) {
    let found = wait_until(PATIENCE, EVERY, || check(run).then_some(()));
    assert!(found.is_some(), "{what}\n{}", run.log_tail());
}

/// Scenario 2: a device unplugged and replugged, rebooted, answering late, answering with
/// exceptions; no wrong value at any point, and the right values after each.
#[test]
fn device_faults_unplug_reboot_late_answers_exceptions() {
    let mut run = Run::start(4, 115_200);
    let since = monotonic_ns();

    // Unplugged: `r` on the device and its controls; values changed meanwhile come after.
    run.harness
        .control(&json!({"cmd": "unplug", "device": 2}))
        .expect("unplug");
    wait_for(&mut run, "unplugged device 2 flagged r", |run| {
        device_error(run, 2).as_deref() == Some("r")
            && control_error(run, 2, "R0").is_some_and(|e| e.contains('r'))
    });
    run.drive(Duration::from_secs(3));
    run.harness
        .control(&json!({"cmd": "replug", "device": 2}))
        .expect("replug");
    let unplug_recovery = run.wait_converged("after the replug");
    assert_eq!(device_error(&mut run, 2).as_deref(), Some(""));

    // Reboot of a Fast Modbus device that forgot its setup: setup written again, events
    // enabled again, values right after.
    run.set(1, "holding", SETUP_REGISTER, 0);
    let starts_before = device_listing(&run, 1)["starts"].as_u64().unwrap_or(0);
    run.harness
        .control(&json!({"cmd": "reboot", "device": 1}))
        .expect("reboot");
    wait_for(&mut run, "setup rewritten after the reboot", |run| {
        run.harness
            .registers(1, "holding", SETUP_REGISTER, 1)
            .is_ok_and(|v| v == [SETUP_VALUE])
    });
    wait_for(&mut run, "events enabled again after the reboot", |run| {
        device_listing(run, 1)["events_enabled"]
            .as_u64()
            .unwrap_or(0)
            > 0
    });
    assert_eq!(
        device_listing(&run, 1)["starts"].as_u64(),
        Some(starts_before + 1)
    );
    run.drive(Duration::from_secs(3));
    let reboot_recovery = run.wait_converged("after the reboot");

    // A device whose every answer comes late (past the configured timeout): its replies are
    // never credited to the next request.
    run.faults(3, &json!({"delay": 1.0, "delay_ms": 700}));
    run.drive(Duration::from_secs(8));
    run.faults(3, &json!({}));
    let late_recovery = run.wait_converged("after the late answers");

    // Exceptions (device busy): `r`, then cleared and the values right.
    run.faults(4, &json!({"exception": 1.0}));
    wait_for(&mut run, "device 4 answering exceptions flagged r", |run| {
        control_error(run, 4, "R0").is_some_and(|e| e.contains('r'))
    });
    run.drive(Duration::from_secs(3));
    run.faults(4, &json!({}));
    let exception_recovery = run.wait_converged("after the exceptions");

    let checked = run.assert_no_bad_value(since, "device faults");
    let events = run.event_matching(since);
    assert_eq!(
        (events.lost, events.wrong),
        (0, 0),
        "device faults: events {events:?}\n{}",
        run.log_tail()
    );
    eprintln!(
        "FIGURES device_faults publications_checked={checked} wrong_values=0 event_changes={} \
         events_lost={} event_duplicates={} recovery_ms: replug={} reboot={} late={} \
         exceptions={}",
        events.changes,
        events.lost,
        events.duplicates,
        unplug_recovery.as_millis(),
        reboot_recovery.as_millis(),
        late_recovery.as_millis(),
        exception_recovery.as_millis(),
    );
}

/// Scenario 2c: an address collision appears at runtime (device 4 is readdressed to 2, so two
/// devices answer at once), then goes away. The devices not involved never get a wrong value,
/// and once the collision is gone every value is right again.
#[test]
fn address_collision_at_runtime_spares_the_others_and_recovers() {
    let mut run = Run::start(4, 115_200);
    let since = monotonic_ns();
    let serial_of_4 = serial(4);
    run.harness
        .control(&json!({"cmd": "set_address", "serial": serial_of_4, "new_address": 2}))
        .expect("readdress device 4 to 2");
    // The two devices at 2 answer together: their replies collide on the line.
    run.drive(Duration::from_secs(8));
    run.harness
        .control(&json!({"cmd": "set_address", "serial": serial_of_4, "new_address": 4}))
        .expect("device 4 back at 4");
    let recovery = run.wait_converged("after the collision");
    // Devices 2 and 4 answered for each other: only the others are held to their history.
    run.topics
        .retain(|_, key| key.address != 2 && key.address != 4);
    let checked = run.assert_no_bad_value(since, "address collision");
    eprintln!(
        "FIGURES collision publications_checked_on_other_devices={checked} wrong_values=0 \
         recovery_ms={}",
        recovery.as_millis()
    );
}

fn device_listing(run: &Run, address: u8) -> Value {
    let list = run.harness.control(&json!({"cmd": "list"})).expect("list");
    list["devices"]
        .as_array()
        .and_then(|devices| {
            devices
                .iter()
                .find(|d| d["address"].as_u64() == Some(u64::from(address)))
        })
        .cloned()
        .unwrap_or(Value::Null)
}

/// A retained snapshot of the broker once two in a row agree (the daemon may be mid-publish).
fn settled_snapshot(run: &Run) -> BTreeMap<String, String> {
    let mut previous = BTreeMap::new();
    wait_until(PATIENCE, EVERY, || {
        let snapshot = run
            .harness
            .retained_snapshot(Duration::from_millis(300))
            .ok()?;
        let same = snapshot == previous && !snapshot.is_empty();
        previous = snapshot;
        same.then(|| previous.clone())
    })
    .expect("a settled retained state")
}

/// Scenario 3: the broker is killed and restarted without persistence: the whole retained state
/// comes back, with what changed while it was down.
#[test]
fn broker_killed_and_restarted_gets_the_whole_retained_state_back() {
    let mut run = Run::start(4, 115_200);
    let before = settled_snapshot(&run);
    assert!(
        before.len() > run.topics.len(),
        "retained state: {before:?}"
    );

    run.harness.kill_broker();
    // While the broker is away, a value changes on the bus.
    run.set(2, "input", 1, 60_000);
    let restarted = Instant::now();
    run.harness.restart_broker().expect("broker restarts");
    let mut expected = before.clone();
    expected.insert("/devices/bench_2/controls/R1".into(), "60000".into());
    let mut last = BTreeMap::new();
    let back = wait_until(PATIENCE, EVERY, || {
        last = settled_snapshot(&run);
        (last == expected).then_some(())
    });
    let missing: Vec<&String> = expected.keys().filter(|t| !last.contains_key(*t)).collect();
    let differing: Vec<(&String, &String, Option<&String>)> = expected
        .iter()
        .filter(|(t, p)| last.get(*t).is_some_and(|q| q != *p))
        .map(|(t, p)| (t, p, last.get(t)))
        .collect();
    let extra: Vec<&String> = last.keys().filter(|t| !expected.contains_key(*t)).collect();
    assert!(
        back.is_some(),
        "retained state after the restart differs: missing {missing:?}, differing \
         {differing:?}, extra {extra:?}\n{}",
        run.log_tail()
    );
    let restore = restarted.elapsed();

    eprintln!(
        "FIGURES broker retained_topics={} restored_after_restart_ms={}",
        expected.len(),
        restore.as_millis()
    );
}

/// Scenario 3b: a broker the daemon was connected to comes back asking for a password the daemon
/// does not have: the refusal must be named in the log (as it is when the first connection is
/// refused, tests/mqtt/logs.rs).
#[test]
fn broker_back_with_a_password_names_the_refused_credentials() {
    let mut run = Run::start(2, 115_200);
    run.harness
        .restart_broker_with_password("gateway", "secret")
        .expect("broker with a password");
    wait_for(&mut run, "refused credentials named in the log", |run| {
        run.harness
            .daemon_log()
            .contains("refused the user name or password")
    });
    assert!(run.harness.daemon_exit().is_none(), "the daemon gave up");
}

/// Scenario 2b: a device that answers half of its requests 600 ms late (past the timeout) and
/// the others at once. No value older than one already published may be published.
#[test]
fn device_answering_sometimes_late_never_publishes_an_older_value() {
    let mut run = Run::start(4, 115_200);
    let since = monotonic_ns();
    run.faults(3, &json!({"delay": 0.5, "delay_ms": 600}));
    run.drive(Duration::from_secs(20));
    run.faults(3, &json!({}));
    run.wait_converged("after the late answers");
    run.assert_no_bad_value(since, "sometimes late answers");
}

/// Scenario 2c: a second master on the pair (wb-mqtt-serial started again by the web UI's
/// config editor, a laptop's Modbus tool) reads registers 10–15 of the classic device at 2,
/// the same shape as the daemon's read of its registers 0–5, while the world changes. The
/// device takes its time to answer (15 ms; 40 ms at 9600), so the daemon's request can go in
/// between the other master's request and its reply, which then looks like the answer to the
/// daemon's. The other master's request is also byte for byte one the daemon sends itself
/// (wb-mqtt-serial with the same template polls exactly so). A bus the daemon keeps busy
/// (Fast Modbus events polled back to back) leaves a second master nothing but collisions;
/// here the daemon reads each register at most every 100 ms (1 s at 9600), classic only, so
/// the bus has silences and most of the other master's requests are answered; at 9600 it also
/// waits for silence before it talks. None of its replies may be published as the daemon's
/// values; the log names the other master; once it stops, everything converges.
fn second_master_scenario(baud: u32) {
    let slow = baud < 19_200;
    let turnaround_us = if slow { 40_000 } else { 15_000 };
    let port = json!({"fast_modbus": false, "read_rate_limit_ms": if slow { 1000 } else { 100 }});
    let mut run = Run::start_edited(4, baud, Link::Pty, false, &port, |entries| {
        for entry in entries.iter_mut().filter(|e| e["address"] == 2) {
            entry["turnaround_us"] = json!(turnaround_us);
        }
    });
    let since = monotonic_ns();
    let sim_before = run.harness.bus_stats().expect("stats");
    let other = run
        .harness
        .control(
            &json!({"cmd": "other_master", "device": 2, "type": "input", "address": 10,
                         "count": 6, "every_ms": 150, "listen": slow}),
        )
        .expect("other_master");
    assert_eq!(other["ok"], true, "{other}");
    run.drive(Duration::from_secs(20));
    run.harness
        .control(&json!({"cmd": "other_master"}))
        .expect("other_master off");
    run.wait_converged("after the other master stopped");
    let sim = run.harness.bus_stats().expect("stats");
    let answered = sim["other_master_answered"].as_u64().unwrap_or(0)
        - sim_before["other_master_answered"].as_u64().unwrap_or(0);
    // The other master's requests really reached device 2 and were answered, or the run proves
    // nothing.
    assert!(
        answered >= 20,
        "the other master got {answered} answers: {sim}"
    );
    let checked = run.assert_no_bad_value(since, &format!("a second master at {baud}"));
    let log = run.harness.daemon_log();
    eprintln!(
        "FIGURES second_master baud={baud} other_master_requests={} answered={answered} \
         publications_checked={checked} wrong_values=0",
        sim["other_master_requests"].as_u64().unwrap_or(0)
            - sim_before["other_master_requests"].as_u64().unwrap_or(0),
    );
    assert!(
        log.contains("another master is polling this bus"),
        "the log does not name the other master\n{}",
        run.log_tail()
    );
}

#[test]
fn a_second_master_at_115200_never_has_its_replies_published() {
    second_master_scenario(115_200);
}

#[test]
fn a_second_master_at_9600_never_has_its_replies_published() {
    second_master_scenario(9600);
}

/// Scenario 4: a short soak under noise, sampling the daemon's RSS, CPU and open file
/// descriptors every 10 s: no descriptor growth, bounded memory growth.
#[test]
fn soak_under_faults_keeps_descriptors_and_memory_flat() {
    let length = if long_variant() {
        Duration::from_secs(30 * 60)
    } else {
        Duration::from_secs(70)
    };
    let mut run = Run::start(8, 115_200);
    let since = monotonic_ns();
    run.faults_on_all(&noise());
    let mut samples = Vec::new();
    let started = Instant::now();
    while started.elapsed() < length {
        let stats = run.harness.daemon_stats().expect("daemon running");
        let fds = run.harness.daemon_open_fds().expect("daemon fds");
        samples.push((started.elapsed().as_secs(), stats.rss_kib, stats.cpu, fds));
        run.drive(Duration::from_secs(10));
    }
    let stats = run.harness.daemon_stats().expect("daemon running");
    let fds = run.harness.daemon_open_fds().expect("daemon fds");
    samples.push((started.elapsed().as_secs(), stats.rss_kib, stats.cpu, fds));
    run.faults_on_all(&json!({}));
    run.wait_converged("after the soak");
    let checked = run.assert_no_bad_value(since, "soak");

    for (at, rss, cpu, fds) in &samples {
        eprintln!(
            "FIGURES soak t={at}s rss_kib={rss} cpu_ms={} fds={fds}",
            cpu.as_millis()
        );
    }
    eprintln!("FIGURES soak publications_checked={checked} wrong_values=0");
    // The first sample is taken once the daemon has published everything (warm); after it,
    // descriptors must not grow and memory may grow only a little.
    let (_, first_rss, _, first_fds) = samples[0];
    let (_, last_rss, _, last_fds) = samples[samples.len() - 1];
    let max_fds = samples.iter().map(|s| s.3).max().unwrap_or(0);
    assert!(max_fds <= first_fds, "open descriptors grew: {samples:?}");
    assert!(last_fds <= first_fds, "{samples:?}");
    assert!(
        last_rss <= first_rss + first_rss / 2 + 4096,
        "RSS grew from {first_rss} KiB to {last_rss} KiB: {samples:?}"
    );
}

/// Drives the simulated world until `check` holds (bounded by the patience).
fn drive_until(run: &mut Run, what: &str, mut check: impl FnMut(&mut Run) -> bool) {
    let deadline = Instant::now() + PATIENCE;
    while !check(run) {
        assert!(Instant::now() < deadline, "{what}\n{}", run.log_tail());
        run.drive(Duration::from_millis(100));
    }
}

/// When the daemon wrote the setup value into the setup register of `address` (the simulator's
/// change log: a write by the master that changed it).
fn setup_writes(run: &Run, address: u8) -> Vec<u64> {
    run.changes()
        .iter()
        .filter(|c| {
            c.address == address
                && c.origin == "master"
                && c.register_type == "holding"
                && c.register == SETUP_REGISTER
                && c.value == SETUP_VALUE
        })
        .map(|c| c.mono_ns)
        .collect()
}

/// For a failure message: the reboot rounds and every change of the setup register of the
/// devices in `missing`, on one clock.
fn setup_register_history(
    run: &Run,
    rounds: &BTreeMap<u8, Vec<Vec<u64>>>,
    missing: &[(u8, u64)],
) -> String {
    let mut lines = Vec::new();
    for address in missing.iter().map(|&(a, _)| a).collect::<BTreeSet<u8>>() {
        lines.push(format!(
            "device {address}: reboot rounds (mono ns) {:?}",
            rounds.get(&address)
        ));
        for change in run.changes().iter().filter(|c| {
            c.address == address && c.register_type == "holding" && c.register == SETUP_REGISTER
        }) {
            lines.push(format!(
                "  {} {} -> {}",
                change.mono_ns, change.origin, change.value
            ));
        }
    }
    lines.join("\n")
}

/// Reboot rounds (the times of one device's reboots in a round) not followed by a setup write
/// after the round's last reboot and before the next round began: which device, when.
fn reboots_without_setup(run: &Run, rounds: &BTreeMap<u8, Vec<Vec<u64>>>) -> Vec<(u8, u64)> {
    let mut missing = Vec::new();
    for (&address, rounds_of_device) in rounds {
        let writes = setup_writes(run, address);
        for (index, round) in rounds_of_device.iter().enumerate() {
            let last = round.last().copied().unwrap_or(0);
            let next = rounds_of_device
                .get(index + 1)
                .and_then(|r| r.first())
                .copied()
                .unwrap_or(u64::MAX);
            if !writes.iter().any(|&w| w >= last && w <= next) {
                missing.push((address, last));
            }
        }
    }
    missing
}

fn all_devices_flagged(run: &mut Run) -> bool {
    (1..=run.devices()).all(|address| device_error(run, address).as_deref() == Some("r"))
}

/// Scenario 2d: reboot storms while values change. The Fast Modbus devices (1, 3) reboot over
/// and over, forgetting their setup register each time: their "I rebooted" event must make the
/// daemon write the setup again and enable events again, every time. The classic devices (2, 4)
/// cannot tell: they reboot while away long enough to be marked offline (a classic device that
/// reboots faster than its device timeout leaves no trace on the bus, in wb-mqtt-serial too),
/// and their setup must be written again when they come back. Nothing wrong is published.
#[test]
fn reboot_storm_rewrites_the_setup_every_time_and_publishes_nothing_wrong() {
    let (fast_rounds, classic_rounds) = if long_variant() { (60, 10) } else { (8, 2) };
    let mut run = Run::start(4, 115_200);
    let since = monotonic_ns();
    // Per device, its rounds of reboots (one or two reboots each) in order.
    let mut reboots: BTreeMap<u8, Vec<Vec<u64>>> = BTreeMap::new();
    let mut reboot = |run: &mut Run, address: u8, new_round: bool| {
        // Stamped before the setup is lost: a write after the stamp that the loss overwrites
        // cannot pass for the rewrite, since the wait below wants the register back at 7.
        let at = monotonic_ns();
        run.set(address, "holding", SETUP_REGISTER, 0);
        let rounds = reboots.entry(address).or_default();
        if new_round || rounds.is_empty() {
            rounds.push(Vec::new());
        }
        if let Some(round) = rounds.last_mut() {
            round.push(at);
        }
        run.harness
            .control(&json!({"cmd": "reboot", "serial": serial(address)}))
            .expect("reboot");
    };
    let setup_back = |run: &mut Run, addresses: &[u8]| {
        addresses.iter().all(|&address| {
            run.harness
                .registers(address, "holding", SETUP_REGISTER, 1)
                .is_ok_and(|v| v == [SETUP_VALUE])
        })
    };

    let mut fast_recovery = Vec::new();
    for round in 0..fast_rounds {
        reboot(&mut run, 1, true);
        reboot(&mut run, 3, true);
        if round % 2 == 1 {
            // A storm: the device reboots again while the daemon may be setting it up.
            run.drive(Duration::from_millis(30));
            reboot(&mut run, 1, false);
        }
        let rebooted = Instant::now();
        // Every round ends with both set up again: the setup written and events enabled (the
        // simulator forgets its event settings on a reboot).
        drive_until(&mut run, "Fast Modbus devices set up again", |run| {
            setup_back(run, &[1, 3])
                && [1, 3].iter().all(|&address| {
                    device_listing(run, address)["events_enabled"]
                        .as_u64()
                        .unwrap_or(0)
                        > 0
                })
        });
        fast_recovery.push(rebooted.elapsed());
    }
    let mut classic_recovery = Vec::new();
    for _ in 0..classic_rounds {
        for address in [2, 4] {
            run.harness
                .control(&json!({"cmd": "unplug", "serial": serial(address)}))
                .expect("unplug");
        }
        drive_until(&mut run, "rebooting classic devices flagged r", |run| {
            [2, 4]
                .iter()
                .all(|&address| device_error(run, address).as_deref() == Some("r"))
        });
        for address in [2, 4] {
            reboot(&mut run, address, true);
            run.harness
                .control(&json!({"cmd": "replug", "serial": serial(address)}))
                .expect("replug");
        }
        let back = Instant::now();
        drive_until(&mut run, "classic devices set up again", |run| {
            setup_back(run, &[2, 4])
        });
        classic_recovery.push(back.elapsed());
    }
    let recovery = run.wait_converged("after the reboot storm");

    let missing = reboots_without_setup(&run, &reboots);
    assert!(
        missing.is_empty(),
        "reboots not followed by a setup write: {missing:?}\n{}\n{}",
        setup_register_history(&run, &reboots, &missing),
        run.log_tail()
    );
    let checked = run.assert_no_bad_value(since, "reboot storm");
    let events = run.event_matching(since);
    assert_eq!(
        (events.lost, events.wrong),
        (0, 0),
        "reboot storm: events {events:?}\n{}",
        run.log_tail()
    );
    let count = |addresses: &[u8]| -> (usize, usize) {
        addresses.iter().fold((0, 0), |(r, w), a| {
            (
                r + reboots
                    .get(a)
                    .map_or(0, |rounds| rounds.iter().map(Vec::len).sum::<usize>()),
                w + setup_writes(&run, *a)
                    .iter()
                    .filter(|&&at| at >= since)
                    .count(),
            )
        })
    };
    let ms = |times: &[Duration]| {
        let max = times.iter().max().copied().unwrap_or_default();
        let min = times.iter().min().copied().unwrap_or_default();
        format!("{}-{}", min.as_millis(), max.as_millis())
    };
    eprintln!(
        "FIGURES reboot_storm fast_reboots/setup_writes={:?} classic_reboots/setup_writes={:?} \
         publications_checked={checked} wrong_values=0 event_changes={} events_lost={} \
         event_duplicates={} setup_back_ms: fast={} classic_after_replug={} converged_ms={}",
        count(&[1, 3]),
        count(&[2, 4]),
        events.changes,
        events.lost,
        events.duplicates,
        ms(&fast_recovery),
        ms(&classic_recovery),
        recovery.as_millis(),
    );
}

/// Cuts the link under the daemon (`link_down`) while values change, until every device is
/// flagged `r`; brings it back; waits for the simulator's values. Recovery after the link came
/// back.
fn link_outage(run: &mut Run) -> Duration {
    run.harness
        .control(&json!({"cmd": "link_down"}))
        .expect("link_down");
    drive_until(
        run,
        "every device flagged r while the link is away",
        all_devices_flagged,
    );
    run.drive(Duration::from_secs(1));
    run.harness
        .control(&json!({"cmd": "link_up"}))
        .expect("link_up");
    run.wait_converged("after the link came back")
}

/// Scenario 5: the port vanishes under the daemon (a USB adapter unplugged: the pty and its
/// symlink disappear, the open descriptor fails) and comes back. Devices are flagged `r` while
/// it is away, the daemon reopens the port by itself (same process) and every value is right
/// after; nothing wrong is published.
fn port_outages(link: Link, what: &str) {
    let rounds = if long_variant() { 10 } else { 2 };
    let mut run = Run::start_on(4, 115_200, link);
    let pid = run.harness.daemon_pid();
    let since = monotonic_ns();
    let mut recoveries = Vec::new();
    for _ in 0..rounds {
        run.drive(Duration::from_secs(2));
        recoveries.push(link_outage(&mut run));
    }
    let mut drop_recoveries = Vec::new();
    if link != Link::Pty {
        // The gateway drops the connection and takes new ones at once.
        for _ in 0..rounds {
            run.drive(Duration::from_secs(1));
            run.harness
                .control(&json!({"cmd": "link_drop"}))
                .expect("link_drop");
            run.drive(Duration::from_secs(1));
            drop_recoveries.push(run.wait_converged("after the dropped connection"));
        }
    }
    assert!(run.harness.daemon_exit().is_none(), "the daemon exited");
    assert_eq!(run.harness.daemon_pid(), pid);
    let checked = run.assert_no_bad_value(since, what);
    let events = run.event_matching(since);
    assert_eq!(
        (events.lost, events.wrong),
        (0, 0),
        "{what}: events {events:?}\n{}",
        run.log_tail()
    );
    let reopened = run.harness.daemon_log().matches("port open").count();
    assert!(
        reopened > rounds,
        "{what}: the port was opened {reopened} times for {rounds} outages"
    );
    let ms = |times: &[Duration]| -> Vec<u128> { times.iter().map(Duration::as_millis).collect() };
    eprintln!(
        "FIGURES {what} outages={rounds} port_opened={reopened} publications_checked={checked} \
         wrong_values=0 event_changes={} events_lost={} event_duplicates={} \
         converged_after_link_back_ms={:?} converged_after_dropped_connection_ms={:?}",
        events.changes,
        events.lost,
        events.duplicates,
        ms(&recoveries),
        ms(&drop_recoveries),
    );
}

#[test]
fn serial_port_vanishing_and_returning_is_reopened_without_a_restart() {
    port_outages(Link::Pty, "pty_outage");
}

#[test]
fn rtu_over_tcp_gateway_dropping_the_connection_is_reconnected() {
    port_outages(Link::RtuOverTcp, "rtu_over_tcp_outage");
}

#[test]
fn modbus_tcp_gateway_dropping_the_connection_is_reconnected() {
    port_outages(Link::ModbusTcp, "modbus_tcp_outage");
}

/// Scenario 3c: the broker is reached over TLS with a client certificate; under bus noise it is
/// killed and restarted twice (a value changing while it is away). The daemon reconnects over
/// TLS by itself, the broker gets every value back, and nothing wrong is published.
#[test]
fn tls_broker_killed_and_restarted_under_noise_gets_everything_back() {
    let rounds = if long_variant() { 10 } else { 2 };
    let mut run = Run::start_with(4, 115_200, Link::Pty, true, false);
    let since = monotonic_ns();
    run.faults_on_all(&noise());
    let mut restores = Vec::new();
    for round in 0..rounds {
        run.drive(Duration::from_secs(3));
        run.harness.kill_broker();
        run.drive(Duration::from_secs(1));
        // The last change while the broker is away; nothing changes it until it is published.
        run.set(2, "input", 1, 60_000 + round);
        run.harness.restart_broker().expect("broker restarts");
        let restarted = Instant::now();
        wait_for(
            &mut run,
            "the value changed while the broker was away",
            |run| {
                run.read_publications();
                run.last_payload
                    .get("/devices/bench_2/controls/R1")
                    .is_some_and(|p| *p == (60_000 + round).to_string())
            },
        );
        restores.push(restarted.elapsed().as_millis());
    }
    run.faults_on_all(&json!({}));
    let recovery = run.wait_converged("after the broker restarts");
    let connections = run
        .harness
        .daemon_log()
        .matches("connected to the MQTT broker")
        .count();
    assert!(
        connections > usize::from(rounds),
        "the daemon connected {connections} times for {rounds} broker restarts"
    );
    let checked = run.assert_no_bad_value(since, "TLS broker restarts");
    let events = run.event_matching(since);
    assert_eq!(
        (events.lost, events.wrong),
        (0, 0),
        "TLS broker restarts: events {events:?}\n{}",
        run.log_tail()
    );
    eprintln!(
        "FIGURES tls_broker restarts={rounds} connections={connections} \
         publications_checked={checked} wrong_values=0 event_changes={} events_lost={} \
         changed_value_back_after_restart_ms={restores:?} converged_after_faults_ms={}",
        events.changes,
        events.lost,
        recovery.as_millis(),
    );
}
