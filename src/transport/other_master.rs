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
//! is none of this master's own requests of the last seconds (an adapter's echo, or a device's
//! late echo of a write,
//! reads as one). Noise forms such a frame once in 65,536 tries of a position; a device's reply
//! does not decode as a request, except a write's echo, which is this master's own frame.

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

/// How long this master's own requests are remembered: a device's echo of a write may come
/// as late as its timeout and late window allow (seconds), and must not pass for another
/// master's request then.
const OWN_MEMORY: Duration = Duration::from_secs(10);

/// At most this many of them (the oldest are let go first).
const OWN_REQUESTS: usize = 256;

/// The longest request frame (a write of 123 registers): stray bytes beyond it cannot complete
/// a request and are let go.
const LONGEST_REQUEST: usize = 9 + 246;

/// What the exchange heard of other masters.
#[derive(Debug, Default)]
pub struct OtherMasters {
    /// This master's requests of the last [`OWN_MEMORY`]: when, and a hash of the frame (no
    /// copy of it per request).
    own: VecDeque<(Duration, u64)>,
    /// Bytes heard outside any reply since the last request found in them (at most
    /// [`LONGEST_REQUEST`]).
    stray: Vec<u8>,
    /// When another master's request to each device was last heard (`None`: to every device,
    /// a broadcast or a Fast Modbus request any device may answer); only the last
    /// [`REPLY_HORIZON`]'s are kept.
    heard_at: BTreeMap<Option<u8>, Duration>,
    /// The last such request, until the driver has taken it ([`Self::take_heard`]).
    unreported: Option<Vec<u8>>,
}

impl OtherMasters {
    /// This master sends `frame` at `now`.
    pub fn sent(&mut self, now: Duration, frame: &[u8]) {
        while self.own.front().is_some_and(|&(at, _)| {
            self.own.len() >= OWN_REQUESTS || at.saturating_add(OWN_MEMORY) < now
        }) {
            self.own.pop_front();
        }
        self.own.push_back((now, frame_hash(frame)));
    }

    /// Bytes heard at `now` outside any reply: before a request, while it was on the wire, in a
    /// late window, after the reply.
    pub fn stray(&mut self, now: Duration, bytes: &[u8]) {
        // Called after every reply taken, mostly with nothing: no scan then.
        if bytes.is_empty() {
            return;
        }
        self.stray.extend_from_slice(bytes);
        // Every request among them counts now, once, and this master's own are let go too:
        // left in the buffer, one would be found again later (a request of its own, once it
        // is no longer among the last few sent, would pass for another master's).
        while let Some((range, foreign)) = any_request(&self.stray, &self.own) {
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
        while let Some((range, target)) = foreign_request(bytes, &self.own) {
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

/// The first complete request in `bytes` that is none of `own`, and the device it asks
/// (`None`: a broadcast, or a Fast Modbus request that any device may answer).
fn foreign_request(
    bytes: &[u8],
    own: &VecDeque<(Duration, u64)>,
) -> Option<(Range<usize>, Option<u8>)> {
    let mut from = 0;
    while let Some((range, foreign)) = any_request(bytes.get(from..)?, own) {
        let range = from + range.start..from + range.end;
        match foreign {
            Some(target) => return Some((range, target)),
            None => from = range.end,
        }
    }
    None
}

/// The first complete request in `bytes`, and, when it is none of `own`, the device it asks
/// (`Some(None)`: a broadcast, or a Fast Modbus request that any device may answer).
fn any_request(
    bytes: &[u8],
    own: &VecDeque<(Duration, u64)>,
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
        let hash = frame_hash(frame);
        let own_frame = own.iter().any(|&(_, sent)| sent == hash);
        Some((start..start + len, (!own_frame).then_some(target)))
    })
}

/// FNV-1a over a frame: enough to tell this master's own frames (a collision would only let
/// one other master's request pass unnoticed among thousands).
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
        heard.sent(ms(0), &read(5, 10));
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
        heard.sent(ms(0), &ours);
        // An adapter's echo of the request, or a device's echo of a write: ours.
        heard.stray(ms(1), &ours);
        // A late reply, another device's reply, noise.
        heard.stray(ms(2), &reply(5));
        heard.stray(ms(3), &reply(7));
        heard.stray(ms(4), &[0x00, 0x13, 0xFF, 0x05, 0x03]);
        heard.in_window(ms(5), &[0x05, 0x03, 0x00, 0x00]);
        assert!(!heard.distrusts_reply_after(5, ms(5)));
        assert_eq!(heard.take_heard(), None);
        // A late echo of it, many requests later, is still its own; once it is older than
        // any echo can be, it is no longer remembered as such.
        for start in 20..100 {
            heard.sent(ms(u64::from(start)), &read(5, start));
        }
        heard.stray(ms(900), &ours);
        assert!(!heard.distrusts_reply_after(5, ms(900)));
        let much_later = OWN_MEMORY + ms(1000);
        heard.sent(much_later, &read(5, 200));
        heard.stray(much_later, &ours);
        assert!(heard.distrusts_reply_after(5, much_later));
    }

    #[test]
    fn a_request_in_a_reply_window_is_found() {
        let mut heard = OtherMasters::default();
        heard.sent(ms(0), &read(5, 10));
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
        heard.sent(ms(0), &ours);
        heard.stray(ms(1), &ours);
        // Once it is no longer remembered as sent, the stray bytes that come next must not
        // bring it back as another master's.
        let much_later = OWN_MEMORY + ms(1000);
        heard.sent(much_later, &read(5, 20));
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
