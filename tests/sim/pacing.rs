//! A long reply through the pacer (100 bytes at 115200 8N2, sent byte by byte at wire times)
//! arrives complete and byte-exact. How well it is timed is measured by the benchmarks, not
//! asserted here: the machines that run the tests are shared and noisy.

use std::time::Duration;

use crate::sim_support::{with_crc, SimProcess, FAST};
use rtu2mqtt::protocol::{LineSettings, Parity, Request, RequestPdu};

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

/// A master that writes its next request as soon as it has read a reply, with no gap of its own,
/// is answered every time: a real UART hands the last bytes of a reply over 4 characters after
/// their stop bit (its receive timeout), so such a master keeps the devices' 3.5-character frame
/// silence without trying, and the simulator's port does the same. At 9600 and 115200.
#[test]
fn a_master_with_no_frame_gap_of_its_own_is_answered_every_time() {
    for (address, line) in [(241, FAST), (50, LineSettings::new(9600, Parity::None, 2))] {
        let sim = SimProcess::start("bus.json", &[]);
        let mut port = sim.master(line);
        let read = Request::classic(address, RequestPdu::ReadCoils { start: 0, count: 1 });
        let unanswered: Vec<(usize, Vec<u8>)> = (0..20)
            .filter_map(|attempt| {
                port.forget_last_read();
                let (bytes, reply) = port.transact(&read);
                let expected = with_crc(&format!("{address:02X} 01 01 00"));
                (reply.is_none() || !bytes.ends_with(&expected)).then_some((attempt, bytes))
            })
            .collect();
        assert!(
            unanswered.is_empty(),
            "{line}: not answered: {unanswered:02X?}"
        );
    }
}
