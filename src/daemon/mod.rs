//! `rtu2mqtt run`: one task per port, the device models, and the sink of device updates (MQTT,
//! or JSON lines on stdout for tests and debugging).

pub mod device_model;
pub mod port_plan;
pub mod port_task;
pub mod stdio;

use std::collections::HashMap;
use std::sync::Arc;

use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;
use tracing::{info, warn};

use crate::device::model::ResolvedPort;
use crate::updates::{ControlWrite, DeviceUpdate};
use device_model::DeviceModel;
use port_plan::port_plan;
use port_task::PortTask;

/// Room for bursts between the port tasks and the sink.
const UPDATE_QUEUE: usize = 4096;
const WRITE_QUEUE: usize = 256;

/// The running bus side: send control writes in, get device updates out.
pub struct BusSide {
    pub updates: mpsc::Receiver<DeviceUpdate>,
    pub writes: mpsc::Sender<ControlWrite>,
    pub tasks: JoinSet<()>,
}

/// Starts one task per port and a router for control writes. Every device is announced with
/// [`DeviceUpdate::Added`] before any of its values.
pub fn start_bus_side(
    ports: Vec<ResolvedPort>,
    fast_modbus: bool,
    shutdown: watch::Receiver<bool>,
) -> BusSide {
    let (update_tx, update_rx) = mpsc::channel(UPDATE_QUEUE);
    let (write_tx, mut write_rx) = mpsc::channel::<ControlWrite>(WRITE_QUEUE);
    let mut routes: HashMap<String, mpsc::Sender<ControlWrite>> = HashMap::new();
    let mut tasks = JoinSet::new();
    for port in ports {
        let plan = port_plan(&port, fast_modbus);
        info!(port = %plan.name, devices = plan.devices.len(), fast_modbus = plan.settings.fast_modbus, "serving port");
        let (port_write_tx, port_write_rx) = mpsc::channel(WRITE_QUEUE);
        let mut models = Vec::new();
        for (index, device) in port.devices.into_iter().enumerate() {
            let device = Arc::new(device);
            routes.insert(device.id.clone(), port_write_tx.clone());
            // The queue is empty at this point: these never wait.
            let _ = update_tx.try_send(DeviceUpdate::Added(Arc::clone(&device)));
            models.push(DeviceModel::new(device, index));
        }
        let task = PortTask::new(plan, models, update_tx.clone(), port_write_rx);
        tasks.spawn(task.run(shutdown.clone()));
    }
    let mut stop = shutdown;
    tasks.spawn(async move {
        loop {
            let write = tokio::select! {
                write = write_rx.recv() => write,
                _ = stop.wait_for(|stop| *stop) => None,
            };
            let Some(write) = write else { return };
            match routes.get(&write.device_id) {
                Some(port) => {
                    let _ = port.send(write).await;
                }
                None => warn!(device = %write.device_id, "write for an unknown device"),
            }
        }
    });
    BusSide {
        updates: update_rx,
        writes: write_tx,
        tasks,
    }
}

/// Resolves when SIGTERM or SIGINT arrives.
pub async fn termination_signal() {
    use tokio::signal::unix::{signal, SignalKind};
    match (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) {
        (Ok(mut term), Ok(mut int)) => {
            tokio::select! {
                _ = term.recv() => {}
                _ = int.recv() => {}
            }
        }
        _ => std::future::pending().await,
    }
}
