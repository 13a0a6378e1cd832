//! `check-config`, `check-templates` and `schema` run as the real binary: bad input gets a
//! located error and a non-zero exit, never a panic.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn check_config(text: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, text).unwrap();
    let out = bin()
        .arg("check-config")
        .arg("-c")
        .arg(&file)
        .arg("--templates")
        .arg(repo("templates"))
        .output()
        .unwrap();
    report(out)
}

fn report(out: Output) -> (bool, String) {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!text.contains("panicked"), "{text}");
    (out.status.success(), text)
}

#[test]
fn shipped_configs_are_ok() {
    for file in ["config/config.json", "config/examples/multi-port.json"] {
        let out = bin()
            .arg("check-config")
            .arg("-c")
            .arg(repo(file))
            .arg("--templates")
            .arg(repo("templates"))
            .output()
            .unwrap();
        let (ok, text) = report(out);
        assert!(ok && text.contains(": ok"), "{file}: {text}");
    }
}

#[test]
fn missing_template() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "device_type": "rtu2mqtt-relay7"}]}]}"#,
    );
    assert!(!ok);
    assert!(text.contains(":2:25: at ports[0].devices[0].device_type: no template for device_type `rtu2mqtt-relay7`"), "{text}");
    assert!(text.contains("did you mean `rtu2mqtt-relay6`"), "{text}");
}

#[test]
fn unknown_format_in_a_config_channel() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "channels": [{"name": "X", "address": 1,
            "format": "u17"}]}]}]}"#,
    );
    assert!(!ok);
    assert!(
        text.contains(":3:13: at ports[0].devices[0].channels[0].format: unknown value `u17`"),
        "{text}"
    );
    assert!(text.contains("s16") && text.contains("bcd32"), "{text}");
}

#[test]
fn duplicate_slave_id_on_a_port() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "device_type": "rtu2mqtt-generic"},
        {"slave_id": "0x01", "device_type": "rtu2mqtt-dimmer"}]}]}"#,
    );
    assert!(!ok);
    assert!(
        text.contains(":3:10: at ports[0].devices[1].slave_id: slave_id 1 is used twice"),
        "{text}"
    );
}

#[test]
fn duplicate_device_id() {
    let (ok, text) = check_config(
        r#"{"ports": [
        {"path": "/dev/x", "devices": [{"slave_id": 1, "device_type": "rtu2mqtt-generic"}]},
        {"path": "/dev/y", "devices": [{"slave_id": 1, "device_type": "rtu2mqtt-generic"}]}]}"#,
    );
    assert!(!ok);
    assert!(text.contains("at ports[1].devices[0]: device id `generic_1` is used twice: also by the device at ports[0].devices[0]"), "{text}");
}

#[test]
fn out_of_range_address() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "channels": [{"name": "Big", "reg_type": "input", "format": "u32", "address": 65535}]}]}]}"#,
    );
    assert!(!ok);
    assert!(
        text.contains("at ports[0].devices[0].channels[0]: register address 65535 is out of range"),
        "{text}"
    );
    assert!(text.contains("spans 2 registers"), "{text}");
}

#[test]
fn key_typos_list_valid_keys() {
    let (ok, text) = check_config(r#"{"ports": [{"path": "/dev/x", "baudrate": 9600}]}"#);
    assert!(!ok);
    assert!(
        text.contains(":1:31: at ports[0].baudrate: unknown key `baudrate`; valid keys:"),
        "{text}"
    );
    assert!(text.contains("baud_rate"), "{text}");

    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "device_type": "rtu2mqtt-relay6", "in1_mod": 3}]}]}"#,
    );
    assert!(!ok);
    assert!(
        text.contains("at ports[0].devices[0].in1_mod: unknown key `in1_mod`; valid keys:"),
        "{text}"
    );
    assert!(text.contains("in1_mode (parameter)"), "{text}");
}

#[test]
fn syntax_errors_have_line_and_column() {
    let (ok, text) = check_config("{\n  \"ports\": [\n    {\"path\": \"/dev/x\",}\n  ]\n}");
    assert!(!ok);
    assert!(text.contains("config.json:3:23: not valid JSON"), "{text}");
}

#[test]
fn unreadable_config_says_so() {
    let out = bin()
        .args(["check-config", "-c", "/nonexistent/rtu2mqtt.json"])
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(
        !ok && text.contains("/nonexistent/rtu2mqtt.json: cannot read the file"),
        "{text}"
    );
}

#[test]
fn environment_overrides_scalars() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, r#"{"mqtt": {"host": "a"}}"#).unwrap();
    let out = bin()
        .arg("check-config")
        .arg("-c")
        .arg(&file)
        .env("RTU2MQTT_MQTT__PORT", "not-a-port")
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(
        !ok && text.contains("mqtt.port") && text.contains("environment variable"),
        "{text}"
    );
    let out = bin()
        .arg("check-config")
        .arg("-c")
        .arg(&file)
        .env("RTU2MQTT_MQTT__PORT", "8883")
        .output()
        .unwrap();
    assert!(report(out).0);
}

#[test]
fn check_templates_reports_per_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("good.json"),
        r#"{"device_type": "g", "device": {"channels": [{"name": "a", "address": 1}]}}"#,
    )
    .unwrap();
    std::fs::write(
        dir.path().join("bad.json"),
        "{\"device_type\": \"b\", \"device\": {\"channels\": [\n  {\"name\": \"a\", \"address\": 1, \"format\": \"float32\"}]}}",
    )
    .unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok);
    assert!(text.contains("good.json: ok"), "{text}");
    assert!(
        text.contains("bad.json:2:31: at device.channels[0].format: unknown value `float32`"),
        "{text}"
    );

    let out = bin()
        .arg("check-templates")
        .arg(repo("templates"))
        .arg(repo("tests/data/wb-templates"))
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(ok, "{text}");
    assert_eq!(text.matches(": ok").count(), 9, "{text}");
}

#[test]
fn schema_prints_json() {
    for kind in ["config", "template"] {
        let out = bin().args(["schema", kind]).output().unwrap();
        assert!(out.status.success());
        let schema: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert!(schema.get("$schema").is_some(), "{kind}");
    }
}

/// As the README shows it: from the repository root, no `--templates` (the shipped templates are
/// built in).
#[test]
fn readme_check_config_works_from_the_repository_root() {
    let out = bin()
        .args(["check-config", "-c", "config/examples/multi-port.json"])
        .current_dir(repo(""))
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(ok && text.contains(": ok"), "{text}");
}

#[test]
fn check_templates_with_nothing_to_check_fails() {
    let dir = tempfile::tempdir().unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok, "{text}");
    assert!(text.contains("no template files"), "{text}");
}

#[test]
fn missing_template_lists_the_directories_searched() {
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 1, "device_type": "NO-SUCH"}]}]}"#,
    );
    assert!(!ok);
    assert!(
        text.contains("searched:")
            && text.contains("/usr/share/wb-mqtt-serial/templates")
            && text.contains("/etc/wb-mqtt-serial.conf.d/templates")
            && text.contains("/usr/share/rtu2mqtt/templates"),
        "{text}"
    );
}
