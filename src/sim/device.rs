//! One virtual device: its register tables (template registers plus the Wiren Board standard
//! ones), classic request execution with the right exceptions, and its Fast Modbus state (scan,
//! events). Pure: no IO, no clock.

use std::time::Duration;

use crate::protocol::pdu::{pack_bits, MAX_WRITE_BITS};
use crate::protocol::timing::STANDARD_BAUD_RATES;
use crate::protocol::{
    EventPacket, EventPoll, EventRange, EventUrgency, ExceptionCode, LineSettings, Parity,
    RegisterType, RequestPdu, ResponsePdu,
};

use super::events::EventState;
use super::faults::Faults;
use super::registers::RegisterMap;

/// Holding registers every Wiren Board device has (fast-modbus.md §5).
pub mod wb {
    /// Baud rate / 100.
    pub const BAUD: u16 = 110;
    /// 0 none, 1 odd, 2 even.
    pub const PARITY: u16 = 111;
    pub const STOP_BITS: u16 = 112;
    /// "Continuous read" switch that wb-mqtt-serial sets at start-up (0 or 1).
    pub const CONTINUOUS_READ: u16 = 114;
    pub const ADDRESS: u16 = 128;
    pub const MODEL: u16 = 200;
    pub const MODEL_LEN: u16 = 20;
    pub const FIRMWARE: u16 = 250;
    pub const FIRMWARE_LEN: u16 = 16;
    pub const SERIAL: u16 = 270;
    pub const SIGNATURE: u16 = 290;
    pub const SIGNATURE_LEN: u16 = 12;
}

/// Everything needed to build a device.
#[derive(Debug, Clone)]
pub struct DeviceSpec {
    pub name: String,
    /// Where its registers came from (for listings).
    pub template: String,
    pub serial: u32,
    pub address: u8,
    pub line: LineSettings,
    /// False: a classic device that ignores 0xFD and answers 0x46 with "illegal function".
    pub fast: bool,
    /// Time from the end of a request to the first byte of the reply.
    pub turnaround: Duration,
    pub model: String,
    pub firmware: String,
    pub signature: String,
    pub registers: RegisterMap,
}

/// A register that changed value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ValueChange {
    pub register_type: RegisterType,
    pub address: u16,
    pub old: u16,
    pub new: u16,
}

#[derive(Debug, Clone)]
pub struct VirtualDevice {
    pub name: String,
    pub template: String,
    pub serial: u32,
    pub fast: bool,
    pub turnaround: Duration,
    /// A slow device's pause in the middle of each addressed reply (zero: none): the first
    /// half of the frame, this silence, then the rest.
    pub reply_pause: Duration,
    /// When the master last configured its events (0x18), on the simulator's clock: when it has
    /// them all enabled, for the benchmark of event enabling.
    pub events_configured_at: Option<Duration>,
    /// False while unplugged: hears nothing, says nothing.
    pub plugged: bool,
    pub faults: Faults,
    registers: RegisterMap,
    events: EventState,
    /// Already reported in the current scan.
    scanned: bool,
    /// (Re)starts so far, the first power-on included.
    pub starts: u32,
}

impl VirtualDevice {
    pub fn new(spec: DeviceSpec) -> Self {
        let mut registers = spec.registers;
        let line = spec.line;
        let holding = RegisterType::Holding;
        registers.insert(holding, wb::BAUD, baud_register(line.baud), true);
        registers.insert(holding, wb::PARITY, parity_register(line.parity), true);
        registers.insert(holding, wb::STOP_BITS, u16::from(line.stop_bits), true);
        if registers.cell(holding, wb::CONTINUOUS_READ).is_none() {
            registers.insert(holding, wb::CONTINUOUS_READ, 0, true);
        }
        registers.insert(holding, wb::ADDRESS, u16::from(spec.address), true);
        write_string(&mut registers, wb::MODEL, wb::MODEL_LEN, &spec.model);
        write_string(
            &mut registers,
            wb::FIRMWARE,
            wb::FIRMWARE_LEN,
            &spec.firmware,
        );
        write_string(
            &mut registers,
            wb::SIGNATURE,
            wb::SIGNATURE_LEN,
            &spec.signature,
        );
        let [hi, lo] = [(spec.serial >> 16) as u16, spec.serial as u16];
        registers.insert(holding, wb::SERIAL, hi, false);
        registers.insert(holding, wb::SERIAL + 1, lo, false);
        // WB templates read the firmware version from input 250.. (channel "FW Version") and the
        // serial number from input 270..271 (channel "Serial"): when the template has those
        // registers, they hold them too.
        if registers.cell(RegisterType::Input, wb::FIRMWARE).is_some() {
            write_string_to(
                &mut registers,
                RegisterType::Input,
                wb::FIRMWARE,
                wb::FIRMWARE_LEN,
                &spec.firmware,
            );
        }
        if registers.cell(RegisterType::Input, wb::SERIAL).is_some() {
            registers.insert(RegisterType::Input, wb::SERIAL, hi, false);
            registers.insert(RegisterType::Input, wb::SERIAL + 1, lo, false);
        }
        Self {
            name: spec.name,
            template: spec.template,
            serial: spec.serial,
            fast: spec.fast,
            turnaround: spec.turnaround,
            reply_pause: Duration::ZERO,
            events_configured_at: None,
            plugged: true,
            faults: Faults::default(),
            registers,
            events: EventState::after_restart(),
            scanned: false,
            starts: 1,
        }
    }

    /// The Modbus address (holding 128).
    pub fn address(&self) -> u8 {
        self.registers
            .get(RegisterType::Holding, wb::ADDRESS)
            .and_then(|value| u8::try_from(value).ok())
            .unwrap_or(0)
    }

    /// The port settings (holding 110–112).
    pub fn line(&self) -> LineSettings {
        let get = |address| {
            self.registers
                .get(RegisterType::Holding, address)
                .unwrap_or(0)
        };
        let parity = match get(wb::PARITY) {
            1 => Parity::Odd,
            2 => Parity::Even,
            _ => Parity::None,
        };
        let stop_bits = if get(wb::STOP_BITS) == 1 { 1 } else { 2 };
        LineSettings::new(u32::from(get(wb::BAUD)) * 100, parity, stop_bits)
    }

    pub fn registers(&self) -> &RegisterMap {
        &self.registers
    }

    pub fn events(&self) -> &EventState {
        &self.events
    }

    /// Another unit of the same model takes this one's place (a replaced device): its serial
    /// number changes, in the scan and in the serial number registers.
    pub fn set_serial(&mut self, serial: u32) {
        self.serial = serial;
        let [hi, lo] = [(serial >> 16) as u16, serial as u16];
        for register_type in [RegisterType::Holding, RegisterType::Input] {
            if self.registers.cell(register_type, wb::SERIAL).is_some() {
                self.registers.insert(register_type, wb::SERIAL, hi, false);
                self.registers
                    .insert(register_type, wb::SERIAL + 1, lo, false);
            }
        }
    }

    /// A power cycle: event settings back at their defaults, the reboot event pending, the flag 0.
    /// Register values and port settings survive (they live in the device's flash or are inputs).
    pub fn reboot(&mut self) {
        self.events = EventState::after_restart();
        // Continuous read lasts until the device restarts.
        self.registers
            .set(RegisterType::Holding, wb::CONTINUOUS_READ, 0);
        self.scanned = false;
        self.starts += 1;
    }

    /// The values of a read, None when it is refused (exception 2). With continuous read on
    /// (holding 114 = 1, as a Wiren Board device has it), a read that covers at least one
    /// register it has answers the others as 0xFFFE (bits as 0) instead of refusing.
    fn read_range(&self, register_type: RegisterType, start: u16, count: u16) -> Option<Vec<u16>> {
        if let Some(values) = self.registers.read_range(register_type, start, count) {
            return Some(values);
        }
        if self
            .registers
            .get(RegisterType::Holding, wb::CONTINUOUS_READ)
            != Some(1)
        {
            return None;
        }
        let missing = match register_type {
            RegisterType::Coil | RegisterType::DiscreteInput => 0,
            _ => 0xFFFE,
        };
        let values: Vec<Option<u16>> = (0..count)
            .map(|offset| {
                start
                    .checked_add(offset)
                    .and_then(|address| self.registers.get(register_type, address))
            })
            .collect();
        values
            .iter()
            .any(Option::is_some)
            .then(|| values.iter().map(|v| v.unwrap_or(missing)).collect())
    }

    /// Executes a classic request and returns the reply PDU and the registers that changed.
    pub fn execute(&mut self, pdu: &RequestPdu) -> (ResponsePdu, Vec<ValueChange>) {
        let exception = |code| ResponsePdu::Exception {
            function: pdu.function(),
            code,
        };
        let (start, count) = pdu.range();
        match pdu {
            RequestPdu::ReadCoils { .. } | RequestPdu::ReadDiscreteInputs { .. } => {
                let register_type = if matches!(pdu, RequestPdu::ReadCoils { .. }) {
                    RegisterType::Coil
                } else {
                    RegisterType::DiscreteInput
                };
                let Some(values) = self.read_range(register_type, start, count) else {
                    return (exception(ExceptionCode::ILLEGAL_DATA_ADDRESS), Vec::new());
                };
                let bits: Vec<bool> = values.iter().map(|&v| v != 0).collect();
                let packed = pack_bits(&bits);
                let reply = if register_type == RegisterType::Coil {
                    ResponsePdu::ReadCoils { packed }
                } else {
                    ResponsePdu::ReadDiscreteInputs { packed }
                };
                (reply, Vec::new())
            }
            RequestPdu::ReadHoldingRegisters { .. } => {
                match self.read_range(RegisterType::Holding, start, count) {
                    Some(values) => (ResponsePdu::ReadHoldingRegisters { values }, Vec::new()),
                    None => (exception(ExceptionCode::ILLEGAL_DATA_ADDRESS), Vec::new()),
                }
            }
            RequestPdu::ReadInputRegisters { .. } => {
                match self.read_range(RegisterType::Input, start, count) {
                    Some(values) => (ResponsePdu::ReadInputRegisters { values }, Vec::new()),
                    None => (exception(ExceptionCode::ILLEGAL_DATA_ADDRESS), Vec::new()),
                }
            }
            RequestPdu::WriteSingleCoil { address, value } => {
                match self.write(RegisterType::Coil, *address, &[u16::from(*value)], true) {
                    Ok(changes) => (
                        ResponsePdu::WriteSingleCoil {
                            address: *address,
                            value: *value,
                        },
                        changes,
                    ),
                    Err(code) => (exception(code), Vec::new()),
                }
            }
            RequestPdu::WriteSingleRegister { address, value } => {
                match self.write(RegisterType::Holding, *address, &[*value], true) {
                    Ok(changes) => (
                        ResponsePdu::WriteSingleRegister {
                            address: *address,
                            value: *value,
                        },
                        changes,
                    ),
                    Err(code) => (exception(code), Vec::new()),
                }
            }
            RequestPdu::WriteMultipleCoils { values, .. } => {
                let values: Vec<u16> = values.iter().map(|&bit| u16::from(bit)).collect();
                match self.write(RegisterType::Coil, start, &values, true) {
                    Ok(changes) => (ResponsePdu::WriteMultipleCoils { start, count }, changes),
                    Err(code) => (exception(code), Vec::new()),
                }
            }
            RequestPdu::WriteMultipleRegisters { values, .. } => {
                match self.write(RegisterType::Holding, start, values, true) {
                    Ok(changes) => (
                        ResponsePdu::WriteMultipleRegisters { start, count },
                        changes,
                    ),
                    Err(code) => (exception(code), Vec::new()),
                }
            }
        }
    }

    /// Writes consecutive registers: all or nothing. `from_master` enforces read-only registers;
    /// the control interface may set any existing register (sensors, inputs).
    pub fn write(
        &mut self,
        register_type: RegisterType,
        start: u16,
        values: &[u16],
        from_master: bool,
    ) -> Result<Vec<ValueChange>, ExceptionCode> {
        if values.is_empty() || values.len() > usize::from(MAX_WRITE_BITS) {
            return Err(ExceptionCode::ILLEGAL_DATA_VALUE);
        }
        let mut targets = Vec::with_capacity(values.len());
        for (offset, &value) in values.iter().enumerate() {
            let address = u16::try_from(offset)
                .ok()
                .and_then(|offset| start.checked_add(offset))
                .ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
            let cell = self
                .registers
                .cell(register_type, address)
                .ok_or(ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
            if from_master && !cell.writable {
                return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS);
            }
            if register_type == RegisterType::Holding {
                check_standard_value(address, value)?;
            }
            targets.push((address, value));
        }
        let mut changes = Vec::new();
        for (address, value) in targets {
            let Some(old) = self.registers.set(register_type, address, value) else {
                continue;
            };
            let new = self.registers.get(register_type, address).unwrap_or(value);
            if old != new {
                changes.push(ValueChange {
                    register_type,
                    address,
                    old,
                    new,
                });
                if let Some(base) = self.registers.event_base_of(register_type, address) {
                    self.events.register_changed(register_type, base);
                }
            }
        }
        Ok(changes)
    }

    /// Handles a 0x18 request; returns the bitmask bytes of the reply.
    pub fn configure_events(&mut self, ranges: &[EventRange]) -> Vec<u8> {
        self.events.configure(ranges, &self.registers)
    }

    pub fn event_urgency(&self) -> EventUrgency {
        self.events.urgency()
    }

    /// The acknowledgement part of a 0x10 request.
    pub fn acknowledge_events(&mut self, poll: &EventPoll) {
        let address = self.address();
        self.events.acknowledge(poll, address, &self.registers);
    }

    /// The packet this device sends after winning an event round.
    pub fn event_packet(&mut self, max_data_len: u8) -> EventPacket {
        self.events.next_packet(max_data_len, &self.registers)
    }

    pub fn is_scanned(&self) -> bool {
        self.scanned
    }

    pub fn set_scanned(&mut self, scanned: bool) {
        self.scanned = scanned;
    }
}

/// Port settings and address registers accept only what a real device accepts.
fn check_standard_value(address: u16, value: u16) -> Result<(), ExceptionCode> {
    let valid = match address {
        wb::ADDRESS => (1..=247).contains(&value),
        wb::BAUD => STANDARD_BAUD_RATES.contains(&(u32::from(value) * 100)),
        wb::PARITY => value <= 2,
        wb::STOP_BITS => (1..=2).contains(&value),
        wb::CONTINUOUS_READ => value <= 1,
        _ => true,
    };
    if valid {
        Ok(())
    } else {
        Err(ExceptionCode::ILLEGAL_DATA_VALUE)
    }
}

fn baud_register(baud: u32) -> u16 {
    u16::try_from(baud / 100).unwrap_or(u16::MAX)
}

fn parity_register(parity: Parity) -> u16 {
    match parity {
        Parity::None => 0,
        Parity::Odd => 1,
        Parity::Even => 2,
    }
}

/// One ASCII character per register, zero padded (read-only).
fn write_string(registers: &mut RegisterMap, start: u16, len: u16, text: &str) {
    write_string_to(registers, RegisterType::Holding, start, len, text);
}

fn write_string_to(
    registers: &mut RegisterMap,
    register_type: RegisterType,
    start: u16,
    len: u16,
    text: &str,
) {
    let mut bytes = text.bytes();
    for offset in 0..len {
        let value = bytes.next().map_or(0, u16::from);
        registers.insert(register_type, start + offset, value, false);
    }
}
