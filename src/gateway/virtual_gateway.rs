//! The whole gateway on virtual time, in one process: the port scheduler, the reply parser, the
//! simulator's pure [`Bus`], the device models and the MQTT planner, on a fake clock, with no
//! threads, no pty and no broker. A scenario runs in milliseconds and is exact: "no reply" and
//! "published within" are facts of the virtual wire, not of a busy machine.
//!
//! The wire between scheduler and bus is [`VirtualGateway::transact`]: the daemon's own sans-IO
//! transport ([`Exchange`]: guard interval, reply window, parser, reply vs garbage vs silence)
//! driven on virtual time, with the bus saying which bytes come back and when (wire times of
//! `protocol::timing`). Only the IO is replaced.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use super::device_model::{apply_port_events, ChannelIndexes, DeviceModel};
use super::port_plan::port_plan;
use crate::config::parse::SourceText;
use crate::config::TemplateLibrary;
use crate::device_updates::{ControlWrite, DeviceUpdate, Repeats};
use crate::mqtt::TopicScheme;
use crate::mqtt::{MqttAction, PlannerSettings, PublicationPlanner, UnchangedPolicy, WriteOutcome};
use crate::port::{NextStep, PortScheduler, ReplyTiming, Transaction, TransactionOutcome};
use crate::protocol::{LineSettings, RegisterType, RequestBody, RequestPdu};
use crate::sim::bus::Bus;
use crate::sim::bus_file::{build_device, parse_line, DeviceEntry, TemplateSource};
use crate::sim::MasterLine;
use crate::transport::exchange::{Exchange, LinkConfig};

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// One MQTT publication, at a virtual time.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Published {
    pub at: Duration,
    pub topic: String,
    pub payload: String,
}

pub struct VirtualGateway {
    /// Virtual time since start.
    pub now: Duration,
    epoch: Instant,
    line: LineSettings,
    exchange: Exchange,
    /// Silence before a request, per device (the port task's rule).
    guard_intervals: crate::port::GuardIntervals,
    scheduler: PortScheduler,
    models: Vec<DeviceModel>,
    planner: PublicationPlanner,
    pub bus: Bus,
    /// The broker's retained topics.
    pub retained: BTreeMap<String, String>,
    /// Every publication, in order.
    pub published: Vec<Published>,
    /// What the sinks were handed (the stdout sink prints these).
    pub updates: Vec<(Duration, DeviceUpdate)>,
    /// Since when the port has been unusable (`None`: it works).
    port_closed_since: Option<Duration>,
    /// Every transaction on the wire, in order.
    pub wire_log: Vec<WireRecord>,
    /// Bytes that reach the master after their transaction ended (a reply later than its
    /// window) stay on the line for the next one, as on a real port: those that arrive before
    /// the next request is written are flushed (or seen in the silence before it), the others
    /// land in its reply window. Off by default: each transaction then hears only its own
    /// request's answer, and bytes after its end are lost.
    pub carry_late_bytes: bool,
    /// What is still on its way to the master (see [`Self::carry_late_bytes`]), in time order.
    late_bytes: std::collections::VecDeque<(Duration, u8)>,
    /// A second master on the bus (with [`Self::carry_late_bytes`]): its requests and the
    /// devices' answers to them reach this master's port as any bytes on the line.
    pub other_master: Option<OtherMaster>,
    /// When this master's last transaction ended (the other master's requests before it
    /// collided with it).
    line_free_at: Duration,
    /// Prints every transaction (diagnosis).
    pub trace: bool,
    /// Times the scheduler said to wait until a time already come (a driver would spin).
    pub spins: u64,
}

/// One transaction on the virtual wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireRecord {
    pub at: Duration,
    pub ended: Duration,
    /// The request's address (0xFD: a broadcast event poll).
    pub address: u8,
    pub fast: bool,
    /// A valid reply came back.
    pub answered: bool,
    /// Registers (or bits) a classic read asked for; 0 for any other request.
    pub registers_read: u16,
}

impl VirtualGateway {
    /// A port at `line` ("115200 8N2") with the shipped templates `devices` (template, slave
    /// id) on it, configured and simulated alike; Fast Modbus on.
    pub fn new(line: &str, devices: &[(&str, u8)]) -> Self {
        Self::with_fast_modbus(line, devices, true)
    }

    /// [`Self::new`] with the site-wide Fast Modbus switch (`fast_modbus` in the config).
    pub fn with_fast_modbus(line: &str, devices: &[(&str, u8)], fast_modbus: bool) -> Self {
        let entries: Vec<Value> = devices
            .iter()
            .map(|&(template, address)| {
                json!({
                    "template": template,
                    "address": address,
                    "serial": 0xFE00_0000u32 + u32::from(address),
                    "line": line,
                })
            })
            .collect();
        Self::from_bus(
            line,
            &entries,
            &repo("templates"),
            fast_modbus,
            1,
            Repeats::All,
        )
    }

    /// A port at `line` with the simulator's bus `entries` (as in a bus file: `template` a
    /// `device_type` found in `templates_dir`, `address`, `fast`, …), each configured with its
    /// template and slave id; `seed` drives the simulator's injected faults. The device models
    /// report `repeats` besides the changes: the scenarios count reads by the values reported
    /// ([`Self::updates`]), so they ask for every one ([`Repeats::All`]); the planner publishes
    /// changes only, as the daemon's default (`max_unchanged_interval` -1, [`Repeats::None`]).
    pub fn from_bus(
        line: &str,
        entries: &[Value],
        templates_dir: &Path,
        fast_modbus: bool,
        seed: u64,
        repeats: Repeats,
    ) -> Self {
        let settings = parse_line(line).expect("a line like 115200 8N2");
        let mut templates = TemplateSource::new(templates_dir, templates_dir);
        let mut devices = Vec::new();
        let simulated = entries
            .iter()
            .map(|entry| {
                let entry: DeviceEntry =
                    serde_json::from_value(entry.clone()).expect("a bus entry");
                let template = entry.template.clone().expect("a template");
                devices.push((template, entry.address));
                build_device(&entry, &mut templates).expect("a simulated device")
            })
            .collect();
        let config = json!({
            "ports": [{
                "path": "/dev/virtual",
                "baud_rate": settings.baud,
                "parity": settings.parity.letter().to_string(),
                "data_bits": settings.data_bits,
                "stop_bits": settings.stop_bits,
                "devices": devices
                    .iter()
                    .map(|(template, address)| json!({"device_type": template, "slave_id": address}))
                    .collect::<Vec<Value>>(),
            }]
        });
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("virtual.json"), &config.to_string()),
            false,
        )
        .expect("the config loads");
        let library = TemplateLibrary::load_dirs(&[templates_dir.to_path_buf()]);
        let port = crate::device::resolve_config(&loaded, &library)
            .expect("the config resolves")
            .remove(0);
        let plan = port_plan(&port, fast_modbus);
        let mut gateway = Self {
            now: Duration::ZERO,
            epoch: Instant::now(),
            line: plan.settings.line,
            // As `Transport::open` sets it for a serial port.
            exchange: Exchange::new(LinkConfig::serial(plan.settings.line)),
            guard_intervals: plan.settings.guard_intervals.clone(),
            scheduler: PortScheduler::new(plan.settings, plan.devices),
            models: Vec::new(),
            planner: PublicationPlanner::new(PlannerSettings {
                topics: TopicScheme::new("", "rtu2mqtt").expect("default topics"),
                unchanged: UnchangedPolicy::OnChange,
                discovery: None,
                clear_discovery_on_exit: false,
            }),
            bus: Bus::new(simulated, seed),
            retained: BTreeMap::new(),
            published: Vec::new(),
            updates: Vec::new(),
            port_closed_since: None,
            wire_log: Vec::new(),
            carry_late_bytes: false,
            late_bytes: std::collections::VecDeque::new(),
            other_master: None,
            line_free_at: Duration::ZERO,
            trace: false,
            spins: 0,
        };
        // As the daemon builds them: one register index per channel list.
        let mut indexes = ChannelIndexes::default();
        for (index, device) in port.devices.into_iter().enumerate() {
            let device = Arc::new(device);
            gateway.sink(vec![DeviceUpdate::Added(Arc::clone(&device))]);
            gateway
                .models
                .push(DeviceModel::sharing(device, index, repeats, &mut indexes));
        }
        gateway
    }

    /// Runs the gateway until `now + duration`.
    pub fn run_for(&mut self, duration: Duration) {
        let end = self.now + duration;
        while self.now < end {
            if let Some(since) = self.port_closed_since {
                // As the port task does while it cannot open the port: wake every 500 ms.
                let events = self.scheduler.port_unavailable(self.now, since);
                self.hand_to_models(events);
                self.now = (self.now + Duration::from_millis(500)).min(end);
                continue;
            }
            match self.scheduler.next(self.now) {
                NextStep::Transmit(transaction) => {
                    if let Some(other) = &mut self.other_master {
                        other.heard(&transaction.request);
                    }
                    let (outcome, timing, done) = self.transact(&transaction);
                    if self.trace {
                        eprintln!(
                            "TX {:.6}..{:.6} {} to={:?} late={:?} -> {} {:?} (on the line: {})",
                            self.now.as_secs_f64(),
                            done.as_secs_f64(),
                            transaction
                                .request
                                .encode()
                                .map(|b| crate::protocol::hex(&b))
                                .unwrap_or_default(),
                            transaction.first_byte_timeout,
                            transaction.late_window,
                            match &outcome {
                                TransactionOutcome::Reply(r) => format!("{r:?}"),
                                other => format!("{other:?}"),
                            },
                            timing,
                            self.late_bytes_summary()
                        );
                    }
                    self.wire_log.push(WireRecord {
                        at: self.now,
                        ended: done,
                        address: transaction.request.address,
                        fast: transaction.request.is_fast(),
                        answered: matches!(outcome, TransactionOutcome::Reply(_)),
                        registers_read: match &transaction.request.body {
                            RequestBody::Classic(
                                RequestPdu::ReadCoils { count, .. }
                                | RequestPdu::ReadDiscreteInputs { count, .. }
                                | RequestPdu::ReadHoldingRegisters { count, .. }
                                | RequestPdu::ReadInputRegisters { count, .. },
                            ) => *count,
                            _ => 0,
                        },
                    });
                    self.now = done;
                    let events = self.scheduler.complete_timed(self.now, outcome, timing);
                    self.hand_to_models(events);
                }
                NextStep::Wait { until } => {
                    if until <= self.now {
                        self.spins += 1;
                        if self.trace && self.spins % 10_000 == 1 {
                            eprintln!("SPIN at {:?} until {until:?}", self.now);
                        }
                    }
                    // At least a microsecond on, never past `end` (which may be less than a
                    // microsecond away: `clamp` would panic).
                    self.now = until.max(self.now + Duration::from_micros(1)).min(end);
                }
            }
        }
    }

    /// Runs until `topic` holds `payload` (retained), at most `limit`; returns when it did.
    pub fn run_until(&mut self, topic: &str, payload: &str, limit: Duration) -> Option<Duration> {
        let end = self.now + limit;
        while self.now < end {
            if self.retained.get(topic).map(String::as_str) == Some(payload) {
                return Some(self.now);
            }
            self.run_for(Duration::from_millis(1));
        }
        (self.retained.get(topic).map(String::as_str) == Some(payload)).then_some(self.now)
    }

    /// The port cannot be opened from now on (`false`), or works again.
    pub fn set_port_usable(&mut self, usable: bool) {
        self.port_closed_since = if usable { None } else { Some(self.now) };
    }

    /// A client publishes `payload` on `/devices/<device>/controls/<control>/on`; the write
    /// goes the way the daemon routes it (planner, then the device's model, then the queue).
    pub fn publish_on(&mut self, device: &str, control: &str, payload: &[u8]) {
        let topic = format!("/devices/{device}/controls/{control}/on");
        let WriteOutcome::Accepted(write) = self.planner.on_message(&topic, payload, false) else {
            return;
        };
        self.write(write);
    }

    /// As the port task takes a write: the model checks and encodes it, the scheduler queues it.
    fn write(&mut self, write: ControlWrite) {
        let Some(model) = self.models.iter_mut().find(|m| m.id() == write.device_id) else {
            return;
        };
        let mut updates = Vec::new();
        let mut refused = Vec::new();
        if let Ok(register_writes) =
            model.take_write(&write.control_id, &write.payload, &mut updates)
        {
            for register_write in register_writes {
                refused.extend(self.scheduler.queue_write(self.now, register_write));
            }
        }
        self.sink(updates);
        self.hand_to_models(refused);
    }

    /// The bytes still on their way to the master: per run of bytes less than 5 ms apart, when
    /// its first arrives and the bytes ("at+hex").
    fn late_bytes_summary(&self) -> String {
        // (first, last, bytes)
        let mut runs: Vec<(Duration, Duration, Vec<u8>)> = Vec::new();
        for &(at, byte) in &self.late_bytes {
            match runs.last_mut() {
                Some((_, last, bytes)) if at <= *last + Duration::from_millis(5) => {
                    *last = at;
                    bytes.push(byte);
                }
                _ => runs.push((at, at, vec![byte])),
            }
        }
        runs.iter()
            .map(|(first, _, bytes)| {
                format!("{:.4}+{}", first.as_secs_f64(), crate::protocol::hex(bytes))
            })
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// The physical world changes a register of the simulated device at `address`.
    pub fn change(&mut self, address: u8, register_type: RegisterType, start: u16, values: &[u16]) {
        let index = self.device_index(address);
        self.bus
            .write_register(index, register_type, start, values, self.now)
            .expect("a register the device has");
    }

    /// A register of the simulated device at `address`.
    /// What was published, as the bench's checks take it (everything is retained here).
    pub fn publications(&self) -> Vec<crate::bench::harness::Publication> {
        self.published
            .iter()
            .map(|p| crate::bench::harness::Publication {
                mono_ns: u64::try_from(p.at.as_nanos()).unwrap_or(u64::MAX),
                topic: p.topic.clone(),
                payload: p.payload.clone(),
                retain: true,
            })
            .collect()
    }

    pub fn register(&self, address: u8, register_type: RegisterType, at: u16) -> Option<u16> {
        let device = self.bus.devices().get(self.device_index(address))?;
        device.registers().get(register_type, at)
    }

    pub fn set_plugged(&mut self, address: u8, plugged: bool) {
        let index = self.device_index(address);
        if let Some(device) = self.bus.device_mut(index) {
            device.plugged = plugged;
        }
    }

    /// The faults the simulated device at `address` injects into its replies from now on.
    pub fn set_faults(&mut self, address: u8, faults: crate::sim::faults::Faults) {
        let index = self.device_index(address);
        if let Some(device) = self.bus.device_mut(index) {
            device.faults = faults;
        }
    }

    /// Every simulated device at `address` restarts (several: a shared address).
    pub fn reboot_all_at(&mut self, address: u8) {
        for index in 0..self.bus.devices().len() {
            if let Some(device) = self
                .bus
                .device_mut(index)
                .filter(|d| d.address() == address)
            {
                device.reboot();
            }
        }
    }

    /// The simulated device restarts: its event settings are gone.
    pub fn reboot(&mut self, address: u8) {
        let index = self.device_index(address);
        if let Some(device) = self.bus.device_mut(index) {
            device.reboot();
        }
    }

    /// Payloads published on `topic` since `since`, in order.
    pub fn published_on(&self, topic: &str, since: Duration) -> Vec<&str> {
        self.published
            .iter()
            .filter(|p| p.topic == topic && p.at >= since)
            .map(|p| p.payload.as_str())
            .collect()
    }

    fn device_index(&self, address: u8) -> usize {
        self.bus
            .devices()
            .iter()
            .position(|d| d.address() == address)
            .expect("a simulated device at that address")
    }

    fn hand_to_models(&mut self, events: Vec<crate::port::PortEvent>) {
        let mut updates = Vec::new();
        apply_port_events(&mut self.models, events, &mut updates);
        crate::gateway::device_model::stop_unsupported_reads(
            &mut self.models,
            &mut self.scheduler,
            self.now,
        );
        self.sink(updates);
    }

    fn sink(&mut self, updates: Vec<DeviceUpdate>) {
        for update in updates {
            self.updates.push((self.now, update.clone()));
            for action in self.planner.handle(update, self.epoch + self.now) {
                if let MqttAction::Publish(publication) = action {
                    if publication.retain {
                        if publication.payload.is_empty() {
                            self.retained.remove(&publication.topic);
                        } else {
                            self.retained
                                .insert(publication.topic.clone(), publication.payload.clone());
                        }
                    }
                    self.published.push(Published {
                        at: self.now,
                        topic: publication.topic,
                        payload: publication.payload,
                    });
                }
            }
        }
    }

    /// One transaction on the virtual wire: what came back, its timing, and when it ended.
    /// The driver loop of `transport::exchange`, with the bus in place of the serial port: the
    /// request is heard at once, bytes arrive at their stop bits' times (a frame's end 4
    /// characters later, the UART's receive timeout), and are read one by one, or in one go
    /// where the exchange asks for a batch read.
    fn transact(
        &mut self,
        transaction: &Transaction,
    ) -> (TransactionOutcome, ReplyTiming, Duration) {
        let mut now = self.now;
        // Where this master's traffic leaves no silence for the other master's requests: all
        // before the last transaction's end, then this request and its answer.
        let mut busy = vec![(Duration::ZERO, self.line_free_at)];
        let mut late_bytes = std::mem::take(&mut self.late_bytes);
        self.other_master_until(now, &busy, &mut late_bytes);
        self.late_bytes = late_bytes;
        self.exchange
            .set_guard_interval(self.guard_intervals.before(transaction.request.address));
        if self.exchange.start(transaction).is_err() {
            return (TransactionOutcome::NoReply, ReplyTiming::default(), now);
        }
        let mut arrivals = std::collections::VecDeque::new();
        loop {
            if let Some(transmit) = self.exchange.poll_transmit(now) {
                let line = MasterLine::exact(self.line);
                // As the simulator's pty hands them over: a frame's end after the UART's
                // receive timeout.
                let received = self.bus.exchange(&transmit.bytes, line, now).received();
                arrivals = crate::sim::pacing::handed_over_at(&received).into();
                let sent_until = now + self.line.wire_time(transmit.bytes.len());
                busy.push((now, sent_until));
                if let Some(other) = &mut self.other_master {
                    other.transmits(now, sent_until);
                }
                if let (Some(&(first, _)), Some(&(last, _))) = (arrivals.front(), arrivals.back()) {
                    busy.push((first.saturating_sub(self.line.char_time()), last));
                }
                if self.carry_late_bytes {
                    // The input is emptied before the request: what came before is read (and
                    // looked at for another master's request), what comes after mixes with the
                    // answer.
                    let (before, late): (Vec<TimedByte>, Vec<TimedByte>) =
                        std::mem::take(&mut self.late_bytes)
                            .into_iter()
                            .partition(|&(t, _)| t <= now);
                    if !before.is_empty() {
                        let bytes: Vec<u8> = before.iter().map(|&(_, byte)| byte).collect();
                        self.exchange.handle_bytes(now, &bytes);
                    }
                    arrivals =
                        merge_on_the_wire(late, arrivals.into(), self.line.char_time()).into();
                }
                self.exchange.handle_sent(now);
            }
            if let Some((outcome, timing)) = self.exchange.poll_outcome() {
                if self.carry_late_bytes {
                    self.late_bytes = std::mem::take(&mut arrivals);
                }
                self.line_free_at = now;
                return (outcome, timing, now);
            }
            if self.carry_late_bytes && self.exchange.awaits_transmit() {
                // As the serial transport: the silence before the request is checked at its
                // end; bytes that came meanwhile are read (another master's request may be
                // among them) and the silence starts again.
                let at = self.exchange.transmit_at().max(now);
                now = at;
                let mut late_bytes = std::mem::take(&mut self.late_bytes);
                self.other_master_until(at, &busy, &mut late_bytes);
                self.late_bytes = late_bytes;
                if self.late_bytes.front().is_some_and(|&(t, _)| t <= at) {
                    let mut heard = Vec::new();
                    while let Some((_, byte)) =
                        self.late_bytes.front().copied().filter(|&(t, _)| t <= at)
                    {
                        self.late_bytes.pop_front();
                        heard.push(byte);
                    }
                    self.exchange.handle_bytes(at, &heard);
                    self.exchange.line_was_busy(at);
                }
                continue;
            }
            let timeout = self.exchange.poll_timeout();
            // As the serial transport: a reply whose timing the exchange has learned is read in
            // one go when it should be complete.
            if let Some(at) = self
                .exchange
                .batch_read_at()
                .filter(|&at| timeout.is_none_or(|t| at <= t))
            {
                now = now.max(at);
                self.other_master_until(now, &busy, &mut arrivals);
                let mut batch = Vec::new();
                while let Some((_, byte)) = arrivals.front().copied().filter(|&(a, _)| a <= now) {
                    arrivals.pop_front();
                    batch.push(byte);
                }
                self.exchange.handle_batch(now, &batch);
                continue;
            }
            // The other master's requests up to now (never later: this transaction may end
            // before, and what comes after it must be checked against the next one's traffic).
            if self.other_master_until(now, &busy, &mut arrivals) {
                continue;
            }
            let next_byte = arrivals
                .front()
                .copied()
                .filter(|&(at, _)| timeout.is_none_or(|t| at <= t));
            // Its next request, if it comes first, is the next thing to happen.
            let other_next = self.other_master.as_ref().map(|other| other.next_at);
            if let Some(at) = other_next.filter(|&at| {
                at > now
                    && next_byte.is_none_or(|(byte_at, _)| at < byte_at)
                    && timeout.is_none_or(|t| at < t)
            }) {
                now = at;
                continue;
            }
            match (next_byte, timeout) {
                (Some((at, byte)), _) => {
                    arrivals.pop_front();
                    now = now.max(at);
                    self.exchange.handle_bytes(now, &[byte]);
                }
                (None, Some(timeout)) => {
                    now = now.max(timeout);
                    self.exchange.handle_timeout(now);
                }
                (None, None) => {
                    if self.carry_late_bytes {
                        self.late_bytes = std::mem::take(&mut arrivals);
                    }
                    self.line_free_at = now;
                    return (TransactionOutcome::NoReply, ReplyTiming::default(), now);
                }
            }
        }
    }
}

/// A byte as it reaches the master's port, at the end of its character.
type TimedByte = (Duration, u8);

/// A second master on the bus: every `every` or so (between half and one and a half times
/// that, seeded; never before its last answer has come) it reads 1–4 holding or input
/// registers 0–15 of one of the bus's devices, as wb-mqtt-serial left running beside rtu2mqtt
/// would. It does not listen before it talks: a request of its that overlaps this master's
/// request or a reply to it is garbled on the wire and nobody answers it; one that falls into a
/// silence (between transactions, or in a reply window while the device is still silent) is
/// answered, and its bytes and the answer reach this master's port.
pub struct OtherMaster {
    every: Duration,
    next_at: Duration,
    rng: crate::sim::faults::XorShift64,
    /// This master's last classic requests: half of the other master's requests are copies of
    /// them, as wb-mqtt-serial's are when it polls the same devices with the same templates.
    copies: std::collections::VecDeque<Vec<u8>>,
    /// When this master's last requests were on the wire: its transceiver does not listen
    /// while it talks (no echo), so the other master's bytes sent meanwhile never reach it.
    transmitting: std::collections::VecDeque<(Duration, Duration)>,
}

/// How many of this master's requests the other master picks its copies from.
const OTHER_MASTER_COPIES: usize = 16;

impl OtherMaster {
    /// Its first request at `from`.
    pub fn new(every: Duration, from: Duration, seed: u64) -> Self {
        Self {
            every,
            next_at: from,
            rng: crate::sim::faults::XorShift64::new(seed),
            copies: std::collections::VecDeque::new(),
            transmitting: std::collections::VecDeque::new(),
        }
    }

    /// This master's request is on the wire from `from` to `to`.
    fn transmits(&mut self, from: Duration, to: Duration) {
        if self.transmitting.len() == OTHER_MASTER_COPIES {
            self.transmitting.pop_front();
        }
        self.transmitting.push_back((from, to));
    }

    /// This master sends `request`: the other master may copy it if it is a read (it polls;
    /// a copy of a write would write an old value again, which no other master does).
    fn heard(&mut self, request: &crate::protocol::Request) {
        if !matches!(&request.body, RequestBody::Classic(pdu) if !pdu.is_write())
            || !(1..=crate::protocol::frame::MAX_DEVICE_ADDRESS).contains(&request.address)
        {
            return;
        }
        if let Ok(frame) = request.encode() {
            if self.copies.len() == OTHER_MASTER_COPIES {
                self.copies.pop_front();
            }
            self.copies.push_back(frame);
        }
    }
}

impl VirtualGateway {
    /// Merges the other master's traffic due until `until` into `stream`; true if there was any.
    fn other_master_until(
        &mut self,
        until: Duration,
        busy: &[(Duration, Duration)],
        stream: &mut std::collections::VecDeque<(Duration, u8)>,
    ) -> bool {
        if self.other_master.is_none() {
            return false;
        }
        // Whatever else is on the wire garbles the other master's request too.
        let char_time = self.line.char_time();
        let mut taken: Vec<(Duration, Duration)> = busy.to_vec();
        taken.extend(
            stream
                .iter()
                .map(|&(at, _)| (at.saturating_sub(char_time), at)),
        );
        let theirs = self.other_master_traffic(until, &taken);
        if theirs.is_empty() {
            return false;
        }
        let ours = std::mem::take(stream).into();
        *stream = merge_on_the_wire(ours, theirs, self.line.char_time()).into();
        true
    }

    /// The other master's requests due until `until`, and the devices' answers to those not
    /// garbled by other traffic (`busy`: times on the wire taken by it), as they reach this
    /// master's port, in time order.
    fn other_master_traffic(
        &mut self,
        until: Duration,
        busy: &[(Duration, Duration)],
    ) -> Vec<(Duration, u8)> {
        let Some(mut other) = self.other_master.take() else {
            return Vec::new();
        };
        let addresses: Vec<u8> = self.bus.devices().iter().map(|d| d.address()).collect();
        let char_time = self.line.char_time();
        let mut traffic = Vec::new();
        while other.next_at <= until && !addresses.is_empty() {
            let at = other.next_at;
            let pick = other.rng.next_u64();
            let address = addresses[(pick % addresses.len() as u64) as usize];
            let start = ((pick >> 8) % 16) as u16;
            let count = 1 + ((pick >> 16) % 4) as u16;
            let pdu = if pick & (1 << 24) == 0 {
                RequestPdu::ReadHoldingRegisters { start, count }
            } else {
                RequestPdu::ReadInputRegisters { start, count }
            };
            let copy = (pick & (1 << 25) != 0)
                .then(|| {
                    let index = (pick >> 32) as usize % other.copies.len().max(1);
                    other.copies.get(index).cloned()
                })
                .flatten();
            let mut done_at = at;
            if let Some(frame) = copy.or_else(|| {
                crate::protocol::Request::classic(address, pdu)
                    .encode()
                    .ok()
            }) {
                let mut heard: Vec<(Duration, u8)> = (1u32..)
                    .zip(&frame)
                    .map(|(n, &byte)| (at + char_time * n, byte))
                    .collect();
                let end = heard.last().map_or(at, |&(t, _)| t);
                let garbled = busy.iter().any(|&(from, to)| at < to && from < end);
                // What this master's transceiver does not hear: bytes sent while it talked.
                heard.retain(|&(byte_end, _)| {
                    let byte_start = byte_end.saturating_sub(char_time);
                    !other
                        .transmitting
                        .iter()
                        .any(|&(from, to)| byte_start < to && from < byte_end)
                });
                if !garbled {
                    let answer = self
                        .bus
                        .exchange(&frame, MasterLine::exact(self.line), at)
                        .received();
                    heard.extend(crate::sim::pacing::handed_over_at(&answer));
                }
                done_at = heard.last().map_or(end, |&(t, _)| t);
                if self.trace {
                    let bytes: Vec<u8> = heard.iter().map(|&(_, b)| b).collect();
                    eprintln!(
                        "OTHER {:.6} garbled={garbled} {}",
                        at.as_secs_f64(),
                        crate::protocol::hex(&bytes)
                    );
                }
                traffic = merge_on_the_wire(traffic, heard, char_time);
            }
            let spread = other.every.as_micros().max(1) as u64;
            other.next_at =
                (at + other.every / 2 + Duration::from_micros(other.rng.next_u64() % spread))
                    .max(done_at + char_time);
        }
        self.other_master = Some(other);
        traffic
    }
}

/// Two byte streams on one wire (each byte at the end of its character, `char_time` long), as
/// the simulator's wire merges overlapping transmissions: a byte of one that overlaps a byte of
/// the other becomes one byte, their wired AND (a 0 bit from either driver wins), at the later
/// end; the others keep their times. Sorted into one stream instead, two replies would reach
/// the master interleaved byte by byte, each byte intact, which no RS-485 pair does (a chance
/// CRC match on such an interleaving once published a wrong value in the fault sweep).
fn merge_on_the_wire(
    first: Vec<(Duration, u8)>,
    second: Vec<(Duration, u8)>,
    char_time: Duration,
) -> Vec<(Duration, u8)> {
    // Characters whose ends are a whole character apart (less rounding) do not overlap.
    let apart = char_time.saturating_sub(Duration::from_nanos(100));
    let mut wire = Vec::with_capacity(first.len() + second.len());
    let mut second = second.into_iter().peekable();
    for (at, byte) in first {
        while let Some(&(other_at, other)) = second.peek() {
            if other_at + apart > at {
                break;
            }
            wire.push((other_at, other));
            second.next();
        }
        match second.peek() {
            Some(&(other_at, other)) if other_at < at + apart => {
                wire.push((at.max(other_at), byte & other));
                second.next();
            }
            _ => wire.push((at, byte)),
        }
    }
    wire.extend(second);
    wire.sort_by_key(|&(at, _)| at);
    wire
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A device whose setup writes coils among holding registers (as ONOKOM TCL-1-MB-B's
    /// parameters on coils 92, 94): the simulated device holds every one of them after the
    /// start-up, and again after it restarted with other values.
    #[test]
    fn coil_setup_items_reach_the_device_and_again_after_a_restart() {
        let dir = tempfile::tempdir().expect("a template directory");
        let template = json!({"device_type": "coil-setup", "device": {"name": "Coil setup",
        "id": "coil-setup",
        "setup": [
            {"title": "swing", "reg_type": "coil", "address": 92, "value": 1},
            {"title": "mode", "reg_type": "holding", "address": 10, "value": 3},
            {"title": "beep", "reg_type": "coil", "address": 94, "value": 0}
        ],
        "channels": [
            {"name": "Power", "reg_type": "coil", "address": 0, "type": "switch"}
        ]}});
        std::fs::write(dir.path().join("coil-setup.json"), template.to_string())
            .expect("template written");
        let entry = json!({"template": "coil-setup", "address": 7, "serial": 0xFE00_0007u32, "line": "9600 8N2"});
        let mut gateway =
            VirtualGateway::from_bus("9600 8N2", &[entry], dir.path(), true, 1, Repeats::All);
        gateway.change(7, RegisterType::Coil, 94, &[1]);
        gateway.run_for(Duration::from_millis(500));
        let setup = |gateway: &VirtualGateway| {
            [
                gateway.register(7, RegisterType::Coil, 92),
                gateway.register(7, RegisterType::Holding, 10),
                gateway.register(7, RegisterType::Coil, 94),
            ]
        };
        assert_eq!(setup(&gateway), [Some(1), Some(3), Some(0)]);
        // Unplugged long enough to be taken offline, changed meanwhile: set up again on return.
        gateway.set_plugged(7, false);
        gateway.run_for(Duration::from_secs(8));
        gateway.change(7, RegisterType::Coil, 92, &[0]);
        gateway.change(7, RegisterType::Coil, 94, &[1]);
        gateway.set_plugged(7, true);
        gateway.run_for(Duration::from_secs(5));
        assert_eq!(setup(&gateway), [Some(1), Some(3), Some(0)]);
    }

    #[test]
    fn overlapping_characters_merge_by_wired_and_not_interleave() {
        let char_time = Duration::from_micros(573);
        let at = |n: u64| Duration::from_micros(10_000 + 573 * n);
        let late = vec![(at(1), 0x06), (at(2), 0x04), (at(3), 0x0C)];
        // Half a character later: every byte overlaps one of the other stream.
        let half = Duration::from_micros(286);
        let reply = vec![(at(1) + half, 0xE9), (at(2) + half, 0x1B), (at(5), 0x4C)];
        assert_eq!(
            merge_on_the_wire(late, reply, char_time),
            vec![
                (at(1) + half, 0x06 & 0xE9),
                (at(2) + half, 0x04 & 0x1B),
                (at(3), 0x0C),
                (at(5), 0x4C)
            ]
        );
        // Back to back, nothing overlaps: both kept, in time order.
        let first = vec![(at(1), 1), (at(2), 2)];
        let second = vec![(at(3), 3), (at(4), 4)];
        assert_eq!(
            merge_on_the_wire(first, second, char_time),
            vec![(at(1), 1), (at(2), 2), (at(3), 3), (at(4), 4)]
        );
    }
}
