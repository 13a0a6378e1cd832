//! The register tables of one virtual device: per table, address → value, whether the master may
//! write it, and which registers can send Fast Modbus events.

use std::collections::{BTreeMap, BTreeSet};

use crate::protocol::RegisterType;

/// One register (or one bit: coils and discrete inputs hold 0 or 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegisterCell {
    pub value: u16,
    /// False for registers the master may only read (input and discrete tables never reach here:
    /// no function writes them).
    pub writable: bool,
}

/// All four tables of a device, plus the registers that can send events.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RegisterMap {
    tables: [BTreeMap<u16, RegisterCell>; 4],
    /// Base address of an event-capable value → its width in registers (1 for bits and 16-bit
    /// registers, 2 for 32-bit values, 4 for 64-bit ones). The event payload is the whole value.
    event_sources: BTreeMap<(RegisterType, u16), u8>,
    /// Event-capable values whose registers hold the least significant word first
    /// (`word_order` little_endian). The payload is the value's number all the same.
    low_word_first: BTreeSet<(RegisterType, u16)>,
}

fn table_index(register_type: RegisterType) -> usize {
    match register_type {
        RegisterType::Coil => 0,
        RegisterType::DiscreteInput => 1,
        RegisterType::Holding => 2,
        RegisterType::Input => 3,
    }
}

/// All register types, in wire order.
pub const REGISTER_TYPES: [RegisterType; 4] = [
    RegisterType::Coil,
    RegisterType::DiscreteInput,
    RegisterType::Holding,
    RegisterType::Input,
];

impl RegisterMap {
    pub fn new() -> Self {
        Self::default()
    }

    fn table(&self, register_type: RegisterType) -> Option<&BTreeMap<u16, RegisterCell>> {
        self.tables.get(table_index(register_type))
    }

    fn table_mut(
        &mut self,
        register_type: RegisterType,
    ) -> Option<&mut BTreeMap<u16, RegisterCell>> {
        self.tables.get_mut(table_index(register_type))
    }

    /// Makes `count` registers from `start` exist (value 0 unless they already exist). A register
    /// defined writable by anyone stays writable. Addresses past 65535 are ignored.
    pub fn define(&mut self, register_type: RegisterType, start: u16, count: u16, writable: bool) {
        let writable =
            writable && matches!(register_type, RegisterType::Coil | RegisterType::Holding);
        let Some(table) = self.table_mut(register_type) else {
            return;
        };
        for offset in 0..count {
            let Some(address) = start.checked_add(offset) else {
                break;
            };
            let cell = table
                .entry(address)
                .or_insert(RegisterCell { value: 0, writable });
            cell.writable |= writable;
        }
    }

    /// Defines one register with a value, replacing whatever was there.
    pub fn insert(
        &mut self,
        register_type: RegisterType,
        address: u16,
        value: u16,
        writable: bool,
    ) {
        let writable =
            writable && matches!(register_type, RegisterType::Coil | RegisterType::Holding);
        let value = normalize(register_type, value);
        if let Some(table) = self.table_mut(register_type) {
            table.insert(address, RegisterCell { value, writable });
        }
    }

    /// Marks the value of `width` registers at `base` as able to send events.
    pub fn mark_event_source(&mut self, register_type: RegisterType, base: u16, width: u8) {
        let width = if register_type.is_bit() {
            1
        } else {
            width.clamp(1, 4)
        };
        self.event_sources.insert((register_type, base), width);
    }

    /// The event-capable value at `base` keeps its least significant word first: its event
    /// payload is still the value (fast-modbus.md §6: "payload = the register's new value",
    /// little-endian), so its words are taken in that order.
    pub fn mark_low_word_first(&mut self, register_type: RegisterType, base: u16) {
        self.low_word_first.insert((register_type, base));
    }

    pub fn cell(&self, register_type: RegisterType, address: u16) -> Option<RegisterCell> {
        self.table(register_type)?.get(&address).copied()
    }

    pub fn get(&self, register_type: RegisterType, address: u16) -> Option<u16> {
        self.cell(register_type, address).map(|cell| cell.value)
    }

    /// Sets an existing register; returns the old value, None when it does not exist.
    pub fn set(&mut self, register_type: RegisterType, address: u16, value: u16) -> Option<u16> {
        let value = normalize(register_type, value);
        let cell = self.table_mut(register_type)?.get_mut(&address)?;
        Some(std::mem::replace(&mut cell.value, value))
    }

    /// `count` values from `start`; None when any of them does not exist.
    pub fn read_range(
        &self,
        register_type: RegisterType,
        start: u16,
        count: u16,
    ) -> Option<Vec<u16>> {
        (0..count)
            .map(|offset| self.get(register_type, start.checked_add(offset)?))
            .collect()
    }

    /// Width in registers when `address` is the base of an event-capable value.
    pub fn event_width(&self, register_type: RegisterType, address: u16) -> Option<u8> {
        self.event_sources.get(&(register_type, address)).copied()
    }

    /// The base address of the event-capable value that `address` is part of.
    pub fn event_base_of(&self, register_type: RegisterType, address: u16) -> Option<u16> {
        self.event_sources
            .range((register_type, address.saturating_sub(3))..=(register_type, address))
            .rev()
            .find(|(&(_, base), &width)| u32::from(address) < u32::from(base) + u32::from(width))
            .map(|(&(_, base), _)| base)
    }

    /// The event payload of the value at `base`: 1 byte for bits; for registers the value
    /// assembled from its registers in the value's word order (most significant word first
    /// unless marked by [`Self::mark_low_word_first`]), sent little-endian.
    pub fn event_payload(&self, register_type: RegisterType, base: u16) -> Vec<u8> {
        let width = self.event_width(register_type, base).unwrap_or(1);
        if register_type.is_bit() {
            return vec![u8::from(self.get(register_type, base).unwrap_or(0) != 0)];
        }
        let mut offsets: Vec<u16> = (0..u16::from(width)).collect();
        if self.low_word_first.contains(&(register_type, base)) {
            offsets.reverse();
        }
        let value = offsets.into_iter().fold(0u64, |acc, offset| {
            let word = base
                .checked_add(offset)
                .and_then(|address| self.get(register_type, address))
                .unwrap_or(0);
            (acc << 16) | u64::from(word)
        });
        let bytes = value.to_le_bytes();
        bytes
            .get(..usize::from(width) * 2)
            .unwrap_or(&bytes)
            .to_vec()
    }

    /// Registers of one table in address order.
    pub fn iter(
        &self,
        register_type: RegisterType,
    ) -> impl Iterator<Item = (u16, RegisterCell)> + '_ {
        self.table(register_type)
            .into_iter()
            .flat_map(|table| table.iter().map(|(&address, &cell)| (address, cell)))
    }

    /// Number of event-capable values.
    pub fn event_source_count(&self) -> usize {
        self.event_sources.len()
    }
}

/// Bits hold 0 or 1.
fn normalize(register_type: RegisterType, value: u16) -> u16 {
    if register_type.is_bit() {
        u16::from(value != 0)
    } else {
        value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wide_event_values_are_sent_little_endian() {
        let mut map = RegisterMap::new();
        map.define(RegisterType::Input, 60, 2, false);
        map.mark_event_source(RegisterType::Input, 60, 2);
        map.set(RegisterType::Input, 60, 0x0001);
        map.set(RegisterType::Input, 61, 0x0203);
        assert_eq!(map.event_base_of(RegisterType::Input, 61), Some(60));
        assert_eq!(map.event_base_of(RegisterType::Input, 62), None);
        assert_eq!(
            map.event_payload(RegisterType::Input, 60),
            vec![0x03, 0x02, 0x01, 0x00]
        );
        map.define(RegisterType::Coil, 0, 1, true);
        map.set(RegisterType::Coil, 0, 7);
        assert_eq!(map.get(RegisterType::Coil, 0), Some(1));
    }

    /// A u32 kept least significant word first (registers 70 = 0x0006, 71 = 0x0004: the value
    /// 0x0004_0006) sends its value, little-endian (fast-modbus.md §6), not its registers
    /// taken most significant first (which made 0x0006_0004 of it).
    #[test]
    fn a_wide_event_value_kept_low_word_first_is_sent_as_its_value() {
        let mut map = RegisterMap::new();
        map.define(RegisterType::Input, 70, 2, false);
        map.mark_event_source(RegisterType::Input, 70, 2);
        map.mark_low_word_first(RegisterType::Input, 70);
        map.set(RegisterType::Input, 70, 0x0006);
        map.set(RegisterType::Input, 71, 0x0004);
        assert_eq!(
            map.event_payload(RegisterType::Input, 70),
            vec![0x06, 0x00, 0x04, 0x00]
        );
    }

    #[test]
    fn ranges_with_holes_do_not_read() {
        let mut map = RegisterMap::new();
        map.define(RegisterType::Holding, 0, 2, true);
        map.define(RegisterType::Holding, 3, 1, true);
        assert_eq!(
            map.read_range(RegisterType::Holding, 0, 2),
            Some(vec![0, 0])
        );
        assert_eq!(map.read_range(RegisterType::Holding, 0, 4), None);
        assert_eq!(map.read_range(RegisterType::Holding, 65535, 2), None);
        map.define(RegisterType::Input, 65534, 5, true);
        assert_eq!(
            map.cell(RegisterType::Input, 65535).map(|c| c.writable),
            Some(false)
        );
    }
}
