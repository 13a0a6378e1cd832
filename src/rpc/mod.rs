//! wb-mqtt-serial's MQTT RPC, served by the running daemon: Wiren Board's tools and web UI, and
//! rtu2mqtt's own site tools (`--via-mqtt`), reach a port the service holds without stopping it.
//! See `docs/rpc.md`.
//!
//! [`message`] (the envelope) and [`params`] (each method's params) are pure; [`methods`] runs
//! a request through the port's bus queue ([`crate::daemon::bus_queue`]); [`server`] is the
//! broker connection; [`client`] is the CLI's caller; [`config_load`] answers `config/Load`.

pub mod client;
pub mod config_load;
pub mod message;
pub mod methods;
pub mod parameters;
pub mod params;
pub mod server;

pub use methods::DeviceTemplates;
pub use server::run_rpc_server;
