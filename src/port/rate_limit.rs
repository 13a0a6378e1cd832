//! The config's `rate_limit`: reads of channels without a read period, at most so many a second
//! on a port (its share), counted per window of one second from the first read after the last
//! window ended, as wb-mqtt-serial counts them. Reads with a period, event polls, writes and
//! preparations are not limited.

use std::time::Duration;

const WINDOW: Duration = Duration::from_secs(1);

#[derive(Debug, Clone)]
pub(super) struct ReadRateLimit {
    per_second: Option<u32>,
    /// The start of the current window (none before the first read).
    window_start: Option<Duration>,
    count: u32,
    reported: bool,
}

impl ReadRateLimit {
    pub(super) fn new(per_second: Option<u32>) -> Self {
        Self {
            per_second,
            window_start: None,
            count: 0,
            reported: false,
        }
    }

    /// Until when low-priority reads must wait, if they must at `now`.
    pub(super) fn held_until(&self, now: Duration) -> Option<Duration> {
        let limit = self.per_second?;
        let end = self.window_start?.saturating_add(WINDOW);
        (now < end && self.count >= limit).then_some(end)
    }

    /// `reads` low-priority channel reads start at `now`.
    pub(super) fn count(&mut self, now: Duration, reads: u32) {
        if self.per_second.is_none() || reads == 0 {
            return;
        }
        if self
            .window_start
            .is_none_or(|start| now >= start.saturating_add(WINDOW))
        {
            self.window_start = Some(now);
            self.count = 0;
        }
        self.count = self.count.saturating_add(reads);
    }

    /// True the first time the limit holds reads back (one log line per port).
    pub(super) fn first_hold(&mut self) -> bool {
        !std::mem::replace(&mut self.reported, true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    #[test]
    fn reads_wait_for_the_next_window_once_the_limit_is_reached() {
        let mut limit = ReadRateLimit::new(Some(10));
        limit.count(ms(100), 6);
        assert_eq!(limit.held_until(ms(200)), None);
        // A merged read may take the count past the limit; then the rest of the window waits.
        limit.count(ms(300), 6);
        assert_eq!(limit.held_until(ms(400)), Some(ms(1100)));
        assert_eq!(limit.held_until(ms(1100)), None);
        // The next window starts with the first read after the last one ended.
        limit.count(ms(1500), 10);
        assert_eq!(limit.held_until(ms(2000)), Some(ms(2500)));
        assert!(limit.first_hold());
        assert!(!limit.first_hold());
    }

    #[test]
    fn without_a_limit_nothing_waits() {
        let mut limit = ReadRateLimit::new(None);
        limit.count(ms(0), 1_000_000);
        assert_eq!(limit.held_until(ms(1)), None);
    }
}
