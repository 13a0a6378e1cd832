//! The fault sweep of `noise_scenarios` over random device layouts: each seed also draws a bus
//! (1–32 devices, 9600 or 115200 baud) and, per device, a template built in memory: channels of
//! every table (coils, discrete inputs, holding and input registers) in the formats u8 … s64,
//! float and double, either word order, scale/offset/round_to, bit fields (`"N:shift:width"`,
//! some across two registers), holes between registers (answered by the device or not: a
//! disabled channel covers them or the device refuses them), `max_read_registers`,
//! `max_reg_hole`, `max_bit_hole`, `read_period_ms`, sporadic and semi-sporadic channels on
//! devices that speak Fast Modbus and on devices that do not, and writable holding registers and
//! coils a client writes to. Then the same faults (`sweep_mixes`) and the same checks:
//!
//! - every published value is one the whole channel (all its registers at one instant) held at
//!   or before the publication, and not older than the one it published last
//!   ([`check_held_values_by_topic`]: a value of several registers holds only words of one
//!   instant, so a torn mix of two moments is "never held");
//! - every change of an awaited value (event and discrete inputs, coils the world toggles, some
//!   wide sporadic inputs: each changes only once its last change was published) is published
//!   exactly once;
//! - after the faults the broker converges on the simulator (read errors cleared);
//! - writes: every value written to a device is one a client asked for that channel (all its
//!   registers at one instant), never an older one after a newer, and none is lost without its
//!   write error (checked 10 s after the convergence: a write asked for at the end of the faults
//!   may still be queued behind a hold-off).
//!
//! The fixed-period reads of a drawn bus are kept under 40 % of its time (`LAYOUT_PERIOD_LOAD`
//! to change it; see [`cap_periods`] for why).
//!
//! The world changes the driven values round robin, one per 10 ms tick, all registers of a value
//! at once, each value's words its own on the bus (as the fault bus does: a value read from the
//! wrong register or device is never held there). Payloads come from the channel's codec as the
//! daemon resolved it, except plain integer channels, decoded here on their own.
//!
//! `SWEEP_SEEDS` (default 50) seeds from `SWEEP_FROM` (1) per mix of `SWEEP_MIX` (a name prefix;
//! all by default): `cargo test --release --lib gateway::layout_sweep::layout_sweep -- --exact
//! --ignored --nocapture --test-threads=1`; one run's wire and publications:
//! `SWEEP_FROM=7 SWEEP_MIX=noise cargo test --release --lib
//! gateway::layout_sweep::layout_sweep_trace -- --exact --ignored --nocapture`.

use std::collections::BTreeMap;
use std::time::Duration;

use serde_json::{json, Value};

use super::noise_scenarios::{
    nanos, report_run, start_other_master_on, sweep_mixes, taken_changes, SweepMix,
};
use super::virtual_gateway::VirtualGateway;
use crate::bench::harness::{Change, Publication};
use crate::bench::history::{check_held_values_by_topic, value_histories, RegisterKey};
use crate::bench::layout::{join_words, wide_words};
use crate::bench::matching::{match_expected, ExpectedChange};
use crate::device::codec::ValueCodec;
use crate::device_updates::{DeviceUpdate, Repeats};
use crate::protocol::RegisterType;
use crate::sim::faults::{Faults, XorShift64};

const TICK: Duration = Duration::from_millis(10);
const FAULT_TIME: Duration = Duration::from_secs(20);
/// A client writes every this many ticks.
const WRITE_EVERY_TICKS: u32 = 4;
const DEVICE_ID: &str = "lay";

/// What moves a channel's value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    /// The world changes it round robin (with the other channels of its slot).
    Driven,
    /// The world changes it once its last change is published (exactly-once check).
    Awaited,
    /// A client writes it; nothing else does.
    Written,
}

/// How a slot's words are made from its sequence number.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fill {
    /// Every word a different function of n ([`wide_words`]).
    Words,
    /// An IEEE float (2 words) or double (4): exponent kept finite, every word changing.
    Float,
    Double,
    /// A coil or discrete input: toggled.
    Bit,
}

/// Registers the world changes at once: one channel, or a register of bit fields.
#[derive(Debug, Clone)]
struct Slot {
    index: usize,
    key: RegisterKey,
    fill: Fill,
    /// Words in address order are the value's low word first.
    low_first: bool,
    role: Role,
}

/// One control of the layout.
#[derive(Debug, Clone)]
struct Chan {
    topic: String,
    key: RegisterKey,
    role: Role,
    /// Its slot (driven and awaited channels).
    slot: Option<usize>,
    /// Decoded here, independently of the codec: (signed, low word first).
    plain: Option<(bool, bool)>,
    fill: Fill,
    low_first: bool,
    /// As the daemon resolved it.
    codec: Option<ValueCodec>,
}

fn register_type_of(name: &str) -> RegisterType {
    match name {
        "coil" => RegisterType::Coil,
        "discrete" => RegisterType::DiscreteInput,
        "holding" => RegisterType::Holding,
        _ => RegisterType::Input,
    }
}

/// `value` (words joined in address order) as `words` words in address order.
fn split_words(value: u64, words: u16) -> Vec<u16> {
    (0..words)
        .rev()
        .map(|i| (value >> (16 * u32::from(i))) as u16)
        .collect()
}

impl Chan {
    /// The payload the daemon publishes when the channel's registers hold `value` (joined in
    /// address order).
    fn payload(&self, value: u64) -> String {
        let mut words = split_words(value, self.key.words);
        if let Some((signed, low_first)) = self.plain {
            if low_first {
                words.reverse();
            }
            let raw = join_words(&words);
            let bits = 16 * u32::from(self.key.words);
            return if signed && bits < 64 {
                let shift = 64 - bits;
                (((raw << shift) as i64) >> shift).to_string()
            } else if signed {
                (raw as i64).to_string()
            } else {
                raw.to_string()
            };
        }
        let Some(codec) = &self.codec else {
            return format!("?{value}");
        };
        match codec.decode(&words) {
            Ok(crate::device::codec::Reading::Value(text)) => text,
            other => format!("{other:?}"),
        }
    }
}

/// The words of a slot's `n`-th value, in address order.
fn fill_words(fill: Fill, words: u16, low_first: bool, n: u16) -> Vec<u16> {
    let mut value_order = match fill {
        Fill::Words => wide_words(n, words),
        Fill::Float => vec![0x4000 | (n & 0x1FFF), n ^ 0xA5A5],
        Fill::Double => vec![0x4000 | (n & 0x03FF), n ^ 0xA5A5, n ^ 0x5A5A, n ^ 0xFFFF],
        Fill::Bit => vec![n & 1],
    };
    if low_first {
        value_order.reverse();
    }
    value_order
}

/// One drawn device: its template, its bus entry, its channels.
struct DrawnDevice {
    template: Value,
    entry: Value,
    chans: Vec<(Chan, Option<Slot>)>,
    summary: String,
}

fn pick<T: Copy>(rng: &mut XorShift64, items: &[T]) -> T {
    items[(rng.next_u64() % items.len() as u64) as usize]
}

/// The registers a table's channels take, and the holes between them.
struct Cursor {
    next: u16,
    holes: Vec<u16>,
}

impl Cursor {
    fn new(rng: &mut XorShift64) -> Self {
        Self {
            next: (rng.next_u64() % 40) as u16,
            holes: Vec::new(),
        }
    }

    /// `count` registers, then maybe a hole.
    fn take(&mut self, rng: &mut XorShift64, count: u16) -> u16 {
        let at = self.next;
        self.next += count;
        let roll = rng.next_u64() % 10;
        let hole = match roll {
            0..=5 => 0,
            6..=8 => 1 + (rng.next_u64() % 3) as u16,
            _ => 4 + (rng.next_u64() % 9) as u16,
        };
        self.holes.extend(self.next..self.next + hole);
        self.next += hole;
        at
    }
}

/// Draws device `address`'s template and channels; `slots` numbers the slots bus-wide.
fn draw_device(rng: &mut XorShift64, address: u8, line: &str, slots: &mut usize) -> DrawnDevice {
    let fast = rng.chance(0.5);
    let holes_answered = rng.chance(0.5);
    let device_type = format!("lay-{address}");
    let prefix = format!("/devices/{DEVICE_ID}_{address}/controls/");
    let mut cursors: BTreeMap<&str, Cursor> = BTreeMap::new();
    for table in ["coil", "discrete", "holding", "input"] {
        cursors.insert(table, Cursor::new(rng));
    }
    let mut channels: Vec<Value> = Vec::new();
    let mut chans: Vec<(Chan, Option<Slot>)> = Vec::new();
    let groups = 2 + rng.next_u64() % 8;
    let mut next_name = 0;
    let mut name = || {
        next_name += 1;
        format!("c{next_name}")
    };
    let mut new_slot = |key: &RegisterKey, fill: Fill, low_first: bool, role: Role| {
        *slots += 1;
        Slot {
            index: *slots - 1,
            key: key.clone(),
            fill,
            low_first,
            role,
        }
    };
    const FORMATS: [(&str, u16, Fill); 10] = [
        ("u8", 1, Fill::Words),
        ("s8", 1, Fill::Words),
        ("u16", 1, Fill::Words),
        ("s16", 1, Fill::Words),
        ("u32", 2, Fill::Words),
        ("s32", 2, Fill::Words),
        ("u64", 4, Fill::Words),
        ("s64", 4, Fill::Words),
        ("float", 2, Fill::Float),
        ("double", 4, Fill::Double),
    ];
    for _ in 0..groups {
        let kind = rng.next_u64() % 100;
        match kind {
            // A value of input or (read-only) holding registers, driven.
            0..=39 => {
                let table = if rng.chance(0.7) { "input" } else { "holding" };
                let (format, words, fill) = pick(rng, &FORMATS);
                let low_first = words > 1 && rng.chance(0.4);
                let address_at = cursors.get_mut(table).expect("table").take(rng, words);
                let name = name();
                let mut channel = json!({"name": name, "reg_type": table,
                    "address": address_at, "format": format, "type": "value"});
                if table == "holding" {
                    channel["readonly"] = json!(true);
                }
                if low_first {
                    channel["word_order"] = json!("little_endian");
                } else if words > 1 && rng.chance(0.3) {
                    channel["word_order"] = json!("big_endian");
                }
                let scaled = rng.chance(0.3);
                if scaled {
                    channel["scale"] = json!(pick(rng, &[0.1, 0.01, 0.5, 2.0, 1.5]));
                    if rng.chance(0.5) {
                        channel["offset"] = json!(pick(rng, &[-40.0, 3.0, 0.25]));
                    }
                    if rng.chance(0.4) {
                        channel["round_to"] = json!(pick(rng, &[0.1, 0.5, 1.0, 0.01]));
                    }
                }
                if rng.chance(0.3) {
                    channel[if rng.chance(0.5) {
                        "sporadic"
                    } else {
                        "semi-sporadic"
                    }] = json!(true);
                }
                if rng.chance(0.2) {
                    channel["read_period_ms"] = json!(pick(rng, &[50, 100, 300, 1000]));
                }
                let key = RegisterKey::wide(address, table, address_at, words);
                let plain = (!scaled && matches!(fill, Fill::Words) && words > 1
                    || (!scaled && (format == "u16" || format == "s16")))
                    .then(|| (format.starts_with('s'), low_first));
                let slot = new_slot(&key, fill, low_first, Role::Driven);
                chans.push((
                    Chan {
                        topic: format!("{prefix}{name}"),
                        key,
                        role: Role::Driven,
                        slot: Some(slot.index),
                        plain,
                        fill,
                        low_first,
                        codec: None,
                    },
                    Some(slot),
                ));
                channels.push(channel);
            }
            // Bit fields of one register (or one across two), driven as one slot.
            40..=54 => {
                let table = if rng.chance(0.6) { "input" } else { "holding" };
                let wide = rng.chance(0.25);
                let words = if wide { 2 } else { 1 };
                let address_at = cursors.get_mut(table).expect("table").take(rng, words);
                let key = RegisterKey::wide(address, table, address_at, words);
                let slot = new_slot(&key, Fill::Words, false, Role::Driven);
                let mut fields: Vec<(u32, u32, &str)> = Vec::new();
                if wide {
                    fields.push((8, 16, "u32"));
                    fields.push((0, 8, "u32"));
                } else {
                    let mut shift = 0;
                    while shift < 16 && fields.len() < 3 {
                        let width = pick(rng, &[1u32, 2, 3, 4, 6, 8]).min(16 - shift);
                        fields.push((shift, width, if rng.chance(0.3) { "s16" } else { "u16" }));
                        shift += width + (rng.next_u64() % 3) as u32;
                    }
                }
                let mut slot = Some(slot);
                for (shift, width, format) in fields {
                    let name = name();
                    let mut channel = json!({"name": name, "reg_type": table,
                        "address": format!("{address_at}:{shift}:{width}"),
                        "format": format, "type": "value"});
                    if table == "holding" {
                        channel["readonly"] = json!(true);
                    }
                    channels.push(channel);
                    let index = slot.as_ref().map_or(0, |s| s.index);
                    chans.push((
                        Chan {
                            topic: format!("{prefix}{name}"),
                            key: key.clone(),
                            role: Role::Driven,
                            slot: Some(index),
                            plain: None,
                            fill: Fill::Words,
                            low_first: false,
                            codec: None,
                        },
                        // The slot goes with the first field only.
                        slot.take(),
                    ));
                }
            }
            // Discrete inputs or read-only coils toggled once published (1–3 of them).
            55..=72 => {
                let table = if rng.chance(0.7) { "discrete" } else { "coil" };
                let sporadic = rng.chance(0.6);
                for _ in 0..1 + rng.next_u64() % 3 {
                    let address_at = cursors.get_mut(table).expect("table").take(rng, 1);
                    let name = name();
                    let mut channel = json!({"name": name, "reg_type": table,
                        "address": address_at, "type": "switch", "readonly": true});
                    if sporadic {
                        channel["sporadic"] = json!(true);
                    }
                    channels.push(channel);
                    let key = RegisterKey::new(address, table, address_at);
                    let slot = new_slot(&key, Fill::Bit, false, Role::Awaited);
                    chans.push((
                        Chan {
                            topic: format!("{prefix}{name}"),
                            key,
                            role: Role::Awaited,
                            slot: Some(slot.index),
                            plain: Some((false, false)),
                            fill: Fill::Bit,
                            low_first: false,
                            codec: None,
                        },
                        Some(slot),
                    ));
                }
            }
            // A wide sporadic input changed once published.
            73..=79 => {
                let (format, words) = pick(rng, &[("u16", 1), ("u32", 2), ("s32", 2), ("u64", 4)]);
                let low_first = words > 1 && rng.chance(0.4);
                let address_at = cursors.get_mut("input").expect("table").take(rng, words);
                let name = name();
                let mut channel = json!({"name": name, "reg_type": "input",
                    "address": address_at, "format": format, "type": "value", "sporadic": true});
                if low_first {
                    channel["word_order"] = json!("little_endian");
                }
                channels.push(channel);
                let key = RegisterKey::wide(address, "input", address_at, words);
                let slot = new_slot(&key, Fill::Words, low_first, Role::Awaited);
                chans.push((
                    Chan {
                        topic: format!("{prefix}{name}"),
                        key,
                        role: Role::Awaited,
                        slot: Some(slot.index),
                        plain: Some((format.starts_with('s'), low_first)),
                        fill: Fill::Words,
                        low_first,
                        codec: None,
                    },
                    Some(slot),
                ));
            }
            // A writable holding value or coil.
            _ => {
                let coil = rng.chance(0.3);
                let (table, format, words, fill) = if coil {
                    ("coil", "u8", 1, Fill::Bit)
                } else {
                    let (format, words, fill) = pick(
                        rng,
                        &[
                            ("u16", 1, Fill::Words),
                            ("s16", 1, Fill::Words),
                            ("u32", 2, Fill::Words),
                            ("s32", 2, Fill::Words),
                            ("u64", 4, Fill::Words),
                            ("float", 2, Fill::Float),
                        ],
                    );
                    ("holding", format, words, fill)
                };
                let low_first = words > 1 && rng.chance(0.4);
                let address_at = cursors.get_mut(table).expect("table").take(rng, words);
                let name = name();
                let mut channel = if coil {
                    json!({"name": name, "reg_type": "coil", "address": address_at,
                        "type": "switch"})
                } else {
                    json!({"name": name, "reg_type": "holding", "address": address_at,
                        "format": format, "type": "value"})
                };
                if low_first {
                    channel["word_order"] = json!("little_endian");
                }
                let scaled = !coil && fill == Fill::Words && words <= 2 && rng.chance(0.3);
                if scaled {
                    channel["scale"] = json!(pick(rng, &[0.1, 0.5, 0.01]));
                }
                if rng.chance(0.2) {
                    channel["read_period_ms"] = json!(pick(rng, &[100, 500]));
                }
                channels.push(channel);
                let key = RegisterKey::wide(address, table, address_at, words);
                let plain = (!scaled && fill == Fill::Words && words > 1
                    || (!scaled && (format == "u16" || format == "s16")))
                    .then(|| (format.starts_with('s'), low_first));
                chans.push((
                    Chan {
                        topic: format!("{prefix}{name}"),
                        key,
                        role: Role::Written,
                        slot: None,
                        plain,
                        fill,
                        low_first,
                        codec: None,
                    },
                    None,
                ));
            }
        }
    }
    if holes_answered {
        // The device answers its holes: disabled channels (the simulator opens them, the
        // daemon does not read them) cover them.
        for (table, cursor) in &cursors {
            for hole in &cursor.holes {
                channels.push(json!({"name": format!("hole {table} {hole}"),
                    "reg_type": table, "address": hole, "enabled": false}));
            }
        }
    }
    let mut device = json!({"name": format!("Layout {address}"), "id": DEVICE_ID,
        "channels": channels});
    let mut limits = Vec::new();
    if rng.chance(0.7) {
        let max = pick(rng, &[0, 1, 2, 3, 4, 8, 16, 125]);
        device["max_read_registers"] = json!(max);
        limits.push(format!("max_read_registers={max}"));
    }
    if rng.chance(0.6) {
        let hole = pick(rng, &[0, 1, 2, 4, 10]);
        device["max_reg_hole"] = json!(hole);
        limits.push(format!("max_reg_hole={hole}"));
    }
    if rng.chance(0.5) {
        let hole = pick(rng, &[0, 1, 4, 16]);
        device["max_bit_hole"] = json!(hole);
        limits.push(format!("max_bit_hole={hole}"));
    }
    let template = json!({"title": "layout sweep", "device_type": device_type,
        "device": device});
    let entry = json!({"name": format!("d{address}"), "template": device_type,
        "address": address, "serial": 0xFE00_0000_u32 + u32::from(address), "line": line,
        "fast": fast, "turnaround_us": 500});
    let summary = format!(
        "device {address}: fast={fast} holes_answered={holes_answered} {} channels={}",
        limits.join(" "),
        chans.len()
    );
    DrawnDevice {
        template,
        entry,
        chans,
        summary,
    }
}

/// Drops the `read_period_ms` of `template`'s channels once the fixed-period reads of the bus
/// (`load`: the share of its time they take so far, about) would take more than `cap` of it:
/// the scheduler serves them strictly first (`DeviceState::urgency` ranks every read with a
/// period before every round-robin one), so past the bus's capacity the other reads never come
/// and those values are never published (found by this sweep, 28 Nov 2026; wb-mqtt-serial's
/// scheduler gives the low priority a share after `max_low_priority_lag`). The sweep keeps them
/// within it unless `LAYOUT_PERIOD_LOAD` (a share, e.g. 100) says otherwise. Returns how many
/// were dropped.
fn cap_periods(
    template: &mut Value,
    baud: u32,
    turnaround: Duration,
    load: &mut f64,
    cap: f64,
) -> usize {
    let Some(channels) = template["device"]["channels"].as_array_mut() else {
        return 0;
    };
    let mut dropped = 0;
    for channel in channels {
        let Some(period) = channel["read_period_ms"].as_f64() else {
            continue;
        };
        let words = match channel["format"].as_str() {
            Some("u32" | "s32" | "float") => 2.0,
            Some("u64" | "s64" | "double") => 4.0,
            _ => 1.0,
        };
        // Request, reply and the silences around them, in characters of 11 bits; and 1 ms.
        let seconds =
            (20.0 + 2.0 * words) * 11.0 / f64::from(baud) + 0.001 + turnaround.as_secs_f64();
        let share = seconds / (period / 1000.0);
        if *load + share > cap {
            if let Some(fields) = channel.as_object_mut() {
                fields.remove("read_period_ms");
            }
            dropped += 1;
        } else {
            *load += share;
        }
    }
    dropped
}

/// A drawn bus running on virtual time, with what the checks need.
struct LayoutBus {
    gateway: VirtualGateway,
    devices: u8,
    baud: u32,
    chans: Vec<Chan>,
    slots: Vec<Slot>,
    /// Values per slot.
    span: u16,
    /// Per slot: values taken so far.
    sequence: Vec<u16>,
    round_robin: Vec<usize>,
    next_slot: usize,
    topics: BTreeMap<String, RegisterKey>,
    initial: BTreeMap<RegisterKey, u16>,
    changes: Vec<Change>,
    /// Awaited topics changed whose new value is not yet published.
    awaiting: BTreeMap<String, String>,
    toggles: usize,
    /// Per written channel (index in `chans`): the words asked for, in order.
    asked: BTreeMap<usize, Vec<Vec<u16>>>,
    next_written: u16,
    rng: XorShift64,
    summary: Vec<String>,
    _templates: tempfile::TempDir,
}

impl LayoutBus {
    /// Draws seed's bus and starts it; None (and why) if it never showed its first values.
    /// `turnaround`: how long the devices take to answer at most (the other master's mixes
    /// slow them down), for [`cap_periods`].
    fn start(seed: u64, trace: bool, turnaround: Duration) -> Result<Self, (String, Box<Self>)> {
        let mut rng = XorShift64::new(seed.wrapping_mul(0x2545_F491_4F6C_DD1D) | 1);
        let devices = match rng.next_u64() % 4 {
            0 => 1 + (rng.next_u64() % 3) as u8,
            1 | 2 => 2 + (rng.next_u64() % 10) as u8,
            _ => 12 + (rng.next_u64() % 21) as u8,
        };
        let baud = if rng.chance(0.5) { 115_200 } else { 9600 };
        let line = format!("{baud} 8N2");
        let dir = tempfile::tempdir().expect("a template directory");
        let mut entries = Vec::new();
        let mut chans = Vec::new();
        let mut slots = Vec::new();
        let mut slot_count = 0;
        let mut summary = vec![format!("bus {devices}x{baud}")];
        // The share of the bus the fixed-period reads may take (see [`cap_periods`]).
        let period_cap: f64 = std::env::var("LAYOUT_PERIOD_LOAD")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(0.4);
        let mut period_load = 0.0;
        for address in 1..=devices {
            let mut drawn = draw_device(&mut rng, address, &line, &mut slot_count);
            let dropped = cap_periods(
                &mut drawn.template,
                baud,
                turnaround,
                &mut period_load,
                period_cap,
            );
            if dropped > 0 {
                drawn
                    .summary
                    .push_str(&format!(" read_periods_dropped={dropped}"));
            }
            std::fs::write(
                dir.path().join(format!("lay-{address}.json")),
                drawn.template.to_string(),
            )
            .expect("template written");
            summary.push(drawn.summary);
            summary.push(format!("  {}", drawn.template["device"]));
            entries.push(drawn.entry);
            for (chan, slot) in drawn.chans {
                chans.push(chan);
                slots.extend(slot);
            }
        }
        if trace {
            for line in &summary {
                eprintln!("LAYOUT {line}");
            }
        }
        let mut gateway =
            VirtualGateway::from_bus(&line, &entries, dir.path(), true, seed.max(1), Repeats::All);
        gateway.trace = trace;
        // The codecs as the daemon resolved them.
        let mut resolved: BTreeMap<(u8, String), ValueCodec> = BTreeMap::new();
        for (_, update) in &gateway.updates {
            if let DeviceUpdate::Added(device) = update {
                for channel in device.channels.iter() {
                    if let Some(register) = channel.registers.first() {
                        resolved.insert(
                            (device.slave_id, channel.id.clone()),
                            register.codec.clone(),
                        );
                    }
                }
            }
        }
        for chan in &mut chans {
            let name = chan
                .topic
                .rsplit('/')
                .next()
                .unwrap_or_default()
                .to_string();
            chan.codec = resolved.get(&(chan.key.address, name)).cloned();
            assert!(chan.codec.is_some(), "{} was not resolved", chan.topic);
        }
        slots.sort_by_key(|s| s.index);
        let span = u16::try_from(65_536 / (slots.len() + 1).max(1))
            .unwrap_or(u16::MAX)
            .min(1024);
        let topics = chans
            .iter()
            .map(|c| (c.topic.clone(), c.key.clone()))
            .collect();
        let round_robin = slots
            .iter()
            .filter(|s| s.role == Role::Driven)
            .map(|s| s.index)
            .collect();
        let mut bus = Self {
            gateway,
            devices,
            baud,
            sequence: vec![0; slots.len()],
            slots,
            span,
            chans,
            round_robin,
            next_slot: 0,
            topics,
            initial: BTreeMap::new(),
            changes: Vec::new(),
            awaiting: BTreeMap::new(),
            toggles: 0,
            asked: BTreeMap::new(),
            // Written values come after every slot's (no value is two channels').
            next_written: 0,
            rng: XorShift64::new(seed ^ 0x5DEE_CE66_D1CE_4E5B),
            summary,
            _templates: dir,
        };
        bus.next_written = u16::try_from(bus.slots.len())
            .unwrap_or(0)
            .wrapping_mul(bus.span);
        for key in bus.topics.values() {
            for register in key.registers() {
                let value = bus.sim_register(&register).unwrap_or(0);
                bus.initial.insert(register, value);
            }
        }
        for index in 0..bus.slots.len() {
            bus.change_slot(index);
        }
        // Awaited changes above wait for their publication as the later ones do.
        for chan in bus.chans.clone() {
            if chan.role == Role::Awaited {
                let payload = bus.sim_payload(&chan).unwrap_or_default();
                bus.awaiting.insert(chan.topic.clone(), payload);
            }
        }
        match bus.run_until_converged(Duration::from_secs(120)) {
            Some(_) => Ok(bus),
            None => Err((
                format!("no first values: {:?}", bus.disagreement()),
                Box::new(bus),
            )),
        }
    }

    fn sim_register(&self, key: &RegisterKey) -> Option<u16> {
        self.gateway.register(
            key.address,
            register_type_of(&key.register_type),
            key.register,
        )
    }

    fn sim_words(&self, key: &RegisterKey) -> Option<Vec<u16>> {
        key.registers().map(|r| self.sim_register(&r)).collect()
    }

    fn sim_payload(&self, chan: &Chan) -> Option<String> {
        Some(chan.payload(join_words(&self.sim_words(&chan.key)?)))
    }

    /// Slot `index` takes its next value (all its words at once); false when used up.
    fn change_slot(&mut self, index: usize) -> bool {
        let Some(slot) = self.slots.get(index).cloned() else {
            return false;
        };
        let sequence = &mut self.sequence[index];
        if *sequence + 1 >= self.span {
            return false;
        }
        *sequence += 1;
        let n = u16::try_from(slot.index)
            .unwrap_or(0)
            .wrapping_mul(self.span)
            .wrapping_add(*sequence);
        let words = fill_words(slot.fill, slot.key.words, slot.low_first, n);
        self.gateway.change(
            slot.key.address,
            register_type_of(&slot.key.register_type),
            slot.key.register,
            &words,
        );
        self.changes.extend(taken_changes(&mut self.gateway));
        true
    }

    fn change_next_driven(&mut self) {
        if self.round_robin.is_empty() {
            return;
        }
        let index = self.round_robin[self.next_slot % self.round_robin.len()];
        self.next_slot += 1;
        self.change_slot(index);
    }

    /// Every awaited value whose last change was published takes its next one.
    fn change_published_awaited(&mut self) {
        let retained = &self.gateway.retained;
        self.awaiting
            .retain(|topic, value| retained.get(topic) != Some(value));
        for chan in self.chans.clone() {
            if chan.role != Role::Awaited || self.awaiting.contains_key(&chan.topic) {
                continue;
            }
            let Some(slot) = chan.slot else { continue };
            if !self.change_slot(slot) {
                continue;
            }
            let payload = self.sim_payload(&chan).unwrap_or_default();
            self.awaiting.insert(chan.topic.clone(), payload);
            self.toggles += 1;
        }
    }

    /// A client writes a new value to a writable channel drawn at random.
    fn write_one(&mut self) {
        let written: Vec<usize> = (0..self.chans.len())
            .filter(|&i| self.chans[i].role == Role::Written)
            .collect();
        if written.is_empty() {
            return;
        }
        let index = written[(self.rng.next_u64() % written.len() as u64) as usize];
        let chan = self.chans[index].clone();
        let Some(codec) = chan.codec.clone() else {
            return;
        };
        let words = if chan.fill == Fill::Bit {
            let last = self.asked.get(&index).and_then(|a| a.last()).map_or_else(
                || self.sim_words(&chan.key).unwrap_or_default(),
                Clone::clone,
            );
            vec![u16::from(last.first().copied().unwrap_or(0) == 0)]
        } else {
            self.next_written = self.next_written.wrapping_add(1);
            fill_words(chan.fill, chan.key.words, chan.low_first, self.next_written)
        };
        let payload = chan.payload(join_words(&words));
        // What the codec makes of that text is what must reach the device.
        let Ok(encoded) = codec.encode(&payload, None) else {
            return;
        };
        self.asked.entry(index).or_default().push(encoded);
        let device = format!("{DEVICE_ID}_{}", chan.key.address);
        let control = chan
            .topic
            .rsplit('/')
            .next()
            .unwrap_or_default()
            .to_string();
        self.gateway
            .publish_on(&device, &control, payload.as_bytes());
    }

    /// The world for `length`: a driven value per tick, awaited ones once published, a write
    /// every few ticks.
    fn drive(&mut self, length: Duration) {
        let end = self.gateway.now + length;
        let mut tick = 0_u32;
        while self.gateway.now < end {
            self.change_next_driven();
            if tick % 10 == 0 {
                self.change_published_awaited();
            }
            if tick % WRITE_EVERY_TICKS == 1 {
                self.write_one();
            }
            tick += 1;
            self.gateway.run_for(TICK);
            self.changes.extend(taken_changes(&mut self.gateway));
        }
    }

    fn faults_on_all(&mut self, faults: Faults) {
        for address in 1..=self.devices {
            self.gateway.set_faults(address, faults);
        }
    }

    /// What still differs between the broker and the simulator (None: converged). Write and
    /// period-miss flags do not count (a write lost under the faults keeps its flag; a
    /// `read_period_ms` a busy slow bus cannot keep is flagged `p` for good).
    fn disagreement(&self) -> Option<String> {
        for chan in &self.chans {
            let value = self.sim_payload(chan);
            let published = self.gateway.retained.get(&chan.topic);
            if published != value.as_ref() {
                return Some(format!(
                    "{}: {published:?}, simulator {value:?}",
                    chan.topic
                ));
            }
        }
        self.gateway
            .retained
            .iter()
            .find(|(topic, flags)| {
                topic.ends_with("/meta/error") && flags.chars().any(|f| f != 'w' && f != 'p')
            })
            .map(|(topic, flags)| format!("{topic} is {flags:?}"))
    }

    fn run_until_converged(&mut self, limit: Duration) -> Option<Duration> {
        let start = self.gateway.now;
        while self.gateway.now < start + limit {
            if self.disagreement().is_none() {
                return Some(self.gateway.now - start);
            }
            self.gateway.run_for(TICK);
            self.changes.extend(taken_changes(&mut self.gateway));
        }
        None
    }

    fn publications(&self) -> Vec<Publication> {
        self.gateway.publications()
    }

    fn chan_of(&self, topic: &str) -> Option<&Chan> {
        self.chans.iter().find(|c| c.topic == topic)
    }

    /// Every value publication since `since` against what its channel held.
    fn check_published(&self, since: Duration) -> (usize, Vec<String>) {
        let by_topic: BTreeMap<&str, &Chan> =
            self.chans.iter().map(|c| (c.topic.as_str(), c)).collect();
        let report = check_held_values_by_topic(
            &self.initial,
            &self.changes,
            &self.publications(),
            nanos(since),
            &self.topics,
            |topic, _, value| {
                by_topic
                    .get(topic)
                    .map_or_else(String::new, |c| c.payload(value))
            },
        );
        let wrong = report
            .bad
            .iter()
            .map(|bad| {
                let chan = self.chan_of(&bad.publication.topic);
                let held: Vec<String> = bad
                    .held
                    .iter()
                    .map(|v| match chan {
                        Some(c) => format!("{v:#x}={}", c.payload(*v)),
                        None => format!("{v:#x}"),
                    })
                    .collect();
                format!(
                    "{} = {} at {:?}: {} (held {held:?}) {:?}",
                    bad.publication.topic,
                    bad.publication.payload,
                    Duration::from_nanos(bad.publication.mono_ns),
                    bad.reason,
                    chan.map(|c| (&c.key, c.role, &c.codec))
                )
            })
            .collect();
        (report.checked, wrong)
    }

    /// Awaited changes since `since`, each to be published exactly once.
    fn awaited_violations(&self, since: Duration, toggles: usize) -> Vec<String> {
        let awaited: Vec<&Chan> = self
            .chans
            .iter()
            .filter(|c| c.role == Role::Awaited)
            .collect();
        let keys: Vec<RegisterKey> = awaited.iter().map(|c| c.key.clone()).collect();
        let (_, changes) = value_histories(&self.initial, &self.changes, &keys);
        let expected: Vec<ExpectedChange> = changes
            .into_iter()
            .filter(|c| c.mono_ns >= nanos(since) && c.origin == "control")
            .filter_map(|c| {
                let chan = awaited.iter().find(|a| a.key == c.key)?;
                Some(ExpectedChange {
                    mono_ns: c.mono_ns,
                    topic: chan.topic.clone(),
                    payload: chan.payload(c.value),
                })
            })
            .collect();
        let matched = match_expected(&expected, &self.publications(), nanos(since) + 1);
        let mut violations = Vec::new();
        if (
            matched.changes,
            matched.lost,
            matched.wrong,
            matched.duplicates,
        ) != (toggles, 0, 0, 0)
        {
            violations.push(format!(
                "awaited changes {toggles}: changes {} matched {} lost {} wrong {} duplicates {} \
                 unmapped {}",
                matched.changes,
                matched.matched,
                matched.lost,
                matched.wrong,
                matched.duplicates,
                matched.unmapped
            ));
        }
        let published = self
            .gateway
            .published
            .iter()
            .filter(|p| p.at > since && awaited.iter().any(|c| c.topic == p.topic))
            .count();
        if published != toggles {
            violations.push(format!(
                "{published} publications of awaited values for {toggles} changes"
            ));
        }
        violations
    }

    /// Writes: every value that reached a device was asked for that channel, never an older
    /// one after a newer; none lost without its write error.
    fn write_violations(&self) -> (usize, Vec<String>) {
        let mut violations = Vec::new();
        let master: Vec<Change> = self
            .changes
            .iter()
            .filter(|c| c.origin == "master")
            .cloned()
            .collect();
        let written: Vec<(usize, &Chan)> = self
            .chans
            .iter()
            .enumerate()
            .filter(|(_, c)| c.role == Role::Written)
            .collect();
        let keys: Vec<RegisterKey> = written.iter().map(|(_, c)| c.key.clone()).collect();
        let (_, changes) = value_histories(&self.initial, &master, &keys);
        // Master writes to registers no written channel has.
        for change in &master {
            let key = RegisterKey::of(change);
            if !keys.iter().any(|k| k.registers().any(|r| r == key)) {
                violations.push(format!("written, never asked: {change:?}"));
            }
        }
        let mut reached = 0;
        let mut last_index: BTreeMap<usize, usize> = BTreeMap::new();
        for change in &changes {
            for (index, chan) in written.iter().filter(|(_, c)| c.key == change.key) {
                reached += 1;
                let words = split_words(change.value, chan.key.words);
                let asked = self.asked.get(index).map_or(&[][..], Vec::as_slice);
                let from = last_index.get(index).copied().unwrap_or(0);
                match asked.iter().skip(from).position(|a| *a == words) {
                    Some(offset) => {
                        last_index.insert(*index, from + offset);
                    }
                    None if asked.contains(&words) => violations.push(format!(
                        "{}: {words:04x?} at {:?} is older than one written before it",
                        chan.topic,
                        Duration::from_nanos(change.mono_ns)
                    )),
                    None => violations.push(format!(
                        "{}: {words:04x?} at {:?} never asked (asked {} values)",
                        chan.topic,
                        Duration::from_nanos(change.mono_ns),
                        asked.len()
                    )),
                }
            }
        }
        for (index, chan) in &written {
            let Some(last) = self.asked.get(index).and_then(|a| a.last()) else {
                continue;
            };
            let held = self.sim_words(&chan.key);
            if held.as_ref() == Some(last) {
                continue;
            }
            let error = self
                .gateway
                .retained
                .get(&format!("{}/meta/error", chan.topic))
                .cloned()
                .unwrap_or_default();
            if !error.contains('w') {
                violations.push(format!(
                    "{} holds {held:04x?}, {last:04x?} asked last, error {error:?}",
                    chan.topic
                ));
            }
        }
        (reached, violations)
    }
}

/// One run: the seed's layout under `mix` for [`FAULT_TIME`], then the recovery; what was
/// wrong and the run's figures. `trace`: every transaction, publication and the layout printed.
fn layout_run(seed: u64, mix: &SweepMix, trace: bool) -> (Vec<String>, String) {
    // The other master's mixes let the devices take up to 40 ms to answer.
    let turnaround = if mix.other_master.is_some() {
        Duration::from_millis(40)
    } else {
        Duration::from_micros(500)
    };
    let mut bus = match LayoutBus::start(seed, trace, turnaround) {
        Ok(bus) => bus,
        Err((why, bus)) => return (vec![why], bus.summary[0].clone()),
    };
    bus.gateway.carry_late_bytes = mix.carry_late_bytes;
    let since = bus.gateway.now;
    let toggles_before = bus.toggles;
    for address in 1..=bus.devices {
        bus.gateway.set_faults(address, (mix.faults)(address, seed));
    }
    start_other_master_on(&mut bus.gateway, mix, seed);
    bus.drive(FAULT_TIME);
    bus.gateway.other_master = None;
    bus.faults_on_all(Faults::default());
    let ended = bus.gateway.now;
    let recovery = bus.run_until_converged(Duration::from_secs(90));
    // Writes asked for at the end of the faults may still be queued (a device held off after
    // a failure): they have 10 s more, as in `write_run`.
    bus.gateway.run_for(Duration::from_secs(10));
    bus.changes.extend(taken_changes(&mut bus.gateway));
    let mut violations = Vec::new();
    if recovery.is_none() {
        violations.push(format!("never converged: {:?}", bus.disagreement()));
    }
    let (checked, wrong) = bus.check_published(since);
    violations.extend(wrong.into_iter().map(|w| format!("wrong: {w}")));
    let toggles = bus.toggles - toggles_before;
    violations.extend(bus.awaited_violations(since, toggles));
    let (reached, write_violations) = bus.write_violations();
    violations.extend(write_violations);
    if bus.gateway.spins > 0 {
        violations.push(format!(
            "the scheduler said to wait until a time already come {} times (the port spins)",
            bus.gateway.spins
        ));
    }
    if trace {
        eprintln!(
            "FAULTS ENDED {:.6} recovery {recovery:?}",
            ended.as_secs_f64()
        );
        for p in bus.gateway.published.iter().filter(|p| p.at >= since) {
            eprintln!("PUB {:.6} {} = {}", p.at.as_secs_f64(), p.topic, p.payload);
        }
        for change in &bus.changes {
            eprintln!(
                "CHANGE {:.6} {} {} {} = {:#06x} ({})",
                change.mono_ns as f64 / 1e9,
                change.address,
                change.register_type,
                change.register,
                change.value,
                change.origin
            );
        }
        for violation in &violations {
            eprintln!("WRONG {violation}");
        }
    }
    let writes: usize = bus.asked.values().map(Vec::len).sum();
    let figures = format!(
        "bus={}x{} channels={} recovery={recovery:?} checked={checked} toggles={toggles} \
         writes={writes} reached={reached} wire={} now={:?}",
        bus.devices,
        bus.baud,
        bus.chans.len(),
        bus.gateway.wire_log.len(),
        bus.gateway.now,
    );
    (violations, figures)
}

/// Runs [`layout_run`] over `seeds` for every mix whose name starts with `only_mix` (all when
/// None); the runs with a violation or a panic.
fn sweep(seeds: std::ops::Range<u64>, only_mix: Option<&str>) -> usize {
    let mut bad = 0;
    for mix in &sweep_mixes() {
        if only_mix.is_some_and(|m| !mix.name.starts_with(m)) {
            continue;
        }
        let started = std::time::Instant::now();
        let mut bad_runs = 0;
        for seed in seeds.clone() {
            let case = format!("LAYOUT {} seed={seed}", mix.name);
            bad_runs += usize::from(!report_run(&case, || layout_run(seed, mix, false)));
        }
        eprintln!(
            "LAYOUT SUMMARY {} seeds {}..{} bad_runs={bad_runs} in {:?}",
            mix.name,
            seeds.start,
            seeds.end,
            started.elapsed()
        );
        bad += bad_runs;
    }
    bad
}

/// The fault sweep over random layouts (see the module docs): `SWEEP_SEEDS` (50) seeds from
/// `SWEEP_FROM` (1), every mix of `sweep_mixes` or those `SWEEP_MIX` starts.
#[test]
#[ignore = "long: many seeds of random layouts under every fault mix"]
fn layout_sweep() {
    let env = |name: &str| std::env::var(name).ok();
    let seeds: u64 = env("SWEEP_SEEDS")
        .and_then(|s| s.parse().ok())
        .unwrap_or(50);
    let from: u64 = env("SWEEP_FROM").and_then(|s| s.parse().ok()).unwrap_or(1);
    let bad = sweep(from..from + seeds, env("SWEEP_MIX").as_deref());
    assert_eq!(bad, 0, "runs with violations or panics");
}

/// One run of [`layout_sweep`] (`SWEEP_FROM` the seed, `SWEEP_MIX` the mix's exact name):
/// the layout, every transaction, publication and register change printed, then what was wrong.
#[test]
#[ignore = "diagnosis: prints one layout run's wire"]
fn layout_sweep_trace() {
    let env = |name: &str| std::env::var(name).ok();
    let seed: u64 = env("SWEEP_FROM").and_then(|s| s.parse().ok()).unwrap_or(1);
    let mix_name = env("SWEEP_MIX").unwrap_or_else(|| "noise".into());
    let mixes = sweep_mixes();
    let mix = mixes.iter().find(|m| m.name == mix_name).expect("a mix");
    let (violations, figures) = layout_run(seed, mix, true);
    eprintln!("seed {seed} {mix_name}: {figures}");
    for violation in &violations {
        eprintln!("VIOLATION {violation}");
    }
}

/// A few seeds of [`layout_sweep`] in the normal suite (a few seconds in debug): random layouts
/// of 8 to 32 devices at both rates, under noise, line errors with late replies, and a second
/// master; nothing wrong published, every awaited change once, no write wrong or lost.
#[test]
fn a_few_random_layouts_under_faults_publish_and_write_only_right_values() {
    let mixes = sweep_mixes();
    for (mix_name, seeds) in [
        ("noise_carry", &[3, 4, 11][..]),
        ("line_errors_late_carry", &[5, 6][..]),
        ("other_master_busy_carry", &[7][..]),
    ] {
        let mix = mixes.iter().find(|m| m.name == mix_name).expect("the mix");
        for &seed in seeds {
            let (violations, figures) = layout_run(seed, mix, false);
            assert!(
                violations.is_empty(),
                "{mix_name} seed {seed}: {violations:#?} ({figures})"
            );
        }
    }
}
