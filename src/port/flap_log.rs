//! How loudly a device's changes between online and offline are told. A device that drops out
//! now and then gets a line for each change; one that flaps (a loose wire, a bus at the edge of
//! its noise margin) would fill the journal with pairs of lines, so after a few drop-outs its
//! changes go to debug and a summary is said once per window until it has stayed put for a
//! whole window. Pure: the scheduler asks and logs.

use std::time::Duration;

/// Drop-outs within [`FLAP_WINDOW`] that make a device count as flapping.
pub const FLAP_LIMIT: usize = 3;
/// The window over which drop-outs are counted, and the period of the summary.
pub const FLAP_WINDOW: Duration = Duration::from_secs(600);

/// What to say of a change or of the passing of time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FlapSay {
    /// Nothing to say (a tick outside a quiet spell, or before its window is over).
    Nothing,
    /// The change, at its usual level.
    Change,
    /// The change, and that further ones go to debug: the device dropped out
    /// [`FLAP_LIMIT`] times in `over`.
    ChangeThenQuiet { over: Duration },
    /// The change, at debug level only.
    Quietly,
    /// A quiet window is over with `drop_outs` drop-outs in it.
    Summary { drop_outs: u32 },
    /// A quiet window is over without a drop-out: changes are told again.
    Settled,
}

#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FlapLog {
    /// The latest drop-outs while changes are told, oldest first.
    recent: Vec<Duration>,
    /// While changes are quiet: when the current window started, and the drop-outs in it.
    quiet: Option<(Duration, u32)>,
}

impl FlapLog {
    /// The device went offline at `now`.
    pub fn went_offline(&mut self, now: Duration) -> FlapSay {
        if let Some((_, drop_outs)) = &mut self.quiet {
            *drop_outs = drop_outs.saturating_add(1);
            return FlapSay::Quietly;
        }
        self.recent
            .retain(|at| now.saturating_sub(*at) < FLAP_WINDOW);
        self.recent.push(now);
        if self.recent.len() < FLAP_LIMIT {
            return FlapSay::Change;
        }
        let over = now.saturating_sub(self.recent[0]);
        self.recent.clear();
        self.quiet = Some((now, 0));
        FlapSay::ChangeThenQuiet { over }
    }

    /// Whether its changes are told at debug level now.
    pub fn is_quiet(&self) -> bool {
        self.quiet.is_some()
    }

    /// The device answered again.
    pub fn came_online(&mut self) -> FlapSay {
        if self.quiet.is_some() {
            FlapSay::Quietly
        } else {
            FlapSay::Change
        }
    }

    /// Any transaction with the device ended at `now`: closes a quiet window that is over.
    pub fn tick(&mut self, now: Duration) -> FlapSay {
        let Some((since, drop_outs)) = self.quiet else {
            return FlapSay::Nothing;
        };
        if now.saturating_sub(since) < FLAP_WINDOW {
            return FlapSay::Nothing;
        }
        if drop_outs == 0 {
            self.quiet = None;
            FlapSay::Settled
        } else {
            self.quiet = Some((now, 0));
            FlapSay::Summary { drop_outs }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn secs(s: u64) -> Duration {
        Duration::from_secs(s)
    }

    #[test]
    fn occasional_drop_outs_are_each_told() {
        let mut log = FlapLog::default();
        for minute in [0, 11, 22, 33] {
            assert_eq!(log.went_offline(secs(minute * 60)), FlapSay::Change);
            assert_eq!(log.came_online(), FlapSay::Change);
            assert_eq!(log.tick(secs(minute * 60 + 5)), FlapSay::Nothing);
        }
    }

    #[test]
    fn a_flapping_device_is_told_three_times_then_summed_up_until_it_settles() {
        let mut log = FlapLog::default();
        assert_eq!(log.went_offline(secs(0)), FlapSay::Change);
        assert_eq!(log.came_online(), FlapSay::Change);
        assert_eq!(log.went_offline(secs(20)), FlapSay::Change);
        assert_eq!(log.came_online(), FlapSay::Change);
        assert_eq!(
            log.went_offline(secs(50)),
            FlapSay::ChangeThenQuiet { over: secs(50) }
        );
        assert_eq!(log.came_online(), FlapSay::Quietly);
        for at in [80, 110, 140] {
            assert_eq!(log.tick(secs(at)), FlapSay::Nothing);
            assert_eq!(log.went_offline(secs(at)), FlapSay::Quietly);
            assert_eq!(log.came_online(), FlapSay::Quietly);
        }
        assert_eq!(log.tick(secs(649)), FlapSay::Nothing);
        assert_eq!(log.tick(secs(650)), FlapSay::Summary { drop_outs: 3 });
        // A window without a drop-out ends the quiet spell.
        assert_eq!(log.tick(secs(1249)), FlapSay::Nothing);
        assert_eq!(log.tick(secs(1250)), FlapSay::Settled);
        assert_eq!(log.tick(secs(1900)), FlapSay::Nothing);
        assert_eq!(log.went_offline(secs(1900)), FlapSay::Change);
    }

    #[test]
    fn drop_outs_further_apart_than_the_window_never_quieten() {
        let mut log = FlapLog::default();
        for at in [0, 400, 800, 1200, 1600] {
            assert_eq!(log.went_offline(secs(at)), FlapSay::Change);
        }
    }
}
