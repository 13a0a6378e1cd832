//! Sends scheduled bytes at their time, on a dedicated thread: a byte is handed to the master
//! when its stop bit would end on a real wire, or up to [`RX_HOLD`] later together with the bytes
//! that followed it, as a UART's receive FIFO hands bytes over in batches. Waking once per byte
//! cost a context switch per byte (most of the simulator's CPU, see docs/sim.md). Without
//! real-time priority it sleeps while more than [`SPIN_THRESHOLD`] remains, then spins: ordinary
//! sleeps overshoot by 50–100 µs. With it, sleeps wake within a few µs and it never spins.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use super::bus::Transmission;
use super::runtime::Clock;

/// Below this much time left, spin instead of sleeping (normal scheduling: sleeps overshoot).
pub const SPIN_THRESHOLD: Duration = Duration::from_micros(250);
/// How much earlier than due a sleep ends, to absorb its overshoot.
const SLEEP_MARGIN: Duration = Duration::from_micros(150);
/// With real-time priority a sleep wakes within a few µs: no spinning, leaving the CPU to the
/// kernel's tty work and to the reader on the other side.
const REALTIME_SPIN_THRESHOLD: Duration = Duration::ZERO;
const REALTIME_SLEEP_MARGIN: Duration = Duration::ZERO;
/// How long a byte may wait for the next ones before it is handed over (2.6 characters at
/// 115200, a quarter of one at 9600): one wake-up then delivers several bytes at high rates.
pub const RX_HOLD: Duration = Duration::from_micros(250);

pub type ByteWriter = Box<dyn FnMut(&[u8]) -> io::Result<()> + Send>;

#[derive(Default)]
struct Queue {
    /// (when the byte has arrived at the master, byte), in time order.
    bytes: VecDeque<(Duration, u8)>,
    /// Arrival time of the last byte taken for writing.
    sent_through: Option<Duration>,
    closed: bool,
}

/// A queue of timed bytes and the thread that writes them.
pub struct Pacer {
    queue: Mutex<Queue>,
    wake: Condvar,
    clock: Clock,
    /// Added to every byte's arrival: what a USB adapter adds between the wire and the master
    /// (an FTDI chip's latency timer is 16 ms by default).
    delivery_delay: Duration,
}

fn lock(mutex: &Mutex<Queue>) -> MutexGuard<'_, Queue> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Pacer {
    pub fn spawn(
        name: &str,
        clock: Clock,
        delivery_delay: Duration,
        writer: ByteWriter,
    ) -> io::Result<(Arc<Self>, JoinHandle<()>)> {
        let pacer = Arc::new(Self {
            queue: Mutex::new(Queue::default()),
            wake: Condvar::new(),
            clock,
            delivery_delay,
        });
        let worker = Arc::clone(&pacer);
        let handle = std::thread::Builder::new()
            .name(format!("sim-pacer-{name}"))
            .spawn(move || {
                let timing = if raise_to_realtime() {
                    (REALTIME_SPIN_THRESHOLD, REALTIME_SLEEP_MARGIN)
                } else {
                    (SPIN_THRESHOLD, SLEEP_MARGIN)
                };
                worker.run(writer, timing)
            })?;
        Ok((pacer, handle))
    }

    /// Queues every byte of `transmission` at its arrival time.
    pub fn schedule(&self, transmission: &Transmission) {
        let mut queue = lock(&self.queue);
        for (at, byte) in transmission.arrivals() {
            let at = at + self.delivery_delay;
            let position = queue.bytes.partition_point(|&(t, _)| t <= at);
            queue.bytes.insert(position, (at, byte));
        }
        drop(queue);
        self.wake.notify_all();
    }

    /// Replaces everything queued by `arrivals` (in time order): the wire's whole pending
    /// schedule, changed by a new reply or a collision. Bytes at or before the last one already
    /// written are not sent again.
    pub fn replace(&self, arrivals: &[(Duration, u8)]) {
        let mut queue = lock(&self.queue);
        let sent_through = queue.sent_through;
        queue.bytes.clear();
        let delay = self.delivery_delay;
        queue.bytes.extend(
            arrivals
                .iter()
                .map(|&(at, byte)| (at + delay, byte))
                .filter(|&(at, _)| sent_through.is_none_or(|sent| at > sent)),
        );
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

    fn run(&self, mut writer: ByteWriter, timing: (Duration, Duration)) {
        let mut due = Vec::with_capacity(256);
        loop {
            let Some(next) = self.wait_for_next(timing) else {
                return;
            };
            // Spin the last stretch without the lock.
            while self.clock.now() < next {
                std::hint::spin_loop();
            }
            let now = self.clock.now();
            let mut queue = lock(&self.queue);
            let first_due = queue.bytes.front().map(|&(at, _)| at);
            while let Some(&(at, byte)) = queue.bytes.front() {
                if at > now {
                    break;
                }
                due.push(byte);
                queue.bytes.pop_front();
                queue.sent_through = Some(at);
            }
            drop(queue);
            let written = writer(&due);
            // The simulator's own timing error (`stats`): how late the first due byte left.
            if let Some(at) = first_due.filter(|_| !due.is_empty()) {
                super::runtime::PACING_ERROR.record(self.clock.now().saturating_sub(at));
            }
            if let Err(err) = written {
                tracing::debug!("sim: pacer write failed: {err}");
                if err.kind() != io::ErrorKind::WouldBlock {
                    self.close();
                    return;
                }
            }
            due.clear();
        }
    }

    /// Sleeps until the next byte is less than the spin threshold away; None once closed.
    fn wait_for_next(
        &self,
        (spin_threshold, sleep_margin): (Duration, Duration),
    ) -> Option<Duration> {
        let mut queue = lock(&self.queue);
        loop {
            if queue.closed {
                return None;
            }
            let timeout = match queue.bytes.front() {
                None => Duration::from_millis(100),
                Some(&(at, _)) => {
                    let hand_over = at + RX_HOLD;
                    let left = hand_over.saturating_sub(self.clock.now());
                    if left <= spin_threshold {
                        return Some(hand_over);
                    }
                    left - sleep_margin
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

/// Asks for SCHED_FIFO (priority 10) for the calling thread, so that compilers and other busy
/// processes on the machine do not preempt a byte in the middle of a frame. Best effort: without
/// the privilege (CAP_SYS_NICE) the thread keeps the normal policy. Its waits are sleeps except
/// for the last [`SPIN_THRESHOLD`] before a byte, and the kernel's real-time throttling bounds it.
pub fn raise_to_realtime() -> bool {
    // SAFETY: prctl(PR_SET_TIMERSLACK, 1 ns) only changes the calling thread's timer slack.
    unsafe { nix::libc::prctl(nix::libc::PR_SET_TIMERSLACK, 1, 0, 0, 0) };
    let param = nix::libc::sched_param { sched_priority: 10 };
    // SAFETY: plain FFI call on the calling thread (pid 0) with a valid, initialised parameter.
    let result = unsafe { nix::libc::sched_setscheduler(0, nix::libc::SCHED_FIFO, &param) };
    if result != 0 {
        tracing::debug!(
            "sim: no real-time priority for {:?}: {}",
            std::thread::current().name(),
            std::io::Error::last_os_error()
        );
    }
    result == 0
}
