//! Scalar value forms the wb-mqtt-serial formats accept: integers written as numbers, decimal
//! strings or `0x..` strings; register addresses with an optional bit field (`"reg:shift:width"`).

use std::borrow::Cow;
use std::fmt;

use schemars::{json_schema, JsonSchema, Schema, SchemaGenerator};
use serde::de::{self, Deserializer, Visitor};
use serde::{Deserialize, Serialize, Serializer};

/// Parses `12`, `-3`, `0x1F` (the forms C's `stoi(…, 0)` accepts for decimal and hex).
/// Only digits may follow the sign and the `0x` (`"0x-14"` and `"0x+1"` are not numbers), and a
/// value that does not fit is `None`, never a wrapped or overflowing number.
pub fn parse_int_text(text: &str) -> Option<i128> {
    let trimmed = text.trim();
    let (negative, digits) = match trimmed.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, trimmed.strip_prefix('+').unwrap_or(trimmed)),
    };
    let magnitude = if let Some(hex) = digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        if hex.is_empty() || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        i128::from_str_radix(hex, 16).ok()?
    } else {
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        digits.parse::<i128>().ok()?
    };
    if negative {
        magnitude.checked_neg()
    } else {
        Some(magnitude)
    }
}

/// A device's `slave_id`: its Modbus address, and for `modbus_io` devices (WBIO modules behind a
/// WB-MIO) the module's position after a colon, as in `"1:2"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SlaveId {
    pub address: i128,
    pub module: Option<i128>,
}

impl SlaveId {
    /// The Modbus address.
    pub fn value(self) -> i128 {
        self.address
    }

    fn parse(text: &str) -> Option<Self> {
        match text.split_once(':') {
            Some((address, module)) => Some(Self {
                address: parse_int_text(address)?,
                module: Some(parse_int_text(module)?),
            }),
            None => Some(Self {
                address: parse_int_text(text)?,
                module: None,
            }),
        }
    }
}

impl fmt::Display for SlaveId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.module {
            Some(module) => write!(f, "{}:{module}", self.address),
            None => write!(f, "{}", self.address),
        }
    }
}

impl<'de> Deserialize<'de> for SlaveId {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = serde_json::Value::deserialize(deserializer)?;
        if let serde_json::Value::String(text) = &value {
            return SlaveId::parse(text).ok_or_else(|| {
                de::Error::custom(format!(
                    "`{text}` is not a slave_id; write a number like 16, \"16\" or \"0x10\" (or \"1:2\" for a modbus_io module)"
                ))
            });
        }
        let int = SerialInt::deserialize(value).map_err(de::Error::custom)?;
        Ok(SlaveId {
            address: int.value(),
            module: None,
        })
    }
}

impl Serialize for SlaveId {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match (self.module, i64::try_from(self.address)) {
            (None, Ok(v)) => serializer.serialize_i64(v),
            _ => serializer.serialize_str(&self.to_string()),
        }
    }
}

impl JsonSchema for SlaveId {
    fn schema_name() -> Cow<'static, str> {
        "SlaveId".into()
    }
    fn json_schema(_: &mut SchemaGenerator) -> Schema {
        json_schema!({
            "description": "A Modbus address 1…247: a number, a decimal string or a \"0x..\" hex string; \"address:module\" for modbus_io modules.",
            "anyOf": [
                {"type": "integer", "minimum": 1, "maximum": 255},
                {"type": "string", "pattern": SLAVE_ID_PATTERN}
            ]
        })
    }
}

const SLAVE_ID_PATTERN: &str =
    "^\\s*[-+]?(0[xX][0-9a-fA-F]+|[0-9]+)(\\s*:\\s*(0[xX][0-9a-fA-F]+|[0-9]+))?\\s*$";

const INT_PATTERN: &str = "^\\s*[-+]?(0[xX][0-9a-fA-F]+|[0-9]+)\\s*$";

/// An integer given as a JSON number or as a decimal or `0x..` string (`slave_id`, `error_value`,
/// `on_value`, `shift`, setup values …).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SerialInt(pub i128);

impl SerialInt {
    pub fn value(self) -> i128 {
        self.0
    }
}

impl fmt::Display for SerialInt {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

impl<'de> Deserialize<'de> for SerialInt {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct IntVisitor;
        impl Visitor<'_> for IntVisitor {
            type Value = SerialInt;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("an integer: a number, a decimal string or a \"0x..\" hex string")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<SerialInt, E> {
                Ok(SerialInt(v.into()))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<SerialInt, E> {
                Ok(SerialInt(v.into()))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<SerialInt, E> {
                if v.fract() == 0.0 && v.abs() < 1e18 {
                    Ok(SerialInt(v as i128))
                } else {
                    Err(E::custom(format!("{v} is not a whole number")))
                }
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<SerialInt, E> {
                parse_int_text(v).map(SerialInt).ok_or_else(|| {
                    E::custom(format!(
                        "`{v}` is not an integer; write a number like 16, \"16\" or \"0x10\""
                    ))
                })
            }
        }
        deserializer.deserialize_any(IntVisitor)
    }
}

impl Serialize for SerialInt {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match i64::try_from(self.0) {
            Ok(v) => serializer.serialize_i64(v),
            Err(_) => serializer.serialize_str(&format!("{:#x}", self.0)),
        }
    }
}

impl JsonSchema for SerialInt {
    fn schema_name() -> Cow<'static, str> {
        "SerialInt".into()
    }
    fn json_schema(_: &mut SchemaGenerator) -> Schema {
        json_schema!({
            "description": "An integer: a number, a decimal string or a \"0x..\" hex string.",
            "anyOf": [{"type": "integer"}, {"type": "string", "pattern": INT_PATTERN}]
        })
    }
}

/// A number given as JSON number or integer string (`min`, `max`, setup `value`).
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd)]
pub struct SerialNumber(pub f64);

impl<'de> Deserialize<'de> for SerialNumber {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct NumberVisitor;
        impl Visitor<'_> for NumberVisitor {
            type Value = SerialNumber;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a number, a decimal string or a \"0x..\" hex string")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<SerialNumber, E> {
                Ok(SerialNumber(v as f64))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<SerialNumber, E> {
                Ok(SerialNumber(v as f64))
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<SerialNumber, E> {
                Ok(SerialNumber(v))
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<SerialNumber, E> {
                if let Some(int) = parse_int_text(v) {
                    return Ok(SerialNumber(int as f64));
                }
                v.trim()
                    .parse::<f64>()
                    .map(SerialNumber)
                    .map_err(|_| E::custom(format!("`{v}` is not a number")))
            }
        }
        deserializer.deserialize_any(NumberVisitor)
    }
}

impl Serialize for SerialNumber {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_f64(self.0)
    }
}

impl JsonSchema for SerialNumber {
    fn schema_name() -> Cow<'static, str> {
        "SerialNumber".into()
    }
    fn json_schema(_: &mut SchemaGenerator) -> Schema {
        json_schema!({
            "description": "A number, or an integer as a decimal or \"0x..\" string.",
            "anyOf": [{"type": "number"}, {"type": "string", "pattern": INT_PATTERN}]
        })
    }
}

/// The largest bit shift wb-mqtt-serial takes in an address (`LoadRegisterBitsAddress` keeps it
/// in a byte and throws above it).
pub const MAX_BIT_SHIFT: u32 = 255;

/// A register address: `16`, `"0x10"`, or a bit field `"16:4:1"` (register, bit shift, bit width).
/// An empty string means "no address" (a write-only channel has only `write_address`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AddressSpec {
    pub register: Option<i64>,
    pub bit_shift: u32,
    pub bit_width: Option<u32>,
}

impl AddressSpec {
    pub fn register(register: i64) -> Self {
        Self {
            register: Some(register),
            bit_shift: 0,
            bit_width: None,
        }
    }

    fn parse(text: &str) -> Result<Self, String> {
        let trimmed = text.trim();
        if trimmed.is_empty() {
            return Ok(Self::default());
        }
        let mut parts = trimmed.split(':');
        let register_text = parts.next().unwrap_or("");
        let register = parse_int_text(register_text)
            .and_then(|v| i64::try_from(v).ok())
            .ok_or_else(|| format!("`{text}` is not an address; write 16, \"0x10\" or \"16:4:1\" (register:shift:width)"))?;
        // A shift above `MAX_BIT_SHIFT` is read here and refused where the register is built:
        // wb-mqtt-serial throws it inside `LoadSimpleChannel`'s `try`, so a channel with one
        // is left out while the rest of the template loads.
        let bit_shift = match parts.next() {
            Some(shift) => shift.trim().parse::<u32>().ok().ok_or_else(|| {
                format!("bit shift in `{text}` must be a number 0…{MAX_BIT_SHIFT}")
            })?,
            None => 0,
        };
        let bit_width = match parts.next() {
            Some(width) => Some(
                width
                    .trim()
                    .parse::<u32>()
                    .ok()
                    .filter(|w| *w <= 64)
                    .ok_or_else(|| format!("bit width in `{text}` must be a number 0…64"))?,
            )
            // 0 means the format's own width, as in wb-mqtt-serial (`"127:8:0"`).
            .filter(|w| *w > 0),
            None => None,
        };
        if parts.next().is_some() {
            return Err(format!(
                "`{text}` has too many `:` parts; write register:shift:width"
            ));
        }
        Ok(Self {
            register: Some(register),
            bit_shift,
            bit_width,
        })
    }
}

impl<'de> Deserialize<'de> for AddressSpec {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct AddressVisitor;
        impl Visitor<'_> for AddressVisitor {
            type Value = AddressSpec;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a register address: 16, \"0x10\" or \"16:4:1\" (register:shift:width)")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<AddressSpec, E> {
                Ok(AddressSpec::register(v))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<AddressSpec, E> {
                i64::try_from(v).map(AddressSpec::register).map_err(|_| {
                    E::custom(format!(
                        "address {v} is out of range: Modbus addresses are 0…65535"
                    ))
                })
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<AddressSpec, E> {
                AddressSpec::parse(v).map_err(E::custom)
            }
        }
        deserializer.deserialize_any(AddressVisitor)
    }
}

impl Serialize for AddressSpec {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match (self.register, self.bit_shift, self.bit_width) {
            (None, _, _) => serializer.serialize_str(""),
            (Some(r), 0, None) => serializer.serialize_i64(r),
            (Some(r), s, None) => serializer.serialize_str(&format!("{r}:{s}")),
            (Some(r), s, Some(w)) => serializer.serialize_str(&format!("{r}:{s}:{w}")),
        }
    }
}

impl JsonSchema for AddressSpec {
    fn schema_name() -> Cow<'static, str> {
        "Address".into()
    }
    fn json_schema(_: &mut SchemaGenerator) -> Schema {
        json_schema!({
            "description": "Register address: a number, a decimal or \"0x..\" string, or \"register:shift:width\" for a bit field.",
            "anyOf": [
                {"type": "integer", "minimum": 0},
                {"type": "string", "pattern": "^\\s*((0[xX][0-9a-fA-F]+|[0-9]+)(:[0-9]+(:[0-9]+)?)?)?\\s*$"}
            ]
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integers_in_every_written_form() {
        for (text, value) in [
            ("16", 16),
            ("0x10", 16),
            ("0X1f", 31),
            ("-5", -5),
            (" 7 ", 7),
        ] {
            assert_eq!(parse_int_text(text), Some(value), "{text}");
        }
        for text in ["", "0x", "1.5", "abc", "12a"] {
            assert_eq!(parse_int_text(text), None, "{text}");
        }
        let v: SerialInt = serde_json::from_str("\"0xFFFFFFFFFFFFFFFF\"").unwrap();
        assert_eq!(v.0, u64::MAX as i128);
        let v: SerialInt = serde_json::from_str("12").unwrap();
        assert_eq!(v.0, 12);
        assert!(serde_json::from_str::<SerialInt>("1.5").is_err());
        assert!(serde_json::from_str::<SerialInt>("true").is_err());
    }

    #[test]
    fn addresses_with_bit_fields() {
        let a: AddressSpec = serde_json::from_str("\"55:4:1\"").unwrap();
        assert_eq!(
            a,
            AddressSpec {
                register: Some(55),
                bit_shift: 4,
                bit_width: Some(1)
            }
        );
        let a: AddressSpec = serde_json::from_str("\"0x1410\"").unwrap();
        assert_eq!(a, AddressSpec::register(0x1410));
        let a: AddressSpec = serde_json::from_str("\"0x10:3\"").unwrap();
        assert_eq!(
            a,
            AddressSpec {
                register: Some(16),
                bit_shift: 3,
                bit_width: None
            }
        );
        let a: AddressSpec = serde_json::from_str("\"\"").unwrap();
        assert_eq!(a.register, None);
        // Read, and refused (or the channel left out) where the register is built.
        let a: AddressSpec = serde_json::from_str("\"1:300:1\"").unwrap();
        assert_eq!(a.bit_shift, 300);
        assert!(serde_json::from_str::<AddressSpec>("\"1:x:1\"").is_err());
        assert!(serde_json::from_str::<AddressSpec>("\"1:2:3:4\"").is_err());
        assert!(serde_json::from_str::<AddressSpec>("\"reg\"").is_err());
        assert!(serde_json::from_str::<AddressSpec>("1.5").is_err());
    }

    #[test]
    fn numbers_from_strings() {
        let n: SerialNumber = serde_json::from_str("\"0x10\"").unwrap();
        assert_eq!(n.0, 16.0);
        let n: SerialNumber = serde_json::from_str("2.5").unwrap();
        assert_eq!(n.0, 2.5);
    }
}
