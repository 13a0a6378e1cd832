//! When the bytes read after a request count as its reply, sans IO: times are durations on the
//! transport's own clock, passed in by the caller.
//!
//! An RTU reply carries no transaction number: a reply to request N that comes after N's timeout
//! looks exactly like the reply to request N+1 when both ask the same device the same thing.
//! So:
//! - the reply clock starts when the request has left the wire (its wire time after `write`
//!   returned), not when `write` returned;
//! - on a serial line, bytes that arrive before the request has left the wire cannot be its reply
//!   (echo, a collision, a straggler) and are thrown away;
//! - after a timeout the line is watched a while longer (the late window): whatever arrives then
//!   is thrown away and reported as a late reply (the scheduler learns a longer timeout for the
//!   device), and the next request waits until the line has been quiet for a frame gap.

use std::time::Duration;

use crate::protocol::{ReplyTiming, Transaction};

/// Longest a babbling line may keep the transport draining after a failed transaction, so that a
/// stuck transmitter cannot stall the port forever.
const MAX_DRAIN: Duration = Duration::from_secs(1);

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Bytes may be the reply.
    Waiting,
    /// The reply failed; bytes are thrown away until `until` and a frame gap of silence.
    Draining {
        until: Duration,
        cap: Duration,
    },
    Finished,
}

/// What to do with bytes that just arrived.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Received {
    /// Hand them to the reply parser.
    Reply,
    /// Throw them away.
    Discard,
}

/// The reply window of one transaction.
#[derive(Debug, Clone)]
pub struct ReplyWindow {
    /// The earliest the request can have left the wire: bytes before cannot be its reply.
    request_end: Duration,
    /// Where the reply clock starts: the request's end, or when `write` returned if later (the
    /// task may have been preempted).
    clock_start: Duration,
    discard_early: bool,
    first_byte_deadline: Option<Duration>,
    deadline: Duration,
    late_window: Duration,
    quiet_gap: Duration,
    phase: Phase,
    first_byte_at: Option<Duration>,
    /// False when the reply's bytes were read in one go after a sleep: `first_byte_at` is then
    /// only the time they were read, an upper bound of when the first came.
    first_byte_exact: bool,
    last_byte_at: Option<Duration>,
    late_byte_at: Option<Duration>,
}

impl ReplyWindow {
    /// `write_started`/`write_returned`: around the `write` of the request. `quiet_gap`: the
    /// silence that ends a frame (and after which the line counts as quiet). `discard_early`: a
    /// serial line, whose timing is known.
    pub fn new(
        transaction: &Transaction,
        (write_started, write_returned): (Duration, Duration),
        quiet_gap: Duration,
        discard_early: bool,
    ) -> Self {
        let request_end = write_started.saturating_add(transaction.request_time);
        let clock_start = request_end.max(write_returned);
        Self {
            request_end,
            clock_start,
            discard_early,
            first_byte_deadline: transaction
                .first_byte_timeout
                .map(|timeout| clock_start.saturating_add(timeout)),
            deadline: clock_start.saturating_add(transaction.reply_timeout),
            late_window: transaction.late_window,
            quiet_gap,
            phase: Phase::Waiting,
            first_byte_at: None,
            first_byte_exact: true,
            last_byte_at: None,
            late_byte_at: None,
        }
    }

    /// When the reply's first byte is due at the latest: the first-byte timeout, else the
    /// reply's.
    pub fn first_byte_deadline(&self) -> Duration {
        self.first_byte_deadline.unwrap_or(self.deadline)
    }

    /// True once bytes counted as the reply arrived.
    pub fn has_reply_bytes(&self) -> bool {
        self.first_byte_at.is_some()
    }

    /// When the request has left the wire (at the earliest).
    pub fn request_end(&self) -> Duration {
        self.request_end
    }

    /// Where the reply clock starts.
    pub fn clock_start(&self) -> Duration {
        self.clock_start
    }

    pub fn is_finished(&self) -> bool {
        self.phase == Phase::Finished
    }

    /// True while bytes may still be the reply.
    pub fn is_waiting(&self) -> bool {
        self.phase == Phase::Waiting
    }

    /// When the last bytes that count as the reply arrived.
    pub fn last_byte_at(&self) -> Option<Duration> {
        self.first_byte_at.and(self.last_byte_at)
    }

    /// When to call [`expire`](Self::expire) if no bytes come before.
    pub fn wake_at(&self) -> Duration {
        match self.phase {
            Phase::Waiting => match (self.last_byte_at, self.first_byte_deadline) {
                (Some(last), _) => last.saturating_add(self.quiet_gap).min(self.deadline),
                (None, Some(first)) => first.min(self.deadline),
                (None, None) => self.deadline,
            },
            Phase::Draining { until, cap } => self.quiet_after(until).min(cap),
            Phase::Finished => Duration::ZERO,
        }
    }

    /// `until`, or a frame gap after the last byte if that is later.
    fn quiet_after(&self, until: Duration) -> Duration {
        self.last_byte_at
            .map_or(until, |last| until.max(last.saturating_add(self.quiet_gap)))
    }

    /// The first bytes after the request were read at `at`, in one go after a sleep, while the
    /// reply was still awaited: they came after the request left the wire (the driver slept past
    /// its end) but when exactly is unknown.
    pub fn receive_batch(&mut self, at: Duration) -> Received {
        let first = self.first_byte_at.is_none();
        let received = self.receive(at.max(self.request_end));
        if first && received == Received::Reply {
            self.first_byte_exact = false;
        }
        received
    }

    /// Whether the first byte's time is known (see [`Self::receive_batch`]).
    pub fn first_byte_exact(&self) -> bool {
        self.first_byte_exact
    }

    /// Bytes arrived at `at`.
    pub fn receive(&mut self, at: Duration) -> Received {
        match self.phase {
            Phase::Waiting if self.discard_early && at < self.request_end => Received::Discard,
            Phase::Waiting => {
                self.first_byte_at.get_or_insert(at);
                self.last_byte_at = Some(at);
                Received::Reply
            }
            Phase::Draining { .. } => {
                if self.first_byte_at.is_none() {
                    self.late_byte_at.get_or_insert(at);
                }
                self.last_byte_at = Some(at);
                Received::Discard
            }
            Phase::Finished => Received::Discard,
        }
    }

    /// The time from [`wake_at`](Self::wake_at) has come (`now`): the reply failed, or the
    /// draining is over. Returns true when the transaction is finished.
    pub fn expire(&mut self, now: Duration) -> bool {
        if now < self.wake_at() {
            return self.is_finished();
        }
        self.phase = match self.phase {
            Phase::Waiting => {
                // Nothing in time: wait a while for a late reply. Bytes that came: just let
                // the line fall quiet.
                let late_window = if self.first_byte_at.is_none() {
                    self.late_window
                } else {
                    Duration::ZERO
                };
                let until = now.saturating_add(late_window);
                let phase = Phase::Draining {
                    until,
                    cap: until.saturating_add(MAX_DRAIN),
                };
                if self.quiet_after(until) <= now {
                    Phase::Finished
                } else {
                    phase
                }
            }
            Phase::Draining { .. } | Phase::Finished => Phase::Finished,
        };
        self.is_finished()
    }

    /// What the scheduler learns from this transaction.
    pub fn timing(&self) -> ReplyTiming {
        let since_end = |at: Duration| at.saturating_sub(self.clock_start);
        ReplyTiming {
            first_byte: self.first_byte_at.map(since_end),
            late_byte: self.late_byte_at.map(since_end),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Request, RequestPdu};

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    /// A classic read at 9600 8N2 (8 bytes = 9.2 ms) with a WB template's timeout.
    fn read_at_9600(late_window: Duration) -> Transaction {
        Transaction {
            request: Request::classic(1, RequestPdu::ReadHoldingRegisters { start: 0, count: 1 }),
            request_time: Duration::from_micros(9167),
            first_byte_timeout: Some(ms(26)),
            reply_timeout: ms(26 + 9 + 24),
            late_window,
            estimated: ms(20),
            expected_reply_start: None,
        }
    }

    #[test]
    fn the_reply_clock_starts_when_the_request_has_left_the_wire() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(26)), (ms(100), ms(100)), ms(20), true);
        assert_eq!(window.request_end(), ms(100) + Duration::from_micros(9167));
        // A reply 0.5 ms after the request, 9.2 ms long: its first byte is at 109.7 ms, the
        // first-byte deadline at 135.2 ms.
        assert!(window.wake_at() > ms(135));
        assert_eq!(window.receive(ms(110)), Received::Reply);
        assert!(!window.expire(ms(112)), "too early to give up");
        assert!(window.is_waiting());
        assert_eq!(window.timing().first_byte, Some(Duration::from_micros(833)));
    }

    #[test]
    fn a_write_that_returns_late_does_not_shorten_the_timeout_nor_drop_the_reply() {
        // `write` returned 3 ms after it started (the task was preempted); the device got the
        // request at once and answers 0.5 ms after its end.
        let mut window = ReplyWindow::new(&read_at_9600(ms(26)), (ms(100), ms(103)), ms(20), true);
        let reply_at = ms(100) + Duration::from_micros(9167 + 500);
        assert_eq!(window.receive(reply_at), Received::Reply);
        let clock_start = ms(100) + Duration::from_micros(9167);
        assert_eq!(window.clock_start(), clock_start);
        // Preempted for longer than the request's wire time: the clock starts at the return.
        let late_return = ReplyWindow::new(&read_at_9600(ms(26)), (ms(100), ms(120)), ms(20), true);
        assert_eq!(late_return.clock_start(), ms(120));
        assert_eq!(late_return.wake_at(), ms(120 + 26));
    }

    #[test]
    fn bytes_before_the_request_left_the_wire_are_not_its_reply() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(26)), (ms(100), ms(100)), ms(20), true);
        assert_eq!(window.receive(ms(105)), Received::Discard);
        assert_eq!(window.timing().first_byte, None);
        // Over TCP the serial side's timing is unknown: nothing is thrown away.
        let mut tcp = ReplyWindow::new(&read_at_9600(ms(26)), (ms(100), ms(100)), ms(20), false);
        assert_eq!(tcp.receive(ms(105)), Received::Reply);
    }

    #[test]
    fn a_late_reply_is_thrown_away_and_reported() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(500)), (ms(0), ms(0)), ms(20), true);
        let first_deadline = window.wake_at();
        assert!(!window.expire(first_deadline), "the late window starts");
        assert!(!window.is_waiting());
        // The reply to this request comes 300 ms after it ended: thrown away, not a reply.
        let late = window.request_end() + ms(300);
        assert_eq!(window.receive(late), Received::Discard);
        assert_eq!(window.receive(late + ms(5)), Received::Discard);
        assert_eq!(window.timing().late_byte, Some(ms(300)));
        assert_eq!(window.timing().first_byte, None);
        // Finished only once the late window has passed and the line was quiet a frame gap.
        let end = window.wake_at();
        assert!(end >= first_deadline + ms(500));
        assert!(window.expire(end));
    }

    #[test]
    fn a_reply_that_keeps_coming_past_the_late_window_delays_the_next_request() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(30)), (ms(0), ms(0)), ms(20), true);
        let deadline = window.wake_at();
        window.expire(deadline);
        let last = deadline + ms(29);
        window.receive(last);
        assert_eq!(
            window.wake_at(),
            last + ms(20),
            "a frame gap after the last byte"
        );
        assert!(!window.expire(deadline + ms(30)));
        assert!(window.expire(last + ms(20)));
    }

    #[test]
    fn silence_without_a_late_window_finishes_at_the_timeout() {
        let mut window =
            ReplyWindow::new(&read_at_9600(Duration::ZERO), (ms(0), ms(0)), ms(20), true);
        let deadline = window.wake_at();
        assert!(window.expire(deadline));
    }

    #[test]
    fn garbage_in_time_needs_only_a_quiet_line() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(500)), (ms(0), ms(0)), ms(20), true);
        let at = window.request_end() + ms(2);
        assert_eq!(window.receive(at), Received::Reply);
        // The parser found no frame; the inter-byte gap passes.
        assert_eq!(window.wake_at(), at + ms(20));
        assert!(
            window.expire(at + ms(20)),
            "no late window after bytes came in time"
        );
    }

    #[test]
    fn a_babbling_line_is_drained_for_a_bounded_time() {
        let mut window = ReplyWindow::new(&read_at_9600(ms(30)), (ms(0), ms(0)), ms(20), true);
        let mut now = window.wake_at();
        window.expire(now);
        let mut rounds = 0;
        while !window.is_finished() {
            now += ms(5);
            window.receive(now);
            if now >= window.wake_at() {
                window.expire(now);
            }
            rounds += 1;
            assert!(rounds < 1000, "never finished");
        }
        assert!(now <= ms(30 + 26 + 59 + 1000 + 10), "{now:?}");
    }
}
