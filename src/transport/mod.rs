//! Getting frames on and off a bus: a serial port (real RS-485 adapter or the simulator's
//! pseudo-terminal), raw RTU frames over TCP, or Modbus TCP (MBAP). [`Transport`] only reads,
//! writes and sleeps; what the bytes mean and when, every timeout, the guard interval and the
//! flush of stale input are decided by the pure [`exchange::Exchange`], which uses its reply
//! window and the protocol's [`ReplyParser`](crate::protocol::ReplyParser).

pub mod exchange;
pub mod fifo;
mod mbap;
mod other_master;
pub mod raw;
mod serial;
/// FIONREAD, shared with the bench's bare master (`src/bench/bare_master.rs`).
#[cfg(feature = "bench")]
pub(crate) use serial::input_queue_len;

use std::io;
use std::path::Path;
use std::time::Duration;

use thiserror::Error;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};

use exchange::{Exchange, Framing, LinkConfig};
use raw::{RawRequest, RawTransfer};
use serial::SerialLink;
use tracing::{debug, warn};

use crate::protocol::{self, LineSettings};
use crate::protocol::{ReplyTiming, Transaction, TransactionOutcome};

pub use mbap::MbapCodec;

/// Why a bus cannot be used (the port task reopens it with a growing delay).
#[derive(Debug, Error)]
pub enum TransportError {
    #[error("cannot open {path}: {source}")]
    Open { path: String, source: io::Error },
    #[error("cannot connect to {address}: {source}")]
    Connect { address: String, source: io::Error },
    #[error("connecting to {address} timed out")]
    ConnectTimeout { address: String },
    #[error("I/O error on {name}: {source}")]
    Io { name: String, source: io::Error },
    #[error("{name} {}", if *serial {
        "went away (a USB adapter unplugged, or its device file removed)"
    } else {
        "closed the connection"
    })]
    Closed { name: String, serial: bool },
    #[error("no transaction on {name} succeeded for {after:?}: closing the connection")]
    Unanswered { name: String, after: Duration },
    #[error("cannot send: {0}")]
    Encode(#[from] protocol::EncodeError),
}

/// Where a bus is.
#[derive(Debug, Clone, PartialEq)]
pub enum Endpoint {
    Serial {
        path: String,
        line: LineSettings,
        /// The pause a reply may make between two bytes when longer than the line's own
        /// allowance ([`exchange::LinkConfig::with_frame_timeout`]): the config's
        /// `frame_timeout_ms`.
        frame_timeout: Duration,
    },
    /// RTU frames over a TCP socket (a transparent gateway).
    RtuOverTcp {
        address: String,
        connect_timeout: Duration,
        /// The pause a reply may make between two bytes, before the TCP lag
        /// ([`exchange::LinkConfig::with_frame_timeout`]): the config's `frame_timeout_ms`.
        frame_timeout: Duration,
    },
    /// Modbus TCP: MBAP header instead of address and CRC.
    ModbusTcp {
        address: String,
        connect_timeout: Duration,
        frame_timeout: Duration,
    },
}

impl Endpoint {
    pub fn name(&self) -> String {
        match self {
            Self::Serial { path, line, .. } => format!("{path} ({line})"),
            Self::RtuOverTcp { address, .. } => format!("tcp://{address}"),
            Self::ModbusTcp { address, .. } => format!("modbus-tcp://{address}"),
        }
    }
}

enum Link {
    Serial(SerialLink),
    Tcp(TcpStream),
}

/// How often, at most, one reply is read after a sleep until its expected end before the line is
/// watched byte by byte again (a device or adapter slower than the wire; garbage).
const MAX_PACED_READS: u32 = 3;

/// Added to a reply's expected end before reading it: the kernel hands received bytes to the
/// reader a little after they arrived (100 µs cost 3 % of the bus's transactions at 115200 for
/// no saving in CPU; docs/performance.md).
const PACING_SLACK: Duration = Duration::from_micros(20);

/// A transaction or raw transfer that has run this long yields to its task's other work at
/// every step: with a link that blocks for short waits ([`SerialLink::block_short_waits`]) it
/// would otherwise never return `Pending` while a line that never falls quiet keeps it going,
/// and the port task's `select!` would not see a shutdown or reload. A transaction at 115200
/// takes ~15 ms: the steps of ordinary ones never yield.
const YIELD_AFTER: Duration = Duration::from_millis(100);

/// Yields once `started` is [`YIELD_AFTER`] ago.
async fn yield_if_long(started: Instant) {
    if started.elapsed() >= YIELD_AFTER {
        tokio::task::yield_now().await;
    }
}

/// An open bus: plain reads, writes and timers around the pure [`Exchange`].
pub struct Transport {
    name: String,
    link: Link,
    exchange: Exchange,
    /// The clock of the exchange: its times are durations since this instant.
    epoch: Instant,
    /// When the operator was last told of another master on this bus, and how many of its
    /// requests were heard since.
    other_master_told: Option<Instant>,
    other_master_requests: u64,
}

/// How often at most the log repeats that another master is heard on a bus.
const OTHER_MASTER_REPEAT: Duration = Duration::from_secs(60);

impl Transport {
    pub async fn open(endpoint: &Endpoint) -> Result<Self, TransportError> {
        let name = endpoint.name();
        let (link, config) = match endpoint {
            Endpoint::Serial {
                path,
                line,
                frame_timeout,
            } => {
                let link = SerialLink::open(path, line).map_err(|source| TransportError::Open {
                    path: path.clone(),
                    source,
                })?;
                let trigger = fifo::receive_fifo_trigger(Path::new(path), &fifo::sysfs_tty());
                if let Some(trigger) = trigger.filter(|&trigger| trigger > 1) {
                    debug!(%path, trigger, "the receive FIFO hands bytes over {trigger} at a time");
                }
                let mut config = LinkConfig::serial(*line).with_frame_timeout(*frame_timeout);
                if let Some(trigger) = trigger {
                    config = config.with_receive_fifo(trigger);
                }
                if link.is_pseudo_terminal() {
                    debug!(%path, "a pseudo-terminal: no wire times its bytes");
                    config = config.on_pseudo_terminal();
                }
                (Link::Serial(link), config)
            }
            Endpoint::RtuOverTcp {
                address,
                connect_timeout,
                frame_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                LinkConfig::tcp(Framing::Rtu).with_frame_timeout(*frame_timeout),
            ),
            Endpoint::ModbusTcp {
                address,
                connect_timeout,
                frame_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                LinkConfig::tcp(Framing::ModbusTcp).with_frame_timeout(*frame_timeout),
            ),
        };
        let mut exchange = Exchange::new(config);
        // Whatever used the line before this handle (this port at other settings, another
        // process) may have just finished: the first request keeps the frame gap too.
        exchange.line_was_busy(Duration::ZERO);
        Ok(Self {
            name,
            link,
            exchange,
            epoch: Instant::now(),
            other_master_told: None,
            other_master_requests: 0,
        })
    }

    /// Tells the operator, at most every [`OTHER_MASTER_REPEAT`], that requests this service
    /// did not send are heard on the bus.
    fn tell_of_other_master(&mut self) {
        let Some(frame) = self.exchange.take_other_master_request() else {
            return;
        };
        self.other_master_requests += 1;
        if self
            .other_master_told
            .is_some_and(|told| told.elapsed() < OTHER_MASTER_REPEAT)
        {
            return;
        }
        warn!(
            port = %self.name,
            request = %protocol::hex(&frame),
            heard = self.other_master_requests,
            "another master is polling this bus (requests rtu2mqtt did not send): replies heard \
             near its requests are not trusted, so its devices may show errors. One master per \
             bus: stop the other one (wb-mqtt-serial: systemctl mask --now wb-mqtt-serial; a \
             laptop's Modbus tool on the same pair)"
        );
        self.other_master_told = Some(Instant::now());
        self.other_master_requests = 0;
    }

    /// True while the transaction started last still waits for the silence before its request:
    /// nothing of it went on the wire (a transaction given up now can be sent again later).
    pub fn request_not_sent(&self) -> bool {
        self.exchange.awaits_transmit()
    }

    /// Keeps this much silence on the bus before every request.
    pub fn set_guard_interval(&mut self, guard_interval: Duration) {
        self.exchange.set_guard_interval(guard_interval);
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The port's receive FIFO hands bytes over `trigger` at a time, whatever the kernel said
    /// when the port was opened (a site tool's `--fifo-trigger`).
    pub fn set_receive_fifo(&mut self, trigger: u32) {
        self.exchange.set_receive_fifo(trigger);
    }

    /// Short waits on a serial line block the thread from now on
    /// ([`SerialLink::block_short_waits`]): only for a transport whose task has its thread
    /// and runtime to itself.
    pub fn block_short_waits(&mut self) {
        if let Link::Serial(link) = &mut self.link {
            link.block_short_waits();
        }
    }

    /// Whether short waits block the thread ([`Self::block_short_waits`]).
    #[cfg(test)]
    pub fn blocks_short_waits(&self) -> bool {
        matches!(&self.link, Link::Serial(link) if link.blocks_short_waits())
    }

    /// When the line was last busy, for the handle that replaces this one.
    pub fn line_busy_until(&self) -> Option<Instant> {
        self.exchange
            .line_busy_until()
            .map(|busy| self.epoch + busy)
    }

    /// This handle replaces one of the same port (closed to reopen it at other settings) whose
    /// line was last busy at `previous`: the frame gap counts from then rather than from this
    /// handle's opening, so a switch after a quiet timeout costs no wait. With no previous
    /// handle (`None`) the gap still counts from the opening. Call it before the first
    /// transaction.
    pub fn continues(&mut self, previous: Option<Instant>) {
        if let Some(busy) = previous {
            // Nothing has run on this handle yet: its clock may as well start then.
            self.epoch = self.epoch.min(busy);
            self.exchange
                .set_line_busy_until(Some(busy.saturating_duration_since(self.epoch)));
        }
    }

    /// The time on the exchange's clock.
    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// Sends the request and waits for its reply. Bus-level failures (silence, garbage) are
    /// outcomes; only a broken port or connection is an error. The timing tells the scheduler
    /// when the reply started, or that it came too late. Every decision is the [`Exchange`]'s;
    /// this only moves bytes and sleeps.
    pub async fn transact(
        &mut self,
        transaction: &Transaction,
    ) -> Result<(TransactionOutcome, ReplyTiming), TransportError> {
        self.exchange.start(transaction)?;
        let started = Instant::now();
        let mut buffer = [0u8; 512];
        let mut paced_reads = 0;
        // The serial line was found quiet and its input empty just now: no flush needed.
        let mut input_empty = false;
        loop {
            yield_if_long(started).await;
            if let Some(transmit) = self.exchange.poll_transmit(self.now()) {
                if transmit.flush_input && !input_empty {
                    self.take_input(&mut buffer)?;
                }
                input_empty = false;
                debug!(port = %self.name, tx = %protocol::hex(&transmit.bytes), "request");
                self.write_all(&transmit.bytes).await?;
                self.exchange.handle_sent(self.now());
            }
            if let Some(result) = self.exchange.poll_outcome() {
                self.tell_of_other_master();
                return Ok(result);
            }
            if let (Some(at), Link::Serial(link)) = (self.exchange.batch_read_at(), &mut self.link)
            {
                let count = match link
                    .read_at(self.epoch + at + PACING_SLACK, &mut buffer)
                    .await
                {
                    Ok(Some(0)) => {
                        return Err(TransportError::Closed {
                            name: self.name.clone(),
                            serial: true,
                        })
                    }
                    Ok(count) => count.unwrap_or(0),
                    Err(source) => {
                        return Err(TransportError::Io {
                            name: self.name.clone(),
                            source,
                        })
                    }
                };
                let bytes = buffer.get(..count).unwrap_or(&[]);
                debug!(port = %self.name, rx = %protocol::hex(bytes), "bytes (batch)");
                self.exchange.handle_batch(self.now(), bytes);
                continue;
            }
            let Some(timeout) = self.exchange.poll_timeout() else {
                // Never after `handle_sent`; a guard against spinning.
                return Ok((TransactionOutcome::NoReply, ReplyTiming::default()));
            };
            let wake = self.epoch + timeout;
            if let (true, Link::Serial(link)) = (self.exchange.awaits_transmit(), &mut self.link) {
                // The silence before the request: checked at its end rather than watched.
                let heard = link
                    .quiet_until(wake, &mut buffer)
                    .await
                    .map_err(|source| TransportError::Io {
                        name: self.name.clone(),
                        source,
                    })?;
                match heard {
                    None => input_empty = true,
                    Some(count) => {
                        let bytes = buffer.get(..count).unwrap_or(&[]);
                        debug!(port = %self.name, rx = %protocol::hex(bytes),
                            "bytes during the silence before a request");
                        let now = self.now();
                        self.exchange.handle_bytes(now, bytes);
                        self.exchange.line_was_busy(now);
                    }
                }
                continue;
            }
            match self.next_bytes(wake, &mut paced_reads, &mut buffer).await? {
                None => self.exchange.handle_timeout(self.now()),
                Some(0) => {
                    return Err(TransportError::Closed {
                        name: self.name.clone(),
                        serial: matches!(self.link, Link::Serial(_)),
                    })
                }
                Some(count) => {
                    let bytes = buffer.get(..count).unwrap_or(&[]);
                    debug!(port = %self.name, rx = %protocol::hex(bytes), "bytes");
                    self.exchange.handle_bytes(self.now(), bytes);
                }
            }
        }
    }

    /// A raw transfer (no protocol): `request`'s bytes out, then what comes back up to its
    /// size, until its first-byte timeout or a silence; every decision is the
    /// [`RawTransfer`]'s. Only a broken port or connection is an error.
    pub async fn transfer_raw(&mut self, request: &RawRequest) -> Result<Vec<u8>, TransportError> {
        // The same silence before it as before any request.
        tokio::time::sleep_until(self.epoch + self.exchange.transmit_at()).await;
        let mut transfer = RawTransfer::new(request.clone(), *self.exchange.config());
        let started = Instant::now();
        let mut buffer = [0u8; 512];
        loop {
            yield_if_long(started).await;
            if let Some(transmit) = transfer.poll_transmit(self.now()) {
                if transmit.flush_input {
                    self.take_input(&mut buffer)?;
                }
                // Its echo, or a device's echo of a write in it, is no other master's request.
                let now = self.now();
                self.exchange.sent_elsewhere(now, &transmit.bytes);
                debug!(port = %self.name, tx = %protocol::hex(&transmit.bytes), "raw request");
                self.write_all(&transmit.bytes).await?;
                transfer.handle_sent(self.now());
            }
            if let Some(answer) = transfer.poll_outcome() {
                if let Some(busy) = transfer.line_busy_until() {
                    self.exchange.line_was_busy(busy);
                }
                return Ok(answer);
            }
            let Some(timeout) = transfer.poll_timeout() else {
                return Ok(Vec::new());
            };
            let wake = self.epoch + timeout;
            // A raw answer has no known length: read it as it comes.
            let mut no_pacing = MAX_PACED_READS;
            match self.next_bytes(wake, &mut no_pacing, &mut buffer).await? {
                None => transfer.handle_timeout(self.now()),
                Some(0) => {
                    return Err(TransportError::Closed {
                        name: self.name.clone(),
                        serial: matches!(self.link, Link::Serial(_)),
                    })
                }
                Some(count) => {
                    let bytes = buffer.get(..count).unwrap_or(&[]);
                    debug!(port = %self.name, rx = %protocol::hex(bytes), "raw bytes");
                    transfer.handle_bytes(self.now(), bytes);
                }
            }
        }
    }

    /// The next bytes on the line (`Some(0)`: the connection closed), or `None` when `wake` came
    /// first. On a serial line, once a reply of known length has begun, the transport sleeps
    /// until it should be complete and reads it in one go (never past `wake`, so no timeout
    /// changes); if nothing more came by then, or after a few such reads, it watches the line.
    async fn next_bytes(
        &mut self,
        wake: Instant,
        paced_reads: &mut u32,
        buffer: &mut [u8],
    ) -> Result<Option<usize>, TransportError> {
        let io_error = |name: &str, source| TransportError::Io {
            name: name.to_owned(),
            source,
        };
        let complete_at = self.exchange.reply_complete_at();
        match &mut self.link {
            Link::Serial(link) => {
                if let Some(complete_at) = complete_at.filter(|_| *paced_reads < MAX_PACED_READS) {
                    let at = self.epoch + complete_at + PACING_SLACK;
                    if at < wake {
                        *paced_reads += 1;
                        match link.read_at(at, buffer).await {
                            Ok(Some(count)) => return Ok(Some(count)),
                            // Nothing more came: the line's own timing rules from here.
                            Ok(None) => *paced_reads = MAX_PACED_READS,
                            Err(source) => return Err(io_error(&self.name, source)),
                        }
                    }
                }
                link.read_until(wake, buffer)
                    .await
                    .map_err(|source| io_error(&self.name, source))
            }
            Link::Tcp(stream) => match timeout_at(wake, AsyncReadExt::read(stream, buffer)).await {
                Err(_elapsed) => Ok(None),
                Ok(Ok(count)) => Ok(Some(count)),
                Ok(Err(source)) => Err(io_error(&self.name, source)),
            },
        }
    }

    /// Drops whatever arrived unasked (late replies, noise) so it cannot pass for the next reply.
    /// Empties the input before a request, handing what came meanwhile (up to `buffer`'s
    /// size; the rest is dropped) to the exchange: not a reply to anything, but another
    /// master's request may be among it.
    fn take_input(&mut self, buffer: &mut [u8]) -> Result<(), TransportError> {
        let io_error = |name: &str, source| TransportError::Io {
            name: name.to_owned(),
            source,
        };
        let count = match &mut self.link {
            Link::Serial(link) => link
                .take_input(buffer)
                .map_err(|source| io_error(&self.name, source))?,
            Link::Tcp(stream) => {
                let mut count = 0;
                let mut scratch = [0u8; 256];
                loop {
                    match stream.try_read(&mut scratch) {
                        Ok(0) => {
                            return Err(TransportError::Closed {
                                name: self.name.clone(),
                                serial: false,
                            })
                        }
                        Ok(read) => {
                            let kept = read.min(buffer.len() - count);
                            if let (Some(to), Some(from)) =
                                (buffer.get_mut(count..count + kept), scratch.get(..kept))
                            {
                                to.copy_from_slice(from);
                            }
                            count += kept;
                        }
                        Err(err) if err.kind() == io::ErrorKind::WouldBlock => break count,
                        Err(source) => return Err(io_error(&self.name, source)),
                    }
                }
            }
        };
        if let Some(bytes) = buffer.get(..count).filter(|bytes| !bytes.is_empty()) {
            debug!(port = %self.name, rx = %protocol::hex(bytes), "bytes before a request");
            self.exchange.handle_bytes(self.now(), bytes);
        }
        Ok(())
    }

    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let result = match &mut self.link {
            Link::Serial(link) => link.write_all(bytes).await,
            Link::Tcp(stream) => AsyncWriteExt::write_all(stream, bytes).await,
        };
        result.map_err(|source| TransportError::Io {
            name: self.name.clone(),
            source,
        })
    }
}

async fn connect(address: &str, connect_timeout: Duration) -> Result<TcpStream, TransportError> {
    let stream = tokio::time::timeout(connect_timeout, TcpStream::connect(address))
        .await
        .map_err(|_| TransportError::ConnectTimeout {
            address: address.to_owned(),
        })?
        .map_err(|source| TransportError::Connect {
            address: address.to_owned(),
            source,
        })?;
    // Small frames must leave at once.
    stream
        .set_nodelay(true)
        .map_err(|source| TransportError::Connect {
            address: address.to_owned(),
            source,
        })?;
    // A path that breaks without a FIN or RST (a NAT's timeout, a bridge powered off) is found
    // by the kernel: keepalive probes while the link is idle, and a bound on unacknowledged
    // requests while it is not (else ~15 minutes of retransmissions). The port task's own rule
    // (`connection_timeout_ms`) reconnects a gateway that keeps the connection but answers
    // nothing. Best effort: a socket that refuses these options still works.
    let socket = socket2::SockRef::from(&stream);
    let keepalive = socket2::TcpKeepalive::new()
        .with_time(TCP_KEEPALIVE_IDLE)
        .with_interval(TCP_KEEPALIVE_INTERVAL)
        .with_retries(TCP_KEEPALIVE_PROBES);
    if let Err(err) = socket.set_tcp_keepalive(&keepalive) {
        debug!(%address, %err, "TCP keepalive not set");
    }
    if let Err(err) = socket.set_tcp_user_timeout(Some(TCP_USER_TIMEOUT)) {
        debug!(%address, %err, "TCP user timeout not set");
    }
    Ok(stream)
}

/// Idle time before the first keepalive probe of a gateway connection, the time between probes,
/// and how many unanswered probes drop it: a dead idle path is noticed within 25 s.
const TCP_KEEPALIVE_IDLE: Duration = Duration::from_secs(10);
const TCP_KEEPALIVE_INTERVAL: Duration = Duration::from_secs(5);
const TCP_KEEPALIVE_PROBES: u32 = 3;
/// How long sent data may stay unacknowledged before the kernel drops the connection.
const TCP_USER_TIMEOUT: Duration = Duration::from_secs(30);

/// The transport on a pseudo-terminal that misbehaves (found by the review of the transport,
/// docs/reliability.md).
#[cfg(test)]
mod line_faults {
    use super::*;
    use crate::protocol::{Parity, Request, RequestPdu};
    use std::io::Write;
    use std::os::fd::AsFd;

    const LINE: LineSettings = LineSettings::new(9600, Parity::None, 2);

    /// A transport on a fresh pty's slave, and the pty's master as the far end of the line.
    /// A line that never falls quiet: a byte every `every` from the pty's other end, until
    /// dropped.
    struct Babbler {
        stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
        thread: Option<std::thread::JoinHandle<()>>,
    }

    impl Babbler {
        fn start(mut master: std::fs::File, every: Duration) -> Self {
            let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
            let stopped = stop.clone();
            let thread = std::thread::spawn(move || {
                while !stopped.load(std::sync::atomic::Ordering::Relaxed) {
                    let _ = master.write_all(&[0x55]);
                    // Paces the bytes; it synchronises nothing.
                    std::thread::sleep(every);
                }
            });
            Self {
                stop,
                thread: Some(thread),
            }
        }
    }

    impl Drop for Babbler {
        fn drop(&mut self) {
            self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
            if let Some(thread) = self.thread.take() {
                let _ = thread.join();
            }
        }
    }

    async fn transport_on_a_pty(line: LineSettings) -> (Transport, std::fs::File) {
        let pty = nix::pty::openpty(None, None).expect("a pty");
        let path = nix::unistd::ttyname(pty.slave.as_fd()).expect("its name");
        let endpoint = Endpoint::Serial {
            path: path.to_string_lossy().into_owned(),
            line,
            frame_timeout: exchange::DEFAULT_FRAME_TIMEOUT,
        };
        let transport = Transport::open(&endpoint).await.expect("opens");
        drop(pty.slave);
        (transport, std::fs::File::from(pty.master))
    }

    /// Holding register 0 of device 1, with these timeouts.
    fn read_one_register(reply_timeout: Duration, first_byte_timeout: Duration) -> Transaction {
        Transaction {
            request_time: LINE.wire_time(8),
            reply_timeout,
            first_byte_timeout: Some(first_byte_timeout),
            late_window: Duration::ZERO,
            estimated: reply_timeout,
            request: Request::classic(1, RequestPdu::ReadHoldingRegisters { start: 0, count: 1 }),
        }
    }

    /// A line that never falls quiet for 3.5 characters (a stuck transmitter, a babbling
    /// device: a byte every 2 ms at 9600, whose frame gap is 4 ms). The request used to wait
    /// for the silence before it with no bound: `transact` never returned, so the scheduler
    /// never learned the bus was unusable and the devices were never flagged. Now the wait ends
    /// after the reply timeout and the drain window (1.1 s here) with a garbled transaction.
    /// (The 5 s bound only stops a hanging test.)
    #[tokio::test]
    async fn a_babbling_line_fails_the_transaction_as_garbled() {
        let (mut transport, master) = transport_on_a_pty(LINE).await;
        let babbler = Babbler::start(master, Duration::from_millis(2));
        let transaction = read_one_register(Duration::from_millis(100), Duration::from_millis(50));
        let result =
            tokio::time::timeout(Duration::from_secs(5), transport.transact(&transaction)).await;
        drop(babbler);
        let outcome = result
            .expect("transact still waiting for a quiet line after 5 s (100 ms timeouts)")
            .expect("the port works");
        assert_eq!(outcome.0, TransactionOutcome::Garbled);
    }

    /// Review of the blocking short waits (27 Nov 2026): the port task abandons a transaction
    /// for a shutdown or a reload through `select!` (`serve`: "Shutdown never waits for the
    /// bus: ... a babbling line"), which only works when `transact` returns `Pending`. On a
    /// babbling line the request waits for silence in short `quiet_until`s (here the 40 ms
    /// guard interval), which block the thread: `transact` yields only when its coop budget
    /// (128) is spent, ~5 s here, and the port's `shutdown.changed()` (cooperative too) is
    /// then polled first only half the time. Without blocking waits it is abandoned at once.
    #[tokio::test]
    async fn a_transaction_waiting_for_a_quiet_line_is_abandoned_at_once() {
        for blocking in [false, true] {
            let (mut transport, master) = transport_on_a_pty(LINE).await;
            if blocking {
                transport.block_short_waits();
            }
            transport.set_guard_interval(Duration::from_millis(40));
            let babbler = Babbler::start(master, Duration::from_millis(10));
            let transaction = read_one_register(Duration::from_secs(60), Duration::from_secs(60));
            let started = std::time::Instant::now();
            tokio::select! {
                biased;
                () = tokio::time::sleep(Duration::from_millis(100)) => {}
                result = transport.transact(&transaction) => panic!("ended: {result:?}"),
            }
            let took = started.elapsed();
            drop(babbler);
            assert!(
                took < Duration::from_secs(1),
                "blocking waits {blocking}: a 100 ms shutdown abandoned the transaction after \
                 {took:?}"
            );
        }
    }

    /// A device stack on the other end of a pty pair (pymodbus's serial server behind socat,
    /// tests/interop_device.rs) answers as soon as the request is written: long before the
    /// request's 8 bytes would have crossed a wire at 9600 (9.2 ms). Its reply was thrown away
    /// as "bytes before the request left the wire" (an echo or a straggler on a real line) and
    /// every read of such a device ended in "no reply", `rtu2mqtt read` and `run` alike. A pty
    /// has no wire: the reply is taken.
    #[tokio::test]
    async fn a_reply_written_at_once_on_a_pty_is_taken() {
        use std::io::Read;
        let (mut transport, mut device) = transport_on_a_pty(LINE).await;
        let reply = crate::protocol::Reply::classic(
            1,
            crate::protocol::ResponsePdu::ReadHoldingRegisters { values: vec![1234] },
        );
        let frame = reply.encode().expect("encodes");
        let answering = std::thread::spawn(move || {
            let mut request = [0u8; 8];
            device.read_exact(&mut request).expect("the request");
            device.write_all(&frame).expect("the reply");
            device
        });
        let transaction = read_one_register(Duration::from_millis(200), Duration::from_millis(150));
        let (outcome, _) =
            tokio::time::timeout(Duration::from_secs(5), transport.transact(&transaction))
                .await
                .expect("in time")
                .expect("the port works");
        let _device = answering.join().expect("the device thread");
        assert_eq!(outcome, TransactionOutcome::Reply(reply));
    }
}
