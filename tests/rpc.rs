//! wb-mqtt-serial's MQTT RPC served by the running daemon, end to end: `rtu2mqtt sim` on a pty,
//! `rtu2mqtt run`, a real mosquitto, and requests published as Wiren Board's tools publish
//! them. Also the CLI's `read --via-mqtt` and its automatic use when the port is busy. At 115200
//! and at 9600.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use rtu2mqtt::child::StopWithParent;
use std::process::{Command, Stdio};

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{retained, rpc, rpc_raw, wait_for, Mosquitto};
use serde_json::{json, Value};
use sim_support::SimProcess;

struct Bench {
    /// The line of the bus, e.g. "115200 8N2".
    line: String,
    broker: Mosquitto,
    sim: SimProcess,
    daemon: DaemonProcess,
    _dir: tempfile::TempDir,
}

fn start(line: &str, baud: u32) -> Bench {
    start_with_generic(line, baud, false)
}

/// With `generic`, also a classic Modbus device (no Fast Modbus) with a bit-field channel at
/// address 22.
fn start_with_generic(line: &str, baud: u32, generic: bool) -> Bench {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let mut sim_devices = vec![
        json!({"name": "relay", "template": "rtu2mqtt-relay6", "address": 20,
               "serial": "0xFE000020", "line": line, "model": "R2M-RELAY6", "firmware": "1.26.0"}),
        json!({"name": "climate", "template": "rtu2mqtt-climate", "address": 21,
               "serial": "0xFE000021", "line": line, "values": {"input:4": 2150}}),
    ];
    let mut config_devices = vec![
        json!({"device_type": "rtu2mqtt-relay6", "slave_id": 20, "in0_mode": 3}),
        json!({"device_type": "rtu2mqtt-climate", "slave_id": 21}),
    ];
    let templates = dir.path().join("templates");
    if generic {
        // Holding 6 = 0b1010_0101: "Holding Bit 3" (6:3:1) is 0, the other bits are mixed.
        sim_devices.push(json!({"name": "generic", "template": "rtu2mqtt-generic",
            "address": 22, "serial": "0xFE000022", "line": line, "fast": false,
            "values": {"holding:6": 0xA5}}));
        // The daemon's template for it: parameters on the simulated registers, one on a
        // register the device does not have (holding 7), two with conditions.
        let template = json!({
            "device_type": "rtu2mqtt-generic-parameters",
            "device": {
                "name": "Generic", "id": "generic", "max_read_registers": 10,
                "parameters": {
                    "scaled": {"title": "Scaled", "address": 1, "format": "s16", "scale": 0.5},
                    "high_bits": {"title": "Bits 8-15", "address": "6:8:8"},
                    "ghost": {"title": "Not on the device", "address": 7},
                    "if_ghost": {"title": "When ghost is 1", "address": 0,
                                 "condition": "ghost==1"},
                    "if_negative": {"title": "When scaled < 0", "address": 2,
                                    "condition": "scaled<0"}
                },
                "channels": [{"name": "Holding Bit 3", "reg_type": "holding",
                              "address": "6:3:1", "type": "switch"}]
            }
        });
        std::fs::create_dir_all(&templates).unwrap();
        std::fs::write(
            templates.join("rtu2mqtt-generic-parameters.json"),
            template.to_string(),
        )
        .unwrap();
        config_devices.push(json!({"device_type": "rtu2mqtt-generic-parameters", "slave_id": 22}));
    }
    std::fs::write(&bus, json!({ "devices": sim_devices }).to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-rpc-test"},
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": config_devices}]
    });
    let templates = templates.to_str().unwrap();
    let extra: &[&str] = if generic {
        &["--templates", templates]
    } else {
        &[]
    };
    let daemon = DaemonProcess::start(&config, extra, Stdio::null(), Stdio::null());
    Bench {
        line: line.to_owned(),
        broker,
        sim,
        daemon,
        _dir: dir,
    }
}

async fn wait_until_served(port: u16) {
    wait_for("the advertised port/Load method", || async {
        let state = retained(port).await?;
        (state.get("/rpc/v1/wb-mqtt-serial/port/Load")? == "1").then_some(())
    })
    .await;
}

/// `rtu2mqtt read …` against the running daemon; (exit code, stdout, stderr).
async fn cli_read(bench: &Bench, extra: &[&str]) -> (i32, String, String) {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
    command.stop_with_parent();
    command
        .args(["read", "--port"])
        .arg(&bench.sim.pty)
        .args(["--address", "21", "--type", "input", "--reg", "4", "--json"])
        .args(["--broker", &format!("127.0.0.1:{}", bench.broker.port)])
        .args(extra);
    let output = tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap();
    (
        output.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

async fn reads_scans_and_errors(bench: &Bench, baud: u32) {
    let port = bench.broker.port;
    let path = bench.sim.pty.to_str().unwrap().to_owned();
    wait_until_served(port).await;

    // ports/Load: the configured port with its settings.
    let ports = rpc(port, "ports", "Load", json!({})).await;
    assert_eq!(
        ports["result"],
        json!([{"path": path, "baud_rate": baud, "data_bits": 8, "parity": "N", "stop_bits": 2}])
    );

    // port/Load: a Modbus read of input 4 of the climate sensor (2150 = 0x0866), byte for byte
    // the reply wb-mqtt-serial gives.
    let params = json!({"path": path, "protocol": "modbus", "slave_id": 21, "function": 4,
                        "address": 4, "count": 1, "format": "HEX", "msg": ""});
    let reply = rpc_raw(
        port,
        "port",
        "Load",
        &json!({"id": 7, "params": params}).to_string(),
    )
    .await;
    assert_eq!(
        reply,
        r#"{"id":7,"result":{"response":"0866"},"error":null}"#
    );

    // port/Load without "protocol": a raw transfer. The same read as a whole RTU frame, and
    // the whole reply back, CRC included; silence is wb-mqtt-serial's "Port IO error: request
    // timed out" (-32000), which modbus-utils-rpc's scanner takes for an empty setting.
    let raw = json!({"path": path, "format": "HEX", "msg": "150400040001731f",
                     "response_size": 7});
    let answer = rpc(port, "port", "Load", raw).await;
    assert_eq!(
        answer["result"],
        json!({"response": "15040208660ed9"}),
        "{answer}"
    );
    let nobody = json!({"path": path, "format": "HEX", "msg": "6303000000018c48",
                        "response_size": 7, "response_timeout": 100});
    let answer = rpc(port, "port", "Load", nobody).await;
    assert_eq!(
        (&answer["error"]["code"], &answer["error"]["message"]),
        (&json!(-32000), &json!("Port IO error: request timed out")),
        "{answer}"
    );

    // A write through port/Load reaches the device.
    let write = json!({"path": path, "protocol": "modbus", "slave_id": 20, "function": 5,
                       "address": 2, "count": 1, "format": "HEX", "msg": "ff00"});
    let written = rpc(port, "port", "Load", write).await;
    assert_eq!(written["result"], json!({"response": ""}), "{written}");
    let k3 = bench
        .sim
        .control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}));
    assert_eq!(k3["value"], 1);

    // A register the device does not have: the Modbus exception, as a result.
    let missing = json!({"path": path, "protocol": "modbus", "slave_id": 21, "function": 3,
                         "address": 9000, "count": 1, "format": "HEX"});
    let refused = rpc(port, "port", "Load", missing).await;
    assert_eq!(refused["result"]["exception"]["code"], 2, "{refused}");

    // port/Scan: both devices, with serial numbers, settings and identity.
    let scan = rpc(port, "port", "Scan", json!({"path": path})).await;
    let devices = scan["result"]["devices"].as_array().expect("devices");
    assert_eq!(devices.len(), 2, "{scan}");
    let relay = devices
        .iter()
        .find(|d| d["sn"] == "4261412896")
        .unwrap_or_else(|| panic!("relay (0xFE000020) in {scan}"));
    assert_eq!(
        relay["cfg"],
        json!({"slave_id": 20, "data_bits": 8, "baud_rate": baud, "parity": "N", "stop_bits": 2})
    );
    assert_eq!(relay["device_signature"], "R2M-RELAY6");
    assert_eq!(relay["fw"]["version"], "1.26.0");
    assert_eq!(relay["configured_device_type"], "rtu2mqtt-relay6");
    assert!(relay.get("errors").is_none(), "{relay}");
    assert!(devices.iter().any(|d| d["sn"] == "4261412897"), "{scan}");

    // device/Probe by address.
    let probe = rpc(
        port,
        "device",
        "Probe",
        json!({"path": path, "slave_id": 21}),
    )
    .await;
    assert_eq!(probe["result"]["sn"], "4261412897", "{probe}");
    assert_eq!(probe["result"]["cfg"]["slave_id"], 21);
    // wb-device-manager scans every port at once: more requests than are served at the same
    // time (8) wait their turn, as wb-mqtt-serial queues them, rather than being refused.
    let probes: Vec<_> = (100..112u8)
        .map(|address| {
            let path = path.to_owned();
            tokio::spawn(async move {
                rpc(
                    port,
                    "device",
                    "Probe",
                    json!({"path": path, "slave_id": address}),
                )
                .await
            })
        })
        .collect();
    for probe in probes {
        let answer = probe.await.unwrap();
        assert_eq!(answer["result"], json!({}), "{answer}");
    }

    // Nobody at address 99: wb-mqtt-serial's E_RPC_REQUEST_TIMEOUT (-32600, which
    // wb-device-manager's bootloader scan relies on) that says so, well before total_timeout.
    let silent = json!({"path": path, "protocol": "modbus", "slave_id": 99, "function": 3,
                        "address": 0, "count": 1, "format": "HEX", "response_timeout": 100});
    let silence = rpc(port, "port", "Load", silent).await;
    assert_eq!(silence["error"]["code"], -32600, "{silence}");
    assert!(
        silence["error"]["message"]
            .as_str()
            .unwrap()
            .contains("no reply from slave 99"),
        "{silence}"
    );

    // The daemon keeps polling between the RPC requests: a new value is published.
    bench
        .sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2210}));
    wait_for("the new temperature on the broker", || async {
        let state = retained(port).await?;
        (state.get("/devices/climate_21/controls/Temperature")? == "22.1").then_some(())
    })
    .await;

    // The CLI through the daemon: with --via-mqtt, and on its own because the port is busy.
    let (code, stdout, stderr) = cli_read(bench, &["--via-mqtt"]).await;
    assert_eq!(code, 0, "stdout {stdout} stderr {stderr}");
    let read: Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(read["registers"], json!([2210]), "{stdout}");
    let (code, stdout, stderr) = cli_read(bench, &[]).await;
    assert_eq!(code, 0, "stdout {stdout} stderr {stderr}");
    assert!(stderr.contains("busy"), "{stderr}");
    assert!(stdout.contains("2210"), "{stdout}");

    // `write` on the busy port: through the service, then read back.
    let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
    command.stop_with_parent();
    command
        .args([
            "write",
            "--port",
            &path,
            "--address",
            "20",
            "--type",
            "coil",
            "--reg",
            "3",
        ])
        .args(["--broker", &format!("127.0.0.1:{port}"), "1"]);
    let output = tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(0), "{stderr}");
    let k4 = bench
        .sim
        .control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 3}));
    assert_eq!(k4["value"], 1, "{stderr}");

    // `scan` on the busy port: through the service, at the settings asked for.
    let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
    command.stop_with_parent();
    command
        .args([
            "scan",
            "--port",
            &path,
            "--json",
            "--parity",
            "N",
            "--stop-bits",
            "2",
        ])
        .args(["--baud", &format!("{baud},19200")])
        .args(["--broker", &format!("127.0.0.1:{port}")]);
    let output = tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(0), "{stdout} {stderr}");
    assert!(
        stderr.contains("through the running rtu2mqtt service"),
        "{stderr}"
    );
    let report: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(report["port_settings_scanned"], 2, "{report}");
    let mut serials: Vec<u64> = report["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["serial"].as_u64().unwrap())
        .collect();
    serials.sort_unstable();
    assert_eq!(serials, [0xFE00_0020, 0xFE00_0021], "{report}");
    let relay = &report["devices"][0];
    assert_eq!(relay["baud_rate"], baud, "{report}");

    // port/Setup: a new address by serial number, and back by address.
    let address_of_climate = || {
        bench.sim.control(
            json!({"cmd": "get", "serial": "0xFE000021", "type": "holding", "address": 128}),
        )["value"]
            .clone()
    };
    let moved = rpc(
        port,
        "port",
        "Setup",
        json!({"path": path, "items": [{"slave_id": 21, "sn": 0xFE00_0021u32, "cfg": {"slave_id": 31}}]}),
    )
    .await;
    assert_eq!(moved, json!({"id": 1, "result": null, "error": null}));
    assert_eq!(address_of_climate(), 31);
    let back = rpc(
        port,
        "port",
        "Setup",
        json!({"path": path, "items": [{"slave_id": 31, "cfg": {"slave_id": 21}}]}),
    )
    .await;
    assert_eq!(back["error"], Value::Null, "{back}");
    assert_eq!(address_of_climate(), 21);
}

/// The retained value of a control once it is no longer `old`.
async fn value_other_than(port: u16, topic: &str, old: &str) -> String {
    wait_for(&format!("{topic} other than {old:?}"), || async {
        let state = retained(port).await?;
        state.get(topic).filter(|v| v.as_str() != old).cloned()
    })
    .await
}

/// `device/SetPoll`: with `poll` false the climate sensor is no longer read (its polled Sound
/// Level stays as it was while the relay's polled Serial follows the simulator twice);
/// with `poll` true it is read again. Then the errors.
async fn set_poll_holds_and_resumes_a_device(bench: &Bench) {
    let port = bench.broker.port;
    let path = bench.sim.pty.to_str().unwrap().to_owned();
    let sound = "/devices/climate_21/controls/Sound Level";
    let serial = "/devices/relay6_20/controls/Serial";
    // The sensor is being polled (port/Setup above moved it away for a while): a change shows.
    let sound_at_start = wait_for("the climate sensor's Sound Level", || async {
        retained(port).await?.get(sound).cloned()
    })
    .await;
    bench
        .sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 3, "value": 555}));
    let sound_before = value_other_than(port, sound, &sound_at_start).await;
    assert_eq!(sound_before, "5.55");
    let held = rpc(
        port,
        "device",
        "SetPoll",
        json!({"device_id": "climate_21", "poll": false}),
    )
    .await;
    assert_eq!(held, json!({"id": 1, "result": {}, "error": null}));
    bench
        .sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 3, "value": 777}));
    let mut serial_now = wait_for("the relay's Serial", || async {
        retained(port).await?.get(serial).cloned()
    })
    .await;
    for low in [1001, 1002] {
        bench.sim.control(
            json!({"cmd": "set", "device": 20, "type": "input", "address": 270, "value": [0, low]}),
        );
        serial_now = value_other_than(port, serial, &serial_now).await;
        assert_eq!(serial_now, low.to_string());
    }
    let state = retained(port).await.unwrap_or_default();
    assert_eq!(
        state.get(sound),
        Some(&sound_before),
        "the held device was read: {state:?}"
    );

    let resumed = rpc(
        port,
        "device",
        "SetPoll",
        json!({"path": path, "slave_id": 21, "poll": true}),
    )
    .await;
    assert_eq!(resumed, json!({"id": 1, "result": {}, "error": null}));
    value_other_than(port, sound, &sound_before).await;

    let unknown = rpc(
        port,
        "device",
        "SetPoll",
        json!({"path": path, "slave_id": 99, "poll": false}),
    )
    .await;
    assert_eq!(unknown["error"]["code"], -32000, "{unknown}");
    assert!(
        unknown["error"]["message"]
            .as_str()
            .unwrap()
            .contains("Port or device not found"),
        "{unknown}"
    );
    let no_poll = rpc(
        port,
        "device",
        "SetPoll",
        json!({"device_id": "climate_21"}),
    )
    .await;
    assert_eq!(no_poll["error"]["code"], -32000, "{no_poll}");
    assert!(
        no_poll["error"]["message"]
            .as_str()
            .unwrap()
            .contains("poll"),
        "{no_poll}"
    );
}

/// `rtu2mqtt set-address` and `fix-addresses` on the port the daemon holds: they go through the
/// service (port/Scan, port/Setup by serial number, port/Scan again), the devices take the
/// addresses, and the daemon's events keep flowing.
async fn set_address_goes_through_the_service(bench: &Bench) {
    let port = bench.broker.port;
    let address_of_climate = || {
        bench.sim.control(
            json!({"cmd": "get", "serial": "0xFE000021", "type": "holding", "address": 128}),
        )["value"]
            .clone()
    };
    let set_address = |address: &str| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
        command.stop_with_parent();
        command
            .args(["set-address", "--port"])
            .arg(&bench.sim.pty)
            .args(["--serial", "0xFE000021", "--address", address])
            .args(["--broker", &format!("127.0.0.1:{port}")]);
        async move {
            let output = tokio::task::spawn_blocking(move || command.output().unwrap())
                .await
                .unwrap();
            (
                output.status.code(),
                String::from_utf8_lossy(&output.stdout).into_owned(),
                String::from_utf8_lossy(&output.stderr).into_owned(),
            )
        }
    };
    let (code, stdout, stderr) = set_address("31").await;
    assert_eq!(code, Some(0), "{stdout} {stderr}");
    assert!(
        stderr.contains("through the running rtu2mqtt service"),
        "{stderr}"
    );
    assert!(stdout.contains("address 21 -> 31"), "{stdout}");
    assert_eq!(address_of_climate(), 31);
    let (code, stdout, stderr) = set_address("21").await;
    assert_eq!(code, Some(0), "{stdout} {stderr}");
    assert_eq!(address_of_climate(), 21);
    // An address another device uses is refused, and nothing is written.
    let (code, _, stderr) = set_address("20").await;
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("already used"), "{stderr}");
    assert_eq!(address_of_climate(), 21);
    // fix-addresses through the service: a duplicate made on purpose is found and resolved.
    let tool = |args: Vec<String>| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
        command.stop_with_parent();
        command
            .args(&args)
            .args(["--broker", &format!("127.0.0.1:{port}")]);
        async move {
            let output = tokio::task::spawn_blocking(move || command.output().unwrap())
                .await
                .unwrap();
            (
                output.status.code(),
                String::from_utf8_lossy(&output.stdout).into_owned(),
                String::from_utf8_lossy(&output.stderr).into_owned(),
            )
        }
    };
    let pty = bench.sim.pty.to_str().unwrap().to_owned();
    let line_args = |line: &str| -> Vec<String> {
        let (baud, rest) = line.split_once(' ').unwrap();
        let parity = &rest[1..2];
        let stop_bits = &rest[2..3];
        ["--baud", baud, "--parity", parity, "--stop-bits", stop_bits]
            .map(str::to_owned)
            .to_vec()
    };
    let set = |serial: &str, address: &str, force: bool| {
        let mut args: Vec<String> = [
            "set-address",
            "--port",
            &pty,
            "--serial",
            serial,
            "--address",
            address,
        ]
        .map(str::to_owned)
        .to_vec();
        if force {
            args.push("--force".into());
        }
        tool(args)
    };
    let (code, stdout, stderr) = set("0xFE000021", "20", true).await;
    assert_eq!(code, Some(0), "{stdout} {stderr}");
    assert_eq!(address_of_climate(), 20);
    let mut fix: Vec<String> = ["fix-addresses", "--port", &pty]
        .map(str::to_owned)
        .to_vec();
    fix.extend(line_args(&bench.line));
    let (code, stdout, stderr) = tool(fix.clone()).await;
    assert_eq!(code, Some(1), "dry run: {stdout} {stderr}");
    assert!(stdout.contains("(planned)"), "{stdout}");
    assert_eq!(address_of_climate(), 20, "a dry run writes nothing");
    fix.push("--apply".into());
    let (code, stdout, stderr) = tool(fix).await;
    assert_eq!(code, Some(0), "{stdout} {stderr}");
    assert!(
        stderr.contains("through the running rtu2mqtt service"),
        "{stderr}"
    );
    assert!(stdout.contains("confirmed by a new scan"), "{stdout}");
    let address_of_relay = || {
        bench.sim.control(
            json!({"cmd": "get", "serial": "0xFE000020", "type": "holding", "address": 128}),
        )["value"]
            .clone()
    };
    assert_ne!(address_of_climate(), address_of_relay());
    // Back as configured.
    for (serial, address) in [("0xFE000020", "20"), ("0xFE000021", "21")] {
        let (code, stdout, stderr) = set(serial, address, true).await;
        assert_eq!(code, Some(0), "{stdout} {stderr}");
    }
    assert_eq!(address_of_climate(), 21);
    assert_eq!(address_of_relay(), 20);
    // The daemon's events still flow: a relay input reaches MQTT.
    let k1 = "/devices/relay6_20/controls/K1";
    let before = wait_for("the relay's K1", || async {
        retained(port).await?.get(k1).cloned()
    })
    .await;
    let flipped = if before == "1" { 0 } else { 1 };
    bench.sim.control(
        json!({"cmd": "set", "device": 20, "type": "coil", "address": 0, "value": flipped}),
    );
    assert_eq!(
        value_other_than(port, k1, &before).await,
        flipped.to_string()
    );
}

/// `device/LoadConfig`, `device/Load`, `device/Set`: exact replies, errors, and the daemon's
/// events flowing before, during and after (`device/SetPoll`: `set_poll_holds_and_resumes_a_device`).
async fn device_methods(bench: &Bench) {
    let port = bench.broker.port;
    let baud: u64 = bench.line.split(' ').next().unwrap().parse().unwrap();
    let path = bench.sim.pty.to_str().unwrap().to_owned();
    wait_until_served(port).await;
    let event_seen = |value: &'static str| {
        wait_for(
            "the relay's Input 1 event on the broker",
            move || async move {
                let state = retained(port).await?;
                (state.get("/devices/relay6_20/controls/Input 1")? == value).then_some(())
            },
        )
    };
    let press = |value: u16| {
        bench.sim.control(
            json!({"cmd": "set", "device": 20, "type": "discrete", "address": 0, "value": value}),
        )
    };
    press(1);
    event_seen("1").await;

    // device/Load: channels by template name, decoded as the daemon publishes them.
    bench
        .sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2150}));
    let load = rpc_raw(
        port,
        "device",
        "Load",
        &json!({"id": 3, "params": {"device_id": "climate_21", "channels": ["Temperature", "Serial"]}})
            .to_string(),
    )
    .await;
    assert_eq!(
        load,
        r#"{"id":3,"result":{"channels":{"Temperature":21.5,"Serial":4261412897}},"error":null}"#
    );
    let by_address = rpc(
        port,
        "device",
        "Load",
        json!({"path": path, "slave_id": 21, "channels": ["Temperature"]}),
    )
    .await;
    assert_eq!(
        by_address,
        json!({"id": 1, "result": {"channels": {"Temperature": 21.5}}, "error": null})
    );
    let unknown = rpc(
        port,
        "device",
        "Load",
        json!({"device_id": "climate_21", "channels": ["Nope"]}),
    )
    .await;
    assert_eq!(
        unknown["error"],
        json!({"code": -32000, "message":
            "Channel \"Nope\" is write only or not found in \"rtu2mqtt-climate\" device template"})
    );
    // Template parameters, read from the device as it holds them (scaled).
    bench.sim.control(
        json!({"cmd": "set", "device": 21, "type": "holding", "address": 101, "value": 250}),
    );
    let parameters = rpc(
        port,
        "device",
        "Load",
        json!({"device_id": "climate_21", "channels": ["Temperature"],
               "parameters": ["baud_rate", "selfheating_compensation_deg"]}),
    )
    .await;
    assert_eq!(
        parameters["result"],
        json!({"channels": {"Temperature": 21.5},
               "parameters": {"baud_rate": baud / 100, "selfheating_compensation_deg": 2.5}}),
        "{parameters}"
    );
    let unknown_parameter = rpc(
        port,
        "device",
        "Load",
        json!({"device_id": "climate_21", "parameters": ["nope"]}),
    )
    .await;
    assert_eq!(
        unknown_parameter["error"],
        json!({"code": -32000, "message":
            "Parameter \"nope\" is write only or not found in \"rtu2mqtt-climate\" device template"})
    );
    // device/Set of parameters: encoded with their format and scale, as the device model
    // encodes a channel; a read-only or unknown one and a bad value are refused, nothing written.
    let set_parameters = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "climate_21",
               "parameters": {"selfheating_compensation_deg": -1.5, "co2_sensor_enabled": 0}}),
    )
    .await;
    assert_eq!(
        set_parameters,
        json!({"id": 1, "result": {}, "error": null})
    );
    let climate_register = |kind: &str, address: u16| {
        bench
            .sim
            .control(json!({"cmd": "get", "device": 21, "type": kind, "address": address}))["value"]
            .clone()
    };
    assert_eq!(climate_register("holding", 101), 0x10000 - 150);
    assert_eq!(climate_register("coil", 3), 0);
    for (parameters, message) in [
        (
            json!({"nope": 1}),
            "Parameter \"nope\" is read only or not found in \"rtu2mqtt-climate\" device template",
        ),
        (
            json!({"motion_filter_time_const_s": 20, "selfheating_compensation_deg": "warm"}),
            "Parameter \"selfheating_compensation_deg\": a value takes a number, got `warm`",
        ),
    ] {
        let refused = rpc(
            port,
            "device",
            "Set",
            json!({"device_id": "climate_21", "parameters": parameters}),
        )
        .await;
        assert_eq!(
            refused["error"],
            json!({"code": -32000, "message": message}),
            "{refused}"
        );
    }
    assert_ne!(climate_register("holding", 282), 20);
    let unconfigured = rpc(
        port,
        "device",
        "Load",
        json!({"path": path, "slave_id": 99, "channels": ["Temperature"]}),
    )
    .await;
    assert_eq!(unconfigured["error"]["code"], -32000, "{unconfigured}");
    assert!(unconfigured["error"]["message"]
        .as_str()
        .unwrap()
        .contains("no configured device at slave_id 99"));

    // device/Set: checked as an /on payload, written through the bus queue.
    let set = rpc_raw(
        port,
        "device",
        "Set",
        &json!({"id": 4, "params": {"device_id": "relay6_20", "channels": {"K5": 1}}}).to_string(),
    )
    .await;
    assert_eq!(set, r#"{"id":4,"result":{},"error":null}"#);
    let k5 = bench
        .sim
        .control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 4}));
    assert_eq!(k5["value"], 1);
    let off = rpc(
        port,
        "device",
        "Set",
        json!({"path": path, "slave_id": 20, "channels": {"K5": "0"}}),
    )
    .await;
    assert_eq!(off, json!({"id": 1, "result": {}, "error": null}));
    let k5 = bench
        .sim
        .control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 4}));
    assert_eq!(k5["value"], 0);
    let read_only = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "relay6_20", "channels": {"Input 1": 1}}),
    )
    .await;
    assert_eq!(
        read_only["error"],
        json!({"code": -32000, "message":
            "Channel \"Input 1\" is read only or not found in \"rtu2mqtt-relay6\" device template"})
    );
    // The device model's check: a switch takes 0 or 1; nothing is written.
    let bad = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "relay6_20", "channels": {"K5": "maybe"}}),
    )
    .await;
    assert_eq!(bad["error"]["code"], -32000, "{bad}");
    assert!(
        bad["error"]["message"]
            .as_str()
            .unwrap()
            .starts_with("Channel \"K5\": a switch takes"),
        "{bad}"
    );

    press(0);
    event_seen("0").await;

    // device/Set on a bit field: the register is read first, only bit 3 changes.
    let holding_6 = || {
        bench
            .sim
            .control(json!({"cmd": "get", "device": 22, "type": "holding", "address": 6}))["value"]
            .clone()
    };
    assert_eq!(holding_6(), 0xA5);
    let bit_on = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "generic_22", "channels": {"Holding Bit 3": "1"}}),
    )
    .await;
    assert_eq!(bit_on, json!({"id": 1, "result": {}, "error": null}));
    assert_eq!(holding_6(), 0xAD);
    // Other bits changed on the device since: they are kept as they are now.
    bench.sim.control(
        json!({"cmd": "set", "device": 22, "type": "holding", "address": 6, "value": 0x1208}),
    );
    let bit_off = rpc(
        port,
        "device",
        "Set",
        json!({"path": path, "slave_id": 22, "channels": {"Holding Bit 3": 0}}),
    )
    .await;
    assert_eq!(bit_off, json!({"id": 1, "result": {}, "error": null}));
    assert_eq!(holding_6(), 0x1200);
    let bad_bit = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "generic_22", "channels": {"Holding Bit 3": "2"}}),
    )
    .await;
    assert_eq!(bad_bit["error"]["code"], -32000, "{bad_bit}");
    assert_eq!(holding_6(), 0x1200);

    // device/LoadConfig: the parameters the config sets as it sets them, every other one read
    // from the device now (as the simulator holds it), the model and firmware.
    let holding = |device: u8, address: u16| -> u64 {
        bench
            .sim
            .control(json!({"cmd": "get", "device": device, "type": "holding", "address": address}))
            ["value"]
            .as_u64()
            .unwrap()
    };
    // in2_mode (holding 10) changed through the service, as the web UI would write it.
    let write = json!({"path": path, "protocol": "modbus", "slave_id": 20, "function": 6,
                       "address": 10, "count": 1, "format": "HEX", "msg": "0004"});
    let written = rpc(port, "port", "Load", write).await;
    assert_eq!(written["result"], json!({"response": ""}), "{written}");
    let mut relay_parameters = serde_json::Map::new();
    relay_parameters.insert("baud_rate".into(), json!(holding(20, 110)));
    relay_parameters.insert("in0_mode".into(), json!(3));
    for input in 1..=6u16 {
        relay_parameters.insert(format!("in{input}_mode"), json!(holding(20, 8 + input)));
    }
    assert_eq!(relay_parameters["in2_mode"], 4);
    assert_eq!(relay_parameters["baud_rate"], baud / 100);
    let config = rpc_raw(
        port,
        "device",
        "LoadConfig",
        &json!({"id": 5, "params": {"device_id": "relay6_20"}}).to_string(),
    )
    .await;
    let expected = json!({"id": 5, "result": {"parameters": relay_parameters, "model": "R2M-RELAY6",
                          "fw": "1.26.0"}, "error": null});
    assert_eq!(config, expected.to_string());

    // Through the simulator's control socket: a signed, scaled parameter, a coil, a plain one.
    for (kind, address, value) in [
        ("holding", 101, 0xFF9C),
        ("coil", 3, 1),
        ("holding", 282, 15),
    ] {
        bench.sim.control(
            json!({"cmd": "set", "device": 21, "type": kind, "address": address, "value": value}),
        );
    }
    let climate = rpc(
        port,
        "device",
        "LoadConfig",
        json!({"path": path, "slave_id": 21}),
    )
    .await;
    assert_eq!(
        climate,
        json!({"id": 1, "result": {"parameters": {
            "baud_rate": baud / 100, "co2_sensor_enabled": 1, "motion_filter_time_const_s": 15,
            "selfheating_compensation_deg": -1}, "model": "R2M-CLIMATE", "fw": "1.0.0"}, "error": null})
    );
    // homeui sends the template it means: the same with the configured one, refused with
    // another (the type changed in the UI and not saved yet), for reading and for writing:
    // another template's registers are never read or written as this device's.
    let with_type =
        |device_type: &str| json!({"path": path, "slave_id": 21, "device_type": device_type});
    assert_eq!(
        rpc(port, "device", "LoadConfig", with_type("rtu2mqtt-climate")).await,
        climate
    );
    for method in ["LoadConfig", "Set"] {
        let mut request = with_type("rtu2mqtt-relay6");
        if method == "Set" {
            request["parameters"] = json!({"baud_rate": 96});
        }
        let refused = rpc(port, "device", method, request).await;
        let message = refused["error"]["message"].as_str().unwrap_or_default();
        assert!(
            message.contains("is configured as \"rtu2mqtt-climate\", not \"rtu2mqtt-relay6\"")
                && message.contains(&format!("device/{method}")),
            "{refused}"
        );
    }
    assert_eq!(holding(21, 110), baud / 100, "nothing written");
    // A device that is no Wiren Board one: parameters only. The one on a register the device
    // does not have is left out (its neighbour, read with it at first, is read again alone),
    // and so is the one whose condition names it; conditions see scaled values.
    for (address, value) in [(1, 0xFFF6), (2, 7)] {
        bench.sim.control(
            json!({"cmd": "set", "device": 22, "type": "holding", "address": address, "value": value}),
        );
    }
    let generic = rpc(
        port,
        "device",
        "LoadConfig",
        json!({"device_id": "generic_22"}),
    )
    .await;
    assert_eq!(
        generic,
        json!({"id": 1, "result": {"parameters": {"high_bits": 0x12, "if_negative": 7,
               "scaled": -5}}, "error": null})
    );
    // A parameter that is a bit field: the other bits as the device holds them.
    let high_bits = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "generic_22", "parameters": {"high_bits": 0x34}}),
    )
    .await;
    assert_eq!(high_bits, json!({"id": 1, "result": {}, "error": null}));
    assert_eq!(holding_6(), 0x3400);
    // A channel and a parameter in the same register, in one request: both land.
    let both = rpc(
        port,
        "device",
        "Set",
        json!({"device_id": "generic_22", "channels": {"Holding Bit 3": 1},
               "parameters": {"high_bits": 0x56}}),
    )
    .await;
    assert_eq!(both, json!({"id": 1, "result": {}, "error": null}));
    assert_eq!(holding_6(), 0x5608);

    // Events still flow after all of it.
    press(1);
    event_seen("1").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn device_methods_at_115200() {
    let bench = start_with_generic("115200 8N2", 115_200, true);
    device_methods(&bench).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn device_methods_at_9600() {
    let bench = start_with_generic("9600 8N2", 9600, true);
    device_methods(&bench).await;
}

/// The address tools and `events` on the daemon's busy port: two devices the daemon does not
/// poll share address 30; the daemon's relay keeps sending events throughout.
async fn site_tools_through_the_daemon(line: &str, baud: u32) {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let devices = json!({"devices": [
        {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020",
         "line": line, "model": "R2M-RELAY6", "firmware": "1.26.0"},
        {"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021",
         "line": line},
        {"name": "spare-a", "template": "rtu2mqtt-climate", "address": 30, "serial": "0xFE000030",
         "line": line},
        {"name": "spare-b", "template": "rtu2mqtt-climate", "address": 30, "serial": "0xFE000031",
         "line": line}
    ]});
    std::fs::write(&bus, devices.to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-tools-test"},
        "template_dirs": [repo("templates")],
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": [
            {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
            {"device_type": "rtu2mqtt-climate", "slave_id": 21}
        ]}]
    });
    let service_config = dir.path().join("service.json");
    std::fs::write(&service_config, config.to_string()).unwrap();
    let daemon = DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());
    let port = broker.port;
    let path = sim.pty.to_str().unwrap().to_owned();
    wait_until_served(port).await;
    let press = |value: u16| {
        sim.control(
            json!({"cmd": "set", "device": 20, "type": "discrete", "address": 0, "value": value}),
        )
    };
    let event_seen = |value: &'static str| {
        wait_for(
            "the relay's Input 1 event on the broker",
            move || async move {
                let state = retained(port).await?;
                (state.get("/devices/relay6_20/controls/Input 1")? == value).then_some(())
            },
        )
    };
    press(1);
    event_seen("1").await;
    let tool = |args: &[&str]| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
        command.stop_with_parent();
        command
            .args(args)
            .args(["--port", &path, "--parity", "N", "--stop-bits", "2"])
            .args(["--baud", &baud.to_string()])
            .args(["--broker", &format!("127.0.0.1:{port}")])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        command
    };
    let address_of = |serial: &str| {
        sim.control(json!({"cmd": "get", "serial": serial, "type": "holding", "address": 128}))
            ["value"]
            .as_u64()
            .unwrap()
    };

    // fix-addresses on the busy port (through the service on its own), an event during it.
    let fix = tool(&["fix-addresses", "--apply", "--range", "30-40"])
        .spawn()
        .unwrap();
    press(0);
    event_seen("0").await;
    let output = tokio::task::spawn_blocking(move || fix.wait_with_output().unwrap())
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(output.status.code(), Some(0), "{stdout} {stderr}");
    assert!(
        stderr.contains("is busy: fixing addresses through the running rtu2mqtt service"),
        "{stderr}"
    );
    assert!(stdout.contains("(confirmed by a new scan)"), "{stdout}");
    let (a, b) = (address_of("0xFE000030"), address_of("0xFE000031"));
    assert_ne!(a, b, "{stdout}");
    assert!((30..=40).contains(&a) && (30..=40).contains(&b), "{a} {b}");
    press(1);
    event_seen("1").await;

    // set-address by serial number with --via-mqtt: port/Setup by sn, then a confirming scan.
    let output = tokio::task::spawn_blocking({
        let mut command = tool(&["set-address", "--serial", "0xFE000031", "--address", "41"]);
        command.arg("--via-mqtt");
        move || command.output().unwrap()
    })
    .await
    .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(output.status.code(), Some(0), "{stdout} {stderr}");
    assert!(stdout.contains("-> 41 (confirmed by a scan)"), "{stdout}");
    assert_eq!(address_of("0xFE000031"), 41);
    press(0);
    event_seen("0").await;

    // events on the busy port: the packets the service received (it keeps acknowledging them),
    // each event as it came. Bounded in time, so that a missed event fails instead of hanging.
    let mut events = tool(&["events", "--json", "--count", "2", "--duration", "60"]);
    events.arg("--service-config").arg(&service_config);
    let mut events = events.spawn().unwrap();
    let mut stderr = std::io::BufReader::new(events.stderr.take().unwrap());
    let ready = tokio::task::spawn_blocking(move || {
        use std::io::BufRead;
        let mut seen = String::new();
        loop {
            let mut line = String::new();
            if stderr.read_line(&mut line).unwrap() == 0 {
                return seen;
            }
            seen.push_str(&line);
            if line.starts_with("showing the events") {
                return seen;
            }
        }
    })
    .await
    .unwrap();
    assert!(
        ready.contains("is busy: showing the running rtu2mqtt service's events"),
        "{ready}"
    );
    assert!(ready.contains("showing the events"), "{ready}");
    press(1);
    event_seen("1").await;
    press(0);
    let output = tokio::task::spawn_blocking(move || events.wait_with_output().unwrap())
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert_eq!(output.status.code(), Some(0), "{stdout}");
    let shown: Vec<Value> = stdout
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    let expected: Vec<Value> = [1, 0]
        .iter()
        .map(|value| {
            json!({"address": 20, "type": "discrete", "register": 0, "value": value,
                   "reboot": false, "device": "relay6_20", "channel": "Input 1",
                   "text": value.to_string(), "repeated": false, "via": "service"})
        })
        .collect();
    assert_eq!(shown, expected, "{stdout}");
    // The service got (and acknowledged) them too, and goes on.
    event_seen("0").await;
    press(1);
    event_seen("1").await;
    assert!(!daemon.log().contains("panicked"), "{}", daemon.log());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn site_tools_through_the_daemon_at_115200() {
    site_tools_through_the_daemon("115200 8N2", 115_200).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn site_tools_through_the_daemon_at_9600() {
    site_tools_through_the_daemon("9600 8N2", 9600).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rpc_through_the_daemon_at_115200() {
    let bench = start("115200 8N2", 115_200);
    reads_scans_and_errors(&bench, 115_200).await;
    set_poll_holds_and_resumes_a_device(&bench).await;
    set_address_goes_through_the_service(&bench).await;
    drop(bench.daemon);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rpc_through_the_daemon_at_9600() {
    let bench = start("9600 8N2", 9600);
    reads_scans_and_errors(&bench, 9600).await;
    set_poll_holds_and_resumes_a_device(&bench).await;
    set_address_goes_through_the_service(&bench).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_the_broker_does_not_confuse_the_tools() {
    // Side by side, as docs/migrating.md suggests for a port left on wb-mqtt-serial: another
    // server of these RPC topics answers every request too, "not my port" for ours, and first
    // (it has no bus work to do).
    let bench = start("115200 8N2", 115_200);
    let port = bench.broker.port;
    wait_until_served(port).await;
    let other_config = json!({
        "mqtt": {"host": "127.0.0.1", "port": port, "client_id": "rtu2mqtt-other-server",
                 "clear_on_exit": true},
        "ports": [{"path": "/dev/ttyRTU2MQTT-NOPE", "baud_rate": 9600,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 5}]}]
    });
    let mut other = DaemonProcess::start(&other_config, &[], Stdio::null(), Stdio::null());
    wait_for("the other server's answer", || async {
        let ports = rpc(port, "ports", "Load", json!({})).await;
        ports.to_string().contains("ttyRTU2MQTT-NOPE").then_some(())
    })
    .await;

    for _ in 0..3 {
        let (code, stdout, stderr) = cli_read(&bench, &["--via-mqtt"]).await;
        assert_eq!(code, 0, "{stdout}{stderr}");
        let reply: Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(reply["registers"], json!([2150]), "{reply}");
    }

    // The other server's clean exit leaves the shared method topics as they were.
    assert!(other.terminate().success());
    let state = retained(port).await.expect("retained state");
    assert_eq!(
        state
            .get("/rpc/v1/wb-mqtt-serial/port/Load")
            .map(String::as_str),
        Some("1")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_json_rpc_errors_and_the_daemon_lives_on() {
    let bench = start("115200 8N2", 115_200);
    let port = bench.broker.port;
    wait_until_served(port).await;

    let not_json: Value =
        serde_json::from_str(&rpc_raw(port, "port", "Load", "not json {").await).unwrap();
    assert_eq!(not_json["id"], Value::Null);
    assert_eq!(not_json["result"], Value::Null);
    assert_eq!(not_json["error"]["code"], -32700, "{not_json}");

    let unknown = rpc(port, "port", "Explode", json!({})).await;
    assert_eq!(unknown["error"]["code"], -32000);
    assert!(unknown["error"]["message"]
        .as_str()
        .unwrap()
        .contains("unknown method port/Explode"));

    let path = bench.sim.pty.to_str().unwrap().to_owned();
    let bad_function = rpc(
        port,
        "port",
        "Load",
        json!({"path": path, "protocol": "modbus", "slave_id": 21, "function": 7}),
    )
    .await;
    assert_eq!(bad_function["error"]["code"], -32000);
    assert!(bad_function["error"]["message"]
        .as_str()
        .unwrap()
        .contains("\"function\""));

    let other_port = rpc(
        port,
        "port",
        "Load",
        json!({"path": "/dev/ttyNOPE", "protocol": "modbus", "slave_id": 1, "function": 3}),
    )
    .await;
    assert!(other_port["error"]["message"]
        .as_str()
        .unwrap()
        .contains("not served"));

    // A scan that cannot end within its total_timeout: the timeout error.
    let hurried = rpc(
        port,
        "port",
        "Scan",
        json!({"path": path, "baud_rate": 1200, "total_timeout": 1}),
    )
    .await;
    assert_eq!(hurried["error"]["code"], -32600, "{hurried}");

    // Scan step by step, as wb-device-manager does: start, next, next until none is left.
    let mut serials = Vec::new();
    for mode in ["start", "next", "next"] {
        let step = rpc(port, "port", "Scan", json!({"path": path, "mode": mode})).await;
        let devices = step["result"]["devices"]
            .as_array()
            .expect("devices")
            .clone();
        assert!(devices.len() <= 1, "{step}");
        serials.extend(devices.iter().map(|d| d["sn"].as_str().unwrap().to_owned()));
    }
    serials.sort();
    assert_eq!(serials, ["4261412896", "4261412897"]);

    // Still serving.
    let ports = rpc(port, "ports", "Load", json!({})).await;
    assert_eq!(ports["result"][0]["path"], path.as_str());
    assert!(
        !bench.daemon.log().contains("panicked"),
        "{}",
        bench.daemon.log()
    );
}

/// A port whose config turns Fast Modbus off (`"fast_modbus": false`) never carries a Fast
/// Modbus frame: no event poll, no event setup, and port/Scan (the web UI's scan, `rtu2mqtt scan`
/// through the service) and requests by serial number (port/Load and port/Setup with `sn`) are
/// refused with the reason. Its devices are polled classically, and served by address.
/// The simulator with one relay at address 20 on `line` (and the directory of its bus file).
fn relay_bus(line: &str) -> (tempfile::TempDir, SimProcess) {
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "relay", "template": "rtu2mqtt-relay6", "address": 20,
                            "serial": "0xFE000020", "line": line}]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    (dir, sim)
}

async fn no_fast_modbus_frame_on_a_port_that_turns_it_off(line: &str, baud: u32) {
    let broker = Mosquitto::start();
    let (_dir, sim) = relay_bus(line);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-rpc-test"},
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "fast_modbus": false,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let daemon = DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());
    let port = broker.port;
    wait_until_served(port).await;
    let path = sim.pty.to_str().unwrap().to_owned();

    // The relay is polled (its sporadic inputs too), and nothing of Fast Modbus ever reached
    // the bus.
    wait_for("the relay's inputs polled", || async {
        let state = retained(port).await?;
        state.get("/devices/relay6_20/controls/Input 1")?;
        let stats = sim.control(json!({"cmd": "stats"}));
        (stats["classic_requests"].as_u64()? >= 20).then_some(())
    })
    .await;
    let stats = sim.control(json!({"cmd": "stats"}));
    assert_eq!(stats["fast_requests"], 0, "{stats}");
    assert_eq!(stats["event_polls"], 0, "{stats}");
    let scan = rpc(port, "port", "Scan", json!({"path": path})).await;
    assert_eq!(scan["error"]["code"], -32000, "{scan}");
    let message = scan["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("Fast Modbus is off") && message.contains("\"fast_modbus\": false"),
        "{message}"
    );
    // Requests by serial number (Fast Modbus 0x46 0x08): refused too.
    let by_serial = rpc(
        port,
        "port",
        "Load",
        json!({"path": path, "protocol": "modbus", "sn": 4261412896u64, "function": 3,
               "address": 128, "count": 1}),
    )
    .await;
    assert_eq!(by_serial["error"]["code"], -32000, "{by_serial}");
    let setup = rpc(
        port,
        "port",
        "Setup",
        json!({"path": path, "items": [{"slave_id": 20, "sn": 4261412896u64,
                                        "cfg": {"slave_id": 31}}]}),
    )
    .await;
    assert_eq!(setup["error"]["code"], -32000, "{setup}");
    for refused in [&by_serial, &setup] {
        let message = refused["error"]["message"].as_str().unwrap();
        assert!(
            message.contains("no Fast Modbus request by serial number is sent"),
            "{message}"
        );
    }
    // By address, classic Modbus: served.
    let classic = rpc(
        port,
        "port",
        "Load",
        json!({"path": path, "protocol": "modbus", "slave_id": 20, "function": 3,
               "address": 128, "count": 1, "format": "HEX"}),
    )
    .await;
    assert_eq!(classic["result"]["response"], "0014", "{classic}");
    let stats = sim.control(json!({"cmd": "stats"}));
    assert_eq!(
        stats["fast_requests"], 0,
        "the refused requests sent nothing: {stats}"
    );
    assert!(!daemon.log().contains("panicked"), "{}", daemon.log());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_fast_modbus_frame_on_a_port_that_turns_it_off_at_115200() {
    no_fast_modbus_frame_on_a_port_that_turns_it_off("115200 8N2", 115_200).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_fast_modbus_frame_on_a_port_that_turns_it_off_at_9600() {
    no_fast_modbus_frame_on_a_port_that_turns_it_off("9600 8N2", 9600).await;
}

/// wb-mqtt-dali (Wiren Board's DALI service) drives its WB-MDALI gateways through the serial
/// service: it waits for `config/Load` to be advertised (it gives up after 5 s otherwise),
/// finds its gateways by `device_type` in `config.ports[].devices[]` (the MQTT id is `id`, else
/// `wb-mdali_<slave_id>`), then writes the gateway's queue with `port/Load` naming the device
/// by `device_id`, without `protocol`, and reads the replies from the device's controls.
/// Here as it does it, against a generic simulated device standing in for the gateway.
async fn a_dali_gateway_as_wb_mqtt_dali_drives_it(line: &str, baud: u32) {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "gateway", "template": "rtu2mqtt-generic", "address": 22,
                            "serial": "0xFE000022", "line": line, "fast": false}]})
        .to_string(),
    )
    .unwrap();
    let templates = dir.path().join("templates");
    std::fs::create_dir_all(&templates).unwrap();
    let gateway_template = json!({
        "title": "WB-MDALI gateway", "device_type": "WB-MDALI", "group": "g-wb",
        "hw": [{"signature": "WBMDALI", "fw": "1.5.0"}],
        "device": {
            "name": "WB-MDALI", "id": "wb-mdali", "max_read_registers": 10,
            "translations": {"ru": {"WB-MDALI gateway": "Шлюз WB-MDALI"}},
            "channels": [
                {"name": "bus_1_bulk_send_pointer", "reg_type": "holding", "address": 0,
                 "type": "value"},
                {"name": "bus_1_bulk_send_frame", "reg_type": "holding", "address": 2,
                 "format": "u32", "type": "value"}
            ]
        }
    });
    std::fs::write(
        templates.join("config-wb-mdali.json"),
        gateway_template.to_string(),
    )
    .unwrap();
    // A WBIO module behind the same address: its registers are not the host's.
    let module_template = json!({
        "device_type": "WBIO-TEST",
        "device": {"name": "WBIO", "id": "wbio-test", "protocol": "modbus_io",
                   "channels": [{"name": "K1", "reg_type": "coil", "address": 0,
                                 "type": "switch"}]}
    });
    std::fs::write(
        templates.join("config-wbio-test.json"),
        module_template.to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-rpc-test",
                 "password": "never-published"},
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "poll_interval": 15,
                   "devices": [{"device_type": "WB-MDALI", "slave_id": 22,
                                "channels": [{"name": "from an older template"}]},
                               {"device_type": "WBIO-TEST", "slave_id": "22:1",
                                "id": "module"},
                               {"device_type": "rtu2mqtt-relay6", "slave_id": 30,
                                "enabled": false, "poll_interval": 9}]}]
    });
    let daemon = DaemonProcess::start(
        &config,
        &["--templates", templates.to_str().unwrap()],
        Stdio::null(),
        Stdio::null(),
    );
    let port = broker.port;

    // What wb-mqtt-dali waits for before anything else.
    wait_for("the advertised config/Load method", || async {
        let state = retained(port).await?;
        (state.get("/rpc/v1/wb-mqtt-serial/config/Load")? == "1").then_some(())
    })
    .await;
    let loaded = rpc(port, "config", "Load", json!({})).await;
    let result = &loaded["result"];
    let config = &result["config"];
    assert_eq!(
        config.get("mqtt"),
        None,
        "credentials are never published: {loaded}"
    );
    assert_eq!(config["ports"][0]["read_rate_limit_ms"], 15, "{loaded}");
    let gateways: Vec<String> = config["ports"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|port| port["enabled"].as_bool().unwrap_or(true))
        .flat_map(|port| port["devices"].as_array().unwrap())
        .filter(|device| device["device_type"] == "WB-MDALI")
        .map(|device| match device["id"].as_str() {
            Some(id) => id.to_owned(),
            None => format!("wb-mdali_{}", device["slave_id"].as_str().unwrap()),
        })
        .collect();
    assert_eq!(gateways, ["wb-mdali_22"], "{loaded}");
    assert_eq!(
        config["ports"][0]["devices"][0],
        json!({"device_type": "WB-MDALI", "slave_id": "22"}),
        "the channel the template no longer has is left out, as wb-mqtt-serial does"
    );
    // A disabled device is converted too, though the running config does not use its template.
    assert_eq!(
        config["ports"][0]["devices"][2],
        json!({"device_type": "rtu2mqtt-relay6", "slave_id": "30", "enabled": false,
               "read_rate_limit_ms": 9}),
        "{loaded}"
    );
    // The device types of the library (the built-in ones too), the Wiren Board group first.
    let listed = |result: &Value| -> Value {
        assert_eq!(result["types"][0]["name"], "g-wb", "{result}");
        result["types"][0]["types"]
            .as_array()
            .unwrap()
            .iter()
            .find(|listed| listed["type"] == "WB-MDALI")
            .cloned()
            .unwrap_or_else(|| panic!("no WB-MDALI in {result}"))
    };
    assert_eq!(
        listed(result),
        json!({"name": "WB-MDALI gateway", "deprecated": false, "type": "WB-MDALI",
               "protocol": "modbus", "mqtt-id": "wb-mdali",
               "hw": [{"signature": "WBMDALI", "fw": "1.5.0"}]})
    );
    assert!(result["schema"].is_object(), "{loaded}");
    let russian = rpc(port, "config", "Load", json!({"lang": "ru"})).await;
    assert_eq!(listed(&russian["result"])["name"], "Шлюз WB-MDALI");
    // A `lang` that is not text is read as wb-mqtt-serial reads it: a number as its text (no
    // such language: English titles); an object is refused.
    let numbered = rpc(port, "config", "Load", json!({"lang": 7})).await;
    assert_eq!(listed(&numbered["result"])["name"], "WB-MDALI gateway");
    let refused = rpc(port, "config", "Load", json!({"lang": {"ru": true}})).await;
    assert_eq!(refused["error"]["code"], -32000, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("lang"),
        "{refused}"
    );

    // The gateway's queue, written as wb-mqtt-dali writes it: one register, then a frame of
    // two (function 16), by device id and without "protocol".
    let gateway = "wb-mdali_22";
    let write = |function: u64, address: u64, count: u64, msg: &str| {
        json!({"device_id": gateway, "function": function, "address": address, "count": count,
               "total_timeout": 1000, "frame_timeout": 0, "format": "HEX", "msg": msg})
    };
    let written = rpc(port, "port", "Load", write(6, 0, 1, "002a")).await;
    assert_eq!(written["result"], json!({"response": ""}), "{written}");
    let written = rpc(port, "port", "Load", write(16, 2, 2, "0001e240")).await;
    assert_eq!(written["result"], json!({"response": ""}), "{written}");
    let held = |address: u64| {
        sim.control(json!({"cmd": "get", "device": 22, "type": "holding", "address": address}))
            ["value"]
            .clone()
    };
    assert_eq!(held(0), 42);
    assert_eq!(held(2), 1);
    assert_eq!(held(3), 0xE240);
    // A read by device id answers with the registers.
    let read = rpc(port, "port", "Load", write(3, 2, 2, "")).await;
    assert_eq!(read["result"], json!({"response": "0001e240"}), "{read}");
    // A module behind a WB-MIO is refused by device id, as wb-mqtt-serial refuses devices of
    // other protocols (its registers are not the host's at these addresses).
    let mut to_module = write(6, 0, 1, "0007");
    to_module["device_id"] = json!("module");
    let refused = rpc(port, "port", "Load", to_module).await;
    assert_eq!(refused["error"]["code"], -32000, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("modbus_io"),
        "{refused}"
    );
    assert_eq!(held(0), 42, "nothing written");
    // A `device_id` that names no configured device gives way to the port the request names
    // (wb-mqtt-serial looks the device up, then the port); without one it is reported.
    let mut by_path = write(3, 2, 2, "");
    by_path["device_id"] = json!("wb-mdali_7");
    by_path["path"] = json!(sim.pty);
    by_path["slave_id"] = json!(22);
    by_path["protocol"] = json!("modbus");
    let read = rpc(port, "port", "Load", by_path.clone()).await;
    assert_eq!(read["result"], json!({"response": "0001e240"}), "{read}");
    by_path.as_object_mut().unwrap().remove("path");
    let unknown = rpc(port, "port", "Load", by_path).await;
    assert_eq!(unknown["error"]["code"], -32000, "{unknown}");
    assert!(
        unknown["error"]["message"]
            .as_str()
            .unwrap()
            .contains("\"wb-mdali_7\""),
        "{unknown}"
    );
    // And the service publishes the gateway's registers where wb-mqtt-dali reads them.
    wait_for("the gateway's registers on MQTT", || async {
        let state = retained(port).await?;
        let pointer = state.get("/devices/wb-mdali_22/controls/bus_1_bulk_send_pointer")?;
        let frame = state.get("/devices/wb-mdali_22/controls/bus_1_bulk_send_frame")?;
        (pointer == "42" && frame == "123456").then_some(())
    })
    .await;

    // A write whose reply is lost is sent once, as wb-mqtt-serial sends it (a queue would
    // carry it out twice); a read is tried again. Polling held (the gateway's and the
    // module's, at the same address), so the requests the device hears are the RPC's only.
    for device in [gateway, "module"] {
        let held_off = rpc(
            port,
            "device",
            "SetPoll",
            json!({"device_id": device, "poll": false}),
        )
        .await;
        assert_eq!(held_off["result"], json!({}), "{held_off}");
    }
    sim.control(json!({"cmd": "faults", "device": 22, "drop": 1.0}));
    let classic_requests = || sim.control(json!({"cmd": "stats"}))["classic_requests"].clone();
    let before = classic_requests().as_u64().unwrap();
    // The time to try again is given: a try waits out the hold-off after a failure (a late
    // reply to the request before must not pass for its answer).
    let patient = |mut request: Value| {
        request["total_timeout"] = json!(10_000);
        request
    };
    let unanswered = rpc(port, "port", "Load", patient(write(6, 0, 1, "0063"))).await;
    assert_eq!(unanswered["error"]["code"], -32600, "{unanswered}");
    assert_eq!(held(0), 99, "the write was carried out");
    assert_eq!(classic_requests(), before + 1, "sent once");
    let unanswered = rpc(port, "port", "Load", patient(write(3, 0, 1, ""))).await;
    assert_eq!(unanswered["error"]["code"], -32600, "{unanswered}");
    assert_eq!(
        classic_requests(),
        before + 2,
        "a read met by silence is sent once, as wb-mqtt-serial sends it (a scan pays one \
         timeout per empty address): {unanswered}"
    );
    sim.control(json!({"cmd": "faults", "device": 22, "drop": 0.0}));
    assert!(!daemon.log().contains("panicked"), "{}", daemon.log());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dali_gateway_as_wb_mqtt_dali_drives_it_at_115200() {
    a_dali_gateway_as_wb_mqtt_dali_drives_it("115200 8N2", 115_200).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dali_gateway_as_wb_mqtt_dali_drives_it_at_9600() {
    a_dali_gateway_as_wb_mqtt_dali_drives_it("9600 8N2", 9600).await;
}

/// A reply too large for one MQTT packet (config/Load of a config with 300 KB of notes) is an
/// error that says so, and the server goes on: sent as it was, the client would refuse the
/// packet and drop the connection with every reply in flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reply_too_large_for_one_packet_is_an_error_and_the_server_goes_on() {
    let broker = Mosquitto::start();
    let (_dir, sim) = relay_bus("115200 8N2");
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-rpc-test"},
        "notes": "x".repeat(300_000),
        "ports": [{"path": sim.pty, "baud_rate": 115_200, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let daemon = DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());
    let port = broker.port;
    wait_until_served(port).await;
    let loaded = rpc(port, "config", "Load", json!({})).await;
    assert_eq!(
        loaded["error"]["code"],
        -32000,
        "{:.300}",
        loaded.to_string()
    );
    let message = loaded["error"]["message"].as_str().unwrap();
    assert!(
        message.starts_with("the reply is ") && message.contains("at most"),
        "{message}"
    );
    let ports = rpc(port, "ports", "Load", json!({})).await;
    assert_eq!(ports["result"][0]["baud_rate"], 115_200, "{ports}");
    assert!(!daemon.log().contains("panicked"), "{}", daemon.log());
}

/// A server on the broker that answers every `port/Scan` with `reply` after `delay`.
async fn scan_server(port: u16, name: &str, delay: std::time::Duration, reply: Value) {
    use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
    let mut options = MqttOptions::new(name, "127.0.0.1", port);
    options.set_keep_alive(std::time::Duration::from_secs(30));
    let (client, mut events) = AsyncClient::new(options, 16);
    client
        .subscribe("/rpc/v1/wb-mqtt-serial/port/Scan/+", QoS::AtLeastOnce)
        .await
        .unwrap();
    let (subscribed, ready) = tokio::sync::oneshot::channel();
    let mut subscribed = Some(subscribed);
    tokio::spawn(async move {
        while let Ok(event) = events.poll().await {
            match event {
                Event::Incoming(Packet::SubAck(_)) => {
                    if let Some(subscribed) = subscribed.take() {
                        let _ = subscribed.send(());
                    }
                }
                Event::Incoming(Packet::Publish(publish)) if !publish.topic.ends_with("/reply") => {
                    let request: Value = serde_json::from_slice(&publish.payload).unwrap();
                    let mut answer = reply.clone();
                    answer["id"] = request["id"].clone();
                    let client = client.clone();
                    let topic = format!("{}/reply", publish.topic);
                    tokio::spawn(async move {
                        tokio::time::sleep(delay).await;
                        let _ = client
                            .publish(topic, QoS::AtLeastOnce, false, answer.to_string())
                            .await;
                    });
                }
                _ => {}
            }
        }
    });
    ready.await.unwrap();
}

/// Beside another server of these topics, a call about a port the right server listed waits for
/// that server's answer however long its bus work takes: the other's "not my port" came at
/// once and was the outcome 2 s later, so a scan of a setting through the service (seconds at
/// 9600) was reported as "not served" (a site tools audit). Before the port is listed, the 2 s
/// grace stands: a port nobody serves is said soon.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_answer_beside_another_server_is_waited_for_once_the_port_is_listed() {
    use rtu2mqtt::rpc::client::{CallError, RpcSession};
    let broker = Mosquitto::start();
    let not_mine = json!({"error": {"code": -32000,
        "message": "port /dev/ttyX is not served by this rtu2mqtt"}});
    scan_server(broker.port, "other", std::time::Duration::ZERO, not_mine).await;
    let found = json!({"result": {"devices": [{"sn": "7"}]}});
    scan_server(
        broker.port,
        "right",
        std::time::Duration::from_secs(3),
        found,
    )
    .await;
    let config: rtu2mqtt::config::config_file::MqttConfig =
        serde_json::from_value(json!({"host": "127.0.0.1", "port": broker.port})).unwrap();
    let timeout = std::time::Duration::from_secs(10);

    let mut session = RpcSession::connect(&config).await.unwrap();
    let early = session
        .call("port", "Scan", json!({"path": "/dev/ttyX"}), timeout)
        .await;
    assert!(
        matches!(&early, Err(CallError::Refused(error)) if error.is_not_served_here()),
        "{early:?}"
    );

    // The same session (one client id; the right server's late answer to the first call has
    // another id and is not taken for this one's).
    session.port_is_served();
    let result = session
        .call("port", "Scan", json!({"path": "/dev/ttyX"}), timeout)
        .await
        .unwrap();
    assert_eq!(result["devices"][0]["sn"], "7", "{result}");
}
