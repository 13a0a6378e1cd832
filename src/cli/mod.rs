//! The subcommands' entry points: each takes its clap arguments and returns the exit code.

pub mod decode;
pub mod sim;
