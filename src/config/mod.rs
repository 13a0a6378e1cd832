//! Config file and device templates: serde types, JSON Schemas, loading with located errors.
// Located errors are built once per bad file, at load time: their size does not matter, and
// boxing them would only make every `match` on `problem` noisier.
#![allow(clippy::result_large_err)]

pub mod error;
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
