//! The wire floor of a scan (scenario 5): what no scan over the default 48-setting plan can
//! beat, from what the scan reported. Pure, so it is built and tested without the `bench`
//! feature.

use std::time::Duration;

use serde_json::Value;

use crate::protocol::timing::ARBITRATION_WINDOWS_SCAN;
use crate::protocol::{LineSettings, Parity, Request, RequestPdu};
use crate::tools::bus::{text_reads, PORT_SETTINGS_REGISTER, TEXT_REGISTERS};
use crate::tools::plan::{same_on_the_wire, scan_plan, PlanFilter};

/// The wire floor of what a scan with `report` (its `--json` output) transmitted and received.
pub fn wire_floor(report: &Value) -> Duration {
    let devices = report["devices"].as_array().cloned().unwrap_or_default();
    let answered_at = |device: &Value| -> Vec<LineSettings> {
        std::iter::once(&device["settings"])
            .chain(device["also_at"].as_array().into_iter().flatten())
            .filter_map(|text| text.as_str().and_then(parse_settings))
            .collect()
    };
    let scan_request = Request::scan_start().encoded_len();
    let mut floor = Duration::ZERO;
    for line in scan_plan(&PlanFilter::default()) {
        let heard = devices
            .iter()
            .filter(|d| answered_at(d).iter().any(|l| same_on_the_wire(l, &line)))
            .count();
        floor += if heard == 0 {
            line.wire_time(scan_request) + line.scan_start_first_byte_timeout()
        } else {
            // A round per device and the "end of scan" round: request, the devices' wait, every
            // window, the reply.
            let round = line.wire_time(scan_request)
                + line.device_arbitration_wait()
                + line.arbitration_window() * ARBITRATION_WINDOWS_SCAN;
            let found_reply = Request::scan_start().expected_reply_len();
            round * u32::try_from(heard + 1).unwrap_or(u32::MAX)
                + line.wire_time(found_reply) * u32::try_from(heard).unwrap_or(u32::MAX)
                + line.wire_time(5)
        };
    }
    for device in &devices {
        let Some(line) = answered_at(device).first().copied() else {
            continue;
        };
        let serial = device["serial"].as_u64().unwrap_or(0) as u32;
        let mut reads = vec![(PORT_SETTINGS_REGISTER, 3)];
        for ((start, count), field) in
            TEXT_REGISTERS
                .into_iter()
                .zip(["model", "firmware", "signature"])
        {
            let text_len = device[field].as_str().map_or(0, str::len);
            let parts = text_reads(start, count);
            let needed = if text_len >= usize::from(parts[0].1) {
                parts.len()
            } else {
                1
            };
            reads.extend(parts.into_iter().take(needed));
        }
        for (start, count) in reads {
            let request =
                Request::by_serial(serial, RequestPdu::ReadHoldingRegisters { start, count });
            floor += line.wire_time(request.encoded_len() + request.expected_reply_len())
                + line.bits_time(u64::from(line.bits_per_char()) * 7) / 2;
        }
    }
    floor
}

/// `9600 8N2`, `9600 8N?` (stop bits not reported: the scan sent with 2).
fn parse_settings(text: &str) -> Option<LineSettings> {
    let (baud, framing) = text.split_once(' ')?;
    let mut chars = framing.chars();
    let _data_bits = chars.next()?;
    let parity = match chars.next()? {
        'N' => Parity::None,
        'E' => Parity::Even,
        'O' => Parity::Odd,
        _ => return None,
    };
    let stop_bits = match chars.next()? {
        '1' => 1,
        _ => 2,
    };
    Some(LineSettings::new(baud.parse().ok()?, parity, stop_bits))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_floor_of_an_empty_bus_is_24_scan_starts() {
        let empty = wire_floor(&json!({"devices": []}));
        let expected: Duration = scan_plan(&PlanFilter::default())
            .iter()
            .map(|line| line.wire_time(5) + line.scan_start_first_byte_timeout())
            .sum();
        assert_eq!(empty, expected);
        assert!(empty > Duration::from_millis(500) && empty < Duration::from_millis(600));
    }

    #[test]
    fn devices_add_their_rounds_and_identity_reads() {
        let empty = wire_floor(&json!({"devices": []}));
        let one = wire_floor(&json!({"devices": [{
            "serial": 1, "settings": "115200 8N?", "also_at": [],
            "model": "WBMR6C", "firmware": "1.0", "signature": null
        }]}));
        let at_9600 = wire_floor(&json!({"devices": [{
            "serial": 1, "settings": "9600 8N1", "also_at": ["9600 8E2"],
            "model": "WBMR6C", "firmware": "1.0", "signature": null
        }]}));
        assert!(one > empty);
        assert!(
            at_9600 > one + Duration::from_millis(200),
            "{at_9600:?} {one:?}"
        );
        assert_eq!(
            parse_settings("19200 8E1"),
            Some(LineSettings::new(19200, Parity::Even, 1))
        );
        assert_eq!(
            parse_settings("9600 8N?"),
            Some(LineSettings::new(9600, Parity::None, 2))
        );
    }
}
