//! Register values for `read`/`write`: formats by name, decoding words into text and back (the
//! daemon's codec, so a value reads the same here as on MQTT), and the Wiren Board standard text
//! registers (model, firmware, signature).

use crate::config::format::{RegisterFormat, WordOrder};
use crate::config::values::parse_int_text;
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

/// The words that write `text` as one value of `format`; a string takes the registers its text
/// needs (`string`: one character per register, `string8`: two).
///
/// Stricter than the daemon's codec, which takes an MQTT `/on` payload as wb-mqtt-serial does
/// (a fraction rounded, a negative number on an unsigned format wrapped): on site a value typed
/// by hand that is not what the register can hold is a mistake to point out, not to guess at.
pub fn encode_value(
    format: RegisterFormat,
    word_order: WordOrder,
    text: &str,
) -> Result<Vec<u16>, String> {
    let count = if format.is_string() {
        let characters = u32::try_from(text.len()).unwrap_or(u32::MAX);
        u16::try_from(format.string_registers(characters)).unwrap_or(u16::MAX)
    } else {
        1
    };
    if format.is_integer() {
        check_integer(format, text.trim())?;
    }
    // A format narrower than its registers (`u8`, `u24` …) is written over zeros: the tool
    // writes whole registers, as typed.
    let codec = codec(format, word_order, count);
    let zeros = vec![0u16; codec.word_count as usize];
    codec
        .encode(text, Some(&zeros))
        .map_err(|err| err.to_string())
}

/// A string `text` written over a field of `registers` registers, padded with zeros as
/// wb-mqtt-serial writes a string channel, so that no character of a longer old text stays
/// behind it.
pub fn encode_string_field(
    format: RegisterFormat,
    text: &str,
    registers: u16,
) -> Result<Vec<u16>, String> {
    codec(format, WordOrder::BigEndian, registers.max(1))
        .encode(text, None)
        .map_err(|err| err.to_string())
}

/// Refuses what an integer format cannot hold exactly: a fraction, and on an unsigned format a
/// negative number or one above its range. Signed and BCD ranges are the codec's.
fn check_integer(format: RegisterFormat, text: &str) -> Result<(), String> {
    let name = format.name();
    let value = match parse_int_text(text) {
        Some(value) => value,
        None => match text.parse::<f64>() {
            // A whole number written as a fraction (`56.0`, `1e3`) is that number.
            Ok(number) if !number.is_finite() => {
                return Err(format!("{text} is not a number a register can hold"))
            }
            Ok(number) if number.fract() == 0.0 => number as i128,
            Ok(_) => {
                return Err(format!(
                    "{text} is not a whole number: a {name} register holds whole numbers, and \
                     nothing is rounded. For a register that holds fractions give --format \
                     float (or --format double for 64 bits)"
                ))
            }
            // Not a number at all: the codec says so.
            Err(_) => return Ok(()),
        },
    };
    if format.is_signed() || format.is_bcd() {
        return Ok(());
    }
    let bits = format.value_bits();
    let max = (1i128 << bits) - 1;
    if value < 0 {
        return Err(format!(
            "{text} is negative: a {name} register holds 0 … {max}. For a signed register give \
             --format s{bits}"
        ));
    }
    if value > max {
        return Err(format!(
            "{text} is out of range for {name}: allowed 0 … {max}"
        ));
    }
    Ok(())
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
            encode_value(RegisterFormat::S16, be, "-2"),
            Ok(vec![0xFFFE])
        );
        assert_eq!(
            encode_value(RegisterFormat::U32, be, "65538"),
            Ok(vec![1, 2])
        );
        assert_eq!(
            encode_value(RegisterFormat::U16, be, "0xFFFF"),
            Ok(vec![0xFFFF])
        );
        assert_eq!(encode_value(RegisterFormat::U16, be, "56.0"), Ok(vec![56]));
        assert_eq!(
            encode_value(RegisterFormat::Float, be, "1.5"),
            Ok(vec![0x3FC0, 0])
        );
        assert!(encode_value(RegisterFormat::U16, be, "abc")
            .unwrap_err()
            .contains("not a number"));
    }

    #[test]
    fn integer_formats_refuse_fractions_instead_of_rounding() {
        let be = WordOrder::BigEndian;
        for (format, text) in [
            (RegisterFormat::U16, "55.7"),
            (RegisterFormat::S16, "2.5"),
            (RegisterFormat::S16, "-0.5"),
            (RegisterFormat::U32, "1e-3"),
            (RegisterFormat::Bcd16, "12.5"),
        ] {
            let refused = encode_value(format, be, text).unwrap_err();
            assert!(
                refused.contains(&format!("{text} is not a whole number"))
                    && refused.contains("--format float"),
                "{format:?} {text}: {refused}"
            );
        }
    }

    #[test]
    fn unsigned_formats_take_their_own_range_only() {
        let be = WordOrder::BigEndian;
        let refused = encode_value(RegisterFormat::U16, be, "-5").unwrap_err();
        assert!(
            refused.contains("-5 is negative") && refused.contains("--format s16"),
            "{refused}"
        );
        assert!(encode_value(RegisterFormat::U16, be, "-5.0")
            .unwrap_err()
            .contains("--format s16"));
        assert!(encode_value(RegisterFormat::U32, be, "-0x1")
            .unwrap_err()
            .contains("--format s32"));
        assert_eq!(
            encode_value(RegisterFormat::U16, be, "70000").unwrap_err(),
            "70000 is out of range for u16: allowed 0 … 65535"
        );
        assert!(encode_value(RegisterFormat::U8, be, "256")
            .unwrap_err()
            .contains("allowed 0 … 255"));
        assert_eq!(
            encode_value(RegisterFormat::U64, be, "18446744073709551615"),
            Ok(vec![0xFFFF; 4])
        );
        // Signed formats keep their signed range.
        assert_eq!(
            encode_value(RegisterFormat::S16, be, "-32768"),
            Ok(vec![0x8000])
        );
        assert!(encode_value(RegisterFormat::S16, be, "32768")
            .unwrap_err()
            .contains("allowed -32768 … 32767"));
    }

    #[test]
    fn strings_take_the_registers_their_text_needs() {
        let be = WordOrder::BigEndian;
        assert_eq!(
            encode_value(RegisterFormat::String, be, "hello"),
            Ok("hello".bytes().map(u16::from).collect())
        );
        assert_eq!(
            encode_value(RegisterFormat::String8, be, "hello"),
            Ok(vec![0x6865, 0x6C6C, 0x6F00])
        );
        assert_eq!(encode_value(RegisterFormat::String, be, ""), Ok(vec![0]));
        for text in ["inf", "-inf", "nan", "NaN"] {
            let refused = encode_value(RegisterFormat::U16, be, text).unwrap_err();
            assert!(
                refused.contains("is not a number a register can hold")
                    && !refused.contains("float"),
                "{refused}"
            );
        }
        assert_eq!(
            encode_string_field(RegisterFormat::String, "hi", 4),
            Ok(vec![u16::from(b'h'), u16::from(b'i'), 0, 0])
        );
        assert_eq!(
            encode_string_field(RegisterFormat::String8, "abc", 3),
            Ok(vec![0x6162, 0x6300, 0])
        );
        assert!(encode_string_field(RegisterFormat::String, "hello", 4)
            .unwrap_err()
            .contains("longer than the 4 characters"));
    }

    #[test]
    fn standard_text_registers() {
        let words: Vec<u16> = "WBMR6C".bytes().map(u16::from).chain([0, 0, 7]).collect();
        assert_eq!(standard_text(&words), Some("WBMR6C".into()));
        assert_eq!(standard_text(&[0, 0]), None);
        assert_eq!(standard_text(&[0xFFFF, 0xFFFF]), None);
    }
}
