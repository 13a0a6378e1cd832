//! A template library of the size a controller has on the daemon's search path
//! (wb-mqtt-serial's, `/usr/share/wb-mqtt-serial/templates`), written for a benchmark run: the
//! daemon's memory must not grow with templates no device uses.

use std::path::Path;

use serde_json::{json, Map, Value};

/// Templates written, and their channels and parameters: single Wiren Board templates run to
/// 100–650 KB (MAP12H's harmonics, ONOKOM's units); these are ~130 KB each.
pub const LIBRARY_FILES: usize = 150;
const CHANNELS: usize = 300;
const PARAMETERS: usize = 150;

/// One synthetic template of device type `LIB-<index>`: channels of every register type and
/// format, parameters with enums and groups, a translation per channel.
fn template(index: usize) -> Value {
    const TYPES: [&str; 4] = ["holding", "input", "coil", "discrete"];
    const FORMATS: [&str; 4] = ["u16", "s16", "u32", "float"];
    let channels: Vec<Value> = (0..CHANNELS)
        .map(|c| {
            let reg_type = TYPES[c % TYPES.len()];
            let mut channel = json!({
                "name": format!("Channel {c}"),
                "reg_type": reg_type,
                "address": c,
                "type": "value",
                "enabled": c < 10,
                "group": format!("g{}", c / 50),
            });
            if !matches!(reg_type, "coil" | "discrete") {
                channel["format"] = json!(FORMATS[c % FORMATS.len()]);
                channel["scale"] = json!(0.1);
            }
            channel
        })
        .collect();
    let parameters: Map<String, Value> = (0..PARAMETERS)
        .map(|p| {
            (
                format!("param_{p}"),
                json!({
                    "title": format!("Parameter {p}"),
                    "address": 1000 + p,
                    "reg_type": "holding",
                    "enum": [0, 1, 2],
                    "enum_titles": ["off", "on", "auto"],
                    "default": 0,
                    "group": format!("g{}", p / 50),
                }),
            )
        })
        .collect();
    let translations: Map<String, Value> = (0..CHANNELS)
        .map(|c| (format!("Channel {c}"), json!(format!("Канал {c}"))))
        .collect();
    json!({
        "title": format!("Library device {index}"),
        "device_type": format!("LIB-{index}"),
        "group": "g-wb",
        "device": {
            "name": format!("Library device {index}"),
            "id": format!("lib{index}"),
            "groups": (0..6).map(|g| json!({"title": format!("Group {g}"), "id": format!("g{g}")})).collect::<Vec<_>>(),
            "parameters": parameters,
            "channels": channels,
            "translations": {"ru": translations},
        }
    })
}

/// Writes [`LIBRARY_FILES`] templates into `dir` (created); returns the bytes written.
pub fn write_template_library(dir: &Path) -> std::io::Result<u64> {
    std::fs::create_dir_all(dir)?;
    let mut bytes = 0;
    for index in 0..LIBRARY_FILES {
        let text = serde_json::to_string_pretty(&template(index))?;
        bytes += text.len() as u64;
        std::fs::write(dir.join(format!("config-lib-{index}.json")), text)?;
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TemplateLibrary;

    #[test]
    fn the_library_is_templates_the_daemon_loads() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = write_template_library(dir.path()).unwrap();
        assert!(bytes > 10_000_000, "{bytes}");
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        assert!(library.errors.is_empty(), "{:?}", library.errors);
        assert_eq!(library.len(), LIBRARY_FILES);
        let template = library.get("LIB-7").expect("loads");
        assert_eq!(
            template.template.device.channels.as_ref().map(Vec::len),
            Some(CHANNELS)
        );
    }
}
