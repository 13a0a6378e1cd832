//! Independent Fast Modbus peers against rtu2mqtt, as real processes (docs/reliability.md,
//! "Independent peers: Fast Modbus from the protocol description").
//!
//! `tests/interop/fast_device.py` (a bus of three Fast Modbus devices on a pty) and
//! `tests/interop/fast_master.py` (a master) were written from shared/protocol/fast-modbus.md
//! and tests/data/vectors.json only, without reading rtu2mqtt's code. Here:
//! - the daemon (`rtu2mqtt run`, a real mosquitto) polls the Python devices through a socat pty
//!   pair at 9600 8N2 and 115200 8N2: values, events (0x18, 0x10, confirmation), the reboot
//!   event, writes from MQTT;
//! - the site tools (`scan`, `read`/`write --serial`) find and use the Python devices;
//! - the Python master scans `rtu2mqtt sim`, reads by serial, enables, polls and confirms events.
//!
//! The tests run one at a time (a lock): the Python devices keep windows of 156 µs by
//! busy-waiting, which two such tests side by side on two cores would spoil. Python, socat and
//! mosquitto are required: a missing one fails the test, it is never skipped.

mod daemon_support;
mod mqtt_support;
mod sim_support;
#[path = "tool_support/mod.rs"]
mod tool_support;

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tool_support::tool;

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{publish, retained, wait_for, Mosquitto};
use rtu2mqtt::child::StopWithParent;
use serde_json::{json, Value};
use sim_support::SimProcess;

const PYTHON: &str = "/usr/bin/python3";
const WAIT: Duration = Duration::from_secs(15);

/// Serials of the Python bus: two from the seed's traces, one home-made (§3: 0x0D00xxxx).
const MCM8: u64 = 0xFE40_00AC;
const MR6C: u64 = 0xFED2_A3A6;
const HOME: u64 = 0x0D00_0005;
const PY_DEVICES: [&str; 3] = [
    "20:0xFE4000AC:WBMCM8",
    "241:0xFED2A3A6:WBMR6C",
    "5:0x0D000005:HOMEMADE",
];

static BUSY: Mutex<bool> = Mutex::new(false);
static FREE: Condvar = Condvar::new();

/// This test's turn on the machine: the tests run one at a time (see the module docs).
struct Turn;

fn one_at_a_time() -> Turn {
    let mut busy = BUSY.lock().unwrap_or_else(|e| e.into_inner());
    while *busy {
        busy = FREE.wait(busy).unwrap_or_else(|e| e.into_inner());
    }
    *busy = true;
    Turn
}

impl Drop for Turn {
    fn drop(&mut self) {
        *BUSY.lock().unwrap_or_else(|e| e.into_inner()) = false;
        FREE.notify_one();
    }
}

fn interop(file: &str) -> PathBuf {
    repo("tests/interop").join(file)
}

/// Python with pyserial, and socat: fail loudly when missing.
fn require_tools() {
    let python = Command::new(PYTHON)
        .args(["-c", "import serial"])
        .output()
        .unwrap_or_else(|e| {
            panic!("{PYTHON} is needed for the interop tests (apt-get install python3): {e}")
        });
    assert!(
        python.status.success(),
        "pyserial is needed for the interop tests (apt-get install python3-serial): {}",
        String::from_utf8_lossy(&python.stderr)
    );
    let socat = Command::new("socat").arg("-V").output();
    assert!(
        matches!(&socat, Ok(out) if out.status.success()),
        "socat is needed for the interop tests (apt-get install socat): {socat:?}"
    );
}

/// Waits for `check` to say yes, or fails naming `what`.
fn wait_until<T>(what: &str, timeout: Duration, mut check: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(found) = check() {
            return found;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        // A condition poll: each round asks again; the pause only paces it.
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Two ptys joined like a cable; killed on drop.
struct Socat {
    child: Child,
    a: PathBuf,
    b: PathBuf,
    _dir: tempfile::TempDir,
}

impl Socat {
    fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("ttyA"), dir.path().join("ttyB"));
        let mut child = Command::new("socat")
            .stop_with_parent()
            .arg("-d")
            .arg("-d")
            .arg(format!("pty,raw,echo=0,link={}", a.display()))
            .arg(format!("pty,raw,echo=0,link={}", b.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("socat.log")).unwrap())
            .spawn()
            .expect("socat");
        let started = Instant::now();
        while !(a.exists() && b.exists()) {
            if let Ok(Some(status)) = child.try_wait() {
                panic!("socat exited: {status}");
            }
            assert!(started.elapsed() < WAIT, "socat made no ptys");
            std::thread::sleep(Duration::from_millis(5));
        }
        Self {
            child,
            a,
            b,
            _dir: dir,
        }
    }
}

impl Drop for Socat {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A Python process speaking JSON lines: commands on stdin, replies and log lines on stdout.
struct PyProcess {
    child: Child,
    stdin: ChildStdin,
    lines: Arc<Mutex<Vec<Value>>>,
    next_id: u64,
    name: &'static str,
}

impl PyProcess {
    fn start(name: &'static str, script: &str, args: &[&str]) -> Self {
        let mut child = Command::new(PYTHON)
            .stop_with_parent()
            .arg(interop(script))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("{PYTHON} {script}: {e}"));
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = lines.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let value = serde_json::from_str(&line).unwrap_or(json!({ "raw": line }));
                sink.lock().unwrap_or_else(|e| e.into_inner()).push(value);
            }
        });
        let process = Self {
            child,
            stdin,
            lines,
            next_id: 1,
            name,
        };
        process.wait_line("its ready line", 0, |l| l.get("ready").is_some());
        process
    }

    fn lines(&self) -> std::sync::MutexGuard<'_, Vec<Value>> {
        self.lines.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn len(&self) -> usize {
        self.lines().len()
    }

    /// The first line from index `from` on that matches; fails after `WAIT` with the tail.
    fn wait_line(
        &self,
        what: &str,
        from: usize,
        matches: impl Fn(&Value) -> bool,
    ) -> (usize, Value) {
        self.wait_line_within(what, from, WAIT, matches)
    }

    fn wait_line_within(
        &self,
        what: &str,
        from: usize,
        timeout: Duration,
        matches: impl Fn(&Value) -> bool,
    ) -> (usize, Value) {
        let deadline = Instant::now() + timeout;
        loop {
            let expired = Instant::now() >= deadline;
            let tail: Vec<String> = {
                let lines = self.lines();
                if let Some((i, line)) = lines
                    .iter()
                    .enumerate()
                    .skip(from)
                    .find(|(_, l)| matches(l))
                {
                    return (i, line.clone());
                }
                if !expired {
                    Vec::new()
                } else {
                    lines.iter().rev().take(40).map(Value::to_string).collect()
                }
            };
            // (the lock is released: a panic here poisons nothing)
            assert!(
                !expired,
                "{}: no {what} within {timeout:?}; its last lines (newest first):\n{}",
                self.name,
                tail.join("\n")
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Lines from index `from` on that match.
    fn lines_from(&self, from: usize, matches: impl Fn(&Value) -> bool) -> Vec<Value> {
        self.lines
            .lock()
            .unwrap()
            .iter()
            .skip(from)
            .filter(|l| matches(l))
            .cloned()
            .collect()
    }

    /// Sends a command, returns its reply (asserted ok).
    fn cmd(&mut self, mut command: Value) -> Value {
        self.cmd_within(&mut command, WAIT)
    }

    fn cmd_within(&mut self, command: &mut Value, timeout: Duration) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        command["id"] = json!(id);
        writeln!(self.stdin, "{command}").unwrap();
        self.stdin.flush().unwrap();
        let (_, reply) = self.wait_line_within(&format!("reply to {command}"), 0, timeout, |l| {
            l["id"] == json!(id) && l.get("ok").is_some()
        });
        assert_eq!(
            reply["ok"],
            json!(true),
            "{}: {command} → {reply}",
            self.name
        );
        reply
    }
}

impl Drop for PyProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if std::thread::panicking() {
            let lines = self.lines();
            let tail: Vec<String> = lines.iter().rev().take(60).map(Value::to_string).collect();
            eprintln!(
                "--- {} (last lines, newest first) ---\n{}",
                self.name,
                tail.join("\n")
            );
        }
    }
}

/// The Python bus: devices 20, 241 and 5. Device 5 is old firmware (replies under 0x60) and
/// its holding 4 cannot send events; device 20's event_count counts every event it holds;
/// device 241 sends its u32 at input 7..8 as one wide event at 7.
fn py_bus(port: &Path, line: &str) -> PyProcess {
    let port = port.to_str().unwrap();
    let mut args = vec!["--port", port, "--line", line];
    for device in PY_DEVICES {
        args.extend(["--device", device]);
    }
    args.extend([
        "--legacy-code",
        "5",
        "--no-events",
        "5:holding:4",
        "--count-pending",
        "20",
    ]);
    args.extend(["--wide", "241:input:7:2", "--realtime"]);
    PyProcess::start("fast_device.py", "fast_device.py", &args)
}

fn is_log(line: &Value, kind: &str, address: u64) -> bool {
    line["log"] == kind && line["address"] == json!(address)
}

/// A 0x18 request the device took: the registers it enabled, as [type, register].
fn enabled_in(config_line: &Value) -> Vec<(String, u64)> {
    let mut enabled = Vec::new();
    for (range, mask) in config_line["ranges"]
        .as_array()
        .unwrap()
        .iter()
        .zip(config_line["masks"].as_array().unwrap())
    {
        let start = range[1].as_u64().unwrap();
        for (i, _) in range[2].as_array().unwrap().iter().enumerate() {
            let byte = mask[i / 8].as_u64().unwrap();
            if byte >> (i % 8) & 1 == 1 {
                enabled.push((range[0].as_str().unwrap().to_owned(), start + i as u64));
            }
        }
    }
    enabled
}

#[test]
fn peers_reproduce_the_documents_vectors_and_arbitration_table() {
    require_tools();
    let out = Command::new(PYTHON)
        .arg(interop("fastmodbus_common.py"))
        .arg(repo("tests/data/vectors.json"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let vectors: Value =
        serde_json::from_str(&std::fs::read_to_string(repo("tests/data/vectors.json")).unwrap())
            .unwrap();
    // Every vector, the six arbitration rounds of §3, four timing figures.
    let expected = vectors["vectors"].as_array().unwrap().len() + 6 + 4;
    assert_eq!(stdout.trim(), format!("ok {expected}"));
}

// ---------------------------------------------------------------------------------------------
// The daemon against the Python devices

const TEMPLATE: &str = r#"{
    "device_type": "interop-fast-io",
    "title": "Interop Fast Modbus I/O (Python peer)",
    "device": {
        "name": "Interop IO",
        "id": "interop",
        "channels": [
            {"name": "Input 0", "reg_type": "discrete", "address": 0, "type": "switch", "sporadic": true},
            {"name": "Input 1", "reg_type": "discrete", "address": 1, "type": "switch", "sporadic": true},
            {"name": "Relay 0", "reg_type": "coil", "address": 0, "type": "switch", "sporadic": true},
            {"name": "Relay 1", "reg_type": "coil", "address": 1, "type": "switch"},
            {"name": "Setpoint", "reg_type": "holding", "address": 3, "type": "range", "max": 65535},
            {"name": "Level", "reg_type": "holding", "address": 4, "type": "value", "sporadic": true},
            {"name": "Counter", "reg_type": "input", "address": 5, "type": "value", "semi-sporadic": true},
            {"name": "Temperature", "reg_type": "input", "address": 6, "type": "value", "format": "s16", "scale": 0.1},
            {"name": "Energy", "reg_type": "input", "address": 7, "type": "value", "format": "u32", "sporadic": true}
        ]
    }
}"#;

/// Device 20's template: the channels above and 50 sporadic holding registers 10..59
/// ("H10".."H59"), 300 bytes of events when all change: more than one 0x11 packet holds
/// (max_data_len 248). (Only on one device: mosquitto queues at most 1000 messages for a
/// subscriber, and the retained state is read by one.)
fn wide_template() -> Value {
    let mut template: Value = serde_json::from_str(TEMPLATE).unwrap();
    template["device_type"] = json!("interop-fast-io-wide");
    let channels = template["device"]["channels"].as_array_mut().unwrap();
    for register in 10..60 {
        channels.push(
            json!({"name": format!("H{register}"), "reg_type": "holding", "address": register,
                             "type": "value", "sporadic": true}),
        );
    }
    template
}

fn topic(address: u64, control: &str) -> String {
    format!("/devices/interop_{address}/controls/{control}")
}

/// Initial values per device address: (type, register, raw value, the exact MQTT payload).
fn initial_values(address: u64) -> Vec<(&'static str, u64, u64, String, &'static str)> {
    vec![
        (
            "holding",
            3,
            1000 + address,
            format!("{}", 1000 + address),
            "Setpoint",
        ),
        (
            "holding",
            4,
            40 + address,
            format!("{}", 40 + address),
            "Level",
        ),
        (
            "input",
            5,
            700 + address,
            format!("{}", 700 + address),
            "Counter",
        ),
        // -12.5 °C as s16 with scale 0.1
        ("input", 6, 0x10000 - 125, "-12.5".to_owned(), "Temperature"),
        ("discrete", 1, 1, "1".to_owned(), "Input 1"),
        ("coil", 1, 1, "1".to_owned(), "Relay 1"),
        ("discrete", 0, 0, "0".to_owned(), "Input 0"),
        ("coil", 0, 0, "0".to_owned(), "Relay 0"),
        // u32, most significant word first: 0x0001_0002
        ("input", 7, 1, "65538".to_owned(), "Energy"),
        ("input", 8, 2, "65538".to_owned(), "Energy"),
    ]
}

async fn retained_is(port: u16, topic: &str, value: &str) -> Option<()> {
    let state = retained(port).await?;
    (state.get(topic).map(String::as_str) == Some(value)).then_some(())
}

/// Waits until the broker holds every (topic, payload); on a timeout, names those it does not.
async fn wait_state(port: u16, what: &str, expected: &[(String, String)]) {
    let deadline = Instant::now() + mqtt_support::TIMEOUT;
    loop {
        let state = retained(port).await.unwrap_or_default();
        let wrong: Vec<String> = expected
            .iter()
            .filter(|(t, v)| state.get(t) != Some(v))
            .map(|(t, v)| format!("{t}: {:?}, expected {v:?}", state.get(t)))
            .collect();
        if wrong.is_empty() {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}:\n{}",
            wrong.join("\n")
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

async fn wait_value(port: u16, address: u64, control: &str, value: &str) {
    let t = topic(address, control);
    wait_for(&format!("{t} = {value}"), || retained_is(port, &t, value)).await;
}

/// One toggle on the device → the event reaches MQTT; the device saw the 0x10 that got the
/// packet and the 0x10 after it confirming it (address and flag).
async fn toggle_arrives_by_event(
    bus: &mut PyProcess,
    broker: u16,
    address: u64,
    kind: &str,
    register: u64,
    control: &str,
) {
    let from = bus.len();
    let value = bus
        .cmd(json!({"cmd": "toggle", "device": address, "type": kind, "address": register}))
        ["value"]
        .clone();
    let payload = value.to_string();
    let t = topic(address, control);
    wait_for(&format!("{t} = {payload} by event"), || {
        retained_is(broker, &t, &payload)
    })
    .await;
    let (packet_at, packet) = bus.wait_line("the event packet", from, |l| {
        is_log(l, "event_packet", address)
            && l["events"]
                .as_array()
                .unwrap()
                .contains(&json!([kind, register]))
    });
    let flag = packet["flag"].as_u64().unwrap();
    let (confirmed_at, _) = bus.wait_line("its confirmation", packet_at, |l| {
        is_log(l, "confirmed", address) && l["flag"] == json!(flag)
    });
    // The 0x10 request that carried the confirmation: FD 46 10 min max <address> <flag>.
    let ack = format!("{address:02X} {flag:02X}");
    let requests = bus.lines_from(packet_at, |l| {
        l["log"] == "rx" && l["hex"].as_str().unwrap().starts_with("FD 46 10 ")
    });
    assert!(
        requests
            .iter()
            .any(|l| l["hex"].as_str().unwrap()[15..20] == ack),
        "no 0x10 with ack {ack} after the packet: {requests:?}"
    );
    assert!(confirmed_at > packet_at);
}

async fn daemon_against_python_devices(line: &str, baud: u32) {
    require_tools();
    let _one = one_at_a_time();
    let socat = Socat::start();
    let mut bus = py_bus(&socat.a, line);
    let addresses = [20u64, 241, 5];
    for address in addresses {
        for (kind, register, raw, _, _) in initial_values(address) {
            bus.cmd(json!({"cmd": "set", "device": address, "type": kind, "address": register, "value": raw}));
        }
    }
    let broker = Mosquitto::start();
    let port = broker.port;
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("interop-fast-io.json"), TEMPLATE).unwrap();
    std::fs::write(
        dir.path().join("interop-fast-io-wide.json"),
        wide_template().to_string(),
    )
    .unwrap();
    let devices: Vec<Value> = addresses
        .iter()
        .map(|&a| {
            let template = if a == 20 {
                "interop-fast-io-wide"
            } else {
                "interop-fast-io"
            };
            json!({"device_type": template, "slave_id": a})
        })
        .collect();
    let config = |devices: &[Value]| {
        json!({
            "mqtt": {"host": "127.0.0.1", "port": port, "client_id": format!("interop-fast-{baud}")},
            "fast_modbus": true,
            "ports": [{"path": socat.b, "baud_rate": baud, "parity": "N", "data_bits": 8, "stop_bits": 2,
                       "devices": devices}]
        })
    };
    let templates = dir.path().to_string_lossy().into_owned();
    let daemon = DaemonProcess::start(
        &config(&devices),
        &["--templates", &templates],
        Stdio::null(),
        Stdio::null(),
    );

    // Values published exactly.
    let expected: Vec<(String, String)> = addresses
        .iter()
        .flat_map(|&a| {
            initial_values(a)
                .into_iter()
                .map(move |(_, _, _, payload, control)| (topic(a, control), payload))
        })
        .collect();
    wait_state(port, "every initial value on MQTT", &expected).await;

    // Events enabled by 0x18 on every device, the sporadic channels among them (device 5
    // answers with holding 4's bit off).
    for address in addresses {
        let (_, setup) =
            bus.wait_line("a 0x18 request", 0, |l| is_log(l, "events_config", address));
        let enabled = enabled_in(&setup);
        for register in [
            ("discrete", 0),
            ("discrete", 1),
            ("coil", 0),
            ("holding", 4),
            ("input", 5),
        ] {
            let expected = !(address == 5 && register == ("holding", 4));
            assert_eq!(
                enabled.contains(&(register.0.to_owned(), register.1)),
                expected,
                "device {address}: {register:?} in {setup}"
            );
        }
    }

    // A toggle reaches MQTT by event, confirmed; on each device.
    toggle_arrives_by_event(&mut bus, port, 20, "discrete", 0, "Input 0").await;
    toggle_arrives_by_event(&mut bus, port, 241, "coil", 0, "Relay 0").await;
    toggle_arrives_by_event(&mut bus, port, 5, "discrete", 0, "Input 0").await;
    // Changes on two devices at once: both arbitrate, both arrive.
    bus.cmd(json!({"cmd": "set", "device": 241, "type": "holding", "address": 4, "value": 4242}));
    bus.cmd(json!({"cmd": "set", "device": 5, "type": "input", "address": 5, "value": 5555}));
    wait_for("Level of 241 and Counter of 5 by event", || async {
        let state = retained(port).await?;
        (state.get(&topic(241, "Level")).map(String::as_str) == Some("4242")
            && state.get(&topic(5, "Counter")).map(String::as_str) == Some("5555"))
        .then_some(())
    })
    .await;

    // A wide value (§6: "more for wide values"): only its low word changes, one event at its
    // first register carries the whole value, little-endian.
    let from = bus.len();
    bus.cmd(json!({"cmd": "set", "device": 241, "type": "input", "address": 8, "value": 5}));
    wait_value(port, 241, "Energy", "65541").await;
    let (_, packet) = bus.wait_line("the wide event", from, |l| is_log(l, "event_packet", 241));
    assert_eq!(packet["events"], json!([["input", 7]]), "{packet}");

    // Several changes at one instant: one packet carries them all.
    let from = bus.len();
    bus.cmd(json!({"cmd": "batch", "commands": [
        {"cmd": "set", "device": 20, "type": "coil", "address": 0, "value": 1},
        {"cmd": "set", "device": 20, "type": "holding", "address": 4, "value": 777},
        {"cmd": "set", "device": 20, "type": "discrete", "address": 1, "value": 0}]}));
    wait_for("three values of 20 from one packet", || async {
        let state = retained(port).await?;
        (state.get(&topic(20, "Relay 0")).map(String::as_str) == Some("1")
            && state.get(&topic(20, "Level")).map(String::as_str) == Some("777")
            && state.get(&topic(20, "Input 1")).map(String::as_str) == Some("0"))
        .then_some(())
    })
    .await;
    let (_, packet) = bus.wait_line("the packet of three", from, |l| {
        is_log(l, "event_packet", 20)
    });
    assert_eq!(packet["events"].as_array().unwrap().len(), 3, "{packet}");

    // A register whose bit the 0x18 reply left off is polled: its change arrives all the same.
    bus.cmd(json!({"cmd": "set", "device": 5, "type": "holding", "address": 4, "value": 4455}));
    wait_value(port, 5, "Level", "4455").await;

    // A lost confirmation: the device does not hear it, a change comes at that moment, and
    // the packet goes again under the same flag with the new event added (§6). The daemon
    // must take the new event from the repeated flag.
    let from = bus.len();
    bus.cmd(json!({"cmd": "lose_ack", "device": 20, "then_set": {"type": "holding", "address": 4, "value": 1234}}));
    bus.cmd(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 0}));
    let (lost_at, lost) =
        bus.wait_line("the lost confirmation", from, |l| is_log(l, "ack_lost", 20));
    let (again_at, again) = bus.wait_line("the packet sent again", lost_at, |l| {
        is_log(l, "event_packet", 20)
    });
    assert_eq!(again["flag"], lost["flag"], "{again}");
    assert!(
        again["events"]
            .as_array()
            .unwrap()
            .contains(&json!(["holding", 4])),
        "{again}"
    );
    bus.wait_line("the repeated packet confirmed", again_at, |l| {
        is_log(l, "confirmed", 20) && l["flag"] == lost["flag"]
    });
    wait_value(port, 20, "Level", "1234").await;
    wait_value(port, 20, "Input 0", "0").await;

    // The reboot event: the daemon confirms it, sends 0x18 again, and events work after it.
    // A rebooted device starts again at flag 0: make its last confirmed packet have flag 0
    // too, so that the reboot packet repeats the flag (§6: "A 'rebooted' event is sent
    // whatever the flag state").
    if bus.cmd(json!({"cmd": "state", "device": 241}))["next_flag"] == json!(0) {
        let from = bus.len();
        bus.cmd(json!({"cmd": "toggle", "device": 241, "type": "discrete", "address": 1}));
        bus.wait_line("one more packet of 241 confirmed", from, |l| {
            is_log(l, "confirmed", 241)
        });
    }
    assert_eq!(
        bus.cmd(json!({"cmd": "state", "device": 241}))["next_flag"],
        json!(1)
    );
    // Input 1 changes right after the reboot, before events are on again: no event can tell;
    // the daemon reads the event registers once after the reboot (§6 Reboot handling).
    let input1 = bus.cmd(json!({"cmd": "get", "device": 241, "type": "discrete", "address": 1}))
        ["value"]
        .as_u64()
        .unwrap();
    let from = bus.len();
    bus.cmd(json!({"cmd": "batch", "commands": [
        {"cmd": "reboot", "device": 241},
        {"cmd": "set", "device": 241, "type": "discrete", "address": 1, "value": 1 - input1}]}));
    let (reboot_at, reboot) = bus.wait_line("the reboot event packet", from, |l| {
        is_log(l, "event_packet", 241)
            && l["events"]
                .as_array()
                .unwrap()
                .contains(&json!(["system", 0]))
    });
    assert_eq!(reboot["flag"], json!(0), "{reboot}");
    bus.wait_line("the reboot event confirmed", reboot_at, |l| {
        is_log(l, "confirmed", 241)
    });
    let (_, again) = bus.wait_line("0x18 again after the reboot", reboot_at, |l| {
        is_log(l, "events_config", 241)
    });
    assert!(
        enabled_in(&again).contains(&("discrete".to_owned(), 0)),
        "{again}"
    );
    wait_value(port, 241, "Input 1", &(1 - input1).to_string()).await;
    toggle_arrives_by_event(&mut bus, port, 241, "discrete", 0, "Input 0").await;

    // 50 registers change at once: 300 bytes of events, more than max_data_len. The device
    // sends what fits and the rest in the next rounds; its event_count says all it holds
    // (--count-pending 20), which the daemon must not trust over data_len (§6).
    let from = bus.len();
    let values: Vec<u64> = (10..60).map(|r| 5000 + r).collect();
    bus.cmd(json!({"cmd": "set", "device": 20, "type": "holding", "address": 10, "value": values}));
    wait_for("H10..H59 of 20 by events", || async {
        let state = retained(port).await?;
        (10..60)
            .all(|r| state.get(&topic(20, &format!("H{r}"))) == Some(&(5000 + r).to_string()))
            .then_some(())
    })
    .await;
    let packets = bus.lines_from(from, |l| is_log(l, "event_packet", 20));
    let first = &packets[0];
    let carried = first["events"].as_array().unwrap().len();
    assert!(carried < 50 && carried * 6 <= 248, "{first}");
    assert_eq!(first["event_count"], json!(50), "{first}");

    // Writes from MQTT land in the device's registers.
    publish(
        port,
        &format!("{}/on", topic(20, "Setpoint")),
        "4321",
        false,
    )
    .await;
    publish(port, &format!("{}/on", topic(241, "Relay 1")), "0", false).await;
    publish(port, &format!("{}/on", topic(5, "Relay 0")), "1", false).await;
    for (address, kind, register, value) in [
        (20, "holding", 3, 4321),
        (241, "coil", 1, 0),
        (5, "coil", 0, 1),
    ] {
        wait_until(
            &format!("{kind} {register} of {address} = {value}"),
            WAIT,
            || {
                let got = bus.cmd(
                    json!({"cmd": "get", "device": address, "type": kind, "address": register}),
                );
                (got["value"] == json!(value)).then_some(())
            },
        );
    }
    wait_for("the written values on MQTT", || async {
        let state = retained(port).await?;
        (state.get(&topic(20, "Setpoint")).map(String::as_str) == Some("4321")
            && state.get(&topic(241, "Relay 1")).map(String::as_str) == Some("0")
            && state.get(&topic(5, "Relay 0")).map(String::as_str) == Some("1"))
        .then_some(())
    })
    .await;

    // The daemon restarts; the devices do not. Their next packets carry flag 0 (device 20)
    // and 1 (device 241): a new master takes the first packet of each whatever its flag.
    // The new daemon serves 20 and 241 only: device 5, unknown to it, reboots; its packet is
    // confirmed all the same (§6: only a confirmation makes a device drop its events).
    for (address, flag) in [(20u64, 0u64), (241, 1)] {
        if bus.cmd(json!({"cmd": "state", "device": address}))["next_flag"] != json!(flag) {
            let from = bus.len();
            bus.cmd(json!({"cmd": "toggle", "device": address, "type": "coil", "address": 0}));
            bus.wait_line("one more packet confirmed", from, |l| {
                is_log(l, "confirmed", address)
            });
        }
        assert_eq!(
            bus.cmd(json!({"cmd": "state", "device": address}))["next_flag"],
            json!(flag)
        );
    }
    drop(daemon);
    let from = bus.len();
    let _daemon = DaemonProcess::start(
        &config(&devices[..2]),
        &["--templates", &templates],
        Stdio::null(),
        Stdio::null(),
    );
    for address in [20, 241] {
        bus.wait_line("the new daemon's 0x18", from, |l| {
            is_log(l, "events_config", address)
        });
    }
    let from = bus.len();
    bus.cmd(json!({"cmd": "reboot", "device": 5}));
    let (at, packet) = bus.wait_line("5's reboot packet", from, |l| is_log(l, "event_packet", 5));
    bus.wait_line("5's reboot packet confirmed", at, |l| {
        is_log(l, "confirmed", 5) && l["flag"] == packet["flag"]
    });
    toggle_arrives_by_event(&mut bus, port, 20, "discrete", 0, "Input 0").await;
    toggle_arrives_by_event(&mut bus, port, 241, "discrete", 0, "Input 0").await;
    let stats = bus.cmd(json!({"cmd": "stats"}));
    eprintln!("{line}: Python device timing {stats}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_against_python_fast_devices_at_9600_8n2() {
    daemon_against_python_devices("9600 8N2", 9600).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_against_python_fast_devices_at_115200_8n2() {
    daemon_against_python_devices("115200 8N2", 115_200).await;
}

/// One Python device (address 20) with `device_args`, a broker and the daemon serving it with
/// `channels` as its template's channels, at 115200 8N2.
struct Rig {
    bus: PyProcess,
    port: u16,
    _daemon: DaemonProcess,
    _broker: Mosquitto,
    _socat: Socat,
    _dir: tempfile::TempDir,
}

impl Rig {
    fn start(device_args: &[&str], channels: Value, initial: &[(&str, u64, u64)]) -> Self {
        Self::serving(device_args, channels, initial, &[20])
    }

    /// As [`Rig::start`], the daemon serving `addresses` (the Python bus has 20 and what
    /// `device_args` adds).
    fn serving(
        device_args: &[&str],
        channels: Value,
        initial: &[(&str, u64, u64)],
        addresses: &[u8],
    ) -> Self {
        require_tools();
        let socat = Socat::start();
        let port_path = socat.a.to_str().unwrap().to_owned();
        let mut args = vec![
            "--port",
            &port_path,
            "--line",
            "115200 8N2",
            "--realtime",
            "--device",
            "20:0xFE4000AC:WBMCM8",
        ];
        args.extend_from_slice(device_args);
        let mut bus = PyProcess::start("fast_device.py", "fast_device.py", &args);
        for &(kind, register, value) in initial {
            bus.cmd(json!({"cmd": "set", "device": 20, "type": kind, "address": register, "value": value}));
        }
        let broker = Mosquitto::start();
        let dir = tempfile::tempdir().unwrap();
        // A polled channel besides: the daemon keeps a device of only sporadic channels alive
        // by reading one of them now and then, which would hide a value an event got wrong.
        let mut channels = channels;
        channels.as_array_mut().unwrap().push(
            json!({"name": "Setpoint", "reg_type": "holding", "address": 3, "type": "value"}),
        );
        let template = json!({"device_type": "interop-wide", "title": "Interop wide values",
            "device": {"name": "Interop wide", "id": "interop", "channels": channels}});
        std::fs::write(dir.path().join("interop-wide.json"), template.to_string()).unwrap();
        let config = json!({
            "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "interop-fast-wide"},
            "ports": [{"path": socat.b, "baud_rate": 115_200, "parity": "N", "data_bits": 8, "stop_bits": 2,
                       "devices": addresses.iter().map(|address| json!({"device_type": "interop-wide", "slave_id": address})).collect::<Vec<_>>()}]
        });
        let templates = dir.path().to_string_lossy().into_owned();
        let daemon = DaemonProcess::start(
            &config,
            &["--templates", &templates],
            Stdio::null(),
            Stdio::null(),
        );
        Self {
            bus,
            port: broker.port,
            _daemon: daemon,
            _broker: broker,
            _socat: socat,
            _dir: dir,
        }
    }
}

/// A device that sends a wide value whole (§6: "more for wide values"), little-endian, for a
/// u32 kept least significant word first (registers 9, 10). The payload is "the register's new
/// value": 0x0004_0006 after register 9 becomes 6. rtu2mqtt's gateway put the payload's words
/// into the registers most significant first whatever the channel's word order and published
/// 393220 (0x0006_0004) until the next read (src/gateway/device_model.rs, `registers_holding`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_publishes_the_wide_event_value_of_a_low_word_first_channel() {
    let _one = one_at_a_time();
    let mut rig = Rig::start(
        &["--wide", "20:input:9:2:little"],
        json!([{"name": "Energy LE", "reg_type": "input", "address": 9, "format": "u32",
                "word_order": "little_endian", "type": "value", "sporadic": true}]),
        &[("input", 9, 3), ("input", 10, 4)],
    );
    wait_value(rig.port, 20, "Energy LE", "262147").await;
    rig.bus
        .wait_line("the 0x18 request", 0, |l| is_log(l, "events_config", 20));
    let recorder = mqtt_support::Recorder::start(rig.port, &topic(20, "Energy LE")).await;
    let from = rig.bus.len();
    rig.bus
        .cmd(json!({"cmd": "set", "device": 20, "type": "input", "address": 9, "value": 6}));
    rig.bus
        .wait_line("the wide event", from, |l| is_log(l, "event_packet", 20));
    wait_value(rig.port, 20, "Energy LE", "262150").await;
    let seen: Vec<String> = recorder
        .messages
        .lock()
        .unwrap()
        .iter()
        .map(|(_, v, _)| v.clone())
        .collect();
    assert!(
        !seen.contains(&"393220".to_owned()),
        "a wrong value was published: {seen:?}"
    );
}

/// A device that takes 0x18 ranges of the four register tables only (§6: "<reg_type(1)>
/// <address(2, BE)> …", "Priority per register") and refuses any other type with exception 3.
/// rtu2mqtt appends wb-mqtt-serial's record for the reboot event (`0F 0000 01 00`, type 15,
/// which §6 defines for events, not for 0x18) to the event setup of a device without setup
/// writes; it took the exception as "no Fast Modbus events" and polled the device for good. Now
/// it asks again without the record (src/port/scheduler.rs, `complete_enable_events`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_gets_events_from_a_device_that_refuses_the_reboot_record() {
    let _one = one_at_a_time();
    let mut rig = Rig::start(
        &["--registers-only", "20"],
        json!([{"name": "Input 0", "reg_type": "discrete", "address": 0, "type": "switch",
                "sporadic": true}]),
        &[],
    );
    wait_value(rig.port, 20, "Input 0", "0").await;
    let from = rig.bus.len();
    rig.bus
        .cmd(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 0}));
    rig.bus.wait_line("the toggle sent by event", from, |l| {
        is_log(l, "event_packet", 20) && l["events"] == json!([["discrete", 0]])
    });
    wait_value(rig.port, 20, "Input 0", "1").await;
}

/// A device that reads nothing of a 0x10 request excluding it (the other reading of §3's
/// `min_address`) never heard its confirmation: rtu2mqtt confirms a packet in the request that
/// rotates past the sender, so such a device sent the same packet again in every round (87
/// times in 8 s in an audit). After one packet sent again, it is confirmed in view.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_confirms_a_device_that_reads_no_request_excluding_it() {
    let _one = one_at_a_time();
    let mut rig = Rig::serving(
        &[
            "--device",
            "21:0x0D000015:HOMEMADE",
            "--deaf-when-excluded",
            "20",
        ],
        json!([{"name": "Input 0", "reg_type": "discrete", "address": 0, "type": "switch",
                "sporadic": true}]),
        &[],
        &[20, 21],
    );
    wait_value(rig.port, 20, "Input 0", "0").await;
    wait_value(rig.port, 21, "Input 0", "0").await;
    let from = rig.bus.len();
    rig.bus
        .cmd(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 0}));
    let (confirmed, _) = rig
        .bus
        .wait_line("device 20's packet confirmed", from, |l| {
            is_log(l, "confirmed", 20)
        });
    let sent = rig.bus.lines()[from..confirmed]
        .iter()
        .filter(|l| is_log(l, "event_packet", 20))
        .count();
    assert!(
        (1..=2).contains(&sent),
        "{sent} packets before the confirmation was heard"
    );
    wait_value(rig.port, 20, "Input 0", "1").await;
}

/// Old firmware refuses 0x18 under its own code (`E0 01`, §2: accept both codes in replies):
/// rtu2mqtt took that for no answer, asked three times more, marked the device offline, then
/// polled it. The refusal is taken at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_takes_a_refusal_of_events_under_the_legacy_code() {
    let _one = one_at_a_time();
    let rig = Rig::start(
        &["--legacy-code", "20", "--refuses-events", "20"],
        json!([{"name": "Input 0", "reg_type": "discrete", "address": 0, "type": "switch",
                "sporadic": true}]),
        &[],
    );
    wait_value(rig.port, 20, "Input 0", "0").await;
    let refused = rig.bus.lines_from(0, |l| is_log(l, "events_refused", 20));
    assert_eq!(refused.len(), 1, "{refused:?}");
    let refusals_sent = rig.bus.lines_from(0, |l| {
        l["log"] == "tx" && l["hex"].as_str().is_some_and(|h| h.starts_with("14 E0 01"))
    });
    assert_eq!(refusals_sent.len(), 1, "{refusals_sent:?}");
}

// ---------------------------------------------------------------------------------------------
// Site tools against the Python devices

/// A child killed when dropped.
struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The site tools' line settings at `baud` 8N2, with a `--latency` generous for a loaded test
/// machine, where the Python devices' real-time pacing can answer some ms late (values are
/// asserted, never timings).
fn line_args(baud: &str) -> [&str; 8] {
    [
        "--baud",
        baud,
        "--parity",
        "N",
        "--stop-bits",
        "2",
        "--latency",
        "50",
    ]
}

fn site_tools_against_python_devices(line: &str, baud: &str) {
    require_tools();
    let _one = one_at_a_time();
    let socat = Socat::start();
    let mut bus = py_bus(&socat.a, line);
    let port = socat.b.to_str().unwrap();
    let settings = line_args(baud);

    let mut args = vec!["scan", "--port", port, "--json"];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let report: Value =
        serde_json::from_str(&run.stdout).unwrap_or_else(|e| panic!("{e}: {}", run.stdout));
    let mut found: Vec<(u64, u64, String)> = report["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["serial"].as_u64().unwrap(),
                d["address"].as_u64().unwrap(),
                d["settings"].as_str().unwrap_or_default().to_owned(),
            )
        })
        .collect();
    found.sort();
    assert_eq!(
        found,
        vec![
            (HOME, 5, line.to_owned()),
            (MCM8, 20, line.to_owned()),
            (MR6C, 241, line.to_owned())
        ],
        "{report}"
    );
    // The model each device reports (holding 200..219), read by the scan.
    for (serial, model) in [(MCM8, "WBMCM8"), (MR6C, "WBMR6C"), (HOME, "HOMEMADE")] {
        let device = report["devices"]
            .as_array()
            .unwrap()
            .iter()
            .find(|d| d["serial"] == json!(serial))
            .unwrap();
        assert_eq!(device["model"], model, "{device}");
    }
    // The scan ran the devices' arbitration: 0x01, 0x02 until end of scan (under 0x60 when
    // device 5, old firmware, wins it).
    let scans = bus.lines_from(0, |l| {
        let hex = l["hex"].as_str().unwrap_or_default();
        l["log"] == "tx" && (hex.contains("FD 46 04") || hex.contains("FD 60 04"))
    });
    assert!(!scans.is_empty(), "no end of scan sent");

    // read / write by serial number.
    bus.cmd(json!({"cmd": "set", "device": 5, "type": "holding", "address": 7, "value": 31337}));
    let mut args = vec![
        "read",
        "--port",
        port,
        "--serial",
        "0x0D000005",
        "--type",
        "holding",
        "--reg",
        "7",
        "--json",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("31337"), "{}", run.stdout);
    let from = bus.len();
    let mut args = vec![
        "write",
        "--port",
        port,
        "--serial",
        "0xFE4000AC",
        "--type",
        "holding",
        "--reg",
        "9",
        "2024",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let got = bus.cmd(json!({"cmd": "get", "device": 20, "type": "holding", "address": 9}));
    assert_eq!(got["value"], json!(2024));
    // It went by serial (0x08), not by address.
    let by_serial = bus.lines_from(from, |l| {
        l["log"] == "rx"
            && l["hex"]
                .as_str()
                .unwrap()
                .starts_with("FD 46 08 FE 40 00 AC 06")
    });
    assert!(!by_serial.is_empty(), "the write did not go by serial");
    let mut args = vec![
        "write",
        "--port",
        port,
        "--serial",
        "0xFED2A3A6",
        "--type",
        "coil",
        "--reg",
        "2",
        "on",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let got = bus.cmd(json!({"cmd": "get", "device": 241, "type": "coil", "address": 2}));
    assert_eq!(got["value"], json!(1));
    // Two registers at once (0x10 inside 0x08), to the old-firmware device (0x09 under 0x60).
    let mut args = vec![
        "write",
        "--port",
        port,
        "--serial",
        "0x0D000005",
        "--type",
        "holding",
        "--reg",
        "7",
        "11",
        "12",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let got = bus.cmd(json!({"cmd": "get", "device": 5, "type": "holding", "address": 8}));
    assert_eq!(got["value"], json!(12));
    // An exception inside 0x09: a register the device does not have.
    let mut args = vec![
        "read",
        "--port",
        port,
        "--serial",
        "0xFE4000AC",
        "--type",
        "holding",
        "--reg",
        "150",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_ne!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("exception 2"),
        "{}{}",
        run.stdout,
        run.stderr
    );

    // events: enables by 0x18, shows the events as they come, confirms them.
    let mut args = vec![
        "events",
        "--port",
        port,
        "--enable",
        "20:discrete:0",
        "--enable",
        "5:coil:0:low",
        "--count",
        "2",
        "--duration",
        "20",
        "--json",
    ];
    args.extend(settings);
    let from = bus.len();
    let mut events = KillOnDrop(
        Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
            .stop_with_parent()
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    bus.wait_line("the events tool's 0x18 to 20", from, |l| {
        is_log(l, "events_config", 20)
    });
    bus.wait_line("the events tool's 0x18 to 5", from, |l| {
        is_log(l, "events_config", 5)
    });
    bus.cmd(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 0}));
    bus.cmd(json!({"cmd": "toggle", "device": 5, "type": "coil", "address": 0}));
    let status = wait_until("the events tool to end", WAIT, || {
        events.0.try_wait().unwrap()
    });
    let (mut output, mut err) = (String::new(), String::new());
    std::io::Read::read_to_string(events.0.stdout.as_mut().unwrap(), &mut output).unwrap();
    std::io::Read::read_to_string(events.0.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(status.success(), "the events tool failed ({status}): {err}");
    let shown: Vec<Value> = output
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|l| l.get("value").is_some() && l["reboot"] == json!(false))
        .map(|l| json!([l["address"], l["type"], l["register"], l["value"]]))
        .collect();
    assert!(shown.contains(&json!([20, "discrete", 0, 1])), "{output}");
    assert!(shown.contains(&json!([5, "coil", 0, 1])), "{output}");
    bus.wait_line("20's packet confirmed", from, |l| {
        is_log(l, "confirmed", 20)
    });
    bus.wait_line("5's packet confirmed", from, |l| is_log(l, "confirmed", 5));

    // set-address by serial: the device takes its new address (register 128 via 0x08).
    let mut args = vec![
        "set-address",
        "--port",
        port,
        "--serial",
        "0x0D000005",
        "--address",
        "7",
    ];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let state = bus.cmd(json!({"cmd": "state", "device": {"serial": HOME}}));
    assert_eq!(state["address"], json!(7), "{state}");
}

/// Two devices share address 20: `fix-addresses --apply` finds them by scan and gives one a
/// free address by serial number, verified by a new scan.
#[test]
fn fix_addresses_separates_python_devices_that_share_an_address() {
    require_tools();
    let _one = one_at_a_time();
    let socat = Socat::start();
    let port = socat.a.to_str().unwrap();
    let mut bus = PyProcess::start(
        "fast_device.py",
        "fast_device.py",
        &[
            "--port",
            port,
            "--line",
            "115200 8N2",
            "--realtime",
            "--device",
            "20:0xFE4000AC:WBMCM8",
            "--device",
            "20:0xFED2A3A6:WBMR6C",
        ],
    );
    let port = socat.b.to_str().unwrap();
    let settings = line_args("115200");
    let mut args = vec!["fix-addresses", "--port", port, "--apply"];
    args.extend(settings);
    let run = tool(&args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let a = bus.cmd(json!({"cmd": "state", "device": {"serial": MCM8}}))["address"].clone();
    let b = bus.cmd(json!({"cmd": "state", "device": {"serial": MR6C}}))["address"].clone();
    assert_ne!(a, b, "{}", run.stdout);
    assert!(a == json!(20) || b == json!(20), "one keeps 20: {a} {b}");
}

#[test]
fn site_tools_find_and_use_python_fast_devices_at_9600_8n2() {
    site_tools_against_python_devices("9600 8N2", "9600");
}

#[test]
fn site_tools_find_and_use_python_fast_devices_at_115200_8n2() {
    site_tools_against_python_devices("115200 8N2", "115200");
}

// ---------------------------------------------------------------------------------------------
// The Python master against the simulator

/// A meter for the simulator: two sporadic u32 values, one kept most significant word first
/// (input 7..8), one least significant word first (input 9..10).
const METER_TEMPLATE: &str = r#"{"device_type": "interop-meter", "device": {"name": "Meter", "channels": [
    {"name": "Energy", "reg_type": "input", "address": 7, "format": "u32", "type": "value", "sporadic": true},
    {"name": "Energy LE", "reg_type": "input", "address": 9, "format": "u32", "word_order": "little_endian",
     "type": "value", "sporadic": true}
]}}"#;

const METER: u64 = 0x0D00_0030;

fn sim_bus(dir: &Path, line: &str) -> PathBuf {
    let relay = sim_support::data("relay.json");
    let meter = dir.join("meter.json");
    std::fs::write(&meter, METER_TEMPLATE).unwrap();
    let bus = json!({"devices": [
        {"name": "relay", "template": relay, "address": 241, "serial": "0xFED2A3A6", "line": line,
         "values": {"input:123": 3300, "coil:1": 1}},
        {"name": "counter", "template": relay, "address": 20, "serial": "0xFE4000AC", "line": line,
         "values": {"input:32": 4711}},
        {"name": "plain", "address": 5, "serial": "0x0D000005", "line": line, "model": "PLAIN",
         "registers": [{"type": "discrete", "address": 0, "count": 4, "events": true},
                       {"type": "holding", "address": 0, "count": 4, "events": true}],
         "values": {"holding:0": [11, 22, 33, 44]}},
        {"name": "meter", "template": meter, "address": 30, "serial": "0x0D000030", "line": line,
         "values": {"input:7": [1, 2], "input:9": [3, 4]}}
    ]});
    let path = dir.join("bus.json");
    std::fs::write(&path, bus.to_string()).unwrap();
    path
}

fn events_of(reply: &Value) -> Vec<(u64, String, u64, Value)> {
    reply["events"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["address"].as_u64().unwrap(),
                e["type"].as_str().unwrap().to_owned(),
                e["id"].as_u64().unwrap(),
                e["value"].clone(),
            )
        })
        .collect()
}

fn sim_device(list: &Value, address: u64) -> &Value {
    list["devices"]
        .as_array()
        .unwrap()
        .iter()
        .find(|d| d["address"] == json!(address))
        .unwrap()
}

/// §3: the number of windows with a 0xFF (some contender still in sends a 0 bit) and the
/// winning word.
fn arbitration(words: &[u64], bits: u32) -> (u64, u64) {
    let mut active = words.to_vec();
    let mut filled = 0;
    for k in (0..bits).rev() {
        let zeros: Vec<u64> = active
            .iter()
            .copied()
            .filter(|w| (w >> k) & 1 == 0)
            .collect();
        if !zeros.is_empty() {
            filled += 1;
            active = zeros;
        }
    }
    (filled, active[0])
}

/// A whole scan of these serials (§4): the winners in order with their 0xFF count, and the
/// 0xFF count before "end of scan".
fn expected_scan(serials: &[u64]) -> (Vec<(u64, u64)>, u64) {
    let mut scanned = Vec::new();
    let mut order = Vec::new();
    loop {
        let words: Vec<u64> = serials
            .iter()
            .map(|s| {
                (if scanned.contains(s) {
                    0b1111u64
                } else {
                    0b0110
                }) << 28
                    | (s & 0x0FFF_FFFF)
            })
            .collect();
        let (fillers, word) = arbitration(&words, 32);
        let winner = serials[words.iter().position(|w| *w == word).unwrap()];
        if scanned.contains(&winner) {
            return (order, fillers);
        }
        scanned.push(winner);
        order.push((winner, fillers));
    }
}

fn python_master_against_sim(line: &str) {
    require_tools();
    let _one = one_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let bus = sim_bus(dir.path(), line);
    let sim = SimProcess::start_with(&bus, &sim_support::data(""), &[]);
    let pty = sim.pty.to_str().unwrap().to_owned();
    let mut master = PyProcess::start(
        "fast_master.py",
        "fast_master.py",
        &["--port", &pty, "--line", line, "session"],
    );

    // Scan: exactly the three devices, with their addresses.
    let scan = master.cmd(json!({"cmd": "scan"}));
    let mut found: Vec<(u64, u64)> = scan["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["serial"].as_u64().unwrap(),
                d["address"].as_u64().unwrap(),
            )
        })
        .collect();
    found.sort();
    assert_eq!(
        found,
        vec![(HOME, 5), (METER, 30), (MCM8, 20), (MR6C, 241)],
        "{scan}"
    );
    // The arbitration as §3 has it: order of the winners and the 0xFF bytes before each reply.
    let (order, end_fillers) = expected_scan(&[MR6C, MCM8, HOME, METER]);
    let seen: Vec<(u64, u64)> = scan["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["serial"].as_u64().unwrap(),
                d["fillers"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(seen, order, "{scan}");
    assert_eq!(scan["end_fillers"], json!(end_fillers), "{scan}");
    assert_eq!(scan["functions"], json!([0x46]), "{scan}");
    // The deprecated 0x60 scan: answered under 0x60 with the legacy timing, same arbitration.
    let legacy = master.cmd(json!({"cmd": "scan", "legacy": true}));
    let seen: Vec<(u64, u64)> = legacy["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["serial"].as_u64().unwrap(),
                d["fillers"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(seen, order, "{legacy}");
    assert_eq!(legacy["functions"], json!([0x60]), "{legacy}");

    // Read by serial: what the bus file says.
    let read = |master: &mut PyProcess, serial: u64, kind: &str, reg: u64, count: u64| {
        master
            .cmd(json!({"cmd": "read", "serial": serial, "type": kind, "reg": reg, "count": count}))
            ["values"]
            .clone()
    };
    assert_eq!(read(&mut master, MR6C, "input", 123, 1), json!([3300]));
    assert_eq!(read(&mut master, MR6C, "coil", 0, 2), json!([0, 1]));
    assert_eq!(read(&mut master, MCM8, "input", 32, 1), json!([4711]));
    assert_eq!(
        read(&mut master, HOME, "holding", 0, 4),
        json!([11, 22, 33, 44])
    );
    let model: Vec<u64> = read(&mut master, HOME, "holding", 200, 5)
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    assert_eq!(model, "PLAIN".bytes().map(u64::from).collect::<Vec<_>>());
    let serial = read(&mut master, MCM8, "holding", 270, 2);
    assert_eq!(serial, json!([MCM8 >> 16, MCM8 & 0xFFFF]));
    // An exception travels inside 0x09 (§2): a register the device does not have.
    assert_eq!(
        read(&mut master, HOME, "holding", 150, 1),
        json!({"exception": 2})
    );

    // Every device reports its start-up (the reboot event); polling confirms them all.
    let idle = master.cmd_within(
        &mut json!({"cmd": "poll", "until_idle": true, "timeout_s": 20}),
        Duration::from_secs(30),
    );
    assert_eq!(idle["idle"], json!(true), "{idle}");
    let mut rebooted: Vec<u64> = events_of(&idle)
        .into_iter()
        .filter(|(_, kind, id, _)| kind == "system" && *id == 0)
        .map(|(address, ..)| address)
        .collect();
    rebooted.sort();
    rebooted.dedup();
    assert_eq!(rebooted, vec![5, 20, 30, 241], "{idle}");

    // Enable events: masks as the bus's registers allow (coil 3 of the relay has none).
    let enabled = master.cmd(json!({"cmd": "enable", "address": 241, "ranges": [
        {"type": "coil", "reg": 0, "priorities": [2, 2, 2, 2]},
        {"type": "discrete", "reg": 0, "priorities": [1, 1]}]}));
    assert_eq!(enabled["masks"], json!([[0b0111], [0b11]]), "{enabled}");
    let enabled = master.cmd(json!({"cmd": "enable", "address": 20, "ranges": [
        {"type": "discrete", "reg": 0, "priorities": [1]}]}));
    assert_eq!(enabled["masks"], json!([[1]]), "{enabled}");
    let enabled = master.cmd(json!({"cmd": "enable", "address": 5, "ranges": [
        {"type": "discrete", "reg": 0, "priorities": [1, 0, 1]},
        {"type": "holding", "reg": 2, "priorities": [2]}]}));
    assert_eq!(enabled["masks"], json!([[0b101], [1]]), "{enabled}");
    // Registers with events on, as the simulator counts them: coils 0..2 and inputs 0..1.
    let list = sim.control(json!({"cmd": "list"}));
    assert_eq!(sim_device(&list, 241)["events_enabled"], json!(5), "{list}");
    assert_eq!(sim_device(&list, 5)["events_enabled"], json!(3), "{list}");

    // A toggle comes back as an event, and is confirmed (nothing pending on the device after).
    let poll = |master: &mut PyProcess, until: Value| {
        let reply = master.cmd_within(
            &mut json!({"cmd": "poll", "until": until, "timeout_s": 20}),
            Duration::from_secs(30),
        );
        assert_eq!(reply["matched"], json!(true), "{reply}");
        assert_eq!(reply["idle"], json!(true), "{reply}");
        reply
    };
    sim.control(json!({"cmd": "toggle", "device": 241, "type": "discrete", "address": 0}));
    let got = poll(
        &mut master,
        json!({"address": 241, "type": "discrete", "id": 0, "value": 1}),
    );
    assert!(
        events_of(&got).contains(&(241, "discrete".into(), 0, json!(1))),
        "{got}"
    );
    let list = sim.control(json!({"cmd": "list"}));
    assert_eq!(sim_device(&list, 241)["pending_events"], json!(0), "{list}");

    // Changes on three devices at once, one at high priority: all arrive.
    sim.control(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 0}));
    sim.control(json!({"cmd": "set", "device": 5, "type": "holding", "address": 2, "value": 999}));
    sim.control(json!({"cmd": "toggle", "device": 241, "type": "coil", "address": 2}));
    let got = poll(
        &mut master,
        json!({"address": 5, "type": "holding", "id": 2, "value": 999}),
    );
    let mut all = events_of(&got);
    if !all.contains(&(20, "discrete".into(), 0, json!(1)))
        || !all.contains(&(241, "coil".into(), 2, json!(1)))
    {
        all.extend(events_of(&poll(&mut master, json!({"address": 20}))));
    }
    for expected in [
        (20, "discrete", 0, 1),
        (5, "holding", 2, 999),
        (241, "coil", 2, 1),
    ] {
        let expected = (
            expected.0,
            expected.1.to_owned(),
            expected.2,
            json!(expected.3),
        );
        assert!(all.contains(&expected), "{expected:?} missing from {all:?}");
    }
    let list = sim.control(json!({"cmd": "list"}));
    for address in [5, 20, 30, 241] {
        assert_eq!(
            sim_device(&list, address)["pending_events"],
            json!(0),
            "{list}"
        );
    }

    // max_data_len (§6): "If the events do not fit max_data_len, the device sends what fits
    // and keeps the rest for the next round; if not even one fits, it sends the count with
    // no payload." Two 1-byte events (5 bytes each) of device 5; nothing else pending.
    sim.control(json!({"cmd": "toggle", "device": 5, "type": "discrete", "address": 0}));
    sim.control(json!({"cmd": "toggle", "device": 5, "type": "discrete", "address": 2}));
    let once = |master: &mut PyProcess, args: Value| {
        let mut command = json!({"cmd": "poll_once", "min_address": 0});
        for (k, v) in args.as_object().unwrap() {
            command[k] = v.clone();
        }
        master.cmd(command)
    };
    let none_fit = once(&mut master, json!({"max_len": 4}));
    assert_eq!(none_fit["reply"], "events", "{none_fit}");
    assert_eq!(none_fit["address"], json!(5), "{none_fit}");
    assert_eq!(none_fit["events"], json!([]), "{none_fit}");
    assert_eq!(
        none_fit["event_count"],
        json!(2),
        "the count of the events it holds: {none_fit}"
    );
    let one_fits = once(&mut master, json!({"max_len": 9}));
    assert_eq!(
        one_fits["events"].as_array().unwrap().len(),
        1,
        "{one_fits}"
    );
    let rest = once(&mut master, json!({}));
    let mut both: Vec<u64> = [&one_fits, &rest]
        .iter()
        .flat_map(|r| {
            r["events"]
                .as_array()
                .unwrap()
                .iter()
                .map(|e| e["id"].as_u64().unwrap())
        })
        .collect();
    both.sort();
    assert_eq!(both, vec![0, 2], "{one_fits} {rest}");
    let idle = master.cmd(json!({"cmd": "poll", "until_idle": true, "timeout_s": 10}));
    assert_eq!(idle["idle"], json!(true), "{idle}");

    // "No events": everyone arbitrates with 0b1111, the lowest address wins (§3).
    let none = once(&mut master, json!({}));
    assert_eq!(none["reply"], "none", "{none}");
    let words: Vec<u64> = [5u64, 20, 30, 241]
        .iter()
        .map(|a| 0b1111 << 8 | a)
        .collect();
    assert_eq!(none["fillers"], json!(arbitration(&words, 12).0), "{none}");
    // min_address above every device: nobody takes part, nothing comes back.
    let silence = once(&mut master, json!({"min_address": 242}));
    assert_eq!(silence["reply"], "silence", "{silence}");
    // One high-priority event (coil 0 of 241 at priority 2) against two with nothing.
    sim.control(json!({"cmd": "toggle", "device": 241, "type": "coil", "address": 0}));
    let high = once(&mut master, json!({"min_address": 0}));
    assert_eq!(high["address"], json!(241), "{high}");
    let words = [
        0b0100 << 8 | 241u64,
        0b1111 << 8 | 20,
        0b1111 << 8 | 5,
        0b1111 << 8 | 30,
    ];
    assert_eq!(high["fillers"], json!(arbitration(&words, 12).0), "{high}");
    let idle = master.cmd(json!({"cmd": "poll", "until_idle": true, "timeout_s": 10}));
    assert_eq!(idle["idle"], json!(true), "{idle}");

    // A lost confirmation: the device sends the packet again under the same flag.
    sim.control(json!({"cmd": "toggle", "device": 5, "type": "discrete", "address": 0}));
    let first = once(&mut master, json!({}));
    assert_eq!(first["address"], json!(5), "{first}");
    let again = once(&mut master, json!({"withhold_ack": true, "min_address": 0}));
    assert_eq!(again["address"], json!(5), "{again}");
    assert_eq!(again["flag"], first["flag"], "{again}");
    assert_eq!(again["events"], first["events"], "{again}");
    assert_eq!(again["duplicate"], json!(true), "{again}");
    let idle = master.cmd(json!({"cmd": "poll", "until_idle": true, "timeout_s": 10}));
    assert_eq!(idle["idle"], json!(true), "{idle}");
    let list = sim.control(json!({"cmd": "list"}));
    assert_eq!(sim_device(&list, 5)["pending_events"], json!(0), "{list}");

    // Wide values (§6: "payload = the register's new value … more for wide values", the
    // payload little-endian): the meter's u32 values come as one event each, at their first
    // register, whatever their word order (the other registers send none: bits 1 and 3 off).
    let enabled = master.cmd(json!({"cmd": "enable", "address": 30, "ranges": [
        {"type": "input", "reg": 7, "priorities": [1, 1, 1, 1]}]}));
    assert_eq!(enabled["masks"], json!([[0b0101]]), "{enabled}");
    sim.control(json!({"cmd": "set", "device": 30, "type": "input", "address": 8, "value": 5}));
    let got = poll(
        &mut master,
        json!({"address": 30, "type": "input", "id": 7}),
    );
    assert!(
        events_of(&got).contains(&(30, "input".into(), 7, json!(0x0001_0005))),
        "{got}"
    );
    // Least significant word first: registers 9, 10 = 6, 4 hold 0x0004_0006.
    sim.control(json!({"cmd": "set", "device": 30, "type": "input", "address": 9, "value": 6}));
    let got = poll(
        &mut master,
        json!({"address": 30, "type": "input", "id": 9}),
    );
    assert!(
        events_of(&got).contains(&(30, "input".into(), 9, json!(0x0004_0006))),
        "{got}"
    );

    // A reboot: the master sees the reboot event, enables the events again, and they work.
    sim.control(json!({"cmd": "reboot", "device": 241}));
    let got = poll(
        &mut master,
        json!({"address": 241, "type": "system", "id": 0}),
    );
    assert_eq!(got["reboots"][0]["address"], json!(241), "{got}");
    assert_eq!(
        got["reboots"][0]["handled"]["reenabled"]["masks"],
        json!([[0b0111], [0b11]]),
        "{got}"
    );
    let list = sim.control(json!({"cmd": "list"}));
    assert_eq!(sim_device(&list, 241)["events_enabled"], json!(5), "{list}");
    sim.control(json!({"cmd": "toggle", "device": 241, "type": "discrete", "address": 1}));
    poll(
        &mut master,
        json!({"address": 241, "type": "discrete", "id": 1, "value": 1}),
    );
}

#[test]
fn python_master_against_the_simulator_at_9600_8n2() {
    python_master_against_sim("9600 8N2");
}

#[test]
fn python_master_against_the_simulator_at_115200_8n2() {
    python_master_against_sim("115200 8N2");
}
