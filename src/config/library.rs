//! Template files found on the search path, by `device_type`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde_json::Value;

use super::error::{LocatedError, Problem};
use super::json_path::JsonPath;
use super::parse::{deserialize_at, SourceText};
use super::template::Template;

/// Templates shipped with the package.
pub const SYSTEM_TEMPLATE_DIR: &str = "/usr/share/rtu2mqtt/templates";
/// The site's own templates; they win over the system ones on equal `device_type`.
pub const USER_TEMPLATE_DIR: &str = "/etc/rtu2mqtt/templates";
/// Where a Wiren Board controller keeps wb-mqtt-serial's template library, and the site's own
/// wb-mqtt-serial templates: searched too (before rtu2mqtt's own directories, which win), so a
/// `/etc/wb-mqtt-serial.conf` works as it is.
pub const WB_SYSTEM_TEMPLATE_DIR: &str = "/usr/share/wb-mqtt-serial/templates";
pub const WB_USER_TEMPLATE_DIR: &str = "/etc/wb-mqtt-serial.conf.d/templates";

/// The templates shipped in `templates/`, built into the binary so that a config using them
/// checks and runs from anywhere (a source checkout, a test) without `--templates`. Every
/// directory of the search path wins over them.
pub const BUILT_IN_TEMPLATES: [(&str, &str); 6] = [
    (
        "rtu2mqtt-climate.json",
        include_str!("../../templates/rtu2mqtt-climate.json"),
    ),
    (
        "rtu2mqtt-counter8.json",
        include_str!("../../templates/rtu2mqtt-counter8.json"),
    ),
    (
        "rtu2mqtt-dimmer.json",
        include_str!("../../templates/rtu2mqtt-dimmer.json"),
    ),
    (
        "rtu2mqtt-energy-meter.json",
        include_str!("../../templates/rtu2mqtt-energy-meter.json"),
    ),
    (
        "rtu2mqtt-generic.json",
        include_str!("../../templates/rtu2mqtt-generic.json"),
    ),
    (
        "rtu2mqtt-relay6.json",
        include_str!("../../templates/rtu2mqtt-relay6.json"),
    ),
];

/// The pseudo directory built-in templates are reported under.
pub const BUILT_IN_DIR: &str = "(built into rtu2mqtt)";

/// One loaded template file: typed for inspection, raw for merging with config devices.
#[derive(Debug, Clone)]
pub struct TemplateFile {
    pub source: SourceText,
    pub template: Template,
    pub raw: Value,
    /// Keys no rtu2mqtt field reads (UI-only keys, or typos): reported, not fatal.
    pub unknown_keys: Vec<JsonPath>,
}

impl TemplateFile {
    pub fn load(path: &Path) -> Result<Self, LocatedError> {
        let source = SourceText::read(path)?;
        Self::from_source(source)
    }

    pub fn from_source(source: SourceText) -> Result<Self, LocatedError> {
        let raw = source.parse_json()?;
        if let Some(err) = other_protocol(&source, &raw) {
            return Err(err);
        }
        let typed = deserialize_at::<Template>(&source, &raw, &JsonPath::root())?;
        Ok(Self {
            source,
            template: typed.value,
            raw,
            unknown_keys: typed.ignored,
        })
    }

    pub fn device_type(&self) -> &str {
        &self.template.device_type
    }

    pub fn is_deprecated(&self) -> bool {
        self.template.deprecated == Some(true)
    }
}

/// A template of another protocol than Modbus, said once for the whole file (at its
/// `device.protocol`) instead of at the first register type only that protocol knows.
fn other_protocol(source: &SourceText, raw: &Value) -> Option<LocatedError> {
    let protocol = raw
        .pointer("/device/protocol")
        .and_then(Value::as_str)
        .filter(|p| !is_modbus_protocol(p))?;
    Some(source.error(
        JsonPath::root().key("device").key("protocol"),
        Problem::UnsupportedProtocol {
            protocol: protocol.to_string(),
        },
    ))
}

/// The protocols of wb-mqtt-serial that are Modbus: what rtu2mqtt can drive.
pub fn is_modbus_protocol(protocol: &str) -> bool {
    matches!(
        protocol,
        "modbus" | "modbus-tcp" | "modbus_tcp" | "modbus_io" | "modbus_io-tcp"
    )
}

/// Where a template's text is: a file of the search path, or built into the binary.
#[derive(Debug, Clone)]
enum TemplateOrigin {
    File(PathBuf),
    BuiltIn { path: PathBuf, text: &'static str },
}

/// One `device_type` of the search path: what scanning the directories read of its file (the
/// file is parsed then, and dropped), and the template itself, read in full when first asked
/// for. A library of hundreds of templates, tens of megabytes of JSON, costs memory only for
/// the templates a config uses.
#[derive(Debug, Clone)]
pub struct TemplateEntry {
    origin: TemplateOrigin,
    pub deprecated: bool,
    /// Its `hw` signatures (Wiren Board models), for choosing a template by model.
    pub signatures: Vec<String>,
    /// Earlier files of the same `device_type` that this one replaced, for messages.
    pub shadowed: Vec<PathBuf>,
    /// What a list of device types shows of it (the RPC's `config/Load`).
    pub listing: TemplateListing,
    loaded: OnceLock<Result<TemplateFile, LocatedError>>,
}

/// One template of the library as a list of device types shows it, and where to read it
/// again: `config/Load` reads the templates of the config's devices at each request, without
/// keeping them.
#[derive(Debug, Clone)]
pub struct ListedTemplate {
    pub device_type: String,
    pub deprecated: bool,
    pub listing: TemplateListing,
    origin: TemplateOrigin,
}

impl ListedTemplate {
    /// The template's JSON, read again; `None` when it no longer reads.
    pub fn read_json(&self) -> Option<Value> {
        let source = match &self.origin {
            TemplateOrigin::File(path) => SourceText::read(path).ok()?,
            TemplateOrigin::BuiltIn { path, text } => SourceText::from_text(path, text),
        };
        source.parse_json().ok()
    }
}

/// A template's title by language, as wb-mqtt-serial's `GetTranslations` reads it: the
/// translations of `title` in `device.translations`, the title itself in English when not
/// translated there; none at all for an empty title.
fn titles(title: &str, device: Option<&Value>) -> Vec<(String, String)> {
    if title.is_empty() {
        return Vec::new();
    }
    let mut titles: Vec<(String, String)> = device
        .and_then(|d| d.get("translations"))
        .and_then(Value::as_object)
        .into_iter()
        .flatten()
        .filter_map(|(lang, words)| {
            let word = words.get(title).and_then(Value::as_str)?;
            (!word.is_empty()).then(|| (lang.clone(), word.to_owned()))
        })
        .collect();
    if !titles.iter().any(|(lang, _)| lang == "en") {
        titles.push(("en".to_owned(), title.to_owned()));
    }
    titles
}

/// What wb-mqtt-serial's list of device types (`config/Load`'s `types`) shows of a template,
/// read as its `TTemplateMap::MakeTemplateFromJson` reads it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TemplateListing {
    /// The title by language: `title` in English, its entries in `device.translations`.
    pub titles: Vec<(String, String)>,
    /// `group` (`g-wb`, `g-wb-old`, …); empty when the template has none.
    pub group: String,
    /// `device.id`: the MQTT device id before `_<slave_id>`.
    pub mqtt_id: String,
    /// `device.protocol`, `modbus` when left out.
    pub protocol: String,
    /// `hw`: each signature and its minimum firmware.
    pub hardware: Vec<(String, Option<String>)>,
}

impl TemplateListing {
    /// Read from a template's JSON.
    pub fn from_template(raw: &Value) -> Self {
        let text = |value: Option<&Value>| value.and_then(Value::as_str).unwrap_or("").to_owned();
        let device = raw.get("device");
        let hardware = raw
            .get("hw")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .map(|hw| {
                (
                    text(hw.get("signature")),
                    hw.get("fw")
                        .and_then(Value::as_str)
                        .filter(|fw| !fw.is_empty())
                        .map(str::to_owned),
                )
            })
            .collect();
        let protocol = device
            .and_then(|d| d.get("protocol"))
            .and_then(Value::as_str)
            .unwrap_or("modbus");
        Self {
            titles: titles(&text(raw.get("title")), device),
            group: text(raw.get("group")),
            mqtt_id: text(device.and_then(|d| d.get("id"))),
            protocol: protocol.to_owned(),
            hardware,
        }
    }

    /// The title in `lang`, else in English, else the device type (wb-mqtt-serial's
    /// `TDeviceTemplate::GetTitle`).
    pub fn title<'a>(&'a self, lang: &str, device_type: &'a str) -> &'a str {
        let find = |wanted: &str| {
            self.titles
                .iter()
                .find(|(lang, _)| lang == wanted)
                .map(|(_, title)| title.as_str())
        };
        find(lang).or_else(|| find("en")).unwrap_or(device_type)
    }
}

impl TemplateEntry {
    pub fn path(&self) -> &Path {
        match &self.origin {
            TemplateOrigin::File(path) | TemplateOrigin::BuiltIn { path, .. } => path,
        }
    }

    /// The template, read and checked the first time (its errors, if any, every time).
    fn load(&self) -> &Result<TemplateFile, LocatedError> {
        self.loaded.get_or_init(|| match &self.origin {
            TemplateOrigin::File(path) => TemplateFile::load(path),
            TemplateOrigin::BuiltIn { path, text } => {
                TemplateFile::from_source(SourceText::from_text(path, text))
            }
        })
    }
}

/// What scanning reads of a template file: enough to index it.
#[derive(Debug, serde::Deserialize)]
struct TemplateHead {
    device_type: String,
    deprecated: Option<bool>,
    hw: Option<Vec<super::template::HardwareSignature>>,
}

/// Every template of the search path by `device_type`, the last loaded winning (later
/// directories, later file names), as wb-mqtt-serial. Templates are indexed when the
/// directories are scanned and read in full when used.
#[derive(Debug, Clone, Default)]
pub struct TemplateLibrary {
    entries: BTreeMap<String, TemplateEntry>,
    /// Files that could not be indexed (not JSON, no `device_type`, another protocol); a
    /// template's own errors show when it is used.
    pub errors: Vec<LocatedError>,
    /// Directories searched, in order.
    pub dirs: Vec<PathBuf>,
    /// Files that could not be indexed, by the `device_type` they declare.
    failed: BTreeMap<String, LocatedError>,
}

impl TemplateLibrary {
    /// The search path: wb-mqtt-serial's system and user dirs, rtu2mqtt's system and user dirs,
    /// then `extra` (config `template_dirs`, then `--templates` options), each later one winning.
    pub fn standard_dirs(extra: &[PathBuf]) -> Vec<PathBuf> {
        let mut dirs = vec![
            PathBuf::from(WB_SYSTEM_TEMPLATE_DIR),
            PathBuf::from(WB_USER_TEMPLATE_DIR),
            PathBuf::from(SYSTEM_TEMPLATE_DIR),
            PathBuf::from(USER_TEMPLATE_DIR),
        ];
        dirs.extend(extra.iter().cloned());
        dirs
    }

    /// What `run` and `check-config` use: the built-in templates, then every directory of
    /// [`Self::standard_dirs`].
    pub fn load_standard(extra: &[PathBuf]) -> Self {
        let mut library = Self::built_in();
        library.merge(Self::load_dirs(&Self::standard_dirs(extra)));
        library
    }

    /// The templates compiled into the binary.
    pub fn built_in() -> Self {
        let mut library = Self::default();
        for (name, text) in BUILT_IN_TEMPLATES {
            let path = Path::new(BUILT_IN_DIR).join(name);
            let source = SourceText::from_text(&path, text);
            library.index(source, TemplateOrigin::BuiltIn { path, text });
        }
        library
    }

    /// Adds `later`'s templates, which win on equal `device_type`, its errors and its dirs.
    fn merge(&mut self, later: Self) {
        self.entries.extend(later.entries);
        self.errors.extend(later.errors);
        self.failed.extend(later.failed);
        self.dirs.extend(later.dirs);
    }

    /// The directories searched, for messages ("searched: …").
    pub fn searched(&self) -> String {
        // A directory that is not there is said so: a typo in `--templates`, or wb-mqtt-serial's
        // library looked for on a laptop.
        let mut names: Vec<String> = self
            .dirs
            .iter()
            .map(|d| {
                if d.is_dir() {
                    d.display().to_string()
                } else {
                    format!("{} (not there)", d.display())
                }
            })
            .collect();
        if !self.entries.is_empty() || names.is_empty() {
            names.insert(0, BUILT_IN_DIR.to_string());
        }
        names.join(", ")
    }

    /// Loads every `*.json` file of the directories that exist (missing ones are skipped: a
    /// fresh system has no user templates).
    pub fn load_dirs(dirs: &[PathBuf]) -> Self {
        let mut library = Self {
            dirs: dirs.to_vec(),
            ..Self::default()
        };
        for dir in dirs {
            let Ok(entries) = std::fs::read_dir(dir) else {
                continue;
            };
            let mut files: Vec<PathBuf> = entries
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.is_file() && p.extension().is_some_and(|e| e == "json"))
                .collect();
            files.sort();
            for file in files {
                match SourceText::read(&file) {
                    Ok(source) => library.index(source, TemplateOrigin::File(file)),
                    Err(err) => library.errors.push(err),
                }
            }
        }
        library
    }

    /// Indexes one template text. As wb-mqtt-serial (`TTemplateMap::AddTemplatesDir`), the
    /// last file indexed wins on equal `device_type`, `deprecated` or not (its library's
    /// `config-X-deprecated.json` sorts before `config-X.json`, and a user's copy comes after
    /// both); a file that is no template leaves an earlier one of its type in place.
    fn index(&mut self, source: SourceText, origin: TemplateOrigin) {
        let raw = match source.parse_json() {
            Ok(raw) => raw,
            Err(err) => {
                self.errors.push(err);
                return;
            }
        };
        let head = match deserialize_at::<TemplateHead>(&source, &raw, &JsonPath::root()) {
            Ok(head) => head.value,
            Err(err) => {
                if let Some(device_type) = raw.get("device_type").and_then(Value::as_str) {
                    self.failed.insert(device_type.to_owned(), err.clone());
                }
                self.errors.push(err);
                return;
            }
        };
        if let Some(err) = other_protocol(&source, &raw) {
            // The last loaded wins here too: an earlier Modbus template of this type is gone.
            self.entries.remove(&head.device_type);
            self.failed.insert(head.device_type, err.clone());
            self.errors.push(err);
            return;
        }
        self.failed.remove(&head.device_type);
        let shadowed = self
            .entries
            .remove(&head.device_type)
            .map(|earlier| {
                let path = earlier.path().to_path_buf();
                let mut shadowed = earlier.shadowed;
                shadowed.push(path);
                shadowed
            })
            .unwrap_or_default();
        self.entries.insert(
            head.device_type,
            TemplateEntry {
                origin,
                deprecated: head.deprecated == Some(true),
                signatures: head
                    .hw
                    .unwrap_or_default()
                    .into_iter()
                    .map(|hw| hw.signature)
                    .collect(),
                shadowed,
                listing: TemplateListing::from_template(&raw),
                loaded: OnceLock::new(),
            },
        );
    }

    /// Adds one template (tests, `check-templates FILE`); replaces one of the same type.
    pub fn insert(&mut self, template: TemplateFile) {
        let device_type = template.device_type().to_string();
        let entry = TemplateEntry {
            origin: TemplateOrigin::File(template.source.path.clone()),
            deprecated: template.is_deprecated(),
            signatures: template
                .template
                .hw
                .iter()
                .flatten()
                .map(|hw| hw.signature.clone())
                .collect(),
            shadowed: Vec::new(),
            listing: TemplateListing::from_template(&template.raw),
            loaded: OnceLock::from(Ok(template)),
        };
        self.entries.insert(device_type, entry);
    }

    /// The template of `device_type` when there is one but it does not load: its error, and
    /// the entry (its file, the earlier files it replaced).
    pub fn broken(&self, device_type: &str) -> Option<(&LocatedError, &TemplateEntry)> {
        let entry = self.entries.get(device_type)?;
        entry.load().as_ref().err().map(|error| (error, entry))
    }

    /// The template of `device_type`, read when first asked for; `None` when there is none or
    /// it does not load ([`Self::load_error_for`] says why).
    pub fn get(&self, device_type: &str) -> Option<&TemplateFile> {
        self.entries.get(device_type)?.load().as_ref().ok()
    }

    /// The templates of these device types only (with the same dirs): what a running service
    /// keeps of the library it resolved its config with.
    pub fn only<'a>(&self, device_types: impl IntoIterator<Item = &'a str>) -> Self {
        let mut kept = Self {
            dirs: self.dirs.clone(),
            ..Self::default()
        };
        for device_type in device_types {
            if let Some(template) = self.get(device_type) {
                kept.insert(template.clone());
            }
        }
        kept
    }

    /// Every device type with what the index knows of its template (nothing is read).
    pub fn entries(&self) -> impl Iterator<Item = (&str, &TemplateEntry)> {
        self.entries
            .iter()
            .map(|(device_type, entry)| (device_type.as_str(), entry))
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// What a list of device types shows of every template, and where each is (nothing is
    /// read).
    pub fn listings(&self) -> Vec<ListedTemplate> {
        self.entries
            .iter()
            .map(|(device_type, entry)| ListedTemplate {
                device_type: device_type.clone(),
                deprecated: entry.deprecated,
                listing: entry.listing.clone(),
                origin: entry.origin.clone(),
            })
            .collect()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Known device types close to `name` (case, punctuation, or a small typo), for hints.
    pub fn similar(&self, name: &str) -> Vec<String> {
        closest(
            name,
            self.entries
                .keys()
                .map(String::as_str)
                .filter(|k| *k != name),
            2,
            3,
        )
    }

    /// The protocol of `device_type`'s template and where the template says it, when the
    /// template was left out because its protocol is not Modbus.
    pub fn unsupported_protocol(&self, device_type: &str) -> Option<(&str, &LocatedError)> {
        let error = self.failed.get(device_type)?;
        match &error.problem {
            Problem::UnsupportedProtocol { protocol } => Some((protocol.as_str(), error)),
            _ => None,
        }
    }

    /// Why `device_type` is missing: a file that failed to load may have been meant.
    pub fn load_error_for(&self, device_type: &str) -> Option<&LocatedError> {
        if let Some(Err(error)) = self.entries.get(device_type).map(TemplateEntry::load) {
            return Some(error);
        }
        if let Some(error) = self.failed.get(device_type) {
            return Some(error);
        }
        let wanted = normalize(device_type);
        self.errors.iter().find(|e| {
            e.file
                .file_stem()
                .and_then(|s| s.to_str())
                .is_some_and(|stem| normalize(stem).contains(&wanted))
        })
    }
}

/// Up to `limit` of `candidates` within `max_distance` edits of `name` (ignoring case and
/// punctuation), closest first: what "did you mean" offers.
pub fn closest<'a>(
    name: &str,
    candidates: impl Iterator<Item = &'a str>,
    max_distance: usize,
    limit: usize,
) -> Vec<String> {
    let wanted = normalize(name);
    let mut ranked: Vec<(usize, &str)> = candidates
        .map(|candidate| (edit_distance(&normalize(candidate), &wanted), candidate))
        .filter(|(distance, _)| *distance <= max_distance)
        .collect();
    ranked.sort();
    ranked.dedup();
    ranked
        .into_iter()
        .take(limit)
        .map(|(_, c)| c.to_string())
        .collect()
}

/// The warning for a key no setting reads, with the keys it may be a misspelling of
/// (`suggestions`, from [`suggest_keys`]) and whether `object` (the JSON object holding it)
/// has them: a misspelt key is ignored, so the key meant keeps its default, which is rarely
/// harmless (`reg_typ` for `reg_type` polls holding registers instead of coils).
pub fn unknown_key_warning(
    what: &str,
    key: &str,
    suggestions: &[String],
    object: Option<&Value>,
) -> String {
    let mut text = format!("unknown {what} `{key}` is ignored");
    if suggestions.is_empty() {
        text.push_str(" (it does nothing)");
        return text;
    }
    let quoted: Vec<String> = suggestions.iter().map(|s| format!("`{s}`")).collect();
    text.push_str(&format!("; did you mean {}?", quoted.join(" or ")));
    let meant_unset = object.is_some_and(|object| {
        suggestions
            .iter()
            .all(|meant| object.get(meant.as_str()).is_none())
    });
    if meant_unset {
        text.push_str(&format!(
            " As {} is not set, its default applies.",
            quoted.join(" or ")
        ));
    }
    text
}

/// Keys close to a misspelt `key`, closest first: a small edit distance, or one is the other
/// with something added (`read_period` → `read_period_ms`).
pub fn suggest_keys<'a>(key: &str, candidates: impl Iterator<Item = &'a str>) -> Vec<String> {
    let wanted = normalize(key);
    let mut ranked: Vec<(usize, &str)> = candidates
        .filter_map(|candidate| {
            let normalized = normalize(candidate);
            let distance = edit_distance(&normalized, &wanted);
            let extends = wanted.len() >= 4
                && normalized.len() >= 4
                && (normalized.starts_with(&wanted) || wanted.starts_with(&normalized));
            (distance <= 2 || extends).then_some((distance, candidate))
        })
        .collect();
    ranked.sort();
    ranked.dedup();
    // Only the closest: `in1_mod` offers `in1_mode`, not every `inN_mode` one edit further.
    let best = ranked.first().map(|(d, _)| *d).unwrap_or(0);
    ranked
        .into_iter()
        .take_while(|(d, _)| *d == best)
        .take(3)
        .map(|(_, c)| c.to_string())
        .collect()
}

fn normalize(name: &str) -> String {
    name.chars()
        .filter(|c| c.is_alphanumeric())
        .flat_map(char::to_lowercase)
        .collect()
}

fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    let mut previous: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.iter().enumerate() {
        let mut current = vec![i + 1];
        for (j, cb) in b.iter().enumerate() {
            let substitution = previous[j] + usize::from(ca != cb);
            current.push(substitution.min(previous[j + 1] + 1).min(current[j] + 1));
        }
        previous = current;
    }
    previous.last().copied().unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, device_type: &str, device_name: &str) {
        let text = format!(
            r#"{{"device_type": "{device_type}", "device": {{"name": "{device_name}", "channels": []}}}}"#
        );
        std::fs::write(dir.join(name), text).unwrap();
    }

    #[test]
    fn later_directories_win_and_bad_files_are_reported() {
        let system = tempfile::tempdir().unwrap();
        let user = tempfile::tempdir().unwrap();
        write(system.path(), "a.json", "A", "system");
        write(system.path(), "b.json", "B", "system");
        write(user.path(), "a.json", "A", "user");
        std::fs::write(user.path().join("broken.json"), "{").unwrap();
        std::fs::write(user.path().join("notes.txt"), "ignored").unwrap();
        let library = TemplateLibrary::load_dirs(&[
            system.path().to_path_buf(),
            user.path().to_path_buf(),
            PathBuf::from("/nonexistent/dir"),
        ]);
        assert_eq!(library.len(), 2);
        assert_eq!(
            library.get("A").unwrap().template.device.name.as_deref(),
            Some("user")
        );
        assert_eq!(library.errors.len(), 1);
        assert!(library.errors[0].file.ends_with("broken.json"));
    }

    #[test]
    fn a_template_is_read_in_full_only_when_used() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "a.json", "A", "fine");
        // Valid JSON with a device_type: indexed; its channel's error shows when it is used.
        std::fs::write(
            dir.path().join("b.json"),
            "{\"device_type\": \"B\", \"device\": {\"channels\": [\n  {\"name\": \"x\", \"address\": 1, \"format\": \"float32\"}]}}",
        )
        .unwrap();
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        assert_eq!(library.len(), 2);
        assert!(library.errors.is_empty(), "{:?}", library.errors);
        let loaded = |library: &TemplateLibrary| {
            library
                .entries()
                .filter(|(_, entry)| entry.loaded.get().is_some())
                .count()
        };
        assert_eq!(loaded(&library), 0, "nothing read before it is used");
        assert!(library.get("A").is_some());
        assert_eq!(loaded(&library), 1);
        assert!(library.get("B").is_none());
        let error = library.load_error_for("B").expect("why B does not load");
        assert!(
            error
                .to_string()
                .contains("b.json:2:31: at device.channels[0].format"),
            "{error}"
        );
        // What a service keeps: the used templates, already read.
        let kept = library.only(["A"]);
        assert_eq!((kept.len(), loaded(&kept)), (1, 1));
    }

    #[test]
    fn a_later_template_of_another_protocol_wins_and_a_later_modbus_one_wins_over_it() {
        let milur = r#"{"device_type": "M", "device": {"protocol": "milur", "channels": []}}"#;
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "a.json", "M", "modbus");
        std::fs::write(dir.path().join("b.json"), milur).unwrap();
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        assert!(library.get("M").is_none());
        assert_eq!(
            library.unsupported_protocol("M").map(|(p, _)| p),
            Some("milur")
        );
        let later = tempfile::tempdir().unwrap();
        write(later.path(), "c.json", "M", "modbus again");
        let library =
            TemplateLibrary::load_dirs(&[dir.path().to_path_buf(), later.path().to_path_buf()]);
        assert!(library.get("M").is_some());
        assert!(library.unsupported_protocol("M").is_none());
    }

    #[test]
    fn the_last_template_loaded_wins_as_in_wb_mqtt_serial() {
        let dir = tempfile::tempdir().unwrap();
        // wb's twins: the deprecated file sorts first, the current one is loaded last.
        std::fs::write(
            dir.path().join("config-x-deprecated.json"),
            r#"{"device_type": "X", "deprecated": true, "device": {"name": "old", "channels": []}}"#,
        )
        .unwrap();
        write(dir.path(), "config-x.json", "X", "current");
        // Two current files of one type in one directory: the later by name.
        write(dir.path(), "a.json", "Y", "first");
        write(dir.path(), "b.json", "Y", "second");
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        let name = |library: &TemplateLibrary, device_type: &str| {
            library
                .get(device_type)
                .and_then(|t| t.template.device.name.clone())
        };
        assert_eq!(name(&library, "X").as_deref(), Some("current"));
        assert_eq!(name(&library, "Y").as_deref(), Some("second"));
        assert!(library.errors.is_empty());
        // A later directory wins, even with a deprecated copy (a user's own, kept on purpose).
        let later = tempfile::tempdir().unwrap();
        std::fs::write(
            later.path().join("x.json"),
            r#"{"device_type": "X", "deprecated": true, "device": {"name": "user's old", "channels": []}}"#,
        )
        .unwrap();
        let library =
            TemplateLibrary::load_dirs(&[dir.path().to_path_buf(), later.path().to_path_buf()]);
        assert_eq!(name(&library, "X").as_deref(), Some("user's old"));
    }

    #[test]
    fn similar_names_closest_first() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "a.json", "WB-MAI6", "x");
        write(dir.path(), "b.json", "WB-MR6C", "x");
        write(dir.path(), "c.json", "WB-MR6CU", "x");
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        assert_eq!(
            library.similar("WB-MR6"),
            vec!["WB-MR6C", "WB-MAI6", "WB-MR6CU"]
        );
    }

    #[test]
    fn similar_names() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "a.json", "WB-MR6C", "x");
        let library = TemplateLibrary::load_dirs(&[dir.path().to_path_buf()]);
        assert_eq!(library.similar("wb-mr6c"), vec!["WB-MR6C"]);
        assert_eq!(library.similar("WB-MR6"), vec!["WB-MR6C"]);
        assert!(library.similar("SDM220").is_empty());
    }
}
