//! `/on` writes the bus side has no room for yet. A write is never dropped for lack of room:
//! while the bus side's queue is full, the latest payload per control waits here (an older
//! payload for the same control is superseded, as the scheduler supersedes an older write to
//! the same register), and the writes go out in the order their controls were first written.
//! Bounded by the number of writable controls, since only writes to known controls get here.

use std::collections::VecDeque;

use crate::device_updates::ControlWrite;

#[derive(Debug, Default)]
pub struct PendingWrites {
    queue: VecDeque<ControlWrite>,
}

impl PendingWrites {
    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    pub fn len(&self) -> usize {
        self.queue.len()
    }

    /// Keeps `write`; returns true when it superseded a waiting write to the same control.
    pub fn push(&mut self, write: ControlWrite) -> bool {
        let same_control = self
            .queue
            .iter_mut()
            .find(|w| w.device_id == write.device_id && w.control_id == write.control_id);
        match same_control {
            Some(waiting) => {
                waiting.payload = write.payload;
                true
            }
            None => {
                self.queue.push_back(write);
                false
            }
        }
    }

    pub fn pop(&mut self) -> Option<ControlWrite> {
        self.queue.pop_front()
    }

    pub fn clear(&mut self) {
        self.queue.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(control: &str, payload: &str) -> ControlWrite {
        ControlWrite {
            device_id: "relay".into(),
            control_id: control.into(),
            payload: payload.into(),
        }
    }

    #[test]
    fn the_latest_payload_per_control_waits_in_first_written_order() {
        let mut pending = PendingWrites::default();
        assert!(!pending.push(write("K1", "1")));
        assert!(!pending.push(write("K2", "1")));
        assert!(pending.push(write("K1", "0")));
        assert!(!pending.push(write("K3", "1")));
        assert_eq!(pending.len(), 3);
        assert_eq!(pending.pop(), Some(write("K1", "0")));
        assert_eq!(pending.pop(), Some(write("K2", "1")));
        // K1 again after it left: a new entry behind K3.
        assert!(!pending.push(write("K1", "1")));
        assert_eq!(pending.pop(), Some(write("K3", "1")));
        assert_eq!(pending.pop(), Some(write("K1", "1")));
        assert_eq!(pending.pop(), None);
        assert!(pending.is_empty());
    }

    #[test]
    fn controls_of_other_devices_are_kept_apart() {
        let mut pending = PendingWrites::default();
        pending.push(write("K1", "1"));
        pending.push(ControlWrite {
            device_id: "other".into(),
            ..write("K1", "0")
        });
        assert_eq!(pending.len(), 2);
    }
}
