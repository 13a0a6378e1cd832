//! `rtu2mqtt run` with `"port_type": "modbus tcp"` against the simulator's Modbus TCP gateway
//! (`sim --modbus-tcp`): values of a Fast Modbus-capable and a classic device are published
//! (read through MBAP: unit id = slave address, no CRC), a write reaches the device, and when the
//! gateway drops the connection (the simulator is restarted on the same port) the daemon
//! reconnects and publishes what the devices hold now. Updates are read as JSON lines (`--stdio`).

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::process::{ChildStdin, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use daemon_support::{repo, DaemonProcess};
use serde_json::{json, Value};
use sim_support::SimProcess;

const BUS: &str = r#"{"devices": [
  {"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021", "line": "9600 8N2",
   "values": {"input:4": 2150, "input:5": 4530, "input:8": 600}},
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "9600 8N2"},
  {"name": "meter", "template": "rtu2mqtt-energy-meter", "address": 30, "serial": "0x0D000030", "line": "9600 8N2",
   "fast": false, "values": {"input:0": [32768, 17254]}}
]}"#;

const PATIENCE: Duration = Duration::from_secs(30);

struct Daemon {
    _process: DaemonProcess,
    stdin: ChildStdin,
    lines: Receiver<Value>,
    seen: Vec<Value>,
}

impl Daemon {
    fn start(port: u16) -> Self {
        Self::start_with(port, json!({}))
    }

    /// With `port_keys` added to the port's config.
    fn start_with(port: u16, port_keys: Value) -> Self {
        let devices = json!([
            {"device_type": "rtu2mqtt-climate", "slave_id": 21},
            {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
            {"device_type": "rtu2mqtt-energy-meter", "slave_id": 30},
        ]);
        let mut port_config = json!({
            "port_type": "modbus tcp", "address": "127.0.0.1", "port": port, "devices": devices,
        });
        if let (Some(config), Some(keys)) = (port_config.as_object_mut(), port_keys.as_object()) {
            config.extend(keys.clone());
        }
        let config = json!({"ports": [port_config]});
        let mut process =
            DaemonProcess::start(&config, &["--stdio"], Stdio::piped(), Stdio::piped());
        let stdin = process.child.stdin.take().unwrap();
        let stdout = process.child.stdout.take().unwrap();
        let (sender, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let value: Value =
                    serde_json::from_str(&line).unwrap_or_else(|_| panic!("not JSON: {line}"));
                if sender.send(value).is_err() {
                    break;
                }
            }
        });
        Self {
            _process: process,
            stdin,
            lines,
            seen: Vec::new(),
        }
    }

    /// Waits (from now on) for `device`/`control` to be published as `value`.
    fn wait_value(&mut self, device: &str, control: &str, value: &str) {
        let deadline = Instant::now() + PATIENCE;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Ok(line) = self.lines.recv_timeout(left) else {
                let tail: Vec<String> = self
                    .seen
                    .iter()
                    .rev()
                    .take(15)
                    .map(Value::to_string)
                    .collect();
                panic!(
                    "no {device}/{control} = {value} within {PATIENCE:?}; last updates (newest first):\n{}",
                    tail.join("\n")
                );
            };
            let found =
                line["device"] == device && line["control"] == control && line["value"] == value;
            self.seen.push(line);
            if found {
                return;
            }
        }
    }

    /// Waits for a value published at any time so far, or from now on.
    fn has_value(&mut self, device: &str, control: &str, value: &str) {
        self.has_value_since(0, device, control, value);
    }

    /// Waits for a value published after the first `mark` updates, or from now on.
    fn has_value_since(&mut self, mark: usize, device: &str, control: &str, value: &str) {
        let seen = self.seen.iter().skip(mark).any(|line| {
            line["device"] == device && line["control"] == control && line["value"] == value
        });
        if !seen {
            self.wait_value(device, control, value);
        }
    }

    fn write(&mut self, device: &str, control: &str, value: &str) {
        let line = json!({"device": device, "control": control, "value": value});
        writeln!(self.stdin, "{line}").unwrap();
        self.stdin.flush().unwrap();
    }
}

fn bus_file(dir: &tempfile::TempDir) -> PathBuf {
    let path = dir.path().join("bus.json");
    std::fs::write(&path, BUS).unwrap();
    path
}

fn start_sim(bus: &std::path::Path, listen: &str) -> (SimProcess, u16) {
    let sim = SimProcess::start_with(
        bus,
        &repo("templates"),
        &["--modbus-tcp", listen, "--tcp-line", "9600 8N2"],
    );
    let banner = sim
        .banner()
        .iter()
        .find(|line| line.starts_with("modbus-tcp "))
        .expect("a modbus-tcp line in the banner")
        .clone();
    let address = banner.split_whitespace().nth(1).unwrap();
    let port = address.rsplit_once(':').unwrap().1.parse().unwrap();
    (sim, port)
}

/// The simulator's change log from now on (`watch` on the control socket).
fn watch_changes(sim: &SimProcess) -> std::io::Lines<BufReader<UnixStream>> {
    let mut stream = UnixStream::connect(&sim.control).unwrap();
    stream.set_read_timeout(Some(PATIENCE)).unwrap();
    writeln!(stream, "{}", json!({"cmd": "watch"})).unwrap();
    let mut lines = BufReader::new(stream).lines();
    let reply: Value = serde_json::from_str(&lines.next().unwrap().unwrap()).unwrap();
    assert_eq!(reply["ok"], true, "{reply}");
    lines
}

#[test]
fn values_and_writes_through_a_modbus_tcp_gateway_that_drops_the_connection() {
    let dir = tempfile::tempdir().unwrap();
    let bus = bus_file(&dir);
    let (sim, port) = start_sim(&bus, "127.0.0.1:0");
    let mut daemon = Daemon::start(port);
    daemon.has_value("climate_21", "Temperature", "21.5");
    daemon.has_value("energy_meter_30", "Voltage", "230.5");
    let changes = watch_changes(&sim);
    daemon.write("relay6_20", "K2", "1");
    let written = changes
        .map(|line| serde_json::from_str::<Value>(&line.unwrap()).unwrap())
        .find(|change| {
            change["address"] == 20 && change["type"] == "coil" && change["register"] == 1
        })
        .expect("the write to K2 reaches the relay");
    assert_eq!(
        (written["value"].clone(), written["origin"].clone()),
        (json!(1), json!("master"))
    );
    daemon.wait_value("relay6_20", "K2", "1");

    // The gateway goes away (connection closed) and comes back on the same port.
    drop(sim);
    let mark = daemon.seen.len();
    let (sim, _) = start_sim(&bus, &format!("127.0.0.1:{port}"));
    sim.control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2225}));
    daemon.wait_value("climate_21", "Temperature", "22.25");
    // The restarted relay has K2 off again: the daemon reads it from the new connection.
    daemon.has_value_since(mark, "relay6_20", "K2", "0");
}

/// Behind a WB-MGE (`connected_to_mge`: Fast Modbus through the Modbus TCP gateway) an event
/// poll goes to unit 0xFD and the packet comes back under the unit of the device that sent it.
/// The relay's inputs come only by events: a toggle and its undoing must be published. Before,
/// every packet was thrown away as a reply from the wrong unit and the input stayed at its old
/// value.
#[test]
fn events_through_a_wb_mge_are_published() {
    let dir = tempfile::tempdir().unwrap();
    let bus = bus_file(&dir);
    let (sim, port) = start_sim(&bus, "127.0.0.1:0");
    let mut daemon = Daemon::start_with(port, json!({"connected_to_mge": true}));
    daemon.has_value("relay6_20", "Input 2", "0");
    daemon.has_value("climate_21", "Temperature", "21.5");
    let mark = daemon.seen.len();
    sim.control(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 1}));
    daemon.has_value_since(mark, "relay6_20", "Input 2", "1");
    sim.control(json!({"cmd": "toggle", "device": 20, "type": "discrete", "address": 1}));
    daemon.has_value_since(mark, "relay6_20", "Input 2", "0");
}
