//! `rtu2mqtt decode`: explain a frame given as hex, as a master or a device would read it.

use std::fmt::Write as _;
use std::process::ExitCode;

use crate::protocol::{self, ParseStatus, ParsedRequest, ReplyParser, RequestParser};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The frame's bytes in hex, e.g. "FD 46 10 00 FF 00 00 C8 9A" (separators optional).
    #[arg(required = true, num_args = 1..)]
    pub hex: Vec<String>,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let bytes = protocol::parse_hex(&args.hex.join(" ")).map_err(anyhow::Error::msg)?;
    let (text, valid) = describe(&bytes);
    print!("{text}");
    Ok(if valid {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// What the bytes are, as a request (master → device) and as a reply (device → master), and
/// whether they are a valid frame at all.
pub fn describe(bytes: &[u8]) -> (String, bool) {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "bytes:   {} ({} bytes)",
        protocol::hex(bytes),
        bytes.len()
    );
    let mut any = false;
    let mut requests = RequestParser::new();
    requests.push(bytes);
    if let ParseStatus::Frame(parsed) =
        first_frame(&mut requests, RequestParser::poll, RequestParser::silence)
    {
        any = true;
        match parsed {
            ParsedRequest::Valid(request) => {
                let _ = writeln!(out, "request: {request:?}");
            }
            ParsedRequest::Rejected(rejected) => {
                let _ = writeln!(
                    out,
                    "request: well-formed but a device rejects it with {} (function 0x{:02X})",
                    rejected.exception, rejected.function
                );
            }
        }
    }
    let mut replies = ReplyParser::any();
    replies.push(bytes);
    if let ParseStatus::Frame(parsed) =
        first_frame(&mut replies, ReplyParser::poll, |_| ParseStatus::NeedMore)
    {
        any = true;
        let _ = writeln!(out, "reply:   {:?}", parsed.reply);
        if parsed.filler_bytes > 0 {
            let _ = writeln!(
                out,
                "         after {} arbitration filler byte(s) 0xFF",
                parsed.filler_bytes
            );
        }
    }
    if !any {
        let crc = protocol::crc16(bytes.get(..bytes.len().saturating_sub(2)).unwrap_or(&[]));
        let _ = writeln!(
            out,
            "not a valid frame (a frame ends with its CRC, low byte first; for these bytes it would be {})",
            protocol::hex(&crc.to_le_bytes())
        );
    }
    (out, any)
}

/// Polls until a frame, skipping errors; at the end of input, `at_end` gets one last chance.
fn first_frame<P, T>(
    parser: &mut P,
    poll: impl Fn(&mut P) -> ParseStatus<T>,
    at_end: impl Fn(&mut P) -> ParseStatus<T>,
) -> ParseStatus<T> {
    loop {
        match poll(parser) {
            ParseStatus::Frame(frame) => return ParseStatus::Frame(frame),
            ParseStatus::Error(_) => continue,
            ParseStatus::NeedMore => return at_end(parser),
        }
    }
}
