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
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use daemon_support::DaemonProcess;
use mqtt_support::{publish, retained, rpc, wait_for, Mosquitto, Recorder};
use serde_json::{json, Value};
use sim_support::SimProcess;

/// Device 40 in the simulator with input 0 = 111 and input 10 = 222, behind a daemon whose
/// response timeout for it is `timeout_ms` and that polls input 0 (`Zero`), and input 10
/// (`Ten`) with `poll_input_10`. Returns the broker, simulator, daemon and a recorder of the
/// controls, once `Zero` is published.
async fn late_device(
    timeout_ms: u64,
    poll_input_10: bool,
) -> (
    Mosquitto,
    SimProcess,
    DaemonProcess,
    Recorder,
    tempfile::TempDir,
) {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let zero = json!({"name": "Zero", "reg_type": "input", "address": 0, "type": "value"});
    let ten = json!({"name": "Ten", "reg_type": "input", "address": 10, "type": "value"});
    let template = |channels: Value| {
        json!({
            "device_type": "late-two",
            "device": {"name": "Late two", "id": "late", "max_read_registers": 1,
                       "channels": channels}
        })
        .to_string()
    };
    // The simulated device has both registers; the daemon polls what it is told to.
    let templates = dir.path().join("templates");
    std::fs::create_dir_all(&templates).unwrap();
    std::fs::write(
        templates.join("late-two.json"),
        template(json!([zero, ten])),
    )
    .unwrap();
    let daemon_templates = dir.path().join("daemon-templates");
    std::fs::create_dir_all(&daemon_templates).unwrap();
    let polled = if poll_input_10 {
        json!([zero, ten])
    } else {
        json!([zero])
    };
    std::fs::write(daemon_templates.join("late-two.json"), template(polled)).unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "two", "template": "templates/late-two.json", "address": 40,
            "serial": "0xFE000040", "line": "115200 8N2", "fast": false,
            "values": {"input:0": 111, "input:10": 222}}]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &templates, &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-transport-faults"},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2, "devices": [
            {"device_type": "late-two", "slave_id": 40, "response_timeout_ms": timeout_ms}
        ]}]
    });
    let daemon = DaemonProcess::start(
        &config,
        &["--templates", daemon_templates.to_str().unwrap()],
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
    (broker, sim, daemon, recorder, dir)
}

/// `port/Load` of input 10 (222) of device 40 on the simulator's port.
fn load_input_10(sim: &SimProcess, response_timeout_ms: u64) -> Value {
    json!({"path": sim.pty.to_str().unwrap(), "protocol": "modbus",
        "slave_id": 40, "function": 4, "address": 10, "count": 1, "format": "HEX",
        "response_timeout": response_timeout_ms, "total_timeout": 10_000})
}

/// Four rounds of: the `port/Load` `params` (its answer checked by `answered`), then a new
/// value of input 0 (112, 113, …), waited for on the broker; after each, no value input 0 never
/// held may have been published (`what` names the requests in the message).
async fn rounds_publish_only_held_values(
    broker: &Mosquitto,
    sim: &SimProcess,
    daemon: &DaemonProcess,
    recorder: &Recorder,
    params: Value,
    answered: fn(&Value) -> bool,
    what: &str,
) {
    for round in 1..=4u32 {
        let answer = rpc(broker.port, "port", "Load", params.clone()).await;
        assert!(answered(&answer), "round {round}: {answer}");
        let expected = (111 + round).to_string();
        sim.control(
            json!({"cmd": "set", "device": 40, "type": "input", "address": 0,
            "value": 111 + round}),
        );
        wait_for("input 0's new value published", || async {
            let state = retained(broker.port).await?;
            state
                .iter()
                .any(|(t, v)| t.ends_with("/controls/Zero") && *v == expected)
                .then_some(())
        })
        .await;
        let wrong: Vec<String> = recorder
            .messages
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, v, _)| {
                t.ends_with("/controls/Zero")
                    && v.parse::<u32>()
                        .map_or(true, |v| !(111..=111 + round).contains(&v))
            })
            .map(|(t, v, _)| format!("{t} = {v}"))
            .collect();
        assert!(
            wrong.is_empty(),
            "input 0 published with a value it never held after {round} {what}: {wrong:?}\n{}",
            daemon.log_tail(30)
        );
    }
}

/// The device answers every request 300 ms late; the daemon's response timeout for it is
/// 1000 ms, so its own reads (input 0 = 111, then 112, 113 …) all succeed. A `port/Load` read
/// of input 10 with a 50 ms response timeout fails; its late reply (222) came while the
/// scheduler's next read of the same device (same function, same length) waited for its answer,
/// and was taken as it: input 0 was published as 222 (the scheduler held a device off after its
/// *own* failed transactions only, defect A). A failed queued (RPC, identity) transaction now
/// holds the device off too (`PortScheduler::queued_done`). Each round changes input 0 and waits
/// for the new value, so a read of input 0 after the RPC has been published before the check.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_reply_to_an_rpc_read_is_never_published_as_a_polled_value() {
    let (broker, sim, daemon, recorder, _dir) = late_device(1000, true).await;
    sim.control(json!({"cmd": "faults", "device": 40, "delay": 1.0, "delay_ms": 300}));
    rounds_publish_only_held_values(
        &broker,
        &sim,
        &daemon,
        &recorder,
        load_input_10(&sim, 50),
        |answer| answer["error"].is_object(),
        "RPC reads",
    )
    .await;
}

/// Review of the port task (27 Nov 2026), finding 2: defect A's rule for raw transfers. A raw
/// `port/Load` (no `protocol`: bytes out as given, wb-mqtt-serial's scripts' usual way to read
/// a register) carries a Modbus read of input 10 (222) of device 40, which the daemon polls
/// (input 0, 111, with a 1000 ms response timeout). The device answers 300 ms late; the raw
/// transfer waits 50 ms (+ 50 ms allowance) and returns nothing. The port task served raw jobs
/// without any hold-off (its `Raw` arm returned before `PortScheduler::queued_done`), so the
/// scheduler's next read of input 0 (same address, function and length) went at once and took
/// the raw request's late reply (222) as its own: `Zero` was published as 222, a value input 0
/// never held. Now a raw transfer that is a Modbus request holds its device off unless the whole
/// reply came (`PortScheduler::raw_done`), and waits for its device's hold-off.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_reply_to_a_raw_rpc_transfer_is_never_published_as_a_polled_value() {
    let (broker, sim, daemon, recorder, _dir) = late_device(1000, false).await;
    sim.control(json!({"cmd": "faults", "device": 40, "delay": 1.0, "delay_ms": 300}));
    // Read input registers from 10, one: 28 04 000a 0001, CRC 1631.
    let raw = json!({"path": sim.pty.to_str().unwrap(), "msg": "2804000a00011631",
        "format": "HEX", "response_size": 7, "response_timeout": 50, "total_timeout": 10_000});
    rounds_publish_only_held_values(
        &broker,
        &sim,
        &daemon,
        &recorder,
        raw,
        // The reply in time, or none (wb-mqtt-serial's "request timed out").
        |answer| {
            answer["result"].is_object()
                || answer["error"]["message"] == "Port IO error: request timed out"
        },
        "raw RPC transfers",
    )
    .await;
}

/// The other way round: the device polls only input 0 (111) and answers half its requests
/// 300 ms late, past the daemon's 100 ms response timeout. A `port/Load` of input 10 (222) with
/// a 1000 ms timeout that went right after one of the scheduler's reads failed took that read's
/// late reply (input 0: 111, same function, same length) as its own answer. A queued
/// transaction now waits for the device's hold-off after a failure
/// (`PortScheduler::queued_may_go_from`): every answer is 222.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_reply_to_a_polled_read_is_never_an_rpc_reads_answer() {
    let (broker, sim, daemon, _recorder, _dir) = late_device(100, false).await;
    sim.control(json!({"cmd": "faults", "device": 40, "delay": 0.5, "delay_ms": 300}));
    // A failure comes about every other read and holds the device off a second; an RPC at a
    // random moment lands in the 200 ms before such a late reply about one time in six (without the
    // wait, the first round mostly failed).
    for round in 1..=12 {
        let answer = rpc(broker.port, "port", "Load", load_input_10(&sim, 1000)).await;
        if answer["error"].is_object() {
            continue;
        }
        assert_eq!(
            answer["result"]["response"],
            "00de",
            "round {round}: input 10 read as {answer}\n{}",
            daemon.log_tail(30)
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
    let log = daemon.log_tail(20);
    daemon.terminate();
    assert!(
        seen >= 2,
        "{seen} connection(s) in 20 s with connection_timeout_ms 2000: the dead connection is \
         kept\n{}",
        log
    );
}

/// A simulator with one classic meter (template `meter`, id `meter`: `Energy`, a `u32` at input
/// 0 holding 0x0001_0002) at address 41 on `line`, pausing `reply_pause_us` in the middle of
/// each reply; `device` adds keys to the template's device (a response timeout). Returns the
/// simulator and the template directory, for the daemon too.
fn one_meter(
    dir: &std::path::Path,
    line: &str,
    reply_pause_us: u64,
    device: Value,
) -> (SimProcess, std::path::PathBuf) {
    let templates = dir.join("templates");
    std::fs::create_dir_all(&templates).unwrap();
    let mut template = json!({"device_type": "meter", "device": {"name": "Meter", "id": "meter",
        "channels": [{"name": "Energy", "reg_type": "input", "address": 0,
                      "type": "value", "format": "u32"}]}});
    for (key, value) in device.as_object().into_iter().flatten() {
        template["device"][key] = value.clone();
    }
    std::fs::write(templates.join("meter.json"), template.to_string()).unwrap();
    let bus = dir.join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "meter", "template": "templates/meter.json", "address": 41,
            "serial": "0xFE000041", "line": line, "fast": false,
            "reply_pause_us": reply_pause_us, "values": {"input:0": [1, 2]}}]})
        .to_string(),
    )
    .unwrap();
    (SimProcess::start_with(&bus, &templates, &[]), templates)
}

/// A slow device (a meter's MCU, a radio modem) that stops 40 ms in the middle of every reply,
/// on its factory line, 9600 8N2. wb-mqtt-serial reads a frame with the device's frame timeout
/// between bytes (`ReadFrame`), so a config with `frame_timeout_ms: 60` serves it; rtu2mqtt
/// gave every such reply up after its own 20 ms (the site tools still do: `rtu2mqtt read` of
/// this device says "unreadable reply"), so the device never published a value.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_that_pauses_mid_reply_is_read_with_its_frame_timeout() {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let (sim, templates) = one_meter(
        dir.path(),
        "9600 8N2",
        40_000,
        json!({"response_timeout_ms": 100}),
    );
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-slow-meter"},
        "ports": [{"path": sim.pty, "baud_rate": 9600, "stop_bits": 2, "devices": [
            {"device_type": "meter", "slave_id": 41, "frame_timeout_ms": 60}
        ]}]
    });
    let daemon = DaemonProcess::start(
        &config,
        &["--templates", templates.to_str().unwrap()],
        Stdio::null(),
        Stdio::null(),
    );
    wait_for("the paused device's value", || async {
        let state = retained(broker.port).await?;
        (state.get("/devices/meter_41/controls/Energy")? == "65538").then_some(())
    })
    .await;
    sim.control(json!({"cmd": "set", "device": 41, "type": "input", "address": 1, "value": 3}));
    wait_for("its next value", || async {
        let state = retained(broker.port).await?;
        (state.get("/devices/meter_41/controls/Energy")? == "65539").then_some(())
    })
    .await;
    let state = retained(broker.port).await.unwrap();
    assert_eq!(
        state
            .get("/devices/meter_41/controls/Energy/meta/error")
            .map_or("", String::as_str),
        "",
        "{}",
        daemon.log_tail(30)
    );
}

/// A second gateway on the same broker while the first holds the port: an integrator trying
/// `rtu2mqtt run` by hand while the service (or wb-mqtt-serial) runs. The second cannot open
/// the port ("another program holds it"); it used to mark the first's devices `r` once their
/// timeout passed, and on its exit (`clear_on_exit`) delete every retained topic of theirs,
/// values and meta, while the first went on serving them. A port that was never this
/// gateway's leaves its devices' Wiren Board topics alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_gateway_that_cannot_open_the_port_leaves_the_first_ones_topics_alone() {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    // A writable limit besides the energy: a write sent now is the first gateway's to carry out.
    let channels = json!({"channels": [
        {"name": "Energy", "reg_type": "input", "address": 0, "type": "value", "format": "u32"},
        {"name": "Limit", "reg_type": "holding", "address": 5, "type": "value"}]});
    let (sim, templates) = one_meter(dir.path(), "115200 8N2", 0, channels);
    let config = |client_id: &str| {
        json!({
            "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": client_id},
            "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2, "devices": [
                {"device_type": "meter", "slave_id": 41, "device_timeout_ms": 100}
            ]}]
        })
    };
    let templates_arg = ["--templates", templates.to_str().unwrap()];
    let first = DaemonProcess::start(
        &config("rtu2mqtt-first"),
        &templates_arg,
        Stdio::null(),
        Stdio::null(),
    );
    wait_for("the first gateway's value", || async {
        let state = retained(broker.port).await?;
        (state.get("/devices/meter_41/controls/Energy")? == "65538").then_some(())
    })
    .await;
    let recorder = Recorder::start(broker.port, "/devices/meter_41/#").await;
    // At debug level: the journal says "another program holds it" once, the tries after it
    // only at debug level.
    let mut second = DaemonProcess::start_with_env(
        &config("rtu2mqtt-second"),
        &templates_arg,
        Stdio::null(),
        Stdio::null(),
        &[("RUST_LOG", "rtu2mqtt=debug")],
    );
    // Three refusals: the port was tried over 1.5 s, fifteen times the device timeout.
    wait_for(
        "the second gateway finding the port held three times",
        || async {
            let log = second.log();
            (log.matches("another program holds it").count() == 1
                && log.matches("cannot open the port (still)").count() >= 2)
                .then_some(())
        },
    )
    .await;
    // A write while the second gateway waits for the port: the first carries it out; the
    // second drops it rather than sending it again, late, should the port become its own.
    // (Sent until the second has heard one: its subscription is not observable otherwise.)
    wait_for("the second gateway dropping a write it heard", || async {
        publish(
            broker.port,
            "/devices/meter_41/controls/Limit/on",
            "7",
            false,
        )
        .await;
        second
            .log()
            .contains("writes dropped: another program holds the port")
            .then_some(())
    })
    .await;
    wait_for("the first gateway's write of the limit", || async {
        let limit =
            sim.control(json!({"cmd": "get", "device": 41, "type": "holding", "address": 5}));
        (limit["value"] == 7).then_some(())
    })
    .await;
    assert!(second.terminate().success());
    wait_for(
        "the first gateway's value after the second left",
        || async {
            let state = retained(broker.port).await?;
            (state.get("/devices/meter_41/controls/Energy")? == "65538"
                && state.contains_key("/devices/meter_41/meta/name"))
            .then_some(())
        },
    )
    .await;
    // Everything the second gateway sent reached the broker before it exited: a marker sent
    // now comes to the recorder after all of it.
    publish(broker.port, "/devices/meter_41/test-marker", "x", false).await;
    wait_for(
        "the recorder to have everything before the marker",
        || async { (recorder.count("test-marker") > 0).then_some(()) },
    )
    .await;
    let harmful: Vec<String> = recorder
        .messages
        .lock()
        .unwrap()
        .iter()
        .filter(|(topic, payload, _)| {
            payload.contains('r') && topic.ends_with("/meta/error")
                || payload.is_empty() && !topic.ends_with("/meta/error")
        })
        .map(|(topic, payload, _)| format!("{topic} = {payload:?}"))
        .collect();
    assert!(
        harmful.is_empty(),
        "the second gateway flagged or deleted the first's topics: {harmful:?}\n{}",
        second.log_tail(20)
    );
    drop(first);
}
