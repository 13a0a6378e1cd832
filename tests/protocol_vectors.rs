//! Every checked frame of `vectors.json` decodes to its meaning, encodes back to the same bytes,
//! and parses the same fed byte by byte as fed whole.

use rtu2mqtt::protocol::fast::{split_event_masks, LEGACY_FUNCTION};
use rtu2mqtt::protocol::{
    parse_hex, EventPoll, EventPriority, EventRange, EventSource, FastReply, FastRequest,
    ParseStatus, ParsedReply, ParsedRequest, RegisterType, Reply, ReplyBody, ReplyParser, Request,
    RequestParser, RequestPdu, ResponsePdu,
};
use serde_json::Value;

const VECTORS: &str = include_str!("data/vectors.json");

struct Vector {
    name: String,
    bytes: Vec<u8>,
    leading_ff: usize,
    meaning: Value,
}

fn vectors() -> Vec<Vector> {
    let doc: Value = serde_json::from_str(VECTORS).expect("vectors.json is JSON");
    doc["vectors"]
        .as_array()
        .expect("a vectors array")
        .iter()
        .map(|v| Vector {
            name: v["name"].as_str().unwrap().to_owned(),
            bytes: parse_hex(v["hex"].as_str().unwrap()).unwrap(),
            leading_ff: v["leading_ff"].as_u64().unwrap() as usize,
            meaning: v["meaning"].clone(),
        })
        .collect()
}

fn num(value: &Value, key: &str) -> u64 {
    value[key]
        .as_u64()
        .unwrap_or_else(|| panic!("meaning has no integer {key}: {value}"))
}

fn u16s(value: &Value) -> Vec<u16> {
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as u16)
        .collect()
}

fn event_ranges(meaning: &Value) -> Vec<EventRange> {
    meaning["ranges"]
        .as_array()
        .unwrap()
        .iter()
        .map(|range| EventRange {
            source: EventSource::from_wire(num(range, "type") as u8),
            start: num(range, "start") as u16,
            priorities: range["priorities"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| EventPriority::from_wire(p.as_u64().unwrap() as u8).unwrap())
                .collect(),
        })
        .collect()
}

/// A classic request PDU from `{function, start, count}` or `{function, register, value}`.
fn request_pdu(meaning: &Value) -> RequestPdu {
    match num(meaning, "function") {
        3 => RequestPdu::ReadHoldingRegisters {
            start: num(meaning, "start") as u16,
            count: num(meaning, "count") as u16,
        },
        6 => RequestPdu::WriteSingleRegister {
            address: num(meaning, "register") as u16,
            value: num(meaning, "value") as u16,
        },
        other => panic!("no vector uses request function {other}"),
    }
}

enum Expected {
    Request(Request),
    Reply(Reply),
}

/// What each vector must decode to, built from its `meaning` alone.
fn expected(vector: &Vector) -> Expected {
    let m = &vector.meaning;
    // Event replies carry no "sub" in their meaning: they are recognised by their event list.
    let sub = m
        .get("sub")
        .and_then(Value::as_u64)
        .or(m.get("events").map(|_| 17));
    let Some(sub) = sub else {
        let address = num(m, "address") as u8;
        return if let Some(code) = m.get("exception") {
            Expected::Reply(Reply::classic(
                address,
                ResponsePdu::Exception {
                    function: num(m, "function") as u8,
                    code: rtu2mqtt::protocol::ExceptionCode(code.as_u64().unwrap() as u8),
                },
            ))
        } else if let Some(registers) = m.get("registers") {
            assert_eq!(num(m, "function"), 3);
            Expected::Reply(Reply::classic(
                address,
                ResponsePdu::ReadHoldingRegisters {
                    values: u16s(registers),
                },
            ))
        } else {
            Expected::Request(Request::classic(address, request_pdu(m)))
        };
    };
    let fast_reply = |reply: FastReply| {
        let function = m.get("command").map_or(0x46, |c| c.as_u64().unwrap() as u8);
        Reply {
            address: 0xFD,
            body: ReplyBody::Fast { function, reply },
        }
    };
    match sub {
        1 => Expected::Request(Request::scan_start()),
        2 => Expected::Request(Request::scan_continue()),
        3 => Expected::Reply(fast_reply(FastReply::ScanFound {
            serial: num(m, "serial") as u32,
            modbus_address: num(m, "address") as u8,
        })),
        4 => Expected::Reply(fast_reply(FastReply::ScanEnd)),
        8 => Expected::Request(Request::by_serial(
            num(m, "serial") as u32,
            request_pdu(&m["pdu"]),
        )),
        9 => {
            let pdu = &m["pdu"];
            let response = match num(pdu, "function") {
                3 => {
                    let model = m["model"].as_str().unwrap();
                    let mut values: Vec<u16> = model.bytes().map(u16::from).collect();
                    values.resize(num(pdu, "byte_count") as usize / 2, 0);
                    ResponsePdu::ReadHoldingRegisters { values }
                }
                6 => ResponsePdu::WriteSingleRegister {
                    address: num(pdu, "register") as u16,
                    value: num(pdu, "value") as u16,
                },
                other => panic!("no vector uses reply function {other}"),
            };
            Expected::Reply(fast_reply(FastReply::BySerial {
                serial: num(m, "serial") as u32,
                pdu: response,
            }))
        }
        16 => Expected::Request(Request::poll_events(EventPoll {
            min_address: num(m, "min_address") as u8,
            max_data_len: num(m, "max_data_len") as u8,
            ack_address: num(m, "ack_address") as u8,
            ack_flag: num(m, "ack_flag") as u8,
        })),
        17 => {
            let events = m["events"]
                .as_array()
                .unwrap()
                .iter()
                .map(|e| rtu2mqtt::protocol::Event {
                    source: EventSource::from_wire(num(e, "type") as u8),
                    id: num(e, "id") as u16,
                    payload: e["payload"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|b| b.as_u64().unwrap() as u8)
                        .collect(),
                })
                .collect();
            Expected::Reply(Reply::fast(
                num(m, "address") as u8,
                FastReply::Events(rtu2mqtt::protocol::EventPacket {
                    flag: num(m, "flag") as u8,
                    event_count: num(m, "event_count") as u8,
                    events,
                }),
            ))
        }
        18 => Expected::Reply(fast_reply(FastReply::NoEvents)),
        24 if m.get("ranges").is_some() => Expected::Request(Request::configure_events(
            num(m, "address") as u8,
            event_ranges(m),
        )),
        24 => {
            let masks: Vec<u8> = m["masks"]
                .as_array()
                .unwrap()
                .iter()
                .flat_map(|mask| {
                    mask.as_array()
                        .unwrap()
                        .iter()
                        .map(|b| b.as_u64().unwrap() as u8)
                })
                .collect();
            Expected::Reply(Reply::fast(
                num(m, "address") as u8,
                FastReply::EventsConfigured { masks },
            ))
        }
        other => panic!("vector {} has unknown sub {other}", vector.name),
    }
}

fn parse_reply(parser: &mut ReplyParser, chunks: &[&[u8]]) -> Option<ParsedReply> {
    for chunk in chunks {
        parser.push(chunk);
        match parser.poll() {
            ParseStatus::Frame(parsed) => return Some(parsed),
            ParseStatus::Error(err) => panic!("error on a valid vector: {err}"),
            ParseStatus::NeedMore => {}
        }
    }
    None
}

fn parse_request(chunks: &[&[u8]]) -> Option<ParsedRequest> {
    let mut parser = RequestParser::new();
    for chunk in chunks {
        parser.push(chunk);
        match parser.poll() {
            ParseStatus::Frame(parsed) => return Some(parsed),
            ParseStatus::Error(err) => panic!("error on a valid vector: {err}"),
            ParseStatus::NeedMore => {}
        }
    }
    None
}

#[test]
fn every_vector_decodes_to_its_meaning_and_encodes_back() {
    let vectors = vectors();
    assert_eq!(vectors.len(), 36, "vectors.json holds 36 frames");
    for vector in &vectors {
        let frame = &vector.bytes[vector.leading_ff..];
        assert!(
            vector.bytes[..vector.leading_ff].iter().all(|&b| b == 0xFF),
            "{}",
            vector.name
        );
        match expected(vector) {
            Expected::Request(request) => {
                assert_eq!(vector.leading_ff, 0);
                assert_eq!(
                    Request::decode(frame).as_ref(),
                    Ok(&request),
                    "{}",
                    vector.name
                );
                assert_eq!(request.encode().unwrap(), frame, "{}", vector.name);
                let whole = parse_request(&[frame]);
                let byte_by_byte = parse_request(&frame.chunks(1).collect::<Vec<_>>());
                assert_eq!(
                    whole,
                    Some(ParsedRequest::Valid(request)),
                    "{}",
                    vector.name
                );
                assert_eq!(byte_by_byte, whole, "{}", vector.name);
            }
            Expected::Reply(reply) => {
                assert_eq!(Reply::decode(frame).as_ref(), Ok(&reply), "{}", vector.name);
                assert_eq!(reply.encode().unwrap(), frame, "{}", vector.name);
                let whole =
                    parse_reply(&mut ReplyParser::any(), &[&vector.bytes]).expect(&vector.name);
                let chunks: Vec<&[u8]> = vector.bytes.chunks(1).collect();
                let byte_by_byte =
                    parse_reply(&mut ReplyParser::any(), &chunks).expect(&vector.name);
                assert_eq!(whole.reply, reply, "{}", vector.name);
                assert_eq!(whole.filler_bytes, vector.leading_ff, "{}", vector.name);
                assert_eq!(whole.frame_len, frame.len(), "{}", vector.name);
                assert_eq!(byte_by_byte, whole, "{}", vector.name);
            }
        }
    }
}

/// Replies parsed by a parser that knows the request, as the master does.
#[test]
fn replies_match_their_requests() {
    let all = vectors();
    let by_name = |name: &str| all.iter().find(|v| v.name == name).unwrap();
    let pairs = [
        ("read_slave_id_request", "read_slave_id_reply"),
        ("read_two_regs_request", "read_two_regs_reply"),
        ("scan_start", "scan_reply_mcm8"),
        ("scan_start", "scan_reply_legacy_code_0x60"),
        ("scan_continue", "scan_end"),
        (
            "by_serial_read_model_request",
            "by_serial_read_model_reply_mcm8",
        ),
        (
            "by_serial_set_address_request",
            "by_serial_set_address_reply",
        ),
        ("events_config_request_mcm8", "events_config_reply_mcm8"),
        ("events_config_request_mr6c", "events_config_reply_mr6c"),
        ("events_config_request_62", "events_config_reply_62"),
        ("events_config_request_multi", "events_config_reply_multi"),
        ("events_request_no_ack", "events_reply_mr6c"),
        ("events_request_ack_241_flag0", "events_reply_mcm8"),
        ("events_request_no_ack", "events_reply_three"),
        ("events_request_no_ack", "events_reply_doc"),
        ("events_request_ack_20_flag0", "events_none"),
    ];
    for (request_name, reply_name) in pairs {
        let request = Request::decode(&by_name(request_name).bytes).unwrap();
        let reply = by_name(reply_name);
        let mut parser = ReplyParser::for_request(&request);
        let chunks: Vec<&[u8]> = reply.bytes.chunks(1).collect();
        let parsed = parse_reply(&mut parser, &chunks).unwrap_or_else(|| panic!("{reply_name}"));
        assert_eq!(parsed.filler_bytes, reply.leading_ff, "{reply_name}");
        assert!(parser.buffered().is_empty());
    }
    // The model read by serial of MR6C is not an answer to the request for MCM8's serial.
    let request = Request::decode(&by_name("by_serial_read_model_request").bytes).unwrap();
    let mut parser = ReplyParser::for_request(&request);
    parser.push(&by_name("by_serial_read_model_reply_mr6c").bytes);
    assert!(!matches!(parser.poll(), ParseStatus::Frame(_)));
}

#[test]
fn multi_range_masks_split_by_request() {
    let all = vectors();
    let request = all
        .iter()
        .find(|v| v.name == "events_config_request_multi")
        .unwrap();
    let ranges = event_ranges(&request.meaning);
    let reply = Reply::decode(
        &all.iter()
            .find(|v| v.name == "events_config_reply_multi")
            .unwrap()
            .bytes,
    )
    .unwrap();
    let ReplyBody::Fast {
        reply: FastReply::EventsConfigured { masks },
        ..
    } = reply.body
    else {
        panic!("not a 0x18 reply");
    };
    assert_eq!(
        split_event_masks(&masks, &ranges),
        Some(vec![vec![5], vec![5, 0]])
    );
    let enabled = rtu2mqtt::protocol::fast::enabled_registers(&masks, &ranges).unwrap();
    assert_eq!(
        enabled[0],
        (EventSource::Register(RegisterType::DiscreteInput), 4, true)
    );
    assert_eq!(
        enabled[1],
        (EventSource::Register(RegisterType::DiscreteInput), 5, false)
    );
    assert_eq!(
        enabled[5],
        (EventSource::Register(RegisterType::Input), 466, true)
    );
    assert_eq!(
        enabled[12],
        (EventSource::Register(RegisterType::Input), 473, false)
    );
}

#[test]
fn legacy_function_code_is_kept() {
    let all = vectors();
    let legacy = all
        .iter()
        .find(|v| v.name == "scan_reply_legacy_code_0x60")
        .unwrap();
    let reply = Reply::decode(&legacy.bytes[legacy.leading_ff..]).unwrap();
    assert!(matches!(
        reply.body,
        ReplyBody::Fast {
            function: LEGACY_FUNCTION,
            ..
        }
    ));
}

#[test]
fn unused_fast_request_kinds_round_trip() {
    // Kinds the vectors do not cover, with hand-checked layouts.
    let request = Request::fast(0xFD, FastRequest::ScanContinue);
    assert_eq!(
        request.encode().unwrap(),
        vec![0xFD, 0x46, 0x02, 0x53, 0x91]
    );
}
