//! The site tools' one IO layer: a serial port switched between port settings, the original
//! settings put back at the end, and the few exchanges the tools need (Fast Modbus scan of one
//! setting, requests by serial number, classic requests), each bounded by its timeouts. Frames
//! and reply windows come from the protocol core and the transport.

use std::fs::File;
use std::io;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::Duration;

use nix::fcntl::{Flock, FlockArg};
use nix::sys::termios::{self, SetArg, Termios};
use thiserror::Error;
use tracing::{debug, info, warn};

use crate::port::{Transaction, TransactionOutcome};
use crate::protocol::{
    fast::{self, FastReply},
    LineSettings, Parity, Reply, ReplyBody, Request, RequestPdu, ResponsePdu,
};
use crate::transport::fifo::{self, FifoForTool};
use crate::transport::{Endpoint, Transport, TransportError};

use super::report::{Identity, ScanReport, SettingProblem};
use super::values::standard_text;

/// Why the port cannot be used at all (exit code 3).
#[derive(Debug, Error)]
pub enum PortError {
    #[error(
        "{path} does not exist: check that the USB-RS485 adapter is plugged in and the name is \
         right (ls /dev/ttyUSB* /dev/ttyACM* /dev/ttyRS485*)"
    )]
    Missing { path: String },
    #[error(
        "no permission to open {path}: run as root or add your user to the group that owns it \
         (usually dialout: sudo usermod -aG dialout $USER, then log in again)"
    )]
    PermissionDenied { path: String },
    #[error(
        "{path} is busy: another program has it open (the rtu2mqtt or wb-mqtt-serial service?). \
         Stop it first (systemctl stop rtu2mqtt) and try again, or go through the rtu2mqtt \
         service: add --broker HOST[:PORT] (or --service-config FILE naming it; --via-mqtt to \
         go through it even when the port is free) to scan, set-address, fix-addresses, read, \
         write or events"
    )]
    Busy { path: String },
    #[error("{path} is not a serial port: {source}")]
    NotSerial { path: String, source: nix::Error },
    #[error("cannot use {path}: {source}")]
    Other { path: String, source: io::Error },
    #[error("{0}")]
    Transport(#[from] TransportError),
    /// Through a running daemon's bus queue (MQTT RPC).
    #[error("{0}")]
    Queued(#[from] crate::daemon::bus_queue::BusQueueError),
    /// The running service could not be asked (broker, no reply, refused).
    #[error("{0}")]
    Service(String),
}

/// What came back for one request.
#[derive(Debug, Clone, PartialEq)]
pub enum Answer {
    /// A reply PDU (an exception too).
    Pdu(ResponsePdu),
    NoReply,
    /// Bytes, but no valid frame (bad CRC, collision, wrong port settings on the other side).
    Garbled,
}

/// How many scan rounds one setting may take: more than the 247 addresses a bus can hold, so a
/// device that keeps answering cannot keep the scan going forever.
const MAX_SCAN_ROUNDS: usize = 300;
/// Garbled scan replies in a row after which a setting is given up.
const MAX_GARBLED_IN_A_ROW: usize = 3;
/// Times a setting's scan starts over after a reply that could not be read.
const MAX_SCAN_RESTARTS: usize = 2;
/// Response timeout of requests to devices a scan has just found.
pub const KNOWN_DEVICE_TIMEOUT: Duration = Duration::from_millis(500);

/// The serial port, the settings it had before, and the transport at the current setting.
pub struct ToolPort {
    path: String,
    /// Kept open so the original settings can be put back, even after a failed open.
    saved: Option<(File, Termios)>,
    current: Option<(LineSettings, Transport)>,
    /// Added to every timeout: what a USB adapter and a loaded machine add to a reply's arrival.
    pub latency: Duration,
    /// The port's receive FIFO, lowered to 1 byte for the tool's run where it can be (put back
    /// on restore).
    fifo: FifoForTool,
    /// The FIFO trigger the operator named (`--fifo-trigger`), whatever the kernel says.
    fifo_trigger: Option<u32>,
}

impl ToolPort {
    /// Checks that the port exists, may be opened, is a serial port and is not in use, and
    /// remembers its settings.
    pub fn open(path: &str, latency: Duration) -> Result<Self, PortError> {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(path)
            .map_err(|source| classify(path, source))?;
        // The daemon (and anything built on serialport) holds an exclusive flock on its port;
        // that also catches a busy port when running as root, which TIOCEXCL does not stop.
        let file = match Flock::lock(file, FlockArg::LockExclusiveNonblock) {
            Ok(locked) => locked.unlock().map_err(|(_, errno)| PortError::Other {
                path: path.to_owned(),
                source: errno.into(),
            })?,
            Err((_, nix::Error::EWOULDBLOCK)) => {
                return Err(PortError::Busy {
                    path: path.to_owned(),
                })
            }
            Err((file, _)) => file,
        };
        let original = termios::tcgetattr(&file).map_err(|source| PortError::NotSerial {
            path: path.to_owned(),
            source,
        })?;
        Ok(Self {
            path: path.to_owned(),
            saved: Some((file, original)),
            current: None,
            latency,
            fifo: FifoForTool::AsItIs,
            fifo_trigger: None,
        })
    }

    /// Makes the port hand bytes over as they come where the kernel allows it: a receive FIFO
    /// that collects several bytes before handing them over is lowered to 1 byte for the tool's
    /// run. Where it cannot be (or `named`, the operator's `--fifo-trigger`, says how many bytes
    /// it collects), every reply is waited for as the FIFO may hand it over: slower, never blind.
    pub fn with_receive_fifo(mut self, named: Option<u32>) -> Self {
        if let Some(trigger) = named {
            self.fifo_trigger = Some(trigger.max(1));
            return self;
        }
        self.fifo = fifo::lower_for_tool(Path::new(&self.path), &fifo::sysfs_tty());
        match &self.fifo {
            FifoForTool::AsItIs => {}
            FifoForTool::Lowered(lowered) => info!(
                port = %self.path,
                "receive FIFO set to hand bytes over one at a time for this run (it collected {} \
                 bytes; put back at the end)",
                lowered.previous
            ),
            FifoForTool::Holds { trigger, why } => warn!(
                port = %self.path,
                "the port's receive FIFO hands bytes over {trigger} at a time and could not be \
                 set to 1 ({why}); every empty setting now waits for the whole arbitration \
                 (slower; run as root for a fast scan)"
            ),
        }
        self
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    /// The transport at `line`, reopened when the setting changes.
    async fn at(&mut self, line: LineSettings) -> Result<&mut Transport, PortError> {
        if self.current.as_ref().map(|(l, _)| *l) != Some(line) {
            let busy_until = self
                .current
                .as_ref()
                .and_then(|(_, transport)| transport.line_busy_until());
            self.current = None;
            // Devices the tools meet are unknown: wb-mqtt-serial's default frame timeout.
            let endpoint = Endpoint::Serial {
                path: self.path.clone(),
                line,
                frame_timeout: crate::transport::exchange::DEFAULT_FRAME_TIMEOUT,
            };
            let mut transport = Transport::open(&endpoint).await.map_err(|err| match err {
                TransportError::Open { source, .. } => classify(&self.path, source),
                other => PortError::Transport(other),
            })?;
            transport.continues(busy_until);
            if let Some(trigger) = self.fifo_trigger {
                transport.set_receive_fifo(trigger);
            }
            self.current = Some((line, transport));
        }
        match &mut self.current {
            Some((_, transport)) => Ok(transport),
            None => unreachable_port(&self.path),
        }
    }

    /// Closes the transport and puts the port's original settings back.
    pub fn restore(&mut self) {
        self.current = None;
        // Dropping a lowered trigger puts the old one back.
        self.fifo = FifoForTool::AsItIs;
        if let Some((file, original)) = self.saved.take() {
            if let Err(err) = termios::tcsetattr(&file, SetArg::TCSANOW, &original) {
                debug!(port = %self.path, %err, "could not restore the port settings");
            }
        }
    }
}

/// A line the site tools talk through: their own serial port ([`ToolPort`]), or a running
/// daemon's port through its bus queue (MQTT RPC). The exchanges below are built on `transact`.
// The futures are Send for the two implementations (checked where the daemon spawns them).
#[allow(async_fn_in_trait)]
pub trait ToolBus {
    /// Added to every timeout: what a USB adapter and a loaded machine add.
    fn latency(&self) -> Duration;

    /// The function code of the scan and of requests by serial number: 0x46, or 0x60 for a
    /// client that asks for the deprecated command (`port/Scan` `"command": 96`).
    fn fast_function(&self) -> u8 {
        fast::FUNCTION
    }

    /// One transaction at `line`.
    async fn transact(
        &mut self,
        line: LineSettings,
        transaction: Transaction,
    ) -> Result<TransactionOutcome, PortError>;

    /// The Fast Modbus scan at one setting: scan start, then continue until a device says the
    /// scan is over. New devices go into `report`; trouble becomes a problem of this setting.
    /// Returns the (serial, address) pairs seen at this setting.
    async fn scan_setting(
        &mut self,
        line: LineSettings,
        report: &mut ScanReport,
    ) -> Result<Vec<(u32, u8)>, PortError> {
        let mut seen = Vec::new();
        let mut garbled_in_a_row = 0;
        let mut restarts = 0;
        let mut retried_silence = false;
        let function = self.fast_function();
        let start = Request::scan_start().with_fast_function(function);
        let next = Request::scan_continue().with_fast_function(function);
        let mut request = start.clone();
        for round in 0..MAX_SCAN_ROUNDS {
            let starting = request == start;
            let transaction = scan_transaction(&line, request.clone(), starting, self.latency());
            match self.transact(line, transaction).await? {
                TransactionOutcome::Reply(Reply {
                    body: ReplyBody::Fast { reply, .. },
                    ..
                }) => match reply {
                    FastReply::ScanFound {
                        serial,
                        modbus_address,
                    } => {
                        garbled_in_a_row = 0;
                        retried_silence = false;
                        debug!(%line, serial, modbus_address, "scan reply");
                        if !seen.iter().any(|(s, _)| *s == serial) {
                            seen.push((serial, modbus_address));
                            report.add_fast(line, serial, modbus_address);
                        }
                        request = next.clone();
                    }
                    FastReply::ScanEnd => return Ok(seen),
                    other => {
                        report.problems.push(SettingProblem {
                            line,
                            what: format!("unexpected reply to a scan request: {other:?}"),
                        });
                        return Ok(seen);
                    }
                },
                TransactionOutcome::Reply(other) => {
                    report.problems.push(SettingProblem {
                        line,
                        what: format!(
                            "a device answered the scan with a classic frame from address {}",
                            other.address
                        ),
                    });
                    return Ok(seen);
                }
                TransactionOutcome::NoReply if round == 0 => return Ok(seen),
                // Devices answered before, so someone must answer (a device or "end of scan"):
                // a late reply was lost to a busy adapter or machine. Ask once more.
                TransactionOutcome::NoReply if !retried_silence => retried_silence = true,
                // A start after an unreadable reply, twice unanswered, with nobody found: the
                // unreadable reply was noise on an empty setting.
                TransactionOutcome::NoReply if starting && seen.is_empty() => return Ok(seen),
                TransactionOutcome::NoReply => {
                    report.problems.push(SettingProblem {
                        line,
                        what: format!(
                            "the scan stopped getting answers after {} device(s); devices may be \
                             missing (noise, a collision, or a device with old firmware)",
                            seen.len()
                        ),
                    });
                    return Ok(seen);
                }
                // The device whose reply was lost counts itself scanned now (fast-modbus.md
                // §3), so a "continue" would never hear from it again: the scan starts over
                // (the devices found answer again and are known), a few times.
                TransactionOutcome::Garbled if restarts < MAX_SCAN_RESTARTS => {
                    restarts += 1;
                    retried_silence = false;
                    debug!(%line, restarts, "unreadable scan reply: scanning this setting again");
                    request = start.clone();
                }
                TransactionOutcome::Garbled => {
                    garbled_in_a_row += 1;
                    if garbled_in_a_row >= MAX_GARBLED_IN_A_ROW {
                        report.problems.push(SettingProblem {
                            line,
                            what: format!(
                                "bad CRC / unreadable replies {garbled_in_a_row} times in a row: \
                                 noise on the line, a missing terminator, or devices at other \
                                 settings; skipped the rest of this setting"
                            ),
                        });
                        return Ok(seen);
                    }
                    if restarts == MAX_SCAN_RESTARTS {
                        restarts += 1;
                        report.problems.push(SettingProblem {
                            line,
                            what: format!(
                                "a scan reply could not be read in {} scans of this setting, so \
                                 a device may be missing: noise on the line, or two devices \
                                 whose serial numbers end alike (the same lower 28 bits) \
                                 answering at once",
                                MAX_SCAN_RESTARTS + 1
                            ),
                        });
                    }
                    request = next.clone();
                }
            }
        }
        report.problems.push(SettingProblem {
            line,
            what: format!("the scan did not end after {MAX_SCAN_ROUNDS} replies; stopped"),
        });
        Ok(seen)
    }

    /// A classic request carried by serial number (0x46 0x08): only the device with that serial
    /// answers, whatever its address.
    async fn by_serial(
        &mut self,
        line: LineSettings,
        serial: u32,
        pdu: RequestPdu,
        timeout: Duration,
    ) -> Result<Answer, PortError> {
        let request = Request::by_serial(serial, pdu).with_fast_function(self.fast_function());
        let transaction = Transaction::to_device(&line, request, timeout + self.latency());
        Ok(match self.transact(line, transaction).await? {
            TransactionOutcome::Reply(Reply {
                body:
                    ReplyBody::Fast {
                        reply: FastReply::BySerial { serial: from, pdu },
                        ..
                    },
                ..
            }) if from == serial => Answer::Pdu(pdu),
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(pdu @ ResponsePdu::Exception { .. }),
                ..
            }) => Answer::Pdu(pdu),
            TransactionOutcome::Reply(_) | TransactionOutcome::Garbled => Answer::Garbled,
            TransactionOutcome::NoReply => Answer::NoReply,
        })
    }

    /// [`Self::by_serial`], once more when nothing readable came: a scan's details of a device
    /// that answered its scan step a moment ago (a reply lost to noise must not pass for a
    /// register the device lacks: a site tools audit saw "stop bits not reported" and a
    /// `FIXME` device type in `--config` for a read lost so).
    async fn by_serial_again_if_lost(
        &mut self,
        line: LineSettings,
        serial: u32,
        pdu: RequestPdu,
        timeout: Duration,
    ) -> Result<Answer, PortError> {
        let answer = self.by_serial(line, serial, pdu.clone(), timeout).await?;
        if matches!(answer, Answer::NoReply | Answer::Garbled) {
            return self.by_serial(line, serial, pdu, timeout).await;
        }
        Ok(answer)
    }

    /// A classic request to one address.
    async fn classic(
        &mut self,
        line: LineSettings,
        address: u8,
        pdu: RequestPdu,
        timeout: Duration,
    ) -> Result<Answer, PortError> {
        let request = Request::classic(address, pdu);
        let transaction = Transaction::to_device(&line, request, timeout + self.latency());
        Ok(match self.transact(line, transaction).await? {
            TransactionOutcome::Reply(Reply {
                body: ReplyBody::Classic(pdu),
                address: from,
            }) if from == address => Answer::Pdu(pdu),
            TransactionOutcome::Reply(_) | TransactionOutcome::Garbled => Answer::Garbled,
            TransactionOutcome::NoReply => Answer::NoReply,
        })
    }

    /// Any Fast Modbus request; the reply as it came.
    async fn fast(
        &mut self,
        line: LineSettings,
        request: Request,
        first_byte_timeout: Duration,
        reply_timeout: Duration,
    ) -> Result<TransactionOutcome, PortError> {
        let request_time = line.wire_time(request.encode().map(|b| b.len()).unwrap_or(16));
        let transaction = Transaction {
            estimated: request_time + reply_timeout,
            request_time,
            reply_timeout: reply_timeout + self.latency(),
            first_byte_timeout: Some(first_byte_timeout + self.latency()),
            late_window: self.latency(),
            request,
        };
        self.transact(line, transaction).await
    }

    /// Port settings, model, firmware and signature from the standard registers, by serial
    /// number; what a device does not have stays empty.
    async fn details(
        &mut self,
        line: LineSettings,
        serial: u32,
    ) -> Result<(Identity, Option<LineSettings>), PortError> {
        let settings = port_settings_in(
            &self
                .by_serial_again_if_lost(line, serial, PORT_SETTINGS_READ, KNOWN_DEVICE_TIMEOUT)
                .await?,
        );
        let mut texts = Vec::new();
        for (start, count) in TEXT_REGISTERS {
            texts.push(self.text_by_serial(line, serial, start, count).await?);
        }
        let mut texts = texts.into_iter();
        let identity = Identity {
            model: texts.next().flatten(),
            firmware: texts.next().flatten(),
            signature: texts.next().flatten(),
        };
        Ok((identity, settings))
    }

    /// A standard text block of up to `count` registers, by serial number: the first
    /// [`TEXT_FIRST_READ`] registers, and the rest only when the text fills them (at 9600 baud
    /// each register is 2.3 ms of wire).
    async fn text_by_serial(
        &mut self,
        line: LineSettings,
        serial: u32,
        start: u16,
        count: u16,
    ) -> Result<Option<String>, PortError> {
        let mut words = Vec::new();
        for (start, count) in text_reads(start, count) {
            let pdu = RequestPdu::ReadHoldingRegisters { start, count };
            match self
                .by_serial_again_if_lost(line, serial, pdu, KNOWN_DEVICE_TIMEOUT)
                .await?
            {
                Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => {
                    let ended = values.contains(&0);
                    words.extend(values);
                    if ended {
                        break;
                    }
                }
                // The first part read is the text a device without the rest has.
                _ if !words.is_empty() => break,
                _ => return Ok(None),
            }
        }
        Ok(standard_text(&words))
    }
}

/// Holding 110..112: baud rate / 100, parity (0 none, 1 odd, 2 even), stop bits.
pub const PORT_SETTINGS_REGISTER: u16 = 110;
/// The read of those three registers.
pub const PORT_SETTINGS_READ: RequestPdu = RequestPdu::ReadHoldingRegisters {
    start: PORT_SETTINGS_REGISTER,
    count: 3,
};
/// Model (200), firmware version (250), signature (290): start and length of each block.
pub const TEXT_REGISTERS: [(u16, u16); 3] = [(200, 20), (250, 16), (290, 12)];
/// Registers of a text block read first: model names, versions and signatures are mostly
/// shorter than 12 characters ("WB-MAP12E", "1.26.1"), and one read costs some 25 bytes of
/// frame around its data (at 9600 baud 29 ms, as much as 12 registers).
pub const TEXT_FIRST_READ: u16 = 12;

/// The reads of a text block: the first part, then the rest.
pub fn text_reads(start: u16, count: u16) -> Vec<(u16, u16)> {
    let first = count.min(TEXT_FIRST_READ);
    let mut reads = vec![(start, first)];
    if count > first {
        reads.push((start + first, count - first));
    }
    reads
}

/// Port settings from the answer to [`PORT_SETTINGS_READ`]; None for another answer.
pub fn port_settings_in(answer: &Answer) -> Option<LineSettings> {
    match answer {
        Answer::Pdu(ResponsePdu::ReadHoldingRegisters { values }) => reported_port_settings(values),
        _ => None,
    }
}

/// Port settings from holding 110..112; None for values no port can have.
pub fn reported_port_settings(words: &[u16]) -> Option<LineSettings> {
    let [baud, parity, stop_bits] = words else {
        return None;
    };
    let parity = match parity {
        0 => Parity::None,
        1 => Parity::Odd,
        2 => Parity::Even,
        _ => return None,
    };
    let stop_bits = u8::try_from(*stop_bits)
        .ok()
        .filter(|n| (1..=2).contains(n))?;
    (*baud > 0).then(|| LineSettings::new(u32::from(*baud) * 100, parity, stop_bits))
}

impl ToolBus for ToolPort {
    fn latency(&self) -> Duration {
        self.latency
    }

    async fn transact(
        &mut self,
        line: LineSettings,
        transaction: Transaction,
    ) -> Result<TransactionOutcome, PortError> {
        let transport = self.at(line).await?;
        Ok(transport.transact(&transaction).await?.0)
    }
}

impl Drop for ToolPort {
    fn drop(&mut self) {
        self.restore();
    }
}

fn unreachable_port<T>(path: &str) -> Result<T, PortError> {
    Err(PortError::Other {
        path: path.to_owned(),
        source: io::Error::other("the port closed unexpectedly"),
    })
}

/// Turns an open error into what the integrator should do about it.
fn classify(path: &str, source: io::Error) -> PortError {
    let path = path.to_owned();
    match (source.kind(), source.raw_os_error()) {
        (io::ErrorKind::NotFound, _) | (_, Some(nix::libc::ENOENT | nix::libc::ENODEV)) => {
            PortError::Missing { path }
        }
        (io::ErrorKind::PermissionDenied, _) | (_, Some(nix::libc::EACCES)) => {
            PortError::PermissionDenied { path }
        }
        (_, Some(nix::libc::EBUSY)) => PortError::Busy { path },
        _ => PortError::Other { path, source },
    }
}

/// Timeouts of a scan request: after a scan start every device takes part, so the first window
/// already carries a byte when anyone uses this setting (an empty setting costs a few ms); after
/// a continue the winner may need every window. A request under the deprecated 0x60 is timed
/// with its longer windows.
pub fn scan_transaction(
    line: &LineSettings,
    request: Request,
    start: bool,
    latency: Duration,
) -> Transaction {
    let request_time = line.wire_time(request.encode().map(|b| b.len()).unwrap_or(5));
    let legacy = request.fast_function == fast::LEGACY_FUNCTION;
    let (scan_reply, start_first_byte) = if legacy {
        (
            line.legacy_scan_reply_timeout(),
            line.legacy_scan_start_first_byte_timeout(),
        )
    } else {
        (
            line.scan_reply_timeout(),
            line.scan_start_first_byte_timeout(),
        )
    };
    let first_byte = if start { start_first_byte } else { scan_reply };
    // 32 windows of filler bytes at most, then the 10-byte scan reply.
    let reply_timeout = scan_reply + line.wire_time(32 + 10);
    Transaction {
        estimated: request_time + reply_timeout,
        request_time,
        reply_timeout: reply_timeout + latency,
        first_byte_timeout: Some(first_byte + latency),
        // Silence after a scan start means nobody at this setting, and the next request goes out
        // at another setting (after an input flush): no late reply to wait for.
        late_window: if start { Duration::ZERO } else { latency },
        request,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bus that answers each request by serial number from a script, in order: `None` for a
    /// lost reply, else the registers read.
    struct Scripted {
        answers: std::collections::VecDeque<Option<Vec<u16>>>,
        asked: usize,
    }

    impl ToolBus for Scripted {
        fn latency(&self) -> Duration {
            Duration::ZERO
        }

        async fn transact(
            &mut self,
            _line: LineSettings,
            transaction: Transaction,
        ) -> Result<TransactionOutcome, PortError> {
            self.asked += 1;
            let serial = match transaction.request.body {
                crate::protocol::RequestBody::Fast(crate::protocol::FastRequest::BySerial {
                    serial,
                    ..
                }) => serial,
                _ => panic!("not a request by serial number"),
            };
            Ok(match self.answers.pop_front().flatten() {
                Some(values) => TransactionOutcome::Reply(Reply::fast(
                    fast::BROADCAST_ADDRESS,
                    FastReply::BySerial {
                        serial,
                        pdu: ResponsePdu::ReadHoldingRegisters { values },
                    },
                )),
                None => TransactionOutcome::NoReply,
            })
        }
    }

    /// A scan's details of a device whose reply to the port settings read was lost once: read
    /// again, so the settings are known (they were reported as "not reported (holding 112)",
    /// and `--config` wrote stop bits 2 for them).
    #[tokio::test]
    async fn details_read_again_when_a_reply_is_lost() {
        let text = |t: &str| {
            let mut words: Vec<u16> = t.bytes().map(u16::from).collect();
            words.resize(12, 0);
            Some(words)
        };
        let mut bus = Scripted {
            answers: [
                None,
                Some(vec![96, 0, 1]),
                text("WBMR6C"),
                None,
                text("1.26.0"),
                text("sig"),
            ]
            .into_iter()
            .collect(),
            asked: 0,
        };
        let (identity, settings) = bus
            .details(LineSettings::new(9600, Parity::None, 2), 0xFE00_0020)
            .await
            .unwrap();
        assert_eq!(settings, Some(LineSettings::new(9600, Parity::None, 1)));
        assert_eq!(identity.model.as_deref(), Some("WBMR6C"));
        assert_eq!(identity.firmware.as_deref(), Some("1.26.0"));
        assert_eq!(bus.asked, 6);
    }

    #[test]
    fn open_errors_become_what_to_do() {
        let missing = classify("/dev/x", io::Error::from_raw_os_error(nix::libc::ENOENT));
        assert!(matches!(missing, PortError::Missing { .. }));
        let denied = classify("/dev/x", io::Error::from_raw_os_error(nix::libc::EACCES));
        assert!(denied.to_string().contains("dialout"), "{denied}");
        let busy = classify("/dev/x", io::Error::from_raw_os_error(nix::libc::EBUSY));
        assert!(busy.to_string().contains("systemctl stop"), "{busy}");
        // Every tool that goes through the service is named.
        for tool in [
            "scan",
            "set-address",
            "fix-addresses",
            "read",
            "write",
            "events",
        ] {
            assert!(busy.to_string().contains(tool), "{tool}: {busy}");
        }
        let other = classify("/dev/x", io::Error::from_raw_os_error(nix::libc::EIO));
        assert!(matches!(other, PortError::Other { .. }));
    }

    #[test]
    fn port_settings_registers() {
        assert_eq!(
            reported_port_settings(&[96, 0, 1]),
            Some(LineSettings::new(9600, Parity::None, 1))
        );
        assert_eq!(
            reported_port_settings(&[1152, 2, 2]),
            Some(LineSettings::new(115_200, Parity::Even, 2))
        );
        assert_eq!(
            reported_port_settings(&[192, 1, 1]),
            Some(LineSettings::new(19200, Parity::Odd, 1))
        );
        assert_eq!(reported_port_settings(&[96, 3, 1]), None);
        assert_eq!(reported_port_settings(&[96, 0, 0]), None);
        assert_eq!(reported_port_settings(&[0, 0, 2]), None);
        assert_eq!(reported_port_settings(&[96, 0]), None);
    }

    #[test]
    fn text_blocks_are_read_short_first() {
        assert_eq!(text_reads(200, 20), vec![(200, 12), (212, 8)]);
        assert_eq!(text_reads(290, 12), vec![(290, 12)]);
        assert_eq!(text_reads(290, 5), vec![(290, 5)]);
    }

    #[test]
    fn an_empty_setting_costs_the_first_window_and_no_late_window() {
        let latency = Duration::from_millis(24);
        for baud in [9600, 115_200] {
            let line = LineSettings::new(baud, Parity::None, 2);
            let start = scan_transaction(&line, Request::scan_start(), true, latency);
            assert_eq!(
                start.first_byte_timeout,
                Some(line.scan_start_first_byte_timeout() + latency)
            );
            assert_eq!(start.late_window, Duration::ZERO);
            let next = scan_transaction(&line, Request::scan_continue(), false, latency);
            assert_eq!(
                next.first_byte_timeout,
                Some(line.scan_reply_timeout() + latency)
            );
            assert_eq!(next.late_window, latency);
            assert!(next.reply_timeout > line.scan_reply_timeout());
        }
    }

    #[test]
    fn a_legacy_scan_goes_out_under_0x60_and_waits_for_its_windows() {
        let line = LineSettings::new(9600, Parity::None, 2);
        let request = Request::scan_start().with_fast_function(fast::LEGACY_FUNCTION);
        assert_eq!(request.encode().unwrap()[..3], [0xFD, 0x60, 0x01]);
        let start = scan_transaction(&line, request, true, Duration::ZERO);
        assert_eq!(
            start.first_byte_timeout,
            Some(line.legacy_scan_start_first_byte_timeout())
        );
        let next = Request::scan_continue().with_fast_function(fast::LEGACY_FUNCTION);
        let next = scan_transaction(&line, next, false, Duration::ZERO);
        assert_eq!(
            next.first_byte_timeout,
            Some(line.legacy_scan_reply_timeout())
        );
        assert_eq!(
            next.reply_timeout,
            line.legacy_scan_reply_timeout() + line.wire_time(42)
        );
    }
}
