use clap::{Parser, Subcommand};

/// Modbus RTU / Modbus TCP devices to MQTT, with Fast Modbus events.
#[derive(Parser)]
#[command(name = "rtu2mqtt", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Explain a Modbus RTU or Fast Modbus frame given as hex (e.g. "FD 46 10 00 FF 00 00 C8 9A").
    Decode(rtu2mqtt::cli::decode::Args),
    /// Run a virtual RS-485 bus of classic and Fast Modbus devices on a pty or TCP port.
    Sim(rtu2mqtt::cli::sim::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Decode(args) => rtu2mqtt::cli::decode::run(args),
        Command::Sim(args) => rtu2mqtt::cli::sim::run(args),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
