//! Site tools (`rtu2mqtt scan`, `set-address`, `fix-addresses`, `read`, `write`, `events`): the
//! pure logic (which port settings to try, what a scan found, how duplicates are resolved, how a
//! register value reads) in sans-IO modules, and one small IO layer ([`bus`]) over the transport.

pub mod adapter;
pub mod bus;
pub mod plan;
pub mod report;
pub mod values;

/// Exit codes shared by the site tools, so scripts can tell what went wrong.
pub mod exit {
    /// Done, and the result is what was asked for.
    pub const OK: u8 = 0;
    /// The bus worked but the answer is not the one wanted: nothing found, no reply, a device
    /// refused, verification failed, duplicates left.
    pub const NOT_FOUND: u8 = 1;
    /// Bad arguments (clap uses 2 as well).
    pub const USAGE: u8 = 2;
    /// The port cannot be used: missing, no permission, busy.
    pub const PORT: u8 = 3;
    /// Stopped by Ctrl-C (128 + SIGINT).
    pub const INTERRUPTED: u8 = 130;
}
