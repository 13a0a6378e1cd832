//! Bounds on what other MQTT clients can make the driver do: how often Home Assistant's birth
//! message resends every discovery config, and how many refused `/on` payloads are logged.
//! Pure: the time comes in as an argument.

use std::time::{Duration, Instant};

/// Births within this window after the first are answered by one resend.
pub const BIRTH_SETTLE: Duration = Duration::from_secs(1);
/// At most one resend of every discovery config per this interval, however many births come.
pub const MIN_DISCOVERY_INTERVAL: Duration = Duration::from_secs(10);

/// Coalesces Home Assistant births (`homeassistant/status online`) into few resends.
#[derive(Debug, Default)]
pub struct BirthCoalescer {
    due: Option<Instant>,
    last_resend: Option<Instant>,
}

impl BirthCoalescer {
    /// A birth arrived: a resend is due after [`BIRTH_SETTLE`], and no sooner than
    /// [`MIN_DISCOVERY_INTERVAL`] after the last one. Further births until then change nothing.
    pub fn birth(&mut self, now: Instant) {
        if self.due.is_some() {
            return;
        }
        let settle = now + BIRTH_SETTLE;
        let spaced = self
            .last_resend
            .map_or(settle, |last| last + MIN_DISCOVERY_INTERVAL);
        self.due = Some(settle.max(spaced));
    }

    /// When the pending resend is due, if one is.
    pub fn due(&self) -> Option<Instant> {
        self.due
    }

    /// True (once) when the resend is due at `now`.
    pub fn take_due(&mut self, now: Instant) -> bool {
        match self.due {
            Some(due) if due <= now => {
                self.due = None;
                self.last_resend = Some(now);
                true
            }
            _ => false,
        }
    }

    /// A (re)connect publishes every config anyway: a pending resend is not needed.
    pub fn resent_now(&mut self, now: Instant) {
        self.due = None;
        self.last_resend = Some(now);
    }
}

/// How many lines of one kind may be logged per [`LogBudget::WINDOW`]; the rest are counted
/// and the count is logged with the first line of a later window.
#[derive(Debug)]
pub struct LogBudget {
    per_window: u32,
    window_start: Option<Instant>,
    used: u32,
    suppressed: u64,
}

/// Whether to log a line now, and how many were left out before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogDecision {
    Log { suppressed_before: u64 },
    Skip,
}

impl LogBudget {
    pub const WINDOW: Duration = Duration::from_secs(60);

    pub fn new(per_window: u32) -> Self {
        Self {
            per_window,
            window_start: None,
            used: 0,
            suppressed: 0,
        }
    }

    pub fn check(&mut self, now: Instant) -> LogDecision {
        let expired = self
            .window_start
            .is_none_or(|start| now.saturating_duration_since(start) >= Self::WINDOW);
        if expired {
            self.window_start = Some(now);
            self.used = 0;
        }
        if self.used < self.per_window {
            self.used += 1;
            LogDecision::Log {
                suppressed_before: std::mem::take(&mut self.suppressed),
            }
        } else {
            self.suppressed += 1;
            LogDecision::Skip
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 15 defect 12: 200 births in a burst give one resend, not 200.
    #[test]
    fn a_burst_of_births_gives_one_resend() {
        let t0 = Instant::now();
        let mut births = BirthCoalescer::default();
        let mut resends = 0;
        for i in 0..200u64 {
            let now = t0 + Duration::from_millis(i);
            births.birth(now);
            if births.take_due(now) {
                resends += 1;
            }
        }
        assert_eq!(births.due(), Some(t0 + BIRTH_SETTLE));
        assert!(births.take_due(t0 + BIRTH_SETTLE));
        resends += 1;
        assert_eq!(resends, 1);
        assert!(!births.take_due(t0 + BIRTH_SETTLE), "only once");
        // A later birth: no sooner than the minimum interval after the last resend.
        births.birth(t0 + Duration::from_secs(2));
        assert_eq!(
            births.due(),
            Some(t0 + BIRTH_SETTLE + MIN_DISCOVERY_INTERVAL)
        );
    }

    #[test]
    fn a_flood_over_a_minute_resends_at_most_every_interval() {
        let t0 = Instant::now();
        let mut births = BirthCoalescer::default();
        let mut resends = 0;
        for i in 0..60_000u64 {
            let now = t0 + Duration::from_millis(i);
            births.birth(now);
            if births.take_due(now) {
                resends += 1;
            }
        }
        assert!(resends <= 7, "{resends} resends in a minute");
    }

    /// Issue 15 defect 12: a flood of refused payloads gives a bounded number of log lines.
    #[test]
    fn log_lines_are_bounded_per_window() {
        let t0 = Instant::now();
        let mut budget = LogBudget::new(5);
        let logged = (0..200_000u64)
            .filter(|i| {
                let now = t0 + Duration::from_micros(*i);
                matches!(budget.check(now), LogDecision::Log { .. })
            })
            .count();
        assert_eq!(logged, 5);
        assert_eq!(
            budget.check(t0 + LogBudget::WINDOW),
            LogDecision::Log {
                suppressed_before: 199_995
            }
        );
    }
}
