//! A served device between its port and its sinks: the last word of every register read, each
//! control's value and error flags; port events in, [`DeviceUpdate`]s out; `/on` payloads in,
//! checked, register writes out.
//!
//! The one home of these rules: how a value is made from register words (event words joined with
//! the others of the same value), whether it changed, when `r`, `w` and `p` are set and cleared,
//! and which payloads a control accepts. The sinks (MQTT, stdout) only map the updates.

use std::collections::BTreeSet;
use std::sync::{Arc, Weak};

use tracing::{debug, warn};

use crate::config::values::parse_int_text;
use crate::device::codec::Decoded;
use crate::device::model::{ResolvedChannel, ResolvedDevice, SharedVec, WriteFunction};
use crate::device_updates::{DeviceUpdate, ErrorFlags, Repeats};
use crate::port::{PortEvent, RegisterSpan, RegisterWrite};
use crate::protocol::RegisterType;

#[derive(Debug)]
pub struct DeviceModel {
    pub device: Arc<ResolvedDevice>,
    /// This device's index on its port (the scheduler's device number).
    index: usize,
    /// The device's id, shared by every value update.
    device_id: Arc<str>,
    /// Which channels read each register, and their ids.
    channel_index: Arc<ChannelIndex>,
    /// The last word of every register a channel reads or writes, per slot of
    /// [`ChannelIndex::registers`] (none until read).
    words: Vec<Option<u16>>,
    errors: Vec<ErrorFlags>,
    /// The last value reported per channel, to tell a change from a repeat (and sent again,
    /// not copied, when it repeats).
    reported: Vec<Option<Arc<str>>>,
    /// Which repeated values the sinks need (see [`Repeats`]).
    repeats: Repeats,
    /// Per channel (at [`ChannelIndex::word_slots`]), the words its reported value was decoded
    /// from, when `words_decoded` says so: the same words make the same text, so a read that
    /// repeats them is known to repeat the value without decoding it.
    last_words: Vec<u16>,
    words_decoded: Vec<bool>,
    /// Where in the channel index the last search for a span's channels ended.
    reader_hint: usize,
    /// Channels that events changed since the last [`DeviceModel::flush_events`].
    pending_events: BTreeSet<usize>,
    /// The registers those events set.
    pending_event_words: Vec<(RegisterType, u16)>,
    /// Kept between reads, so that a read of many values allocates nothing for them unless
    /// they changed: the channels a read touched, a channel's words, its value's text.
    touched: Vec<usize>,
    word_buffer: Vec<u16>,
    text: String,
    /// Reads whose value was `unsupported_value`, for the scheduler to stop
    /// ([`Self::take_unsupported_reads`]).
    unsupported_reads: Vec<crate::port::RegisterSpan>,
    /// The writes handed out by [`Self::take_write`] and not yet done, the latest per first
    /// register as the scheduler keeps them, with the bits of both defined when one replaced
    /// another (as the scheduler merges them). A bit field written next goes over their words
    /// rather than over the words last read: the scheduler keeps only the latest write of a
    /// register, so one composed over the read would undo them.
    pending_writes: Vec<RegisterWrite>,
    /// The register whose write was reported done by the event just applied: the words the
    /// scheduler reports next ([`PortEvent::Values`]) are those it sent.
    write_done: Option<(RegisterType, u16)>,
    /// The port reported the device offline and not online since ([`Self::is_offline`]).
    offline: bool,
    /// Channels with a press counter whose next 0 is not published: a Wiren Board device
    /// counts again from 0 after a restart, and that 0 would fire the `whenChanged` rules on
    /// the counter (wb-mqtt-serial's `DoNotPublishNextZeroPressCounter`). Set when the device
    /// goes offline, or reports a restart once its counter was published; a channel leaves it
    /// at its first other value.
    held_press_counters: Vec<usize>,
    /// Write-only channels (no register read) written and not yet done, with the register
    /// each write starts at: the channel is published once none of its writes is left, from
    /// the words written (the other write-only channels of a register are not: nobody wrote
    /// them). A write replaced before it went (a later one of the same register) takes its
    /// place.
    written_only: Vec<(usize, RegisterType, u16)>,
}

/// Which channels read each register, and the channels' ids as updates carry them: built once
/// per channel list and shared, as the list is, by the devices made from the same template and
/// overrides.
#[derive(Debug)]
struct ChannelIndex {
    /// The list indexed (matched by identity, see [`SharedVec::ptr_eq`]).
    channels: SharedVec<ResolvedChannel>,
    /// (register type, address, channel) for every register (or bit) that a channel reads,
    /// sorted. The address is a u32, as [`RegisterSpan::end`]: a value may end past 65535.
    readers: Vec<(RegisterType, u32, u32)>,
    control_ids: Vec<Arc<str>>,
    /// Per channel, where its words are in `word_registers` and in
    /// [`DeviceModel::last_words`]: (start, count); none for a channel with a register it
    /// does not read (it has no value to decode).
    word_slots: Vec<Option<(usize, usize)>>,
    /// The register of every word of every channel, in the order its value is decoded from:
    /// found here rather than in the channel's registers, which a read of many values would
    /// otherwise bring into the cache one by one only to find them unchanged.
    word_registers: Vec<(RegisterType, u16)>,
    /// Per entry of `word_registers`, its slot in `registers`.
    word_register_slots: Vec<usize>,
    /// Every register a channel reads or writes, sorted: the slots of
    /// [`DeviceModel::words`]. A read's words fill consecutive slots, found with one search
    /// per read rather than one hash lookup per word; words no channel uses are not kept.
    registers: Vec<(RegisterType, u16)>,
    /// Per channel, whether it is a pushbutton (its every value is reported, see
    /// [`Repeats::report`]; the type as `mqtt::layout::is_pushbutton` reads it).
    pushbuttons: Vec<bool>,
}

/// The channel indexes in use, to share one between the devices of one channel list (the
/// devices of one template and overrides share the list, see [`SharedVec`]). Kept by whoever
/// builds the models: the daemon's bus side for all its ports and reloads, a test's gateway.
#[derive(Debug, Default)]
pub struct ChannelIndexes(Vec<Weak<ChannelIndex>>);

impl ChannelIndexes {
    /// The index of `channels`: the one another device of the same list uses, or a new one.
    fn index_of(&mut self, channels: &SharedVec<ResolvedChannel>) -> Arc<ChannelIndex> {
        self.0.retain(|index| index.strong_count() > 0);
        if let Some(index) = self
            .0
            .iter()
            .filter_map(Weak::upgrade)
            .find(|index| SharedVec::ptr_eq(&index.channels, channels))
        {
            return index;
        }
        let index = Arc::new(ChannelIndex::build(channels));
        self.0.push(Arc::downgrade(&index));
        index
    }
}

impl ChannelIndex {
    fn build(channels: &SharedVec<ResolvedChannel>) -> Self {
        let mut readers = Vec::new();
        for (index, channel) in channels.iter().enumerate() {
            let index = u32::try_from(index).unwrap_or(u32::MAX);
            for read in channel.registers.iter().filter_map(|r| r.read) {
                let span = read.span();
                for address in u32::from(span.start)..span.end() {
                    readers.push((span.register_type, address, index));
                }
            }
        }
        readers.sort_unstable();
        readers.dedup();
        readers.shrink_to_fit();
        let mut word_slots = Vec::with_capacity(channels.len());
        let mut word_registers = Vec::new();
        for channel in channels.iter() {
            let reads: Option<Vec<_>> = channel.registers.iter().map(|r| r.read).collect();
            let Some(reads) = reads else {
                word_slots.push(None);
                continue;
            };
            let start = word_registers.len();
            for read in reads {
                for i in 0..read.count.max(1) {
                    word_registers.push((read.reg_type, read.address.wrapping_add(i)));
                }
            }
            word_slots.push(Some((start, word_registers.len() - start)));
        }
        word_registers.shrink_to_fit();
        let mut registers = word_registers.clone();
        for channel in channels.iter() {
            for write in channel.registers.iter().filter_map(|r| r.write) {
                for i in 0..write.count.max(1) {
                    registers.push((write.reg_type, write.address.wrapping_add(i)));
                }
            }
        }
        registers.sort_unstable();
        registers.dedup();
        registers.shrink_to_fit();
        let word_register_slots = word_registers
            .iter()
            .map(|register| registers.binary_search(register).unwrap_or(usize::MAX))
            .collect();
        Self {
            channels: channels.clone(),
            readers,
            control_ids: channels.iter().map(|c| Arc::from(c.id.as_str())).collect(),
            word_slots,
            word_registers,
            word_register_slots,
            registers,
            pushbuttons: channels
                .iter()
                .map(|c| c.control_type == "pushbutton")
                .collect(),
        }
    }

    /// The slot of `register` in [`Self::registers`].
    fn slot_of(&self, register: (RegisterType, u16)) -> Option<usize> {
        self.registers.binary_search(&register).ok()
    }

    /// The first slot at or after `register` (the slots of a span's words follow it in
    /// address order).
    fn first_slot_from(&self, register: (RegisterType, u16)) -> usize {
        self.registers.partition_point(|&entry| entry < register)
    }

    /// How many words [`DeviceModel::last_words`] keeps for all channels.
    fn word_count(&self) -> usize {
        self.word_registers.len()
    }

    /// The channels that read any register of `span`, in channel order, into `out`. `hint`:
    /// where the last search ended, kept by the caller; a device's reads come in address
    /// order (a read of many values arrives as one span per value), so the next span usually
    /// starts there and needs no search.
    /// Whether a channel reads `register`.
    fn is_read(&self, (register_type, address): (RegisterType, u16)) -> bool {
        let key = (register_type, u32::from(address));
        let at = self.readers.partition_point(|&(t, a, _)| (t, a) < key);
        self.readers.get(at).is_some_and(|&(t, a, _)| (t, a) == key)
    }

    fn readers_of(&self, span: &RegisterSpan, out: &mut Vec<usize>, hint: &mut usize) {
        out.clear();
        if span.count == 0 {
            // No register, but still "overlapping" a wider value around its start (as
            // `reads_span` has it): too odd to index.
            out.extend(
                self.channels
                    .iter()
                    .enumerate()
                    .filter(|(_, channel)| reads_span(channel, span))
                    .map(|(index, _)| index),
            );
            return;
        }
        let start = u32::from(span.start);
        let end = span.end();
        let before = |&(register_type, address, _): &(RegisterType, u32, u32)| {
            (register_type, address) < (span.register_type, start)
        };
        // The hint is the first entry not before the span when the one at it is not and the
        // one just before it is (the entries are sorted).
        let hinted = self.readers.get(*hint).is_some_and(|entry| !before(entry))
            && hint
                .checked_sub(1)
                .is_none_or(|previous| self.readers.get(previous).is_some_and(before));
        let first = if hinted {
            *hint
        } else {
            self.readers.partition_point(before)
        };
        let matching =
            self.readers
                .iter()
                .skip(first)
                .take_while(|&&(register_type, address, _)| {
                    register_type == span.register_type && address < end
                });
        out.extend(matching.map(|&(_, _, channel)| channel as usize));
        *hint = first + out.len();
        if !out.is_sorted_by(|a, b| a < b) {
            out.sort_unstable();
            out.dedup();
        }
    }
}

/// Longest `/on` payload looked at; anything longer is refused before parsing.
pub const MAX_PAYLOAD: usize = 4096;

/// Why a `/on` payload was not written.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WriteRejected {
    #[error("no control `{0}` on this device")]
    UnknownControl(String),
    #[error("control `{0}` is read-only")]
    ReadOnly(String),
    /// The MQTT side hands non-UTF-8 payloads over with U+FFFD in place of the bad bytes.
    #[error("the payload is not UTF-8 text")]
    NotText,
    #[error("the payload is {0} bytes long; a control takes at most {MAX_PAYLOAD}")]
    TooLong(usize),
    #[error("a {control_type} takes {expected}, got `{payload}`")]
    BadFormat {
        control_type: String,
        expected: &'static str,
        payload: String,
    },
    /// Out of the control's limits or the register format's range (the codec's reason).
    #[error("{0}")]
    BadValue(String),
}

impl DeviceModel {
    /// The model of `device`, the `index`th of its port, reporting `repeats` besides the
    /// changes (the sinks that read its updates say which they need).
    pub fn new(device: Arc<ResolvedDevice>, index: usize, repeats: Repeats) -> Self {
        Self::sharing(device, index, repeats, &mut ChannelIndexes::default())
    }

    /// [`Self::new`], sharing the register → channels index with the other models built from
    /// the same channel list through `indexes`.
    pub fn sharing(
        device: Arc<ResolvedDevice>,
        index: usize,
        repeats: Repeats,
        indexes: &mut ChannelIndexes,
    ) -> Self {
        let errors = vec![ErrorFlags::default(); device.channels.len()];
        let channel_index = indexes.index_of(&device.channels);
        let words = vec![None; channel_index.registers.len()];
        Self {
            reported: vec![None; device.channels.len()],
            repeats,
            last_words: vec![0; channel_index.word_count()],
            words_decoded: vec![false; device.channels.len()],
            reader_hint: 0,
            device_id: Arc::from(device.id.as_str()),
            channel_index,
            device,
            index,
            words,
            errors,
            pending_events: BTreeSet::new(),
            pending_event_words: Vec::new(),
            touched: Vec::new(),
            word_buffer: Vec::new(),
            text: String::new(),
            unsupported_reads: Vec::new(),
            pending_writes: Vec::new(),
            write_done: None,
            offline: false,
            held_press_counters: Vec::new(),
            written_only: Vec::new(),
        }
    }

    /// Starts as the model of a device known offline: the model this one replaces (a reload
    /// restarted its port) had it offline, and the MQTT side keeps the `r` it published on
    /// every readable control. This model holds that `r` too, so that it clears it at the
    /// control's first good read, as after any failed read (a model that starts with clear
    /// flags has nothing to clear, and the `r` would stay on the broker).
    pub fn known_offline(mut self) -> Self {
        self.offline = true;
        for (flags, channel) in self.errors.iter_mut().zip(self.device.channels.iter()) {
            if channel.is_read() {
                flags.read = true;
            }
        }
        // Its counters went offline with it, and MQTT keeps their last values.
        self.hold_press_counters();
        self
    }

    /// The press counters whose next 0 this model holds back (see
    /// [`Self::holding_press_counters`]), by control id.
    pub fn held_press_counters(&self) -> Vec<String> {
        self.held_press_counters
            .iter()
            .filter_map(|&index| self.device.channels.get(index))
            .map(|channel| channel.id.clone())
            .collect()
    }

    /// Holds back the next 0 of the press counters `controls`, as the model this one replaces
    /// (a reload restarted its port) did: MQTT keeps their last values.
    pub fn holding_press_counters(mut self, controls: &[String]) -> Self {
        for (index, channel) in self.device.channels.iter().enumerate() {
            let press_counter = channel.registers.iter().any(|r| r.press_counter);
            if press_counter
                && controls.contains(&channel.id)
                && !self.held_press_counters.contains(&index)
            {
                self.held_press_counters.push(index);
            }
        }
        self
    }

    /// The device was reported offline and not online since: what a model that replaces this
    /// one starts from ([`Self::known_offline`]).
    pub fn is_offline(&self) -> bool {
        self.offline
    }

    /// The reads that answered `unsupported_value` since the last call: wb-mqtt-serial stops
    /// reading such a register until the device reconnects (`UnsupportedRegisterOnBorder`).
    pub fn take_unsupported_reads(&mut self) -> Vec<crate::port::RegisterSpan> {
        std::mem::take(&mut self.unsupported_reads)
    }

    pub fn id(&self) -> &str {
        &self.device.id
    }

    /// Applies one port event about this device. Values delivered by events are published by
    /// [`DeviceModel::flush_events`], once every event of the packet is in.
    pub fn apply(&mut self, event: PortEvent, out: &mut Vec<DeviceUpdate>) {
        if !matches!(
            event,
            PortEvent::EventValue { .. } | PortEvent::Rebooted { .. }
        ) {
            // Keep the order in which things happened.
            self.flush_events(out);
        }
        let write_done = self.write_done.take();
        match event {
            PortEvent::Values { span, values, .. } => {
                let written = write_done == Some((span.register_type, span.start));
                self.settle_pending_writes(&span, &values, written);
                self.store_words(span.register_type, span.start, &values);
                let mut touched = std::mem::take(&mut self.touched);
                self.channel_index
                    .readers_of(&span, &mut touched, &mut self.reader_hint);
                // A value of several registers that this span covers only in part is not
                // published from it: its other words came from another read (or write), and
                // the device may have changed it in between (a u32 counter passing 65535 would
                // come out as 0). Its own read, which covers it whole, publishes it, as
                // wb-mqtt-serial sets a register's value only from the read of all its words.
                let channels = &self.device.channels;
                touched.retain(|&index| {
                    channels
                        .get(index)
                        .is_some_and(|channel| !covers_in_part(channel, &span))
                });
                self.publish_channels(&touched, false, out);
                self.touched = touched;
                if written {
                    self.publish_write_only(&span, out);
                }
            }
            PortEvent::EventValue {
                register_type,
                address,
                payload,
                ..
            } => {
                let carried = crate::protocol::event_payload_words(&payload);
                let width = self.event_width(register_type, address, carried.len());
                // A register set again before the pending values were published: a device
                // that queues its changes reports a short pulse as two events, possibly in one
                // packet. The values as they stood come out first, as wb-mqtt-serial publishes
                // every event, rather than the pulse being folded away.
                let sets_a_pending_word = (0..width).any(|offset| {
                    self.pending_event_words
                        .contains(&(register_type, address.wrapping_add(offset)))
                });
                if sets_a_pending_word {
                    self.flush_events(out);
                }
                self.pending_event_words
                    .extend((0..width).map(|offset| (register_type, address.wrapping_add(offset))));
                // The value's low words (the scheduler takes no packet with a value wider than
                // the read that holds its register, so this is all of them there).
                let skip = carried.len().saturating_sub(usize::from(width));
                let value = carried.get(skip..).unwrap_or(&[]);
                let registers = self.registers_holding(register_type, address, value);
                self.store_words(register_type, address, &registers);
                // Part of a wider value (its first words, or words inside it: a channel on the
                // low word of a u32): its other words, as last read, may be older than these (a
                // device updates a value at once). Forgotten, so that the value waits for the
                // read the scheduler makes at once rather than being published half updated;
                // not those this packet set, which come with these.
                let span = RegisterSpan::new(register_type, address, width);
                self.forget_words_beside(&span);
                // Published once the whole packet is in (see `flush_events`): a packet may carry
                // several words of one value, and a value made of old and new words is wrong.
                let mut touched = std::mem::take(&mut self.touched);
                self.channel_index
                    .readers_of(&span, &mut touched, &mut self.reader_hint);
                self.pending_events.extend(touched.iter().copied());
                self.touched = touched;
            }
            PortEvent::ReadFailed {
                span, unsupported, ..
            } => {
                if unsupported {
                    debug!(device = %self.device.id, ?span, "register not supported by the device");
                }
                self.set_flags(|c| reads_span(c, &span), |flags| flags.read = true, out);
            }
            PortEvent::PeriodMissed { span, missed, .. } => {
                self.set_flags(
                    |c| reads_span(c, &span),
                    |flags| flags.period_missed = missed,
                    out,
                );
            }
            PortEvent::WriteDone {
                register_type,
                address,
                ..
            } => {
                self.write_done = Some((register_type, address));
                self.set_flags(
                    |c| writes_register(c, register_type, address),
                    |flags| flags.write = false,
                    out,
                );
            }
            PortEvent::WriteFailed {
                register_type,
                address,
                permanent,
                ..
            } => {
                if permanent {
                    // Given up: the device keeps what it had.
                    self.pending_writes
                        .retain(|w| (w.register_type, w.address) != (register_type, address));
                    self.written_only
                        .retain(|&(_, t, a)| (t, a) != (register_type, address));
                }
                self.set_flags(
                    |c| writes_register(c, register_type, address),
                    |flags| flags.write = true,
                    out,
                );
            }
            PortEvent::Online { .. } => {
                self.offline = false;
                out.push(DeviceUpdate::Online {
                    device_id: self.device.id.clone(),
                    online: true,
                });
            }
            PortEvent::Offline { .. } => {
                self.offline = true;
                self.hold_published_press_counters();
                out.push(DeviceUpdate::Online {
                    device_id: self.device.id.clone(),
                    online: false,
                });
                // Every control of a dead device at once, as wb-mqtt-serial does, rather than
                // one by one as each read fails in turn (seconds apart under back-off).
                self.set_flags(ResolvedChannel::is_read, |flags| flags.read = true, out);
            }
            PortEvent::Rebooted { .. } => {
                // Also a device that restarted too briefly to be seen offline (a power blip),
                // but not the power-on report at the service's start.
                self.hold_published_press_counters();
                // The device may hold other values now: an event for one word of a wider value
                // must not be joined with words read before the restart. The reads that follow
                // the new setup bring every word back.
                self.words.fill(None);
                // Events of the packet that reported the restart are not joined with those
                // words either; the reads after the new setup publish them.
                self.pending_events.clear();
                self.pending_event_words.clear();
            }
        }
    }

    /// Publishes the channels that events changed, each once, made of the newest words. A
    /// channel with a word never read yet waits for its read (done at once after the events
    /// setup), rather than being published half-known.
    pub fn flush_events(&mut self, out: &mut Vec<DeviceUpdate>) {
        self.pending_event_words.clear();
        if self.pending_events.is_empty() {
            return;
        }
        let mut touched = std::mem::take(&mut self.touched);
        touched.clear();
        touched.extend(std::mem::take(&mut self.pending_events));
        self.publish_channels(&touched, true, out);
        self.touched = touched;
    }

    /// How many words an event payload holds for the value at `address`: what its bytes carry,
    /// but no more than the channel's register there.
    fn event_width(&self, register_type: RegisterType, address: u16, carried: usize) -> u16 {
        if register_type.is_bit() {
            return 1;
        }
        let carried = u16::try_from(carried.max(1)).unwrap_or(u16::MAX);
        let channel_width = self
            .device
            .channels
            .iter()
            .flat_map(|c| c.registers.iter().filter_map(|r| r.read))
            .find(|r| r.reg_type == register_type && r.address == address)
            .map(|r| r.count.max(1));
        channel_width.map_or(carried, |width| width.min(carried))
    }

    /// The registers from `address` on that hold the value an event carried (`value`, words
    /// most significant first): the payload is the value itself, whatever order the device
    /// keeps its words and bytes in (wb-mqtt-serial takes the payload as the register's value),
    /// so a channel with `word_order` or `byte_order` little_endian gets them reordered.
    fn registers_holding<'a>(
        &self,
        register_type: RegisterType,
        address: u16,
        value: &'a [u16],
    ) -> std::borrow::Cow<'a, [u16]> {
        use crate::config::format::{ByteOrder, WordOrder};
        let codec = self
            .device
            .channels
            .iter()
            .flat_map(|c| c.registers.iter())
            .find(|r| {
                r.read.is_some_and(|read| {
                    read.reg_type == register_type
                        && read.address == address
                        && usize::from(read.count.max(1)) == value.len()
                })
            })
            .map(|r| &r.codec);
        match codec {
            Some(codec)
                if codec.word_order == WordOrder::LittleEndian
                    || codec.byte_order == ByteOrder::LittleEndian =>
            {
                std::borrow::Cow::Owned(codec.ordered_words(value).collect())
            }
            _ => std::borrow::Cow::Borrowed(value),
        }
    }

    /// Holds the press counters published so far: one never published is published at 0
    /// (at the service's start, or a device that did not answer then), as the control would
    /// otherwise show nothing until the first press.
    fn hold_published_press_counters(&mut self) {
        self.hold_press_counters();
        let reported = &self.reported;
        self.held_press_counters
            .retain(|&index| matches!(reported.get(index), Some(Some(_))));
    }

    fn hold_press_counters(&mut self) {
        self.held_press_counters.clear();
        self.held_press_counters.extend(
            self.device
                .channels
                .iter()
                .enumerate()
                .filter(|(_, channel)| channel.registers.iter().any(|r| r.press_counter))
                .map(|(index, _)| index),
        );
    }

    /// Whether channel `index`, decoded from `word_buffer`, is a press counter at 0 held back
    /// since its device went offline or restarted; any other value releases it.
    fn zero_press_count_held(&mut self, index: usize, channel: &ResolvedChannel) -> bool {
        let Some(at) = self.held_press_counters.iter().position(|&i| i == index) else {
            return false;
        };
        let mut rest = self.word_buffer.as_slice();
        let mut zero = false;
        for register in &channel.registers {
            let count = register
                .read
                .map_or(1, |read| usize::from(read.count.max(1)));
            let (part, after) = rest.split_at(count.min(rest.len()));
            rest = after;
            zero |= register.press_counter && part.iter().all(|&word| word == 0);
        }
        if !zero {
            self.held_press_counters.swap_remove(at);
        }
        zero
    }

    /// Publishes the write-only controls (a `pushbutton`, a `wo-switch`, a channel with a
    /// `write_address` alone) whose writes the write at `span` completes: their value is what
    /// was written (the words the model keeps of those registers), as wb-mqtt-serial publishes
    /// a register once a write set it. Only the controls written: another write-only control
    /// of the same register (a second pushbutton, another bit) was not.
    fn publish_write_only(&mut self, span: &RegisterSpan, out: &mut Vec<DeviceUpdate>) {
        if self.written_only.is_empty() {
            return;
        }
        let in_span = |&(_, register_type, address): &(usize, RegisterType, u16)| {
            register_type == span.register_type
                && address >= span.start
                && u32::from(address) < span.end()
        };
        let mut done: Vec<usize> = self
            .written_only
            .iter()
            .filter(|entry| in_span(entry))
            .map(|&(index, _, _)| index)
            .collect();
        self.written_only.retain(|entry| !in_span(entry));
        done.sort_unstable();
        done.dedup();
        let device = Arc::clone(&self.device);
        for index in done {
            if self.written_only.iter().any(|&(i, _, _)| i == index) {
                continue; // Another register of it is still to be written.
            }
            let Some(channel) = device.channels.get(index) else {
                continue;
            };
            let mut text = String::new();
            let mut decoded = true;
            for (position, register) in channel.registers.iter().enumerate() {
                let Some(target) = register.write else {
                    decoded = false;
                    break;
                };
                let words: Option<Vec<u16>> = (0..target.count.max(1))
                    .map(|offset| self.word((target.reg_type, target.address.wrapping_add(offset))))
                    .collect();
                let Some(words) = words else {
                    decoded = false;
                    break;
                };
                if position > 0 {
                    text.push(';');
                }
                decoded &= matches!(
                    register.codec.decode_into(&words, &mut text),
                    Ok(Decoded::Text)
                );
            }
            if !decoded {
                continue;
            }
            let pushbutton = self
                .channel_index
                .pushbuttons
                .get(index)
                .copied()
                .unwrap_or(false);
            let report_repeat = self.repeats.report(false, pushbutton);
            let Some(last) = self.reported.get_mut(index) else {
                continue;
            };
            let changed = last.as_deref() != Some(text.as_str());
            let value = match last {
                Some(last) if !changed => Arc::clone(last),
                _ => Arc::clone(last.insert(Arc::from(text.as_str()))),
            };
            if changed || report_repeat {
                self.push_value(index, value, false, changed, out);
            }
        }
    }

    /// Forgets the words of the values `span` holds only part of, outside it, but for those
    /// the events of the packet under way set.
    fn forget_words_beside(&mut self, span: &RegisterSpan) {
        let device = Arc::clone(&self.device);
        let values = device
            .channels
            .iter()
            .flat_map(|c| c.registers.iter().filter_map(|r| r.read))
            .filter(|read| spans_overlap(read, span));
        for value in values {
            for offset in 0..value.count.max(1) {
                let address = value.address.wrapping_add(offset);
                let register = (value.reg_type, address);
                let inside =
                    u32::from(address) >= u32::from(span.start) && u32::from(address) < span.end();
                if !inside && !self.pending_event_words.contains(&register) {
                    self.set_word(register, None);
                }
            }
        }
    }

    /// Reports the values of the `touched` channels whose words are all known: each change,
    /// and each repeat that [`Repeats::report`] asks for. A good value clears `r` first,
    /// changed or not.
    fn publish_channels(
        &mut self,
        touched: &[usize],
        from_event: bool,
        out: &mut Vec<DeviceUpdate>,
    ) {
        let mut text = std::mem::take(&mut self.text);
        // The channels that read their `unsupported_value` (rare: no allocation otherwise).
        let mut unsupported = Vec::new();
        for &index in touched {
            if !self.gather_words(index) {
                continue;
            }
            // Checked on every value, repeated or not: any count but 0 releases the hold.
            let zero_held = self.held_press_counters.contains(&index) && {
                let device = Arc::clone(&self.device);
                device
                    .channels
                    .get(index)
                    .is_some_and(|channel| self.zero_press_count_held(index, channel))
            };
            let flags = self.errors.get(index).copied().unwrap_or_default();
            let report_repeat = self.repeats.report(
                from_event,
                self.channel_index
                    .pushbuttons
                    .get(index)
                    .copied()
                    .unwrap_or(false),
            );
            if self.repeats_decoded_words(index) {
                // The words of the value reported last: the same value, not decoded again.
                if flags.read {
                    self.update_flags(
                        index,
                        ErrorFlags {
                            read: false,
                            ..flags
                        },
                        out,
                    );
                }
                if report_repeat && !zero_held {
                    if let Some(Some(last)) = self.reported.get(index) {
                        let value = Arc::clone(last);
                        self.push_value(index, value, from_event, false, out);
                    }
                }
                continue;
            }
            let device = Arc::clone(&self.device);
            let Some(channel) = device.channels.get(index) else {
                continue;
            };
            text.clear();
            let reading = decode_words(channel, &self.word_buffer, &mut text);
            if let Some(decoded) = self.words_decoded.get_mut(index) {
                *decoded = false;
            }
            match reading {
                Ok(Decoded::Text) => {
                    // Clear `r` before the good value, as wb-mqtt-serial does.
                    if flags.read {
                        self.update_flags(
                            index,
                            ErrorFlags {
                                read: false,
                                ..flags
                            },
                            out,
                        );
                    }
                    let Some(last) = self.reported.get_mut(index) else {
                        continue;
                    };
                    if zero_held {
                        // Kept as the value reported, so that the next count is a change.
                        *last = Some(Arc::from(text.as_str()));
                        self.remember_decoded_words(index);
                        continue;
                    }
                    // Most reads repeat the value: a new one is copied, a repeat sent again.
                    let changed = last.as_deref() != Some(text.as_str());
                    let value = match last {
                        Some(last) if !changed => Arc::clone(last),
                        _ => Arc::clone(last.insert(Arc::from(text.as_str()))),
                    };
                    self.remember_decoded_words(index);
                    if changed || report_repeat {
                        self.push_value(index, value, from_event, changed, out);
                    }
                }
                Ok(decoded @ (Decoded::DeviceError | Decoded::Unsupported)) => {
                    if decoded == Decoded::Unsupported {
                        unsupported.push(index);
                    }
                    self.update_flags(
                        index,
                        ErrorFlags {
                            read: true,
                            ..flags
                        },
                        out,
                    );
                }
                Err(err) => {
                    warn!(device = %device.id, control = %channel.id, %err, "cannot decode the value");
                    self.update_flags(
                        index,
                        ErrorFlags {
                            read: true,
                            ..flags
                        },
                        out,
                    );
                }
            }
        }
        self.text = text;
        if !unsupported.is_empty() {
            self.stop_unsupported(&unsupported);
        }
    }

    /// Hands the reads of the `unsupported` channels to the scheduler to stop, but not a read
    /// another channel needs: bit fields of one register share its read, and one field at its
    /// `unsupported_value` must not stop the others (wb-mqtt-serial stops that channel's
    /// register alone, as each field is a register of its own there).
    fn stop_unsupported(&mut self, unsupported: &[usize]) {
        fn read_spans(channel: &ResolvedChannel) -> impl Iterator<Item = RegisterSpan> + '_ {
            channel
                .registers
                .iter()
                .filter_map(|register| register.read.map(|r| r.span()))
        }
        let channels = &self.device.channels;
        for channel in unsupported.iter().filter_map(|&index| channels.get(index)) {
            for span in read_spans(channel) {
                let needed_elsewhere = channels.iter().enumerate().any(|(other, channel)| {
                    !unsupported.contains(&other) && read_spans(channel).any(|s| s == span)
                });
                if !needed_elsewhere && !self.unsupported_reads.contains(&span) {
                    self.unsupported_reads.push(span);
                }
            }
        }
    }

    fn push_value(
        &self,
        index: usize,
        value: Arc<str>,
        from_event: bool,
        changed: bool,
        out: &mut Vec<DeviceUpdate>,
    ) {
        // The index has the id of every channel the model has.
        let Some(control_id) = self.channel_index.control_ids.get(index) else {
            return;
        };
        let control_id = Arc::clone(control_id);
        out.push(DeviceUpdate::Value {
            device_id: Arc::clone(&self.device_id),
            control_id,
            value,
            from_event,
            changed,
        });
    }

    /// Puts the words of every register of the `index`th channel into `word_buffer`, in
    /// order; false until all have been read.
    /// Keeps `values`, the words of the registers from `start` on, for the channels that use
    /// them: the slots from the first at or after `start`, while they are within the span. (No
    /// channel's registers go past 65535: the config refuses them, so a span's words past it
    /// have no slot.)
    fn store_words(&mut self, register_type: RegisterType, start: u16, values: &[u16]) {
        let index = &self.channel_index;
        let mut slot = index.first_slot_from((register_type, start));
        while let Some(&(slot_type, address)) = index.registers.get(slot) {
            let offset = usize::from(address.wrapping_sub(start));
            let (true, Some(&value)) = (slot_type == register_type, values.get(offset)) else {
                break;
            };
            if let Some(word) = self.words.get_mut(slot) {
                *word = Some(value);
            }
            slot += 1;
        }
    }

    fn word(&self, register: (RegisterType, u16)) -> Option<u16> {
        let slot = self.channel_index.slot_of(register)?;
        self.words.get(slot).copied().flatten()
    }

    fn set_word(&mut self, register: (RegisterType, u16), value: Option<u16>) {
        if let Some(slot) = self.channel_index.slot_of(register) {
            if let Some(word) = self.words.get_mut(slot) {
                *word = value;
            }
        }
    }

    fn gather_words(&mut self, index: usize) -> bool {
        let words = &mut self.word_buffer;
        words.clear();
        let Some(Some((start, count))) = self.channel_index.word_slots.get(index).copied() else {
            return false;
        };
        let Some(registers) = self.channel_index.word_registers.get(start..start + count) else {
            return false;
        };
        let Some(slots) = self
            .channel_index
            .word_register_slots
            .get(start..start + registers.len())
        else {
            return false;
        };
        for &slot in slots {
            match self.words.get(slot) {
                Some(Some(word)) => words.push(*word),
                _ => return false,
            }
        }
        true
    }

    /// Whether `word_buffer` holds the words the channel's reported value was decoded from.
    fn repeats_decoded_words(&self, index: usize) -> bool {
        // Compared word by word: most values are one or two words, too few for `memcmp`.
        self.words_decoded.get(index).copied().unwrap_or(false)
            && self
                .last_words_of(index)
                .is_some_and(|last| last.iter().eq(self.word_buffer.iter()))
    }

    fn last_words_of(&self, index: usize) -> Option<&[u16]> {
        let (start, count) = (*self.channel_index.word_slots.get(index)?)?;
        self.last_words.get(start..start + count)
    }

    /// Keeps `word_buffer` as the words of the channel's reported value.
    fn remember_decoded_words(&mut self, index: usize) {
        let Some(Some((start, count))) = self.channel_index.word_slots.get(index).copied() else {
            return;
        };
        if count != self.word_buffer.len() {
            return;
        }
        let Some(slot) = self.last_words.get_mut(start..start + count) else {
            return;
        };
        slot.copy_from_slice(&self.word_buffer);
        if let Some(decoded) = self.words_decoded.get_mut(index) {
            *decoded = true;
        }
    }

    fn set_flags(
        &mut self,
        matches: impl Fn(&ResolvedChannel) -> bool,
        change: impl Fn(&mut ErrorFlags),
        out: &mut Vec<DeviceUpdate>,
    ) {
        let device = Arc::clone(&self.device);
        for (index, channel) in device.channels.iter().enumerate() {
            if matches(channel) {
                let mut flags = self.errors.get(index).copied().unwrap_or_default();
                change(&mut flags);
                self.update_flags(index, flags, out);
            }
        }
    }

    fn update_flags(&mut self, index: usize, flags: ErrorFlags, out: &mut Vec<DeviceUpdate>) {
        let Some(current) = self.errors.get_mut(index) else {
            return;
        };
        if *current == flags {
            return;
        }
        *current = flags;
        if let Some(channel) = self.device.channels.get(index) {
            out.push(DeviceUpdate::ControlError {
                device_id: self.device.id.clone(),
                control_id: channel.id.clone(),
                errors: flags,
            });
        }
    }

    /// The register writes for a `/on` payload, checked against the control type, its limits
    /// and its register format. The payload is trimmed first.
    pub fn write(
        &self,
        control_id: &str,
        payload: &str,
    ) -> Result<Vec<RegisterWrite>, WriteRejected> {
        let channel = self
            .device
            .channel(control_id)
            .ok_or_else(|| WriteRejected::UnknownControl(control_id.to_owned()))?;
        if channel.readonly {
            return Err(WriteRejected::ReadOnly(control_id.to_owned()));
        }
        let payload = check_payload(channel, payload)?;
        let current: Vec<Option<Vec<u16>>> = channel
            .registers
            .iter()
            .map(|register| {
                let target = register.write.or(register.read)?;
                let count = target.count.max(1);
                // A bit field in registers no channel reads (a `write_address` of its own) goes
                // over what was last written there, and before that over what the setup writes
                // there on connect, or zeros, as wb-mqtt-serial composes it from its register
                // cache (`TModbusTest.WriteHoldingRegiterWithOffsetWriteOptions`; the setup
                // writes go through that cache too). In a register that is read, its other bits
                // must have been read first. A write not yet done comes before either.
                let never_read = (0..count).all(|i| {
                    !self
                        .channel_index
                        .is_read((target.reg_type, target.address.wrapping_add(i)))
                });
                (0..count)
                    .map(|i| {
                        let register = (target.reg_type, target.address.wrapping_add(i));
                        self.pending_word(register)
                            .or_else(|| self.word(register))
                            .or_else(|| never_read.then(|| self.setup_word(register).unwrap_or(0)))
                    })
                    .collect()
            })
            .collect();
        let current_refs: Vec<Option<&[u16]>> = current.iter().map(|c| c.as_deref()).collect();
        let encoded = channel
            .encode(payload, &current_refs)
            .map_err(|err| WriteRejected::BadValue(err.to_string()))?;
        let mut writes = Vec::new();
        for (register, values) in channel.registers.iter().zip(encoded) {
            let Some(target) = register.write.or(register.read) else {
                continue;
            };
            if !target.reg_type.is_writable() {
                return Err(WriteRejected::ReadOnly(control_id.to_owned()));
            }
            // A bit field defines only its bits: the scheduler puts the register's other bits,
            // as the device holds them when the write goes, under them.
            let defined = if register.codec.is_partial() {
                register.codec.field_mask_words()
            } else {
                Vec::new()
            };
            writes.push(RegisterWrite {
                device: self.index,
                register_type: target.reg_type,
                address: target.address,
                force_multiple: register.write_function == WriteFunction::Multiple,
                one_by_one: register.write_function == WriteFunction::Single && values.len() > 1,
                values,
                defined,
            });
        }
        Ok(writes)
    }

    /// Whether a channel reads `address` of `register_type` (a bit field written there goes
    /// over its bits as read; in a register no channel reads, over what the setup leaves there).
    pub fn reads_register(&self, register_type: RegisterType, address: u16) -> bool {
        self.channel_index.is_read((register_type, address))
    }

    /// A `/on` payload to carry out: its register writes, or `w` on the control (in `out`) and
    /// the reason it was refused.
    pub fn take_write(
        &mut self,
        control_id: &str,
        payload: &str,
        out: &mut Vec<DeviceUpdate>,
    ) -> Result<Vec<RegisterWrite>, WriteRejected> {
        let result = self.write(control_id, payload);
        match &result {
            Ok(writes) => {
                let write_only = self
                    .device
                    .channels
                    .iter()
                    .position(|c| c.id == control_id)
                    .filter(|&index| {
                        self.device.channels[index]
                            .registers
                            .iter()
                            .all(|r| r.read.is_none())
                    });
                for write in writes {
                    let start = (write.register_type, write.address);
                    if let Some(index) = write_only {
                        self.written_only.retain(|&(_, t, a)| (t, a) != start);
                        self.written_only.push((index, start.0, start.1));
                    }
                    let mut pending = write.clone();
                    if let Some(older) = self
                        .pending_writes
                        .iter()
                        .position(|w| (w.register_type, w.address) == start)
                    {
                        let older = self.pending_writes.remove(older);
                        if !pending.defined.is_empty() {
                            for (index, mask) in pending.defined.iter_mut().enumerate() {
                                *mask |= older.defined_bits(index);
                            }
                        }
                    }
                    self.pending_writes.push(pending);
                }
            }
            Err(_) => self.set_flags(|c| c.id == control_id, |flags| flags.write = true, out),
        }
        result
    }

    /// The word the device's setup leaves in `register` (the last setup item's that writes it).
    fn setup_word(&self, (register_type, address): (RegisterType, u16)) -> Option<u16> {
        self.device
            .setup
            .iter()
            .rev()
            .filter(|item| item.register.reg_type == register_type)
            .find_map(|item| {
                item.words
                    .get(usize::from(address.checked_sub(item.register.address)?))
                    .copied()
            })
    }

    /// The word a write not yet done puts in `register` (the latest such write's).
    fn pending_word(&self, (register_type, address): (RegisterType, u16)) -> Option<u16> {
        self.pending_writes
            .iter()
            .rev()
            .filter(|w| w.register_type == register_type)
            .find_map(|w| {
                w.values
                    .get(usize::from(address.checked_sub(w.address)?))
                    .copied()
            })
    }

    /// Forgets the pending writes that `values`, read or (`written`) written at `span`, show
    /// done: the register holds their words now, and the cache has them. A bit field's write is
    /// shown done only by the words written, and by its bits there: the scheduler puts the
    /// device's newest words under the others when it sends it, and a read that shows its
    /// bits before it went shows them by chance (the device may change them again before).
    fn settle_pending_writes(&mut self, span: &RegisterSpan, values: &[u16], written: bool) {
        if self.pending_writes.is_empty() {
            return;
        }
        self.pending_writes.retain(|write| {
            let shown = (written || write.defined.is_empty())
                && write.register_type == span.register_type
                && write
                    .address
                    .checked_sub(span.start)
                    .map(usize::from)
                    .and_then(|offset| values.get(offset..offset + write.values.len()))
                    .is_some_and(|held| {
                        held.iter()
                            .zip(&write.values)
                            .enumerate()
                            .all(|(i, (h, w))| {
                                let mask = write.defined_bits(i);
                                h & mask == w & mask
                            })
                    });
            !shown
        });
    }
}

/// Hands the port events of one transaction to the models of their devices, in order, then
/// publishes the event values of the packet once all its words are in. `models` are the port's
/// devices in the scheduler's order.
pub fn apply_port_events(
    models: &mut [DeviceModel],
    events: impl IntoIterator<Item = PortEvent>,
    out: &mut Vec<DeviceUpdate>,
) {
    // Only the models that events reached have any to publish (every call ends with none
    // pending): the others, most of a large bus, are not looked at again.
    let mut evented: Vec<usize> = Vec::new();
    for event in events {
        let device = match &event {
            PortEvent::Values { device, .. }
            | PortEvent::EventValue { device, .. }
            | PortEvent::ReadFailed { device, .. }
            | PortEvent::PeriodMissed { device, .. }
            | PortEvent::WriteDone { device, .. }
            | PortEvent::WriteFailed { device, .. }
            | PortEvent::Online { device }
            | PortEvent::Offline { device }
            | PortEvent::Rebooted { device } => *device,
        };
        if matches!(event, PortEvent::EventValue { .. }) && evented.last() != Some(&device) {
            evented.push(device);
        }
        if let Some(model) = models.get_mut(device) {
            model.apply(event, out);
        }
    }
    evented.sort_unstable();
    evented.dedup();
    for device in evented {
        if let Some(model) = models.get_mut(device) {
            model.flush_events(out);
        }
    }
}

/// Hands the reads that answered `unsupported_value` from the device models (the port's, in
/// the scheduler's order) to the scheduler, which stops them.
pub fn stop_unsupported_reads(
    models: &mut [DeviceModel],
    scheduler: &mut crate::port::PortScheduler,
    now: std::time::Duration,
) {
    for (device, model) in models.iter_mut().enumerate() {
        for span in model.take_unsupported_reads() {
            scheduler.stop_reading(now, device, span);
        }
    }
}

/// Checks an `/on` payload against the control type (what wb-mqtt-serial accepts for it);
/// returns what to write: a `text` payload as received (wb-mqtt-serial writes it as is), any
/// other trimmed. Limits and format ranges are the codec's to check.
fn check_payload<'a>(
    channel: &ResolvedChannel,
    payload: &'a str,
) -> Result<&'a str, WriteRejected> {
    if payload.len() > MAX_PAYLOAD {
        return Err(WriteRejected::TooLong(payload.len()));
    }
    if payload.contains(char::REPLACEMENT_CHARACTER) {
        return Err(WriteRejected::NotText);
    }
    let text = payload.trim();
    match channel.control_type.as_str() {
        "rgb" => {
            let parts: Vec<&str> = text.split(';').collect();
            let colour = parts.len() == 3 && parts.iter().all(|p| p.trim().parse::<u8>().is_ok());
            if !colour {
                return Err(bad_format(channel, "R;G;B with each part 0…255", text));
            }
        }
        "text" | "w1-id" => return Ok(payload),
        // Every other type takes a number, as wb-mqtt-serial converts any `/on` text with the
        // register's format whatever the control type: a switch's other numbers are positions
        // (ONOKOM's vanes 2…6 on a `switch`), a `range` with a scale takes fractions (a
        // setpoint of 22.5 °C on `s16` with scale 0.01), and an integer may come in hex
        // (`0x1F`, `0X00FF`: `FromScaledTextValue` reads base 16 after `0x`). "1" and "0" are
        // `on_value` and `off_value` where the channel has them; the codec and the limits
        // check the rest.
        _ => {
            let parts_are_numbers = text.split(';').all(|p| {
                parse_int_text(p).is_some() || p.trim().parse::<f64>().is_ok_and(f64::is_finite)
            });
            if !parts_are_numbers {
                return Err(bad_format(channel, "a number", text));
            }
        }
    }
    Ok(text)
}

fn bad_format(channel: &ResolvedChannel, expected: &'static str, payload: &str) -> WriteRejected {
    let mut shown: String = payload.chars().take(64).collect();
    if shown.len() < payload.len() {
        shown.push('…');
    }
    WriteRejected::BadFormat {
        control_type: channel.control_type.clone(),
        expected,
        payload: shown,
    }
}

fn spans_overlap(register: &crate::device::model::RegisterRef, span: &RegisterSpan) -> bool {
    let register = register.span();
    register.register_type == span.register_type
        && u32::from(register.start) < span.end()
        && u32::from(span.start) < register.end()
}

/// Whether `span` holds some but not all the words of one of the values `channel` reads.
fn covers_in_part(channel: &ResolvedChannel, span: &RegisterSpan) -> bool {
    channel.registers.iter().filter_map(|r| r.read).any(|read| {
        let register = read.span();
        spans_overlap(&read, span) && (register.start < span.start || register.end() > span.end())
    })
}

fn reads_span(channel: &ResolvedChannel, span: &RegisterSpan) -> bool {
    channel
        .registers
        .iter()
        .filter_map(|r| r.read)
        .any(|r| spans_overlap(&r, span))
}

/// Decodes a channel's value into `text` from the words of all its registers, in order
/// (joined with `;`, as [`ResolvedChannel::decode`] does).
fn decode_words(
    channel: &ResolvedChannel,
    words: &[u16],
    text: &mut String,
) -> Result<Decoded, crate::device::CodecError> {
    let mut rest = words;
    for (position, register) in channel.registers.iter().enumerate() {
        let count = register
            .read
            .map_or(1, |read| usize::from(read.count.max(1)));
        let (part, after) = rest.split_at(count.min(rest.len()));
        rest = after;
        if position > 0 {
            text.push(';');
        }
        match register.codec.decode_into(part, text) {
            Ok(Decoded::Text) => {}
            other => return other,
        }
    }
    Ok(Decoded::Text)
}

fn writes_register(channel: &ResolvedChannel, register_type: RegisterType, address: u16) -> bool {
    channel
        .registers
        .iter()
        .filter_map(|r| r.write.or(r.read))
        .any(|r| r.reg_type == register_type && r.address == address)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TemplateFile;
    use crate::device::{resolve_template_device, Reading};
    use std::collections::HashMap;

    fn relay() -> DeviceModel {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("templates/rtu2mqtt-relay6.json");
        let template = TemplateFile::load(&path).unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({"slave_id": 20})).unwrap();
        DeviceModel::new(Arc::new(device), 0, Repeats::All)
    }

    fn values(out: &[DeviceUpdate]) -> Vec<(String, String, bool)> {
        out.iter()
            .filter_map(|u| match u {
                DeviceUpdate::Value {
                    control_id,
                    value,
                    from_event,
                    ..
                } => Some((control_id.to_string(), value.to_string(), *from_event)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn read_values_become_control_values() {
        let mut model = relay();
        let mut out = Vec::new();
        let span = RegisterSpan::new(RegisterType::Coil, 0, 2);
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![1, 0].into(),
            },
            &mut out,
        );
        assert_eq!(
            values(&out),
            vec![
                ("K1".into(), "1".into(), false),
                ("K2".into(), "0".into(), false)
            ]
        );
        // u32 serial number, big-endian words.
        let mut out = Vec::new();
        let span = RegisterSpan::new(RegisterType::Input, 270, 2);
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![0xFE40, 0x00AC].into(),
            },
            &mut out,
        );
        assert_eq!(
            values(&out),
            vec![("Serial".into(), "4265607340".into(), false)]
        );
    }

    #[test]
    fn event_values_are_published_after_the_packet() {
        let mut model = relay();
        let mut out = Vec::new();
        let event = PortEvent::EventValue {
            device: 0,
            register_type: RegisterType::Input,
            address: 32,
            payload: vec![0x2C, 0x01],
        };
        model.apply(event, &mut out);
        assert!(out.is_empty(), "waits for the rest of the packet");
        model.flush_events(&mut out);
        assert_eq!(
            values(&out),
            vec![("Input 1 counter".into(), "300".into(), true)]
        );
    }

    /// A device that queues its changes reports a short pulse of a coil as two events of one
    /// packet: both values are published, in order, not only the last.
    #[test]
    fn a_pulse_reported_in_one_packet_is_published_as_it_happened() {
        let mut model = relay();
        // Device 20 (0x14), flag 0, 3 events, 15 bytes: coil 0 = 1, coil 1 = 1, coil 0 = 0.
        let published = feed_packet(
            &mut model,
            "14 46 11 00 03 0F 01 01 00 00 01 01 01 00 01 01 01 01 00 00 00",
        );
        assert_eq!(
            published,
            [one("K1", "1"), one("K2", "1"), one("K1", "0")].concat()
        );
        // The next packet holds each coil once: one value each, after the packet.
        let published = feed_packet(
            &mut model,
            "14 46 11 01 02 0A 01 01 00 00 01 01 01 00 01 00",
        );
        assert_eq!(published, [one("K1", "1"), one("K2", "0")].concat());
    }

    fn template_model(template: &str, slave_id: u8) -> DeviceModel {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(format!("templates/{template}.json"));
        let template = TemplateFile::load(&path).unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({ "slave_id": slave_id }))
                .unwrap();
        DeviceModel::new(Arc::new(device), 0, Repeats::All)
    }

    /// Feeds one 0x11 event packet, given as on the wire without its CRC, to the model the way
    /// the port scheduler does, and returns the published values of the controls.
    fn feed_packet(model: &mut DeviceModel, frame_hex: &str) -> Vec<(String, String)> {
        let mut frame = crate::protocol::parse_hex(frame_hex).unwrap();
        let crc = crate::protocol::crc16(&frame);
        frame.extend(crc.to_le_bytes());
        let reply = crate::protocol::Reply::decode(&frame).unwrap();
        let crate::protocol::ReplyBody::Fast {
            reply: crate::protocol::FastReply::Events(packet),
            ..
        } = reply.body
        else {
            panic!("not an event packet: {reply:?}");
        };
        let mut out = Vec::new();
        for event in packet.events {
            let crate::protocol::EventSource::Register(register_type) = event.source else {
                continue;
            };
            model.apply(
                PortEvent::EventValue {
                    device: 0,
                    register_type,
                    address: event.id,
                    payload: event.payload,
                },
                &mut out,
            );
        }
        model.flush_events(&mut out);
        control_values(&out)
    }

    /// The (control, value) of the values in `out`.
    fn control_values(out: &[DeviceUpdate]) -> Vec<(String, String)> {
        values(out)
            .into_iter()
            .map(|(control, value, _)| (control, value))
            .collect()
    }

    fn poll(model: &mut DeviceModel, start: u16, words: &[u16]) -> Vec<(String, String)> {
        let mut out = Vec::new();
        let count = u16::try_from(words.len()).unwrap();
        model.apply(
            PortEvent::Values {
                device: 0,
                span: RegisterSpan::new(RegisterType::Input, start, count),
                values: words.to_vec().into(),
            },
            &mut out,
        );
        control_values(&out)
    }

    /// A read's words reach the channels that use them, wherever they sit in the span; the
    /// words between them, which no channel uses, are not kept and harm nothing.
    #[test]
    fn a_read_with_gaps_fills_each_channel_from_its_own_words() {
        let raw = serde_json::json!({
            "device_type": "gaps",
            "device": {
                "name": "Gaps", "id": "gaps",
                "channels": [
                    {"name": "A", "reg_type": "input", "address": 2},
                    {"name": "B", "reg_type": "input", "address": 5, "format": "u32"},
                    {"name": "C", "reg_type": "holding", "address": 5},
                    {"name": "D", "reg_type": "input", "address": 9}
                ]
            }
        });
        let template = TemplateFile::from_source(crate::config::parse::SourceText::from_text(
            std::path::Path::new("gaps.json"),
            &raw.to_string(),
        ))
        .unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({"slave_id": 1})).unwrap();
        let mut model = DeviceModel::new(Arc::new(device), 0, Repeats::None);
        // Inputs 0..10: A = 2, B = 5/6, D = 9; 0, 1, 3, 4, 7, 8 are nobody's.
        assert_eq!(
            poll(&mut model, 0, &[100, 101, 7, 103, 104, 1, 2, 107, 108, 42]),
            [one("A", "7"), one("B", "65538"), one("D", "42")].concat()
        );
        // The holding register at the same address is another register.
        assert_eq!(poll(&mut model, 5, &[1, 3]), one("B", "65539"));
        // A read that ends inside B does not publish B from one new word and one old: the
        // device may have changed both since (a u32 passing 65535). B's own read does.
        assert_eq!(poll(&mut model, 4, &[0, 2]), vec![]);
        assert_eq!(poll(&mut model, 6, &[4]), vec![]);
        assert_eq!(poll(&mut model, 5, &[2, 4]), one("B", "131076"));
        assert_eq!(poll(&mut model, 9, &[42]), vec![]);
    }

    /// A u32 counter and a channel on its low word read on their own (another period): the
    /// counter passes 65535 between the two reads. The low word's read must not publish the
    /// counter as 0 (old high word, new low word), a value the device never held; the
    /// counter's own read publishes 65536.
    #[test]
    fn a_read_of_one_word_of_a_wider_value_does_not_publish_it() {
        let mut model = model_of_template(serde_json::json!({
            "device_type": "torn",
            "device": {
                "name": "Torn", "id": "torn",
                "channels": [
                    {"name": "Counter", "reg_type": "input", "address": 10, "format": "u32"},
                    {"name": "Low", "reg_type": "input", "address": 11, "read_period_ms": 100}
                ]
            }
        }));
        assert_eq!(
            poll(&mut model, 10, &[0, 0xFFFF]),
            [one("Counter", "65535"), one("Low", "65535")].concat()
        );
        assert_eq!(poll(&mut model, 11, &[0]), one("Low", "0"));
        assert_eq!(poll(&mut model, 10, &[1, 0]), one("Counter", "65536"));
    }

    fn model_of_template(raw: serde_json::Value) -> DeviceModel {
        let template = TemplateFile::from_source(crate::config::parse::SourceText::from_text(
            std::path::Path::new("inline.json"),
            &raw.to_string(),
        ))
        .unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({"slave_id": 1})).unwrap();
        DeviceModel::new(Arc::new(device), 0, Repeats::None)
    }

    /// A press counter at input 10 and a value at 11.
    fn presses() -> DeviceModel {
        model_of_template(serde_json::json!({
            "device_type": "presses",
            "device": {
                "name": "Presses", "id": "presses",
                "channels": [
                    {"name": "Presses", "reg_type": "press_counter", "address": 10, "type": "value"},
                    {"name": "Level", "reg_type": "input", "address": 11, "type": "value"}
                ]
            }
        }))
    }

    /// A Wiren Board device counts button presses again from 0 after a restart: that first 0
    /// is not published (a `whenChanged` rule on the counter would fire by itself after every
    /// bus or power glitch), as wb-mqtt-serial's `DoNotPublishNextZeroPressCounter` holds it
    /// after the device went offline; the next count is published as a change. Other values
    /// are published as ever, and so is a 0 that comes with no restart in between.
    #[test]
    fn a_press_counter_back_at_zero_after_a_restart_is_not_published() {
        let mut model = presses();
        let offline = PortEvent::Offline { device: 0 };
        let online = PortEvent::Online { device: 0 };
        assert_eq!(
            poll(&mut model, 10, &[3, 7]),
            [one("Presses", "3"), one("Level", "7")].concat()
        );
        for (back, level) in [(offline, 1), (PortEvent::Rebooted { device: 0 }, 2)] {
            model.apply(back, &mut Vec::new());
            model.apply(online.clone(), &mut Vec::new());
            assert_eq!(
                poll(&mut model, 10, &[0, level]),
                one("Level", &level.to_string())
            );
            assert_eq!(poll(&mut model, 10, &[0, level]), vec![]);
            assert_eq!(poll(&mut model, 10, &[1, level]), one("Presses", "1"));
        }
        // No restart: a 0 is a value like any other.
        assert_eq!(poll(&mut model, 10, &[0, 2]), one("Presses", "0"));
    }

    /// A write-only control (`pushbutton`, `wo-switch`, a `write_address` alone) gets the value
    /// written once its write is done, as wb-mqtt-serial publishes a register a write set:
    /// homeui shows a wo-switch's state, and a rule on a pushbutton fires.
    #[test]
    fn a_write_only_control_is_published_with_what_was_written() {
        let mut model = model_of_template(serde_json::json!({
            "device_type": "write-only",
            "device": {
                "name": "Write only", "id": "wo",
                "channels": [
                    {"name": "Reset", "reg_type": "holding", "address": 10, "type": "pushbutton"},
                    {"name": "Relay", "reg_type": "coil", "address": 5, "type": "wo-switch"},
                    {"name": "Level", "reg_type": "holding", "address": 20, "type": "value"},
                    {"name": "Speed", "reg_type": "holding", "write_address": 30, "type": "value", "format": "u32"}
                ]
            }
        }));
        let mut written = |control: &str, payload: &str| write_done(&mut model, control, payload);
        assert_eq!(written("Reset", "1"), one("Reset", "1"));
        assert_eq!(
            written("Reset", "1"),
            one("Reset", "1"),
            "a pushbutton every time"
        );
        assert_eq!(written("Relay", "1"), one("Relay", "1"));
        assert_eq!(written("Relay", "0"), one("Relay", "0"));
        assert_eq!(written("Speed", "70000"), one("Speed", "70000"));
        // A control that reads its register: from the words written, as before.
        assert_eq!(written("Level", "5"), one("Level", "5"));
    }

    /// Writes `payload` to `control` as the scheduler reports a write done (done, then the
    /// words written), and returns the values published.
    fn write_done(model: &mut DeviceModel, control: &str, payload: &str) -> Vec<(String, String)> {
        let mut out = Vec::new();
        let writes = model.take_write(control, payload, &mut out).unwrap();
        for write in writes {
            model.apply(
                PortEvent::WriteDone {
                    device: 0,
                    register_type: write.register_type,
                    address: write.address,
                },
                &mut out,
            );
            let count = u16::try_from(write.values.len()).unwrap();
            model.apply(
                PortEvent::Values {
                    device: 0,
                    span: RegisterSpan::new(write.register_type, write.address, count),
                    values: write.values.clone().into(),
                },
                &mut out,
            );
        }
        control_values(&out)
    }

    /// Write-only controls that share a register (three command pushbuttons with their own
    /// `on_value`, write-only bit fields of one command register) or take several registers:
    /// a write publishes the control written, once all its registers are, and no other.
    #[test]
    fn a_write_publishes_only_the_write_only_control_written() {
        let mut model = model_of_template(serde_json::json!({
            "device_type": "commands",
            "device": {
                "name": "Commands", "id": "commands",
                "channels": [
                    {"name": "Open", "reg_type": "holding", "address": 10, "type": "pushbutton", "on_value": 1},
                    {"name": "Close", "reg_type": "holding", "address": 10, "type": "pushbutton", "on_value": 2},
                    {"name": "Start", "reg_type": "holding", "write_address": "40:0:1", "type": "pushbutton"},
                    {"name": "Mode", "reg_type": "holding", "write_address": "40:4:4", "type": "value"},
                    {"name": "Pair", "type": "value", "consists_of": [
                        {"reg_type": "holding", "write_address": 30},
                        {"reg_type": "holding", "write_address": 31}
                    ]}
                ]
            }
        }));
        assert_eq!(write_done(&mut model, "Close", "1"), one("Close", "1"));
        assert_eq!(write_done(&mut model, "Open", "1"), one("Open", "1"));
        assert_eq!(write_done(&mut model, "Start", "1"), one("Start", "1"));
        assert_eq!(write_done(&mut model, "Mode", "5"), one("Mode", "5"));
        assert_eq!(write_done(&mut model, "Pair", "1;2"), one("Pair", "1;2"));
    }

    /// The hold of a press counter's next 0 goes over to the model that replaces this one at a
    /// reload: by `known_offline` for a device offline then, and by
    /// `holding_press_counters` for one that came back with a counter still held. A counter
    /// never published is published at 0 when its device comes back (it has no value to keep).
    #[test]
    fn a_press_counter_hold_survives_a_reload() {
        let mut offline = presses().known_offline();
        offline.apply(PortEvent::Online { device: 0 }, &mut Vec::new());
        assert_eq!(poll(&mut offline, 10, &[0, 7]), one("Level", "7"));
        assert_eq!(offline.held_press_counters(), ["Presses"]);
        let mut rebuilt = presses().holding_press_counters(&offline.held_press_counters());
        assert_eq!(poll(&mut rebuilt, 10, &[0, 7]), one("Level", "7"));
        assert_eq!(poll(&mut rebuilt, 10, &[2, 7]), one("Presses", "2"));
        assert!(rebuilt.held_press_counters().is_empty());

        let mut late = presses();
        late.apply(PortEvent::Offline { device: 0 }, &mut Vec::new());
        late.apply(PortEvent::Online { device: 0 }, &mut Vec::new());
        assert_eq!(
            poll(&mut late, 10, &[0, 7]),
            [one("Presses", "0"), one("Level", "7")].concat()
        );
    }

    fn one(control: &str, value: &str) -> Vec<(String, String)> {
        vec![(control.to_owned(), value.to_owned())]
    }

    /// Issue 15 defect 1: a u32 counter at input 60/61 holds 0, 5 (= 5); the device reports
    /// each register by its own event (2-byte payloads, little-endian as the protocol says).
    #[test]
    fn an_event_for_one_word_of_a_wide_value_keeps_the_other_word() {
        let mut model = template_model("rtu2mqtt-counter8", 20);
        assert_eq!(poll(&mut model, 60, &[0, 5]), one("Input 1 counter", "5"));
        // 60 = 1: device 20, 0x11, flag 1, 1 event, 6 data bytes: len 2, input, id 60, value 1.
        // The value's first word alone: 61 may have changed with it, so nothing is published
        // until the value is read (the scheduler reads it at once), never 1:5 on trust.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 01 01 06 02 04 003C 0100"),
            Vec::new()
        );
        assert_eq!(
            poll(&mut model, 60, &[1, 5]),
            one("Input 1 counter", "65541")
        );
        // 61 = 7, reported by an event of its own (a device that makes each register an event
        // source): 60 may have changed with it, so it is not joined with 60 as last read
        // either; the read the scheduler makes at once publishes the value.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 00 01 06 02 04 003D 0700"),
            Vec::new()
        );
        assert_eq!(
            poll(&mut model, 60, &[1, 7]),
            one("Input 1 counter", "65543")
        );
        // A device that reports the whole value at its first register (4 bytes) sets both.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 01 01 08 04 04 003C 0900 0200"),
            one("Input 1 counter", "131081")
        );
    }

    /// An event's payload is the value itself, little-endian (the protocol's §6; wb-mqtt-serial
    /// copies it into the register's value), whatever order the device keeps its words in: a
    /// counter kept low word first publishes what one kept high word first does, and its
    /// registers hold what a read would bring. (Found by an independent device stack,
    /// tests/interop_fast.rs: the words were stored high word first whatever the order.)
    #[test]
    fn a_wide_event_is_the_value_whatever_the_word_order() {
        use crate::config::format::WordOrder;
        for (word_order, registers) in [
            (WordOrder::BigEndian, [4, 6]),
            (WordOrder::LittleEndian, [6, 4]),
        ] {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("templates/rtu2mqtt-counter8.json");
            let template = TemplateFile::load(&path).unwrap();
            let mut device =
                resolve_template_device(&template, &serde_json::json!({ "slave_id": 20 })).unwrap();
            let mut channels: Vec<ResolvedChannel> = device.channels.iter().cloned().collect();
            for channel in &mut channels {
                for register in &mut channel.registers {
                    register.codec.word_order = word_order;
                }
            }
            device.channels = channels.into();
            let mut model = DeviceModel::new(Arc::new(device), 0, Repeats::All);
            // Input 60/61 = 262150 (0x0004_0006): payload 06 00 04 00.
            assert_eq!(
                feed_packet(&mut model, "14 46 11 01 01 08 04 04 003C 0600 0400"),
                one("Input 1 counter", "262150"),
                "{word_order:?}"
            );
            assert_eq!(
                poll(&mut model, 60, &registers),
                one("Input 1 counter", "262150"),
                "{word_order:?}: the registers as a read brings them"
            );
        }
    }

    /// Issue 15 defect 1: illuminance, u32 x 0.01 at input 9/10, polled as 655.36.
    #[test]
    fn an_event_for_the_first_word_of_a_scaled_value_keeps_the_second() {
        let mut model = template_model("rtu2mqtt-climate", 20);
        assert_eq!(poll(&mut model, 9, &[1, 0]), one("Illuminance", "655.36"));
        // Register 9 reported (1) alone: never 0.01; the value waits for its read.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 01 01 06 02 04 0009 0100"),
            Vec::new()
        );
        assert_eq!(poll(&mut model, 9, &[1, 0]), one("Illuminance", "655.36"));
        // Register 10 becomes 1, reported alone: never 0.01, and not joined with 9 as last
        // read either (9 may have changed with it); the read publishes 655.37.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 00 01 06 02 04 000A 0100"),
            Vec::new()
        );
        assert_eq!(poll(&mut model, 9, &[1, 1]), one("Illuminance", "655.37"));
    }

    /// Both words in one packet (a carry from 0x0000FFFF to 0x00010000): one publication, of
    /// the new value, never the half-updated 0x0001FFFF.
    #[test]
    fn words_of_one_packet_are_published_together() {
        let mut model = template_model("rtu2mqtt-counter8", 20);
        assert_eq!(
            poll(&mut model, 60, &[0, 0xFFFF]),
            one("Input 1 counter", "65535")
        );
        assert_eq!(
            feed_packet(
                &mut model,
                "14 46 11 01 02 0C 02 04 003C 0100 02 04 003D 0000"
            ),
            one("Input 1 counter", "65536")
        );
    }

    /// A word never read (events before the first poll, or after a restart): nothing is
    /// published until the read brings the other word.
    #[test]
    fn a_value_with_an_unknown_word_waits_for_its_read() {
        let mut model = template_model("rtu2mqtt-counter8", 20);
        assert!(feed_packet(&mut model, "14 46 11 01 01 06 02 04 003C 0100").is_empty());
        assert_eq!(
            poll(&mut model, 60, &[1, 5]),
            one("Input 1 counter", "65541")
        );
        let mut out = Vec::new();
        model.apply(PortEvent::Rebooted { device: 0 }, &mut out);
        assert!(
            feed_packet(&mut model, "14 46 11 00 01 06 02 04 003D 0700").is_empty(),
            "words from before the restart are not joined with new ones"
        );
        // An event in the same packet as the restart report is not joined with them either.
        let mut out = Vec::new();
        model.apply(
            PortEvent::EventValue {
                device: 0,
                register_type: RegisterType::Input,
                address: 61,
                payload: vec![8, 0],
            },
            &mut out,
        );
        model.apply(PortEvent::Rebooted { device: 0 }, &mut out);
        model.flush_events(&mut out);
        assert!(values(&out).is_empty(), "{out:?}");
        assert_eq!(poll(&mut model, 60, &[0, 7]), one("Input 1 counter", "7"));
    }

    #[test]
    fn read_error_is_cleared_before_the_next_value() {
        let mut model = relay();
        let span = RegisterSpan::new(RegisterType::Coil, 0, 1);
        let mut out = Vec::new();
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span,
                unsupported: false,
            },
            &mut out,
        );
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span,
                unsupported: false,
            },
            &mut out,
        );
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![1].into(),
            },
            &mut out,
        );
        let kinds: Vec<String> = out
            .iter()
            .map(|u| match u {
                DeviceUpdate::ControlError {
                    control_id, errors, ..
                } => format!("{control_id} error '{errors}'"),
                DeviceUpdate::Value {
                    control_id, value, ..
                } => format!("{control_id} = {value}"),
                other => format!("{other:?}"),
            })
            .collect();
        assert_eq!(kinds, ["K1 error 'r'", "K1 error ''", "K1 = 1"]);
    }

    /// Issue 15 defect 9: a dead device sets `r` on every readable control at once.
    #[test]
    fn offline_sets_r_on_every_control_together() {
        let mut model = relay();
        let mut out = Vec::new();
        model.apply(PortEvent::Offline { device: 0 }, &mut out);
        let readable = model.device.channels.iter().filter(|c| c.is_read()).count();
        let flagged = out
            .iter()
            .filter(|u| matches!(u, DeviceUpdate::ControlError { errors, .. } if errors.read))
            .count();
        assert!(readable > 5);
        assert_eq!(flagged, readable);
    }

    /// A model that replaces one that knew its device offline (a reload restarted the port)
    /// starts with the `r` the MQTT side kept on every readable control, and clears it at the
    /// control's first good read, before its value; a failure meanwhile reports nothing new.
    /// (A model that started clear reported no `r` to clear, and the `r` stayed.)
    #[test]
    fn a_model_known_offline_clears_the_kept_r_at_the_first_good_read() {
        let mut old = relay();
        let mut out = Vec::new();
        assert!(!old.is_offline());
        old.apply(PortEvent::Offline { device: 0 }, &mut out);
        assert!(old.is_offline());
        old.apply(PortEvent::Online { device: 0 }, &mut out);
        assert!(!old.is_offline());

        let mut model = relay().known_offline();
        assert!(model.is_offline());
        let span = RegisterSpan::new(RegisterType::Coil, 0, 1);
        let mut out = Vec::new();
        model.apply(PortEvent::Offline { device: 0 }, &mut out);
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span,
                unsupported: false,
            },
            &mut out,
        );
        assert!(
            !out.iter()
                .any(|u| matches!(u, DeviceUpdate::ControlError { .. })),
            "{out:?}"
        );
        let mut out = Vec::new();
        model.apply(PortEvent::Online { device: 0 }, &mut out);
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![1].into(),
            },
            &mut out,
        );
        let kinds: Vec<String> = out
            .iter()
            .filter_map(|u| match u {
                DeviceUpdate::ControlError {
                    control_id, errors, ..
                } => Some(format!("{control_id} error '{errors}'")),
                DeviceUpdate::Value {
                    control_id, value, ..
                } => Some(format!("{control_id} = {value}")),
                _ => None,
            })
            .collect();
        assert_eq!(kinds, ["K1 error ''", "K1 = 1"]);
        assert!(!model.is_offline());
    }

    /// A model of one device with `channel` only, writing holding register 0.
    fn model_of(mut channel: ResolvedChannel) -> DeviceModel {
        let holding = crate::device::RegisterRef {
            reg_type: RegisterType::Holding,
            address: 0,
            count: 1,
            bit_shift: 0,
            bit_width: 0,
        };
        for register in &mut channel.registers {
            register.write = Some(holding);
        }
        let mut device = (*relay().device).clone();
        device.channels = vec![channel].into();
        DeviceModel::new(Arc::new(device), 0, Repeats::All)
    }

    fn accepts(channel: &ResolvedChannel, payload: &str) -> bool {
        model_of(channel.clone())
            .write(&channel.id, payload)
            .is_ok()
    }

    /// A switch takes any number, as in wb-mqtt-serial (a multi-position switch); no words.
    #[test]
    fn switch_takes_numbers() {
        let k1 = crate::mqtt::layout::tests::channel("K1", "switch");
        let model = model_of(k1);
        assert_eq!(model.write("K1", " 0\n").unwrap()[0].values, [0]);
        assert_eq!(model.write("K1", "3").unwrap()[0].values, [3]);
        for bad in ["on", "", "true", "\u{FFFD}"] {
            assert!(model.write("K1", bad).is_err(), "{bad:?}");
        }
        assert_eq!(model.write("K1", "1\u{FFFD}"), Err(WriteRejected::NotText));
    }

    /// A range takes a fraction (scaled registers publish them), within its limits.
    #[test]
    fn range_respects_limits() {
        let mut level = crate::mqtt::layout::tests::channel("Level", "range");
        level.min = Some(0.0);
        level.max = Some(100.0);
        assert!(accepts(&level, "42"));
        assert!(!accepts(&level, "101"));
        assert!(!accepts(&level, "-1"));
        assert!(!accepts(&level, "half"));
        let refusal = |level: &ResolvedChannel, text: &str| match model_of(level.clone())
            .write("Level", text)
        {
            Err(WriteRejected::BadValue(why)) => why,
            other => panic!("{text}: {other:?}"),
        };
        assert_eq!(
            refusal(&level, "101"),
            "101 is outside this control's limits: allowed 0 … 100"
        );
        let mut only_max = level.clone();
        only_max.min = None;
        assert_eq!(
            refusal(&only_max, "150"),
            "150 is outside this control's limits: at most 100"
        );
        let mut only_min = level.clone();
        only_min.max = None;
        assert_eq!(
            refusal(&only_min, "-3"),
            "-3 is outside this control's limits: at least 0"
        );
        level.registers[0].codec.scale = 0.01;
        assert_eq!(
            model_of(level).write("Level", "22.5").unwrap()[0].values,
            [2250]
        );
    }

    #[test]
    fn value_must_be_a_number_in_format_range() {
        let setpoint = crate::mqtt::layout::tests::channel("Setpoint", "value");
        assert!(accepts(&setpoint, "12"));
        assert!(!accepts(&setpoint, "abc"));
        assert!(!accepts(&setpoint, "NaN"));
        // u16 cannot hold it.
        assert!(matches!(
            model_of(setpoint).write("Setpoint", "70000"),
            Err(WriteRejected::BadValue(_))
        ));
    }

    /// Review F4: wb-mqtt-serial reads an integer `/on` text after `0x` (or `0X`) in base 16
    /// (`FromScaledTextValue`), whatever the control type; the limits still apply.
    #[test]
    fn a_hexadecimal_payload_is_written_as_wb_mqtt_serial_writes_it() {
        let k1 = crate::mqtt::layout::tests::channel("K1", "switch");
        let model = model_of(k1);
        assert_eq!(model.write("K1", "0x1").unwrap()[0].values, [1]);
        assert_eq!(model.write("K1", " 0X00FF ").unwrap()[0].values, [255]);
        for bad in ["0x", "0xG1", "x1", "0x1.5"] {
            assert!(model.write("K1", bad).is_err(), "{bad:?}");
        }
        let mut level = crate::mqtt::layout::tests::channel("Level", "range");
        level.max = Some(100.0);
        assert!(accepts(&level, "0x64"));
        assert!(!accepts(&level, "0x65"), "over max in hex");
        let setpoint = crate::mqtt::layout::tests::channel("Setpoint", "value");
        assert!(matches!(
            model_of(setpoint).write("Setpoint", "0x10000"),
            Err(WriteRejected::BadValue(_))
        ));
    }

    /// A `text` payload is written as received, spaces included, as wb-mqtt-serial writes it;
    /// the string register is padded with zeros after it.
    #[test]
    fn a_text_payload_is_written_as_received() {
        let mut text = crate::mqtt::layout::tests::channel("Text", "text");
        text.registers[0].codec = crate::device::codec::ValueCodec {
            word_count: 6,
            ..crate::device::codec::ValueCodec::plain(crate::config::format::RegisterFormat::String)
        };
        let mut model = model_of(text);
        let words = |model: &DeviceModel, payload: &str| -> Vec<u16> {
            model.write("Text", payload).unwrap()[0].values.clone()
        };
        let spaced: Vec<u16> = "  ab \n".bytes().map(u16::from).collect();
        assert_eq!(words(&model, "  ab \n"), spaced);
        assert_eq!(words(&model, "   "), [0x20, 0x20, 0x20, 0, 0, 0]);
        // A one-character register takes the first character as sent, a space too.
        let mut char8 = crate::mqtt::layout::tests::channel("Char", "text");
        char8.registers[0].codec =
            crate::device::codec::ValueCodec::plain(crate::config::format::RegisterFormat::Char8);
        model = model_of(char8);
        assert_eq!(model.write("Char", " ").unwrap()[0].values, [0x20]);
        assert_eq!(model.write("Char", "!").unwrap()[0].values, [0x21]);
    }

    #[test]
    fn rgb_needs_three_parts() {
        let mut rgb = crate::mqtt::layout::tests::channel("RGB", "rgb");
        let register = rgb.registers[0].clone();
        rgb.registers = vec![register.clone(), register.clone(), register];
        assert!(accepts(&rgb, "255;0;10"));
        assert!(!accepts(&rgb, "255;0"));
        assert!(!accepts(&rgb, "256;0;0"));
    }

    #[test]
    fn huge_payloads_are_refused() {
        let text = crate::mqtt::layout::tests::channel("Text", "text");
        let refused = model_of(text)
            .write("Text", &"a".repeat(MAX_PAYLOAD + 1))
            .unwrap_err();
        assert_eq!(
            refused.to_string(),
            "the payload is 4097 bytes long; a control takes at most 4096"
        );
    }

    /// A refused payload sets `w` once; the next successful write clears it.
    #[test]
    fn a_refused_write_sets_w_until_a_write_succeeds() {
        let mut model = relay();
        let mut out = Vec::new();
        assert!(model.take_write("K1", "on", &mut out).is_err());
        assert!(model.take_write("K1", "on", &mut out).is_err());
        model.apply(
            PortEvent::WriteDone {
                device: 0,
                register_type: RegisterType::Coil,
                address: 0,
            },
            &mut out,
        );
        let flags: Vec<String> = out
            .iter()
            .filter_map(|u| match u {
                DeviceUpdate::ControlError { errors, .. } => Some(errors.to_string()),
                _ => None,
            })
            .collect();
        assert_eq!(flags, ["w", ""]);
    }

    /// Issue 16: the model tells a change from a repeat, for every sink.
    #[test]
    fn values_say_whether_they_changed() {
        let mut model = relay();
        let span = RegisterSpan::new(RegisterType::Coil, 0, 1);
        let mut changes = Vec::new();
        for word in [1, 1, 0] {
            let mut out = Vec::new();
            model.apply(
                PortEvent::Values {
                    device: 0,
                    span,
                    values: vec![word].into(),
                },
                &mut out,
            );
            changes.extend(out.iter().filter_map(|u| match u {
                DeviceUpdate::Value { changed, .. } => Some(*changed),
                _ => None,
            }));
        }
        assert_eq!(changes, [true, false, true]);
    }

    /// A small deterministic generator for the randomized tests.
    struct Random(u64);

    impl Random {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        fn below(&mut self, bound: u64) -> u64 {
            self.next() % bound.max(1)
        }
    }

    const TEMPLATES: [&str; 6] = [
        "rtu2mqtt-climate",
        "rtu2mqtt-counter8",
        "rtu2mqtt-dimmer",
        "rtu2mqtt-energy-meter",
        "rtu2mqtt-generic",
        "rtu2mqtt-relay6",
    ];

    /// The channel index finds the channels that the scan of every channel (`reads_span`)
    /// finds, in the same order, for random spans around every template's registers (empty,
    /// partly overlapping and past-65535 spans included) and on random channel lists.
    #[test]
    fn the_channel_index_finds_what_the_scan_of_every_channel_finds() {
        let mut random = Random(0x2545_F491_4F6C_DD1D);
        let mut devices: Vec<Arc<ResolvedDevice>> = TEMPLATES
            .iter()
            .map(|template| Arc::clone(&template_model(template, 20).device))
            .collect();
        // Random lists: overlapping registers of every type, bits, wide values, the address
        // space's end.
        for _ in 0..20 {
            let mut device = (*devices[0]).clone();
            let template_channel = device.channels[0].clone();
            let channels = device.channels.make_mut();
            channels.clear();
            for number in 0..random.below(40) + 1 {
                let mut channel = template_channel.clone();
                channel.id = format!("C{number}");
                for register in &mut channel.registers {
                    let register_type = [
                        RegisterType::Coil,
                        RegisterType::DiscreteInput,
                        RegisterType::Holding,
                        RegisterType::Input,
                    ][random.below(4) as usize];
                    let address = if random.below(8) == 0 {
                        u16::MAX - random.below(4) as u16
                    } else {
                        random.below(64) as u16
                    };
                    register.read = (random.below(10) > 0).then_some(crate::device::RegisterRef {
                        reg_type: register_type,
                        address,
                        count: random.below(5) as u16,
                        bit_shift: 0,
                        bit_width: 0,
                    });
                }
                channels.push(channel);
            }
            devices.push(Arc::new(device));
        }
        let mut found = Vec::new();
        let mut spans = 0;
        for device in &devices {
            let model = DeviceModel::new(Arc::clone(device), 0, Repeats::All);
            let mut reads = read_spans(device);
            reads.sort_by_key(|r| (r.register_type, r.start));
            // Searches start from where the last ended; half of the spans follow each other in
            // address order, as a read of many values arrives, the others jump anywhere.
            let mut hint = 0;
            let mut next_read = 0;
            for _ in 0..400 {
                let in_order = random.below(2) == 0;
                let at = if in_order {
                    next_read
                } else {
                    random.below(reads.len() as u64) as usize
                };
                next_read = (at + 1) % reads.len().max(1);
                let around = reads.get(at);
                let register_type = around.map_or(RegisterType::Holding, |r| r.register_type);
                let base = around.map_or(0, |r| r.start);
                let start = base.saturating_sub(random.below(4) as u16).saturating_add(
                    if random.below(2) == 0 {
                        random.below(4) as u16
                    } else {
                        0
                    },
                );
                let count = random.below(70) as u16;
                let span = match around {
                    Some(&read) if in_order => read,
                    _ => RegisterSpan::new(register_type, start, count),
                };
                let scanned: Vec<usize> = (0..device.channels.len())
                    .filter(|&i| reads_span(&device.channels[i], &span))
                    .collect();
                model.channel_index.readers_of(&span, &mut found, &mut hint);
                assert_eq!(found, scanned, "{span:?} on {}", device.id);
                spans += 1;
            }
        }
        assert_eq!(spans, 26 * 400);
    }

    /// Devices of one channel list share one index (and its control ids); another list gets
    /// its own.
    #[test]
    fn devices_of_one_channel_list_share_its_index() {
        let mut indexes = ChannelIndexes::default();
        let device = (*template_model("rtu2mqtt-relay6", 20).device).clone();
        let first = DeviceModel::sharing(Arc::new(device.clone()), 0, Repeats::All, &mut indexes);
        let mut other = device.clone();
        other.id = "relay6_21".into();
        let second = DeviceModel::sharing(Arc::new(other.clone()), 1, Repeats::All, &mut indexes);
        assert!(Arc::ptr_eq(&first.channel_index, &second.channel_index));
        other.channels.make_mut()[0].id = "K1'".into();
        let third = DeviceModel::sharing(Arc::new(other), 2, Repeats::All, &mut indexes);
        assert!(!Arc::ptr_eq(&first.channel_index, &third.channel_index));
        assert_eq!(&*third.channel_index.control_ids[0], "K1'");
        // Built without the builder's cache: an index of its own, no global state.
        let alone = DeviceModel::new(Arc::new(device), 3, Repeats::All);
        assert!(!Arc::ptr_eq(&first.channel_index, &alone.channel_index));
        drop((first, second));
        assert_eq!(indexes.0.iter().filter(|i| i.strong_count() > 0).count(), 1);
    }

    /// Random reads of every template publish, for each channel whose values the read holds
    /// whole (a value read only in part waits for its own read), what
    /// `ResolvedChannel::decode` makes of the channel's words, and say whether it changed;
    /// a value read again is the same shared text.
    /// The register spans `device`'s channels read.
    fn read_spans(device: &ResolvedDevice) -> Vec<RegisterSpan> {
        device
            .channels
            .iter()
            .flat_map(|c| c.registers.iter().filter_map(|r| r.read))
            .map(|r| r.span())
            .collect()
    }

    #[test]
    fn read_values_are_what_the_channel_decodes() {
        let mut random = Random(0x9E37_79B9_7F4A_7C15);
        for template in TEMPLATES {
            let mut model = template_model(template, 20);
            let device = Arc::clone(&model.device);
            let mut words: HashMap<(RegisterType, u16), u16> = HashMap::new();
            let mut last: HashMap<String, Arc<str>> = HashMap::new();
            let reads = read_spans(&device);
            for _ in 0..300 {
                let around = reads[random.below(reads.len() as u64) as usize];
                let span = RegisterSpan::new(
                    around.register_type,
                    around.start.saturating_sub(random.below(3) as u16),
                    around.count + random.below(6) as u16,
                );
                let values: Vec<u16> = (0..span.count)
                    .map(|_| match random.below(4) {
                        0 => 0,
                        1 => 1,
                        2 => 0xFFFF,
                        _ => random.next() as u16,
                    })
                    .map(|word| {
                        if around.register_type.is_bit() {
                            word & 1
                        } else {
                            word
                        }
                    })
                    .collect();
                for (offset, value) in values.iter().enumerate() {
                    words.insert((span.register_type, span.start + offset as u16), *value);
                }
                let mut out = Vec::new();
                model.apply(
                    PortEvent::Values {
                        device: 0,
                        span,
                        values: values.into(),
                    },
                    &mut out,
                );
                let mut expected = Vec::new();
                for channel in device
                    .channels
                    .iter()
                    .filter(|c| reads_span(c, &span) && !covers_in_part(c, &span))
                {
                    let parts: Option<Vec<Vec<u16>>> = channel
                        .registers
                        .iter()
                        .map(|register| {
                            let read = register.read?;
                            (0..read.count.max(1))
                                .map(|i| words.get(&(read.reg_type, read.address + i)).copied())
                                .collect()
                        })
                        .collect();
                    let Some(parts) = parts else { continue };
                    let parts: Vec<&[u16]> = parts.iter().map(Vec::as_slice).collect();
                    if let Ok(Reading::Value(text)) = channel.decode(&parts) {
                        expected.push((channel.id.clone(), text));
                    }
                }
                let published: Vec<(String, String)> = out
                    .iter()
                    .filter_map(|u| match u {
                        DeviceUpdate::Value {
                            device_id,
                            control_id,
                            value,
                            changed,
                            from_event: false,
                        } => {
                            assert_eq!(&**device_id, device.id);
                            let before = last.insert(control_id.to_string(), Arc::clone(value));
                            assert_eq!(
                                *changed,
                                before.as_deref() != Some(&**value),
                                "{template} {control_id}"
                            );
                            if let (false, Some(before)) = (*changed, before) {
                                assert!(Arc::ptr_eq(&before, value), "a repeat is not copied");
                            }
                            Some((control_id.to_string(), value.to_string()))
                        }
                        _ => None,
                    })
                    .collect();
                assert_eq!(published, expected, "{template} {span:?}");
            }
        }
    }

    #[test]
    fn writes_are_encoded_and_checked() {
        let model = relay();
        assert_eq!(
            model.write("K3", "1"),
            Ok(vec![RegisterWrite {
                device: 0,
                register_type: RegisterType::Coil,
                address: 2,
                values: vec![1],
                force_multiple: false,
                one_by_one: false,
                defined: Vec::new(),
            }])
        );
        assert!(matches!(
            model.write("K3", "on"),
            Err(WriteRejected::BadFormat { .. })
        ));
        assert_eq!(
            model.write("Serial", "1"),
            Err(WriteRejected::ReadOnly("Serial".into()))
        );
        assert_eq!(
            model.write("nope", "1"),
            Err(WriteRejected::UnknownControl("nope".into()))
        );
    }

    /// `device` with its first channel made a pushbutton, modelled reporting `repeats`.
    fn with_pushbutton(device: &ResolvedDevice, repeats: Repeats) -> DeviceModel {
        let mut device = device.clone();
        device.channels.make_mut()[0].control_type = "pushbutton".into();
        DeviceModel::new(Arc::new(device), 0, repeats)
    }

    fn read_coils(model: &mut DeviceModel, words: &[u16]) -> Vec<DeviceUpdate> {
        let mut out = Vec::new();
        model.apply(
            PortEvent::Values {
                device: 0,
                span: RegisterSpan::new(RegisterType::Coil, 0, words.len() as u16),
                values: words.to_vec().into(),
            },
            &mut out,
        );
        out
    }

    /// (control, value, changed) of every value update.
    fn reported(out: &[DeviceUpdate]) -> Vec<(String, String, bool)> {
        out.iter()
            .filter_map(|u| match u {
                DeviceUpdate::Value {
                    control_id,
                    value,
                    changed,
                    ..
                } => Some((control_id.to_string(), value.to_string(), *changed)),
                _ => None,
            })
            .collect()
    }

    fn report(control: &str, value: &str, changed: bool) -> (String, String, bool) {
        (control.to_owned(), value.to_owned(), changed)
    }

    /// Issue 14: with changes only asked for, a read that repeats a value reports nothing for
    /// it; asked for every value, the repeat comes (marked unchanged).
    #[test]
    fn a_repeated_value_is_reported_only_when_the_sinks_ask_for_repeats() {
        let device = Arc::clone(&relay().device);
        let mut changes_only = DeviceModel::new(Arc::clone(&device), 0, Repeats::None);
        let mut every_value = DeviceModel::new(device, 0, Repeats::All);
        for model in [&mut changes_only, &mut every_value] {
            assert_eq!(
                reported(&read_coils(model, &[1, 0])),
                [report("K1", "1", true), report("K2", "0", true)]
            );
        }
        assert!(read_coils(&mut changes_only, &[1, 0]).is_empty());
        assert_eq!(
            reported(&read_coils(&mut changes_only, &[1, 1])),
            [report("K2", "1", true)]
        );
        assert_eq!(
            reported(&read_coils(&mut every_value, &[1, 0])),
            [report("K1", "1", false), report("K2", "0", false)]
        );
    }

    /// A pushbutton's every value is reported, whatever the sinks asked for.
    #[test]
    fn a_pushbutton_reports_every_value() {
        let mut model = with_pushbutton(&relay().device, Repeats::None);
        assert_eq!(
            reported(&read_coils(&mut model, &[1, 0])),
            [report("K1", "1", true), report("K2", "0", true)]
        );
        assert_eq!(
            reported(&read_coils(&mut model, &[1, 0])),
            [report("K1", "1", false)]
        );
    }

    /// The stdout sink's repeats: every event value, not a read repeating one.
    #[test]
    fn event_repeats_are_reported_when_asked_for_and_read_repeats_are_not() {
        let mut model = template_model("rtu2mqtt-counter8", 20);
        model.repeats = Repeats::Events;
        assert_eq!(poll(&mut model, 60, &[0, 5]), one("Input 1 counter", "5"));
        assert_eq!(poll(&mut model, 60, &[0, 5]), Vec::new());
        // An event repeating the value: the same value, reported as an event value.
        assert_eq!(
            feed_packet(&mut model, "14 46 11 00 01 08 04 04 003C 0500 0000"),
            one("Input 1 counter", "5")
        );
    }

    /// A read that fails sets `r`; the next good read clears it even though it repeats the
    /// value (which, asked for changes only, is not reported again).
    #[test]
    fn r_is_cleared_by_a_good_read_that_repeats_the_value() {
        let mut model = DeviceModel::new(Arc::clone(&relay().device), 0, Repeats::None);
        assert_eq!(
            reported(&read_coils(&mut model, &[1])),
            [report("K1", "1", true)]
        );
        let mut out = Vec::new();
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span: RegisterSpan::new(RegisterType::Coil, 0, 1),
                unsupported: false,
            },
            &mut out,
        );
        let flags = |out: &[DeviceUpdate]| -> Vec<(String, String)> {
            out.iter()
                .filter_map(|u| match u {
                    DeviceUpdate::ControlError {
                        control_id, errors, ..
                    } => Some((control_id.clone(), errors.to_string())),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(flags(&out), [("K1".to_owned(), "r".to_owned())]);
        let out = read_coils(&mut model, &[1]);
        assert_eq!(flags(&out), [("K1".to_owned(), String::new())]);
        assert!(reported(&out).is_empty(), "{out:?}");
    }

    /// For every template and every choice of repeats, on random reads (mostly repeating
    /// words), events, failed reads, restarts and lost devices: a model reports exactly what a
    /// model reporting every value and decoding every value afresh (as before issue 14)
    /// reports, less the repeats not asked for; error flags alike.
    #[test]
    fn a_model_reports_what_every_value_gives_less_the_repeats_not_asked_for() {
        let mut random = Random(0xD1B5_4A32_D192_ED03);
        let mut devices: Vec<Arc<ResolvedDevice>> = TEMPLATES
            .iter()
            .map(|template| Arc::clone(&template_model(template, 20).device))
            .collect();
        devices.push(Arc::clone(
            &with_pushbutton(&relay().device, Repeats::All).device,
        ));
        let mut repeats_seen = 0;
        for device in &devices {
            for repeats in [Repeats::None, Repeats::Events, Repeats::All] {
                let mut all = DeviceModel::new(Arc::clone(device), 0, Repeats::All);
                let mut asked = DeviceModel::new(Arc::clone(device), 0, repeats);
                let reads = read_spans(device);
                for _ in 0..400 {
                    let around = reads[random.below(reads.len() as u64) as usize];
                    let word = |random: &mut Random| -> u16 {
                        let word = match random.below(8) {
                            0 => 0xFFFF,
                            1 => random.next() as u16,
                            other => (other % 2) as u16,
                        };
                        if around.register_type.is_bit() {
                            word & 1
                        } else {
                            word
                        }
                    };
                    let events: Vec<PortEvent> = match random.below(10) {
                        0..=5 => {
                            let span = RegisterSpan::new(
                                around.register_type,
                                around.start.saturating_sub(random.below(2) as u16),
                                around.count + random.below(3) as u16,
                            );
                            let values: Vec<u16> =
                                (0..span.count).map(|_| word(&mut random)).collect();
                            vec![PortEvent::Values {
                                device: 0,
                                span,
                                values: values.into(),
                            }]
                        }
                        6 | 7 => (0..=random.below(2))
                            .map(|_| {
                                let [low, high] = word(&mut random).to_le_bytes();
                                PortEvent::EventValue {
                                    device: 0,
                                    register_type: around.register_type,
                                    address: around.start + random.below(2) as u16,
                                    payload: vec![low, high],
                                }
                            })
                            .collect(),
                        8 => vec![PortEvent::ReadFailed {
                            device: 0,
                            span: around,
                            unsupported: false,
                        }],
                        _ => vec![match random.below(3) {
                            0 => PortEvent::Rebooted { device: 0 },
                            1 => PortEvent::Offline { device: 0 },
                            _ => PortEvent::Online { device: 0 },
                        }],
                    };
                    let mut from_all = Vec::new();
                    let mut from_asked = Vec::new();
                    // No value known to repeat its words: every one decoded again.
                    all.words_decoded.fill(false);
                    apply_port_events(
                        std::slice::from_mut(&mut all),
                        events.clone(),
                        &mut from_all,
                    );
                    apply_port_events(std::slice::from_mut(&mut asked), events, &mut from_asked);
                    let expected: Vec<String> = from_all
                        .iter()
                        .filter(|u| match u {
                            DeviceUpdate::Value {
                                control_id,
                                from_event,
                                changed,
                                ..
                            } => {
                                let pushbutton = device
                                    .channel(control_id)
                                    .is_some_and(|c| c.control_type == "pushbutton");
                                repeats_seen += usize::from(!changed);
                                *changed || repeats.report(*from_event, pushbutton)
                            }
                            _ => true,
                        })
                        .map(|u| format!("{u:?}"))
                        .collect();
                    let got: Vec<String> = from_asked.iter().map(|u| format!("{u:?}")).collect();
                    assert_eq!(got, expected, "{} {repeats:?}", device.id);
                }
            }
        }
        assert!(repeats_seen > 1000, "{repeats_seen} repeats only");
    }
}
