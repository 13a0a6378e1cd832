//! `rtu2mqtt run`: the daemon.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use tokio::sync::watch;
use tracing::info;

use crate::config::library::TemplateLibrary;
use crate::config::load::{load_config, DEFAULT_CONFIG_PATH};
use crate::daemon::{start_bus_side, stdio, termination_signal};
use crate::device::resolve_config;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// No broker: print device updates as JSON lines on stdout and take writes as JSON lines
    /// on stdin ({"device":…,"control":…,"value":…}).
    #[arg(long)]
    pub stdio: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    super::init_logging();
    let loaded = match load_config(&args.config) {
        Ok(loaded) => loaded,
        Err(errors) => {
            for error in &errors.0 {
                eprintln!("{error}");
            }
            return Ok(ExitCode::FAILURE);
        }
    };
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(args.templates.iter().cloned());
    let library = TemplateLibrary::load_dirs(&TemplateLibrary::standard_dirs(&dirs));
    let ports = match resolve_config(&loaded, &library) {
        Ok(ports) => ports,
        Err(errors) => {
            for error in &errors.0 {
                eprintln!("{error}");
            }
            return Ok(ExitCode::FAILURE);
        }
    };
    if !args.stdio {
        anyhow::bail!(
            "MQTT publishing is not built yet: run with --stdio to see device updates on stdout"
        );
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async move {
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let mut bus = start_bus_side(ports, loaded.config.fast_modbus, shutdown_rx);
        let printer = tokio::spawn(stdio::print_updates(bus.updates));
        tokio::spawn(stdio::read_writes(bus.writes.clone()));
        info!("running; stop with Ctrl-C or SIGTERM");
        termination_signal().await;
        info!("stopping");
        let _ = shutdown_tx.send(true);
        bus.tasks.abort_all();
        drop(bus.writes);
        let _ = printer.await;
    });
    Ok(ExitCode::SUCCESS)
}
