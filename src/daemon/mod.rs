//! `rtu2mqtt run`: one task per port, the device models, and the sink of device updates (MQTT,
//! or JSON lines on stdout for tests and debugging).

pub mod bus_queue;
pub mod event_log;
pub mod identity;
pub mod port_task;
pub mod stdio;

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinHandle;
use tracing::{info, warn};

use crate::device::model::ResolvedPort;
use crate::device_updates::{ControlWrite, DeviceUpdate, Repeats};
use crate::gateway::device_model::{ChannelIndexes, DeviceModel};
use crate::gateway::port_plan::port_plan;
use crate::protocol::LineSettings;
use crate::service::{PortVitals, ServiceHealth};
use crate::status::{PortStatus, StatusHub};
use bus_queue::BusQueue;
use event_log::EventLog;
use port_task::{Handover, PortTask};

/// Room for bursts between the port tasks and the sink.
const UPDATE_QUEUE: usize = 4096;
const WRITE_QUEUE: usize = 256;

/// The running bus side: send control writes in, get device updates out; [`BusControl`] stops
/// it or swaps ports on a reload.
pub struct BusSide {
    pub updates: mpsc::Receiver<DeviceUpdate>,
    pub writes: mpsc::Sender<ControlWrite>,
    pub control: BusControl,
}

/// Which device ids route to which port task's write queue.
type Routes = Arc<Mutex<HashMap<String, mpsc::Sender<ControlWrite>>>>;

/// A port task's write queue, both ends.
type WriteQueue = (mpsc::Sender<ControlWrite>, mpsc::Receiver<ControlWrite>);

/// A port task ready to run.
struct PreparedPort {
    task: PortTask,
    /// The `Added` announcements that must reach the sink before any of its values.
    added: Vec<DeviceUpdate>,
    /// Its write queue.
    writes: mpsc::Sender<ControlWrite>,
}

/// What users outside the port tasks (MQTT RPC, the status page) may know and use of a running
/// port: its configuration and the queue of its bus.
#[derive(Clone, Debug)]
pub struct PortAccess {
    /// As in the logs (`/dev/ttyRS485-1 (9600 8N2)`, `tcp://…`).
    pub name: String,
    pub resolved: Arc<ResolvedPort>,
    /// Its serial settings (none for TCP gateways).
    pub line: Option<LineSettings>,
    pub queue: BusQueue,
    /// Its event packets, for a watcher (a port restarted by a reload starts a new log).
    pub events: Arc<EventLog>,
    /// Whether its config lets it send Fast Modbus frames
    /// ([`fast_modbus_on`](crate::gateway::port_plan::fast_modbus_on)).
    pub fast_modbus: bool,
}

/// The running ports, by [`port_key`] (the device path, or `address:port`); kept up to date
/// across reloads.
pub type PortDirectory = Arc<Mutex<BTreeMap<String, PortAccess>>>;

/// One running port task and what it was started from (to tell on a reload whether it changed).
struct RunningPort {
    resolved: ResolvedPort,
    config: serde_json::Value,
    stop: watch::Sender<bool>,
    /// Hands back the writes the task left unsent, and the devices it knew offline, when it
    /// stops.
    task: oneshot::Receiver<Handover>,
    /// Its write queue, where its devices' routes lead.
    writes: mpsc::Sender<ControlWrite>,
    vitals: Arc<PortVitals>,
    status: Option<Arc<PortStatus>>,
}

/// Owns the port tasks: stops them all at shutdown, and on a reload stops, starts or restarts
/// only the ports whose configuration changed.
pub struct BusControl {
    ports: BTreeMap<String, RunningPort>,
    routes: Routes,
    updates: mpsc::Sender<DeviceUpdate>,
    fast_modbus: bool,
    router: JoinHandle<()>,
    health: Arc<ServiceHealth>,
    directory: PortDirectory,
    /// The status page's registry of ports, when the page is on.
    status: Option<Arc<StatusHub>>,
    /// The repeated values the sink needs from the device models.
    repeats: Repeats,
    /// Shared by the models of all ports and reloads built from one channel list.
    channel_indexes: ChannelIndexes,
}

/// What a reload did, for the log and the tests.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct ReloadSummary {
    pub ports_started: Vec<String>,
    pub ports_stopped: Vec<String>,
    pub ports_restarted: Vec<String>,
    pub ports_unchanged: Vec<String>,
    pub devices_removed: Vec<String>,
}

/// A port is the same port across reloads when it names the same device path or gateway.
fn port_key(port: &ResolvedPort) -> String {
    match (&port.config.path, &port.config.address) {
        (Some(path), _) => path.clone(),
        (None, Some(address)) => format!("{address}:{}", port.config.port.unwrap_or_default()),
        (None, None) => format!("port {}", port.index),
    }
}

/// Starts one task per port and a router for control writes. Every device is announced with
/// [`DeviceUpdate::Added`] before any of its values.
/// `repeats`: the values the sink needs besides the changes (see [`Repeats`]).
pub fn start_bus_side(
    ports: Vec<ResolvedPort>,
    fast_modbus: bool,
    health: Arc<ServiceHealth>,
    repeats: Repeats,
) -> BusSide {
    start_bus_side_with_status(ports, fast_modbus, health, None, repeats)
}

/// [`start_bus_side`], with every port counted for the status page in `status`.
pub fn start_bus_side_with_status(
    ports: Vec<ResolvedPort>,
    fast_modbus: bool,
    health: Arc<ServiceHealth>,
    status: Option<Arc<StatusHub>>,
    repeats: Repeats,
) -> BusSide {
    let (update_tx, update_rx) = mpsc::channel(UPDATE_QUEUE);
    let (write_tx, mut write_rx) = mpsc::channel::<ControlWrite>(WRITE_QUEUE);
    let routes: Routes = Arc::default();
    let router_routes = Arc::clone(&routes);
    let router = tokio::spawn(async move {
        while let Some(mut write) = write_rx.recv().await {
            // A queue closes when its port task stops; a reload that restarts the port has
            // routed the device to the new task's queue by then: look again.
            for _ in 0..2 {
                let port = lock(&router_routes).get(&write.device_id).cloned();
                let Some(port) = port else {
                    warn!(device = %write.device_id, "write for an unknown device");
                    break;
                };
                match port.send(write).await {
                    Ok(()) => break,
                    Err(mpsc::error::SendError(unsent)) => write = unsent,
                }
            }
        }
    });
    let mut control = BusControl {
        ports: BTreeMap::new(),
        routes,
        updates: update_tx,
        fast_modbus,
        router,
        health,
        directory: PortDirectory::default(),
        status,
        repeats,
        channel_indexes: ChannelIndexes::default(),
    };
    for port in ports {
        let prepared = control.prepare_port(&port, &[]);
        for update in prepared.added {
            // Nothing consumes yet and the queue is empty: these never wait.
            let _ = control.updates.try_send(update);
        }
        control.spawn_port(port, prepared.task, prepared.writes);
    }
    BusSide {
        updates: update_rx,
        writes: write_tx,
        control,
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl BusControl {
    /// Sets up a port's device models and write route; returns the port task, not yet running,
    /// and the `Added` announcements that must reach the sink before any of its values. The
    /// models of the devices in `offline` start as known offline.
    fn prepare_port(&mut self, port: &ResolvedPort, offline: &[String]) -> PreparedPort {
        let queue = self.write_queue_for(port);
        self.prepare_port_with(port, queue, offline, &[])
    }

    /// A write queue for `port`, its devices' routes leading there from now on: writes sent
    /// while its task is still being prepared wait in it.
    fn write_queue_for(&self, port: &ResolvedPort) -> WriteQueue {
        let (sender, receiver) = mpsc::channel(WRITE_QUEUE);
        let mut routes = lock(&self.routes);
        for device in &port.devices {
            routes.insert(device.id.clone(), sender.clone());
        }
        (sender, receiver)
    }

    fn prepare_port_with(
        &mut self,
        port: &ResolvedPort,
        (port_write_tx, port_write_rx): WriteQueue,
        offline: &[String],
        held_press_counters: &[(String, Vec<String>)],
    ) -> PreparedPort {
        let plan = port_plan(port, self.fast_modbus);
        let vitals = self.health.add_port(&plan.name, port.devices.len());
        info!(port = %plan.name, devices = plan.devices.len(), fast_modbus = plan.settings.fast_modbus, "serving port");
        let mut models = Vec::new();
        let mut added = Vec::new();
        let mut devices = Vec::new();
        for (index, device) in port.devices.iter().enumerate() {
            let device = Arc::new(device.clone());
            added.push(DeviceUpdate::Added(Arc::clone(&device)));
            devices.push(Arc::clone(&device));
            let known_offline = offline.contains(&device.id);
            let held = held_press_counters
                .iter()
                .find(|(id, _)| *id == device.id)
                .map_or(&[][..], |(_, controls)| controls.as_slice());
            let model =
                DeviceModel::sharing(device, index, self.repeats, &mut self.channel_indexes);
            // A device the stopped task of its port knew offline keeps its `r` on MQTT (the
            // planner keeps it when the device is announced again): the new model holds it
            // too, and clears it at the first good read.
            let model = if known_offline {
                model.known_offline()
            } else {
                model
            };
            models.push(model.holding_press_counters(held));
        }
        let (queue, queued) = BusQueue::new();
        let line = match &plan.endpoint {
            crate::transport::Endpoint::Serial { line, .. } => Some(*line),
            _ => None,
        };
        let events = Arc::new(EventLog::default());
        lock(&self.directory).insert(
            port_key(port),
            PortAccess {
                name: plan.name.clone(),
                resolved: Arc::new(port.clone()),
                line,
                queue: queue.clone(),
                events: Arc::clone(&events),
                fast_modbus: plan.settings.fast_modbus,
            },
        );
        let identity_plans = port
            .devices
            .iter()
            .map(|device| identity::identity_plan(device, plan.settings.response_lag))
            .collect();
        let status = self.status.as_ref().map(|hub| {
            let mut settings = serde_json::to_value(&port.config).unwrap_or_default();
            if let Some(settings) = settings.as_object_mut() {
                settings.remove("devices");
            }
            let status = Arc::new(PortStatus::new(&plan.name, settings, devices));
            hub.add_port(Arc::clone(&status));
            status
        });
        let mut task = PortTask::new(plan, models, self.updates.clone(), port_write_rx)
            .with_vitals(vitals)
            .with_bus_queue(queue.clone(), queued)
            .with_event_log(events)
            .with_identity(identity_plans);
        if let Some(status) = status {
            task = task.with_status(status);
        }
        PreparedPort {
            task,
            added,
            writes: port_write_tx,
        }
    }

    /// The running ports and their bus queues, for MQTT RPC and the status page.
    pub fn port_directory(&self) -> PortDirectory {
        Arc::clone(&self.directory)
    }

    fn spawn_port(
        &mut self,
        port: ResolvedPort,
        task: PortTask,
        writes: mpsc::Sender<ControlWrite>,
    ) {
        let vitals = task.vitals();
        let status = task.status();
        let (stop, stopped) = watch::channel(false);
        let task = run_on_own_thread(&port_key(&port), task, stopped);
        let config = serde_json::to_value(&port.config).unwrap_or_default();
        self.ports.insert(
            port_key(&port),
            RunningPort {
                resolved: port,
                config,
                stop,
                task,
                writes,
                vitals,
                status,
            },
        );
    }

    /// Stops a port task (a transaction in flight is abandoned); its devices stop taking
    /// writes, unless a route to another queue was set up for them already. Returns the port
    /// and what its task handed back: the writes it left unsent, the devices it knew offline.
    async fn stop_port(&mut self, key: &str) -> Option<(ResolvedPort, Handover)> {
        let running = self.ports.remove(key)?;
        lock(&self.directory).remove(key);
        let _ = running.stop.send(true);
        // A task that panicked hands back nothing.
        let handover = running.task.await.unwrap_or_default();
        self.health.remove_port(&running.vitals);
        if let (Some(hub), Some(status)) = (&self.status, &running.status) {
            hub.remove_port(status);
        }
        let mut routes = lock(&self.routes);
        for device in &running.resolved.devices {
            if routes
                .get(&device.id)
                .is_some_and(|route| route.same_channel(&running.writes))
            {
                routes.remove(&device.id);
            }
        }
        Some((running.resolved, handover))
    }

    /// Applies a new configuration: unchanged ports keep running untouched; removed ports stop
    /// and their devices' topics are cleared; new ports start; changed ports restart (their
    /// devices are set up again), and devices no longer configured are cleared. Writes a
    /// stopped task left unsent go to the task that serves their device now, before any newer
    /// write; those of devices no longer configured are dropped.
    pub async fn reload(&mut self, ports: Vec<ResolvedPort>, fast_modbus: bool) -> ReloadSummary {
        let mut summary = ReloadSummary::default();
        let switch_changed = fast_modbus != self.fast_modbus;
        self.fast_modbus = fast_modbus;
        let mut new_ports: BTreeMap<String, ResolvedPort> =
            ports.into_iter().map(|p| (port_key(&p), p)).collect();
        let mut changed = Vec::new();
        let mut moved = Vec::new();
        for (key, old) in &self.ports {
            let unchanged = !switch_changed
                && new_ports.get(key).is_some_and(|new| {
                    old.resolved.devices == new.devices
                        && old.config == serde_json::to_value(&new.config).unwrap_or_default()
                        // Its share of `rate_limit` (which another port's channels change too).
                        && old.resolved.low_priority_read_limit == new.low_priority_read_limit
                });
            if unchanged {
                // Same port, same devices: the running task stays as it is; only its place in
                // the config may have moved (`ports/Load` lists the ports in that order).
                if let Some(new) = new_ports.remove(key) {
                    moved.push((key.clone(), new.index));
                }
                summary.ports_unchanged.push(key.clone());
            } else {
                changed.push(key.clone());
            }
        }
        for (key, index) in moved {
            if let Some(running) = self.ports.get_mut(&key) {
                running.resolved.index = index;
            }
            if let Some(access) = lock(&self.directory).get_mut(&key) {
                if access.resolved.index != index {
                    let mut resolved = (*access.resolved).clone();
                    resolved.index = index;
                    access.resolved = Arc::new(resolved);
                }
            }
        }
        // The new queues first: a write sent while the old tasks stop waits there.
        let queues: BTreeMap<String, WriteQueue> = new_ports
            .iter()
            .map(|(key, port)| (key.clone(), self.write_queue_for(port)))
            .collect();
        let still_configured: Vec<String> = new_ports
            .values()
            .flat_map(|p| p.devices.iter().map(|d| d.id.clone()))
            .collect();
        let mut unsent = Vec::new();
        // The devices the stopped tasks knew offline (a device may move to another port).
        let mut offline = Vec::new();
        let mut held_press_counters = Vec::new();
        for key in changed {
            let Some((old, left)) = self.stop_port(&key).await else {
                continue;
            };
            unsent.extend(left.writes);
            offline.extend(left.offline);
            held_press_counters.extend(left.held_press_counters);
            for device in &old.devices {
                if !still_configured.contains(&device.id) {
                    let _ = self
                        .updates
                        .send(DeviceUpdate::Removed {
                            device_id: device.id.clone(),
                        })
                        .await;
                    summary.devices_removed.push(device.id.clone());
                }
            }
            if new_ports.contains_key(&key) {
                summary.ports_restarted.push(key);
            } else {
                summary.ports_stopped.push(key);
            }
        }
        for write in unsent
            .iter()
            .filter(|w| !still_configured.contains(&w.device_id))
        {
            info!(device = %write.device_id, control = %write.control_id,
                "a write not yet sent is dropped: its device is no longer configured");
        }
        for ((key, port), queue) in new_ports.into_iter().zip(queues.into_values()) {
            if !summary.ports_restarted.contains(&key) {
                summary.ports_started.push(key);
            }
            let carried: Vec<ControlWrite> = unsent
                .iter()
                .filter(|write| port.devices.iter().any(|d| d.id == write.device_id))
                .cloned()
                .collect();
            let prepared = self.prepare_port_with(&port, queue, &offline, &held_press_counters);
            for update in prepared.added {
                let _ = self.updates.send(update).await;
            }
            let task = prepared.task.with_carried_writes(carried);
            self.spawn_port(port, task, prepared.writes);
        }
        summary
    }

    /// Stops every port task (a transaction in flight is abandoned; a write whose request never
    /// went is handed on with the unsent ones) and the write router.
    pub async fn stop(mut self) {
        for running in self.ports.values() {
            let _ = running.stop.send(true);
        }
        let keys: Vec<String> = self.ports.keys().cloned().collect();
        for key in keys {
            self.stop_port(&key).await;
        }
        self.router.abort();
    }
}

/// Runs a port task on a thread and runtime of its own, so that its transport may block the
/// thread for the short waits of a transaction (one system call and one wake-up each, not the
/// reactor's rounds: docs/performance.md, 27 Nov). Its channels to the rest of the daemon work
/// across runtimes; its helper tasks run on the caller's runtime. Should no thread or runtime
/// be had, it runs on the caller's runtime, not blocking.
fn run_on_own_thread(
    key: &str,
    task: PortTask,
    stopped: watch::Receiver<bool>,
) -> oneshot::Receiver<Handover> {
    let (done, handover) = oneshot::channel();
    let callers = tokio::runtime::Handle::try_current().ok();
    // Taken by the thread, or back by the caller if no thread could be started (the failed
    // spawn drops the closure, and the task would go with it).
    let slot = Arc::new(Mutex::new(Some((task, stopped, done))));
    let in_thread = Arc::clone(&slot);
    let helpers = callers.clone();
    let port = key.to_owned();
    let spawned = std::thread::Builder::new()
        .name(thread_name(key))
        .spawn(move || {
            let Some((task, stopped, done)) = lock(&in_thread).take() else {
                return;
            };
            match tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            {
                Ok(runtime) => {
                    let helpers = helpers.unwrap_or_else(|| runtime.handle().clone());
                    let handover = runtime.block_on(task.owning_its_thread(helpers).run(stopped));
                    let _ = done.send(handover);
                }
                Err(err) => {
                    warn!(%port, %err, "no runtime of its own for the port task; it shares the main one");
                    run_on_shared_runtime(helpers.as_ref(), task, stopped, done);
                }
            }
        });
    if let Err(err) = spawned {
        warn!(port = %key, %err, "no thread of its own for the port task; it shares the main one");
        let taken = lock(&slot).take();
        if let Some((task, stopped, done)) = taken {
            run_on_shared_runtime(callers.as_ref(), task, stopped, done);
        }
    }
    handover
}

/// The fallback of [`run_on_own_thread`]: the task on `runtime`, its waits through the reactor.
/// Without a runtime (never in the daemon) it cannot run: its writes are dropped, logged.
fn run_on_shared_runtime(
    runtime: Option<&tokio::runtime::Handle>,
    task: PortTask,
    stopped: watch::Receiver<bool>,
    done: oneshot::Sender<Handover>,
) {
    match runtime {
        Some(runtime) => drop(runtime.spawn(async move {
            let _ = done.send(task.run(stopped).await);
        })),
        None => warn!("the port task has no runtime to run on: its port is not served"),
    }
}

/// A port thread's name as `top -H` and `ps -L` show it: the port's last path component
/// (`ttyRS485-1`, `192.168.1.5:502`), cut to the 15 bytes Linux keeps.
fn thread_name(key: &str) -> String {
    // A NUL (a config path can hold one) would make the thread's start panic.
    let key = key.replace('\0', "");
    let name = key.rsplit('/').next().unwrap_or(&key);
    let mut end = name.len().min(15);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    name.get(..end).unwrap_or("port").to_owned()
}

/// Resolves when SIGTERM or SIGINT arrives. The handlers are installed by this call, not when
/// the future is first polled: READY may reach systemd before the first poll, and a SIGTERM sent
/// in between would otherwise kill the process with the default action instead of a clean stop.
pub fn termination_signal() -> impl std::future::Future<Output = ()> {
    use tokio::signal::unix::{signal, SignalKind};
    let handlers = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    );
    async move {
        match handlers {
            (Ok(mut term), Ok(mut int)) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = int.recv() => {}
                }
            }
            _ => std::future::pending().await,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::termination_signal;

    /// Named after the port, as Linux can keep it (15 bytes, cut on a character boundary).
    #[test]
    fn a_port_thread_is_named_after_its_port() {
        assert_eq!(super::thread_name("/dev/ttyRS485-1"), "ttyRS485-1");
        assert_eq!(super::thread_name("192.168.1.5:502"), "192.168.1.5:502");
        assert_eq!(
            super::thread_name("/dev/serial/by-id/usb-FTDI_FT232R"),
            "usb-FTDI_FT232R"
        );
        assert_eq!(super::thread_name("/dev/ttyПорт-номер"), "ttyПорт-н");
        assert_eq!(super::thread_name("/dev/tty\0S1"), "ttyS1");
    }

    /// A SIGTERM between the call and the first poll is caught, not fatal: `run` sends READY
    /// before its main loop first polls the future (without the handlers installed by the call,
    /// this test process dies of the signal).
    #[test]
    fn a_termination_signal_before_the_first_poll_is_caught() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        runtime.block_on(async {
            let terminate = termination_signal();
            nix::sys::signal::raise(nix::sys::signal::Signal::SIGTERM).unwrap();
            tokio::time::timeout(std::time::Duration::from_secs(10), terminate)
                .await
                .expect("the SIGTERM raised before the first poll is delivered");
        });
    }
}
