//! The benchmark bus: N identical devices with `events` discrete inputs that send Fast Modbus
//! events (`sporadic`) and `registers` input registers polled classically. One generated template
//! serves the simulator and the daemon, so both read the same register map, and each register
//! has a known topic and payload (plain 16-bit values, no scale).

use serde_json::{json, Value};

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

impl BenchLayout {
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
}
