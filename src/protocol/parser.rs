//! Incremental frame parsers: feed bytes as they arrive, poll for `NeedMore`, a frame, or an error.
//!
//! [`ReplyParser`] is the master's side: it knows which request it sent, so it knows which replies
//! are possible and how long each is from its header. It skips the 0xFF arbitration filler, drops
//! bytes that cannot start a possible reply, checks the CRC, and after a bad candidate moves on by
//! one byte, so a valid frame that follows garbage is never lost.
//!
//! [`RequestParser`] is the device's side (used by the simulator): it finds requests in the byte
//! stream and tells which well-formed requests a device must reject with an exception.

use super::crc::crc_is_valid;
use super::fast::{self, EventRange, FastRequest};
use super::frame::{Reply, ReplyBody, Request, RequestBody, MAX_DEVICE_ADDRESS, MAX_FRAME_LEN};
use super::pdu::{ExceptionCode, FrameLength, RequestPdu, ResponsePdu, EXCEPTION_FLAG};
use super::DecodeError;
use tracing::warn;

/// No valid frame starts with 0xFF (255 is not an address): devices send it during arbitration.
pub const ARBITRATION_FILLER: u8 = 0xFF;

/// What a parser has after the bytes fed so far.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ParseStatus<T> {
    /// No complete frame yet: feed more bytes.
    NeedMore,
    /// A complete, checked frame. Bytes after it stay buffered for the next poll.
    Frame(T),
    /// Bytes were dropped for this reason. Poll again: what followed them is still buffered.
    Error(ParseError),
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseError {
    #[error("{dropped} byte(s) that cannot start the expected frame")]
    Garbage { dropped: usize },
    #[error("CRC mismatch")]
    BadCrc,
    #[error("frame with a valid CRC but a malformed body: {0}")]
    Malformed(DecodeError),
    #[error("a valid frame that does not answer the request (from address {address})")]
    Unexpected { address: u8 },
    #[error("frame cut short by silence on the line")]
    Interrupted,
}

/// A reply found by [`ReplyParser`], with the arbitration filler that preceded it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParsedReply {
    pub reply: Reply,
    /// 0xFF bytes skipped before this frame (one per arbitration window with a dominant bit).
    pub filler_bytes: usize,
    /// Bytes of the frame itself, address to CRC.
    pub frame_len: usize,
}

/// The master's reply parser for one request.
#[derive(Debug, Clone)]
pub struct ReplyParser {
    expected: Expected,
    buffer: Vec<u8>,
    filler_bytes: usize,
}

/// Which replies a [`ReplyParser`] accepts.
#[derive(Debug, Clone)]
enum Expected {
    Any,
    ReplyTo(Request),
}

impl ReplyParser {
    /// A parser for the replies to `request` (nothing is accepted after a classic broadcast).
    pub fn for_request(request: &Request) -> Self {
        Self::new(Expected::ReplyTo(request.clone()))
    }

    /// A parser that accepts any well-formed device frame (a bus monitor's view).
    pub fn any() -> Self {
        Self::new(Expected::Any)
    }

    fn new(expected: Expected) -> Self {
        Self {
            expected,
            buffer: Vec::with_capacity(64),
            filler_bytes: 0,
        }
    }

    /// Bytes still buffered (not yet part of a frame or dropped).
    pub fn buffered(&self) -> &[u8] {
        &self.buffer
    }

    /// Forget everything buffered, e.g. before the next request.
    pub fn clear(&mut self) {
        self.buffer.clear();
        self.filler_bytes = 0;
    }

    pub fn push(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
    }

    /// `push` then `poll`.
    pub fn feed(&mut self, bytes: &[u8]) -> ParseStatus<ParsedReply> {
        self.push(bytes);
        self.poll()
    }

    pub fn poll(&mut self) -> ParseStatus<ParsedReply> {
        let filler = self
            .buffer
            .iter()
            .take_while(|&&b| b == ARBITRATION_FILLER)
            .count();
        self.buffer.drain(..filler);
        self.filler_bytes += filler;
        if self.buffer.is_empty() {
            return ParseStatus::NeedMore;
        }
        let garbage = leading_garbage(&self.buffer, |rest| self.is_plausible_start(rest));
        if garbage > 0 {
            self.buffer.drain(..garbage);
            return ParseStatus::Error(ParseError::Garbage { dropped: garbage });
        }
        let len = match Reply::length_from_header(&self.buffer) {
            FrameLength::Known(len) => len,
            // A plausible start always has a known or still-incomplete length.
            FrameLength::NeedMore | FrameLength::Unknown => return ParseStatus::NeedMore,
        };
        let Some(candidate) = self.buffer.get(..len) else {
            return ParseStatus::NeedMore;
        };
        if !crc_is_valid(candidate) {
            self.buffer.drain(..1);
            return ParseStatus::Error(ParseError::BadCrc);
        }
        let decoded = Reply::decode(candidate);
        if let Ok(reply) = &decoded {
            warn_of_dropped_events(reply, candidate);
        }
        self.buffer.drain(..len);
        match decoded {
            Err(err) => ParseStatus::Error(ParseError::Malformed(err)),
            Ok(reply) if self.answers(&reply) => ParseStatus::Frame(ParsedReply {
                reply,
                filler_bytes: std::mem::take(&mut self.filler_bytes),
                frame_len: len,
            }),
            Ok(reply) => ParseStatus::Error(ParseError::Unexpected {
                address: reply.address,
            }),
        }
    }

    /// Could a reply we accept start with these bytes? Judges only the bytes present.
    fn is_plausible_start(&self, bytes: &[u8]) -> bool {
        let length_ok = match Reply::length_from_header(bytes) {
            FrameLength::Known(len) => (4..=MAX_FRAME_LEN).contains(&len),
            FrameLength::NeedMore => true,
            FrameLength::Unknown => false,
        };
        length_ok
            && match &self.expected {
                Expected::Any => bytes.first().is_some_and(|&b| b != ARBITRATION_FILLER),
                Expected::ReplyTo(request) => header_matches(request, bytes),
            }
    }

    fn answers(&self, reply: &Reply) -> bool {
        match &self.expected {
            Expected::Any => true,
            Expected::ReplyTo(request) => answers(request, reply),
        }
    }
}

/// Event packets with an event past their `data_len` seen by this process (see
/// [`warn_of_dropped_events`]).
static BAD_EVENT_PACKETS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
/// How many of them are told at warning level before only one in a thousand is.
const BAD_EVENT_PACKETS_TOLD: u64 = 5;

/// An event packet whose events overran its `data_len` keeps the events before the bad one
/// (see [`fast::decode_events`]): the rest are lost, which the log tells.
fn warn_of_dropped_events(reply: &Reply, frame: &[u8]) {
    let ReplyBody::Fast {
        reply: fast::FastReply::Events(packet),
        ..
    } = &reply.body
    else {
        return;
    };
    // address, function, sub-command, flag, event_count, data_len
    let Some(&data_len) = frame.get(5) else {
        return;
    };
    let kept: usize = packet.events.iter().map(fast::Event::wire_len).sum();
    if kept != usize::from(data_len) {
        // A device with this firmware bug sends such a packet with every change: the first
        // few are told, then one in a thousand (a log on a controller's flash is not to be
        // filled at the event rate).
        let seen = BAD_EVENT_PACKETS.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        if seen > BAD_EVENT_PACKETS_TOLD && seen % 1000 != 0 {
            tracing::debug!(
                address = reply.address,
                seen,
                "another event packet with an event longer than its data"
            );
            return;
        }
        warn!(
            seen,
            address = reply.address,
            flag = packet.flag,
            event_count = packet.event_count,
            kept = packet.events.len(),
            dropped_bytes = usize::from(data_len).saturating_sub(kept),
            "event packet with an event longer than its data: the events after it are dropped, \
             the packet is confirmed"
        );
    }
}

/// True when `reply` answers `request`: the checks that need the whole decoded reply (the
/// function, byte counts, echoes of writes, serial numbers). The parser applies them to every
/// frame; a transport without RTU framing (Modbus TCP) applies them to what it decoded.
pub fn answers(request: &Request, reply: &Reply) -> bool {
    match (&request.body, &reply.body) {
        (RequestBody::Classic(pdu), ReplyBody::Classic(answer)) => pdu.is_answered_by(answer),
        (
            RequestBody::Fast(FastRequest::BySerial { serial, pdu }),
            ReplyBody::Fast { reply, .. },
        ) => {
            matches!(reply, fast::FastReply::BySerial { serial: s, pdu: answer } if s == serial && pdu.is_answered_by(answer))
        }
        (
            RequestBody::Fast(FastRequest::ConfigureEvents { ranges }),
            ReplyBody::Fast { reply, .. },
        ) => {
            matches!(reply, fast::FastReply::EventsConfigured { masks } if masks.len() == mask_len(ranges))
        }
        // Old firmware answers under 0x60 whatever the request went under (fast-modbus.md §2:
        // accept both in replies), refusals included.
        (RequestBody::Fast(_), ReplyBody::Classic(ResponsePdu::Exception { function, .. })) => {
            fast::is_fast_function(*function)
        }
        (RequestBody::Fast(_), ReplyBody::Fast { .. }) => true,
        _ => false,
    }
}

/// How many leading bytes cannot start a frame.
fn leading_garbage(buffer: &[u8], plausible_start: impl Fn(&[u8]) -> bool) -> usize {
    (0..buffer.len())
        .take_while(|&at| buffer.get(at..).is_some_and(|rest| !plausible_start(rest)))
        .count()
}

fn mask_len(ranges: &[EventRange]) -> usize {
    ranges.iter().map(EventRange::mask_len).sum()
}

/// Checks the header bytes present against what may answer `request`. `None` at an index means the
/// byte has not arrived yet, which never rules a start out.
fn header_matches(request: &Request, bytes: &[u8]) -> bool {
    let at = |i: usize| bytes.get(i).copied();
    let is = |i: usize, ok: &dyn Fn(u8) -> bool| at(i).is_none_or(ok);
    let fast_fn = |b: u8| fast::is_fast_function(b);
    match &request.body {
        _ if !request.expects_reply() => false,
        RequestBody::Classic(pdu) => {
            is(0, &|b| b == request.address)
                && classic_reply_header_matches(pdu, bytes.get(1..).unwrap_or(&[]))
        }
        RequestBody::Fast(FastRequest::ScanStart | FastRequest::ScanContinue) => {
            is(0, &|b| b == fast::BROADCAST_ADDRESS)
                && is(1, &fast_fn)
                && is(2, &|b| b == fast::SCAN_REPLY || b == fast::SCAN_END)
        }
        RequestBody::Fast(FastRequest::BySerial { serial, pdu }) => {
            let serial = serial.to_be_bytes();
            is(0, &|b| b == fast::BROADCAST_ADDRESS)
                && is(1, &fast_fn)
                && is(2, &|b| b == fast::BY_SERIAL_REPLY)
                && (0..4).all(|i| is(3 + i, &|b| serial.get(i) == Some(&b)))
                && classic_reply_header_matches(pdu, bytes.get(7..).unwrap_or(&[]))
        }
        // A packet from below `min_address` is taken too: its sender ignores the field (its
        // fault), but the packet is real, and refusing it would leave the sender sending it
        // again in every round, winning every arbitration over the devices it should let speak.
        RequestBody::Fast(FastRequest::PollEvents(_)) => match at(0) {
            None => true,
            Some(fast::BROADCAST_ADDRESS) => is(1, &fast_fn) && is(2, &|b| b == fast::NO_EVENTS),
            Some(address) => {
                (1..=MAX_DEVICE_ADDRESS).contains(&address)
                    && is(1, &fast_fn)
                    && is(2, &|b| b == fast::EVENTS_REPLY)
            }
        },
        RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) => {
            let expected_len = mask_len(ranges);
            is(0, &|b| b == request.address)
                && match at(1) {
                    None => true,
                    Some(b) if fast_fn(b) => {
                        is(2, &|b| b == fast::CONFIGURE_EVENTS)
                            && is(3, &|b| usize::from(b) == expected_len)
                    }
                    Some(b) => {
                        b == fast::FUNCTION | EXCEPTION_FLAG
                            || b == fast::LEGACY_FUNCTION | EXCEPTION_FLAG
                    }
                }
        }
    }
}

/// `bytes` starts at the reply PDU's function code.
fn classic_reply_header_matches(request: &RequestPdu, bytes: &[u8]) -> bool {
    let function = request.function();
    match bytes.first() {
        None => true,
        Some(&b) if b == function | EXCEPTION_FLAG => true,
        Some(&b) if b == function => match (request, bytes.get(1)) {
            (_, None) => true,
            (
                RequestPdu::ReadCoils { .. }
                | RequestPdu::ReadDiscreteInputs { .. }
                | RequestPdu::ReadHoldingRegisters { .. }
                | RequestPdu::ReadInputRegisters { .. },
                Some(&byte_count),
            ) => usize::from(byte_count) + 2 == request.reply_pdu_len(),
            _ => true,
        },
        Some(_) => false,
    }
}

/// A request found by [`RequestParser`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ParsedRequest {
    Valid(Request),
    /// A well-formed frame (good CRC) that the addressed device must answer with an exception:
    /// an unknown function or sub-command, or a quantity out of range.
    Rejected(RejectedRequest),
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RejectedRequest {
    pub address: u8,
    pub function: u8,
    /// For a 0x46/0x08 request: the serial number and the embedded function code; the exception
    /// then travels inside a 0x09 reply.
    pub by_serial: Option<(u32, u8)>,
    pub exception: ExceptionCode,
}

impl RejectedRequest {
    /// The exception reply a device sends for this request.
    pub fn exception_reply(&self) -> Reply {
        match self.by_serial {
            Some((serial, function)) => Reply::fast(
                fast::BROADCAST_ADDRESS,
                fast::FastReply::BySerial {
                    serial,
                    pdu: ResponsePdu::Exception {
                        function,
                        code: self.exception,
                    },
                },
            ),
            None => Reply::classic(
                self.address,
                ResponsePdu::Exception {
                    function: self.function & !EXCEPTION_FLAG,
                    code: self.exception,
                },
            ),
        }
    }
}

/// The device side's request parser.
#[derive(Debug, Clone, Default)]
pub struct RequestParser {
    buffer: Vec<u8>,
}

impl RequestParser {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn push(&mut self, bytes: &[u8]) {
        self.buffer.extend_from_slice(bytes);
    }

    pub fn feed(&mut self, bytes: &[u8]) -> ParseStatus<ParsedRequest> {
        self.push(bytes);
        self.poll()
    }

    pub fn buffered(&self) -> &[u8] {
        &self.buffer
    }

    pub fn poll(&mut self) -> ParseStatus<ParsedRequest> {
        if self.buffer.is_empty() {
            return ParseStatus::NeedMore;
        }
        let garbage = leading_garbage(&self.buffer, is_plausible_request_start);
        if garbage > 0 {
            self.buffer.drain(..garbage);
            return ParseStatus::Error(ParseError::Garbage { dropped: garbage });
        }
        match Request::length_from_header(&self.buffer) {
            FrameLength::Known(len) => match self.buffer.get(..len) {
                Some(_) => self.take_frame(len),
                None => ParseStatus::NeedMore,
            },
            FrameLength::NeedMore => ParseStatus::NeedMore,
            // Only silence ends a frame of unknown length; a frame is never longer than 256 bytes.
            FrameLength::Unknown if self.buffer.len() > MAX_FRAME_LEN => {
                self.buffer.drain(..1);
                ParseStatus::Error(ParseError::Garbage { dropped: 1 })
            }
            FrameLength::Unknown => ParseStatus::NeedMore,
        }
    }

    /// The line has been silent for 3.5 characters: whatever is buffered is a whole frame or noise.
    /// Returns the rejected frame of an unknown function, or why the buffer was dropped.
    pub fn silence(&mut self) -> ParseStatus<ParsedRequest> {
        if self.buffer.is_empty() {
            return ParseStatus::NeedMore;
        }
        if Request::length_from_header(&self.buffer) == FrameLength::Unknown
            && crc_is_valid(&self.buffer)
        {
            let len = self.buffer.len();
            return self.take_frame(len);
        }
        self.buffer.clear();
        ParseStatus::Error(ParseError::Interrupted)
    }

    fn take_frame(&mut self, len: usize) -> ParseStatus<ParsedRequest> {
        let Some(frame) = self.buffer.get(..len) else {
            return ParseStatus::NeedMore;
        };
        if !crc_is_valid(frame) {
            self.buffer.drain(..1);
            return ParseStatus::Error(ParseError::BadCrc);
        }
        let status = match Request::decode(frame) {
            Ok(request) => ParseStatus::Frame(ParsedRequest::Valid(request)),
            Err(err) => match err.exception() {
                Some(exception) => {
                    ParseStatus::Frame(ParsedRequest::Rejected(rejected(frame, exception)))
                }
                None => ParseStatus::Error(ParseError::Malformed(err)),
            },
        };
        self.buffer.drain(..len);
        status
    }
}

fn rejected(frame: &[u8], exception: ExceptionCode) -> RejectedRequest {
    let at = |i: usize| frame.get(i).copied().unwrap_or(0);
    let by_serial =
        (fast::is_fast_function(at(1)) && at(2) == fast::BY_SERIAL_REQUEST && frame.len() >= 10)
            .then(|| (u32::from_be_bytes([at(3), at(4), at(5), at(6)]), at(7)));
    RejectedRequest {
        address: at(0),
        function: at(1),
        by_serial,
        exception,
    }
}

/// Requests go to a device address, to the classic broadcast 0, or to the Fast Modbus address.
fn is_plausible_request_start(bytes: &[u8]) -> bool {
    let address_ok = bytes
        .first()
        .is_some_and(|&a| a <= MAX_DEVICE_ADDRESS || a == fast::BROADCAST_ADDRESS);
    let function_ok = bytes
        .get(1)
        .is_none_or(|&f| f != 0 && f & EXCEPTION_FLAG == 0);
    let length_ok = match Request::length_from_header(bytes) {
        FrameLength::Known(len) => (4..=MAX_FRAME_LEN).contains(&len),
        FrameLength::NeedMore | FrameLength::Unknown => true,
    };
    address_ok && function_ok && length_ok
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{crc16, parse_hex, EventPoll};

    fn with_crc(hex: &str) -> Vec<u8> {
        let mut frame = parse_hex(hex).unwrap();
        let crc = crc16(&frame);
        frame.extend(crc.to_le_bytes());
        frame
    }

    fn poll() -> Request {
        Request::poll_events(EventPoll {
            min_address: 0,
            max_data_len: 248,
            ack_address: 0,
            ack_flag: 0,
        })
    }

    /// A CRC-valid event packet whose second event overruns `data_len` is still a frame from
    /// its sender with its flag (so it is confirmed), carrying the event before the bad one.
    #[test]
    fn an_event_packet_with_a_bad_event_length_is_a_frame_with_the_events_before_it() {
        let mut parser = ReplyParser::for_request(&poll());
        let mut bytes = vec![0xFF, 0xFF];
        bytes.extend(with_crc("F1 46 11 01 02 09 01 01 0000 01 05 0F 0000"));
        let ParseStatus::Frame(parsed) = parser.feed(&bytes) else {
            panic!("no frame");
        };
        assert_eq!(parsed.filler_bytes, 2);
        assert_eq!(parsed.reply.address, 241);
        let ReplyBody::Fast {
            reply: fast::FastReply::Events(packet),
            ..
        } = &parsed.reply.body
        else {
            panic!("not an event packet: {:?}", parsed.reply);
        };
        assert_eq!((packet.flag, packet.event_count), (1, 2));
        assert_eq!(packet.events.len(), 1);
        assert_eq!(packet.events[0].payload, vec![1]);
        assert_eq!(parser.poll(), ParseStatus::NeedMore);
        // It re-encodes (with the data it kept) and decodes to itself.
        let encoded = parsed.reply.encode().unwrap();
        assert_eq!(Reply::decode(&encoded), Ok(parsed.reply.clone()));
    }

    /// A device that ignores `min_address` still has its packet taken (its events are real),
    /// so it is confirmed instead of sending the packet again in every round.
    #[test]
    fn a_packet_from_below_min_address_is_taken() {
        let request = Request::poll_events(EventPoll {
            min_address: 21,
            max_data_len: 166,
            ack_address: 20,
            ack_flag: 0,
        });
        let mut parser = ReplyParser::for_request(&request);
        let ParseStatus::Frame(parsed) = parser.feed(&with_crc("14 46 11 01 01 05 01 01 0001 01"))
        else {
            panic!("no frame");
        };
        assert_eq!(parsed.reply.address, 20);
    }

    /// Old firmware refuses a Fast Modbus request under 0x60 (`E0`), whatever it went under:
    /// a refusal, not noise to wait through.
    #[test]
    fn a_refusal_under_the_legacy_function_answers_a_fast_request() {
        let request = Request::configure_events(
            20,
            vec![EventRange::registers(
                crate::protocol::RegisterType::Coil,
                0,
                vec![crate::protocol::EventPriority::High],
            )],
        );
        for refusal in ["14 E0 01", "14 C6 01"] {
            let mut parser = ReplyParser::for_request(&request);
            let ParseStatus::Frame(parsed) = parser.feed(&with_crc(refusal)) else {
                panic!("{refusal}: no frame");
            };
            assert!(answers(&request, &parsed.reply), "{refusal}");
            assert!(matches!(
                parsed.reply.body,
                ReplyBody::Classic(ResponsePdu::Exception { code, .. })
                    if code == ExceptionCode::ILLEGAL_FUNCTION
            ));
        }
    }

    /// Every event overruns: the packet has none, but its sender and flag still arrive.
    #[test]
    fn an_event_packet_whose_first_event_overruns_is_confirmable_with_no_events() {
        let mut parser = ReplyParser::for_request(&poll());
        let ParseStatus::Frame(parsed) =
            parser.feed(&with_crc("14 46 11 00 01 06 08 03 0001 0102"))
        else {
            panic!("no frame");
        };
        assert_eq!(parsed.reply.address, 20);
        assert!(matches!(
            &parsed.reply.body,
            ReplyBody::Fast { reply: fast::FastReply::Events(p), .. } if p.flag == 0 && p.events.is_empty()
        ));
    }
}
