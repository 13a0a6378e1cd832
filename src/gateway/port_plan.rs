//! From a resolved port (config + templates) to what its scheduler needs: line timing, one
//! register-level plan per device, and where the bus is.

use std::time::Duration;

use crate::config::config_file::{PortConfig, PortType};
use crate::device::model::{ResolvedDevice, ResolvedPort};
use crate::port::{
    DevicePlan, HealthPolicy, MergeLimits, PlannedRead, PortSettings, SetupWrite,
    MIN_LATE_REPLY_HOLDOFF,
};
use crate::protocol::{LineSettings, Parity, RegisterType};
use crate::transport::Endpoint;

/// Everything one port task needs.
#[derive(Debug, Clone)]
pub struct PortPlan {
    pub name: String,
    pub endpoint: Endpoint,
    pub settings: PortSettings,
    pub devices: Vec<DevicePlan>,
}

/// Serial settings of a port; TCP gateways are modelled at 9600 8N2 as wb-mqtt-serial does.
pub fn line_settings(port: &PortConfig) -> LineSettings {
    match port.port_type {
        PortType::Serial => LineSettings {
            baud: port.baud_rate,
            data_bits: port.data_bits,
            parity: port.parity,
            stop_bits: port.stop_bits,
        },
        PortType::Tcp | PortType::ModbusTcp => LineSettings::new(9600, Parity::None, 2),
    }
}

fn endpoint(port: &PortConfig) -> Endpoint {
    let address = format!(
        "{}:{}",
        port.address.as_deref().unwrap_or("127.0.0.1"),
        port.port.unwrap_or(502)
    );
    let connect_timeout = Duration::from_millis(port.connect_timeout_ms);
    match port.port_type {
        PortType::Serial => Endpoint::Serial {
            path: port.path.clone().unwrap_or_default(),
            line: line_settings(port),
        },
        PortType::Tcp => Endpoint::RtuOverTcp {
            address,
            connect_timeout,
        },
        PortType::ModbusTcp => Endpoint::ModbusTcp {
            address,
            connect_timeout,
        },
    }
}

/// `fast_modbus` is the site-wide switch; Modbus TCP gateways pass the extension only when they
/// say so (`connected_to_mge`).
pub fn port_plan(port: &ResolvedPort, fast_modbus: bool) -> PortPlan {
    let line = line_settings(&port.config);
    let mut settings = PortSettings::for_line(line);
    settings.fast_modbus = fast_modbus
        && (port.config.port_type != PortType::ModbusTcp || port.config.connected_to_mge);
    if let Some(interval) = port.config.event_interval_ms {
        settings.event_interval = Duration::from_millis(interval.clamp(5, 10_000));
    }
    settings.guard_interval = port
        .devices
        .iter()
        .map(|d| d.timing.guard_interval)
        .max()
        .unwrap_or_default();
    let endpoint = endpoint(&port.config);
    PortPlan {
        name: endpoint.name(),
        endpoint,
        settings,
        devices: port.devices.iter().map(device_plan).collect(),
    }
}

pub fn device_plan(device: &ResolvedDevice) -> DevicePlan {
    let mut reads: Vec<PlannedRead> = Vec::new();
    for channel in &device.channels {
        let events = channel.events;
        for register in channel.registers.iter().filter_map(|r| r.read) {
            let read = PlannedRead {
                span: register.span(),
                period: channel.read_period,
                events,
            };
            // Bit fields of one register share a read.
            if !reads.contains(&read) {
                reads.push(read);
            }
        }
    }
    let setup = device
        .setup
        .iter()
        .filter(|s| s.register.reg_type == RegisterType::Holding && !s.words.is_empty())
        .map(|s| SetupWrite {
            address: s.register.address,
            values: s.words.clone(),
        })
        .collect();
    let defaults = HealthPolicy::default();
    DevicePlan {
        name: device.id.clone(),
        address: device.slave_id,
        response_timeout: device.timing.response_timeout,
        merge: MergeLimits {
            max_read_registers: device.timing.max_read_registers,
            max_register_hole: device.timing.max_reg_hole,
            max_bit_hole: device.timing.max_bit_hole,
        },
        // Unset (-1 in the config) means: never disconnect for that reason.
        health: HealthPolicy {
            max_fail_cycles: device.timing.device_max_fail_cycles.unwrap_or(u32::MAX),
            device_timeout: device.timing.device_timeout.unwrap_or(Duration::MAX),
            late_reply_holdoff: (device.timing.response_timeout * 2).max(MIN_LATE_REPLY_HOLDOFF),
            ..defaults
        },
        reads,
        setup,
    }
}
