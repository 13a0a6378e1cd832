//! Classic Modbus PDUs (function code + body), both directions.
//!
//! | fc   | request body                                   | reply body                          |
//! |------|------------------------------------------------|-------------------------------------|
//! | 0x01 | start(2) count(2), count 1..=2000              | byte_count(1) coils packed LSB first |
//! | 0x02 | start(2) count(2), count 1..=2000              | byte_count(1) inputs packed          |
//! | 0x03 | start(2) count(2), count 1..=125               | byte_count(1) registers(2 each, BE)  |
//! | 0x04 | start(2) count(2), count 1..=125               | byte_count(1) registers              |
//! | 0x05 | address(2) value(2): 0xFF00 on, 0x0000 off     | echo of the request                  |
//! | 0x06 | address(2) value(2)                            | echo of the request                  |
//! | 0x0F | start(2) count(2) byte_count(1) packed bits    | start(2) count(2)                    |
//! | 0x10 | start(2) count(2) byte_count(1) registers      | start(2) count(2)                    |
//! | any  |                                                | exception: fc\|0x80, code(1)         |

use super::wire::Reader;
use super::{DecodeError, EncodeError};

pub const READ_COILS: u8 = 0x01;
pub const READ_DISCRETE_INPUTS: u8 = 0x02;
pub const READ_HOLDING_REGISTERS: u8 = 0x03;
pub const READ_INPUT_REGISTERS: u8 = 0x04;
pub const WRITE_SINGLE_COIL: u8 = 0x05;
pub const WRITE_SINGLE_REGISTER: u8 = 0x06;
pub const WRITE_MULTIPLE_COILS: u8 = 0x0F;
pub const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
/// Set in the function code of an exception reply.
pub const EXCEPTION_FLAG: u8 = 0x80;

/// Most bits one 0x01/0x02 request may read.
pub const MAX_READ_BITS: u16 = 2000;
/// Most registers one 0x03/0x04 request may read.
pub const MAX_READ_REGISTERS: u16 = 125;
/// Most coils one 0x0F request may write.
pub const MAX_WRITE_BITS: u16 = 1968;
/// Most registers one 0x10 request may write.
pub const MAX_WRITE_REGISTERS: u16 = 123;

const COIL_ON: u16 = 0xFF00;
const COIL_OFF: u16 = 0x0000;

/// A Modbus exception code. Kept as the raw byte so that codes this crate does not name still
/// round-trip; the constants name the ones the standard defines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ExceptionCode(pub u8);

impl ExceptionCode {
    pub const ILLEGAL_FUNCTION: Self = Self(1);
    pub const ILLEGAL_DATA_ADDRESS: Self = Self(2);
    pub const ILLEGAL_DATA_VALUE: Self = Self(3);
    pub const DEVICE_FAILURE: Self = Self(4);
    pub const ACKNOWLEDGE: Self = Self(5);
    pub const BUSY: Self = Self(6);
    pub const MEMORY_PARITY_ERROR: Self = Self(8);
    pub const GATEWAY_PATH_UNAVAILABLE: Self = Self(0x0A);
    pub const GATEWAY_TARGET_FAILED: Self = Self(0x0B);

    /// It refuses what was asked for good (illegal function, address or value), as
    /// wb-mqtt-serial's `RethrowSerialDeviceException` tells a permanent error from a
    /// transient one (busy, device failure, and any other code): asking again will not help.
    pub fn is_permanent(self) -> bool {
        matches!(
            self,
            Self::ILLEGAL_FUNCTION | Self::ILLEGAL_DATA_ADDRESS | Self::ILLEGAL_DATA_VALUE
        )
    }

    pub fn description(self) -> &'static str {
        match self.0 {
            1 => "illegal function",
            2 => "illegal data address",
            3 => "illegal data value",
            4 => "device failure",
            5 => "acknowledge",
            6 => "busy",
            8 => "memory parity error",
            0x0A => "gateway path unavailable",
            0x0B => "gateway target failed to respond",
            _ => "unknown exception",
        }
    }
}

impl std::fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "exception {} ({})", self.0, self.description())
    }
}

/// A classic request, as the master sends it and a device receives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RequestPdu {
    ReadCoils { start: u16, count: u16 },
    ReadDiscreteInputs { start: u16, count: u16 },
    ReadHoldingRegisters { start: u16, count: u16 },
    ReadInputRegisters { start: u16, count: u16 },
    WriteSingleCoil { address: u16, value: bool },
    WriteSingleRegister { address: u16, value: u16 },
    WriteMultipleCoils { start: u16, values: Vec<bool> },
    WriteMultipleRegisters { start: u16, values: Vec<u16> },
}

/// A classic reply, as a device sends it and the master receives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ResponsePdu {
    /// Coil states packed LSB first; the last byte is padded with zeros. See [`unpack_bits`].
    ReadCoils {
        packed: Vec<u8>,
    },
    ReadDiscreteInputs {
        packed: Vec<u8>,
    },
    ReadHoldingRegisters {
        values: Vec<u16>,
    },
    ReadInputRegisters {
        values: Vec<u16>,
    },
    WriteSingleCoil {
        address: u16,
        value: bool,
    },
    WriteSingleRegister {
        address: u16,
        value: u16,
    },
    WriteMultipleCoils {
        start: u16,
        count: u16,
    },
    WriteMultipleRegisters {
        start: u16,
        count: u16,
    },
    /// `function` is the request's function code (without the 0x80 flag).
    Exception {
        function: u8,
        code: ExceptionCode,
    },
}

impl RequestPdu {
    /// A write (functions 5, 6, 15, 16): it changes the device.
    pub fn is_write(&self) -> bool {
        matches!(
            self,
            Self::WriteSingleCoil { .. }
                | Self::WriteSingleRegister { .. }
                | Self::WriteMultipleCoils { .. }
                | Self::WriteMultipleRegisters { .. }
        )
    }

    pub fn function(&self) -> u8 {
        match self {
            Self::ReadCoils { .. } => READ_COILS,
            Self::ReadDiscreteInputs { .. } => READ_DISCRETE_INPUTS,
            Self::ReadHoldingRegisters { .. } => READ_HOLDING_REGISTERS,
            Self::ReadInputRegisters { .. } => READ_INPUT_REGISTERS,
            Self::WriteSingleCoil { .. } => WRITE_SINGLE_COIL,
            Self::WriteSingleRegister { .. } => WRITE_SINGLE_REGISTER,
            Self::WriteMultipleCoils { .. } => WRITE_MULTIPLE_COILS,
            Self::WriteMultipleRegisters { .. } => WRITE_MULTIPLE_REGISTERS,
        }
    }

    /// Appends function code and body. Fails when a count is outside the standard's limits.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        out.push(self.function());
        match self {
            Self::ReadCoils { start, count } | Self::ReadDiscreteInputs { start, count } => {
                check_count(*count, MAX_READ_BITS, "bits to read")?;
                push_u16s(out, &[*start, *count]);
            }
            Self::ReadHoldingRegisters { start, count }
            | Self::ReadInputRegisters { start, count } => {
                check_count(*count, MAX_READ_REGISTERS, "registers to read")?;
                push_u16s(out, &[*start, *count]);
            }
            Self::WriteSingleCoil { address, value } => {
                push_u16s(out, &[*address, if *value { COIL_ON } else { COIL_OFF }]);
            }
            Self::WriteSingleRegister { address, value } => push_u16s(out, &[*address, *value]),
            Self::WriteMultipleCoils { start, values } => {
                let count = count_of(values.len(), MAX_WRITE_BITS, "coils to write")?;
                let packed = pack_bits(values);
                push_u16s(out, &[*start, count]);
                out.push(byte_len(packed.len())?);
                out.extend_from_slice(&packed);
            }
            Self::WriteMultipleRegisters { start, values } => {
                let count = count_of(values.len(), MAX_WRITE_REGISTERS, "registers to write")?;
                push_u16s(out, &[*start, count]);
                out.push(byte_len(values.len() * 2)?);
                push_u16s(out, values);
            }
        }
        Ok(())
    }

    /// Decodes exactly one request PDU. Values outside the standard's limits are errors whose
    /// [`DecodeError::exception`] is the code a device answers with.
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut reader = Reader::new(bytes);
        let function = reader.u8()?;
        let pdu = match function {
            READ_COILS | READ_DISCRETE_INPUTS => {
                let start = reader.u16_be()?;
                let count = reader.u16_be()?;
                decode_count(count, MAX_READ_BITS, function)?;
                if function == READ_COILS {
                    Self::ReadCoils { start, count }
                } else {
                    Self::ReadDiscreteInputs { start, count }
                }
            }
            READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
                let start = reader.u16_be()?;
                let count = reader.u16_be()?;
                decode_count(count, MAX_READ_REGISTERS, function)?;
                if function == READ_HOLDING_REGISTERS {
                    Self::ReadHoldingRegisters { start, count }
                } else {
                    Self::ReadInputRegisters { start, count }
                }
            }
            WRITE_SINGLE_COIL => {
                let address = reader.u16_be()?;
                let value = decode_coil(reader.u16_be()?, function)?;
                Self::WriteSingleCoil { address, value }
            }
            WRITE_SINGLE_REGISTER => Self::WriteSingleRegister {
                address: reader.u16_be()?,
                value: reader.u16_be()?,
            },
            WRITE_MULTIPLE_COILS => {
                let start = reader.u16_be()?;
                let count = reader.u16_be()?;
                decode_count(count, MAX_WRITE_BITS, function)?;
                let byte_count = reader.u8()?;
                if usize::from(byte_count) != usize::from(count).div_ceil(8) {
                    return Err(DecodeError::InvalidValue {
                        function,
                        what: "byte count does not match the coil count",
                    });
                }
                let packed = reader.take(usize::from(byte_count))?;
                Self::WriteMultipleCoils {
                    start,
                    values: unpack_bits(packed, usize::from(count)),
                }
            }
            WRITE_MULTIPLE_REGISTERS => {
                let start = reader.u16_be()?;
                let count = reader.u16_be()?;
                decode_count(count, MAX_WRITE_REGISTERS, function)?;
                let byte_count = reader.u8()?;
                if usize::from(byte_count) != usize::from(count) * 2 {
                    return Err(DecodeError::InvalidValue {
                        function,
                        what: "byte count does not match the register count",
                    });
                }
                let values = read_u16s(&mut reader, usize::from(count))?;
                Self::WriteMultipleRegisters { start, values }
            }
            other => return Err(DecodeError::UnknownFunction(other)),
        };
        reader.finish()?;
        Ok(pdu)
    }

    /// The length of the request PDU that starts with `bytes`, once enough of it is known.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(&function) = bytes.first() else {
            return FrameLength::NeedMore;
        };
        match function {
            READ_COILS..=WRITE_SINGLE_REGISTER => FrameLength::Known(5),
            WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => match bytes.get(5) {
                Some(&byte_count) => FrameLength::Known(6 + usize::from(byte_count)),
                None => FrameLength::NeedMore,
            },
            _ => FrameLength::Unknown,
        }
    }

    /// The register or bit range this request touches: `(start, count)`.
    pub fn range(&self) -> (u16, u16) {
        match self {
            Self::ReadCoils { start, count }
            | Self::ReadDiscreteInputs { start, count }
            | Self::ReadHoldingRegisters { start, count }
            | Self::ReadInputRegisters { start, count } => (*start, *count),
            Self::WriteSingleCoil { address, .. } | Self::WriteSingleRegister { address, .. } => {
                (*address, 1)
            }
            Self::WriteMultipleCoils { start, values } => {
                (*start, u16::try_from(values.len()).unwrap_or(u16::MAX))
            }
            Self::WriteMultipleRegisters { start, values } => {
                (*start, u16::try_from(values.len()).unwrap_or(u16::MAX))
            }
        }
    }

    /// The exact length of a successful (non-exception) reply PDU to this request: function
    /// code, byte count and data of a read; the 5-byte echo of a write. An exception is shorter
    /// (2 bytes).
    pub fn reply_pdu_len(&self) -> usize {
        match self {
            Self::ReadCoils { count, .. } | Self::ReadDiscreteInputs { count, .. } => {
                2 + usize::from(*count).div_ceil(8)
            }
            Self::ReadHoldingRegisters { count, .. } | Self::ReadInputRegisters { count, .. } => {
                2 + 2 * usize::from(*count)
            }
            _ => 5,
        }
    }

    /// True when `reply` is a plausible answer to this request: the same function, the byte count
    /// the request asked for, an echo of what was written; or an exception for this function.
    pub fn is_answered_by(&self, reply: &ResponsePdu) -> bool {
        match (self, reply) {
            (_, ResponsePdu::Exception { function, .. }) => *function == self.function(),
            (Self::ReadCoils { count, .. }, ResponsePdu::ReadCoils { packed })
            | (
                Self::ReadDiscreteInputs { count, .. },
                ResponsePdu::ReadDiscreteInputs { packed },
            ) => packed.len() == usize::from(*count).div_ceil(8),
            (
                Self::ReadHoldingRegisters { count, .. },
                ResponsePdu::ReadHoldingRegisters { values },
            )
            | (
                Self::ReadInputRegisters { count, .. },
                ResponsePdu::ReadInputRegisters { values },
            ) => values.len() == usize::from(*count),
            (
                Self::WriteSingleCoil { address, value },
                ResponsePdu::WriteSingleCoil {
                    address: a,
                    value: v,
                },
            ) => address == a && value == v,
            (
                Self::WriteSingleRegister { address, value },
                ResponsePdu::WriteSingleRegister {
                    address: a,
                    value: v,
                },
            ) => address == a && value == v,
            (
                Self::WriteMultipleCoils { start, values },
                ResponsePdu::WriteMultipleCoils { start: s, count },
            ) => start == s && values.len() == usize::from(*count),
            (
                Self::WriteMultipleRegisters { start, values },
                ResponsePdu::WriteMultipleRegisters { start: s, count },
            ) => start == s && values.len() == usize::from(*count),
            _ => false,
        }
    }
}

impl ResponsePdu {
    /// The function code on the wire (with the 0x80 flag for exceptions).
    pub fn function(&self) -> u8 {
        match self {
            Self::ReadCoils { .. } => READ_COILS,
            Self::ReadDiscreteInputs { .. } => READ_DISCRETE_INPUTS,
            Self::ReadHoldingRegisters { .. } => READ_HOLDING_REGISTERS,
            Self::ReadInputRegisters { .. } => READ_INPUT_REGISTERS,
            Self::WriteSingleCoil { .. } => WRITE_SINGLE_COIL,
            Self::WriteSingleRegister { .. } => WRITE_SINGLE_REGISTER,
            Self::WriteMultipleCoils { .. } => WRITE_MULTIPLE_COILS,
            Self::WriteMultipleRegisters { .. } => WRITE_MULTIPLE_REGISTERS,
            Self::Exception { function, .. } => function | EXCEPTION_FLAG,
        }
    }

    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        out.push(self.function());
        match self {
            Self::ReadCoils { packed } | Self::ReadDiscreteInputs { packed } => {
                out.push(byte_len(packed.len())?);
                out.extend_from_slice(packed);
            }
            Self::ReadHoldingRegisters { values } | Self::ReadInputRegisters { values } => {
                out.push(byte_len(values.len() * 2)?);
                push_u16s(out, values);
            }
            Self::WriteSingleCoil { address, value } => {
                push_u16s(out, &[*address, if *value { COIL_ON } else { COIL_OFF }]);
            }
            Self::WriteSingleRegister { address, value } => push_u16s(out, &[*address, *value]),
            Self::WriteMultipleCoils { start, count }
            | Self::WriteMultipleRegisters { start, count } => push_u16s(out, &[*start, *count]),
            Self::Exception { code, .. } => out.push(code.0),
        }
        Ok(())
    }

    /// Decodes exactly one reply PDU.
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut reader = Reader::new(bytes);
        let function = reader.u8()?;
        let pdu = if function & EXCEPTION_FLAG != 0 {
            Self::Exception {
                function: function & !EXCEPTION_FLAG,
                code: ExceptionCode(reader.u8()?),
            }
        } else {
            match function {
                READ_COILS | READ_DISCRETE_INPUTS => {
                    let byte_count = reader.u8()?;
                    let packed = reader.take(usize::from(byte_count))?.to_vec();
                    if function == READ_COILS {
                        Self::ReadCoils { packed }
                    } else {
                        Self::ReadDiscreteInputs { packed }
                    }
                }
                READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
                    let byte_count = reader.u8()?;
                    if byte_count % 2 != 0 {
                        return Err(DecodeError::InvalidValue {
                            function,
                            what: "odd byte count in a register reply",
                        });
                    }
                    let values = read_u16s(&mut reader, usize::from(byte_count / 2))?;
                    if function == READ_HOLDING_REGISTERS {
                        Self::ReadHoldingRegisters { values }
                    } else {
                        Self::ReadInputRegisters { values }
                    }
                }
                WRITE_SINGLE_COIL => {
                    let address = reader.u16_be()?;
                    let value = decode_coil(reader.u16_be()?, function)?;
                    Self::WriteSingleCoil { address, value }
                }
                WRITE_SINGLE_REGISTER => Self::WriteSingleRegister {
                    address: reader.u16_be()?,
                    value: reader.u16_be()?,
                },
                WRITE_MULTIPLE_COILS => Self::WriteMultipleCoils {
                    start: reader.u16_be()?,
                    count: reader.u16_be()?,
                },
                WRITE_MULTIPLE_REGISTERS => Self::WriteMultipleRegisters {
                    start: reader.u16_be()?,
                    count: reader.u16_be()?,
                },
                other => return Err(DecodeError::UnknownFunction(other)),
            }
        };
        reader.finish()?;
        Ok(pdu)
    }

    /// The length of the reply PDU that starts with `bytes`, once enough of it is known.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(&function) = bytes.first() else {
            return FrameLength::NeedMore;
        };
        if function & EXCEPTION_FLAG != 0 {
            return FrameLength::Known(2);
        }
        match function {
            READ_COILS..=READ_INPUT_REGISTERS => match bytes.get(1) {
                Some(&byte_count) => FrameLength::Known(2 + usize::from(byte_count)),
                None => FrameLength::NeedMore,
            },
            WRITE_SINGLE_COIL
            | WRITE_SINGLE_REGISTER
            | WRITE_MULTIPLE_COILS
            | WRITE_MULTIPLE_REGISTERS => FrameLength::Known(5),
            _ => FrameLength::Unknown,
        }
    }
}

/// How long a frame (or PDU) is, judged from the bytes seen so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameLength {
    /// The header is not complete yet.
    NeedMore,
    /// The whole thing is this many bytes.
    Known(usize),
    /// The header names something whose length this crate cannot know (an unknown function).
    Unknown,
}

/// Packs bits LSB first, as coil and discrete-input data travel.
pub fn pack_bits(bits: &[bool]) -> Vec<u8> {
    bits.chunks(8)
        .map(|chunk| {
            chunk
                .iter()
                .enumerate()
                .fold(0u8, |byte, (i, &bit)| byte | (u8::from(bit) << i))
        })
        .collect()
}

/// Unpacks the first `count` bits (LSB first); missing bytes read as 0.
pub fn unpack_bits(packed: &[u8], count: usize) -> Vec<bool> {
    (0..count)
        .map(|i| {
            packed
                .get(i / 8)
                .is_some_and(|byte| byte & (1 << (i % 8)) != 0)
        })
        .collect()
}

fn push_u16s(out: &mut Vec<u8>, values: &[u16]) {
    for value in values {
        out.extend_from_slice(&value.to_be_bytes());
    }
}

fn read_u16s(reader: &mut Reader<'_>, count: usize) -> Result<Vec<u16>, DecodeError> {
    (0..count).map(|_| reader.u16_be()).collect()
}

fn check_count(count: u16, max: u16, what: &'static str) -> Result<(), EncodeError> {
    if count == 0 || count > max {
        Err(EncodeError::CountOutOfRange {
            what,
            count: usize::from(count),
            max: usize::from(max),
        })
    } else {
        Ok(())
    }
}

fn count_of(len: usize, max: u16, what: &'static str) -> Result<u16, EncodeError> {
    match u16::try_from(len) {
        Ok(count) if count > 0 && count <= max => Ok(count),
        _ => Err(EncodeError::CountOutOfRange {
            what,
            count: len,
            max: usize::from(max),
        }),
    }
}

fn byte_len(len: usize) -> Result<u8, EncodeError> {
    u8::try_from(len).map_err(|_| EncodeError::TooLong { len })
}

fn decode_count(count: u16, max: u16, function: u8) -> Result<(), DecodeError> {
    if count == 0 || count > max {
        Err(DecodeError::InvalidValue {
            function,
            what: "quantity out of range",
        })
    } else {
        Ok(())
    }
}

fn decode_coil(raw: u16, function: u8) -> Result<bool, DecodeError> {
    match raw {
        COIL_ON => Ok(true),
        COIL_OFF => Ok(false),
        _ => Err(DecodeError::InvalidValue {
            function,
            what: "coil value is neither 0xFF00 nor 0x0000",
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bits_pack_lsb_first() {
        let bits = [true, false, true, true, false, false, false, false, true];
        assert_eq!(pack_bits(&bits), vec![0b0000_1101, 0b0000_0001]);
        assert_eq!(unpack_bits(&[0b0000_1101, 1], 9), bits);
        assert_eq!(unpack_bits(&[], 3), vec![false; 3]);
    }

    #[test]
    fn bad_counts_are_illegal_values() {
        let err = RequestPdu::decode(&[3, 0, 0, 0, 126]).unwrap_err();
        assert_eq!(err.exception(), Some(ExceptionCode::ILLEGAL_DATA_VALUE));
        let err = RequestPdu::decode(&[5, 0, 0, 0x12, 0x34]).unwrap_err();
        assert_eq!(err.exception(), Some(ExceptionCode::ILLEGAL_DATA_VALUE));
        let err = RequestPdu::decode(&[0x10, 0, 0, 0, 2, 3, 0, 1, 0]).unwrap_err();
        assert_eq!(err.exception(), Some(ExceptionCode::ILLEGAL_DATA_VALUE));
        let err = RequestPdu::decode(&[0x2B, 0, 0]).unwrap_err();
        assert_eq!(err.exception(), Some(ExceptionCode::ILLEGAL_FUNCTION));
    }

    #[test]
    fn encode_rejects_oversized_writes() {
        let pdu = RequestPdu::WriteMultipleRegisters {
            start: 0,
            values: vec![0; 124],
        };
        assert!(pdu.encode(&mut Vec::new()).is_err());
        let pdu = RequestPdu::ReadCoils { start: 0, count: 0 };
        assert!(pdu.encode(&mut Vec::new()).is_err());
    }

    #[test]
    fn write_multiple_coils_round_trip() {
        let pdu = RequestPdu::WriteMultipleCoils {
            start: 19,
            values: vec![true, false, true],
        };
        let mut bytes = Vec::new();
        pdu.encode(&mut bytes).unwrap();
        assert_eq!(bytes, vec![0x0F, 0, 19, 0, 3, 1, 0b101]);
        assert_eq!(RequestPdu::decode(&bytes).unwrap(), pdu);
    }
}
