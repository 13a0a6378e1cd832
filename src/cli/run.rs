//! `rtu2mqtt run`: the daemon.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;
use tokio::signal::unix::{signal, SignalKind};
use tokio::sync::watch;
use tracing::{error, info, warn};

use crate::config::config_file::HttpConfig;
use crate::config::library::ListedTemplate;
use crate::config::library::TemplateLibrary;
use crate::config::load::{load_config, LoadedConfig, DEFAULT_CONFIG_PATH};
use crate::daemon::{start_bus_side_with_status, stdio, termination_signal, BusControl, BusSide};
use crate::device::model::ResolvedPort;
use crate::device::resolve_config;
use crate::mqtt::{run_mqtt_reporting, MqttSettings, UnchangedPolicy};
use crate::rpc::{run_rpc_server, DeviceTemplates};
use crate::service::{notify_systemd, BrokerState, ServiceHealth};
use crate::status::{StatusHub, StatusServer};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// No broker: print device updates as JSON lines on stdout and take writes as JSON lines
    /// on stdin ({"device":…,"control":…,"value":…}) instead of MQTT. Runs until Ctrl-C or
    /// SIGTERM; the end of stdin only ends the writes (so `< /dev/null` just polls).
    #[arg(long)]
    pub stdio: bool,
    /// The status page's socket, already bound (the demo binds it before printing its URL, so
    /// two demos cannot race for the same port); `http.listen` must name the same address.
    #[arg(skip)]
    pub http_listener: Option<std::sync::Arc<std::net::TcpListener>>,
}

/// Loads the config and resolves its devices against the templates; the errors as the
/// integrator reads them otherwise. Also the templates the devices use (for the RPC).
/// The config, its ports resolved, the templates its devices use, and the device types of the
/// whole library (for the RPC's `config/Load`).
type Loaded = (
    LoadedConfig,
    Vec<ResolvedPort>,
    TemplateLibrary,
    Vec<ListedTemplate>,
);

fn load(args: &Args) -> Result<Loaded, Vec<String>> {
    let loaded = load_config(&args.config)
        .map_err(|errors| errors.0.iter().map(ToString::to_string).collect::<Vec<_>>())?;
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(args.templates.iter().cloned());
    let library = TemplateLibrary::load_standard(&dirs);
    let ports = resolve_config(&loaded, &library)
        .map_err(|errors| errors.0.iter().map(ToString::to_string).collect::<Vec<_>>())?;
    let used = library.only(
        ports
            .iter()
            .flat_map(|port| &port.devices)
            .filter_map(|device| device.device_type.as_deref()),
    );
    Ok((loaded, ports, used, library.listings()))
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    super::init_logging();
    let (loaded, ports, templates, types) = match load(&args) {
        Ok(loaded) => loaded,
        Err(errors) => {
            for error in &errors {
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
    let running_mqtt = restart_only(&loaded.config);
    let http = loaded.config.http.clone();
    let templates = DeviceTemplates::new(templates, types, args.config.clone());
    let result = runtime.block_on(async move {
        // Installed first: from here on SIGHUP reloads instead of killing the process.
        let mut hangups = signal(SignalKind::hangup()).context("cannot handle SIGHUP")?;
        let terminate = termination_signal();
        tokio::pin!(terminate);
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let health = Arc::new(ServiceHealth::new(if args.stdio {
            BrokerState::NotUsed
        } else {
            BrokerState::Connecting
        }));
        // The status page, when configured: bound before the buses start, so that a port in
        // use stops the daemon with a clear message instead of running without its page.
        let status = match &http {
            Some(http) => {
                let hub = Arc::new(StatusHub::new());
                let prebound = args
                    .http_listener
                    .as_ref()
                    .map(|listener| listener.try_clone())
                    .transpose()?;
                let server =
                    StatusServer::bind(http, prebound, Arc::clone(&hub), shutdown_rx.clone())
                        .await?;
                Some((hub, server))
            }
            None => None,
        };
        let BusSide {
            updates,
            writes,
            control: mut bus,
        } = start_bus_side_with_status(
            ports,
            fast_modbus,
            Arc::clone(&health),
            status.as_ref().map(|(hub, _)| Arc::clone(hub)),
            // What the one sink (stdout or MQTT) needs besides the changes.
            if args.stdio {
                stdio::REPEATS
            } else {
                UnchangedPolicy::from_config(mqtt_settings.max_unchanged_interval).repeats()
            },
        );
        // Only now: READY waits for every port to have tried to open, and before the ports are
        // registered there are none to wait for.
        let notifier = tokio::spawn(notify_systemd(Arc::clone(&health), shutdown_rx.clone()));
        let status_server = status.map(|(hub, server)| {
            hub.set_writes(writes.clone());
            hub.set_port_directory(bus.port_directory());
            tokio::spawn(server.serve())
        });
        // wb-mqtt-serial's MQTT RPC, on its own broker connection (not with --stdio).
        let mut rpc_task = None;
        let mut sink = if args.stdio {
            tokio::spawn(stdio::read_writes(writes.clone()));
            tokio::spawn(async move {
                stdio::print_updates(updates).await;
                Ok(())
            })
        } else {
            let mut stop = shutdown_rx.clone();
            let stopped = async move {
                let _ = stop.wait_for(|stop| *stop).await;
            };
            let mut rpc_stop = shutdown_rx.clone();
            rpc_task = Some(tokio::spawn(run_rpc_server(
                mqtt_settings.broker.clone(),
                bus.port_directory(),
                templates.clone(),
                async move {
                    let _ = rpc_stop.wait_for(|stop| *stop).await;
                },
            )));
            tokio::spawn(run_mqtt_reporting(
                mqtt_settings,
                updates,
                writes.clone(),
                stopped,
                Some(Arc::clone(&health)),
            ))
        };
        info!("running; stop with Ctrl-C or SIGTERM, reload the config with SIGHUP");
        let finished = loop {
            tokio::select! {
                () = &mut terminate => break None,
                result = &mut sink => break Some(result),
                _ = hangups.recv() => reload(&args, &mut bus, &templates, &running_mqtt, &http).await,
            }
        };
        info!("stopping");
        let _ = shutdown_tx.send(true);
        // Port tasks finish their transaction in flight; none outlives the runtime.
        bus.stop().await;
        drop(writes);
        // The sink ends once the port tasks are gone; MQTT first clears its retained topics.
        let finished = match finished {
            Some(result) => Some(result),
            None => Some(sink.await),
        };
        let _ = notifier.await;
        if let Some(rpc_task) = rpc_task {
            let _ = rpc_task.await;
        }
        if let Some(server) = status_server {
            // Open pages are told to close; a client that holds its connection does not hold
            // the exit.
            let _ = tokio::time::timeout(std::time::Duration::from_secs(2), server).await;
        }
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

/// What a reload cannot change, as the config has it: the `mqtt` section, and
/// `max_unchanged_interval` (the MQTT side's policy and the device models' repeats are set once).
type RestartOnly = (serde_json::Value, i64);

fn restart_only(config: &crate::config::config_file::Config) -> RestartOnly {
    (
        serde_json::to_value(&config.mqtt).unwrap_or_default(),
        config.max_unchanged_interval,
    )
}

/// SIGHUP: re-reads the config and templates and applies the difference port by port. A config
/// that does not load leaves everything running as it was.
async fn reload(
    args: &Args,
    bus: &mut BusControl,
    templates: &DeviceTemplates,
    running_mqtt: &RestartOnly,
    running_http: &Option<HttpConfig>,
) {
    info!(config = %args.config.display(), "SIGHUP: reloading the config and templates");
    let (loaded, ports, used_templates, types) = match load(args) {
        Ok(loaded) => loaded,
        Err(errors) => {
            error!(
                "reload failed, the running configuration stays in force: {}",
                errors.join("; ")
            );
            return;
        }
    };
    let (mqtt, unchanged_interval) = restart_only(&loaded.config);
    if mqtt != running_mqtt.0 {
        warn!("the mqtt section changed: it takes effect when the service restarts");
    }
    if unchanged_interval != running_mqtt.1 {
        warn!("max_unchanged_interval changed: it takes effect when the service restarts");
    }
    if loaded.config.http != *running_http {
        warn!("the http section changed: it takes effect when the service restarts");
    }
    templates.replace(used_templates, types);
    let summary = bus.reload(ports, loaded.config.fast_modbus).await;
    info!(
        started = ?summary.ports_started,
        restarted = ?summary.ports_restarted,
        stopped = ?summary.ports_stopped,
        unchanged = summary.ports_unchanged.len(),
        devices_removed = ?summary.devices_removed,
        "reload applied"
    );
}
