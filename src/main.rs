use clap::{CommandFactory, Parser, Subcommand};
use rtu2mqtt::cli;

/// Modbus RTU / Modbus TCP devices to MQTT, with Fast Modbus events.
#[derive(Parser)]
#[command(name = "rtu2mqtt", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check a config file and the templates its devices use; print "ok" or every error.
    CheckConfig(cli::check::CheckConfigArgs),
    /// Check template files (or directories of them); print "ok" or the errors per file.
    CheckTemplates(cli::check::CheckTemplatesArgs),
    /// Show what rtu2mqtt resolved for the config's devices (or one): channels with register,
    /// format, scale, period and event mode, and the setup writes in order.
    Describe(cli::check::DescribeArgs),
    /// Print the JSON Schema of the config file or of templates.
    Schema(cli::schema::SchemaArgs),
    /// Set the config's serial ports up for the daemon (root; the systemd unit runs it before
    /// the daemon): each UART's receive FIFO hands bytes over one at a time, as wb-mqtt-serial
    /// sets it.
    PreparePorts(cli::prepare_ports::Args),
    /// Zero set-up demo: simulated devices, a broker (the one on 127.0.0.1:1883, else a built-in
    /// one) and the daemon.
    Demo(cli::demo::Args),
    /// Serve the buses of the config: poll devices, receive Fast Modbus events, publish values.
    Run(cli::run::Args),
    /// Explain a Modbus RTU or Fast Modbus frame given as hex (e.g. "FD 46 10 00 FF 00 00 C8 9A").
    Decode(cli::decode::Args),
    /// Find the devices on a port: Fast Modbus scan at every port setting (and, with --classic,
    /// address by address); serial, address, settings, model, firmware; duplicates flagged.
    Scan(cli::scan::Args),
    /// Change a device's Modbus address by its serial number (Fast Modbus), and verify it.
    SetAddress(cli::address::SetAddressArgs),
    /// Find devices that share an address and give them free ones by serial number (dry run
    /// unless --apply); verified by a new scan.
    FixAddresses(cli::address::FixAddressesArgs),
    /// Read registers or bits of one device (by address or serial number): raw words and values.
    Read(cli::access::ReadArgs),
    /// Write holding registers or coils of one device, then read them back.
    Write(cli::access::WriteArgs),
    /// Show the Fast Modbus events of a port as they come (acknowledged), with channel names
    /// from a config.
    Events(cli::events::Args),
    /// Run a virtual RS-485 bus of classic and Fast Modbus devices on a pty or TCP port.
    Sim(cli::sim::Args),
    /// Run the benchmarks and write bench/results/latest.md with PNG plots (docs/bench.md).
    #[cfg(feature = "bench")]
    Bench(cli::bench::Args),
    /// Print the bcrypt hash of a password read from stdin, for the status page's
    /// `http.password_hash` (e.g. `printf '%s' 'secret' | rtu2mqtt hash-password`).
    HashPassword(cli::hash_password::Args),
    /// Print a shell completion script (e.g. `rtu2mqtt completions bash > /etc/bash_completion.d/rtu2mqtt`).
    Completions(cli::generate::CompletionsArgs),
    /// Write the man pages (rtu2mqtt.1 and one per subcommand) into a directory.
    #[command(hide = true)]
    Manpages(cli::generate::ManpagesArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    if !matches!(
        cli.command,
        Command::Run(_) | Command::Demo(_) | Command::Sim(_)
    ) {
        quiet_on_closed_stdout();
    }
    if matches!(
        cli.command,
        Command::Scan(_)
            | Command::Events(_)
            | Command::Read(_)
            | Command::Write(_)
            | Command::SetAddress(_)
            | Command::FixAddresses(_)
    ) {
        cli::init_tool_logging();
    }
    let result = match cli.command {
        Command::CheckConfig(args) => cli::check::run_check_config(args),
        Command::CheckTemplates(args) => cli::check::run_check_templates(args),
        Command::PreparePorts(args) => cli::prepare_ports::run(args),
        Command::Describe(args) => cli::check::run_describe(args),
        Command::Schema(args) => cli::schema::run(args),
        Command::Run(args) => cli::run::run(args),
        Command::Demo(args) => cli::demo::run(args),
        Command::Decode(args) => cli::decode::run(args),
        Command::Sim(args) => cli::sim::run(args),
        #[cfg(feature = "bench")]
        Command::Bench(args) => cli::bench::run_bench(args),
        Command::Scan(args) => cli::scan::run(args),
        Command::Events(args) => cli::events::run(args),
        Command::Read(args) => cli::access::run_read(args),
        Command::Write(args) => cli::access::run_write(args),
        Command::SetAddress(args) => cli::address::run_set_address(args),
        Command::FixAddresses(args) => cli::address::run_fix_addresses(args),
        Command::HashPassword(args) => cli::hash_password::run(args),
        Command::Completions(args) => cli::generate::completions(args, Cli::command()),
        Command::Manpages(args) => cli::generate::manpages(args, Cli::command()),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// A command whose output is piped into `head` (or a closed terminal) ends quietly when the
/// reader goes away, as other command-line tools do, instead of a panic at the next print: Rust
/// ignores SIGPIPE, so the write fails and `println!` panics. Not for the long-running commands
/// (the daemon, the demo, the simulator): they log and end on their own terms. Sockets are not
/// affected (the standard library sends with MSG_NOSIGNAL).
fn quiet_on_closed_stdout() {
    use nix::sys::signal::{signal, SigHandler, Signal};
    // SAFETY: at the start of `main`, before any thread exists; the default action needs no
    // handler code.
    let _ = unsafe { signal(Signal::SIGPIPE, SigHandler::SigDfl) };
}
