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
use crate::mqtt::{run_mqtt, MqttSettings};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// No broker: print device updates as JSON lines on stdout and take writes as JSON lines
    /// on stdin ({"device":…,"control":…,"value":…}) instead of MQTT.
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
    let library = TemplateLibrary::load_standard(&dirs);
    let ports = match resolve_config(&loaded, &library) {
        Ok(ports) => ports,
        Err(errors) => {
            for error in &errors.0 {
                eprintln!("{error}");
            }
            return Ok(ExitCode::FAILURE);
        }
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let mqtt_settings = MqttSettings::from_config(&loaded.config);
    let fast_modbus = loaded.config.fast_modbus;
    let result = runtime.block_on(async move {
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let mut bus = start_bus_side(ports, fast_modbus, shutdown_rx.clone());
        let mut sink = if args.stdio {
            tokio::spawn(stdio::read_writes(bus.writes.clone()));
            tokio::spawn(async move {
                stdio::print_updates(bus.updates).await;
                Ok(())
            })
        } else {
            let mut stop = shutdown_rx.clone();
            let stopped = async move {
                let _ = stop.wait_for(|stop| *stop).await;
            };
            tokio::spawn(run_mqtt(
                mqtt_settings,
                bus.updates,
                bus.writes.clone(),
                stopped,
            ))
        };
        info!("running; stop with Ctrl-C or SIGTERM");
        let finished = tokio::select! {
            _ = termination_signal() => None,
            result = &mut sink => Some(result),
        };
        info!("stopping");
        let _ = shutdown_tx.send(true);
        // Port tasks notice the shutdown between transactions; none outlives the runtime.
        while bus.tasks.join_next().await.is_some() {}
        drop(bus.writes);
        // The sink ends once the port tasks are gone; MQTT first clears its retained topics.
        let finished = match finished {
            Some(result) => Some(result),
            None => Some(sink.await),
        };
        match finished {
            Some(Ok(Err(err))) => Err(anyhow::Error::new(err).context("MQTT")),
            Some(Err(join)) => Err(anyhow::anyhow!("the MQTT task failed: {join}")),
            _ => Ok(()),
        }
    });
    // A blocked stdin read must not hold the exit.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    result?;
    Ok(ExitCode::SUCCESS)
}
