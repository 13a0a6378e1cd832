//! The MQTT side's integration tests, one module per former test binary: one link instead of
//! four on a small machine.

#[path = "../daemon_support/mod.rs"]
mod daemon_support;
#[path = "../mqtt_support/mod.rs"]
mod mqtt_support;

mod broker;
mod discovery_schema;
mod logs;
mod tls;
