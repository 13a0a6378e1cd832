//! Getting frames on and off a bus: a serial port (real RS-485 adapter or the simulator's
//! pseudo-terminal), raw RTU frames over TCP, or Modbus TCP (MBAP). [`Transport`] only reads,
//! writes and sleeps; what the bytes mean and when, every timeout, the guard interval and the
//! flush of stale input are decided by the pure [`exchange::Exchange`], which uses the reply
//! window of [`receive`] and the protocol's [`ReplyParser`](crate::protocol::ReplyParser).

pub mod exchange;
mod mbap;
pub mod receive;

use std::io;
use std::time::Duration;

use thiserror::Error;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{timeout_at, Instant};

use exchange::{Exchange, Framing, LinkConfig};
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tracing::debug;

use crate::port::{Outcome, ReplyTiming, Transaction};
use crate::protocol::{self, LineSettings};

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

/// An open bus: plain reads, writes and timers around the pure [`Exchange`].
pub struct Transport {
    name: String,
    link: Link,
    exchange: Exchange,
    /// The clock of the exchange: its times are durations since this instant.
    epoch: Instant,
}

impl Transport {
    pub async fn open(endpoint: &Endpoint) -> Result<Self, TransportError> {
        let name = endpoint.name();
        let (link, config) = match endpoint {
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
                let config = LinkConfig {
                    framing: Framing::Rtu,
                    serial: Some(*line),
                    quiet_gap: gap,
                    guard_interval: Duration::ZERO,
                };
                (Link::Serial(stream), config)
            }
            Endpoint::RtuOverTcp {
                address,
                connect_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                tcp_config(Framing::Rtu),
            ),
            Endpoint::ModbusTcp {
                address,
                connect_timeout,
            } => (
                Link::Tcp(connect(address, *connect_timeout).await?),
                tcp_config(Framing::ModbusTcp),
            ),
        };
        Ok(Self {
            name,
            link,
            exchange: Exchange::new(config),
            epoch: Instant::now(),
        })
    }

    /// Keeps this much silence on the bus before every request.
    pub fn set_guard_interval(&mut self, guard_interval: Duration) {
        self.exchange.set_guard_interval(guard_interval);
    }

    pub fn name(&self) -> &str {
        &self.name
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
    ) -> Result<(Outcome, ReplyTiming), TransportError> {
        self.exchange.start(transaction)?;
        let mut buffer = [0u8; 512];
        loop {
            if let Some(transmit) = self.exchange.poll_transmit(self.now()) {
                if transmit.flush_input {
                    self.flush_input()?;
                }
                debug!(port = %self.name, tx = %protocol::hex(&transmit.bytes), "request");
                self.write_all(&transmit.bytes).await?;
                self.exchange.handle_sent(self.now());
            }
            if let Some(result) = self.exchange.poll_outcome() {
                return Ok(result);
            }
            let Some(timeout) = self.exchange.poll_timeout() else {
                // Never after `handle_sent`; a guard against spinning.
                return Ok((Outcome::NoReply, ReplyTiming::default()));
            };
            let wake = self.epoch + timeout;
            match timeout_at(wake, self.read(&mut buffer)).await {
                Err(_elapsed) => self.exchange.handle_timeout(self.now()),
                Ok(Ok(0)) => {
                    return Err(TransportError::Closed {
                        name: self.name.clone(),
                    })
                }
                Ok(Ok(count)) => {
                    let bytes = buffer.get(..count).unwrap_or(&[]);
                    debug!(port = %self.name, rx = %protocol::hex(bytes), "bytes");
                    self.exchange.handle_bytes(self.now(), bytes);
                }
                Ok(Err(source)) => {
                    return Err(TransportError::Io {
                        name: self.name.clone(),
                        source,
                    })
                }
            }
        }
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

/// A TCP link: the far side's serial timing is unknown, so no early bytes are thrown away and a
/// frame may pause for a network's delay.
fn tcp_config(framing: Framing) -> LinkConfig {
    LinkConfig {
        framing,
        serial: None,
        quiet_gap: Duration::from_millis(50),
        guard_interval: Duration::ZERO,
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
    Ok(stream)
}
