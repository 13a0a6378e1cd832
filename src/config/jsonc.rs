//! JSON with comments, as wb-mqtt-serial accepts it (its sample config and some templates use `//`).
//!
//! Comments are replaced by spaces rather than removed, so byte offsets, lines and columns of the
//! stripped text are those of the file the integrator edits: every error can point into the
//! original file.

/// Replaces `// …` and `/* … */` comments outside strings with spaces (newlines are kept), and
/// a trailing comma before `}` or `]` with a space: wb-mqtt-serial reads its files with jsoncpp,
/// whose default reader accepts both, and a released WB-MWAC-v2 template has trailing commas.
///
/// An unterminated block comment is blanked to the end; the JSON parser then reports what is
/// missing at the end of the file, which is where the integrator has to look anyway.
pub fn strip_comments(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    let mut in_string = false;
    while i < bytes.len() {
        let byte = bytes[i];
        if in_string {
            out.push(byte);
            if byte == b'\\' {
                if let Some(&next) = bytes.get(i + 1) {
                    out.push(next);
                    i += 1;
                }
            } else if byte == b'"' {
                in_string = false;
            }
            i += 1;
            continue;
        }
        match (byte, bytes.get(i + 1)) {
            (b'"', _) => {
                in_string = true;
                out.push(byte);
                i += 1;
            }
            (b'/', Some(b'/')) => {
                while i < bytes.len() && bytes[i] != b'\n' {
                    out.push(blank(bytes[i]));
                    i += 1;
                }
            }
            (b'/', Some(b'*')) => {
                out.extend_from_slice(b"  ");
                i += 2;
                while i < bytes.len() {
                    if bytes[i] == b'*' && bytes.get(i + 1) == Some(&b'/') {
                        out.extend_from_slice(b"  ");
                        i += 2;
                        break;
                    }
                    out.push(blank(bytes[i]));
                    i += 1;
                }
            }
            _ => {
                out.push(byte);
                i += 1;
            }
        }
    }
    blank_trailing_commas(&mut out);
    // Only ASCII bytes of comments were replaced by ASCII spaces, and multi-byte characters inside
    // comments are blanked byte by byte, so the result is valid UTF-8.
    String::from_utf8(out).unwrap_or_default()
}

/// Blanks every `,` outside strings that only whitespace separates from a closing `}` or `]`
/// (comments are already blanked).
fn blank_trailing_commas(bytes: &mut [u8]) {
    let mut in_string = false;
    let mut i = 0;
    while i < bytes.len() {
        let byte = bytes[i];
        if in_string {
            if byte == b'\\' {
                i += 1;
            } else if byte == b'"' {
                in_string = false;
            }
        } else if byte == b'"' {
            in_string = true;
        } else if byte == b',' {
            let next = bytes[i + 1..]
                .iter()
                .find(|b| !b.is_ascii_whitespace())
                .copied();
            if matches!(next, Some(b'}' | b']')) {
                bytes[i] = b' ';
            }
        }
        i += 1;
    }
}

/// Keeps line breaks (so line numbers stay right) and blanks everything else of a comment.
fn blank(byte: u8) -> u8 {
    match byte {
        b'\n' | b'\r' => byte,
        _ => b' ',
    }
}

/// 1-based line and column (in characters) of a byte offset, for messages like `file:12:5`.
pub fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let before = text.get(..offset).unwrap_or(text);
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map(|p| p + 1).unwrap_or(0);
    let column = before
        .get(line_start..)
        .map(|s| s.chars().count())
        .unwrap_or(0)
        + 1;
    (line, column)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_comments_are_blanked_and_positions_kept() {
        let text = "{\n  // a comment\n  \"a\": 1 // trailing\n}";
        let stripped = strip_comments(text);
        assert_eq!(stripped.len(), text.len());
        let value: serde_json::Value = serde_json::from_str(&stripped).unwrap();
        assert_eq!(value["a"], 1);
        assert_eq!(stripped.find("\"a\""), text.find("\"a\""));
    }

    #[test]
    fn slashes_inside_strings_are_kept() {
        let text = r#"{"url": "http://x/y", "esc": "a\"//b", "b": "/* no */"}"#;
        let stripped = strip_comments(text);
        assert_eq!(stripped, text);
    }

    #[test]
    fn block_comments_keep_newlines() {
        let text = "{/* one\ntwo */\"a\": 2}";
        let stripped = strip_comments(text);
        assert_eq!(stripped.matches('\n').count(), 1);
        let value: serde_json::Value = serde_json::from_str(&stripped).unwrap();
        assert_eq!(value["a"], 2);
    }

    #[test]
    fn unterminated_block_comment_is_blanked_to_the_end() {
        let stripped = strip_comments("{\"a\": 1 /* open");
        assert!(serde_json::from_str::<serde_json::Value>(&stripped).is_err());
        assert!(!stripped.contains("open"));
    }

    #[test]
    fn non_ascii_in_comments_and_strings() {
        let text = "{\"t\": \"Вход\" // комментарий\n}";
        let stripped = strip_comments(text);
        let value: serde_json::Value = serde_json::from_str(&stripped).unwrap();
        assert_eq!(value["t"], "Вход");
    }

    #[test]
    fn trailing_commas_are_blanked_outside_strings() {
        let text = "{\"a\": [1, 2,\n], \"b\": \"x,]\", /* c */ \"c\": {\"d\": 1, // e\n},}";
        let stripped = strip_comments(text);
        assert_eq!(stripped.len(), text.len());
        let value: serde_json::Value = serde_json::from_str(&stripped).unwrap();
        assert_eq!(value["a"], serde_json::json!([1, 2]));
        assert_eq!(value["b"], "x,]");
        assert_eq!(value["c"]["d"], 1);
        assert!(serde_json::from_str::<serde_json::Value>(&strip_comments("[1,,]")).is_err());
    }

    #[test]
    fn line_column_counts_characters() {
        let text = "ab\nцd\"x";
        assert_eq!(line_column(text, 0), (1, 1));
        assert_eq!(line_column(text, 3), (2, 1));
        let quote = text.find('"').unwrap();
        assert_eq!(line_column(text, quote), (2, 3));
        assert_eq!(line_column(text, 10_000).0, 2);
    }
}
