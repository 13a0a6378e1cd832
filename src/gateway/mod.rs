//! The pure core between a port's scheduler and the sinks (MQTT, stdout): what a configured port
//! asks of its scheduler, and the device model that turns port events into control values and
//! error flags and `/on` payloads into register writes. No IO, no clock; `daemon` runs it.

pub mod device_model;
pub mod port_plan;

#[cfg(test)]
mod layout_sweep;
#[cfg(test)]
mod noise_scenarios;
#[cfg(test)]
mod scenarios;
#[cfg(test)]
pub(crate) mod virtual_gateway;
