//! One bus transaction as every layer sees it: the request with its timeouts, what the line
//! carried back, and when. The scheduler (`port`) makes them, the transport carries them out;
//! both take the types from here so that neither depends on the other.

use std::time::Duration;

use super::fast::{EventPacket, FastReply};
use super::{LineSettings, Reply, ReplyBody, Request};

/// How much longer than its length a reply to one device may take on the line: adapters hand
/// bytes over in batches, and a loaded machine reads them late.
const REPLY_SLACK_CHARACTERS: usize = 32;

/// The longest a timed-out request watches the line for its late reply.
pub const MAX_LATE_WINDOW: Duration = Duration::from_millis(100);

/// One request and how long to wait for its reply. Every timeout counts from the end of the
/// request on the wire: `request_time` after the transport handed it over.
#[derive(Debug, Clone, PartialEq)]
pub struct Transaction {
    pub request: Request,
    /// Wire time of the request itself: the reply clock starts after it.
    pub request_time: Duration,
    /// From the end of the request to the end of the reply.
    pub reply_timeout: Duration,
    /// Give up when not even one byte arrived by then (the device's response timeout; event
    /// requests: nobody takes part).
    pub first_byte_timeout: Option<Duration>,
    /// After a timeout, how long to keep watching the line and throw away what comes (a late
    /// reply must not pass for the reply to the next request).
    pub late_window: Duration,
    /// Expected bus time of the whole transaction.
    pub estimated: Duration,
}

/// What the transport saw of a reply's timing, counted from the end of the request.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplyTiming {
    /// The first byte of the reply arrived this long after the request.
    pub first_byte: Option<Duration>,
    /// Nothing came in time, but bytes came this long after the request, after the timeout: a
    /// late reply, thrown away.
    pub late_byte: Option<Duration>,
    /// Bytes came in time (`first_byte`), but none of them began a reply to the request: the
    /// parser dropped them all (another device's late reply, noise), or what looked like the
    /// reply's header came only after bytes that were dropped (a run of another device's frame
    /// can read as one). They ended the wait, yet the device's own reply may still be on its
    /// way, as after silence.
    pub foreign_bytes_only: bool,
    /// A reply came, but another master's request was heard shortly before it or in its
    /// window: it may answer that request, so it was not taken (the outcome is `Garbled`).
    pub another_master: bool,
    /// An event poll's reply began with the header of this address's event packet and was
    /// unreadable after it (the outcome is `Garbled`): noise, or two devices with one address,
    /// which win the arbitration together and send at once.
    pub garbled_packet_from: Option<u8>,
}

/// What came back for a transaction.
#[derive(Debug, Clone, PartialEq)]
pub enum TransactionOutcome {
    Reply(Reply),
    /// Nothing, or nothing that answers the request, before the timeout.
    NoReply,
    /// Bytes arrived but no valid frame (CRC errors, a collision).
    Garbled,
}

impl TransactionOutcome {
    /// The event packet an event poll brought, and who sent it.
    pub fn event_packet(&self) -> Option<(u8, &EventPacket)> {
        match self {
            Self::Reply(Reply {
                address,
                body:
                    ReplyBody::Fast {
                        reply: FastReply::Events(packet),
                        ..
                    },
            }) => Some((*address, packet)),
            _ => None,
        }
    }
}

impl Transaction {
    /// When silence would have ended the wait for its reply, the request sent at `sent_at`:
    /// the first byte's timeout after the request, or the whole reply's when there is none.
    /// Bytes that could not begin the reply may end the wait sooner
    /// ([`ReplyTiming::foreign_bytes_only`]); a late reply to it can still come until then.
    pub fn silence_ends_wait_at(&self, sent_at: Duration) -> Duration {
        sent_at + self.request_time + self.first_byte_timeout.unwrap_or(self.reply_timeout)
    }

    /// A request to one device outside the scheduler (site tools, identity reads, RPC): the
    /// first byte within `response_timeout` (the device's time and the adapter's, counted from
    /// the end of the request), then the longest reply the request allows, with some slack.
    pub fn to_device(line: &LineSettings, request: Request, response_timeout: Duration) -> Self {
        let request_time = line.wire_time(request.encoded_len());
        let reply_time = line.wire_time(request.max_reply_len() + REPLY_SLACK_CHARACTERS);
        Self {
            estimated: request_time + response_timeout + reply_time,
            request_time,
            reply_timeout: response_timeout + reply_time,
            first_byte_timeout: Some(response_timeout),
            late_window: response_timeout.min(MAX_LATE_WINDOW),
            request,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Parity, RequestPdu};

    #[test]
    fn a_request_to_one_device_waits_for_its_longest_reply() {
        let line = LineSettings {
            baud: 9600,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 2,
        };
        let request = Request::classic(
            20,
            RequestPdu::ReadHoldingRegisters {
                start: 0,
                count: 10,
            },
        );
        let timeout = Duration::from_millis(124);
        let transaction = Transaction::to_device(&line, request, timeout);
        // 8 bytes of request; 25 bytes of reply (3 + 20 + CRC) and 32 of slack.
        assert_eq!(transaction.request_time, line.wire_time(8));
        assert_eq!(transaction.first_byte_timeout, Some(timeout));
        assert_eq!(transaction.reply_timeout, timeout + line.wire_time(25 + 32));
        assert_eq!(transaction.late_window, Duration::from_millis(100));
    }
}
