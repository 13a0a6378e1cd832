//! The receiving side of the virtual line: which port settings the master used, and how bytes
//! that arrive with timestamps become requests (a gap of 3.5 characters ends a frame).

use std::time::Duration;

use crate::protocol::{LineSettings, Parity, ParseStatus, ParsedRequest, RequestParser};

/// The parity the master's line is known to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ObservedParity {
    Known(Parity),
    /// A Linux pseudo-terminal clears PARENB on its end: only PARODD survives, so "none" and
    /// "even" cannot be told apart there. Devices with either parity hear such a master.
    NoneOrEven,
}

/// The settings the master sent a request with, as far as the transport can tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct MasterLine {
    pub baud: u32,
    pub data_bits: u8,
    pub stop_bits: u8,
    pub parity: ObservedParity,
}

impl MasterLine {
    /// Settings known exactly (TCP listener, tests).
    pub fn exact(line: LineSettings) -> Self {
        Self {
            baud: line.baud,
            data_bits: line.data_bits,
            stop_bits: line.stop_bits,
            parity: ObservedParity::Known(line.parity),
        }
    }

    /// Does a device with these settings understand the master? A mismatch is noise to it.
    ///
    /// The stop bits do not count: a UART receiver checks only the first stop bit, whatever
    /// number it is set to (16550-compatible datasheets: "the receiver will ignore all stop
    /// bits beyond the first"; a few UARTs can be told to check both, which the scan allows for
    /// by sending a troubled setting again with 1), and a second one is just idle line before
    /// the next start bit. So a
    /// device at 8N1 hears a master at 8N2 and the other way round, and the master hears the
    /// replies of both; two devices that differ only in stop bits answer the same request.
    pub fn matches(&self, device: &LineSettings) -> bool {
        let parity_ok = match self.parity {
            ObservedParity::Known(parity) => parity == device.parity,
            ObservedParity::NoneOrEven => device.parity != Parity::Odd,
        };
        self.baud == device.baud && self.data_bits == device.data_bits && parity_ok
    }

    /// The settings to time the line with (parity "none" when it cannot be told).
    pub fn settings(&self) -> LineSettings {
        let parity = match self.parity {
            ObservedParity::Known(parity) => parity,
            ObservedParity::NoneOrEven => Parity::None,
        };
        LineSettings {
            data_bits: self.data_bits,
            ..LineSettings::new(self.baud, parity, self.stop_bits)
        }
    }
}

/// A request as it arrived.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReceivedRequest {
    pub request: ParsedRequest,
    /// Bytes of the frame, CRC included.
    pub frame_len: usize,
    /// When the first byte of the frame was read.
    pub first_byte_at: Duration,
    /// When its last byte was read.
    pub last_byte_at: Duration,
    pub line: MasterLine,
    /// Sent by a second master on the bus ([`super::other_master`]), not the one served.
    pub from_other_master: bool,
}

impl ReceivedRequest {
    /// When the frame ended on a wire at `device_line`: a master writes a whole frame at once to a
    /// pseudo-terminal, so the frame takes its wire time from its first byte's arrival. The
    /// master's characters carry the master's stop bits (a device at 8N1 hearing a master at 8N2
    /// sees each character followed by one more idle bit), the rest is the device's settings
    /// (parity "none" or "even" from a pty is the device's).
    pub fn end_on_wire(&self, device_line: &LineSettings) -> Duration {
        let sent_with = LineSettings {
            stop_bits: self.line.stop_bits,
            ..*device_line
        };
        self.last_byte_at
            .max(self.first_byte_at + sent_with.wire_time(self.frame_len))
    }
}

/// Turns timestamped chunks of bytes into requests.
#[derive(Debug, Clone, Default)]
pub struct RequestAssembler {
    parser: RequestParser,
    frame_started_at: Option<Duration>,
    last_byte_at: Duration,
    line: Option<MasterLine>,
}

impl RequestAssembler {
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes read at `at` from a master using `line`. Returns the requests they complete.
    pub fn receive(
        &mut self,
        bytes: &[u8],
        at: Duration,
        line: MasterLine,
    ) -> Vec<ReceivedRequest> {
        let mut requests = Vec::new();
        if bytes.is_empty() {
            return requests;
        }
        if let Some(deadline) = self.silence_deadline() {
            if at >= deadline {
                requests.extend(self.on_silence());
            }
        }
        if self.line.is_some_and(|old| old != line) {
            // Settings changed in the middle of a frame: what was buffered is noise.
            self.parser = RequestParser::new();
            self.frame_started_at = None;
        }
        self.line = Some(line);
        if self.parser.buffered().is_empty() {
            self.frame_started_at = Some(at);
        }
        self.last_byte_at = at;
        self.parser.push(bytes);
        self.drain(at, false, &mut requests);
        requests
    }

    /// When the line will have been silent long enough to end the buffered frame.
    pub fn silence_deadline(&self) -> Option<Duration> {
        let line = self.line?;
        (!self.parser.buffered().is_empty())
            .then(|| self.last_byte_at + line.settings().frame_silence())
    }

    /// The line has been silent past [`Self::silence_deadline`].
    pub fn on_silence(&mut self) -> Vec<ReceivedRequest> {
        let mut requests = Vec::new();
        let at = self.last_byte_at;
        self.drain(at, true, &mut requests);
        self.frame_started_at = None;
        requests
    }

    fn drain(&mut self, at: Duration, silence: bool, out: &mut Vec<ReceivedRequest>) {
        let Some(line) = self.line else {
            return;
        };
        let mut silence_used = false;
        // Each poll consumes bytes or returns NeedMore, so this ends; the bound is a safety net.
        for _ in 0..=2 * crate::protocol::frame::MAX_FRAME_LEN {
            let before = self.parser.buffered().len();
            let status = match self.parser.poll() {
                ParseStatus::NeedMore if silence && !silence_used => {
                    silence_used = true;
                    self.parser.silence()
                }
                status => status,
            };
            let after = self.parser.buffered().len();
            match status {
                ParseStatus::NeedMore => break,
                ParseStatus::Error(err) => {
                    tracing::debug!("sim: line noise: {err}");
                }
                ParseStatus::Frame(request) => {
                    out.push(ReceivedRequest {
                        request,
                        frame_len: before.saturating_sub(after),
                        first_byte_at: self.frame_started_at.unwrap_or(at),
                        last_byte_at: at,
                        line,
                        from_other_master: false,
                    });
                    self.frame_started_at = Some(at);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{parse_hex, Request};

    fn line() -> MasterLine {
        MasterLine::exact(LineSettings::new(9600, Parity::None, 2))
    }

    #[test]
    fn a_frame_split_in_chunks_is_one_request() {
        let mut assembler = RequestAssembler::new();
        let frame = parse_hex("14 03 00 80 00 01 87 27").unwrap();
        let ms = Duration::from_millis;
        assert!(assembler.receive(&frame[..3], ms(10), line()).is_empty());
        let requests = assembler.receive(&frame[3..], ms(11), line());
        assert_eq!(requests.len(), 1);
        assert_eq!(requests[0].frame_len, 8);
        assert_eq!(requests[0].first_byte_at, ms(10));
        assert_eq!(
            requests[0].request,
            ParsedRequest::Valid(Request::decode(&frame).unwrap())
        );
    }

    #[test]
    fn a_long_gap_drops_the_partial_frame() {
        let mut assembler = RequestAssembler::new();
        let frame = parse_hex("14 03 00 80 00 01 87 27").unwrap();
        let ms = Duration::from_millis;
        assert!(assembler.receive(&frame[..3], ms(10), line()).is_empty());
        assert!(assembler.receive(&frame[3..], ms(20), line()).is_empty());
        assert!(assembler.receive(&frame, ms(40), line()).len() == 1);
    }

    #[test]
    fn unknown_functions_end_at_silence() {
        let mut assembler = RequestAssembler::new();
        let frame = parse_hex("14 2B 0E 01 00 F3 19").unwrap();
        let frame = {
            let mut f = frame[..5].to_vec();
            crate::protocol::crc::append_crc(&mut f);
            f
        };
        assert!(assembler.receive(&frame, Duration::ZERO, line()).is_empty());
        let deadline = assembler.silence_deadline().unwrap();
        assert!(deadline > Duration::from_millis(4));
        let requests = assembler.on_silence();
        assert!(matches!(requests[0].request, ParsedRequest::Rejected(_)));
        assert_eq!(assembler.silence_deadline(), None);
    }

    #[test]
    fn pty_parity_is_ambiguous() {
        let pty = MasterLine {
            baud: 9600,
            data_bits: 8,
            stop_bits: 1,
            parity: ObservedParity::NoneOrEven,
        };
        assert!(pty.matches(&LineSettings::new(9600, Parity::None, 1)));
        assert!(pty.matches(&LineSettings::new(9600, Parity::Even, 1)));
        assert!(!pty.matches(&LineSettings::new(9600, Parity::Odd, 1)));
        assert!(!pty.matches(&LineSettings::new(4800, Parity::None, 1)));
    }

    #[test]
    fn stop_bits_do_not_stop_a_device_hearing_the_master() {
        for (master_stop, device_stop) in [(1, 1), (1, 2), (2, 1), (2, 2)] {
            for parity in [Parity::None, Parity::Even, Parity::Odd] {
                let master = MasterLine::exact(LineSettings::new(19200, parity, master_stop));
                assert!(
                    master.matches(&LineSettings::new(19200, parity, device_stop)),
                    "{parity:?} {master_stop} -> {device_stop}"
                );
            }
        }
        let master = MasterLine::exact(LineSettings::new(19200, Parity::None, 2));
        assert!(!master.matches(&LineSettings::new(19200, Parity::Even, 2)));
        assert!(!master.matches(&LineSettings::new(9600, Parity::None, 2)));
        let seven_bits = LineSettings {
            data_bits: 7,
            ..LineSettings::new(19200, Parity::None, 2)
        };
        assert!(!master.matches(&seven_bits));
    }

    #[test]
    fn a_frame_ends_after_the_masters_stop_bits() {
        let mut assembler = RequestAssembler::new();
        let frame = parse_hex("14 03 00 80 00 01 87 27").unwrap();
        let master = MasterLine::exact(LineSettings::new(9600, Parity::None, 2));
        let requests = assembler.receive(&frame, Duration::ZERO, master);
        let one_stop_bit = LineSettings::new(9600, Parity::None, 1);
        // 8 characters of 11 bits, not of the device's 10.
        assert_eq!(
            requests[0].end_on_wire(&one_stop_bit),
            LineSettings::new(9600, Parity::None, 2).wire_time(8)
        );
    }
}
