//! Independent Modbus masters against the real `rtu2mqtt sim`: mbpoll (libmodbus 3.1) and
//! pymodbus 3.0 read and write the simulator's devices over its pty at 9600 8N2 and 115200 8N2,
//! pymodbus also over Modbus TCP (`--modbus-tcp`) and RTU over TCP (`--tcp`). What they read
//! is compared with the bus file and the control socket, what they write is read back through
//! the control socket, and exceptions, timeouts and broadcasts are checked with their exact
//! codes; raw frames of every function code the simulator lacks must get exception 1. The tools
//! are required: a missing one fails the test (`scripts/test` installs them). Bus:
//! tests/data/sim/interop-bus.json; the pymodbus side: tests/interop/pymodbus_master.py.
//! Findings and tool quirks: docs/sim.md, "Checked with independent masters".

#[path = "sim_support/mod.rs"]
mod sim_support;

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, ExitStatus, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use rtu2mqtt::protocol::{LineSettings, Parity, Request, RequestPdu};
use serde_json::{json, Value};
use sim_support::SimProcess;

const BUS: &str = "interop-bus.json";
const PYTHON: &str = "/usr/bin/python3";

/// A device of the bus file and the values it starts with.
#[derive(Clone, Copy)]
struct Device {
    address: u8,
    baud: u32,
    coils: &'static [u64],
    discrete: &'static [u64],
    holding: &'static [u64],
    input: &'static [u64],
}

const FAST: Device = Device {
    address: 17,
    baud: 115_200,
    coils: &[1, 0, 1, 1, 0, 0, 1],
    discrete: &[0, 1, 1, 0, 1],
    holding: &[1700, 1701, 1702],
    input: &[17, 170, 1717, 65535],
};
const FAST_B: Device = Device {
    address: 19,
    baud: 115_200,
    coils: &[0, 1, 1],
    discrete: &[1, 1, 0, 0, 1],
    holding: &[1900, 1901, 1902],
    input: &[19, 190, 1919, 32768],
};
const SLOW: Device = Device {
    address: 18,
    baud: 9600,
    coils: &[1, 1, 0, 1, 0, 1, 1],
    discrete: &[1, 0, 0, 1, 1],
    holding: &[1800, 1801, 1802],
    input: &[18, 180, 1818, 65534],
};
const SLOW_B: Device = Device {
    address: 21,
    baud: 9600,
    coils: &[0, 0, 1],
    discrete: &[0, 0, 1, 1, 0],
    holding: &[2100, 2101, 2102],
    input: &[21, 210, 2121, 4096],
};

/// Each table holds 16 coils / discrete inputs and 10 registers from address 0.
fn padded(values: &[u64], len: usize) -> Vec<u64> {
    let mut all = values.to_vec();
    all.resize(len, 0);
    all
}

// --- the tools -------------------------------------------------------------------------------

/// mbpoll, or a loud failure: these tests never skip.
fn require_mbpoll() {
    let found = Command::new("mbpoll")
        .arg("-V")
        .output()
        .is_ok_and(|out| out.status.success());
    assert!(
        found,
        "mbpoll is not installed (apt-get install mbpoll; scripts/test installs it)"
    );
}

fn require_pymodbus() {
    let found = Command::new(PYTHON)
        .args(["-c", "import pymodbus, serial"])
        .output()
        .is_ok_and(|out| out.status.success());
    assert!(
        found,
        "{PYTHON} cannot import pymodbus and serial (apt-get install python3-pymodbus \
         python3-serial; scripts/test installs them)"
    );
}

/// Lines of a child's stdout and stderr, as they come.
fn lines_of(child: &mut Child) -> Receiver<String> {
    let (sender, lines) = mpsc::channel();
    let out = child
        .stdout
        .take()
        .map(|out| Box::new(out) as Box<dyn std::io::Read + Send>);
    let err = child
        .stderr
        .take()
        .map(|err| Box::new(err) as Box<dyn std::io::Read + Send>);
    for stream in [out, err].into_iter().flatten() {
        let sender = sender.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stream).lines().map_while(Result::ok) {
                if sender.send(line).is_err() {
                    break;
                }
            }
        });
    }
    lines
}

/// What one mbpoll run printed (stdout and stderr, in arrival order) and how it ended.
struct Mbpoll {
    status: ExitStatus,
    output: String,
}

impl Mbpoll {
    /// The `[ref]: value` lines: (reference, value). Input registers above 32767 print as
    /// `65535 (-1)`: the first number is the register.
    fn values(&self) -> Vec<(u32, u64)> {
        self.output
            .lines()
            .filter_map(|line| {
                let rest = line.trim().strip_prefix('[')?;
                let (reference, value) = rest.split_once("]:")?;
                let value = value.split_whitespace().next()?;
                Some((reference.parse().ok()?, value.parse().ok()?))
            })
            .collect()
    }

    fn only_values(&self) -> Vec<u64> {
        self.values().into_iter().map(|(_, value)| value).collect()
    }
}

/// Runs mbpoll to completion (20 s at most: killed and failed beyond).
fn mbpoll(args: &[String]) -> Mbpoll {
    let mut child = Command::new("mbpoll")
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mbpoll starts");
    let lines = lines_of(&mut child);
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("mbpoll {args:?} did not finish within 20 s");
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    // The readers end with the child's pipes.
    let output: Vec<String> = lines.iter().collect();
    Mbpoll {
        status,
        output: output.join("\n"),
    }
}

/// mbpoll's options for one poll of `device` on the pty: RTU 8N2 at its baud rate, PDU
/// (0-based) addresses, 1 s timeout. `count`: registers to read; 0 for a write (the values
/// given after the port say how many).
fn rtu_args(sim: &SimProcess, device: Device, table: u8, start: u16, count: u16) -> Vec<String> {
    let mut args: Vec<String> = [
        "-m", "rtu", "-d", "8", "-s", "2", "-P", "none", "-0", "-1", "-o", "1",
    ]
    .iter()
    .map(ToString::to_string)
    .collect();
    args.extend([
        "-b".into(),
        device.baud.to_string(),
        "-a".into(),
        device.address.to_string(),
        "-t".into(),
        table.to_string(),
        "-r".into(),
        start.to_string(),
    ]);
    if count > 0 {
        args.extend(["-c".into(), count.to_string()]);
    }
    args.push(sim.pty.display().to_string());
    args
}

fn with(mut args: Vec<String>, extra: &[&str]) -> Vec<String> {
    args.extend(extra.iter().map(ToString::to_string));
    args
}

/// pymodbus as a master, one operation per line (tests/interop/pymodbus_master.py).
struct PyMaster {
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<String>,
}

impl PyMaster {
    fn start(config: Value) -> Self {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/pymodbus_master.py");
        let mut child = Command::new(PYTHON)
            .arg(script)
            .arg(config.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("python starts");
        let stdin = child.stdin.take().unwrap();
        let lines = lines_of(&mut child);
        let mut master = Self {
            child,
            stdin,
            lines,
        };
        let ready = master.next_json(&config);
        assert_eq!(ready, json!({"ready": true}), "pymodbus master {config}");
        master
    }

    fn serial(sim: &SimProcess, baud: u32) -> Self {
        Self::start(json!({"serial": sim.pty, "baud": baud}))
    }

    fn next_json(&mut self, what: &Value) -> Value {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => match serde_json::from_str::<Value>(&line) {
                    Ok(value) if value.is_object() => return value,
                    // Python's own noise (a traceback) goes into the failure below.
                    _ => eprintln!("pymodbus master: {line}"),
                },
                Err(RecvTimeoutError::Timeout) => panic!("pymodbus master: no answer to {what}"),
                Err(RecvTimeoutError::Disconnected) => {
                    panic!(
                        "pymodbus master exited on {what}: {:?}",
                        self.child.try_wait()
                    )
                }
            }
        }
    }

    /// Runs one operation; pymodbus must not have logged a warning meanwhile (it warns when it
    /// finds bytes waiting before a request: a reply nobody asked for).
    fn call(&mut self, op: Value) -> Value {
        writeln!(self.stdin, "{op}").unwrap();
        self.stdin.flush().unwrap();
        let mut result = self.next_json(&op);
        let warnings = result
            .as_object_mut()
            .and_then(|fields| fields.remove("warnings"))
            .unwrap_or(Value::Null);
        assert_eq!(warnings, json!([]), "pymodbus warned during {op}");
        result
    }
}

impl Drop for PyMaster {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

// --- the simulator's side ----------------------------------------------------------------------

fn get(sim: &SimProcess, address: u8, table: &str, start: u16, count: u16) -> Vec<u64> {
    let reply = sim.control(json!({"cmd": "get", "device": address, "type": table,
        "address": start, "count": count}));
    reply["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect()
}

fn set(sim: &SimProcess, address: u8, table: &str, start: u16, values: &[u64]) {
    sim.control(
        json!({"cmd": "set", "device": address, "type": table, "address": start,
        "value": values}),
    );
}

/// (requests heard, requests answered, pacer writes) so far.
fn stats(sim: &SimProcess) -> (u64, u64, u64) {
    let reply = sim.control(json!({"cmd": "stats"}));
    (
        reply["requests"].as_u64().unwrap(),
        reply["answered"].as_u64().unwrap(),
        reply["pacing"]["writes"].as_u64().unwrap(),
    )
}

/// Polls the control socket until `done` holds (10 s at most).
fn wait_until(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting until {what}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The `tcp` or `modbus-tcp` listener's address from the banner.
fn listener(sim: &SimProcess, kind: &str) -> String {
    sim.banner()
        .iter()
        .find_map(|line| {
            let rest = line.strip_prefix(kind)?.strip_prefix(' ')?;
            Some(rest.split_whitespace().next()?.to_string())
        })
        .unwrap_or_else(|| panic!("no {kind} line in {:?}", sim.banner()))
}

fn start_sim() -> SimProcess {
    SimProcess::start(
        BUS,
        &["--tcp", "127.0.0.1:0", "--modbus-tcp", "127.0.0.1:0"],
    )
}

// --- mbpoll (libmodbus) on the pty -------------------------------------------------------------

#[test]
fn mbpoll_reads_the_four_tables_at_9600_and_115200() {
    require_mbpoll();
    let sim = start_sim();
    for device in [SLOW, FAST] {
        let read = |table: u8, start: u16, count: u16| {
            let run = mbpoll(&rtu_args(&sim, device, table, start, count));
            assert!(run.status.success(), "{}", run.output);
            let refs: Vec<u32> = run.values().iter().map(|&(r, _)| r).collect();
            let expected: Vec<u32> = (u32::from(start)..u32::from(start + count)).collect();
            assert_eq!(refs, expected, "{}", run.output);
            run.only_values()
        };
        let name = device.address;
        assert_eq!(read(0, 0, 7), device.coils, "coils of {name}");
        assert_eq!(read(1, 0, 5), device.discrete, "discrete inputs of {name}");
        assert_eq!(read(3, 0, 4), device.input, "input registers of {name}");
        assert_eq!(read(4, 0, 3), device.holding, "holding registers of {name}");
        // The Wiren Board standard register: the device's own address.
        assert_eq!(read(4, 128, 1), [u64::from(name)]);
        // What the control socket sets is what a master reads.
        set(&sim, name, "input", 8, &[4321, 65000]);
        set(&sim, name, "discrete", 14, &[1, 0]);
        assert_eq!(read(3, 7, 3), [0, 4321, 65000]);
        assert_eq!(read(1, 13, 3), [0, 1, 0]);
    }
}

#[test]
fn mbpoll_writes_single_and_multiple_coils_and_registers() {
    require_mbpoll();
    let sim = start_sim();
    for device in [SLOW, FAST] {
        let address = device.address;
        // One value: function 5 or 6; several: 15 or 16 (mbpoll -v prints the request).
        let write = |table: u8, start: u16, values: &[&str], function: u8| {
            let args = with(rtu_args(&sim, device, table, start, 0), &["-v"]);
            let run = mbpoll(&with(args, values));
            assert!(run.status.success(), "{}", run.output);
            assert!(
                run.output
                    .contains(&format!("Written {} references.", values.len())),
                "{}",
                run.output
            );
            let request = format!("[{address:02X}][{function:02X}][00][{start:02X}]");
            assert!(
                run.output.contains(&request),
                "no {request} in {}",
                run.output
            );
        };
        write(0, 4, &["1"], 0x05);
        write(0, 9, &["1", "1", "0", "1", "1"], 0x0F);
        write(4, 9, &["4242"], 0x06);
        write(4, 3, &["7", "65535", "9"], 0x10);
        let mut coils = padded(device.coils, 16);
        coils[4] = 1;
        coils[9..14].copy_from_slice(&[1, 1, 0, 1, 1]);
        assert_eq!(
            get(&sim, address, "coil", 0, 16),
            coils,
            "coils of {address}"
        );
        let mut holding = padded(device.holding, 10);
        holding[3..6].copy_from_slice(&[7, 65535, 9]);
        holding[9] = 4242;
        assert_eq!(get(&sim, address, "holding", 0, 10), holding);
        // A coil back to 0 by function 5.
        write(0, 0, &["0"], 0x05);
        assert_eq!(get(&sim, address, "coil", 0, 1), [0]);
    }
    // Writes to one device leave the other devices at the same speed alone.
    assert_eq!(get(&sim, 21, "holding", 0, 10), padded(SLOW_B.holding, 10));
    assert_eq!(get(&sim, 19, "coil", 0, 16), padded(FAST_B.coils, 16));
}

#[test]
fn mbpoll_shows_the_exceptions_and_times_out_on_a_missing_slave() {
    require_mbpoll();
    let sim = start_sim();
    for device in [SLOW, FAST] {
        let failed = |args: Vec<String>, message: &str| {
            let run = mbpoll(&args);
            assert!(
                run.output.contains(&format!("failed: {message}"))
                    || run.output.contains(&format!("failed(-1): {message}")),
                "expected {message:?} from mbpoll {args:?}: {}",
                run.output
            );
            assert!(run.values().is_empty(), "{}", run.output);
            run
        };
        // Holding 0..=9 exist: 8..=11 crosses the end. Exception 2.
        let run = failed(rtu_args(&sim, device, 4, 8, 4), "Illegal data address");
        assert!(!run.status.success());
        failed(rtu_args(&sim, device, 3, 20, 1), "Illegal data address");
        failed(rtu_args(&sim, device, 0, 15, 2), "Illegal data address");
        // The model string (holding 200..) is read-only: exception 2 to a write.
        failed(
            with(rtu_args(&sim, device, 4, 200, 0), &["1"]),
            "Illegal data address",
        );
        // Address register 128 takes 1..=247: exception 3.
        failed(
            with(rtu_args(&sim, device, 4, 128, 0), &["0"]),
            "Illegal data value",
        );
        // Report slave id (0x11) is not implemented: exception 1. mbpoll -u prints it
        // but exits 0.
        failed(
            with(rtu_args(&sim, device, 4, 0, 1), &["-u"]),
            "Illegal function",
        );
        // A slave nobody is at: silence, heard but not answered.
        let before = stats(&sim);
        let mut missing = device;
        missing.address = 99;
        let run = failed(
            with(rtu_args(&sim, missing, 4, 0, 1), &["-o", "0.2"]),
            "Connection timed out",
        );
        assert!(!run.status.success());
        let after = stats(&sim);
        assert_eq!((after.0 - before.0, after.1 - before.1), (1, 0));
    }
    // A device hears only requests at its own baud rate.
    let mut wrong_speed = SLOW;
    wrong_speed.baud = 115_200;
    let run = mbpoll(&with(rtu_args(&sim, wrong_speed, 4, 0, 1), &["-o", "0.2"]));
    assert!(
        run.output.contains("Connection timed out"),
        "{}",
        run.output
    );
    // Nothing was written by the rejected writes.
    assert_eq!(get(&sim, 18, "holding", 128, 1), [18]);
    assert_eq!(get(&sim, 17, "holding", 128, 1), [17]);
}

/// libmodbus writes its next request as soon as it has read a reply: mbpoll polling two slaves
/// in turn, 10 ms between rounds, sends them back to back. Every poll must succeed. Stopped
/// with Ctrl-C (SIGINT), mbpoll prints its statistics; the poll it was in may be cut short.
#[test]
fn mbpoll_back_to_back_polls_all_succeed_at_9600_and_115200() {
    require_mbpoll();
    let sim = start_sim();
    for ((first, second), polls) in [((SLOW, SLOW_B), 24), ((FAST, FAST_B), 80)] {
        let slaves = format!("{0},{1},{0},{1}", first.address, second.address);
        let mut args: Vec<String> = rtu_args(&sim, first, 4, 0, 3)
            .into_iter()
            .filter(|arg| arg != "-1")
            .collect();
        let at = args.iter().position(|arg| arg == "-a").unwrap() + 1;
        args[at] = slaves;
        args.extend(["-l".into(), "10".into()]);
        let before = stats(&sim);
        let mut child = Command::new("mbpoll")
            .args(&args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("mbpoll starts");
        let lines = lines_of(&mut child);
        // One more than counted: the poll SIGINT interrupts may be cut short.
        wait_until(&format!("mbpoll has sent {polls} requests"), || {
            stats(&sim).0 > before.0 + polls
        });
        let pid = nix::unistd::Pid::from_raw(i32::try_from(child.id()).unwrap());
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGINT).unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while child.try_wait().unwrap().is_none() {
            if Instant::now() > deadline {
                let _ = child.kill();
                panic!("mbpoll did not stop on SIGINT");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let output: Vec<String> = lines.iter().collect();
        let text = output.join("\n");
        assert!(!text.contains("failed"), "{text}");
        // Each "-- Polling slave N..." followed by its three registers.
        let mut complete = 0;
        let mut slave: Option<Device> = None;
        let mut values = Vec::new();
        for line in &output {
            if let Some(rest) = line.strip_prefix("-- Polling slave ") {
                let address: u8 = rest.split('.').next().unwrap().parse().unwrap();
                slave = [first, second].into_iter().find(|d| d.address == address);
                assert!(slave.is_some(), "{line}");
                values.clear();
            } else if let Some((_, value)) = line.split_once("]:") {
                values.push(value.trim().parse::<u64>().unwrap());
                if values.len() == 3 {
                    let polled = slave.take().expect("values after a poll line");
                    assert_eq!(values, polled.holding, "slave {}", polled.address);
                    complete += 1;
                }
            }
        }
        assert!(
            complete >= polls,
            "{complete} complete polls of {polls}: {text}"
        );
        // "N frames transmitted, M received, 0 errors": all but the one SIGINT cut short.
        let statistics = output
            .iter()
            .find(|line| line.contains("frames transmitted"))
            .unwrap_or_else(|| panic!("no statistics: {text}"));
        let numbers: Vec<u64> = statistics
            .split(|c: char| !c.is_ascii_digit())
            .filter_map(|n| n.parse().ok())
            .collect();
        let (sent, received, errors) = (numbers[0], numbers[1], numbers[2]);
        assert_eq!(received, complete, "{statistics}");
        assert!(sent == received || sent == received + 1, "{statistics}");
        assert_eq!(errors, 0, "{statistics}");
        // The simulator answered every request it heard.
        let after = stats(&sim);
        assert_eq!(
            after.0 - before.0,
            after.1 - before.1,
            "unanswered requests"
        );
        assert!(after.0 - before.0 >= complete, "{after:?}");
    }
}

/// A master killed with a reply on its way leaves the reply on the line, not in the next
/// master's input: libmodbus (which does not flush a port it opens) read that stale reply as
/// the answer to its own request while the simulator kept it in its pty. Real ports start empty.
#[test]
fn a_reply_to_a_master_that_has_gone_is_not_read_by_the_next_one() {
    require_mbpoll();
    let sim = start_sim();
    let (_, _, writes) = stats(&sim);
    let mut gone = sim.master(LineSettings::new(9600, Parity::None, 2));
    let request = Request::classic(
        SLOW.address,
        RequestPdu::ReadHoldingRegisters { start: 0, count: 3 },
    );
    gone.send(&request.encode().unwrap());
    drop(gone);
    // 18 03 06 <6 bytes> CRC: 11 bytes, each its own hand-over at 9600 (a character is longer
    // than the receiver's 250 µs batching).
    wait_until("the reply to the master that has gone is over", || {
        stats(&sim).2 >= writes + 11
    });
    set(&sim, SLOW.address, "holding", 0, &[555, 556, 557]);
    let run = mbpoll(&rtu_args(&sim, SLOW, 4, 0, 3));
    assert!(run.status.success(), "{}", run.output);
    assert_eq!(run.only_values(), [555, 556, 557], "{}", run.output);
}

/// Every function code a master may send (1..=127) that the simulator does not implement gets
/// exception 1 (illegal function) from the addressed device at either speed, never silence;
/// a broadcast of one gets no reply. The frames are raw (no master library offers them all).
#[test]
fn every_function_code_the_simulator_lacks_gets_exception_1() {
    let sim = start_sim();
    let implemented = [1, 2, 3, 4, 5, 6, 15, 16];
    for device in [FAST, SLOW] {
        let mut port = sim.master(LineSettings::new(device.baud, Parity::None, 2));
        let functions: Vec<u8> = if device.baud == FAST.baud {
            (1..=0x7F).filter(|f| !implemented.contains(f)).collect()
        } else {
            // At 9600 the ones the masters above sent.
            vec![0x07, 0x08, 0x11, 0x16, 0x17, 0x2B]
        };
        for function in functions {
            let frame = with_crc(&[device.address, function, 0, 0, 0, 1]);
            port.send(&frame);
            let expected = with_crc(&[device.address, function | 0x80, 1]);
            let chunks = port.read_until(Duration::from_secs(2), |all| all.len() >= expected.len());
            let reply: Vec<u8> = chunks.into_iter().flat_map(|(_, bytes)| bytes).collect();
            assert_eq!(
                reply, expected,
                "function {function:#04x} to {}",
                device.address
            );
        }
        let before = stats(&sim);
        port.send(&with_crc(&[0, 0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 7]));
        wait_until("the broadcast is heard", || stats(&sim).0 > before.0);
        assert_eq!(
            stats(&sim).1,
            before.1,
            "a device answered a broadcast 0x17"
        );
    }
}

fn with_crc(bytes: &[u8]) -> Vec<u8> {
    let mut frame = bytes.to_vec();
    frame.extend_from_slice(&rtu2mqtt::protocol::crc16(bytes).to_le_bytes());
    frame
}

// --- pymodbus ------------------------------------------------------------------------------------

/// Reads, writes, exceptions and unsupported functions, by pymodbus over any transport.
fn exercise(sim: &SimProcess, master: &mut PyMaster, device: Device) {
    let unit = device.address;
    let read = |master: &mut PyMaster, table: &str, address: u16, count: u16| {
        master.call(
            json!({"op": "read", "table": table, "address": address, "count": count,
            "unit": unit}),
        )
    };
    let coils = padded(device.coils, 16);
    assert_eq!(read(master, "coil", 0, 7), json!({"bits": coils[..7]}));
    let discrete = padded(device.discrete, 16);
    assert_eq!(read(master, "discrete", 0, 16), json!({"bits": discrete}));
    assert_eq!(
        read(master, "input", 0, 4),
        json!({"registers": device.input})
    );
    let holding = padded(device.holding, 10);
    assert_eq!(
        read(master, "holding", 0, 4),
        json!({"registers": holding[..4]})
    );
    // Writes, echoed as the standard says, then seen through the control socket.
    let op = |name: &str, address: u16, values: Value| {
        let key = if values.is_array() { "values" } else { "value" };
        json!({"op": name, "address": address, key: values, "unit": unit})
    };
    assert_eq!(
        master.call(op("write_coil", 5, json!(1))),
        json!({"address": 5, "value": 1})
    );
    assert_eq!(
        master.call(op("write_coils", 7, json!([1, 0, 1, 1, 1, 0, 0, 1, 1]))),
        json!({"address": 7, "count": 9})
    );
    assert_eq!(
        master.call(op("write_register", 8, json!(60000))),
        json!({"address": 8, "value": 60000})
    );
    assert_eq!(
        master.call(op("write_registers", 4, json!([11, 12, 13]))),
        json!({"address": 4, "count": 3})
    );
    let mut coils = padded(device.coils, 16);
    coils[5] = 1;
    coils[7..16].copy_from_slice(&[1, 0, 1, 1, 1, 0, 0, 1, 1]);
    assert_eq!(get(sim, unit, "coil", 0, 16), coils);
    let mut holding = padded(device.holding, 10);
    holding[4..7].copy_from_slice(&[11, 12, 13]);
    holding[8] = 60000;
    assert_eq!(get(sim, unit, "holding", 0, 10), holding);
    assert_eq!(read(master, "coil", 0, 16), json!({"bits": coils}));
    assert_eq!(
        read(master, "holding", 0, 10),
        json!({"registers": holding})
    );
    // Exceptions: 2 for a range across the end or a read-only register, 3 for a bad count or
    // a bad value of a standard register.
    let exception = |function: u8, code: u8| json!({"function": function, "exception": code});
    assert_eq!(read(master, "holding", 9, 2), exception(3, 2));
    assert_eq!(read(master, "input", 10, 1), exception(4, 2));
    assert_eq!(read(master, "coil", 16, 1), exception(1, 2));
    assert_eq!(read(master, "holding", 0, 0), exception(3, 3));
    assert_eq!(read(master, "holding", 0, 126), exception(3, 3));
    assert_eq!(read(master, "discrete", 0, 2001), exception(2, 3));
    // Coils 0..=15 exist: 9 from 10 run past the end, refused whole.
    assert_eq!(
        master.call(op("write_coils", 10, json!(vec![0; 9]))),
        exception(15, 2)
    );
    assert_eq!(
        master.call(op("write_register", 200, json!(1))),
        exception(6, 2)
    );
    assert_eq!(
        master.call(op("write_register", 111, json!(7))),
        exception(6, 3)
    );
    assert_eq!(
        master.call(op("write_registers", 0, json!([]))),
        exception(16, 3)
    );
    // Functions the simulator does not implement: exception 1 each.
    assert_eq!(
        master.call(
            json!({"op": "readwrite", "read_address": 0, "read_count": 3,
            "write_address": 5, "values": [1, 2], "unit": unit})
        ),
        exception(0x17, 1)
    );
    assert_eq!(
        master.call(json!({"op": "device_id", "unit": unit})),
        exception(0x2B, 1)
    );
    assert_eq!(
        master.call(json!({"op": "diag_query", "data": 0x1234, "unit": unit})),
        exception(0x08, 1)
    );
    assert_eq!(
        master.call(json!({"op": "report_slave_id", "unit": unit})),
        exception(0x11, 1)
    );
    assert_eq!(
        master.call(
            json!({"op": "mask_write", "address": 0, "and_mask": 255, "or_mask": 0,
            "unit": unit})
        ),
        exception(0x16, 1)
    );
    // Nothing the rejected requests carried was written.
    assert_eq!(get(sim, unit, "holding", 0, 10), holding);
    assert_eq!(get(sim, unit, "holding", 111, 1), [0]);
}

/// A request to a slave nobody is at gets no reply.
fn no_reply(master: &mut PyMaster, unit: u8) {
    let result = master.call(
        json!({"op": "read", "table": "holding", "address": 0, "count": 1,
        "unit": unit}),
    );
    let error = result["error"].as_str().unwrap_or_default();
    assert!(error.contains("No response received"), "{result}");
}

#[test]
fn pymodbus_rtu_on_the_pty_at_9600_and_115200() {
    require_pymodbus();
    let sim = start_sim();
    for device in [SLOW, FAST] {
        let mut master = PyMaster::serial(&sim, device.baud);
        exercise(&sim, &mut master, device);
        let before = stats(&sim);
        no_reply(&mut master, 99);
        let after = stats(&sim);
        assert_eq!((after.0 - before.0, after.1 - before.1), (1, 0));
    }
}

#[test]
fn pymodbus_modbus_tcp_through_the_gateway() {
    require_pymodbus();
    let sim = start_sim();
    let address = listener(&sim, "modbus-tcp");
    let mut master = PyMaster::start(json!({"tcp": address, "framer": "socket"}));
    // The gateway's line is 9600 8N2: the devices at 9600 are behind it.
    exercise(&sim, &mut master, SLOW);
    exercise(&sim, &mut master, SLOW_B);
    // A unit nobody answers for, and one at another speed: exception 0x0B from the gateway.
    let missing = json!({"function": 3, "exception": 0x0B});
    for unit in [99, FAST.address] {
        let result = master.call(json!({"op": "read", "table": "holding", "address": 0,
            "count": 1, "unit": unit}));
        assert_eq!(result, missing, "unit {unit}");
    }
}

#[test]
fn pymodbus_rtu_over_tcp() {
    require_pymodbus();
    let sim = start_sim();
    let address = listener(&sim, "tcp");
    let mut master = PyMaster::start(json!({"tcp": address, "framer": "rtu"}));
    exercise(&sim, &mut master, SLOW_B);
    no_reply(&mut master, FAST.address);
}

/// Broadcasts (unit 0) from independent masters: every device at the master's line settings
/// executes them, none answers.
#[test]
fn broadcast_writes_from_independent_masters_apply_and_get_no_reply() {
    require_pymodbus();
    require_mbpoll();
    let sim = start_sim();
    for (value, devices, others) in [
        (3, [SLOW, SLOW_B], [FAST, FAST_B]),
        (4, [FAST, FAST_B], [SLOW, SLOW_B]),
    ] {
        let mut master = PyMaster::serial(&sim, devices[0].baud);
        let untouched: Vec<(Vec<u64>, Vec<u64>)> = others
            .iter()
            .map(|d| {
                (
                    get(&sim, d.address, "holding", 0, 10),
                    get(&sim, d.address, "coil", 0, 16),
                )
            })
            .collect();
        let ops = [
            json!({"op": "write_register", "address": 9, "value": value * 1000, "unit": 0}),
            json!({"op": "write_registers", "address": 6, "values": [value, value + 1], "unit": 0}),
            json!({"op": "write_coil", "address": 15, "value": 1, "unit": 0}),
            json!({"op": "write_coils", "address": 12, "values": [1, 0, 1], "unit": 0}),
        ];
        for op in ops {
            let before = stats(&sim);
            assert_eq!(master.call(op.clone()), json!({"broadcast": true}));
            // pymodbus 3.0 sends its next request at once after a broadcast, which would run
            // into this one on the line (both lost): wait until the devices have it.
            wait_until(&format!("{op} is executed"), || stats(&sim).0 > before.0);
            let after = stats(&sim);
            assert_eq!(after.1, before.1, "a device answered {op}");
        }
        for device in devices {
            let holding = get(&sim, device.address, "holding", 6, 4);
            assert_eq!(
                holding,
                [value, value + 1, 0, value * 1000],
                "{}",
                device.address
            );
            let coils = get(&sim, device.address, "coil", 12, 4);
            assert_eq!(coils, [1, 0, 1, 1], "{}", device.address);
        }
        // Devices at other settings did not hear them.
        for (device, (holding, coils)) in others.iter().zip(untouched) {
            assert_eq!(get(&sim, device.address, "holding", 0, 10), holding);
            assert_eq!(get(&sim, device.address, "coil", 0, 16), coils);
        }
        // The next request after a broadcast is answered as usual.
        assert_eq!(
            master.call(
                json!({"op": "read", "table": "holding", "address": 9, "count": 1,
                "unit": devices[1].address})
            ),
            json!({"registers": [value * 1000]})
        );
    }
    // Through the Modbus TCP gateway, unit 0 is a broadcast too: libmodbus waits for a reply
    // to it (and times out), pymodbus does not.
    let gateway = listener(&sim, "modbus-tcp");
    let (host, port) = gateway.rsplit_once(':').unwrap();
    let before = stats(&sim);
    let run = mbpoll(
        &[
            "-m", "tcp", "-p", port, "-a", "0", "-t", "4", "-0", "-r", "2", "-1", "-o", "0.3",
            host, "2222",
        ]
        .map(String::from),
    );
    assert!(
        run.output.contains("Connection timed out"),
        "{}",
        run.output
    );
    let mut master = PyMaster::start(json!({"tcp": gateway, "framer": "socket"}));
    assert_eq!(
        master.call(json!({"op": "write_register", "address": 1, "value": 1111, "unit": 0})),
        json!({"broadcast": true})
    );
    wait_until("both broadcasts are executed", || {
        stats(&sim).0 >= before.0 + 2
    });
    for device in [SLOW, SLOW_B] {
        assert_eq!(
            get(&sim, device.address, "holding", 1, 2),
            [1111, 2222],
            "{}",
            device.address
        );
    }
    assert_eq!(get(&sim, FAST.address, "holding", 1, 2), FAST.holding[1..3]);
    assert_eq!(stats(&sim).1, before.1, "a device answered a broadcast");
}
