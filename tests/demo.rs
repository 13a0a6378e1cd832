//! `rtu2mqtt demo` as a user runs it: the simulator, the daemon, and (here) no broker. Values
//! come, the built-in scenario's input clicks arrive by Fast Modbus events, and Ctrl-C stops
//! everything and removes the demo's directory.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use serde_json::Value;

#[test]
fn demo_without_a_broker_shows_events_and_stops_cleanly() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .args(["demo", "--no-broker"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let pid = child.id();
    let stdout = child.stdout.take().unwrap();
    let (lines_tx, lines) = mpsc::channel::<Value>();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Ok(value) = serde_json::from_str(&line) {
                let _ = lines_tx.send(value);
            }
        }
    });
    let mut seen = Vec::new();
    let clicked = loop {
        match lines.recv_timeout(Duration::from_secs(20)) {
            Ok(line) => {
                seen.push(line.clone());
                // The scenario toggles the relay's input 1 every 3 s.
                if line["device"] == "relay6_20"
                    && line["control"] == "Input 1"
                    && line["event"] == true
                {
                    break line;
                }
            }
            Err(_) => {
                let _ = child.kill();
                panic!("no event from the demo's scenario; got: {seen:?}");
            }
        }
    };
    assert!(clicked["value"] == "0" || clicked["value"] == "1");
    assert!(seen
        .iter()
        .any(|l| l["device"] == "climate_21" && l["control"] == "Temperature"));
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(pid as i32),
        nix::sys::signal::Signal::SIGINT,
    )
    .unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "demo exit status {status}");
    let dir = std::env::temp_dir().join(format!("rtu2mqtt-demo-{pid}"));
    assert!(!dir.exists(), "{} is left behind", dir.display());
}
