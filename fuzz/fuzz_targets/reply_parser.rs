//! The master's reply parser on arbitrary bytes in arbitrary chunks, for every kind of request:
//! never a panic, never an unbounded buffer, and every frame it returns re-encodes to valid bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::protocol::{
    EventPoll, EventPriority, EventRange, ParseStatus, RegisterType, Reply, ReplyParser, Request,
    RequestPdu,
};

fn request_for(selector: u8) -> Option<Request> {
    let range = EventRange::registers(RegisterType::Coil, 0, vec![EventPriority::High; 9]);
    Some(match selector % 9 {
        0 => return None,
        1 => Request::classic(20, RequestPdu::ReadHoldingRegisters { start: 128, count: 3 }),
        2 => Request::classic(20, RequestPdu::ReadCoils { start: 0, count: 11 }),
        3 => Request::classic(20, RequestPdu::WriteSingleRegister { address: 1, value: 2 }),
        4 => Request::scan_start(),
        5 => Request::by_serial(0xFE40_00AC, RequestPdu::ReadInputRegisters { start: 0, count: 2 }),
        6 => Request::poll_events(EventPoll { min_address: 0, max_data_len: 255, ack_address: 0, ack_flag: 0 }),
        7 => Request::configure_events(20, vec![range]),
        _ => Request::classic(0, RequestPdu::WriteSingleCoil { address: 0, value: true }),
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else { return };
    let Some((&chunk, bytes)) = rest.split_first() else { return };
    let mut parser = match request_for(selector) {
        Some(request) => ReplyParser::for_request(&request),
        None => ReplyParser::any(),
    };
    for piece in bytes.chunks(usize::from(chunk).max(1)) {
        parser.push(piece);
        loop {
            match parser.poll() {
                ParseStatus::NeedMore => break,
                ParseStatus::Error(_) => {}
                ParseStatus::Frame(parsed) => {
                    let encoded = parsed.reply.encode().expect("a parsed reply re-encodes");
                    assert_eq!(Reply::decode(&encoded).as_ref(), Ok(&parsed.reply));
                }
            }
        }
        assert!(parser.buffered().len() <= 512, "the parser buffers only what may still be a frame");
    }
});
