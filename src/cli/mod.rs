//! The subcommands' entry points: each takes its clap arguments and returns the exit code.
// Located errors are built once per bad file, at load time: their size does not matter, and
// boxing them would only make every `match` on `problem` noisier.
#![allow(clippy::result_large_err)]

pub mod check;
pub mod decode;
pub mod schema;
