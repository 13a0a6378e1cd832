//! Raw register words ↔ the value string published on MQTT, for one register value of a channel.
//!
//! Reading follows wb-mqtt-serial: words are put in order (`word_order`, then `byte_order`
//! inside each word), joined most significant first, the bit field is cut out
//! (`>> shift & mask`), `error_value`/`unsupported_value` are compared on that raw field, and
//! only then is it interpreted (sign, IEEE, BCD, text) and scaled. `on_value`/`off_value` are
//! compared with the text that gives, as wb-mqtt-serial's `TDeviceChannel::GetTextValue` does.

use super::number_text::format_g;
use crate::config::format::{ByteOrder, RegisterFormat, WordOrder};
use crate::config::values::parse_int_text;

/// Everything needed to turn the words of one register value into text and back.
#[derive(Debug, Clone, PartialEq)]
pub struct ValueCodec {
    pub format: RegisterFormat,
    pub word_order: WordOrder,
    pub byte_order: ByteOrder,
    /// Bit offset of the field inside the joined words (0 for whole registers).
    pub bit_shift: u32,
    /// Width of the field in bits (the format's width unless the address gives one).
    pub bit_width: u32,
    /// Words the value spans: 16-bit registers, or single bits for coils and discrete inputs.
    pub word_count: u32,
    /// Coils and discrete inputs: every word is one bit (0 or 1).
    pub is_bit: bool,
    pub scale: f64,
    pub offset: f64,
    /// Rounding step of the published value; 0 = no rounding. Published as meta `precision`.
    pub round_to: f64,
    /// Raw field values that mean "read error" (`r`) and "register not supported".
    pub error_value: Option<u64>,
    pub unsupported_value: Option<u64>,
    /// `on_value` / `off_value`: integers in the channel's units (after scale and offset), as
    /// wb-mqtt-serial takes them. A read whose text (formatted, scaled) is exactly this number
    /// is published as "1" / "0"; a "1" / "0" written is written as this number, through scale
    /// and offset and cut to the field's width (`src/serial_port_driver.cpp`).
    pub on_value: Option<i128>,
    pub off_value: Option<i128>,
}

/// What a read produced.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reading {
    /// The text to publish.
    Value(String),
    /// The device reported `error_value`: set the read error flag, keep the last value.
    DeviceError,
    /// The device reported `unsupported_value`: set `r` and stop polling this register.
    Unsupported,
}

/// What [`ValueCodec::decode_into`] produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decoded {
    /// The text to publish, appended to the caller's buffer.
    Text,
    /// As [`Reading::DeviceError`].
    DeviceError,
    /// As [`Reading::Unsupported`].
    Unsupported,
}

/// Why words could not be decoded or a text could not be encoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    #[error("expected {expected} register words, got {got}")]
    WordCount { expected: usize, got: usize },
    #[error("raw value {0:#x} is not valid BCD (a nibble is above 9)")]
    InvalidBcd(u64),
    #[error("`{0}` is not a number")]
    NotANumber(String),
    /// A control's own `min`/`max` (either may be absent): `at most 100`, `at least 5`,
    /// `allowed 5 … 100`.
    #[error("{value} is outside this control's limits: {limits}")]
    OutsideLimits { value: String, limits: String },
    #[error("{value} is out of range for {format}: allowed {min} … {max}")]
    OutOfRange {
        value: String,
        format: &'static str,
        min: String,
        max: String,
    },
    #[error("`{text}` is longer than the {capacity} characters the register holds")]
    StringTooLong { text: String, capacity: u32 },
    #[error("the register has not been read yet: this value fills only some of its bits, and the others are written as the device holds them (send it again once the control shows a value)")]
    NeedsCurrentWords,
    #[error("`{0}` does not fit a char8 register: it holds one character from U+0000 to U+00FF")]
    NotOneByteCharacter(String),
}

impl ValueCodec {
    /// A plain codec for `format`, whole registers, no scaling: a starting point for tests and
    /// for setup items.
    pub fn plain(format: RegisterFormat) -> Self {
        Self {
            format,
            word_order: WordOrder::BigEndian,
            byte_order: ByteOrder::BigEndian,
            bit_shift: 0,
            bit_width: format.value_bits(),
            word_count: format.registers().max(1),
            is_bit: false,
            scale: 1.0,
            offset: 0.0,
            round_to: 0.0,
            error_value: None,
            unsupported_value: None,
            on_value: None,
            off_value: None,
        }
    }

    /// A codec for one coil or discrete input.
    pub fn bit() -> Self {
        Self {
            is_bit: true,
            bit_width: 1,
            word_count: 1,
            ..Self::plain(RegisterFormat::U8)
        }
    }

    /// True when the value does not fill its registers, so a write must merge it into their
    /// current contents (read-modify-write): a bit field, and a format narrower than the
    /// registers it takes (`u8`, `s8`, `char8`, `bcd8` in one register, `u24`, `s24`, `bcd24`
    /// in two). wb-mqtt-serial writes them so, over its register cache
    /// (`ComposeRawSingleWriteRequestData`, `ComposeRawMultipleWriteRequestData`: the value's
    /// `GetDataWidth()` bits are replaced, the other bits kept).
    pub fn is_partial(&self) -> bool {
        !self.is_bit
            && !self.format.is_string()
            && (self.bit_shift > 0 || self.bit_width < self.word_count.saturating_mul(16))
    }

    fn mask(&self) -> u128 {
        if self.bit_width >= 128 {
            u128::MAX
        } else {
            (1u128 << self.bit_width) - 1
        }
    }

    fn check_len(&self, words: &[u16]) -> Result<(), CodecError> {
        if words.len() != self.word_count as usize {
            return Err(CodecError::WordCount {
                expected: self.word_count as usize,
                got: words.len(),
            });
        }
        Ok(())
    }

    /// The raw field (before sign, IEEE or BCD interpretation), as compared with `error_value`.
    pub fn raw_field(&self, words: &[u16]) -> Result<u64, CodecError> {
        self.check_len(words)?;
        if self.is_bit {
            return Ok(words.first().map(|w| u64::from(*w != 0)).unwrap_or(0));
        }
        let joined = self
            .ordered_words(words)
            .fold(0u128, |acc, w| (acc << 16) | u128::from(w));
        Ok(((joined >> self.bit_shift.min(127)) & self.mask()) as u64)
    }

    /// Words most significant first, bytes swapped where `byte_order` says so. The same order
    /// taken twice is where it started: given a value's words most significant first, it gives
    /// the registers that hold the value (what an event's payload, the value itself, becomes).
    pub fn ordered_words<'a>(&self, words: &'a [u16]) -> impl Iterator<Item = u16> + 'a {
        let swap = self.byte_order == ByteOrder::LittleEndian;
        let reverse = self.word_order == WordOrder::LittleEndian;
        let count = words.len();
        (0..count).map(move |i| {
            let index = if reverse { count - 1 - i } else { i };
            let word = words.get(index).copied().unwrap_or(0);
            if swap {
                word.swap_bytes()
            } else {
                word
            }
        })
    }

    /// Decodes the words of one register value.
    pub fn decode(&self, words: &[u16]) -> Result<Reading, CodecError> {
        let mut text = String::new();
        Ok(match self.decode_into(words, &mut text)? {
            Decoded::Text => Reading::Value(text),
            Decoded::DeviceError => Reading::DeviceError,
            Decoded::Unsupported => Reading::Unsupported,
        })
    }

    /// [`ValueCodec::decode`] appending the text to `text` (left as it was unless the result
    /// is [`Decoded::Text`]): the device model decodes every read value into one buffer.
    pub fn decode_into(&self, words: &[u16], text: &mut String) -> Result<Decoded, CodecError> {
        let start = text.len();
        if self.format.is_string() && !self.is_bit {
            self.check_len(words)?;
            text.push_str(&self.decode_string(words));
        } else {
            let field = self.raw_field(words)?;
            if self.unsupported_value == Some(field) {
                return Ok(Decoded::Unsupported);
            }
            if self.error_value == Some(field) {
                return Ok(Decoded::DeviceError);
            }
            self.field_text(field, text)?;
        }
        // wb-mqtt-serial compares the text it would publish with the decimal text of
        // `on_value` / `off_value`: with a scale 0.1, raw 100 is "10" and matches on_value 10;
        // on `s16`, 0xFFFF is "-1" and never matches on_value 65535 (it is published as -1).
        for (value, switch_text) in [(self.on_value, '1'), (self.off_value, '0')] {
            if value.is_some_and(|value| is_decimal_text_of(&text[start..], value)) {
                text.truncate(start);
                text.push(switch_text);
                break;
            }
        }
        Ok(Decoded::Text)
    }

    fn has_transform(&self) -> bool {
        self.scale != 1.0 || self.offset != 0.0 || self.round_to != 0.0
    }

    fn field_text(&self, field: u64, text: &mut String) -> Result<(), CodecError> {
        let format = self.format;
        if self.is_bit {
            if self.has_transform() {
                text.push_str(&self.scaled_text(field as f64));
            } else {
                push_display(text, field);
            }
            return Ok(());
        }
        match format {
            // A float32 prints with 7 significant digits, scaled or not, as wb-mqtt-serial's
            // `ToScaledTextValue<float>` (`src/register.cpp`) prints it: 15 would show the
            // float's error (11.0000002384186 for 1.1 × 10).
            RegisterFormat::Float => {
                let value = f64::from(f32::from_bits(field as u32));
                text.push_str(&format_g(self.scaled_value(value), 7));
            }
            RegisterFormat::Double => text.push_str(&self.scaled_text(f64::from_bits(field))),
            RegisterFormat::Char8 => text.push(char::from((field & 0xFF) as u8)),
            _ if format.is_bcd() => {
                let value =
                    decode_bcd(field, format.value_bits()).ok_or(CodecError::InvalidBcd(field))?;
                self.integer_text(i128::from(value), text);
            }
            // The sign comes from the format's width, not the field's: wb-mqtt-serial cuts a
            // field out unsigned (`GetRegisterValueFromReadData` in `src/modbus_common.cpp`:
            // `>> offset & mask`) and `ConvertFromRawValue` (`src/register.cpp`) then takes
            // `Get<int16_t>` of it, so an `s16` field of 4 bits reads 0xF as 15, not -1.
            _ if format.is_signed() => {
                let bits = format.value_bits().clamp(1, 64);
                let shift = 64 - bits;
                let value = ((field << shift) as i64) >> shift;
                self.integer_text(i128::from(value), text);
            }
            // wb-mqtt-serial prints a `u8` as `Get<uint8_t>` of the field (a cast), so a field
            // wider than the format (`"300:0:16"`) shows its low 8 bits; the wider unsigned
            // formats print the whole field (`Get<uint64_t>`).
            RegisterFormat::U8 => self.integer_text(i128::from(field & 0xFF), text),
            _ => self.integer_text(i128::from(field), text),
        }
        Ok(())
    }

    fn integer_text(&self, value: i128, text: &mut String) {
        if self.has_transform() {
            text.push_str(&self.scaled_text(value as f64));
        } else {
            push_display(text, value);
        }
    }

    fn scaled_text(&self, raw: f64) -> String {
        format_g(self.scaled_value(raw), 15)
    }

    /// `raw × scale + offset`, rounded to `round_to` (no-op for 1, 0, 0).
    fn scaled_value(&self, raw: f64) -> f64 {
        self.rounded(raw * self.scale + self.offset)
    }

    /// `value` (in the channel's units) to the nearest multiple of `round_to`, if it has one.
    fn rounded(&self, value: f64) -> f64 {
        if self.round_to > 0.0 {
            (value / self.round_to).round() * self.round_to
        } else {
            value
        }
    }

    /// The characters of a `string` (one per register, its low byte) or `string8` (two per
    /// register, high byte first), up to the first 0x00 or 0xFF. `word_order: little_endian`
    /// takes the registers last first, as wb-mqtt-serial's `GetRegisterValue` reverses the words
    /// of any value before `GetStringRegisterValue` reads them.
    fn decode_string(&self, words: &[u16]) -> String {
        let mut bytes = Vec::new();
        let reverse = self.word_order == WordOrder::LittleEndian;
        let count = words.len();
        for i in 0..count {
            let index = if reverse { count - 1 - i } else { i };
            let word = words.get(index).copied().unwrap_or(0);
            let word = if self.byte_order == ByteOrder::LittleEndian {
                word.swap_bytes()
            } else {
                word
            };
            match self.format {
                RegisterFormat::String8 => bytes.extend_from_slice(&word.to_be_bytes()),
                _ => bytes.push((word & 0xFF) as u8),
            }
        }
        let end = bytes
            .iter()
            .position(|b| *b == 0 || *b == 0xFF)
            .unwrap_or(bytes.len());
        bytes.truncate(end);
        String::from_utf8_lossy(&bytes).into_owned()
    }

    /// Encodes a value text for writing. `current` holds the register's present words; it is
    /// needed (and only used) for bit fields, whose other bits must be kept.
    pub fn encode(&self, text: &str, current: Option<&[u16]>) -> Result<Vec<u16>, CodecError> {
        if self.format.is_string() && !self.is_bit {
            return match self.switch_value(text.trim()) {
                Some(value) => self.encode_string(&value.to_string()),
                None => self.encode_string(text),
            };
        }
        // A character is taken as sent (a space is a character), as wb-mqtt-serial takes it;
        // numbers are trimmed.
        let text = if self.format == RegisterFormat::Char8 {
            text
        } else {
            text.trim()
        };
        let field = self.text_to_field(text)?;
        if self.is_bit {
            return Ok(vec![u16::from(field != 0)]);
        }
        let base: u128 = if self.is_partial() {
            let current = current.ok_or(CodecError::NeedsCurrentWords)?;
            self.check_len(current)?;
            self.ordered_words(current)
                .fold(0u128, |acc, w| (acc << 16) | u128::from(w))
        } else {
            0
        };
        let shift = self.bit_shift.min(127);
        let joined =
            (base & !(self.mask() << shift)) | ((u128::from(field) & self.mask()) << shift);
        Ok(self.register_words(joined))
    }

    /// The bits of its registers the value occupies, as register words in address order (all
    /// ones for a whole-register value): what a write of it defines.
    pub fn field_mask_words(&self) -> Vec<u16> {
        if !self.is_partial() {
            return vec![u16::MAX; self.word_count as usize];
        }
        self.register_words(self.mask() << self.bit_shift.min(127))
    }

    /// `joined` (the value's registers as one number, first register most significant in the
    /// format's order) as register words in address order.
    fn register_words(&self, joined: u128) -> Vec<u16> {
        let count = self.word_count as usize;
        let mut ordered: Vec<u16> = (0..count)
            .map(|i| joined.checked_shr(16 * (count - 1 - i) as u32).unwrap_or(0) as u16)
            .collect();
        if self.byte_order == ByteOrder::LittleEndian {
            ordered.iter_mut().for_each(|w| *w = w.swap_bytes());
        }
        if self.word_order == WordOrder::LittleEndian {
            ordered.reverse();
        }
        ordered
    }

    /// `on_value` for "1" and `off_value` for "0", when the channel has them.
    fn switch_value(&self, text: &str) -> Option<i128> {
        match text {
            "1" => self.on_value,
            "0" => self.off_value,
            _ => None,
        }
    }

    /// The raw field for a value text (inverse of scale/offset, then format range check).
    pub fn text_to_field(&self, text: &str) -> Result<u64, CodecError> {
        match self.switch_value(text) {
            Some(value) => self.switch_field(value),
            None => self.value_field(text),
        }
    }

    /// The field wb-mqtt-serial writes for `on_value` / `off_value`: the number through scale
    /// and offset like any value, then cut to the field's width whatever the format's sign
    /// (`GetRawValue` masks every integer format), so on_value 65535 on `s16` is 0xFFFF.
    fn switch_field(&self, value: i128) -> Result<u64, CodecError> {
        let text = value.to_string();
        if self.is_bit || self.format.is_bcd() || !self.format.is_integer() {
            return self.value_field(&text);
        }
        Ok((self.integer_for(&text)? as u64) & (self.mask() as u64))
    }

    fn value_field(&self, text: &str) -> Result<u64, CodecError> {
        if self.is_bit {
            // A coil or discrete input takes any value that is not 0 after scale and offset
            // as 1, as wb-mqtt-serial converts it like a register value first.
            return Ok(u64::from(self.integer_for(text)? != 0));
        }
        match self.format {
            // The inverse of the read, which shows the byte as the character of that code point
            // (Latin-1): what was read is written back as the same byte. The first byte of the
            // text's UTF-8 (what wb-mqtt-serial writes) would turn a read `é` (0xE9) into 0xC3.
            RegisterFormat::Char8 => match text.chars().next() {
                None => Ok(0),
                Some(c) => u8::try_from(c)
                    .map(u64::from)
                    .map_err(|_| CodecError::NotOneByteCharacter(text.to_string())),
            },
            // A number that is not finite once scale and offset are undone (`nan`, `inf` on a
            // `text` control, 1e300 with a scale 1e-10) is refused rather than written as an
            // IEEE infinity or NaN nobody asked for.
            RegisterFormat::Float => {
                let value = self.unscale(self.rounded(parse_number(text)?));
                if !value.is_finite() || value.abs() > f64::from(f32::MAX) {
                    return Err(self.out_of_range(
                        text,
                        f32::MIN.to_string(),
                        f32::MAX.to_string(),
                    ));
                }
                Ok(u64::from((value as f32).to_bits()))
            }
            RegisterFormat::Double => {
                let value = self.unscale(self.rounded(parse_number(text)?));
                if !value.is_finite() {
                    return Err(self.out_of_range(
                        text,
                        f64::MIN.to_string(),
                        f64::MAX.to_string(),
                    ));
                }
                Ok(value.to_bits())
            }
            format if format.is_bcd() => {
                let digits = format.value_bits() / 4;
                let max = 10i128.pow(digits) - 1;
                let value = self.integer_for(text)?;
                if !(0..=max).contains(&value) {
                    return Err(self.out_of_range(text, "0".to_string(), max.to_string()));
                }
                Ok(encode_bcd(value as u64))
            }
            format => {
                let value = self.integer_for(text)?;
                // A field wider than its format (`u8` at `"300:0:16"`) takes what the format
                // holds: wb-mqtt-serial cuts the value to the format's width (`GetRawValue`) and
                // reads back only that much of a `u8`.
                let bits = self.bit_width.min(format.value_bits()).clamp(1, 64);
                // A negative value on an unsigned format is written as its two's complement
                // in the field's width, as wb-mqtt-serial writes it (its `stoull` wraps and
                // the result is masked): Danfoss EKC 204A1 declares r36 as `u16` with scale
                // 0.1 and a range of -15 … -3 °C, which the controller reads as signed.
                let min = -(1i128 << (bits - 1));
                // A signed field narrower than its format reads back unsigned (see
                // `field_text`), so it takes what it can show: -8 … 15 for 4 bits.
                let max = if format.is_signed() && bits >= format.value_bits() {
                    (1i128 << (bits - 1)) - 1
                } else {
                    (1i128 << bits) - 1
                };
                if !(min..=max).contains(&value) {
                    return Err(self.out_of_range(text, min.to_string(), max.to_string()));
                }
                let width_mask = u64::MAX.checked_shr(64 - bits).unwrap_or(u64::MAX);
                Ok((value as u64) & width_mask & (self.mask() as u64))
            }
        }
    }

    fn unscale(&self, value: f64) -> f64 {
        let scale = if self.scale == 0.0 { 1.0 } else { self.scale };
        (value - self.offset) / scale
    }

    /// Integers are taken exactly when there is nothing to unscale (u64 counters would lose
    /// digits through f64); otherwise unscaled and rounded to the nearest integer. A fraction
    /// is first rounded to `round_to`, an integer text is not: wb-mqtt-serial's conversion
    /// (`FromScaledTextValue`) takes an integer text on its integer path and only a fraction
    /// on its floating one, which rounds (float and double formats always take that one).
    fn integer_for(&self, text: &str) -> Result<i128, CodecError> {
        let integer = parse_int_text(text);
        if let (Some(value), true) = (integer, self.scale == 1.0 && self.offset == 0.0) {
            return Ok(value);
        }
        let number = match integer {
            Some(value) => value as f64,
            None => self.rounded(parse_number(text)?),
        };
        let value = self.unscale(number).round();
        if !value.is_finite() || value.abs() > 1.8e19 {
            return Err(self.out_of_range(
                text,
                "-9223372036854775808".into(),
                "18446744073709551615".into(),
            ));
        }
        Ok(value as i128)
    }

    fn out_of_range(&self, text: &str, min: String, max: String) -> CodecError {
        CodecError::OutOfRange {
            value: text.to_string(),
            format: self.format.name(),
            min,
            max,
        }
    }

    fn encode_string(&self, text: &str) -> Result<Vec<u16>, CodecError> {
        let count = self.word_count as usize;
        let per_word = if self.format == RegisterFormat::String8 {
            2
        } else {
            1
        };
        let capacity = count * per_word;
        let bytes = text.as_bytes();
        if bytes.len() > capacity {
            return Err(CodecError::StringTooLong {
                text: text.to_string(),
                capacity: capacity as u32,
            });
        }
        let byte_at = |i: usize| u16::from(bytes.get(i).copied().unwrap_or(0));
        let words = (0..count).map(|i| {
            let word = if per_word == 2 {
                (byte_at(2 * i) << 8) | byte_at(2 * i + 1)
            } else {
                byte_at(i)
            };
            if self.byte_order == ByteOrder::LittleEndian {
                word.swap_bytes()
            } else {
                word
            }
        });
        let mut words: Vec<u16> = words.collect();
        // The first characters in the last register, as wb-mqtt-serial writes a string with
        // `word_order: little_endian` (`ComposeRawMultipleWriteRequestData` reverses the words)
        // and as it is read back.
        if self.word_order == WordOrder::LittleEndian {
            words.reverse();
        }
        Ok(words)
    }
}

fn parse_number(text: &str) -> Result<f64, CodecError> {
    if let Some(value) = parse_int_text(text) {
        return Ok(value as f64);
    }
    text.parse::<f64>()
        .map_err(|_| CodecError::NotANumber(text.to_string()))
}

/// True when `text` is exactly how C++'s `std::to_string` prints `value` (no sign on zero, no
/// leading zeros, no exponent): the comparison wb-mqtt-serial makes for `on_value`.
fn is_decimal_text_of(text: &str, value: i128) -> bool {
    let digits = text.strip_prefix('-').unwrap_or(text);
    let canonical = !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits == "0" || !digits.starts_with('0'))
        && text != "-0";
    canonical && text.parse::<i128>() == Ok(value)
}

/// Packed BCD (one decimal digit per nibble) to its value; None when a nibble is above 9.
fn decode_bcd(raw: u64, bits: u32) -> Option<u64> {
    let mut value = 0u64;
    for nibble_index in (0..bits / 4).rev() {
        let digit = (raw >> (nibble_index * 4)) & 0xF;
        if digit > 9 {
            return None;
        }
        value = value * 10 + digit;
    }
    Some(value)
}

fn encode_bcd(mut value: u64) -> u64 {
    let mut raw = 0u64;
    let mut shift = 0;
    while value > 0 {
        raw |= (value % 10) << shift;
        value /= 10;
        shift += 4;
    }
    raw
}

#[cfg(test)]
#[path = "codec_tests.rs"]
mod tests;

/// Appends `value` as `to_string` would print it, without a String of its own.
fn push_display(text: &mut String, value: impl std::fmt::Display) {
    use std::fmt::Write;
    // Writing into a String cannot fail.
    let _ = write!(text, "{value}");
}
