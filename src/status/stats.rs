//! What the status page and `/metrics` know of one port, kept by its port task from outcomes it
//! already sees: plain integers, updated once per transaction and only while the status server is
//! on. Pure: time is passed in (the port task's clock), nothing here knows tokio.

use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use crate::device_updates::{DeviceUpdate, ErrorFlags};
use crate::port::{DeviceReport, Transaction, TransactionOutcome};
use crate::protocol::fast::{FastReply, FastRequest};
use crate::protocol::{Reply, ReplyBody, RequestBody, ResponsePdu};

/// Rates and bus utilisation are averaged over this many whole seconds.
pub const WINDOW_SECONDS: u64 = 10;
/// Per-second buckets kept: the window plus the second in progress.
const BUCKETS: usize = WINDOW_SECONDS as usize + 1;
/// Recent frames kept per device for its frames log.
pub const FRAMES_PER_DEVICE: usize = 40;
/// Upper bounds (ms) of the event round-trip histogram's buckets; the last bucket is +Inf.
pub const LATENCY_BOUNDS_MS: [u64; 12] =
    [5, 10, 20, 50, 100, 200, 300, 500, 1000, 2000, 5000, 10000];

/// Errors by kind, as the status page and `/metrics` count them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ErrorCounts {
    /// No reply before the timeout.
    pub timeout: u64,
    /// Bytes came, but no valid frame (bad CRC, a collision, noise).
    pub bad_crc: u64,
    /// The device answered with a Modbus exception.
    pub exception: u64,
    /// A reply came, but another master had just asked that device: it was not taken (it may
    /// answer the other master's request).
    pub another_master: u64,
}

impl ErrorCounts {
    fn count(&mut self, kind: Option<ErrorKind>) {
        match kind {
            Some(ErrorKind::Timeout) => self.timeout += 1,
            Some(ErrorKind::BadCrc) => self.bad_crc += 1,
            Some(ErrorKind::Exception) => self.exception += 1,
            Some(ErrorKind::AnotherMaster) => self.another_master += 1,
            None => {}
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ErrorKind {
    Timeout,
    BadCrc,
    Exception,
    AnotherMaster,
}

fn error_kind(outcome: &TransactionOutcome, another_master: bool) -> Option<ErrorKind> {
    match outcome {
        TransactionOutcome::NoReply => Some(ErrorKind::Timeout),
        TransactionOutcome::Garbled if another_master => Some(ErrorKind::AnotherMaster),
        TransactionOutcome::Garbled => Some(ErrorKind::BadCrc),
        TransactionOutcome::Reply(Reply {
            body: ReplyBody::Classic(ResponsePdu::Exception { .. }),
            ..
        }) => Some(ErrorKind::Exception),
        TransactionOutcome::Reply(Reply {
            body:
                ReplyBody::Fast {
                    reply:
                        FastReply::BySerial {
                            pdu: ResponsePdu::Exception { .. },
                            ..
                        },
                    ..
                },
            ..
        }) => Some(ErrorKind::Exception),
        TransactionOutcome::Reply(_) => None,
    }
}

/// Totals since the port task started.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PortTotals {
    pub transactions: u64,
    pub event_rounds: u64,
    /// Event rounds that brought events.
    pub event_rounds_with_events: u64,
    pub errors: ErrorCounts,
    /// Time the line was busy with transactions (request, waiting, reply).
    pub busy: Duration,
    /// When a reply was last not taken because another master had just asked its device.
    pub another_master_at: Option<Duration>,
}

#[derive(Debug, Clone, Copy, Default)]
struct Bucket {
    second: u64,
    transactions: u64,
    event_rounds: u64,
    busy: Duration,
}

/// A cumulative histogram in Prometheus' sense: `counts[i]` are observations `<= bounds[i]`,
/// the last one (+Inf) is all of them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Histogram {
    pub counts: [u64; LATENCY_BOUNDS_MS.len() + 1],
    pub sum: Duration,
    pub count: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Self {
            counts: [0; LATENCY_BOUNDS_MS.len() + 1],
            sum: Duration::ZERO,
            count: 0,
        }
    }
}

impl Histogram {
    pub fn observe(&mut self, value: Duration) {
        let ms = value.as_millis();
        for (bound, count) in LATENCY_BOUNDS_MS.iter().zip(self.counts.iter_mut()) {
            if ms <= u128::from(*bound) {
                *count += 1;
            }
        }
        self.counts[LATENCY_BOUNDS_MS.len()] += 1;
        self.sum += value;
        self.count += 1;
    }
}

/// One request and what came back, kept for a device's frames log (decoded only when asked).
#[derive(Debug, Clone)]
pub struct FrameRecord {
    pub at: Duration,
    pub request: crate::protocol::Request,
    pub outcome: TransactionOutcome,
    /// From the start of the request to the outcome.
    pub took: Duration,
}

/// The last known value of a control and where it came from.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ControlState {
    pub value: Option<String>,
    pub errors: ErrorFlags,
    pub from_event: bool,
    pub updated: Option<Duration>,
}

#[derive(Debug, Clone, Default)]
pub struct DeviceStats {
    pub address: u8,
    pub online: bool,
    pub last_seen: Option<Duration>,
    pub transactions: u64,
    pub errors: ErrorCounts,
    /// The scheduler's view, copied once a second.
    pub schedule: Option<DeviceReport>,
    pub controls: BTreeMap<String, ControlState>,
    pub frames: VecDeque<FrameRecord>,
    /// Start of the first event request since this device last reported events or an event round
    /// came back empty: the first request that could have carried a change it reports now.
    event_pending_since: Option<Duration>,
}

/// The counters of one port.
#[derive(Debug, Clone, Default)]
pub struct PortStats {
    pub open: bool,
    pub totals: PortTotals,
    buckets: [Bucket; BUCKETS],
    pub event_latency: Histogram,
    pub devices: Vec<DeviceStats>,
    /// Device ids in port order (to map updates to devices).
    device_ids: Vec<String>,
    /// When the schedule of the devices was last copied from the scheduler.
    schedule_second: Option<u64>,
}

/// Rates over the last [`WINDOW_SECONDS`] whole seconds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PortRates {
    /// Share of the window the line was busy, 0..=100.
    pub bus_utilisation_percent: f64,
    pub transactions_per_second: f64,
    pub event_rounds_per_second: f64,
}

impl PortStats {
    /// `devices`: (MQTT id, slave address) in port order.
    pub fn new(devices: &[(String, u8)]) -> Self {
        Self {
            devices: devices
                .iter()
                .map(|(_, address)| DeviceStats {
                    address: *address,
                    ..DeviceStats::default()
                })
                .collect(),
            device_ids: devices.iter().map(|(id, _)| id.clone()).collect(),
            ..Self::default()
        }
    }

    /// A copy for a view: everything but the frames logs (which only their own view reads).
    pub fn copy_without_frames(&self) -> Self {
        Self {
            open: self.open,
            totals: self.totals,
            buckets: self.buckets,
            event_latency: self.event_latency.clone(),
            devices: self
                .devices
                .iter()
                .map(|device| DeviceStats {
                    address: device.address,
                    online: device.online,
                    last_seen: device.last_seen,
                    transactions: device.transactions,
                    errors: device.errors,
                    schedule: device.schedule.clone(),
                    controls: device.controls.clone(),
                    frames: VecDeque::new(),
                    event_pending_since: device.event_pending_since,
                })
                .collect(),
            device_ids: Vec::new(),
            schedule_second: self.schedule_second,
        }
    }

    pub fn device_ids(&self) -> &[String] {
        &self.device_ids
    }

    pub fn set_open(&mut self, open: bool) {
        self.open = open;
    }

    fn bucket(&mut self, now: Duration) -> &mut Bucket {
        let second = now.as_secs();
        let slot = &mut self.buckets[(second % BUCKETS as u64) as usize];
        if slot.second != second {
            *slot = Bucket {
                second,
                ..Bucket::default()
            };
        }
        slot
    }

    fn device_by_address(&self, address: u8) -> Option<usize> {
        self.devices.iter().position(|d| d.address == address)
    }

    /// A transaction ended: count it, its errors and its wire time; keep it in its device's log.
    /// `another_master`: its reply was not taken because another master had just asked the
    /// device ([`crate::protocol::ReplyTiming::another_master`]). Returns the device whose
    /// events it brought, if any, for [`Self::events_published`].
    pub fn transaction_done(
        &mut self,
        started: Duration,
        now: Duration,
        transaction: &Transaction,
        outcome: &TransactionOutcome,
        another_master: bool,
    ) -> Option<usize> {
        let took = now.saturating_sub(started);
        let kind = error_kind(outcome, another_master);
        if kind == Some(ErrorKind::AnotherMaster) {
            self.totals.another_master_at = Some(now);
        }
        let event_round = matches!(
            transaction.request.body,
            RequestBody::Fast(FastRequest::PollEvents(_))
        );
        self.totals.transactions += 1;
        self.totals.busy += took;
        self.totals.errors.count(kind);
        let bucket = self.bucket(started);
        bucket.transactions += 1;
        bucket.busy += took;
        if event_round {
            bucket.event_rounds += 1;
            self.totals.event_rounds += 1;
            // This request could carry any change not yet reported.
            for device in &mut self.devices {
                device.event_pending_since.get_or_insert(started);
            }
        }
        // The device the frames belong to: the one addressed, or for an event round the one
        // that won the arbitration.
        let (device, events_from) = match outcome {
            TransactionOutcome::Reply(Reply {
                address,
                body:
                    ReplyBody::Fast {
                        reply: FastReply::Events(_),
                        ..
                    },
            }) if event_round => {
                self.totals.event_rounds_with_events += 1;
                let device = self.device_by_address(*address);
                (device, device)
            }
            TransactionOutcome::Reply(Reply {
                body:
                    ReplyBody::Fast {
                        reply: FastReply::NoEvents,
                        ..
                    },
                ..
            }) if event_round => {
                // Nobody had anything: every change from now on is carried from the next round.
                for device in &mut self.devices {
                    device.event_pending_since = None;
                }
                (None, None)
            }
            _ if event_round => (None, None),
            _ => (self.device_by_address(transaction.request.address), None),
        };
        if let Some(stats) = device.and_then(|d| self.devices.get_mut(d)) {
            stats.transactions += 1;
            stats.errors.count(kind);
            if matches!(outcome, TransactionOutcome::Reply(_)) {
                stats.last_seen = Some(now);
            }
            if stats.frames.len() == FRAMES_PER_DEVICE {
                stats.frames.pop_front();
            }
            stats.frames.push_back(FrameRecord {
                at: started,
                request: transaction.request.clone(),
                outcome: outcome.clone(),
                took,
            });
        }
        events_from
    }

    /// The events of `device`'s round were handed to MQTT at `now`: one round-trip observation.
    pub fn events_published(&mut self, device: usize, now: Duration) {
        let Some(stats) = self.devices.get_mut(device) else {
            return;
        };
        if let Some(since) = stats.event_pending_since.take() {
            self.event_latency.observe(now.saturating_sub(since));
        }
    }

    /// Whether the scheduler's view of the devices is due to be copied (once a second).
    pub fn schedule_due(&mut self, now: Duration) -> bool {
        let second = now.as_secs();
        if self.schedule_second == Some(second) {
            return false;
        }
        self.schedule_second = Some(second);
        true
    }

    pub fn set_schedule(&mut self, device: usize, report: Option<DeviceReport>) {
        if let Some(stats) = self.devices.get_mut(device) {
            stats.schedule = report;
        }
    }

    /// What the device models told MQTT: values, error flags, online.
    pub fn observe_update(&mut self, update: &DeviceUpdate, now: Duration) {
        let (device_id, control_id): (&str, Option<&str>) = match update {
            DeviceUpdate::Value {
                device_id,
                control_id,
                ..
            } => (device_id, Some(control_id)),
            DeviceUpdate::ControlError {
                device_id,
                control_id,
                ..
            } => (device_id, Some(control_id)),
            DeviceUpdate::Online { device_id, .. } => (device_id, None),
            _ => return,
        };
        let Some(index) = self.device_ids.iter().position(|id| id == device_id) else {
            return;
        };
        let device = &mut self.devices[index];
        match update {
            DeviceUpdate::Value {
                value,
                from_event,
                changed,
                ..
            } => {
                let control_id = control_id.unwrap_or_default();
                // Looked up before an entry is made: most values are of known controls.
                if !device.controls.contains_key(control_id) {
                    device
                        .controls
                        .insert(control_id.to_owned(), ControlState::default());
                }
                let Some(control) = device.controls.get_mut(control_id) else {
                    return;
                };
                // The source is how the value last changed: a poll that confirms what an event
                // brought does not make it a polled value.
                if *changed || control.value.is_none() {
                    control.from_event = *from_event;
                    control.updated = Some(now);
                }
                if control.value.as_deref() != Some(&**value) {
                    control.value = Some(value.to_string());
                }
            }
            DeviceUpdate::ControlError { errors, .. } => {
                device
                    .controls
                    .entry(control_id.unwrap_or_default().to_owned())
                    .or_default()
                    .errors = *errors;
            }
            DeviceUpdate::Online { online, .. } => device.online = *online,
            _ => {}
        }
    }

    /// Rates over the last whole seconds before `now` (fewer at start-up).
    pub fn rates(&self, now: Duration) -> PortRates {
        let current = now.as_secs();
        let span = WINDOW_SECONDS.min(current);
        if span == 0 {
            return PortRates::default();
        }
        let first = current - span;
        let mut transactions = 0;
        let mut event_rounds = 0;
        let mut busy = Duration::ZERO;
        for bucket in &self.buckets {
            if bucket.second >= first && bucket.second < current {
                transactions += bucket.transactions;
                event_rounds += bucket.event_rounds;
                busy += bucket.busy;
            }
        }
        let seconds = span as f64;
        PortRates {
            bus_utilisation_percent: (busy.as_secs_f64() / seconds * 100.0).min(100.0),
            transactions_per_second: transactions as f64 / seconds,
            event_rounds_per_second: event_rounds as f64 / seconds,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::fast::{EventPacket, EventPoll};
    use crate::protocol::{Request, RequestPdu};

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    fn transaction(request: Request) -> Transaction {
        Transaction {
            request,
            request_time: ms(1),
            reply_timeout: ms(50),
            first_byte_timeout: None,
            late_window: ms(0),
            estimated: ms(10),
        }
    }

    fn read(address: u8) -> Transaction {
        transaction(Request::classic(
            address,
            RequestPdu::ReadHoldingRegisters { start: 0, count: 1 },
        ))
    }

    fn event_poll() -> Transaction {
        transaction(Request::poll_events(EventPoll {
            min_address: 1,
            max_data_len: 100,
            ack_address: 0,
            ack_flag: 0,
        }))
    }

    fn stats() -> PortStats {
        PortStats::new(&[("a".into(), 1), ("b".into(), 2)])
    }

    #[test]
    fn errors_are_counted_by_kind_for_port_and_device() {
        let mut stats = stats();
        stats.transaction_done(ms(0), ms(10), &read(1), &TransactionOutcome::NoReply, false);
        stats.transaction_done(
            ms(10),
            ms(20),
            &read(2),
            &TransactionOutcome::Garbled,
            false,
        );
        let exception = TransactionOutcome::Reply(Reply {
            address: 2,
            body: ReplyBody::Classic(ResponsePdu::Exception {
                function: 3,
                code: crate::protocol::ExceptionCode(2),
            }),
        });
        stats.transaction_done(ms(20), ms(30), &read(2), &exception, false);
        // A reply not taken because another master had just asked the device: no bad CRC.
        stats.transaction_done(ms(30), ms(40), &read(1), &TransactionOutcome::Garbled, true);
        assert_eq!(
            stats.totals.errors,
            ErrorCounts {
                timeout: 1,
                bad_crc: 1,
                exception: 1,
                another_master: 1,
            }
        );
        assert_eq!(stats.devices[0].errors.another_master, 1);
        assert_eq!(stats.totals.another_master_at, Some(ms(40)));
        assert_eq!(stats.devices[0].errors.timeout, 1);
        assert_eq!(stats.devices[1].errors.bad_crc, 1);
        assert_eq!(stats.devices[1].errors.exception, 1);
        // An exception is an answer: the device was seen.
        assert_eq!(stats.devices[1].last_seen, Some(ms(30)));
        assert_eq!(stats.devices[0].last_seen, None);
        assert_eq!(stats.devices[1].frames.len(), 2);
    }

    #[test]
    fn rates_cover_the_last_whole_seconds() {
        let mut stats = stats();
        // 20 transactions of 100 ms each in second 1: 2 s busy over a 10 s window at second 11.
        for i in 0..20 {
            let start = ms(1000 + i * 40);
            stats.transaction_done(
                start,
                start + ms(100),
                &read(1),
                &TransactionOutcome::NoReply,
                false,
            );
        }
        let rates = stats.rates(ms(11_500));
        assert_eq!(rates.transactions_per_second, 2.0);
        assert!((rates.bus_utilisation_percent - 20.0).abs() < 1e-9);
        // Second 1 has left the window by second 12.
        assert_eq!(stats.rates(ms(12_000)).transactions_per_second, 0.0);
    }

    #[test]
    fn event_round_trip_counts_from_the_first_round_that_could_carry_it() {
        let mut stats = stats();
        let nothing = TransactionOutcome::Reply(Reply::fast(0xFD, FastReply::NoEvents));
        assert_eq!(
            stats.transaction_done(ms(0), ms(5), &event_poll(), &nothing, false),
            None
        );
        // Round at 100 ms: device 2 wins, device 1 still has its change pending.
        let events = TransactionOutcome::Reply(Reply::fast(
            2,
            FastReply::Events(EventPacket {
                flag: 0,
                event_count: 0,
                events: Vec::new(),
            }),
        ));
        let from = stats.transaction_done(ms(100), ms(110), &event_poll(), &events, false);
        assert_eq!(from, Some(1));
        stats.events_published(1, ms(112));
        let events_of_1 = TransactionOutcome::Reply(Reply::fast(
            1,
            FastReply::Events(EventPacket {
                flag: 0,
                event_count: 0,
                events: Vec::new(),
            }),
        ));
        assert_eq!(
            stats.transaction_done(ms(200), ms(210), &event_poll(), &events_of_1, false),
            Some(0)
        );
        stats.events_published(0, ms(215));
        assert_eq!(stats.event_latency.count, 2);
        assert_eq!(stats.event_latency.sum, ms(12) + ms(115));
        // 12 ms is within 20 ms, 115 ms only within 200 ms.
        assert_eq!(stats.event_latency.counts[1], 0);
        assert_eq!(stats.event_latency.counts[2], 1);
        assert_eq!(stats.event_latency.counts[5], 2);
        assert_eq!(stats.totals.event_rounds, 3);
        assert_eq!(stats.totals.event_rounds_with_events, 2);
    }

    #[test]
    fn updates_set_control_values_and_their_source() {
        let mut stats = stats();
        stats.observe_update(
            &DeviceUpdate::Value {
                device_id: "b".into(),
                control_id: "K1".into(),
                value: "1".into(),
                from_event: true,
                changed: true,
            },
            ms(5),
        );
        stats.observe_update(
            &DeviceUpdate::Online {
                device_id: "b".into(),
                online: true,
            },
            ms(5),
        );
        // A poll that reads the same value again leaves the source at "event".
        stats.observe_update(
            &DeviceUpdate::Value {
                device_id: "b".into(),
                control_id: "K1".into(),
                value: "1".into(),
                from_event: false,
                changed: false,
            },
            ms(6),
        );
        let control = &stats.devices[1].controls["K1"];
        assert_eq!(control.value.as_deref(), Some("1"));
        assert!(control.from_event);
        assert_eq!(control.updated, Some(ms(5)));
        assert!(stats.devices[1].online);
        assert!(!stats.devices[0].online);
    }
}
