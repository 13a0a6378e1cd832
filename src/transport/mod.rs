//! Getting frames on and off a bus: a serial port (real RS-485 adapter or the simulator's
//! pseudo-terminal), raw RTU frames over TCP, or Modbus TCP (MBAP). Every reply is found by the
//! protocol's [`ReplyParser`], within the reply window of [`receive`]: timeouts counted from the
//! end of the request on the wire, a late window after a timeout, a quiet line before the next
//! request. Stale input is flushed before each request.

mod mbap;
pub mod receive;

use std::io;
use std::time::Duration;

use thiserror::Error;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};

use receive::{Received, ReplyWindow};
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tracing::debug;

use crate::port::{Outcome, ReplyTiming, Transaction};
use crate::protocol::{self, LineSettings, ParseStatus, ReplyParser};

pub use mbap::MbapCodec;

/// Why a bus cannot be used (the port task reopens it with a growing delay).
#[derive(Debug, Error)]
pub enum TransportError {
    #[error("cannot open {path}: {source}")]
    Open {
        path: String,
        source: tokio_serial::Error,
    },
    #[error("cannot connect to {address}: {source}")]
    Connect { address: String, source: io::Error },
    #[error("connecting to {address} timed out")]
    ConnectTimeout { address: String },
    #[error("I/O error on {name}: {source}")]
    Io { name: String, source: io::Error },
    #[error("{name} closed the connection")]
    Closed { name: String },
    #[error("cannot send: {0}")]
    Encode(#[from] protocol::EncodeError),
}

/// Where a bus is.
#[derive(Debug, Clone, PartialEq)]
pub enum Endpoint {
    Serial {
        path: String,
        line: LineSettings,
    },
    /// RTU frames over a TCP socket (a transparent gateway).
    RtuOverTcp {
        address: String,
        connect_timeout: Duration,
    },
    /// Modbus TCP: MBAP header instead of address and CRC.
    ModbusTcp {
        address: String,
        connect_timeout: Duration,
    },
}

impl Endpoint {
    pub fn name(&self) -> String {
        match self {
            Self::Serial { path, line } => format!("{path} ({line})"),
            Self::RtuOverTcp { address, .. } => format!("tcp://{address}"),
            Self::ModbusTcp { address, .. } => format!("modbus-tcp://{address}"),
        }
    }
}

enum Link {
    Serial(SerialStream),
    Tcp(TcpStream),
}

/// An open bus.
pub struct Transport {
    name: String,
    link: Link,
    mbap: Option<MbapCodec>,
    /// Silence between bytes after which a started reply is given up.
    inter_byte_timeout: Duration,
    /// Silence kept before every request.
    guard_interval: Duration,
    /// When the bus was last busy (end of the last reply or request).
    last_activity: Instant,
    /// The clock of reply windows.
    epoch: Instant,
}

impl Transport {
    pub async fn open(endpoint: &Endpoint) -> Result<Self, TransportError> {
        let name = endpoint.name();
        let (link, mbap, inter_byte_timeout) = match endpoint {
            Endpoint::Serial { path, line } => {
                let builder = tokio_serial::new(path, line.baud)
                    .data_bits(match line.data_bits {
                        5 => tokio_serial::DataBits::Five,
                        6 => tokio_serial::DataBits::Six,
                        7 => tokio_serial::DataBits::Seven,
                        _ => tokio_serial::DataBits::Eight,
                    })
                    .parity(match line.parity {
                        protocol::Parity::None => tokio_serial::Parity::None,
                        protocol::Parity::Even => tokio_serial::Parity::Even,
                        protocol::Parity::Odd => tokio_serial::Parity::Odd,
                    })
                    .stop_bits(if line.stop_bits == 2 {
                        tokio_serial::StopBits::Two
                    } else {
                        tokio_serial::StopBits::One
                    });
                let stream =
                    builder
                        .open_native_async()
                        .map_err(|source| TransportError::Open {
                            path: path.clone(),
                            source,
                        })?;
                // USB adapters deliver in bursts: allow several characters of silence, at least 20 ms
                // (wb-mqtt-serial's default frame timeout).
                let gap = (line.char_time() * 8).max(Duration::from_millis(20));
                (Link::Serial(stream), None, gap)
            }
            Endpoint::RtuOverTcp {
                address,
                connect_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                None,
                Duration::from_millis(50),
            ),
            Endpoint::ModbusTcp {
                address,
                connect_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                Some(MbapCodec::default()),
                Duration::from_millis(50),
            ),
        };
        Ok(Self {
            name,
            link,
            mbap,
            inter_byte_timeout,
            guard_interval: Duration::ZERO,
            last_activity: Instant::now(),
            epoch: Instant::now(),
        })
    }

    /// Keeps this much silence on the bus before every request.
    pub fn set_guard_interval(&mut self, guard_interval: Duration) {
        self.guard_interval = guard_interval;
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Sends the request and waits for its reply. Bus-level failures (silence, garbage) are
    /// outcomes; only a broken port or connection is an error. The timing tells the scheduler
    /// when the reply started, or that it came too late.
    pub async fn transact(
        &mut self,
        transaction: &Transaction,
    ) -> Result<(Outcome, ReplyTiming), TransportError> {
        self.flush_input()?;
        let frame = transaction.request.encode()?;
        let wire = match &mut self.mbap {
            Some(mbap) => mbap.wrap(&frame),
            None => frame.clone(),
        };
        if !self.guard_interval.is_zero() {
            tokio::time::sleep_until(self.last_activity + self.guard_interval).await;
        }
        debug!(port = %self.name, tx = %protocol::hex(&frame), "request");
        let write_started = self.epoch.elapsed();
        self.write_all(&wire).await?;
        let serial = matches!(self.link, Link::Serial(_));
        let mut window = ReplyWindow::new(
            transaction,
            (write_started, self.epoch.elapsed()),
            self.inter_byte_timeout,
            serial,
        );
        self.last_activity = self.epoch + window.clock_start();
        if !transaction.request.expects_reply() {
            // A broadcast: nobody answers, but the line is busy until it has left.
            tokio::time::sleep_until(self.last_activity).await;
            return Ok((Outcome::NoReply, ReplyTiming::default()));
        }
        let mut parser = ReplyParser::for_request(&transaction.request);
        let mut garbled = false;
        let mut buffer = [0u8; 512];
        while !window.is_finished() {
            let wake = self.epoch + window.wake_at();
            let count = match timeout_at(wake, self.read(&mut buffer)).await {
                Err(_elapsed) => {
                    window.expire(self.epoch.elapsed());
                    continue;
                }
                Ok(Ok(0)) => {
                    return Err(TransportError::Closed {
                        name: self.name.clone(),
                    })
                }
                Ok(Ok(count)) => count,
                Ok(Err(source)) => {
                    return Err(TransportError::Io {
                        name: self.name.clone(),
                        source,
                    })
                }
            };
            let bytes = buffer.get(..count).unwrap_or(&[]);
            self.last_activity = Instant::now();
            let unwrapped = match &mut self.mbap {
                Some(mbap) => mbap.unwrap(bytes),
                None => bytes.to_vec(),
            };
            if window.receive(self.epoch.elapsed()) == Received::Discard {
                debug!(port = %self.name, rx = %protocol::hex(bytes), "bytes outside the reply window dropped");
                continue;
            }
            debug!(port = %self.name, rx = %protocol::hex(bytes), "reply bytes");
            parser.push(&unwrapped);
            loop {
                match parser.poll() {
                    ParseStatus::NeedMore => break,
                    ParseStatus::Frame(parsed) => {
                        return Ok((Outcome::Reply(parsed.reply), window.timing()))
                    }
                    ParseStatus::Error(err) => {
                        debug!(port = %self.name, %err, "dropped reply bytes");
                        garbled = true;
                    }
                }
            }
        }
        let outcome = if garbled || !parser.buffered().is_empty() {
            Outcome::Garbled
        } else {
            Outcome::NoReply
        };
        Ok((outcome, window.timing()))
    }

    /// Drops whatever arrived unasked (late replies, noise) so it cannot pass for the next reply.
    fn flush_input(&mut self) -> Result<(), TransportError> {
        match &mut self.link {
            Link::Serial(stream) => {
                stream
                    .clear(tokio_serial::ClearBuffer::Input)
                    .map_err(|source| TransportError::Io {
                        name: self.name.clone(),
                        source: source.into(),
                    })
            }
            Link::Tcp(stream) => {
                let mut scratch = [0u8; 256];
                loop {
                    match stream.try_read(&mut scratch) {
                        Ok(0) => {
                            return Err(TransportError::Closed {
                                name: self.name.clone(),
                            })
                        }
                        Ok(_) => continue,
                        Err(err) if err.kind() == io::ErrorKind::WouldBlock => return Ok(()),
                        Err(source) => {
                            return Err(TransportError::Io {
                                name: self.name.clone(),
                                source,
                            })
                        }
                    }
                }
            }
        }
    }

    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let result = match &mut self.link {
            Link::Serial(stream) => AsyncWriteExt::write_all(stream, bytes).await,
            Link::Tcp(stream) => AsyncWriteExt::write_all(stream, bytes).await,
        };
        result.map_err(|source| TransportError::Io {
            name: self.name.clone(),
            source,
        })
    }

    async fn read(&mut self, buffer: &mut [u8]) -> io::Result<usize> {
        match &mut self.link {
            Link::Serial(stream) => read_some(stream, buffer).await,
            Link::Tcp(stream) => read_some(stream, buffer).await,
        }
    }
}

async fn read_some<R: AsyncRead + Unpin>(reader: &mut R, buffer: &mut [u8]) -> io::Result<usize> {
    AsyncReadExt::read(reader, buffer).await
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
    Ok(stream)
}
