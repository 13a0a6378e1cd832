//! The inputs of a port's scheduler: the port's timing settings and, per device, what to read,
//! what to write at start-up, and which registers may send events. Built from the config and
//! device templates; expressed in registers so that the bus logic knows nothing of channels.

use std::time::Duration;

use super::health::HealthPolicy;
use super::read_plan::{MergeLimits, RegisterSpan};
use crate::protocol::{LineSettings, RegisterType, RequestPdu};

/// Timing of one bus.
#[derive(Debug, Clone, PartialEq)]
pub struct PortSettings {
    /// For wire-time estimates and arbitration timeouts. TCP gateways are modelled at their
    /// serial side's settings (9600 8N2 when unknown, as wb-mqtt-serial does).
    pub line: LineSettings,
    /// The site-wide switch: when false, no 0xFD or 0x46 frame ever leaves the port.
    pub fast_modbus: bool,
    /// Longest time between two event requests.
    pub event_interval: Duration,
    /// Added to arbitration timeouts: USB adapters deliver bytes late.
    pub latency_margin: Duration,
    /// Expected device turnaround, for wire-time estimates.
    pub turnaround: Duration,
    /// Silence kept on the bus before a request to these devices (slow or picky ones: their
    /// `guard_interval_us`), not before other devices' requests or broadcasts, as
    /// wb-mqtt-serial keeps it (`TModbusTest.GuardInterval`).
    pub guard_intervals: GuardIntervals,
    /// Reads of channels without a read period, at most this many a second (the config's
    /// `rate_limit`, this port's share); `None`: as many as the bus carries.
    pub low_priority_reads_per_second: Option<u32>,
    /// Added to every device's configured response timeout: [`TCP_RESPONSE_LAG`] on a TCP
    /// gateway, nothing on a serial line. The scheduler adds it to the floor of each device's
    /// response timeout, so its late window, hold-offs and estimates include it.
    pub response_lag: Duration,
}

/// What a TCP gateway adds to a device's response timeout, as wb-mqtt-serial does
/// (`ResponseTCPLag`, src/port/tcp_port.cpp): the network and the gateway's own turnaround.
/// Configs written for wb-mqtt-serial set `response_timeout_ms` with it silently added.
pub const TCP_RESPONSE_LAG: Duration = Duration::from_millis(500);

impl PortSettings {
    pub fn for_line(line: LineSettings) -> Self {
        Self {
            line,
            fast_modbus: true,
            event_interval: line.event_poll_interval(),
            latency_margin: Duration::from_millis(5),
            turnaround: Duration::from_millis(1),
            guard_intervals: GuardIntervals::default(),
            low_priority_reads_per_second: None,
            response_lag: Duration::ZERO,
        }
    }
}

/// The devices of a port that want silence on the bus before their requests.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GuardIntervals(pub Vec<(u8, Duration)>);

impl GuardIntervals {
    /// The silence to keep before a request to `address` (none for broadcasts).
    pub fn before(&self, address: u8) -> Duration {
        self.0
            .iter()
            .find(|(device, _)| *device == address)
            .map(|(_, guard)| *guard)
            .unwrap_or_default()
    }
}

/// How a channel's registers are kept up to date.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EventMode {
    /// Read periodically; no events.
    Polled,
    /// Events only, once enabled: not polled (one slow keep-alive read per device).
    Sporadic,
    /// Events and polling both.
    SemiSporadic,
}

/// One channel's registers to keep up to date.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedRead {
    pub span: RegisterSpan,
    /// Read at this period with high priority; None: round-robin in the remaining time, and at
    /// least in turns with the periodic reads once they have had the bus 1 s longer.
    pub period: Option<Duration>,
    /// A round-robin read (no `period`) is read again no sooner than this after it was last
    /// read: wb-mqtt-serial's `read_rate_limit_ms` (`poll_interval` in old configs).
    pub rate_limit: Option<Duration>,
    pub events: EventMode,
    /// The oldest firmware that has these registers (a template's `fw`, on a device whose
    /// firmware is read): not read until the device's firmware is known
    /// ([`super::PortScheduler::firmware_known`]), never on older firmware.
    pub min_firmware: Option<String>,
}

/// Registers written whenever the device (re)connects or reboots, in the plan's order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SetupWrite {
    /// Coil (0x05, or 0x0F for several) or Holding (0x06, or 0x10 for several); the port plan
    /// holds no other.
    pub register_type: RegisterType,
    pub address: u16,
    /// One value per register (0/1 for coils).
    pub values: Vec<u16>,
    /// Use 0x0F/0x10 even for one value (`holding_multi`), as [`RegisterWrite::force_multiple`].
    pub force_multiple: bool,
    /// Per value, the bits the setup does not define (empty: none; always none for coils):
    /// taken from what was last read or written of the register, when there is such
    /// ([`crate::device::SetupItem`]'s `kept_bits`).
    pub kept_bits: Vec<u16>,
}

impl SetupWrite {
    /// The words to write: `values`, with the kept bits from `last_read` (per register, None
    /// where it has been neither read nor written).
    pub fn words_over(&self, last_read: impl Fn(u16) -> Option<u16>) -> Vec<u16> {
        self.values
            .iter()
            .enumerate()
            .map(|(i, &value)| {
                let kept = self.kept_bits.get(i).copied().unwrap_or(0);
                let address = self.address.wrapping_add(i as u16);
                match last_read(address) {
                    Some(read) if kept != 0 => (read & kept) | (value & !kept),
                    _ => value,
                }
            })
            .collect()
    }
}

/// One device on the bus.
#[derive(Debug, Clone, PartialEq)]
pub struct DevicePlan {
    /// For logs.
    pub name: String,
    pub address: u8,
    /// The configured response timeout (the larger of port and device, 500 ms when neither sets
    /// one); the line's allowance is added on top and the learned response time may raise it.
    pub response_timeout: Duration,
    pub merge: MergeLimits,
    pub health: HealthPolicy,
    pub reads: Vec<PlannedRead>,
    pub setup: Vec<SetupWrite>,
    /// The template sets `enable_wb_continuous_read`: holding 114 is set to 1 before the setup
    /// writes at every (re)connection, and while it holds reads may span up to 10 registers
    /// (80 bits) the device lacks, which it answers as 0xFFFE instead of refusing the read. So
    /// a register is read on its own until it has answered once, as wb-mqtt-serial reads a
    /// register of unknown availability: merged with others, one the device lacks would pass
    /// for a value.
    pub continuous_read: bool,
    /// How long a write that cannot go (no answer, the port unavailable) keeps being tried
    /// before it is given up (`max_write_fail_time_s`, 600 s by default as in wb-mqtt-serial).
    pub write_retry_time: Duration,
}

/// A write requested from outside (MQTT, RPC). The latest value per register wins.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RegisterWrite {
    /// Index into the port's devices.
    pub device: usize,
    /// Coil or Holding.
    pub register_type: RegisterType,
    pub address: u16,
    /// One value per register (0/1 for coils).
    pub values: Vec<u16>,
    /// Use 0x0F/0x10 even for one value (`holding_multi`; some devices accept nothing else).
    pub force_multiple: bool,
    /// A value of several registers written with one 0x06 per register (`holding_single`),
    /// the last register first, as wb-mqtt-serial writes it (`TModbusTest.HoldingSingleMulti`:
    /// a device that acts on a write to the first register finds the others in place). One
    /// write all the same: done (and its value published) once every register has taken its
    /// word; a register that refuses ends it, and the registers before it are not written.
    pub one_by_one: bool,
    /// The bits of each value word the write defines, one mask per word, for a bit field (a
    /// field of some bits of its registers): when it is sent, the other bits are those of the
    /// newest word of the register the scheduler has seen since it was queued (read, evented
    /// or written), as the device holds them then. Empty: the whole words (every other write).
    pub defined: Vec<u16>,
}

impl RegisterWrite {
    /// How many requests the write takes: one per register when [`Self::one_by_one`].
    pub fn request_count(&self) -> usize {
        if self.one_by_one {
            self.values.len()
        } else {
            1
        }
    }

    /// The `sent`th request of the write (from 0, see [`Self::request_count`]): its first
    /// register and its words, for [`write_pdu`]. One by one, the last register goes first.
    pub fn request(&self, sent: usize) -> (u16, &[u16]) {
        if !self.one_by_one {
            return (self.address, &self.values);
        }
        let index = self.values.len().saturating_sub(sent + 1);
        let address = self
            .address
            .wrapping_add(u16::try_from(index).unwrap_or(u16::MAX));
        (address, self.values.get(index..=index).unwrap_or(&[]))
    }

    /// The bits of value word `index` the write defines (none beyond its words).
    pub(crate) fn defined_bits(&self, index: usize) -> u16 {
        match self.defined.get(index) {
            Some(&mask) => mask,
            None if self.defined.is_empty() && index < self.values.len() => u16::MAX,
            None => 0,
        }
    }
}

/// The request that writes `values` from `address`: 0x05 or 0x06 for one value (unless
/// `force_multiple`), 0x0F or 0x10 otherwise. May not encode (no values, or more than one
/// request carries): see [`write_encodes`].
pub(crate) fn write_pdu(
    register_type: RegisterType,
    address: u16,
    values: &[u16],
    force_multiple: bool,
) -> RequestPdu {
    match (register_type, values) {
        (RegisterType::Coil, [value]) if !force_multiple => RequestPdu::WriteSingleCoil {
            address,
            value: *value != 0,
        },
        (RegisterType::Coil, values) => RequestPdu::WriteMultipleCoils {
            start: address,
            values: values.iter().map(|&v| v != 0).collect(),
        },
        (_, [value]) if !force_multiple => RequestPdu::WriteSingleRegister {
            address,
            value: *value,
        },
        (_, values) => RequestPdu::WriteMultipleRegisters {
            start: address,
            values: values.to_vec(),
        },
    }
}

/// Whether a write of `values` at `address` can go out: to a coil or holding register (the
/// only writable tables), in a request that encodes (some values, no more than one request
/// carries). A request that does not encode would fail the port: its driver takes an encode
/// error for a broken port.
pub(crate) fn write_encodes(
    register_type: RegisterType,
    address: u16,
    values: &[u16],
    force_multiple: bool,
) -> bool {
    matches!(register_type, RegisterType::Coil | RegisterType::Holding)
        && write_pdu(register_type, address, values, force_multiple)
            .encode(&mut Vec::new())
            .is_ok()
}
