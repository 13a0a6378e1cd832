//! wb-mqtt-serial parity of the MQTT RPC where wb-device-manager (the web UI's scan) depends on
//! it, and scans that run beside each other: a daemon on the simulator, a real mosquitto. Each
//! test came with a review of the site tools and the RPC and failed on the code before its fix.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::process::Stdio;

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{retained, rpc, wait_for, Mosquitto};
use serde_json::json;
use sim_support::SimProcess;

/// A daemon on the simulator: a relay at 20 and a WB-MAP12E energy meter at 30 (serial
/// 0xFE123456), 115200 8N2.
fn bench() -> (Mosquitto, SimProcess, DaemonProcess, tempfile::TempDir) {
    let broker = Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let devices = json!({"devices": [
        {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020",
         "line": "115200 8N2", "model": "WBMR6C", "firmware": "1.26.0"},
        {"name": "meter", "template": "rtu2mqtt-relay6", "address": 30, "serial": "0xFE123456",
         "line": "115200 8N2", "model": "MAP12E", "firmware": "2.4.0"}
    ]});
    std::fs::write(&bus, devices.to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-review"},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2, "devices": [
            {"device_type": "rtu2mqtt-relay6", "slave_id": 20}
        ]}]
    });
    let daemon = DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null());
    (broker, sim, daemon, dir)
}

async fn served(port: u16) {
    wait_for("the advertised port/Load method", || async {
        let state = retained(port).await?;
        (state.get("/rpc/v1/wb-mqtt-serial/port/Load")? == "1").then_some(())
    })
    .await;
}

/// wb-mqtt-serial answers a `port/Load` nobody answers with E_RPC_REQUEST_TIMEOUT (-32600)
/// (rpc_port_load_modbus_serial_client_task.cpp: `catch (const TResponseTimeoutException&)
/// { OnError(WBMQTT::E_RPC_REQUEST_TIMEOUT, …) }`); wb-device-manager turns exactly that code
/// into SerialTimeoutException (serial_rpc.py), which its bootloader scan needs
/// (bootloader_scan.py `is_in_bootloader_mode`: `except SerialTimeoutException: return True`).
/// rtu2mqtt answers -32000: devices in bootloader are never found, timeouts look like failures.
#[tokio::test(flavor = "multi_thread")]
async fn port_load_silence_is_wb_request_timeout() {
    let (broker, sim, _daemon, _dir) = bench();
    served(broker.port).await;
    let path = sim.pty.to_str().unwrap();
    let silent = json!({"path": path, "protocol": "modbus", "slave_id": 99, "function": 3,
                        "address": 0, "count": 1, "format": "HEX", "response_timeout": 100});
    let reply = rpc(broker.port, "port", "Load", silent).await;
    assert_eq!(reply["error"]["code"], -32600, "{reply}");
}

/// wb-device-manager's Fast Modbus scan sends `"command": 96` (0x60) at every setting
/// (main.py: "Use 0x60 for scanning as the last device with deprecated command only was sold
/// 18.12.24"); wb-mqtt-serial scans with it. rtu2mqtt refuses: the web UI finds no device and
/// lists every setting as a failed port. rtu2mqtt scans with 0x60 then: its scan, and its
/// reads by serial number of what it found (whose `sn` goes on to requests by serial number).
#[tokio::test(flavor = "multi_thread")]
async fn port_scan_with_command_96_finds_the_devices_as_wb_device_manager_asks() {
    let (broker, sim, _daemon, _dir) = bench();
    served(broker.port).await;
    let path = sim.pty.to_str().unwrap();
    let params = json!({"path": path, "baud_rate": 115200, "parity": "N", "data_bits": 8,
                        "stop_bits": 2, "command": 96, "total_timeout": 10000});
    let reply = rpc(broker.port, "port", "Scan", params).await;
    let devices = reply["result"]["devices"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    assert_eq!(devices.len(), 2, "{reply}");
}

/// wb-mqtt-serial reports the serial number of a WB-MAP meter as its lower 24 bits
/// (rpc_port_scan_serial_client_task.cpp `GetSnFromRegister`: `^MAP[0-9]{1,2}.*` →
/// `sn & 0x00FFFFFF`), the number on its sticker and the one wb-device-manager keys it by.
#[tokio::test(flavor = "multi_thread")]
async fn port_scan_reports_a_map_meter_by_its_lower_24_bits_as_wb_mqtt_serial_does() {
    let (broker, sim, _daemon, _dir) = bench();
    served(broker.port).await;
    let path = sim.pty.to_str().unwrap();
    let reply = rpc(broker.port, "port", "Scan", json!({"path": path})).await;
    let devices = reply["result"]["devices"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    let meter = devices
        .iter()
        .find(|d| d["cfg"]["slave_id"] == 30)
        .unwrap_or_else(|| panic!("meter at 30 in {reply}"));
    assert_eq!(meter["device_signature"], "MAP12E", "{meter}");
    assert_eq!(
        meter["sn"],
        (0xFE12_3456_u32 & 0x00FF_FFFF).to_string(),
        "{meter}"
    );
    // rtu2mqtt's own field: the whole number, for requests by serial number.
    assert_eq!(
        meter["fast_modbus_sn"],
        0xFE12_3456_u32.to_string(),
        "{meter}"
    );
    let relay = devices
        .iter()
        .find(|d| d["cfg"]["slave_id"] == 20)
        .unwrap_or_else(|| panic!("relay at 20 in {reply}"));
    assert_eq!(relay["sn"], 0xFE00_0020_u32.to_string(), "{relay}");
    assert!(relay.get("fast_modbus_sn").is_none(), "{relay}");
}

/// Two `port/Scan` requests on one port at once (the web UI's scan and `rtu2mqtt scan`, or the
/// status page's scan button): each scan is a chain of queued transactions (0x46 0x01, then
/// 0x02 …), and the queue interleaves the two chains. A scan start of one marks every device
/// un-scanned again in the middle of the other, and a continue of one takes a device from the
/// other: one of them ends early and lists fewer devices. wb-mqtt-serial runs a scan as one
/// serial-client task (rpc_port_scan_serial_client_task.cpp), never interleaved.
#[tokio::test(flavor = "multi_thread")]
async fn two_scans_at_once_each_find_every_device() {
    let (broker, sim, _daemon, _dir) = bench();
    served(broker.port).await;
    let path = sim.pty.to_str().unwrap().to_owned();
    for round in 0..5 {
        let one = rpc(
            broker.port,
            "port",
            "Scan",
            json!({"path": path, "mode": "all"}),
        );
        let two = async {
            let params = json!({"path": path, "mode": "all", "total_timeout": 9999});
            rpc(broker.port, "port", "Scan", params).await
        };
        let (one, two) = tokio::join!(one, two);
        for reply in [&one, &two] {
            let found = reply["result"]["devices"].as_array().map_or(0, Vec::len);
            assert_eq!(
                found, 2,
                "round {round}: a scan run beside another one: {reply}"
            );
        }
    }
}
