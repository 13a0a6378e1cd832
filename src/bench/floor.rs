//! What one timed wake-up costs on this machine, for reading scenario 7's CPU per transaction:
//! a gateway sleeps between a request and its reply, so every transaction pays at least one.

use std::time::Duration;

use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use nix::time::{clock_gettime, ClockId as CpuClock};

/// The CPU time of one wake-up of an otherwise idle thread: arm a timerfd `period` ahead, block
/// reading it, `rounds` times (two syscalls and one sleep each, nothing else), measured on the
/// thread's own CPU clock. Runs on its own thread, so that it starts from the same idle state as
/// the daemon's runtime between transactions. None if the clock or the timer is unavailable.
pub fn wake_up_cost(period: Duration, rounds: u32) -> Option<Duration> {
    let measure = move || -> Option<Duration> {
        let timer = TimerFd::new(ClockId::CLOCK_MONOTONIC, TimerFlags::TFD_CLOEXEC).ok()?;
        let start = clock_gettime(CpuClock::CLOCK_THREAD_CPUTIME_ID).ok()?;
        for _ in 0..rounds {
            timer
                .set(
                    Expiration::OneShot(period.into()),
                    TimerSetTimeFlags::empty(),
                )
                .ok()?;
            timer.wait().ok()?;
        }
        let end = clock_gettime(CpuClock::CLOCK_THREAD_CPUTIME_ID).ok()?;
        let spent = Duration::from(end).checked_sub(Duration::from(start))?;
        spent.checked_div(rounds)
    };
    std::thread::spawn(measure).join().ok().flatten()
}
