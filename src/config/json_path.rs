//! Where in a JSON document something is: a path (`ports[0].devices[2].slave_id`) and, found by
//! scanning the source text, its line and column.
//!
//! Errors are found on parsed values (serde, merge, cross-checks), which no longer know their
//! position; the path is what they keep, and [`locate`] turns it back into `line:column`.

use std::fmt;

/// One step of a [`JsonPath`].
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum PathSegment {
    Key(String),
    Index(usize),
}

/// A path from the document root, printed like `ports[0].devices[2].slave_id`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Hash)]
pub struct JsonPath(pub Vec<PathSegment>);

impl JsonPath {
    pub fn root() -> Self {
        Self::default()
    }

    pub fn key(&self, key: impl Into<String>) -> Self {
        let mut next = self.clone();
        next.0.push(PathSegment::Key(key.into()));
        next
    }

    pub fn index(&self, index: usize) -> Self {
        let mut next = self.clone();
        next.0.push(PathSegment::Index(index));
        next
    }

    pub fn join(&self, tail: &JsonPath) -> Self {
        let mut next = self.clone();
        next.0.extend(tail.0.iter().cloned());
        next
    }

    pub fn is_root(&self) -> bool {
        self.0.is_empty()
    }

    pub fn segments(&self) -> &[PathSegment] {
        &self.0
    }

    /// The value at this path in `document`, if there is one.
    pub fn find<'a>(&self, document: &'a serde_json::Value) -> Option<&'a serde_json::Value> {
        self.0
            .iter()
            .try_fold(document, |value, segment| match segment {
                PathSegment::Key(key) => value.get(key),
                PathSegment::Index(index) => value.get(index),
            })
    }

    /// Parses the path notation serde_path_to_error prints (`a.b[3].c`, `?` for unknown parts).
    pub fn parse(text: &str) -> Self {
        let mut segments = Vec::new();
        for part in text.split('.') {
            if part.is_empty() || part == "?" {
                continue;
            }
            let (key, mut rest) = match part.find('[') {
                Some(pos) => (&part[..pos], &part[pos..]),
                None => (part, ""),
            };
            if !key.is_empty() {
                segments.push(PathSegment::Key(key.to_string()));
            }
            while let Some(stripped) = rest.strip_prefix('[') {
                let end = stripped.find(']').unwrap_or(stripped.len());
                if let Ok(index) = stripped[..end].parse() {
                    segments.push(PathSegment::Index(index));
                }
                rest = stripped.get(end + 1..).unwrap_or("");
            }
        }
        JsonPath(segments)
    }
}

impl fmt::Display for JsonPath {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.0.is_empty() {
            return f.write_str("(top level)");
        }
        for (i, segment) in self.0.iter().enumerate() {
            match segment {
                PathSegment::Key(key) if i == 0 => write!(f, "{key}")?,
                PathSegment::Key(key) => write!(f, ".{key}")?,
                PathSegment::Index(index) => write!(f, "[{index}]")?,
            }
        }
        Ok(())
    }
}

/// Byte offset in `text` (JSON, comments already blanked) of what `path` names: the key for an
/// object member, the element for an array item. When the path goes further than the document
/// (a key that is missing), the offset of the deepest part that exists is returned.
pub fn locate(text: &str, path: &JsonPath) -> Option<usize> {
    let mut scanner = Scanner {
        bytes: text.as_bytes(),
        pos: 0,
    };
    scanner.skip_ws();
    let mut found = scanner.pos;
    for segment in &path.0 {
        scanner.skip_ws();
        let here = match segment {
            PathSegment::Key(key) => scanner.enter_member(key),
            PathSegment::Index(index) => scanner.enter_element(*index),
        };
        match here {
            Some(offset) => found = offset,
            None => break,
        }
    }
    Some(found)
}

struct Scanner<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl Scanner<'_> {
    fn peek(&self) -> Option<u8> {
        self.bytes.get(self.pos).copied()
    }

    fn skip_ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.pos += 1;
        }
    }

    /// At `{`: moves to the value of member `key`; returns the offset of the key.
    fn enter_member(&mut self, key: &str) -> Option<usize> {
        if self.peek() != Some(b'{') {
            return None;
        }
        self.pos += 1;
        loop {
            self.skip_ws();
            if self.peek() != Some(b'"') {
                return None;
            }
            let key_start = self.pos;
            let name = self.read_string()?;
            self.skip_ws();
            if self.peek() != Some(b':') {
                return None;
            }
            self.pos += 1;
            self.skip_ws();
            if name == key {
                return Some(key_start);
            }
            self.skip_value()?;
            self.skip_ws();
            if self.peek() != Some(b',') {
                return None;
            }
            self.pos += 1;
        }
    }

    /// At `[`: moves to element `index`; returns its offset.
    fn enter_element(&mut self, index: usize) -> Option<usize> {
        if self.peek() != Some(b'[') {
            return None;
        }
        self.pos += 1;
        for _ in 0..index {
            self.skip_ws();
            self.skip_value()?;
            self.skip_ws();
            if self.peek() != Some(b',') {
                return None;
            }
            self.pos += 1;
        }
        self.skip_ws();
        if matches!(self.peek(), None | Some(b']')) {
            return None;
        }
        Some(self.pos)
    }

    fn read_string(&mut self) -> Option<String> {
        let start = self.pos;
        self.skip_string()?;
        let raw = std::str::from_utf8(self.bytes.get(start..self.pos)?).ok()?;
        serde_json::from_str(raw).ok()
    }

    fn skip_string(&mut self) -> Option<()> {
        self.pos += 1;
        while let Some(byte) = self.peek() {
            self.pos += 1;
            match byte {
                b'\\' => self.pos += 1,
                b'"' => return Some(()),
                _ => {}
            }
        }
        None
    }

    fn skip_value(&mut self) -> Option<()> {
        match self.peek()? {
            b'"' => self.skip_string(),
            b'{' | b'[' => {
                let mut depth = 0usize;
                while let Some(byte) = self.peek() {
                    match byte {
                        b'"' => {
                            self.skip_string()?;
                            continue;
                        }
                        b'{' | b'[' => depth += 1,
                        b'}' | b']' => {
                            depth -= 1;
                            if depth == 0 {
                                self.pos += 1;
                                return Some(());
                            }
                        }
                        _ => {}
                    }
                    self.pos += 1;
                }
                None
            }
            _ => {
                while let Some(byte) = self.peek() {
                    if matches!(byte, b',' | b'}' | b']' | b' ' | b'\t' | b'\n' | b'\r') {
                        break;
                    }
                    self.pos += 1;
                }
                Some(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::jsonc::line_column;

    const DOC: &str = r#"{
  "mqtt": {"host": "a"},
  "ports": [
    {"path": "/dev/x", "devices": [
      {"slave_id": 1},
      {"name": "b\"]}", "slave_id": "0x10"}
    ]}
  ]
}"#;

    fn at(path: &str) -> (usize, usize) {
        let offset = locate(DOC, &JsonPath::parse(path)).unwrap();
        line_column(DOC, offset)
    }

    #[test]
    fn finds_keys_and_elements() {
        assert_eq!(at("mqtt.host"), (2, 12));
        assert_eq!(at("ports[0].devices[1].slave_id"), (6, 25));
        assert_eq!(at("ports[0].devices[0]"), (5, 7));
    }

    #[test]
    fn missing_parts_fall_back_to_the_deepest_existing_one() {
        assert_eq!(at("ports[0].devices[1].nothing"), at("ports[0].devices[1]"));
        assert_eq!(at("ports[5]"), at("ports"));
    }

    #[test]
    fn path_round_trips_through_text() {
        let path = JsonPath::root()
            .key("ports")
            .index(0)
            .key("devices")
            .index(2)
            .key("slave_id");
        assert_eq!(path.to_string(), "ports[0].devices[2].slave_id");
        assert_eq!(JsonPath::parse(&path.to_string()), path);
        assert_eq!(JsonPath::parse("a[1][2].b").to_string(), "a[1][2].b");
    }
}
