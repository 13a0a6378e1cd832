//! The daemon under a stand-in for systemd: `NOTIFY_SOCKET` is a datagram socket of this test,
//! `WATCHDOG_USEC` asks for watchdog pings. READY comes once the port is open and the broker has
//! answered, the STATUS line says so, WATCHDOG pings keep coming while the port task works, and
//! SIGTERM brings STOPPING and a clean exit.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::os::unix::net::UnixDatagram;
use std::process::Stdio;
use std::time::Duration;

use daemon_support::{repo, DaemonProcess};
use mqtt_support::Mosquitto;
use serde_json::json;
use sim_support::SimProcess;

const BUS: &str = r#"{"devices": [
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "115200 8N2"}
]}"#;

/// The next notification, or a failure naming what was expected.
fn next(socket: &UnixDatagram, expecting: &str, seen: &[String]) -> String {
    let mut buf = [0u8; 4096];
    match socket.recv(&mut buf) {
        Ok(n) => String::from_utf8_lossy(&buf[..n]).into_owned(),
        Err(err) => panic!("no notification ({err}) while expecting {expecting}; got {seen:?}"),
    }
}

#[test]
fn ready_status_watchdog_and_stopping() {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(&bus, BUS).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let socket_path = dir.path().join("notify.sock");
    let socket = UnixDatagram::bind(&socket_path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();

    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-notify"},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let socket_env = socket_path.display().to_string();
    let mut daemon = DaemonProcess::start_with_env(
        &config,
        &[],
        Stdio::null(),
        Stdio::null(),
        // A 2 s watchdog: pings at least every second.
        &[("NOTIFY_SOCKET", &socket_env), ("WATCHDOG_USEC", "2000000")],
    );

    let mut seen = Vec::new();
    while !seen
        .iter()
        .any(|m: &String| m.lines().any(|l| l == "READY=1"))
    {
        let message = next(&socket, "READY=1", &seen);
        seen.push(message);
    }
    // READY comes with (or after) a status naming the open port and the connected broker.
    let mut status = seen
        .iter()
        .flat_map(|m| m.lines())
        .filter_map(|l| l.strip_prefix("STATUS="))
        .next_back()
        .map(str::to_owned);
    let mut pings = 0;
    while pings < 3
        || !status
            .as_deref()
            .is_some_and(|s| s.contains("1/1 devices online"))
    {
        let message = next(
            &socket,
            "WATCHDOG=1 pings and a status with the device online",
            &seen,
        );
        for line in message.lines() {
            if line == "WATCHDOG=1" {
                pings += 1;
            }
            if let Some(text) = line.strip_prefix("STATUS=") {
                status = Some(text.to_owned());
            }
        }
        seen.push(message);
    }
    let status = status.unwrap();
    assert!(status.contains("1/1 ports open"), "{status}");
    assert!(status.contains("MQTT connected"), "{status}");

    let pid = nix::unistd::Pid::from_raw(daemon.child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    loop {
        let message = next(&socket, "STOPPING=1", &seen);
        if message.lines().any(|l| l == "STOPPING=1") {
            break;
        }
        seen.push(message);
    }
    let exit = daemon.child.wait().unwrap();
    assert!(exit.success(), "exit status {exit}");
}

#[test]
fn a_port_that_cannot_open_does_not_hold_back_ready() {
    // A missing USB adapter must not keep systemd waiting (and time the start out): the port has
    // had its chance, READY comes, and the status line names the closed port.
    let dir = tempfile::tempdir().unwrap();
    let socket_path = dir.path().join("notify.sock");
    let socket = UnixDatagram::bind(&socket_path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let config = json!({
        "ports": [{"path": dir.path().join("no-such-tty"), "baud_rate": 9600,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let socket_env = socket_path.display().to_string();
    let mut daemon = DaemonProcess::start_with_env(
        &config,
        &["--stdio"],
        Stdio::null(),
        Stdio::null(),
        &[("NOTIFY_SOCKET", &socket_env)],
    );
    let mut seen = Vec::new();
    loop {
        let message = next(&socket, "READY=1 with the port closed", &seen);
        let ready = message.lines().any(|l| l == "READY=1");
        seen.push(message);
        if ready {
            break;
        }
    }
    let status: Vec<&str> = seen
        .iter()
        .flat_map(|m| m.lines())
        .filter_map(|l| l.strip_prefix("STATUS="))
        .collect();
    assert!(
        status
            .iter()
            .any(|s| s.contains("0/1 ports open") && s.contains("closed:")),
        "{status:?}"
    );
    assert!(daemon.terminate().success());
}
