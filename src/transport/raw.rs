//! A raw transfer (wb-mqtt-serial's `port/Load` without `protocol`), sans IO: bytes out as
//! given, then whatever comes back, up to a size, until the first byte's timeout or a silence
//! between bytes. No frame is parsed: the caller speaks a protocol rtu2mqtt does not know (a
//! meter's own, a device's bootloader), so silence is an empty answer, never an error.
//!
//! Times are durations on the transport's clock, passed in by the caller, as for
//! [`Exchange`](super::exchange::Exchange).

use std::time::Duration;

use super::exchange::{LinkConfig, Transmit};
use crate::protocol::crc::crc_is_valid;

/// What the caller asks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawRequest {
    pub bytes: Vec<u8>,
    /// Stop once this many bytes came (0: send only).
    pub response_size: usize,
    /// For the first byte, counted from the end of the request on the wire.
    pub response_timeout: Duration,
    /// Silence after a byte that ends the answer.
    pub frame_timeout: Duration,
}

impl RawRequest {
    /// The device address of a Modbus RTU frame these bytes make (an address 1…247, at least
    /// a function code, a valid CRC): a raw transfer is often one (wb-mqtt-serial's scripts
    /// read registers that way), and a late reply to it is then as dangerous to the scheduler's
    /// next request to that device as any other ([`PortScheduler::raw_done`](crate::port::scheduler::PortScheduler::raw_done)).
    /// `None` for other protocols' bytes, broadcasts and requests by serial number.
    pub fn modbus_address(&self) -> Option<u8> {
        let address = *self.bytes.first()?;
        ((1..=247).contains(&address) && self.bytes.len() >= 4 && crc_is_valid(&self.bytes))
            .then_some(address)
    }

    /// Whether `answer` is a whole Modbus RTU frame from `address` (a reply, or an exception):
    /// nothing of the device's answer can still be on its way.
    pub fn answered_by(answer: &[u8], address: u8) -> bool {
        answer.len() >= 4 && answer.first() == Some(&address) && crc_is_valid(answer)
    }
}

#[derive(Debug)]
enum State {
    Pending,
    /// Handed to the driver at `write_started`; waiting for [`RawTransfer::handle_sent`].
    Sending {
        write_started: Duration,
    },
    Receiving {
        /// When the request has left the wire: earlier bytes are not the answer (an echo, a
        /// straggler of the last transaction).
        clock_start: Duration,
        last_byte: Option<Duration>,
    },
    Done,
}

/// One raw transfer on one link.
#[derive(Debug)]
pub struct RawTransfer {
    request: RawRequest,
    link: LinkConfig,
    state: State,
    received: Vec<u8>,
    /// The end of the request on the wire or the last byte received, whichever is later.
    line_busy_until: Option<Duration>,
}

impl RawTransfer {
    pub fn new(request: RawRequest, link: LinkConfig) -> Self {
        Self {
            received: Vec::with_capacity(request.response_size.min(4096)),
            request,
            link,
            state: State::Pending,
            line_busy_until: None,
        }
    }

    /// The bytes to write (once), after dropping what the line delivered unasked.
    pub fn poll_transmit(&mut self, now: Duration) -> Option<Transmit> {
        if !matches!(self.state, State::Pending) {
            return None;
        }
        self.state = State::Sending { write_started: now };
        Some(Transmit {
            flush_input: true,
            bytes: self.request.bytes.clone(),
        })
    }

    /// The driver's `write` returned at `now`.
    pub fn handle_sent(&mut self, now: Duration) {
        let State::Sending { write_started } = self.state else {
            return;
        };
        // On a serial line the request is still leaving the wire when `write` returns.
        let on_wire = self
            .link
            .serial
            .map(|line| write_started + line.wire_time(self.request.bytes.len()))
            .unwrap_or(now);
        let clock_start = on_wire.max(now);
        self.line_busy_until = Some(clock_start);
        if self.request.response_size == 0 {
            self.state = State::Done;
            return;
        }
        self.state = State::Receiving {
            clock_start,
            last_byte: None,
        };
    }

    /// Bytes read at `now`.
    pub fn handle_bytes(&mut self, now: Duration, bytes: &[u8]) {
        let State::Receiving {
            clock_start,
            last_byte,
        } = &mut self.state
        else {
            return;
        };
        if self.link.discards_early_bytes() && now < *clock_start && last_byte.is_none() {
            return;
        }
        let room = self
            .request
            .response_size
            .saturating_sub(self.received.len());
        self.received
            .extend_from_slice(bytes.get(..room.min(bytes.len())).unwrap_or_default());
        *last_byte = Some(now);
        self.line_busy_until = Some(now);
        if self.received.len() >= self.request.response_size {
            self.state = State::Done;
        }
    }

    /// When to call [`Self::handle_timeout`] if no byte comes first.
    pub fn poll_timeout(&self) -> Option<Duration> {
        match self.state {
            State::Receiving {
                clock_start,
                last_byte: None,
            } => Some(clock_start + self.request.response_timeout),
            State::Receiving {
                last_byte: Some(at),
                ..
            } => Some(at + self.request.frame_timeout),
            _ => None,
        }
    }

    pub fn handle_timeout(&mut self, now: Duration) {
        if self.poll_timeout().is_some_and(|at| now >= at) {
            self.state = State::Done;
        }
    }

    /// The answer, once the transfer is over (empty when nothing came).
    pub fn poll_outcome(&mut self) -> Option<Vec<u8>> {
        matches!(self.state, State::Done).then(|| std::mem::take(&mut self.received))
    }

    /// Until when the line was busy with this transfer, finished or not (for the guard
    /// interval of the next request).
    pub fn line_busy_until(&self) -> Option<Duration> {
        self.line_busy_until
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_raw_modbus_request_is_known_by_its_address_and_crc() {
        let request = |bytes: Vec<u8>| RawRequest {
            bytes,
            response_size: 7,
            response_timeout: Duration::from_millis(50),
            frame_timeout: Duration::from_millis(20),
        };
        // Read input 10 of device 40.
        let read = vec![0x28, 0x04, 0x00, 0x0A, 0x00, 0x01, 0x16, 0x31];
        assert_eq!(request(read.clone()).modbus_address(), Some(40));
        let mut bad_crc = read.clone();
        bad_crc[7] ^= 1;
        assert_eq!(request(bad_crc).modbus_address(), None);
        let mut broadcast = read.clone();
        broadcast[0] = 0;
        assert_eq!(request(broadcast).modbus_address(), None);
        assert_eq!(request(b"/?!\r\n".to_vec()).modbus_address(), None);
        assert_eq!(request(Vec::new()).modbus_address(), None);
        // Its reply: 28 04 02 00 DE + CRC.
        let mut reply = vec![0x28, 0x04, 0x02, 0x00, 0xDE];
        crate::protocol::crc::append_crc(&mut reply);
        assert!(RawRequest::answered_by(&reply, 40));
        assert!(!RawRequest::answered_by(&reply, 41));
        assert!(!RawRequest::answered_by(&reply[..6], 40));
        assert!(!RawRequest::answered_by(&[], 40));
    }
    use crate::protocol::{LineSettings, Parity};

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    fn line_9600() -> LineSettings {
        LineSettings {
            baud: 9600,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 2,
        }
    }

    fn request(size: usize) -> RawRequest {
        RawRequest {
            bytes: vec![0x01, 0x03, 0x00, 0x00, 0x00, 0x01, 0x84, 0x0A],
            response_size: size,
            response_timeout: ms(500),
            frame_timeout: ms(20),
        }
    }

    /// Sends the request at 0 with `write` returning at once; the clock starts once the
    /// 8 bytes have left the wire at 9600 8N2 (8 × 11 bits ≈ 9.17 ms).
    fn sent(size: usize) -> RawTransfer {
        let mut raw = RawTransfer::new(request(size), LinkConfig::serial(line_9600()));
        let transmit = raw.poll_transmit(ms(0)).unwrap();
        assert!(transmit.flush_input);
        assert_eq!(transmit.bytes, request(size).bytes);
        assert_eq!(raw.poll_transmit(ms(0)), None, "written once");
        raw.handle_sent(ms(0));
        raw
    }

    #[test]
    fn the_answer_ends_at_its_size() {
        let mut raw = sent(7);
        let wire = line_9600().wire_time(8);
        assert_eq!(raw.poll_timeout(), Some(wire + ms(500)));
        raw.handle_bytes(ms(20), &[0x01, 0x03, 0x02]);
        assert_eq!(raw.poll_outcome(), None);
        assert_eq!(raw.poll_timeout(), Some(ms(40)), "then the frame timeout");
        raw.handle_bytes(ms(25), &[0x00, 0x2A, 0x39, 0x9B, 0xFF]);
        assert_eq!(
            raw.poll_outcome(),
            Some(vec![0x01, 0x03, 0x02, 0x00, 0x2A, 0x39, 0x9B]),
            "nothing past the size"
        );
        assert_eq!(
            raw.line_busy_until(),
            Some(ms(25)),
            "the guard interval counts from the last byte, after the transfer too"
        );
    }

    #[test]
    fn a_silence_ends_a_shorter_answer_and_silence_is_empty() {
        let mut raw = sent(100);
        raw.handle_bytes(ms(20), &[0xAA, 0xBB]);
        raw.handle_timeout(ms(39));
        assert_eq!(raw.poll_outcome(), None, "not yet silent long enough");
        raw.handle_timeout(ms(40));
        assert_eq!(raw.poll_outcome(), Some(vec![0xAA, 0xBB]));

        let mut silent = sent(100);
        let first_byte_deadline = silent.poll_timeout().unwrap();
        silent.handle_timeout(first_byte_deadline);
        assert_eq!(silent.poll_outcome(), Some(Vec::new()));
    }

    #[test]
    fn bytes_before_the_request_left_the_wire_are_not_the_answer() {
        let mut raw = sent(4);
        raw.handle_bytes(ms(3), &[0x01, 0x03]);
        raw.handle_bytes(ms(12), &[0x05, 0x06]);
        raw.handle_bytes(ms(13), &[0x07, 0x08]);
        assert_eq!(raw.poll_outcome(), Some(vec![0x05, 0x06, 0x07, 0x08]));
    }

    #[test]
    fn send_only_needs_no_answer() {
        let mut raw = sent(0);
        assert_eq!(raw.poll_timeout(), None);
        assert_eq!(raw.poll_outcome(), Some(Vec::new()));
    }
}
