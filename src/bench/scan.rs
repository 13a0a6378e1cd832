//! Scenario 5: the site tool `rtu2mqtt scan` over all 48 port settings (24 transmissions: the
//! stop bits are not visible on the wire), run as a user runs it (its own process, the
//! simulator's pty), on a bus with devices at three settings and on an empty bus (what an empty
//! setting costs).

use crate::child::StopWithParent;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use super::harness::{Harness, HarnessOptions};
use super::layout::BenchLayout;
use crate::protocol::timing::ARBITRATION_WINDOWS_SCAN;
use crate::protocol::{LineSettings, Parity, Request, RequestPdu};
use crate::tools::bus::{text_reads, PORT_SETTINGS_REGISTER, TEXT_REGISTERS};
use crate::tools::plan::{same_on_the_wire, scan_plan, PlanFilter};

/// One `rtu2mqtt scan --json` run.
#[derive(Debug, Clone, Default)]
pub struct ScanRun {
    pub label: String,
    /// Devices on the simulated bus.
    pub devices_on_bus: usize,
    /// Distinct port settings those devices use.
    pub settings_used: usize,
    /// Port settings the scan covered (48: each transmission covers 1 and 2 stop bits).
    pub settings_scanned: usize,
    /// Settings transmitted at (24).
    pub transmissions: usize,
    pub devices_found: usize,
    /// Wall time of the scan process, start to exit.
    pub elapsed: Duration,
    /// What no scan can beat: per transmission, the scan request's wire time plus the
    /// first-byte timeout after it; where devices answered, their scan rounds instead, and each
    /// device's identity reads (request, the device's 3.5-character turnaround, reply), all on
    /// the wire at that setting.
    pub wire_floor: Duration,
    pub problem: Option<String>,
}

/// Six devices: two at each of 115200 8N2, 9600 8N2 and 19200 8E1.
pub fn devices_at_three_settings() -> Vec<(u8, &'static str)> {
    vec![
        (1, "115200 8N2"),
        (2, "115200 8N2"),
        (3, "9600 8N2"),
        (4, "9600 8N2"),
        (5, "19200 8E1"),
        (6, "19200 8E1"),
    ]
}

/// Scans a bus holding `devices` (address, line) with the default 48-setting plan.
pub fn run_scan(binary: &Path, mosquitto: &Path, label: &str, devices: &[(u8, &str)]) -> ScanRun {
    let mut run = ScanRun {
        label: label.to_owned(),
        devices_on_bus: devices.len(),
        ..ScanRun::default()
    };
    let mut lines: Vec<&str> = devices.iter().map(|(_, line)| *line).collect();
    lines.sort_unstable();
    lines.dedup();
    run.settings_used = lines.len();
    match scan_into(&mut run, binary, mosquitto, devices) {
        Ok(report) => run.wire_floor = wire_floor(&report),
        Err(err) => run.problem = Some(format!("{err:#}")),
    }
    run
}

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

fn scan_into(
    run: &mut ScanRun,
    binary: &Path,
    mosquitto: &Path,
    devices: &[(u8, &str)],
) -> anyhow::Result<Value> {
    let layout = BenchLayout {
        devices: 1,
        events: 1,
        registers: 1,
        baud: 115_200,
        fast_devices: true,
    };
    let (template_name, template) = layout.template();
    let bus_devices: Vec<Value> = devices
        .iter()
        .map(|(address, line)| {
            json!({
                "name": format!("d{address}"),
                "template": layout.device_type(),
                "address": address,
                "serial": 0xFE00_0000_u32 + u32::from(*address),
                "line": line,
                "fast": true,
            })
        })
        .collect();
    let mut options = HarnessOptions::new(
        binary,
        json!({"seed": 1, "devices": bus_devices}),
        vec![(template_name, template)],
    );
    options.mosquitto = mosquitto.to_path_buf();
    let harness = Harness::start(&options)?;
    let started = Instant::now();
    let output = Command::new(binary)
        .stop_with_parent()
        .arg("scan")
        .arg("--port")
        .arg(harness.pty())
        .arg("--json")
        // The simulator plays the UART as the tools leave a controller's own port (each byte
        // handed over as it comes); there the tool reads that back from the kernel, which a
        // pseudo-terminal cannot tell.
        .args(["--fifo-trigger", "1"])
        .output()?;
    run.elapsed = started.elapsed();
    let report: Value = serde_json::from_slice(&output.stdout).map_err(|err| {
        anyhow::anyhow!(
            "scan output is not JSON ({err}); exit {}; stderr: {}",
            output.status,
            String::from_utf8_lossy(&output.stderr)
        )
    })?;
    run.settings_scanned = report["port_settings_scanned"].as_u64().unwrap_or(0) as usize;
    run.transmissions = report["transmissions"].as_u64().unwrap_or(0) as usize;
    run.devices_found = report["devices"].as_array().map_or(0, Vec::len);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

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
