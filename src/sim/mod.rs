//! `rtu2mqtt sim`: a virtual RS-485 bus of classic and Fast Modbus devices, wire-accurate in bytes
//! and in time. Everything the tests, the benchmarks and `demo` run against.
//!
//! Sans-IO core (pure, deterministic, time passed in):
//!
//! | module           | what                                                                   |
//! |------------------|------------------------------------------------------------------------|
//! | [`registers`]    | register tables of one device, event-capable registers                 |
//! | [`device`]       | one virtual device: WB standard registers, classic execution, scan     |
//! | [`events`]       | Fast Modbus event state: enabled registers, flag, acks, reboot event   |
//! | [`bus`]          | all devices: who hears a request, arbitration, collisions, timing      |
//! | [`line`]         | settings the master used; timestamped bytes → requests                 |
//! | [`wire`]         | the half-duplex timeline: frame gaps, request/reply collisions          |
//! | [`faults`]       | dropped / corrupted / late replies, seeded                             |
//! | [`other_master`] | a second master that does not listen before it talks                   |
//!
//! Set-up and IO: [`bus_file`] and [`from_template`] (through the shared template loader) build
//! devices; [`control`] is the JSON-lines control protocol; [`pacing`] sends bytes on time;
//! [`pty`] and [`tcp`] are the transports ([`mbap`]: the Modbus TCP gateway's framing).

pub mod bus;
pub mod device;
pub mod events;
pub mod faults;
pub mod line;
pub mod other_master;
pub mod registers;
pub mod transmission;
pub mod wire;

#[cfg(test)]
mod bus_tests;

pub use bus::{Bus, ChangeOrigin, RegisterChange};
pub use device::{DeviceSpec, ValueChange, VirtualDevice};
pub use faults::Faults;
pub use line::{MasterLine, ObservedParity, ReceivedRequest, RequestAssembler};
pub use registers::RegisterMap;
pub use transmission::{Burst, Transmission};
pub use wire::Wire;

pub mod bus_file;
pub mod from_template;

/// Why the simulator could not be set up or a control command failed.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    // Not `source`: the reason is in the message once (a caller printing the error chain
    // would repeat it).
    #[error("{path}: {reason}")]
    Io {
        path: std::path::PathBuf,
        reason: std::io::Error,
    },
    #[error("{path}: {message}")]
    Json {
        path: std::path::PathBuf,
        message: String,
    },
    #[error("no template with device_type {device_type:?} in {dirs}{hint}")]
    TemplateNotFound {
        device_type: String,
        /// The directories searched.
        dirs: String,
        hint: String,
    },
    /// A template the shared loader rejected (the message locates the problem).
    #[error("{0}")]
    Template(String),
    #[error("bus file: {0}")]
    BusFile(String),
}
pub mod control;
pub mod control_socket;
pub mod link;
pub mod mbap;
pub mod pacing;
pub mod pty;
pub mod runtime;
pub mod script;
pub mod tcp;
