//! Injected faults: lost replies, corrupted CRCs, late replies, busy exceptions, line noise
//! (garbage in place of a reply), line errors (a flipped bit anywhere in a reply, a reply cut
//! short, a stray byte beside it). Decided by a tiny seeded xorshift generator so that a run is
//! reproducible.

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
    /// One bit of one byte of the reply is inverted: the commonest line error, and unlike
    /// `corrupt_crc` it can hit the address, the function code or the byte count.
    pub flip_bit: f64,
    /// The reply stops after part of it (a device reset mid-reply, a line dropout).
    pub truncate: f64,
    /// A stray byte (0x00, 0xFF or any) right before or right after the reply, as a
    /// transceiver switching its driver on or off can put on an unbiased line.
    pub glitch: f64,
    /// The faults end after hitting this many replies (none: they last).
    pub times: Option<u32>,
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
            flip_bit: 0.0,
            truncate: 0.0,
            glitch: 0.0,
            times: None,
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
    /// [`flip_bit`] with this seed.
    FlipBit(u64),
    /// [`truncate`] with this seed.
    Truncate(u64),
    /// [`glitch`] with this seed.
    Glitch(u64),
}

impl Faults {
    pub fn is_none(&self) -> bool {
        self.drop_reply <= 0.0
            && self.corrupt_crc <= 0.0
            && self.delay_reply <= 0.0
            && self.exception <= 0.0
            && self.garbage <= 0.0
            && self.flip_bit <= 0.0
            && self.truncate <= 0.0
            && self.glitch <= 0.0
    }

    /// A reply was hit: one fewer of `times` left, none left ends the faults.
    pub fn spend(&mut self) {
        match self.times {
            Some(left) if left <= 1 => *self = Faults::default(),
            Some(left) => self.times = Some(left - 1),
            None => {}
        }
    }

    /// Draws the fate of one reply (at most one fault at a time, in this order). A fault whose
    /// probability is 0 draws nothing, so adding one keeps the runs of the others as they were.
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
        } else if rng.chance(self.flip_bit) {
            FaultAction::FlipBit(rng.next_u64())
        } else if rng.chance(self.truncate) {
            FaultAction::Truncate(rng.next_u64())
        } else if rng.chance(self.glitch) {
            FaultAction::Glitch(rng.next_u64())
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

/// Inverts bit `seed % 8` of the byte `seed / 8` (modulo the length) of `frame`.
pub fn flip_bit(frame: &mut [u8], seed: u64) {
    if frame.is_empty() {
        return;
    }
    let index = ((seed >> 3) % frame.len() as u64) as usize;
    frame[index] ^= 1 << (seed & 7);
}

/// Cuts `frame` to 1 … len − 1 bytes (a frame of one byte or none is left as it is).
pub fn truncate(frame: &mut Vec<u8>, seed: u64) {
    if frame.len() > 1 {
        let keep = 1 + (seed % (frame.len() as u64 - 1)) as usize;
        frame.truncate(keep);
    }
}

/// Puts a stray byte right before `frame` (even seeds) or right after it (odd ones): 0x00 or
/// 0xFF (a line pulled low or left high while the driver switches) or, one time in three, any.
pub fn glitch(frame: &mut Vec<u8>, seed: u64) {
    let byte = match (seed >> 1) % 3 {
        0 => 0x00,
        1 => 0xFF,
        _ => (seed >> 8) as u8,
    };
    if seed & 1 == 0 {
        frame.insert(0, byte);
    } else {
        frame.push(byte);
    }
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

    #[test]
    fn line_errors_change_what_they_say() {
        let reply = vec![0x14, 0x03, 0x02, 0x00, 0x14, 0xB5, 0x76];
        let mut flipped = reply.clone();
        flip_bit(&mut flipped, (2 << 3) | 3);
        assert_eq!(flipped, vec![0x14, 0x03, 0x0A, 0x00, 0x14, 0xB5, 0x76]);
        for seed in 0..200 {
            let mut flipped = reply.clone();
            flip_bit(&mut flipped, seed);
            let differing: u32 = flipped
                .iter()
                .zip(&reply)
                .map(|(a, b)| (a ^ b).count_ones())
                .sum();
            assert_eq!(differing, 1, "seed {seed}");

            let mut cut = reply.clone();
            truncate(&mut cut, seed);
            assert!((1..reply.len()).contains(&cut.len()), "seed {seed}");
            assert_eq!(cut[..], reply[..cut.len()]);

            let mut stray = reply.clone();
            glitch(&mut stray, seed);
            assert_eq!(stray.len(), reply.len() + 1);
            let kept = if seed & 1 == 0 {
                &stray[1..]
            } else {
                &stray[..reply.len()]
            };
            assert_eq!(kept, &reply[..], "seed {seed}");
        }
        let mut empty = Vec::new();
        flip_bit(&mut empty, 5);
        truncate(&mut empty, 5);
        assert!(empty.is_empty());
        let mut one = vec![0x14];
        truncate(&mut one, 5);
        assert_eq!(one, vec![0x14]);
    }

    #[test]
    fn a_fault_left_at_zero_draws_nothing() {
        // The draws of a mix of two faults, as they were before the line errors existed: the
        // sweep's seeds must give the same runs.
        let two = Faults {
            corrupt_crc: 0.3,
            garbage: 0.3,
            ..Faults::default()
        };
        let mut drawn = XorShift64::new(9);
        let mut reference = XorShift64::new(9);
        for _ in 0..100 {
            let expected = if reference.chance(0.3) {
                FaultAction::CorruptCrc
            } else if reference.chance(0.3) {
                FaultAction::Garbage(reference.next_u64())
            } else {
                FaultAction::None
            };
            assert_eq!(two.draw(&mut drawn), expected);
        }
        let mut rng = XorShift64::new(3);
        let only_glitch = Faults {
            glitch: 1.0,
            ..Faults::default()
        };
        assert!(matches!(only_glitch.draw(&mut rng), FaultAction::Glitch(_)));
    }
}
