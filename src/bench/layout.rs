//! The benchmark bus: N identical devices with `events` discrete inputs that send Fast Modbus
//! events (`sporadic`) and `registers` input registers polled classically. One generated template
//! serves the simulator and the daemon, so both read the same register map, and each register
//! has a known topic and payload (plain 16-bit values, no scale).

use std::collections::BTreeMap;

use serde_json::{json, Value};

use super::history::RegisterKey;

/// Devices at addresses `1..=devices`, all on one line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BenchLayout {
    pub devices: u8,
    /// Discrete inputs 0.. with events (`E0`, `E1`, …).
    pub events: u16,
    /// Input registers 0.. polled (`R0`, `R1`, …).
    pub registers: u16,
    pub baud: u32,
    /// Do the devices speak Fast Modbus? (false: classic devices that refuse 0x46.)
    pub fast_devices: bool,
}

/// The MQTT device id prefix: ids are `bench_<address>`.
pub const DEVICE_ID: &str = "bench";

/// The fault suite's bus (`tests/fault_suite.rs`, and on virtual time
/// `src/gateway/noise_scenarios.rs`): event inputs and polled registers per device, odd
/// addresses speak Fast Modbus, even ones are classic, and the template writes
/// [`FAULT_BUS_SETUP_VALUE`] to [`FAULT_BUS_SETUP_REGISTER`] at setup (to see it rewritten after
/// a reboot).
pub const FAULT_BUS_EVENTS: u16 = 2;
pub const FAULT_BUS_REGISTERS: u16 = 4;
pub const FAULT_BUS_SETUP_REGISTER: u16 = 100;
pub const FAULT_BUS_SETUP_VALUE: u16 = 7;

/// A value of the fault suite's bus that spans several input registers (high word first, as
/// Wiren Board devices store them). The suite changes all its words at once, as a real device
/// does, and gives every word a new value at every update (see [`wide_words`]): a value made of
/// words of two different moments, or half updated, is one the device never held.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WideChannel {
    pub name: &'static str,
    /// First input register.
    pub address: u16,
    /// `u32`, `s32` or `u64` (the template's format).
    pub format: &'static str,
    pub words: u16,
    /// Sent by Fast Modbus events (on the fast devices; the classic ones poll it).
    pub sporadic: bool,
    /// Each new value waits until the last one was published (so every change must be
    /// published exactly once, as the event inputs' toggles); otherwise it changes round robin
    /// with the registers, faster than any poll.
    pub awaited: bool,
}

/// The fault bus's multi-register values (issue 15, defect 1: a value delivered by an event is
/// never published half updated). Next to the registers and to each other, so that a classic
/// device reads them in two requests (0–5 and 10–15) and the bus's poll cycle stays close to
/// what it was with the 16-bit registers alone.
pub const FAULT_BUS_WIDE: [WideChannel; 3] = [
    WideChannel {
        name: "C0",
        address: 10,
        format: "u32",
        words: 2,
        sporadic: true,
        awaited: true,
    },
    WideChannel {
        name: "Q0",
        address: 12,
        format: "u64",
        words: 4,
        sporadic: true,
        awaited: false,
    },
    WideChannel {
        name: "L0",
        address: 4,
        format: "s32",
        words: 2,
        sporadic: false,
        awaited: false,
    },
];

/// The wide value a register slot holds at its `n`-th value: word 0 is `n`, every other word a
/// different function of `n`, so all words change together and no mix of two moments' words is
/// a value the device held.
pub fn wide_words(n: u16, words: u16) -> Vec<u16> {
    const MIXES: [u16; 4] = [0, 0xA5A5, 0x5A5A, 0xFFFF];
    (0..usize::from(words))
        .map(|i| n ^ MIXES.get(i).copied().unwrap_or(0x3C3C))
        .collect()
}

/// Words high first, joined.
pub fn join_words(words: &[u16]) -> u64 {
    words
        .iter()
        .fold(0u64, |acc, &word| (acc << 16) | u64::from(word))
}

impl WideChannel {
    /// The wide channel whose first register is `register` (input registers).
    pub fn at(register_type: &str, register: u16) -> Option<&'static WideChannel> {
        FAULT_BUS_WIDE
            .iter()
            .find(|c| register_type == "input" && c.address == register)
    }

    /// The payload the daemon publishes for the joined words `value`.
    pub fn payload(&self, value: u64) -> String {
        match self.format {
            "s32" => (value as u32 as i32).to_string(),
            "s64" => (value as i64).to_string(),
            _ => value.to_string(),
        }
    }

    pub fn topic(&self, address: u8) -> String {
        format!("{}{}", BenchLayout::topic_prefix(address), self.name)
    }

    fn template_channel(&self) -> Value {
        let mut channel = json!({
            "name": self.name, "reg_type": "input", "address": self.address,
            "format": self.format, "type": "value",
        });
        if self.sporadic {
            channel["sporadic"] = json!(true);
        }
        channel
    }
}

/// One input value the fault suite changes: `words` registers at `register` of `address`, and
/// its index among all such values (no two indices share a value: see [`FaultSlot::words_for`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FaultSlot {
    pub index: usize,
    pub address: u8,
    pub register: u16,
    pub words: u16,
}

impl FaultSlot {
    /// The words of this slot's `sequence`-th value with `span` values per slot: word 0 is
    /// index × span + sequence, unique on the bus.
    pub fn words_for(&self, span: u16, sequence: u16) -> Vec<u16> {
        let n = u16::try_from(self.index)
            .unwrap_or(0)
            .wrapping_mul(span)
            .wrapping_add(sequence);
        wide_words(n, self.words)
    }

    pub fn key(&self) -> RegisterKey {
        RegisterKey::wide(self.address, "input", self.register, self.words)
    }
}

impl BenchLayout {
    /// The fault bus's input values: (changed round robin, one per tick: per device its
    /// registers and the wide values not awaited; awaited: per device the wide values whose next
    /// change waits for the last one to be published).
    pub fn fault_slots(&self) -> (Vec<FaultSlot>, Vec<FaultSlot>) {
        let mut round_robin = Vec::new();
        let mut awaited = Vec::new();
        for address in 1..=self.devices {
            for register in 0..self.registers {
                round_robin.push((address, register, 1));
            }
            for wide in FAULT_BUS_WIDE.iter() {
                let slot = (address, wide.address, wide.words);
                if wide.awaited {
                    awaited.push(slot);
                } else {
                    round_robin.push(slot);
                }
            }
        }
        let slot = |(index, (address, register, words)): (usize, (u8, u16, u16))| FaultSlot {
            index,
            address,
            register,
            words,
        };
        let offset = round_robin.len();
        (
            round_robin.into_iter().enumerate().map(slot).collect(),
            awaited
                .into_iter()
                .enumerate()
                .map(|(i, s)| slot((offset + i, s)))
                .collect(),
        )
    }

    /// Values per slot: every slot's values are its own.
    pub fn fault_span(&self) -> u16 {
        let (round_robin, awaited) = self.fault_slots();
        u16::try_from(65_536 / (round_robin.len() + awaited.len()).max(1)).unwrap_or(u16::MAX)
    }

    /// Every value topic of the fault bus and the value it shows (event inputs, registers, wide
    /// values).
    pub fn fault_topics(&self) -> BTreeMap<String, RegisterKey> {
        let mut topics = BTreeMap::new();
        for address in 1..=self.devices {
            let prefix = Self::topic_prefix(address);
            for event in 0..self.events {
                topics.insert(
                    format!("{prefix}E{event}"),
                    RegisterKey::new(address, "discrete", event),
                );
            }
            for register in 0..self.registers {
                topics.insert(
                    format!("{prefix}R{register}"),
                    RegisterKey::new(address, "input", register),
                );
            }
            for wide in FAULT_BUS_WIDE.iter() {
                topics.insert(
                    wide.topic(address),
                    RegisterKey::wide(address, "input", wide.address, wide.words),
                );
            }
        }
        topics
    }

    /// The payload the daemon publishes for `key` holding `value` (its words joined).
    pub fn fault_payload(key: &RegisterKey, value: u64) -> String {
        match WideChannel::at(&key.register_type, key.register) {
            Some(wide) if key.words > 1 => wide.payload(value),
            _ => value.to_string(),
        }
    }

    /// The fault suite's bus of `devices` at `baud` (see [`FAULT_BUS_EVENTS`]).
    pub fn fault_bus(devices: u8, baud: u32) -> Self {
        Self {
            devices,
            events: FAULT_BUS_EVENTS,
            registers: FAULT_BUS_REGISTERS,
            baud,
            fast_devices: true,
        }
    }

    /// The fault suite's template (with its setup write) as (file name, template), and the
    /// simulator's device entries, odd addresses Fast Modbus.
    pub fn fault_bus_files(&self) -> (String, Value, Vec<Value>) {
        let (name, mut template) = self.template();
        template["device"]["setup"] = json!([{"title": "Mode",
            "address": FAULT_BUS_SETUP_REGISTER, "value": FAULT_BUS_SETUP_VALUE}]);
        if let Some(channels) = template["device"]["channels"].as_array_mut() {
            channels.extend(FAULT_BUS_WIDE.iter().map(WideChannel::template_channel));
        }
        let mut entries = self.bus()["devices"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        for entry in &mut entries {
            let address = entry["address"].as_u64().unwrap_or(0);
            entry["fast"] = json!(address % 2 == 1);
        }
        (name, template, entries)
    }

    pub fn device_type(&self) -> String {
        format!("bench-e{}-r{}", self.events, self.registers)
    }

    pub fn line(&self) -> String {
        format!("{} 8N2", self.baud)
    }

    /// The template file (name, JSON).
    pub fn template(&self) -> (String, Value) {
        let mut channels = Vec::new();
        for event in 0..self.events {
            channels.push(json!({
                "name": format!("E{event}"), "reg_type": "discrete", "address": event,
                "type": "switch", "readonly": true, "sporadic": true,
            }));
        }
        for register in 0..self.registers {
            channels.push(json!({
                "name": format!("R{register}"), "reg_type": "input", "address": register,
                "type": "value",
            }));
        }
        let template = json!({
            "title": "rtu2mqtt benchmark device",
            "device_type": self.device_type(),
            "device": {
                "name": "Bench",
                "id": DEVICE_ID,
                // 0: the protocol's maximum, so 60 registers are one request.
                "max_read_registers": 0,
                "channels": channels,
            }
        });
        (format!("{}.json", self.device_type()), template)
    }

    /// The simulator's bus file.
    pub fn bus(&self) -> Value {
        let devices: Vec<Value> = (1..=self.devices)
            .map(|address| {
                json!({
                    "name": format!("d{address}"),
                    "template": self.device_type(),
                    "address": address,
                    "serial": 0xFE00_0000_u32 + u32::from(address),
                    "line": self.line(),
                    "fast": self.fast_devices,
                    "turnaround_us": 500,
                })
            })
            .collect();
        json!({"seed": 1, "devices": devices})
    }

    /// The daemon's `ports` for a harness whose pty is `pty`; `port_extra` keys are merged into
    /// the port (e.g. `event_interval_ms`, `response_timeout_ms`).
    pub fn ports(&self, pty: &std::path::Path, port_extra: &Value) -> Value {
        let devices: Vec<Value> = (1..=self.devices)
            .map(|address| json!({"device_type": self.device_type(), "slave_id": address}))
            .collect();
        let mut port = json!({
            "path": pty, "baud_rate": self.baud, "parity": "N", "data_bits": 8, "stop_bits": 2,
            "devices": devices,
        });
        if let (Some(fields), Value::Object(extra)) = (port.as_object_mut(), port_extra) {
            fields.extend(extra.clone());
        }
        json!([port])
    }

    pub fn topic_prefix(address: u8) -> String {
        format!("/devices/{DEVICE_ID}_{address}/controls/")
    }

    /// Where a register change must be published, and the payload.
    pub fn topic_of(
        &self,
        address: u8,
        register_type: &str,
        register: u16,
        value: u16,
    ) -> Option<(String, String)> {
        if address == 0 || address > self.devices {
            return None;
        }
        let name = match register_type {
            "discrete" if register < self.events => format!("E{register}"),
            "input" if register < self.registers => format!("R{register}"),
            _ => return None,
        };
        Some((
            format!("{}{name}", Self::topic_prefix(address)),
            value.to_string(),
        ))
    }

    /// Every value topic of the bus (to wait until all have their first value).
    pub fn value_topics(&self) -> Vec<String> {
        let mut topics = Vec::new();
        for address in 1..=self.devices {
            let prefix = Self::topic_prefix(address);
            topics.extend((0..self.events).map(|e| format!("{prefix}E{e}")));
            topics.extend((0..self.registers).map(|r| format!("{prefix}R{r}")));
        }
        topics
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_follow_the_template() {
        let layout = BenchLayout {
            devices: 2,
            events: 8,
            registers: 60,
            baud: 115_200,
            fast_devices: true,
        };
        assert_eq!(
            layout.topic_of(2, "discrete", 7, 1),
            Some(("/devices/bench_2/controls/E7".into(), "1".into()))
        );
        assert_eq!(
            layout.topic_of(1, "input", 59, 300),
            Some(("/devices/bench_1/controls/R59".into(), "300".into()))
        );
        assert_eq!(layout.topic_of(1, "discrete", 8, 1), None);
        assert_eq!(layout.topic_of(3, "input", 0, 1), None);
        assert_eq!(layout.value_topics().len(), 2 * 68);
        let (_, template) = layout.template();
        assert_eq!(
            template["device"]["channels"].as_array().map(Vec::len),
            Some(68)
        );
        assert_eq!(layout.bus()["devices"][1]["address"], 2);
    }

    #[test]
    fn wide_values_change_every_word_and_mixes_are_never_held() {
        for channel in &FAULT_BUS_WIDE {
            let (a, b) = (
                wide_words(0x1234, channel.words),
                wide_words(0x1235, channel.words),
            );
            assert!(a.iter().zip(&b).all(|(x, y)| x != y), "{channel:?}");
            // The high word of one moment with the others of the next: held by no slot.
            let mut mixed = a.clone();
            mixed[1..].copy_from_slice(&b[1..]);
            let held = |n: u16| join_words(&wide_words(n, channel.words));
            assert!((0..=u16::MAX).all(|n| held(n) != join_words(&mixed)));
        }
        let signed = WideChannel::at("input", 4).expect("L0");
        assert_eq!(
            signed.payload(join_words(&wide_words(0x8001, 2))),
            "-2147408476"
        );
        assert_eq!(
            FAULT_BUS_WIDE[0].payload(join_words(&wide_words(1, 2))),
            "107940"
        );
        let (_, template, _) = BenchLayout::fault_bus(2, 9600).fault_bus_files();
        let channels = template["device"]["channels"].as_array().expect("channels");
        assert_eq!(channels.len(), 2 + 4 + 3);
        assert_eq!(channels[6]["format"], "u32");
        assert_eq!(channels[6]["sporadic"], true);
    }

    #[test]
    fn fault_slots_give_every_value_its_own_words() {
        let layout = BenchLayout::fault_bus(3, 9600);
        let (round_robin, awaited) = layout.fault_slots();
        assert_eq!(round_robin.len(), 3 * (4 + 2));
        assert_eq!(awaited.len(), 3);
        assert_eq!(awaited[0].index, round_robin.len());
        let span = layout.fault_span();
        assert_eq!(span, u16::try_from(65_536 / 21).unwrap());
        let mut first_words: Vec<u16> = round_robin
            .iter()
            .chain(&awaited)
            .flat_map(|slot| (1..span).map(move |seq| slot.words_for(span, seq)[0]))
            .collect();
        let all = first_words.len();
        first_words.sort_unstable();
        first_words.dedup();
        assert_eq!(first_words.len(), all);
        let topics = layout.fault_topics();
        assert_eq!(topics.len(), 3 * (2 + 4 + 3));
        let c0 = &topics["/devices/bench_2/controls/C0"];
        assert_eq!((c0.register, c0.words), (10, 2));
        assert_eq!(BenchLayout::fault_payload(c0, 70_000), "70000");
    }
}
