//! A long reply through the pacer (100 bytes at 115200 8N2, sent byte by byte at wire times)
//! arrives complete and byte-exact. How well it is timed is measured by the benchmarks, not
//! asserted here: the machines that run the tests are shared and noisy.

use std::time::Duration;

use crate::sim_support::{SimProcess, FAST};
use rtu2mqtt::protocol::{Request, RequestPdu};

#[test]
fn a_100_byte_reply_at_115200_8n2_arrives_byte_exact() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    // 760 coils: address, function, byte count, 95 data bytes, CRC = 100 bytes.
    let request = Request::classic(
        40,
        RequestPdu::ReadCoils {
            start: 0,
            count: 760,
        },
    );
    sim.control(
        serde_json::json!({"cmd": "set", "device": 40, "type": "coil", "address": 9, "value": 1}),
    );
    port.send(&request.encode().unwrap());
    let received: Vec<u8> = port
        .read_until(Duration::from_secs(2), |all| all.len() >= 100)
        .into_iter()
        .flat_map(|(_, bytes)| bytes)
        .collect();
    let mut expected = vec![0x28, 0x01, 95];
    expected.extend(std::iter::repeat_n(0u8, 95));
    expected[3 + 1] = 0b10; // coil 9: bit 1 of the second data byte
    let crc = rtu2mqtt::protocol::crc16(&expected).to_le_bytes();
    expected.extend_from_slice(&crc);
    assert_eq!(received, expected);
}
