//! MQTT RPC requests on arbitrary bytes: any MQTT client can publish to the request topics, so
//! the envelope and the params of every method, served or not, are read without a panic, and a
//! request that is read has a bounded total_timeout (and a `port/EventLog` wait within it).
#![no_main]

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::rpc::message::parse_request;
use rtu2mqtt::rpc::params::{parse_method, Method, MAX_TOTAL_TIMEOUT, NOT_SERVED, SERVED};

fuzz_target!(|data: &[u8]| {
    let Some((&selector, payload)) = data.split_first() else {
        return;
    };
    let Ok(request) = parse_request(payload) else {
        return;
    };
    let methods: Vec<&(&str, &str)> = SERVED.iter().chain(NOT_SERVED).collect();
    let (service, method) = methods[usize::from(selector) % methods.len()];
    if let Ok(method) = parse_method(service, method, &request.params) {
        assert!(method.total_timeout() <= MAX_TOTAL_TIMEOUT);
        // A long poll answers before its caller stops waiting.
        if let Method::PortEventLog(read) = &method {
            assert!(read.wait < read.total_timeout || read.wait.is_zero());
        }
    }
});
