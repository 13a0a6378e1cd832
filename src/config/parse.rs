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
    Problem::Invalid(message.to_string())
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
