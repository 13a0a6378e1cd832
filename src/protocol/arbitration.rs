//! Bus arbitration of Fast Modbus broadcast requests.
//!
//! In each window a contender sends one bit of its arbitration word, MSB first. A 0 bit is
//! dominant: the device sends one 0xFF byte at the start of the window. A 1 bit is recessive: the
//! device listens, and drops out if it hears a byte. The lowest word wins; the master sees one 0xFF
//! per window in which any remaining contender had a 0 bit, then the winner's frame.
//!
//! Words are a 4-bit priority marker followed by an identifier: 28 low bits of the serial number
//! for scans (32 windows), the 8-bit Modbus address for events (12 windows).

use super::timing::{ARBITRATION_WINDOWS_EVENTS, ARBITRATION_WINDOWS_SCAN};

/// Marker of a device that has not answered this scan yet.
pub const SCAN_MARKER_UNSCANNED: u32 = 0b0110;
/// Marker of a device already scanned; if it wins, it sends "end of scan".
pub const SCAN_MARKER_SCANNED: u32 = 0b1111;
/// Marker of a device with a high-priority event pending.
pub const EVENT_MARKER_HIGH: u32 = 0b0100;
/// Marker of a device with only low-priority events (or only the reboot event).
pub const EVENT_MARKER_LOW: u32 = 0b0110;
/// Marker of a device with nothing to report; if it wins, it sends "no events".
pub const EVENT_MARKER_NONE: u32 = 0b1111;

/// What a device has to say in an event round, which sets its marker.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum EventUrgency {
    High,
    Low,
    Nothing,
}

/// An arbitration word of `windows` bits, sent MSB first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ArbitrationWord {
    pub bits: u32,
    pub windows: u32,
}

impl ArbitrationWord {
    /// The word of a device in a scan round.
    pub fn scan(serial: u32, already_scanned: bool) -> Self {
        let marker = if already_scanned {
            SCAN_MARKER_SCANNED
        } else {
            SCAN_MARKER_UNSCANNED
        };
        Self {
            bits: (marker << 28) | (serial & 0x0FFF_FFFF),
            windows: ARBITRATION_WINDOWS_SCAN,
        }
    }

    /// The word of a device in an event round.
    pub fn event(urgency: EventUrgency, address: u8) -> Self {
        let marker = match urgency {
            EventUrgency::High => EVENT_MARKER_HIGH,
            EventUrgency::Low => EVENT_MARKER_LOW,
            EventUrgency::Nothing => EVENT_MARKER_NONE,
        };
        Self {
            bits: (marker << 8) | u32::from(address),
            windows: ARBITRATION_WINDOWS_EVENTS,
        }
    }

    /// The bit sent in `window` (0 = first): false is dominant.
    pub fn bit(&self, window: u32) -> bool {
        match self.windows.checked_sub(window + 1) {
            Some(shift) if shift < 32 => (self.bits >> shift) & 1 == 1,
            _ => true,
        }
    }
}

/// The result of one arbitration round.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Arbitration {
    /// Index of the winner among the contenders.
    pub winner: usize,
    /// For each window, whether a filler byte was on the wire (some remaining contender sent 0).
    pub dominant_windows: Vec<bool>,
}

impl Arbitration {
    /// The 0xFF bytes the master sees before the winner's frame.
    pub fn filler_bytes(&self) -> usize {
        self.dominant_windows.iter().filter(|&&d| d).count()
    }
}

/// Runs a round among `contenders` (all with the same number of windows). None when there are
/// none. Equal words (which unique serials and addresses rule out) go to the first listed.
pub fn arbitrate(contenders: &[ArbitrationWord]) -> Option<Arbitration> {
    let windows = contenders.iter().map(|c| c.windows).max()?;
    let mut in_contest: Vec<bool> = vec![true; contenders.len()];
    let mut dominant_windows = Vec::with_capacity(usize::try_from(windows).unwrap_or(0));
    for window in 0..windows {
        let dominant = contenders
            .iter()
            .zip(&in_contest)
            .any(|(word, &still_in)| still_in && !word.bit(window));
        if dominant {
            for (word, still_in) in contenders.iter().zip(in_contest.iter_mut()) {
                if word.bit(window) {
                    *still_in = false;
                }
            }
        }
        dominant_windows.push(dominant);
    }
    let winner = in_contest.iter().position(|&still_in| still_in)?;
    Some(Arbitration {
        winner,
        dominant_windows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const MCM8_SERIAL: u32 = 0xFE40_00AC;
    const MR6C_SERIAL: u32 = 0xFED2_A3A6;

    fn round(words: &[ArbitrationWord]) -> (usize, usize) {
        let outcome = arbitrate(words).unwrap();
        (outcome.winner, outcome.filler_bytes())
    }

    /// Every round of the traces in seed 000 (fast-modbus.md §3 table).
    #[test]
    fn seed_traces_are_reproduced() {
        let mcm8 = |scanned| ArbitrationWord::scan(MCM8_SERIAL, scanned);
        let mr6c = |scanned| ArbitrationWord::scan(MR6C_SERIAL, scanned);
        assert_eq!(round(&[mcm8(false), mr6c(false)]), (0, 22));
        assert_eq!(round(&[mcm8(true), mr6c(false)]), (1, 15));
        assert_eq!(round(&[mcm8(true), mr6c(true)]), (0, 20));

        let relay = |urgency| ArbitrationWord::event(urgency, 241);
        let counter = |urgency| ArbitrationWord::event(urgency, 20);
        assert_eq!(
            round(&[relay(EventUrgency::High), counter(EventUrgency::Low)]),
            (0, 6)
        );
        assert_eq!(
            round(&[relay(EventUrgency::Nothing), counter(EventUrgency::Low)]),
            (1, 8)
        );
        assert_eq!(
            round(&[relay(EventUrgency::Nothing), counter(EventUrgency::Nothing)]),
            (1, 6)
        );
    }

    #[test]
    fn lone_contender_sends_its_zero_bits() {
        // 0b0110 marker + address 0x01: zeros in windows 0, 3, 4..=10 → 1 + 1 + 7 = 9.
        assert_eq!(
            round(&[ArbitrationWord::event(EventUrgency::Low, 1)]),
            (0, 9)
        );
        assert!(arbitrate(&[]).is_none());
    }

    #[test]
    fn lower_address_wins_between_equal_markers() {
        let words = [
            ArbitrationWord::event(EventUrgency::Low, 30),
            ArbitrationWord::event(EventUrgency::Low, 7),
            ArbitrationWord::event(EventUrgency::Nothing, 2),
        ];
        assert_eq!(arbitrate(&words).unwrap().winner, 1);
    }
}
