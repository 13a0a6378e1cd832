//! Faults of the transport and the port task, end to end (found by the review of both,
//! docs/reliability.md "Defects found by review"): `rtu2mqtt sim` on a pty, a real mosquitto,
//! `rtu2mqtt run`, or a TCP gateway that misbehaves.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::process::Stdio;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use daemon_support::DaemonProcess;
use mqtt_support::{retained, wait_for, Mosquitto, Recorder, TIMEOUT};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::{json, Value};
use sim_support::SimProcess;

static CALLS: AtomicU32 = AtomicU32::new(0);

async fn rpc(port: u16, service: &str, method: &str, params: Value) -> Value {
    let client_id = format!(
        "transport-faults-{}-{}",
        std::process::id(),
        CALLS.fetch_add(1, Ordering::Relaxed)
    );
    let request_topic = format!("/rpc/v1/wb-mqtt-serial/{service}/{method}/{client_id}");
    let reply_topic = format!("{request_topic}/reply");
    let payload = json!({"id": 1, "params": params}).to_string();
    let (client, mut eventloop) =
        AsyncClient::new(MqttOptions::new(&client_id, "127.0.0.1", port), 16);
    let exchange = async {
        loop {
            match eventloop.poll().await.expect("RPC client") {
                Event::Incoming(Packet::ConnAck(_)) => {
                    client
                        .subscribe(reply_topic.as_str(), QoS::AtLeastOnce)
                        .await
                        .unwrap();
                }
                Event::Incoming(Packet::SubAck(_)) => {
                    client
                        .publish(
                            request_topic.as_str(),
                            QoS::AtLeastOnce,
                            false,
                            payload.as_str(),
                        )
                        .await
                        .unwrap();
                }
                Event::Incoming(Packet::Publish(reply)) if reply.topic == reply_topic => {
                    return String::from_utf8(reply.payload.to_vec()).unwrap();
                }
                _ => {}
            }
        }
    };
    let reply = tokio::time::timeout(TIMEOUT, exchange)
        .await
        .expect("an RPC reply");
    let _ = client.disconnect().await;
    serde_json::from_str(&reply).unwrap()
}

/// A device with two input registers read apart (`max_read_registers` 1): input 0 holds 111,
/// input 10 holds 222. It answers every request 300 ms late; the daemon's response timeout for it
/// is 1000 ms, so its own reads all succeed. A `port/Load` read of input 10 with a 50 ms
/// response timeout fails; its late reply (222) comes while the scheduler's next read of the same
/// device (input 0, same function, same length) waits for its answer, and is taken as it: the
/// control of input 0 was published as 222: the scheduler held a device off after its *own*
/// failed transactions (defect A) only. A failed queued (RPC, identity) transaction now holds
/// the device off too (`PortScheduler::queued_done`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_reply_to_an_rpc_read_is_never_published_as_a_polled_value() {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let template = json!({
        "device_type": "review-two",
        "device": {
            "name": "Review two", "id": "review", "max_read_registers": 1,
            "channels": [
                {"name": "Zero", "reg_type": "input", "address": 0, "type": "value"},
                {"name": "Ten", "reg_type": "input", "address": 10, "type": "value"}
            ]
        }
    });
    let templates = dir.path().join("templates");
    std::fs::create_dir_all(&templates).unwrap();
    std::fs::write(templates.join("review-two.json"), template.to_string()).unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "two", "template": "templates/review-two.json", "address": 40,
            "serial": "0xFE000040", "line": "115200 8N2", "fast": false,
            "values": {"input:0": 111, "input:10": 222}}]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &templates, &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-transport-faults"},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2, "devices": [
            {"device_type": "review-two", "slave_id": 40, "response_timeout_ms": 1000}
        ]}]
    });
    let daemon = DaemonProcess::start(
        &config,
        &["--templates", templates.to_str().unwrap()],
        Stdio::null(),
        Stdio::null(),
    );
    let recorder = Recorder::start(broker.port, "/devices/+/controls/+").await;
    wait_for("input 0 published", || async {
        let state = retained(broker.port).await?;
        state
            .iter()
            .any(|(t, v)| t.ends_with("/controls/Zero") && v == "111")
            .then_some(())
    })
    .await;
    wait_for("the advertised port/Load method", || async {
        let state = retained(broker.port).await?;
        (state.get("/rpc/v1/wb-mqtt-serial/port/Load")? == "1").then_some(())
    })
    .await;
    sim.control(json!({"cmd": "faults", "device": 40, "delay": 1.0, "delay_ms": 300}));
    tokio::time::sleep(Duration::from_secs(1)).await;
    let path = sim.pty.to_str().unwrap().to_owned();
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut calls = 0;
    while Instant::now() < deadline && calls < 10 {
        calls += 1;
        let answer = rpc(
            broker.port,
            "port",
            "Load",
            json!({"path": path, "protocol": "modbus",
            "slave_id": 40, "function": 4, "address": 10, "count": 1, "format": "HEX",
            "response_timeout": 50, "total_timeout": 5000}),
        )
        .await;
        eprintln!("port/Load: {answer}");
        tokio::time::sleep(Duration::from_millis(800)).await;
        let wrong: Vec<String> = recorder
            .messages
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, v, _)| t.ends_with("/controls/Zero") && v != "111")
            .map(|(t, v, _)| format!("{t} = {v}"))
            .collect();
        assert!(
            wrong.is_empty(),
            "input 0 (always 111) published with another value after {calls} RPC reads: \
             {wrong:?}\n{}",
            daemon
                .log()
                .lines()
                .rev()
                .take(30)
                .collect::<Vec<_>>()
                .join("\n")
        );
    }
}

/// An RTU-over-TCP gateway that stops answering but never closes the connection (powered off
/// behind a NAT, a Wi-Fi bridge gone: no FIN, no RST). wb-mqtt-serial reconnects once no
/// exchange succeeded for `connection_timeout_ms` (default 5000) over `connection_max_fail_cycles`
/// (default 2) cycles (`TPortOpenCloseLogic::CloseIfNeeded`). Without that rule the dead socket
/// is kept until the kernel gives up retransmitting (about 15 minutes), and the port stays down
/// after the gateway is back.
#[test]
fn a_gateway_that_stops_answering_without_closing_is_reconnected() {
    use std::io::Read;
    use std::net::TcpListener;
    use std::sync::atomic::AtomicUsize;
    use std::sync::Arc;
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let connections = Arc::new(AtomicUsize::new(0));
    let counted = connections.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { return };
            counted.fetch_add(1, Ordering::SeqCst);
            // Reads every request, answers none, never closes.
            std::thread::spawn(move || {
                let mut buffer = [0u8; 256];
                while matches!(stream.read(&mut buffer), Ok(n) if n > 0) {}
            });
        }
    });
    let config = json!({"ports": [{
        "port_type": "tcp", "address": "127.0.0.1", "port": port,
        "connection_timeout_ms": 2000, "connection_max_fail_cycles": 2,
        "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}],
    }]});
    let mut daemon = DaemonProcess::start(&config, &["--stdio"], Stdio::piped(), Stdio::null());
    let deadline = Instant::now() + Duration::from_secs(20);
    while Instant::now() < deadline && connections.load(Ordering::SeqCst) < 2 {
        std::thread::sleep(Duration::from_millis(100));
    }
    let seen = connections.load(Ordering::SeqCst);
    let log = daemon.log();
    daemon.terminate();
    assert!(
        seen >= 2,
        "{seen} connection(s) in 20 s with connection_timeout_ms 2000: the dead connection is \
         kept\n{}",
        log.lines().rev().take(20).collect::<Vec<_>>().join("\n")
    );
}
