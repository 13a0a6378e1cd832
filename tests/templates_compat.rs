//! The twelve upstream templates of the compatibility corpus load unchanged and resolve to the
//! right registers, formats and event flags.

use std::path::{Path, PathBuf};

use rtu2mqtt::config::TemplateFile;
use rtu2mqtt::device::{
    check_template, resolve_template_device, EventMode, RegisterFormat, RegisterType,
    ResolvedDevice,
};
use serde_json::json;

fn corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/compat/wb-templates")
}

fn template(name: &str) -> TemplateFile {
    TemplateFile::load(&corpus().join(name)).unwrap_or_else(|e| panic!("{e}"))
}

fn device(name: &str, config: serde_json::Value) -> ResolvedDevice {
    resolve_template_device(&template(name), &config).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn all_twelve_load_and_resolve() {
    let mut count = 0;
    for entry in std::fs::read_dir(corpus()).unwrap() {
        let path = entry.unwrap().path();
        let file = TemplateFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let errors = check_template(&file);
        assert!(
            errors.is_empty(),
            "{}: {}",
            path.display(),
            errors
                .iter()
                .map(|e| e.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        );
        count += 1;
    }
    assert_eq!(count, 12);
}

#[test]
fn dump() {
    for (name, cfg) in [
        (
            "config-wb-m1w2.json",
            json!({"slave_id": 7, "channels": [{"name": "Input 2", "device_type": "input2_discrete"}], "baud_rate": 192}),
        ),
        (
            "config-wb-mai11-deprecated.json",
            json!({"slave_id": 7, "channels": [{"name": "Input 2", "device_type": "p_4_20ma"}]}),
        ),
    ] {
        let d = device(name, cfg);
        println!("{} {} wb={} {:?}", d.id, d.name, d.is_wb, d.timing);
        for c in &d.channels {
            println!(
                "  {:?} {:?} {} {:?} ro={} ev={:?} {:?}",
                c.id,
                c.title,
                c.control_type,
                c.registers
                    .iter()
                    .map(|r| (r.read, r.codec.format))
                    .collect::<Vec<_>>(),
                c.readonly,
                c.events,
                c.units
            );
        }
        for s in &d.setup {
            println!(
                "  SETUP {} {:?} {} {:?}",
                s.title, s.register, s.value, s.words
            );
        }
    }
}
