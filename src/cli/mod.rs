//! The subcommands' entry points: each takes its clap arguments and returns the exit code.
// Located errors are built once per bad file, at load time: their size does not matter, and
// boxing them would only make every `match` on `problem` noisier.
#![allow(clippy::result_large_err)]

pub mod access;
pub mod address;
#[cfg(feature = "bench")]
pub mod bench;
pub mod check;
pub mod decode;
pub mod demo;
pub mod events;
pub mod generate;
pub mod hash_password;
pub mod prepare_ports;
pub mod run;
pub mod scan;
pub mod schema;
pub mod sim;
pub mod via_mqtt;

/// Logs to stderr; `RUST_LOG` (e.g. `debug`, `rtu2mqtt::transport=debug`) picks the detail.
/// Colours only on a terminal: journald and log files would store the escape codes as text.
pub fn init_logging() {
    init_logging_at("info");
}

/// The site tools log only warnings unless `RUST_LOG` asks for more (`RUST_LOG=debug` shows
/// every frame): their results go to stdout, and stderr stays for what went wrong.
pub fn init_tool_logging() {
    init_logging_at("warn");
}

fn init_logging_at(default: &str) {
    use std::io::IsTerminal;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let colour = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none();
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(colour)
        .with_writer(std::io::stderr)
        .try_init();
}
