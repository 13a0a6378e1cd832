//! The JSON Schemas validate the shipped config, the examples, our templates and the wb-format
//! fixtures (an editor using the schema agrees with the loader).

use std::path::{Path, PathBuf};

use rtu2mqtt::cli::schema::{schema_json, SchemaKind};
use rtu2mqtt::config::jsonc::strip_comments;

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn json_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    files.sort();
    files
}

fn assert_valid(kind: SchemaKind, files: &[PathBuf]) {
    let schema = schema_json(kind);
    let validator = jsonschema::validator_for(&schema).unwrap();
    assert!(!files.is_empty());
    for file in files {
        let text = strip_comments(&std::fs::read_to_string(file).unwrap());
        let instance: serde_json::Value = serde_json::from_str(&text).unwrap();
        let errors: Vec<String> = validator
            .iter_errors(&instance)
            .map(|e| format!("{} at {}", e, e.instance_path()))
            .collect();
        assert!(
            errors.is_empty(),
            "{}: {}",
            file.display(),
            errors.join("\n")
        );
    }
}

#[test]
fn config_schema_accepts_shipped_configs() {
    let mut files = vec![repo("config/config.json")];
    // `*-bus.json` are bus files of the simulator (docs/sim.md), not daemon configs.
    files.extend(
        json_files(&repo("config/examples"))
            .into_iter()
            .filter(|f| !f.to_string_lossy().ends_with("-bus.json")),
    );
    assert!(files.iter().any(|f| f.ends_with("sim-daemon.json")));
    assert_valid(SchemaKind::Config, &files);
}

#[test]
fn template_schema_accepts_all_templates() {
    let mut files = json_files(&repo("templates"));
    files.extend(json_files(&repo("tests/data/wb-templates")));
    assert_valid(SchemaKind::Template, &files);
}

#[test]
fn config_schema_rejects_typos() {
    let validator = jsonschema::validator_for(&schema_json(SchemaKind::Config)).unwrap();
    assert!(!validator.is_valid(&serde_json::json!({"mqtt": {"hots": "x"}})));
    assert!(!validator.is_valid(&serde_json::json!({"ports": [{"port_type": "rtu"}]})));
}

/// `rtu2mqtt schema config | head -1`: a reader that is gone ends the command quietly (as
/// `SIGPIPE` ends other tools), not with a panic and a backtrace. The pipe's read end is closed
/// before the command starts, so its first write finds no reader.
#[test]
fn output_into_a_closed_pipe_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let (read_end, write_end) = nix::unistd::pipe().unwrap();
    drop(read_end);
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .args(["schema", "config"])
        .stdout(std::process::Stdio::from(write_end))
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        output.status.signal(),
        Some(13),
        "{:?} {stderr}",
        output.status
    );
}

/// An editor using the schema agrees with `check-config` on the port's line settings and the
/// broker's address: each config is valid in the schema exactly when the loader takes it.
#[test]
fn config_schema_agrees_with_the_loader() {
    use rtu2mqtt::config::load::load_config_source;
    use rtu2mqtt::config::parse::SourceText;
    let validator = jsonschema::validator_for(&schema_json(SchemaKind::Config)).unwrap();
    let port = |key: &str, value: serde_json::Value| serde_json::json!({"ports": [{"path": "/dev/ttyRS485-1", key: value}]});
    let mut configs = Vec::new();
    for stop_bits in [0, 1, 2, 3, 255] {
        configs.push(port("stop_bits", stop_bits.into()));
    }
    for data_bits in [0, 4, 5, 7, 8, 9, 255] {
        configs.push(port("data_bits", data_bits.into()));
    }
    for baud in [0, 1, 109, 110, 9600, 9601, 921_600, 4_000_000, 4_000_001] {
        configs.push(port("baud_rate", baud.into()));
    }
    for host in [
        "localhost",
        "192.168.1.10",
        "::1",
        "mqtt://localhost",
        "mqtts://broker.lan:8883",
        "localhost:1883",
        "broker/x",
        "",
        "   ",
        " localhost",
        "[::1]",
        "[::1]:1883",
        "fe80::1%eth0",
    ] {
        configs.push(serde_json::json!({"mqtt": {"host": host}}));
    }
    for mqtt_port in [0, 1, 1883] {
        configs.push(serde_json::json!({"mqtt": {"port": mqtt_port}}));
    }
    for config in configs {
        let text = config.to_string();
        let loaded = load_config_source(
            SourceText::from_text(std::path::Path::new("config.json"), &text),
            false,
        );
        assert_eq!(
            validator.is_valid(&config),
            loaded.is_ok(),
            "{text}: the schema and the loader disagree ({:?})",
            loaded.err().map(|e| e.to_string())
        );
    }
}

/// What the schema says of the settings an integrator looks up most: the defaults are the
/// loader's, and the texts are for users, not the code's names.
#[test]
fn config_schema_describes_defaults_for_users() {
    let schema = schema_json(SchemaKind::Config);
    let port = &schema["$defs"]["PortConfig"]["properties"];
    assert_eq!(port["stop_bits"]["default"], 1);
    assert_eq!(port["data_bits"]["default"], 8);
    assert_eq!(port["baud_rate"]["default"], 9600);
    assert!(port["stop_bits"]["description"]
        .as_str()
        .is_some_and(|d| d.contains("Default 1")));
    let description = schema["description"].as_str().unwrap();
    assert!(
        !description.contains("::") && !description.contains("split_ignored"),
        "{description}"
    );
    assert!(description.contains("warning"), "{description}");
}
