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
use super::scan_floor::wire_floor;

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
