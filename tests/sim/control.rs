//! The simulator's other faces: RTU over TCP, the control socket's change stream, scripts, faults.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::os::unix::net::UnixStream;
use std::time::Duration;

use crate::sim_support::{with_crc, SimProcess, FAST};
use rtu2mqtt::protocol::{ParseStatus, ReplyParser, Request, RequestPdu};
use serde_json::{json, Value};

#[test]
fn rtu_over_tcp_uses_the_listener_settings() {
    let sim = SimProcess::start(
        "bus.json",
        &["--tcp", "127.0.0.1:0", "--tcp-line", "115200 8N2"],
    );
    let list = sim.control(json!({"cmd": "list"}));
    assert_eq!(list["devices"].as_array().map(Vec::len), Some(8));
    let address = banner_tcp_address(&sim);
    let mut stream = TcpStream::connect(address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    let request = Request::classic(
        241,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    stream.write_all(&request.encode().unwrap()).unwrap();
    let mut parser = ReplyParser::for_request(&request);
    let mut buf = [0u8; 64];
    let mut bytes = Vec::new();
    loop {
        let len = stream.read(&mut buf).unwrap();
        assert!(len > 0);
        bytes.extend_from_slice(&buf[..len]);
        if matches!(parser.feed(&buf[..len]), ParseStatus::Frame(_)) {
            break;
        }
    }
    // 241 runs at 115200 8N2: it answered, so the listener's line has --tcp-line's settings.
    // (Devices at other settings stay silent: src/sim/bus_tests.rs proves it on virtual time.)
    assert_eq!(bytes, with_crc("F1 03 02 00 F1"));
}

fn banner_tcp_address(sim: &SimProcess) -> String {
    // "tcp 127.0.0.1:PORT (115200 8N2)": port 0 was asked for, the banner names the bound one.
    sim.banner()
        .iter()
        .find_map(|line| {
            line.strip_prefix("tcp ")
                .and_then(|rest| rest.split(' ').next())
        })
        .expect("tcp line in the banner")
        .to_string()
}

#[test]
fn watch_streams_register_changes_from_master_and_script() {
    let script = crate::sim_support::data("toggle.script");
    let sim = SimProcess::start("bus.json", &["--script", script.to_str().unwrap()]);
    let mut watcher = UnixStream::connect(&sim.control).unwrap();
    writeln!(watcher, "{}", json!({"cmd": "watch"})).unwrap();
    let mut lines = BufReader::new(watcher).lines();
    let ack: Value = serde_json::from_str(&lines.next().unwrap().unwrap()).unwrap();
    assert_eq!(ack["ok"], true);
    let mut port = sim.master(FAST);
    let write = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 9,
            value: 3,
        },
    );
    assert_eq!(port.transact(&write).0, write.encode().unwrap());
    let mut from_master = false;
    for line in lines.by_ref().take(20) {
        let change: Value = serde_json::from_str(&line.unwrap()).unwrap();
        assert!(change["mono_ns"].as_u64().unwrap() > 0);
        if change["origin"] == "master" {
            assert_eq!(
                (
                    change["address"].clone(),
                    change["type"].clone(),
                    change["register"].clone(),
                    change["value"].clone()
                ),
                (json!(20), json!("holding"), json!(9), json!(3))
            );
            from_master = true;
            break;
        }
        assert_eq!(
            (change["device"].clone(), change["type"].clone()),
            (json!("relay"), json!("coil"))
        );
    }
    assert!(from_master);
}

#[test]
fn faults_corrupt_replies() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    let read = Request::classic(
        30,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    // A dropped reply is silence, proved on virtual time in src/sim/bus_tests.rs; here the
    // control command's effect shows in a corrupted reply.
    sim.control(json!({"cmd": "faults", "device": 30, "corrupt_crc": 1.0}));
    port.send(&read.encode().unwrap());
    let bytes: Vec<u8> = port
        .read_until(Duration::from_secs(2), |all| all.len() >= 7)
        .into_iter()
        .flat_map(|(_, bytes)| bytes)
        .collect();
    let good = with_crc("1E 03 02 00 1E");
    assert_eq!(bytes.len(), good.len());
    assert_eq!(bytes[..6], good[..6]);
    assert_eq!(bytes[6], good[6] ^ 0xFF);
    sim.control(json!({"cmd": "faults", "device": 30}));
    assert_eq!(port.transact(&read).0, good);
}
