//! Sends scheduled bytes at their time, on a dedicated thread: each byte is written when its stop
//! bit would end on a real wire. Sleeps while more than [`SPIN_THRESHOLD`] remains, then spins:
//! OS sleeps alone overshoot by 50–100 µs, more than a character at 115200 baud.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use super::bus::Transmission;
use super::runtime::Clock;

/// Below this much time left, spin instead of sleeping.
pub const SPIN_THRESHOLD: Duration = Duration::from_micros(250);
/// How much earlier than due a sleep ends, to absorb its overshoot.
const SLEEP_MARGIN: Duration = Duration::from_micros(150);

pub type ByteWriter = Box<dyn FnMut(&[u8]) -> io::Result<()> + Send>;

#[derive(Default)]
struct Queue {
    /// (when the byte has arrived at the master, byte), in time order.
    bytes: VecDeque<(Duration, u8)>,
    closed: bool,
}

/// A queue of timed bytes and the thread that writes them.
pub struct Pacer {
    queue: Mutex<Queue>,
    wake: Condvar,
    clock: Clock,
}

fn lock(mutex: &Mutex<Queue>) -> MutexGuard<'_, Queue> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Pacer {
    pub fn spawn(
        name: &str,
        clock: Clock,
        writer: ByteWriter,
    ) -> io::Result<(Arc<Self>, JoinHandle<()>)> {
        let pacer = Arc::new(Self {
            queue: Mutex::new(Queue::default()),
            wake: Condvar::new(),
            clock,
        });
        let worker = Arc::clone(&pacer);
        let handle = std::thread::Builder::new()
            .name(format!("sim-pacer-{name}"))
            .spawn(move || worker.run(writer))?;
        Ok((pacer, handle))
    }

    /// Queues every byte of `transmission` at its arrival time.
    pub fn schedule(&self, transmission: &Transmission) {
        let mut queue = lock(&self.queue);
        for (at, byte) in transmission.arrivals() {
            let position = queue.bytes.partition_point(|&(t, _)| t <= at);
            queue.bytes.insert(position, (at, byte));
        }
        drop(queue);
        self.wake.notify_all();
    }

    pub fn close(&self) {
        lock(&self.queue).closed = true;
        self.wake.notify_all();
    }

    /// Bytes still waiting to be sent.
    pub fn backlog(&self) -> usize {
        lock(&self.queue).bytes.len()
    }

    fn run(&self, mut writer: ByteWriter) {
        let mut due = Vec::with_capacity(256);
        loop {
            let Some(next) = self.wait_for_next() else {
                return;
            };
            // Spin the last stretch without the lock.
            while self.clock.now() < next {
                std::hint::spin_loop();
            }
            let now = self.clock.now();
            let mut queue = lock(&self.queue);
            while let Some(&(at, byte)) = queue.bytes.front() {
                if at > now {
                    break;
                }
                due.push(byte);
                queue.bytes.pop_front();
            }
            drop(queue);
            if let Err(err) = writer(&due) {
                tracing::debug!("sim: pacer write failed: {err}");
                if err.kind() != io::ErrorKind::WouldBlock {
                    self.close();
                    return;
                }
            }
            due.clear();
        }
    }

    /// Sleeps until the next byte is less than [`SPIN_THRESHOLD`] away; None once closed.
    fn wait_for_next(&self) -> Option<Duration> {
        let mut queue = lock(&self.queue);
        loop {
            if queue.closed {
                return None;
            }
            let timeout = match queue.bytes.front() {
                None => Duration::from_millis(100),
                Some(&(at, _)) => {
                    let left = at.saturating_sub(self.clock.now());
                    if left <= SPIN_THRESHOLD {
                        return Some(at);
                    }
                    left - SLEEP_MARGIN
                }
            };
            queue = self
                .wake
                .wait_timeout(queue, timeout)
                .map(|(guard, _)| guard)
                .unwrap_or_else(|poisoned| poisoned.into_inner().0);
        }
    }
}
