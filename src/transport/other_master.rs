//! Another master on the bus, sans IO: requests heard on the line that this master did not
//! send.
//!
//! Modbus RTU has one master per bus. A second one (wb-mqtt-serial started again beside
//! rtu2mqtt, a laptop with mbpoll on the same pair) sends requests the devices answer, and an
//! RTU reply carries nothing that says which request it answers: the reply to the other master's
//! read of holding 0–3 of device 5 is a valid answer to this master's read of holding 10–13 of
//! device 5. Taken as such, it publishes values the registers never held. So a reply is not
//! trusted when another master's request was heard shortly before it or in its window, and the
//! driver is told, so that the operator hears of the second master.
//!
//! What counts as another master's request: a complete frame with a valid CRC that decodes as a
//! request (classic functions 1–6, 15, 16; Fast Modbus scan, event poll, request by serial) and
//! is not this master's own frame heard again. Own frames heard again are only two: a device's
//! reply to a single write (functions 5, 6), which is the request itself and may come late;
//! and an adapter's echo of the request in progress. Any other copy of a request this master
//! also sends is another master's: wb-mqtt-serial polling the same devices with the same
//! templates sends exactly this master's reads, and the reply to its copy of this master's
//! last read lands in the window of this master's next one.
//!
//! An echo and another master's copy that comes before the reply look alike. What tells them
//! apart is when and how regularly they come: an adapter echoes every request, as the first
//! bytes heard after it, within its latency of the request's end on the wire
//! ([`ECHO_LATENCY`]); another master cannot copy each of this master's requests that quickly.
//! So a copy heard first and in time counts as the echo only if the request before was echoed
//! in time too (the first such copy is distrusted without telling the operator; until the line
//! is decided, replies are read as they come, since a batch read loses the time), and after
//! [`ECHOES_TO_KNOW`] such requests, with few misses (first bytes that were something else, or
//! nothing heard at all; a single write's copy is its reply and says nothing), the line is
//! known to echo
//! ([`OtherMasters::line_echoes`]): only then is a copy heard first but read late (a batch read,
//! a broadcast's echo read before the next request) taken for the echo. Any other copy (a
//! second one, one after other bytes, one late on a line not known to echo) is another master's:
//! on a controller's own ports and on a pty, which do not echo, every copy is.
//!
//! Noise forms such a frame once in 65,536 tries of a position; a device's reply does not
//! decode as a request, except a single write's echo.

use std::collections::{BTreeMap, VecDeque};
use std::ops::Range;
use std::time::Duration;

use crate::protocol::fast::FastRequest;
use crate::protocol::frame::MAX_DEVICE_ADDRESS;
use crate::protocol::pdu::FrameLength;
use crate::protocol::{Request, RequestBody};

/// How long after another master's request a reply is not trusted: the longest a device takes
/// to answer it, at any baud rate, with room to spare. Wider costs only replies while another
/// master is heard; narrower could let its reply through.
pub const REPLY_HORIZON: Duration = Duration::from_secs(1);

/// How long after another master's request was last heard it counts as still polling the bus
/// ([`OtherMasters::polls_lately`]): one that polls at all is heard within seconds, unless its
/// requests keep colliding with this master's traffic.
pub const POLLING_HORIZON: Duration = Duration::from_secs(10);

/// How long this master's single writes are remembered: a device's echo of one may come as
/// late as its timeout and late window allow (seconds), and must not pass for another
/// master's request then.
const OWN_MEMORY: Duration = Duration::from_secs(10);

/// At most this many of them (the oldest are let go first).
const OWN_WRITES: usize = 256;

/// Requests echoed in time (less those whose first bytes heard were no echo) before the line
/// is known to echo: one may be another master's copy sent just after this master's request,
/// three in a row cannot.
const ECHOES_TO_KNOW: u8 = 3;

/// The longest request frame (a write of 123 registers): stray bytes beyond it cannot complete
/// a request and are let go.
const LONGEST_REQUEST: usize = 9 + 246;

/// What the exchange heard of other masters.
#[derive(Debug, Default)]
pub struct OtherMasters {
    /// Single writes (functions 5, 6) of the last [`OWN_MEMORY`]: when sent, and their hash.
    writes: VecDeque<(Duration, u64)>,
    /// What was heard first after this master's last request: its echo or not.
    echo: EchoWatch,
    /// Bytes heard outside any reply since the last request found in them (at most
    /// [`LONGEST_REQUEST`]).
    stray: Vec<u8>,
    /// When another master's request to each device was last heard (`None`: to every device,
    /// a broadcast or a Fast Modbus request any device may answer); only the last
    /// [`REPLY_HORIZON`]'s are kept.
    heard_at: BTreeMap<Option<u8>, Duration>,
    /// The last such request, until the driver has taken it ([`Self::take_heard`]).
    unreported: Option<Vec<u8>>,
    /// When another master's request (not a possible echo) was last heard, to any device.
    last_heard: Option<Duration>,
}

/// The first bytes heard after each request this master writes, as evidence of an echo (see
/// the module's documentation). Buffers reused from request to request.
#[derive(Debug, Default)]
struct EchoWatch {
    /// The last request written, and the one being written (it becomes `last` once written:
    /// bytes read before, when the input is emptied before writing it, may still hold the
    /// echo of the one before).
    last: Vec<u8>,
    next: Vec<u8>,
    /// An echo complete by then came in time: the request's end on the wire and an adapter's
    /// latency.
    in_time_by: Duration,
    /// How many of the first bytes heard since `last` was written match it.
    matched: usize,
    verdict: Verdict,
    /// Evidence that the line echoes: up for each request echoed in time, down for each whose
    /// first bytes heard were something else; [`ECHOES_TO_KNOW`] makes the line known to echo.
    score: u8,
}

#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    /// Nothing, or only a beginning of the request, heard since it was written.
    #[default]
    Open,
    /// The first bytes heard were no copy of it.
    NotEcho,
    /// The first bytes heard were a copy of it. `own`: taken for its echo (once); else it
    /// counts as another master's, told to the operator unless `quiet` (a first echo in time
    /// on a line not yet seen to echo: most likely an echo, it is not trusted but not told).
    Copy { own: bool, quiet: bool },
}

/// An adapter hands an echo over at most this long after the request has left the wire (a
/// USB adapter's latency timer is 16 ms by default; a receive FIFO's timeout is a few
/// characters).
const ECHO_LATENCY: Duration = Duration::from_millis(20);

/// Evidence kept at most: a line known to echo stays known through a few transactions whose
/// first bytes were noise.
const MAX_ECHO_SCORE: u8 = 2 * ECHOES_TO_KNOW;

impl EchoWatch {
    fn sent(&mut self, now: Duration, on_the_wire_until: Duration) {
        if self.verdict == Verdict::Open && !self.last.is_empty() {
            // Nothing at all was heard after the last request: no echo (an echoing adapter
            // echoes every request).
            self.score = self.score.saturating_sub(1);
        }
        std::mem::swap(&mut self.last, &mut self.next);
        self.in_time_by = on_the_wire_until.max(now) + ECHO_LATENCY;
        self.matched = 0;
        self.verdict = Verdict::Open;
    }

    fn known(&self) -> bool {
        self.score >= ECHOES_TO_KNOW
    }

    /// Some echo was heard in time lately, but not enough to know the line echoes.
    fn undecided(&self) -> bool {
        self.score > 0 && !self.known()
    }

    /// Bytes heard at `now`, in the order heard.
    fn observe(&mut self, now: Duration, bytes: &[u8]) {
        if self.verdict != Verdict::Open || bytes.is_empty() || self.last.is_empty() {
            return;
        }
        let rest = self.last.get(self.matched..).unwrap_or_default();
        let count = rest.len().min(bytes.len());
        if bytes.get(..count) != rest.get(..count) {
            self.verdict = Verdict::NotEcho;
            self.score = self.score.saturating_sub(1);
            return;
        }
        self.matched += count;
        if self.matched < self.last.len() {
            return;
        }
        if is_single_write(&self.last) {
            // A device's reply to a single write is the request itself: no sign of an echo.
            self.verdict = Verdict::Copy {
                own: true,
                quiet: false,
            };
            return;
        }
        self.verdict = if now <= self.in_time_by {
            // An echo in time, or another master's copy sent right after this request: taken
            // for the echo only if the request before was echoed in time too (another master
            // cannot copy each of this master's requests that quickly).
            let own = self.score >= 1;
            self.score = (self.score + 1).min(MAX_ECHO_SCORE);
            Verdict::Copy { own, quiet: true }
        } else {
            // Read late (a batch read, the next request's emptied input): when it came is
            // unknown. On a line known to echo it is the echo, and one more sign of it.
            let own = self.known();
            if own {
                self.score = (self.score + 1).min(MAX_ECHO_SCORE);
            }
            Verdict::Copy { own, quiet: false }
        };
    }

    /// Whether `frame`, a request heard, is a copy of the last request, and then whether it is
    /// its echo (once) or another master's.
    fn claims(&mut self, frame: &[u8]) -> Option<Heard> {
        if frame != self.last.as_slice() {
            return None;
        }
        let heard = match self.verdict {
            Verdict::Copy { own: true, .. } => Heard::Own,
            Verdict::Copy { quiet: true, .. } => Heard::Foreign { quiet: true },
            Verdict::Open | Verdict::NotEcho | Verdict::Copy { .. } => {
                return Some(Heard::Foreign { quiet: false })
            }
        };
        // Only the first copy heard can be the echo.
        self.verdict = Verdict::Copy {
            own: false,
            quiet: false,
        };
        Some(heard)
    }
}

/// What a request heard is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Heard {
    /// This master's own frame heard again.
    Own,
    /// Another master's; told to the operator unless `quiet`.
    Foreign { quiet: bool },
}

/// A write of one coil or register: the device's reply is the request itself.
fn is_single_write(frame: &[u8]) -> bool {
    matches!(frame.get(1), Some(0x05 | 0x06))
}

impl OtherMasters {
    /// This master is about to write the request `frame` ([`Self::sent`] once written).
    pub fn writing(&mut self, frame: &[u8]) {
        self.echo.next.clear();
        self.echo.next.extend_from_slice(frame);
    }

    /// The request of [`Self::writing`] has been written at `now`, and is on the wire until
    /// `on_the_wire_until`.
    pub fn sent(&mut self, now: Duration, on_the_wire_until: Duration) {
        self.echo.sent(now, on_the_wire_until);
        while self.writes.front().is_some_and(|&(at, _)| {
            self.writes.len() >= OWN_WRITES || at.saturating_add(OWN_MEMORY) < now
        }) {
            self.writes.pop_front();
        }
        if is_single_write(&self.echo.last) {
            self.writes.push_back((now, frame_hash(&self.echo.last)));
        }
    }

    /// Bytes heard at `now`, every one in the order heard, before anything else is done with
    /// them: the first after a request tell whether it was echoed.
    pub fn observe(&mut self, now: Duration, bytes: &[u8]) {
        self.echo.observe(now, bytes);
    }

    /// An echo was heard in time lately, but not often enough to know the line echoes: replies
    /// are to be read as they come (a batch read loses the time that tells an echo).
    pub fn echo_undecided(&self) -> bool {
        self.echo.undecided()
    }

    /// This master's raw transfer `frame` was written at `now`: its reply is the transfer's to
    /// read, so any copy of it heard first after it is its own (its echo, read late).
    pub fn sent_raw(&mut self, now: Duration, frame: &[u8]) {
        self.writing(frame);
        self.sent(now, now);
        self.echo.in_time_by = Duration::MAX;
    }

    /// Whether the line is known to echo this master's requests (see the module's
    /// documentation).
    #[cfg(test)]
    pub fn line_echoes(&self) -> bool {
        self.echo.known()
    }

    /// On a line known to echo, the length of the last request's copy in front of `bytes`
    /// (more bytes follow it), else 0.
    pub fn known_echo_in_front(&self, bytes: &[u8]) -> usize {
        let last = &self.echo.last;
        if self.echo.known() && bytes.len() > last.len() && bytes.starts_with(last) {
            last.len()
        } else {
            0
        }
    }

    /// Bytes heard at `now` outside any reply: before a request, while it was on the wire, in a
    /// late window, after the reply ([`Self::observe`] first).
    pub fn stray(&mut self, now: Duration, bytes: &[u8]) {
        // Called after every reply taken, mostly with nothing: no scan then.
        if bytes.is_empty() {
            return;
        }
        let mut stray = std::mem::take(&mut self.stray);
        stray.extend_from_slice(bytes);
        // Every request among them counts now, once, and this master's own are let go too:
        // left in the buffer, one would be found again later, when it is no longer its own.
        while let Some((range, heard)) = self.any_request(&stray, now) {
            if let Some((target, quiet)) = heard {
                let frame = stray.get(range.clone()).unwrap_or_default().to_vec();
                self.heard(now, target, frame, quiet);
            }
            stray.drain(..range.end);
        }
        let excess = stray.len().saturating_sub(LONGEST_REQUEST);
        stray.drain(..excess);
        self.stray = stray;
    }

    /// Bytes heard in a reply window (by `now`) that were not the reply: before the frame taken
    /// for it, or all of them when none was ([`Self::observe`] first, as they came).
    pub fn in_window(&mut self, now: Duration, mut bytes: &[u8]) {
        while let Some((range, heard)) = self.any_request(bytes, now) {
            if let Some((target, quiet)) = heard {
                let frame = bytes.get(range.clone()).unwrap_or_default().to_vec();
                self.heard(now, target, frame, quiet);
            }
            bytes = bytes.get(range.end..).unwrap_or_default();
        }
    }

    /// The first complete request in `bytes`, and, unless it is this master's own frame heard
    /// again, the device it asks (`None`: a broadcast, or a Fast Modbus request that any device
    /// may answer) and whether the operator is not to be told.
    #[allow(clippy::type_complexity)]
    fn any_request(
        &mut self,
        bytes: &[u8],
        now: Duration,
    ) -> Option<(Range<usize>, Option<(Option<u8>, bool)>)> {
        let (range, target) = first_request(bytes)?;
        let frame = bytes.get(range.clone()).unwrap_or_default();
        let heard = match self.echo.claims(frame) {
            Some(Heard::Own) => None,
            Some(Heard::Foreign { quiet }) => Some((target, quiet)),
            None if self.is_recent_single_write(now, frame) => None,
            None => Some((target, false)),
        };
        Some((range, heard))
    }

    /// A device's reply to one of this master's single writes of the last [`OWN_MEMORY`]: the
    /// request itself.
    fn is_recent_single_write(&self, now: Duration, frame: &[u8]) -> bool {
        if !is_single_write(frame) {
            return false;
        }
        let hash = frame_hash(frame);
        self.writes
            .iter()
            .any(|&(at, sent)| sent == hash && at.saturating_add(OWN_MEMORY) >= now)
    }

    fn heard(&mut self, now: Duration, target: Option<u8>, frame: Vec<u8>, quiet: bool) {
        self.heard_at
            .retain(|_, &mut at| at.saturating_add(REPLY_HORIZON) >= now);
        self.heard_at.insert(target, now);
        if !quiet {
            self.unreported = Some(frame);
            self.last_heard = Some(now);
        }
    }

    /// Whether another master was heard less than [`POLLING_HORIZON`] before `now`: its
    /// requests to a device may go unheard here (garbled by a collision in this master's
    /// window) while the device still answers them.
    pub fn polls_lately(&self, now: Duration) -> bool {
        self.last_heard
            .is_some_and(|heard| heard.saturating_add(POLLING_HORIZON) >= now)
    }

    /// Whether a reply from `address` whose clock started at `clock_start` may answer another
    /// master's request: one to that device, or to every device, was heard less than
    /// [`REPLY_HORIZON`] before, or since. (A reply carries the address of the device that
    /// sent it: another device's request is not answered by it.)
    pub fn distrusts_reply_after(&self, address: u8, clock_start: Duration) -> bool {
        [Some(address), None].iter().any(|target| {
            self.heard_at
                .get(target)
                .is_some_and(|heard| heard.saturating_add(REPLY_HORIZON) >= clock_start)
        })
    }

    /// Another master's request heard since the last call, for the operator.
    pub fn take_heard(&mut self) -> Option<Vec<u8>> {
        self.unreported.take()
    }
}

/// The first complete request in `bytes` and the device it asks (`None`: a broadcast, or a
/// Fast Modbus request that any device may answer).
fn first_request(bytes: &[u8]) -> Option<(Range<usize>, Option<u8>)> {
    (0..bytes.len()).find_map(|start| {
        let rest = bytes.get(start..)?;
        let FrameLength::Known(len) = Request::length_from_header(rest) else {
            return None;
        };
        let frame = rest.get(..len)?;
        let request = Request::decode(frame).ok()?;
        let target = match &request.body {
            // A device's answer to an event setup reads as a setup request: not another
            // master's.
            RequestBody::Fast(FastRequest::ConfigureEvents { .. }) => return None,
            RequestBody::Fast(_) => None,
            RequestBody::Classic(_) => (1..=MAX_DEVICE_ADDRESS)
                .contains(&request.address)
                .then_some(request.address),
        };
        Some((start..start + len, target))
    })
}

/// FNV-1a over a frame: enough to tell this master's own frames (a collision would only let
/// one other master's request pass unnoticed).
fn frame_hash(frame: &[u8]) -> u64 {
    frame.iter().fold(0xCBF2_9CE4_8422_2325, |hash, &byte| {
        (hash ^ u64::from(byte)).wrapping_mul(0x0000_0100_0000_01B3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Reply, RequestPdu, ResponsePdu};

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    fn read(address: u8, start: u16) -> Vec<u8> {
        Request::classic(
            address,
            RequestPdu::ReadHoldingRegisters { start, count: 2 },
        )
        .encode()
        .unwrap_or_default()
    }

    /// This master writes `frame` at `at`; it is on the wire until then too (an instant line).
    fn send(heard: &mut OtherMasters, at: Duration, frame: &[u8]) {
        heard.writing(frame);
        heard.sent(at, at);
    }

    /// `bytes` heard at `at`, outside any reply.
    fn hear(heard: &mut OtherMasters, at: Duration, bytes: &[u8]) {
        heard.observe(at, bytes);
        heard.stray(at, bytes);
    }

    /// Requests each echoed at once, as many as make the line known to echo.
    fn echo_a_few(heard: &mut OtherMasters, from: Duration) {
        for n in 0..ECHOES_TO_KNOW {
            let at = from + ms(u64::from(n) * 10);
            send(heard, at, &read(9, u16::from(n)));
            hear(heard, at + ms(1), &read(9, u16::from(n)));
        }
    }

    fn write_register(address: u8, register: u16) -> Vec<u8> {
        Request::classic(
            address,
            RequestPdu::WriteSingleRegister {
                address: register,
                value: 7,
            },
        )
        .encode()
        .unwrap_or_default()
    }

    fn reply(address: u8) -> Vec<u8> {
        Reply::classic(
            address,
            ResponsePdu::ReadHoldingRegisters {
                values: vec![0x1234, 0x5678],
            },
        )
        .encode()
        .unwrap_or_default()
    }

    #[test]
    fn another_masters_request_is_found_among_stray_bytes_in_pieces() {
        let mut heard = OtherMasters::default();
        send(&mut heard, ms(0), &read(5, 10));
        let theirs = read(5, 0);
        let (head, tail) = theirs.split_at(3);
        heard.stray(ms(100), &[0x00, 0xFF]);
        heard.stray(ms(101), head);
        assert!(!heard.distrusts_reply_after(5, ms(102)), "not complete yet");
        heard.stray(ms(102), tail);
        assert!(heard.distrusts_reply_after(5, ms(103)));
        assert!(heard.distrusts_reply_after(5, ms(102) + REPLY_HORIZON));
        assert!(!heard.distrusts_reply_after(5, ms(103) + REPLY_HORIZON));
        assert_eq!(heard.take_heard(), Some(theirs));
        assert_eq!(heard.take_heard(), None);
    }

    #[test]
    fn own_requests_replies_and_noise_are_no_other_master() {
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        let ours = read(5, 10);
        send(&mut heard, ms(100), &ours);
        // The adapter's echo of the request, heard first and in time: ours.
        hear(&mut heard, ms(101), &ours);
        // A late reply, another device's reply, noise.
        hear(&mut heard, ms(102), &reply(5));
        hear(&mut heard, ms(103), &reply(7));
        hear(&mut heard, ms(104), &[0x00, 0x13, 0xFF, 0x05, 0x03]);
        heard.in_window(ms(105), &[0x05, 0x03, 0x00, 0x00]);
        assert!(!heard.distrusts_reply_after(5, ms(105)));
        assert_eq!(heard.take_heard(), None);
        // A device's reply to a single write is the request itself, and may come late, many
        // requests later: ours, until it is older than any reply can be.
        let mut heard = OtherMasters::default();
        let write = write_register(5, 3);
        send(&mut heard, ms(10), &write);
        for start in 20..100 {
            send(&mut heard, ms(u64::from(start)), &read(5, start));
        }
        hear(&mut heard, ms(900), &write);
        assert!(!heard.distrusts_reply_after(5, ms(900)));
        let much_later = OWN_MEMORY + ms(1000);
        send(&mut heard, much_later, &read(5, 200));
        hear(&mut heard, much_later, &write);
        assert!(heard.distrusts_reply_after(5, much_later));
    }

    #[test]
    fn a_copy_of_an_own_read_is_another_masters_unless_an_echo_the_line_has_shown() {
        // wb-mqtt-serial polling the same device with the same template sends exactly this
        // master's reads: the reply to its copy of the read of 10–15 answers this master's
        // read of 0–5 of the same shape.
        let ours = read(5, 10);
        // On a line that has never echoed, a copy heard first and in time is not trusted,
        // though not told (it may be a first echo); any later one is another master's.
        let mut heard = OtherMasters::default();
        send(&mut heard, ms(0), &ours);
        hear(&mut heard, ms(13), &ours);
        assert!(heard.distrusts_reply_after(5, ms(14)));
        assert_eq!(heard.take_heard(), None);
        let mut heard = OtherMasters::default();
        send(&mut heard, ms(0), &ours);
        hear(&mut heard, ms(100), &ours);
        assert!(heard.distrusts_reply_after(5, ms(101)));
        assert_eq!(heard.take_heard(), Some(ours.clone()));
        // After other bytes (the reply), or a second copy: another master's.
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        send(&mut heard, ms(100), &ours);
        hear(&mut heard, ms(105), &reply(5));
        heard.in_window(ms(106), &ours);
        assert!(heard.distrusts_reply_after(5, ms(106)));
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        send(&mut heard, ms(100), &ours);
        hear(&mut heard, ms(101), &ours);
        assert!(!heard.distrusts_reply_after(5, ms(101)));
        hear(&mut heard, ms(102), &ours);
        assert!(heard.distrusts_reply_after(5, ms(102)));
    }

    #[test]
    fn a_line_is_known_to_echo_from_echoes_in_time_and_stays_so_through_a_little_noise() {
        let ours = read(5, 10);
        let mut heard = OtherMasters::default();
        for n in 0..ECHOES_TO_KNOW {
            assert!(!heard.line_echoes());
            let at = ms(u64::from(n) * 100);
            send(&mut heard, at, &ours);
            // In two pieces, the second after the request has left the wire (a USB adapter).
            hear(&mut heard, at + ms(1), &ours[..5]);
            hear(&mut heard, at + ECHO_LATENCY, &ours[5..]);
        }
        assert!(heard.line_echoes());
        // The first echo on a line never seen to echo was not trusted (quietly) for a horizon.
        assert!(heard.distrusts_reply_after(5, ms(300)));
        assert_eq!(heard.take_heard(), None);
        // A batch read: the echo in front of the reply, read late.
        let t = ms(1500);
        send(&mut heard, t, &ours);
        let mut batch = ours.clone();
        batch.extend(reply(5));
        heard.observe(t + ms(50), &batch);
        assert_eq!(heard.known_echo_in_front(&batch), ours.len());
        heard.stray(t + ms(50), &ours);
        assert!(!heard.distrusts_reply_after(5, t + ms(50)));
        // Noise heard first after a request: still known; a run of requests whose first bytes
        // are no echo: no longer.
        send(&mut heard, t + ms(100), &ours);
        hear(&mut heard, t + ms(101), &[0x00]);
        assert!(heard.line_echoes());
        for n in 0..MAX_ECHO_SCORE {
            let at = t + ms(200 + u64::from(n) * 10);
            send(&mut heard, at, &ours);
            hear(&mut heard, at + ms(1), &reply(5));
        }
        assert!(!heard.line_echoes());
        assert_eq!(heard.known_echo_in_front(&batch), 0);
        // A copy heard late on a line not known to echo: another master's, told.
        send(&mut heard, t + ms(400), &ours);
        hear(&mut heard, t + ms(500), &ours);
        assert!(heard.distrusts_reply_after(5, t + ms(500)));
        assert_eq!(heard.take_heard(), Some(ours));
    }

    #[test]
    fn answered_single_writes_and_silent_requests_are_no_sign_of_an_echo() {
        // A device's reply to a single write is the request itself, and comes in time: on a
        // line without echo, writes in a row must not make it "known to echo".
        let mut heard = OtherMasters::default();
        for n in 0..10 {
            let write = write_register(5, n);
            let at = ms(u64::from(n) * 10);
            send(&mut heard, at, &write);
            hear(&mut heard, at + ms(2), &write);
            assert!(!heard.echo_undecided());
        }
        assert!(!heard.line_echoes());
        assert!(!heard.distrusts_reply_after(5, ms(100)));
        // On a line known to echo, a request after which nothing at all was heard lowers the
        // evidence (an echoing adapter echoes every request).
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        assert!(heard.line_echoes());
        send(&mut heard, ms(100), &read(5, 0));
        send(&mut heard, ms(700), &read(5, 0));
        assert!(!heard.line_echoes());
        assert!(
            heard.echo_undecided(),
            "replies read as they come until decided"
        );
    }

    #[test]
    fn another_master_copying_late_never_makes_the_line_known_to_echo() {
        // The device does not answer this master; another master's identical read comes 40 ms
        // after each of its requests, again and again.
        let ours = read(5, 10);
        let mut heard = OtherMasters::default();
        for n in 0..20 {
            let at = ms(n * 600);
            send(&mut heard, at, &ours);
            hear(&mut heard, at + ms(40), &ours);
            assert!(heard.distrusts_reply_after(5, at + ms(41)));
        }
        assert!(!heard.line_echoes());
    }

    #[test]
    fn on_a_line_that_echoes_a_request_without_reply_has_its_echo_read_before_the_next() {
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        assert!(heard.line_echoes());
        let broadcast = Request::classic(
            0,
            RequestPdu::WriteMultipleRegisters {
                start: 3,
                values: vec![1, 2],
            },
        )
        .encode()
        .unwrap_or_default();
        send(&mut heard, ms(100), &broadcast);
        // Its echo comes after its transaction, in the input emptied before the next request
        // (being written, not yet sent), late.
        heard.writing(&read(5, 0));
        hear(&mut heard, ms(200), &broadcast);
        heard.sent(ms(201), ms(201));
        assert!(!heard.distrusts_reply_after(5, ms(201)));
        assert_eq!(heard.take_heard(), None);
        // Heard once more: another master's, and any device's reply may answer a broadcast.
        hear(&mut heard, ms(230), &broadcast);
        assert!(heard.distrusts_reply_after(7, ms(231)));
        assert_eq!(heard.take_heard(), Some(broadcast));
    }

    #[test]
    fn a_request_in_a_reply_window_is_found() {
        let mut heard = OtherMasters::default();
        send(&mut heard, ms(0), &read(5, 10));
        let mut window = vec![0x00];
        window.extend(read(5, 0));
        heard.in_window(ms(50), &window);
        assert!(heard.distrusts_reply_after(5, ms(40)));
        assert_eq!(heard.take_heard(), Some(read(5, 0)));
    }

    #[test]
    fn requests_heard_together_count_once_then_age() {
        let mut heard = OtherMasters::default();
        let mut burst = read(5, 0);
        burst.extend(reply(5));
        burst.extend(read(6, 4));
        burst.extend(read(7, 8));
        heard.stray(ms(100), &burst);
        assert_eq!(heard.take_heard(), Some(read(7, 8)), "the last one heard");
        // Later stray bytes find nothing left over: the distrust ends a horizon after the
        // burst, not after them.
        heard.stray(ms(900), &reply(5));
        assert!(!heard.distrusts_reply_after(5, ms(101) + REPLY_HORIZON));
        assert_eq!(heard.take_heard(), None);
    }

    #[test]
    fn only_the_device_asked_is_distrusted_unless_any_may_answer() {
        let mut heard = OtherMasters::default();
        heard.stray(ms(10), &read(7, 0));
        assert!(heard.distrusts_reply_after(7, ms(11)));
        assert!(
            !heard.distrusts_reply_after(5, ms(11)),
            "device 5's reply cannot answer a request to device 7"
        );
        // An event poll of another master: any device may answer it.
        let poll = Request::poll_events(crate::protocol::EventPoll {
            min_address: 1,
            max_data_len: 100,
            ack_address: 0,
            ack_flag: 0,
        })
        .encode()
        .unwrap_or_default();
        heard.stray(ms(20), &poll);
        assert!(heard.distrusts_reply_after(5, ms(21)));
        assert!(heard.distrusts_reply_after(0xFD, ms(21)));
        assert!(!heard.distrusts_reply_after(5, ms(21) + REPLY_HORIZON));
    }

    #[test]
    fn an_own_request_heard_is_let_go_not_found_later() {
        let mut heard = OtherMasters::default();
        echo_a_few(&mut heard, ms(0));
        let ours = read(5, 10);
        send(&mut heard, ms(100), &ours);
        hear(&mut heard, ms(101), &ours);
        // Once it is no longer remembered as sent, the stray bytes that come next must not
        // bring it back as another master's.
        let much_later = OWN_MEMORY + ms(1000);
        send(&mut heard, much_later, &read(5, 20));
        heard.stray(much_later, &[0x00]);
        assert!(!heard.distrusts_reply_after(5, much_later));
        assert_eq!(heard.take_heard(), None);
    }

    #[test]
    fn stray_bytes_stay_bounded() {
        let mut heard = OtherMasters::default();
        for _ in 0..100 {
            heard.stray(ms(1), &[0x13; 50]);
        }
        assert!(heard.stray.len() <= LONGEST_REQUEST);
        assert!(!heard.distrusts_reply_after(5, ms(1)));
    }
}
