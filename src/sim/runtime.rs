//! What the transport threads, the control socket and the script share: the bus behind a mutex,
//! the clock, the change log, the stop flag.

use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use serde_json::json;

use super::bus::{Bus, ChangeOrigin, RegisterChange};

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

pub struct SimRuntime {
    bus: Mutex<Bus>,
    pub clock: Clock,
    pub log: ChangeLog,
    stop: AtomicBool,
}

impl SimRuntime {
    pub fn new(bus: Bus, log: ChangeLog) -> Self {
        Self {
            bus: Mutex::new(bus),
            clock: Clock::start(),
            log,
            stop: AtomicBool::new(false),
        }
    }

    /// Runs `f` on the bus at the current time, then logs the register changes it made.
    pub fn with_bus<R>(&self, f: impl FnOnce(&mut Bus, Duration) -> R) -> R {
        let mut bus = lock(&self.bus);
        let result = f(&mut bus, self.clock.now());
        let changes = bus.take_changes();
        drop(bus);
        self.log.record(&changes, &self.clock);
        result
    }

    pub fn stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }

    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
}
