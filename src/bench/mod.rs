//! Benchmarks and the process harness they share with end-to-end tests (docs/bench.md).
//!
//! Always built: [`harness`] (broker, simulator, daemon and subscriber as processes),
//! [`matching`] (changes ↔ publications), [`history`] (was each published value ever held), [`layout`] (the benchmark bus) and [`library`] (a template library of a controller's size), and the pure parts of the report
//! ([`report_date`], [`scan_floor`]). With the `bench`
//! feature: the scenarios, the Markdown report and the PNG plots behind `rtu2mqtt bench`.

pub mod harness;
pub mod history;
pub mod layout;
pub mod library;
pub mod matching;
pub mod report_date;
pub mod scan_floor;

#[cfg(feature = "bench")]
pub mod bare_master;
#[cfg(feature = "bench")]
pub mod floor;
#[cfg(feature = "bench")]
pub mod plots;
#[cfg(feature = "bench")]
pub mod report;
#[cfg(feature = "bench")]
pub mod scan;
#[cfg(feature = "bench")]
pub mod scenarios;
