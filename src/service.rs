//! Life under systemd (`Type=notify`): READY once every port has had its first chance to open and
//! the broker its first chance to answer; WATCHDOG pings only while every port task makes
//! progress (a hung port stops them, and systemd restarts the service); STATUS lines a person reads
//! in `systemctl status`; STOPPING on shutdown. Without `NOTIFY_SOCKET` nothing is sent.
//!
//! The port tasks and the MQTT task report into [`ServiceHealth`] with plain atomics; the
//! decisions (ready, alive, the status line) are pure functions of it, tested without systemd.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use sd_notify::NotifyState;
use tokio::sync::watch;
use tracing::{debug, warn};

/// A port task that has not reported for this long is hung (its longest legitimate silence is a
/// bounded wait or one transaction, both far shorter).
pub const PORT_STALL_LIMIT: Duration = Duration::from_secs(20);

/// What one port task reports.
#[derive(Debug)]
pub struct PortVitals {
    name: String,
    devices: usize,
    tried: AtomicBool,
    open: AtomicBool,
    online: AtomicUsize,
    /// Milliseconds since [`ServiceHealth`] was made, at the task's last report.
    last_beat_ms: AtomicU64,
    epoch: Instant,
}

impl PortVitals {
    /// The port was opened (true) or could not be (false): its first chance has been taken.
    pub fn set_open(&self, open: bool) {
        self.open.store(open, Ordering::Relaxed);
        self.tried.store(true, Ordering::Relaxed);
        self.beat();
    }

    pub fn set_devices_online(&self, online: usize) {
        self.online.store(online, Ordering::Relaxed);
    }

    /// The task is alive and making progress.
    pub fn beat(&self) {
        let ms = u64::try_from(self.epoch.elapsed().as_millis()).unwrap_or(u64::MAX);
        self.last_beat_ms.store(ms, Ordering::Relaxed);
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum BrokerState {
    /// The first connection attempt has not finished.
    Connecting = 0,
    Connected = 1,
    /// The last attempt failed (the client keeps retrying).
    Unreachable = 2,
    /// `run --stdio`: no broker.
    NotUsed = 3,
}

/// Shared by the port tasks, the MQTT task and the notifier.
#[derive(Debug)]
pub struct ServiceHealth {
    epoch: Instant,
    /// Changes on a reload (SIGHUP).
    ports: Mutex<Vec<Arc<PortVitals>>>,
    broker: AtomicU8,
    broker_tried: AtomicBool,
}

impl ServiceHealth {
    pub fn new(broker: BrokerState) -> Self {
        Self {
            epoch: Instant::now(),
            ports: Mutex::new(Vec::new()),
            broker: AtomicU8::new(broker as u8),
            broker_tried: AtomicBool::new(broker == BrokerState::NotUsed),
        }
    }

    /// Registers a port with `devices` devices; its task reports through the returned handle.
    pub fn add_port(&self, name: &str, devices: usize) -> Arc<PortVitals> {
        let vitals = Arc::new(PortVitals {
            name: name.to_owned(),
            devices,
            tried: AtomicBool::new(false),
            open: AtomicBool::new(false),
            online: AtomicUsize::new(0),
            last_beat_ms: AtomicU64::new(0),
            epoch: self.epoch,
        });
        self.ports().push(Arc::clone(&vitals));
        vitals
    }

    /// The port's task has ended (reload or shutdown): it no longer counts.
    pub fn remove_port(&self, vitals: &Arc<PortVitals>) {
        self.ports().retain(|p| !Arc::ptr_eq(p, vitals));
    }

    fn ports(&self) -> MutexGuard<'_, Vec<Arc<PortVitals>>> {
        self.ports.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub fn set_broker(&self, state: BrokerState) {
        self.broker.store(state as u8, Ordering::Relaxed);
        if state != BrokerState::Connecting {
            self.broker_tried.store(true, Ordering::Relaxed);
        }
    }

    fn broker(&self) -> BrokerState {
        match self.broker.load(Ordering::Relaxed) {
            1 => BrokerState::Connected,
            2 => BrokerState::Unreachable,
            3 => BrokerState::NotUsed,
            _ => BrokerState::Connecting,
        }
    }

    /// Every port has tried to open and the broker has answered or failed once.
    pub fn is_ready(&self) -> bool {
        self.broker_tried.load(Ordering::Relaxed)
            && self.ports().iter().all(|p| p.tried.load(Ordering::Relaxed))
    }

    /// Every port task reported within `limit` of `now` (time since this struct was made).
    pub fn ports_alive(&self, now: Duration, limit: Duration) -> bool {
        let now_ms = u64::try_from(now.as_millis()).unwrap_or(u64::MAX);
        let limit_ms = u64::try_from(limit.as_millis()).unwrap_or(u64::MAX);
        self.ports()
            .iter()
            .all(|p| now_ms.saturating_sub(p.last_beat_ms.load(Ordering::Relaxed)) <= limit_ms)
    }

    /// The names of the ports whose task has not reported within `limit`.
    pub fn stalled_ports(&self, now: Duration, limit: Duration) -> Vec<String> {
        let now_ms = u64::try_from(now.as_millis()).unwrap_or(u64::MAX);
        let limit_ms = u64::try_from(limit.as_millis()).unwrap_or(u64::MAX);
        self.ports()
            .iter()
            .filter(|p| now_ms.saturating_sub(p.last_beat_ms.load(Ordering::Relaxed)) > limit_ms)
            .map(|p| p.name.clone())
            .collect()
    }

    /// One line for `systemctl status`, e.g. "2/2 ports open, 7/8 devices online, MQTT connected".
    pub fn status_line(&self) -> String {
        let ports = self.ports();
        let open = ports
            .iter()
            .filter(|p| p.open.load(Ordering::Relaxed))
            .count();
        let devices: usize = ports.iter().map(|p| p.devices).sum();
        let online: usize = ports
            .iter()
            .map(|p| p.online.load(Ordering::Relaxed).min(p.devices))
            .sum();
        let closed: Vec<&str> = ports
            .iter()
            .filter(|p| p.tried.load(Ordering::Relaxed) && !p.open.load(Ordering::Relaxed))
            .map(|p| p.name.as_str())
            .collect();
        let broker = match self.broker() {
            BrokerState::Connecting => "MQTT connecting",
            BrokerState::Connected => "MQTT connected",
            BrokerState::Unreachable => "MQTT unreachable",
            BrokerState::NotUsed => "no MQTT (stdio)",
        };
        let mut line = format!(
            "{open}/{} ports open, {online}/{devices} devices online, {broker}",
            ports.len()
        );
        if !closed.is_empty() {
            line.push_str("; closed: ");
            line.push_str(&closed.join(", "));
        }
        line
    }

    fn elapsed(&self) -> Duration {
        self.epoch.elapsed()
    }
}

/// Sends READY, STATUS and WATCHDOG as the health allows, until `shutdown`; then STOPPING.
/// Returns at once when not started by systemd.
pub async fn notify_systemd(health: Arc<ServiceHealth>, mut shutdown: watch::Receiver<bool>) {
    if std::env::var_os("NOTIFY_SOCKET").is_none() {
        return;
    }
    let watchdog = sd_notify::watchdog_enabled();
    // Pings at half the watchdog period, as systemd recommends; status at least every second.
    let tick = watchdog
        .map(|w| (w / 2).min(Duration::from_secs(1)))
        .unwrap_or(Duration::from_secs(1))
        .max(Duration::from_millis(10));
    let stall_limit = watchdog.map_or(PORT_STALL_LIMIT, |w| w.min(PORT_STALL_LIMIT));
    let mut ready_sent = false;
    let mut last_status = String::new();
    let mut stall_logged = false;
    loop {
        let status = health.status_line();
        let mut states = Vec::new();
        if !ready_sent && health.is_ready() {
            states.push(NotifyState::Ready);
            ready_sent = true;
        }
        if status != last_status {
            states.push(NotifyState::Status(&status));
        }
        if watchdog.is_some() {
            let now = health.elapsed();
            if health.ports_alive(now, stall_limit) {
                states.push(NotifyState::Watchdog);
                stall_logged = false;
            } else if !stall_logged {
                warn!(ports = ?health.stalled_ports(now, stall_limit), "a port task makes no progress: watchdog pings stopped");
                stall_logged = true;
            }
        }
        if !states.is_empty() {
            if let Err(err) = sd_notify::notify(&states) {
                debug!(%err, "sd_notify failed");
            }
        }
        last_status = status;
        tokio::select! {
            _ = tokio::time::sleep(tick) => {}
            _ = shutdown.wait_for(|stop| *stop) => break,
        }
    }
    let _ = sd_notify::notify(&[
        NotifyState::Stopping,
        NotifyState::Status("stopping: finishing transactions, clearing retained topics"),
    ]);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ready_needs_every_port_tried_and_the_broker_answered() {
        let health = ServiceHealth::new(BrokerState::Connecting);
        let a = health.add_port("/dev/ttyRS485-1", 3);
        let b = health.add_port("/dev/ttyRS485-2", 1);
        assert!(!health.is_ready());
        a.set_open(true);
        b.set_open(false);
        assert!(!health.is_ready(), "broker not tried yet");
        health.set_broker(BrokerState::Unreachable);
        assert!(health.is_ready(), "a failed first attempt counts");
    }

    #[test]
    fn stdio_mode_is_ready_when_the_ports_are() {
        let health = ServiceHealth::new(BrokerState::NotUsed);
        let a = health.add_port("a", 1);
        assert!(!health.is_ready());
        a.set_open(true);
        assert!(health.is_ready());
    }

    #[test]
    fn status_line_counts_ports_devices_and_names_closed_ports() {
        let health = ServiceHealth::new(BrokerState::Connecting);
        let a = health.add_port("/dev/ttyRS485-1", 3);
        let b = health.add_port("/dev/ttyRS485-2", 2);
        a.set_open(true);
        a.set_devices_online(3);
        b.set_open(false);
        health.set_broker(BrokerState::Connected);
        assert_eq!(
            health.status_line(),
            "1/2 ports open, 3/5 devices online, MQTT connected; closed: /dev/ttyRS485-2"
        );
    }

    #[test]
    fn a_port_that_stops_beating_is_stalled() {
        let health = ServiceHealth::new(BrokerState::NotUsed);
        let a = health.add_port("a", 1);
        let b = health.add_port("b", 1);
        a.beat();
        b.beat();
        let limit = Duration::from_secs(20);
        let now = health.elapsed();
        assert!(health.ports_alive(now, limit));
        // Seen 30 s later without new beats: both are stalled.
        let later = now + Duration::from_secs(30);
        assert!(!health.ports_alive(later, limit));
        assert_eq!(health.stalled_ports(later, limit), vec!["a", "b"]);
    }
}
