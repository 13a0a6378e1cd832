//! The device side's request parser on arbitrary bytes, with silences at arbitrary places: never a
//! panic, and every request it returns re-encodes to the same frame.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::protocol::{ParseStatus, ParsedRequest, Request, RequestParser};

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, bytes)) = data.split_first() else { return };
    let mut parser = RequestParser::new();
    for (i, piece) in bytes.chunks(usize::from(chunk % 32).max(1)).enumerate() {
        parser.push(piece);
        let mut status = parser.poll();
        if i % 3 == 2 {
            status = match status {
                ParseStatus::NeedMore => parser.silence(),
                other => other,
            };
        }
        loop {
            match status {
                ParseStatus::NeedMore => break,
                ParseStatus::Error(_) => {}
                ParseStatus::Frame(ParsedRequest::Valid(request)) => {
                    let encoded = request.encode().expect("a parsed request re-encodes");
                    assert_eq!(Request::decode(&encoded).as_ref(), Ok(&request));
                }
                ParseStatus::Frame(ParsedRequest::Rejected(rejected)) => {
                    let _ = rejected.exception_reply().encode();
                }
            }
            status = parser.poll();
        }
    }
    let _ = parser.silence();
});
