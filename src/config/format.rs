//! Register value formats and orders, named as in wb-mqtt-serial templates.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// How the bits of a register value are read (`format` in a template).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum RegisterFormat {
    U8,
    S8,
    U16,
    S16,
    U24,
    S24,
    U32,
    S32,
    U64,
    S64,
    Float,
    Double,
    Char8,
    Bcd8,
    Bcd16,
    Bcd24,
    Bcd32,
    /// One character per 16-bit register (in its low byte); needs `string_data_size`.
    String,
    /// Two characters per 16-bit register; needs `string_data_size`.
    String8,
}

impl RegisterFormat {
    /// Every format, for listing and exhaustive tests.
    pub const ALL: [RegisterFormat; 19] = [
        Self::U8,
        Self::S8,
        Self::U16,
        Self::S16,
        Self::U24,
        Self::S24,
        Self::U32,
        Self::S32,
        Self::U64,
        Self::S64,
        Self::Float,
        Self::Double,
        Self::Char8,
        Self::Bcd8,
        Self::Bcd16,
        Self::Bcd24,
        Self::Bcd32,
        Self::String,
        Self::String8,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Self::U8 => "u8",
            Self::S8 => "s8",
            Self::U16 => "u16",
            Self::S16 => "s16",
            Self::U24 => "u24",
            Self::S24 => "s24",
            Self::U32 => "u32",
            Self::S32 => "s32",
            Self::U64 => "u64",
            Self::S64 => "s64",
            Self::Float => "float",
            Self::Double => "double",
            Self::Char8 => "char8",
            Self::Bcd8 => "bcd8",
            Self::Bcd16 => "bcd16",
            Self::Bcd24 => "bcd24",
            Self::Bcd32 => "bcd32",
            Self::String => "string",
            Self::String8 => "string8",
        }
    }

    /// Bits of the value itself (0 for strings, whose size comes from `string_data_size`).
    pub fn value_bits(self) -> u32 {
        match self {
            Self::U8 | Self::S8 | Self::Char8 | Self::Bcd8 => 8,
            Self::U16 | Self::S16 | Self::Bcd16 => 16,
            Self::U24 | Self::S24 | Self::Bcd24 => 24,
            Self::U32 | Self::S32 | Self::Float | Self::Bcd32 => 32,
            Self::U64 | Self::S64 | Self::Double => 64,
            Self::String | Self::String8 => 0,
        }
    }

    /// 16-bit registers the value occupies (a string channel: `string_data_size`, in either
    /// string format).
    pub fn registers(self) -> u32 {
        self.value_bits().div_ceil(16)
    }

    /// Registers a text of `characters` needs in this format (one character per register for
    /// `string`, two for `string8`): what the site tools write. A string *channel* takes
    /// `string_data_size` registers in either format, as wb-mqtt-serial reads it.
    pub fn string_registers(self, characters: u32) -> u32 {
        match self {
            Self::String8 => characters.div_ceil(2),
            _ => characters,
        }
    }

    pub fn is_signed(self) -> bool {
        matches!(
            self,
            Self::S8 | Self::S16 | Self::S24 | Self::S32 | Self::S64
        )
    }

    pub fn is_string(self) -> bool {
        matches!(self, Self::String | Self::String8)
    }

    pub fn is_bcd(self) -> bool {
        matches!(self, Self::Bcd8 | Self::Bcd16 | Self::Bcd24 | Self::Bcd32)
    }

    /// Formats whose raw value is an integer (printed exactly when there is no scale).
    pub fn is_integer(self) -> bool {
        !matches!(
            self,
            Self::Float | Self::Double | Self::Char8 | Self::String | Self::String8
        )
    }
}

/// Order of 16-bit words in a multi-register value (`word_order`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    /// Most significant word first (at the lowest address).
    #[default]
    BigEndian,
    LittleEndian,
}

/// Order of the two bytes inside each 16-bit word (`byte_order`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ByteOrder {
    #[default]
    BigEndian,
    LittleEndian,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_match_serde_names() {
        for format in RegisterFormat::ALL {
            let json = serde_json::to_string(&format).unwrap();
            assert_eq!(json, format!("\"{}\"", format.name()));
            let back: RegisterFormat = serde_json::from_str(&json).unwrap();
            assert_eq!(back, format);
        }
    }

    #[test]
    fn unknown_format_lists_valid_ones() {
        let err = serde_json::from_str::<RegisterFormat>("\"u17\"")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("u17") && err.contains("s16") && err.contains("string8"),
            "{err}"
        );
    }

    #[test]
    fn register_counts() {
        assert_eq!(RegisterFormat::U8.registers(), 1);
        assert_eq!(RegisterFormat::U24.registers(), 2);
        assert_eq!(RegisterFormat::Float.registers(), 2);
        assert_eq!(RegisterFormat::Double.registers(), 4);
        assert_eq!(RegisterFormat::String8.string_registers(5), 3);
        assert_eq!(RegisterFormat::String.string_registers(5), 5);
    }
}
