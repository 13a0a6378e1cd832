//! Templates of makers other than Wiren Board, and devices of protocols other than Modbus in a
//! wb-mqtt-serial config: what `check-config`, `describe`, `run` and `check-templates` say.
//! (A controller with one Mercury or Milur meter beside its Modbus devices is common.)

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
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

/// `rtu2mqtt <command> -c CONFIG` with the wb-format fixtures as templates (the non-Modbus
/// meter `TEST-NOT-MODBUS`, protocol `milur`, is in tests/data/wb-rules).
fn with_fixtures(command: &str, config: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("config.json");
    std::fs::write(&file, config).unwrap();
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
    assert!(ok && text.contains("ok (1 ports, 1 devices"), "{text}");
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
