//! Site tools against the simulator on a pty: `scan`, `set-address`, `fix-addresses`, `read`,
//! `write`, `events`. The bus (tests/data/sim/site-bus.json) has six devices at three port
//! settings: two Fast Modbus devices share address 10 at 9600 8N2, one at 115200 8N2, two at
//! 19200 8O1, and a classic-only device at address 40, 115200 8N2.
//!
//! A pseudo-terminal cannot tell parity N from E, so devices at 8N2 also answer at 8E2 here; the
//! scan reports the setting their registers (110..112) name and the other one as "also at". The
//! scan sends with 2 stop bits; devices at 8O1 hear it (a receiver checks only the first stop
//! bit) and report their 1 stop bit.

mod daemon_support;
mod mqtt_support;
mod sim_support;
#[path = "tool_support/mod.rs"]
mod tool_support;

use std::process::Command;
use tool_support::{tool, Run};

use nix::sys::termios::{self, BaudRate, ControlFlags, SetArg};
use serde_json::{json, Value};
use sim_support::SimProcess;

/// Generous for a loaded test machine; values are asserted, never timings.
const LATENCY_MS: &str = "100";

fn sim() -> SimProcess {
    SimProcess::start("site-bus.json", &[])
}

fn port(sim: &SimProcess) -> String {
    sim.pty.to_str().unwrap().to_owned()
}

fn scan_json(sim: &SimProcess, extra: &[&str]) -> Value {
    let port = port(sim);
    let mut args = vec!["scan", "--port", &port, "--json", "--latency", LATENCY_MS];
    args.extend_from_slice(extra);
    let run = tool(&args);
    assert!(
        run.code == 0 || run.code == 1,
        "{}{}",
        run.stdout,
        run.stderr
    );
    serde_json::from_str(&run.stdout).unwrap_or_else(|e| panic!("{e}: {}", run.stdout))
}

/// The devices of a scan as (serial, address, settings), sorted by serial.
fn found(report: &Value) -> Vec<(u64, u64, String)> {
    let mut devices: Vec<(u64, u64, String)> = report["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["serial"].as_u64().unwrap_or(0),
                d["address"].as_u64().unwrap(),
                d["settings"].as_str().unwrap().to_owned(),
            )
        })
        .collect();
    devices.sort();
    devices
}

/// The Fast Modbus devices of site-bus.json as `found` lists them.
fn site_bus_fast_devices() -> Vec<(u64, u64, String)> {
    vec![
        (0xFE00_0010, 10, "9600 8N2".into()),
        (0xFE00_0011, 10, "9600 8N2".into()),
        (0xFE00_0020, 20, "115200 8N2".into()),
        (0xFE00_0030, 30, "19200 8O1".into()),
        (0xFE00_0031, 31, "19200 8O1".into()),
    ]
}

fn device(report: &Value, serial: u64) -> &Value {
    report["devices"]
        .as_array()
        .unwrap()
        .iter()
        .find(|d| d["serial"].as_u64() == Some(serial))
        .unwrap_or_else(|| panic!("serial {serial:#X} not found in {report}"))
}

#[test]
fn scan_finds_every_fast_device_at_its_settings_and_flags_the_duplicate() {
    let sim = sim();
    // Whatever the port was set to before the scan, it is set to again after.
    let before = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.pty)
        .unwrap();
    let mut settings = termios::tcgetattr(&before).unwrap();
    termios::cfmakeraw(&mut settings);
    settings
        .control_flags
        .insert(ControlFlags::PARENB | ControlFlags::PARODD);
    settings.control_flags.remove(ControlFlags::CSTOPB);
    termios::cfsetspeed(&mut settings, BaudRate::B57600).unwrap();
    termios::tcsetattr(&before, SetArg::TCSANOW, &settings).unwrap();
    let report = scan_json(&sim, &[]);
    // 8 baud rates × 3 parities sent, each covering 1 and 2 stop bits.
    assert_eq!(report["port_settings_scanned"], 48);
    assert_eq!(report["transmissions"], 24);
    assert_eq!(found(&report), site_bus_fast_devices(), "{report:#}");
    let relay = device(&report, 0xFE00_0011);
    assert_eq!(relay["model"], "WBMR6C");
    assert_eq!(relay["firmware"], "1.26.1");
    assert_eq!(relay["fast_modbus"], true);
    assert_eq!(relay["stop_bits"], 2);
    assert_eq!(relay["also_at"], json!(["9600 8E2"]));
    // Heard by a master sending 2 stop bits; the registers say 1.
    let odd = device(&report, 0xFE00_0030);
    assert_eq!(odd["stop_bits"], 1);
    assert_eq!(odd["also_at"], json!([]));
    assert_eq!(
        report["duplicates"],
        json!([{"settings": "9600 8N2", "address": 10, "serials": [0xFE00_0010u32, 0xFE00_0011u32]}])
    );
    let settings = termios::tcgetattr(&before).unwrap();
    assert_eq!(termios::cfgetospeed(&settings), BaudRate::B57600);
    assert!(settings.control_flags.contains(ControlFlags::PARODD));
    assert!(!settings.control_flags.contains(ControlFlags::CSTOPB));
}

#[test]
fn scan_table_names_the_duplicate_and_how_to_fix_it() {
    let sim = sim();
    let port = port(&sim);
    let run = tool(&[
        "scan",
        "--port",
        &port,
        "--baud",
        "9600",
        "--parity",
        "N",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("duplicate: address 10 at 9600 8N2 is used by 2 devices"),
        "{}",
        run.stdout
    );
    // The command to paste, with the real port.
    assert!(
        run.stdout.contains(&format!(
            "fix with rtu2mqtt fix-addresses --port {port} --apply"
        )),
        "{}",
        run.stdout
    );
    assert_eq!(
        run.stdout.matches("DUPLICATE ADDRESS").count(),
        2,
        "{}",
        run.stdout
    );
}

#[test]
fn classic_scan_finds_the_device_without_fast_modbus() {
    let sim = sim();
    let fast_only = scan_json(
        &sim,
        &["--baud", "115200", "--parity", "N", "--stop-bits", "2"],
    );
    assert_eq!(
        found(&fast_only),
        vec![(0xFE00_0020, 20, "115200 8N2".into())]
    );
    let report = scan_json(
        &sim,
        &[
            "--baud",
            "115200",
            "--parity",
            "N",
            "--stop-bits",
            "2",
            "--classic",
            "--range",
            "15-45",
            "--timeout",
            "150",
        ],
    );
    assert_eq!(
        found(&report),
        vec![
            (0xFE00_0020, 20, "115200 8N2".into()),
            (0xFE00_0040, 40, "115200 8N2".into()),
        ],
        "{report:#}"
    );
    let classic = device(&report, 0xFE00_0040);
    assert_eq!(classic["fast_modbus"], false);
    assert_eq!(classic["model"], "OLDBOX");
}

#[test]
fn scan_config_snippet_picks_the_template_by_model() {
    let sim = sim();
    let port = port(&sim);
    let templates = sim_support::data("");
    let run = tool(&[
        "scan",
        "--port",
        &port,
        "--baud",
        "19200",
        "--parity",
        "O",
        "--config",
        "--latency",
        LATENCY_MS,
        "--templates",
        templates.to_str().unwrap(),
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let snippet: Value = serde_json::from_str(&run.stdout).unwrap();
    assert_eq!(
        snippet["ports"][0]["devices"],
        json!([{"slave_id": 30, "device_type": "sim-relay"}, {"slave_id": 31, "device_type": "sim-relay"}])
    );
    assert_eq!(snippet["ports"][0]["baud_rate"], 19200);
    assert_eq!(snippet["ports"][0]["parity"], "O");
    assert_eq!(snippet["ports"][0]["stop_bits"], 1);
}

#[test]
fn scan_errors_say_what_is_wrong_with_the_port() {
    let missing = tool(&["scan", "--port", "/dev/ttyNOSUCH-rtu2mqtt"]);
    assert_eq!(missing.code, 3, "{}", missing.stderr);
    assert!(
        missing.stderr.contains("does not exist"),
        "{}",
        missing.stderr
    );

    let sim = sim();
    let port = port(&sim);
    let holder = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.pty)
        .unwrap();
    let lock =
        nix::fcntl::Flock::lock(holder, nix::fcntl::FlockArg::LockExclusiveNonblock).unwrap();
    let busy = tool(&["scan", "--port", &port]);
    assert_eq!(busy.code, 3, "{}", busy.stderr);
    assert!(busy.stderr.contains("is busy"), "{}", busy.stderr);
    drop(lock);

    let nobody = tool(&[
        "scan",
        "--port",
        &port,
        "--baud",
        "38400",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(nobody.code, 1, "{}{}", nobody.stdout, nobody.stderr);
    assert!(
        nobody.stderr.contains("no device answered"),
        "{}",
        nobody.stderr
    );
}

#[test]
fn fix_addresses_plans_then_applies_and_a_second_scan_confirms() {
    let sim = sim();
    let port = port(&sim);
    let only_9600 = [
        "--baud",
        "9600,115200",
        "--parity",
        "N",
        "--latency",
        LATENCY_MS,
    ];
    let mut dry = vec!["fix-addresses", "--port", &port, "--range", "10-30"];
    dry.extend_from_slice(&only_9600);
    let run = tool(&dry);
    assert_eq!(run.code, 1, "duplicates left: {}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("serial 4261412881 (0xFE000011) at 9600 8N?: address 10 -> 11 (planned)"),
        "{}",
        run.stdout
    );
    // The dry run wrote nothing.
    let control = sim
        .control(json!({"cmd": "get", "serial": "0xFE000011", "type": "holding", "address": 128}));
    assert_eq!(control["value"], 10);

    let mut apply = dry.clone();
    apply.push("--apply");
    let run = tool(&apply);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("address 10 -> 11 (confirmed by a new scan)"),
        "{}",
        run.stdout
    );
    let control = sim
        .control(json!({"cmd": "get", "serial": "0xFE000011", "type": "holding", "address": 128}));
    assert_eq!(control["value"], 11);

    let report = scan_json(&sim, &["--baud", "9600", "--parity", "N"]);
    assert_eq!(
        found(&report),
        vec![
            (0xFE00_0010, 10, "9600 8N2".into()),
            (0xFE00_0011, 11, "9600 8N2".into())
        ]
    );
    assert_eq!(report["duplicates"], json!([]));
    let mut again = vec!["fix-addresses", "--port", &port];
    again.extend_from_slice(&only_9600);
    assert_eq!(tool(&again).code, 0);
}

#[test]
fn set_address_by_serial_is_verified_and_refuses_a_taken_address() {
    let sim = sim();
    let port = port(&sim);
    let odd = [
        "--baud",
        "19200",
        "--parity",
        "O",
        "--stop-bits",
        "1",
        "--latency",
        LATENCY_MS,
    ];
    let mut taken = vec![
        "set-address",
        "--port",
        &port,
        "--serial",
        "0xFE000031",
        "--address",
        "30",
    ];
    taken.extend_from_slice(&odd);
    let run = tool(&taken);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("already used at 19200 8O1"),
        "{}",
        run.stderr
    );

    // Decimal serial, settings found by the scan (no --baud).
    let run = tool(&[
        "set-address",
        "--port",
        &port,
        "--serial",
        "4261412913",
        "--address",
        "77",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("address 31 -> 77 (confirmed by a scan)"),
        "{}",
        run.stdout
    );
    let control = sim
        .control(json!({"cmd": "get", "serial": "0xFE000031", "type": "holding", "address": 128}));
    assert_eq!(control["value"], 77);

    let mut missing = vec![
        "set-address",
        "--port",
        &port,
        "--serial",
        "0x12345678",
        "--address",
        "5",
    ];
    missing.extend_from_slice(&odd);
    let run = tool(&missing);
    assert_eq!(run.code, 1);
    assert!(
        run.stderr
            .contains("no device with serial 305419896 (0x12345678)"),
        "{}",
        run.stderr
    );
}

const AT_115200: [&str; 8] = [
    "--baud",
    "115200",
    "--parity",
    "N",
    "--stop-bits",
    "2",
    "--latency",
    LATENCY_MS,
];

fn access(sim: &SimProcess, args: &[&str]) -> Run {
    let port = port(sim);
    let mut all = vec![args[0], "--port", &port];
    all.extend_from_slice(&args[1..]);
    tool(&all)
}

/// `write` of `value` to holding `reg` of the device at `address`, at 115200 8N2, with
/// `options` (`--format`, `--timeout`, ...).
fn write_holding(sim: &SimProcess, address: &str, reg: &str, options: &[&str], value: &str) -> Run {
    let mut args = vec![
        "write",
        "--address",
        address,
        "--type",
        "holding",
        "--reg",
        reg,
    ];
    args.extend_from_slice(options);
    args.extend_from_slice(&AT_115200);
    args.extend_from_slice(&["--", value]);
    access(sim, &args)
}

#[test]
fn read_prints_raw_and_decoded_values_by_address_and_by_serial() {
    let sim = sim();
    sim.control(json!({"cmd": "set", "device": "fast-relay", "type": "holding", "address": 1000, "value": [0xFFFF, 0xFFFB]}));
    let mut args = vec![
        "read",
        "--address",
        "20",
        "--type",
        "holding",
        "--reg",
        "1000",
        "--format",
        "s32",
    ];
    args.extend_from_slice(&AT_115200);
    let run = access(&sim, &args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout.contains("[1000]: 0xFFFF  65535"),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout.contains("[1001]: 0xFFFB  65531"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("s32: -5"), "{}", run.stdout);

    // By serial: the two devices at address 10 are told apart; the setting is found by a scan.
    for (serial, value) in [("0xFE000010", 3300), ("0xFE000011", 5000)] {
        let run = access(
            &sim,
            &[
                "read",
                "--serial",
                serial,
                "--type",
                "input",
                "--reg",
                "123",
                "--json",
                "--latency",
                LATENCY_MS,
            ],
        );
        assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
        let body: Value = serde_json::from_str(&run.stdout).unwrap();
        assert_eq!(body["registers"], json!([value]));
        assert_eq!(body["settings"], "9600 8N2");
    }

    // Classic-only device, its settings given.
    let mut args = vec![
        "read",
        "--address",
        "40",
        "--type",
        "holding",
        "--reg",
        "128",
        "--json",
    ];
    args.extend_from_slice(&AT_115200);
    let run = access(&sim, &args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert_eq!(
        serde_json::from_str::<Value>(&run.stdout).unwrap()["values"],
        json!(["40"])
    );
}

#[test]
fn read_failures_are_explained() {
    let sim = sim();
    let mut args = vec![
        "read",
        "--address",
        "20",
        "--type",
        "holding",
        "--reg",
        "5000",
    ];
    args.extend_from_slice(&AT_115200);
    let run = access(&sim, &args);
    assert_eq!(run.code, 1);
    assert!(
        run.stderr
            .contains("refused: exception 2 (illegal data address)"),
        "{}",
        run.stderr
    );

    let mut args = vec![
        "read",
        "--address",
        "99",
        "--type",
        "holding",
        "--reg",
        "0",
        "--timeout",
        "100",
    ];
    args.extend_from_slice(&AT_115200);
    let run = access(&sim, &args);
    assert_eq!(run.code, 1);
    assert!(
        run.stderr
            .contains("no reply from address 99 at 115200 8N2"),
        "{}",
        run.stderr
    );

    // Both devices at address 10 answer a classic request: the reply is unreadable.
    let run = access(
        &sim,
        &[
            "read",
            "--address",
            "10",
            "--type",
            "holding",
            "--reg",
            "128",
            "--baud",
            "9600",
            "--parity",
            "N",
            "--stop-bits",
            "2",
            "--latency",
            LATENCY_MS,
        ],
    );
    assert_eq!(run.code, 1);
    assert!(
        run.stderr.contains("a duplicate address?"),
        "{}",
        run.stderr
    );
}

#[test]
fn write_sets_registers_and_coils_and_reads_them_back() {
    let sim = sim();
    let mut args = vec![
        "write",
        "--serial",
        "0xFE000020",
        "--type",
        "holding",
        "--reg",
        "1000",
        "--format",
        "s32",
    ];
    args.extend_from_slice(&AT_115200);
    args.extend_from_slice(&["--", "-5", "70000"]);
    let run = access(&sim, &args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("s32: -5 70000"), "{}", run.stdout);
    let control = sim.control(json!({"cmd": "get", "device": "fast-relay", "type": "holding", "address": 1000, "count": 4}));
    assert_eq!(control["values"], json!([0xFFFF, 0xFFFB, 0x0001, 0x1170]));

    let mut args = vec!["write", "--address", "20", "--type", "coil", "--reg", "2"];
    args.extend_from_slice(&AT_115200);
    args.push("1");
    let run = access(&sim, &args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let control =
        sim.control(json!({"cmd": "get", "device": "fast-relay", "type": "coil", "address": 2}));
    assert_eq!(control["value"], 1);

    let mut args = vec!["write", "--address", "20", "--type", "input", "--reg", "2"];
    args.extend_from_slice(&AT_115200);
    args.push("1");
    let run = access(&sim, &args);
    assert_eq!(run.code, 2);
    assert!(run.stderr.contains("read-only"), "{}", run.stderr);

    // An option after `--` (there for the negative value) is named, not read as a number;
    // nothing is written.
    let args = [
        "write",
        "--address",
        "20",
        "--type",
        "holding",
        "--reg",
        "1000",
        "--format",
        "s32",
        "--",
        "-2",
        "--baud",
        "115200",
    ];
    let run = access(&sim, &args);
    assert_eq!(run.code, 2, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("\"--baud\" is not a value: options go before `--`"),
        "{}",
        run.stderr
    );
    let control = sim.control(json!({"cmd": "get", "device": "fast-relay", "type": "holding", "address": 1000, "count": 2}));
    assert_eq!(control["values"], json!([0xFFFF, 0xFFFB]));
}

/// Latency for a test whose check needs the first scan start's reply: a late one (a loaded
/// test machine) would be taken for "nobody at this setting".
const SLOW_START_MS: &str = "300";

/// `write --address 10` (and `read`) with no single port setting named: the scan finds address
/// 10 at 9600 8N2 held by TWO devices (relay-a and relay-b). A request by address would reach both
/// (a write changes both, and their replies collide), so the tool refuses before sending
/// anything and names `--serial` for each and `fix-addresses`.
#[test]
fn write_and_read_by_address_refuse_a_duplicate_the_scan_just_saw() {
    let sim = sim();
    let run = access(
        &sim,
        &[
            "write",
            "--address",
            "10",
            "--type",
            "coil",
            "--reg",
            "2",
            "--baud",
            "9600,115200",
            "--parity",
            "N",
            "--latency",
            SLOW_START_MS,
            "1",
        ],
    );
    let a = sim.control(json!({"cmd": "get", "device": "relay-a", "type": "coil", "address": 2}));
    let b = sim.control(json!({"cmd": "get", "device": "relay-b", "type": "coil", "address": 2}));
    assert!(
        a["value"] == 0 && b["value"] == 0,
        "a device at the duplicate address was written (relay-a coil 2 = {}, relay-b coil 2 = \
         {}); exit {}\nstdout: {}\nstderr: {}",
        a["value"],
        b["value"],
        run.code,
        run.stdout,
        run.stderr
    );
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    for words in [
        "address 10 at 9600 8N2 is used by 2 devices",
        "--serial 4261412880",
        "--serial 4261412881",
        "fix-addresses",
    ] {
        assert!(run.stderr.contains(words), "{words:?} in {}", run.stderr);
    }
    let run = access(
        &sim,
        &[
            "read",
            "--address",
            "10",
            "--type",
            "coil",
            "--reg",
            "2",
            "--baud",
            "9600,115200",
            "--parity",
            "N",
            "--latency",
            SLOW_START_MS,
        ],
    );
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("is used by 2 devices") && run.stdout.is_empty(),
        "{}{}",
        run.stdout,
        run.stderr
    );
}

/// `write` takes a value as typed: a fraction into an integer format, or a negative number into
/// an unsigned one, is a bad argument (exit 2) that names the format to use, and nothing is
/// written; the daemon's codec would round 55.7 to 56 and wrap -5 to 0xFFFB.
#[test]
fn write_refuses_values_an_integer_format_cannot_hold_exactly() {
    let sim = sim();
    let holding_1000 = || {
        sim.control(json!({"cmd": "get", "device": "fast-relay", "type": "holding", "address": 1000, "count": 2}))
            ["values"]
            .clone()
    };
    sim.control(json!({"cmd": "set", "device": "fast-relay", "type": "holding", "address": 1000, "value": [7, 7]}));
    let write =
        |format: &str, value: &str| write_holding(&sim, "20", "1000", &["--format", format], value);
    for (format, value, words) in [
        (
            "u16",
            "55.7",
            vec!["55.7 is not a whole number", "--format float"],
        ),
        (
            "s16",
            "2.5",
            vec!["2.5 is not a whole number", "--format float"],
        ),
        (
            "u32",
            "0.5",
            vec!["0.5 is not a whole number", "--format double"],
        ),
        (
            "u16",
            "-5",
            vec!["-5 is negative", "0 … 65535", "--format s16"],
        ),
        (
            "u16",
            "70000",
            vec!["70000 is out of range for u16: allowed 0 … 65535"],
        ),
        ("s16", "40000", vec!["allowed -32768 … 32767"]),
    ] {
        let run = write(format, value);
        assert_eq!(
            run.code, 2,
            "{format} {value}: {}{}",
            run.stdout, run.stderr
        );
        for words in words {
            assert!(
                run.stderr.contains(words),
                "{format} {value}: {words:?} in {}",
                run.stderr
            );
        }
        assert_eq!(
            holding_1000(),
            json!([7, 7]),
            "{format} {value} was written"
        );
    }
    // Hex is a whole number; a whole number written with a point is that number.
    let run = write("u16", "0xFFFF");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert_eq!(holding_1000(), json!([0xFFFF, 7]));
    let run = write("s32", "-70000.0");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert_eq!(holding_1000(), json!([0xFFFE, 0xEE90]));
}

/// The write is answered, but the read-back is not (the device took a new address from the
/// write, so nothing answers at the old one): the value is not verified, exit 1.
#[test]
fn write_whose_read_back_fails_is_not_verified() {
    let sim = sim();
    let run = write_holding(&sim, "40", "128", &["--timeout", "100"], "41");
    let address = sim
        .control(json!({"cmd": "get", "serial": "0xFE000040", "type": "holding", "address": 128}));
    assert_eq!(address["value"], 41, "the write was carried out");
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "written, but reading back failed: no reply from address 40 at 115200 8N2 within \
             100 ms"
        ),
        "{}",
        run.stderr
    );

    // A command register: the acknowledgement is the result, nothing is read back.
    let run = write_holding(
        &sim,
        "41",
        "128",
        &["--timeout", "100", "--no-read-back"],
        "42",
    );
    let address = sim
        .control(json!({"cmd": "get", "serial": "0xFE000040", "type": "holding", "address": 128}));
    assert_eq!(address["value"], 42, "the write was carried out");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("written: the device acknowledged it (not read back: --no-read-back)"),
        "{}",
        run.stdout
    );
    assert!(!run.stderr.contains("reading back"), "{}", run.stderr);
}

/// The service (the real daemon) on the simulator's pty, polling the `sim-relay` at 20, once it
/// has advertised `port/Load`: what the site tools go through when the port is busy.
fn service_polling_the_relay(
    broker: &mqtt_support::Mosquitto,
    sim: &SimProcess,
    client_id: &str,
) -> daemon_support::DaemonProcess {
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": client_id},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2,
                   "devices": [{"device_type": "sim-relay", "slave_id": 20}]}]
    });
    let data = sim_support::data("");
    let daemon = daemon_support::DaemonProcess::start(
        &config,
        &["--templates", data.to_str().unwrap()],
        std::process::Stdio::null(),
        std::process::Stdio::null(),
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(mqtt_support::wait_for(
        "the advertised port/Load method",
        || async {
            let state = mqtt_support::retained(broker.port).await?;
            (state.get("/rpc/v1/wb-mqtt-serial/port/Load")? == "1").then_some(())
        },
    ));
    daemon
}

/// A simulator on a bus of these devices.
fn bus_of(devices: Value) -> (tempfile::TempDir, SimProcess) {
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(&bus, json!({ "devices": devices }).to_string()).unwrap();
    let sim = SimProcess::start_with(&bus, &sim_support::data(""), &[]);
    (dir, sim)
}

/// A string value takes the registers its text needs from `--reg` on (`string`: one character
/// per register, `string8`: two), and reads those back; more than one request carries is a bad
/// argument.
#[test]
fn write_string_takes_the_registers_its_text_needs() {
    let relay = sim_support::data("relay.json");
    let (_dir, sim) = bus_of(json!([
        {"name": "relay", "template": relay.to_str().unwrap(), "address": 20,
         "serial": "0xFE000020", "line": "115200 8N2",
         "registers": [{"type": "holding", "address": 1000, "count": 8}],
         "values": {"holding:1000": [9, 9, 9, 9, 9, 9, 9, 9]}}
    ]));
    let holding = || {
        sim.control(json!({"cmd": "get", "device": "relay", "type": "holding", "address": 1000, "count": 8}))
            ["values"]
            .clone()
    };
    let write =
        |format: &str, value: &str| write_holding(&sim, "20", "1000", &["--format", format], value);
    let run = write("string", "hello");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("[1004]: 0x006F  111"), "{}", run.stdout);
    assert!(run.stdout.contains("string: hello"), "{}", run.stdout);
    assert_eq!(holding(), json!([104, 101, 108, 108, 111, 9, 9, 9]));

    let run = write("string8", "hello");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("string8: hello"), "{}", run.stdout);
    assert_eq!(
        holding(),
        json!([0x6865, 0x6C6C, 0x6F00, 108, 111, 9, 9, 9])
    );
    assert!(
        run.stderr
            .contains("note: only the 3 register(s) the text needs are written"),
        "{}",
        run.stderr
    );

    // Over the field's size: the rest of the field is cleared, as wb-mqtt-serial writes a
    // string channel.
    let run = write_holding(
        &sim,
        "20",
        "1000",
        &["--format", "string", "--count", "8"],
        "hi",
    );
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(!run.stderr.contains("note:"), "{}", run.stderr);
    assert_eq!(holding(), json!([104, 105, 0, 0, 0, 0, 0, 0]));
    let run = write_holding(&sim, "20", "1000", &["--count", "2"], "7");
    assert_eq!(run.code, 2, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("--count is for a string value"),
        "{}",
        run.stderr
    );
    assert_eq!(
        holding(),
        json!([104, 105, 0, 0, 0, 0, 0, 0]),
        "nothing written"
    );

    let long = "x".repeat(124);
    let run = write("string", &long);
    assert_eq!(run.code, 2, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("124 registers to write: one Modbus request carries 1..=123 registers"),
        "{}",
        run.stderr
    );
}

/// `write --address 20` with no single port setting named: the scan of the whole plan sees
/// address 20 at 9600 8N2 (relay "near") and at 115200 8N2 (relay "far"). The request is not
/// sent to the first one found: the tool names both with their settings and how to pick one.
/// Address 21 is one device seen at two settings (the pty cannot tell N from E): one device.
#[test]
fn a_request_by_address_refuses_devices_with_that_address_at_different_settings() {
    let relay = sim_support::data("relay.json");
    let relay = relay.to_str().unwrap();
    let (_dir, sim) = bus_of(json!([
        {"name": "near", "template": relay, "address": 20, "serial": "0xFE000020",
         "line": "9600 8N2"},
        {"name": "far", "template": relay, "address": 20, "serial": "0xFE000021",
         "line": "115200 8N2"},
        {"name": "single", "template": relay, "address": 21, "serial": "0xFE000022",
         "line": "115200 8N2", "values": {"input:123": 3300}}
    ]));
    let plan = [
        "--baud",
        "9600,115200",
        "--parity",
        "N,E",
        "--latency",
        SLOW_START_MS,
    ];
    let mut args = vec!["write", "--address", "20", "--type", "coil", "--reg", "2"];
    args.extend_from_slice(&plan);
    args.push("1");
    let run = access(&sim, &args);
    let coil = |device: &str| {
        sim.control(json!({"cmd": "get", "device": device, "type": "coil", "address": 2}))["value"]
            .clone()
    };
    assert!(
        coil("near") == 0 && coil("far") == 0,
        "a device with address 20 was written; exit {}\nstdout: {}\nstderr: {}",
        run.code,
        run.stdout,
        run.stderr
    );
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    for words in [
        "address 20 is used by 2 devices at different port settings",
        "serial 4261412896 (0xFE000020) at 9600 8N2",
        "serial 4261412897 (0xFE000021) at 115200 8N2",
        "--serial 4261412896 or --serial 4261412897",
        "--baud, --parity and --stop-bits",
    ] {
        assert!(run.stderr.contains(words), "{words:?} in {}", run.stderr);
    }

    let mut args = vec![
        "read",
        "--address",
        "21",
        "--type",
        "input",
        "--reg",
        "123",
        "--json",
    ];
    args.extend_from_slice(&plan);
    let run = access(&sim, &args);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let body: Value = serde_json::from_str(&run.stdout).unwrap();
    assert_eq!(body["settings"], "115200 8N2", "{body}");
    assert_eq!(body["registers"], json!([3300]), "{body}");
}

/// Through the running service, `read` and `write` say what failed in the words they use on the
/// port itself: an exception as `refused: exception 2 (illegal data address)`, silence as "no
/// reply … within N ms" (not "the service refused", not the settings twice); a read-back that
/// fails leaves the write not verified (exit 1); a value the format cannot hold is refused as
/// on the port.
#[test]
fn read_and_write_through_the_service_explain_failures_as_on_the_port() {
    let broker = mqtt_support::Mosquitto::start();
    let relay = sim_support::data("relay.json");
    let (_dir, sim) = bus_of(json!([
        {"name": "relay", "template": relay.to_str().unwrap(), "address": 20,
         "serial": "0xFE000020", "line": "115200 8N2", "model": "WBMR6C", "firmware": "1.26.0",
         "registers": [{"type": "holding", "address": 1000, "count": 2}]},
        {"name": "meter", "address": 30, "serial": "0x0D00001E", "line": "115200 8N2",
         "fast": false, "registers": [{"type": "holding", "address": 0, "count": 8}]}
    ]));
    let _daemon = service_polling_the_relay(&broker, &sim, "rtu2mqtt-site-tools-rw");
    let broker_option = format!("127.0.0.1:{}", broker.port);
    let via_service = |args: &[&str]| {
        let mut all = args.to_vec();
        all.extend_from_slice(&["--via-mqtt", "--broker", &broker_option]);
        access(&sim, &all)
    };

    let run = via_service(&[
        "read",
        "--address",
        "20",
        "--type",
        "holding",
        "--reg",
        "5000",
    ]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("address 20 at 115200 8N2 refused: exception 2 (illegal data address)"),
        "{}",
        run.stderr
    );

    let run = via_service(&[
        "read",
        "--address",
        "99",
        "--type",
        "holding",
        "--reg",
        "0",
        "--timeout",
        "100",
    ]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "no reply from address 99 at 115200 8N2 within 100 ms: check the address/serial"
        ) && !run.stderr.contains("refused"),
        "{}",
        run.stderr
    );

    let run = via_service(&[
        "write",
        "--address",
        "20",
        "--type",
        "holding",
        "--reg",
        "1000",
        "55.7",
    ]);
    assert_eq!(run.code, 2, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("55.7 is not a whole number"),
        "{}",
        run.stderr
    );
    let holding =
        sim.control(json!({"cmd": "get", "device": "relay", "type": "holding", "address": 1000}));
    assert_eq!(holding["value"], 0, "nothing written");

    // The meter takes a new address from the write: nothing answers the read-back at 30.
    let run = via_service(&[
        "write",
        "--address",
        "30",
        "--type",
        "holding",
        "--reg",
        "128",
        "--timeout",
        "100",
        "31",
    ]);
    let meter =
        sim.control(json!({"cmd": "get", "device": "meter", "type": "holding", "address": 128}));
    assert_eq!(meter["value"], 31, "the write was carried out");
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "written, but reading back failed: no reply from address 30 at 115200 8N2 within \
             100 ms"
        ),
        "{}",
        run.stderr
    );

    // --no-read-back: the acknowledgement is the result, through the service too.
    let run = via_service(&[
        "write",
        "--address",
        "31",
        "--type",
        "holding",
        "--reg",
        "128",
        "--timeout",
        "100",
        "--no-read-back",
        "32",
    ]);
    let meter =
        sim.control(json!({"cmd": "get", "device": "meter", "type": "holding", "address": 128}));
    assert_eq!(meter["value"], 32, "the write was carried out");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("written: the device acknowledged it (not read back: --no-read-back)"),
        "{}",
        run.stdout
    );
}

/// Runs `rtu2mqtt events` in the background; its stdout lines arrive on the channel.
fn spawn_events(args: &[&str]) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    use std::io::BufRead;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            if sender.send(line).is_err() {
                break;
            }
        }
    });
    (child, receiver)
}

fn next_json(lines: &std::sync::mpsc::Receiver<String>) -> Value {
    let line = lines
        .recv_timeout(std::time::Duration::from_secs(30))
        .expect("events printed nothing more");
    serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"))
}

#[test]
fn events_are_decoded_named_from_the_config_and_acknowledged() {
    let sim = sim();
    let port = port(&sim);
    let config = sim.dir.path().join("config.json");
    std::fs::write(
        &config,
        json!({
            "ports": [{"path": port, "baud_rate": 115200, "parity": "N", "data_bits": 8, "stop_bits": 2,
                       "devices": [{"device_type": "sim-relay", "slave_id": 20}]}]
        })
        .to_string(),
    )
    .unwrap();
    let templates = sim_support::data("");
    let (mut child, lines) = spawn_events(&[
        "events",
        "--port",
        &port,
        "--config",
        config.to_str().unwrap(),
        "--templates",
        templates.to_str().unwrap(),
        "--json",
        "--count",
        "2",
        "--latency",
        LATENCY_MS,
    ]);
    // The config's channels with events are enabled (K1..K3, the inputs, the counter); then the
    // device reports its start-up, and they are enabled again.
    let mut enabled = Vec::new();
    let mut reboot_seen = false;
    while !(reboot_seen && enabled.len() == 12) {
        let line = next_json(&lines);
        if line["reboot"] == true {
            reboot_seen = true;
        } else if line.get("enabled").is_some() {
            assert_eq!(line["enabled"], true, "{line}");
            enabled.push((
                line["type"].as_str().unwrap().to_owned(),
                line["register"].as_u64().unwrap(),
            ));
        } else {
            panic!("unexpected line before the values changed: {line}");
        }
    }
    assert!(enabled.contains(&("coil".into(), 0)), "{enabled:?}");
    assert!(enabled.contains(&("input".into(), 32)), "{enabled:?}");

    sim.control(
        json!({"cmd": "set", "device": "fast-relay", "type": "coil", "address": 0, "value": 1}),
    );
    let first = next_json(&lines);
    assert_eq!(
        (
            &first["address"],
            &first["type"],
            &first["register"],
            &first["value"],
            &first["channel"]
        ),
        (
            &json!(20),
            &json!("coil"),
            &json!(0),
            &json!(1),
            &json!("K1")
        ),
        "{first}"
    );
    assert!(
        first["device"].as_str().unwrap().contains("relay"),
        "{first}"
    );
    sim.control(
        json!({"cmd": "set", "device": "fast-relay", "type": "input", "address": 32, "value": 7}),
    );
    let second = next_json(&lines);
    assert_eq!(
        (&second["type"], &second["register"], &second["value"]),
        (&json!("input"), &json!(32), &json!(7)),
        "{second}"
    );
    assert_eq!(second["text"], "7", "{second}");
    // --count 2: the tool confirms the last packet and ends by itself.
    let status = child.wait().unwrap();
    assert!(status.success(), "{status}");
    // Confirmed: the device has nothing more to send.
    let after = tool(&[
        "events",
        "--port",
        &port,
        "--baud",
        "115200",
        "--parity",
        "N",
        "--stop-bits",
        "2",
        "--json",
        "--duration",
        "0.3",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(after.code, 0, "{}", after.stderr);
    assert_eq!(after.stdout, "", "the acknowledged events came again");
}

/// A device that takes no events (nobody at the address, or a classic device) is said and left
/// out; the tool goes on watching the others (it stopped at the first such device).
#[test]
fn events_watch_the_devices_that_took_them_when_another_did_not() {
    let sim = sim();
    let port = port(&sim);
    // Half a second of `events --json` at `line` ("19200 8O1"), enabling `enables`.
    let watch_events = |line: &str, enables: &[&str]| {
        let (baud, settings) = line.split_once(' ').unwrap();
        let (parity, stop_bits) = (&settings[1..2], &settings[2..]);
        let mut args = vec![
            "events",
            "--port",
            &port,
            "--baud",
            baud,
            "--parity",
            parity,
            "--stop-bits",
            stop_bits,
            "--json",
            "--duration",
            "0.5",
            "--latency",
            LATENCY_MS,
        ];
        for enable in enables {
            args.extend(["--enable", enable]);
        }
        tool(&args)
    };
    let run = watch_events("19200 8O1", &["30:coil:2", "99:coil:0"]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let enabled: Vec<Value> = run
        .stdout
        .lines()
        .filter_map(|line| serde_json::from_str::<Value>(line).ok())
        .filter(|line| line.get("enabled").is_some())
        .collect();
    // (Again after the device's start-up report: a reboot is answered by enabling anew.)
    assert!(
        !enabled.is_empty()
            && enabled.iter().all(|line| *line
                == json!({"enabled": true, "address": 30, "type": "coil", "register": 2})),
        "{}",
        run.stdout
    );
    assert!(
        run.stderr.contains(
            "address 99 at 19200 8O1: events not enabled (no reply, twice: not connected, or \
             another address?); watching the others"
        ),
        "{}",
        run.stderr
    );
    // Nobody took them: nothing to watch.
    let run = watch_events("19200 8O1", &["99:coil:0"]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("events were enabled on no device: nothing to watch")
            && !run.stderr.contains("watching the others"),
        "{}",
        run.stderr
    );
    // A classic device refuses the request as an unknown function: it has no events.
    let run = watch_events("115200 8N2", &["40:holding:0", "20:coil:0"]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "address 40 at 115200 8N2: events not enabled (the device refused, exception 1 \
             (illegal function): it has no Fast Modbus events"
        ),
        "{}",
        run.stderr
    );
}

#[test]
fn events_at_19200_8o1_with_enable_options() {
    let sim = sim();
    let port = port(&sim);
    let (mut child, lines) = spawn_events(&[
        "events",
        "--port",
        &port,
        "--baud",
        "19200",
        "--parity",
        "O",
        "--stop-bits",
        "1",
        "--enable",
        "30:coil:2",
        "--enable",
        "31:discrete:1:low",
        "--json",
        "--count",
        "2",
        "--latency",
        LATENCY_MS,
    ]);
    // Enabled, then each device reports its start-up and is enabled again.
    let mut reboots = 0;
    let mut enabled = 0;
    while !(reboots == 2 && enabled == 4) {
        let line = next_json(&lines);
        if line["reboot"] == true {
            reboots += 1;
        } else {
            assert_eq!(line["enabled"], true, "{line}");
            enabled += 1;
        }
    }
    sim.control(json!({"cmd": "set", "device": "odd-a", "type": "coil", "address": 2, "value": 1}));
    let first = next_json(&lines);
    assert_eq!(
        (
            &first["address"],
            &first["type"],
            &first["register"],
            &first["value"]
        ),
        (&json!(30), &json!("coil"), &json!(2), &json!(1))
    );
    assert_eq!(first["channel"], Value::Null);
    sim.control(
        json!({"cmd": "set", "device": "odd-b", "type": "discrete", "address": 1, "value": 1}),
    );
    let second = next_json(&lines);
    assert_eq!(
        (
            &second["address"],
            &second["type"],
            &second["register"],
            &second["value"]
        ),
        (&json!(31), &json!("discrete"), &json!(1), &json!(1))
    );
    assert!(child.wait().unwrap().success());
}

#[test]
fn ctrl_c_ends_events_with_130_and_restores_the_port_settings() {
    let sim = sim();
    let port = port(&sim);
    let before = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.pty)
        .unwrap();
    let mut settings = termios::tcgetattr(&before).unwrap();
    termios::cfmakeraw(&mut settings);
    termios::cfsetspeed(&mut settings, BaudRate::B4800).unwrap();
    termios::tcsetattr(&before, SetArg::TCSANOW, &settings).unwrap();
    let (child, lines) = spawn_events(&[
        "events",
        "--port",
        &port,
        "--baud",
        "115200",
        "--parity",
        "N",
        "--stop-bits",
        "2",
        "--enable",
        "20:coil:0",
        "--json",
        "--latency",
        LATENCY_MS,
    ]);
    // Running: it has enabled the events (and is now polling).
    assert_eq!(next_json(&lines)["enabled"], true);
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(i32::try_from(child.id()).unwrap()),
        nix::sys::signal::Signal::SIGINT,
    )
    .unwrap();
    let output = child.wait_with_output().unwrap();
    assert_eq!(output.status.code(), Some(130));
    let after = termios::tcgetattr(&before).unwrap();
    assert_eq!(termios::cfgetospeed(&after), BaudRate::B4800);
}

#[test]
fn bad_crc_at_one_setting_is_reported_and_the_scan_goes_on() {
    let sim = sim();
    sim.control(json!({"cmd": "faults", "device": "odd-a", "corrupt_crc": 1.0}));
    let report = scan_json(&sim, &["--baud", "19200,115200"]);
    let problems = report["problems"].as_array().unwrap();
    assert!(
        problems
            .iter()
            .any(|p| p["settings"] == "19200 8O2"
                && p["problem"].as_str().unwrap().contains("bad CRC")),
        "{report:#}"
    );
    // Every setting is still scanned, and the devices elsewhere found.
    assert!(
        found(&report).contains(&(0xFE00_0020, 20, "115200 8N2".into())),
        "{report:#}"
    );
    assert_eq!(report["port_settings_scanned"], 12);
    // The troubled one sent again with 1 stop bit (in case the port's receiver checks both),
    // where the corrupt replies stay corrupt.
    assert_eq!(report["transmissions"], 7);
    assert!(
        problems.iter().any(|p| p["settings"] == "19200 8O1"),
        "{report:#}"
    );
}

/// A scan reply lost to noise: its sender counts itself scanned (fast-modbus.md §3), so the
/// scan's "continue" never heard it again and the scan ended without it and without a word.
/// The setting is scanned again instead; a reply that stays unreadable is said, and the other
/// devices at that setting are still found.
#[test]
fn a_scan_reply_lost_to_noise_does_not_lose_its_device() {
    let sim = sim();
    let at_115200 = ["--baud", "115200", "--parity", "N", "--stop-bits", "2"];
    sim.control(json!({"cmd": "faults", "device": 20, "corrupt_crc": 1.0, "times": 1}));
    let report = scan_json(&sim, &at_115200);
    assert_eq!(
        found(&report),
        vec![(0xFE00_0020, 20, "115200 8N2".into())],
        "{report:#}"
    );
    assert_eq!(report["problems"], json!([]), "{report:#}");
    // A device whose replies are never read (as two devices whose serials share their lower
    // 28 bits, always answering at once): said, and the other device at its setting found.
    sim.control(json!({"cmd": "faults", "device": "relay-b", "corrupt_crc": 1.0}));
    let report = scan_json(
        &sim,
        &["--baud", "9600", "--parity", "N", "--stop-bits", "2"],
    );
    assert_eq!(
        found(&report),
        vec![(0xFE00_0010, 10, "9600 8N2".into())],
        "{report:#}"
    );
    let problems = report["problems"].as_array().unwrap();
    assert!(
        problems.iter().any(|p| p["settings"] == "9600 8N2"
            && p["problem"]
                .as_str()
                .unwrap()
                .contains("could not be read in 3 scans")),
        "{report:#}"
    );
}

/// Through a USB adapter that hands bytes over late (the simulator holds every byte 40 ms, more
/// than an FTDI chip's 16 ms latency timer), a scan whose allowance covers the delay finds every
/// device at its own setting, and nothing at the settings that follow one in use, where the
/// late bytes arrive.
#[test]
fn scan_through_a_slow_usb_adapter_finds_every_device_at_its_settings() {
    let sim = SimProcess::start("site-bus.json", &["--adapter-latency-ms", "40"]);
    let port = port(&sim);
    let run = tool(&["scan", "--port", &port, "--json", "--latency", LATENCY_MS]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let report: Value = serde_json::from_str(&run.stdout).unwrap();
    assert_eq!(found(&report), site_bus_fast_devices(), "{report:#}");
}

/// A controller's own UART hands bytes over as its receive FIFO fills: a 16550 collects 8
/// before it raises its interrupt, or waits for 4 quiet characters. The arbitration fillers of
/// these devices come every third window, so the FIFO hands the first one over only with the
/// 8th, 22 windows into the scan (about 270 ms at 1200 baud, well past the first window and the
/// allowance). Told of the FIFO (`--fifo-trigger`, as the kernel tells it on a real port), the
/// scan waits for the whole arbitration and finds both devices; without, it found none.
#[test]
fn scan_through_a_receive_fifo_waits_for_the_fillers_it_holds() {
    let sim = SimProcess::start("fifo-bus.json", &["--rx-fifo-trigger", "8"]);
    let report = scan_json(
        &sim,
        &["--baud", "1200", "--parity", "N", "--fifo-trigger", "8"],
    );
    assert_eq!(
        found(&report),
        vec![
            (0xFDB6_DB6D, 50, "1200 8N2".into()),
            (0xFDB6_DB6F, 51, "1200 8N2".into()),
        ],
        "{report:#}"
    );
    assert_eq!(report["problems"], json!([]), "{report:#}");
}

/// Serial numbers with long runs of 1 bits leave many arbitration windows silent (a recessive
/// bit sends nothing); the winner's frame comes after the last window. An independent device
/// stack found the scan giving such devices up after 20 ms without a byte ("no device
/// answered ... check wiring"): at 9600 any serial with 14 bits of 1 in a row, at 4800 with 7.
#[test]
fn scan_finds_devices_whose_serials_leave_arbitration_windows_silent() {
    let sim = SimProcess::start("silent-windows-bus.json", &[]);
    let report = scan_json(&sim, &["--baud", "9600,4800", "--parity", "N"]);
    assert_eq!(
        found(&report),
        vec![
            (0xFE00_FE00, 61, "4800 8N2".into()),
            (0xFE7F_FFFF, 60, "9600 8N2".into()),
        ],
        "{report:#}"
    );
    assert_eq!(report["problems"], json!([]), "{report:#}");
}

/// Devices that differ only in stop bits answer the same transmission: each is found once, at
/// the stop bits its registers report, and a shared address is a duplicate whatever the stop
/// bits. `--stop-bits 1` lists only the device that reports 1.
#[test]
fn stop_bits_come_from_the_devices_and_do_not_split_a_duplicate() {
    let sim = SimProcess::start("stop-bits-bus.json", &[]);
    let report = scan_json(&sim, &["--baud", "9600,19200"]);
    assert_eq!(report["transmissions"], 6);
    assert_eq!(report["port_settings_scanned"], 12);
    assert_eq!(
        found(&report),
        vec![
            (0xFE00_0101, 10, "9600 8N1".into()),
            (0xFE00_0102, 10, "9600 8N2".into()),
            (0xFE00_0103, 12, "19200 8E2".into()),
        ],
        "{report:#}"
    );
    // Not "also at" 9600 8N2: that is its own setting on the wire. (The pty cannot send parity
    // E, so the 8E2 transmission reached it too.)
    assert_eq!(device(&report, 0xFE00_0101)["also_at"], json!(["9600 8E2"]));
    assert_eq!(device(&report, 0xFE00_0101)["stop_bits"], 1);
    // Likewise the 8N2 transmission reached "even", first; its registers say E.
    assert_eq!(
        device(&report, 0xFE00_0103)["also_at"],
        json!(["19200 8N2"])
    );
    assert_eq!(
        report["duplicates"],
        json!([{"settings": "9600 8N (any stop bits)", "address": 10,
                "serials": [0xFE00_0101u32, 0xFE00_0102u32]}])
    );

    let port = port(&sim);
    let run = tool(&[
        "scan",
        "--port",
        &port,
        "--baud",
        "9600",
        "--parity",
        "N",
        "--config",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("9600 8N2: stop bits 2, as the devices here use 1 and 2"),
        "{}",
        run.stdout
    );
    let body = &run.stdout[run.stdout.find('{').unwrap()..];
    let snippet: Value = serde_json::from_str(body).unwrap();
    assert_eq!(snippet["ports"].as_array().unwrap().len(), 1, "{snippet:#}");
    assert_eq!(snippet["ports"][0]["stop_bits"], 2);

    let one = scan_json(
        &sim,
        &["--baud", "9600", "--parity", "N", "--stop-bits", "1"],
    );
    assert_eq!(
        found(&one),
        vec![(0xFE00_0101, 10, "9600 8N1".into())],
        "{one:#}"
    );
    assert_eq!(one["other_stop_bits"], 1);
    assert_eq!(one["port_settings_scanned"], 1);
}

/// Through the service, a port whose config has no event channels is said to have nothing to
/// show (before any broker is asked), instead of waiting for events that never come.
#[test]
fn events_through_the_service_on_a_port_without_event_channels_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/ttyRS485-9", "baud_rate": 9600, "devices": [
            {"device_type": "rtu2mqtt-energy-meter", "slave_id": 1}]}]}"#,
    )
    .unwrap();
    let run = tool(&[
        "events",
        "--port",
        "/dev/ttyRS485-9",
        "--via-mqtt",
        "--broker",
        "127.0.0.1:1",
        "--config",
        config.to_str().unwrap(),
    ]);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("no channel of /dev/ttyRS485-9 in ")
            && run
                .stderr
                .contains("has events (sporadic or semi-sporadic)"),
        "{}",
        run.stderr
    );
}

/// A bus where a device without Fast Modbus (address 11) sits at the setting of two Fast Modbus
/// devices that share address 10: the Fast Modbus scan does not see it.
fn classic_neighbour_bus() -> (tempfile::TempDir, SimProcess) {
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let relay = sim_support::data("relay.json");
    let relay = relay.to_str().unwrap();
    std::fs::write(
        &bus,
        json!({"devices": [
            {"name": "relay-a", "template": relay, "address": 10, "serial": "0xFE000010",
             "line": "9600 8N2", "model": "WBMR6C", "firmware": "1.26.0"},
            {"name": "relay-b", "template": relay, "address": 10, "serial": "0xFE000011",
             "line": "9600 8N2", "model": "WBMR6C", "firmware": "1.26.1"},
            {"name": "meter", "address": 11, "serial": "0xFE000040", "line": "9600 8N2",
             "fast": false, "registers": [{"type": "holding", "address": 0, "count": 8}]}
        ]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &sim_support::data(""), &[]);
    (dir, sim)
}

/// `set-address` and `fix-addresses` ask the new address with a classic request before they
/// move a device there: the device without Fast Modbus at 11 answers, so set-address refuses
/// (naming what answered) and fix-addresses picks 12.
#[test]
fn address_tools_keep_off_an_address_a_classic_device_answers() {
    let (_dir, sim) = classic_neighbour_bus();
    let port = port(&sim);
    let at_9600 = ["--baud", "9600", "--parity", "N", "--latency", LATENCY_MS];
    let address_of = |serial: &str| {
        sim.control(json!({"cmd": "get", "serial": serial, "type": "holding", "address": 128}))
            ["value"]
            .clone()
    };
    let mut set = vec![
        "set-address",
        "--port",
        &port,
        "--serial",
        "0xFE000011",
        "--address",
        "11",
    ];
    set.extend_from_slice(&at_9600);
    let run = tool(&set);
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "address 11 is already used at 9600 8N?: a device answered a classic request there \
             (holding 128 = 11)"
        ),
        "{}",
        run.stderr
    );
    assert_eq!(address_of("0xFE000011"), 10, "nothing written");

    let mut fix = vec![
        "fix-addresses",
        "--port",
        &port,
        "--range",
        "10-20",
        "--apply",
    ];
    fix.extend_from_slice(&at_9600);
    let run = tool(&fix);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("address 11 at 9600 8N? is not free: a device answered a classic request"),
        "{}",
        run.stderr
    );
    assert!(
        run.stdout
            .contains("address 10 -> 12 (confirmed by a new scan)"),
        "{}",
        run.stdout
    );
    assert_eq!(address_of("0xFE000011"), 12);
    assert_eq!(address_of("0xFE000040"), 11);
}

/// A value wider than a register (u32, big and little word order) comes in one event whose
/// payload is the value, little-endian, whatever the word order (fast-modbus.md §6: "payload =
/// the register's new value"): the command puts it into the channel's registers in the
/// channel's word order and decodes it with the channel's codec. Such channels are enabled from
/// the config too, at their first register.
#[test]
fn events_decode_values_wider_than_a_register_in_their_word_order() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("wide.json"),
        json!({
            "device_type": "sim-wide",
            "device": {"name": "Wide", "id": "wide", "channels": [
                {"name": "Big", "reg_type": "input", "address": 9, "type": "value",
                 "format": "u32", "scale": 0.01, "semi-sporadic": true},
                {"name": "Little", "reg_type": "input", "address": 20, "type": "value",
                 "format": "u32", "word_order": "little_endian", "scale": 0.01,
                 "sporadic": true}
            ]}
        })
        .to_string(),
    )
    .unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [{"name": "wide", "template": "wide.json", "address": 25,
                            "serial": "0xFE000025", "line": "115200 8N2"}]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, dir.path(), &[]);
    let port = port(&sim);
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        json!({
            "ports": [{"path": port, "baud_rate": 115200, "parity": "N", "data_bits": 8, "stop_bits": 2,
                       "devices": [{"device_type": "sim-wide", "slave_id": 25}]}]
        })
        .to_string(),
    )
    .unwrap();
    let (mut child, lines) = spawn_events(&[
        "events",
        "--port",
        &port,
        "--config",
        config.to_str().unwrap(),
        "--templates",
        dir.path().to_str().unwrap(),
        "--json",
        "--count",
        "2",
        "--latency",
        LATENCY_MS,
    ]);
    let mut enabled = Vec::new();
    let mut reboot_seen = false;
    while !(reboot_seen && enabled.len() == 4) {
        let line = next_json(&lines);
        if line["reboot"] == true {
            reboot_seen = true;
        } else if line.get("enabled").is_some() {
            assert_eq!(line["enabled"], true, "{line}");
            enabled.push(line["register"].as_u64().unwrap());
        } else {
            panic!("unexpected line before the values changed: {line}");
        }
    }
    assert!(enabled.contains(&9) && enabled.contains(&20), "{enabled:?}");
    // 0x0001_0002 = 65538: 655.38 at scale 0.01.
    sim.control(
        json!({"cmd": "set", "device": "wide", "type": "input", "address": 9, "value": [1, 2]}),
    );
    let big = next_json(&lines);
    assert_eq!(
        (
            &big["register"],
            &big["value"],
            &big["channel"],
            &big["text"]
        ),
        (&json!(9), &json!(65538), &json!("Big"), &json!("655.38")),
        "{big}"
    );
    // Low word first: the same value, and the same payload (it used to be the registers taken
    // most significant first, 0x0002_0001: docs/reliability.md, "Independent peers").
    sim.control(
        json!({"cmd": "set", "device": "wide", "type": "input", "address": 20, "value": [2, 1]}),
    );
    let little = next_json(&lines);
    assert_eq!(
        (
            &little["register"],
            &little["value"],
            &little["channel"],
            &little["text"]
        ),
        (
            &json!(20),
            &json!(65538),
            &json!("Little"),
            &json!("655.38")
        ),
        "{little}"
    );
    assert!(child.wait().unwrap().success());
}

/// `events` on a port another program holds, with no broker known: the port is busy (exit 3),
/// whatever else is missing, and the message names every tool that goes through the service.
#[test]
fn events_on_a_busy_port_says_busy_and_names_the_tools_that_go_through_the_service() {
    let sim = sim();
    let port = port(&sim);
    let holder = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.pty)
        .unwrap();
    let _lock =
        nix::fcntl::Flock::lock(holder, nix::fcntl::FlockArg::LockExclusiveNonblock).unwrap();
    let run = tool(&[
        "events",
        "--port",
        &port,
        "--service-config",
        "/nonexistent/rtu2mqtt.json",
    ]);
    assert_eq!(run.code, 3, "{}{}", run.stdout, run.stderr);
    assert!(run.stderr.contains("is busy"), "{}", run.stderr);
    assert!(
        run.stderr
            .contains("scan, set-address, fix-addresses, read, write or events"),
        "{}",
        run.stderr
    );
}

/// A count Modbus does not allow is a bad argument (exit 2), said before the port is opened
/// (here it does not even exist); the limits depend on the register type.
#[test]
fn a_bad_count_exits_2_before_the_port_is_opened() {
    let read = |register_type: &str, count: &str| {
        tool(&[
            "read",
            "--port",
            "/dev/ttyNOSUCH-rtu2mqtt",
            "--address",
            "1",
            "--type",
            register_type,
            "--reg",
            "0",
            "--count",
            count,
            "--baud",
            "9600",
            "--parity",
            "N",
        ])
    };
    for (register_type, count, limit) in [
        ("holding", "0", "1..=125 registers"),
        ("holding", "200", "1..=125 registers"),
        ("input", "126", "1..=125 registers"),
        ("coil", "2001", "1..=2000 bits"),
    ] {
        let run = read(register_type, count);
        assert_eq!(run.code, 2, "{register_type} {count}: {}", run.stderr);
        assert!(run.stderr.contains(limit), "{}", run.stderr);
        assert!(!run.stderr.contains("does not exist"), "{}", run.stderr);
    }
    // 200 coils are one request: on to the port, which is missing.
    let run = read("coil", "200");
    assert_eq!(run.code, 3, "{}", run.stderr);
    assert!(run.stderr.contains("does not exist"), "{}", run.stderr);
}

/// `scan --classic` cannot go through the service (it scans with Fast Modbus only): with
/// `--via-mqtt`, or on a busy port whose service is known, it is refused as bad usage before
/// anything is scanned or asked.
#[test]
fn scan_classic_through_the_service_is_refused_before_scanning() {
    let sim = sim();
    let port = port(&sim);
    let forced = tool(&[
        "scan",
        "--port",
        &port,
        "--classic",
        "--via-mqtt",
        "--broker",
        "127.0.0.1:1",
    ]);
    assert_eq!(forced.code, 2, "{}{}", forced.stdout, forced.stderr);
    assert!(
        forced
            .stderr
            .contains("--classic is not available through the service"),
        "{}",
        forced.stderr
    );
    assert!(
        forced.stderr.contains("stop the service"),
        "{}",
        forced.stderr
    );
    let holder = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&sim.pty)
        .unwrap();
    let _lock =
        nix::fcntl::Flock::lock(holder, nix::fcntl::FlockArg::LockExclusiveNonblock).unwrap();
    let busy = tool(&[
        "scan",
        "--port",
        &port,
        "--classic",
        "--broker",
        "127.0.0.1:1",
    ]);
    assert_eq!(busy.code, 2, "{}{}", busy.stdout, busy.stderr);
    assert!(
        busy.stderr
            .contains("--classic is not available through the service"),
        "{}",
        busy.stderr
    );
}

/// The classic scan's first progress line already estimates the time left (every address as a
/// silent one until probes have been timed), and the summary counts the classic probes.
#[test]
fn classic_scan_progress_estimates_from_the_start_and_the_summary_counts_probes() {
    let sim = sim();
    let port = port(&sim);
    let run = tool(&[
        "scan",
        "--port",
        &port,
        "--baud",
        "115200",
        "--parity",
        "N",
        "--stop-bits",
        "2",
        "--classic",
        "--range",
        "38-41",
        "--timeout",
        "150",
        "--latency",
        LATENCY_MS,
    ]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    let first = run
        .stderr
        .lines()
        .find(|l| l.starts_with("classic scan"))
        .unwrap_or_else(|| panic!("no progress: {}", run.stderr));
    assert!(first.contains("address 38: 0/4 (0%)"), "{first}");
    let left: f64 = first
        .split("about ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{first}"));
    // Four silent addresses at 150 ms + 100 ms allowance: at least a second.
    assert!(left >= 1.0, "{first}");
    assert!(
        run.stdout
            .contains("covered by 1 Fast Modbus transmission(s) and 4 classic probe(s)"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("OLDBOX"), "{}", run.stdout);
}

/// Through the running service (the daemon holds the port), `set-address` asks the new address
/// with a classic request through the service's bus queue (`port/Load`), as `read` does: the
/// meter without Fast Modbus at 30, which the service does not poll, answers and the address is
/// refused; a silent one is taken.
#[test]
fn set_address_through_the_service_probes_the_new_address_there() {
    let broker = mqtt_support::Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    let relay = sim_support::data("relay.json");
    std::fs::write(
        &bus,
        json!({"devices": [
            {"name": "relay", "template": relay.to_str().unwrap(), "address": 20,
             "serial": "0xFE000020", "line": "115200 8N2", "model": "WBMR6C", "firmware": "1.26.0"},
            {"name": "meter", "address": 30, "serial": "0x0D00001E", "line": "115200 8N2",
             "fast": false, "registers": [{"type": "holding", "address": 0, "count": 8}]}
        ]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &sim_support::data(""), &[]);
    let _daemon = service_polling_the_relay(&broker, &sim, "rtu2mqtt-site-tools-test");
    let port = port(&sim);
    let broker_option = format!("127.0.0.1:{}", broker.port);
    let set = |address: &str| {
        tool(&[
            "set-address",
            "--port",
            &port,
            "--serial",
            "0xFE000020",
            "--address",
            address,
            "--broker",
            &broker_option,
        ])
    };
    let address_of_relay = || {
        sim.control(
            json!({"cmd": "get", "serial": "0xFE000020", "type": "holding", "address": 128}),
        )["value"]
            .clone()
    };
    let run = set("30");
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("through the running rtu2mqtt service"),
        "{}",
        run.stderr
    );
    assert!(
        run.stderr.contains(
            "address 30 is already used at 115200 8N?: a device answered a classic request there \
             (holding 128 = 30)"
        ),
        "{}",
        run.stderr
    );
    assert_eq!(address_of_relay(), 20, "nothing written");
    let run = set("31");
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout
            .contains("address 20 -> 31 (confirmed by a scan)"),
        "{}",
        run.stdout
    );
    assert_eq!(address_of_relay(), 31);
}

/// Through the running service, `fix-addresses` keeps the address of the device the service
/// polls there: the service reads its serial number (its identity read) and `port/Scan` names
/// it (`configured_device`). A newcomer with a lower serial number (which would keep the
/// address by the rule without the service) joins the configured relay at 20 and is the one
/// moved; the tool says which device the service polls at 20.
#[test]
fn fix_addresses_through_the_service_keeps_the_device_it_polls() {
    let broker = mqtt_support::Mosquitto::start();
    let dir = tempfile::tempdir().unwrap();
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        json!({"devices": [
            {"name": "relay", "template": "rtu2mqtt-relay6", "address": 20,
             "serial": "0xFE000020", "line": "115200 8N2", "model": "WBMR6C", "firmware": "1.26.0"},
            {"name": "newcomer", "template": "rtu2mqtt-relay6", "address": 21,
             "serial": "0xFE000005", "line": "115200 8N2", "model": "WBMR6C", "firmware": "1.26.0"}
        ]})
        .to_string(),
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &daemon_support::repo("templates"), &[]);
    let config = json!({
        "mqtt": {"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-site-tools-fix"},
        "ports": [{"path": sim.pty, "baud_rate": 115200, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    });
    let _daemon = daemon_support::DaemonProcess::start(
        &config,
        &[],
        std::process::Stdio::null(),
        std::process::Stdio::null(),
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    // The service has read who is at 20 (the meta is published after the read is kept).
    runtime.block_on(mqtt_support::wait_for(
        "the relay's serial number in its meta",
        || async {
            let state = mqtt_support::retained(broker.port).await?;
            let meta: Value = serde_json::from_str(state.get("/devices/relay6_20/meta")?).ok()?;
            (meta["serial_number"] == "4261412896").then_some(())
        },
    ));
    sim.control(json!({"cmd": "set_address", "serial": "0xFE000005", "new_address": 20}));
    let port = port(&sim);
    let broker_option = format!("127.0.0.1:{}", broker.port);
    let run = tool(&[
        "fix-addresses",
        "--port",
        &port,
        "--baud",
        "115200",
        "--parity",
        "N",
        "--via-mqtt",
        "--broker",
        &broker_option,
        "--apply",
    ]);
    let address_of = |serial: &str| {
        sim.control(json!({"cmd": "get", "serial": serial, "type": "holding", "address": 128}))
            ["value"]
            .clone()
    };
    assert_eq!(
        address_of("0xFE000020"),
        20,
        "the relay the service polls at 20 was moved\n{}{}",
        run.stdout,
        run.stderr
    );
    assert_eq!(address_of("0xFE000005"), 1, "{}{}", run.stdout, run.stderr);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains(
            "the service polls relay6_20 at 20, and it read serial 4261412896 (0xFE000020) there"
        ),
        "{}",
        run.stderr
    );
}

/// A baud rate no port runs at (0, 1: a typo) is refused before the port is opened: it timed
/// every reply in minutes (a read ran 171 s, a scan for good; a site tools audit), and 0 hangs
/// a real port up.
#[test]
fn a_baud_rate_typo_is_refused_at_once() {
    for (args, baud) in [
        (&["scan", "--port", "/dev/null", "--baud"][..], "0"),
        (
            &[
                "read",
                "--port",
                "/dev/null",
                "--address",
                "1",
                "--reg",
                "0",
                "--baud",
            ][..],
            "1",
        ),
        (
            &["scan", "--port", "/dev/null", "--baud"][..],
            "9600,5000000",
        ),
    ] {
        let mut args = args.to_vec();
        args.push(baud);
        let run = tool(&args);
        assert_eq!(run.code, 2, "{args:?}: {}{}", run.stdout, run.stderr);
        assert!(run.stderr.contains("out of 110..4000000"), "{}", run.stderr);
    }
}

/// A write by address to two devices that share it, at a setting given (no scan before it):
/// both take it, their replies collide, and the tool says that each most likely carried it out,
/// not only "unreadable reply" (a site tools audit), at 9600 8N2.
#[test]
fn a_write_to_a_shared_address_says_both_devices_took_it() {
    let sim = sim();
    let run = access(
        &sim,
        &[
            "write",
            "--address",
            "10",
            "--type",
            "coil",
            "--reg",
            "3",
            "--baud",
            "9600",
            "--parity",
            "N",
            "--stop-bits",
            "2",
            "--latency",
            LATENCY_MS,
            "1",
        ],
    );
    assert_eq!(run.code, 1, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("unreadable reply")
            && run
                .stderr
                .contains("each of them most likely carried out the write"),
        "{}",
        run.stderr
    );
    for serial in ["0xFE000010", "0xFE000011"] {
        let coil =
            sim.control(json!({"cmd": "get", "serial": serial, "type": "coil", "address": 3}));
        assert_eq!(coil["value"], 1, "{serial}: {coil}");
    }
}

/// `scan --classic` at 9600: a device without Fast Modbus at the address of one the Fast Modbus
/// scan found is said (the two answer a read of the serial number at once), where it was
/// skipped and the clash invisible to every tool (a site tools audit); the Fast Modbus device
/// alone there is not taken for a clash.
#[test]
fn classic_scan_says_a_classic_device_sharing_a_fast_modbus_address() {
    let relay = sim_support::data("relay.json");
    let relay = relay.to_str().unwrap().to_owned();
    for with_meter in [true, false] {
        let dir = tempfile::tempdir().unwrap();
        let bus = dir.path().join("bus.json");
        let mut devices = vec![json!({"name": "relay", "template": relay, "address": 12,
            "serial": "0xFE000012", "line": "9600 8N2", "model": "WBMR6C", "firmware": "1.26.0"})];
        if with_meter {
            devices.push(
                json!({"name": "meter", "address": 12, "serial": "0xFE000040",
                "line": "9600 8N2", "fast": false,
                "registers": [{"type": "holding", "address": 0, "count": 8}]}),
            );
        }
        std::fs::write(&bus, json!({ "devices": devices }).to_string()).unwrap();
        let sim = SimProcess::start_with(&bus, &sim_support::data(""), &[]);
        let report = scan_json(
            &sim,
            &[
                "--baud",
                "9600",
                "--parity",
                "N",
                "--stop-bits",
                "2",
                "--classic",
                "--range",
                "11-13",
                "--timeout",
                "150",
            ],
        );
        let problems = report["problems"].to_string();
        assert_eq!(
            problems.contains("a device without Fast Modbus probably shares this address"),
            with_meter,
            "meter at 12: {with_meter}: {report:#}"
        );
        assert_eq!(found(&report), vec![(0xFE00_0012, 12, "9600 8N2".into())]);
    }
}
