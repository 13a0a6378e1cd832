//! What one timed wake-up costs on this machine, for reading scenario 7's CPU per transaction:
//! a gateway sleeps between a request and its reply, so every transaction pays at least one.
//! On a shared VM that cost moves from minute to minute (13–40 µs were seen here within an
//! hour), so it is measured during each run's own window, beside the daemon.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use nix::time::{clock_gettime, ClockId as CpuClock};

/// A thread that does nothing but sleep `period` at a time on a timerfd (arm it, block reading
/// it: two syscalls and one wake-up per round), and measures its own CPU clock meanwhile.
pub struct WakeUpMeter {
    stop: Arc<AtomicBool>,
    thread: JoinHandle<Option<Duration>>,
}

impl WakeUpMeter {
    pub fn start(period: Duration) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let stopped = Arc::clone(&stop);
        let thread = std::thread::spawn(move || measure(period, &stopped));
        Self { stop, thread }
    }

    /// The CPU time of one wake-up, on average since the start; None if the clock or the
    /// timer was unavailable, or too few rounds ran.
    pub fn finish(self) -> Option<Duration> {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().ok().flatten()
    }
}

fn measure(period: Duration, stop: &AtomicBool) -> Option<Duration> {
    let timer = TimerFd::new(ClockId::CLOCK_MONOTONIC, TimerFlags::TFD_CLOEXEC).ok()?;
    let sleep_once = || -> Option<()> {
        timer
            .set(
                Expiration::OneShot(period.into()),
                TimerSetTimeFlags::empty(),
            )
            .ok()?;
        timer.wait().ok()
    };
    // The first rounds of a new thread pay for its stack's pages and the timer's set-up.
    for _ in 0..20 {
        sleep_once()?;
    }
    let start = clock_gettime(CpuClock::CLOCK_THREAD_CPUTIME_ID).ok()?;
    let mut rounds: u32 = 0;
    while !stop.load(Ordering::Relaxed) {
        sleep_once()?;
        rounds += 1;
    }
    let end = clock_gettime(CpuClock::CLOCK_THREAD_CPUTIME_ID).ok()?;
    let spent = Duration::from(end).checked_sub(Duration::from(start))?;
    (rounds >= 50).then(|| spent / rounds)
}
