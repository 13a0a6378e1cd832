//! Config file and device templates: serde types, JSON Schemas, loading with located errors.
// Located errors are built once per bad file, at load time: their size does not matter, and
// boxing them would only make every `match` on `problem` noisier.
#![allow(clippy::result_large_err)]

pub mod error;
pub mod format;
pub mod json_path;
pub mod jsonc;
pub mod values;

pub use error::{ErrorList, LocatedError, Problem};
pub use json_path::JsonPath;
pub mod condition;
pub mod config_file;
pub mod library;
pub mod load;
pub mod parse;
pub mod template;

pub use library::{TemplateFile, TemplateLibrary};
pub use load::{load_config, LoadedConfig};

/// The device timing keys bounded at load time with their values, for a config device and a
/// template device alike (the two types share these field names).
macro_rules! device_durations {
    ($device:expr) => {{
        let device = $device;
        [
            ("response_timeout_ms", device.response_timeout_ms),
            ("frame_timeout_ms", device.frame_timeout_ms),
            ("guard_interval_us", device.guard_interval_us),
            ("min_request_interval", device.min_request_interval),
            ("device_timeout_ms", device.device_timeout_ms),
            ("max_write_fail_time_s", device.max_write_fail_time_s),
            ("read_rate_limit_ms", device.read_rate_limit_ms),
            ("poll_interval", device.poll_interval),
        ]
        .into_iter()
        .filter_map(|(key, value)| value.map(|value| (key, value)))
        .collect::<Vec<(&'static str, i64)>>()
    }};
}
pub(crate) use device_durations;
