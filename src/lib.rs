//! rtu2mqtt: Modbus RTU / Modbus TCP devices to MQTT, with Fast Modbus events.
//!
//! Layers, from the wire up (see `README.md` and the architecture notes):
//! `protocol` (sans-IO codec, parser, timing) → `sim` (virtual bus) / transport → port scheduler
//! → `device` (templates, value codecs) → MQTT.

pub mod bench;
pub mod cli;
pub mod config;
pub mod daemon;
pub mod device;
pub mod embedded_broker;
pub mod mqtt;
pub mod port;
pub mod protocol;
pub mod service;
pub mod sim;
pub mod status;
pub mod tools;
pub mod transport;
pub mod updates;
