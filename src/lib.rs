//! rtu2mqtt: Modbus RTU / Modbus TCP devices to MQTT, with Fast Modbus events.
//!
//! Layers, from the wire up (see `docs/architecture.md`): `protocol` (sans-IO codec, parser,
//! timing) → `transport` → `port` (scheduler) → `config`/`device` (templates, value codecs) →
//! `gateway` (port plan, device model) → `mqtt`; `daemon` wires them with tokio, `sim` is the
//! virtual bus.

pub mod bench;
pub mod child;
pub mod cli;
pub mod config;
pub mod daemon;
pub mod device;
pub mod device_updates;
pub mod embedded_broker;
pub mod gateway;
pub mod mqtt;
pub mod port;
pub mod protocol;
pub mod rpc;
pub mod service;
pub mod sim;
pub mod status;
pub mod tools;
pub mod transport;
