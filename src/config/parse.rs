//! Reading a JSON file (with comments) into typed values, keeping every error located and
//! collecting the keys no field took.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde_json::Value;

use super::error::{LocatedError, Problem};
use super::json_path::{JsonPath, PathSegment};
use super::jsonc::strip_comments;

/// A file's text with comments blanked, kept to locate errors found later.
#[derive(Debug, Clone)]
pub struct SourceText {
    pub path: PathBuf,
    pub text: String,
}

impl SourceText {
    pub fn read(path: &Path) -> Result<Self, LocatedError> {
        let text = std::fs::read_to_string(path)
            .map_err(|err| LocatedError::file_level(path, Problem::Io(err.to_string())))?;
        Ok(Self::from_text(path, &text))
    }

    pub fn from_text(path: &Path, text: &str) -> Self {
        // A byte order mark (Windows editors save UTF-8 with one) is skipped, as jsoncpp, which
        // wb-mqtt-serial reads its files with, skips it; lines and columns are then those an
        // editor shows, which does not show the mark.
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        Self {
            path: path.to_path_buf(),
            text: strip_comments(text),
        }
    }

    /// An error at `path` inside this file.
    pub fn error(&self, path: JsonPath, problem: Problem) -> LocatedError {
        LocatedError::new(&self.path, Some(&self.text), path, problem)
    }

    /// Parses the JSON syntax; errors carry serde_json's line and column.
    pub fn parse_json(&self) -> Result<Value, LocatedError> {
        if self.text.trim().is_empty() {
            // serde_json would say "EOF while parsing a value" at line 1, column 0.
            return Err(LocatedError::file_level(
                &self.path,
                Problem::Syntax("the file is empty (or holds only comments)".into()),
            ));
        }
        serde_json::from_str(&self.text).map_err(|err| LocatedError {
            file: self.path.clone(),
            path: JsonPath::root(),
            line_column: Some((err.line(), err.column())),
            problem: Problem::Syntax(strip_position(&err.to_string())),
        })
    }
}

/// serde_json appends " at line L column C"; the location is printed separately.
fn strip_position(message: &str) -> String {
    match message.rfind(" at line ") {
        Some(pos) => message[..pos].to_string(),
        None => message.to_string(),
    }
}

/// A typed value and the paths (relative to where it was read) of keys no field took.
pub struct Typed<T> {
    pub value: T,
    pub ignored: Vec<JsonPath>,
}

/// Deserializes `raw` (found at `base` in `source`) into `T`, with the error's JSON path.
pub fn deserialize_at<T: DeserializeOwned>(
    source: &SourceText,
    raw: &Value,
    base: &JsonPath,
) -> Result<Typed<T>, LocatedError> {
    let mut ignored = Vec::new();
    let result = {
        let mut record = |path: serde_ignored::Path| ignored.push(ignored_path(&path));
        let deserializer = serde_ignored::Deserializer::new(raw, &mut record);
        serde_path_to_error::deserialize::<_, T>(deserializer)
    };
    match result {
        Ok(value) => Ok(Typed { value, ignored }),
        Err(err) => {
            let inner = base.join(&error_path(err.path()));
            Err(source.error(inner, problem_from_serde(&err.inner().to_string())))
        }
    }
}

/// serde's messages, reworded where an integrator needs more than serde says.
fn problem_from_serde(message: &str) -> Problem {
    if let Some(rest) = message.strip_prefix("unknown field `") {
        if let Some((key, tail)) = rest.split_once('`') {
            let valid = tail
                .split('`')
                .enumerate()
                .filter(|(i, _)| i % 2 == 1)
                .map(|(_, name)| name.to_string())
                .collect::<Vec<_>>();
            return Problem::UnknownKey {
                key: key.to_string(),
                valid,
            };
        }
    }
    if let Some(rest) = message.strip_prefix("unknown variant `") {
        if let Some((name, tail)) = rest.split_once('`') {
            let valid: Vec<&str> = tail
                .split('`')
                .enumerate()
                .filter(|(i, _)| i % 2 == 1)
                .map(|(_, n)| n)
                .collect();
            return Problem::Invalid(format!(
                "unknown value `{name}`; valid values: {}",
                valid.join(", ")
            ));
        }
    }
    Problem::Invalid(plain_type_error(message).unwrap_or_else(|| message.to_string()))
}

/// serde's "invalid type: string \"9600\", expected u32" in the integrator's words: JSON kinds
/// and ranges instead of Rust's type names, and a hint when a number or `true`/`false` was
/// written in quotes. `None` for other messages.
fn plain_type_error(message: &str) -> Option<String> {
    let (kind, rest) = if let Some(rest) = message.strip_prefix("invalid type: ") {
        ("type", rest)
    } else if let Some(rest) = message.strip_prefix("invalid value: ") {
        ("value", rest)
    } else if let Some(rest) = message.strip_prefix("invalid length ") {
        ("length", rest)
    } else {
        return None;
    };
    let (found, expected) = rest.rsplit_once(", expected ")?;
    let expected_words = expected_in_words(expected);
    if kind == "length" {
        return Some(format!("{found} entries, expected {expected_words}"));
    }
    let quoted = found
        .strip_prefix("string ")
        .and_then(|s| serde_json::from_str::<String>(s).ok());
    let found_words = match &quoted {
        Some(text) => format!("the text {}", serde_json::Value::from(text.as_str())),
        None => found_in_words(found),
    };
    let numeric = expected_words.starts_with("a whole number") || expected_words == "a number";
    let hint = match &quoted {
        Some(text) if numeric && text.trim().parse::<f64>().is_ok() => {
            "; write the number without the quotes"
        }
        Some(text)
            if expected_words == "true or false" && matches!(text.trim(), "true" | "false") =>
        {
            "; write it without the quotes"
        }
        _ => "",
    };
    Some(if kind == "value" && found.starts_with("integer ") {
        format!("{found_words} is out of range: expected {expected_words}")
    } else {
        format!("expected {expected_words}, found {found_words}{hint}")
    })
}

fn expected_in_words(expected: &str) -> String {
    match expected {
        "u8" => "a whole number from 0 to 255".into(),
        "u16" => "a whole number from 0 to 65535".into(),
        "u32" => "a whole number from 0 to 4294967295".into(),
        "u64" | "u128" | "usize" => "a whole number, 0 or more".into(),
        "i8" | "i16" | "i32" | "i64" | "i128" | "isize" => "a whole number".into(),
        "f32" | "f64" => "a number".into(),
        "a boolean" => "true or false".into(),
        "a sequence" => "a list `[…]`".into(),
        "a map" => "an object `{…}`".into(),
        "a string" => "a string in quotes".into(),
        other if other.starts_with("struct ") || other.starts_with("a map ") => {
            "an object `{…}`".into()
        }
        other if other.starts_with("a sequence ") || other.starts_with("a tuple") => {
            "a list `[…]`".into()
        }
        other => other.to_string(),
    }
}

/// serde's `Unexpected` (`integer \`5\``, `floating point \`1.5\``, `map` …) as JSON says it.
fn found_in_words(found: &str) -> String {
    let ticked = |prefix: &str| {
        found
            .strip_prefix(prefix)
            .map(|v| v.trim_matches('`').to_string())
    };
    if let Some(value) = ticked("integer ").or_else(|| ticked("floating point ")) {
        return value;
    }
    if let Some(value) = ticked("boolean ") {
        return value;
    }
    match found {
        "map" => "an object `{…}`".into(),
        "sequence" => "a list `[…]`".into(),
        "unit value" | "null" | "Option value" => "null".into(),
        other => other.to_string(),
    }
}

fn error_path(path: &serde_path_to_error::Path) -> JsonPath {
    let mut out = JsonPath::root();
    for segment in path.iter() {
        out = match segment {
            serde_path_to_error::Segment::Seq { index } => out.index(*index),
            serde_path_to_error::Segment::Map { key } => out.key(key.clone()),
            serde_path_to_error::Segment::Enum { variant } => out.key(variant.clone()),
            serde_path_to_error::Segment::Unknown => out,
        };
    }
    out
}

fn ignored_path(path: &serde_ignored::Path) -> JsonPath {
    match path {
        serde_ignored::Path::Root => JsonPath::root(),
        serde_ignored::Path::Seq { parent, index } => ignored_path(parent).index(*index),
        serde_ignored::Path::Map { parent, key } => ignored_path(parent).key(key.clone()),
        serde_ignored::Path::Some { parent }
        | serde_ignored::Path::NewtypeStruct { parent }
        | serde_ignored::Path::NewtypeVariant { parent } => ignored_path(parent),
    }
}

/// The value at `path` inside `root`.
pub fn value_at<'a>(root: &'a Value, path: &JsonPath) -> Option<&'a Value> {
    path.segments()
        .iter()
        .try_fold(root, |value, segment| match segment {
            PathSegment::Key(key) => value.get(key),
            PathSegment::Index(index) => value.get(*index),
        })
}

/// Property names the JSON Schema allows for the object at `path` (for "valid keys: …").
pub fn schema_keys_at(schema: &Value, path: &JsonPath) -> Vec<String> {
    let mut current = vec![schema];
    for segment in path.segments() {
        let mut next = Vec::new();
        for node in current.iter().flat_map(|n| expand(schema, n)) {
            match segment {
                PathSegment::Key(key) => {
                    if let Some(prop) = node.get("properties").and_then(|p| p.get(key)) {
                        next.push(prop);
                    } else if let Some(extra) =
                        node.get("additionalProperties").filter(|v| v.is_object())
                    {
                        next.push(extra);
                    }
                }
                PathSegment::Index(_) => {
                    if let Some(items) = node.get("items") {
                        next.push(items);
                    }
                }
            }
        }
        current = next;
    }
    let mut keys: Vec<String> = current
        .iter()
        .flat_map(|n| expand(schema, n))
        .filter_map(|n| n.get("properties").and_then(Value::as_object))
        .flat_map(|props| props.keys().cloned())
        .collect();
    keys.sort();
    keys.dedup();
    keys
}

/// A schema node with `$ref`, `anyOf`, `oneOf` and `allOf` followed.
fn expand<'a>(root: &'a Value, node: &'a Value) -> Vec<&'a Value> {
    let mut out = Vec::new();
    let mut stack = vec![node];
    let mut steps = 0;
    while let Some(n) = stack.pop() {
        steps += 1;
        if steps > 256 {
            break;
        }
        if let Some(reference) = n.get("$ref").and_then(Value::as_str) {
            let pointer = reference.trim_start_matches('#');
            if let Some(target) = root.pointer(pointer) {
                stack.push(target);
            }
        }
        for combinator in ["anyOf", "oneOf", "allOf"] {
            if let Some(list) = n.get(combinator).and_then(Value::as_array) {
                stack.extend(list.iter());
            }
        }
        out.push(n);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::config_file::Config;

    fn source(text: &str) -> SourceText {
        SourceText::from_text(Path::new("test.json"), text)
    }

    #[test]
    fn syntax_errors_have_line_and_column() {
        let src = source("{\n  \"a\": 1,\n  \"b\": \n}");
        let err = src.parse_json().unwrap_err();
        assert_eq!(err.line_column.map(|(l, _)| l), Some(4));
        assert!(matches!(err.problem, Problem::Syntax(_)));
    }

    #[test]
    fn type_errors_have_path_and_position() {
        let text = "{\"ports\": [{\"path\": \"/dev/x\",\n \"baud_rate\": \"fast\"}]}";
        let src = source(text);
        let raw = src.parse_json().unwrap();
        let err = deserialize_at::<Config>(&src, &raw, &JsonPath::root())
            .err()
            .unwrap();
        assert_eq!(err.path.to_string(), "ports[0].baud_rate");
        assert_eq!(err.line_column, Some((2, 2)));
    }

    #[test]
    fn unknown_keys_list_the_valid_ones() {
        let src = source("{\"mqtt\": {\"hots\": \"x\"}}");
        let raw = src.parse_json().unwrap();
        let err = deserialize_at::<Config>(&src, &raw, &JsonPath::root())
            .err()
            .unwrap();
        match &err.problem {
            Problem::UnknownKey { key, valid } => {
                assert_eq!(key, "hots");
                assert!(valid.contains(&"host".to_string()));
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(err.path.to_string(), "mqtt.hots");
    }

    #[test]
    fn schema_keys_follow_refs_and_arrays() {
        let schema = serde_json::to_value(schemars::schema_for!(Config)).unwrap();
        let keys = schema_keys_at(&schema, &JsonPath::parse("ports[0].devices[1]"));
        assert!(
            keys.contains(&"slave_id".to_string()) && keys.contains(&"device_type".to_string()),
            "{keys:?}"
        );
        let keys = schema_keys_at(&schema, &JsonPath::parse("mqtt"));
        assert!(keys.contains(&"host".to_string()));
    }
}
