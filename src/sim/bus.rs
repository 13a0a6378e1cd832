//! The virtual RS-485 bus: every device hears every request sent with its port settings, and the
//! bus works out what goes back on the wire and when: classic replies after the device's
//! turnaround, arbitration filler bytes at the start of each window where a contender sends a 0
//! bit, the winner's frame after the last window, and wired-AND garbage when several devices
//! answer at once. Pure and deterministic: time comes in with each request, faults come from a
//! seeded generator.

use std::time::Duration;

use crate::protocol::fast::BROADCAST_ADDRESS;
use crate::protocol::frame::{CLASSIC_BROADCAST, MAX_DEVICE_ADDRESS};
use crate::protocol::parser::ARBITRATION_FILLER;
use crate::protocol::{
    arbitrate, ArbitrationWord, EventPoll, EventUrgency, ExceptionCode, FastReply, FastRequest,
    LineSettings, ParsedRequest, RegisterType, RejectedRequest, Reply, ReplyBody, RequestBody,
    RequestPdu, ResponsePdu,
};

use super::device::{ValueChange, VirtualDevice};
use super::faults::{busy_exception, flip_bit, garbage, glitch, truncate, FaultAction, XorShift64};
use super::line::{MasterLine, ReceivedRequest};
use super::other_master::OtherMaster;
pub use super::transmission::Transmission;
use super::transmission::{collide, Burst, TimedFrame};
use super::wire::Wire;

/// Who changed a register.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChangeOrigin {
    /// A write request from the master.
    Master,
    /// The control interface or a script (the physical world).
    Control,
}

/// One register change, for the change log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RegisterChange {
    pub at: Duration,
    pub device: String,
    pub address: u8,
    pub serial: u32,
    pub change: ValueChange,
    pub origin: ChangeOrigin,
}

/// A reply a device is about to send.
struct PlannedReply {
    device: usize,
    frame: Vec<u8>,
    start: Duration,
    line: LineSettings,
    /// The reply of an arbitration winner: it starts right after the arbitration or not at all.
    after_arbitration: bool,
}

pub struct Bus {
    devices: Vec<VirtualDevice>,
    rng: XorShift64,
    changes: Vec<RegisterChange>,
    stats: BusStats,
    link: LinkState,
    /// When the outside world (the control interface, a script) last acted on or looked at
    /// the bus: see [`Bus::outside_acts`].
    outside_acted_at: Duration,
    /// A second master sending on this bus (the `other_master` control command).
    other_master: Option<OtherMaster>,
}

/// Whether the master's links (the pty, TCP connections) are there: the `link_down`,
/// `link_up` and `link_drop` control commands take them away, as an unplugged USB adapter or a
/// gateway dropping its connections does. The transports act on it (src/sim/pty.rs, tcp.rs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LinkState {
    /// False while the links are away: no pty, TCP connections closed as soon as accepted.
    pub up: bool,
    /// Bumped each time the links are cut: a link opened under an older generation ends.
    pub generation: u64,
}

/// What the bus has served since it started (the `stats` control command; benchmarks count
/// transactions with it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BusStats {
    /// Requests heard (valid or not), whoever they were for.
    pub requests: u64,
    /// Classic Modbus requests (functions 1..16).
    pub classic_requests: u64,
    /// Registers (or coils, inputs) that classic read requests asked for.
    pub registers_read: u64,
    /// Fast Modbus requests (0x46), broadcast or addressed.
    pub fast_requests: u64,
    /// Requests that got bytes back (a reply, arbitration fillers).
    pub answered: u64,
    /// Bytes sent back, arbitration fillers included.
    pub reply_bytes: u64,
    /// Event polls (0x10) heard by at least one Fast Modbus device.
    pub event_polls: u64,
    /// Event polls where two devices or more had events to send and arbitrated for the bus.
    pub contended_event_polls: u64,
    /// The most devices with events that arbitrated in one poll.
    pub max_event_contenders: u64,
    /// Requests a second master sent ([`OtherMaster`]; counted in `requests` too when they
    /// reached the devices intact).
    pub other_master_requests: u64,
    /// Those the devices answered.
    pub other_master_answered: u64,
}

impl Bus {
    pub fn new(devices: Vec<VirtualDevice>, seed: u64) -> Self {
        Self {
            devices,
            rng: XorShift64::new(seed),
            changes: Vec::new(),
            stats: BusStats::default(),
            link: LinkState {
                up: true,
                generation: 0,
            },
            outside_acted_at: Duration::ZERO,
            other_master: None,
        }
    }

    /// A second master on the bus from now on, or none.
    pub fn set_other_master(&mut self, other: Option<OtherMaster>) {
        self.other_master = other;
    }

    /// When the second master sends next, and whether it waits for silence first.
    pub fn other_master_due(&self) -> Option<(Duration, bool)> {
        self.other_master
            .as_ref()
            .map(|other| (other.due(), other.listens))
    }

    /// The second master's request if it is due at `now` (counted as sent).
    pub fn other_master_turn(&mut self, now: Duration) -> Option<Vec<u8>> {
        let frame = self.other_master.as_mut()?.turn(now)?.to_vec();
        self.stats.other_master_requests += 1;
        Some(frame)
    }

    pub fn link(&self) -> LinkState {
        self.link
    }

    /// Cuts every link to the master; they stay away until [`Bus::restore_links`] when
    /// `stay_down`, else they may come back at once (a dropped connection).
    pub fn cut_links(&mut self, stay_down: bool) {
        self.link.generation += 1;
        self.link.up = !stay_down;
    }

    pub fn restore_links(&mut self) {
        self.link.up = true;
    }

    pub fn stats(&self) -> BusStats {
        self.stats
    }

    pub fn devices(&self) -> &[VirtualDevice] {
        &self.devices
    }

    pub fn device_mut(&mut self, index: usize) -> Option<&mut VirtualDevice> {
        self.devices.get_mut(index)
    }

    /// Register changes since the last call.
    pub fn take_changes(&mut self) -> Vec<RegisterChange> {
        std::mem::take(&mut self.changes)
    }

    /// The outside world (a control command, a script step) acts on the bus at `now`. A request
    /// is stamped when its bytes were read, but handled once the reading thread has the bus:
    /// a command in between came first in the devices' history, so what the request changes
    /// is stamped after the command. Otherwise a write read before a `set` and
    /// handled after it would be logged before the `set` while its value is the one that stayed.
    pub fn outside_acts(&mut self, now: Duration) {
        self.outside_acted_at = self.outside_acted_at.max(now);
    }

    /// Writes registers of device `index` from outside the bus (control interface, script).
    pub fn write_register(
        &mut self,
        index: usize,
        register_type: RegisterType,
        start: u16,
        values: &[u16],
        at: Duration,
    ) -> Result<(), ExceptionCode> {
        let device = self
            .devices
            .get_mut(index)
            .ok_or(ExceptionCode::GATEWAY_TARGET_FAILED)?;
        let changes = device.write(register_type, start, values, false)?;
        self.record(index, changes, at, ChangeOrigin::Control);
        Ok(())
    }

    fn record(
        &mut self,
        index: usize,
        changes: Vec<ValueChange>,
        at: Duration,
        origin: ChangeOrigin,
    ) {
        let Some(device) = self.devices.get(index) else {
            return;
        };
        // Strictly after: the log is sorted by time, and its lines of two threads may swap.
        let at = match origin {
            ChangeOrigin::Master if at <= self.outside_acted_at => self
                .outside_acted_at
                .saturating_add(Duration::from_nanos(1)),
            ChangeOrigin::Master => at,
            ChangeOrigin::Control => at,
        };
        for change in changes {
            self.changes.push(RegisterChange {
                at,
                device: device.name.clone(),
                address: device.address(),
                serial: device.serial,
                change,
                origin,
            });
        }
    }

    /// Convenience for tests and fuzzing: `frame` written at once at `at` on an idle wire,
    /// followed by silence. Bytes that are not exactly one frame get no answer (see [`Wire`]).
    pub fn exchange(&mut self, frame: &[u8], line: MasterLine, at: Duration) -> Transmission {
        let mut transmission = Transmission::default();
        let mut wire = Wire::new();
        let mut respond = |request: &ReceivedRequest| {
            let answer = self.handle(request);
            transmission.append(answer.clone());
            answer
        };
        wire.master_writes(frame, at, line, &mut respond);
        wire.on_silence(Duration::MAX, &mut respond);
        transmission
    }

    /// What goes back on the wire in answer to one request.
    pub fn handle(&mut self, received: &ReceivedRequest) -> Transmission {
        // Only the addressed devices can answer a classic or addressed request: skip reading
        // every device's port settings for it (most of the work per request on a large bus).
        let addressed = match &received.request {
            ParsedRequest::Valid(request) => request.address,
            ParsedRequest::Rejected(rejected) => rejected.address,
        };
        let only = (1..=MAX_DEVICE_ADDRESS)
            .contains(&addressed)
            .then_some(addressed);
        let listeners: Vec<usize> = (0..self.devices.len())
            .filter(|&i| {
                self.devices.get(i).is_some_and(|d| {
                    d.plugged
                        && only.is_none_or(|address| d.address() == address)
                        && received.line.matches(&d.line())
                })
            })
            .collect();
        let mut replies = Vec::new();
        let mut fillers = Vec::new();
        self.count_request(&received.request);
        match &received.request {
            ParsedRequest::Rejected(rejected) => {
                self.reject(rejected, &listeners, received, &mut replies);
            }
            ParsedRequest::Valid(request) => match &request.body {
                RequestBody::Classic(pdu) => {
                    self.classic(request.address, pdu, &listeners, received, &mut replies);
                }
                RequestBody::Fast(fast) if request.address == BROADCAST_ADDRESS => {
                    let fast_listeners: Vec<usize> = listeners
                        .iter()
                        .copied()
                        .filter(|&i| self.devices.get(i).is_some_and(|d| d.fast))
                        .collect();
                    self.fast_broadcast(
                        fast,
                        request.fast_function,
                        &fast_listeners,
                        received,
                        &mut replies,
                        &mut fillers,
                    );
                }
                RequestBody::Fast(fast) => {
                    self.fast_addressed(
                        request.address,
                        fast,
                        request.fast_function,
                        &listeners,
                        received,
                        &mut replies,
                    );
                }
            },
        }
        let transmission = self.finish(fillers, replies);
        let reply_bytes = transmission.bytes().len() as u64;
        if reply_bytes > 0 {
            self.stats.answered += 1;
            self.stats.reply_bytes += reply_bytes;
            if received.from_other_master {
                self.stats.other_master_answered += 1;
            }
        }
        transmission
    }

    fn count_request(&mut self, request: &ParsedRequest) {
        self.stats.requests += 1;
        let ParsedRequest::Valid(request) = request else {
            return;
        };
        match &request.body {
            RequestBody::Classic(pdu) => {
                self.stats.classic_requests += 1;
                if let RequestPdu::ReadCoils { count, .. }
                | RequestPdu::ReadDiscreteInputs { count, .. }
                | RequestPdu::ReadHoldingRegisters { count, .. }
                | RequestPdu::ReadInputRegisters { count, .. } = pdu
                {
                    self.stats.registers_read += u64::from(*count);
                }
            }
            RequestBody::Fast(_) => self.stats.fast_requests += 1,
        }
    }

    fn at_address(&self, listeners: &[usize], address: u8) -> Vec<usize> {
        listeners
            .iter()
            .copied()
            .filter(|&i| self.devices.get(i).is_some_and(|d| d.address() == address))
            .collect()
    }

    /// A reply after the device's turnaround, timed on its settings before the request ran. A
    /// device knows the request has ended only after a frame gap of silence: never sooner.
    fn plan(
        &self,
        index: usize,
        reply: &Reply,
        line: LineSettings,
        received: &ReceivedRequest,
    ) -> Option<PlannedReply> {
        let device = self.devices.get(index)?;
        let frame = match reply.encode() {
            Ok(frame) => frame,
            Err(err) => {
                tracing::warn!("sim: {}: reply does not encode: {err}", device.name);
                return None;
            }
        };
        Some(PlannedReply {
            device: index,
            frame,
            start: received.end_on_wire(&line) + device.turnaround.max(line.frame_gap()),
            line,
            after_arbitration: false,
        })
    }

    fn reject(
        &mut self,
        rejected: &RejectedRequest,
        listeners: &[usize],
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
    ) {
        let targets: Vec<usize> = match (rejected.address, rejected.by_serial) {
            (BROADCAST_ADDRESS, Some((serial, _))) => listeners
                .iter()
                .copied()
                .filter(|&i| {
                    self.devices
                        .get(i)
                        .is_some_and(|d| d.fast && d.serial == serial)
                })
                .collect(),
            (address, _) if (1..=MAX_DEVICE_ADDRESS).contains(&address) => {
                self.at_address(listeners, address)
            }
            _ => Vec::new(),
        };
        for index in targets {
            let Some(device) = self.devices.get(index) else {
                continue;
            };
            let reply = if rejected.function == crate::protocol::fast::FUNCTION && !device.fast {
                illegal_function(rejected.address, rejected.function)
            } else {
                rejected.exception_reply()
            };
            replies.extend(self.plan(index, &reply, device.line(), received));
        }
    }

    fn classic(
        &mut self,
        address: u8,
        pdu: &RequestPdu,
        listeners: &[usize],
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
    ) {
        let targets = if address == CLASSIC_BROADCAST {
            listeners.to_vec()
        } else {
            self.at_address(listeners, address)
        };
        for index in targets {
            let Some(device) = self.devices.get_mut(index) else {
                continue;
            };
            let line = device.line();
            let (response, changes) = device.execute(pdu);
            let at = received.end_on_wire(&line);
            self.record(index, changes, at, ChangeOrigin::Master);
            if address != CLASSIC_BROADCAST {
                replies.extend(self.plan(
                    index,
                    &Reply::classic(address, response),
                    line,
                    received,
                ));
            }
        }
    }

    fn fast_addressed(
        &mut self,
        address: u8,
        request: &FastRequest,
        function: u8,
        listeners: &[usize],
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
    ) {
        if !(1..=MAX_DEVICE_ADDRESS).contains(&address) {
            return;
        }
        for index in self.at_address(listeners, address) {
            let Some(device) = self.devices.get_mut(index) else {
                continue;
            };
            let line = device.line();
            let reply = match request {
                FastRequest::ConfigureEvents { ranges } if device.fast => {
                    device.events_configured_at = Some(received.end_on_wire(&line));
                    fast_reply(
                        function,
                        address,
                        FastReply::EventsConfigured {
                            masks: device.configure_events(ranges),
                        },
                    )
                }
                _ => illegal_function(address, function),
            };
            replies.extend(self.plan(index, &reply, line, received));
        }
    }

    /// `function`: 0x46, or the deprecated 0x60, which the devices answer under the code they
    /// were asked with, and a scan under it with the legacy timing.
    fn fast_broadcast(
        &mut self,
        request: &FastRequest,
        function: u8,
        listeners: &[usize],
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
        fillers: &mut Vec<Burst>,
    ) {
        match request {
            FastRequest::ScanStart | FastRequest::ScanContinue => {
                if *request == FastRequest::ScanStart {
                    for &i in listeners {
                        if let Some(device) = self.devices.get_mut(i) {
                            device.set_scanned(false);
                        }
                    }
                }
                let contenders: Vec<(usize, ArbitrationWord)> = listeners
                    .iter()
                    .filter_map(|&i| {
                        let d = self.devices.get(i)?;
                        Some((i, ArbitrationWord::scan(d.serial, d.is_scanned())))
                    })
                    .collect();
                let timing = if function == crate::protocol::fast::LEGACY_FUNCTION {
                    ArbitrationTiming::LegacyScan
                } else {
                    ArbitrationTiming::Standard
                };
                self.arbitration_round(&contenders, timing, received, replies, fillers, |device| {
                    if device.is_scanned() {
                        fast_reply(function, BROADCAST_ADDRESS, FastReply::ScanEnd)
                    } else {
                        device.set_scanned(true);
                        fast_reply(
                            function,
                            BROADCAST_ADDRESS,
                            FastReply::ScanFound {
                                serial: device.serial,
                                modbus_address: device.address(),
                            },
                        )
                    }
                });
            }
            FastRequest::PollEvents(poll) => {
                self.event_round(poll, function, listeners, received, replies, fillers)
            }
            FastRequest::BySerial { serial, pdu } => {
                for &index in listeners {
                    let Some(device) = self.devices.get_mut(index).filter(|d| d.serial == *serial)
                    else {
                        continue;
                    };
                    let line = device.line();
                    let (response, changes) = device.execute(pdu);
                    self.record(
                        index,
                        changes,
                        received.end_on_wire(&line),
                        ChangeOrigin::Master,
                    );
                    let reply = fast_reply(
                        function,
                        BROADCAST_ADDRESS,
                        FastReply::BySerial {
                            serial: *serial,
                            pdu: response,
                        },
                    );
                    replies.extend(self.plan(index, &reply, line, received));
                }
            }
            // Event settings go to a device's own address, never to 0xFD.
            FastRequest::ConfigureEvents { .. } => {}
        }
    }

    fn event_round(
        &mut self,
        poll: &EventPoll,
        function: u8,
        listeners: &[usize],
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
        fillers: &mut Vec<Burst>,
    ) {
        for &i in listeners {
            if let Some(device) = self.devices.get_mut(i) {
                device.acknowledge_events(poll);
            }
        }
        let contenders: Vec<(usize, ArbitrationWord)> = listeners
            .iter()
            .filter_map(|&i| {
                let d = self.devices.get(i)?;
                let address = d.address();
                let takes_part =
                    (1..=MAX_DEVICE_ADDRESS).contains(&address) && address >= poll.min_address;
                takes_part.then(|| (i, ArbitrationWord::event(d.event_urgency(), address)))
            })
            .collect();
        let with_events = contenders
            .iter()
            .filter(|&&(i, _)| {
                self.devices
                    .get(i)
                    .is_some_and(|d| d.event_urgency() != EventUrgency::Nothing)
            })
            .count() as u64;
        if !contenders.is_empty() {
            self.stats.event_polls += 1;
        }
        if with_events >= 2 {
            self.stats.contended_event_polls += 1;
        }
        self.stats.max_event_contenders = self.stats.max_event_contenders.max(with_events);
        let max_data_len = poll.max_data_len;
        let timing = ArbitrationTiming::Standard;
        self.arbitration_round(&contenders, timing, received, replies, fillers, |device| {
            if device.event_urgency() == EventUrgency::Nothing {
                fast_reply(function, BROADCAST_ADDRESS, FastReply::NoEvents)
            } else {
                let address = device.address();
                fast_reply(
                    function,
                    address,
                    FastReply::Events(device.event_packet(max_data_len)),
                )
            }
        });
    }

    /// Runs one arbitration among `contenders`: filler bytes for the dominant windows, then the
    /// frame of the winner (of every winner when two words are equal, which collides).
    fn arbitration_round(
        &mut self,
        contenders: &[(usize, ArbitrationWord)],
        timing: ArbitrationTiming,
        received: &ReceivedRequest,
        replies: &mut Vec<PlannedReply>,
        fillers: &mut Vec<Burst>,
        mut winner_reply: impl FnMut(&mut VirtualDevice) -> Reply,
    ) {
        let words: Vec<ArbitrationWord> = contenders.iter().map(|&(_, word)| word).collect();
        let Some(outcome) = arbitrate(&words) else {
            return;
        };
        let Some(&winning_word) = words.get(outcome.winner) else {
            return;
        };
        let winners: Vec<usize> = contenders
            .iter()
            .filter(|&&(_, word)| word == winning_word)
            .map(|&(i, _)| i)
            .collect();
        let Some(line) = winners
            .first()
            .and_then(|&i| self.devices.get(i))
            .map(VirtualDevice::line)
        else {
            return;
        };
        let (wait, window) = match timing {
            ArbitrationTiming::Standard => {
                (line.device_arbitration_wait(), line.arbitration_window())
            }
            ArbitrationTiming::LegacyScan => (
                line.bits_time(crate::protocol::timing::LEGACY_SCAN_WAIT_BITS),
                line.bits_time(crate::protocol::timing::LEGACY_SCAN_WINDOW_BITS),
            ),
        };
        let first_window = received.end_on_wire(&line) + wait;
        for (index, &dominant) in outcome.dominant_windows.iter().enumerate() {
            if dominant {
                fillers.push(Burst {
                    start: first_window + window * u32::try_from(index).unwrap_or(u32::MAX),
                    char_time: line.char_time(),
                    bytes: vec![ARBITRATION_FILLER],
                });
            }
        }
        let frame_start = first_window + window * winning_word.windows;
        for index in winners {
            let Some(device) = self.devices.get_mut(index) else {
                continue;
            };
            let device_line = device.line();
            let reply = winner_reply(device);
            if let Some(mut planned) = self.plan(index, &reply, device_line, received) {
                planned.start = frame_start;
                planned.after_arbitration = true;
                replies.push(planned);
            }
        }
    }

    /// Applies faults, merges colliding replies, orders everything in time.
    fn finish(&mut self, fillers: Vec<Burst>, replies: Vec<PlannedReply>) -> Transmission {
        let mut sent = Vec::new();
        for mut reply in replies {
            let action = match self.devices.get_mut(reply.device) {
                Some(device) => {
                    let action = device.faults.draw(&mut self.rng);
                    if action != FaultAction::None {
                        device.faults.spend();
                    }
                    action
                }
                None => FaultAction::None,
            };
            match action {
                FaultAction::None => {}
                FaultAction::Drop => continue,
                FaultAction::CorruptCrc => {
                    if let Some(last) = reply.frame.last_mut() {
                        *last ^= 0xFF;
                    }
                }
                // A device that won the arbitration sends at once: the windows are timed, and a
                // late start would lose the bus to the next round. Only addressed replies can
                // come late.
                FaultAction::Delay(_) if reply.after_arbitration => {}
                FaultAction::Delay(delay) => reply.start += delay,
                FaultAction::Exception => {
                    if let Some(exception) = busy_exception(&reply.frame) {
                        reply.frame = exception;
                    }
                }
                FaultAction::Garbage(seed) => reply.frame = garbage(seed, reply.frame.len()),
                FaultAction::FlipBit(seed) => flip_bit(&mut reply.frame, seed),
                FaultAction::Truncate(seed) => truncate(&mut reply.frame, seed),
                FaultAction::Glitch(seed) => glitch(&mut reply.frame, seed),
            }
            sent.push(reply);
        }
        let mut bursts = fillers;
        if sent.len() > 1 {
            let frames: Vec<TimedFrame> = sent
                .into_iter()
                .map(|reply| TimedFrame {
                    start: reply.start,
                    char_time: reply.line.char_time(),
                    frame: reply.frame,
                })
                .collect();
            bursts.extend(collide(&frames));
        } else {
            for reply in sent {
                let pause = self
                    .devices
                    .get(reply.device)
                    .map_or(Duration::ZERO, |d| d.reply_pause);
                bursts.extend(paused_reply(reply, pause));
            }
        }
        bursts.sort_by_key(|burst| burst.start);
        Transmission { bursts }
    }
}

/// A reply as one burst, or, from a slow device (`pause` > 0) that was addressed, its first
/// half, `pause` of silence, then the rest. A reply after an arbitration is never paused: the
/// windows are timed.
fn paused_reply(reply: PlannedReply, pause: Duration) -> Vec<Burst> {
    let char_time = reply.line.char_time();
    if pause.is_zero() || reply.after_arbitration || reply.frame.len() < 2 {
        return vec![Burst {
            start: reply.start,
            char_time,
            bytes: reply.frame,
        }];
    }
    let mut first = reply.frame;
    let rest = first.split_off(first.len() / 2);
    let rest_start = reply.start + char_time * first.len() as u32 + pause;
    vec![
        Burst {
            start: reply.start,
            char_time,
            bytes: first,
        },
        Burst {
            start: rest_start,
            char_time,
            bytes: rest,
        },
    ]
}

/// When a device's arbitration windows open and how long each lasts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ArbitrationTiming {
    /// The extension's: 42 bits (and 800 µs) after the request, windows of 12 bits and a reserve.
    Standard,
    /// A scan under the deprecated 0x60: 44 bits after the request, windows of 20 bits.
    LegacyScan,
}

/// A Fast Modbus reply under `function` (0x46, or 0x60 when asked under 0x60).
fn fast_reply(function: u8, address: u8, reply: FastReply) -> Reply {
    Reply {
        address,
        body: ReplyBody::Fast { function, reply },
    }
}

fn illegal_function(address: u8, function: u8) -> Reply {
    Reply::classic(
        address,
        ResponsePdu::Exception {
            function,
            code: ExceptionCode::ILLEGAL_FUNCTION,
        },
    )
}
