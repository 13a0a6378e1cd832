//! Config and template loading on arbitrary text: the whole path `check-config` runs (JSON with
//! comments, typed loading, the port and device checks, merging with a template, resolving
//! every channel) and `check-templates` runs (every subdevice choice). Never a panic, never a
//! stack overflow, whatever the numbers, names and conditions are. The seeds in
//! `fuzz/seeds/config_load` hold the hostile inputs found by hand (deep conditions, huge
//! addresses and shifts, "0x-14", i128::MIN, names with `+ # /` and NUL).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::{TemplateFile, TemplateLibrary};
use rtu2mqtt::device::{check_template, resolve_config};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    // The same text as a template, checked alone and used by a device …
    let template_source = SourceText::from_text(Path::new("fuzz-template.json"), text);
    let mut library = TemplateLibrary::built_in();
    if let Ok(template) = TemplateFile::from_source(template_source) {
        let _ = check_template(&template);
        library.insert(template);
    }
    // … and as a config, resolved against the built-in templates and that one.
    let config_source = SourceText::from_text(Path::new("fuzz-config.json"), text);
    if let Ok(loaded) = load_config_source(config_source, false) {
        let _ = resolve_config(&loaded, &library);
    }
});
