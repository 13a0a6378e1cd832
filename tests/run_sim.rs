//! `rtu2mqtt run` against `rtu2mqtt sim` over a pseudo-terminal, with updates read as JSON lines
//! (`--stdio`, the daemon without a broker): the proof that the real processes are wired as the
//! virtual-time scenarios (`src/gateway/scenarios.rs`) assume. Values of several devices, a
//! coil change arriving by event, events re-enabled after a reboot, a write reaching the device;
//! RTU over TCP; a failed port reopened; the Wiren Board templates at 9600 8O1; no wrong value
//! when every reply comes after the timeout; a quick shutdown. Unplugged devices, slow lines
//! (1200) and classic polling are scenarios on virtual time.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{ChildStdin, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use daemon_support::{repo, DaemonProcess};
use serde_json::{json, Value};
use sim_support::SimProcess;

const BUS: &str = r#"{"devices": [
  {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "115200 8N2"},
  {"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021", "line": "115200 8N2",
   "values": {"input:4": 2150, "input:5": 4530, "input:8": 600}},
  {"name": "counter", "template": "rtu2mqtt-counter8", "address": 22, "serial": "0xFE000022", "line": "115200 8N2"},
  {"name": "meter", "template": "rtu2mqtt-energy-meter", "address": 30, "serial": "0x0D000030", "line": "115200 8N2",
   "fast": false, "values": {"input:0": [32768, 17254]}}
]}"#;

/// The daemon with `--stdio`; killed on drop.
struct Daemon {
    _process: DaemonProcess,
    stdin: ChildStdin,
    lines: Receiver<Value>,
    seen: Vec<Value>,
    /// How long a value may take to show up (longer on slow lines).
    patience: Duration,
}

impl Daemon {
    fn start(pty: &Path) -> Self {
        Self::start_on(json!({"path": pty, "baud_rate": 115200, "stop_bits": 2}))
    }

    /// `port` is the config's port object without its devices: it gets all four.
    fn start_on(mut port: Value) -> Self {
        let devices: Vec<Value> = [
            ("rtu2mqtt-relay6", 20),
            ("rtu2mqtt-climate", 21),
            ("rtu2mqtt-counter8", 22),
            ("rtu2mqtt-energy-meter", 30),
        ]
        .iter()
        .map(|(template, address)| json!({"device_type": template, "slave_id": address}))
        .collect();
        port["devices"] = Value::from(devices);
        Self::start_ports(json!([port]))
    }

    fn start_ports(ports: Value) -> Self {
        Self::start_config(json!({ "ports": ports }))
    }

    fn start_config(config: Value) -> Self {
        Self::start_config_with_env(config, &[])
    }

    fn start_config_with_env(config: Value, env: &[(&str, &str)]) -> Self {
        Self::start_config_with(config, &[], env)
    }

    /// `args`: more arguments of `run` (another `--templates` directory).
    fn start_config_with(config: Value, args: &[&str], env: &[(&str, &str)]) -> Self {
        let mut process = DaemonProcess::start_with_env(
            &config,
            &[&["--stdio"], args].concat(),
            Stdio::piped(),
            Stdio::piped(),
            env,
        );
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
            patience: Duration::from_secs(10),
        }
    }

    /// Reads updates until one matches; fails with the last ones seen.
    fn wait_for(
        &mut self,
        what: &str,
        timeout: Duration,
        matches: impl Fn(&Value) -> bool,
    ) -> Value {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    let found = matches(&line);
                    self.seen.push(line.clone());
                    if found {
                        return line;
                    }
                }
                Err(_) => {
                    let tail: Vec<String> = self
                        .seen
                        .iter()
                        .rev()
                        .take(15)
                        .map(Value::to_string)
                        .collect();
                    panic!(
                        "no {what} within {timeout:?}; last updates (newest first):\n{}",
                        tail.join("\n")
                    );
                }
            }
        }
    }

    /// A value published at any time so far, or from now on.
    fn has_value(&mut self, device: &str, control: &str, value: &str) -> Value {
        let matches = |line: &Value| {
            line["device"] == device && line["control"] == control && line["value"] == value
        };
        if let Some(line) = self.seen.iter().find(|line| matches(line)) {
            return line.clone();
        }
        self.wait_value(device, control, value)
    }

    /// A value delivered by a Fast Modbus event from now on. (Right after the daemon turned a
    /// device's events on, it reads every channel once: a change made then is published by that
    /// read first and by its event too; only the event proves that events work.)
    fn wait_event(&mut self, device: &str, control: &str, value: &str) -> Value {
        self.wait_for(
            &format!("event {device}/{control} = {value}"),
            self.patience,
            |line| {
                line["device"] == device
                    && line["control"] == control
                    && line["value"] == value
                    && line["event"] == true
            },
        )
    }

    /// A value published from now on.
    fn wait_value(&mut self, device: &str, control: &str, value: &str) -> Value {
        self.wait_for(
            &format!("{device}/{control} = {value}"),
            self.patience,
            |line| line["device"] == device && line["control"] == control && line["value"] == value,
        )
    }

    fn write(&mut self, device: &str, control: &str, value: &str) {
        writeln!(
            self.stdin,
            "{}",
            json!({"device": device, "control": control, "value": value})
        )
        .unwrap();
        self.stdin.flush().unwrap();
    }
}

fn start_sim(extra: &[&str]) -> SimProcess {
    start_sim_bus(BUS, extra)
}

fn start_sim_bus(bus_json: &str, extra: &[&str]) -> SimProcess {
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(&bus, bus_json).unwrap();
    // The bus file is read at start-up; its directory may go afterwards.
    SimProcess::start_with(&bus, &repo("templates"), extra)
}

fn start() -> (SimProcess, Daemon) {
    let sim = start_sim(&[]);
    let daemon = Daemon::start(&sim.pty);
    (sim, daemon)
}

/// The simulator's change log, from the moment of the call.
struct ChangeWatch {
    lines: std::io::Lines<BufReader<std::os::unix::net::UnixStream>>,
}

impl ChangeWatch {
    fn start(sim: &SimProcess) -> Self {
        let mut stream = std::os::unix::net::UnixStream::connect(&sim.control).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        writeln!(stream, "{}", json!({"cmd": "watch"})).unwrap();
        let mut lines = BufReader::new(stream).lines();
        let reply: Value = serde_json::from_str(&lines.next().unwrap().unwrap()).unwrap();
        assert_eq!(reply["ok"], true, "{reply}");
        Self { lines }
    }

    /// Waits (10 s at most) for a change of one register to `value`.
    fn wait_change(&mut self, address: u8, kind: &str, register: u16, value: u64) -> Value {
        loop {
            let line = self
                .lines
                .next()
                .unwrap_or_else(|| panic!("the change log closed"))
                .unwrap_or_else(|err| {
                    panic!("no change of device {address} {kind} {register} to {value}: {err}")
                });
            let change: Value = serde_json::from_str(&line).unwrap();
            if change["address"] == address
                && change["type"] == kind
                && change["register"] == register
                && change["value"] == value
            {
                return change;
            }
        }
    }
}

/// Waits until the daemon has turned the device's events on and confirmed everything it had
/// pending (the reboot event included): from then on every change travels by event.
fn wait_events_ready(sim: &SimProcess, address: u8) {
    wait_events_ready_within(sim, address, Duration::from_secs(10))
}

fn wait_events_ready_within(sim: &SimProcess, address: u8, patience: Duration) {
    let deadline = Instant::now() + patience;
    loop {
        let list = sim.control(json!({"cmd": "list"}));
        let device = list["devices"]
            .as_array()
            .unwrap()
            .iter()
            .find(|d| d["address"] == address)
            .unwrap()
            .clone();
        if device["events_enabled"].as_u64() > Some(0) && device["pending_events"] == 0 {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "events of device {address} never got ready: {device}"
        );
        // A condition poll: each round asks the simulator again; the pause only paces it.
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn values_events_writes_and_reboots() {
    let (sim, mut daemon) = start();
    // Values of every device, decoded by their templates.
    daemon.has_value("climate_21", "Temperature", "21.5");
    daemon.has_value("climate_21", "Humidity", "45.3");
    daemon.has_value("climate_21", "CO2", "600");
    daemon.has_value("energy_meter_30", "Voltage", "230.5");
    daemon.has_value("counter8_22", "Input 1", "0");
    daemon.has_value("relay6_20", "K1", "0");
    wait_events_ready(&sim, 20);

    // A coil changed on the device arrives by event (K1 is events-only once events are on).
    sim.control(json!({"cmd": "toggle", "device": 20, "type": "coil", "address": 0}));
    daemon.wait_event("relay6_20", "K1", "1");

    // A write from the MQTT side changes the device's register and the published value.
    let mut changes = ChangeWatch::start(&sim);
    daemon.write("relay6_20", "K3", "1");
    let change = changes.wait_change(20, "coil", 2, 1);
    assert_eq!(change["origin"], "master", "{change}");
    daemon.wait_value("relay6_20", "K3", "1");

    // An invalid payload writes nothing and marks the control `w`.
    daemon.write("relay6_20", "K4", "maybe");
    daemon.wait_for("K4 error w", Duration::from_secs(5), |line| {
        line["device"] == "relay6_20" && line["control"] == "K4" && line["error"] == "w"
    });
    assert_eq!(
        sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 3}))["value"],
        0
    );

    // After a reboot the device's event settings are gone; the daemon sets them up again, so a
    // change of an events-only input still arrives by event.
    sim.control(json!({"cmd": "reboot", "device": 21}));
    sim.control(json!({"cmd": "reboot", "device": 20}));
    wait_events_ready(&sim, 20);
    sim.control(json!({"cmd": "set", "device": 20, "type": "discrete", "address": 1, "value": 1}));
    daemon.wait_event("relay6_20", "Input 2", "1");
    sim.control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2275}));
    daemon.wait_value("climate_21", "Temperature", "22.75");
}

#[test]
fn rtu_over_tcp_serves_the_same_devices() {
    let sim = start_sim(&["--tcp", "127.0.0.1:0", "--tcp-line", "115200 8N2"]);
    let banner = sim
        .banner()
        .iter()
        .find(|line| line.starts_with("tcp "))
        .expect("a tcp line in the banner")
        .clone();
    let address = banner.split_whitespace().nth(1).unwrap().to_owned();
    let (host, port) = address.rsplit_once(':').unwrap();
    let mut daemon = Daemon::start_on(
        json!({"port_type": "tcp", "address": host, "port": port.parse::<u16>().unwrap()}),
    );
    daemon.has_value("climate_21", "Temperature", "21.5");
    daemon.has_value("energy_meter_30", "Voltage", "230.5");
    wait_events_ready(&sim, 20);
    sim.control(json!({"cmd": "toggle", "device": 20, "type": "coil", "address": 5}));
    daemon.wait_event("relay6_20", "K6", "1");
}

/// A bus file with one device of `BUS`.
fn one_device_bus(dir: &Path, name: &str) -> PathBuf {
    let bus: Value = serde_json::from_str(BUS).unwrap();
    let device = bus["devices"]
        .as_array()
        .unwrap()
        .iter()
        .find(|d| d["name"] == name)
        .unwrap()
        .clone();
    let path = dir.join(format!("{name}.json"));
    std::fs::write(&path, json!({ "devices": [device] }).to_string()).unwrap();
    path
}

#[test]
fn a_failed_port_is_reopened_while_the_other_port_keeps_working() {
    let dir = tempfile::tempdir().unwrap();
    let relay_bus = one_device_bus(dir.path(), "relay");
    let climate_bus = one_device_bus(dir.path(), "climate");
    let relay_sim = SimProcess::start_with(&relay_bus, &repo("templates"), &[]);
    let climate_sim = SimProcess::start_with(&climate_bus, &repo("templates"), &[]);
    // The daemon's path for the relay bus, like a /dev/serial/by-id link: re-pointed when the
    // "adapter" comes back.
    let relay_port = dir.path().join("ttyUSB-relay");
    std::os::unix::fs::symlink(&relay_sim.pty, &relay_port).unwrap();
    let mut daemon = Daemon::start_ports(json!([
        {"path": relay_port, "baud_rate": 115200, "stop_bits": 2,
         "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]},
        {"path": climate_sim.pty, "baud_rate": 115200, "stop_bits": 2,
         "devices": [{"device_type": "rtu2mqtt-climate", "slave_id": 21}]}
    ]));
    daemon.has_value("relay6_20", "K1", "0");
    daemon.has_value("climate_21", "Temperature", "21.5");

    // The relay's adapter goes away: its device is marked offline after its device timeout,
    // and the other port is served all the while.
    drop(relay_sim);
    daemon.wait_for("relay offline", Duration::from_secs(15), |line| {
        line["device"] == "relay6_20" && line["online"] == false
    });
    climate_sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 8, "value": 812}));
    daemon.wait_value("climate_21", "CO2", "812");

    // It comes back (a new simulator behind the same path): the port is reopened.
    let relay_sim = SimProcess::start_with(&relay_bus, &repo("templates"), &[]);
    std::fs::remove_file(&relay_port).unwrap();
    std::os::unix::fs::symlink(&relay_sim.pty, &relay_port).unwrap();
    relay_sim
        .control(json!({"cmd": "set", "device": 20, "type": "coil", "address": 4, "value": 1}));
    daemon.wait_for(
        "K5 on after the port came back",
        Duration::from_secs(20),
        |line| line["device"] == "relay6_20" && line["control"] == "K5" && line["value"] == "1",
    );
}

/// `BUS` with every device on `line` ("9600 8N2").
fn bus_on_line(line: &str) -> String {
    BUS.replace("115200 8N2", line)
}

/// The repository's templates are Wiren Board style (`response_timeout_ms: 1`, the allowance is
/// added by the master): values, a change and a write at a slow baud rate, with Fast Modbus
/// events and without. `sim_args`: how the simulator hands bytes over.
fn wb_templates_at(baud: u32, fast_modbus: bool, patience: Duration, sim_args: &[&str]) {
    // Odd parity and one stop bit: the simulator hears only a master whose serial port was set
    // so (a pty passes both on), which proves the config's line settings reach the port.
    let sim = start_sim_bus(&bus_on_line(&format!("{baud} 8O1")), sim_args);
    // Only Wiren Board devices: a third-party meter (500 ms) would lend its timeout to the rest.
    let devices: Vec<Value> = [
        ("rtu2mqtt-relay6", 20),
        ("rtu2mqtt-climate", 21),
        ("rtu2mqtt-counter8", 22),
    ]
    .iter()
    .map(|(template, address)| json!({"device_type": template, "slave_id": address}))
    .collect();
    let mut daemon = Daemon::start_config(json!({
        "fast_modbus": fast_modbus,
        "ports": [{"path": sim.pty, "baud_rate": baud, "parity": "O", "stop_bits": 1, "devices": devices}]
    }));
    daemon.patience = patience;
    daemon.has_value("climate_21", "Temperature", "21.5");
    daemon.has_value("climate_21", "Humidity", "45.3");
    daemon.has_value("counter8_22", "Input 1", "0");
    daemon.has_value("relay6_20", "K1", "0");
    if fast_modbus {
        wait_events_ready_within(&sim, 20, patience);
        sim.control(json!({"cmd": "toggle", "device": 20, "type": "coil", "address": 0}));
        daemon.wait_event("relay6_20", "K1", "1");
    } else {
        sim.control(json!({"cmd": "toggle", "device": 20, "type": "coil", "address": 0}));
        daemon.wait_value("relay6_20", "K1", "1");
    }
    sim.control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2275}));
    daemon.wait_value("climate_21", "Temperature", "22.75");
    daemon.write("relay6_20", "K3", "1");
    daemon.wait_value("relay6_20", "K3", "1");
    assert_eq!(
        sim.control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 2}))["value"],
        1
    );
    // A loaded test machine may deliver a reply late now and then (it is then thrown away and
    // the device may be flagged for a moment): what counts is that every device ends up online.
    for device in ["relay6_20", "climate_21", "counter8_22"] {
        let last = daemon
            .seen
            .iter()
            .rev()
            .find(|line| line["device"] == device && line["online"].is_boolean());
        assert_eq!(
            last.map(|line| line["online"].clone()),
            Some(Value::Bool(true)),
            "{device} at {baud}"
        );
    }
}

#[test]
fn wb_templates_at_9600_8o1_with_fast_modbus() {
    wb_templates_at(9600, true, Duration::from_secs(15), &[]);
}

/// The same through a controller's own UART as Linux sets it up: a 16550 whose receive FIFO
/// hands bytes over 8 at a time, or 4 quiet characters after the last (arbitration fillers,
/// event packets and short replies come in bursts and late). The pty does not tell the daemon
/// of the FIFO (the exchange tests cover what it does when told): this checks that replies
/// handed over so are still assembled and answered in time. It is not a bound on the daemon's
/// allowances: with 3 ms instead of 24 it passes too.
#[test]
fn wb_templates_at_9600_8o1_through_a_uart_fifo() {
    wb_templates_at(
        9600,
        true,
        Duration::from_secs(15),
        &["--rx-fifo-trigger", "8"],
    );
}

/// A meter whose every reply starts 600 ms after the request, with the default 500 ms response
/// timeout: its channels are read one by one (same function, same length), so a late reply
/// credited to the next request would publish one channel's value under another's name.
#[test]
fn replies_after_the_timeout_never_publish_a_wrong_value() {
    // Floats with swapped words: 230.5 V, 5 A, 1000 W, 50 Hz.
    let bus = r#"{"devices": [
      {"name": "meter", "template": "rtu2mqtt-energy-meter", "address": 30, "serial": "0x0D000030",
       "line": "9600 8N2", "fast": false,
       "values": {"input:0": [32768, 17254], "input:6": [0, 16544], "input:12": [0, 17530]}}
    ]}"#;
    let sim = start_sim_bus(bus, &[]);
    sim.control(json!({"cmd": "faults", "device": 30, "delay": 1.0, "delay_ms": 600}));
    let mut daemon = Daemon::start_config(json!({
        "fast_modbus": false,
        "ports": [{"path": sim.pty, "baud_rate": 9600, "stop_bits": 2, "devices": [
            {"device_type": "rtu2mqtt-energy-meter", "slave_id": 30, "max_read_registers": 2}
        ]}]
    }));
    daemon.patience = Duration::from_secs(20);
    daemon.has_value("energy_meter_30", "Voltage", "230.5");
    daemon.has_value("energy_meter_30", "Current", "5");
    daemon.has_value("energy_meter_30", "Active Power", "1000");
    // Keep reading a while: every value the meter's channels get must be theirs.
    let until = Instant::now() + Duration::from_secs(8);
    while let Some(left) = until.checked_duration_since(Instant::now()) {
        if let Ok(line) = daemon.lines.recv_timeout(left) {
            daemon.seen.push(line);
        }
    }
    let expected = [
        ("Voltage", "230.5"),
        ("Current", "5"),
        ("Active Power", "1000"),
    ];
    let wrong: Vec<&Value> = daemon
        .seen
        .iter()
        .filter(|line| line["value"].is_string())
        .filter(|line| {
            expected
                .iter()
                .any(|(control, value)| line["control"] == *control && line["value"] != *value)
        })
        .collect();
    assert!(wrong.is_empty(), "wrong values published: {wrong:?}");
}

/// SIGTERM while the daemon waits on a device with a one-minute response timeout that never
/// answers: the daemon exits at once instead of finishing the wait.
#[test]
fn shutdown_does_not_wait_for_a_long_response_timeout() {
    let sim = start_sim(&[]);
    sim.control(json!({"cmd": "unplug", "device": 30}));
    let devices: Vec<Value> = [("rtu2mqtt-relay6", 20), ("rtu2mqtt-energy-meter", 30)]
        .iter()
        .map(|(template, address)| json!({"device_type": template, "slave_id": address}))
        .collect();
    let mut daemon = Daemon::start_config_with_env(
        json!({
            "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2,
                       "response_timeout_ms": 60000, "devices": devices}]
        }),
        &[("RUST_LOG", "rtu2mqtt::transport=debug")],
    );
    // The request to the meter (address 30 = 0x1E) has gone out: the port now waits a minute.
    let deadline = Instant::now() + Duration::from_secs(10);
    while !daemon._process.log().contains("1E 04 00") {
        assert!(Instant::now() < deadline, "no request to the meter");
        // A condition poll on the daemon's log; the pause only paces it.
        std::thread::sleep(Duration::from_millis(20));
    }
    let process = &mut daemon._process;
    let pid = nix::unistd::Pid::from_raw(process.child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    // Every request now waits a minute for its reply; the daemon must not.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if let Some(status) = process.child.try_wait().unwrap() {
            assert!(status.success(), "exit status {status}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "still running 20 s after SIGTERM"
        );
        // A condition poll on the child's exit; the pause only paces it.
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `rate_limit`: reads of channels without `read_period_ms` stay within the port's share (here
/// the whole limit, one port), at 115200 and at 9600.
fn reads_stay_within_the_rate_limit_at(baud: u32) {
    let line = format!("{baud} 8N2");
    let bus = json!({"devices": [{
        "name": "plain", "address": 40, "serial": "0xFE000040", "line": line, "fast": false,
        "registers": [{"type": "input", "address": 0, "count": 40}]
    }]});
    let sim = start_sim_bus(&bus.to_string(), &[]);
    // Every other register: twenty reads of one register each per round, none merged.
    let channels: Vec<Value> = (0..20)
        .map(|i| json!({"name": format!("r{i}"), "reg_type": "input", "address": i * 2}))
        .collect();
    let limit = 5;
    let mut daemon = Daemon::start_config(json!({
        "rate_limit": limit,
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": [
            {"slave_id": 40, "id": "plain", "channels": channels}
        ]}]
    }));
    daemon.patience = Duration::from_secs(30);
    daemon.has_value("plain", "r0", "0");
    let stats = || sim.control(json!({"cmd": "stats"}));
    let first = stats();
    let window_us = 3_000_000;
    let last = loop {
        let now = stats();
        if now["t_us"].as_u64().unwrap() >= first["t_us"].as_u64().unwrap() + window_us {
            break now;
        }
        // A condition poll on the simulator's clock; the pause only paces it.
        std::thread::sleep(Duration::from_millis(50));
    };
    let reads =
        last["registers_read"].as_u64().unwrap() - first["registers_read"].as_u64().unwrap();
    let elapsed_s =
        (last["t_us"].as_u64().unwrap() - first["t_us"].as_u64().unwrap()).div_ceil(1_000_000);
    // At most the limit in each of the one-second windows the span touches; a bus without the
    // limit reads some 50 (9600) to 350 (115200) registers a second here.
    assert!(
        reads <= limit * (elapsed_s + 1),
        "{reads} registers read in {elapsed_s} s at {baud} with rate_limit {limit}"
    );
    assert!(
        reads >= limit,
        "reads stopped: {reads} in {elapsed_s} s at {baud}"
    );
}

#[test]
fn reads_stay_within_the_rate_limit_at_115200() {
    reads_stay_within_the_rate_limit_at(115_200);
}

#[test]
fn reads_stay_within_the_rate_limit_at_9600() {
    reads_stay_within_the_rate_limit_at(9600);
}

/// A subdevice's parameters named like channel keys reach the device: the legacy WB-MAI11's
/// `min` and `max` (the range an input's value is scaled to), here in the fixture
/// `WB-TEST-INPUTS` whose `analog` subdevice declares them as the MAI11's do (0x0408, 0x040A).
/// wb-mqtt-serial writes them (`MergeChannelProperties` copies every key of a slot's override
/// into the slot, `AppendSetupItems` makes a setup item of each named like a parameter);
/// rtu2mqtt dropped them as channel keys and wrote only the others.
#[test]
fn subdevice_parameters_named_like_channel_keys_reach_the_device() {
    let templates = repo("tests/data/wb-templates");
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    // Input 2 is shifted by 0x2000: its subdevices' setup at 0x2400…, values at 0x2500….
    let bus_json = json!({"devices": [{"name": "inputs", "template": "WB-TEST-INPUTS",
        "address": 7, "serial": "0xFE000007", "line": "115200 8N2", "fast": false,
        "registers": [{"type": "holding", "address": 0x2400, "count": 16},
                      {"type": "input", "address": 0x2500, "count": 8}]}]});
    std::fs::write(&bus, bus_json.to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &templates, &[]);
    let mut daemon = Daemon::start_config_with(
        json!({"ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2, "devices": [
            {"device_type": "WB-TEST-INPUTS", "slave_id": 7, "channels": [
                {"name": "Input 2", "device_type": "analog_pair", "channels": [
                    {"name": "IN_P", "device_type": "analog", "data_rate": 45, "min": 5, "max": 2000},
                    {"name": "IN_N", "device_type": "analog", "data_rate": 90, "max": 3000}]}]}]}]}),
        &["--templates", templates.to_str().unwrap()],
        &[],
    );
    // The setup is written before the device's first poll: once a value of it is published,
    // the setup is there.
    daemon.wait_for("a value of IN 2 P", daemon.patience, |line| {
        line["device"] == "wb-test-inputs_7" && line["control"] == "IN 2 P Value"
    });
    let holding = sim.control(
        json!({"cmd": "get", "device": 7, "type": "holding", "address": 0x2400, "count": 12}),
    );
    // 0x2400 IN_P type, 0x2401 IN_N type (stride 1: IN_N moved by each register's width),
    // 0x2402/0x2403 rates, 0x2408 IN_P min, 0x240A IN_P max, 0x240B IN_N max; IN_N's min and
    // the measurements are not given, so not written.
    assert_eq!(
        holding["values"],
        json!([4866, 4866, 45, 90, 0, 0, 0, 0, 5, 0, 2000, 3000]),
        "{holding}"
    );
}
