//! What the daemon's log tells an integrator about the broker, read as journald stores it
//! (stderr not a terminal).

use rtu2mqtt::child::StopWithParent;
use std::process::{Command, Stdio};

use crate::daemon_support::{repo, DaemonProcess};
use crate::mqtt_support::{wait_for, Mosquitto};
use serde_json::json;

/// Issue 15 defect 9: wrong credentials are logged as refused credentials (the broker is
/// reachable: "cannot reach the broker" sent integrators to check the network), and a log that
/// is not a terminal carries no ANSI colour codes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_credentials_are_named_and_logs_have_no_colour_codes() {
    let broker = Mosquitto::start_with_password("gateway", "right");
    let dir = tempfile::tempdir().unwrap();
    let config_path = dir.path().join("config.json");
    let log_path = dir.path().join("daemon.log");
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "user": "gateway", "password": "wrong"},
        "ports": [{"path": dir.path().join("no-such-tty"), "baud_rate": 9600, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    std::fs::write(&config_path, config.to_string()).unwrap();
    let mut daemon = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .stop_with_parent()
        .arg("run")
        .arg("--templates")
        .arg(repo("templates"))
        .arg("-c")
        .arg(&config_path)
        .env_remove("NO_COLOR")
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log_path).unwrap())
        .spawn()
        .unwrap();
    let log = wait_for("the refusal in the log", || async {
        let log = std::fs::read_to_string(&log_path).unwrap_or_default();
        // The main client's line and the RPC server's.
        (log.matches("refused the user name or password").count() >= 2).then_some(log)
    })
    .await;
    let _ = daemon.kill();
    let _ = daemon.wait();
    assert!(log.contains("check mqtt.user"), "{log}");
    assert!(!log.contains("cannot reach the MQTT broker"), "{log}");
    // Said in words by the RPC server too, not as rumqttc's debug output.
    assert!(log.contains("MQTT RPC: the MQTT broker refused"), "{log}");
    assert!(!log.contains("NotAuthorized"), "{log}");
    assert!(
        !log.contains('\u{1b}'),
        "ANSI escape codes in a non-terminal log:\n{log:?}"
    );
}

/// Two gateways with one `mqtt.client_id` (a `rtu2mqtt run` by hand beside the service): the
/// broker closes the older connection whenever the other connects. Each used to reconnect at
/// once after every connection (the delay started over at each connect), republishing
/// everything twice a second, and the log said only "lost the MQTT broker". The delay now
/// grows while connections do not hold, and the log names the likely cause.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_gateways_with_one_client_id_are_told_and_back_off() {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-clash"},
        "ports": [{"path": dir.path().join("no-such-tty"), "baud_rate": 9600, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let start = || DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());
    let daemons = [start(), start()];
    let log = wait_for("the hint about the client id", || async {
        daemons
            .iter()
            .map(DaemonProcess::log)
            .find(|log| log.contains("same mqtt.client_id"))
    })
    .await;
    drop(daemons);
    // The delays before the reconnects grew: not every one was the first delay.
    let delays: Vec<&str> = log
        .lines()
        .filter(|line| line.contains("lost the MQTT broker"))
        .filter_map(|line| line.split("retry_in=").nth(1))
        .collect();
    assert!(delays.len() >= 3, "{log}");
    assert!(
        delays.iter().any(|d| d.starts_with("1s")),
        "{delays:?}\n{log}"
    );
}
