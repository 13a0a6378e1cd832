//! The bus scheduler of one port, sans IO: the driver asks [`PortScheduler::next`] what to send,
//! sends it, and hands the outcome to [`PortScheduler::complete`], passing the time in each call.
//!
//! Order of precedence on the bus:
//! 1. the Fast Modbus event request when its slot is due (every 50/100/200 ms by baud rate);
//! 2. queued writes (a device's wait for its setup writes, which would undo them);
//! 3. device preparation (setup writes, 0x18 event setup, first reads);
//! 4. classic reads, periodic ones first, the rest round-robin.
//!
//! No transaction starts if its estimated wire time would make the next event request late:
//! instead, the event request goes out early, which resets its slot. When nothing else is due,
//! events are polled at once, so event latency falls to the wire time whenever the bus has slack.

use std::time::Duration;

use tracing::{debug, info, warn};

use super::device::{DeviceState, Failure, ReadChoice, LOW_PRIORITY, MAX_EVENT_SETUP_TRIES};
use super::due_index::{DueIndex, Placement};
use super::events::{EventPoller, WIDE_DATA_LEN};
use super::flap_log::{FlapSay, FLAP_LIMIT, FLAP_WINDOW};
use super::health::DeadRetryBudget;
use super::plan::{write_encodes, write_pdu, DevicePlan, PortSettings, RegisterWrite};
use super::rate_limit::ReadRateLimit;
use super::read_plan::RegisterSpan;
use crate::protocol::fast::enabled_registers;
use crate::protocol::timing::ADAPTER_LATENCY_ALLOWANCE;
pub use crate::protocol::transaction::{ReplyTiming, Transaction, TransactionOutcome};
use crate::protocol::{
    EventPoll, EventRange, EventSource, ExceptionCode, FastReply, RegisterType, Reply, ReplyBody,
    Request, RequestBody, RequestPdu, ResponsePdu,
};

/// How long a failed write keeps being retried unless its device says otherwise
/// (`DevicePlan::write_retry_time`, `max_write_fail_time_s`).
#[cfg(test)]
const WRITE_RETRY_TIME: Duration = Duration::from_secs(600);

/// Reads of channels with a read period go first, but once they have had the bus this much
/// longer than the other reads, one of those goes (wb-mqtt-serial's `maxLowPriorityLag` of its
/// register scheduler): a bus whose periodic reads ask for more than it has would otherwise
/// never read the other channels again, and their last values would stay up with no error.
const MAX_LOW_PRIORITY_LAG: Duration = Duration::from_secs(1);

/// Wiren Board devices' continuous-read switch (holding 114; 1: on, until the device restarts).
const CONTINUOUS_READ_REGISTER: u16 = 114;

/// What the driver does next.
#[derive(Debug, Clone, PartialEq)]
pub enum NextStep {
    Transmit(Transaction),
    /// Nothing to do before this time (or before a write is queued).
    Wait {
        until: Duration,
    },
}

/// What the scheduler knows of one device, for the status page.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeviceReport {
    /// The smoothed time to the first byte of its replies (none before the first reply).
    pub learned_response_time: Option<Duration>,
    /// How long a request to it waits for the first byte now.
    pub response_timeout: Duration,
    pub events_active: bool,
    /// "setup writes", "event setup", "ready", or "waiting for the device" while it is offline.
    pub setup: &'static str,
    /// Polling held by [`PortScheduler::hold_polling`].
    pub suspended: bool,
}

/// Register words of one reply, seen through the part that belongs to one value: a read of
/// many values hands each its part of one shared buffer (one allocation per reply, not one per
/// value).
#[derive(Clone)]
pub struct ReadWords {
    reply: std::sync::Arc<[u16]>,
    start: usize,
    end: usize,
}

impl ReadWords {
    /// `range` of these words, if it is within them.
    fn part(&self, range: std::ops::Range<usize>) -> Option<Self> {
        let start = self.start.checked_add(range.start)?;
        let end = self.start.checked_add(range.end)?;
        (start <= end && end <= self.end).then(|| Self {
            reply: std::sync::Arc::clone(&self.reply),
            start,
            end,
        })
    }
}

impl From<Vec<u16>> for ReadWords {
    fn from(words: Vec<u16>) -> Self {
        let end = words.len();
        Self {
            reply: words.into(),
            start: 0,
            end,
        }
    }
}

impl std::ops::Deref for ReadWords {
    type Target = [u16];

    fn deref(&self) -> &[u16] {
        self.reply.get(self.start..self.end).unwrap_or(&[])
    }
}

impl PartialEq for ReadWords {
    fn eq(&self, other: &Self) -> bool {
        **self == **other
    }
}

impl Eq for ReadWords {}

impl std::fmt::Debug for ReadWords {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        (**self).fmt(f)
    }
}

/// What the port tells the device model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PortEvent {
    /// Values read (bits as 0/1), one per register of `span`.
    Values {
        device: usize,
        span: RegisterSpan,
        values: ReadWords,
    },
    /// A value reported by an event: the payload is little-endian.
    EventValue {
        device: usize,
        register_type: RegisterType,
        address: u16,
        payload: Vec<u8>,
    },
    /// A periodic read is late on average (more than 10 % over its period), or on time again.
    PeriodMissed {
        device: usize,
        span: RegisterSpan,
        missed: bool,
    },
    /// `unsupported`: the device says the register does not exist; it is no longer read.
    ReadFailed {
        device: usize,
        span: RegisterSpan,
        unsupported: bool,
    },
    WriteDone {
        device: usize,
        register_type: RegisterType,
        address: u16,
    },
    WriteFailed {
        device: usize,
        register_type: RegisterType,
        address: u16,
        permanent: bool,
    },
    Online {
        device: usize,
    },
    Offline {
        device: usize,
    },
    /// The device restarted (its reboot event), or answers a read it refused before (replaced
    /// or updated): it is set up and read again from the start.
    Rebooted {
        device: usize,
    },
}

#[derive(Debug, Clone, PartialEq)]
enum InFlight {
    PollEvents {
        started: Duration,
    },
    /// Holding 114 = 1 (see [`DevicePlan::continuous_read`]).
    ContinuousRead {
        device: usize,
        value: u16,
    },
    Setup {
        device: usize,
        index: usize,
    },
    EnableEvents {
        device: usize,
        ranges: Vec<EventRange>,
        members: Vec<usize>,
    },
    /// A 0x18 turning off the events of registers nothing reads: the first `taken` of the
    /// device's queue (see `DeviceState::unread_register_event`).
    DisableEvents {
        device: usize,
        taken: usize,
    },
    Read {
        device: usize,
        span: RegisterSpan,
        members: Vec<usize>,
    },
    Write {
        write: PendingWrite,
    },
}

/// What of a transaction fits the time left before the event slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fit {
    Whole,
    /// The first this many members of a merged read.
    Prefix(usize),
    Nothing,
}

/// The timing of an event poll. Every poll of a port has the same length and the same longest
/// reply (its `max_data_len` is the port's, or the protocol's largest after a packet in which
/// nothing fitted), so it is worked out once per budget, not per poll.
#[derive(Debug, Clone, Copy, PartialEq)]
struct EventPollTiming {
    estimated: Duration,
    request_time: Duration,
    reply_timeout: Duration,
    first_byte_timeout: Duration,
    late_window: Duration,
}

impl EventPollTiming {
    fn new(settings: &PortSettings, request: &Request) -> Self {
        let line = &settings.line;
        // USB adapters deliver late, and a loaded machine reads late: a short first-byte timeout
        // would end the poll while the arbitration is still going on, and its bytes would land
        // in the next request's window. A bus with Fast Modbus devices always answers (someone
        // wins with "no events"), so the allowance costs only when nobody takes part.
        let margin = settings.latency_margin.max(ADAPTER_LATENCY_ALLOWANCE);
        // The usual answer is "no events" after a few arbitration windows; longer packets are
        // rare and bounded by the poll's max_data_len.
        let typical = line.arbitration_wait() + line.arbitration_window() * 6;
        let request_len = request.encoded_len();
        Self {
            estimated: line.transaction_time(request_len, typical, request.expected_reply_len()),
            request_time: line.wire_time(request_len),
            reply_timeout: line.event_reply_timeout()
                + line.wire_time(request.max_reply_len() + 32)
                + margin,
            first_byte_timeout: line.event_first_byte_timeout() + margin,
            late_window: margin,
        }
    }

    fn transaction(&self, request: Request) -> Transaction {
        Transaction {
            estimated: self.estimated,
            request_time: self.request_time,
            reply_timeout: self.reply_timeout,
            first_byte_timeout: Some(self.first_byte_timeout),
            late_window: self.late_window,
            request,
        }
    }
}

/// A write's register (device, table, address): a newer write to it replaces a queued one.
pub type WriteKey = (usize, RegisterType, u16);

/// The register `write` goes to.
pub fn write_key(write: &RegisterWrite) -> WriteKey {
    (write.device, write.register_type, write.address)
}

#[derive(Debug, Clone, PartialEq)]
struct PendingWrite {
    write: RegisterWrite,
    give_up_at: Duration,
    /// A bit-field write's words (bit `i`: word `i`) whose other bits are those of a word seen
    /// since it was queued, newer than the words the device model composed it over.
    seen: u128,
    /// It failed once and that was logged: a write carried out a minute later, when the device
    /// is back, leaves a trace in the journal.
    failure_told: bool,
    /// Requests of the write the device has taken ([`RegisterWrite::request`]), while it was
    /// set up for the `sent_during`th time ([`DeviceState::preparations`]): a write one register
    /// at a time goes on from the next. A failed request, or a device set up again since,
    /// starts the write over from its last register, as wb-mqtt-serial writes the whole value
    /// again: the device may not hold the registers taken before.
    sent: usize,
    sent_during: u32,
}

impl PendingWrite {
    /// The requests taken that still count for a device set up `preparations` times.
    fn requests_taken(&self, preparations: u32) -> usize {
        if self.sent_during == preparations {
            self.sent
        } else {
            0
        }
    }
}

impl PendingWrite {
    /// Puts `word`, which the device holds now in the write's word `index`, under the bits the
    /// write does not define.
    fn see(&mut self, index: usize, word: u16) {
        let mask = self.write.defined_bits(index);
        if let Some(value) = self.write.values.get_mut(index) {
            *value = (word & !mask) | (*value & mask);
            self.seen |= 1u128.checked_shl(index as u32).unwrap_or(0);
        }
    }

    /// Takes the place of `older`, a queued write of the same register. The device model
    /// composed this one over it, so these words hold the fields of both: the bits either
    /// defines are defined, and the other bits of the words `older` had seen newer are those.
    fn take_over(&mut self, older: &PendingWrite) {
        if self.write.defined.is_empty() {
            return;
        }
        for index in 0..self.write.values.len() {
            let mask = self.write.defined_bits(index) | older.write.defined_bits(index);
            if let Some(defined) = self.write.defined.get_mut(index) {
                *defined = mask;
            }
            let older_saw = older.seen & 1u128.checked_shl(index as u32).unwrap_or(0) != 0;
            if let (true, Some(&word)) = (older_saw, older.write.values.get(index)) {
                self.see(index, word);
            }
        }
        if self.write.defined.iter().all(|&m| m == u16::MAX) {
            self.write.defined = Vec::new();
        }
    }
}

/// What the device holds now in registers `span` of `device` (read, evented or written): the
/// queued bit-field writes there keep it under the bits they do not define, so that a write
/// composed over older words does not undo a change the device made since (see
/// [`RegisterWrite::defined`]). Nothing to do, and no cost, while no such write is queued.
/// An outcome as the device gave it: a gateway's exception for the device behind it (0x0A: no
/// path to it, 0x0B: it did not respond) is no answer from the device: silence, not a device
/// that answered and refused (it would never go offline, and its setup never be written again
/// when it came back). wb-mqtt-serial counts it a failed transfer too.
fn device_outcome(outcome: TransactionOutcome) -> TransactionOutcome {
    match outcome {
        TransactionOutcome::Reply(Reply {
            body:
                ReplyBody::Classic(ResponsePdu::Exception {
                    code:
                        ExceptionCode::GATEWAY_PATH_UNAVAILABLE | ExceptionCode::GATEWAY_TARGET_FAILED,
                    ..
                }),
            ..
        }) => TransactionOutcome::NoReply,
        outcome => outcome,
    }
}

fn see_words(writes: &mut [PendingWrite], device: usize, span: RegisterSpan, values: &[u16]) {
    for pending in writes {
        let write = &pending.write;
        if write.defined.is_empty()
            || write.device != device
            || write.register_type != span.register_type
        {
            continue;
        }
        for index in 0..write.values.len() {
            let Ok(offset) = u16::try_from(index) else {
                break;
            };
            let word = pending
                .write
                .address
                .checked_add(offset)
                .and_then(|address| address.checked_sub(span.start))
                .and_then(|at| values.get(usize::from(at)));
            if let Some(&word) = word {
                pending.see(index, word);
            }
        }
    }
}

/// The scheduler of one port.
#[derive(Debug)]
pub struct PortScheduler {
    settings: PortSettings,
    devices: Vec<DeviceState>,
    events: EventPoller,
    event_poll_timing: EventPollTiming,
    /// The timing of a poll with the protocol's largest budget (see `EventPoller::nothing_fitted`):
    /// its reply may be longer, and its reply timeout covers it.
    wide_event_poll_timing: EventPollTiming,
    writes: Vec<PendingWrite>,
    in_flight: Option<InFlight>,
    /// When the transaction in flight started.
    in_flight_since: Duration,
    /// When that transaction's wait for its reply would end in silence, at the earliest: the
    /// request's wire time and the first-byte timeout after it started.
    in_flight_reply_by: Duration,
    /// The bus time retries of devices that seem dead may still take.
    dead_retries: DeadRetryBudget,
    /// The shared address last warned of, and when (see `complete_event_poll`).
    shared_address_told: Option<(u8, Duration)>,
    /// When the last event poll ended and how long it took.
    last_event_poll: (Duration, Duration),
    /// Whether anything but an event poll went out since the last event poll.
    sent_since_event_poll: bool,
    /// Whether the devices' first preparation is over (see [`Self::in_startup_sweep`]).
    startup_swept: bool,
    /// Which devices may be prepared or read now, in the order they are picked.
    index: DueIndex,
    /// The first device at each address: event packets name their sender by address.
    by_address: Vec<Option<usize>>,
    /// The config's `rate_limit` on reads of channels without a read period.
    read_rate_limit: ReadRateLimit,
    /// Bus time given to reads with a read period more than to the others (see
    /// [`MAX_LOW_PRIORITY_LAG`]).
    low_priority_lag: Duration,
}

impl PortScheduler {
    pub fn new(settings: PortSettings, plans: Vec<DevicePlan>) -> Self {
        let events = EventPoller::new(&settings);
        let event_poll_timing =
            EventPollTiming::new(&settings, &Request::poll_events(events.request()));
        let wide_event_poll_timing = EventPollTiming::new(
            &settings,
            &Request::poll_events(EventPoll {
                max_data_len: WIDE_DATA_LEN,
                ..events.request()
            }),
        );
        let devices: Vec<DeviceState> = plans
            .into_iter()
            .map(|mut plan| {
                // Its request would not encode (and fail the port): a config the resolver should
                // have refused.
                plan.setup.retain(|write| {
                    let encodes = write_encodes(
                        write.register_type,
                        write.address,
                        &write.values,
                        write.force_multiple,
                    );
                    if !encodes {
                        warn!(device = %plan.name, register_type = ?write.register_type, address = write.address, count = write.values.len(), "a setup write no request can carry: never written");
                    }
                    encodes
                });
                // A TCP gateway's lag is part of the device's floor, as in wb-mqtt-serial.
                plan.response_timeout = plan.response_timeout.saturating_add(settings.response_lag);
                DeviceState::new(plan, settings.fast_modbus, &settings.line)
            })
            .collect();
        let mut by_address = vec![None; usize::from(u8::MAX) + 1];
        for (index, device) in devices.iter().enumerate() {
            if let Some(slot @ None) = by_address.get_mut(usize::from(device.plan.address)) {
                *slot = Some(index);
            }
        }
        Self {
            index: DueIndex::new(devices.len()),
            by_address,
            read_rate_limit: ReadRateLimit::new(settings.low_priority_reads_per_second),
            settings,
            devices,
            events,
            event_poll_timing,
            wide_event_poll_timing,
            writes: Vec::new(),
            in_flight: None,
            in_flight_since: Duration::ZERO,
            low_priority_lag: Duration::ZERO,
            in_flight_reply_by: Duration::ZERO,
            dead_retries: DeadRetryBudget::default(),
            shared_address_told: None,
            last_event_poll: (Duration::ZERO, Duration::ZERO),
            sent_since_event_poll: false,
            startup_swept: false,
        }
    }

    /// Another device took this one's place (same address, other serial number): setup,
    /// event setup and first reads all over again.
    pub fn set_up_again(&mut self, device: usize) {
        if let Some(state) = self.devices.get_mut(device) {
            state.restart_preparation();
            self.index.mark_stale(device);
        }
    }

    /// The device answered `span` with its `unsupported_value`: not read again until the
    /// device reconnects or restarts, as a register it refused (wb-mqtt-serial's
    /// `UnsupportedRegisterOnBorder`). Merged reads go on without it.
    pub fn stop_reading(&mut self, now: Duration, device: usize, span: RegisterSpan) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        if state.stop_reading(now, span) {
            debug!(device = %state.plan.name, ?span, "unsupported value: no longer read");
            self.index.mark_stale(device);
        }
    }

    /// The firmware of `device` was read (`None`: it could not be): channels that need newer
    /// firmware are never read and reported unsupported (`r`), as wb-mqtt-serial does; the
    /// others, held until now, are read.
    pub fn firmware_known(
        &mut self,
        now: Duration,
        device: usize,
        firmware: Option<&str>,
    ) -> Vec<PortEvent> {
        let Some(state) = self.devices.get_mut(device) else {
            return Vec::new();
        };
        let closed = state.firmware_known(now, firmware);
        self.index.mark_stale(device);
        if !closed.is_empty() {
            info!(
                device = %state.plan.name,
                firmware = firmware.unwrap_or("?"),
                count = closed.len(),
                "channels that need newer firmware are not read"
            );
        }
        closed
            .into_iter()
            .map(|span| PortEvent::ReadFailed {
                device,
                span,
                unsupported: true,
            })
            .collect()
    }

    pub fn device_count(&self) -> usize {
        self.devices.len()
    }

    /// The device's polling is held ([`Self::hold_polling`]), as of its last expiry check.
    pub fn polling_held(&self, device: usize) -> bool {
        self.devices
            .get(device)
            .is_some_and(|state| state.suspended)
    }

    /// What the status page shows of a device's schedule.
    pub fn device_report(&self, device: usize, now: Duration) -> Option<DeviceReport> {
        let state = self.devices.get(device)?;
        Some(DeviceReport {
            learned_response_time: state.response.learned(),
            response_timeout: state.response.timeout(now),
            events_active: state.events_active(),
            setup: state.setup_state(),
            suspended: state.suspended,
        })
    }

    /// Holds the polling of a device until `until` (`Duration::MAX`: until resumed), or resumes
    /// it (`None`): no reads and no preparation while held; writes and its events still go. A
    /// hold asked again moves its end. Returns false for an unknown device.
    pub fn hold_polling(&mut self, device: usize, until: Option<Duration>) -> bool {
        let Some(state) = self.devices.get_mut(device) else {
            return false;
        };
        let suspended = until.is_some();
        if state.suspended != suspended {
            if suspended {
                info!(device = %state.plan.name, "polling held by the operator");
            } else {
                info!(device = %state.plan.name, "polling resumed by the operator");
            }
        }
        state.suspended = suspended;
        state.suspended_until = until.filter(|&until| until != Duration::MAX);
        self.index.mark_stale(device);
        true
    }

    /// Ends the device's hold if its time is up.
    fn expire_hold(&mut self, device: usize, now: Duration) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        if state.suspended_until.is_some_and(|until| now >= until) {
            info!(device = %state.plan.name, "polling hold expired: polling again");
            state.suspended = false;
            state.suspended_until = None;
            self.index.mark_stale(device);
        }
    }

    /// Brings the index up to `now`: devices changed since they were placed, and those whose
    /// wake time has come (their holds end here), are placed again.
    fn refresh(&mut self, now: Duration) {
        if self.index.is_before_placements(now) {
            self.index.mark_all_stale();
        }
        loop {
            self.place_stale(now);
            let Some(device) = self.index.take_woken(now) else {
                break;
            };
            self.expire_hold(device, now);
        }
    }

    /// Places again the devices changed since they were last placed.
    fn place_stale(&mut self, now: Duration) {
        while let Some(device) = self.index.take_stale() {
            let Some(state) = self.devices.get(device) else {
                continue;
            };
            let placement = Self::placement(state, now);

            self.index.place(device, state.plan.address, now, placement);
        }
    }

    /// Where a device stands at `now` (see [`DueIndex`]): the conditions of
    /// [`choose_preparation`](Self::choose_preparation) and [`choose_read`](Self::choose_read)
    /// but the dead devices' budget, which is checked when choosing.
    fn placement(state: &DeviceState, now: Duration) -> Placement {
        let events_active = state.events_active();
        if state.suspended {
            return Placement {
                wake: state.suspended_until,
                events_active,
                ..Placement::default()
            };
        }
        let seems_dead = state.health.seems_dead();
        let open_at = state.health.may_transact_from();
        if now < open_at {
            return Placement {
                wake: Some(open_at),
                seems_dead,
                events_active,
                ..Placement::default()
            };
        }
        if state.needs_preparation() {
            return Placement {
                preparing: true,
                seems_dead,
                events_active,
                ..Placement::default()
            };
        }
        let outlook = state.read_outlook(now);
        Placement {
            preparing: false,
            read: outlook.urgency,
            seems_dead,
            wake: outlook.next_due,
            events_active,
        }
    }

    /// Queues a write; a queued write to the same register is replaced (the latest value wins;
    /// a bit field's write defines the bits either defined, see [`RegisterWrite::defined`]).
    /// A write no request can carry (no values, more than one request holds, a table that
    /// cannot be written, an unknown device) is refused at once: its permanent
    /// [`PortEvent::WriteFailed`] is returned, for the device model. A write for a device that is
    /// offline is kept, and a passing failure is returned (`w` while it waits).
    #[must_use = "a refused write's failure must reach the device model"]
    pub fn queue_write(&mut self, now: Duration, write: RegisterWrite) -> Option<PortEvent> {
        let known = write.device < self.devices.len();
        if !known
            || !write_encodes(
                write.register_type,
                write.address,
                &write.values,
                write.force_multiple,
            )
        {
            warn!(
                device = write.device,
                register_type = ?write.register_type,
                address = write.address,
                count = write.values.len(),
                "a write no request can carry: refused"
            );
            return Some(PortEvent::WriteFailed {
                device: write.device,
                register_type: write.register_type,
                address: write.address,
                permanent: true,
            });
        }
        let mut write = write;
        // A mask that does not fit the words, or that defines them all: the whole words.
        if write.defined.len() != write.values.len() || write.defined.iter().all(|&m| m == u16::MAX)
        {
            write.defined = Vec::new();
        }
        let retry_time = self
            .devices
            .get(write.device)
            .map_or(Duration::ZERO, |d| d.plan.write_retry_time);
        // A write for a device that is offline waits for it, `w` meanwhile: said once.
        let offline = self
            .devices
            .get(write.device)
            .filter(|d| d.health.is_offline());
        if let Some(state) = offline {
            info!(device = %state.plan.name, register_type = ?write.register_type, address = write.address, ?retry_time,
                "write kept for a device that is offline: sent once it answers (meta/error w meanwhile)");
        }
        // `w` at once, as wb-mqtt-serial flags a write to a disconnected device before it
        // retries it; cleared when the write is done.
        let waits = offline.map(|_| PortEvent::WriteFailed {
            device: write.device,
            register_type: write.register_type,
            address: write.address,
            permanent: false,
        });
        let mut pending = PendingWrite {
            write,
            give_up_at: now.saturating_add(retry_time),
            seen: 0,
            failure_told: offline.is_some(),
            sent: 0,
            sent_during: 0,
        };
        let same_register = |p: &PendingWrite| write_key(&p.write) == write_key(&pending.write);
        if let Some(replaced) = self.writes.iter().position(same_register) {
            let replaced = self.writes.remove(replaced);
            pending.take_over(&replaced);
        }
        self.writes.push(pending);
        waits
    }

    /// The port task stops while the transaction in flight still waits for the line (its
    /// request never went): forgotten, so that a write in it is among [`Self::unsent_writes`]
    /// and handed on to the task that replaces this one, not lost.
    pub fn forget_unsent_in_flight(&mut self) {
        self.in_flight = None;
    }

    /// The register of the write in flight, if the transaction in flight is one.
    pub fn write_in_flight(&self) -> Option<WriteKey> {
        match &self.in_flight {
            Some(InFlight::Write { write }) => Some(write_key(&write.write)),
            _ => None,
        }
    }

    /// The registers of the queued writes that have not gone on the wire (device, table,
    /// address): what a stopping port task hands on to the task that replaces it. The write in
    /// flight, if any, is not among them: it may have reached the device, and repeating it
    /// (a pushbutton, a counter reset) would act twice.
    pub fn unsent_writes(&self) -> impl Iterator<Item = WriteKey> + '_ {
        // A write one register at a time whose last request is not the one in flight is
        // handed on whole: the registers below would never be written otherwise.
        let in_flight = match &self.in_flight {
            Some(InFlight::Write { write }) if write.sent + 1 >= write.write.request_count() => {
                Some(write_key(&write.write))
            }
            _ => None,
        };
        self.writes
            .iter()
            .map(|pending| write_key(&pending.write))
            .filter(move |key| Some(*key) != in_flight)
    }

    /// Whether events are polled (the index must be up to date).
    fn events_active(&self) -> bool {
        self.settings.fast_modbus && self.index.any_events_active()
    }

    /// What to do now. Call again after [`complete`](Self::complete) or when `until` has passed.
    pub fn next(&mut self, now: Duration) -> NextStep {
        if self.in_flight.is_some() {
            return NextStep::Wait { until: now };
        }
        self.refresh(now);
        #[cfg(test)]
        self.check_index(now);
        if self.read_rate_limit.held_until(now).is_some() && self.read_rate_limit.first_hold() {
            info!(
                "rate_limit reached: reads of channels without read_period_ms wait for the next \
                 second (this is logged once)"
            );
        }
        let events_active = self.events_active() && !self.in_startup_sweep(now);
        if events_active && now >= self.event_due_at() {
            return self.start_event_poll(now);
        }
        match self.choose(now) {
            Some((transaction, in_flight)) => {
                let slot_left = self.event_due_at().saturating_sub(now);
                if !events_active {
                    return self.commit(now, transaction, in_flight);
                }
                // A keep-alive read is the least urgent work there is: one at a time between
                // event polls. All of a bus's keep-alives fall due together (their devices were
                // set up together), and sent in a row before the slot they held every event
                // back by all of them (8 devices at 115200: 15 ms, the idle bus's p99).
                if self.sent_since_event_poll && self.is_keepalive(&in_flight) {
                    return self.start_event_poll(now);
                }
                // Read what fits before the event slot (all of it if possible) ...
                match self.longest_fit(now, &transaction, &in_flight, slot_left) {
                    Fit::Whole => return self.commit(now, transaction, in_flight),
                    Fit::Prefix(taken) => {
                        if let Some((part, in_flight)) = self.read_prefix(now, &in_flight, taken) {
                            return self.commit(now, part, in_flight);
                        }
                    }
                    Fit::Nothing => {}
                }
                // ... or poll events early, which resets the slot. What can never fit a whole
                // interval goes anyway, at its smallest: a late event request beats a read that
                // never runs.
                // Never twice in a row, though: right after a poll the slot is as long as it gets,
                // and polling again would starve the read for good.
                let interval = self.settings.event_interval;
                if self.sent_since_event_poll
                    && self.longest_fit(now, &transaction, &in_flight, interval) != Fit::Nothing
                {
                    return self.start_event_poll(now);
                }
                let (smallest, in_flight) = self
                    .read_prefix(now, &in_flight, 1)
                    .unwrap_or((transaction, in_flight));
                self.commit(now, smallest, in_flight)
            }
            None if events_active => self.start_event_poll(now),
            None => NextStep::Wait {
                until: self.earliest_deadline(now),
            },
        }
    }

    /// Whether the port is still preparing its devices for the first time: event polls wait
    /// until, for the first time since the port started, no device's preparation may go.
    /// Before a device's values have been read once, nothing its events say is news (the first
    /// read, which follows the preparation, reads it all), and a device not yet set up has only
    /// its reboot to report, which the setup answers anyway. Polls in the middle of the sweep
    /// would only hold back the setup of the devices after them (on 30 devices at 115200,
    /// 5 polls: ~15 % of the start-up). Later preparations (a reboot, a device back online)
    /// go between event polls as usual.
    fn in_startup_sweep(&mut self, now: Duration) -> bool {
        if self.startup_swept {
            return false;
        }
        if self.choose_preparation(now).is_some() {
            return true;
        }
        self.startup_swept = true;
        false
    }

    fn is_keepalive(&self, in_flight: &InFlight) -> bool {
        match in_flight {
            InFlight::Read {
                device, members, ..
            } => self
                .devices
                .get(*device)
                .is_some_and(|state| state.is_keepalive_read(members)),
            _ => false,
        }
    }

    /// When the next event poll is due: its slot, but on a line so slow that a poll takes more
    /// than half the interval, never before the bus has had as much time for other requests as
    /// the last poll took. At 1200 baud an event poll takes longer than the 200 ms interval;
    /// without this, the bus would carry nothing else.
    fn event_due_at(&self) -> Duration {
        let (ended, took) = self.last_event_poll;
        if took.saturating_mul(2) > self.settings.event_interval {
            self.events.next_at().max(ended.saturating_add(took))
        } else {
            self.events.next_at()
        }
    }

    fn commit(&mut self, now: Duration, transaction: Transaction, in_flight: InFlight) -> NextStep {
        self.sent_since_event_poll = !matches!(in_flight, InFlight::PollEvents { .. });
        if let InFlight::Read {
            device, members, ..
        } = &in_flight
        {
            let low_priority = self.devices.get(*device).map_or(0, |state| {
                members
                    .iter()
                    .filter(|&&member| {
                        state
                            .plan
                            .reads
                            .get(member)
                            .is_some_and(|read| read.period.is_none())
                    })
                    .count()
            });
            self.read_rate_limit
                .count(now, u32::try_from(low_priority).unwrap_or(u32::MAX));
        }
        self.in_flight = Some(in_flight);
        self.in_flight_since = now;
        self.in_flight_reply_by = transaction.silence_ends_wait_at(now);
        NextStep::Transmit(transaction)
    }

    /// Takes the outcome of the transaction [`next`](Self::next) returned.
    pub fn complete(&mut self, now: Duration, outcome: TransactionOutcome) -> Vec<PortEvent> {
        self.complete_timed(now, outcome, ReplyTiming::default())
    }

    /// Takes the outcome of the transaction [`next`](Self::next) returned, with what the
    /// transport saw of its timing: the device's response time is learned from it.
    pub fn complete_timed(
        &mut self,
        now: Duration,
        outcome: TransactionOutcome,
        timing: ReplyTiming,
    ) -> Vec<PortEvent> {
        let mut out = Vec::new();
        self.complete_into(now, outcome, timing, &mut out);
        out
    }

    /// [`complete_timed`](Self::complete_timed) adding its events to `out`: a driver that
    /// keeps one buffer allocates nothing for them per transaction (a merged read of 60
    /// registers reports 60 values).
    pub fn complete_into(
        &mut self,
        now: Duration,
        outcome: TransactionOutcome,
        timing: ReplyTiming,
        out: &mut Vec<PortEvent>,
    ) {
        let outcome = device_outcome(outcome);
        let device = match &self.in_flight {
            Some(InFlight::Setup { device, .. })
            | Some(InFlight::ContinuousRead { device, .. })
            | Some(InFlight::EnableEvents { device, .. })
            | Some(InFlight::DisableEvents { device, .. })
            | Some(InFlight::Read { device, .. }) => Some(*device),
            Some(InFlight::Write { write }) => Some(write.write.device),
            Some(InFlight::PollEvents { .. }) | None => None,
        };
        // The late window this transaction went without (see `classic_transaction`).
        let late_window_skipped = device
            .and_then(|d| self.devices.get(d))
            .is_some_and(|d| !d.health.watches_late_reply());
        if let Some(device) = device {
            self.learn_response_time(now, device, &outcome, timing);
            // Silence through the timeout and the late window (watched: it failed its last
            // request too) is a dead device, not a slow one: retried at its normal timeout.
            let silent = !matches!(outcome, TransactionOutcome::Reply(_))
                && timing.first_byte.is_none()
                && timing.late_byte.is_none();
            if let (true, false, Some(state)) =
                (silent, late_window_skipped, self.devices.get_mut(device))
            {
                state.response.silent();
            }
        }
        let was_offline = device
            .and_then(|d| self.devices.get(d))
            .is_some_and(|d| d.health.is_offline());
        let was_dead = device
            .and_then(|d| self.devices.get(d))
            .is_some_and(|d| d.health.seems_dead());
        // Sent while every device seemed dead: the dead devices' share kept the bus for nobody
        // then (`may_transact`), so it is not charged; charged, it would hold the others'
        // retries back long after the first came back.
        let share_waived = was_dead && self.every_device_seems_dead();
        match self.in_flight.take() {
            None => warn!("a transaction outcome arrived with nothing in flight"),
            Some(InFlight::PollEvents { started }) => {
                self.last_event_poll = (now, now.saturating_sub(started));
                self.complete_event_poll(now, started, outcome, &timing, out)
            }
            Some(InFlight::ContinuousRead { device, value }) => {
                self.complete_continuous_read(now, device, value, outcome, out)
            }
            Some(InFlight::Setup { device, index }) => {
                self.complete_setup(now, device, index, outcome, out)
            }
            Some(InFlight::EnableEvents {
                device,
                ranges,
                members,
            }) => self.complete_enable_events(now, device, &ranges, &members, outcome, out),
            Some(InFlight::DisableEvents { device, taken }) => {
                self.complete_disable_events(now, device, taken, outcome, out)
            }
            Some(InFlight::Read {
                device,
                span,
                members,
            }) => {
                self.balance_priorities(now, device, &members);
                self.complete_read(now, device, span, &members, outcome, out)
            }
            Some(InFlight::Write { write }) => self.complete_write(now, write, outcome, out),
        }
        // Only a request that heard nothing in time skipped a window: a reply that began in
        // time (garbled, or not this device's) had none to watch.
        let heard_nothing_in_time = timing.first_byte.is_none() && timing.late_byte.is_none();
        if let (true, true, Some(state)) = (
            late_window_skipped,
            heard_nothing_in_time,
            device.and_then(|d| self.devices.get_mut(d)),
        ) {
            if !state.health.answered_last() {
                // It failed (a loss after an answer, or a retry of a device that seems dead):
                // its next request waits as long as if the window had been watched, the window
                // counted at the device's configured timeout. What it learned above
                // that came from its own late replies (`ResponseTimer::answered_late` raises the
                // timeout to 1.5 × the lateness seen and at least twice the timeout missed): the
                // raised timeout already is the window that reply fell into, and adding it again
                // would hold the device back three times its worst lateness and more.
                let window = state.response.floor();
                state.health.hold_off_longer(window);
            }
        }
        // Bytes that could not begin its reply (another device's late reply, noise) ended the
        // wait before its timeout, but its own reply may still be on its way: the hold-off counts
        // from when silence would have ended the wait, as after silence. Counted from now, a
        // reply later than the hold-off from here would be taken as the answer to its next
        // request of the same function and length (another range's values).
        if let (true, Some(state)) = (
            timing.foreign_bytes_only && timing.late_byte.is_none(),
            device.and_then(|d| self.devices.get_mut(d)),
        ) {
            if !state.health.answered_last() {
                state
                    .health
                    .hold_off_longer(self.in_flight_reply_by.saturating_sub(now));
            }
        }
        let still_offline = device
            .and_then(|d| self.devices.get(d))
            .is_some_and(|d| d.health.is_offline());
        if timing.late_byte.is_some() && was_offline && still_offline {
            // It answered, late: alive. Retried on its own schedule, with the longer timeout it
            // has learned, not held back like a dead device.
            if let Some(state) = device.and_then(|d| self.devices.get_mut(d)) {
                state.heard_from(now);
            }
        } else if was_dead && !share_waived {
            // A retry of a device that seemed dead: its cost comes out of the dead devices' share
            // of the bus, however many there are.
            self.dead_retries
                .spend(now, now.saturating_sub(self.in_flight_since));
        }
        if let Some(device) = device {
            self.index.mark_stale(device);
        }
    }

    /// A transaction the scheduler did not send (a queued one: an RPC's, an identity read) ended
    /// at `now` with `outcome`. When it failed, the devices at its address are held off as
    /// after a failure of their own (`complete_into`): an RTU reply carries no transaction
    /// number, and a late reply to it would otherwise be taken as the reply to the scheduler's
    /// next request to that device with the same function and length (a wrong value). Held
    /// off, their late reply can only land in another device's window, where its address gives
    /// it away. Only the hold-off: the device's health and learned response time stay as they
    /// were (the transaction ran on its caller's timeout). Requests by serial number (address
    /// 0xFD) hold off nobody: their reply carries the 0xFD address and the by-serial command,
    /// which no reply to the scheduler's requests (by address, or event polls and scans, whose
    /// commands differ) can be taken for; broadcasts have no reply.
    ///
    /// `sent_at` is when the transaction was handed to the transport: bytes that could not begin
    /// its reply may have ended the wait early, and then the hold-off counts from when silence
    /// would have ended it ([`Transaction::silence_ends_wait_at`]), as for the scheduler's own.
    pub fn queued_done(
        &mut self,
        now: Duration,
        transaction: &Transaction,
        sent_at: Duration,
        outcome: TransactionOutcome,
        timing: ReplyTiming,
    ) {
        let request = &transaction.request;
        if !request.expects_reply() || !matches!(request.body, RequestBody::Classic(_)) {
            return;
        }
        if matches!(device_outcome(outcome), TransactionOutcome::Reply(_)) {
            return;
        }
        let failed_at = if timing.foreign_bytes_only && timing.late_byte.is_none() {
            now.max(transaction.silence_ends_wait_at(sent_at))
        } else {
            now
        };
        // Silence in time: the late window it did not watch counts too, at the device's
        // configured timeout (as for the scheduler's own failures that skipped it).
        let heard_nothing_in_time = timing.first_byte.is_none() && timing.late_byte.is_none();
        self.hold_off_address(failed_at, request.address, heard_nothing_in_time);
    }

    /// A raw transfer (`port/Load` without `protocol`) whose bytes were a Modbus request to
    /// `address` ([`RawRequest::modbus_address`](crate::transport::raw::RawRequest::modbus_address))
    /// ended at `now`: unless the device's whole reply came, the devices at that address are
    /// held off as after a queued transaction that heard nothing in time (a raw transfer does
    /// not tell when bytes came, so its late window counts as skipped).
    pub fn raw_done(&mut self, now: Duration, address: u8, answered: bool) {
        if !answered {
            self.hold_off_address(now, address, true);
        }
    }

    /// Holds every device at `address` off after a failure at `failed_at` of a transaction the
    /// scheduler did not send; `window_skipped` adds the device's late window.
    fn hold_off_address(&mut self, failed_at: Duration, address: u8, window_skipped: bool) {
        for (index, state) in self.devices.iter_mut().enumerate() {
            if state.plan.address != address {
                continue;
            }
            let skipped_window = if window_skipped {
                state.response.floor()
            } else {
                Duration::ZERO
            };
            state
                .health
                .hold_off_after_foreign_failure(failed_at, skipped_window);
            self.index.mark_stale(index);
        }
    }

    /// From when a queued transaction carrying `request` may go: not before every device at
    /// its address is past its hold-off after a failure. The rule of [`Self::queued_done`] the
    /// other way round: a late reply to the scheduler's failed request to that device, still
    /// on its way, would otherwise be taken as the queued request's reply (same address, and
    /// often the same function and length) and handed to its caller (an RPC `port/Load`, an
    /// identity read) as the device's answer. `Duration::ZERO` for requests no late reply
    /// can be taken for (by serial number, broadcasts).
    pub fn queued_may_go_from(&self, request: &Request) -> Duration {
        if !request.expects_reply() || !matches!(request.body, RequestBody::Classic(_)) {
            return Duration::ZERO;
        }
        self.address_may_go_from(request.address)
    }

    /// From when a request to `address` may go: not before every device there is past its
    /// hold-off after a failure (see [`Self::queued_may_go_from`]; raw transfers that are Modbus
    /// requests wait for it too).
    pub fn address_may_go_from(&self, address: u8) -> Duration {
        self.devices
            .iter()
            .filter(|state| state.plan.address == address)
            .map(|state| state.health.quiet_until())
            .max()
            .unwrap_or(Duration::ZERO)
    }

    fn learn_response_time(
        &mut self,
        now: Duration,
        device: usize,
        outcome: &TransactionOutcome,
        timing: ReplyTiming,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        if let Some(late) = timing.late_byte {
            let before = state.response.timeout(now);
            state.response.answered_late(now, late);
            info!(
                device = %state.plan.name,
                late_ms = late.as_millis() as u64,
                timeout_ms = before.as_millis() as u64,
                new_timeout_ms = state.response.timeout(now).as_millis() as u64,
                "reply came after the response timeout: thrown away, waiting longer from now on"
            );
        } else if let (TransactionOutcome::Reply(_), Some(first_byte)) =
            (outcome, timing.first_byte)
        {
            state.response.answered(first_byte);
        }
    }

    /// Whether a device may be sent a request now: offline devices only in their retry slot, and
    /// those that seem dead only while the dead devices' share of the bus is not in the red
    /// (whatever this retry costs: see [`DeadRetryBudget::allows`]). With every device dead the
    /// share protects nobody and is not waited for: behind a Modbus TCP gateway that fell
    /// silent, a device answering again stayed offline for 45–100 s while an absent one, whose
    /// retry cost less, took the share each time it held its cost.
    fn may_transact(&self, device: &DeviceState, now: Duration) -> bool {
        device.health.may_transact(now)
            && (!device.health.seems_dead()
                || self.every_device_seems_dead()
                || self.dead_retries.allows(now))
    }

    /// No device but those that seem dead (or whose polling is held): nothing to keep the bus
    /// free for.
    fn every_device_seems_dead(&self) -> bool {
        self.devices
            .iter()
            .all(|device| device.health.seems_dead() || device.suspended)
    }

    /// The port cannot be opened (or was lost) since `since`: devices not heard from for their
    /// device timeout are marked offline and their values as not read; writes waiting for the
    /// port are flagged `w` at once (wb-mqtt-serial's closed-port cycle flags every write it
    /// could not flush), and still sent when the port is back within their retry time.
    pub fn port_unavailable(&mut self, now: Duration, since: Duration) -> Vec<PortEvent> {
        let mut out = Vec::new();
        for pending in self.writes.iter_mut().filter(|p| !p.failure_told) {
            pending.failure_told = true;
            let write = &pending.write;
            debug!(device = write.device, register_type = ?write.register_type, address = write.address,
                "write waits for the port (meta/error w meanwhile)");
            out.push(PortEvent::WriteFailed {
                device: write.device,
                register_type: write.register_type,
                address: write.address,
                permanent: false,
            });
        }
        for (index, state) in self.devices.iter_mut().enumerate() {
            if !state.health.port_lost(now, since) {
                continue;
            }
            warn!(device = %state.plan.name, "port unavailable: device marked offline");
            state.restart_preparation();
            self.index.mark_stale(index);
            out.push(PortEvent::Offline { device: index });
            for span in state.plan.reads.iter().map(|r| r.span) {
                out.push(PortEvent::ReadFailed {
                    device: index,
                    span,
                    unsupported: false,
                });
            }
        }
        out
    }

    fn start_event_poll(&mut self, now: Duration) -> NextStep {
        if self.events.rotation_optional() && self.choose(now).is_none() {
            self.events.skip_rotation();
        }
        let poll = self.events.request();
        let timing = if poll.max_data_len == WIDE_DATA_LEN {
            self.wide_event_poll_timing
        } else {
            self.event_poll_timing
        };
        let request = Request::poll_events(poll);
        #[cfg(test)]
        assert_eq!(
            EventPollTiming::new(&self.settings, &request),
            timing,
            "an event poll timed as the first one with its budget"
        );
        let transaction = timing.transaction(request);
        self.events.started(now);
        self.commit(now, transaction, InFlight::PollEvents { started: now })
    }

    /// A request to one device: its response timeout (wb-mqtt-serial's rule as the floor, the
    /// learned response time above it) to the first byte, then the reply's wire time.
    fn classic_transaction(
        &self,
        now: Duration,
        device: &DeviceState,
        request: Request,
    ) -> Transaction {
        let line = &self.settings.line;
        let request_len = request.encoded_len();
        let reply_len = request.expected_reply_len();
        let response_timeout = device.response.timeout(now);
        // After a timeout the line is watched a while longer for the late reply, to learn a
        // longer response time from it; meanwhile the bus carries nothing. A device that
        // answered its last request (an isolated loss, the usual case on a noisy line) skips
        // that watch and the bus goes on with the others at once: its own next request waits
        // as long as before (its holdoff grows by the window skipped, see `complete_timed`), and
        // its late reply can only land in another device's window, where its address gives it
        // away. A second failure in a row gets the window back, so a device that became slow is
        // learned at its next request; a device that seems dead watches it on one retry in a
        // few (`DeviceHealth::watches_late_reply`).
        let late_window = if device.health.watches_late_reply() {
            response_timeout
        } else {
            Duration::ZERO
        };
        let request_time = line.wire_time(request_len);
        // The silence the transport keeps before the device's requests takes the bus as long.
        let guard = self.settings.guard_intervals.before(device.plan.address);
        let estimated = guard
            + if device.health.is_offline() {
                // An offline device costs its whole timeout and the late window after it.
                request_time + response_timeout + late_window
            } else {
                line.transaction_time(request_len, self.settings.turnaround, reply_len)
            };
        Transaction {
            request,
            request_time,
            reply_timeout: response_timeout + line.wire_time(reply_len) + ADAPTER_LATENCY_ALLOWANCE,
            first_byte_timeout: Some(response_timeout),
            late_window,
            estimated,
        }
    }

    /// The most urgent non-event transaction, without committing to it.
    fn choose(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        self.choose_write(now)
            .or_else(|| self.choose_preparation(now))
            .or_else(|| self.choose_read(now))
    }

    /// The first queued write whose device may be sent a request now. A device's writes wait
    /// while its setup writes are due (after a (re)connection or a reboot), as wb-mqtt-serial
    /// sets a device up before anything else: a write that went first would be undone by a
    /// setup write to its register. Not while its polling is held, which holds its setup too.
    fn choose_write(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        let pending = self.writes.iter().find(|p| {
            self.devices
                .get(p.write.device)
                .is_some_and(|d| (d.suspended || !d.setup_pending()) && self.may_transact(d, now))
        })?;
        let device = self.devices.get(pending.write.device)?;
        let mut pending = pending.clone();
        pending.sent = pending.requests_taken(device.preparations);
        pending.sent_during = device.preparations;
        let write = &pending.write;
        let (address, values) = write.request(pending.sent);
        let pdu = write_pdu(write.register_type, address, values, write.force_multiple);
        let transaction =
            self.classic_transaction(now, device, Request::classic(device.plan.address, pdu));
        Some((transaction, InFlight::Write { write: pending }))
    }

    /// The first of the devices that seem dead, in `candidates`' order, that the dead
    /// devices' budget lets go now.
    fn first_dead_allowed<T: Copy>(
        &self,
        now: Duration,
        mut candidates: impl Iterator<Item = T>,
        device_of: impl Fn(T) -> usize,
    ) -> Option<T> {
        // A retry costs something: if nothing may go, nothing dearer may (no scan).
        if !self.dead_retries.allows(now) && !self.every_device_seems_dead() {
            return None;
        }
        candidates.find(|&candidate| {
            self.devices
                .get(device_of(candidate))
                .is_some_and(|d| self.may_transact(d, now))
        })
    }

    /// Setup writes or the event setup of the first device (by index) whose preparation may go:
    /// the index keeps those in order, apart from those that seem dead (budget permitting).
    fn choose_preparation(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        let dead = self.first_dead_allowed(now, self.index.dead_preparing(), |d| d);
        let index = match (self.index.first_preparing(), dead) {
            (Some(healthy), Some(dead)) => healthy.min(dead),
            (healthy, dead) => healthy.or(dead)?,
        };
        self.preparation_of(now, index)
    }

    /// The preparation step of device `index`. (A device is unprepared only while a setup write
    /// or, with Fast Modbus on, its event setup is due.)
    fn preparation_of(&self, now: Duration, index: usize) -> Option<(Transaction, InFlight)> {
        let device = self.devices.get(index)?;
        if let Some(value) = device.continuous_read_due() {
            let pdu = RequestPdu::WriteSingleRegister {
                address: CONTINUOUS_READ_REGISTER,
                value,
            };
            let transaction =
                self.classic_transaction(now, device, Request::classic(device.plan.address, pdu));
            return Some((
                transaction,
                InFlight::ContinuousRead {
                    device: index,
                    value,
                },
            ));
        }
        if let Some(setup_index) = device.next_setup_write() {
            let write = device.plan.setup.get(setup_index)?;
            let words = device.setup_words(setup_index)?;
            let pdu = write_pdu(
                write.register_type,
                write.address,
                &words,
                write.force_multiple,
            );
            let transaction =
                self.classic_transaction(now, device, Request::classic(device.plan.address, pdu));
            return Some((
                transaction,
                InFlight::Setup {
                    device: index,
                    index: setup_index,
                },
            ));
        }
        if self.settings.fast_modbus && device.wants_events() {
            let (ranges, members) = device.event_ranges();
            let request = Request::configure_events(device.plan.address, ranges.clone());
            let transaction = self.classic_transaction(now, device, request);
            return Some((
                transaction,
                InFlight::EnableEvents {
                    device: index,
                    ranges,
                    members,
                },
            ));
        }
        if device.is_prepared() && device.has_events_to_disable() {
            let (ranges, taken) = device.disable_ranges();
            let request = Request::configure_events(device.plan.address, ranges);
            let transaction = self.classic_transaction(now, device, request);
            return Some((
                transaction,
                InFlight::DisableEvents {
                    device: index,
                    taken,
                },
            ));
        }
        None
    }

    /// The most urgent read of all devices that may be read now (ties: the lowest index): the
    /// index keeps them in that order, apart from those that seem dead (budget permitting).
    fn choose_read(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        if self.low_priority_lag >= MAX_LOW_PRIORITY_LAG {
            if let Some(choice) = self.choose_low_priority_read(now) {
                return Some(choice);
            }
        }
        self.choose_read_by_priority(now)
    }

    /// The most urgent read of a channel without a read period, of the devices that may be
    /// read now (those that seem dead as their budget allows: an offline device's retries are
    /// such reads): when reads with a period have had the bus for [`MAX_LOW_PRIORITY_LAG`] more
    /// than the others. A scan of every device, only while the periodic reads ask for more
    /// than the bus has.
    fn choose_low_priority_read(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        let dead_may_go = self.dead_retries.allows(now) || self.every_device_seems_dead();
        let (device, choice) = self
            .devices
            .iter()
            .enumerate()
            .filter(|(_, d)| {
                !d.needs_preparation()
                    && !d.suspended
                    && (dead_may_go || !d.health.seems_dead())
                    && self.may_transact(d, now)
            })
            .filter_map(|(index, d)| d.choose_low_priority_read(now).map(|c| (index, c)))
            .min_by_key(|(_, choice)| choice.urgency)?;
        if self.held_by_rate_limit(now, &choice) {
            return None;
        }
        self.read_of(now, device, choice)
    }

    /// Reads in their due order: those with a read period first.
    fn choose_read_by_priority(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        let dead = self.first_dead_allowed(now, self.index.dead_reads(), |(_, d)| d);
        let (_, device) = match (self.index.first_read(), dead) {
            (Some(healthy), Some(dead)) => healthy.min(dead),
            (healthy, dead) => healthy.or(dead)?,
        };
        let choice = self.devices.get(device)?.choose_read(now)?;
        if self.held_by_rate_limit(now, &choice) {
            return None;
        }
        self.read_of(now, device, choice)
    }

    /// Periodic reads come first in the due order: a round-robin read first means none is due,
    /// and round-robin reads wait while `rate_limit` holds them.
    fn held_by_rate_limit(&self, now: Duration, choice: &ReadChoice) -> bool {
        choice.urgency.0 == LOW_PRIORITY && self.read_rate_limit.held_until(now).is_some()
    }

    fn read_of(
        &self,
        now: Duration,
        device: usize,
        choice: ReadChoice,
    ) -> Option<(Transaction, InFlight)> {
        let ReadChoice { span, members, .. } = choice;
        let state = self.devices.get(device)?;
        let span = state.plan.merge.at_least_min(span);
        let transaction = self.classic_transaction(
            now,
            state,
            Request::classic(state.plan.address, span.read_request()),
        );
        Some((
            transaction,
            InFlight::Read {
                device,
                span,
                members,
            },
        ))
    }

    /// What of the transaction fits `budget`: all of it, or the longest leading part of a
    /// merged read that does.
    fn longest_fit(
        &self,
        now: Duration,
        transaction: &Transaction,
        in_flight: &InFlight,
        budget: Duration,
    ) -> Fit {
        if transaction.estimated <= budget {
            return Fit::Whole;
        }
        let InFlight::Read { members, .. } = in_flight else {
            return Fit::Nothing;
        };
        let fits = |taken: usize| {
            self.prefix_transaction(now, in_flight, taken)
                .is_some_and(|shorter| shorter.estimated <= budget)
        };
        // A longer prefix never takes less time (its span only grows), so the longest that fits
        // is found by bisection: a handful of prefixes built instead of one per member (a
        // 60-register read that misses the slot by a little tried 59 before).
        let (mut fitting, mut too_long) = (0, members.len());
        while too_long - fitting > 1 {
            let middle = fitting + (too_long - fitting) / 2;
            if fits(middle) {
                fitting = middle;
            } else {
                too_long = middle;
            }
        }
        let fit = if fitting == 0 {
            Fit::Nothing
        } else {
            Fit::Prefix(fitting)
        };
        #[cfg(test)]
        assert_eq!(
            fit,
            (1..members.len())
                .rev()
                .find(|&taken| fits(taken))
                .map_or(Fit::Nothing, Fit::Prefix),
            "bisection against the scan of every prefix"
        );
        fit
    }

    /// The read of the first `taken` members of a merged read.
    fn read_prefix(
        &self,
        now: Duration,
        in_flight: &InFlight,
        taken: usize,
    ) -> Option<(Transaction, InFlight)> {
        let InFlight::Read {
            device, members, ..
        } = in_flight
        else {
            return None;
        };
        let (transaction, span) = self.prefix_read(now, *device, members, taken)?;
        let part = members.get(..taken)?.to_vec();
        Some((
            transaction,
            InFlight::Read {
                device: *device,
                span,
                members: part,
            },
        ))
    }

    /// [`read_prefix`](Self::read_prefix)'s transaction alone (no members list built).
    fn prefix_transaction(
        &self,
        now: Duration,
        in_flight: &InFlight,
        taken: usize,
    ) -> Option<Transaction> {
        let InFlight::Read {
            device, members, ..
        } = in_flight
        else {
            return None;
        };
        self.prefix_read(now, *device, members, taken)
            .map(|(transaction, _)| transaction)
    }

    fn prefix_read(
        &self,
        now: Duration,
        device: usize,
        members: &[usize],
        taken: usize,
    ) -> Option<(Transaction, RegisterSpan)> {
        let state = self.devices.get(device)?;
        let part = members.get(..taken)?;
        let first = state.read_span(*part.first()?)?;
        let mut span = first;
        for &member in part {
            let member_span = state.read_span(member)?;
            let end = span.end().max(member_span.end());
            span.count = u16::try_from(end - u32::from(span.start)).ok()?;
        }
        // As long as the device needs, as the whole read was (`read_of`).
        let span = state.plan.merge.at_least_min(span);
        let request = Request::classic(state.plan.address, span.read_request());
        Some((self.classic_transaction(now, state, request), span))
    }

    fn earliest_deadline(&self, now: Duration) -> Duration {
        let budget_applies = !self.every_device_seems_dead();
        let offline_gate = |d: &DeviceState, at: Duration| {
            if d.health.seems_dead() && budget_applies {
                at.max(self.dead_retries.available_at(now))
            } else {
                at
            }
        };
        let held_until = self.read_rate_limit.held_until(now);
        // A device held off after a failure (its late-reply hold-off) is due no sooner than the
        // hold-off's end, online or not: waiting "until now" would have the port spin.
        let devices = self
            .devices
            .iter()
            .filter(|d| !d.suspended)
            .filter_map(|d| {
                d.next_deadline(held_until)
                    .map(|at| offline_gate(d, at.max(d.health.may_transact_from())))
            });
        let writes = self.writes.iter().filter_map(|p| {
            self.devices.get(p.write.device).and_then(|d| {
                let held_off = Some(d.health.may_transact_from()).filter(|&from| from > now);
                d.health
                    .retry_at()
                    .or(held_off)
                    .map(|at| offline_gate(d, at))
            })
        });
        devices
            .chain(writes)
            .min()
            .unwrap_or(now + Duration::from_secs(1))
            .max(now)
    }

    fn device_by_address(&self, address: u8) -> Option<usize> {
        self.by_address.get(usize::from(address)).copied().flatten()
    }

    fn complete_event_poll(
        &mut self,
        now: Duration,
        started: Duration,
        outcome: TransactionOutcome,
        timing: &ReplyTiming,
        out: &mut Vec<PortEvent>,
    ) {
        match outcome {
            TransactionOutcome::Reply(Reply {
                address,
                body:
                    ReplyBody::Fast {
                        reply: FastReply::Events(packet),
                        ..
                    },
            }) => {
                // Devices changed since the last placement may have had their events turned off.
                self.place_stale(now);
                let highest_listener = self.index.highest_listener().unwrap_or(0);
                let sender = self.device_by_address(address);
                // A packet naming registers the plan does not read, or values wider than its
                // reads there, is the sign of a frame that noise changed past what its CRC
                // caught (one garbled frame in 65,536 passes CRC-16; in a sweep a collision
                // moved a u32's event from input 10 to input 8, and the device, confirmed, dropped
                // the real one: its value stayed old for good). Not confirmed the first time, so
                // the device sends it again; the same packet twice is what the device means.
                if let Some((device, state)) =
                    sender.and_then(|d| self.devices.get_mut(d).map(|state| (d, state)))
                {
                    if state.hold_back_unexpected(&packet) {
                        debug!(device = %state.plan.name, address, "event packet naming registers or widths the plan does not read: not confirmed, so that the device sends it again");
                        state.heard_from(now);
                        self.index.mark_stale(device);
                        self.events.garbled(now, None, 0);
                        return;
                    }
                }
                let reboot_before_setup = !packet.events.is_empty()
                    && packet.events.iter().all(|event| event.is_reboot())
                    && sender
                        .and_then(|d| self.devices.get(d))
                        .is_some_and(|d| !d.is_prepared());
                let nothing_fitted = packet.events.is_empty() && packet.event_count > 0;
                if reboot_before_setup {
                    self.events
                        .packet_received_at_leisure(address, packet.flag, highest_listener);
                } else if nothing_fitted {
                    let widened =
                        self.events
                            .nothing_fitted(now, address, packet.flag, highest_listener);
                    debug!(
                        address,
                        event_count = packet.event_count,
                        widened,
                        "events that do not fit the poll's max_data_len: asking with the largest"
                    );
                } else {
                    self.events
                        .packet_received(now, address, packet.flag, highest_listener);
                }
                let Some(device) = sender else {
                    debug!(address, "events from a device that is not in the config");
                    return;
                };
                if let Some(state) = self.devices.get_mut(device) {
                    if state.heard_from(now) {
                        if state.flaps.is_quiet() {
                            debug!(device = %state.plan.name, "offline device sent events: trying it again at once");
                        } else {
                            info!(device = %state.plan.name, "offline device sent events: trying it again at once");
                        }
                    }
                    self.index.mark_stale(device);
                }
                let seen_before = self.devices.get_mut(device).map_or(0, |state| {
                    state.events_seen_before(packet.flag, &packet.events)
                });
                // A value wider than the read that holds its register: the device and its
                // template disagree, or the frame was corrupted in a way its CRC missed (one in
                // 65,536 garbled frames passes CRC-16; a collision moved an event's register
                // in a sweep). Nothing of such a packet is taken: what it names is read instead.
                let untrusted = self.devices.get(device).is_some_and(|state| {
                    packet
                        .events
                        .iter()
                        .any(|event| state.event_fits_plan(event) == Some(false))
                });
                if untrusted {
                    if let Some(state) = self.devices.get_mut(device) {
                        if state.first_untrusted_packet() {
                            warn!(device = %state.plan.name, address, "an event packet names values wider than the template's registers there: not taken, the registers are read instead (a template that does not fit the device, or noise)");
                        } else {
                            debug!(device = %state.plan.name, address, "event packet not taken (values wider than the registers): read instead");
                        }
                        for event in &packet.events {
                            if let EventSource::Register(register_type) = event.source {
                                state.read_again(register_type, event.id);
                            }
                        }
                    }
                    self.index.mark_stale(device);
                }
                if seen_before > 0 {
                    debug!(address, seen_before, "packet sent again (its confirmation was lost): its first events were applied already");
                }
                for (index, event) in packet.events.into_iter().enumerate() {
                    if index < seen_before && !event.is_reboot() {
                        continue;
                    }
                    if event.is_reboot() {
                        if let Some(state) = self.devices.get_mut(device) {
                            if std::mem::replace(&mut state.power_on_report_pending, false) {
                                debug!(device = %state.plan.name, "device's power-on report (the first since this service started): setting it up again");
                            } else {
                                info!(device = %state.plan.name, "device reports a restart: setting it up again");
                            }
                            state.restart_preparation();
                        }
                        out.push(PortEvent::Rebooted { device });
                        continue;
                    }
                    if untrusted {
                        continue;
                    }
                    if let EventSource::Register(register_type) = event.source {
                        let words = crate::protocol::event_payload_words(&event.payload);
                        if let Some(state) = self.devices.get_mut(device) {
                            if state.unread_register_event(register_type, event.id) {
                                info!(device = %state.plan.name, ?register_type, address = event.id, "events from a register no channel reads: turning them off");
                                self.index.mark_stale(device);
                            }
                            state.read_partial_event_value(register_type, event.id, words.len());
                            // A one-register value is that register's word: setup writes that
                            // keep bits of it keep these (a wider one's word order is the
                            // channel's, unknown here: its next read tells).
                            if let [_] = words.as_slice() {
                                let span = RegisterSpan::new(register_type, event.id, 1);
                                state.note_words(span, &words);
                                see_words(&mut self.writes, device, span, &words);
                            }
                        }
                        out.push(PortEvent::EventValue {
                            device,
                            register_type,
                            address: event.id,
                            payload: event.payload,
                        });
                    }
                }
            }
            TransactionOutcome::Reply(_) | TransactionOutcome::NoReply => {
                self.events.nothing_pending(started)
            }

            TransactionOutcome::Garbled => {
                let highest_listener = self.index.highest_listener().unwrap_or(0);
                let shared = self
                    .events
                    .garbled(now, timing.garbled_packet_from, highest_listener);
                // Once per address in ten minutes: noise can look alike now and then.
                let told_lately = |(told, at): (u8, Duration)| {
                    shared == Some(told) && now.saturating_sub(at) < SHARED_ADDRESS_WARNING_EVERY
                };
                if let Some(address) =
                    shared.filter(|_| !self.shared_address_told.is_some_and(told_lately))
                {
                    self.shared_address_told = Some((address, now));
                    let device = self
                        .device_by_address(address)
                        .and_then(|d| self.devices.get(d))
                        .map_or_else(|| "not in the config".to_owned(), |d| d.plan.name.clone());
                    warn!(address, %device,
                        "event polls keep colliding at this address: two devices with one \
                         address? Their events cannot be told apart, and their reads may be \
                         garbled too; devices with events above it, if any, are polled past \
                         it meanwhile. Give one a free address: `rtu2mqtt fix-addresses` \
                         (docs/tools.md)");
                }
            }
        }
    }

    /// As wb-mqtt-serial's `EnableWbContinuousRead`: a refusal means firmware without it (its
    /// reads then keep the template's holes); silence fails like a setup write.
    fn complete_continuous_read(
        &mut self,
        now: Duration,
        device: usize,
        value: u16,
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        match WriteOutcome::of(&outcome) {
            // Illegal function, address or value: firmware without continuous read.
            WriteOutcome::Refused(code) => {
                Self::health_success(state, device, now, out);
                if state.continuous_read_answered(None) {
                    info!(device = %state.plan.name, %code, "device refuses continuous read (older firmware): its registers are read without holes");
                } else {
                    debug!(device = %state.plan.name, %code, "continuous read refused");
                }
            }
            WriteOutcome::Taken => {
                Self::health_success(state, device, now, out);
                state.continuous_read_answered(Some(value));
                debug!(device = %state.plan.name, value, "continuous read set");
            }
            WriteOutcome::Failed(failure) => {
                self.preparation_write_failed(now, device, failure, out)
            }
        }
    }

    /// A write of the device's preparation (continuous read, setup) got no readable reply, or
    /// an exception that says "not now": the preparation is tried again later, as
    /// wb-mqtt-serial's transient errors fail a device's prepare.
    fn preparation_write_failed(
        &mut self,
        now: Duration,
        device: usize,
        failure: Failure,
        out: &mut Vec<PortEvent>,
    ) {
        if let Some(state) = self.devices.get_mut(device) {
            Self::health_failure(state, device, now, failure, out);
        }
        self.setup_failed_for_writes(now, device, out);
    }

    fn complete_setup(
        &mut self,
        now: Duration,
        device: usize,
        index: usize,
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        match WriteOutcome::of(&outcome) {
            WriteOutcome::Refused(code) => {
                warn!(device = %state.plan.name, index, %code, "setup write refused; skipping it");
                Self::health_success(state, device, now, out);
                state.setup_write_done(index);
            }
            WriteOutcome::Taken => {
                Self::health_success(state, device, now, out);
                // A bit-field write waiting for the setup goes over what it wrote.
                if self.writes.iter().any(|p| !p.write.defined.is_empty()) {
                    if let Some((write, words)) =
                        state.plan.setup.get(index).zip(state.setup_words(index))
                    {
                        let count = u16::try_from(words.len()).unwrap_or(u16::MAX);
                        let span = RegisterSpan::new(write.register_type, write.address, count);
                        see_words(&mut self.writes, device, span, &words);
                    }
                }
                state.setup_write_done(index);
            }
            WriteOutcome::Failed(failure) => {
                self.preparation_write_failed(now, device, failure, out)
            }
        }
    }

    /// Gives up the queued writes whose retry time is over without their having gone (the
    /// port unavailable all that time: nothing tried and failed them), as a failed write is
    /// given up then: a command never goes out long after it was given, when the port is back.
    pub fn expire_writes(&mut self, now: Duration) -> Vec<PortEvent> {
        let in_flight = match &self.in_flight {
            Some(InFlight::Write { write }) => Some(write_key(&write.write)),
            _ => None,
        };
        let mut out = Vec::new();
        let devices = &self.devices;
        self.writes.retain(|pending| {
            if now < pending.give_up_at || Some(write_key(&pending.write)) == in_flight {
                return true;
            }
            if let Some(state) = devices.get(pending.write.device) {
                warn!(device = %state.plan.name, address = pending.write.address, "write given up: the port has been unavailable since it was asked for");
            }
            out.push(PortEvent::WriteFailed {
                device: pending.write.device,
                register_type: pending.write.register_type,
                address: pending.write.address,
                permanent: true,
            });
            false
        });
        out
    }

    /// The device did not answer a setup write: its writes waiting for the setup (see
    /// [`Self::choose_write`]) fail with it, as they would have failed had they gone, and are
    /// given up at the time they would have been: the wait neither loses a write nor keeps one
    /// past its retry time.
    fn setup_failed_for_writes(&mut self, now: Duration, device: usize, out: &mut Vec<PortEvent>) {
        let mut index = 0;
        while let Some(pending) = self.writes.get(index) {
            if pending.write.device != device {
                index += 1;
                continue;
            }
            let give_up = now >= pending.give_up_at;
            out.push(PortEvent::WriteFailed {
                device,
                register_type: pending.write.register_type,
                address: pending.write.address,
                permanent: give_up,
            });
            if give_up {
                if let Some(state) = self.devices.get(device) {
                    warn!(device = %state.plan.name, address = pending.write.address, "write given up: the device did not answer its setup");
                }
                self.writes.remove(index);
            } else {
                index += 1;
            }
        }
    }

    fn complete_enable_events(
        &mut self,
        now: Duration,
        device: usize,
        ranges: &[EventRange],
        members: &[usize],
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        match outcome {
            TransactionOutcome::Reply(Reply {
                body:
                    ReplyBody::Fast {
                        reply: FastReply::EventsConfigured { masks },
                        ..
                    },
                ..
            }) => {
                Self::health_success(state, device, now, out);
                let enabled = enabled_registers(&masks, ranges).unwrap_or_default();
                state.events_configured(now, members, &enabled);
            }
            // An exception other than "illegal function" to a request that carried the reboot
            // event's record: the device may take only the four register tables in 0x18 (the
            // protocol defines its ranges by register type). Asked again without the record
            // before it is taken for a device without events.
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(ResponsePdu::Exception { code, .. }),
                ..
            }) if code != ExceptionCode::ILLEGAL_FUNCTION
                && !state.reboot_record_refused
                && ranges
                    .iter()
                    .any(|range| range.source == EventSource::System) =>
            {
                info!(device = %state.plan.name, %code, "event setup refused: asking again without the reboot event's record");
                Self::health_success(state, device, now, out);
                state.reboot_record_refused = true;
            }
            TransactionOutcome::Reply(_) => {
                // Asked again at every reconnect (its firmware may have been updated), said once.
                if std::mem::replace(&mut state.no_events_told, true) {
                    debug!(device = %state.plan.name, "device does not support Fast Modbus events: polling it");
                } else {
                    info!(device = %state.plan.name, "device does not support Fast Modbus events: polling it");
                }
                Self::health_success(state, device, now, out);
                state.events_refused(now);
            }
            // The request may have reached the device: transient, as wb-mqtt-serial's
            // "Failed to enable events" fails the device's prepare and it is tried again.
            failed @ (TransactionOutcome::NoReply | TransactionOutcome::Garbled) => {
                let garbled = failed == TransactionOutcome::Garbled;
                Self::health_failure(state, device, now, Failure::without_reply(&failed), out);
                let answer = if garbled {
                    "no readable answer"
                } else {
                    "no answer"
                };
                if !state.event_setup_failed(now) {
                    debug!(device = %state.plan.name, "{answer} to the event setup: trying it again");
                } else if state.health.is_offline() {
                    // The device is away (said when it was marked offline), not deaf to the
                    // event setup: asked again when it answers, said then if it fails again.
                    debug!(device = %state.plan.name, tries = MAX_EVENT_SETUP_TRIES, "{answer} to the event setup while offline: asked for again when it answers");
                } else if std::mem::replace(&mut state.event_setup_unanswered_told, true) {
                    debug!(device = %state.plan.name, tries = MAX_EVENT_SETUP_TRIES, "{answer} to the event setup: polling it");
                } else {
                    warn!(device = %state.plan.name, tries = MAX_EVENT_SETUP_TRIES, "{answer} to the event setup: polling it (asked for once more when it next comes online)");
                }
            }
        }
    }

    /// The 0x18 that turned off events nothing reads: not sent again, whatever the outcome (a
    /// device that keeps sending them costs one request per register and connection at most).
    fn complete_disable_events(
        &mut self,
        now: Duration,
        device: usize,
        taken: usize,
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        state.events_disabled(taken);
        match outcome {
            TransactionOutcome::Reply(_) => Self::health_success(state, device, now, out),
            failed @ (TransactionOutcome::NoReply | TransactionOutcome::Garbled) => {
                Self::health_failure(state, device, now, Failure::without_reply(&failed), out)
            }
        }
    }

    /// The time of a read goes to its class: a read with a period adds to
    /// [`Self::low_priority_lag`], another takes from it.
    fn balance_priorities(&mut self, now: Duration, device: usize, members: &[usize]) {
        let spent = now.saturating_sub(self.in_flight_since);
        let periodic = members.first().is_some_and(|&first| {
            self.devices
                .get(device)
                .and_then(|d| d.plan.reads.get(first))
                .is_some_and(|read| read.period.is_some())
        });
        self.low_priority_lag = if periodic {
            // Bounded: a long spell with nothing else to read (the others all rate-limited or
            // offline) must not later hand the others the bus for as long.
            (self.low_priority_lag + spent).min(MAX_LOW_PRIORITY_LAG * 2)
        } else {
            self.low_priority_lag.saturating_sub(spent)
        };
    }

    fn complete_read(
        &mut self,
        now: Duration,
        device: usize,
        span: RegisterSpan,
        members: &[usize],
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        // Nothing came (else bytes that made no reply, or the wrong one).
        let silent = outcome == TransactionOutcome::NoReply;
        let values = match outcome {
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(pdu),
                ..
            }) => match pdu {
                ResponsePdu::ReadHoldingRegisters { values }
                | ResponsePdu::ReadInputRegisters { values } => values,
                ResponsePdu::ReadCoils { packed } | ResponsePdu::ReadDiscreteInputs { packed } => {
                    crate::protocol::pdu::unpack_bits(&packed, usize::from(span.count))
                        .into_iter()
                        .map(u16::from)
                        .collect()
                }
                ResponsePdu::Exception { code, .. } => {
                    Self::health_success(state, device, now, out);
                    let permanent = code.is_permanent();
                    if permanent && members.len() > 1 {
                        debug!(device = %state.plan.name, ?span, %code, "merged read refused: reading its parts one by one");
                        state.split_reads(now, members);
                    } else {
                        Self::reads_failed(state, device, now, members, permanent, out);
                    }
                    return;
                }
                _ => Vec::new(),
            },
            _ => Vec::new(),
        };
        if values.len() != usize::from(span.count) {
            Self::reads_failed(state, device, now, members, false, out);
            let failure = if silent {
                Failure::Silent
            } else {
                Failure::Unreadable
            };
            Self::health_failure(state, device, now, failure, out);
            return;
        }
        Self::health_success(state, device, now, out);
        if state.refused_read_answered(members) {
            info!(device = %state.plan.name, ?span, "device answers a read it refused before (replaced or updated?): setting it up again");
            out.push(PortEvent::Rebooted { device });
        }
        state.note_words(span, &values);
        see_words(&mut self.writes, device, span, &values);
        let values = ReadWords::from(values);
        for &member in members {
            let Some(member_span) = state.read_span(member) else {
                continue;
            };
            let offset = usize::from(member_span.start.saturating_sub(span.start));
            if let Some(part) = values.part(offset..offset + usize::from(member_span.count)) {
                out.push(PortEvent::Values {
                    device,
                    span: member_span,
                    values: part,
                });
            }
            if let Some(missed) = state.read_done(now, member) {
                out.push(PortEvent::PeriodMissed {
                    device,
                    span: member_span,
                    missed,
                });
            }
        }
    }

    fn complete_write(
        &mut self,
        now: Duration,
        pending: PendingWrite,
        outcome: TransactionOutcome,
        out: &mut Vec<PortEvent>,
    ) {
        let write = &pending.write;
        let (device, register_type, address) = (write.device, write.register_type, write.address);
        let Some(state) = self.devices.get_mut(device) else {
            return;
        };
        let replaced = |writes: &[PendingWrite]| {
            writes.iter().any(|p| {
                p.write.device == device
                    && p.write.register_type == register_type
                    && p.write.address == address
                    && p.write.values != pending.write.values
            })
        };
        match WriteOutcome::of(&outcome) {
            WriteOutcome::Refused(code) => {
                warn!(device = %state.plan.name, address, %code, "write refused by the device");
                Self::health_success(state, device, now, out);
                self.writes.retain(|p| !(p.write == pending.write));
                out.push(PortEvent::WriteFailed {
                    device,
                    register_type,
                    address,
                    permanent: true,
                });
            }
            WriteOutcome::Taken if pending.sent + 1 < write.request_count() => {
                // One register of a value written one at a time: the device holds its word;
                // the write goes on with the next (its value is published once all are in).
                Self::health_success(state, device, now, out);
                let (address, values) = write.request(pending.sent);
                let span = RegisterSpan::new(register_type, address, 1);
                let words = values.to_vec();
                state.note_words(span, &words);
                if let Some(queued) = self.writes.iter_mut().find(|p| p.write == pending.write) {
                    queued.sent = pending.sent + 1;
                    queued.sent_during = pending.sent_during;
                }
                see_words(&mut self.writes, device, span, &words);
            }
            WriteOutcome::Taken => {
                Self::health_success(state, device, now, out);
                self.writes.retain(|p| !(p.write == pending.write));
                let span = RegisterSpan::new(
                    register_type,
                    address,
                    u16::try_from(write.values.len()).unwrap_or(u16::MAX),
                );
                // The device holds these words now: a setup write that keeps bits of the
                // register keeps these, not those of an older read, and so does a bit-field
                // write queued since.
                state.note_words(span, &write.values);
                see_words(&mut self.writes, device, span, &write.values);
                out.push(PortEvent::WriteDone {
                    device,
                    register_type,
                    address,
                });
                out.push(PortEvent::Values {
                    device,
                    span,
                    values: write.values.clone().into(),
                });
            }
            // No reply, or busy / a device failure: sent again (wb-mqtt-serial retries a write
            // that failed with a transient error for its max_write_fail_time).
            WriteOutcome::Failed(failure) => {
                Self::health_failure(state, device, now, failure, out);
                let give_up = now >= pending.give_up_at;
                if give_up || replaced(&self.writes) {
                    self.writes.retain(|p| !(p.write == pending.write));
                } else if let Some(queued) =
                    self.writes.iter_mut().find(|p| p.write == pending.write)
                {
                    // Sent again whole: the registers taken before may not hold their words.
                    queued.sent = 0;
                }
                let name = &state.plan.name;
                if give_up {
                    warn!(device = %name, ?register_type, address, "write given up: the device did not take it in its retry time (max_write_fail_time_s)");
                } else if let Some(queued) = self
                    .writes
                    .iter_mut()
                    .find(|p| p.write == pending.write && !p.failure_told)
                {
                    queued.failure_told = true;
                    let retried_for = pending.give_up_at.saturating_sub(now);
                    info!(device = %name, ?register_type, address, ?retried_for, "write not taken by the device: kept and sent again until it is (meta/error w meanwhile)");
                }
                out.push(PortEvent::WriteFailed {
                    device,
                    register_type,
                    address,
                    permanent: give_up,
                });
            }
        }
    }

    /// Reports the failure of every planned read a request covered.
    fn reads_failed(
        state: &mut DeviceState,
        device: usize,
        now: Duration,
        members: &[usize],
        unsupported: bool,
        out: &mut Vec<PortEvent>,
    ) {
        for &member in members {
            if let Some(span) = state.read_span(member) {
                out.push(PortEvent::ReadFailed {
                    device,
                    span,
                    unsupported,
                });
            }
            state.read_failed(now, member, unsupported);
        }
    }

    fn health_success(
        state: &mut DeviceState,
        device: usize,
        now: Duration,
        out: &mut Vec<PortEvent>,
    ) {
        if state.record_success(now) {
            if state.flaps.came_online() == FlapSay::Quietly {
                debug!(device = %state.plan.name, "device is online");
            } else {
                info!(device = %state.plan.name, "device is online");
            }
            out.push(PortEvent::Online { device });
        }
        Self::tell_flaps(state, now);
    }

    /// Closes a quiet spell of a flapping device's log once its window is over.
    fn tell_flaps(state: &mut DeviceState, now: Duration) {
        let minutes = FLAP_WINDOW.as_secs() / 60;
        let now_state = if state.health.is_online() {
            "online"
        } else {
            "offline"
        };
        match state.flaps.tick(now) {
            FlapSay::Summary { drop_outs } => {
                info!(device = %state.plan.name, drop_outs,
                    "device dropped out {drop_outs} times in the last {minutes} minutes; now {now_state}");
            }
            FlapSay::Settled => {
                info!(device = %state.plan.name,
                    "device did not drop out in the last {minutes} minutes (now {now_state}): its offline/online changes are logged again");
            }
            _ => {}
        }
    }

    fn health_failure(
        state: &mut DeviceState,
        device: usize,
        now: Duration,
        failure: Failure,
        out: &mut Vec<PortEvent>,
    ) {
        if state.record_failure(now, failure) {
            let counts = state.failures_since_success;
            let (silent, unreadable) = (counts.silent, counts.unreadable);
            let say = state.flaps.went_offline(now);
            if say == FlapSay::Quietly {
                debug!(device = %state.plan.name, address = state.plan.address, unreadable, silent,
                    not_now = counts.not_now, "device marked offline");
            } else if let (0, 0, Some(code)) = (silent, unreadable, counts.last_not_now) {
                warn!(device = %state.plan.name, address = state.plan.address, %code,
                    "device answers its preparation with an exception that says not now (busy, \
                     device failure): marked offline, its preparation retried with growing delay");
            } else if unreadable == 0 {
                warn!(device = %state.plan.name, address = state.plan.address, "device does not answer: marked offline, retrying with growing delay");
            } else {
                warn!(device = %state.plan.name, address = state.plan.address, unreadable, silent,
                    "no readable reply from the device: marked offline, retrying with growing delay \
                     (unreadable replies: noise, a missing terminator, two devices at this \
                     address, or another master on the bus)");
            }
            if let FlapSay::ChangeThenQuiet { over } = say {
                info!(device = %state.plan.name, drop_outs = FLAP_LIMIT,
                    "device dropped out {FLAP_LIMIT} times in {} s: its further offline/online changes are logged at debug level, with a summary every {} minutes (its controls' meta/error show the state meanwhile)",
                    over.as_secs(), FLAP_WINDOW.as_secs() / 60);
            }
            out.push(PortEvent::Offline { device });
        }
        Self::tell_flaps(state, now);
    }
}

/// A write's outcome as wb-mqtt-serial sorts it (`RethrowSerialDeviceException`): taken,
/// refused for good, or failed and to be tried again (no reply, garbage, or an exception that
/// says "not now": busy, device failure). Setup writes, the continuous-read switch and channel
/// writes all go by it.
enum WriteOutcome {
    Taken,
    Refused(ExceptionCode),
    Failed(Failure),
}

impl WriteOutcome {
    fn of(outcome: &TransactionOutcome) -> Self {
        match outcome {
            TransactionOutcome::Reply(reply) => match reply.exception_code() {
                None => Self::Taken,
                Some(code) if code.is_permanent() => Self::Refused(code),
                Some(code) => Self::Failed(Failure::NotNow(code)),
            },
            failed => Self::Failed(Failure::without_reply(failed)),
        }
    }
}

/// How often the warning of two devices with one address may come again for the same address.
const SHARED_ADDRESS_WARNING_EVERY: Duration = Duration::from_secs(600);

/// The choices as they were made before the index, by a scan of every device: the index is
/// checked against them at every [`PortScheduler::next`] of the unit tests.
#[cfg(test)]
impl PortScheduler {
    fn choose_preparation_by_scan(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        for (index, device) in self.devices.iter().enumerate() {
            if !device.needs_preparation() || device.suspended || !self.may_transact(device, now) {
                continue;
            }
            if let Some(choice) = self.preparation_of(now, index) {
                return Some(choice);
            }
        }
        None
    }

    fn choose_read_by_scan(&self, now: Duration) -> Option<(Transaction, InFlight)> {
        let (device, choice) = self
            .devices
            .iter()
            .enumerate()
            .filter(|(_, d)| !d.needs_preparation() && !d.suspended && self.may_transact(d, now))
            .filter_map(|(index, d)| d.choose_read(now).map(|choice| (index, choice)))
            .min_by_key(|(_, choice)| choice.urgency)?;
        if self.held_by_rate_limit(now, &choice) {
            return None;
        }
        self.read_of(now, device, choice)
    }

    fn check_index(&self, now: Duration) {
        for state in &self.devices {
            assert_eq!(
                state.choose_read(now),
                state.choose_read_by_sorting(now),
                "{}: read at {now:?}",
                state.plan.name
            );
            assert!(
                state.suspended_until.is_none_or(|until| now < until),
                "{}: a hold past its end at {now:?}",
                state.plan.name
            );
        }
        assert_eq!(
            self.events_active(),
            self.settings.fast_modbus && self.devices.iter().any(DeviceState::events_active),
            "events active at {now:?}"
        );
        assert_eq!(
            self.choose_preparation(now),
            self.choose_preparation_by_scan(now),
            "preparation at {now:?}"
        );
        assert_eq!(
            self.choose_read_by_priority(now),
            self.choose_read_by_scan(now),
            "read at {now:?}"
        );
    }
}

#[cfg(test)]
#[path = "scheduler_tests.rs"]
mod tests;
