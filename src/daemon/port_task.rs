//! The task that owns one bus: it opens the transport (again, with a growing delay, when it
//! fails), asks the scheduler what to do, does it, and turns what happened into device updates.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use tracing::{debug, info, warn};

use super::bus_queue::{
    BusQueue, BusQueueError, BusQueueReceiver, QueuedJob, QueuedRaw, QueuedTransaction,
};
use super::event_log::EventLog;
use super::identity::{read_identity, IdentityPlan, IdentityRead};
use crate::device_updates::{ControlWrite, DeviceIdentity, DeviceUpdate};
use crate::gateway::device_model::{apply_port_events, DeviceModel};
use crate::gateway::port_plan::{PortPlan, ReconnectRule};
use crate::mqtt::throttle::{LogBudget, LogDecision};
use crate::port::scheduler::{write_key, WriteKey};
use crate::port::{
    GuardIntervals, NextStep, PortEvent, PortScheduler, ReplyTiming, Transaction,
    TransactionOutcome,
};
use crate::protocol::LineSettings;
use crate::service::{BrokerState, PortVitals, ServiceHealth};
use crate::status::hub::PortCommand;
use crate::status::PortStatus;
use crate::transport::fifo::{self, TriggerChange};
use crate::transport::raw::RawRequest;
use crate::transport::{Endpoint, Transport, TransportError};

const FIRST_REOPEN_DELAY: Duration = Duration::from_millis(500);
const MAX_REOPEN_DELAY: Duration = Duration::from_secs(10);

/// What a stopped task hands to the one that replaces it (a reload that restarts its port).
#[derive(Debug, Default)]
pub struct Handover {
    /// The writes it took or was given and never put on the wire, oldest first.
    pub writes: Vec<ControlWrite>,
    /// The devices its models knew offline ([`DeviceModel::is_offline`]): their new models
    /// start so ([`DeviceModel::known_offline`]), as the MQTT side keeps their `r`.
    pub offline: Vec<String>,
    /// Per device, the press counters whose next 0 its model held back
    /// ([`DeviceModel::held_press_counters`]): their new models hold it too.
    pub held_press_counters: Vec<(String, Vec<String>)>,
}

pub struct PortTask {
    plan_name: String,
    endpoint: crate::transport::Endpoint,
    guard_intervals: GuardIntervals,
    scheduler: PortScheduler,
    models: Vec<DeviceModel>,
    updates: mpsc::Sender<DeviceUpdate>,
    writes: mpsc::Receiver<ControlWrite>,
    /// Writes handed on by the task this one replaces (a reload restarted the port): older
    /// than anything in `writes`, so they go first.
    carried: VecDeque<ControlWrite>,
    /// The writes taken from `writes`, the registers each was queued as and the order it was
    /// taken in, for as long as one of those may still be unsent: handed on if the task stops
    /// before they go. A register leaves an entry once a write to it that carried the entry
    /// (queued writes to one register merge) has been done or given up.
    taken: Vec<(ControlWrite, Vec<WriteKey>, u64)>,
    /// The order number the next taken write gets.
    next_taken: u64,
    /// The register of the write in flight and the order numbers it carries (those below).
    write_sent: Option<(WriteKey, u64)>,
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
    /// The port has been this task's: opened, or failed for another reason than another
    /// program holding it. Until then its devices may be that program's (wb-mqtt-serial still
    /// running): they are not marked offline, and MQTT leaves their Wiren Board topics alone
    /// ([`DeviceUpdate::BusServed`]).
    bus_served: bool,
    /// The port's receive FIFO could not be set to 1 byte: said once, not at every reopen.
    fifo_held_reported: bool,
    /// Transactions asked from outside the scheduler (RPC), served between its own.
    queued: Option<BusQueueReceiver>,
    /// A queued transaction waiting for its device's hold-off after a failure to end (from
    /// when it may go: [`PortScheduler::queued_may_go_from`]); the queue waits behind it, so
    /// jobs keep their order.
    deferred: Option<(Duration, BusWork)>,
    /// The sending side of that queue, for this port's identity reads.
    queue: Option<BusQueue>,
    identity: IdentityState,
    /// The status page's counters of this port; none while the status server is off.
    status: Option<Arc<PortStatus>>,
    /// Event packets as they came, for a watcher through RPC (`rtu2mqtt events`).
    event_log: Option<Arc<EventLog>>,
    /// Kept between transactions (emptied after each), so that a read of many values
    /// allocates no lists: its events, then the updates made of them.
    port_events: Vec<PortEvent>,
    update_buffer: Vec<DeviceUpdate>,
    /// A TCP gateway's connection is closed after this long without a successful transaction.
    reconnect: Option<ReconnectRule>,
    /// The task has its thread and runtime to itself: its serial transports block the thread
    /// for short waits ([`Transport::block_short_waits`]), and its helper tasks run on this
    /// other runtime (a blocked thread would hold them up for as long as the bus is busy).
    own_thread: Option<tokio::runtime::Handle>,
    /// The open connection's transactions under that rule.
    connection: Option<ConnectionWatch>,
}

/// wb-mqtt-serial's `TPortOpenCloseLogic::CloseIfNeeded` over one open connection, a cycle
/// being one transaction: a gateway that keeps its connection but answers nothing (its serial
/// side stuck, a path that broke without a FIN) is closed and reopened.
#[derive(Debug, Clone, Copy)]
struct ConnectionWatch {
    rule: ReconnectRule,
    last_success: Duration,
    /// Failed transactions still allowed before the connection may be closed.
    remaining: u32,
}

impl ConnectionWatch {
    fn opened(rule: ReconnectRule, now: Duration) -> Self {
        Self {
            rule,
            last_success: now,
            remaining: rule.failed_cycles,
        }
    }

    /// A transaction ended at `now`, answered or not: true when the connection is to be closed.
    fn transaction_done(&mut self, now: Duration, answered: bool) -> bool {
        if answered {
            self.last_success = now;
            self.remaining = self.rule.failed_cycles;
        }
        self.remaining = self.remaining.saturating_sub(1);
        self.remaining == 0 && now.saturating_sub(self.last_success) > self.rule.after
    }
}

/// Who each device is (model, serial number, firmware), read when it comes online or restarts,
/// by a worker task through the bus queue, one device at a time.
#[derive(Default)]
struct IdentityState {
    /// Per device: what to read (none when the device cannot say).
    plans: Vec<Option<IdentityPlan>>,
    /// Per device: what was published (the serial number last read among it), standing for the
    /// parts a later read gets no answer for.
    known: Vec<DeviceIdentity>,
    /// Per device: a read is asked for (`Some`), and whether the worker has begun it.
    reading: Vec<Option<Arc<AtomicBool>>>,
    /// Per device: the device restarted or came online while its read was under way: what
    /// that read got may be the device before (a replaced one), so it is thrown away and the
    /// device read again.
    asked_again: Vec<bool>,
    /// Per device: a read was wanted while its polling was held (an operator, a site tool
    /// changing its address); asked once the hold ends.
    held_back: Vec<bool>,
    /// Per device: after a read that got nothing (noise, a full bus queue, a reopen), when to
    /// try again and the delay that led there.
    retries: IdentityRetries,
    requests: Option<mpsc::UnboundedSender<(usize, Arc<AtomicBool>)>>,
    results: Option<mpsc::Receiver<(usize, IdentityRead)>>,
}

/// When to read a device's identity again after a read that got nothing for one of its
/// registers: channels held to a minimum firmware wait for it, a replaced device is noticed by
/// it, and a device that stays online is otherwise never asked again (reads start when it
/// comes online or restarts). 2 s (what gets nothing is most often a noise burst or a queue
/// busy with a site tool), doubling to 10 minutes.
#[derive(Debug, Default)]
struct IdentityRetries {
    /// Per device: (when, the delay that led there).
    due: Vec<Option<(Duration, Duration)>>,
}

const FIRST_IDENTITY_RETRY: Duration = Duration::from_secs(2);
const MAX_IDENTITY_RETRY: Duration = Duration::from_secs(600);

impl IdentityRetries {
    fn with_devices(count: usize) -> Self {
        Self {
            due: vec![None; count],
        }
    }

    /// The read of `device` at `now` got nothing: tried again later, each time later still.
    fn failed(&mut self, device: usize, now: Duration) {
        if let Some(slot) = self.due.get_mut(device) {
            let delay = slot.map_or(FIRST_IDENTITY_RETRY, |(_, last)| {
                (last * 2).min(MAX_IDENTITY_RETRY)
            });
            *slot = Some((now + delay, delay));
        }
    }

    /// The read of `device` got an answer: no retry.
    fn succeeded(&mut self, device: usize) {
        if let Some(slot) = self.due.get_mut(device) {
            *slot = None;
        }
    }

    /// Devices whose retry is due at `now` (their entries stay, for the next delay, until the
    /// read's result comes).
    fn due_at(&self, now: Duration) -> impl Iterator<Item = usize> + '_ {
        self.due
            .iter()
            .enumerate()
            .filter(move |(_, slot)| slot.is_some_and(|(at, _)| at <= now))
            .map(|(device, _)| device)
    }
}

/// A queued job that takes bus time.
enum BusWork {
    Transaction(QueuedTransaction),
    Raw(QueuedRaw),
}

impl BusWork {
    fn line(&self) -> Option<LineSettings> {
        match self {
            BusWork::Transaction(job) => job.line,
            BusWork::Raw(job) => job.line,
        }
    }

    /// Its caller gave up waiting (a timeout dropped the receiving side).
    fn withdrawn(&self) -> bool {
        match self {
            BusWork::Transaction(job) => job.reply.is_closed(),
            BusWork::Raw(job) => job.reply.is_closed(),
        }
    }

    fn refuse(self, why: BusQueueError) {
        match self {
            BusWork::Transaction(job) => {
                let _ = job.reply.send(Err(why));
            }
            BusWork::Raw(job) => {
                let _ = job.reply.send(Err(why));
            }
        }
    }
}

/// The open bus, and the settings it was switched to for queued transactions (a serial port
/// only; `None` while it is at the port's own settings).
struct OpenBus {
    transport: Option<Transport>,
    away: Option<LineSettings>,
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
            guard_intervals: plan.settings.guard_intervals.clone(),
            scheduler: PortScheduler::new(plan.settings, plan.devices),
            models,
            updates,
            writes,
            carried: VecDeque::new(),
            taken: Vec::new(),
            next_taken: 0,
            write_sent: None,
            refused_log: LogBudget::new(REFUSED_WRITE_LOG_LINES),
            epoch: Instant::now(),
            vitals: None,
            online: Vec::new(),
            transacted: false,
            bus_served: false,
            fifo_held_reported: false,
            queued: None,
            deferred: None,
            queue: None,
            identity: IdentityState::default(),
            status: None,
            event_log: None,
            port_events: Vec::new(),
            update_buffer: Vec::new(),
            reconnect: plan.reconnect,
            connection: None,
            own_thread: None,
        }
    }

    /// The task will run alone on its thread and runtime: its serial transports may block the
    /// thread for short waits, which costs nothing else there and saves the reactor's rounds.
    /// Its helper tasks (the identity reader) run on `helpers`.
    pub fn owning_its_thread(mut self, helpers: tokio::runtime::Handle) -> Self {
        self.own_thread = Some(helpers);
        self
    }

    async fn open_transport(&self, endpoint: &Endpoint) -> Result<Transport, TransportError> {
        let mut transport = Transport::open(endpoint).await?;
        if self.own_thread.is_some() {
            transport.block_short_waits();
        }
        Ok(transport)
    }

    /// Writes that a stopped task of this port left unsent ([`Self::run`]'s result), to go
    /// before any new one.
    pub fn with_carried_writes(mut self, writes: Vec<ControlWrite>) -> Self {
        self.carried.extend(writes);
        self
    }

    /// Serves the transactions sent through `queue` (RPC, the status page), between its own.
    pub fn with_bus_queue(mut self, queue: BusQueue, queued: BusQueueReceiver) -> Self {
        self.queue = Some(queue);
        self.queued = Some(queued);
        self
    }

    /// Reads who each device is when it comes online or restarts (through the bus queue: give
    /// one with [`Self::with_bus_queue`]); one plan per device, in model order.
    pub fn with_identity(mut self, plans: Vec<Option<IdentityPlan>>) -> Self {
        let count = plans.len();
        self.identity.plans = plans;
        self.identity.known = vec![DeviceIdentity::default(); count];
        self.identity.reading = vec![None; count];
        self.identity.asked_again = vec![false; count];
        self.identity.held_back = vec![false; count];
        self.identity.retries = IdentityRetries::with_devices(count);
        self
    }

    /// Starts the worker that reads identities one device at a time.
    fn start_identity_worker(&mut self) {
        let Some(queue) = self.queue.clone() else {
            return;
        };
        if self.identity.plans.iter().all(Option::is_none) {
            return;
        }
        let (requests, mut pending) = mpsc::unbounded_channel::<(usize, Arc<AtomicBool>)>();
        let (results_tx, results) = mpsc::channel(self.identity.plans.len().max(1));
        let plans = self.identity.plans.clone();
        let line = self
            .home_line()
            .unwrap_or(LineSettings::WIREN_BOARD_DEFAULT);
        let worker = async move {
            while let Some((device, started)) = pending.recv().await {
                let Some(Some(plan)) = plans.get(device) else {
                    continue;
                };
                started.store(true, Ordering::Relaxed);
                let read = read_identity(&queue, line, plan).await;
                if results_tx.send((device, read)).await.is_err() {
                    return;
                }
            }
        };
        match &self.own_thread {
            Some(helpers) => drop(helpers.spawn(worker)),
            None => drop(tokio::spawn(worker)),
        }
        self.identity.requests = Some(requests);
        self.identity.results = Some(results);
    }

    fn ask_identity(&mut self, device: usize) {
        if self.scheduler.polling_held(device) {
            // Its hold says no reads: a site tool may be changing its address, or an operator
            // working on it.
            if let Some(held_back) = self.identity.held_back.get_mut(device) {
                *held_back = true;
            }
            return;
        }
        let (Some(requests), Some(Some(_)), Some(reading)) = (
            &self.identity.requests,
            self.identity.plans.get(device),
            self.identity.reading.get_mut(device),
        ) else {
            return;
        };
        match reading {
            // Under way: it may have read part of the device before.
            Some(started) if started.load(Ordering::Relaxed) => {
                if let Some(again) = self.identity.asked_again.get_mut(device) {
                    *again = true;
                }
            }
            // Still queued: it reads the device as it is now.
            Some(_) => {}
            None => {
                let started = Arc::new(AtomicBool::new(false));
                if requests.send((device, started.clone())).is_ok() {
                    *reading = Some(started);
                }
            }
        }
    }

    /// Asks again for the identities whose retry is due (a retry stays due until its read's
    /// result comes: one under way is not asked again), and for those held back by a hold that
    /// has ended.
    fn ask_due_identity_retries(&mut self) {
        let now = self.now();
        let reading = &self.identity.reading;
        let mut due: Vec<usize> = self
            .identity
            .retries
            .due_at(now)
            .filter(|&device| reading.get(device).is_some_and(Option::is_none))
            .collect();
        for (device, held_back) in self.identity.held_back.iter_mut().enumerate() {
            if *held_back && !self.scheduler.polling_held(device) {
                *held_back = false;
                due.push(device);
            }
        }
        for device in due {
            self.ask_identity(device);
        }
    }

    /// A device's identity came: published (what got no answer as it was known); a serial
    /// number other than the last one means another device took its place, which is set up
    /// afresh.
    async fn identity_read(&mut self, device: usize, read: IdentityRead) {
        if let Some(reading) = self.identity.reading.get_mut(device) {
            *reading = None;
        }
        if self
            .identity
            .asked_again
            .get_mut(device)
            .is_some_and(std::mem::take)
        {
            // Part of it may be the device before its restart (a replaced one).
            self.ask_identity(device);
            return;
        }
        let Some(model) = self.models.get(device) else {
            return;
        };
        let device_id = model.id().to_owned();
        let now = self.now();
        if read.complete() {
            self.identity.retries.succeeded(device);
        } else {
            debug!(port = %self.plan_name, device = %device_id, unanswered = ?read.unanswered,
                "identity not fully readable now: tried again later");
            self.identity.retries.failed(device, now);
            if read == IdentityRead::nothing() {
                return;
            }
        }
        // The serial number published is the number read ([`IdentityRead::serial`] as text).
        let previous = self
            .identity
            .known
            .get(device)
            .and_then(|known| known.serial_number.as_deref()?.parse::<u32>().ok());
        let replaced = matches!((previous, read.serial), (Some(old), Some(new)) if old != new);
        match (previous, read.serial) {
            (Some(old), Some(new)) if old != new => {
                warn!(
                    port = %self.plan_name,
                    device = %device_id,
                    old_serial = old,
                    new_serial = new,
                    "another device answers at this address (serial number changed): a replaced \
                     device? setting it up afresh"
                );
                self.scheduler.set_up_again(device);
            }
            _ => debug!(
                port = %self.plan_name,
                device = %device_id,
                model = ?read.identity.model,
                serial = ?read.identity.serial_number,
                firmware = ?read.identity.firmware,
                "device identified"
            ),
        }
        if let Some(serial) = read.serial {
            // For the RPC's scan: which device at an address is the one polled here.
            if let Some(queue) = &self.queue {
                queue.note_serial(device, serial);
            }
        }
        // Channels held to a minimum firmware: read now, or never on this firmware. (A firmware
        // that got no answer keeps them waiting for the retry.)
        if !read.unanswered.firmware {
            let mut events =
                self.scheduler
                    .firmware_known(now, device, read.identity.firmware.as_deref());
            if !events.is_empty() {
                self.dispatch(&mut events).await;
            }
        }
        let Some(known) = self.identity.known.get_mut(device) else {
            return;
        };
        // Another device: what got no answer is unknown, not the device before's.
        *known = if replaced {
            read.over(&DeviceIdentity::default())
        } else {
            read.over(known)
        };
        let identity = known.clone();
        self.send(vec![DeviceUpdate::Identity {
            device_id,
            identity,
        }])
        .await;
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
        for command in status.take_commands() {
            match command {
                // Until resumed.
                PortCommand::Suspend { device, suspended } => {
                    self.hold_polling(device, suspended.then_some(Duration::MAX));
                }
            }
        }
    }

    /// The status page's one hook into a transaction: counted after its updates went out (an
    /// event round trip ends at the hand-over to MQTT).
    fn record_transaction(
        &self,
        started: Duration,
        transaction: &Transaction,
        outcome: &TransactionOutcome,
        timing: ReplyTiming,
    ) {
        let Some(status) = &self.status else {
            return;
        };
        let now = self.now();
        status.record(|stats| {
            if let Some(device) =
                stats.transaction_done(started, now, transaction, outcome, timing.another_master)
            {
                stats.events_published(device, now);
            }
            if stats.schedule_due(now) {
                for device in 0..self.scheduler.device_count() {
                    stats.set_schedule(device, self.scheduler.device_report(device, now));
                }
            }
        });
    }

    /// Records the event packets it receives into `log` while someone watches it.
    pub fn with_event_log(mut self, log: Arc<EventLog>) -> Self {
        self.event_log = Some(log);
        self
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

    /// Makes a serial port's UART hand received bytes over as they come, as wb-mqtt-serial does
    /// when it opens a port (and leaves it so): with the kernel's default trigger (8 bytes on a
    /// 16550A) a reply's end reaches the reader 4 characters late, which every transaction would
    /// wait for, and the fillers of an arbitration may be held until the winner's frame is in.
    /// Where it cannot be lowered, the transport allows for the trigger it reads.
    fn lower_receive_fifo_trigger(&mut self) {
        let Endpoint::Serial { path, .. } = &self.endpoint else {
            return;
        };
        match fifo::lower_to_one_byte(Path::new(path), &fifo::sysfs_tty()) {
            TriggerChange::NotReported | TriggerChange::AlreadyOne => {}
            TriggerChange::Lowered { previous, .. } => info!(
                port = %self.plan_name,
                "receive FIFO set to hand bytes over one at a time (it collected {previous}; \
                 rx_trig_bytes, as wb-mqtt-serial sets it)"
            ),
            TriggerChange::Holds { .. } if self.fifo_held_reported => {}
            TriggerChange::Holds { trigger, why } => {
                self.fifo_held_reported = true;
                warn!(
                port = %self.plan_name,
                "the UART hands received bytes over {trigger} at a time and could not be set to 1 \
                 ({why}): replies are waited for that much longer (`sudo rtu2mqtt prepare-ports \
                 -c CONFIG` sets it; the systemd service runs it at every start)"
                );
            }
        }
    }

    /// Serves the port until `shutdown`; then hands back, for the task that replaces it, the
    /// writes it took or was given and never put on the wire, oldest first (a reload that
    /// restarts the port must not lose a user's command), and the devices it knew offline.
    /// Every update it made has been sent by then.
    pub async fn run(mut self, shutdown: watch::Receiver<bool>) -> Handover {
        self.serve_until_stopped(shutdown).await;
        self.handover()
    }

    /// What the stopped task hands on ([`Self::run`]).
    fn handover(&mut self) -> Handover {
        Handover {
            writes: self.unsent_writes(),
            offline: self
                .models
                .iter()
                .filter(|model| model.is_offline())
                .map(|model| model.id().to_owned())
                .collect(),
            held_press_counters: self
                .models
                .iter()
                .map(|model| (model.id().to_owned(), model.held_press_counters()))
                .filter(|(_, held)| !held.is_empty())
                .collect(),
        }
    }

    fn unsent_writes(&mut self) -> Vec<ControlWrite> {
        let unsent: Vec<WriteKey> = self.scheduler.unsent_writes().collect();
        let mut writes: Vec<ControlWrite> = self.carried.drain(..).collect();
        writes.extend(
            self.taken
                .drain(..)
                .filter(|(_, keys, _)| keys.iter().any(|key| unsent.contains(key)))
                .map(|(write, _, _)| write),
        );
        // Closed first, so that no write can come in after the last one is taken.
        self.writes.close();
        while let Ok(write) = self.writes.try_recv() {
            writes.push(write);
        }
        writes
    }

    async fn serve_until_stopped(&mut self, mut shutdown: watch::Receiver<bool>) {
        self.start_identity_worker();
        let mut delay = FIRST_REOPEN_DELAY;
        // Since when the port has been unusable: its devices go offline after their timeout.
        let mut closed_since = self.now();
        let mut open_failures = OpenFailures::default();
        loop {
            self.lower_receive_fifo_trigger();
            let opened = tokio::select! {
                opened = self.open_transport(&self.endpoint) => opened,
                _ = shutdown.changed() => return,
            };
            match opened {
                Ok(transport) => {
                    match open_failures.opened(Instant::now()) {
                        Some((unusable, tries)) => {
                            info!(port = %self.plan_name, ?unusable, tries, "port open again")
                        }
                        None => info!(port = %self.plan_name, "port open"),
                    }
                    self.serve_bus().await;
                    self.set_open(true);
                    self.transacted = false;
                    match self.serve(transport, &mut shutdown).await {
                        Ok(()) => return,
                        Err(err) => {
                            warn!(port = %self.plan_name, %err, "port failed; reopening");
                            // That said it: a reopen that fails at once is not said again.
                            open_failures.told(Instant::now());
                        }
                    }
                    self.set_open(false);
                    if self.transacted {
                        delay = FIRST_REOPEN_DELAY;
                        closed_since = self.now();
                    }
                }
                Err(err) => {
                    // The first failure is told, then now and then while it lasts: an adapter
                    // unplugged for a day is one line an hour, not one every 10 s.
                    let told = open_failures.failed(Instant::now());
                    let held = held_by_another_program(&err);
                    if !held {
                        self.serve_bus().await;
                    }
                    match told {
                        Told::Quietly(tries) => {
                            debug!(port = %self.plan_name, %err, tries, "cannot open the port (still)");
                        }
                        Told::Again { unusable, tries } => {
                            warn!(port = %self.plan_name, %err, ?unusable, tries, retry_every = ?MAX_REOPEN_DELAY,
                                "the port still cannot be opened");
                        }
                        Told::First if held => {
                            warn!(port = %self.plan_name, %err, retry_in = ?delay,
                                "cannot open the port: another program holds it locked (another \
                                 rtu2mqtt, a `rtu2mqtt run` in a terminal, or a tool built on the \
                                 same serial library; wb-mqtt-serial takes no lock and is not seen \
                                 here, see `rtu2mqtt prepare-ports`)");
                        }
                        Told::First if permission_denied(&err) => {
                            warn!(port = %self.plan_name, %err, retry_in = ?delay,
                                "cannot open the port: no permission. The service's unit gives \
                                 it the dialout group; run by hand, add your user to the group \
                                 that owns the port (usually dialout: `sudo usermod -aG dialout \
                                 $USER`, then log in again)");
                        }
                        Told::First if is_network(&err) => {
                            warn!(port = %self.plan_name, %err, retry_in = ?delay,
                                "cannot connect to the gateway (powered and on the network? its \
                                 address and port right in the config?); tried again until it \
                                 answers");
                        }
                        Told::First => {
                            warn!(port = %self.plan_name, %err, retry_in = ?delay,
                                "cannot open the port (a USB adapter not plugged in, or a typo in \
                                 the config?); tried again until it opens");
                        }
                    }
                    self.set_open(false);
                }
            }
            // Wake at least every FIRST_REOPEN_DELAY meanwhile, so that devices go offline on
            // time even while the reopen delay is long.
            let reopen_at = Instant::now() + delay;
            loop {
                self.beat();
                if self.bus_served {
                    // Writes wait in the scheduler, their retry time running: given up when it
                    // is over, not sent hours later when the port is back.
                    self.take_waiting_writes().await;
                    let now = self.now();
                    let mut events = self.scheduler.port_unavailable(now, closed_since);
                    events.extend(self.scheduler.expire_writes(now));
                    self.dispatch(&mut events).await;
                } else {
                    // Another program holds the port, and its devices' topics are that
                    // program's: it carries out the writes sent to them (it hears the same
                    // `/on`). Kept, they would go out again, late, once the port is ours.
                    let mut dropped = self.carried.len();
                    self.carried.clear();
                    while self.writes.try_recv().is_ok() {
                        dropped += 1;
                    }
                    if dropped > 0 {
                        info!(port = %self.plan_name, dropped, "writes dropped: another program holds the port and serves its devices");
                    }
                }
                self.refuse_queued("it failed and is being reopened");
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
        transport: Transport,
        shutdown: &mut watch::Receiver<bool>,
    ) -> Result<(), TransportError> {
        let mut bus = OpenBus {
            transport: Some(transport),
            away: None,
        };
        let now = self.now();
        self.connection = self
            .reconnect
            .map(|rule| ConnectionWatch::opened(rule, now));
        // A queued transaction may go before the scheduler's next one, never two in a row while
        // the scheduler has something to send: event polls keep their slots.
        let mut queued_turn = true;
        loop {
            if *shutdown.borrow() {
                return Ok(());
            }
            self.beat();
            self.take_waiting_writes().await;
            while let Some(Ok((device, read))) =
                self.identity.results.as_mut().map(mpsc::Receiver::try_recv)
            {
                self.identity_read(device, read).await;
            }
            self.ask_due_identity_retries();
            if queued_turn {
                if let Some(job) = self.next_queued_job() {
                    queued_turn = false;
                    tokio::select! {
                        result = self.serve_queued(&mut bus, job) => result?,
                        _ = shutdown.changed() => return Ok(()),
                    }
                    continue;
                }
            }
            self.apply_status_commands();
            let next = self.scheduler.next(self.now());
            if matches!(next, NextStep::Wait { .. }) {
                // Nothing of the scheduler's to send: a deferred job whose time has come goes
                // now, whoever went last.
                if let Some(job) = self.ready_deferred_job() {
                    queued_turn = false;
                    tokio::select! {
                        result = self.serve_queued(&mut bus, job) => result?,
                        _ = shutdown.changed() => return Ok(()),
                    }
                    continue;
                }
            }
            match next {
                NextStep::Transmit(transaction) => {
                    let started = self.now();
                    queued_turn = true;
                    self.note_write_sent();
                    // The transaction is the scheduler's in flight from here: a port lost on
                    // the way back to its own settings fails it like a port lost during it
                    // (left in flight, the scheduler would wait for its outcome for ever).
                    let back_home = if bus.away.is_some() {
                        self.switch_line(&mut bus, None).await
                    } else {
                        Ok(())
                    };
                    let result = match (back_home, bus.transport.as_mut()) {
                        (Err(err), _) => Err(err),
                        (Ok(()), None) => Err(self.lost_port()),
                        (Ok(()), Some(transport)) => {
                            // Shutdown never waits for the bus: a transaction may take seconds
                            // (long timeouts, a guard interval, a babbling line).
                            transport.set_guard_interval(
                                self.guard_intervals.before(transaction.request.address),
                            );
                            let finished = tokio::select! {
                                result = transport.transact(&transaction) => Some(result),
                                _ = shutdown.changed() => None,
                            };
                            let Some(result) = finished else {
                                // Stopping. A request still waiting for the line never went:
                                // a write in it is handed on with the unsent ones.
                                if transport.request_not_sent() {
                                    self.scheduler.forget_unsent_in_flight();
                                }
                                return Ok(());
                            };
                            result
                        }
                    };
                    self.transacted |= result.is_ok();
                    let (outcome, timing, failure) = match result {
                        Ok((outcome, timing)) => (outcome, timing, None),
                        Err(err) => (
                            TransactionOutcome::NoReply,
                            ReplyTiming::default(),
                            Some(err),
                        ),
                    };
                    let answered = matches!(outcome, TransactionOutcome::Reply(_));
                    let recorded = self.status.as_ref().map(|_| outcome.clone());
                    if let (Some(log), Some((address, packet))) =
                        (&self.event_log, outcome.event_packet())
                    {
                        log.record(std::time::Instant::now(), address, packet);
                    }
                    let mut events = std::mem::take(&mut self.port_events);
                    self.scheduler
                        .complete_into(self.now(), outcome, timing, &mut events);
                    self.note_writes_completed(&events);
                    self.dispatch(&mut events).await;
                    self.port_events = events;
                    if let Some(outcome) = recorded {
                        self.record_transaction(started, &transaction, &outcome, timing);
                    }
                    if let Some(err) = failure {
                        return Err(err);
                    }
                    self.watch_connection(&transaction, answered)?;
                }
                NextStep::Wait { until } => {
                    let deferred_from = self.deferred.as_ref().map(|(from, _)| *from);
                    let until = deferred_from.map_or(until, |from| until.min(from));
                    let wake = (self.epoch + until).min(Instant::now() + HEARTBEAT);
                    tokio::select! {
                        _ = tokio::time::sleep_until(wake) => {}
                        write = self.writes.recv() => match write {
                            Some(write) => self.handle_write(write).await,
                            None => return Ok(()),
                        },
                        Some((device, read)) = next_identity(&mut self.identity.results) => {
                            self.identity_read(device, read).await;
                        }
                        job = next_queued(&mut self.queued), if self.deferred.is_none() => match job {
                            Some(job) => {
                                if let Some(job) = self.take_job(job).and_then(|job| self.defer_if_held(job)) {
                                    queued_turn = false;
                                    tokio::select! {
                                        result = self.serve_queued(&mut bus, job) => result?,
                                        _ = shutdown.changed() => return Ok(()),
                                    }
                                }
                            }
                            // Nobody can queue any more: stop listening.
                            None => self.queued = None,
                        },
                        _ = shutdown.changed() => return Ok(()),
                    }
                }
            }
        }
    }

    /// Carries out at once what a queued job asks that takes no bus time (a hold on a
    /// device's polling); the transaction to serve, if it is one.
    /// The next queued job that may go now: the deferred one once its time has come (nothing
    /// else before it), else the next from the queue unless its device is held off (then it is
    /// deferred). Jobs that take no bus time are carried out on the way.
    fn next_queued_job(&mut self) -> Option<BusWork> {
        if self.deferred.is_some() {
            return self.ready_deferred_job();
        }
        while let Some(job) = self.queued.as_mut().and_then(|q| q.try_recv().ok()) {
            if let Some(work) = self.take_job(job) {
                return self.defer_if_held(work);
            }
        }
        None
    }

    /// The deferred job once its time has come and its device's hold-off has not moved since
    /// it was deferred (a failure of the scheduler's own request to it in the meantime starts
    /// a new one: its late reply must not be the job's answer); deferred again if it has.
    fn ready_deferred_job(&mut self) -> Option<BusWork> {
        let now = self.now();
        match self.deferred.take() {
            Some((from, job)) if from <= now => self.defer_if_held(job),
            held => {
                self.deferred = held;
                None
            }
        }
    }

    /// `work` if it may go now, else `None` with it kept as the deferred job.
    fn defer_if_held(&mut self, work: BusWork) -> Option<BusWork> {
        let from = match &work {
            BusWork::Transaction(job) => {
                self.scheduler.queued_may_go_from(&job.transaction.request)
            }
            BusWork::Raw(raw) => raw
                .request
                .modbus_address()
                .map_or(Duration::ZERO, |address| {
                    self.scheduler.address_may_go_from(address)
                }),
        };
        if from <= self.now() {
            return Some(work);
        }
        debug!(port = %self.plan_name, "queued transaction waits for its device's hold-off after a failure");
        self.deferred = Some((from, work));
        None
    }

    fn take_job(&mut self, job: QueuedJob) -> Option<BusWork> {
        match job {
            QueuedJob::Transaction(transaction) => Some(BusWork::Transaction(transaction)),
            QueuedJob::Raw(raw) => Some(BusWork::Raw(raw)),
            QueuedJob::HoldPolling {
                device,
                hold_for,
                done,
            } => {
                self.hold_polling(device, hold_for);
                let _ = done.send(());
                None
            }
        }
    }

    /// One queued transaction, at the settings it asks for. Its caller gets the outcome; only a
    /// broken port is an error here (the port task reopens it).
    async fn serve_queued(
        &mut self,
        bus: &mut OpenBus,
        job: BusWork,
    ) -> Result<(), TransportError> {
        if job.withdrawn() {
            // Its caller timed out before its turn.
            return Ok(());
        }
        let home = self.home_line();
        let wanted = match (job.line(), home) {
            (Some(line), Some(home)) if line != home => Some(line),
            _ => None,
        };
        if wanted != bus.away {
            if let Err(err) = self.switch_line(bus, wanted).await {
                let line = wanted.or(home).map(|l| l.to_string()).unwrap_or_default();
                job.refuse(BusQueueError::Settings {
                    line,
                    reason: err.to_string(),
                });
                // Back at the port's own settings, or the port task reopens the port.
                return self.switch_line(bus, None).await;
            }
        }
        let Some(transport) = bus.transport.as_mut() else {
            job.refuse(BusQueueError::Stopped);
            return Err(self.lost_port());
        };
        let job = match job {
            BusWork::Transaction(job) => job,
            BusWork::Raw(raw) => {
                debug!(port = %self.plan_name, away = ?bus.away, "queued raw transfer");
                let result = transport.transfer_raw(&raw.request).await;
                // A Modbus request sent raw: the scheduler holds its device off unless its
                // whole reply came, as after any queued transaction that failed.
                if let Some(address) = raw.request.modbus_address() {
                    let answered = result
                        .as_ref()
                        .is_ok_and(|answer| RawRequest::answered_by(answer, address));
                    let now = self.now();
                    self.scheduler.raw_done(now, address, answered);
                }
                return match result {
                    Ok(answer) => {
                        let _ = raw.reply.send(Ok(answer));
                        Ok(())
                    }
                    Err(err) => {
                        let _ = raw
                            .reply
                            .send(Err(BusQueueError::PortClosed(err.to_string())));
                        Err(err)
                    }
                };
            }
        };
        debug!(port = %self.plan_name, away = ?bus.away, "queued transaction");
        let started = self.now();
        transport.set_guard_interval(self.guard_intervals.before(job.transaction.request.address));
        let result = transport.transact(&job.transaction).await;
        // The scheduler holds a device whose transaction failed off until a late reply to it
        // could no longer come (`PortScheduler::queued_done`), as after its own failures.
        let (outcome, timing) = match &result {
            Ok((outcome, timing)) => (outcome.clone(), *timing),
            Err(_) => (TransactionOutcome::NoReply, ReplyTiming::default()),
        };
        let now = self.now();
        self.scheduler
            .queued_done(now, &job.transaction, started, outcome, timing);
        match result {
            Ok((outcome, timing)) => {
                // The status page counts it with the scheduler's own: the line was as busy.
                self.record_transaction(started, &job.transaction, &outcome, timing);
                let answered = matches!(outcome, TransactionOutcome::Reply(_));
                let _ = job.reply.send(Ok(outcome));
                self.watch_connection(&job.transaction, answered)
            }
            Err(err) => {
                let _ = job
                    .reply
                    .send(Err(BusQueueError::PortClosed(err.to_string())));
                Err(err)
            }
        }
    }

    /// Counts a transaction against the connection's reconnection rule (a broadcast, which
    /// nobody answers, not at all): an error when the connection is to be closed and reopened.
    fn watch_connection(
        &mut self,
        transaction: &Transaction,
        answered: bool,
    ) -> Result<(), TransportError> {
        let now = self.now();
        let Some(watch) = self.connection.as_mut() else {
            return Ok(());
        };
        if !transaction.request.expects_reply() || !watch.transaction_done(now, answered) {
            return Ok(());
        }
        Err(TransportError::Unanswered {
            name: self.plan_name.clone(),
            after: now.saturating_sub(watch.last_success),
        })
    }

    /// The serial settings of the port (none for TCP gateways).
    fn home_line(&self) -> Option<LineSettings> {
        match &self.endpoint {
            Endpoint::Serial { line, .. } => Some(*line),
            _ => None,
        }
    }

    /// Reopens the serial port at `away` (its own settings when `None`). The old handle is
    /// closed first: the port is opened exclusively.
    async fn switch_line(
        &self,
        bus: &mut OpenBus,
        away: Option<LineSettings>,
    ) -> Result<(), TransportError> {
        let Endpoint::Serial {
            path,
            line,
            frame_timeout,
        } = &self.endpoint
        else {
            return Ok(());
        };
        let busy_until = bus.transport.as_ref().and_then(Transport::line_busy_until);
        bus.transport = None;
        bus.away = None;
        let endpoint = Endpoint::Serial {
            path: path.clone(),
            line: away.unwrap_or(*line),
            frame_timeout: *frame_timeout,
        };
        let mut transport = self.open_transport(&endpoint).await?;
        transport.continues(busy_until);
        debug!(port = %self.plan_name, settings = %endpoint.name(), "port settings switched");
        bus.transport = Some(transport);
        bus.away = away;
        Ok(())
    }

    fn lost_port(&self) -> TransportError {
        TransportError::Closed {
            name: self.plan_name.clone(),
            serial: matches!(self.endpoint, Endpoint::Serial { .. }),
        }
    }

    /// Answers every queued transaction with "port closed" (the port is being reopened).
    fn refuse_queued(&mut self, why: &str) {
        if let Some((_, job)) = self.deferred.take() {
            job.refuse(BusQueueError::PortClosed(why.to_owned()));
        }
        let Some(queued) = self.queued.as_mut() else {
            return;
        };
        let mut jobs = Vec::new();
        while let Ok(job) = queued.try_recv() {
            jobs.push(job);
        }
        for job in jobs {
            match job {
                QueuedJob::Transaction(job) => {
                    BusWork::Transaction(job).refuse(BusQueueError::PortClosed(why.to_owned()));
                }
                QueuedJob::Raw(raw) => {
                    BusWork::Raw(raw).refuse(BusQueueError::PortClosed(why.to_owned()));
                }
                // A hold takes no bus: the scheduler keeps it while the port is reopened.
                job @ QueuedJob::HoldPolling { .. } => {
                    let _ = self.take_job(job);
                }
            }
        }
    }

    /// Holds the polling of the port's `device`-th device for `hold_for` from now, or resumes
    /// it; the status page sees the change.
    fn hold_polling(&mut self, device: usize, hold_for: Option<Duration>) {
        let now = self.now();
        let until = hold_for.map(|hold| now.saturating_add(hold));
        self.scheduler.hold_polling(device, until);
        if let Some(status) = &self.status {
            let report = self.scheduler.device_report(device, now);
            status.record(|stats| stats.set_schedule(device, report));
        }
    }

    /// Takes the writes handed on by the task this one replaced, then those in the queue, in
    /// that order (oldest first).
    async fn take_waiting_writes(&mut self) {
        while let Some(write) = self.carried.pop_front() {
            self.handle_write(write).await;
        }
        while let Ok(write) = self.writes.try_recv() {
            self.handle_write(write).await;
        }
    }

    /// Called with the scheduler's transaction in flight: if it is a write, it carries every
    /// write taken so far for its register (queued writes to one register merge).
    fn note_write_sent(&mut self) {
        self.write_sent = self
            .scheduler
            .write_in_flight()
            .map(|key| (key, self.next_taken));
    }

    /// After the transaction in flight completed with `events`: a write done or given up is no
    /// longer owed for the writes it carried. Kept as owed, they would be handed on at a reload
    /// together with a later write to the same register and written again (a bit field's other
    /// bits set back to what they were, a command bit acting twice).
    fn note_writes_completed(&mut self, events: &[PortEvent]) {
        let Some((sent, carried_below)) = self.write_sent.take() else {
            return;
        };
        let finished = events.iter().any(|event| match *event {
            PortEvent::WriteDone {
                device,
                register_type,
                address,
            }
            | PortEvent::WriteFailed {
                device,
                register_type,
                address,
                permanent: true,
            } => (device, register_type, address) == sent,
            _ => false,
        });
        if !finished {
            return;
        }
        for (_, keys, order) in &mut self.taken {
            if *order < carried_below {
                keys.retain(|key| *key != sent);
            }
        }
        self.taken.retain(|(_, keys, _)| !keys.is_empty());
    }

    async fn handle_write(&mut self, write: ControlWrite) {
        let now = self.now();
        let Some(model) = self.models.iter_mut().find(|m| m.id() == write.device_id) else {
            debug!(device = %write.device_id, "write for a device not on this port");
            return;
        };
        let mut updates = Vec::new();
        // Writes the scheduler refuses (no request can carry them): their failure goes to the
        // model as any given-up write's.
        let mut refused = Vec::new();
        match model.take_write(&write.control_id, &write.payload, &mut updates) {
            Ok(register_writes) => {
                let keys = register_writes.iter().map(write_key).collect();
                for register_write in register_writes {
                    refused.extend(self.scheduler.queue_write(now, register_write));
                }
                // Only what may still be unsent is kept (the scheduler's queue bounds it).
                let unsent: Vec<WriteKey> = self.scheduler.unsent_writes().collect();
                self.taken
                    .retain(|(_, keys, _)| keys.iter().any(|key| unsent.contains(key)));
                self.taken.push((write, keys, self.next_taken));
                self.next_taken += 1;
            }
            Err(reason) => {
                let decision = self.refused_log.check(std::time::Instant::now());
                match decision {
                    LogDecision::Log {
                        suppressed_before: 0,
                    } => {
                        warn!(device = %write.device_id, control = %write.control_id, %reason, "write refused");
                    }
                    LogDecision::Log { suppressed_before } => {
                        warn!(device = %write.device_id, control = %write.control_id, %reason, suppressed_before, "write refused");
                    }
                    LogDecision::Skip => {}
                }
            }
        }
        self.send(updates).await;
        if !refused.is_empty() {
            self.dispatch(&mut refused).await;
        }
    }

    /// Turns `events` (emptied) into device updates and sends them.
    async fn dispatch(&mut self, events: &mut Vec<PortEvent>) {
        if let Some(vitals) = &self.vitals {
            if self.online.len() != self.models.len() {
                self.online = vec![false; self.models.len()];
            }
            let mut changed = false;
            for event in events.iter() {
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
        for event in events.iter() {
            if let PortEvent::Online { device } | PortEvent::Rebooted { device } = event {
                self.ask_identity(*device);
            }
        }
        let mut updates = std::mem::take(&mut self.update_buffer);
        apply_port_events(&mut self.models, events.drain(..), &mut updates);
        let now = self.now();
        crate::gateway::device_model::stop_unsupported_reads(
            &mut self.models,
            &mut self.scheduler,
            now,
        );
        self.send_all(&mut updates).await;
        self.update_buffer = updates;
    }

    /// The port is this task's from now on: its devices' topics are this gateway's (once).
    async fn serve_bus(&mut self) {
        if self.bus_served {
            return;
        }
        self.bus_served = true;
        let served = self
            .models
            .iter()
            .map(|model| DeviceUpdate::BusServed {
                device_id: model.id().to_string(),
            })
            .collect();
        self.send(served).await;
    }

    async fn send(&self, mut updates: Vec<DeviceUpdate>) {
        self.send_all(&mut updates).await;
    }

    /// Sends `updates`, emptying it.
    async fn send_all(&self, updates: &mut Vec<DeviceUpdate>) {
        if let Some(status) = &self.status {
            let now = self.now();
            status.record(|stats| {
                for update in updates.iter() {
                    stats.observe_update(update, now);
                }
            });
        }
        for update in updates.drain(..) {
            // The MQTT side drains this queue into its latest-value-per-topic state at once, so
            // waiting here only happens if that task itself is stuck (`try_send` first: most
            // of a read's many values find room, and need no future).
            let update = match self.updates.try_send(update) {
                Ok(()) => continue,
                Err(mpsc::error::TrySendError::Closed(_)) => return,
                Err(mpsc::error::TrySendError::Full(update)) => update,
            };
            if self.updates.send(update).await.is_err() {
                return;
            }
        }
    }
}

/// The next queued transaction; never resolves when there is no queue.
async fn next_queued(queued: &mut Option<BusQueueReceiver>) -> Option<QueuedJob> {
    match queued {
        Some(queued) => queued.recv().await,
        None => std::future::pending().await,
    }
}

/// The next identity read; never resolves without a worker.
async fn next_identity(
    results: &mut Option<mpsc::Receiver<(usize, IdentityRead)>>,
) -> Option<(usize, IdentityRead)> {
    match results {
        Some(results) => results.recv().await,
        None => std::future::pending().await,
    }
}

/// How a port's failures to open are told: the first one, then at growing intervals (1 min,
/// 10 min, then every hour) while they last.
#[derive(Debug, Default)]
struct OpenFailures {
    since: Option<Instant>,
    tries: u32,
    told_at: Option<Instant>,
}

/// What to say of one failure to open.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Told {
    /// The first: everything about it.
    First,
    /// Still failing, after this long: said again.
    Again { unusable: Duration, tries: u32 },
    /// Still failing: at debug level only.
    Quietly(u32),
}

impl OpenFailures {
    fn failed(&mut self, now: Instant) -> Told {
        self.tries += 1;
        let since = *self.since.get_or_insert(now);
        let Some(told_at) = self.told_at else {
            self.told_at = Some(now);
            return Told::First;
        };
        let unusable = now.saturating_duration_since(since);
        let gap = match told_at.saturating_duration_since(since) {
            told if told < Duration::from_secs(60) => Duration::from_secs(60),
            told if told < Duration::from_secs(600) => Duration::from_secs(540),
            _ => Duration::from_secs(3600),
        };
        if now.saturating_duration_since(told_at) >= gap {
            self.told_at = Some(now);
            Told::Again {
                unusable,
                tries: self.tries,
            }
        } else {
            Told::Quietly(self.tries)
        }
    }

    /// The port was said to have failed at `now`: failures to reopen it count from then.
    fn told(&mut self, now: Instant) {
        self.since.get_or_insert(now);
        self.told_at = Some(now);
    }

    /// The port opened: how long it was unusable and how many tries failed, if any.
    fn opened(&mut self, now: Instant) -> Option<(Duration, u32)> {
        let failures = std::mem::take(self);
        failures
            .since
            .map(|since| (now.saturating_duration_since(since), failures.tries))
    }
}

/// Whether opening failed because the port is taken: `EBUSY`, or the exclusive lock (TIOCEXCL)
/// another program set, which the serial library reports only in words.
fn held_by_another_program(err: &TransportError) -> bool {
    match err {
        TransportError::Open { source, .. } => {
            source.raw_os_error() == Some(nix::libc::EBUSY)
                || source.to_string().contains("exclusive lock")
        }
        _ => false,
    }
}

/// Whether opening failed for want of permission on the device node.
/// A TCP port (a gateway) that could not be reached, as opposed to a serial one.
fn is_network(err: &TransportError) -> bool {
    matches!(
        err,
        TransportError::Connect { .. } | TransportError::ConnectTimeout { .. }
    )
}

fn permission_denied(err: &TransportError) -> bool {
    matches!(err, TransportError::Open { source, .. }
        if source.kind() == std::io::ErrorKind::PermissionDenied
            || source.raw_os_error() == Some(nix::libc::EACCES))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An unplugged adapter is told once, then after a minute, ten minutes, and every hour:
    /// not every 10 s for as long as it lasts; opening again says how long it took.
    #[test]
    fn failures_to_open_are_told_at_growing_intervals() {
        let start = Instant::now();
        let at = |secs: u64| start + Duration::from_secs(secs);
        let mut failures = OpenFailures::default();
        let mut told = Vec::new();
        for secs in (0..=7300).step_by(10) {
            match failures.failed(at(secs)) {
                Told::Quietly(_) => {}
                Told::First => told.push(secs),
                Told::Again { unusable, .. } => told.push(unusable.as_secs()),
            }
        }
        assert_eq!(told, vec![0, 60, 600, 4200]);
        assert_eq!(
            failures.opened(at(7310)),
            Some((Duration::from_secs(7310), 731))
        );
        assert_eq!(failures.opened(at(7320)), None, "forgotten once open");
        assert_eq!(failures.failed(at(7330)), Told::First);
        // A port that failed while open was said to: its reopen failing at once is not.
        let mut failures = OpenFailures::default();
        failures.told(at(0));
        assert_eq!(failures.failed(at(1)), Told::Quietly(1));
        assert!(matches!(failures.failed(at(61)), Told::Again { .. }));
    }

    /// wb-mqtt-serial's `TPortOpenCloseLogic`: closed once no transaction succeeded for the
    /// timeout and over the cycles; a success starts both over.
    #[test]
    fn a_connection_is_closed_after_its_timeout_and_cycles_without_an_answer() {
        let ms = Duration::from_millis;
        let rule = ReconnectRule {
            after: ms(2000),
            failed_cycles: 3,
        };
        let mut watch = ConnectionWatch::opened(rule, ms(0));
        // Time alone is not enough: 3 failed transactions are.
        assert!(!watch.transaction_done(ms(2500), false));
        assert!(!watch.transaction_done(ms(2600), false));
        assert!(watch.transaction_done(ms(2700), false));
        // Cycles alone are not enough: the timeout is.
        let mut watch = ConnectionWatch::opened(rule, ms(0));
        for at in 1..=20 {
            assert!(!watch.transaction_done(ms(at * 100), false), "at {at}");
        }
        assert!(watch.transaction_done(ms(2001), false));
        // A success starts both over.
        let mut watch = ConnectionWatch::opened(rule, ms(0));
        assert!(!watch.transaction_done(ms(1900), false));
        assert!(!watch.transaction_done(ms(1950), true));
        assert!(!watch.transaction_done(ms(3000), false));
        assert!(!watch.transaction_done(ms(3900), false));
        assert!(watch.transaction_done(ms(3951), false));
    }

    /// A port task for a relay module at 20 on a port nobody answers on.
    fn relay_task(writes: mpsc::Receiver<ControlWrite>) -> PortTask {
        relay_task_at("/dev/rtu2mqtt-test-no-such-port", writes)
    }

    /// [`relay_task`] on the serial port at `path`.
    fn relay_task_at(path: &str, writes: mpsc::Receiver<ControlWrite>) -> PortTask {
        use crate::config::parse::SourceText;
        let config = serde_json::json!({"ports": [{
            "path": path, "baud_rate": 115200, "stop_bits": 2,
            "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]
        }]});
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        let templates = Path::new(env!("CARGO_MANIFEST_DIR")).join("templates");
        let library = crate::config::TemplateLibrary::load_dirs(&[templates]);
        let port = crate::device::resolve_config(&loaded, &library)
            .unwrap()
            .remove(0);
        let plan = crate::gateway::port_plan::port_plan(&port, true);
        let models = port
            .devices
            .iter()
            .enumerate()
            .map(|(index, device)| {
                DeviceModel::new(
                    Arc::new(device.clone()),
                    index,
                    crate::device_updates::Repeats::None,
                )
            })
            .collect();
        let (updates, _) = mpsc::channel(64);
        PortTask::new(plan, models, updates, writes)
    }

    fn write(control: &str, payload: &str) -> ControlWrite {
        ControlWrite {
            device_id: "relay6_20".into(),
            control_id: control.into(),
            payload: payload.into(),
        }
    }

    /// A reload that restarts the port must not lose a user's command: what the task took and
    /// never sent, what it was handed and never took up, and what still waits in its queue are
    /// handed back, oldest first; a write to an unknown control is not.
    #[tokio::test]
    async fn a_stopping_task_hands_back_the_writes_it_never_sent() {
        let (sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        // Taken into the scheduler: the device is not set up yet, so they wait.
        task.handle_write(write("K1", "1")).await;
        task.handle_write(write("No such control", "1")).await;
        task.handle_write(write("K2", "1")).await;
        sender.send(write("K3", "1")).await.unwrap();
        let mut task = task.with_carried_writes(vec![write("K4", "1")]);
        let handed: Vec<(String, String)> = task
            .unsent_writes()
            .into_iter()
            .map(|w| (w.control_id, w.payload))
            .collect();
        let expected: Vec<(String, String)> = ["K4", "K1", "K2", "K3"]
            .into_iter()
            .map(|c| (c.to_owned(), "1".to_owned()))
            .collect();
        assert_eq!(handed, expected);
        assert!(
            sender.send(write("K5", "1")).await.is_err(),
            "the queue is closed once the task has stopped taking writes"
        );
    }

    /// A stopping task names the devices it knew offline, so that their new models start so
    /// (and clear the `r` the MQTT side keeps at their first good read); a device that came
    /// back is not named.
    #[tokio::test]
    async fn a_stopping_task_names_the_devices_it_knew_offline() {
        let (_sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        assert!(task.handover().offline.is_empty());
        task.dispatch(&mut vec![PortEvent::Offline { device: 0 }])
            .await;
        assert_eq!(task.handover().offline, ["relay6_20"]);
        task.dispatch(&mut vec![PortEvent::Online { device: 0 }])
            .await;
        assert!(task.handover().offline.is_empty());
    }

    /// A stopping task hands on the press counters whose next 0 its models hold back (a
    /// counter published before its device went offline), so that the models after a reload
    /// hold it too and do not publish the 0 a restarted device counts from.
    #[tokio::test]
    async fn a_stopping_task_hands_on_the_press_counters_it_holds() {
        let (_sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        task.dispatch(&mut vec![PortEvent::Values {
            device: 0,
            span: crate::port::RegisterSpan::new(crate::protocol::RegisterType::Input, 464, 1),
            values: vec![3].into(),
        }])
        .await;
        assert!(task.handover().held_press_counters.is_empty());
        task.dispatch(&mut vec![PortEvent::Offline { device: 0 }])
            .await;
        assert_eq!(
            task.handover().held_press_counters,
            [(
                "relay6_20".to_owned(),
                vec!["Input 0 single press counter".to_owned()]
            )]
        );
    }

    /// The daemon runs each port task on a thread and runtime of its own (no runtime here: a
    /// task put on the caller's would panic). Stopped, it hands back the writes it never sent.
    #[test]
    fn a_port_task_on_its_own_thread_runs_stops_and_hands_back_its_writes() {
        let (sender, receiver) = mpsc::channel(8);
        let task = relay_task(receiver).with_carried_writes(vec![write("K4", "1")]);
        let (stop, stopped) = watch::channel(false);
        let key = "/dev/rtu2mqtt-test-own-thread";
        let unsent = crate::daemon::run_on_own_thread(key, task, stopped);
        sender
            .blocking_send(write("K1", "0"))
            .expect("the task takes writes");
        // Named after its port, as `top -H` shows it (a poll on the kernel's thread list: the
        // thread may not have started yet).
        let named = |name: &str| {
            std::fs::read_dir("/proc/self/task").is_ok_and(|tasks| {
                tasks.flatten().any(|task| {
                    std::fs::read_to_string(task.path().join("comm"))
                        .is_ok_and(|comm| comm.trim_end() == name)
                })
            })
        };
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while !named("rtu2mqtt-test-o") {
            assert!(
                std::time::Instant::now() < deadline,
                "no thread named after the port"
            );
            std::thread::yield_now();
        }
        stop.send(true).expect("the task listens");
        let handed: Vec<String> = unsent
            .blocking_recv()
            .expect("the task ran and stopped")
            .writes
            .into_iter()
            .map(|w| w.control_id)
            .collect();
        assert_eq!(handed, ["K4", "K1"]);
    }

    /// A task that owns its thread opens its serial transports with blocking short waits; one
    /// on a shared runtime does not.
    #[tokio::test]
    async fn a_task_on_its_own_thread_opens_its_transports_with_blocking_waits() {
        use std::os::fd::AsFd;
        let pty = nix::pty::openpty(None, None).expect("a pty");
        let path = nix::unistd::ttyname(pty.slave.as_fd()).expect("its name");
        let path = path.to_string_lossy();
        for owning in [false, true] {
            let (_sender, receiver) = mpsc::channel(8);
            let mut task = relay_task_at(&path, receiver);
            if owning {
                task = task.owning_its_thread(tokio::runtime::Handle::current());
            }
            let transport = task.open_transport(&task.endpoint).await.expect("opens");
            assert_eq!(transport.blocks_short_waits(), owning);
        }
    }

    /// Review of the port threads (27 Nov 2026): when no thread can be started (EAGAIN: the
    /// process or user thread limit, memory on a small controller), `run_on_own_thread` means
    /// to run the task on the caller's runtime. But the failed `spawn` drops its closure, and
    /// with it the port's current-thread runtime, inside the caller's runtime: tokio panics
    /// ("Cannot drop a runtime in a context where blocking is not allowed") in `spawn_port`,
    /// i.e. in the daemon's start or reload. Run in a child process that may start no thread
    /// (another user, RLIMIT_NPROC 1).
    #[test]
    fn a_port_task_that_gets_no_thread_runs_on_the_callers_runtime() {
        const CHILD: &str = "RTU2MQTT_REVIEW_NO_THREADS";
        const NAME: &str =
            "daemon::port_task::tests::a_port_task_that_gets_no_thread_runs_on_the_callers_runtime";
        if std::env::var_os(CHILD).is_none() {
            let output = std::process::Command::new(std::env::current_exe().unwrap())
                .args(["--exact", NAME, "--test-threads=1", "--nocapture"])
                .env(CHILD, "1")
                .env("RUST_BACKTRACE", "0")
                .output()
                .expect("the child runs");
            assert!(
                output.status.success(),
                "the child failed:\n{}{}",
                String::from_utf8_lossy(&output.stdout),
                String::from_utf8_lossy(&output.stderr)
            );
            return;
        }
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("a runtime");
        // Root is not bound by RLIMIT_NPROC: the child becomes nobody. Another user is, and
        // already runs more than one process.
        // SAFETY: geteuid only reads the process's credentials.
        if unsafe { nix::libc::geteuid() } == 0 {
            // SAFETY: plain system calls; glibc applies setuid/setgid to every thread.
            unsafe {
                assert_eq!(nix::libc::setgroups(0, std::ptr::null()), 0);
                assert_eq!(nix::libc::setgid(65534), 0);
                assert_eq!(nix::libc::setuid(65534), 0);
            }
        }
        nix::sys::resource::setrlimit(nix::sys::resource::Resource::RLIMIT_NPROC, 1, 1)
            .expect("the limit");
        assert!(
            std::thread::Builder::new().spawn(|| {}).is_err(),
            "threads still start: the test cannot show anything here"
        );
        let handed = runtime.block_on(async {
            let (_sender, receiver) = mpsc::channel(8);
            let task = relay_task(receiver).with_carried_writes(vec![write("K4", "1")]);
            let (stop, stopped) = watch::channel(false);
            let unsent = crate::daemon::run_on_own_thread("test port", task, stopped);
            tokio::task::yield_now().await;
            stop.send(true).expect("the task listens");
            unsent.await.expect("the task ran and stopped")
        });
        let handed: Vec<String> = handed.writes.into_iter().map(|w| w.control_id).collect();
        assert_eq!(handed, ["K4"]);
    }

    /// Review of the port task (27 Nov 2026), finding 4: a write that went and was answered
    /// stayed among the writes owed to a replacing task as long as a later write to the same
    /// register was queued; a reload then handed on both, and the first was written again
    /// (merged into the second: its bits of a bit field set back, a command bit acting twice).
    /// Only writes taken after the one in flight are owed once it is done.
    #[tokio::test]
    async fn a_write_done_is_not_handed_on_with_a_later_one_to_the_same_register() {
        let (_sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        task.handle_write(write("K1", "1")).await;
        let key = task.scheduler.unsent_writes().next().expect("K1 queued");
        // As `note_write_sent` records it when the scheduler puts K1's write in flight.
        task.write_sent = Some((key, task.next_taken));
        task.handle_write(write("K1", "0")).await;
        task.note_writes_completed(&[PortEvent::WriteDone {
            device: key.0,
            register_type: key.1,
            address: key.2,
        }]);
        let handed: Vec<(String, String)> = task
            .unsent_writes()
            .into_iter()
            .map(|w| (w.control_id, w.payload))
            .collect();
        assert_eq!(handed, [("K1".to_owned(), "0".to_owned())]);
    }

    /// A write that failed and will be tried again is still owed.
    #[tokio::test]
    async fn a_write_that_failed_for_now_is_still_handed_on() {
        let (_sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        task.handle_write(write("K1", "1")).await;
        let key = task.scheduler.unsent_writes().next().expect("K1 queued");
        task.write_sent = Some((key, task.next_taken));
        task.note_writes_completed(&[PortEvent::WriteFailed {
            device: key.0,
            register_type: key.1,
            address: key.2,
            permanent: false,
        }]);
        let handed: Vec<String> = task
            .unsent_writes()
            .into_iter()
            .map(|w| w.payload)
            .collect();
        assert_eq!(handed, ["1"]);
    }

    /// Review of the port task (27 Nov 2026), finding 6: an identity read that got nothing (a
    /// full bus queue, a reopen, noise) left the device's channels held to a minimum firmware
    /// unread until it next came online or restarted, which a stable device never does. It is
    /// tried again, 2 s later, then later each time up to 10 minutes, until one is answered.
    #[test]
    fn an_identity_read_that_got_nothing_is_tried_again_later_each_time() {
        let mut retries = IdentityRetries::with_devices(2);
        let at = |s: u64| Duration::from_secs(s);
        assert_eq!(FIRST_IDENTITY_RETRY, at(2));
        assert_eq!(retries.due_at(at(1000)).count(), 0, "nothing failed yet");
        retries.failed(1, at(100));
        assert_eq!(retries.due_at(at(101)).count(), 0);
        assert_eq!(retries.due_at(at(102)).collect::<Vec<_>>(), [1]);
        // Asked again at 102; still due until its result comes (the serve loop does not ask a
        // read under way again: `ask_due_identity_retries`).
        retries.failed(1, at(103));
        assert_eq!(retries.due_at(at(106)).count(), 0);
        assert_eq!(retries.due_at(at(107)).collect::<Vec<_>>(), [1]);
        let mut now = at(107);
        for _ in 0..10 {
            retries.failed(1, now);
            now += MAX_IDENTITY_RETRY;
        }
        assert_eq!(
            retries.due[1].map(|(_, delay)| delay),
            Some(MAX_IDENTITY_RETRY)
        );
        retries.succeeded(1);
        assert_eq!(
            retries.due_at(at(1_000_000)).count(),
            0,
            "answered: no more retries"
        );
        // Out-of-range devices are ignored.
        retries.failed(7, now);
        retries.succeeded(7);
    }

    /// The relay task with an identity plan for its device (WB texts, no serial number).
    fn relay_task_with_identity() -> PortTask {
        let (_write_tx, writes) = mpsc::channel(8);
        let plan = IdentityPlan {
            address: 20,
            texts: true,
            serial: None,
            response_timeout: Duration::from_millis(100),
        };
        relay_task_at("/dev/null", writes).with_identity(vec![Some(plan)])
    }

    /// [`relay_task_with_identity`], its identity reads asked on the channel returned.
    fn relay_task_asking_identity() -> (PortTask, AskedReads) {
        let mut task = relay_task_with_identity();
        let (requests, asked) = mpsc::unbounded_channel();
        task.identity.requests = Some(requests);
        (task, AskedReads(asked))
    }

    /// The identity worker's side of the channel, as a test sees it.
    struct AskedReads(mpsc::UnboundedReceiver<(usize, Arc<AtomicBool>)>);

    impl AskedReads {
        /// The device asked for next, its read begun by the worker.
        fn begun(&mut self) -> Option<usize> {
            let (device, started) = self.0.try_recv().ok()?;
            started.store(true, Ordering::Relaxed);
            Some(device)
        }

        /// The device asked for next, its read still queued.
        fn queued(&mut self) -> Option<usize> {
            self.0.try_recv().ok().map(|(device, _)| device)
        }
    }

    fn identity(model: &str, serial: &str, firmware: &str) -> DeviceIdentity {
        DeviceIdentity {
            model: Some(model.into()),
            serial_number: Some(serial.into()),
            firmware: Some(firmware.into()),
        }
    }

    /// Review of 28 Nov: a replaced device (serial 1 -> 2) whose model and firmware got no
    /// answer in the read that noticed it: the old device's model and firmware were published
    /// under the new serial number until a retry answered them. They are unknown now.
    #[tokio::test]
    async fn a_replaced_device_does_not_inherit_the_old_ones_firmware() {
        let mut task = relay_task_with_identity();
        task.identity.known[0] = identity("WBMR6", "1", "1.0");
        let replaced = IdentityRead {
            identity: DeviceIdentity {
                serial_number: Some("2".into()),
                ..DeviceIdentity::default()
            },
            serial: Some(2),
            unanswered: crate::daemon::identity::Unanswered {
                serial: false,
                model: true,
                firmware: true,
            },
        };
        task.identity_read(0, replaced).await;
        assert_eq!(
            task.identity.known[0].serial_number.as_deref(),
            Some("2"),
            "the replacement is noticed"
        );
        assert_ne!(
            task.identity.known[0].firmware.as_deref(),
            Some("1.0"),
            "the old device's firmware published for the new one: {:?}",
            task.identity.known[0]
        );
    }

    /// The port task's side of finding 6: a read that got nothing schedules the retry, an
    /// answered one clears it. Half a read (the serial number unanswered) is tried again, and
    /// what it did answer is taken, the serial number standing as it was known.
    #[tokio::test]
    async fn an_empty_identity_read_schedules_a_retry_and_an_answer_clears_it() {
        let mut task = relay_task_with_identity();
        task.identity_read(0, IdentityRead::nothing()).await;
        let now = task.now();
        assert_eq!(
            task.identity
                .retries
                .due_at(now + FIRST_IDENTITY_RETRY)
                .collect::<Vec<_>>(),
            [0],
            "nothing read: tried again later"
        );
        task.identity.known[0] = identity("WBMR6", "1", "1.0");
        let answered = IdentityRead {
            identity: identity("WBMR6C", "2", "1.26.0"),
            serial: Some(2),
            unanswered: Default::default(),
        };
        let half = IdentityRead {
            identity: DeviceIdentity {
                serial_number: None,
                ..answered.identity.clone()
            },
            serial: None,
            unanswered: crate::daemon::identity::Unanswered {
                serial: true,
                ..Default::default()
            },
        };
        task.identity_read(0, half).await;
        assert_eq!(
            task.identity
                .retries
                .due_at(now + FIRST_IDENTITY_RETRY * 3)
                .collect::<Vec<_>>(),
            [0],
            "half a read: tried again later"
        );
        assert_eq!(task.identity.known[0], identity("WBMR6C", "1", "1.26.0"));
        task.identity_read(0, answered).await;
        assert_eq!(
            task.identity
                .retries
                .due_at(now + MAX_IDENTITY_RETRY * 2)
                .count(),
            0,
            "answered: no retry"
        );
        assert_eq!(task.identity.known[0], identity("WBMR6C", "2", "1.26.0"));
    }

    /// The serve loop's step: a due retry asks the identity worker again, once, and only once
    /// in all: the serve loop's turns while it runs (the retry stays due until its result)
    /// are not a restart seen during the read (review of 28 Nov: each retry read twice).
    #[tokio::test]
    async fn a_due_identity_retry_asks_the_worker_again_once() {
        let (mut task, mut asked) = relay_task_asking_identity();
        task.ask_due_identity_retries();
        assert!(asked.queued().is_none(), "nothing failed: nothing asked");
        task.identity_read(0, IdentityRead::nothing()).await;
        task.ask_due_identity_retries();
        assert!(asked.queued().is_none(), "not due yet");
        // Due now (as 2 s later).
        task.identity.retries.due[0] = Some((Duration::ZERO, FIRST_IDENTITY_RETRY));
        task.ask_due_identity_retries();
        assert_eq!(asked.begun(), Some(0));
        task.ask_due_identity_retries();
        task.ask_due_identity_retries();
        assert!(asked.queued().is_none(), "asked once while the read runs");
        task.identity_read(0, IdentityRead::default()).await;
        task.ask_due_identity_retries();
        assert!(asked.queued().is_none(), "answered in full, yet read again");
    }

    /// A device that restarts while its identity is being read (a replacement noticed by its
    /// restart event just as a read began): the running read may have got the device before,
    /// so its result is thrown away and the device read again. A read still queued when the
    /// restart is seen reads the device as it is: not asked twice (a device that comes online
    /// and reports its power-on restart at once).
    #[tokio::test]
    async fn a_restart_during_an_identity_read_reads_it_again_after() {
        let (mut task, mut asked) = relay_task_asking_identity();
        task.ask_identity(0);
        assert_eq!(asked.queued(), Some(0));
        task.ask_identity(0);
        task.identity_read(0, IdentityRead::default()).await;
        assert!(
            asked.queued().is_none(),
            "queued when the restart came: once"
        );
        task.ask_identity(0);
        assert_eq!(asked.begun(), Some(0));
        task.ask_identity(0);
        assert!(asked.queued().is_none(), "not twice at once");
        let before_restart = IdentityRead {
            identity: identity("WBMR6C", "1", "1.26.0"),
            serial: Some(1),
            unanswered: Default::default(),
        };
        task.identity_read(0, before_restart).await;
        assert_eq!(
            task.identity.known[0],
            DeviceIdentity::default(),
            "thrown away"
        );
        assert_eq!(asked.begun(), Some(0), "asked again after the first");
        task.identity_read(0, IdentityRead::default()).await;
        assert!(asked.queued().is_none(), "and only once");
    }

    /// A device whose polling is held (a site tool changing its address, an operator) is not
    /// read for its identity, though it came online or restarted meanwhile: asked once, when
    /// the hold ends.
    #[tokio::test]
    async fn an_identity_read_waits_for_the_end_of_a_hold() {
        let (mut task, mut asked) = relay_task_asking_identity();
        task.hold_polling(0, Some(Duration::MAX));
        task.ask_identity(0);
        task.ask_due_identity_retries();
        assert!(asked.queued().is_none(), "read while held");
        task.hold_polling(0, None);
        task.ask_due_identity_retries();
        task.ask_due_identity_retries();
        assert_eq!(asked.queued(), Some(0));
        assert!(asked.queued().is_none(), "asked once");
    }

    /// Two writes to one register: both are handed on, in order (the second only replaced the
    /// first in the queue; replayed, the same happens again). What the scheduler no longer
    /// holds as unsent is left out: `unsent_writes_leave_out_the_one_in_flight_and_those_done`.
    #[tokio::test]
    async fn only_writes_still_queued_are_handed_back() {
        let (_sender, receiver) = mpsc::channel(8);
        let mut task = relay_task(receiver);
        task.handle_write(write("K1", "1")).await;
        task.handle_write(write("K1", "0")).await;
        let handed: Vec<String> = task
            .unsent_writes()
            .into_iter()
            .map(|w| w.payload)
            .collect();
        assert_eq!(handed, ["1", "0"]);
    }

    #[test]
    fn a_port_another_program_holds_is_told_apart() {
        let open = |source: std::io::Error| TransportError::Open {
            path: "/dev/ttyRS485-1".into(),
            source,
        };
        assert!(held_by_another_program(&open(
            std::io::Error::from_raw_os_error(nix::libc::EBUSY)
        )));
        // What the serial library says when another program set TIOCEXCL.
        assert!(held_by_another_program(&open(std::io::Error::other(
            "Unable to acquire exclusive lock on serial port"
        ))));
        assert!(!held_by_another_program(&open(
            std::io::Error::from_raw_os_error(nix::libc::ENOENT)
        )));
        assert!(permission_denied(&open(std::io::Error::from_raw_os_error(
            nix::libc::EACCES
        ))));
        assert!(!permission_denied(&open(
            std::io::Error::from_raw_os_error(nix::libc::EBUSY)
        )));
    }

    /// Review of the port task (27 Nov 2026), finding 1: the port is lost while it is switched
    /// back from a queued transaction's settings to its own. `serve` asks the scheduler for its
    /// next step first (which puts that transaction in flight), then reopens the port at its own
    /// settings; when that reopen failed, `?` left `serve` with the transaction still in flight
    /// in the scheduler and never completed (now it fails as if lost during the transaction).
    /// After the port was reopened, `next()` answered
    /// `Wait { until: now }` for ever: the port task spun, sent nothing again (no poll, no
    /// write: a write in flight was never sent nor given up, `expire_writes` kept it), and its
    /// devices were never marked offline (no transaction failed).
    ///
    /// Sequence, on a pty behind a symlink: a queued transaction at 9600 on the 115200 port
    /// (the port is switched away); once its request is on the line, the symlink is removed;
    /// the transaction times out; the scheduler's next transaction cannot switch back (ENOENT).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_port_lost_while_switching_back_leaves_nothing_in_flight() {
        use crate::protocol::{Parity, Request, RequestPdu};
        use std::io::Read;
        use std::os::fd::AsFd;

        let pty = nix::pty::openpty(None, None).expect("a pty");
        let slave = nix::unistd::ttyname(pty.slave.as_fd()).expect("its name");
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ttyTEST");
        std::os::unix::fs::symlink(&slave, &link).unwrap();
        let (_write_tx, writes) = mpsc::channel(8);
        let (queue, queued) = BusQueue::new();
        let mut task =
            relay_task_at(link.to_str().unwrap(), writes).with_bus_queue(queue.clone(), queued);
        let transport = Transport::open(&task.endpoint).await.expect("opens");
        drop(pty.slave);

        // The far end of the line: everything the port sends, as it comes.
        let (bytes_tx, mut bytes_rx) = mpsc::unbounded_channel::<Vec<u8>>();
        let mut master = std::fs::File::from(pty.master);
        let stop_reader = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stopped = stop_reader.clone();
        let reader = std::thread::spawn(move || {
            let mut buffer = [0u8; 256];
            while !stopped.load(std::sync::atomic::Ordering::Relaxed) {
                match master.read(&mut buffer) {
                    Ok(n) if n > 0 => {
                        let _ = bytes_tx.send(buffer[..n].to_vec());
                    }
                    // No slave open (between two opens of the port): EIO until one is.
                    _ => std::thread::sleep(Duration::from_millis(5)),
                }
            }
        });

        let away = LineSettings::new(9600, Parity::None, 2);
        let request = Request::classic(
            0x33,
            RequestPdu::ReadHoldingRegisters { start: 0, count: 1 },
        );
        let frame = request.encode().unwrap();
        let transaction = Transaction::to_device(&away, request, Duration::from_millis(500));
        let rpc = tokio::spawn(async move { queue.transact(Some(away), transaction).await });
        let unlink = tokio::spawn(async move {
            let mut seen = Vec::new();
            while let Some(chunk) = bytes_rx.recv().await {
                seen.extend(chunk);
                if seen.windows(frame.len()).any(|w| w == frame.as_slice()) {
                    // The port is at 9600 and waits for the reply: it goes away now.
                    std::fs::remove_file(&link).unwrap();
                    return true;
                }
            }
            false
        });
        let (_stop, mut shutdown) = watch::channel(false);
        let served = tokio::time::timeout(
            Duration::from_secs(20),
            task.serve(transport, &mut shutdown),
        )
        .await
        .expect("serve ends once the port cannot be reopened");
        stop_reader.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(unlink.await.unwrap(), "the queued request reached the line");
        assert!(served.is_err(), "the port could not be switched back");
        let _ = rpc.await;
        let _ = reader.join();

        // What `serve` does once the port is open again: ask the scheduler, well after every
        // hold-off. A transaction must go; `Wait { until: now }` is a scheduler that still
        // waits for the outcome of a transaction that never went.
        let later = task.now() + Duration::from_secs(60);
        let next = task.scheduler.next(later);
        assert!(
            matches!(next, NextStep::Transmit(_)),
            "after the port was lost switching back, the scheduler answers {next:?} at {later:?}: \
             the transaction it was given is still in flight, and the port task spins for ever"
        );
    }

    /// Review of the port task (27 Nov 2026), finding 3: a deferred queued transaction went once
    /// the time it was deferred to had come, without looking again at its device's hold-off.
    /// The hold-off may have moved meanwhile: `serve` serves the deferred job only when it is
    /// the queue's turn, and when the last job was a queued one (`queued_turn` false) the
    /// scheduler goes first at that time, to the same device (its reads are due at the end of
    /// the same hold-off). When that read fails, its late reply is on its way, and the
    /// deferred job goes right after it (`ready_deferred_job`: `from <= now`), and takes that
    /// late reply as its answer (an RPC's `port/Load` of input 10 answered with input 0's
    /// value: defect A's second direction, `a_late_reply_to_a_polled_read_is_never_an_rpc_reads_answer`).
    /// Here the device's hold-off is moved after the job was deferred; the job must wait for
    /// it again.
    #[tokio::test]
    async fn a_deferred_queued_transaction_waits_for_a_hold_off_that_moved() {
        use crate::protocol::{Request, RequestPdu};
        let (_write_tx, writes) = mpsc::channel(8);
        let mut task = relay_task(writes);
        let line = LineSettings::new(115200, crate::protocol::Parity::None, 2);
        let read = |start| {
            Transaction::to_device(
                &line,
                Request::classic(20, RequestPdu::ReadInputRegisters { start, count: 1 }),
                Duration::from_millis(100),
            )
        };
        let (reply, _outcome) = tokio::sync::oneshot::channel();
        let job = BusWork::Transaction(QueuedTransaction {
            line: None,
            transaction: read(10),
            reply,
        });
        // Deferred until the device's hold-off at the time, which has ended now.
        task.deferred = Some((Duration::ZERO, job));
        // Meanwhile another transaction to the device failed (the scheduler's own, or, as
        // here, a queued one): its late reply may still come, for a second and more.
        let now = task.now();
        task.scheduler.queued_done(
            now,
            &read(0),
            now,
            TransactionOutcome::NoReply,
            ReplyTiming::default(),
        );
        let held_until = task.scheduler.queued_may_go_from(&read(10).request);
        assert!(held_until > task.now() + Duration::from_millis(500));
        let taken = task.next_queued_job();
        assert!(
            taken.is_none(),
            "the deferred transaction to device 20 goes at {:?}, while the device is held off \
             until {held_until:?} after a failure: a late reply may be taken as its answer",
            task.now()
        );
    }
}
