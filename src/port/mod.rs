//! One bus: the sans-IO scheduler that decides what the bus does next (event requests, writes,
//! device preparation, classic reads), device health, and the read plan. A port task drives it
//! with a transport; tests drive it with a fake clock and scripted outcomes.

mod device;
mod due_index;
mod events;
mod flap_log;
pub mod health;
pub mod plan;
mod rate_limit;
pub mod read_plan;
pub mod scheduler;

pub use health::{HealthPolicy, MIN_LATE_REPLY_HOLDOFF};
pub use plan::{
    DevicePlan, EventMode, GuardIntervals, PlannedRead, PortSettings, RegisterWrite, SetupWrite,
};
pub use read_plan::{MergeLimits, RegisterSpan};
pub use scheduler::{
    DeviceReport, NextStep, PortEvent, PortScheduler, ReplyTiming, Transaction, TransactionOutcome,
};
