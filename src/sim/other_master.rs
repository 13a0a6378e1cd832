//! A second master on the bus (the `other_master` control command): a wb-mqtt-serial the web
//! UI's editor restarted, or a laptop's Modbus tool on the same pair. It sends one request at a
//! fixed pace whatever is on the wire, as such a master does: it does not listen before it
//! talks (unless told to: then it waits for a frame gap of silence, and more of its requests
//! are answered). Its bytes reach the master under test as they would on a real pair (RS-485 is one
//! shared line), and the devices answer it ([`super::wire::Wire::other_master_sends`]).
//! Pure: time comes in with every call.

use std::time::Duration;

use crate::protocol::{Request, RequestPdu};

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OtherMaster {
    /// The request, CRC included.
    frame: Vec<u8>,
    every: Duration,
    next: Duration,
    /// It waits for a frame gap of silence before it talks (most masters do not).
    pub listens: bool,
}

impl OtherMaster {
    /// Reads `count` registers of `register_type` from `start` at `address`, every `every`
    /// from `now + every`.
    pub fn reading(
        address: u8,
        pdu: RequestPdu,
        every: Duration,
        now: Duration,
    ) -> Result<Self, String> {
        if every.is_zero() {
            return Err("\"every_ms\" must be above 0 (leave it out to stop)".into());
        }
        let frame = Request::classic(address, pdu)
            .encode()
            .map_err(|err| format!("the request does not encode: {err}"))?;
        Ok(Self {
            frame,
            every,
            next: now + every,
            listens: false,
        })
    }

    pub fn frame(&self) -> &[u8] {
        &self.frame
    }

    /// When it sends next.
    pub fn due(&self) -> Duration {
        self.next
    }

    /// Its request if it is due at `now`. After a stall (the simulator's thread held up) it
    /// sends once, not every request it missed.
    pub fn turn(&mut self, now: Duration) -> Option<&[u8]> {
        if now < self.next {
            return None;
        }
        self.next += self.every;
        if self.next <= now {
            self.next = now + self.every;
        }
        Some(&self.frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    #[test]
    fn sends_at_its_pace_and_once_after_a_stall() {
        let pdu = RequestPdu::ReadInputRegisters { start: 2, count: 2 };
        let mut other = OtherMaster::reading(3, pdu, ms(200), ms(1000)).unwrap();
        assert_eq!(
            other.frame(),
            [0x03, 0x04, 0x00, 0x02, 0x00, 0x02, 0xD1, 0xE9]
        );
        assert_eq!(other.due(), ms(1200));
        assert_eq!(other.turn(ms(1199)), None);
        assert!(other.turn(ms(1200)).is_some());
        assert_eq!(other.due(), ms(1400));
        assert!(other.turn(ms(1400)).is_some());
        // Held up for a second: one request, then the pace again from there.
        assert!(other.turn(ms(2450)).is_some());
        assert_eq!(other.due(), ms(2650));
        assert_eq!(other.turn(ms(2500)), None);
    }

    #[test]
    fn a_zero_pace_is_refused() {
        let pdu = RequestPdu::ReadHoldingRegisters { start: 0, count: 1 };
        assert!(OtherMaster::reading(1, pdu, Duration::ZERO, ms(0)).is_err());
    }
}
