//! The shared half-duplex wire of one link: the master's bytes and the devices' bytes on one
//! timeline, as an RS-485 pair carries them.
//!
//! - The master's UART sends what it is given back to back: bytes written while earlier ones are
//!   still on the wire follow them without a gap.
//! - Devices see a frame only after 3.5 characters of silence on the line ([`crate::protocol::LineSettings::frame_gap`]). Master
//!   bytes that follow sooner belong to the same frame, so two requests written at once (or before
//!   the first has ended) are one run of bytes that is not a frame: noise, nobody answers (as a
//!   Modbus RTU slave that delimits frames by silence). A silence of more than 1.5 characters
//!   inside a run makes it noise too (a strict slave's t1.5: a frame must be sent back to back).
//! - Whatever overlaps in time merges by wired AND (a 0 bit from any driver wins): device replies
//!   with each other, and a master request with a reply still on the wire. Both are garbled then:
//!   the master reads the merged reply bytes, and no device answers the collided request (bit skew
//!   spoils it even where the AND left the bytes intact).
//!
//! Pure and deterministic: time comes in with every call.

use std::time::Duration;

use crate::protocol::frame::MAX_FRAME_LEN;
use crate::protocol::{ParseStatus, RequestParser};

use super::line::{MasterLine, ReceivedRequest};
use super::pacing::Arrival;
use super::transmission::{Burst, Transmission};

/// Byte times are whole nanoseconds computed two ways (per character, per frame): bytes that
/// touch within this much are back to back, not overlapping. A bit lasts 1 µs at 1 Mbaud.
const ROUNDING: Duration = Duration::from_nanos(100);

/// One device byte on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Slot {
    start: Duration,
    char_time: Duration,
    byte: u8,
}

impl Slot {
    /// When its stop bit ends, i.e. when the master's UART hands it over.
    fn end(&self) -> Duration {
        self.start + self.char_time
    }

    /// Shares more than [`ROUNDING`] with `start..end`.
    fn overlaps(&self, start: Duration, end: Duration) -> bool {
        let shared = self.end().min(end).saturating_sub(self.start.max(start));
        shared > ROUNDING
    }
}

/// Master bytes not yet followed by a frame gap.
#[derive(Debug, Clone)]
struct Run {
    /// The bytes as devices hear them (merged with any device byte they overlapped).
    bytes: Vec<u8>,
    start: Duration,
    end: Duration,
    line: MasterLine,
    /// Overlapped a device's transmission, or outgrew any frame: noise whatever it holds.
    spoiled: bool,
    /// Sent by a second master ([`Wire::other_master_sends`]): its bytes are on the wire as
    /// the master hears them too.
    other_master: bool,
}

impl Run {
    /// When its frame gap ends: the devices answer it then.
    fn deadline(&self) -> Duration {
        self.end + self.line.settings().frame_gap()
    }
}

/// What the wire did with bytes the master wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MasterWrite {
    /// The request collided with device bytes still on the wire (which are now merged).
    pub collided: bool,
    /// A request ended by the silence before these bytes, and was answered.
    pub answered: bool,
}

/// The wire's timeline: device bytes the master has not read yet, the master's run.
#[derive(Debug, Clone, Default)]
pub struct Wire {
    /// Device bytes not yet handed to the master, in time order, never overlapping.
    pending: Vec<Slot>,
    /// When the last device byte put on the wire ends (`None`: no device has sent yet).
    devices_quiet_from: Option<Duration>,
    /// When the master's UART has sent everything it was given.
    master_free_at: Duration,
    run: Option<Run>,
    /// A second master's request not yet followed by a frame gap (answered then, unless
    /// something overlapped it).
    other_run: Option<Run>,
}

impl Wire {
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes the master wrote, read by the simulator at `at`. A run that had already ended by
    /// silence before them is answered first (`respond` gets it), so that these bytes collide
    /// with its reply if they land on it.
    pub fn master_writes(
        &mut self,
        bytes: &[u8],
        at: Duration,
        line: MasterLine,
        respond: impl FnMut(&ReceivedRequest) -> Transmission,
    ) -> MasterWrite {
        let mut outcome = MasterWrite::default();
        if bytes.is_empty() {
            return outcome;
        }
        let settings = line.settings();
        let start = at.max(self.master_free_at);
        outcome.answered = self.on_silence(start, respond);
        // Bytes within a second master's request or its frame gap: the devices hear one run
        // of noise (this run is spoiled by its bytes below).
        if let Some(other) = &mut self.other_run {
            if start < other.deadline() {
                other.spoiled = true;
            }
        }
        self.forget_delivered(at);
        let mut run = match self.run.take() {
            // New settings in the middle of a run: what came before is noise to everyone.
            Some(mut run) if run.line == line => {
                // A silence of more than 1.5 characters inside a frame (but less than the 3.5
                // that end it) makes the frame incomplete: a slave discards it, and what
                // follows before the next frame gap belongs to the discarded frame (the Modbus
                // RTU spec's t1.5; fast-modbus.md §1).
                if start.saturating_sub(run.end) > settings.char_time() * 3 / 2 + ROUNDING {
                    tracing::debug!(
                        "sim: a silence of more than 1.5 characters inside a frame: nobody answers"
                    );
                    run.spoiled = true;
                }
                run
            }
            _ => Run {
                bytes: Vec::new(),
                start,
                end: start,
                line,
                // A request that starts before the line has been quiet for a frame gap after a
                // device's bytes is, to every device that heard them, their continuation.
                // (One that starts before the latest device byte ends collides with it below, or
                // precedes it: a late reply still to come is not silence to keep.)
                spoiled: self.devices_quiet_from.is_some_and(|quiet| {
                    start >= quiet.saturating_sub(ROUNDING) && start < quiet + settings.frame_gap()
                }),
                other_master: false,
            },
        };
        if run.spoiled && run.bytes.is_empty() {
            tracing::debug!(
                "sim: a request less than 3.5 characters after a reply: nobody answers"
            );
        }
        for (index, &byte) in bytes.iter().enumerate() {
            // Wire time from the frame's start, not a sum of rounded character times.
            let byte_start = start + settings.wire_time(index);
            let byte_end = start + settings.wire_time(index + 1);
            let mut heard = byte;
            for slot in self
                .pending
                .iter_mut()
                .filter(|slot| slot.overlaps(byte_start, byte_end))
            {
                slot.byte &= byte;
                heard &= slot.byte;
                outcome.collided = true;
            }
            if run.bytes.len() < 2 * MAX_FRAME_LEN {
                run.bytes.push(heard);
            } else {
                run.spoiled = true;
            }
            run.end = byte_end;
        }
        run.spoiled |= outcome.collided;
        self.master_free_at = run.end;
        self.run = Some(run);
        outcome
    }

    /// A second master ([`super::other_master`]) sends `frame` from `at` at the settings of
    /// `line`, whatever is on the wire. Its bytes go on the wire as a device's do, so the master
    /// receives them (except while it talks itself: its transceiver does not listen then), and
    /// merge by AND with whatever they overlap. It collides with the master's
    /// request still on the wire or not yet followed by a frame gap (the devices hear one run:
    /// noise, nobody answers either), with device bytes it overlaps or follows within a frame
    /// gap, and with master bytes written before its own frame gap has passed. Otherwise the
    /// devices answer it once that gap has passed, like the master's. Runs that silence had
    /// already ended are answered first, so this may land on their replies. True if it
    /// collided.
    pub fn other_master_sends(
        &mut self,
        frame: &[u8],
        at: Duration,
        line: MasterLine,
        respond: impl FnMut(&ReceivedRequest) -> Transmission,
    ) -> bool {
        if frame.is_empty() {
            return false;
        }
        self.on_silence(at, respond);
        self.forget_delivered(at);
        let settings = line.settings();
        let end = at + settings.wire_time(frame.len());
        let mut collided = false;
        let mut bytes = frame.to_vec();
        // Bytes sent while the master itself talks: its transceiver does not listen then (no
        // echo), so it never hears them; the devices hear both merged.
        let mut unheard = vec![false; bytes.len()];
        if let Some(run) = &mut self.run {
            run.spoiled = true;
            collided = true;
            let run_settings = run.line.settings();
            for ((index, byte), unheard) in bytes.iter_mut().enumerate().zip(&mut unheard) {
                let byte_start = at + settings.wire_time(index);
                let byte_end = at + settings.wire_time(index + 1);
                for (position, heard) in run.bytes.iter_mut().enumerate() {
                    let heard_start = run.start + run_settings.wire_time(position);
                    let heard_end = run.start + run_settings.wire_time(position + 1);
                    let shared = byte_end
                        .min(heard_end)
                        .saturating_sub(byte_start.max(heard_start));
                    if shared > ROUNDING {
                        *heard &= *byte;
                        *byte = *heard;
                        *unheard = true;
                    }
                }
            }
        }
        if let Some(other) = &mut self.other_run {
            other.spoiled = true;
            collided = true;
        }
        collided |= self.pending.iter().any(|slot| slot.overlaps(at, end))
            || self
                .devices_quiet_from
                .is_some_and(|quiet| at + ROUNDING >= quiet && at < quiet + settings.frame_gap());
        let bursts = bytes
            .iter()
            .zip(&unheard)
            .enumerate()
            .filter(|(_, (_, &unheard))| !unheard)
            .map(|(index, (&byte, _))| Burst {
                start: at + settings.char_time() * u32::try_from(index).unwrap_or(u32::MAX),
                char_time: settings.char_time(),
                bytes: vec![byte],
            })
            .collect();
        self.transmit(&Transmission { bursts });
        self.other_run = Some(Run {
            bytes,
            start: at,
            end,
            line,
            spoiled: collided,
            other_master: true,
        });
        collided
    }

    /// When a master that listens before it talks may start: a frame gap after the last
    /// byte anyone put on the wire (at `line`'s settings).
    pub fn quiet_at(&self, line: MasterLine) -> Duration {
        let busy_until = self
            .devices_quiet_from
            .unwrap_or_default()
            .max(self.master_free_at);
        busy_until + line.settings().frame_gap()
    }

    /// When the master's current run, or a second master's request, will have been followed by
    /// a frame gap (the earlier of the two).
    pub fn silence_deadline(&self) -> Option<Duration> {
        [&self.run, &self.other_run]
            .into_iter()
            .flatten()
            .map(Run::deadline)
            .min()
    }

    /// Time has reached `now`: ends the runs whose frame gap has passed and answers them, in
    /// the order they ended. True if one was a request that got an answer on the wire.
    pub fn on_silence(
        &mut self,
        now: Duration,
        mut respond: impl FnMut(&ReceivedRequest) -> Transmission,
    ) -> bool {
        let mut answered = false;
        while let Some(deadline) = self.silence_deadline().filter(|&deadline| now >= deadline) {
            let run = if self
                .run
                .as_ref()
                .is_some_and(|run| run.deadline() == deadline)
            {
                self.run.take()
            } else {
                self.other_run.take()
            };
            answered |= run.is_some_and(|run| self.answer(&run, &mut respond));
        }
        answered
    }

    fn answer(
        &mut self,
        run: &Run,
        mut respond: impl FnMut(&ReceivedRequest) -> Transmission,
    ) -> bool {
        // Device bytes put on the wire within a second master's frame gap (a
        // reply to the master scheduled before that request was known) are, to every device,
        // more bytes of that frame.
        if run.other_master
            && self
                .pending
                .iter()
                .any(|slot| slot.overlaps(run.end, run.deadline()))
        {
            return false;
        }
        let Some(request) = run_as_request(run) else {
            return false;
        };
        let transmission = respond(&request);
        let answered = !transmission.is_empty();
        self.transmit(&transmission);
        answered
    }

    /// Puts device bytes on the wire; bytes overlapping others already there merge by AND.
    pub fn transmit(&mut self, transmission: &Transmission) {
        for burst in &transmission.bursts {
            for (index, &byte) in burst.bytes.iter().enumerate() {
                let slot = Slot {
                    start: burst.start + burst.char_time * u32::try_from(index).unwrap_or(u32::MAX),
                    char_time: burst.char_time,
                    byte,
                };
                self.devices_quiet_from = Some(
                    self.devices_quiet_from
                        .map_or(slot.end(), |quiet| quiet.max(slot.end())),
                );
                // `pending` never overlaps, so its ends are in start order too: only the
                // slots between the first ending after this one's start and the first
                // starting after its end can overlap it (a scan of all of them was the
                // simulator's largest cost: quadratic in a reply's length).
                let end = slot.end();
                let from = self
                    .pending
                    .partition_point(|other| other.end() <= slot.start);
                let to = self.pending.partition_point(|other| other.start < end);
                let mut merged = false;
                for other in self
                    .pending
                    .get_mut(from..to.max(from))
                    .unwrap_or_default()
                    .iter_mut()
                    .filter(|other| other.overlaps(slot.start, end))
                {
                    other.byte &= byte;
                    merged = true;
                }
                if !merged {
                    let position = self
                        .pending
                        .partition_point(|other| other.start <= slot.start);
                    self.pending.insert(position, slot);
                }
            }
        }
    }

    /// Device bytes still to be handed to the master, with the time each arrives.
    pub fn arrivals(&self) -> Vec<(Duration, u8)> {
        self.received()
            .into_iter()
            .map(|arrival| (arrival.at, arrival.byte))
            .collect()
    }

    /// The same bytes as the master's UART receives them (for its receive FIFO's timing).
    pub fn received(&self) -> Vec<Arrival> {
        self.pending
            .iter()
            .map(|slot| Arrival {
                at: slot.end(),
                byte: slot.byte,
                char_time: slot.char_time,
            })
            .collect()
    }

    /// Device bytes still to come after `now` (those before have reached the master).
    pub fn forget_delivered(&mut self, now: Duration) {
        self.pending.retain(|slot| slot.end() > now);
    }
}

/// A run is a request only if it is exactly one frame: anything before, after or inside it
/// (another request, noise) makes it noise, as a slave checks the CRC of all it got.
fn run_as_request(run: &Run) -> Option<ReceivedRequest> {
    if run.spoiled {
        tracing::debug!("sim: request collided with a reply on the wire: nobody answers");
        return None;
    }
    let mut parser = RequestParser::new();
    parser.push(&run.bytes);
    let status = match parser.poll() {
        ParseStatus::NeedMore => parser.silence(),
        status => status,
    };
    match status {
        ParseStatus::Frame(request) if parser.buffered().is_empty() => Some(ReceivedRequest {
            request,
            frame_len: run.bytes.len(),
            first_byte_at: run.start,
            last_byte_at: run.end,
            line: run.line,
            from_other_master: run.other_master,
        }),
        ParseStatus::Frame(_) => {
            tracing::debug!(
                "sim: {} bytes without a frame gap are not one frame: nobody answers",
                run.bytes.len()
            );
            None
        }
        ParseStatus::Error(err) => {
            tracing::debug!("sim: line noise: {err}");
            None
        }
        ParseStatus::NeedMore => None,
    }
}
