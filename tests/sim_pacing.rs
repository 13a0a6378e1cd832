//! The one timing assertion the issue demands: a 100-byte reply at 115200 8N2 arrives in
//! 9.5 ms ± 10 %. The machine is shared and noisy, so this measures from the arrival of the first
//! byte to the arrival of the last (what the simulator controls, not the scheduling of the
//! request), and takes the best of 3 tries: one clean try proves the pacing, a preempted one
//! proves only that the machine was busy. Run with `--nocapture` to see the measured jitter.

mod sim_support;

use std::time::Duration;

use rtu2mqtt::protocol::{Request, RequestPdu};
use sim_support::{SimProcess, FAST};

#[test]
fn a_100_byte_reply_at_115200_8n2_takes_9_5_ms() {
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
    let char_time = FAST.char_time();
    let mut errors = Vec::new();
    for attempt in 0..3 {
        let sent_at = std::time::Instant::now();
        port.send(&request.encode().unwrap());
        let chunks = port.read_until(Duration::from_secs(2), |all| all.len() >= 100);
        let received: usize = chunks.iter().map(|(_, bytes)| bytes.len()).sum();
        assert_eq!(received, 100, "attempt {attempt}");
        let (first_at, _) = chunks.first().unwrap();
        let (last_at, _) = chunks.last().unwrap();
        let span = *last_at - *first_at;
        // Per-byte deviation from the ideal schedule (byte i at first + i × char time).
        let mut index = 0u32;
        let mut worst = Duration::ZERO;
        for (at, bytes) in &chunks {
            index += u32::try_from(bytes.len()).unwrap();
            let ideal = *first_at + char_time * (index - 1);
            worst = worst.max(
                at.saturating_duration_since(ideal)
                    .max(ideal.saturating_duration_since(*at)),
            );
        }
        // Request on the wire (8 chars) + 500 µs turnaround + the first reply char.
        let expected_latency = char_time * 9 + Duration::from_micros(500);
        eprintln!(
            "attempt {attempt}: request→first byte {:.3} ms (model {:.3} ms)",
            (*first_at - sent_at).as_secs_f64() * 1e3,
            expected_latency.as_secs_f64() * 1e3
        );
        eprintln!(
            "attempt {attempt}: first→last {:.3} ms over {} reads (ideal 99 chars = {:.3} ms), worst byte deviation {:.1} µs",
            span.as_secs_f64() * 1e3,
            chunks.len(),
            (char_time * 99).as_secs_f64() * 1e3,
            worst.as_secs_f64() * 1e6
        );
        let error = (span.as_secs_f64() - 9.5e-3).abs() / 9.5e-3;
        errors.push(error);
        if error <= 0.10 {
            return;
        }
    }
    panic!("no try within 9.5 ms ± 10 %: relative errors {errors:?}");
}
