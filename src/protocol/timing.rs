//! Wire timing: character times, frame silence, arbitration windows and reply timeouts, the event
//! poll interval. Pure arithmetic on [`LineSettings`]; durations, never a clock.

use std::fmt;
use std::time::Duration;

/// Parity of the serial line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Parity {
    None,
    Even,
    Odd,
}

impl Parity {
    /// The letter of the usual "8N1" notation.
    pub fn letter(self) -> char {
        match self {
            Self::None => 'N',
            Self::Even => 'E',
            Self::Odd => 'O',
        }
    }
}

/// Baud rate and character framing of a serial line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LineSettings {
    pub baud: u32,
    pub data_bits: u8,
    pub parity: Parity,
    pub stop_bits: u8,
}

/// The baud rates a serial port is usually set to, slowest first: the series wb-mqtt-serial's
/// port settings offer (110 … 115200) and the faster standard UART rates. Any other rate is legal
/// but far more often a typo (9601, 96000) than a device's real setting.
pub const USUAL_BAUD_RATES: [u32; 14] = [
    110, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115_200, 230_400, 460_800, 921_600,
];

/// Baud rates a scan tries, slowest first: the usual ones from 1200 to 115200.
pub const STANDARD_BAUD_RATES: [u32; 8] = usual_baud_rates_from(3);

const fn usual_baud_rates_from<const N: usize>(first: usize) -> [u32; N] {
    let mut out = [0; N];
    let mut i = 0;
    while i < N {
        out[i] = USUAL_BAUD_RATES[first + i];
        i += 1;
    }
    out
}

/// Whether `baud` is one of [`USUAL_BAUD_RATES`].
pub fn is_usual_baud_rate(baud: u32) -> bool {
    USUAL_BAUD_RATES.contains(&baud)
}

/// The usual baud rates as a config check lists them: "110, 300, …, 921600".
pub fn usual_baud_rates_text() -> String {
    USUAL_BAUD_RATES
        .iter()
        .map(u32::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

const NANOS_PER_SECOND: u64 = 1_000_000_000;

impl LineSettings {
    /// 9600 8N2: what Wiren Board devices ship with.
    pub const WIREN_BOARD_DEFAULT: Self = Self::new(9600, Parity::None, 2);

    pub const fn new(baud: u32, parity: Parity, stop_bits: u8) -> Self {
        Self {
            baud,
            data_bits: 8,
            parity,
            stop_bits,
        }
    }

    /// Start bit + data bits + parity bit + stop bits.
    pub fn bits_per_char(&self) -> u32 {
        1 + u32::from(self.data_bits)
            + u32::from(self.parity != Parity::None)
            + u32::from(self.stop_bits)
    }

    /// Time of `bits` bit periods, rounded up to whole nanoseconds. A zero baud rate is read as 1
    /// baud so that no input can divide by zero.
    pub fn bits_time(&self, bits: u64) -> Duration {
        let baud = u64::from(self.baud.max(1));
        Duration::from_nanos(bits.saturating_mul(NANOS_PER_SECOND).div_ceil(baud))
    }

    pub fn bit_time(&self) -> Duration {
        self.bits_time(1)
    }

    /// One character on the wire.
    pub fn char_time(&self) -> Duration {
        self.bits_time(u64::from(self.bits_per_char()))
    }

    /// Time `bytes` characters occupy the wire, sent back to back.
    pub fn wire_time(&self, bytes: usize) -> Duration {
        let bytes = u64::try_from(bytes).unwrap_or(u64::MAX);
        self.bits_time(bytes.saturating_mul(u64::from(self.bits_per_char())))
    }

    /// The silence between frames that devices and masters keep: 3.5 characters at every
    /// baud rate (what Fast Modbus devices and wb-mqtt-serial use; see [`Self::frame_silence`]
    /// for the Modbus spec's fixed 1.75 ms above 19200).
    pub fn frame_gap(&self) -> Duration {
        self.char_time().saturating_mul(7) / 2
    }

    /// How long after the last byte of a frame a UART hands it to the reader: a 16550's
    /// receive timeout, 4 characters of quiet line with bytes still in its FIFO. A master's
    /// first-byte timeouts allow for it; the simulator delivers the end of every frame so.
    pub fn receive_timeout(&self) -> Duration {
        self.char_time().saturating_mul(RECEIVE_TIMEOUT_CHARS)
    }

    /// The silence that ends an RTU frame: 3.5 characters, fixed at 1.75 ms above 19200 baud.
    pub fn frame_silence(&self) -> Duration {
        if self.baud > 19200 {
            Duration::from_micros(1750)
        } else {
            self.bits_time(u64::from(self.bits_per_char()) * 7)
                .div_f64(2.0)
        }
    }

    /// Whole bits needed to cover `duration` (rounded up).
    fn bits_covering(&self, duration: Duration) -> u64 {
        let nanos = u64::try_from(duration.as_nanos()).unwrap_or(u64::MAX);
        nanos
            .saturating_mul(u64::from(self.baud.max(1)))
            .div_ceil(NANOS_PER_SECOND)
    }

    /// Quiet time after a Fast Modbus broadcast request before the first arbitration window:
    /// `max(3.5 characters, 12 bits + 800 µs)`, a character being the extension's 12 bits
    /// (start, 8 data, parity, 2 stop: the article's `3.5 × 12 = 42 bits`) whatever the line's
    /// own framing, as the windows are.
    pub fn arbitration_wait(&self) -> Duration {
        self.bits_time(ARBITRATION_WAIT_BITS)
            .max(self.bits_time(12) + Duration::from_micros(800))
    }

    /// When a device opens the first arbitration window after the end of a broadcast request:
    /// `max(42 bits, 800 µs rounded up to whole bits)`. This is the article's device-side
    /// figure (807.3 µs at 115200, 4.375 ms at 9600), never later than
    /// [`Self::arbitration_wait`], which masters use with its extra 12 bits as a margin.
    pub fn device_arbitration_wait(&self) -> Duration {
        let floor = self.bits_covering(Duration::from_micros(800));
        self.bits_time(ARBITRATION_WAIT_BITS.max(floor))
    }

    /// One arbitration window: `max(13 bits, 12 bits + 50 µs rounded up to whole bits)`.
    pub fn arbitration_window(&self) -> Duration {
        let reserve_bits = self.bits_covering(Duration::from_micros(50));
        self.bits_time(13.max(12 + reserve_bits))
    }

    /// Longest time from the end of a scan request to the first byte of the winner's frame:
    /// wait + 32 windows (4-bit marker + 28-bit serial).
    pub fn scan_reply_timeout(&self) -> Duration {
        self.arbitration_wait() + self.arbitration_window() * ARBITRATION_WINDOWS_SCAN
    }

    /// Longest time from the end of an event request to the first byte of the winner's frame:
    /// wait + 12 windows (4-bit marker + 8-bit address).
    pub fn event_reply_timeout(&self) -> Duration {
        self.arbitration_wait() + self.arbitration_window() * ARBITRATION_WINDOWS_EVENTS
    }

    /// When nothing at all has arrived by then after an event request, no device takes part:
    /// every address 1..=247 has a 0 bit within its first 5 bits, so a contender sends a filler
    /// byte by window 4 + 5 = 9.
    pub fn event_first_byte_timeout(&self) -> Duration {
        self.arbitration_wait() + self.arbitration_window() * EVENT_FIRST_DOMINANT_WINDOW
    }

    /// After a scan start every device is un-scanned, and the marker 0b0110 starts with a 0 bit:
    /// if any device uses these settings, the first window already carries a filler byte.
    pub fn scan_start_first_byte_timeout(&self) -> Duration {
        self.arbitration_wait() + self.arbitration_window()
    }

    /// [`Self::scan_reply_timeout`] for the deprecated 0x60 scan: its first window opens 44
    /// bits after the request and each is 20 bits long (32 windows), never shorter than the
    /// 0x46 scan's.
    pub fn legacy_scan_reply_timeout(&self) -> Duration {
        let windows = u64::from(ARBITRATION_WINDOWS_SCAN) * LEGACY_SCAN_WINDOW_BITS;
        self.bits_time(LEGACY_SCAN_WAIT_BITS + windows)
            .max(self.scan_reply_timeout())
    }

    /// [`Self::scan_start_first_byte_timeout`] for the deprecated 0x60 scan: the end of its
    /// first window (44 + 20 bits), never shorter than the 0x46 scan's.
    pub fn legacy_scan_start_first_byte_timeout(&self) -> Duration {
        self.bits_time(LEGACY_SCAN_WAIT_BITS + LEGACY_SCAN_WINDOW_BITS)
            .max(self.scan_start_first_byte_timeout())
    }

    /// How often the master asks for events: every 50 ms at 115200 baud and above, 100 ms from
    /// 38400, 200 ms below.
    pub fn event_poll_interval(&self) -> Duration {
        match self.baud {
            115_200.. => Duration::from_millis(50),
            38_400.. => Duration::from_millis(100),
            _ => Duration::from_millis(200),
        }
    }

    /// Wire time of one transaction: request, device turnaround, reply, and the frame gap a
    /// master keeps before its next request.
    pub fn transaction_time(
        &self,
        request_len: usize,
        turnaround: Duration,
        reply_len: usize,
    ) -> Duration {
        self.wire_time(request_len) + turnaround + self.wire_time(reply_len) + self.frame_gap()
    }
}

/// A 16550's receive timeout, in characters (see [`LineSettings::receive_timeout`]).
pub const RECEIVE_TIMEOUT_CHARS: u32 = 4;

/// What USB-RS485 adapters and the kernel add to a reply's arrival: wb-mqtt-serial's allowance on
/// serial lines, added to every response timeout.
pub const ADAPTER_LATENCY_ALLOWANCE: Duration = Duration::from_millis(24);

/// The response timeout when neither the port nor the device sets one (wb-mqtt-serial's default).
pub const DEFAULT_RESPONSE_TIMEOUT: Duration = Duration::from_millis(500);

/// The longest a learned response time may grow: a device slower than this is broken, and a
/// longer wait would stall the bus (and shutdown) for nothing.
pub const MAX_LEARNED_RESPONSE_TIMEOUT: Duration = Duration::from_secs(3);

/// How long a late reply keeps its device's response timeout raised before the smoothed
/// estimate alone decides again.
pub const LATE_REPLY_MEMORY: Duration = Duration::from_secs(300);

impl LineSettings {
    /// wb-mqtt-serial's response timeout on a serial line: the configured one (the larger of port
    /// and device, 500 ms when neither sets it) plus 24 ms of adapter latency and one character.
    /// Counted from the end of the request to the first byte of the reply. Templates say 1 ms
    /// because the allowance is always added.
    pub fn response_timeout_floor(&self, configured: Duration) -> Duration {
        configured
            .saturating_add(ADAPTER_LATENCY_ALLOWANCE)
            .saturating_add(self.char_time())
    }
}

/// One device's response time, learned as TCP learns its retransmission timeout (RFC 6298): a
/// smoothed time to the first byte and its variation. The timeout never falls below the
/// configured floor; a late reply (bytes after the timeout) raises it for
/// [`LATE_REPLY_MEMORY`], so that the device's next answers arrive in time instead of landing in
/// the window of the next request.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseTimer {
    floor: Duration,
    smoothed: Option<Duration>,
    variation: Duration,
    /// A timeout that covers the latest late reply, and until when it holds.
    late: Option<(Duration, Duration)>,
}

impl ResponseTimer {
    pub fn new(floor: Duration) -> Self {
        Self {
            floor,
            smoothed: None,
            variation: Duration::ZERO,
            late: None,
        }
    }

    pub fn floor(&self) -> Duration {
        self.floor
    }

    /// The smoothed time to the first byte learned so far (none before the first reply).
    pub fn learned(&self) -> Option<Duration> {
        self.smoothed
    }

    /// How long to wait for the first byte of a reply, from the end of the request.
    pub fn timeout(&self, now: Duration) -> Duration {
        let learned = self
            .smoothed
            .map(|smoothed| smoothed.saturating_mul(3) / 2 + self.variation.saturating_mul(4))
            .unwrap_or_default();
        let late = self
            .late
            .filter(|(_, until)| now < *until)
            .map(|(timeout, _)| timeout)
            .unwrap_or_default();
        let ceiling = MAX_LEARNED_RESPONSE_TIMEOUT.max(self.floor);
        learned.max(late).min(ceiling).max(self.floor)
    }

    /// A reply started `latency` after the end of its request.
    pub fn answered(&mut self, latency: Duration) {
        match self.smoothed {
            None => {
                self.smoothed = Some(latency);
                self.variation = latency / 2;
            }
            Some(smoothed) => {
                let deviation = smoothed.abs_diff(latency);
                self.variation = (self.variation * 3 + deviation) / 4;
                self.smoothed = Some((smoothed * 7 + latency) / 8);
            }
        }
    }

    /// Bytes came `latency` after the end of a request whose timeout had passed: wait half as long
    /// again for a while (and at least twice the timeout that was too short).
    pub fn answered_late(&mut self, now: Duration, latency: Duration) {
        let covering = (latency.saturating_mul(3) / 2).max(self.timeout(now).saturating_mul(2));
        let covering = covering.min(MAX_LEARNED_RESPONSE_TIMEOUT.max(self.floor));
        let raised = self
            .late
            .filter(|(_, until)| now < *until)
            .map_or(covering, |(timeout, _)| timeout.max(covering));
        // Not a sample of the smoothed estimate: one straggler must not dominate it for long.
        self.late = Some((raised, now.saturating_add(LATE_REPLY_MEMORY)));
    }
    /// Nothing at all came back for a request, through its timeout and the late window after it:
    /// the device is silent, not slow. What its answers taught above the floor (the smoothed
    /// time, a late reply's longer timeout) is forgotten: kept, it would make every retry of a
    /// dead device hold the bus for that time (twice, with the late window) instead of its
    /// normal one, at the others' expense. A device that comes back slow is taught again by its
    /// next late reply, which a retry's late window catches as long as it comes within twice
    /// the normal timeout (as for a device never heard from).
    pub fn silent(&mut self) {
        self.late = None;
        self.smoothed = None;
        self.variation = Duration::ZERO;
    }
}

/// Windows of a scan arbitration.
/// 3.5 characters of the extension's 12 bits: the least wait before the first arbitration
/// window, at any framing.
pub const ARBITRATION_WAIT_BITS: u64 = 42;

pub const ARBITRATION_WINDOWS_SCAN: u32 = 32;
/// The deprecated 0x60 scan: bits from the end of the request to its first arbitration window.
pub const LEGACY_SCAN_WAIT_BITS: u64 = 44;
/// The deprecated 0x60 scan: bits of one arbitration window.
pub const LEGACY_SCAN_WINDOW_BITS: u64 = 20;
/// Windows of an event arbitration.
pub const ARBITRATION_WINDOWS_EVENTS: u32 = 12;
/// The window by which any event contender has sent a filler byte.
pub const EVENT_FIRST_DOMINANT_WINDOW: u32 = 9;

impl fmt::Display for LineSettings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} {}{}{}",
            self.baud,
            self.data_bits,
            self.parity.letter(),
            self.stop_bits
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn micros(d: Duration) -> f64 {
        d.as_secs_f64() * 1e6
    }

    #[test]
    fn character_times() {
        let fast = LineSettings::new(115_200, Parity::None, 2);
        assert!((micros(fast.char_time()) - 95.486).abs() < 0.01);
        let slow = LineSettings::new(9600, Parity::None, 2);
        assert!((micros(slow.char_time()) - 1145.83).abs() < 0.01);
        assert_eq!(LineSettings::new(9600, Parity::None, 1).bits_per_char(), 10);
        assert_eq!(LineSettings::new(9600, Parity::Even, 1).bits_per_char(), 11);
        assert_eq!(LineSettings::new(9600, Parity::Odd, 2).bits_per_char(), 12);
        let seven_bits = LineSettings {
            data_bits: 7,
            ..LineSettings::new(9600, Parity::Even, 1)
        };
        assert_eq!(seven_bits.bits_per_char(), 10);
    }

    #[test]
    fn frame_silence() {
        assert_eq!(
            LineSettings::new(115_200, Parity::None, 2).frame_silence(),
            Duration::from_micros(1750)
        );
        let at_9600 = LineSettings::new(9600, Parity::None, 2).frame_silence();
        assert!((micros(at_9600) - 4010.4).abs() < 0.1);
    }

    #[test]
    fn a_scan_tries_the_eight_usual_rates_from_1200_to_115200() {
        assert_eq!(
            STANDARD_BAUD_RATES,
            [1200, 2400, 4800, 9600, 19200, 38400, 57600, 115_200]
        );
        assert!(STANDARD_BAUD_RATES.iter().all(|&b| is_usual_baud_rate(b)));
        assert!(!is_usual_baud_rate(9601) && !is_usual_baud_rate(96_000));
    }

    #[test]
    fn the_legacy_scan_waits_for_its_longer_windows() {
        // 9600: 44 + 32 × 20 bits = 684 bits = 71.25 ms (0x46: 47.7 ms); first byte by 64 bits.
        let slow = LineSettings::new(9600, Parity::None, 2);
        assert!((micros(slow.legacy_scan_reply_timeout()) - 71_250.0).abs() < 1.0);
        assert!((micros(slow.legacy_scan_start_first_byte_timeout()) - 6_666.67).abs() < 1.0);
        for baud in STANDARD_BAUD_RATES {
            let line = LineSettings::new(baud, Parity::None, 2);
            assert!(line.legacy_scan_reply_timeout() >= line.scan_reply_timeout());
            assert!(
                line.legacy_scan_start_first_byte_timeout() >= line.scan_start_first_byte_timeout()
            );
        }
    }

    #[test]
    fn arbitration_matches_the_article_at_115200() {
        let line = LineSettings::new(115_200, Parity::None, 2);
        // 12 bits + ceil(50 µs / 8.68 µs) = 6 bits → 18 bits = 156.25 µs.
        assert!((micros(line.arbitration_window()) - 156.25).abs() < 0.01);
        // 12 bits + 800 µs = 904.2 µs beats 3.5 chars (334 µs).
        assert!((micros(line.arbitration_wait()) - 904.17).abs() < 0.01);
        assert!((micros(line.scan_reply_timeout()) - (904.17 + 32.0 * 156.25)).abs() < 0.1);
        assert!((micros(line.event_reply_timeout()) - (904.17 + 12.0 * 156.25)).abs() < 0.1);
        assert!(line.event_first_byte_timeout() < line.event_reply_timeout());
        // The article: ceil(800 µs / 8.681 µs) = 93 bits = 807.3 µs.
        assert!((micros(line.device_arbitration_wait()) - 807.29).abs() < 0.01);
        for baud in STANDARD_BAUD_RATES {
            for (parity, stop_bits) in [(Parity::None, 1), (Parity::Even, 1), (Parity::Odd, 2)] {
                let line = LineSettings::new(baud, parity, stop_bits);
                assert!(line.device_arbitration_wait() <= line.arbitration_wait());
            }
        }
    }

    /// Below 52500 baud the 3.5 characters rule, of the extension's 12-bit characters (the
    /// article: "3.5 * (1 start + 8 data + 1 parity + 2 stop) = 42 bits") whatever the line's
    /// framing: 4.375 ms at 9600, where 3.5 characters of 8N2 would be 4.01 ms and of 8N1 3.65.
    #[test]
    fn arbitration_waits_42_bits_on_slow_lines_at_any_framing() {
        for (parity, stop_bits) in [(Parity::None, 1), (Parity::None, 2), (Parity::Even, 1)] {
            let line = LineSettings::new(9600, parity, stop_bits);
            assert!((micros(line.device_arbitration_wait()) - 4375.0).abs() < 0.01);
            assert!((micros(line.arbitration_wait()) - 4375.0).abs() < 0.01);
            assert!(
                (micros(line.event_reply_timeout()) - (4375.0 + 12.0 * 13.0 * 104.1667)).abs()
                    < 0.1
            );
        }
    }

    #[test]
    fn slow_lines_use_thirteen_bit_windows() {
        let line = LineSettings::new(9600, Parity::None, 2);
        // 50 µs is under one bit (104 µs): 12 + 1 = 13 bits.
        assert_eq!(line.arbitration_window(), line.bits_time(13));
        let line = LineSettings::new(1200, Parity::Even, 1);
        assert_eq!(line.arbitration_window(), line.bits_time(13));
        // 42 bits at 1200 = 35 ms, more than 12 bits + 800 µs.
        assert!(line.arbitration_wait() > Duration::from_millis(30));
    }

    #[test]
    fn event_poll_interval_by_baud() {
        let at = |baud| LineSettings::new(baud, Parity::None, 2).event_poll_interval();
        assert_eq!(at(230_400), Duration::from_millis(50));
        assert_eq!(at(115_200), Duration::from_millis(50));
        assert_eq!(at(57_600), Duration::from_millis(100));
        assert_eq!(at(38_400), Duration::from_millis(100));
        assert_eq!(at(19_200), Duration::from_millis(200));
        assert_eq!(at(9600), Duration::from_millis(200));
    }

    #[test]
    fn published_event_round_figure() {
        // 42 characters (request, filler, 2-byte event reply...) = 4.01 ms at 115200 8N2.
        let line = LineSettings::new(115_200, Parity::None, 2);
        assert!((line.wire_time(42).as_secs_f64() * 1e3 - 4.01).abs() < 0.01);
        let slow = LineSettings::new(9600, Parity::None, 2);
        assert!((slow.wire_time(42).as_secs_f64() * 1e3 - 48.1).abs() < 0.1);
        // A 100-byte reply at 115200 8N2 takes 9.55 ms.
        assert!((line.wire_time(100).as_secs_f64() * 1e3 - 9.549).abs() < 0.01);
    }

    #[test]
    fn wiren_board_response_timeout_floor() {
        // A WB template's 1 ms at 9600 8N2: 1 + 24 + 1.146 ms.
        let slow = LineSettings::new(9600, Parity::None, 2);
        let floor = slow.response_timeout_floor(Duration::from_millis(1));
        assert!((micros(floor) - 26_145.8).abs() < 0.1, "{floor:?}");
        let fast = LineSettings::new(115_200, Parity::None, 2);
        let floor = fast.response_timeout_floor(DEFAULT_RESPONSE_TIMEOUT);
        assert!((micros(floor) - 524_095.5).abs() < 0.1, "{floor:?}");
        // At 1200 8N2 one character is 9.2 ms.
        let slowest = LineSettings::new(1200, Parity::None, 2);
        let floor = slowest.response_timeout_floor(Duration::from_millis(1));
        assert!((micros(floor) - 34_166.7).abs() < 0.1, "{floor:?}");
    }

    #[test]
    fn response_timer_never_goes_below_its_floor() {
        let floor = Duration::from_millis(26);
        let mut timer = ResponseTimer::new(floor);
        assert_eq!(timer.timeout(Duration::ZERO), floor);
        for _ in 0..50 {
            timer.answered(Duration::from_millis(1));
        }
        assert_eq!(timer.timeout(Duration::ZERO), floor);
    }

    #[test]
    fn a_slow_device_gets_a_timeout_above_its_answers() {
        let mut timer = ResponseTimer::new(Duration::from_millis(26));
        for latency in [40, 45, 38, 42, 44, 39, 41, 43] {
            timer.answered(Duration::from_millis(latency));
        }
        let timeout = timer.timeout(Duration::ZERO);
        assert!(timeout > Duration::from_millis(60), "{timeout:?}");
        assert!(timeout < Duration::from_millis(200), "{timeout:?}");
    }

    #[test]
    fn a_late_reply_raises_the_timeout_for_a_while() {
        let floor = Duration::from_millis(524);
        let mut timer = ResponseTimer::new(floor);
        let now = Duration::from_secs(10);
        timer.answered_late(now, Duration::from_millis(600));
        let raised = timer.timeout(now);
        assert!(raised >= Duration::from_millis(900), "{raised:?}");
        assert!(raised <= MAX_LEARNED_RESPONSE_TIMEOUT);
        // Still raised a minute later, back to what the answers justify after the memory ends.
        assert_eq!(timer.timeout(now + Duration::from_secs(60)), raised);
        let later = timer.timeout(now + LATE_REPLY_MEMORY);
        assert!(later < raised, "{later:?}");
        assert!(later >= floor);
    }

    #[test]
    fn silence_through_the_raised_timeout_forgets_it() {
        let floor = Duration::from_millis(524);
        let mut timer = ResponseTimer::new(floor);
        // It answered slowly for a while, then a reply came later still.
        for _ in 0..8 {
            timer.answered(Duration::from_millis(700));
        }
        let now = Duration::from_secs(10);
        timer.answered_late(now, Duration::from_millis(1100));
        assert!(timer.timeout(now) >= Duration::from_millis(1000));
        timer.silent();
        assert_eq!(timer.timeout(now), floor);
        // Late again: raised again.
        timer.answered_late(now, Duration::from_millis(700));
        assert!(timer.timeout(now) >= Duration::from_millis(1000));
    }

    #[test]
    fn learned_timeouts_are_bounded() {
        let mut timer = ResponseTimer::new(Duration::from_millis(26));
        timer.answered_late(Duration::ZERO, Duration::from_secs(3600));
        assert_eq!(timer.timeout(Duration::ZERO), MAX_LEARNED_RESPONSE_TIMEOUT);
        // A configured floor above the bound still wins.
        let mut patient = ResponseTimer::new(Duration::from_secs(5));
        patient.answered_late(Duration::ZERO, Duration::from_secs(3600));
        assert_eq!(patient.timeout(Duration::ZERO), Duration::from_secs(5));
    }

    #[test]
    fn zero_baud_does_not_divide_by_zero() {
        let line = LineSettings::new(0, Parity::None, 1);
        assert!(line.char_time() > Duration::ZERO);
        assert!(line.arbitration_window() > Duration::ZERO);
    }
}
