//! What goes back on the wire: bursts of bytes with their times, and how colliding frames merge.

use std::time::Duration;

use crate::protocol::crc::crc_is_valid;
use crate::protocol::parser::ARBITRATION_FILLER;

/// Bytes sent back to back from `start`, one character time each.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Burst {
    /// When the start bit of the first byte goes on the wire.
    pub start: Duration,
    pub char_time: Duration,
    pub bytes: Vec<u8>,
}

/// Everything the devices put on the wire in answer to one request.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Transmission {
    /// In time order; they never overlap.
    pub bursts: Vec<Burst>,
}

impl Transmission {
    pub fn is_empty(&self) -> bool {
        self.bursts.iter().all(|burst| burst.bytes.is_empty())
    }

    /// The bytes as the master reads them.
    pub fn bytes(&self) -> Vec<u8> {
        self.bursts
            .iter()
            .flat_map(|b| b.bytes.iter().copied())
            .collect()
    }

    /// Each byte with the time its stop bit ends.
    pub fn arrivals(&self) -> Vec<(Duration, u8)> {
        self.received()
            .into_iter()
            .map(|arrival| (arrival.at, arrival.byte))
            .collect()
    }

    /// The bytes as the master's UART receives them (for its receive timeout).
    pub fn received(&self) -> Vec<super::pacing::Arrival> {
        self.bursts
            .iter()
            .flat_map(|burst| {
                burst.bytes.iter().enumerate().map(move |(i, &byte)| {
                    let index = u32::try_from(i + 1).unwrap_or(u32::MAX);
                    super::pacing::Arrival {
                        at: burst.start + burst.char_time * index,
                        byte,
                        char_time: burst.char_time,
                    }
                })
            })
            .collect()
    }

    /// When the last byte has arrived.
    pub fn end(&self) -> Option<Duration> {
        self.arrivals().last().map(|&(at, _)| at)
    }

    /// Leading 0xFF arbitration bytes.
    pub fn filler_count(&self) -> usize {
        self.bytes()
            .iter()
            .take_while(|&&b| b == ARBITRATION_FILLER)
            .count()
    }

    pub(crate) fn append(&mut self, other: Transmission) {
        self.bursts.extend(other.bursts);
        self.bursts.sort_by_key(|burst| burst.start);
    }
}

/// A frame that starts at a given time.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TimedFrame {
    pub start: Duration,
    pub char_time: Duration,
    pub frame: Vec<u8>,
}

/// Several devices talking at once. RS-485 receivers see roughly the wired AND of the drivers
/// (a 0 bit from anyone pulls the line), so bytes that overlap in time merge by AND. Two devices
/// are never exactly in step: if the merged bytes still carry a valid CRC (identical replies
/// started together), the last byte is spoiled, as bit-level skew would on a real bus.
pub fn collide(replies: &[TimedFrame]) -> Vec<Burst> {
    let mut bytes: Vec<(Duration, Duration, u8)> = replies
        .iter()
        .flat_map(|reply| {
            let char_time = reply.char_time;
            reply.frame.iter().enumerate().map(move |(i, &byte)| {
                let index = u32::try_from(i).unwrap_or(u32::MAX);
                (reply.start + char_time * index, char_time, byte)
            })
        })
        .collect();
    bytes.sort_by_key(|&(start, _, _)| start);
    let mut merged: Vec<(Duration, Duration, u8)> = Vec::with_capacity(bytes.len());
    for (start, char_time, byte) in bytes {
        match merged.last_mut() {
            Some(last) if start < last.0 + last.1 => last.2 &= byte,
            _ => merged.push((start, char_time, byte)),
        }
    }
    let frame: Vec<u8> = merged.iter().map(|&(_, _, byte)| byte).collect();
    if crc_is_valid(&frame) {
        if let Some(last) = merged.last_mut() {
            last.2 ^= 0xFF;
        }
    }
    merged
        .into_iter()
        .map(|(start, char_time, byte)| Burst {
            start,
            char_time,
            bytes: vec![byte],
        })
        .collect()
}
