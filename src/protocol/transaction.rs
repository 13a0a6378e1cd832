//! One bus transaction as every layer sees it: the request with its timeouts, what the line
//! carried back, and when. The scheduler (`port`) makes them, the transport carries them out;
//! both take the types from here so that neither depends on the other.

use std::time::Duration;

use super::{Reply, Request};

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
}

/// What came back for a transaction.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Reply(Reply),
    /// Nothing, or nothing that answers the request, before the timeout.
    NoReply,
    /// Bytes arrived but no valid frame (CRC errors, a collision).
    Garbled,
}
