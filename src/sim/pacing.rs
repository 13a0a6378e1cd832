//! Hands the devices' bytes to the master as a UART does, on a dedicated thread. A byte is
//! handed over when its stop bit ends, or up to [`RX_HOLD`] later together with the bytes that
//! followed it (a UART's receive FIFO hands bytes over in batches); but the last byte before
//! the line falls quiet waits for the UART's receive timeout, [`RECEIVE_TIMEOUT_CHARS`] characters
//! after its stop bit, as a 16550 holds bytes below its trigger level until the line has been
//! quiet that long. So the end of every frame reaches the master 4 characters late, as on the
//! controllers' own ports and PC serial cards, and a master that reads a reply and writes its
//! next request at once keeps the devices' 3.5-character frame silence without trying, here as
//! on real hardware (with the end handed over at its stop bit, such a master talked into that
//! silence, which real ports never make it do). Waking once per byte cost a context switch per
//! byte (most of the simulator's CPU, see docs/sim.md). Without real-time priority it sleeps
//! while more than [`SPIN_THRESHOLD`] remains, then spins: ordinary sleeps overshoot by
//! 50–100 µs. With it, sleeps wake within a few µs and it never spins.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use super::runtime::Clock;
use crate::protocol::timing::RECEIVE_TIMEOUT_CHARS;

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

/// One byte of the devices as the master's UART receives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arrival {
    /// When its stop bit ends.
    pub at: Duration,
    pub byte: u8,
    /// One character on the wire (the receive timeout counts in these).
    pub char_time: Duration,
}

impl Arrival {
    /// When the UART hands this byte over if no other follows it: its receive timeout
    /// (`LineSettings::receive_timeout`) after its stop bit.
    fn quiet_at(&self) -> Duration {
        self.at + self.char_time * RECEIVE_TIMEOUT_CHARS
    }

    /// Whether the line falls quiet after this byte, `next` being the byte after it if any.
    fn ends_a_frame(&self, next: Option<&Arrival>) -> bool {
        next.is_none_or(|next| next.at > self.quiet_at())
    }
}

/// The master's receiver: how its UART and adapter hand the devices' bytes over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Receiver {
    /// Added to every hand-over: what a USB adapter adds between its UART and the master (an
    /// FTDI chip's latency timer is 16 ms by default).
    pub delivery_delay: Duration,
    /// A 16550's receive FIFO trigger level: bytes are handed over when this many have come, or
    /// the receive timeout after the line falls quiet. `Some(1)`: as they come (batched within
    /// [`RX_HOLD`]), a frame's end too (the trigger wb-mqtt-serial and rtu2mqtt set on a
    /// controller's UART). `None`: as they come, but a frame's end the receive timeout late (a
    /// UART left at the kernel's trigger, for the bytes a frame ends with).
    pub fifo_trigger: Option<usize>,
}

/// When the receiver hands the first bytes of `arrivals` (in time order) over, and how many.
/// Without a FIFO trigger above 1: the first byte and those after it up to [`RX_HOLD`] after its
/// stop bit. With one: once that many bytes have come, at the last one's stop bit. Either way,
/// when the line falls quiet for [`RECEIVE_TIMEOUT_CHARS`] characters after one of them first,
/// that byte and those before it, the receive timeout after its stop bit; with a trigger of 1
/// at that byte's stop bit (a FIFO that triggers at every byte has nothing to hold). `None` for
/// no bytes.
pub fn hand_over(
    arrivals: impl IntoIterator<Item = Arrival>,
    fifo_trigger: Option<usize>,
) -> Option<(Duration, usize)> {
    let collects = fifo_trigger.filter(|&trigger| trigger > 1);
    let every_byte = fifo_trigger == Some(1);
    let mut arrivals = arrivals.into_iter().peekable();
    let first = *arrivals.peek()?;
    let hold_until = first.at + RX_HOLD;
    let mut count = 0;
    while let Some(arrival) = arrivals.next() {
        count += 1;
        if collects.is_some_and(|trigger| count >= trigger) {
            return Some((arrival.at, count));
        }
        let next = arrivals.peek();
        if arrival.ends_a_frame(next) {
            let at = if every_byte {
                arrival.at
            } else {
                arrival.quiet_at()
            };
            return Some((at, count));
        }
        // Bytes within the hold go together; the next one is past it.
        if collects.is_none() && next.is_some_and(|next| next.at > hold_until) {
            return Some((hold_until, count));
        }
    }
    None
}

/// When each byte reaches a reader that takes every byte as soon as the UART hands it over (no
/// batching): at its stop bit, or the receive timeout after it for the last byte before the line
/// falls quiet. The virtual-time gateway reads bytes so.
pub fn handed_over_at(arrivals: &[Arrival]) -> Vec<(Duration, u8)> {
    arrivals
        .iter()
        .enumerate()
        .map(|(index, arrival)| {
            let at = if arrival.ends_a_frame(arrivals.get(index + 1)) {
                arrival.quiet_at()
            } else {
                arrival.at
            };
            (at, arrival.byte)
        })
        .collect()
}

#[derive(Default)]
struct Queue {
    /// In time order.
    bytes: VecDeque<Arrival>,
    /// Arrival time of the last byte taken for writing.
    sent_through: Option<Duration>,
    closed: bool,
}

impl Queue {
    /// The next hand-over, with the adapter's delay added.
    fn next_hand_over(&self, receiver: Receiver) -> Option<(Duration, usize)> {
        hand_over(self.bytes.iter().copied(), receiver.fifo_trigger)
            .map(|(at, count)| (at + receiver.delivery_delay, count))
    }
}

/// A queue of timed bytes and the thread that writes them.
pub struct Pacer {
    queue: Mutex<Queue>,
    wake: Condvar,
    clock: Clock,
    receiver: Receiver,
}

fn lock(mutex: &Mutex<Queue>) -> MutexGuard<'_, Queue> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Pacer {
    pub fn spawn(
        name: &str,
        clock: Clock,
        receiver: Receiver,
        writer: ByteWriter,
    ) -> io::Result<(Arc<Self>, JoinHandle<()>)> {
        let pacer = Arc::new(Self {
            queue: Mutex::new(Queue::default()),
            wake: Condvar::new(),
            clock,
            receiver,
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

    /// Replaces everything queued by `arrivals` (in time order): the wire's whole pending
    /// schedule, changed by a new reply or a collision. Bytes at or before the last one already
    /// written are not sent again.
    pub fn replace(&self, arrivals: &[Arrival]) {
        let mut queue = lock(&self.queue);
        let sent_through = queue.sent_through;
        queue.bytes.clear();
        queue.bytes.extend(
            arrivals
                .iter()
                .filter(|arrival| sent_through.is_none_or(|sent| arrival.at > sent)),
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
            // The schedule may have changed meanwhile (a collision): hand over what is due now.
            let Some((at, count)) = queue
                .next_hand_over(self.receiver)
                .filter(|&(at, _)| at <= now)
            else {
                continue;
            };
            for _ in 0..count {
                let Some(arrival) = queue.bytes.pop_front() else {
                    break;
                };
                due.push(arrival.byte);
                queue.sent_through = Some(arrival.at);
            }
            drop(queue);
            let written = writer(&due);
            // The simulator's own timing error (`stats`): how late the hand-over was.
            super::runtime::PACING_ERROR.record(self.clock.now().saturating_sub(at));
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

    /// Sleeps until the next hand-over is less than the spin threshold away; None once closed.
    fn wait_for_next(
        &self,
        (spin_threshold, sleep_margin): (Duration, Duration),
    ) -> Option<Duration> {
        let mut queue = lock(&self.queue);
        loop {
            if queue.closed {
                return None;
            }
            let timeout = match queue.next_hand_over(self.receiver) {
                None => Duration::from_millis(100),
                Some((at, _)) => {
                    let left = at.saturating_sub(self.clock.now());
                    if left <= spin_threshold {
                        return Some(at);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn us(n: u64) -> Duration {
        Duration::from_micros(n)
    }

    /// `count` bytes back to back from `start`, 100 µs each.
    fn frame(start: u64, count: u64) -> Vec<Arrival> {
        (1..=count)
            .map(|i| Arrival {
                at: us(start + 100 * i),
                byte: i as u8,
                char_time: us(100),
            })
            .collect()
    }

    #[test]
    fn the_end_of_a_frame_is_handed_over_four_characters_after_its_last_byte() {
        assert_eq!(hand_over(frame(0, 2), None), Some((us(200 + 400), 2)));
        assert_eq!(hand_over(Vec::new(), None), None);
        let mut two_frames = frame(0, 2);
        two_frames.extend(frame(700, 1));
        assert_eq!(
            handed_over_at(&two_frames),
            [(us(100), 1), (us(200 + 400), 2), (us(800 + 400), 1)]
        );
    }

    #[test]
    fn a_long_frame_goes_in_batches_of_the_hold_then_its_end() {
        let bytes = frame(0, 8);
        // Bytes at 100..=800 µs: the first batch holds those up to 100 + 250 µs.
        assert_eq!(hand_over(bytes.clone(), None), Some((us(350), 3)));
        assert_eq!(hand_over(bytes[3..].to_vec(), None), Some((us(650), 3)));
        assert_eq!(
            hand_over(bytes[6..].to_vec(), None),
            Some((us(800 + 400), 2))
        );
    }

    #[test]
    fn a_pause_shorter_than_the_timeout_keeps_the_frame_going() {
        // Arbitration fillers a window apart, then the winner's frame.
        let mut bytes = frame(0, 1);
        bytes.extend(frame(300, 2));
        assert_eq!(hand_over(bytes.clone(), None), Some((us(350), 1)));
        // A pause of more than 4 characters ends a frame: its last byte goes at the timeout.
        let mut bytes = frame(0, 1);
        bytes.extend(frame(600, 2));
        assert_eq!(hand_over(bytes, None), Some((us(100 + 400), 1)));
    }

    /// Arbitration fillers 3 characters (of 100 µs) apart.
    fn fillers_of(count: u32) -> Vec<Arrival> {
        (0..count)
            .map(|i| Arrival {
                at: us(300 * u64::from(i) + 100),
                byte: 0xFF,
                char_time: us(100),
            })
            .collect()
    }

    #[test]
    fn a_fifo_hands_bytes_over_at_its_trigger_level_or_after_the_line_falls_quiet() {
        // A 16-byte frame through a FIFO that triggers at 8: two batches at the 8th and 16th
        // byte's stop bit (the last batch reached the trigger: no timeout to wait for).
        let bytes = frame(0, 16);
        assert_eq!(hand_over(bytes.clone(), Some(8)), Some((us(800), 8)));
        assert_eq!(hand_over(bytes[8..].to_vec(), Some(8)), Some((us(1600), 8)));
        // Fewer than 8 left: the receive timeout after the frame's end.
        assert_eq!(hand_over(frame(0, 5), Some(8)), Some((us(500 + 400), 5)));
        // Arbitration fillers 3 characters apart never leave the line quiet for 4: the first
        // is held until the 8th has come.
        let fillers = fillers_of(10);
        assert_eq!(hand_over(fillers.clone(), None), Some((us(100 + 250), 1)));
        assert_eq!(hand_over(fillers, Some(8)), Some((us(2200), 8)));
        // A trigger of one byte hands every byte over as it comes (batched within the hold, as
        // without a trigger), a frame's end at its stop bit.
        assert_eq!(hand_over(frame(0, 2), Some(1)), Some((us(200), 2)));
        assert_eq!(hand_over(frame(100, 1), Some(1)), Some((us(200), 1)));
        assert_eq!(hand_over(fillers_of(3), Some(1)), Some((us(100 + 250), 1)));
        let mut bytes = frame(0, 1);
        bytes.extend(frame(600, 2));
        assert_eq!(hand_over(bytes, Some(1)), Some((us(100), 1)));
    }
}
