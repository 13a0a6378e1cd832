//! Properties of the protocol core: every message type round-trips through encode and decode,
//! the parsers find frames however the bytes are chunked and whatever garbage precedes them, and
//! no input makes anything panic.

use proptest::collection::vec;
use proptest::prelude::*;
use rtu2mqtt::protocol::fast::LEGACY_FUNCTION;
use rtu2mqtt::protocol::{
    Event, EventPacket, EventPoll, EventPriority, EventRange, EventSource, ExceptionCode,
    FastReply, FastRequest, ParseStatus, ParsedRequest, RegisterType, Reply, ReplyBody,
    ReplyParser, Request, RequestParser, RequestPdu, ResponsePdu,
};

fn register_type() -> impl Strategy<Value = RegisterType> {
    prop_oneof![
        Just(RegisterType::Coil),
        Just(RegisterType::DiscreteInput),
        Just(RegisterType::Holding),
        Just(RegisterType::Input)
    ]
}

fn request_pdu() -> impl Strategy<Value = RequestPdu> {
    prop_oneof![
        (any::<u16>(), 1..=2000u16)
            .prop_map(|(start, count)| RequestPdu::ReadCoils { start, count }),
        (any::<u16>(), 1..=2000u16)
            .prop_map(|(start, count)| RequestPdu::ReadDiscreteInputs { start, count }),
        (any::<u16>(), 1..=125u16)
            .prop_map(|(start, count)| RequestPdu::ReadHoldingRegisters { start, count }),
        (any::<u16>(), 1..=125u16)
            .prop_map(|(start, count)| RequestPdu::ReadInputRegisters { start, count }),
        (any::<u16>(), any::<bool>())
            .prop_map(|(address, value)| RequestPdu::WriteSingleCoil { address, value }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| RequestPdu::WriteSingleRegister { address, value }),
        (any::<u16>(), vec(any::<bool>(), 1..=1968))
            .prop_map(|(start, values)| RequestPdu::WriteMultipleCoils { start, values }),
        (any::<u16>(), vec(any::<u16>(), 1..=123))
            .prop_map(|(start, values)| RequestPdu::WriteMultipleRegisters { start, values }),
    ]
}

/// Reply PDUs that fit a frame (and an 0x09 frame, which has 5 more header bytes).
fn response_pdu() -> impl Strategy<Value = ResponsePdu> {
    prop_oneof![
        vec(any::<u8>(), 0..=240).prop_map(|packed| ResponsePdu::ReadCoils { packed }),
        vec(any::<u8>(), 0..=240).prop_map(|packed| ResponsePdu::ReadDiscreteInputs { packed }),
        vec(any::<u16>(), 0..=120).prop_map(|values| ResponsePdu::ReadHoldingRegisters { values }),
        vec(any::<u16>(), 0..=120).prop_map(|values| ResponsePdu::ReadInputRegisters { values }),
        (any::<u16>(), any::<bool>())
            .prop_map(|(address, value)| ResponsePdu::WriteSingleCoil { address, value }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(address, value)| ResponsePdu::WriteSingleRegister { address, value }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(start, count)| ResponsePdu::WriteMultipleCoils { start, count }),
        (any::<u16>(), any::<u16>())
            .prop_map(|(start, count)| ResponsePdu::WriteMultipleRegisters { start, count }),
        (1..=0x7Fu8, any::<u8>()).prop_map(|(function, code)| ResponsePdu::Exception {
            function,
            code: ExceptionCode(code)
        }),
    ]
}

fn event_range() -> impl Strategy<Value = EventRange> {
    let priority = prop_oneof![
        Just(EventPriority::Disabled),
        Just(EventPriority::Low),
        Just(EventPriority::High)
    ];
    (register_type(), any::<u16>(), vec(priority, 1..=40)).prop_map(
        |(register_type, start, priorities)| {
            EventRange::registers(register_type, start, priorities)
        },
    )
}

fn fast_request() -> impl Strategy<Value = FastRequest> {
    prop_oneof![
        Just(FastRequest::ScanStart),
        Just(FastRequest::ScanContinue),
        (any::<u32>(), request_pdu())
            .prop_map(|(serial, pdu)| FastRequest::BySerial { serial, pdu }),
        (any::<u8>(), any::<u8>(), any::<u8>(), 0..=1u8).prop_map(
            |(min_address, max_data_len, ack_address, ack_flag)| {
                FastRequest::PollEvents(EventPoll {
                    min_address,
                    max_data_len,
                    ack_address,
                    ack_flag,
                })
            }
        ),
        vec(event_range(), 1..=5).prop_map(|ranges| FastRequest::ConfigureEvents { ranges }),
    ]
}

fn event() -> impl Strategy<Value = Event> {
    let source = prop_oneof![
        register_type().prop_map(EventSource::Register),
        Just(EventSource::System),
        (5..=14u8).prop_map(EventSource::Other),
    ];
    (source, any::<u16>(), vec(any::<u8>(), 0..=8)).prop_map(|(source, id, payload)| Event {
        source,
        id,
        payload,
    })
}

fn fast_reply() -> impl Strategy<Value = FastReply> {
    prop_oneof![
        (any::<u32>(), 1..=247u8).prop_map(|(serial, modbus_address)| FastReply::ScanFound {
            serial,
            modbus_address
        }),
        Just(FastReply::ScanEnd),
        (any::<u32>(), response_pdu())
            .prop_map(|(serial, pdu)| FastReply::BySerial { serial, pdu }),
        (0..=1u8, any::<u8>(), vec(event(), 0..=15)).prop_map(|(flag, event_count, events)| {
            FastReply::Events(EventPacket {
                flag,
                event_count,
                events,
            })
        }),
        Just(FastReply::NoEvents),
        vec(any::<u8>(), 0..=64).prop_map(|masks| FastReply::EventsConfigured { masks }),
    ]
}

fn request() -> impl Strategy<Value = Request> {
    prop_oneof![
        (0..=247u8, request_pdu()).prop_map(|(address, pdu)| Request::classic(address, pdu)),
        fast_request().prop_map(|request| {
            let address = if matches!(request, FastRequest::ConfigureEvents { .. }) {
                20
            } else {
                0xFD
            };
            Request::fast(address, request)
        }),
    ]
    // A 0x08 wrapper around a long write would pass 256 bytes; encode refuses it (tested below).
    .prop_filter("fits one frame", |request| request.encode().is_ok())
}

fn reply() -> impl Strategy<Value = Reply> {
    prop_oneof![
        (1..=247u8, response_pdu()).prop_map(|(address, pdu)| Reply::classic(address, pdu)),
        (
            1..=247u8,
            prop_oneof![Just(0x46u8), Just(LEGACY_FUNCTION)],
            fast_reply()
        )
            .prop_map(|(address, function, reply)| Reply {
                address,
                body: ReplyBody::Fast { function, reply }
            }),
    ]
}

/// Polls until a frame; errors are allowed before it.
fn first_reply(parser: &mut ReplyParser) -> Option<Reply> {
    loop {
        match parser.poll() {
            ParseStatus::Frame(parsed) => return Some(parsed.reply),
            ParseStatus::Error(_) => continue,
            ParseStatus::NeedMore => return None,
        }
    }
}

fn split_at_points(bytes: &[u8], cuts: &[usize]) -> Vec<Vec<u8>> {
    let mut points: Vec<usize> = cuts.iter().map(|c| c % (bytes.len() + 1)).collect();
    points.sort_unstable();
    let mut chunks = Vec::new();
    let mut from = 0;
    for point in points.into_iter().chain([bytes.len()]) {
        chunks.push(bytes[from..point].to_vec());
        from = point;
    }
    chunks
}

proptest! {
    #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn requests_round_trip(request in request()) {
        let bytes = request.encode().unwrap();
        prop_assert_eq!(Request::decode(&bytes), Ok(request.clone()));
        let mut parser = RequestParser::new();
        let mut found = None;
        for byte in &bytes {
            if let ParseStatus::Frame(parsed) = parser.feed(std::slice::from_ref(byte)) {
                found = Some(parsed);
            }
        }
        prop_assert_eq!(found, Some(ParsedRequest::Valid(request)));
    }

    #[test]
    fn replies_round_trip(reply in reply()) {
        let bytes = reply.encode().unwrap();
        prop_assert_eq!(Reply::decode(&bytes), Ok(reply.clone()));
    }

    #[test]
    fn reply_parser_ignores_chunking_and_filler(reply in reply(), filler in 0usize..40, cuts in vec(any::<usize>(), 0..6)) {
        let mut bytes = vec![0xFF; filler];
        bytes.extend(reply.encode().unwrap());
        let mut parser = ReplyParser::any();
        let mut found = None;
        for chunk in split_at_points(&bytes, &cuts) {
            parser.push(&chunk);
            if let ParseStatus::Frame(parsed) = parser.poll() {
                prop_assert_eq!(parsed.filler_bytes, filler);
                found = Some(parsed.reply);
            }
        }
        prop_assert_eq!(found, Some(reply));
    }

    /// Garbage that cannot start the expected reply is dropped, and the reply after it is found.
    #[test]
    fn reply_parser_resynchronises(count in 1..=125u16, values in vec(any::<u16>(), 125), garbage in vec(any::<u8>(), 0..64)) {
        let request = Request::classic(17, RequestPdu::ReadHoldingRegisters { start: 0, count });
        let reply = Reply::classic(17, ResponsePdu::ReadHoldingRegisters { values: values[..usize::from(count)].to_vec() });
        let mut bytes: Vec<u8> = garbage.into_iter().filter(|&b| b != 17).collect();
        bytes.extend(reply.encode().unwrap());
        let mut parser = ReplyParser::for_request(&request);
        parser.push(&bytes);
        prop_assert_eq!(first_reply(&mut parser), Some(reply));
    }

    #[test]
    fn garbage_never_panics(bytes in vec(any::<u8>(), 0..400), cuts in vec(any::<usize>(), 0..8), request in request()) {
        let _ = Request::decode(&bytes);
        let _ = Reply::decode(&bytes);
        let mut any = ReplyParser::any();
        let mut matching = ReplyParser::for_request(&request);
        let mut requests = RequestParser::new();
        for chunk in split_at_points(&bytes, &cuts) {
            any.push(&chunk);
            matching.push(&chunk);
            requests.push(&chunk);
            while !matches!(any.poll(), ParseStatus::NeedMore) {}
            while !matches!(matching.poll(), ParseStatus::NeedMore) {}
            while !matches!(requests.poll(), ParseStatus::NeedMore) {}
        }
        let _ = requests.silence();
        prop_assert!(any.buffered().len() <= 260);
        prop_assert!(requests.buffered().is_empty());
    }
}

#[test]
fn oversized_by_serial_write_is_refused() {
    let request = Request::by_serial(
        1,
        RequestPdu::WriteMultipleRegisters {
            start: 0,
            values: vec![0; 123],
        },
    );
    assert!(request.encode().is_err());
}

#[test]
fn header_lookalike_garbage_does_not_hide_the_reply() {
    // The garbage starts like the expected reply (address, function, byte count), then breaks off.
    let request = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    let mut bytes = vec![0x14, 0x03, 0x02, 0x00];
    bytes.extend([0x14, 0x03, 0x02, 0x00, 0x14, 0xB5, 0x88]);
    let mut parser = ReplyParser::for_request(&request);
    parser.push(&bytes);
    assert_eq!(
        first_reply(&mut parser),
        Some(Reply::classic(
            20,
            ResponsePdu::ReadHoldingRegisters { values: vec![20] }
        ))
    );
}

#[test]
fn unknown_function_is_rejected_after_silence() {
    // 0x2B (encapsulated interface) to device 20 with a valid CRC: illegal function.
    let mut frame = vec![0x14, 0x2B, 0x0E, 0x01, 0x00];
    rtu2mqtt::protocol::crc::append_crc(&mut frame);
    let mut parser = RequestParser::new();
    assert_eq!(parser.feed(&frame), ParseStatus::NeedMore);
    let ParseStatus::Frame(ParsedRequest::Rejected(rejected)) = parser.silence() else {
        panic!("expected a rejected request");
    };
    assert_eq!(rejected.exception, ExceptionCode::ILLEGAL_FUNCTION);
    assert_eq!(rejected.exception_reply().encode().unwrap(), {
        let mut reply = vec![0x14, 0xAB, 0x01];
        rtu2mqtt::protocol::crc::append_crc(&mut reply);
        reply
    });
}

#[test]
fn bad_quantity_by_serial_is_rejected_inside_a_0x09_reply() {
    let mut frame = vec![
        0xFD, 0x46, 0x08, 0xFE, 0x40, 0x00, 0xAC, 0x03, 0x00, 0xC8, 0x00, 0x7E,
    ];
    rtu2mqtt::protocol::crc::append_crc(&mut frame);
    let ParseStatus::Frame(ParsedRequest::Rejected(rejected)) = RequestParser::new().feed(&frame)
    else {
        panic!("expected a rejected request");
    };
    assert_eq!(
        rejected.exception_reply(),
        Reply::fast(
            0xFD,
            FastReply::BySerial {
                serial: 0xFE40_00AC,
                pdu: ResponsePdu::Exception {
                    function: 3,
                    code: ExceptionCode::ILLEGAL_DATA_VALUE
                }
            }
        )
    );
}

#[test]
fn fast_exception_answers_a_configure_request() {
    let request = Request::configure_events(
        5,
        vec![EventRange::registers(
            RegisterType::Coil,
            0,
            vec![EventPriority::High],
        )],
    );
    let exception = Reply::classic(
        5,
        ResponsePdu::Exception {
            function: 0x46,
            code: ExceptionCode::ILLEGAL_FUNCTION,
        },
    );
    let mut parser = ReplyParser::for_request(&request);
    parser.push(&exception.encode().unwrap());
    assert_eq!(first_reply(&mut parser), Some(exception));
}
