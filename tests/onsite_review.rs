//! From an on-site review: an integrator switches a controller from wb-mqtt-serial to rtu2mqtt
//! with a laptop, runs `check-config`, `describe` and `run` on the configs they have, and makes
//! the common mistakes. Every test runs the real binary and reads what it prints.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"));
    // The tests set the environment overrides they need and no others.
    for (key, _) in std::env::vars() {
        if key.starts_with("RTU2MQTT_") {
            command.env_remove(key);
        }
    }
    command
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// stdout and stderr together, with the exit status; never a panic.
fn report(out: Output) -> (bool, String) {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!text.contains("panicked"), "{text}");
    (out.status.success(), text)
}

/// Writes `bytes` as a config file and runs `rtu2mqtt COMMAND -c FILE --templates templates/`
/// with `extra` arguments and `env` set.
fn run_on(command: &str, bytes: &[u8], extra: &[&str], env: &[(&str, &str)]) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, bytes).unwrap();
    let out = bin()
        .arg(command)
        .arg("-c")
        .arg(&file)
        .arg("--templates")
        .arg(repo("templates"))
        .args(extra)
        .envs(env.iter().copied())
        .output()
        .unwrap();
    report(out)
}

fn check_config(text: &str) -> (bool, String) {
    run_on("check-config", text.as_bytes(), &[], &[])
}

/// Words of Rust's type system that mean nothing to an integrator.
const RUST_WORDS: [&str; 12] = [
    "u8",
    "u16",
    "u32",
    "u64",
    "i32",
    "i64",
    "f64",
    "sequence",
    "map,",
    "floating point",
    "struct ",
    "Os {",
];

/// `text` with the temporary directories' names taken out: a random name (`.tmpu85ZCR`) may
/// hold a word the check looks for.
fn assert_no_rust_words(text: &str) {
    let words: String = text
        .split_inclusive(char::is_whitespace)
        .map(|word| {
            if word.contains("/tmp/") {
                "PATH "
            } else {
                word
            }
        })
        .collect();
    for word in RUST_WORDS {
        assert!(!words.contains(word), "`{word}` in: {text}");
    }
}

#[test]
fn a_number_written_in_quotes_is_said_so_in_plain_words() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/ttyRS485-1",
            "baud_rate": "9600", "devices": []}]}"#,
    );
    assert!(!ok);
    assert!(text.contains(":2:13: at ports[0].baud_rate:"), "{text}");
    assert!(
        text.contains("expected a whole number") && text.contains("without the quotes"),
        "{text}"
    );
    assert_no_rust_words(&text);

    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/ttyRS485-1", "stop_bits": "2", "devices": []}]}"#,
    );
    assert!(!ok);
    assert!(text.contains("at ports[0].stop_bits:"), "{text}");
    assert!(text.contains("without the quotes"), "{text}");
    assert_no_rust_words(&text);
}

#[test]
fn type_errors_name_json_kinds_not_rust_types() {
    let cases = [
        (
            r#"{"ports": [{"path": "/dev/x", "enabled": "false", "devices": []}]}"#,
            "ports[0].enabled",
            "expected true or false",
        ),
        (
            r#"{"ports": [{"path": "/dev/x", "devices": {}}]}"#,
            "ports[0].devices",
            "expected a list",
        ),
        (
            r#"{"ports": {"path": "/dev/x"}}"#,
            "ports",
            "expected a list",
        ),
        (
            r#"{"ports": [{"path": "/dev/x", "response_timeout_ms": 100.5, "devices": []}]}"#,
            "ports[0].response_timeout_ms",
            "expected a whole number",
        ),
        (
            r#"{"mqtt": {"port": 70000}, "ports": []}"#,
            "mqtt.port",
            "0 to 65535",
        ),
        (
            r#"{"mqtt": "localhost", "ports": []}"#,
            "mqtt",
            "expected an object",
        ),
    ];
    for (config, at, words) in cases {
        let (ok, text) = check_config(config);
        assert!(!ok, "{config}: {text}");
        assert!(text.contains(&format!("at {at}:")), "{config}: {text}");
        assert!(text.contains(words), "{config}: {text}");
        assert_no_rust_words(&text);
    }
}

#[test]
fn a_config_saved_with_a_byte_order_mark_loads() {
    // Windows editors (Notepad) save UTF-8 with a BOM; jsoncpp, which wb-mqtt-serial reads
    // its config with, skips it.
    let mut bytes = b"\xEF\xBB\xBF".to_vec();
    bytes.extend_from_slice(
        br#"{"ports": [{"path": "/dev/ttyRS485-1", "baud_rate": 115200, "devices": [
            {"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]}"#,
    );
    let (ok, text) = run_on("check-config", &bytes, &[], &[]);
    assert!(ok, "{text}");
    assert!(text.contains(": ok (1 port, 1 device"), "{text}");
    // A problem after the mark is still located as an editor shows it (a port key nothing
    // reads is a warning: wb-mqtt-serial ignores it too).
    let mut bytes = b"\xEF\xBB\xBF".to_vec();
    bytes.extend_from_slice(br#"{"ports": [{"path": "/dev/x", "baudrate": 9600}]}"#);
    let (ok, text) = run_on("check-config", &bytes, &[], &[]);
    assert!(ok, "{text}");
    assert!(
        text.contains(":1:31: at ports[0].baudrate: warning:"),
        "{text}"
    );
}

#[test]
fn an_empty_config_file_is_said_to_be_empty() {
    for text in ["", "  \n\n"] {
        let (ok, out) = check_config(text);
        assert!(!ok, "{out}");
        assert!(out.contains("the file is empty"), "{out}");
        assert!(!out.contains(":1:0:") && !out.contains("EOF"), "{out}");
    }
}

/// A port key nothing reads and close to no valid key (a `title` for the integrator): ignored
/// with a warning, as wb-mqtt-serial ignores it (its ports schema has no
/// `additionalProperties`).
#[test]
fn an_unknown_key_without_a_close_match_is_set_apart_from_the_valid_keys() {
    let (ok, text) =
        check_config(r#"{"ports": [{"path": "/dev/x", "title": "Bus 1", "devices": []}]}"#);
    assert!(ok, "{text}");
    assert!(
        text.contains("warning: unknown port key `title` is ignored (it does nothing)"),
        "{text}"
    );
    // Where rtu2mqtt's own sections are concerned, an unknown key is still an error.
    let (ok, text) = check_config(r#"{"mqtt": {"title": "x"}, "ports": []}"#);
    assert!(!ok);
    assert!(
        text.contains("unknown key `title`. Valid keys: host,"),
        "{text}"
    );
}

#[test]
fn describe_finds_a_device_by_its_slave_id_as_the_config_writes_it() {
    let config = br#"{"ports": [{"path": "/dev/ttyRS485-1", "devices": [
        {"device_type": "rtu2mqtt-relay6", "slave_id": "0x10"},
        {"device_type": "rtu2mqtt-climate", "slave_id": "21"}]}]}"#;
    for (wanted, id) in [
        ("0x10", "relay6_0x10"),
        ("16", "relay6_0x10"),
        ("21", "climate_21"),
    ] {
        let (ok, text) = run_on("describe", config, &[wanted], &[]);
        assert!(ok, "{wanted}: {text}");
        assert!(text.starts_with(id), "{wanted}: {text}");
        assert_eq!(text.matches("(slave_id ").count(), 1, "{wanted}: {text}");
    }
}

#[test]
fn a_bad_environment_override_names_its_variable() {
    let config = br#"{"ports": [{"path": "/dev/x", "devices": []}]}"#;
    let (ok, text) = run_on(
        "check-config",
        config,
        &[],
        &[("RTU2MQTT_MQTT__PORT", "abc")],
    );
    assert!(!ok);
    assert!(text.contains("RTU2MQTT_MQTT__PORT"), "{text}");
    // The value is not in the file: no line and column of it.
    assert!(!text.contains("config.json:1:1:"), "{text}");
    assert_no_rust_words(&text);

    let (ok, text) = run_on(
        "check-config",
        config,
        &[],
        &[("RTU2MQTT_PORTS__0__BAUD_RATE", "19200")],
    );
    assert!(!ok);
    assert!(
        text.contains("RTU2MQTT_PORTS__0__BAUD_RATE") && text.contains("scalar settings"),
        "{text}"
    );
    assert_no_rust_words(&text);
}

#[test]
fn a_missing_template_names_the_searched_directories_that_are_not_there() {
    // A typo in --templates (or wb-mqtt-serial's library absent on a laptop): the list of
    // directories searched says which of them do not exist.
    let dir = tempfile::tempdir().unwrap();
    let typo = dir.path().join("tempaltes");
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 1, "device_type": "WB-MR6C"}]}]}"#,
    )
    .unwrap();
    let out = bin()
        .arg("check-config")
        .arg("-c")
        .arg(&config)
        .arg("--templates")
        .arg(&typo)
        .arg("--templates")
        .arg(repo("templates"))
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok);
    assert!(
        text.contains(&format!("{} (not there)", typo.display())),
        "{text}"
    );
    assert!(
        !text.contains(&format!("{} (not there)", repo("templates").display())),
        "{text}"
    );
}
