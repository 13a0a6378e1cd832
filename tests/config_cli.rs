//! `check-config`, `check-templates`, `schema` and `prepare-ports` run as the real binary: bad input gets a
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

fn check_config_strict(text: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, text).unwrap();
    let out = bin()
        .arg("check-config")
        .arg("--strict")
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

/// Keys nothing reads on a port or a device are ignored with a warning, as wb-mqtt-serial
/// ignores them (a config it runs must run here), naming the closest valid key for a typo;
/// `--strict` makes them errors.
#[test]
fn key_typos_suggest_the_closest_keys() {
    let (ok, text) = check_config(r#"{"ports": [{"path": "/dev/x", "baudrate": 9600}]}"#);
    assert!(ok, "{text}");
    assert!(
        text.contains(":1:31: at ports[0].baudrate: warning: unknown port key `baudrate` is ignored; did you mean `baud_rate`?"),
        "{text}"
    );
    assert!(text.contains("wb-mqtt-serial ignores it too"), "{text}");
    let (ok, text) = check_config_strict(r#"{"ports": [{"path": "/dev/x", "baudrate": 9600}]}"#);
    assert!(!ok && text.contains("--strict"), "{text}");

    // A device with a big template: the closest few, not every parameter name.
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "devices": [
        {"slave_id": 1, "device_type": "rtu2mqtt-relay6", "in1_mod": 3}]}]}"#,
    );
    assert!(ok, "{text}");
    assert!(
        text.contains("at ports[0].devices[0].in1_mod: warning: `in1_mod` is neither a device setting nor a parameter of the template (did you mean `in1_mode`?): ignored, as wb-mqtt-serial ignores it"),
        "{text}"
    );
    assert!(!text.contains("`in0_mode`"), "only the closest: {text}");

    // A template with hundreds of parameters: no list of them all.
    let dir = tempfile::tempdir().unwrap();
    let parameters: Vec<String> = (0..400)
        .map(|i| format!(r#""input{i}_mode": {{"address": {i}}}"#))
        .collect();
    std::fs::write(
        dir.path().join("big.json"),
        format!(
            r#"{{"device_type": "big", "device": {{"parameters": {{{}}}, "channels": [{{"name": "a", "address": 1}}]}}}}"#,
            parameters.join(", ")
        ),
    )
    .unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 1, "device_type": "big", "input7_mod": 1}]}]}"#,
    )
    .unwrap();
    let out = bin()
        .arg("check-config")
        .arg("-c")
        .arg(&config)
        .arg("--templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(ok && text.contains("did you mean `input7_mode`"), "{text}");
    assert!(text.len() < 600, "{text}");
}

#[test]
fn syntax_errors_have_line_and_column() {
    let (ok, text) =
        check_config("{\n  \"ports\": [\n    {\"path\": \"/dev/x\" \"baud_rate\": 1}\n  ]\n}");
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
    let files = |dir: &str| std::fs::read_dir(repo(dir)).unwrap().count();
    assert_eq!(
        text.matches(": ok").count(),
        files("templates") + files("tests/data/wb-templates"),
        "{text}"
    );
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

/// `check-config` with the wb-format fixtures (tests/data/wb-templates, tests/data/wb-rules).
fn check_config_with_fixtures(text: &str) -> (bool, String) {
    with_fixtures("check-config", text)
}

/// `rtu2mqtt <command> -c CONFIG` with the wb-format fixtures as templates (the non-Modbus
/// meter `TEST-NOT-MODBUS`, protocol `milur`, is in tests/data/wb-rules).
fn with_fixtures(command: &str, text: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, text).unwrap();
    let out = bin()
        .arg(command)
        .arg("-c")
        .arg(&file)
        .arg("--templates")
        .arg(repo("tests/data/wb-templates"))
        .arg("--templates")
        .arg(repo("tests/data/wb-rules"))
        .output()
        .unwrap();
    report(out)
}

fn one_device(device: &str) -> String {
    format!(r#"{{"ports": [{{"path": "/dev/x", "devices": [{device}]}}]}}"#)
}

/// wb-mqtt-serial's `unsuccessful-*` test configs, rewritten against our own fixtures: each one
/// is rejected, with a message that says why.
#[test]
fn wb_mqtt_serial_unsuccessful_cases_are_rejected() {
    let cases = [
        // 0–3: error_value that is negative, a negative string, not a number, too wide.
        (
            r#"{"slave_id": 1, "channels": [{"name": "x", "reg_type": "holding", "address": 0, "type": "switch", "error_value": -4}]}"#,
            "error_value -4 is not raw register content of this 16-bit value: give the raw words as read, 0…4294967295",
        ),
        (
            r#"{"slave_id": 1, "channels": [{"name": "x", "reg_type": "holding", "address": 0, "type": "switch", "error_value": "-4"}]}"#,
            "error_value",
        ),
        (
            r#"{"slave_id": 1, "channels": [{"name": "x", "reg_type": "holding", "address": 0, "type": "switch", "error_value": "blah"}]}"#,
            "error_value",
        ),
        (
            r#"{"slave_id": 1, "channels": [{"name": "x", "reg_type": "holding", "address": 0, "type": "switch", "error_value": 4294967296}]}"#,
            "error_value",
        ),
        // 4–5: a subdevice type the slot does not offer, or that does not exist.
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "param1": 0, "channels": [{"name": "Sub1", "device_type": "subdevice2"}]}"#,
            "not a choice of this slot",
        ),
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub2", "device_type": "subdevice9"}]}"#,
            "not a choice of this slot",
        ),
        // 6–7: setup items without value or without address.
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub1", "device_type": "subdevice1", "setup": [{"title": "bad", "address": 10}]}]}"#,
            "value",
        ),
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub1", "device_type": "subdevice1", "setup": [{"title": "bad", "value": 10}]}]}"#,
            "address",
        ),
        // 8: a slot overridden without naming its subdevice (wb: "… must contain device_type",
        // "… device_type must be 'subdevice1'").
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub2", "setup": [{"title": "bad", "address": 1, "value": 10}]}]}"#,
            "overrides subdevice slot `Sub2` without saying which subdevice it holds",
        ),
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub1", "enabled": false}]}"#,
            r#"add "device_type": "subdevice1" (the only subdevice this slot takes)"#,
        ),
        // 9: a subdevice type on a channel that is no slot.
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub1", "device_type": "subdevice1", "channels": [{"name": "c1", "device_type": "subdevice1"}]}]}"#,
            "c1",
        ),
        // 10: a required subdevice parameter missing.
        (
            r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub2", "device_type": "subdevice3"}]}"#,
            "requires parameter `mode`",
        ),
        // 11: required parameters missing (param1; param2 once param1 == 1).
        (
            r#"{"slave_id": 22, "device_type": "TEST-RULES"}"#,
            "requires parameter `param1`",
        ),
        (
            r#"{"slave_id": 23, "device_type": "TEST-RULES", "param1": 1}"#,
            "requires parameter `param2`",
        ),
        // 12: a value the enum does not allow.
        (
            r#"{"slave_id": 22, "device_type": "TEST-RULES", "param1": 2, "param3": 11}"#,
            "parameter `param3` cannot be 11; allowed: 1 (One), 2 (Two), 3 (Three)",
        ),
        // 13: two declarations of param4 in effect at once.
        (
            r#"{"slave_id": 22, "device_type": "TEST-RULES", "param1": 4}"#,
            "parameter `param4` is declared 2 times",
        ),
        // min/max.
        (
            r#"{"slave_id": 22, "device_type": "TEST-RULES", "param1": 2, "param5": 11}"#,
            "outside its range 0…10",
        ),
    ];
    let mut failures = Vec::new();
    for (i, (device, expected)) in cases.iter().enumerate() {
        let (ok, text) = check_config_with_fixtures(&one_device(device));
        if ok || !text.contains(expected) {
            failures.push(format!("case {i} ({expected}): ok={ok}\n{text}"));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn parameter_rules_accept_valid_values() {
    for device in [
        r#"{"slave_id": 22, "device_type": "TEST-RULES", "param1": 2, "param3": 3, "param5": 10}"#,
        r#"{"slave_id": 23, "device_type": "TEST-RULES", "param1": 1, "param2": 0}"#,
        r#"{"slave_id": 24, "device_type": "TEST-RULES", "param1": 3, "param4": 7}"#,
        r#"{"slave_id": 2, "device_type": "TEST-SUBDEVICE", "channels": [{"name": "Sub2", "device_type": "subdevice3", "mode": 2}]}"#,
    ] {
        let (ok, text) = check_config_with_fixtures(&one_device(device));
        assert!(ok, "{device}: {text}");
    }
}

#[test]
fn modbus_io_slave_ids() {
    let (ok, text) = check_config_with_fixtures(&one_device(
        r#"{"slave_id": "1:1", "device_type": "TEST-WBIO"}, {"slave_id": "1:2", "device_type": "TEST-WBIO"}"#,
    ));
    assert!(ok, "{text}");
    let (ok, text) = check_config_with_fixtures(&one_device(
        r#"{"slave_id": "1:1", "device_type": "TEST-WBIO"}, {"slave_id": "1:1", "device_type": "TEST-WBIO", "id": "other"}"#,
    ));
    assert!(!ok && text.contains("slave_id 1:1 is used twice"), "{text}");
    let (ok, text) = check_config_with_fixtures(&one_device(
        r#"{"slave_id": 1, "device_type": "TEST-WBIO"}"#,
    ));
    assert!(!ok && text.contains("\"address:module\""), "{text}");
}

#[test]
fn broadcast_and_reserved_slave_ids_are_rejected() {
    for slave_id in ["0", "248", "255", "\"0x00\""] {
        let (ok, text) = check_config(&one_device(&format!(
            r#"{{"slave_id": {slave_id}, "device_type": "rtu2mqtt-generic"}}"#
        )));
        assert!(!ok, "{slave_id}: {text}");
        assert!(text.contains("slave_id"), "{text}");
    }
    let (ok, text) = check_config(&one_device(
        r#"{"slave_id": 0, "device_type": "rtu2mqtt-generic"}"#,
    ));
    assert!(!ok && text.contains("broadcast"), "{text}");
    // A Modbus TCP server's unit id 255 is fine.
    let (ok, text) = check_config(
        r#"{"ports": [{"port_type": "modbus tcp", "address": "10.0.0.2", "port": 502, "devices": [
            {"slave_id": 255, "device_type": "rtu2mqtt-generic"}]}]}"#,
    );
    assert!(ok, "{text}");
}

#[test]
fn huge_durations_are_rejected() {
    let (ok, text) = check_config(&one_device(
        r#"{"slave_id": 1, "device_type": "rtu2mqtt-generic", "response_timeout_ms": 9223372036854775807}"#,
    ));
    assert!(
        !ok && text.contains("`response_timeout_ms` 9223372036854775807 is out of range"),
        "{text}"
    );
    let (ok, text) = check_config(
        r#"{"ports": [{"path": "/dev/x", "frame_timeout_ms": 99999999, "guard_interval_us": 99999999999, "devices": []}]}"#,
    );
    assert!(
        !ok && text.contains("frame_timeout_ms") && text.contains("guard_interval_us"),
        "{text}"
    );
    let (ok, text) = check_config(&one_device(
        r#"{"slave_id": 1, "channels": [{"name": "x", "address": 1, "read_period_ms": 9223372036854775807}]}"#,
    ));
    assert!(!ok && text.contains("read_period_ms"), "{text}");
    // In a template too.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("slow.json"),
        r#"{"device_type": "slow", "device": {"response_timeout_ms": 100000000, "channels": [{"name": "a", "address": 1}]}}"#,
    )
    .unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok && text.contains("response_timeout_ms"), "{text}");
}

#[test]
fn tls_files_must_exist_and_pair() {
    let (ok, text) = check_config(r#"{"mqtt": {"tls": {"ca_file": "/nonexistent/ca.pem"}}}"#);
    assert!(
        !ok && text.contains("mqtt.tls.ca_file") && text.contains("/nonexistent/ca.pem"),
        "{text}"
    );
    let dir = tempfile::tempdir().unwrap();
    let cert = dir.path().join("client.pem");
    std::fs::write(&cert, "x").unwrap();
    let (ok, text) = check_config(&format!(
        r#"{{"mqtt": {{"tls": {{"cert_file": "{}"}}}}}}"#,
        cert.display()
    ));
    assert!(!ok && text.contains("needs its private key"), "{text}");
}

#[test]
fn names_that_cannot_be_topics_are_rejected() {
    for (device, what) in [
        (
            r#"{"slave_id": 1, "device_type": "rtu2mqtt-generic", "id": "+"}"#,
            "device id `+` contains `+`",
        ),
        (
            r#"{"slave_id": 1, "device_type": "rtu2mqtt-generic", "id": "a/b"}"#,
            "contains `/`",
        ),
        (
            r#"{"slave_id": 1, "device_type": "rtu2mqtt-generic", "id": "a\u0000b"}"#,
            "contains NUL",
        ),
        (
            r#"{"slave_id": 1, "channels": [{"name": "Lvl#", "address": 1}]}"#,
            "channel name `Lvl#` contains `#`",
        ),
        (
            r#"{"slave_id": 1, "channels": [{"name": "K2/on", "address": 1}]}"#,
            "channel name `K2/on` contains `/`",
        ),
    ] {
        let (ok, text) = check_config(&one_device(device));
        assert!(
            !ok && text.contains(what) && text.contains("config.json"),
            "{device}: {text}"
        );
    }
    let long = "x".repeat(65_536);
    let (ok, text) = check_config(&one_device(&format!(
        r#"{{"slave_id": 1, "device_type": "rtu2mqtt-generic", "id": "{long}"}}"#
    )));
    assert!(
        !ok && text.contains("at most 200 bytes"),
        "{}",
        &text[..text.len().min(500)]
    );
    // Wiren Board channel names with spaces and parentheses are fine.
    let (ok, text) = check_config(&one_device(
        r#"{"slave_id": 1, "channels": [{"name": "Input 1 (counter), Hz", "address": 1}]}"#,
    ));
    assert!(ok, "{text}");
}

#[test]
fn hostile_numbers_are_errors() {
    for device in [
        r#"{"slave_id": 1, "channels": [{"name": "x", "format": "u32", "address": "9223372036854775807"}]}"#,
        r#"{"slave_id": 1, "channels": [{"name": "x", "address": "0x-14"}]}"#,
        r#"{"slave_id": "0x-1", "channels": [{"name": "x", "address": 1}]}"#,
        r#"{"slave_id": 1, "channels": [{"name": "x", "address": "-0x80000000000000000000000000000000"}]}"#,
    ] {
        let (ok, text) = check_config(&one_device(device));
        assert!(!ok, "{device}: {text}");
    }
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("shifty.json"),
        r#"{"device_type": "shifty", "device": {"channels": [
            {"name": "slot", "device_type": "s", "shift": "0x7fffffffffffffffffff"}],
            "subdevices": [{"device_type": "s", "device": {"channels": [{"name": "a", "address": 1}]}}]}}"#,
    )
    .unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok && text.contains("shift"), "{text}");
}

#[test]
fn deep_conditions_are_an_error_not_a_crash() {
    let deep = format!("{}a==1{}", "(".repeat(20_000), ")".repeat(20_000));
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("deep.json"),
        format!(
            r#"{{"device_type": "deep", "device": {{"channels": [{{"name": "a", "address": 1, "condition": "{deep}"}}]}}}}"#
        ),
    )
    .unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.code().is_some(), "killed by a signal");
    let (ok, text) = report(out);
    assert!(
        !ok && text.contains("condition"),
        "{}",
        &text[..text.len().min(500)]
    );
}

#[test]
fn check_templates_reports_deprecated_twins_and_foreign_protocols() {
    let out = bin()
        .arg("check-templates")
        .arg(repo("tests/data/wb-rules"))
        .output()
        .unwrap();
    let (_, text) = report(out);
    assert!(
        text.contains("device_type `TEST-PAIR` is also defined in")
            && text.contains("config-test-pair.json is used"),
        "{text}"
    );
    assert_eq!(
        text.matches("protocol `milur` is not supported").count(),
        1,
        "{text}"
    );
}

#[test]
fn misspelt_and_protected_keys_warn_and_fail_under_strict() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("typo.json"),
        "{\"device_type\": \"typo\", \"device\": {\"channels\": [\n  {\"name\": \"a\", \"address\": 1, \"scal\": 0.1}]}}",
    )
    .unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/x", "devices": [{"slave_id": 1, "device_type": "typo", "channels": [
            {"name": "a", "read_period": 500, "address": 7}]}]}]}"#,
    )
    .unwrap();
    let run = |strict: bool| {
        let mut command = bin();
        command
            .arg("check-config")
            .arg("-c")
            .arg(&config)
            .arg("--templates")
            .arg(dir.path());
        if strict {
            command.arg("--strict");
        }
        report(command.output().unwrap())
    };
    let (ok, text) = run(false);
    assert!(ok, "warnings alone do not fail: {text}");
    assert!(
        text.contains("typo.json:2:31: at device.channels[0].scal: warning: unknown key `scal` is ignored; did you mean `scale`? As `scale` is not set, its default applies."),
        "{text}"
    );
    assert!(
        text.contains("at ports[0].devices[0].channels[0].read_period: warning: unknown channel key `read_period` is ignored; did you mean `read_period_ms`?"),
        "{text}"
    );
    assert!(
        text.contains("at ports[0].devices[0].channels[0].address: warning: the template's `address` defines the register and cannot be overridden"),
        "{text}"
    );
    let (ok, text) = run(true);
    assert!(
        !ok && text.contains("3 warning(s), which --strict counts as errors"),
        "{text}"
    );
}

#[test]
fn template_errors_do_not_leak_internal_wording() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bad.json"),
        r#"{"device_type": "bad", "device": {"channels": [{"name": "a", "format": "u16"}]}}"#,
    )
    .unwrap();
    let out = bin()
        .arg("check-templates")
        .arg(dir.path())
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok && text.contains("needs `address`"), "{text}");
    assert!(
        !text.contains("(check)")
            && !text.contains("(top level)")
            && !text.contains("template used by"),
        "{text}"
    );
}

#[test]
fn a_foreign_protocol_is_named_in_check_config() {
    let (ok, text) = check_config_with_fixtures(&one_device(
        r#"{"slave_id": 1, "device_type": "TEST-NOT-MODBUS"}"#,
    ));
    assert!(!ok, "{text}");
    assert!(text.contains("protocol `milur` is not supported"), "{text}");
    assert!(!text.contains("reg_type"), "{text}");
}

/// `rtu2mqtt describe -c CONFIG --templates tests/data/wb-templates`.
fn describe_command(config: &Path) -> Command {
    let mut command = bin();
    command
        .arg("describe")
        .arg("-c")
        .arg(config)
        .arg("--templates")
        .arg(repo("tests/data/wb-templates"));
    command
}

#[test]
fn describe_shows_what_was_resolved() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/x", "devices": [
            {"slave_id": 7, "device_type": "WB-TEST-INPUTS", "baud_rate": 192,
             "channels": [{"name": "Input 1", "device_type": "in1_discrete"}]},
            {"slave_id": 8, "device_type": "WB-TEST-SENSOR", "poll_interval": 2000,
             "channels": [{"name": "Input 2 counter", "read_period_ms": 250}]},
            {"slave_id": "1:2", "device_type": "TEST-WBIO"}]}]}"#,
    )
    .unwrap();
    let describe = |extra: &[&str]| {
        let out = describe_command(&config)
            .arg("--templates")
            .arg(repo("tests/data/wb-rules"))
            .args(extra)
            .output()
            .unwrap();
        report(out)
    };
    let (ok, text) = describe(&[]);
    assert!(ok, "{text}");
    assert!(
        text.contains("setup (written in this order on connect):"),
        "{text}"
    );
    assert!(text.contains("1. holding 110 = 192  (Baud rate)"), "{text}");
    assert!(text.contains("holding 55:4:1"), "{text}");
    assert!(
        text.contains("response timeout: 1 ms configured, 26 ms in force"),
        "{text}"
    );

    let (ok, text) = describe(&["--json", "wb-test-sensor_8"]);
    assert!(ok, "{text}");
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let devices = json["devices"].as_array().unwrap();
    assert_eq!(devices.len(), 1);
    let counter = devices[0]["channels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "Input 2 counter")
        .unwrap();
    assert_eq!(counter["read_period_ms"], 250);
    // The device's old `poll_interval` is the read rate limit of its channels without a
    // period of their own.
    let limited: Vec<&serde_json::Value> = devices[0]["channels"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["read_period_ms"].is_null())
        .collect();
    assert!(!limited.is_empty(), "{text}");
    assert!(
        limited.iter().all(|c| c["read_rate_limit_ms"] == 2000),
        "{text}"
    );
    // The template's 1 ms is what wb-mqtt-serial's templates say; the port task waits the 24 ms
    // adapter allowance and one character (1.04 ms at 9600 8N1, the port default) on top, as wb-mqtt-serial.
    assert_eq!(devices[0]["response_timeout_ms"], 1);
    assert_eq!(devices[0]["response_timeout_in_force_ms"], 26.0);
    assert_eq!(counter["events"], "semi-sporadic");
    assert_eq!(counter["registers"][0]["read"]["address"], 33);

    let (ok, text) = describe(&["--json", "test_wbio_1:2"]);
    assert!(ok, "{text}");
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(json["devices"][0]["slave_id"], 1);
    assert_eq!(
        json["devices"][0]["channels"][1]["registers"][0]["read"]["address"],
        1034
    );

    let (ok, text) = describe(&["nonexistent"]);
    assert!(!ok && text.contains("devices: wb-test-inputs_7"), "{text}");
}

/// `describe` says when a port polls without Fast Modbus (its own `fast_modbus: false`, the
/// site-wide switch, a Modbus TCP gateway that does not pass it): every channel polled there,
/// sporadic ones too.
#[test]
fn describe_says_where_fast_modbus_is_off() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    let describe = |config_text: &str| {
        std::fs::write(&config, config_text).unwrap();
        let text = |extra: &[&str]| {
            let out = describe_command(&config).args(extra).output().unwrap();
            let (ok, text) = report(out);
            assert!(ok, "{text}");
            text
        };
        let json: serde_json::Value = serde_json::from_str(&text(&["--json"])).unwrap();
        let flags: Vec<bool> = json["devices"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d["fast_modbus"].as_bool().unwrap())
            .collect();
        (
            text(&[]).matches("Fast Modbus is off on this port").count(),
            flags,
        )
    };
    let device = r#"[{"slave_id": 8, "device_type": "WB-TEST-SENSOR"}]"#;
    let other = r#"[{"slave_id": 9, "device_type": "WB-TEST-SENSOR"}]"#;
    let two_ports = |site: &str, second: &str| {
        format!(
            r#"{{{site} "ports": [{{"path": "/dev/x", "devices": {device}}},
                {{"path": "/dev/y", {second} "devices": {other}}}]}}"#
        )
    };
    assert_eq!(describe(&two_ports("", "")), (0, vec![true, true]));
    assert_eq!(
        describe(&two_ports("", r#""fast_modbus": false,"#)),
        (1, vec![true, false])
    );
    assert_eq!(
        describe(&two_ports(
            r#""fast_modbus": false,"#,
            r#""fast_modbus": true,"#
        )),
        (2, vec![false, false])
    );
    let gateway = format!(
        r#"{{"ports": [{{"port_type": "modbus tcp", "address": "10.0.0.5", "port": 502,
            "devices": {device}}}]}}"#
    );
    assert_eq!(describe(&gateway), (1, vec![false]));
}

/// A TCP gateway's port adds its 500 ms to every device's timeout, as the port task does and
/// wb-mqtt-serial does; `describe` says so (it showed the serial figure and no gateway).
#[test]
fn describe_counts_a_tcp_gateways_allowance_in_the_timeout_in_force() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"port_type": "tcp", "address": "127.0.0.1", "port": 5020,
            "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]}"#,
    )
    .unwrap();
    let (ok, text) = report(describe_command(&config).output().unwrap());
    assert!(ok, "{text}");
    assert!(
        text.contains("in force (the TCP gateway's 500 ms, the adapter allowance of 24 ms"),
        "{text}"
    );
    let (ok, text) = report(describe_command(&config).arg("--json").output().unwrap());
    assert!(ok, "{text}");
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let device = &json["devices"][0];
    let added = device["response_timeout_in_force_ms"].as_f64().unwrap()
        - device["response_timeout_ms"].as_f64().unwrap();
    assert!((524.0..527.0).contains(&added), "{added}: {text}");
}

/// A port another process holds open (wb-mqtt-serial, which takes no lock, still running on
/// it) is named by `prepare-ports`, which the unit runs as root before the daemon: the only
/// place that can see it. The service still starts.
#[test]
fn prepare_ports_names_another_process_that_has_the_port_open() {
    let dir = tempfile::tempdir().unwrap();
    let held = dir.path().join("ttyS9");
    let free = dir.path().join("ttyS10");
    std::fs::write(&held, "").unwrap();
    std::fs::write(&free, "").unwrap();
    let _holder = std::fs::File::open(&held).unwrap();
    let config = dir.path().join("config.json");
    let port = |path: &Path| serde_json::json!({"path": path, "devices": []});
    std::fs::write(
        &config,
        serde_json::json!({"ports": [port(&held), port(&free)]}).to_string(),
    )
    .unwrap();
    let prepare = |except: &[u32]| {
        let mut command = bin();
        command
            .arg("prepare-ports")
            .arg("-c")
            .arg(&config)
            .arg("--sysfs-tty")
            .arg(dir.path().join("sys"));
        for pid in except {
            command.arg("--except-pid").arg(pid.to_string());
        }
        let out = command.output().unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{stdout}");
        stdout
    };
    let stdout = prepare(&[]);
    let warning = format!("{}: warning: also open in ", held.display());
    let line = stdout
        .lines()
        .find(|line| line.starts_with(&warning))
        .unwrap_or_else(|| panic!("no warning for the held port: {stdout}"));
    assert!(
        line.contains(&format!("(pid {})", std::process::id()))
            && line.contains("systemctl mask --now wb-mqtt-serial"),
        "{line}"
    );
    assert!(
        !stdout.contains(&format!("{}: warning", free.display())),
        "{stdout}"
    );
    // At a reload the unit names its own daemon, which has every port open, as no other master.
    let stdout = prepare(&[std::process::id()]);
    assert!(!stdout.contains("warning"), "{stdout}");
    assert!(
        stdout.contains(&format!("{}: ", held.display())),
        "{stdout}"
    );
}

/// `prepare-ports` sets each serial port's receive FIFO trigger to 1 byte (on a fake
/// `/sys/class/tty`), says so per port, leaves ports without the attribute and TCP ports alone,
/// and succeeds where it cannot (the service must start anyway).
#[test]
fn prepare_ports_lowers_each_uarts_receive_fifo_trigger() {
    let dir = tempfile::tempdir().unwrap();
    let dev = dir.path().join("dev");
    let sysfs = dir.path().join("sys");
    std::fs::create_dir_all(&dev).unwrap();
    for (name, trigger) in [
        ("ttyS7", Some("8\n")),
        ("ttyS8", Some("1\n")),
        ("ttyUSB0", None),
    ] {
        std::fs::write(dev.join(name), "").unwrap();
        std::fs::create_dir_all(sysfs.join(name)).unwrap();
        if let Some(trigger) = trigger {
            std::fs::write(sysfs.join(name).join("rx_trig_bytes"), trigger).unwrap();
        }
    }
    let port = |name: &str| serde_json::json!({"path": dev.join(name), "devices": []});
    let config = serde_json::json!({"ports": [
        port("ttyS7"),
        port("ttyS8"),
        port("ttyUSB0"),
        port("ttyUSB9"),
        {"port_type": "tcp", "address": "127.0.0.1", "port": 1, "devices": []},
    ]});
    let file = dir.path().join("config.json");
    std::fs::write(&file, config.to_string()).unwrap();
    let out = bin()
        .arg("prepare-ports")
        .arg("-c")
        .arg(&file)
        .arg("--sysfs-tty")
        .arg(&sysfs)
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(ok, "{text}");
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4, "one line per serial port:\n{text}");
    assert!(
        lines[0]
            .ends_with("ttyS7: receive FIFO set to hand bytes over one at a time (it collected 8)"),
        "{text}"
    );
    assert!(
        lines[1].ends_with("ttyS8: receive FIFO hands bytes over one at a time"),
        "{text}"
    );
    assert!(
        lines[2].contains("ttyUSB0: no receive FIFO trigger to set"),
        "{text}"
    );
    assert!(lines[3].contains("ttyUSB9: does not exist"), "{text}");
    let trigger = std::fs::read_to_string(sysfs.join("ttyS7/rx_trig_bytes")).unwrap();
    assert_eq!(trigger, "1");

    // A config that does not load: the errors and a failure, as check-config.
    std::fs::write(&file, "{ \"ports\": [ }").unwrap();
    let out = bin()
        .arg("prepare-ports")
        .arg("-c")
        .arg(&file)
        .output()
        .unwrap();
    let (ok, text) = report(out);
    assert!(!ok && text.contains("config.json"), "{text}");
}

/// A template with a channel wb-mqtt-serial leaves out passes `check-templates`, which says
/// which channel is left out and why.
#[test]
fn check_templates_shows_the_warnings_of_a_template_that_loads() {
    let file = repo("tests/data/wb-templates/config-test-unloadable-channels.json");
    let out = bin().arg("check-templates").arg(&file).output().unwrap();
    let (ok, text) = report(out);
    assert!(ok, "{text}");
    assert!(
        text.contains("warning: channel `Firmware` is ignored"),
        "{text}"
    );
    assert!(text.trim_end().ends_with(": ok"), "{text}");
}

// Devices of protocols other than Modbus in a wb-mqtt-serial config: what `check-config`,
// `describe` and `check-templates` say (a controller with one Mercury or Milur meter beside its
// Modbus devices is common).

fn port_with(meter: &str) -> String {
    format!(
        r#"{{"ports": [
            {{"path": "/dev/ttyRS485-1", "devices": [
                {meter},
                {{"slave_id": 2, "device_type": "TEST-METER"}}]}},
            {{"path": "/dev/ttyRS485-2", "devices": [{{"slave_id": 3, "device_type": "TEST-METER"}}]}}]}}"#
    )
}

#[test]
fn a_device_whose_template_is_of_another_protocol_is_named_so() {
    let config = port_with(r#"{"slave_id": 145, "device_type": "TEST-NOT-MODBUS"}"#);
    for command in ["check-config", "describe"] {
        let (ok, text) = with_fixtures(command, &config);
        assert!(!ok, "{text}");
        // Said at the device, with the protocol, where the template says it and what to do;
        // not "no template … check the name, or add the template file".
        assert!(
            text.contains(
                "at ports[0].devices[0].device_type: device_type `TEST-NOT-MODBUS`: protocol `milur` is not supported (its template: "
            ) && text.contains("config-test-meter-bus.json:7:9)")
                && text.contains("Keep this port on wb-mqtt-serial")
                && text.contains(r#"set `"enabled": false` on this device"#),
            "{command}: {text}"
        );
        assert!(
            !text.contains("no template for device_type"),
            "{command}: {text}"
        );
        assert_eq!(text.lines().count(), 1, "{command}: {text}");
    }
    // Disabled, as a wb-mqtt-serial config may have it: the other devices run.
    let config =
        port_with(r#"{"slave_id": 145, "device_type": "TEST-NOT-MODBUS", "enabled": false}"#);
    let (ok, text) = with_fixtures("check-config", &config);
    assert!(ok && text.contains("ok (2 ports, 2 devices"), "{text}");
}

#[test]
fn a_config_device_of_another_protocol_is_named_at_its_protocol() {
    // A device defined in the config (no device_type) with that protocol's register types.
    let meter = r#"{"slave_id": 7, "protocol": "milur", "name": "Milur", "id": "milur7",
        "channels": [{"name": "P", "reg_type": "power", "address": 102}]}"#;
    let (ok, text) = with_fixtures("check-config", &port_with(meter));
    assert!(!ok, "{text}");
    assert!(
        text.contains("at ports[0].devices[0].protocol: protocol `milur` is not supported")
            && text.contains("Keep this port on wb-mqtt-serial"),
        "{text}"
    );
    assert!(!text.contains("unknown value `power`"), "{text}");
    // Disabled (in the device or with its port), it is left alone: its channels are not read
    // as Modbus channels.
    let disabled = meter.replace(r#""slave_id": 7,"#, r#""slave_id": 7, "enabled": false,"#);
    let (ok, text) = with_fixtures("check-config", &port_with(&disabled));
    assert!(ok && text.contains("ok (2 ports, 2 devices"), "{text}");
    let port_off = format!(
        r#"{{"ports": [
            {{"path": "/dev/ttyRS485-1", "enabled": false, "devices": [{meter}]}},
            {{"path": "/dev/ttyRS485-2", "devices": [{{"slave_id": 3, "device_type": "TEST-METER"}}]}}]}}"#
    );
    let (ok, text) = with_fixtures("check-config", &port_off);
    assert!(ok && text.contains("ok (1 port, 1 device,"), "{text}");
    // Its path is not on this machine: said, not failed; the disabled port is not mentioned.
    assert!(
        text.contains("note: the serial port /dev/ttyRS485-2 does not exist on this machine"),
        "{text}"
    );
    assert!(!text.contains("/dev/ttyRS485-1 does not exist"), "{text}");
}

#[test]
fn check_templates_lists_other_protocols_without_failing() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        repo("tests/data/wb-templates/config-test-meter.json"),
        dir.path().join("config-test-meter.json"),
    )
    .unwrap();
    std::fs::copy(
        repo("tests/data/wb-rules/config-test-meter-bus.json"),
        dir.path().join("config-test-meter-bus.json"),
    )
    .unwrap();
    let check = || {
        report(
            bin()
                .arg("check-templates")
                .arg(dir.path())
                .output()
                .unwrap(),
        )
    };
    let (ok, text) = check();
    // wb-mqtt-serial's library holds a few dozen of them: the exit status says whether a
    // Modbus template has an error.
    assert!(ok, "{text}");
    assert!(
        text.contains(
            "config-test-meter-bus.json:7:9: at device.protocol: protocol `milur` is not supported"
        ) && text.contains("config-test-meter.json: ok")
            && text.contains("1 template(s) of other protocols than Modbus were not checked"),
        "{text}"
    );
    // A real error still fails the run, and is not hidden among them.
    std::fs::write(
        dir.path().join("config-broken.json"),
        r#"{"device_type": "broken", "device": {"channels": [{"name": "a", "format": "u16"}]}}"#,
    )
    .unwrap();
    let (ok, text) = check();
    assert!(!ok && text.contains("needs `address`"), "{text}");
}

/// As in wb-mqtt-serial, the last template file of a device_type is used even when it does not
/// load; the message names it, its error, and the earlier file it replaced.
#[test]
fn a_later_template_that_does_not_load_is_named_with_the_one_it_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let (first, second) = (dir.path().join("a"), dir.path().join("b"));
    std::fs::create_dir_all(&first).unwrap();
    std::fs::create_dir_all(&second).unwrap();
    std::fs::write(
        first.join("x.json"),
        r#"{"device_type": "X", "device": {"name": "x", "channels": [{"name": "c", "address": 1, "format": "u16"}]}}"#,
    )
    .unwrap();
    std::fs::write(
        second.join("x.json"),
        "{\"device_type\": \"X\", \"device\": {\"name\": \"x\", \"channels\": [\n {\"name\": \"c\", \"address\": 1, \"format\": \"float32\"}]}}",
    )
    .unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"ports": [{"path": "/dev/x", "devices": [{"device_type": "X", "slave_id": 1}]}]}"#,
    )
    .unwrap();
    let run = |dirs: &[&std::path::Path]| {
        let mut command = bin();
        command.arg("check-config").arg("-c").arg(&config);
        for dir in dirs {
            command.arg("--templates").arg(dir);
        }
        report(command.output().unwrap())
    };
    let (ok, text) = run(&[&first, &second]);
    assert!(!ok, "{text}");
    let (a, b) = (first.join("x.json"), second.join("x.json"));
    assert!(
        text.contains(&format!(
            "the template of device_type `X` ({}) does not load (the error is below); it replaces {} of the same device_type",
            b.display(),
            a.display()
        )) && text.contains("at device.channels[0].format: unknown value `float32`"),
        "{text}"
    );
    assert!(!text.contains("did you mean"), "{text}");
    // The other order: the good one is the last, and used.
    let (ok, text) = run(&[&second, &first]);
    assert!(ok, "{text}");
}

/// A `max_unchanged_interval` under 5 s works as 5 s; `check-config` says so, without failing.
#[test]
fn a_short_max_unchanged_interval_is_said_to_be_raised() {
    let (ok, text) = check_config(
        r#"{"max_unchanged_interval": 3, "ports": [{"path": "/dev/ttyRS485-1", "devices": []}]}"#,
    );
    assert!(ok, "{text}");
    assert!(
        text.contains("note: max_unchanged_interval 3 is raised to 5 s"),
        "{text}"
    );
    let (ok, text) = check_config(
        r#"{"max_unchanged_interval": 10, "ports": [{"path": "/dev/ttyRS485-1", "devices": []}]}"#,
    );
    assert!(ok && !text.contains("max_unchanged_interval"), "{text}");
}

/// A config channel override whose name the template does not have (a typo, or a channel a
/// newer template renamed) and that has no register of its own: wb-mqtt-serial loads it, fails
/// and ignores it with a warning (`LoadSimpleChannel`), so such a config runs there. It is a
/// warning here too, naming the template's closest channel; the rest of the device is kept.
#[test]
fn an_override_of_a_channel_the_template_lacks_is_a_warning_with_the_closest_name() {
    let config = r#"{"ports": [{"path": "/dev/x", "devices": [
        {"device_type": "rtu2mqtt-energy-meter", "slave_id": 30,
         "channels": [{"name": "Voltag", "enabled": false}]}]}]}"#;
    let (ok, text) = check_config(config);
    assert!(ok, "{text}");
    assert!(
        text.contains("the template has no channel `Voltag` (did you mean `Voltage`?)"),
        "{text}"
    );
    assert!(text.contains("ignored"), "{text}");
    // A channel of the config's own (with an address) is still taken as one.
    let own = r#"{"ports": [{"path": "/dev/x", "devices": [
        {"device_type": "rtu2mqtt-energy-meter", "slave_id": 30,
         "channels": [{"name": "Extra", "reg_type": "input", "address": 500}]}]}]}"#;
    let (ok, text) = check_config(own);
    assert!(ok, "{text}");
    assert!(!text.contains("no channel `Extra`"), "{text}");
}

/// A period out of range in a channel override is the config's mistake: the error points at
/// the config's line, not at the template channel it would land on.
#[test]
fn an_out_of_range_period_override_is_reported_where_the_config_has_it() {
    let config = r#"{"ports": [{"path": "/dev/x", "devices": [
        {"device_type": "rtu2mqtt-relay6", "slave_id": 20,
         "channels": [
           {"name": "K1", "read_period_ms": -5}]}]}]}"#;
    let (ok, text) = check_config(config);
    assert!(!ok, "{text}");
    assert!(
        text.contains("`read_period_ms` -5 is out of range"),
        "{text}"
    );
    assert!(
        text.contains("config.json:4:27:") && !text.contains("rtu2mqtt-relay6.json"),
        "the config's line and column, not the template's: {text}"
    );
}

/// A device with neither a template nor channels of its own (`device_type` forgotten) would run
/// and never be polled: a warning names it, and `--strict` fails on it. wb-mqtt-serial accepts
/// it too (its schema of a device without template requires only `slave_id`), only logging
/// "the device has no channels".
#[test]
fn a_device_without_device_type_or_channels_is_a_warning_that_names_it() {
    let config = r#"{"ports": [{"path": "/dev/ttyRS485-1", "devices": [
        {"slave_id": 20, "device_type": "rtu2mqtt-relay6"},
        {"slave_id": 23},
        {"slave_id": 24, "channels": [{"name": "T", "address": 1}]}]}]}"#;
    let (ok, text) = check_config(config);
    assert!(ok, "a warning alone does not fail: {text}");
    assert!(
        text.contains(
            "config.json:3:9: at ports[0].devices[1]: warning: the device with slave_id 23 on \
             port /dev/ttyRS485-1 has neither `device_type` nor `channels`: nothing will be \
             polled for it. `device_type` (the name of its template, e.g. \"WB-MR6C\") is \
             probably missing."
        ),
        "{text}"
    );
    assert_eq!(text.matches("warning:").count(), 1, "{text}");
    assert!(text.contains(": ok (1 port, 3 devices"), "{text}");
    let (ok, text) = check_config_strict(config);
    assert!(
        !ok && text.contains("1 warning(s), which --strict counts as errors"),
        "{text}"
    );

    // A device whose config turns off every channel of its template (kept for its setup
    // writes) is as asked: no warning, --strict passes.
    let all_off: Vec<String> = RELAY6_CHANNELS
        .iter()
        .map(|name| format!(r#"{{"name": "{name}", "enabled": false}}"#))
        .collect();
    let config = format!(
        r#"{{"ports": [{{"path": "/dev/ttyRS485-1", "devices": [
        {{"slave_id": 20, "device_type": "rtu2mqtt-relay6", "channels": [{}]}}]}}]}}"#,
        all_off.join(", ")
    );
    let (ok, text) = check_config_strict(&config);
    assert!(ok && !text.contains("warning:"), "{text}");
}

/// Every channel of templates/rtu2mqtt-relay6.json.
const RELAY6_CHANNELS: &[&str] = &[
    "K1",
    "K2",
    "K3",
    "K4",
    "K5",
    "K6",
    "Input 0",
    "Input 1",
    "Input 2",
    "Input 3",
    "Input 4",
    "Input 5",
    "Input 6",
    "Input 0 counter",
    "Input 1 counter",
    "Input 2 counter",
    "Input 3 counter",
    "Input 4 counter",
    "Input 5 counter",
    "Input 6 counter",
    "Input 0 single press counter",
    "Input 0 long press counter",
    "Input 1 single press counter",
    "Input 1 long press counter",
    "Input 2 single press counter",
    "Input 2 long press counter",
    "Input 3 single press counter",
    "Input 3 long press counter",
    "Input 4 single press counter",
    "Input 4 long press counter",
    "Input 5 single press counter",
    "Input 5 long press counter",
    "Input 6 single press counter",
    "Input 6 long press counter",
    "Serial",
    "FW Version",
    "Uptime",
    "MCU Voltage",
];

/// `"host": "mqtt://localhost"` or `"port": 0` would have `run` retry the broker forever with a
/// resolver error: refused where the config has them, saying what to write instead.
#[test]
fn a_broker_url_as_host_and_port_0_are_refused() {
    let (ok, text) = check_config(r#"{"mqtt": {"host": "mqtt://localhost"}}"#);
    assert!(!ok, "{text}");
    assert!(
        text.contains(
            "config.json:1:11: at mqtt.host: `mqtt://localhost` is a URL, not a host: write the \
             host name or IP address alone, \"host\": \"localhost\""
        ),
        "{text}"
    );
    assert!(!text.contains("TLS"), "plain mqtt:// needs no TLS: {text}");
    let (ok, text) = check_config(r#"{"mqtt": {"host": "mqtts://broker.lan"}}"#);
    assert!(!ok, "{text}");
    assert!(
        text.contains(
            "\"host\": \"broker.lan\"; TLS is set apart: add \"tls\": {} to the `mqtt` section"
        ) && text.contains("\"port\": 8883"),
        "{text}"
    );
    let (ok, text) = check_config(r#"{"mqtt": {"host": "localhost", "port": 0}}"#);
    assert!(!ok, "{text}");
    assert!(
        text.contains(
            "config.json:1:32: at mqtt.port: port 0 is no port a broker listens on: write the \
             broker's TCP port, \"port\": 1883"
        ),
        "{text}"
    );
    let (ok, text) = check_config(r#"{"mqtt": {"host": "192.168.1.10", "port": 8883}}"#);
    assert!(ok, "{text}");
}

/// A baud rate none of a bus's devices is likely set to (9601, 96000) shows on site only as
/// devices that do not answer: a warning names the port; an odd rate a device really uses is
/// still accepted.
#[test]
fn an_unusual_baud_rate_is_a_warning_that_names_the_port() {
    for baud in [9601, 96000] {
        let config = format!(
            r#"{{"ports": [{{"path": "/dev/ttyRS485-2", "baud_rate": {baud}, "devices": [
            {{"slave_id": 20, "device_type": "rtu2mqtt-relay6"}}]}}]}}"#
        );
        let (ok, text) = check_config(&config);
        assert!(ok, "{baud}: {text}");
        assert!(
            text.contains(&format!(
                "config.json:1:40: at ports[0].baud_rate: warning: baud_rate {baud} of port \
                 /dev/ttyRS485-2 is not a usual serial speed (110, 300, 600, 1200, 2400, 4800, \
                 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600): a typo?"
            )),
            "{baud}: {text}"
        );
        let (ok, text) = check_config_strict(&config);
        assert!(
            !ok && text.contains("1 warning(s), which --strict counts as errors"),
            "{baud}: {text}"
        );
    }
    for baud in [9600, 115200, 921600] {
        let config = format!(
            r#"{{"ports": [{{"path": "/dev/x", "baud_rate": {baud}, "devices": [
            {{"slave_id": 20, "device_type": "rtu2mqtt-relay6"}}]}}]}}"#
        );
        let (ok, text) = check_config_strict(&config);
        assert!(ok && !text.contains("warning"), "{baud}: {text}");
    }
    // Out of the loader's bounds it is no serial speed at all: refused.
    let (ok, text) = check_config(r#"{"ports": [{"path": "/dev/x", "baud_rate": 10000000}]}"#);
    assert!(
        !ok && text.contains(
            "at ports[0].baud_rate: baud_rate 10000000 is not a serial speed: the usual ones are \
             110, 300"
        ),
        "{text}"
    );
}

/// The count after "ok" is of the template library searched, not of the templates the config
/// uses: said so.
#[test]
fn the_template_count_is_of_the_library() {
    let (ok, text) = check_config(r#"{"ports": []}"#);
    assert!(ok, "{text}");
    assert!(
        text.contains(": ok (0 ports, 0 devices, 0 channels; ")
            && text.contains(" templates in the library)"),
        "{text}"
    );
}

/// The service takes its secrets from /etc/rtu2mqtt/environment; `check-config --env-file`
/// takes them too (the package's postinst checks the config so), quotes and comments as systemd
/// reads them, and variables that are not rtu2mqtt's left alone.
#[test]
fn check_config_takes_the_secrets_of_an_environment_file() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.json");
    std::fs::write(
        &config,
        r#"{"http": {"listen": "0.0.0.0:8080", "user": "site"}, "ports": []}"#,
    )
    .unwrap();
    let hash = format!("$2b$12${}", "a".repeat(53));
    let environment = dir.path().join("environment");
    std::fs::write(
        &environment,
        format!("# secrets\nRUST_LOG=debug\n\nRTU2MQTT_HTTP__PASSWORD_HASH=\"{hash}\"\n"),
    )
    .unwrap();
    let check = |env_file: Option<&Path>| {
        let mut command = bin();
        command.arg("check-config").arg("-c").arg(&config);
        if let Some(file) = env_file {
            command.arg("--env-file").arg(file);
        }
        let out = command.output().unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
        )
    };
    let (ok, stdout) = check(None);
    assert!(!ok && stdout.contains("password_hash"), "{stdout}");
    let (ok, stdout) = check(Some(&environment));
    assert!(ok, "{stdout}");
    let (ok, stdout) = check(Some(&dir.path().join("missing")));
    assert!(!ok, "{stdout}");
}
