//! The port scheduler's index of its devices: which may be prepared or read now, in the order
//! the scheduler picks them, and when each must be looked at again. The scheduler's choice of
//! the next transaction then costs O(log n) in the number of devices instead of a scan of every
//! device and every planned read per transaction.
//!
//! A device's [`Placement`] is computed from its state at some time `t` and stays exact until
//! its `wake` time or until the device's state changes: the scheduler marks a device
//! [`stale`](DueIndex::mark_stale) whenever it changes it, and places it again before choosing.

use std::collections::BTreeSet;
use std::time::Duration;

use super::device::ReadUrgency;

/// Where one device stands, computed from its state at one time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct Placement {
    /// Its preparation (setup writes, event setup) may go now.
    pub preparing: bool,
    /// It may be read now, with this urgency.
    pub read: Option<ReadUrgency>,
    /// Offline with no sign of life: it goes only when the dead devices' budget allows.
    pub seems_dead: bool,
    /// When the placement must be computed again (a read becomes due, a retry slot opens, a
    /// hold ends), if the passing of time alone can change it.
    pub wake: Option<Duration>,
    /// Fast Modbus events are enabled on it.
    pub events_active: bool,
}

#[derive(Debug, Clone, Default)]
pub(super) struct DueIndex {
    placed: Vec<Placement>,
    /// Devices changed since they were last placed.
    stale: Vec<usize>,
    is_stale: Vec<bool>,
    /// The time of the latest placement: an earlier `now` (a clock going back) places every
    /// device again.
    placed_at: Duration,
    /// Devices whose preparation may go now, by index: those that seem dead apart.
    preparing: BTreeSet<usize>,
    dead_preparing: BTreeSet<usize>,
    /// Devices that may be read now, most urgent first (ties: the lowest index).
    reads: BTreeSet<(ReadUrgency, usize)>,
    dead_reads: BTreeSet<(ReadUrgency, usize)>,
    wakes: BTreeSet<(Duration, usize)>,
    /// Devices with events enabled, by address (the event poll's rotation wants the highest).
    listeners: BTreeSet<(u8, usize)>,
}

impl DueIndex {
    /// An index of `count` devices, all stale.
    pub(super) fn new(count: usize) -> Self {
        Self {
            placed: vec![Placement::default(); count],
            stale: (0..count).collect(),
            is_stale: vec![true; count],
            ..Self::default()
        }
    }

    pub(super) fn mark_stale(&mut self, device: usize) {
        if let Some(flag) = self.is_stale.get_mut(device) {
            if !*flag {
                *flag = true;
                self.stale.push(device);
            }
        }
    }

    pub(super) fn mark_all_stale(&mut self) {
        self.placed_at = Duration::ZERO;
        for device in 0..self.placed.len() {
            self.mark_stale(device);
        }
    }

    /// Takes one stale device, to be placed again.
    pub(super) fn take_stale(&mut self) -> Option<usize> {
        let device = self.stale.pop()?;
        if let Some(flag) = self.is_stale.get_mut(device) {
            *flag = false;
        }
        Some(device)
    }

    /// Takes a device whose wake time has come by `now`; it is marked stale.
    pub(super) fn take_woken(&mut self, now: Duration) -> Option<usize> {
        let &(at, device) = self.wakes.first()?;
        if at > now {
            return None;
        }
        self.wakes.pop_first();
        if let Some(placed) = self.placed.get_mut(device) {
            placed.wake = None;
        }
        self.mark_stale(device);
        Some(device)
    }

    /// Whether `now` comes before the latest placement (the clock went back).
    pub(super) fn is_before_placements(&self, now: Duration) -> bool {
        now < self.placed_at
    }

    pub(super) fn place(&mut self, device: usize, address: u8, now: Duration, new: Placement) {
        let Some(old) = self.placed.get(device).copied() else {
            return;
        };
        self.placed_at = self.placed_at.max(now);
        if old == new {
            return;
        }
        self.set_member(device, old, false, address);
        self.set_member(device, new, true, address);
        if let Some(slot) = self.placed.get_mut(device) {
            *slot = new;
        }
    }

    fn set_member(&mut self, device: usize, placement: Placement, member: bool, address: u8) {
        fn set<T: Ord>(set: &mut BTreeSet<T>, value: T, member: bool) {
            if member {
                set.insert(value);
            } else {
                set.remove(&value);
            }
        }
        if placement.preparing {
            let preparing = if placement.seems_dead {
                &mut self.dead_preparing
            } else {
                &mut self.preparing
            };
            set(preparing, device, member);
        }
        if let Some(urgency) = placement.read {
            let reads = if placement.seems_dead {
                &mut self.dead_reads
            } else {
                &mut self.reads
            };
            set(reads, (urgency, device), member);
        }
        if let Some(at) = placement.wake {
            set(&mut self.wakes, (at, device), member);
        }
        if placement.events_active {
            set(&mut self.listeners, (address, device), member);
        }
    }

    /// The first device whose preparation may go now, not seeming dead.
    pub(super) fn first_preparing(&self) -> Option<usize> {
        self.preparing.first().copied()
    }

    /// Devices seeming dead whose preparation may go now, by index.
    pub(super) fn dead_preparing(&self) -> impl Iterator<Item = usize> + '_ {
        self.dead_preparing.iter().copied()
    }

    /// The most urgent device that may be read now, not seeming dead.
    pub(super) fn first_read(&self) -> Option<(ReadUrgency, usize)> {
        self.reads.first().copied()
    }

    /// Devices seeming dead that may be read now, most urgent first.
    pub(super) fn dead_reads(&self) -> impl Iterator<Item = (ReadUrgency, usize)> + '_ {
        self.dead_reads.iter().copied()
    }

    pub(super) fn any_events_active(&self) -> bool {
        !self.listeners.is_empty()
    }

    /// The highest address with events enabled.
    pub(super) fn highest_listener(&self) -> Option<u8> {
        self.listeners.last().map(|&(address, _)| address)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    fn read(urgency: (u8, u64), wake: Option<u64>) -> Placement {
        Placement {
            read: Some((urgency.0, ms(urgency.1), None)),
            wake: wake.map(ms),
            ..Placement::default()
        }
    }

    #[test]
    fn reads_come_most_urgent_first_and_ties_by_index() {
        let mut index = DueIndex::new(3);
        while index.take_stale().is_some() {}
        index.place(0, 1, ms(0), read((1, 5), None));
        index.place(1, 2, ms(0), read((0, 9), None));
        index.place(2, 3, ms(0), read((0, 9), None));
        assert_eq!(index.first_read().map(|(_, d)| d), Some(1));
        index.place(1, 2, ms(0), Placement::default());
        assert_eq!(index.first_read().map(|(_, d)| d), Some(2));
        index.place(2, 3, ms(0), Placement::default());
        assert_eq!(index.first_read().map(|(_, d)| d), Some(0));
    }

    #[test]
    fn a_device_wakes_once_its_time_has_come_and_is_then_stale() {
        let mut index = DueIndex::new(2);
        while index.take_stale().is_some() {}
        index.place(0, 1, ms(0), read((1, 0), Some(30)));
        index.place(1, 2, ms(0), read((1, 0), Some(10)));
        assert_eq!(index.take_woken(ms(9)), None);
        assert_eq!(index.take_woken(ms(10)), Some(1));
        assert_eq!(index.take_woken(ms(10)), None);
        assert_eq!(index.take_stale(), Some(1));
        assert_eq!(index.take_stale(), None);
        assert_eq!(index.take_woken(ms(40)), Some(0));
    }

    #[test]
    fn dead_devices_and_listeners_are_kept_apart() {
        let mut index = DueIndex::new(3);
        while index.take_stale().is_some() {}
        let dead = Placement {
            seems_dead: true,
            preparing: true,
            ..Placement::default()
        };
        index.place(0, 7, ms(0), dead);
        index.place(
            1,
            9,
            ms(0),
            Placement {
                events_active: true,
                ..read((1, 0), None)
            },
        );
        index.place(
            2,
            4,
            ms(0),
            Placement {
                events_active: true,
                preparing: true,
                ..Placement::default()
            },
        );
        assert_eq!(index.first_preparing(), Some(2));
        assert_eq!(index.dead_preparing().collect::<Vec<_>>(), vec![0]);
        assert_eq!(index.highest_listener(), Some(9));
        index.place(1, 9, ms(0), Placement::default());
        assert_eq!(index.highest_listener(), Some(4));
        assert!(index.any_events_active());
        index.place(2, 4, ms(0), Placement::default());
        assert!(!index.any_events_active());
        assert_eq!(index.first_read(), None);
    }
}
