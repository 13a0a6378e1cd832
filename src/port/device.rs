//! One device as its port's scheduler sees it: preparation (setup writes, event setup), which
//! reads are due, which are replaced by events or unsupported, and its health.

use std::time::Duration;

use tracing::warn;

use super::flap_log::FlapLog;
use super::health::{DeviceHealth, HealthChange};
use super::plan::{DevicePlan, EventMode};
use super::read_plan::RegisterSpan;
use crate::protocol::fast::REBOOT_EVENT_ID;
use crate::protocol::frame::MAX_FRAME_LEN;
use crate::protocol::timing::ResponseTimer;
use crate::protocol::{
    Event, EventPriority, EventRange, EventSource, ExceptionCode, LineSettings, RegisterType,
    TransactionOutcome,
};

/// How often a device whose every channel comes by events is read anyway, so that a dead device
/// is noticed.
pub(super) const KEEPALIVE_PERIOD: Duration = Duration::from_secs(1);
/// The shortest stretch of reads over which a periodic read's "period missed" flag is decided
/// (wb-mqtt-serial's: ten periods, at least 10 s).
const PERIOD_CHECK_MIN_WINDOW: Duration = Duration::from_secs(10);

/// Registers between two event values that are filled with disabled entries rather than
/// starting a new record: up to 4, as wb-mqtt-serial's `DISABLE_EVENTS_IN_HOLES` (the next
/// value at most 5 registers past the last one, `TModbusExtTest.EventsEnablerRangesWithHoles`).
const MAX_EVENT_HOLE: u32 = 4;

/// Event setups (0x18) in a row that may go unanswered (silence, a garbled reply) before the
/// device is polled instead: each failure is transient (the request may have reached the
/// device) and counts against its health, and the setup is tried again under its back-off, as
/// wb-mqtt-serial's prepare is; a device that never answers 0x18 (no Fast Modbus, and silent
/// about it) must still be read in the end.
pub(super) const MAX_EVENT_SETUP_TRIES: u32 = 3;

/// Registers whose events one device connection may have turned off (see
/// [`DeviceState::unread_register_event`]): a device that reports ever new registers cannot
/// make the list, or the bus time spent on it, grow without end.
const MAX_EVENTS_TO_DISABLE: usize = 64;

/// The holes a read may span while continuous read is on: wb-mqtt-serial's
/// `MAX_HOLE_CONTINUOUS_16_BIT_REGISTERS` and `…_1_BIT_REGISTERS`.
const CONTINUOUS_READ_REGISTER_HOLE: u16 = 10;
const CONTINUOUS_READ_BIT_HOLE: u16 = 80;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Preparation {
    /// Continuous read (holding 114 = 1) is to be switched on, before the setup writes.
    ContinuousRead,
    /// Setup write `next` is due.
    Setup {
        next: usize,
    },
    /// The 0x18 event setup is due.
    Events,
    Done,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Exclusion {
    None,
    /// Events enabled: polled only as the keep-alive, or once after (re)connecting.
    EventsOnly,
    /// The device said the register does not exist.
    Unsupported,
    /// Needs a minimum firmware: not read until the device's is known.
    AwaitingFirmware,
    /// Needs newer firmware than the device has.
    NewerFirmware,
    /// Wider than one request may carry (or empty): never read, whatever happens.
    Unreadable,
}

impl Exclusion {
    /// Never read, whatever else happens, until the device or its firmware changes.
    fn never_read(self) -> bool {
        matches!(
            self,
            Exclusion::Unsupported
                | Exclusion::AwaitingFirmware
                | Exclusion::NewerFirmware
                | Exclusion::Unreadable
        )
    }
}

#[derive(Debug, Clone)]
struct ReadState {
    next_due: Duration,
    last_read: Option<Duration>,
    exclusion: Exclusion,
    /// Read once after (re)connecting even when events deliver it.
    initial_pending: bool,
    /// Not merged with others: a merged read including it was refused, and the reads are
    /// taken one by one until each has answered or been refused on its own.
    solo: bool,
    /// Split off and not yet read on its own.
    solo_unknown: bool,
    /// Has answered once: the device has it (see [`DevicePlan::continuous_read`]).
    present: bool,
    /// The intervals between this read's reads since its "period missed" flag was last decided:
    /// their sum and number (decided once they cover ten periods, at least 10 s, as
    /// wb-mqtt-serial's `TReadPeriodMissChecker` decides).
    interval_window: (Duration, u32),
    /// The actual period is more than 10 % over `read_period_ms`.
    period_missed: bool,
}

/// Lower is more urgent: periodic reads first, then by due time, then least recently read.
pub(super) type ReadUrgency = (u8, Duration, Option<Duration>);

/// The class of a [`ReadUrgency`] of a channel without a read period (round-robin).
pub(super) const LOW_PRIORITY: u8 = 1;

/// The read a device would do now, and how urgent it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct ReadChoice {
    pub span: RegisterSpan,
    /// Indices of the planned reads this request covers.
    pub members: Vec<usize>,
    pub urgency: ReadUrgency,
}

/// What a device's reads look like from `now` on, for the scheduler's due order: the urgency of
/// the read [`DeviceState::choose_read`] would pick now, and the first later time at which
/// another read becomes due (until then the urgency cannot change without the device's state
/// changing).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct ReadOutlook {
    pub urgency: Option<ReadUrgency>,
    pub next_due: Option<Duration>,
}

/// What a failed transaction of a device brought.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Failure {
    /// Nothing came.
    Silent,
    /// Bytes came that made no reply.
    Unreadable,
    /// An exception that says "not now" (busy, a device failure: any but illegal function,
    /// address or value), which wb-mqtt-serial takes for a transient error: what was asked
    /// is asked again later.
    NotNow(ExceptionCode),
}

impl Failure {
    /// A transaction that ended without a reply: `Garbled` (bytes that made none) or not.
    pub(super) fn without_reply(outcome: &TransactionOutcome) -> Self {
        if *outcome == TransactionOutcome::Garbled {
            Self::Unreadable
        } else {
            Self::Silent
        }
    }
}

/// Failed transactions since a device's last good one, by kind (for the operator's line when
/// it goes offline).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct FailureCounts {
    pub silent: u32,
    pub unreadable: u32,
    pub not_now: u32,
    pub last_not_now: Option<ExceptionCode>,
}

#[derive(Debug, Clone)]
pub(super) struct DeviceState {
    pub plan: DevicePlan,
    /// How many times the device has been set up again (reconnected, restarted, replaced): a
    /// write sent one register at a time starts over when this changed since its last
    /// register was taken, as the device may have lost the registers written before.
    pub preparations: u32,
    pub health: DeviceHealth,
    /// How long to wait for this device's replies: the configured floor, raised by what it does.
    pub response: ResponseTimer,
    fast_modbus: bool,
    preparation: Preparation,
    reads: Vec<ReadState>,
    /// The planned reads' indices ordered by (span, index): the order reads are merged in.
    by_span: Vec<usize>,
    events_active: bool,
    /// Polling held by the operator (status page, MQTT RPC `device/SetPoll`): no reads or
    /// preparation; writes and events still go.
    pub suspended: bool,
    /// When a hold asked for a limited time ends (`None`: until resumed).
    pub suspended_until: Option<Duration>,
    /// A merged read over unconfigured registers was refused: no more holes for this device,
    /// as wb-mqtt-serial turns them off (`HolesAutoDisable`).
    holes_off: bool,
    /// The device took continuous read (holding 114 = 1) since it last (re)connected.
    continuous_read_on: bool,
    /// The device refused continuous read since it last (re)connected.
    continuous_read_refused: bool,
    /// Said once: the device refuses continuous read.
    continuous_read_refusal_told: bool,
    /// A read split off a refused merged read was refused on its own: the refusal is
    /// explained, and the others may be merged again once all are known.
    split_found_refused: bool,
    /// The holding registers whose setup writes keep bits of what is there, with the last word
    /// read or written there (empty on most devices).
    setup_reads: Vec<(u16, Option<u16>)>,
    /// Event setups in a row that got no readable reply (see [`MAX_EVENT_SETUP_TRIES`]);
    /// cleared by a reply to one (or, once, when the device comes online after it was given up).
    event_setup_failures: u32,
    /// The event setup was given up and taken up again once when the device came online
    /// (see [`Self::record_success`]); not again until a 0x18 is answered.
    event_setup_taken_up_again: bool,
    /// The device refused a 0x18 that carried the reboot event's record (type 15, which the
    /// protocol names only as an event type, so a device may take register tables only): its
    /// event setups go without it.
    pub(super) reboot_record_refused: bool,
    /// Registers that sent events no planned read covers, to be turned off (priority 0) by the
    /// next 0x18; the first `events_disable_sent` of them went already, the others are in
    /// (type, address) order. Kept for the
    /// device's connection (cleared when its preparation starts over), so each is turned off
    /// once whatever the device does after.
    events_to_disable: Vec<(RegisterType, u16)>,
    events_disable_sent: usize,
    /// The latest event packet's flag, its number of events and a digest of them: a packet
    /// sent again under the same flag (its confirmation was lost) starts with the same events.
    last_packet: Option<(u8, usize, u64)>,
    /// A packet of this device was not trusted and that was said at warning level.
    untrusted_packet_told: bool,
    /// Said once at info level (then at debug level at every reconnect): the device refused
    /// the event setup / did not answer it and is polled.
    pub(super) no_events_told: bool,
    pub(super) event_setup_unanswered_told: bool,
    /// Failed transactions since the last good one, by kind.
    pub(super) failures_since_success: FailureCounts,
    /// How loudly its changes between online and offline are told.
    pub(super) flaps: FlapLog,
    /// The flag of the event packet left unconfirmed once (see
    /// [`Self::hold_back_unexpected`]).
    held_back_flag: Option<u8>,
    /// No reboot event came from it since this service started: the first one is its
    /// power-on report, pending since then (no news for the journal).
    pub(super) power_on_report_pending: bool,
}

impl DeviceState {
    pub(super) fn new(plan: DevicePlan, fast_modbus: bool, line: &LineSettings) -> Self {
        let reads = plan
            .reads
            .iter()
            .map(|read| ReadState {
                next_due: Duration::ZERO,
                last_read: None,
                exclusion: if !read.span.fits_one_read() {
                    // Its request would not encode (and fail the port): a config the parser
                    // should have refused.
                    warn!(device = %plan.name, span = ?read.span, "a read no request can carry: never read");
                    Exclusion::Unreadable
                } else if read.min_firmware.is_some() {
                    Exclusion::AwaitingFirmware
                } else {
                    Exclusion::None
                },
                initial_pending: true,
                solo: false,
                solo_unknown: false,
                present: false,
                interval_window: (Duration::ZERO, 0),
                period_missed: false,
            })
            .collect();
        let mut by_span: Vec<usize> = (0..plan.reads.len()).collect();
        by_span.sort_by_key(|&i| (plan.reads.get(i).map(|r| r.span), i));
        let health = DeviceHealth::new(plan.health);
        let response = ResponseTimer::new(line.response_timeout_floor(plan.response_timeout));
        let mut setup_reads: Vec<(u16, Option<u16>)> = plan
            .setup
            .iter()
            .filter(|write| write.register_type == RegisterType::Holding)
            .flat_map(|write| {
                write
                    .kept_bits
                    .iter()
                    .enumerate()
                    .filter(|(_, &kept)| kept != 0)
                    .map(|(i, _)| (write.address.wrapping_add(i as u16), None))
            })
            .collect();
        setup_reads.sort_unstable();
        setup_reads.dedup();
        let mut state = Self {
            plan,
            health,
            response,
            fast_modbus,
            preparation: Preparation::Done,
            reads,
            by_span,
            events_active: false,
            suspended: false,
            suspended_until: None,
            holes_off: false,
            continuous_read_on: false,
            continuous_read_refused: false,
            continuous_read_refusal_told: false,
            split_found_refused: false,
            setup_reads,
            event_setup_failures: 0,
            reboot_record_refused: false,
            event_setup_taken_up_again: false,
            events_to_disable: Vec::new(),
            events_disable_sent: 0,
            last_packet: None,
            untrusted_packet_told: false,
            no_events_told: false,
            event_setup_unanswered_told: false,
            failures_since_success: FailureCounts::default(),
            flaps: FlapLog::default(),
            held_back_flag: None,
            power_on_report_pending: true,
            preparations: 0,
        };
        state.preparation = state.first_preparation_step();
        state
    }

    fn first_preparation_step(&self) -> Preparation {
        if self.plan.continuous_read {
            Preparation::ContinuousRead
        } else {
            self.setup_step()
        }
    }

    fn setup_step(&self) -> Preparation {
        if self.plan.setup.is_empty() {
            self.after_setup()
        } else {
            Preparation::Setup { next: 0 }
        }
    }

    fn after_setup(&self) -> Preparation {
        if self.fast_modbus
            && self.event_setup_failures < MAX_EVENT_SETUP_TRIES
            && self
                .plan
                .reads
                .iter()
                .any(|r| r.events != EventMode::Polled)
        {
            Preparation::Events
        } else {
            Preparation::Done
        }
    }

    pub(super) fn events_active(&self) -> bool {
        self.events_active
    }

    /// Where the device's preparation stands, in words (status page).
    pub(super) fn setup_state(&self) -> &'static str {
        if self.health.is_offline() {
            // Set up again once it answers: "ready" would say it is.
            return "waiting for the device";
        }
        match self.preparation {
            Preparation::ContinuousRead | Preparation::Setup { .. } => "setup writes",
            Preparation::Events => "event setup",
            Preparation::Done => "ready",
        }
    }

    pub(super) fn is_prepared(&self) -> bool {
        self.preparation == Preparation::Done
    }

    /// Whether a preparation step is due: setup, event setup, or turning off events nothing
    /// reads (see [`Self::unread_register_event`]).
    pub(super) fn needs_preparation(&self) -> bool {
        !self.is_prepared() || self.has_events_to_disable() || self.continuous_read_due().is_some()
    }

    /// An event came for `register_type`/`address`: when no planned read covers it (enabled by
    /// an earlier config, another master or the firmware), it is queued to be turned off, as
    /// wb-mqtt-serial's `DisableEventsFromRegs` does, once per device connection and for at
    /// most [`MAX_EVENTS_TO_DISABLE`] registers. True when it was queued now.
    pub(super) fn unread_register_event(
        &mut self,
        register_type: RegisterType,
        address: u16,
    ) -> bool {
        let covered = self.plan.reads.iter().any(|read| {
            read.span.register_type == register_type
                && u32::from(address) >= u32::from(read.span.start)
                && u32::from(address) < read.span.end()
        });
        let key = (register_type, address);
        if covered
            || self.events_to_disable.len() >= MAX_EVENTS_TO_DISABLE
            || self.events_to_disable.contains(&key)
        {
            return false;
        }
        // The part not sent yet is kept in order, so that neighbours share a range.
        let unsent = self
            .events_to_disable
            .get(self.events_disable_sent..)
            .unwrap_or_default();
        let at = self.events_disable_sent + unsent.partition_point(|&queued| queued < key);
        self.events_to_disable.insert(at, key);
        true
    }

    pub(super) fn has_events_to_disable(&self) -> bool {
        self.events_disable_sent < self.events_to_disable.len()
    }

    /// The 0x18 ranges that turn off the events queued by [`Self::unread_register_event`] and
    /// not sent yet (priority 0; neighbours share a range), as many as one request carries,
    /// and how many of the queue they take.
    pub(super) fn disable_ranges(&self) -> (Vec<EventRange>, usize) {
        let pending = self
            .events_to_disable
            .get(self.events_disable_sent..)
            .unwrap_or_default();
        // address, 0x46, 0x18, list_len, CRC: the rest of the frame is the list.
        let mut room = MAX_FRAME_LEN - 6;
        let mut ranges: Vec<EventRange> = Vec::new();
        let mut taken = 0;
        // In order (see `unread_register_event`): what is taken is a prefix of the queue.
        for &(register_type, address) in pending {
            let source = EventSource::Register(register_type);
            let next_to_last = ranges.last_mut().filter(|range| {
                range.source == source
                    && u32::from(range.start) + range.priorities.len() as u32 == u32::from(address)
                    && range.priorities.len() < 255
            });
            if let (Some(range), true) = (next_to_last, room >= 1) {
                range.priorities.push(EventPriority::Disabled);
                room -= 1;
            } else if room >= 5 {
                ranges.push(EventRange::registers(
                    register_type,
                    address,
                    vec![EventPriority::Disabled],
                ));
                room -= 5;
            } else {
                break;
            }
            taken += 1;
        }
        (ranges, taken)
    }

    /// The 0x18 of [`Self::disable_ranges`] went (answered or not: it is not sent again).
    pub(super) fn events_disabled(&mut self, taken: usize) {
        self.events_disable_sent = self
            .events_disable_sent
            .saturating_add(taken)
            .min(self.events_to_disable.len());
    }

    pub(super) fn next_setup_write(&self) -> Option<usize> {
        match self.preparation {
            Preparation::Setup { next } => Some(next),
            _ => None,
        }
    }

    /// Whether setup writes are due: the device's writes wait for them (a write that went
    /// first would be undone by a setup write to its register).
    pub(super) fn setup_pending(&self) -> bool {
        matches!(
            self.preparation,
            Preparation::ContinuousRead | Preparation::Setup { .. }
        )
    }

    /// The value holding 114 (continuous read) is to be set to now, if any. At (re)connection,
    /// before the setup writes: on (1) when every register read is known to exist, else off
    /// (0): the device may still have it on from before (wb-mqtt-serial, or this daemon before
    /// a restart), and in continuous read a merged read over a register it lacks answers
    /// 0xFFFE for it instead of being refused. Once every register read has answered (those it
    /// refused are no longer read), on, and reads merge over holes.
    pub(super) fn continuous_read_due(&self) -> Option<u16> {
        if !self.plan.continuous_read {
            return None;
        }
        if self.preparation == Preparation::ContinuousRead {
            return Some(u16::from(self.all_reads_present()));
        }
        let switch_on = self.is_prepared()
            && !self.continuous_read_on
            && !self.continuous_read_refused
            && self.all_reads_present();
        switch_on.then_some(1)
    }

    /// Whether every register read (not excluded for good) has answered once.
    fn all_reads_present(&self) -> bool {
        self.reads
            .iter()
            .all(|r| r.present || !matches!(r.exclusion, Exclusion::None | Exclusion::EventsOnly))
    }

    /// The device took `value` for continuous read, or refused it (`None`: firmware without
    /// it). True when a refusal is to be told (once per device).
    pub(super) fn continuous_read_answered(&mut self, value: Option<u16>) -> bool {
        if self.preparation == Preparation::ContinuousRead {
            self.preparation = self.setup_step();
        }
        self.continuous_read_on = value == Some(1);
        self.continuous_read_refused = value.is_none();
        value.is_none() && !std::mem::replace(&mut self.continuous_read_refusal_told, true)
    }

    /// Whether read `index` is to be read on its own: split off after a refused merged read,
    /// or not yet known to exist while continuous read is on (a safeguard: it is switched on
    /// once every read has answered).
    fn reads_alone(&self, index: usize) -> bool {
        self.reads
            .get(index)
            .is_some_and(|r| r.solo || (self.continuous_read_on && !r.present))
    }

    /// Keeps what a read of holding registers found, or a write put, where setup writes keep
    /// bits (as wb-mqtt-serial's register cache takes both in).
    pub(super) fn note_words(&mut self, span: RegisterSpan, values: &[u16]) {
        if self.setup_reads.is_empty() || span.register_type != RegisterType::Holding {
            return;
        }
        for (address, last) in &mut self.setup_reads {
            if let Some(&word) = address
                .checked_sub(span.start)
                .and_then(|offset| values.get(usize::from(offset)))
            {
                *last = Some(word);
            }
        }
    }

    /// The words of setup write `index`: its values, with the bits it keeps from what was last
    /// read or written of the register (as wb-mqtt-serial writes setup over its register
    /// cache).
    pub(super) fn setup_words(&self, index: usize) -> Option<Vec<u16>> {
        let write = self.plan.setup.get(index)?;
        Some(write.words_over(|address| {
            self.setup_reads
                .iter()
                .find(|(at, _)| *at == address)
                .and_then(|(_, last)| *last)
        }))
    }

    pub(super) fn wants_events(&self) -> bool {
        self.preparation == Preparation::Events
    }

    pub(super) fn setup_write_done(&mut self, index: usize) {
        if self.preparation == (Preparation::Setup { next: index }) {
            self.preparation = if index + 1 < self.plan.setup.len() {
                Preparation::Setup { next: index + 1 }
            } else {
                self.after_setup()
            };
        }
    }

    /// The 0x18 request's ranges and the planned reads they cover. As wb-mqtt-serial does, a
    /// value takes one entry, at its first register (a device reports a wide value there, and
    /// an entry per word would make it report each word on its own); values close together
    /// share a record, the registers between them disabled (priority 0), which costs less than
    /// a new record's header. High priority for channels that also have a read period.
    pub(super) fn event_ranges(&self) -> (Vec<EventRange>, Vec<usize>) {
        let mut candidates: Vec<(usize, RegisterSpan, EventPriority)> = self
            .plan
            .reads
            .iter()
            .enumerate()
            .filter(|(i, r)| {
                r.events != EventMode::Polled && self.exclusion(*i).is_some_and(|e| !e.never_read())
            })
            .map(|(i, r)| {
                let priority = if r.period.is_some() {
                    EventPriority::High
                } else {
                    EventPriority::Low
                };
                (i, r.span, priority)
            })
            .collect();
        candidates.sort_by_key(|(_, span, _)| (span.register_type, span.start));
        // A device with no setup writes also gets wb-mqtt-serial's `0F 0000 01 00` record (the
        // reboot event disabled): it drops the power-on "I rebooted" still pending, which would
        // otherwise come in after the setup and start it all over. Nothing can be lost by it
        // here: a reboot before this request only undid what this request and the first reads
        // after it set up again; one after it arms the event anew (the device restarts with its
        // defaults). A device with setup writes does not get it: a reboot between its setup
        // and this request would go unnoticed, and its setup with it.
        let clear_reboot = self.plan.setup.is_empty() && !self.reboot_record_refused;
        // address, 0x46, 0x18, list_len, CRC: the rest of the frame is the list.
        let mut room = MAX_FRAME_LEN - 6 - if clear_reboot { 5 } else { 0 };
        let mut ranges: Vec<EventRange> = Vec::new();
        let mut members = Vec::new();
        for (index, span, priority) in candidates {
            if span.count == 0 {
                continue;
            }
            let source = EventSource::Register(span.register_type);
            // The same first register as the previous value (bit fields of one register).
            if let Some(last) = ranges.last_mut().filter(|last| {
                last.source == source
                    && u32::from(last.start) + last.priorities.len() as u32 > u32::from(span.start)
            }) {
                let offset = usize::from(span.start.wrapping_sub(last.start));
                if let Some(slot) = last.priorities.get_mut(offset) {
                    *slot = (*slot).max(priority);
                }
                members.push(index);
                continue;
            }
            // Close after the previous value: extend its record over the hole.
            if let Some(last) = ranges.last_mut().filter(|last| {
                let end = u32::from(last.start) + last.priorities.len() as u32;
                last.source == source
                    && u32::from(span.start) - end <= MAX_EVENT_HOLE
                    && (u32::from(span.start) - end) as usize + 1 + last.priorities.len() <= 255
            }) {
                let end = u32::from(last.start) + last.priorities.len() as u32;
                let hole = (u32::from(span.start) - end) as usize;
                if hole < room {
                    room -= hole + 1;
                    last.priorities
                        .extend(std::iter::repeat_n(EventPriority::Disabled, hole));
                    last.priorities.push(priority);
                    members.push(index);
                }
                continue;
            }
            if 5 > room {
                continue;
            }
            room -= 5;
            ranges.push(EventRange::registers(
                span.register_type,
                span.start,
                vec![priority],
            ));
            members.push(index);
        }
        if clear_reboot && !ranges.is_empty() {
            ranges.push(EventRange {
                source: EventSource::System,
                start: REBOOT_EVENT_ID,
                priorities: vec![EventPriority::Disabled],
            });
        }
        (ranges, members)
    }

    fn exclusion(&self, index: usize) -> Option<Exclusion> {
        self.reads.get(index).map(|r| r.exclusion)
    }

    /// Applies a 0x18 reply: `enabled` lists every requested register with its bit.
    pub(super) fn events_configured(
        &mut self,
        now: Duration,
        members: &[usize],
        enabled: &[(EventSource, u16, bool)],
    ) {
        let is_enabled = |register_type: RegisterType, address: u16| {
            enabled
                .iter()
                .any(|&(t, a, on)| on && t == EventSource::Register(register_type) && a == address)
        };
        let mut any = false;
        for &member in members {
            let (Some(plan), Some(state)) =
                (self.plan.reads.get(member), self.reads.get_mut(member))
            else {
                continue;
            };
            // Events of a value are enabled at its first register (see `event_ranges`).
            let on = is_enabled(plan.span.register_type, plan.span.start);
            any |= on;
            if on && plan.events == EventMode::Sporadic && state.exclusion == Exclusion::None {
                state.exclusion = Exclusion::EventsOnly;
            }
        }
        self.events_active = any;
        self.event_setup_failures = 0;
        self.event_setup_taken_up_again = false;
        self.finish_preparation(now);
    }

    /// The device has no (working) event support: poll everything.
    pub(super) fn events_refused(&mut self, now: Duration) {
        self.events_active = false;
        self.event_setup_failures = 0;
        self.event_setup_taken_up_again = false;
        self.finish_preparation(now);
    }

    /// The event setup got no readable reply (counted against the device's health by the
    /// scheduler, which may have started its preparation over): it stays due, and is tried
    /// again when the device's back-off lets it, up to [`MAX_EVENT_SETUP_TRIES`] in a row;
    /// then the device is polled. True when it was given up.
    pub(super) fn event_setup_failed(&mut self, now: Duration) -> bool {
        self.event_setup_failures = self.event_setup_failures.saturating_add(1);
        if self.event_setup_failures < MAX_EVENT_SETUP_TRIES {
            return false;
        }
        // Still to come after setup writes (a restart): `after_setup` skips it now.
        if self.preparation == Preparation::Events {
            self.events_active = false;
            self.finish_preparation(now);
        }
        true
    }

    fn finish_preparation(&mut self, now: Duration) {
        self.preparation = Preparation::Done;
        for read in &mut self.reads {
            read.next_due = now;
            read.initial_pending = !read.exclusion.never_read();
        }
    }

    /// After a reboot or a reconnection: setup, event setup and first reads all over again.
    /// Registers the device refused are asked again too: a device that restarted may have new
    /// firmware (an update reboots it), and one that was away may have been replaced.
    /// What refused reads taught goes with them: reads split apart are merged again and holes
    /// are tried again (wb-mqtt-serial turns holes back on when a device disconnects).
    /// How many leading events of this packet the previous one carried already: a device that
    /// missed the confirmation sends the old events again under the same flag, new ones
    /// appended (fast-modbus.md §6). Applied again, a queue of changes (a button's 1 then 0)
    /// would be published twice over. (A reboot event among them is acted on again all the
    /// same: the scheduler never skips one, a second setup being harmless.)
    pub(super) fn events_seen_before(&mut self, flag: u8, events: &[Event]) -> usize {
        let previous = self.last_packet.take();
        self.last_packet = Some((flag, events.len(), events_digest(events)));
        match previous {
            Some((previous_flag, count, digest))
                if previous_flag == flag
                    && count <= events.len()
                    && events
                        .get(..count)
                        .is_some_and(|prefix| events_digest(prefix) == digest) =>
            {
                count
            }
            _ => 0,
        }
    }

    pub(super) fn restart_preparation(&mut self) {
        self.preparations = self.preparations.wrapping_add(1);
        self.untrusted_packet_told = false;
        self.events_active = false;
        self.events_to_disable.clear();
        self.events_disable_sent = 0;
        self.preparation = self.first_preparation_step();
        self.continuous_read_on = false;
        self.continuous_read_refused = false;
        self.holes_off = false;
        self.split_found_refused = false;
        for read in &mut self.reads {
            if matches!(
                read.exclusion,
                Exclusion::EventsOnly | Exclusion::Unsupported
            ) {
                read.exclusion = Exclusion::None;
            }
            read.initial_pending = true;
            read.solo = false;
            read.solo_unknown = false;
            // The device that answers now may be another (replaced, or other firmware) that
            // lacks a register this one had: with continuous read on it would answer it as
            // 0xFFFE in a merged read. Found again before continuous read goes on.
            read.present = false;
        }
    }

    /// The device's firmware is known (`None`: it could not be read, taken as new enough):
    /// reads that need newer firmware are closed, the others due now. Returns the spans that
    /// were just closed.
    pub(super) fn firmware_known(
        &mut self,
        now: Duration,
        firmware: Option<&str>,
    ) -> Vec<RegisterSpan> {
        let mut closed = Vec::new();
        for (plan, read) in self.plan.reads.iter().zip(self.reads.iter_mut()) {
            let Some(required) = &plan.min_firmware else {
                continue;
            };
            let has = crate::device::firmware::firmware_has(firmware, required);
            match read.exclusion {
                Exclusion::Unreadable => {}
                Exclusion::AwaitingFirmware | Exclusion::NewerFirmware if has => {
                    read.exclusion = Exclusion::None;
                    read.initial_pending = true;
                    read.next_due = now;
                }
                Exclusion::NewerFirmware => {}
                _ if !has => {
                    read.exclusion = Exclusion::NewerFirmware;
                    read.initial_pending = false;
                    closed.push(plan.span);
                }
                _ => {}
            }
        }
        closed
    }

    /// An event carried `words` registers from `start`, part of a value read there, of a
    /// wider one it falls inside (a channel on the low word of a u32), or of one it overlaps
    /// (two u32 values sharing a register): the value's other words
    /// may have changed with it (a device updates a value at once), so the value is read once
    /// at the next turn, events-only or not, rather than joined with words read before
    /// (src/gateway/device_model.rs waits for that read).
    pub(super) fn read_partial_event_value(
        &mut self,
        register_type: RegisterType,
        start: u16,
        words: usize,
    ) {
        let event_end = u32::from(start).saturating_add(u32::try_from(words).unwrap_or(u32::MAX));
        for (plan, read) in self.plan.reads.iter().zip(self.reads.iter_mut()) {
            let value = plan.span;
            let overlaps = u32::from(value.start) < event_end && u32::from(start) < value.end();
            let holds_whole = value.start >= start && value.end() <= event_end;
            if value.register_type == register_type
                && overlaps
                && !holds_whole
                && !read.exclusion.never_read()
            {
                read.initial_pending = true;
            }
        }
    }

    /// Whether a register event fits a value this device's plan reads there: its payload must
    /// not run past the end of the read that holds its register (a payload wider than the
    /// channel says the template and device disagree, or that a frame corrupted past what its
    /// CRC caught names another register). `None` when no read holds the register; `Some(true)`
    /// for events of other sources (system events).
    pub(super) fn event_fits_plan(&self, event: &Event) -> Option<bool> {
        let EventSource::Register(register_type) = event.source else {
            return Some(true);
        };
        let words = crate::protocol::event_payload_words(&event.payload).len();
        self.plan
            .reads
            .iter()
            .filter(|plan| plan.span.register_type == register_type)
            .filter_map(|plan| {
                let offset = event.id.checked_sub(plan.span.start)?;
                (offset < plan.span.count).then(|| usize::from(plan.span.count - offset))
            })
            .max()
            .map(|room| words <= room)
    }

    /// Whether to leave `packet` unconfirmed once: it names a register no read holds, or a
    /// value wider than the read that holds it (see the scheduler). The next packet under the
    /// same flag (the device sending it again, changed or not) is taken whatever it holds: a
    /// frame corrupted past its CRC does not come twice, and a device whose packets always
    /// look so (a template that does not fit it) loses one round per packet, never more.
    pub(super) fn hold_back_unexpected(&mut self, packet: &crate::protocol::EventPacket) -> bool {
        let held_flag = self.held_back_flag.take();
        let unexpected = packet
            .events
            .iter()
            .any(|event| self.event_fits_plan(event) != Some(true));
        if !unexpected || held_flag == Some(packet.flag) {
            return false;
        }
        self.held_back_flag = Some(packet.flag);
        true
    }

    /// The reads that hold `start` are made again at the next turn (an event whose value is not
    /// taken is read instead).
    pub(super) fn read_again(&mut self, register_type: RegisterType, start: u16) {
        for (plan, read) in self.plan.reads.iter().zip(self.reads.iter_mut()) {
            let span = plan.span;
            if span.register_type == register_type
                && start >= span.start
                && start - span.start < span.count
                && !read.exclusion.never_read()
            {
                read.initial_pending = true;
            }
        }
    }

    /// Says (once per connection, then at debug level) that a packet of this device is not
    /// trusted. True the first time.
    pub(super) fn first_untrusted_packet(&mut self) -> bool {
        !std::mem::replace(&mut self.untrusted_packet_told, true)
    }

    /// A read of `members` was answered with values: if one of them had been refused (the
    /// keep-alive of a device with nothing else to read), the device at this address is not the
    /// one that refused it (replaced, or new firmware), so it is set up and read again from the
    /// start, as after a reboot. True when that happened.
    pub(super) fn refused_read_answered(&mut self, members: &[usize]) -> bool {
        let refused_before = members.iter().any(|&member| {
            self.reads
                .get(member)
                .is_some_and(|r| r.exclusion == Exclusion::Unsupported)
        });
        if refused_before {
            self.restart_preparation();
        }
        refused_before
    }

    /// True when the device came online.
    /// A Fast Modbus event came from this device: alive, whatever its own requests saw.
    pub(super) fn heard_from(&mut self, now: Duration) -> bool {
        self.health.heard_from(now)
    }

    /// True when the device came online. One whose event setup was given up for want of a
    /// reply (it may not have been there at all) gets it again, once: a device powered up
    /// after the gateway gets its events, and one that answers reads but never 0x18 costs
    /// [`MAX_EVENT_SETUP_TRIES`] more requests, not a round of them at every reconnection.
    pub(super) fn record_success(&mut self, now: Duration) -> bool {
        self.failures_since_success = FailureCounts::default();
        let came_online = self.health.record_success(now) == HealthChange::CameOnline;
        let given_up = self.event_setup_failures >= MAX_EVENT_SETUP_TRIES;
        if came_online && given_up && !self.event_setup_taken_up_again {
            self.event_setup_taken_up_again = true;
            self.event_setup_failures = 0;
            if self.preparation == Preparation::Done {
                self.preparation = self.after_setup();
            }
        }
        came_online
    }

    /// True when the device went offline (its preparation then starts over when it returns).
    pub(super) fn record_failure(&mut self, now: Duration, failure: Failure) -> bool {
        let counts = &mut self.failures_since_success;
        match failure {
            Failure::Silent => counts.silent += 1,
            Failure::Unreadable => counts.unreadable += 1,
            Failure::NotNow(code) => {
                counts.not_now += 1;
                counts.last_not_now = Some(code);
            }
        }
        let went_offline = self.health.record_failure(now) == HealthChange::WentOffline;
        if went_offline {
            self.restart_preparation();
        }
        went_offline
    }

    /// Whether nothing else keeps this device under watch, so one read that is not polled
    /// must: an events-only one, else one the device refused (its exception is an answer, so
    /// silence still means the device is gone, and a device that answers it again was
    /// replaced or updated). Without it a device that refuses every read (a wrong template at
    /// that address) would never be asked anything again and stay "online" unwatched.
    fn keepalive_index(&self) -> Option<usize> {
        let any_polled = self.reads.iter().any(|r| r.exclusion == Exclusion::None);
        if any_polled {
            return None;
        }
        self.reads
            .iter()
            .position(|r| r.exclusion == Exclusion::EventsOnly)
            .or_else(|| {
                self.reads
                    .iter()
                    .position(|r| r.exclusion == Exclusion::Unsupported)
            })
    }

    /// Whether read `index` is only ever asked as the keep-alive.
    fn is_keepalive_only(exclusion: Exclusion) -> bool {
        matches!(exclusion, Exclusion::EventsOnly | Exclusion::Unsupported)
    }

    /// When read `index` is due: `Some(ZERO)` when it is due whatever the time, `None` when
    /// only a change of state can make it due. `keepalive` is [`Self::keepalive_index`].
    fn due_from(&self, index: usize, keepalive: Option<usize>) -> Option<Duration> {
        let read = self.reads.get(index)?;
        match read.exclusion {
            Exclusion::Unsupported if keepalive == Some(index) => Some(read.next_due),
            Exclusion::Unsupported
            | Exclusion::AwaitingFirmware
            | Exclusion::NewerFirmware
            | Exclusion::Unreadable => None,
            _ if read.initial_pending => Some(Duration::ZERO),
            Exclusion::None => Some(read.next_due),
            Exclusion::EventsOnly if keepalive == Some(index) => Some(read.next_due),
            Exclusion::EventsOnly => None,
        }
    }

    fn urgency(&self, index: usize) -> ReadUrgency {
        let plan = self.plan.reads.get(index);
        let read = self.reads.get(index);
        let class = if plan.is_none_or(|p| p.period.is_none()) {
            LOW_PRIORITY
        } else {
            0
        };
        (
            class,
            read.map_or(Duration::ZERO, |r| r.next_due),
            read.and_then(|r| r.last_read),
        )
    }

    /// See [`ReadOutlook`]; the urgency is that of [`Self::choose_read`] at `now`.
    pub(super) fn read_outlook(&self, now: Duration) -> ReadOutlook {
        let keepalive = self.keepalive_index();
        let mut outlook = ReadOutlook {
            urgency: None,
            next_due: None,
        };
        for index in 0..self.reads.len() {
            match self.due_from(index, keepalive) {
                Some(at) if at <= now => {
                    let urgency = self.urgency(index);
                    if outlook.urgency.is_none_or(|best| urgency < best) {
                        outlook.urgency = Some(urgency);
                    }
                }
                Some(at) if outlook.next_due.is_none_or(|next| at < next) => {
                    outlook.next_due = Some(at);
                }
                _ => {}
            }
        }
        outlook
    }

    pub(super) fn choose_read(&self, now: Duration) -> Option<ReadChoice> {
        self.choose_read_where(now, |_| true)
    }

    /// [`Self::choose_read`] starting with a read of a channel without a read period.
    pub(super) fn choose_low_priority_read(&self, now: Duration) -> Option<ReadChoice> {
        self.choose_read_where(now, |urgency| urgency.0 == LOW_PRIORITY)
    }

    fn choose_read_where(
        &self,
        now: Duration,
        first_may_be: impl Fn(ReadUrgency) -> bool,
    ) -> Option<ReadChoice> {
        let keepalive = self.keepalive_index();
        let is_due = |i: usize| self.due_from(i, keepalive).is_some_and(|at| at <= now);
        let urgency = |i: usize| self.urgency(i);
        let first = (0..self.reads.len())
            .filter(|&i| is_due(i) && first_may_be(urgency(i)))
            .min_by_key(|&i| urgency(i))?;
        let first_span = self.plan.reads.get(first)?.span;
        let mut span = first_span;
        let mut members = vec![first];
        if !self.reads_alone(first) {
            // The due reads after the first, by span: `by_span` is in that order already.
            let followers = self
                .by_span
                .iter()
                .copied()
                .filter(|&i| i != first && is_due(i) && !self.reads_alone(i))
                .filter_map(|i| self.plan.reads.get(i).map(|p| (p.span, i)))
                .filter(|(s, _)| {
                    s.register_type == first_span.register_type && s.start >= first_span.start
                });
            span = self.merge_followers(span, followers, &mut members);
        }
        Some(ReadChoice {
            span,
            members,
            urgency: urgency(first),
        })
    }

    /// [`Self::choose_read`] as it was written first (collecting and sorting the due reads):
    /// the unit tests check the two agree.
    #[cfg(test)]
    pub(super) fn choose_read_by_sorting(&self, now: Duration) -> Option<ReadChoice> {
        let keepalive = self.keepalive_index();
        let due: Vec<usize> = (0..self.reads.len())
            .filter(|&i| self.due_from(i, keepalive).is_some_and(|at| at <= now))
            .collect();
        let urgency = |i: usize| self.urgency(i);
        let first = *due.iter().min_by_key(|&&i| urgency(i))?;
        let first_span = self.plan.reads.get(first)?.span;
        let mut span = first_span;
        let mut members = vec![first];
        if !self.reads_alone(first) {
            let mut followers: Vec<(RegisterSpan, usize)> = due
                .iter()
                .filter(|&&i| i != first && !self.reads_alone(i))
                .filter_map(|&i| self.plan.reads.get(i).map(|p| (p.span, i)))
                .filter(|(s, _)| s.register_type == span.register_type && s.start >= span.start)
                .collect();
            followers.sort();
            span = self.merge_followers(span, followers, &mut members);
        }
        Some(ReadChoice {
            span,
            members,
            urgency: urgency(first),
        })
    }

    /// `span` extended over `followers` (in span order) as far as the merge limits allow; the
    /// reads taken join `members`.
    fn merge_followers(
        &self,
        mut span: RegisterSpan,
        followers: impl IntoIterator<Item = (RegisterSpan, usize)>,
        members: &mut Vec<usize>,
    ) -> RegisterSpan {
        let limits = self.merge_limits();
        for (next, index) in followers {
            match limits.extend(span, next) {
                Some(extended) => {
                    span = extended;
                    members.push(index);
                }
                None => break,
            }
        }
        span
    }

    /// Whether a read of `members` is only the keep-alive read of a device with nothing polled
    /// (values all by events, or every read refused; not a first read).
    pub(super) fn is_keepalive_read(&self, members: &[usize]) -> bool {
        !members.is_empty()
            && members.iter().all(|&member| {
                self.reads
                    .get(member)
                    .is_some_and(|r| Self::is_keepalive_only(r.exclusion) && !r.initial_pending)
            })
    }

    pub(super) fn read_span(&self, index: usize) -> Option<RegisterSpan> {
        self.plan.reads.get(index).map(|r| r.span)
    }

    fn reschedule(&mut self, now: Duration, index: usize) {
        let keepalive = self.keepalive_index() == Some(index);
        let planned = self.plan.reads.get(index);
        let period = planned.and_then(|p| p.period);
        let rate_limit = planned.and_then(|p| p.rate_limit);
        if let Some(read) = self.reads.get_mut(index) {
            read.next_due = match (keepalive, period) {
                (true, _) => now + KEEPALIVE_PERIOD,
                // From when it was due, not from when it was made: counted from the read, every
                // period was lengthened by the wait for the transaction under way. A read more
                // than half a period late counts from now: a bus that cannot keep the period is
                // not given to this read alone (the others starved at 1200 baud).
                (false, Some(period)) => {
                    let due = read.next_due;
                    if now.saturating_sub(due) <= period / 2 {
                        due + period
                    } else {
                        now + period
                    }
                }
                // Round-robin: due again at once (or when its rate limit allows), ordered by
                // when it was last read.
                (false, None) => now + rate_limit.unwrap_or(Duration::ZERO),
            };
        }
    }

    /// Records a good read. Returns the new state of the read's "period missed" flag when it
    /// changed: decided once the intervals since the last decision cover ten periods (10 s at
    /// least), set when their average is 10 % over the period, kept until the next decision.
    pub(super) fn read_done(&mut self, now: Duration, index: usize) -> Option<bool> {
        let period = self.plan.reads.get(index).and_then(|p| p.period);
        let read = self.reads.get_mut(index)?;
        read.solo_unknown = false;
        read.present = true;
        let previous = read.last_read.replace(now);
        let was_initial = std::mem::replace(&mut read.initial_pending, false);
        let mut changed = None;
        if let (Some(period), Some(previous), false) = (period, previous, was_initial) {
            let (total, reads) = &mut read.interval_window;
            *total += now.saturating_sub(previous);
            *reads += 1;
            if *total >= (period * 10).max(PERIOD_CHECK_MIN_WINDOW) {
                let average = total.as_secs_f64() / f64::from(*reads);
                let missed = average >= period.as_secs_f64() * 1.1;
                read.interval_window = (Duration::ZERO, 0);
                if missed != read.period_missed {
                    read.period_missed = missed;
                    changed = Some(missed);
                }
            }
        }
        self.reschedule(now, index);
        self.merge_again_once_split_reads_are_known();
        changed
    }

    pub(super) fn read_failed(&mut self, now: Duration, index: usize, unsupported: bool) {
        if let Some(read) = self.reads.get_mut(index) {
            read.last_read = Some(now);
            if unsupported {
                read.exclusion = Exclusion::Unsupported;
                read.initial_pending = false;
                if std::mem::take(&mut read.solo_unknown) {
                    self.split_found_refused = true;
                }
            }
        }
        self.reschedule(now, index);
        self.merge_again_once_split_reads_are_known();
    }

    /// Marks the planned read of `span` unsupported (not read until the device restarts);
    /// false when there is none or it already was.
    pub(super) fn stop_reading(&mut self, now: Duration, span: RegisterSpan) -> bool {
        let Some(index) = self.plan.reads.iter().position(|r| r.span == span) else {
            return false;
        };
        if self.reads.get(index).map(|r| r.exclusion) == Some(Exclusion::Unsupported) {
            return false;
        }
        self.read_failed(now, index, true);
        true
    }

    /// A merged read was refused: read each part on its own to find the unsupported one.
    /// Once each has answered or been refused, the others are merged again (without the
    /// refused ones, which are no longer read), as wb-mqtt-serial marks only the refused
    /// register unavailable and goes on merging the rest (`UnavailableRegisterInTheMiddle`).
    /// A read over unconfigured registers is first tried again without holes.
    pub(super) fn split_reads(&mut self, now: Duration, members: &[usize]) {
        let without_holes = !self.holes_off && self.has_holes(members);
        self.holes_off |= without_holes;
        for &member in members {
            if let Some(read) = self.reads.get_mut(member) {
                if !without_holes {
                    read.solo = true;
                    read.solo_unknown = true;
                }
                read.next_due = now;
            }
        }
    }

    /// Whether the reads `members` leave registers between them unread (holes). Not the words a
    /// read asks past its last member for `min_read_registers`, and reads that overlap (a value
    /// and bit fields of its registers) do not hide a hole.
    fn has_holes(&self, members: &[usize]) -> bool {
        let mut spans: Vec<RegisterSpan> =
            members.iter().filter_map(|&m| self.read_span(m)).collect();
        spans.sort_unstable_by_key(|s| s.start);
        let mut covered_to: Option<u32> = None;
        for span in spans {
            if covered_to.is_some_and(|end| u32::from(span.start) > end) {
                return true;
            }
            covered_to = Some(covered_to.map_or(span.end(), |end| end.max(span.end())));
        }
        false
    }

    /// The merge limits in force: the plan's, with wb-mqtt-serial's holes (10 registers, 80
    /// bits) at least while continuous read is on, and without holes once a read over them was
    /// refused.
    fn merge_limits(&self) -> super::read_plan::MergeLimits {
        let mut limits = self.plan.merge;
        if self.continuous_read_on {
            limits.max_register_hole = limits.max_register_hole.max(CONTINUOUS_READ_REGISTER_HOLE);
            limits.max_bit_hole = limits.max_bit_hole.max(CONTINUOUS_READ_BIT_HOLE);
        }
        if self.holes_off {
            limits.max_register_hole = 0;
            limits.max_bit_hole = 0;
        }
        limits
    }

    /// When every read split off has answered or been refused on its own: if one was refused,
    /// the rest are merged again; if none was, the device refuses the merged read itself (a
    /// limit of its own on long reads) and they stay apart, as before.
    fn merge_again_once_split_reads_are_known(&mut self) {
        if !self.split_found_refused || self.reads.iter().any(|r| r.solo && r.solo_unknown) {
            return;
        }
        self.split_found_refused = false;
        for read in &mut self.reads {
            read.solo = false;
        }
    }

    /// When this device next has something to do (for an idle port's sleep); reads of channels
    /// without a read period not before `low_priority_held_until` (`rate_limit`).
    pub(super) fn next_deadline(
        &self,
        low_priority_held_until: Option<Duration>,
    ) -> Option<Duration> {
        let retry = self.health.retry_at();
        let reads = (0..self.reads.len())
            .filter(|&i| match self.reads.get(i).map(|r| r.exclusion) {
                Some(Exclusion::None) => true,
                Some(exclusion) if Self::is_keepalive_only(exclusion) => {
                    self.keepalive_index() == Some(i)
                }
                _ => false,
            })
            .filter_map(|i| {
                let due = self.reads.get(i)?.next_due;
                let periodic = self.plan.reads.get(i).is_some_and(|p| p.period.is_some());
                Some(match low_priority_held_until {
                    Some(held) if !periodic => due.max(held),
                    _ => due,
                })
            })
            .min();
        match (reads, retry) {
            (Some(read), Some(retry)) => Some(read.max(retry)),
            (read, retry) => read.or(retry),
        }
    }
}

fn events_digest(events: &[Event]) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut hasher = std::collections::hash_map::DefaultHasher::new();
    events.hash(&mut hasher);
    hasher.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TemplateFile;
    use crate::device::resolve_template_device;
    use crate::protocol::{hex, Request};

    fn counter8() -> DeviceState {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("templates/rtu2mqtt-counter8.json");
        let template = TemplateFile::load(&path).unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({"slave_id": 20})).unwrap();
        DeviceState::new(
            crate::gateway::port_plan::device_plan(&device),
            true,
            &LineSettings::WIREN_BOARD_DEFAULT,
        )
    }

    /// Issue 15 defect 1: one entry per value at its first register; the second words of the
    /// u32 counters (61, 63, …) are holes filled with priority 0 inside one record.
    #[test]
    fn events_are_enabled_once_per_value() {
        let device = counter8();
        let (ranges, members) = device.event_ranges();
        let request = Request::configure_events(20, ranges).encode().unwrap();
        // The template has no setup writes: the reboot event is disabled at the end (its
        // power-on report dropped), as wb-mqtt-serial does.
        let list = "24 \
             02 0000 08 01 01 01 01 01 01 01 01 \
             04 003C 0F 01 00 01 00 01 00 01 00 01 00 01 00 01 00 01 \
             0F 0000 01 00";
        let expected = crate::protocol::parse_hex(&format!("14 46 18 {list}")).unwrap();
        assert_eq!(
            hex(request.get(..request.len() - 2).unwrap()),
            hex(&expected)
        );
        assert_eq!(members.len(), 16);
    }

    /// A device with setup writes keeps its power-on reboot event: a reboot between its setup
    /// and its event setup must still be reported, or the setup would be lost unnoticed.
    #[test]
    fn a_device_with_setup_writes_keeps_its_reboot_event() {
        let mut plan = counter8().plan;
        plan.setup.push(crate::port::plan::SetupWrite {
            register_type: RegisterType::Holding,
            address: 100,
            values: vec![7],
            force_multiple: false,
            kept_bits: Vec::new(),
        });
        let device = DeviceState::new(plan, true, &LineSettings::WIREN_BOARD_DEFAULT);
        let (ranges, _) = device.event_ranges();
        assert_eq!(ranges.len(), 2);
        assert!(ranges
            .iter()
            .all(|r| matches!(r.source, EventSource::Register(_))));
    }

    /// A value counts as event-driven when its first register is enabled.
    #[test]
    fn a_value_is_evented_when_its_first_register_is() {
        let mut device = counter8();
        let (_, members) = device.event_ranges();
        let counter = device
            .plan
            .reads
            .iter()
            .position(|r| r.span.register_type == RegisterType::Input && r.span.start == 60)
            .unwrap();
        let input = EventSource::Register(RegisterType::Input);
        device.events_configured(
            Duration::ZERO,
            &members,
            &[(input, 60, true), (input, 61, false)],
        );
        assert!(device.events_active());
        assert_eq!(device.exclusion(counter), Some(Exclusion::EventsOnly));
    }
}
