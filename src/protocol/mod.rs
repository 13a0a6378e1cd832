//! The protocol core: pure code, no IO, no clock. Every frame rtu2mqtt sends or accepts is built
//! and checked here, and nowhere else.
//!
//! Where to find what:
//!
//! | topic                                               | module            |
//! |-----------------------------------------------------|-------------------|
//! | CRC16                                               | [`crc`]           |
//! | classic functions 0x01–0x06, 0x0F, 0x10, exceptions | [`pdu`]           |
//! | Fast Modbus sub-commands 0x01–0x04, 0x08–0x12, 0x18 | [`fast`]          |
//! | whole frames: address, PDU, CRC                     | [`frame`]         |
//! | finding frames in a byte stream                     | [`parser`]        |
//! | arbitration words and rounds                        | [`arbitration`]   |
//! | character time, silences, windows, poll interval    | [`timing`]        |
//!
//! Nothing here panics on any input: decoders return [`DecodeError`], encoders [`EncodeError`].

pub mod arbitration;
pub mod crc;
pub mod fast;
pub mod frame;
pub mod parser;
pub mod pdu;
pub mod timing;
pub mod transaction;
mod wire;

pub use arbitration::{arbitrate, Arbitration, ArbitrationWord, EventUrgency};
pub use crc::crc16;
pub use fast::{
    event_payload_words, Event, EventPacket, EventPoll, EventPriority, EventRange, EventSource,
    FastReply, FastRequest, RegisterType,
};
pub use frame::{Reply, ReplyBody, Request, RequestBody};
pub use parser::{
    ParseError, ParseStatus, ParsedReply, ParsedRequest, RejectedRequest, ReplyParser,
    RequestParser,
};
pub use pdu::{ExceptionCode, RequestPdu, ResponsePdu};
pub use timing::{LineSettings, Parity};
pub use transaction::{ReplyTiming, Transaction, TransactionOutcome};

/// Why bytes did not decode to a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("frame ends before its header says it does")]
    Truncated,
    #[error("{0} byte(s) left after the end of the frame")]
    TrailingBytes(usize),
    #[error("CRC mismatch")]
    BadCrc,
    #[error("unknown function code 0x{0:02X}")]
    UnknownFunction(u8),
    #[error("unknown Fast Modbus sub-command 0x{0:02X}")]
    UnknownSubCommand(u8),
    #[error("function 0x{function:02X}: {what}")]
    InvalidValue { function: u8, what: &'static str },
}

impl DecodeError {
    /// The exception a device answers a request with when the request failed to decode this way.
    /// None for frames a device must ignore (bad CRC).
    pub fn exception(&self) -> Option<ExceptionCode> {
        match self {
            Self::UnknownFunction(_) | Self::UnknownSubCommand(_) => {
                Some(ExceptionCode::ILLEGAL_FUNCTION)
            }
            Self::InvalidValue { .. } | Self::Truncated | Self::TrailingBytes(_) => {
                Some(ExceptionCode::ILLEGAL_DATA_VALUE)
            }
            Self::BadCrc => None,
        }
    }
}

/// Why a message could not be encoded (it would break the protocol's limits).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    #[error("{count} {what}: allowed 1..={max}")]
    CountOutOfRange {
        what: &'static str,
        count: usize,
        max: usize,
    },
    #[error("{len} bytes do not fit the frame")]
    TooLong { len: usize },
}

/// Hex dump for logs and CLI output: `FD 46 10 …`.
pub fn hex(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len() * 3);
    for (i, byte) in bytes.iter().enumerate() {
        if i > 0 {
            out.push(' ');
        }
        out.push_str(&format!("{byte:02X}"));
    }
    out
}

/// Parses hex like `FD 46 10`, `fd4610` or `0xFD,0x46`: pairs of hex digits, separators ignored.
pub fn parse_hex(text: &str) -> Result<Vec<u8>, String> {
    let cleaned: String = text
        .replace("0x", "")
        .replace("0X", "")
        .chars()
        .filter(|c| !c.is_whitespace() && *c != ',' && *c != ':' && *c != '-')
        .collect();
    if cleaned.len() % 2 != 0 {
        return Err(format!("odd number of hex digits in {text:?}"));
    }
    (0..cleaned.len())
        .step_by(2)
        .map(|i| {
            cleaned
                .get(i..i + 2)
                .and_then(|pair| u8::from_str_radix(pair, 16).ok())
                .ok_or_else(|| format!("not a hex byte at position {i} in {text:?}"))
        })
        .collect()
}
