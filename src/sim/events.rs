//! The Fast Modbus event state of one device: which registers send events and at what priority,
//! the changes not yet confirmed by the master, the packet flag, and the reboot event.
//!
//! Semantics (fast-modbus.md §6): a device keeps every change of an enabled register until the
//! master confirms the packet that carried it, by echoing the device's address and the packet's
//! flag in a later 0x10 request. A packet that is not confirmed is sent again, with any newer
//! events added, under the same flag; after a confirmation the flag toggles. Payloads are the
//! register's value at the time of sending (devices keep no queue). After every (re)start all
//! settings are back at their defaults: everything off except the low-priority reboot event,
//! which is pending, and the flag is 0.

use std::collections::{BTreeMap, BTreeSet};

use crate::protocol::fast::REBOOT_EVENT_ID;
use crate::protocol::{
    Event, EventPacket, EventPoll, EventPriority, EventRange, EventSource, EventUrgency,
    RegisterType,
};

use super::registers::RegisterMap;

/// What a pending event is about. Register events sort before the reboot event, as in the
/// seed's traces (coil 0, then "rebooted").
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum EventKey {
    Register(RegisterType, u16),
    Reboot,
}

/// Longest event data that fits a 256-byte frame: address, 0x46, 0x11, flag, count, data_len, CRC.
pub const MAX_EVENT_DATA: usize = 256 - 8;

#[derive(Debug, Clone, PartialEq, Eq)]
struct SentPacket {
    flag: u8,
    events: Vec<(EventKey, Vec<u8>)>,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EventState {
    enabled: BTreeMap<(RegisterType, u16), EventPriority>,
    reboot_priority: EventPriority,
    unconfirmed: BTreeSet<EventKey>,
    /// The flag of the next new packet.
    flag: u8,
    /// The last packet sent and not confirmed yet.
    sent: Option<SentPacket>,
}

impl Default for EventState {
    fn default() -> Self {
        Self::after_restart()
    }
}

impl EventState {
    /// The state after power-on or a reboot.
    pub fn after_restart() -> Self {
        Self {
            enabled: BTreeMap::new(),
            reboot_priority: EventPriority::Low,
            unconfirmed: BTreeSet::from([EventKey::Reboot]),
            flag: 0,
            sent: None,
        }
    }

    /// A register value changed: remember it when its events are enabled.
    pub fn register_changed(&mut self, register_type: RegisterType, base: u16) {
        if self.enabled.contains_key(&(register_type, base)) {
            self.unconfirmed
                .insert(EventKey::Register(register_type, base));
        }
    }

    /// Applies a 0x18 request; returns the reply's bitmask bytes (a bit per register, LSB first,
    /// each range starting a new byte; 1 = events enabled).
    pub fn configure(&mut self, ranges: &[EventRange], registers: &RegisterMap) -> Vec<u8> {
        let mut masks = Vec::new();
        for range in ranges {
            let mut mask = vec![0u8; range.mask_len()];
            for (index, &priority) in range.priorities.iter().enumerate() {
                let Some(address) = u16::try_from(index)
                    .ok()
                    .and_then(|offset| range.start.checked_add(offset))
                else {
                    continue;
                };
                if self.set_priority(range.source, address, priority, registers) {
                    if let Some(byte) = mask.get_mut(index / 8) {
                        *byte |= 1 << (index % 8);
                    }
                }
            }
            masks.extend(mask);
        }
        masks
    }

    /// True when events of this register are now enabled.
    fn set_priority(
        &mut self,
        source: EventSource,
        address: u16,
        priority: EventPriority,
        registers: &RegisterMap,
    ) -> bool {
        let enable = priority != EventPriority::Disabled;
        match source {
            EventSource::System if address == REBOOT_EVENT_ID => {
                self.reboot_priority = priority;
                if !enable {
                    self.unconfirmed.remove(&EventKey::Reboot);
                }
                enable
            }
            EventSource::Register(register_type)
                if registers.event_width(register_type, address).is_some() && enable =>
            {
                self.enabled.insert((register_type, address), priority);
                true
            }
            EventSource::Register(register_type) => {
                self.enabled.remove(&(register_type, address));
                self.unconfirmed
                    .remove(&EventKey::Register(register_type, address));
                false
            }
            EventSource::System | EventSource::Other(_) => false,
        }
    }

    fn priority_of(&self, key: EventKey) -> EventPriority {
        match key {
            EventKey::Register(register_type, address) => self
                .enabled
                .get(&(register_type, address))
                .copied()
                .unwrap_or(EventPriority::Disabled),
            EventKey::Reboot => self.reboot_priority,
        }
    }

    /// The marker this device arbitrates with. Events stay unconfirmed (and counted here) while
    /// a packet carrying them waits for its confirmation.
    pub fn urgency(&self) -> EventUrgency {
        if self.unconfirmed.is_empty() {
            EventUrgency::Nothing
        } else if self
            .unconfirmed
            .iter()
            .any(|&key| self.priority_of(key) == EventPriority::High)
        {
            EventUrgency::High
        } else {
            EventUrgency::Low
        }
    }

    /// Handles the acknowledgement part of a 0x10 request heard by the device at `address`.
    pub fn acknowledge(&mut self, poll: &EventPoll, address: u8, registers: &RegisterMap) {
        if poll.ack_address != address {
            return;
        }
        let Some(sent) = self.sent.take_if(|sent| sent.flag == poll.ack_flag) else {
            return;
        };
        for (key, payload) in sent.events {
            let unchanged = match key {
                EventKey::Register(register_type, base) => {
                    registers.event_payload(register_type, base) == payload
                }
                EventKey::Reboot => true,
            };
            if unchanged {
                self.unconfirmed.remove(&key);
            }
        }
        self.flag ^= 1;
    }

    /// The 0x11 packet the device sends when it wins: the unconfirmed events that fit
    /// `max_data_len` (all of them counted when not even one fits), under the flag of the packet
    /// that is still unconfirmed, if any.
    pub fn next_packet(&mut self, max_data_len: u8, registers: &RegisterMap) -> EventPacket {
        let flag = self.sent.as_ref().map_or(self.flag, |sent| sent.flag);
        let keys = &self.unconfirmed;
        let budget = usize::from(max_data_len).min(MAX_EVENT_DATA);
        let mut used = 0;
        let mut events = Vec::new();
        let mut sent_events = Vec::new();
        for &key in keys {
            let event = make_event(key, registers);
            if used + event.wire_len() > budget {
                break;
            }
            used += event.wire_len();
            sent_events.push((key, event.payload.clone()));
            events.push(event);
        }
        let event_count = if events.is_empty() {
            keys.len()
        } else {
            events.len()
        };
        self.sent = Some(SentPacket {
            flag,
            events: sent_events,
        });
        EventPacket {
            flag,
            event_count: u8::try_from(event_count).unwrap_or(u8::MAX),
            events,
        }
    }

    /// Registers whose events are enabled, with their priority (for the control interface).
    pub fn enabled(&self) -> impl Iterator<Item = (RegisterType, u16, EventPriority)> + '_ {
        self.enabled.iter().map(|(&(t, a), &p)| (t, a, p))
    }

    pub fn pending_count(&self) -> usize {
        self.unconfirmed.len()
    }
}

fn make_event(key: EventKey, registers: &RegisterMap) -> Event {
    match key {
        EventKey::Register(register_type, base) => Event {
            source: EventSource::Register(register_type),
            id: base,
            payload: registers.event_payload(register_type, base),
        },
        EventKey::Reboot => Event::reboot(),
    }
}
