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
//! An echo and another master's copy that comes before the reply look alike; only their time
//! tells them apart: an echo is heard while the request is still on the wire. A copy heard
//! then is the echo, and after three such requests in a row the line is known to echo
//! ([`OtherMasters::line_echoes`], until bytes heard while a request goes out are no echo):
//! only on such a line is a copy of the request in progress heard later (its echo handed over
//! late, in a batch read, after a request without reply) taken for the echo, once. On a line
//! that does not echo (a controller's own ports) every copy heard after the request has left
//! the wire is another master's.
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

/// How long this master's single writes are remembered: a device's echo of one may come as
/// late as its timeout and late window allow (seconds), and must not pass for another
/// master's request then.
const OWN_MEMORY: Duration = Duration::from_secs(10);

/// At most this many of them (the oldest are let go first).
const OWN_WRITES: usize = 256;

/// Echoes heard in a row before the line is known to echo: one may be another master's copy
/// that happened to start just as this master's request ended, three in a row cannot.
const ECHOES_TO_KNOW: u8 = 3;

/// The longest request frame (a write of 123 registers): stray bytes beyond it cannot complete
/// a request and are let go.
const LONGEST_REQUEST: usize = 9 + 246;

/// What the exchange heard of other masters.
#[derive(Debug, Default)]
pub struct OtherMasters {
    /// This master's own frames, to tell them from another master's when heard.
    own: OwnFrames,
    /// Bytes heard outside any reply since the last request found in them (at most
    /// [`LONGEST_REQUEST`]).
    stray: Vec<u8>,
    /// When another master's request to each device was last heard (`None`: to every device,
    /// a broadcast or a Fast Modbus request any device may answer); only the last
    /// [`REPLY_HORIZON`]'s are kept.
    heard_at: BTreeMap<Option<u8>, Duration>,
    /// The last such request, until the driver has taken it ([`Self::take_heard`]).
    unreported: Option<Vec<u8>>,
    /// The line echoes this master's requests (an echo was heard while a request went out).
    line_echoes: bool,
    /// The request in progress, and how much of its echo has been heard since it was sent
    /// (`usize::MAX`: what came first was no echo); the request being written. Buffers reused
    /// from request to request.
    echo_bytes: Vec<u8>,
    echo_heard: usize,
    writing_bytes: Vec<u8>,
    /// Requests in a row whose echo was heard while they went out.
    echoes_in_a_row: u8,
}

/// This master's own frames that may be heard again (see the module's documentation).
#[derive(Debug, Default)]
struct OwnFrames {
    /// The request whose echo may still come: the transaction in progress's, or the last one
    /// sent if it expects no reply, until heard once. A hash of the frame (no copy of it).
    echo: Option<u64>,
    /// Whether `echo` expects a reply (its echo comes before the reply, within its
    /// transaction).
    echo_expects_reply: bool,
    /// The request being written: its hash, whether it expects a reply, whether it is a
    /// single write. It becomes `echo` once written: bytes read before (the input emptied
    /// before writing it) may still hold the echo of the one before.
    writing: Option<(u64, bool, bool)>,
    /// Single writes (functions 5, 6) of the last [`OWN_MEMORY`]: when sent, and their hash.
    writes: VecDeque<(Duration, u64)>,
}

impl OwnFrames {
    fn sent(&mut self, now: Duration) {
        let Some((hash, expects_reply, single_write)) = self.writing.take() else {
            return;
        };
        self.echo = Some(hash);
        self.echo_expects_reply = expects_reply;
        while self.writes.front().is_some_and(|&(at, _)| {
            self.writes.len() >= OWN_WRITES || at.saturating_add(OWN_MEMORY) < now
        }) {
            self.writes.pop_front();
        }
        if single_write {
            self.writes.push_back((now, hash));
        }
    }

    /// Whether `frame`, a request heard at `now`, is this master's own; `echo_possible`: it may
    /// be the echo of the request in progress.
    fn claims(&mut self, now: Duration, frame: &[u8], echo_possible: bool) -> bool {
        let hash = frame_hash(frame);
        if echo_possible && self.echo == Some(hash) {
            self.echo = None;
            return true;
        }
        is_single_write(frame)
            && self
                .writes
                .iter()
                .any(|&(at, sent)| sent == hash && at.saturating_add(OWN_MEMORY) >= now)
    }
}

/// A write of one coil or register: the device's reply is the request itself.
fn is_single_write(frame: &[u8]) -> bool {
    matches!(frame.get(1), Some(0x05 | 0x06))
}

impl OtherMasters {
    /// This master is about to write the request `frame` ([`Self::sent`] once written).
    pub fn writing(&mut self, frame: &[u8], expects_reply: bool) {
        self.own.writing = Some((frame_hash(frame), expects_reply, is_single_write(frame)));
        self.writing_bytes.clear();
        self.writing_bytes.extend_from_slice(frame);
    }

    /// The request of [`Self::writing`] has been written, at `now`.
    pub fn sent(&mut self, now: Duration) {
        if self.own.writing.is_some() {
            std::mem::swap(&mut self.echo_bytes, &mut self.writing_bytes);
            self.echo_heard = 0;
        }
        self.own.sent(now);
    }

    /// How many of `bytes`, heard once the request in progress has left the wire, continue
    /// its echo begun while it went out (0 if none began, or these do not continue it).
    pub fn echo_continues(&self, bytes: &[u8]) -> usize {
        let rest = match self.echo_heard {
            0 | usize::MAX => return 0,
            heard => self.echo_bytes.get(heard..).unwrap_or_default(),
        };
        let count = rest.len().min(bytes.len());
        if bytes.get(..count) == rest.get(..count) {
            count
        } else {
            0
        }
    }

    /// The transaction in progress is over: an echo of its request would have come by now
    /// (before its reply, or within its reply window); a copy heard later is another
    /// master's. A request that expects no reply keeps its echo until the next one is sent.
    pub fn transaction_over(&mut self) {
        if self.own.echo_expects_reply {
            self.own.echo = None;
        }
    }

    /// Whether the line echoes this master's requests (see the module's documentation).
    pub fn line_echoes(&self) -> bool {
        self.line_echoes
    }

    /// Bytes heard at `now` while this master's request was still on the wire: its echo, or a
    /// collision.
    pub fn stray_while_sending(&mut self, now: Duration, bytes: &[u8]) {
        if let Some(rest) = self.echo_bytes.get(self.echo_heard..) {
            let count = rest.len().min(bytes.len());
            let before = self.echo_heard;
            self.echo_heard = if bytes.get(..count) == rest.get(..count) {
                before + count
            } else {
                usize::MAX
            };
            if before < self.echo_bytes.len() && self.echo_heard == self.echo_bytes.len() {
                self.echoes_in_a_row = self.echoes_in_a_row.saturating_add(1);
            }
        }
        if self.echo_heard == usize::MAX {
            // Heard while the request went out, and not its echo: a collision.
            self.echoes_in_a_row = 0;
        }
        self.line_echoes = self.echoes_in_a_row >= ECHOES_TO_KNOW;
        self.scan_stray(now, bytes, true);
    }

    /// Bytes heard at `now` outside any reply: before a request, in a late window, after the
    /// reply.
    pub fn stray(&mut self, now: Duration, bytes: &[u8]) {
        self.scan_stray(now, bytes, self.line_echoes);
    }

    fn scan_stray(&mut self, now: Duration, bytes: &[u8], echo_possible: bool) {
        // Called after every reply taken, mostly with nothing: no scan then.
        if bytes.is_empty() {
            return;
        }
        self.stray.extend_from_slice(bytes);
        // Every request among them counts now, once, and this master's own are let go too:
        // left in the buffer, one would be found again later, when it is no longer its own.
        while let Some((range, foreign)) =
            any_request(&self.stray, now, &mut self.own, echo_possible)
        {
            if let Some(target) = foreign {
                let frame = self.stray.get(range.clone()).unwrap_or_default().to_vec();
                self.heard(now, target, frame);
            }
            self.stray.drain(..range.end);
        }
        let excess = self.stray.len().saturating_sub(LONGEST_REQUEST);
        self.stray.drain(..excess);
    }

    /// Bytes heard in a reply window (by `now`) that were not the reply: before the frame taken
    /// for it, or all of them when none was.
    pub fn in_window(&mut self, now: Duration, mut bytes: &[u8]) {
        while let Some((range, target)) =
            foreign_request(bytes, now, &mut self.own, self.line_echoes)
        {
            self.heard(
                now,
                target,
                bytes.get(range.clone()).unwrap_or_default().to_vec(),
            );
            bytes = bytes.get(range.end..).unwrap_or_default();
        }
    }

    fn heard(&mut self, now: Duration, target: Option<u8>, frame: Vec<u8>) {
        self.heard_at
            .retain(|_, &mut at| at.saturating_add(REPLY_HORIZON) >= now);
        self.heard_at.insert(target, now);
        self.unreported = Some(frame);
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

/// The first complete request in `bytes` that `own` does not claim, and the device it asks
/// (`None`: a broadcast, or a Fast Modbus request that any device may answer).
fn foreign_request(
    bytes: &[u8],
    now: Duration,
    own: &mut OwnFrames,
    echo_possible: bool,
) -> Option<(Range<usize>, Option<u8>)> {
    let mut from = 0;
    while let Some((range, foreign)) = any_request(bytes.get(from..)?, now, own, echo_possible) {
        let range = from + range.start..from + range.end;
        match foreign {
            Some(target) => return Some((range, target)),
            None => from = range.end,
        }
    }
    None
}

/// The first complete request in `bytes`, and, when `own` does not claim it, the device it
/// asks (`Some(None)`: a broadcast, or a Fast Modbus request that any device may answer).
fn any_request(
    bytes: &[u8],
    now: Duration,
    own: &mut OwnFrames,
    echo_possible: bool,
) -> Option<(Range<usize>, Option<Option<u8>>)> {
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
        Some((
            start..start + len,
            (!own.claims(now, frame, echo_possible)).then_some(target),
        ))
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

    /// This master writes `frame` at `at`, expecting a reply.
    fn send(heard: &mut OtherMasters, at: Duration, frame: &[u8]) {
        heard.writing(frame, true);
        heard.sent(at);
    }

    /// Requests echoed while they go out, as many as make the line known to echo.
    fn echo_a_few(heard: &mut OtherMasters, from: Duration) {
        for n in 0..ECHOES_TO_KNOW {
            let at = from + ms(u64::from(n) * 10);
            send(heard, at, &read(9, u16::from(n)));
            heard.stray_while_sending(at, &read(9, u16::from(n)));
            heard.transaction_over();
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
        let ours = read(5, 10);
        send(&mut heard, ms(0), &ours);
        // An adapter's echo of the request while it goes out: ours.
        heard.stray_while_sending(ms(1), &ours);
        // A late reply, another device's reply, noise.
        heard.stray(ms(2), &reply(5));
        heard.stray(ms(3), &reply(7));
        heard.stray(ms(4), &[0x00, 0x13, 0xFF, 0x05, 0x03]);
        heard.in_window(ms(5), &[0x05, 0x03, 0x00, 0x00]);
        heard.transaction_over();
        assert!(!heard.distrusts_reply_after(5, ms(5)));
        assert_eq!(heard.take_heard(), None);
        // A device's reply to a single write is the request itself, and may come late, many
        // requests later: ours, until it is older than any reply can be.
        let write = write_register(5, 3);
        send(&mut heard, ms(10), &write);
        heard.transaction_over();
        for start in 20..100 {
            send(&mut heard, ms(u64::from(start)), &read(5, start));
            heard.transaction_over();
        }
        heard.stray(ms(900), &write);
        assert!(!heard.distrusts_reply_after(5, ms(900)));
        let much_later = OWN_MEMORY + ms(1000);
        send(&mut heard, much_later, &read(5, 200));
        heard.transaction_over();
        heard.stray(much_later, &write);
        assert!(heard.distrusts_reply_after(5, much_later));
    }

    #[test]
    fn a_copy_of_an_own_read_heard_after_its_echo_or_transaction_is_another_masters() {
        // wb-mqtt-serial polling the same device with the same template sends exactly this
        // master's reads: the reply to its copy of the read of 10–15 answers this master's
        // read of 0–5 of the same shape.
        let mut heard = OtherMasters::default();
        let ours = read(5, 10);
        send(&mut heard, ms(0), &ours);
        heard.transaction_over();
        heard.stray(ms(100), &ours);
        assert!(heard.distrusts_reply_after(5, ms(101)));
        assert_eq!(heard.take_heard(), Some(ours.clone()));
        // Heard while the request goes out, a copy is its echo (in two pieces: the adapter
        // hands the rest over after the request has left the wire); a second one is another
        // master's. Three such echoes in a row make the line known to echo; bytes heard while
        // a request goes out that are no echo (a collision) unmake it.
        let mut heard = OtherMasters::default();
        for n in 0..ECHOES_TO_KNOW {
            assert!(!heard.line_echoes());
            let at = ms(u64::from(n) * 100);
            send(&mut heard, at, &ours);
            heard.stray_while_sending(at + ms(1), &ours[..5]);
            assert_eq!(heard.echo_continues(&ours[5..]), 3);
            heard.stray_while_sending(at + ms(2), &ours[5..]);
            assert!(!heard.distrusts_reply_after(5, at + ms(5)));
            if n + 1 < ECHOES_TO_KNOW {
                heard.transaction_over();
            }
        }
        assert!(heard.line_echoes());
        heard.in_window(ms(306), &ours);
        assert!(heard.distrusts_reply_after(5, ms(306)));
        heard.transaction_over();
        send(&mut heard, ms(400), &ours);
        heard.stray_while_sending(ms(401), &[0x00, 0x13]);
        assert!(!heard.line_echoes());
        // On a line that does not echo, even the first copy in the window is another master's.
        let mut heard = OtherMasters::default();
        send(&mut heard, ms(0), &ours);
        heard.in_window(ms(5), &ours);
        assert!(heard.distrusts_reply_after(5, ms(5)));
    }

    #[test]
    fn on_a_line_that_echoes_a_request_without_reply_keeps_its_echo_until_the_next_is_written() {
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
        heard.writing(&broadcast, false);
        heard.sent(ms(0));
        heard.transaction_over();
        // Its echo comes after its transaction, in the input emptied before the next request.
        heard.writing(&read(5, 0), true);
        heard.stray(ms(20), &broadcast);
        heard.sent(ms(21));
        assert!(!heard.distrusts_reply_after(5, ms(21)));
        assert_eq!(heard.take_heard(), None);
        // Heard once more: another master's, and any device's reply may answer a broadcast.
        heard.transaction_over();
        heard.stray(ms(30), &broadcast);
        assert!(heard.distrusts_reply_after(7, ms(31)));
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
        let ours = read(5, 10);
        send(&mut heard, ms(0), &ours);
        heard.stray_while_sending(ms(1), &ours);
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
