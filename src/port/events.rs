//! The state of a port's event polling: when the next 0x10 request is due, which packet it
//! confirms, and the `min_address` rotation that keeps a chatty device from starving the others.

use std::time::Duration;

use super::plan::PortSettings;
use crate::protocol::frame::{EVENT_PACKET_OVERHEAD, MAX_DEVICE_ADDRESS, MAX_EVENT_DATA_LEN};
use crate::protocol::EventPoll;

/// Event requests sent back to back after packets, before the interval applies again: enough to
/// drain a burst from several devices, not enough to starve classic reads.
const MAX_BURST: u32 = 8;

#[derive(Debug, Clone)]
pub(super) struct EventPoller {
    interval: Duration,
    next_at: Duration,
    min_address: u8,
    ack: Option<(u8, u8)>,
    max_data_len: u8,
    /// The next request asks with the protocol's largest budget: a packet said it had events
    /// and carried none (not even one fitted `max_data_len`).
    wide_next: bool,
    /// The request under way asks with the largest budget.
    wide_in_flight: bool,
    burst: u32,
    /// When the round of requests under way began (its first request): rounds start an
    /// interval apart, however long the bursts in them take.
    round_started: Option<Duration>,
    /// When the latest request began.
    last_started: Duration,
    /// Addresses that sent a packet since the bus last had nothing pending (bit per address).
    served: [u64; 4],
    /// The rotation past the last sender may be skipped: it came in answer to a request to the
    /// whole bus and had sent nothing before since the bus last had nothing pending.
    rotation_optional: bool,
    /// The latest confirmation sent, with the `min_address` of the request that carried it.
    confirmation_sent: Option<(u8, u8, u8)>,
    /// Devices confirmed in a request that includes them (bit per address): they sent a packet
    /// again under a flag confirmed in a request that left them out. fast-modbus.md does not say
    /// whether a device left out by `min_address` reads the confirmation; wb-mqtt-serial
    /// confirms in a request that starts at the sender, so a device may never have met the
    /// other case, and would otherwise send the same packet in every round.
    confirm_in_view: [u64; 4],
    /// The address whose event packets came garbled in the latest polls, and how many times
    /// in a row: two devices with one address win every arbitration together.
    collisions: Option<(u8, u32)>,
}

/// Event polls garbled in a row under one address's packet header before it is taken for two
/// devices sharing that address, and the polls go past it.
const SHARED_ADDRESS_COLLISIONS: u32 = 3;

impl EventPoller {
    pub(super) fn new(settings: &PortSettings) -> Self {
        Self {
            interval: settings.event_interval,
            next_at: Duration::ZERO,
            min_address: 0,
            ack: None,
            max_data_len: max_data_len(settings),
            wide_next: false,
            wide_in_flight: false,
            burst: 0,
            round_started: None,
            last_started: Duration::ZERO,
            served: [0; 4],
            rotation_optional: false,
            confirmation_sent: None,
            confirm_in_view: [0; 4],
            collisions: None,
        }
    }

    pub(super) fn next_at(&self) -> Duration {
        self.next_at
    }

    pub(super) fn request(&self) -> EventPoll {
        let (ack_address, ack_flag) = self.ack.unwrap_or((0, 0));
        EventPoll {
            min_address: self.min_address,
            max_data_len: if self.wide_next {
                WIDE_DATA_LEN
            } else {
                self.max_data_len
            },
            ack_address,
            ack_flag,
        }
    }

    pub(super) fn started(&mut self, now: Duration) {
        if let Some((address, flag)) = self.ack {
            self.confirmation_sent = Some((address, flag, self.min_address));
        }
        self.wide_in_flight = std::mem::take(&mut self.wide_next);
        self.round_started.get_or_insert(now);
        self.last_started = now;
        self.next_at = now + self.interval;
    }

    /// The round is over: the next one starts an interval after this one began, so that a
    /// burst does not push every later round back by its own length (32 devices at 115200
    /// with 50 changes/s: rounds 70 ms apart instead of 50, event p99 67 ms on virtual time).
    /// A round that took more than half the interval leaves the bus to other requests for at
    /// least half an interval after its last request began.
    fn end_round(&mut self) {
        let started = self.round_started.take().unwrap_or(self.last_started);
        self.next_at = (started + self.interval).max(self.last_started + self.interval / 2);
    }

    /// A device sent a packet: confirm it next time, let the devices above it speak first, and
    /// ask again at once (more may be waiting), up to [`MAX_BURST`] requests in a row; the
    /// request after that waits for the next slot and starts a new burst.
    ///
    /// `highest_listener` is the highest address with events enabled: after a packet from it
    /// the rotation starts again from the bottom of the bus, since a request above every device
    /// would be answered by nobody and cost a whole first-byte timeout.
    pub(super) fn packet_received(
        &mut self,
        now: Duration,
        address: u8,
        flag: u8,
        highest_listener: u8,
    ) {
        self.confirm_and_rotate(address, flag, highest_listener);
        if self.burst < MAX_BURST {
            self.burst += 1;
            self.next_at = now;
        } else {
            // The burst is over; the next slot starts a new one. Without this, a bus that never
            // runs out of events (no "no events" reply to end the burst) would get one packet
            // per interval for good, and events would queue up in the devices.
            self.burst = 0;
            self.end_round();
        }
    }

    /// A packet with events of which none fitted the request's `max_data_len` ("if not even one
    /// fits, it sends the count with no payload", fast-modbus.md §6): an event wider than the
    /// port's budget would never come. The packet is confirmed (the device cleared nothing, it
    /// sent nothing), and the next request, at once, asks with the protocol's largest budget
    /// without rotating past the sender, so that it takes part. Only once in a row: a packet
    /// that had the large budget already and still carried nothing is a packet like any other
    /// (confirmed and rotated past), so a device that always answers so cannot hold the bus.
    /// False when that was the case.
    pub(super) fn nothing_fitted(
        &mut self,
        now: Duration,
        address: u8,
        flag: u8,
        highest_listener: u8,
    ) -> bool {
        if self.wide_in_flight {
            self.packet_received(now, address, flag, highest_listener);
            return false;
        }
        self.ack = Some((address, flag));
        self.rotation_optional = false;
        self.wide_next = true;
        self.min_address = self.min_address.min(address);
        self.next_at = now;
        true
    }

    /// A packet that needs no quick follow-up (only the power-on "I rebooted" of a device that
    /// is still to be set up, which its setup will answer): confirmed and rotated past as
    /// [`Self::packet_received`] does, but the next request waits for its slot. At start-up
    /// every device has that event pending; asking again at once for each of them cost a poll
    /// per device between the event setups (30 devices at 115200: 140 ms).
    pub(super) fn packet_received_at_leisure(
        &mut self,
        address: u8,
        flag: u8,
        highest_listener: u8,
    ) {
        self.confirm_and_rotate(address, flag, highest_listener);
        self.end_round();
    }

    /// The next request confirms the packet and lets the devices above its sender speak first.
    fn confirm_and_rotate(&mut self, address: u8, flag: u8, highest_listener: u8) {
        self.ack = Some((address, flag));
        if self
            .collisions
            .is_some_and(|(collided, _)| collided == address)
        {
            // Heard alone: no longer two devices there (or it was noise).
            self.collisions = None;
        }
        let (word, bit) = (usize::from(address / 64), 1u64 << (address % 64));
        if let Some((confirmed, confirmed_flag, left_out_below)) = self.confirmation_sent {
            if confirmed == address && confirmed_flag == flag && left_out_below > address {
                if let Some(in_view) = self.confirm_in_view.get_mut(word) {
                    *in_view |= bit;
                }
            }
        }
        let in_view = self.confirm_in_view.get(word).is_some_and(|w| w & bit != 0);
        let sent_before = self.served.get(word).is_some_and(|w| w & bit != 0);
        if let Some(served) = self.served.get_mut(word) {
            *served |= bit;
        }
        self.rotation_optional = !sent_before && self.min_address == 0;
        // A device confirmed in view is so only for its first packet of a sweep: a second one
        // rotates past it as any other, so that it cannot keep the bus from the devices below
        // it (a misread, after a confirmation lost to noise, costs no more than that).
        self.min_address = if address >= highest_listener.min(MAX_DEVICE_ADDRESS) {
            0
        } else if in_view && !sent_before {
            address
        } else {
            address + 1
        };
    }

    /// Whether the next request may ask the whole bus instead of rotating past the last sender
    /// (see [`Self::skip_rotation`]).
    pub(super) fn rotation_optional(&self) -> bool {
        self.rotation_optional
    }

    /// The next request asks the whole bus, not only the devices above the last sender: for a
    /// bus with nothing else to send. The rotation is there against a device that keeps winning
    /// the arbitration, and one that sends a second packet before the bus runs dry still gets
    /// it. Otherwise it only costs: on an idle bus every poll goes at once anyway, and a
    /// device below the sender with a change had to wait for the empty poll above it and the
    /// poll after that (8 devices at 115200, 20 changes/s: 6 of the 22 changes published more
    /// than 10 ms late on virtual time). A busy bus keeps the rotation: its sweep upwards
    /// serves the devices that waited before those whose changes came during the round.
    pub(super) fn skip_rotation(&mut self) {
        if self.rotation_optional {
            self.min_address = 0;
        }
        self.rotation_optional = false;
    }

    /// "No events" or silence. If part of the address range was excluded, ask the whole bus again
    /// at once; otherwise wait for the next slot.
    pub(super) fn nothing_pending(&mut self, started: Duration) {
        self.ack = None;
        self.burst = 0;
        self.served = [0; 4];
        self.rotation_optional = false;
        if self.min_address != 0 {
            self.min_address = 0;
            self.next_at = started;
        } else {
            self.end_round();
        }
    }

    /// An unreadable reply (noise, collision): confirm nothing, so the device sends its packet
    /// again under the same flag, in the next round. `packet_from`: the address whose packet
    /// header began it. The same address [`SHARED_ADDRESS_COLLISIONS`] times in a row is two
    /// devices with one address: they win every arbitration together and collide, and every
    /// device above them went unheard for good (a site tools audit: a relay's input stale for
    /// 75 s, with no word in the log). The next request then starts past that address (when a
    /// device with events is above it, `highest_listener`), so that the others are heard in
    /// every interval; once nothing more is pending there, the whole bus is asked again at once.
    /// Returns the address when it has just been taken for a shared one.
    pub(super) fn garbled(
        &mut self,
        _now: Duration,
        packet_from: Option<u8>,
        highest_listener: u8,
    ) -> Option<u8> {
        self.ack = None;
        self.rotation_optional = false;
        self.burst = 0;
        self.end_round();
        let Some(address) = packet_from else {
            self.collisions = None;
            return None;
        };
        let count = match self.collisions {
            Some((last, count)) if last == address => count.saturating_add(1),
            _ => 1,
        };
        self.collisions = Some((address, count));
        if count < SHARED_ADDRESS_COLLISIONS {
            return None;
        }
        if address < highest_listener.min(MAX_DEVICE_ADDRESS) {
            self.min_address = address + 1;
        }
        (count == SHARED_ADDRESS_COLLISIONS).then_some(address)
    }
}

/// The budget of a request after a packet in which nothing fitted: all a frame holds.
pub(super) const WIDE_DATA_LEN: u8 = MAX_EVENT_DATA_LEN as u8;

/// The most event data a reply may carry: what the line moves in one interval, less the frame
/// overhead, within what one frame can hold.
fn max_data_len(settings: &PortSettings) -> u8 {
    let char_nanos = settings.line.char_time().as_nanos().max(1);
    let chars = settings.event_interval.as_nanos() / char_nanos;
    let data = usize::try_from(chars)
        .unwrap_or(usize::MAX)
        .saturating_sub(EVENT_PACKET_OVERHEAD)
        .clamp(6, MAX_EVENT_DATA_LEN);
    u8::try_from(data).unwrap_or(u8::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{LineSettings, Parity};

    fn poller(baud: u32) -> EventPoller {
        EventPoller::new(&PortSettings::for_line(LineSettings::new(
            baud,
            Parity::None,
            2,
        )))
    }

    #[test]
    fn data_budget_by_baud() {
        assert_eq!(poller(115_200).request().max_data_len, 248);
        // 200 ms at 9600 8N2 = 174 characters, less 8.
        assert_eq!(poller(9600).request().max_data_len, 166);
        assert_eq!(poller(1200).request().max_data_len, 13);
    }

    #[test]
    fn ack_and_rotation() {
        let mut events = poller(115_200);
        let ms = Duration::from_millis;
        events.started(ms(0));
        assert_eq!(events.next_at(), ms(50));
        events.packet_received(ms(3), 20, 1, 30);
        assert_eq!(
            events.request(),
            EventPoll {
                min_address: 21,
                max_data_len: 248,
                ack_address: 20,
                ack_flag: 1
            }
        );
        assert_eq!(events.next_at(), ms(3), "asks again at once");
        events.started(ms(3));
        events.nothing_pending(ms(3));
        assert_eq!(events.request().min_address, 0, "the whole bus again");
        assert_eq!(events.request().ack_address, 0);
        assert_eq!(events.next_at(), ms(3));
        events.started(ms(6));
        events.nothing_pending(ms(6));
        assert_eq!(
            events.next_at(),
            ms(50),
            "then the next round, an interval after this one began"
        );
    }

    /// A device that sends its packet again under the flag just confirmed in a request that
    /// left it out (it reads no request that excludes it) is confirmed in requests that include
    /// it from then on; the others are still rotated past.
    #[test]
    fn a_device_that_missed_a_confirmation_it_was_left_out_of_gets_the_next_in_view() {
        let ms = Duration::from_millis;
        let mut events = poller(9600);
        events.started(ms(0));
        events.packet_received(ms(20), 20, 1, 30);
        assert_eq!(
            (events.request().min_address, events.request().ack_address),
            (21, 20)
        );
        events.started(ms(20));
        events.nothing_pending(ms(20));
        events.started(ms(30));
        events.packet_received(ms(50), 20, 1, 30);
        assert_eq!(
            events.request(),
            EventPoll {
                min_address: 20,
                max_data_len: 166,
                ack_address: 20,
                ack_flag: 1
            },
            "confirmed where it listens"
        );
        // Its second packet of the sweep is rotated past, as any device's.
        events.started(ms(50));
        events.packet_received(ms(70), 20, 0, 30);
        assert_eq!(events.request().min_address, 21);
        events.started(ms(70));
        events.packet_received(ms(90), 25, 1, 30);
        assert_eq!(events.request().min_address, 26, "the others rotated past");
        // The next sweep: its first packet is confirmed in view again.
        events.started(ms(90));
        events.nothing_pending(ms(90));
        events.started(ms(100));
        events.packet_received(ms(120), 20, 1, 30);
        assert_eq!(events.request().min_address, 20, "and so from then on");
        // A packet under a new flag after a confirmation is no such sign.
        let mut events = poller(9600);
        events.started(ms(0));
        events.packet_received(ms(20), 20, 1, 30);
        events.started(ms(20));
        events.packet_received(ms(40), 20, 0, 30);
        assert_eq!(events.request().min_address, 21);
    }

    /// A device confirmed in view that has a packet for every request does not keep the bus
    /// from the devices below it: after its second packet of a sweep the rotation goes on.
    #[test]
    fn a_device_confirmed_in_view_does_not_starve_the_devices_below_it() {
        let ms = Duration::from_millis;
        let mut events = poller(115_200);
        // Device 10 missed a confirmation it was left out of: confirmed in view from then on.
        events.started(ms(0));
        events.packet_received(ms(1), 10, 1, 30);
        events.started(ms(1));
        events.nothing_pending(ms(1));
        events.started(ms(2));
        events.packet_received(ms(3), 10, 1, 30);
        assert_eq!(events.request().min_address, 10);
        // From now on device 10 answers every request that includes it with a new packet.
        let mut asked_below = 0;
        let mut flag = 0;
        for n in 0..200u64 {
            let now = ms(4 + n);
            let request = events.request();
            events.started(now);
            if request.min_address <= 5 {
                asked_below += 1;
            }
            if request.min_address <= 10 {
                flag ^= 1;
                events.packet_received(now, 10, flag, 30);
            } else {
                events.nothing_pending(now);
            }
        }
        assert!(asked_below >= 50, "device 5 asked {asked_below} times");
    }

    #[test]
    fn rounds_keep_their_rhythm_and_a_long_one_leaves_half_an_interval() {
        let ms = Duration::from_millis;
        let mut events = poller(115_200);
        // Three packets and "no events": 20 ms of polls, the next round still at 50 ms.
        for n in 0..3u64 {
            events.started(ms(5 * n));
            events.packet_received(ms(5 * n + 4), 3 + n as u8, 0, 30);
        }
        events.started(ms(15));
        events.nothing_pending(ms(15));
        assert_eq!(events.request().min_address, 0);
        assert_eq!(events.next_at(), ms(15), "the bus below the rotation first");
        events.started(ms(15));
        events.nothing_pending(ms(15));
        assert_eq!(events.next_at(), ms(50));
        // At 9600 a poll takes ~48 ms: a burst of 8 outlasts the 200 ms interval; the bus is
        // left to other requests for 100 ms after the last poll began.
        let mut events = poller(9600);
        for n in 0..MAX_BURST {
            events.started(ms(48 * u64::from(n)));
            events.packet_received(ms(48 * u64::from(n) + 40), 5, 0, 30);
        }
        events.started(ms(384));
        events.packet_received(ms(424), 5, 1, 30);
        assert_eq!(events.next_at(), ms(484));
    }

    #[test]
    fn bursts_are_bounded_and_each_slot_starts_a_new_one() {
        let mut events = poller(115_200);
        let mut now = Duration::ZERO;
        // A bus that never runs out of events: every request brings a packet.
        for round in 0..3 {
            let round_start = now;
            for _ in 0..MAX_BURST {
                events.started(now);
                events.packet_received(now, 5, 0, 30);
                assert_eq!(events.next_at(), now, "round {round}: asks again at once");
                now += Duration::from_millis(2);
            }
            events.started(now);
            events.packet_received(now, 5, 1, 30);
            assert_eq!(
                events.next_at(),
                round_start + Duration::from_millis(50),
                "round {round}: the burst ends, the next round an interval after it began"
            );
            now = events.next_at();
        }
    }

    #[test]
    fn a_packet_at_leisure_is_confirmed_at_the_next_slot() {
        let mut events = poller(115_200);
        let ms = Duration::from_millis;
        events.started(ms(10));
        events.packet_received_at_leisure(7, 1, 30);
        assert_eq!(events.next_at(), ms(60), "no poll before the slot");
        assert_eq!(
            (events.request().ack_address, events.request().ack_flag),
            (7, 1)
        );
        assert_eq!(events.request().min_address, 8);
    }

    #[test]
    fn the_rotation_may_be_skipped_after_a_first_packet_only() {
        let mut events = poller(115_200);
        let ms = Duration::from_millis;
        // A first packet, in answer to a request to the whole bus: optional.
        events.started(ms(0));
        events.packet_received(ms(4), 5, 0, 30);
        assert_eq!(events.request().min_address, 6);
        assert!(events.rotation_optional());
        events.skip_rotation();
        assert_eq!(events.request().min_address, 0, "the whole bus");
        assert_eq!(events.request().ack_address, 5, "still confirms the packet");
        assert!(!events.rotation_optional());
        // The same device again before the bus ran dry: rotated past.
        events.started(ms(4));
        events.packet_received(ms(8), 5, 1, 30);
        assert!(!events.rotation_optional());
        events.skip_rotation();
        assert_eq!(events.request().min_address, 6);
        // A first packet in answer to a rotated request: the sweep goes on.
        events.started(ms(8));
        events.packet_received(ms(12), 9, 0, 30);
        assert!(!events.rotation_optional());
        assert_eq!(events.request().min_address, 10);
        // "No events" forgets who sent: 5 is a first sender again.
        events.started(ms(12));
        events.nothing_pending(ms(12));
        events.started(ms(12));
        events.nothing_pending(ms(12));
        events.started(ms(50));
        events.packet_received(ms(54), 5, 0, 30);
        assert!(events.rotation_optional());
        // Noise ends the chance: the next slot asks as the rotation says.
        events.started(ms(54));
        events.garbled(ms(58), None, 247);
        assert!(!events.rotation_optional());
    }

    #[test]
    fn after_the_highest_listener_the_rotation_starts_from_the_bottom() {
        let mut events = poller(115_200);
        events.started(Duration::ZERO);
        events.packet_received(Duration::ZERO, 29, 0, 32);
        assert_eq!(events.request().min_address, 30);
        events.packet_received(Duration::ZERO, 32, 1, 32);
        assert_eq!(events.request().min_address, 0, "nobody above 32 listens");
        assert_eq!(
            events.request().ack_address,
            32,
            "still confirms the packet"
        );
        // A device above the highest listener (not configured, or its events not enabled yet)
        events.packet_received(Duration::ZERO, 40, 0, 32);
        assert_eq!(events.request().min_address, 0);
        events.packet_received(Duration::ZERO, MAX_DEVICE_ADDRESS, 0, 0);
        assert_eq!(events.request().min_address, 0);
    }

    /// Polls garbled under one address's packet header: the third in a row takes it for two
    /// devices sharing the address (said once) and the next round starts past it; noise with
    /// no header, or another address, starts the count again; the address heard alone ends it.
    #[test]
    fn polls_garbled_under_one_address_go_past_it() {
        let ms = Duration::from_millis;
        let mut events = poller(115_200);
        assert_eq!(events.garbled(ms(0), Some(10), 30), None);
        assert_eq!(events.garbled(ms(50), None, 30), None);
        assert_eq!(events.garbled(ms(100), Some(10), 30), None);
        assert_eq!(events.garbled(ms(150), Some(10), 30), None);
        assert_eq!(events.request().min_address, 0, "two in a row only");
        assert_eq!(events.garbled(ms(200), Some(10), 30), Some(10));
        assert_eq!(events.request().min_address, 11);
        events.nothing_pending(ms(250));
        assert_eq!(events.request().min_address, 0, "the whole bus again");
        assert_eq!(events.garbled(ms(300), Some(10), 30), None, "said once");
        assert_eq!(events.request().min_address, 11, "and past it again");
        events.nothing_pending(ms(350));
        events.packet_received(ms(400), 10, 1, 30);
        events.nothing_pending(ms(450));
        assert_eq!(events.garbled(ms(500), Some(10), 30), None);
        assert_eq!(
            events.request().min_address,
            0,
            "heard alone: counted afresh"
        );
        // The highest device with events, or 247: said, but nobody above to make room for (a
        // request past it would only cost a timeout).
        for (address, highest) in [(30, 30), (247, 247)] {
            let mut events = poller(115_200);
            for at in 0..2 {
                assert_eq!(events.garbled(ms(at * 50), Some(address), highest), None);
            }
            assert_eq!(
                events.garbled(ms(100), Some(address), highest),
                Some(address)
            );
            assert_eq!(events.request().min_address, 0, "{address}");
        }
    }
}
