//! `rtu2mqtt decode`: explain a frame given as hex, as a master or a device would read it, in
//! the words of an integrator (addresses, registers, values, what a Fast Modbus sub-command
//! means), with `--json` for scripts.

use std::process::ExitCode;

use serde_json::{json, Value};

use crate::protocol::fast::{self, EventPacket, FastReply, FastRequest};
use crate::protocol::{
    self, pdu, Event, EventPriority, EventSource, ParseStatus, ParsedRequest, Reply, ReplyBody,
    ReplyParser, Request, RequestBody, RequestParser, RequestPdu, ResponsePdu,
};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The frame's bytes in hex, e.g. "FD 46 10 00 FF 00 00 C8 9A" (separators optional).
    #[arg(required = true, num_args = 1..)]
    pub hex: Vec<String>,
    /// Print JSON: {bytes, valid, request: {summary, details}, reply: {...}}.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    // Bytes that are no hex: bad input (exit 2, as every tool's bad arguments), not a frame
    // that failed its check (exit 1).
    let bytes = match protocol::parse_hex(&args.hex.join(" ")) {
        Ok(bytes) if !bytes.is_empty() => bytes,
        Ok(_) => {
            eprintln!("error: no bytes given: e.g. rtu2mqtt decode 14 03 00 80 00 01 87 27");
            return Ok(ExitCode::from(crate::tools::exit::USAGE));
        }
        Err(message) => {
            eprintln!("error: {message}");
            return Ok(ExitCode::from(crate::tools::exit::USAGE));
        }
    };
    let explained = explain(&bytes);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&explained.to_json())?);
    } else {
        print!("{}", explained.to_text());
    }
    Ok(if explained.valid() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// One reading of the bytes: a summary line and detail lines.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Reading {
    pub summary: String,
    pub details: Vec<String>,
}

/// The bytes read as a request, as a reply, or neither.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Explained {
    pub bytes: Vec<u8>,
    pub request: Option<Reading>,
    pub reply: Option<Reading>,
    pub filler_bytes: usize,
}

impl Explained {
    pub fn valid(&self) -> bool {
        self.request.is_some() || self.reply.is_some()
    }

    /// The CRC the bytes would need (when they are not valid).
    fn expected_crc(&self) -> [u8; 2] {
        protocol::crc16(
            self.bytes
                .get(..self.bytes.len().saturating_sub(2))
                .unwrap_or(&[]),
        )
        .to_le_bytes()
    }

    pub fn to_text(&self) -> String {
        let mut out = format!(
            "bytes:   {} ({} bytes)\n",
            protocol::hex(&self.bytes),
            self.bytes.len()
        );
        for (label, reading) in [("request", &self.request), ("reply", &self.reply)] {
            if let Some(reading) = reading {
                out.push_str(&format!("{label:<8} {}\n", reading.summary));
                for detail in &reading.details {
                    out.push_str(&format!("         - {detail}\n"));
                }
            }
        }
        if self.filler_bytes > 0 && self.reply.is_some() {
            out.push_str(&format!(
                "         after {} arbitration filler byte(s) 0xFF\n",
                self.filler_bytes
            ));
        }
        if !self.valid() {
            out.push_str(&format!(
                "not a valid frame (a frame ends with its CRC, low byte first; for these bytes it \
                 would be {})\n",
                protocol::hex(&self.expected_crc())
            ));
        }
        out
    }

    pub fn to_json(&self) -> Value {
        let reading = |r: &Option<Reading>| {
            r.as_ref()
                .map(|r| json!({"summary": r.summary, "details": r.details}))
        };
        json!({
            "bytes": protocol::hex(&self.bytes),
            "valid": self.valid(),
            "request": reading(&self.request),
            "reply": reading(&self.reply),
            "filler_bytes": self.filler_bytes,
            "crc_expected": (!self.valid()).then(|| protocol::hex(&self.expected_crc())),
        })
    }
}

/// What the bytes are, as a request (master → device) and as a reply (device → master).
pub fn explain(bytes: &[u8]) -> Explained {
    let mut explained = Explained {
        bytes: bytes.to_vec(),
        ..Explained::default()
    };
    let mut rejected_request = false;
    let mut requests = RequestParser::new();
    requests.push(bytes);
    if let ParseStatus::Frame(parsed) =
        first_frame(&mut requests, RequestParser::poll, RequestParser::silence)
    {
        rejected_request = matches!(parsed, ParsedRequest::Rejected(_));
        explained.request = Some(match parsed {
            ParsedRequest::Valid(request) => explain_request(&request),
            ParsedRequest::Rejected(rejected) => Reading {
                summary: format!(
                    "to address {}: well-formed, but a device rejects it with {} (function 0x{:02X})",
                    rejected.address, rejected.exception, rejected.function
                ),
                details: Vec::new(),
            },
        });
    }
    let mut replies = ReplyParser::any();
    replies.push(bytes);
    if let ParseStatus::Frame(parsed) =
        first_frame(&mut replies, ReplyParser::poll, |_| ParseStatus::NeedMore)
    {
        explained.reply = Some(explain_reply(&parsed.reply));
        explained.filler_bytes = parsed.filler_bytes;
        if rejected_request {
            // A reply that a device would refuse as a request: the reply is what it is.
            explained.request = None;
        }
    }
    explained
}

/// Kept for callers of the old API: the text and whether the bytes are a frame.
pub fn describe(bytes: &[u8]) -> (String, bool) {
    let explained = explain(bytes);
    (explained.to_text(), explained.valid())
}

fn who(address: u8) -> String {
    match address {
        0 => "broadcast (address 0, nobody answers)".into(),
        fast::BROADCAST_ADDRESS => format!("every Fast Modbus device (address {address})"),
        _ => format!("address {address}"),
    }
}

fn range(start: u16, count: u16) -> String {
    if count <= 1 {
        format!("{start}")
    } else {
        format!(
            "{start}..{} ({count})",
            u32::from(start) + u32::from(count) - 1
        )
    }
}

fn classic_request(pdu: &RequestPdu) -> (String, Vec<String>) {
    let bits = |v: &[bool]| {
        v.iter()
            .map(|b| if *b { "1" } else { "0" })
            .collect::<Vec<_>>()
            .join(" ")
    };
    let words = |v: &[u16]| {
        v.iter()
            .map(|w| format!("{w} (0x{w:04X})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    match pdu {
        RequestPdu::ReadCoils { start, count } => {
            (format!("read coils {}", range(*start, *count)), vec![])
        }
        RequestPdu::ReadDiscreteInputs { start, count } => (
            format!("read discrete inputs {}", range(*start, *count)),
            vec![],
        ),
        RequestPdu::ReadHoldingRegisters { start, count } => (
            format!("read holding registers {}", range(*start, *count)),
            vec![],
        ),
        RequestPdu::ReadInputRegisters { start, count } => (
            format!("read input registers {}", range(*start, *count)),
            vec![],
        ),
        RequestPdu::WriteSingleCoil { address, value } => (
            format!("write coil {address} = {}", u8::from(*value)),
            vec![],
        ),
        RequestPdu::WriteSingleRegister { address, value } => (
            format!("write holding register {address} = {value} (0x{value:04X})"),
            vec![],
        ),
        RequestPdu::WriteMultipleCoils { start, values } => (
            format!(
                "write coils {}",
                range(*start, u16::try_from(values.len()).unwrap_or(u16::MAX))
            ),
            vec![format!("values: {}", bits(values))],
        ),
        RequestPdu::WriteMultipleRegisters { start, values } => (
            format!(
                "write holding registers {}",
                range(*start, u16::try_from(values.len()).unwrap_or(u16::MAX))
            ),
            vec![format!("values: {}", words(values))],
        ),
    }
}

fn classic_reply(pdu: &ResponsePdu) -> (String, Vec<String>) {
    let words = |v: &[u16]| {
        v.iter()
            .map(|w| format!("{w} (0x{w:04X})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let bits = |packed: &[u8]| {
        pdu::unpack_bits(packed, packed.len() * 8)
            .iter()
            .map(|b| if *b { "1" } else { "0" })
            .collect::<Vec<_>>()
            .join(" ")
    };
    match pdu {
        ResponsePdu::ReadCoils { packed } => (
            "coil states".into(),
            vec![format!(
                "bits from the first coil on (the last byte is padded): {}",
                bits(packed)
            )],
        ),
        ResponsePdu::ReadDiscreteInputs { packed } => (
            "discrete input states".into(),
            vec![format!(
                "bits from the first input on (the last byte is padded): {}",
                bits(packed)
            )],
        ),
        ResponsePdu::ReadHoldingRegisters { values } => (
            format!("{} holding register value(s)", values.len()),
            vec![format!("values: {}", words(values))],
        ),
        ResponsePdu::ReadInputRegisters { values } => (
            format!("{} input register value(s)", values.len()),
            vec![format!("values: {}", words(values))],
        ),
        ResponsePdu::WriteSingleCoil { address, value } => (
            format!("coil {address} written: {}", u8::from(*value)),
            vec![],
        ),
        ResponsePdu::WriteSingleRegister { address, value } => (
            format!("holding register {address} written: {value}"),
            vec![],
        ),
        ResponsePdu::WriteMultipleCoils { start, count } => {
            (format!("coils {} written", range(*start, *count)), vec![])
        }
        ResponsePdu::WriteMultipleRegisters { start, count } => (
            format!("holding registers {} written", range(*start, *count)),
            vec![],
        ),
        ResponsePdu::Exception { function, code } => {
            (format!("refused function 0x{function:02X}: {code}"), vec![])
        }
    }
}

fn priority(p: EventPriority) -> &'static str {
    match p {
        EventPriority::Disabled => "off",
        EventPriority::Low => "low",
        EventPriority::High => "high",
    }
}

fn source(source: EventSource) -> String {
    match source {
        EventSource::Register(t) => crate::sim::control::register_type_name(t).to_owned(),
        EventSource::System => "system".to_owned(),
        EventSource::Other(byte) => format!("unknown type {byte}"),
    }
}

fn event_text(event: &Event) -> String {
    if event.is_reboot() {
        return "system event 0: the device restarted (its event settings are lost)".into();
    }
    let value = event
        .value()
        .map_or_else(|| protocol::hex(&event.payload), |v| v.to_string());
    format!("{} {} = {value}", source(event.source), event.id)
}

fn packet_details(address: u8, packet: &EventPacket) -> Vec<String> {
    let mut details = vec![format!(
        "packet flag {} (the master confirms it with ack address {address}, flag {})",
        packet.flag, packet.flag
    )];
    details.extend(packet.events.iter().map(event_text));
    details
}

pub fn explain_request(request: &Request) -> Reading {
    let to = who(request.address);
    match &request.body {
        RequestBody::Classic(pdu) => {
            let (what, details) = classic_request(pdu);
            Reading {
                summary: format!("to {to}: {what}"),
                details,
            }
        }
        RequestBody::Fast(fast) => match fast {
            FastRequest::ScanStart => Reading {
                summary: format!("to {to}: Fast Modbus scan, start (0x46 0x01)"),
                details: vec![
                    "every device takes part; the winner of the arbitration answers with its serial number and address".into(),
                ],
            },
            FastRequest::ScanContinue => Reading {
                summary: format!("to {to}: Fast Modbus scan, next device (0x46 0x02)"),
                details: vec!["devices not reported yet take part; when none is left one answers \"end of scan\"".into()],
            },
            FastRequest::BySerial { serial, pdu } => {
                let (what, details) = classic_request(pdu);
                Reading {
                    summary: format!(
                        "to the device with serial {serial} (0x{serial:08X}), whatever its address (0x46 0x08): {what}"
                    ),
                    details,
                }
            }
            FastRequest::PollEvents(poll) => {
                let mut details = vec![
                    if poll.min_address <= 1 {
                        "every device may answer".to_owned()
                    } else {
                        format!("devices below address {} stay silent this round", poll.min_address)
                    },
                    format!("at most {} bytes of event data per reply", poll.max_data_len),
                ];
                details.push(if poll.ack_address == 0 {
                    "confirms nothing".to_owned()
                } else {
                    format!(
                        "confirms the last packet of address {} (flag {})",
                        poll.ack_address, poll.ack_flag
                    )
                });
                Reading {
                    summary: format!("to {to}: does anyone have events? (0x46 0x10)"),
                    details,
                }
            }
            FastRequest::ConfigureEvents { ranges } => Reading {
                summary: format!("to {to}: set which registers send events (0x46 0x18)"),
                details: ranges
                    .iter()
                    .map(|r| {
                        let prios: Vec<&str> = r.priorities.iter().map(|p| priority(*p)).collect();
                        format!(
                            "{} {}: {}",
                            source(r.source),
                            range(r.start, u16::try_from(r.priorities.len()).unwrap_or(u16::MAX)),
                            prios.join(" ")
                        )
                    })
                    .collect(),
            },
        },
    }
}

pub fn explain_reply(reply: &Reply) -> Reading {
    let from = who(reply.address);
    match &reply.body {
        ReplyBody::Classic(pdu) => {
            let (what, details) = classic_reply(pdu);
            Reading {
                summary: format!("from {from}: {what}"),
                details,
            }
        }
        ReplyBody::Fast {
            function,
            reply: fast,
        } => {
            let legacy = if *function == fast::LEGACY_FUNCTION {
                vec!["function 0x60: old firmware's code for Fast Modbus replies".to_owned()]
            } else {
                vec![]
            };
            let (summary, mut details) = match fast {
                FastReply::ScanFound { serial, modbus_address } => (
                    format!(
                        "scan: found the device with serial {serial} (0x{serial:08X}) at address {modbus_address}"
                    ),
                    vec![],
                ),
                FastReply::ScanEnd => ("scan: no device left to report (end of scan)".into(), vec![]),
                FastReply::BySerial { serial, pdu } => {
                    let (what, details) = classic_reply(pdu);
                    (
                        format!("from the device with serial {serial} (0x{serial:08X}): {what}"),
                        details,
                    )
                }
                FastReply::Events(packet) => (
                    format!(
                        "events of address {}: {} event(s)",
                        reply.address,
                        packet.events.len()
                    ),
                    packet_details(reply.address, packet),
                ),
                FastReply::NoEvents => ("no device has events".into(), vec![]),
                FastReply::EventsConfigured { masks } => (
                    format!("from {from}: event settings accepted"),
                    vec![format!(
                        "enabled bits per range, first register in the lowest bit: {}",
                        protocol::hex(masks)
                    )],
                ),
            };
            details.extend(legacy);
            Reading { summary, details }
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::EventPoll;

    fn text(hex: &str) -> String {
        explain(&protocol::parse_hex(hex).unwrap()).to_text()
    }

    #[test]
    fn a_read_request_and_its_reply_in_words() {
        let request = Request::classic(
            20,
            RequestPdu::ReadHoldingRegisters {
                start: 128,
                count: 1,
            },
        )
        .encode()
        .unwrap();
        let explained = explain(&request);
        assert_eq!(
            explained.request.unwrap().summary,
            "to address 20: read holding registers 128"
        );
        let reply = Reply::classic(20, ResponsePdu::ReadHoldingRegisters { values: vec![20] })
            .encode()
            .unwrap();
        let explained = explain(&reply);
        let reading = explained.reply.unwrap();
        assert_eq!(
            reading.summary,
            "from address 20: 1 holding register value(s)"
        );
        assert_eq!(reading.details, vec!["values: 20 (0x0014)".to_owned()]);
    }

    #[test]
    fn an_event_poll_says_what_it_confirms() {
        let poll = Request::poll_events(EventPoll {
            min_address: 0,
            max_data_len: 100,
            ack_address: 20,
            ack_flag: 1,
        })
        .encode()
        .unwrap();
        let out = text(&protocol::hex(&poll));
        assert!(
            out.contains("does anyone have events? (0x46 0x10)"),
            "{out}"
        );
        assert!(
            out.contains("confirms the last packet of address 20 (flag 1)"),
            "{out}"
        );
    }

    #[test]
    fn scan_replies_and_exceptions_in_words() {
        let found = Reply::fast(
            fast::BROADCAST_ADDRESS,
            FastReply::ScanFound {
                serial: 0xFE40_00AC,
                modbus_address: 20,
            },
        )
        .encode()
        .unwrap();
        assert!(text(&protocol::hex(&found))
            .contains("found the device with serial 4265607340 (0xFE4000AC) at address 20"));
        let refused = Reply::classic(
            20,
            ResponsePdu::Exception {
                function: 3,
                code: protocol::ExceptionCode::ILLEGAL_DATA_ADDRESS,
            },
        )
        .encode()
        .unwrap();
        assert!(text(&protocol::hex(&refused)).contains("illegal data address"));
    }

    #[test]
    fn garbage_is_not_a_frame_and_json_says_so() {
        let explained = explain(&[0x14, 0x03, 0x00]);
        assert!(!explained.valid());
        assert_eq!(explained.to_json()["valid"], false);
        assert!(explained.to_text().contains("not a valid frame"));
    }
}
