//! What to read from a device: register spans, and how several are merged into one request.

use crate::protocol::pdu::{MAX_READ_BITS, MAX_READ_REGISTERS};
use crate::protocol::{RegisterType, RequestPdu};

/// Consecutive registers (or bits) of one type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RegisterSpan {
    pub register_type: RegisterType,
    pub start: u16,
    pub count: u16,
}

impl RegisterSpan {
    pub fn new(register_type: RegisterType, start: u16, count: u16) -> Self {
        Self {
            register_type,
            start,
            count,
        }
    }

    /// One past the last address (as u32: a span may end at 65535).
    pub fn end(&self) -> u32 {
        u32::from(self.start) + u32::from(self.count)
    }

    /// Whether one read request can ask for this span: 1 to 125 registers (2000 bits), not
    /// past the last address.
    pub fn fits_one_read(&self) -> bool {
        self.count >= 1 && self.count <= protocol_max(self.register_type) && self.end() <= 65_536
    }

    pub fn contains(&self, other: &RegisterSpan) -> bool {
        self.register_type == other.register_type
            && self.start <= other.start
            && other.end() <= self.end()
    }

    /// The read request for this span.
    pub fn read_request(&self) -> RequestPdu {
        let (start, count) = (self.start, self.count);
        match self.register_type {
            RegisterType::Coil => RequestPdu::ReadCoils { start, count },
            RegisterType::DiscreteInput => RequestPdu::ReadDiscreteInputs { start, count },
            RegisterType::Holding => RequestPdu::ReadHoldingRegisters { start, count },
            RegisterType::Input => RequestPdu::ReadInputRegisters { start, count },
        }
    }
}

/// Most registers (or bits) one read request may ask for.
pub fn protocol_max(register_type: RegisterType) -> u16 {
    if register_type.is_bit() {
        MAX_READ_BITS
    } else {
        MAX_READ_REGISTERS
    }
}

/// How far a device lets reads be merged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MergeLimits {
    /// Most registers per read; 0 means the protocol's maximum (125 registers, 2000 bits).
    pub max_read_registers: u16,
    /// Unconfigured registers allowed inside one read.
    pub max_register_hole: u16,
    /// Unconfigured bits allowed inside one read.
    pub max_bit_hole: u16,
    /// Fewest registers (or bits) per read: a shorter read asks for this many from its start,
    /// for devices that refuse shorter ones (wb-mqtt-serial's `min_read_registers`); 0 or 1:
    /// no minimum.
    pub min_read_registers: u16,
}

impl Default for MergeLimits {
    /// wb-mqtt-serial's defaults: one register per read, no holes.
    fn default() -> Self {
        Self {
            max_read_registers: 1,
            max_register_hole: 0,
            max_bit_hole: 0,
            min_read_registers: 1,
        }
    }
}

impl MergeLimits {
    /// `span` read as the device needs it: at least `min_read_registers` long, but never
    /// longer than one request may carry (125 registers, 2000 bits: the config takes any
    /// number, and a request that does not encode would fail the port) nor past the end of the
    /// address space. The words beyond the span are read and not used
    /// (`TModbusTest.MinReadRegisters`).
    pub fn at_least_min(&self, span: RegisterSpan) -> RegisterSpan {
        let room = u16::try_from(65_536 - u32::from(span.start)).unwrap_or(u16::MAX);
        let min = self
            .min_read_registers
            .min(room)
            .min(protocol_max(span.register_type));
        let count = span.count.max(min);
        RegisterSpan { count, ..span }
    }

    pub fn max_count(&self, register_type: RegisterType) -> u16 {
        let protocol_max = protocol_max(register_type);
        match self.max_read_registers {
            0 => protocol_max,
            limit => limit.min(protocol_max),
        }
    }

    fn max_hole(&self, register_type: RegisterType) -> u16 {
        if register_type.is_bit() {
            self.max_bit_hole
        } else {
            self.max_register_hole
        }
    }

    /// `candidate` extended to also cover `next`, if the limits allow. `next` must not start
    /// before `candidate`.
    pub fn extend(&self, candidate: RegisterSpan, next: RegisterSpan) -> Option<RegisterSpan> {
        if candidate.register_type != next.register_type || next.start < candidate.start {
            return None;
        }
        let gap = u32::from(next.start).saturating_sub(candidate.end());
        let end = candidate.end().max(next.end());
        let count = u16::try_from(end - u32::from(candidate.start)).ok()?;
        (gap <= u32::from(self.max_hole(candidate.register_type))
            && count <= self.max_count(candidate.register_type))
        .then_some(RegisterSpan { count, ..candidate })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn holding(start: u16, count: u16) -> RegisterSpan {
        RegisterSpan::new(RegisterType::Holding, start, count)
    }

    #[test]
    fn extends_adjacent_and_within_holes() {
        let limits = MergeLimits {
            max_read_registers: 10,
            max_register_hole: 2,
            max_bit_hole: 0,
            min_read_registers: 1,
        };
        assert_eq!(
            limits.extend(holding(0, 2), holding(2, 2)),
            Some(holding(0, 4))
        );
        assert_eq!(
            limits.extend(holding(0, 2), holding(4, 1)),
            Some(holding(0, 5))
        );
        assert_eq!(
            limits.extend(holding(0, 2), holding(5, 1)),
            None,
            "hole of 3 > 2"
        );
        assert_eq!(
            limits.extend(holding(0, 8), holding(8, 4)),
            None,
            "12 > 10 registers"
        );
        assert_eq!(
            limits.extend(holding(0, 2), holding(1, 4)),
            Some(holding(0, 5)),
            "overlap"
        );
        let other_type = RegisterSpan::new(RegisterType::Input, 2, 1);
        assert_eq!(limits.extend(holding(0, 2), other_type), None);
    }

    #[test]
    fn zero_means_protocol_maximum() {
        let limits = MergeLimits {
            max_read_registers: 0,
            ..MergeLimits::default()
        };
        assert_eq!(limits.max_count(RegisterType::Input), 125);
        assert_eq!(limits.max_count(RegisterType::Coil), 2000);
        assert_eq!(MergeLimits::default().max_count(RegisterType::Coil), 1);
    }

    #[test]
    fn a_span_may_end_at_the_last_address() {
        assert_eq!(RegisterSpan::new(RegisterType::Coil, 65535, 1).end(), 65536);
    }
}
