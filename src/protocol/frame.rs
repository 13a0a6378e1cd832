//! Whole RTU frames (ADUs): `address | function | body | CRC16 (low byte first)`.
//!
//! [`Request`] is what the master sends, [`Reply`] what a device sends. Both encode to bytes and
//! decode from exactly one frame; the incremental parsers in [`super::parser`] find frames in a
//! byte stream.

use super::crc::{append_crc, crc_is_valid};
use super::fast::{self, EventPoll, EventRange, FastReply, FastRequest};
use super::pdu::{ExceptionCode, FrameLength, RequestPdu, ResponsePdu, EXCEPTION_FLAG};
use super::{DecodeError, EncodeError};
use std::time::Duration;

/// Longest RTU frame the standard allows.
pub const MAX_FRAME_LEN: usize = 256;
/// Address 0: a classic broadcast that no device answers.
pub const CLASSIC_BROADCAST: u8 = 0;
/// Highest address a device may have.
pub const MAX_DEVICE_ADDRESS: u8 = 247;

/// Bytes around a PDU in an RTU frame: the address before it, the CRC after it.
pub const RTU_OVERHEAD: usize = 3;
/// Bytes of a Fast Modbus frame's function code (0x46), which precedes the sub-command.
const FAST_FUNCTION_LEN: usize = 1;
/// A 0x11 event packet's sub-command, flag, event count and data length, before its data.
const EVENT_PACKET_HEADER_LEN: usize = 4;
/// Bytes of a 0x11 event packet around its event data: address, function, header, CRC.
pub const EVENT_PACKET_OVERHEAD: usize = RTU_OVERHEAD + FAST_FUNCTION_LEN + EVENT_PACKET_HEADER_LEN;
/// The most event data one packet can carry within the longest RTU frame.
pub const MAX_EVENT_DATA_LEN: usize = MAX_FRAME_LEN - EVENT_PACKET_OVERHEAD;

/// A frame from the master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    pub address: u8,
    pub body: RequestBody,
    /// The function code a Fast Modbus request goes out with: [`fast::FUNCTION`] (0x46), or
    /// [`fast::LEGACY_FUNCTION`] (0x60) for a scan and its requests by serial number when a
    /// client asks for the old command ([`Self::with_fast_function`]). Unused by classic requests.
    pub fast_function: u8,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RequestBody {
    Classic(RequestPdu),
    Fast(FastRequest),
}

/// A frame from a device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    pub address: u8,
    pub body: ReplyBody,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReplyBody {
    /// A classic reply, including exceptions (also exceptions to a 0x46 request).
    Classic(ResponsePdu),
    /// `function` is 0x46, or 0x60 from old firmware.
    Fast { function: u8, reply: FastReply },
}

impl Request {
    pub fn classic(address: u8, pdu: RequestPdu) -> Self {
        Self {
            address,
            body: RequestBody::Classic(pdu),
            fast_function: fast::FUNCTION,
        }
    }

    pub fn scan_start() -> Self {
        Self::fast(fast::BROADCAST_ADDRESS, FastRequest::ScanStart)
    }

    pub fn scan_continue() -> Self {
        Self::fast(fast::BROADCAST_ADDRESS, FastRequest::ScanContinue)
    }

    pub fn by_serial(serial: u32, pdu: RequestPdu) -> Self {
        Self::fast(
            fast::BROADCAST_ADDRESS,
            FastRequest::BySerial { serial, pdu },
        )
    }

    pub fn poll_events(poll: EventPoll) -> Self {
        Self::fast(fast::BROADCAST_ADDRESS, FastRequest::PollEvents(poll))
    }

    pub fn configure_events(address: u8, ranges: Vec<EventRange>) -> Self {
        Self::fast(address, FastRequest::ConfigureEvents { ranges })
    }

    pub fn fast(address: u8, request: FastRequest) -> Self {
        Self {
            address,
            body: RequestBody::Fast(request),
            fast_function: fast::FUNCTION,
        }
    }

    /// The same Fast Modbus request under another function code: 0x60, the deprecated scan
    /// command that wb-device-manager still sends (its replies come under either code).
    pub fn with_fast_function(mut self, function: u8) -> Self {
        self.fast_function = function;
        self
    }

    /// True when no reply may follow: a classic broadcast.
    pub fn expects_reply(&self) -> bool {
        self.address != CLASSIC_BROADCAST
    }

    pub fn is_fast(&self) -> bool {
        matches!(self.body, RequestBody::Fast(_))
    }

    /// When devices arbitrate for the reply (an event poll, a scan): the longest time from the
    /// end of the request to the start of the winner's frame on `line` (every window, fast-modbus.md
    /// §3). Until then the reply may be filler bytes with silent windows between them.
    pub fn arbitration_time(&self, line: &crate::protocol::LineSettings) -> Option<Duration> {
        match &self.body {
            RequestBody::Fast(FastRequest::PollEvents(_)) => Some(line.event_reply_timeout()),
            RequestBody::Fast(FastRequest::ScanStart | FastRequest::ScanContinue) => Some(
                if self.fast_function == crate::protocol::fast::LEGACY_FUNCTION {
                    line.legacy_scan_reply_timeout()
                } else {
                    line.scan_reply_timeout()
                },
            ),
            _ => None,
        }
    }

    /// The length of the whole reply frame (address to CRC) when the device answers as asked:
    /// exact for classic requests, requests by serial number, scans and 0x18; for an event poll
    /// the shortest answer, "no events" (an event packet announces its length in its header).
    /// 0 for a classic broadcast, which nobody answers. An exception reply is 5 bytes.
    pub fn expected_reply_len(&self) -> usize {
        if !self.expects_reply() {
            return 0;
        }
        let fast = |sub_and_body: usize| RTU_OVERHEAD + FAST_FUNCTION_LEN + sub_and_body;
        match &self.body {
            RequestBody::Classic(pdu) => RTU_OVERHEAD + pdu.reply_pdu_len(),
            // 0x09, serial number, the classic reply PDU.
            RequestBody::Fast(FastRequest::BySerial { pdu, .. }) => fast(5 + pdu.reply_pdu_len()),
            // 0x03, serial number, Modbus address (or 0x04, the end of the scan, shorter).
            RequestBody::Fast(FastRequest::ScanStart | FastRequest::ScanContinue) => fast(6),
            // 0x12.
            RequestBody::Fast(FastRequest::PollEvents(_)) => fast(1),
            // 0x18, mask length, one bit per register asked for.
            RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) => {
                fast(2 + ranges.iter().map(EventRange::mask_len).sum::<usize>())
            }
        }
    }

    /// How much of the reply tells the rest: the expected reply, and after an event poll at
    /// least an event packet up to its data length (address, function, header; the "no
    /// events" frame is one byte shorter). A reader that takes this much in one go knows the
    /// whole frame's length after it.
    pub fn reply_len_known_after(&self) -> usize {
        match &self.body {
            RequestBody::Fast(FastRequest::PollEvents(_)) if self.expects_reply() => self
                .expected_reply_len()
                .max(1 + FAST_FUNCTION_LEN + EVENT_PACKET_HEADER_LEN),
            _ => self.expected_reply_len(),
        }
    }

    /// The longest reply frame (address to CRC) this request may get: for an event poll a
    /// packet carrying `max_data_len` bytes of events; otherwise [`Self::expected_reply_len`].
    pub fn max_reply_len(&self) -> usize {
        match &self.body {
            RequestBody::Fast(FastRequest::PollEvents(poll)) if self.expects_reply() => {
                EVENT_PACKET_OVERHEAD + usize::from(poll.max_data_len)
            }
            _ => self.expected_reply_len(),
        }
    }

    /// Bytes of the frame on the wire (CRC included); 0 when it cannot be encoded.
    pub fn encoded_len(&self) -> usize {
        self.encode().map(|frame| frame.len()).unwrap_or(0)
    }

    /// The frame as it goes on the wire, CRC included.
    pub fn encode(&self) -> Result<Vec<u8>, EncodeError> {
        let mut out = Vec::with_capacity(16);
        out.push(self.address);
        match &self.body {
            RequestBody::Classic(pdu) => pdu.encode(&mut out)?,
            RequestBody::Fast(request) => {
                out.push(self.fast_function);
                request.encode(&mut out)?;
            }
        }
        finish_frame(out)
    }

    /// Decodes exactly one frame (CRC included).
    pub fn decode(frame: &[u8]) -> Result<Self, DecodeError> {
        let (address, body) = split_frame(frame)?;
        let (body, fast_function) = match body.split_first() {
            Some((&function, rest)) if fast::is_fast_function(function) => {
                (RequestBody::Fast(FastRequest::decode(rest)?), function)
            }
            _ => (
                RequestBody::Classic(RequestPdu::decode(body)?),
                fast::FUNCTION,
            ),
        };
        Ok(Self {
            address,
            body,
            fast_function,
        })
    }

    /// The whole frame length (CRC included) judged from its first bytes.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(pdu) = bytes.get(1..) else {
            return FrameLength::NeedMore;
        };
        let body_len = match pdu.split_first() {
            None => FrameLength::NeedMore,
            Some((&function, rest)) if fast::is_fast_function(function) => {
                add(FastRequest::length_from_header(rest), 1)
            }
            Some(_) => RequestPdu::length_from_header(pdu),
        };
        add(body_len, 3)
    }
}

impl Reply {
    pub fn classic(address: u8, pdu: ResponsePdu) -> Self {
        Self {
            address,
            body: ReplyBody::Classic(pdu),
        }
    }

    pub fn fast(address: u8, reply: FastReply) -> Self {
        Self {
            address,
            body: ReplyBody::Fast {
                function: fast::FUNCTION,
                reply,
            },
        }
    }

    /// The exception a classic reply carries instead of its answer, if it does.
    pub fn exception_code(&self) -> Option<ExceptionCode> {
        match &self.body {
            ReplyBody::Classic(ResponsePdu::Exception { code, .. }) => Some(*code),
            _ => None,
        }
    }

    pub fn encode(&self) -> Result<Vec<u8>, EncodeError> {
        let mut out = Vec::with_capacity(16);
        out.push(self.address);
        match &self.body {
            ReplyBody::Classic(pdu) => pdu.encode(&mut out)?,
            ReplyBody::Fast { function, reply } => {
                out.push(*function);
                reply.encode(&mut out)?;
            }
        }
        finish_frame(out)
    }

    pub fn decode(frame: &[u8]) -> Result<Self, DecodeError> {
        let (address, pdu) = split_frame(frame)?;
        Self::decode_pdu(address, pdu)
    }

    /// Decodes a reply that travelled without address byte and CRC (Modbus TCP carries the
    /// unit id in its header and relies on TCP's own checks).
    pub fn decode_pdu(address: u8, pdu: &[u8]) -> Result<Self, DecodeError> {
        let body = match pdu.split_first() {
            Some((&function, rest)) if fast::is_fast_function(function) => ReplyBody::Fast {
                function,
                reply: FastReply::decode(rest)?,
            },
            _ => ReplyBody::Classic(ResponsePdu::decode(pdu)?),
        };
        Ok(Self { address, body })
    }

    /// The whole frame length (CRC included) judged from its first bytes.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(pdu) = bytes.get(1..) else {
            return FrameLength::NeedMore;
        };
        let body_len = match pdu.split_first() {
            None => FrameLength::NeedMore,
            Some((&function, rest))
                if fast::is_fast_function(function) && function & EXCEPTION_FLAG == 0 =>
            {
                add(FastReply::length_from_header(rest), 1)
            }
            Some(_) => ResponsePdu::length_from_header(pdu),
        };
        add(body_len, 3)
    }
}

fn add(length: FrameLength, extra: usize) -> FrameLength {
    match length {
        FrameLength::Known(len) => FrameLength::Known(len + extra),
        other => other,
    }
}

fn finish_frame(mut out: Vec<u8>) -> Result<Vec<u8>, EncodeError> {
    append_crc(&mut out);
    if out.len() > MAX_FRAME_LEN {
        return Err(EncodeError::TooLong { len: out.len() });
    }
    Ok(out)
}

/// Checks length and CRC; returns the address and the PDU bytes between address and CRC.
fn split_frame(frame: &[u8]) -> Result<(u8, &[u8]), DecodeError> {
    if frame.len() < 4 {
        return Err(DecodeError::Truncated);
    }
    if !crc_is_valid(frame) {
        return Err(DecodeError::BadCrc);
    }
    let (&address, rest) = frame.split_first().ok_or(DecodeError::Truncated)?;
    let pdu = rest
        .get(..rest.len().saturating_sub(2))
        .ok_or(DecodeError::Truncated)?;
    Ok((address, pdu))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::fast::{Event, EventPacket, EventPriority, EventSource, RegisterType};

    fn encoded_len(reply: &Reply) -> usize {
        reply.encode().map(|frame| frame.len()).unwrap_or(0)
    }

    #[test]
    fn a_request_under_the_deprecated_0x60_keeps_its_code_both_ways() {
        let request = Request::by_serial(
            0xFE40_00AC,
            RequestPdu::ReadHoldingRegisters {
                start: 200,
                count: 20,
            },
        )
        .with_fast_function(fast::LEGACY_FUNCTION);
        let frame = request.encode().unwrap();
        assert_eq!(frame[..3], [0xFD, 0x60, 0x08]);
        assert_eq!(
            Request::length_from_header(&frame),
            FrameLength::Known(frame.len())
        );
        assert_eq!(Request::decode(&frame), Ok(request));
        // The usual code stays the default.
        assert_eq!(
            Request::scan_start().encode().unwrap(),
            [0xFD, 0x46, 0x01, 0x13, 0x90]
        );
    }

    #[test]
    fn expected_reply_len_is_the_length_of_the_encoded_reply() {
        let read = Request::classic(7, RequestPdu::ReadInputRegisters { start: 0, count: 3 });
        let values = ResponsePdu::ReadInputRegisters {
            values: vec![1, 2, 3],
        };
        assert_eq!(read.expected_reply_len(), 11);
        assert_eq!(
            read.expected_reply_len(),
            encoded_len(&Reply::classic(7, values))
        );

        let coils = Request::classic(7, RequestPdu::ReadCoils { start: 0, count: 9 });
        let packed = ResponsePdu::ReadCoils { packed: vec![0, 1] };
        assert_eq!(
            coils.expected_reply_len(),
            encoded_len(&Reply::classic(7, packed))
        );

        let write = RequestPdu::WriteMultipleRegisters {
            start: 4,
            values: vec![1, 2],
        };
        let echo = ResponsePdu::WriteMultipleRegisters { start: 4, count: 2 };
        assert_eq!(
            Request::classic(7, write.clone()).expected_reply_len(),
            encoded_len(&Reply::classic(7, echo.clone()))
        );

        let by_serial = Request::by_serial(0xFE00_0001, write);
        let answer = FastReply::BySerial {
            serial: 0xFE00_0001,
            pdu: echo,
        };
        assert_eq!(
            by_serial.expected_reply_len(),
            encoded_len(&Reply::fast(fast::BROADCAST_ADDRESS, answer))
        );

        let found = FastReply::ScanFound {
            serial: 0xFE00_0001,
            modbus_address: 7,
        };
        assert_eq!(
            Request::scan_start().expected_reply_len(),
            encoded_len(&Reply::fast(fast::BROADCAST_ADDRESS, found))
        );

        let ranges = vec![EventRange::registers(
            RegisterType::DiscreteInput,
            0,
            vec![EventPriority::Low; 9],
        )];
        let configured = FastReply::EventsConfigured {
            masks: vec![0xFF, 0x01],
        };
        assert_eq!(
            Request::configure_events(7, ranges).expected_reply_len(),
            encoded_len(&Reply::fast(7, configured))
        );
    }

    #[test]
    fn an_event_poll_expects_no_events_and_allows_a_full_packet() {
        let poll = Request::poll_events(EventPoll {
            min_address: 0,
            max_data_len: 10,
            ack_address: 0,
            ack_flag: 0,
        });
        assert_eq!(
            poll.expected_reply_len(),
            encoded_len(&Reply::fast(fast::BROADCAST_ADDRESS, FastReply::NoEvents))
        );
        // Two discrete inputs: 4 bytes of header and 1 of value each, 10 bytes of event data.
        let packet = EventPacket {
            flag: 1,
            event_count: 2,
            events: vec![
                Event {
                    source: EventSource::Register(RegisterType::DiscreteInput),
                    id: 1,
                    payload: vec![1],
                },
                Event {
                    source: EventSource::Register(RegisterType::DiscreteInput),
                    id: 2,
                    payload: vec![0],
                },
            ],
        };
        assert_eq!(
            poll.max_reply_len(),
            encoded_len(&Reply::fast(7, FastReply::Events(packet)))
        );
    }

    #[test]
    fn nobody_answers_a_classic_broadcast() {
        let write = RequestPdu::WriteSingleRegister {
            address: 1,
            value: 2,
        };
        let broadcast = Request::classic(CLASSIC_BROADCAST, write);
        assert_eq!(broadcast.expected_reply_len(), 0);
        assert_eq!(broadcast.max_reply_len(), 0);
    }
}
