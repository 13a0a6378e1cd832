//! The task that owns one bus: it opens the transport (again, with a growing delay, when it
//! fails), asks the scheduler what to do, does it, and turns what happened into device updates.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use tracing::{debug, info, warn};

use crate::gateway::device_model::{apply_port_events, DeviceModel};
use crate::gateway::port_plan::PortPlan;
use crate::mqtt::throttle::{LogBudget, LogDecision};
use crate::port::{Action, Outcome, PortEvent, PortScheduler, ReplyTiming, Transaction};
use crate::service::{BrokerState, PortVitals, ServiceHealth};
use crate::status::hub::PortCommand;
use crate::status::PortStatus;
use crate::transport::{Transport, TransportError};
use crate::updates::{ControlWrite, DeviceUpdate};

const FIRST_REOPEN_DELAY: Duration = Duration::from_millis(500);
const MAX_REOPEN_DELAY: Duration = Duration::from_secs(10);

pub struct PortTask {
    plan_name: String,
    endpoint: crate::transport::Endpoint,
    guard_interval: Duration,
    scheduler: PortScheduler,
    models: Vec<DeviceModel>,
    updates: mpsc::Sender<DeviceUpdate>,
    writes: mpsc::Receiver<ControlWrite>,
    /// Refused `/on` payloads are logged a few per minute: any MQTT client can send them.
    refused_log: LogBudget,
    epoch: Instant,
    /// What systemd's watchdog and status line learn from this task.
    vitals: Option<Arc<PortVitals>>,
    online: Vec<bool>,
    /// A transaction went through the transport since the port was last opened: a port that
    /// opens and fails at once (a gateway that accepts connections and drops them) is still
    /// unusable, its devices go offline and the reopen delay keeps growing.
    transacted: bool,
    /// The status page's counters of this port; none while the status server is off.
    status: Option<Arc<PortStatus>>,
}

/// Refused writes logged per minute on one port; the rest are counted.
const REFUSED_WRITE_LOG_LINES: u32 = 10;

/// The task reports progress at least this often, even with nothing to do on the bus.
const HEARTBEAT: Duration = Duration::from_secs(1);

impl PortTask {
    pub fn new(
        plan: PortPlan,
        models: Vec<DeviceModel>,
        updates: mpsc::Sender<DeviceUpdate>,
        writes: mpsc::Receiver<ControlWrite>,
    ) -> Self {
        Self {
            plan_name: plan.name,
            endpoint: plan.endpoint,
            guard_interval: plan.settings.guard_interval,
            scheduler: PortScheduler::new(plan.settings, plan.devices),
            models,
            updates,
            writes,
            refused_log: LogBudget::new(REFUSED_WRITE_LOG_LINES),
            epoch: Instant::now(),
            vitals: None,
            online: Vec::new(),
            transacted: false,
            status: None,
        }
    }

    /// Counts transactions, errors and values for the status page into `status`.
    pub fn with_status(mut self, status: Arc<PortStatus>) -> Self {
        // The counters' times are on this task's clock.
        self.epoch = status.epoch;
        self.status = Some(status);
        self
    }

    /// The handle given to [`Self::with_status`].
    pub fn status(&self) -> Option<Arc<PortStatus>> {
        self.status.clone()
    }

    /// What the status page asked for (hold or resume a device's polling).
    fn apply_status_commands(&mut self) {
        let Some(status) = &self.status else {
            return;
        };
        let now = self.now();
        for command in status.take_commands() {
            match command {
                PortCommand::Suspend { device, suspended } => {
                    self.scheduler.set_suspended(device, suspended);
                    let report = self.scheduler.device_report(device, now);
                    status.record(|stats| stats.set_schedule(device, report));
                }
            }
        }
    }

    /// The status page's one hook into a transaction: counted after its updates went out (an
    /// event round trip ends at the hand-over to MQTT).
    fn record_transaction(&self, started: Duration, transaction: &Transaction, outcome: &Outcome) {
        let Some(status) = &self.status else {
            return;
        };
        let now = self.now();
        status.record(|stats| {
            if let Some(device) = stats.transaction_done(started, now, transaction, outcome) {
                stats.events_published(device, now);
            }
            if stats.schedule_due(now) {
                for device in 0..self.scheduler.device_count() {
                    stats.set_schedule(device, self.scheduler.device_report(device, now));
                }
            }
        });
    }

    /// Reports open/closed, progress and devices online into `vitals`.
    pub fn with_vitals(mut self, vitals: Arc<PortVitals>) -> Self {
        self.vitals = Some(vitals);
        self
    }

    /// The handle given to [`Self::with_vitals`] (a detached one if none was).
    pub fn vitals(&self) -> Arc<PortVitals> {
        self.vitals
            .clone()
            .unwrap_or_else(|| ServiceHealth::new(BrokerState::NotUsed).add_port("", 0))
    }

    fn beat(&self) {
        if let Some(vitals) = &self.vitals {
            vitals.beat();
        }
    }

    fn set_open(&self, open: bool) {
        if let Some(vitals) = &self.vitals {
            vitals.set_open(open);
        }
        if let Some(status) = &self.status {
            status.record(|stats| stats.set_open(open));
        }
    }

    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// Serves the bus until `shutdown` turns true.
    pub async fn run(mut self, mut shutdown: watch::Receiver<bool>) {
        let mut delay = FIRST_REOPEN_DELAY;
        // Since when the port has been unusable: its devices go offline after their timeout.
        let mut closed_since = self.now();
        loop {
            let opened = tokio::select! {
                opened = Transport::open(&self.endpoint) => opened,
                _ = shutdown.changed() => return,
            };
            match opened {
                Ok(mut transport) => {
                    transport.set_guard_interval(self.guard_interval);
                    info!(port = %self.plan_name, "port open");
                    self.set_open(true);
                    self.transacted = false;
                    match self.serve(transport, &mut shutdown).await {
                        Ok(()) => return,
                        Err(err) => warn!(port = %self.plan_name, %err, "port failed; reopening"),
                    }
                    self.set_open(false);
                    if self.transacted {
                        delay = FIRST_REOPEN_DELAY;
                        closed_since = self.now();
                    }
                }
                Err(err) => {
                    warn!(port = %self.plan_name, %err, retry_in = ?delay, "cannot open the port");
                    self.set_open(false);
                }
            }
            // Wake at least every FIRST_REOPEN_DELAY meanwhile, so that devices go offline on
            // time even while the reopen delay is long.
            let reopen_at = Instant::now() + delay;
            loop {
                self.beat();
                let events = self.scheduler.port_unavailable(self.now(), closed_since);
                self.dispatch(events).await;
                let wake = reopen_at.min(Instant::now() + FIRST_REOPEN_DELAY);
                tokio::select! {
                    _ = tokio::time::sleep_until(wake) => {}
                    _ = shutdown.changed() => return,
                }
                if Instant::now() >= reopen_at {
                    break;
                }
            }
            delay = (delay * 2).min(MAX_REOPEN_DELAY);
        }
    }

    async fn serve(
        &mut self,
        mut transport: Transport,
        shutdown: &mut watch::Receiver<bool>,
    ) -> Result<(), TransportError> {
        loop {
            if *shutdown.borrow() {
                return Ok(());
            }
            self.beat();
            while let Ok(write) = self.writes.try_recv() {
                self.handle_write(write).await;
            }
            self.apply_status_commands();
            match self.scheduler.next(self.now()) {
                Action::Transmit(transaction) => {
                    let started = self.now();
                    // Shutdown never waits for the bus: a transaction may take seconds (long
                    // timeouts, a guard interval, a babbling line).
                    let result = tokio::select! {
                        result = transport.transact(&transaction) => result,
                        _ = shutdown.changed() => return Ok(()),
                    };
                    self.transacted |= result.is_ok();
                    let (outcome, timing) = match &result {
                        Ok((outcome, timing)) => (outcome.clone(), *timing),
                        Err(_) => (Outcome::NoReply, ReplyTiming::default()),
                    };
                    let recorded = self.status.as_ref().map(|_| outcome.clone());
                    let events = self.scheduler.complete_timed(self.now(), outcome, timing);
                    self.dispatch(events).await;
                    if let Some(outcome) = recorded {
                        self.record_transaction(started, &transaction, &outcome);
                    }
                    result?;
                }
                Action::Wait { until } => {
                    let wake = (self.epoch + until).min(Instant::now() + HEARTBEAT);
                    tokio::select! {
                        _ = tokio::time::sleep_until(wake) => {}
                        write = self.writes.recv() => match write {
                            Some(write) => self.handle_write(write).await,
                            None => return Ok(()),
                        },
                        _ = shutdown.changed() => return Ok(()),
                    }
                }
            }
        }
    }

    async fn handle_write(&mut self, write: ControlWrite) {
        let now = self.now();
        let Some(model) = self.models.iter_mut().find(|m| m.id() == write.device_id) else {
            debug!(device = %write.device_id, "write for a device not on this port");
            return;
        };
        let mut updates = Vec::new();
        match model.take_write(&write.control_id, &write.payload, &mut updates) {
            Ok(register_writes) => {
                for register_write in register_writes {
                    self.scheduler.queue_write(now, register_write);
                }
            }
            Err(reason) => {
                let decision = self.refused_log.check(std::time::Instant::now());
                if let LogDecision::Log { suppressed_before } = decision {
                    warn!(device = %write.device_id, control = %write.control_id, %reason, suppressed_before, "write refused");
                }
            }
        }
        self.send(updates).await;
    }

    async fn dispatch(&mut self, events: Vec<PortEvent>) {
        if let Some(vitals) = &self.vitals {
            if self.online.len() != self.models.len() {
                self.online = vec![false; self.models.len()];
            }
            let mut changed = false;
            for event in &events {
                if let PortEvent::Online { device } | PortEvent::Offline { device } = event {
                    if let Some(slot) = self.online.get_mut(*device) {
                        *slot = matches!(event, PortEvent::Online { .. });
                        changed = true;
                    }
                }
            }
            if changed {
                vitals.set_devices_online(self.online.iter().filter(|o| **o).count());
            }
        }
        let mut updates = Vec::new();
        apply_port_events(&mut self.models, events, &mut updates);
        self.send(updates).await;
    }

    async fn send(&self, updates: Vec<DeviceUpdate>) {
        if let Some(status) = &self.status {
            let now = self.now();
            status.record(|stats| {
                for update in &updates {
                    stats.observe_update(update, now);
                }
            });
        }
        for update in updates {
            // The MQTT side drains this queue into its latest-value-per-topic state at once, so
            // waiting here only happens if that task itself is stuck.
            if self.updates.send(update).await.is_err() {
                return;
            }
        }
    }
}
