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
