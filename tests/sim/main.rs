//! The simulator's integration tests, one module per former test binary: one link instead of
//! four on a small machine.

#[path = "../sim_support/mod.rs"]
mod sim_support;

mod control;
mod pacing;
mod pty;
mod templates;
