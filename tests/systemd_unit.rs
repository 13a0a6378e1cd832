//! The shipped systemd unit passes `systemd-analyze verify` (pointed at the binary under test,
//! since the unit names its installed path), and says what the service contract needs.

use std::path::Path;
use std::process::Command;

fn unit_text() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/rtu2mqtt.service");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn unit_passes_systemd_analyze_verify() {
    let analyze = ["/usr/bin/systemd-analyze", "/bin/systemd-analyze"]
        .into_iter()
        .find(|p| Path::new(p).exists())
        .expect("this test needs systemd-analyze (apt-get install systemd; scripts/test does it)");
    let dir = tempfile::tempdir().expect("temp dir");
    let unit = unit_text().replace("/usr/bin/rtu2mqtt", env!("CARGO_BIN_EXE_rtu2mqtt"));
    let path = dir.path().join("rtu2mqtt.service");
    std::fs::write(&path, unit).expect("write unit");
    let out = Command::new(analyze)
        .args(["verify", "--man=no"])
        .arg(&path)
        .output()
        .expect("run systemd-analyze");
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Warnings about the host's own units (not ours) are not ours to fix.
    let ours: Vec<&str> = stderr.lines().filter(|l| l.contains("rtu2mqtt")).collect();
    assert!(
        out.status.success() && ours.is_empty(),
        "systemd-analyze verify failed ({}):\n{stderr}",
        out.status
    );
}

#[test]
fn unit_is_a_notify_service_with_watchdog_and_reload() {
    let unit = unit_text();
    for line in [
        "Type=notify",
        "NotifyAccess=main",
        "WatchdogSec=30s",
        "Restart=on-failure",
        "ExecReload=/bin/kill -HUP $MAINPID",
        "Environment=CONFIG_FILE=/etc/rtu2mqtt/config.json",
        "EnvironmentFile=-/etc/rtu2mqtt/environment",
        "ExecStartPre=/usr/bin/rtu2mqtt check-config -c ${CONFIG_FILE}",
        "ExecStartPre=+/usr/bin/rtu2mqtt prepare-ports -c ${CONFIG_FILE}",
        "ExecStart=/usr/bin/rtu2mqtt run -c ${CONFIG_FILE}",
        "ExecReload=-+/usr/bin/rtu2mqtt prepare-ports -c ${CONFIG_FILE} --except-pid $MAINPID",
        "SupplementaryGroups=dialout",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "DevicePolicy=closed",
    ] {
        assert!(
            unit.lines().any(|l| l.trim() == line),
            "systemd/rtu2mqtt.service lacks `{line}`"
        );
    } // One place names the config: a drop-in that sets CONFIG_FILE moves every step to it.
    for line in unit
        .lines()
        .filter(|l| l.starts_with("Exec") && l.contains(" -c "))
    {
        assert!(
            line.split(" -c ")
                .nth(1)
                .and_then(|rest| rest.split(' ').next())
                == Some("${CONFIG_FILE}"),
            "`{line}` names its own config"
        );
    }
}
