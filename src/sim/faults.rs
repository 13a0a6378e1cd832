//! Injected faults: lost replies, corrupted CRCs, late replies, busy exceptions, line noise
//! (garbage in place of a reply). Decided by a tiny seeded
//! xorshift generator so that a run is reproducible.

use std::time::Duration;

/// Probabilities (0.0–1.0) per reply of one device.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Faults {
    /// The device executes the request but its reply never reaches the wire.
    pub drop_reply: f64,
    /// The last CRC byte of the reply is inverted.
    pub corrupt_crc: f64,
    /// The reply starts `delay` later than it should (beyond the master's timeout).
    pub delay_reply: f64,
    pub delay: Duration,
    /// A classic reply is replaced by exception 6 (slave device busy), as a device that is
    /// momentarily unable to serve the request answers.
    pub exception: f64,
    /// The reply is replaced by as many random bytes (noise on the line).
    pub garbage: f64,
}

impl Default for Faults {
    fn default() -> Self {
        Self {
            drop_reply: 0.0,
            corrupt_crc: 0.0,
            delay_reply: 0.0,
            delay: Duration::from_secs(1),
            exception: 0.0,
            garbage: 0.0,
        }
    }
}

/// What happens to one reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultAction {
    None,
    Drop,
    CorruptCrc,
    Delay(Duration),
    Exception,
    /// Replace the reply by random bytes drawn from this seed.
    Garbage(u64),
}

impl Faults {
    pub fn is_none(&self) -> bool {
        self.drop_reply <= 0.0
            && self.corrupt_crc <= 0.0
            && self.delay_reply <= 0.0
            && self.exception <= 0.0
            && self.garbage <= 0.0
    }

    /// Draws the fate of one reply (at most one fault at a time, in this order).
    pub fn draw(&self, rng: &mut XorShift64) -> FaultAction {
        if self.is_none() {
            FaultAction::None
        } else if rng.chance(self.drop_reply) {
            FaultAction::Drop
        } else if rng.chance(self.corrupt_crc) {
            FaultAction::CorruptCrc
        } else if rng.chance(self.delay_reply) {
            FaultAction::Delay(self.delay)
        } else if rng.chance(self.exception) {
            FaultAction::Exception
        } else if rng.chance(self.garbage) {
            FaultAction::Garbage(rng.next_u64())
        } else {
            FaultAction::None
        }
    }
}

/// Marsaglia's xorshift64: enough randomness for fault injection, no dependency.
#[derive(Debug, Clone)]
pub struct XorShift64(u64);

impl XorShift64 {
    pub fn new(seed: u64) -> Self {
        Self(if seed == 0 {
            0x9E37_79B9_7F4A_7C15
        } else {
            seed
        })
    }

    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }

    /// True with probability `p` (values outside 0..=1 are clamped).
    pub fn chance(&mut self, p: f64) -> bool {
        if p <= 0.0 {
            return false;
        }
        if p >= 1.0 {
            return true;
        }
        let unit = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        unit < p
    }
}

/// The busy exception (code 6) a classic reply `frame` (address, function, …) is replaced by;
/// None for Fast Modbus frames (broadcast 0xFD, function 0x46), which keep their reply.
pub fn busy_exception(frame: &[u8]) -> Option<Vec<u8>> {
    const SLAVE_DEVICE_BUSY: u8 = 6;
    match frame {
        [address, function, ..] if *address != 0xFD && *function < 0x80 && *function != 0x46 => {
            let mut reply = vec![*address, function | 0x80, SLAVE_DEVICE_BUSY];
            crate::protocol::crc::append_crc(&mut reply);
            Some(reply)
        }
        _ => None,
    }
}

/// `length` random bytes: noise where a reply should have been.
pub fn garbage(seed: u64, length: usize) -> Vec<u8> {
    let mut rng = XorShift64::new(seed);
    (0..length.max(1)).map(|_| rng.next_u64() as u8).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probabilities_roughly_hold() {
        let mut rng = XorShift64::new(1);
        let hits = (0..10_000).filter(|_| rng.chance(0.25)).count();
        assert!((2200..2800).contains(&hits), "{hits}");
        assert!(!XorShift64::new(0).chance(0.0));
        assert!(XorShift64::new(0).chance(1.0));
    }

    #[test]
    fn busy_exception_of_a_classic_reply_only() {
        assert_eq!(
            busy_exception(&[0x14, 0x03, 0x02, 0x00, 0x14, 0xB5, 0x76]),
            Some(vec![0x14, 0x83, 0x06, 0xD0, 0xF6])
        );
        assert_eq!(busy_exception(&[0xFD, 0x46, 0x09, 0, 0]), None);
        assert_eq!(busy_exception(&[0x14, 0x46, 0x11, 0, 0]), None);
        assert_eq!(garbage(7, 5).len(), 5);
        assert_eq!(garbage(7, 5), garbage(7, 5));
    }
}
