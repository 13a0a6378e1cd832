//! Errors in config files and templates, each located: file, JSON path, line and column.

use std::fmt;
use std::path::{Path, PathBuf};

use super::json_path::{locate, JsonPath};
use super::jsonc::line_column;

/// What is wrong, independent of where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Problem {
    #[error("cannot read the file: {0}")]
    Io(String),
    #[error("not valid JSON: {0}")]
    Syntax(String),
    #[error("unknown key `{key}`{}", unknown_key_hint(key, valid))]
    UnknownKey { key: String, valid: Vec<String> },
    #[error("{0}")]
    Invalid(String),
    /// Not fatal (unless `check-config --strict`): a setting that does nothing.
    #[error("warning: {0}")]
    Warning(String),
    #[error(
        "no template for device_type `{device_type}`{} (searched: {searched})",
        similar_hint(similar)
    )]
    MissingTemplate {
        device_type: String,
        similar: Vec<String>,
        /// The template directories searched, in order.
        searched: String,
    },
    /// The device's template is there but does not load (its error follows).
    #[error(
        "the template of device_type `{device_type}` ({file}) does not load (the error is below){}",
        shadowed_hint(file, shadowed)
    )]
    BrokenTemplate {
        device_type: String,
        file: String,
        /// Earlier files of the same type it replaced.
        shadowed: Vec<String>,
    },
    /// A template of another protocol than Modbus (Mercury, DLMS, Milur …): rtu2mqtt cannot
    /// drive its devices. Not an error of the file: `check-templates` lists it apart.
    #[error(
        "protocol `{protocol}` is not supported: rtu2mqtt speaks Modbus (RTU, TCP, modbus_io) \
         only, so devices of this template cannot be used; keep them on wb-mqtt-serial"
    )]
    UnsupportedProtocol { protocol: String },
    /// A config device of another protocol: its template's (`template` is where that template
    /// says so) or its own `protocol`.
    #[error(
        "{}protocol `{protocol}` is not supported{}: rtu2mqtt speaks Modbus (RTU, TCP, \
         modbus_io) only and cannot poll this device. Keep this port on wb-mqtt-serial (one \
         program serves a port), or set `\"enabled\": false` on this device to run the port's \
         other devices without it",
        device_type.as_ref().map(|d| format!("device_type `{d}`: ")).unwrap_or_default(),
        template.as_ref().map(|t| format!(" (its template: {t})")).unwrap_or_default()
    )]
    UnsupportedDevice {
        device_type: Option<String>,
        protocol: String,
        template: Option<String>,
    },
    #[error("slave_id {slave_id} is used twice on this port: also by the device at {other}")]
    DuplicateSlaveId { slave_id: String, other: String },
    #[error("device id `{id}` is used twice: also by the device at {other}; set a distinct `id`")]
    DuplicateDeviceId { id: String, other: String },
    #[error("port `{port}` is configured twice: also at {other}")]
    DuplicatePort { port: String, other: String },
    #[error("register address {address} is out of range: Modbus addresses are 0…65535{}", span_hint(*count))]
    AddressOutOfRange { address: i64, count: u32 },
}

/// Valid keys are listed when there are few (a port's); a device with a big template has
/// hundreds of parameters, so only the closest few are offered.
const LIST_VALID_KEYS_UP_TO: usize = 40;

fn unknown_key_hint(key: &str, valid: &[String]) -> String {
    // Parameters are listed as "id (parameter)": suggest on the id, show the label.
    let bare = |label: &str| label.trim_end_matches(" (parameter)").to_string();
    let bare_names: Vec<String> = valid.iter().map(|v| bare(v)).collect();
    let suggestions = super::library::suggest_keys(key, bare_names.iter().map(String::as_str));
    let mut out = String::new();
    if !suggestions.is_empty() {
        let labels: Vec<String> = suggestions
            .iter()
            .map(|name| {
                let label = valid
                    .iter()
                    .find(|v| bare(v) == *name)
                    .cloned()
                    .unwrap_or_else(|| name.clone());
                match label.strip_suffix(" (parameter)") {
                    Some(id) => format!("`{id}` (a parameter of the template)"),
                    None => format!("`{label}`"),
                }
            })
            .collect();
        out.push_str(&format!("; did you mean {}?", labels.join(" or ")));
    }
    if valid.len() <= LIST_VALID_KEYS_UP_TO {
        if suggestions.is_empty() {
            out.push('.');
        }
        out.push_str(&format!(" Valid keys: {}", valid.join(", ")));
    } else if suggestions.is_empty() {
        out.push_str(&format!(
            " ({} settings and template parameters are valid here; `rtu2mqtt describe` and the template list them)",
            valid.len()
        ));
    }
    out
}

fn similar_hint(similar: &[String]) -> String {
    if similar.is_empty() {
        "; check the name, or add the template file to a templates directory (`--templates DIR` or `template_dirs`)".to_string()
    } else {
        format!(
            "; did you mean {}?",
            similar
                .iter()
                .map(|s| format!("`{s}`"))
                .collect::<Vec<_>>()
                .join(" or ")
        )
    }
}

fn span_hint(count: u32) -> String {
    if count > 1 {
        format!(" (the value spans {count} registers from there)")
    } else {
        String::new()
    }
}

/// A [`Problem`] with where it is: what an integrator on site needs to fix it.
#[derive(Debug, Clone, PartialEq)]
pub struct LocatedError {
    pub file: PathBuf,
    pub path: JsonPath,
    /// 1-based line and column in `file`, when the path could be found in the text.
    pub line_column: Option<(usize, usize)>,
    pub problem: Problem,
}

impl LocatedError {
    /// `file:line:column`, or the file alone: where the error is, for another message.
    pub fn location(&self) -> String {
        match self.line_column {
            Some((line, column)) => format!("{}:{line}:{column}", self.file.display()),
            None => self.file.display().to_string(),
        }
    }

    /// Locates `path` in `source` (the comment-blanked text of `file`).
    pub fn new(file: &Path, source: Option<&str>, path: JsonPath, problem: Problem) -> Self {
        let line_column =
            source.and_then(|text| locate(text, &path).map(|offset| line_column(text, offset)));
        Self {
            file: file.to_path_buf(),
            path,
            line_column,
            problem,
        }
    }

    /// An error that belongs to a whole file (cannot read it, no path inside).
    pub fn file_level(file: &Path, problem: Problem) -> Self {
        Self {
            file: file.to_path_buf(),
            path: JsonPath::root(),
            line_column: None,
            problem,
        }
    }
}

impl fmt::Display for LocatedError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some((line, column)) = self.line_column {
            write!(f, ":{line}:{column}")?;
        }
        if !self.path.is_root() {
            write!(f, ": at {}", self.path)?;
        }
        write!(f, ": {}", self.problem)
    }
}

impl std::error::Error for LocatedError {}

/// All errors found in one pass, so the integrator can fix them in one go.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorList(pub Vec<LocatedError>);

impl fmt::Display for ErrorList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, error) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{error}")?;
        }
        Ok(())
    }
}

impl std::error::Error for ErrorList {}

impl From<LocatedError> for ErrorList {
    fn from(error: LocatedError) -> Self {
        ErrorList(vec![error])
    }
}

/// For [`Problem::BrokenTemplate`]: the files of the same type it replaced, which are not used.
fn shadowed_hint(file: &str, shadowed: &[String]) -> String {
    if shadowed.is_empty() {
        return String::new();
    }
    format!(
        "; it replaces {} of the same device_type, which is not used (the last file loaded \
         wins, as in wb-mqtt-serial): fix or remove {file}",
        shadowed.join(", ")
    )
}
