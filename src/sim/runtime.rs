//! What the transport threads, the control socket and the script share: the bus behind a mutex,
//! the clock, the change log, the stop flag.

use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use serde_json::json;

use super::bus::{Bus, ChangeOrigin, RegisterChange};
use super::pacing::Receiver;

/// Time since the simulator started, and the matching CLOCK_MONOTONIC reading for logs that
/// other processes on the machine compare with their own clocks.
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    epoch: Instant,
    monotonic_ns_at_epoch: i128,
}

impl Clock {
    pub fn start() -> Self {
        let monotonic_ns_at_epoch = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
            .map_or(0, |ts| {
                i128::from(ts.tv_sec()) * 1_000_000_000 + i128::from(ts.tv_nsec())
            });
        Self {
            epoch: Instant::now(),
            monotonic_ns_at_epoch,
        }
    }

    pub fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    pub fn instant_at(&self, at: Duration) -> Instant {
        self.epoch + at
    }

    /// CLOCK_MONOTONIC in nanoseconds at `at`.
    pub fn monotonic_ns(&self, at: Duration) -> i128 {
        self.monotonic_ns_at_epoch + i128::try_from(at.as_nanos()).unwrap_or(i128::MAX)
    }
}

/// JSON lines of register changes: to a file or stdout, and to control connections that `watch`.
#[derive(Default)]
pub struct ChangeLog {
    sink: Mutex<Option<Box<dyn Write + Send>>>,
    watchers: Mutex<Vec<Sender<String>>>,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl ChangeLog {
    pub fn new(sink: Option<Box<dyn Write + Send>>) -> Self {
        Self {
            sink: Mutex::new(sink),
            watchers: Mutex::new(Vec::new()),
        }
    }

    pub fn watch(&self, watcher: Sender<String>) {
        lock(&self.watchers).push(watcher);
    }

    pub fn record(&self, changes: &[RegisterChange], clock: &Clock) {
        if changes.is_empty() {
            return;
        }
        let lines: Vec<String> = changes.iter().map(|c| change_line(c, clock)).collect();
        if let Some(sink) = lock(&self.sink).as_mut() {
            for line in &lines {
                if let Err(err) = writeln!(sink, "{line}").and_then(|()| sink.flush()) {
                    tracing::warn!("sim: change log: {err}");
                }
            }
        }
        lock(&self.watchers)
            .retain(|watcher| lines.iter().all(|line| watcher.send(line.clone()).is_ok()));
    }
}

/// One change as a JSON line: `t_us` since the simulator started, `mono_ns` on CLOCK_MONOTONIC.
pub fn change_line(change: &RegisterChange, clock: &Clock) -> String {
    json!({
        "t_us": u64::try_from(change.at.as_micros()).unwrap_or(u64::MAX),
        "mono_ns": u64::try_from(clock.monotonic_ns(change.at)).unwrap_or(0),
        "device": change.device,
        "address": change.address,
        "serial": change.serial,
        "type": super::control::register_type_name(change.change.register_type),
        "register": change.change.address,
        "old": change.change.old,
        "value": change.change.new,
        "origin": match change.origin {
            ChangeOrigin::Master => "master",
            ChangeOrigin::Control => "control",
        },
    })
    .to_string()
}

/// How late the pacers hand bytes to the master (the simulator's own timing error), for the
/// `stats` control command. Process-wide: a simulator process runs one bus.
pub static PACING_ERROR: PacingError = PacingError::new();

/// Upper bounds (µs) of the lateness buckets; the last bucket takes the rest.
pub const PACING_BUCKETS_US: [u64; 8] = [10, 50, 100, 250, 500, 1_000, 5_000, u64::MAX];

pub struct PacingError {
    writes: AtomicU64,
    late_sum_ns: AtomicU64,
    late_max_ns: AtomicU64,
    buckets: [AtomicU64; PACING_BUCKETS_US.len()],
}

impl PacingError {
    const fn new() -> Self {
        Self {
            writes: AtomicU64::new(0),
            late_sum_ns: AtomicU64::new(0),
            late_max_ns: AtomicU64::new(0),
            buckets: [const { AtomicU64::new(0) }; PACING_BUCKETS_US.len()],
        }
    }

    /// One write of due bytes, `late` after the first of them was due.
    pub fn record(&self, late: Duration) {
        let ns = u64::try_from(late.as_nanos()).unwrap_or(u64::MAX);
        self.writes.fetch_add(1, Ordering::Relaxed);
        self.late_sum_ns.fetch_add(ns, Ordering::Relaxed);
        self.late_max_ns.fetch_max(ns, Ordering::Relaxed);
        let us = ns / 1_000;
        let bucket = PACING_BUCKETS_US
            .iter()
            .position(|&bound| us < bound)
            .unwrap_or(PACING_BUCKETS_US.len() - 1);
        if let Some(counter) = self.buckets.get(bucket) {
            counter.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// `{"writes", "late_mean_us", "late_max_us", "late_buckets_us": [[bound, count]…]}`.
    pub fn to_json(&self) -> serde_json::Value {
        let writes = self.writes.load(Ordering::Relaxed);
        let sum = self.late_sum_ns.load(Ordering::Relaxed);
        let buckets: Vec<serde_json::Value> = PACING_BUCKETS_US
            .iter()
            .zip(&self.buckets)
            .map(|(&bound, count)| {
                json!([
                    (bound != u64::MAX).then_some(bound),
                    count.load(Ordering::Relaxed)
                ])
            })
            .collect();
        json!({
            "writes": writes,
            "late_mean_us": if writes == 0 { 0.0 } else { sum as f64 / writes as f64 / 1_000.0 },
            "late_max_us": self.late_max_ns.load(Ordering::Relaxed) as f64 / 1_000.0,
            "late_buckets_us": buckets,
        })
    }
}

pub struct SimRuntime {
    bus: Mutex<Bus>,
    pub clock: Clock,
    pub log: ChangeLog,
    stop: AtomicBool,
    /// The bus's [`super::bus::LinkState`], mirrored after every command so that the
    /// transports' loops read it without taking the bus's lock.
    link_up: AtomicBool,
    link_generation: AtomicU64,
    /// When the bus's second master sends next (ns on [`Clock`], `u64::MAX`: none), mirrored
    /// like the links so that the transports' loops wait for it without the bus's lock.
    other_master_due_ns: AtomicU64,
    other_master_listens: AtomicBool,
    /// How the pty's master receives the devices' bytes: its UART's FIFO, a USB adapter's
    /// delay.
    pub receiver: Receiver,
}

impl SimRuntime {
    pub fn new(bus: Bus, log: ChangeLog) -> Self {
        Self {
            bus: Mutex::new(bus),
            clock: Clock::start(),
            log,
            stop: AtomicBool::new(false),
            link_up: AtomicBool::new(true),
            link_generation: AtomicU64::new(0),
            other_master_due_ns: AtomicU64::new(u64::MAX),
            other_master_listens: AtomicBool::new(false),
            receiver: Receiver::default(),
        }
    }

    /// Bytes reach the master over the pty `latency` after they end on the wire, as through a
    /// USB adapter that holds them for its latency timer.
    pub fn with_adapter_latency(mut self, latency: Duration) -> Self {
        self.receiver.delivery_delay = latency;
        self
    }

    /// The master's UART hands bytes over `trigger` at a time, or once the line has been quiet
    /// for its receive timeout, as a 16550 with that receive FIFO trigger level does.
    pub fn with_fifo_trigger(mut self, trigger: usize) -> Self {
        self.receiver.fifo_trigger = Some(trigger.max(1));
        self
    }

    /// Runs `f` on the bus at the current time, then logs the register changes it made.
    pub fn with_bus<R>(&self, f: impl FnOnce(&mut Bus, Duration) -> R) -> R {
        let mut bus = lock(&self.bus);
        let result = f(&mut bus, self.clock.now());
        let changes = bus.take_changes();
        let link = bus.link();
        let other_master_due = bus.other_master_due();
        drop(bus);
        self.other_master_due_ns.store(
            other_master_due.map_or(u64::MAX, |(due, _)| {
                u64::try_from(due.as_nanos()).unwrap_or(u64::MAX - 1)
            }),
            Ordering::SeqCst,
        );
        self.other_master_listens.store(
            other_master_due.is_some_and(|(_, listens)| listens),
            Ordering::SeqCst,
        );
        self.link_up.store(link.up, Ordering::SeqCst);
        self.link_generation
            .store(link.generation, Ordering::SeqCst);
        self.log.record(&changes, &self.clock);
        result
    }

    pub fn stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }

    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// Whether the master may have a link now (see [`super::bus::LinkState`]).
    pub fn link_up(&self) -> bool {
        self.link_up.load(Ordering::SeqCst)
    }

    /// When the bus's second master sends next, if there is one, and whether it waits for
    /// silence first.
    pub fn other_master_due(&self) -> Option<(Duration, bool)> {
        match self.other_master_due_ns.load(Ordering::SeqCst) {
            u64::MAX => None,
            ns => Some((
                Duration::from_nanos(ns),
                self.other_master_listens.load(Ordering::SeqCst),
            )),
        }
    }

    /// The links' generation: a link opened under another one must end.
    pub fn link_generation(&self) -> u64 {
        self.link_generation.load(Ordering::SeqCst)
    }
}
