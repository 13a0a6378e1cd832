//! Register values for `read`/`write`: formats by name, decoding words into text and back (the
//! daemon's codec, so a value reads the same here as on MQTT), and the Wiren Board standard text
//! registers (model, firmware, signature).

use crate::config::format::{RegisterFormat, WordOrder};
use crate::device::codec::{Reading, ValueCodec};

/// A format by its template name (`u16`, `s32`, `float`, ...).
pub fn parse_format(text: &str) -> Result<RegisterFormat, String> {
    RegisterFormat::ALL
        .iter()
        .copied()
        .find(|f| f.name().eq_ignore_ascii_case(text))
        .ok_or_else(|| {
            let names: Vec<&str> = RegisterFormat::ALL.iter().map(|f| f.name()).collect();
            format!("format {text:?}: use one of {}", names.join(", "))
        })
}

/// The codec for `format` over `count` registers (strings take them all).
pub fn codec(format: RegisterFormat, word_order: WordOrder, count: u16) -> ValueCodec {
    let mut codec = ValueCodec::plain(format);
    codec.word_order = word_order;
    if format.is_string() {
        codec.word_count = u32::from(count.max(1));
    }
    codec
}

/// Registers one value of `format` takes (strings: all `count`).
pub fn value_width(format: RegisterFormat, count: u16) -> u16 {
    if format.is_string() {
        count.max(1)
    } else {
        u16::try_from(format.registers().max(1)).unwrap_or(1)
    }
}

/// The words as values of `format`: one text per value; a short tail is reported, not dropped
/// silently.
pub fn decode_words(
    format: RegisterFormat,
    word_order: WordOrder,
    words: &[u16],
) -> Result<Vec<String>, String> {
    let count = u16::try_from(words.len()).unwrap_or(u16::MAX);
    let width = usize::from(value_width(format, count));
    if words.len() % width != 0 {
        return Err(format!(
            "{} register(s) do not make whole {} values ({width} register(s) each): use --count {}",
            words.len(),
            format.name(),
            words.len().div_ceil(width) * width
        ));
    }
    let codec = codec(format, word_order, count);
    words
        .chunks(width)
        .map(|chunk| match codec.decode(chunk) {
            Ok(Reading::Value(text)) => Ok(text),
            Ok(other) => Ok(format!("{other:?}")),
            Err(err) => Err(err.to_string()),
        })
        .collect()
}

/// The words that write `text` as one value of `format` (`count` registers for strings).
pub fn encode_value(
    format: RegisterFormat,
    word_order: WordOrder,
    text: &str,
    count: u16,
) -> Result<Vec<u16>, String> {
    codec(format, word_order, count)
        .encode(text, None)
        .map_err(|err| err.to_string())
}

/// A Wiren Board text register block (model at 200, firmware at 250, signature at 290): one
/// character per register, ended by 0. None when empty or not text.
pub fn standard_text(words: &[u16]) -> Option<String> {
    let text: String = words
        .iter()
        .take_while(|w| **w != 0)
        .map(|w| {
            u8::try_from(*w)
                .ok()
                .filter(|b| b.is_ascii_graphic() || *b == b' ')
        })
        .collect::<Option<Vec<u8>>>()?
        .into_iter()
        .map(char::from)
        .collect();
    let text = text.trim().to_owned();
    (!text.is_empty()).then_some(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_by_name() {
        assert_eq!(parse_format("S32"), Ok(RegisterFormat::S32));
        assert_eq!(parse_format("float"), Ok(RegisterFormat::Float));
        assert!(parse_format("int").unwrap_err().contains("u16"));
    }

    #[test]
    fn words_decode_per_value_and_orders_apply() {
        let be = WordOrder::BigEndian;
        assert_eq!(
            decode_words(RegisterFormat::S16, be, &[0xFFFF, 5]).unwrap(),
            ["-1", "5"]
        );
        assert_eq!(
            decode_words(RegisterFormat::U32, be, &[1, 2]).unwrap(),
            ["65538"]
        );
        assert_eq!(
            decode_words(RegisterFormat::U32, WordOrder::LittleEndian, &[2, 1]).unwrap(),
            ["65538"]
        );
        assert_eq!(
            decode_words(RegisterFormat::Float, be, &[0x3FC0, 0]).unwrap(),
            ["1.5"]
        );
        assert!(decode_words(RegisterFormat::U32, be, &[1, 2, 3])
            .unwrap_err()
            .contains("--count 4"));
    }

    #[test]
    fn values_encode_to_words() {
        let be = WordOrder::BigEndian;
        assert_eq!(
            encode_value(RegisterFormat::S16, be, "-2", 1),
            Ok(vec![0xFFFE])
        );
        assert_eq!(
            encode_value(RegisterFormat::U32, be, "65538", 2),
            Ok(vec![1, 2])
        );
        assert!(encode_value(RegisterFormat::U16, be, "70000", 1).is_err());
        assert!(encode_value(RegisterFormat::U16, be, "abc", 1).is_err());
    }

    #[test]
    fn standard_text_registers() {
        let words: Vec<u16> = "WBMR6C".bytes().map(u16::from).chain([0, 0, 7]).collect();
        assert_eq!(standard_text(&words), Some("WBMR6C".into()));
        assert_eq!(standard_text(&[0, 0]), None);
        assert_eq!(standard_text(&[0xFFFF, 0xFFFF]), None);
    }
}
