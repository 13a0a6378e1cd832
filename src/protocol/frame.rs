//! Whole RTU frames (ADUs): `address | function | body | CRC16 (low byte first)`.
//!
//! [`Request`] is what the master sends, [`Reply`] what a device sends. Both encode to bytes and
//! decode from exactly one frame; the incremental parsers in [`super::parser`] find frames in a
//! byte stream.

use super::crc::{append_crc, crc_is_valid};
use super::fast::{self, EventPoll, EventRange, FastReply, FastRequest};
use super::pdu::{FrameLength, RequestPdu, ResponsePdu, EXCEPTION_FLAG};
use super::{DecodeError, EncodeError};

/// Longest RTU frame the standard allows.
pub const MAX_FRAME_LEN: usize = 256;
/// Address 0: a classic broadcast that no device answers.
pub const CLASSIC_BROADCAST: u8 = 0;
/// Highest address a device may have.
pub const MAX_DEVICE_ADDRESS: u8 = 247;

/// A frame from the master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    pub address: u8,
    pub body: RequestBody,
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
        }
    }

    /// True when no reply may follow: a classic broadcast.
    pub fn expects_reply(&self) -> bool {
        self.address != CLASSIC_BROADCAST
    }

    pub fn is_fast(&self) -> bool {
        matches!(self.body, RequestBody::Fast(_))
    }

    /// The frame as it goes on the wire, CRC included.
    pub fn encode(&self) -> Result<Vec<u8>, EncodeError> {
        let mut out = Vec::with_capacity(16);
        out.push(self.address);
        match &self.body {
            RequestBody::Classic(pdu) => pdu.encode(&mut out)?,
            RequestBody::Fast(request) => {
                out.push(fast::FUNCTION);
                request.encode(&mut out)?;
            }
        }
        finish_frame(out)
    }

    /// Decodes exactly one frame (CRC included).
    pub fn decode(frame: &[u8]) -> Result<Self, DecodeError> {
        let (address, body) = split_frame(frame)?;
        let body = match body.split_first() {
            Some((&fast::FUNCTION, rest)) => RequestBody::Fast(FastRequest::decode(rest)?),
            _ => RequestBody::Classic(RequestPdu::decode(body)?),
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
            Some((&fast::FUNCTION, rest)) => add(FastRequest::length_from_header(rest), 1),
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
        let (address, body) = split_frame(frame)?;
        let body = match body.split_first() {
            Some((&function, rest)) if fast::is_fast_function(function) => ReplyBody::Fast {
                function,
                reply: FastReply::decode(rest)?,
            },
            _ => ReplyBody::Classic(ResponsePdu::decode(body)?),
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
