//! The built-in status page and Prometheus metrics (docs/status-page.md): an HTTP server inside
//! the daemon, off unless the config has an `http` section.
//!
//! Cost: with the server off, no port task has a [`hub::PortStatus`] and nothing is counted.
//! With it on, each port task updates its plain-integer [`stats::PortStats`] once per
//! transaction (one uncontended lock); the views (JSON, metrics, decoded frames) are built only
//! when a request asks for them.

pub mod auth;
pub mod hub;
pub mod limits;
pub mod server;
pub mod stats;

pub use hub::{PortStatus, StatusHub};
pub use server::StatusServer;
