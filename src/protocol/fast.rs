//! Fast Modbus: the vendor extension under function code 0x46 (0x60 in replies of old firmware).
//!
//! Every frame is `address | 0x46 | sub-command | body | CRC`. The layouts after the sub-command:
//!
//! | sub  | direction       | body                                                        |
//! |------|-----------------|-------------------------------------------------------------|
//! | 0x01 | master → 0xFD   | —  (start scan)                                             |
//! | 0x02 | master → 0xFD   | —  (continue scan)                                          |
//! | 0x03 | device → 0xFD   | serial(4, BE) modbus_address(1)  (scan reply)               |
//! | 0x04 | device → 0xFD   | —  (end of scan)                                            |
//! | 0x08 | master → 0xFD   | serial(4, BE) classic request PDU                           |
//! | 0x09 | device → 0xFD   | serial(4, BE) classic reply PDU (or exception)              |
//! | 0x10 | master → 0xFD   | min_address(1) max_data_len(1) ack_address(1) ack_flag(1)   |
//! | 0x11 | device → itself | flag(1) event_count(1) data_len(1) events(data_len)         |
//! | 0x12 | device → 0xFD   | —  (no events)                                              |
//! | 0x18 | master → device | list_len(1) { reg_type(1) start(2, BE) count(1) priority × count } |
//! | 0x18 | device → master | len(1) bitmasks: ceil(count/8) bytes per range, LSB first   |
//!
//! An event is `payload_len(1) type(1) id(2, BE) payload(payload_len, little-endian)`.

use super::pdu::{FrameLength, RequestPdu, ResponsePdu};
use super::wire::Reader;
use super::{DecodeError, EncodeError};

/// The address of Fast Modbus broadcast requests and of replies that come "from the bus".
pub const BROADCAST_ADDRESS: u8 = 0xFD;
/// The function code of the extension.
pub const FUNCTION: u8 = 0x46;
/// The deprecated function code that old firmware still puts in its replies.
pub const LEGACY_FUNCTION: u8 = 0x60;

pub const SCAN_START: u8 = 0x01;
pub const SCAN_CONTINUE: u8 = 0x02;
pub const SCAN_REPLY: u8 = 0x03;
pub const SCAN_END: u8 = 0x04;
pub const BY_SERIAL_REQUEST: u8 = 0x08;
pub const BY_SERIAL_REPLY: u8 = 0x09;
pub const EVENTS_REQUEST: u8 = 0x10;
pub const EVENTS_REPLY: u8 = 0x11;
pub const NO_EVENTS: u8 = 0x12;
pub const CONFIGURE_EVENTS: u8 = 0x18;

/// True for the function codes a Fast Modbus reply may carry.
pub fn is_fast_function(function: u8) -> bool {
    function == FUNCTION || function == LEGACY_FUNCTION
}

/// Register tables as the extension numbers them (event types 1–4 and 0x18 ranges).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RegisterType {
    Coil = 1,
    DiscreteInput = 2,
    Holding = 3,
    Input = 4,
}

impl RegisterType {
    pub fn from_wire(byte: u8) -> Option<Self> {
        match byte {
            1 => Some(Self::Coil),
            2 => Some(Self::DiscreteInput),
            3 => Some(Self::Holding),
            4 => Some(Self::Input),
            _ => None,
        }
    }

    pub fn to_wire(self) -> u8 {
        self as u8
    }

    /// Coils and discrete inputs are single bits; the others 16-bit registers.
    pub fn is_bit(self) -> bool {
        matches!(self, Self::Coil | Self::DiscreteInput)
    }

    /// Coils and holding registers can be written.
    pub fn is_writable(self) -> bool {
        matches!(self, Self::Coil | Self::Holding)
    }
}

/// Per-register event priority in a 0x18 request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum EventPriority {
    Disabled = 0,
    Low = 1,
    High = 2,
}

impl EventPriority {
    pub fn from_wire(byte: u8) -> Option<Self> {
        match byte {
            0 => Some(Self::Disabled),
            1 => Some(Self::Low),
            2 => Some(Self::High),
            _ => None,
        }
    }
}

/// One range of a 0x18 request: consecutive registers of one type, a priority each.
/// `source` is a register table, or [`EventSource::System`] for system events: wb-mqtt-serial
/// appends `0F 0000 01 00` (the reboot event, disabled) to every enable request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EventRange {
    pub source: EventSource,
    pub start: u16,
    /// One per register, 1..=255 of them.
    pub priorities: Vec<EventPriority>,
}

impl EventRange {
    /// A range of registers of one table.
    pub fn registers(
        register_type: RegisterType,
        start: u16,
        priorities: Vec<EventPriority>,
    ) -> Self {
        Self {
            source: EventSource::Register(register_type),
            start,
            priorities,
        }
    }

    /// Bytes of this range's bitmask in the reply.
    pub fn mask_len(&self) -> usize {
        self.priorities.len().div_ceil(8)
    }
}

/// The body of a 0x10 "does anyone have events?" request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EventPoll {
    /// Devices with a lower address stay silent this round (lets others be heard).
    pub min_address: u8,
    /// The most event data (the 0x11 `data_len`) a device may send in its reply.
    pub max_data_len: u8,
    /// The device whose last packet this request confirms (0: none).
    pub ack_address: u8,
    /// The flag of the packet being confirmed.
    pub ack_flag: u8,
}

/// What an event is about: a register table, a system event, or a type this crate does not know
/// (kept so a newer device's packet still parses).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum EventSource {
    Register(RegisterType),
    System,
    Other(u8),
}

/// Event type of system events (`id` 0: "I rebooted").
pub const SYSTEM_EVENT_TYPE: u8 = 15;
/// `id` of the system event that a device sends after every (re)start.
pub const REBOOT_EVENT_ID: u16 = 0;

impl EventSource {
    pub fn from_wire(byte: u8) -> Self {
        match (RegisterType::from_wire(byte), byte) {
            (Some(register_type), _) => Self::Register(register_type),
            (None, SYSTEM_EVENT_TYPE) => Self::System,
            (None, other) => Self::Other(other),
        }
    }

    /// In words, as the tools print it: `coil`, `discrete`, `holding`, `input`, `system`, or
    /// `type N`.
    pub fn name(self) -> String {
        match self {
            Self::Register(RegisterType::Coil) => "coil".to_owned(),
            Self::Register(RegisterType::DiscreteInput) => "discrete".to_owned(),
            Self::Register(RegisterType::Holding) => "holding".to_owned(),
            Self::Register(RegisterType::Input) => "input".to_owned(),
            Self::System => "system".to_owned(),
            Self::Other(byte) => format!("type {byte}"),
        }
    }

    pub fn to_wire(self) -> u8 {
        match self {
            Self::Register(register_type) => register_type.to_wire(),
            Self::System => SYSTEM_EVENT_TYPE,
            Self::Other(byte) => byte,
        }
    }
}

/// An event payload (a little-endian number) as the 16-bit registers that hold it, high word
/// first as registers hold them: `[0x2C, 0x01]` is `[0x012C]`, `[1, 0, 2, 0]` is `[2, 1]`. A bit
/// (one byte) is one word. Empty for an empty payload.
pub fn event_payload_words(payload: &[u8]) -> Vec<u16> {
    payload
        .chunks(2)
        .rev()
        .map(|pair| u16::from_le_bytes([pair[0], pair.get(1).copied().unwrap_or(0)]))
        .collect()
}

/// One event of a 0x11 packet.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Event {
    pub source: EventSource,
    /// The register address, or the system event's number.
    pub id: u16,
    /// The new value, little-endian: 1 byte for bits, 2 for a 16-bit register.
    pub payload: Vec<u8>,
}

impl Event {
    /// The reboot event: the device lost its event settings and must be set up again.
    pub fn reboot() -> Self {
        Self {
            source: EventSource::System,
            id: REBOOT_EVENT_ID,
            payload: Vec::new(),
        }
    }

    pub fn is_reboot(&self) -> bool {
        self.source == EventSource::System && self.id == REBOOT_EVENT_ID
    }

    /// The payload as an unsigned little-endian number (None when longer than 8 bytes).
    pub fn value(&self) -> Option<u64> {
        if self.payload.len() > 8 {
            return None;
        }
        Some(
            self.payload
                .iter()
                .rev()
                .fold(0u64, |acc, &byte| (acc << 8) | u64::from(byte)),
        )
    }

    /// Bytes this event takes inside a packet's event data.
    pub fn wire_len(&self) -> usize {
        4 + self.payload.len()
    }
}

/// The body of a 0x11 reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EventPacket {
    /// Toggles with every new packet; the master echoes it to confirm.
    pub flag: u8,
    /// What the device says it sent. When nothing fitted `max_data_len` this differs from
    /// `events.len()`: trust `events`.
    pub event_count: u8,
    pub events: Vec<Event>,
}

/// A Fast Modbus request from the master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FastRequest {
    ScanStart,
    ScanContinue,
    BySerial { serial: u32, pdu: RequestPdu },
    PollEvents(EventPoll),
    ConfigureEvents { ranges: Vec<EventRange> },
}

/// A Fast Modbus reply from a device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FastReply {
    ScanFound {
        serial: u32,
        modbus_address: u8,
    },
    ScanEnd,
    BySerial {
        serial: u32,
        pdu: ResponsePdu,
    },
    Events(EventPacket),
    NoEvents,
    /// The raw bitmask bytes; split them with [`split_event_masks`] using the request's ranges.
    EventsConfigured {
        masks: Vec<u8>,
    },
}

impl FastRequest {
    pub fn sub_command(&self) -> u8 {
        match self {
            Self::ScanStart => SCAN_START,
            Self::ScanContinue => SCAN_CONTINUE,
            Self::BySerial { .. } => BY_SERIAL_REQUEST,
            Self::PollEvents(_) => EVENTS_REQUEST,
            Self::ConfigureEvents { .. } => CONFIGURE_EVENTS,
        }
    }

    /// Appends sub-command and body (not address and function).
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        out.push(self.sub_command());
        match self {
            Self::ScanStart | Self::ScanContinue => {}
            Self::BySerial { serial, pdu } => {
                out.extend_from_slice(&serial.to_be_bytes());
                pdu.encode(out)?;
            }
            Self::PollEvents(poll) => {
                out.extend_from_slice(&[
                    poll.min_address,
                    poll.max_data_len,
                    poll.ack_address,
                    poll.ack_flag,
                ]);
            }
            Self::ConfigureEvents { ranges } => {
                let len_at = out.len();
                out.push(0);
                for range in ranges {
                    let count = u8::try_from(range.priorities.len())
                        .ok()
                        .filter(|&count| count > 0)
                        .ok_or(EncodeError::CountOutOfRange {
                            what: "registers in an event range",
                            count: range.priorities.len(),
                            max: 255,
                        })?;
                    out.push(range.source.to_wire());
                    out.extend_from_slice(&range.start.to_be_bytes());
                    out.push(count);
                    out.extend(range.priorities.iter().map(|&p| p as u8));
                }
                let list_len = out.len() - len_at - 1;
                out[len_at] =
                    u8::try_from(list_len).map_err(|_| EncodeError::TooLong { len: list_len })?;
            }
        }
        Ok(())
    }

    /// Decodes sub-command and body.
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut reader = Reader::new(bytes);
        let request = match reader.u8()? {
            SCAN_START => Self::ScanStart,
            SCAN_CONTINUE => Self::ScanContinue,
            BY_SERIAL_REQUEST => {
                let serial = reader.u32_be()?;
                Self::BySerial {
                    serial,
                    pdu: RequestPdu::decode(reader.rest())?,
                }
            }
            EVENTS_REQUEST => Self::PollEvents(EventPoll {
                min_address: reader.u8()?,
                max_data_len: reader.u8()?,
                ack_address: reader.u8()?,
                ack_flag: reader.u8()?,
            }),
            CONFIGURE_EVENTS => {
                let list_len = reader.u8()?;
                let mut list = Reader::new(reader.take(usize::from(list_len))?);
                let mut ranges = Vec::new();
                while !list.is_empty() {
                    ranges.push(decode_event_range(&mut list)?);
                }
                Self::ConfigureEvents { ranges }
            }
            other => return Err(DecodeError::UnknownSubCommand(other)),
        };
        reader.finish()?;
        Ok(request)
    }

    /// The length of `sub-command + body` that starts with `bytes`.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(&sub) = bytes.first() else {
            return FrameLength::NeedMore;
        };
        match sub {
            SCAN_START | SCAN_CONTINUE => FrameLength::Known(1),
            BY_SERIAL_REQUEST => {
                match RequestPdu::length_from_header(bytes.get(5..).unwrap_or(&[])) {
                    FrameLength::Known(pdu_len) => FrameLength::Known(5 + pdu_len),
                    other => other,
                }
            }
            EVENTS_REQUEST => FrameLength::Known(5),
            CONFIGURE_EVENTS => match bytes.get(1) {
                Some(&list_len) => FrameLength::Known(2 + usize::from(list_len)),
                None => FrameLength::NeedMore,
            },
            _ => FrameLength::Unknown,
        }
    }
}

fn decode_event_range(list: &mut Reader<'_>) -> Result<EventRange, DecodeError> {
    let invalid = |what| DecodeError::InvalidValue {
        function: FUNCTION,
        what,
    };
    let source = match EventSource::from_wire(list.u8()?) {
        EventSource::Other(_) => return Err(invalid("unknown register type in an event range")),
        known => known,
    };
    let start = list.u16_be()?;
    let count = list.u8()?;
    if count == 0 {
        return Err(invalid("empty event range"));
    }
    let priorities = list
        .take(usize::from(count))?
        .iter()
        .map(|&byte| {
            EventPriority::from_wire(byte).ok_or(invalid("event priority is not 0, 1 or 2"))
        })
        .collect::<Result<_, _>>()?;
    Ok(EventRange {
        source,
        start,
        priorities,
    })
}

impl FastReply {
    pub fn sub_command(&self) -> u8 {
        match self {
            Self::ScanFound { .. } => SCAN_REPLY,
            Self::ScanEnd => SCAN_END,
            Self::BySerial { .. } => BY_SERIAL_REPLY,
            Self::Events(_) => EVENTS_REPLY,
            Self::NoEvents => NO_EVENTS,
            Self::EventsConfigured { .. } => CONFIGURE_EVENTS,
        }
    }

    /// Appends sub-command and body.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        out.push(self.sub_command());
        match self {
            Self::ScanFound {
                serial,
                modbus_address,
            } => {
                out.extend_from_slice(&serial.to_be_bytes());
                out.push(*modbus_address);
            }
            Self::ScanEnd | Self::NoEvents => {}
            Self::BySerial { serial, pdu } => {
                out.extend_from_slice(&serial.to_be_bytes());
                pdu.encode(out)?;
            }
            Self::Events(packet) => {
                out.push(packet.flag);
                out.push(packet.event_count);
                let data_len: usize = packet.events.iter().map(Event::wire_len).sum();
                out.push(
                    u8::try_from(data_len).map_err(|_| EncodeError::TooLong { len: data_len })?,
                );
                for event in &packet.events {
                    let payload_len =
                        u8::try_from(event.payload.len()).map_err(|_| EncodeError::TooLong {
                            len: event.payload.len(),
                        })?;
                    out.push(payload_len);
                    out.push(event.source.to_wire());
                    out.extend_from_slice(&event.id.to_be_bytes());
                    out.extend_from_slice(&event.payload);
                }
            }
            Self::EventsConfigured { masks } => {
                out.push(
                    u8::try_from(masks.len())
                        .map_err(|_| EncodeError::TooLong { len: masks.len() })?,
                );
                out.extend_from_slice(masks);
            }
        }
        Ok(())
    }

    /// Decodes sub-command and body.
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut reader = Reader::new(bytes);
        let reply = match reader.u8()? {
            SCAN_REPLY => Self::ScanFound {
                serial: reader.u32_be()?,
                modbus_address: reader.u8()?,
            },
            SCAN_END => Self::ScanEnd,
            BY_SERIAL_REPLY => {
                let serial = reader.u32_be()?;
                Self::BySerial {
                    serial,
                    pdu: ResponsePdu::decode(reader.rest())?,
                }
            }
            EVENTS_REPLY => {
                let flag = reader.u8()?;
                let event_count = reader.u8()?;
                let data_len = reader.u8()?;
                let (events, _dropped) = decode_events(reader.take(usize::from(data_len))?);
                Self::Events(EventPacket {
                    flag,
                    event_count,
                    events,
                })
            }
            NO_EVENTS => Self::NoEvents,
            CONFIGURE_EVENTS => {
                let len = reader.u8()?;
                Self::EventsConfigured {
                    masks: reader.take(usize::from(len))?.to_vec(),
                }
            }
            other => return Err(DecodeError::UnknownSubCommand(other)),
        };
        reader.finish()?;
        Ok(reply)
    }

    /// The length of `sub-command + body` that starts with `bytes`.
    pub fn length_from_header(bytes: &[u8]) -> FrameLength {
        let Some(&sub) = bytes.first() else {
            return FrameLength::NeedMore;
        };
        let from_len_byte = |at: usize, header: usize| match bytes.get(at) {
            Some(&len) => FrameLength::Known(header + usize::from(len)),
            None => FrameLength::NeedMore,
        };
        match sub {
            SCAN_REPLY => FrameLength::Known(6),
            SCAN_END | NO_EVENTS => FrameLength::Known(1),
            BY_SERIAL_REPLY => match ResponsePdu::length_from_header(bytes.get(5..).unwrap_or(&[]))
            {
                FrameLength::Known(pdu_len) => FrameLength::Known(5 + pdu_len),
                other => other,
            },
            EVENTS_REPLY => from_len_byte(3, 4),
            CONFIGURE_EVENTS => from_len_byte(1, 2),
            _ => FrameLength::Unknown,
        }
    }
}

/// The events in a 0x11 packet's `data_len` bytes, and how many bytes at their end were dropped
/// (0: all of them were events). An event whose length overruns the data ends the list: the
/// events before it (each complete and within the data) are kept, it and the rest are dropped.
/// The packet still names its sender and flag, so it can be confirmed: wb-mqtt-serial
/// (`ModbusExt::ReadEvents`) takes both from the header before its events throw "invalid event
/// data size", and a packet never confirmed would be sent again for ever.
pub fn decode_events(data: &[u8]) -> (Vec<Event>, usize) {
    let mut reader = Reader::new(data);
    let mut events = Vec::new();
    let mut rest = data.len();
    while !reader.is_empty() {
        let Ok(event) = decode_event(&mut reader) else {
            return (events, rest);
        };
        rest = rest.saturating_sub(event.wire_len());
        events.push(event);
    }
    (events, 0)
}

fn decode_event(data: &mut Reader<'_>) -> Result<Event, DecodeError> {
    let payload_len = data.u8()?;
    let source = EventSource::from_wire(data.u8()?);
    let id = data.u16_be()?;
    let payload = data.take(usize::from(payload_len))?.to_vec();
    Ok(Event {
        source,
        id,
        payload,
    })
}

/// Splits the bitmask bytes of a 0x18 reply into one bitmask per requested range.
/// None when the reply's length does not fit the request.
pub fn split_event_masks(masks: &[u8], ranges: &[EventRange]) -> Option<Vec<Vec<u8>>> {
    let expected: usize = ranges.iter().map(EventRange::mask_len).sum();
    if expected != masks.len() {
        return None;
    }
    let mut rest = masks;
    let mut split = Vec::with_capacity(ranges.len());
    for range in ranges {
        let (mask, tail) = rest.split_at(range.mask_len());
        split.push(mask.to_vec());
        rest = tail;
    }
    Some(split)
}

/// For each register of each requested range: `(type, address, events enabled?)`, in request order.
/// None when the reply's length does not fit the request.
pub fn enabled_registers(
    masks: &[u8],
    ranges: &[EventRange],
) -> Option<Vec<(EventSource, u16, bool)>> {
    let split = split_event_masks(masks, ranges)?;
    let mut enabled = Vec::new();
    for (range, mask) in ranges.iter().zip(split) {
        for index in 0..range.priorities.len() {
            let bit = mask
                .get(index / 8)
                .is_some_and(|byte| byte & (1 << (index % 8)) != 0);
            let offset = u16::try_from(index).unwrap_or(u16::MAX);
            enabled.push((range.source, range.start.wrapping_add(offset), bit));
        }
    }
    Some(enabled)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{parse_hex, Request, RequestBody};

    #[test]
    fn event_payloads_become_register_words_high_word_first() {
        assert_eq!(event_payload_words(&[0x2C, 0x01]), [0x012C]);
        assert_eq!(event_payload_words(&[1, 0, 2, 0]), [2, 1]);
        assert_eq!(event_payload_words(&[1]), [1]);
        assert_eq!(event_payload_words(&[0x34, 0x12, 0x56]), [0x0056, 0x1234]);
        assert!(event_payload_words(&[]).is_empty());
    }

    /// An event whose length overruns the packet's data ends the list: the events before it are
    /// kept (each complete), it and what follows are dropped, and the packet's sender and flag
    /// survive so the next 0x10 confirms it.
    #[test]
    fn an_event_overrunning_the_data_drops_only_itself_and_what_follows() {
        let coil = Event {
            source: EventSource::Register(RegisterType::Coil),
            id: 0,
            payload: vec![1],
        };
        let data = |hex: &str| parse_hex(hex).unwrap();
        // payload_len 5, no byte left
        assert_eq!(
            decode_events(&data("01 01 0000 01 05 0F 0000")),
            (vec![coil.clone()], 4)
        );
        // a header cut short after the first event
        assert_eq!(
            decode_events(&data("01 01 0000 01 02 03")),
            (vec![coil.clone()], 2)
        );
        // the first event already overruns
        assert_eq!(decode_events(&data("09 03 0001 0102")), (Vec::new(), 6));
        assert_eq!(decode_events(&[]), (Vec::new(), 0));
        assert_eq!(
            decode_events(&data("01 01 0000 01 00 0F 0000")),
            (vec![coil.clone(), Event::reboot()], 0)
        );

        let body = data("11 01 02 09 01 01 0000 01 05 0F 0000");
        assert_eq!(
            FastReply::decode(&body),
            Ok(FastReply::Events(EventPacket {
                flag: 1,
                event_count: 2,
                events: vec![coil],
            }))
        );
        // The data itself must still be there: a frame shorter than its data_len is no packet.
        assert!(FastReply::decode(&data("11 01 02 09 01 01 0000 01")).is_err());
    }

    /// wb-mqtt-serial's enable request: holding 1 at low priority, then the reboot event disabled
    /// (TPollTest.SingleDeviceSingleRegisterWithEvents).
    #[test]
    fn enable_request_with_the_reboot_record_decodes() {
        let frame = parse_hex("01 46 18 0A 03 00 01 01 01 0F 00 00 01 00 28 7D").unwrap();
        let request = Request::decode(&frame).unwrap();
        let RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) = &request.body else {
            panic!("not a 0x18 request");
        };
        assert_eq!(
            ranges,
            &vec![
                EventRange::registers(RegisterType::Holding, 1, vec![EventPriority::Low]),
                EventRange {
                    source: EventSource::System,
                    start: 0,
                    priorities: vec![EventPriority::Disabled],
                },
            ]
        );
        assert_eq!(request.encode().unwrap(), frame);
        let unknown = parse_hex("01 46 18 05 07 00 01 01 01").unwrap();
        assert!(FastRequest::decode(&unknown[2..]).is_err());
    }
}
