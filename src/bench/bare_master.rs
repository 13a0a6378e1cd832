//! The floor under scenario 7: the CPU that the simplest master keeping the daemon's timing
//! rules pays per transaction on this machine, measured on the same simulated bus in the same
//! run. It polls the bench devices' 60 input registers round robin and does nothing else:
//! write the request, sleep until the reply should be in, read it (waiting on the port only if
//! it is not), keep 3.5 characters of silence, ask the kernel whether the line stayed quiet.
//! Two sleeps per transaction, five system calls, no MQTT, no scheduler, no events: no
//! gateway that sleeps through replies and keeps the frame gap can cost less here. A second
//! round sleeps once per transaction (the reply read 3.5 characters after its predicted end,
//! the next request written at once, as the daemon does not: see docs/performance.md), for the
//! floor of that design. A third round goes through the daemon's own transport (the exchange,
//! the serial link blocking for short waits, as a port task on its own thread runs it): what
//! the daemon's bus code adds to the floor before any scheduling, device model or MQTT.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::Duration;

use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::resource::{getrusage, UsageWho};
use nix::sys::termios::{self, BaudRate, ControlFlags, SetArg};
use nix::sys::time::TimeSpec;
use nix::time::{clock_gettime, clock_nanosleep, ClockId, ClockNanosleepFlags};

use super::floor::WakeUpMeter;
use super::harness::{Harness, HarnessOptions};
use super::layout::BenchLayout;
use crate::protocol::{LineSettings, Parity, Request, RequestPdu};
use crate::transport::input_queue_len;

/// The simulator's devices answer this long after a request has ended (the layout's
/// `turnaround_us`).
const TURNAROUND: Duration = Duration::from_micros(500);
/// Slack after the predicted end of a reply before reading it (the simulator hands bytes over
/// in batches of up to 250 µs).
const READ_SLACK: Duration = Duration::from_micros(300);
/// A reply not complete at its predicted end is waited for this long at most.
const REPLY_WAIT: Duration = Duration::from_millis(100);

/// Which loop a round runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum FloorMaster {
    /// Two sleeps per transaction: the reply, then the frame gap.
    #[default]
    TwoSleeps,
    /// One sleep: the reply and the gap in one.
    OneSleep,
    /// The daemon's transport, its short waits blocking the thread.
    DaemonTransport,
}

impl std::fmt::Display for FloorMaster {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::TwoSleeps => "bare, 2 sleeps",
            Self::OneSleep => "bare, 1 sleep",
            Self::DaemonTransport => "the daemon's transport",
        })
    }
}

/// One round of the bare master.
#[derive(Debug, Clone, Default)]
pub struct BareMasterRun {
    pub baud: u32,
    pub devices: u8,
    pub master: FloorMaster,
    pub transactions: usize,
    /// Transactions whose reply came whole with a good CRC.
    pub answered: usize,
    /// The master thread's CPU clock over the transactions.
    pub cpu: Duration,
    /// The master thread's voluntary context switches (its sleeps) over the transactions.
    pub wake_ups: u64,
    /// One bare timed wake-up, measured beside it (see [`WakeUpMeter`]).
    pub wake_up_cost: Option<Duration>,
    pub problem: Option<String>,
}

impl BareMasterRun {
    pub fn cpu_per_transaction_us(&self) -> Option<f64> {
        (self.transactions > 0).then(|| self.cpu.as_secs_f64() * 1e6 / self.transactions as f64)
    }

    pub fn wake_ups_per_transaction(&self) -> Option<f64> {
        (self.transactions > 0).then(|| self.wake_ups as f64 / self.transactions as f64)
    }
}

/// Runs `transactions` reads of 60 input registers on a bus of `devices` bench devices at
/// `baud` with `master`.
pub fn run_bare_master(
    binary: &Path,
    mosquitto: &Path,
    baud: u32,
    devices: u8,
    master: FloorMaster,
    transactions: usize,
) -> BareMasterRun {
    let mut run = BareMasterRun {
        baud,
        devices,
        master,
        ..BareMasterRun::default()
    };
    if let Err(err) = measure_into(&mut run, binary, mosquitto, transactions) {
        run.problem = Some(format!("{err:#}"));
    }
    run
}

fn measure_into(
    run: &mut BareMasterRun,
    binary: &Path,
    mosquitto: &Path,
    transactions: usize,
) -> anyhow::Result<()> {
    let layout = BenchLayout {
        devices: run.devices,
        events: 8,
        registers: 60,
        baud: run.baud,
        fast_devices: true,
    };
    let mut options = HarnessOptions::new(binary, layout.bus(), vec![layout.template()]);
    options.mosquitto = mosquitto.to_path_buf();
    let harness = Harness::start(&options)?;
    let line = LineSettings::new(run.baud, Parity::None, 2);
    let mut port = open_raw(harness.pty(), run.baud)?;
    let requests: Vec<Vec<u8>> = (1..=run.devices)
        .map(|address| {
            Request::classic(
                address,
                RequestPdu::ReadInputRegisters {
                    start: 0,
                    count: layout.registers,
                },
            )
            .encode()
        })
        .collect::<Result<_, _>>()
        .map_err(|err| anyhow::anyhow!("encoding the request: {err:?}"))?;
    let reply_len = 5 + 2 * usize::from(layout.registers);
    let plan = Plan {
        line,
        reply_len,
        one_sleep: run.master == FloorMaster::OneSleep,
    };
    if run.master == FloorMaster::DaemonTransport {
        return through_transport(run, &harness, &layout, transactions);
    }
    // A few rounds first: the simulator's and this thread's first transactions pay for pages
    // and caches.
    for request in requests.iter().cycle().take(16) {
        plan.transact(&mut port, request)?;
    }
    let window = Window::open()?;
    for request in requests.iter().cycle().take(transactions) {
        run.answered += usize::from(plan.transact(&mut port, request)?);
        run.transactions += 1;
    }
    window.close_into(run)
}

/// The measured stretch of a round: this thread's CPU clock and sleeps, and a bare wake-up's
/// cost measured beside it.
struct Window {
    meter: WakeUpMeter,
    cpu: Duration,
    sleeps: u64,
}

impl Window {
    fn open() -> anyhow::Result<Self> {
        let meter = WakeUpMeter::start(Duration::from_millis(5));
        let (cpu, sleeps) = thread_usage()?;
        Ok(Self { meter, cpu, sleeps })
    }

    fn close_into(self, run: &mut BareMasterRun) -> anyhow::Result<()> {
        let (cpu, sleeps) = thread_usage()?;
        run.wake_up_cost = self.meter.finish();
        run.cpu = cpu.saturating_sub(self.cpu);
        run.wake_ups = sleeps.saturating_sub(self.sleeps);
        Ok(())
    }
}

/// The same round robin through the daemon's own transport (the exchange, the serial link, its
/// short waits blocking the thread) on a current-thread runtime, as a port task runs it.
fn through_transport(
    run: &mut BareMasterRun,
    harness: &Harness,
    layout: &BenchLayout,
    transactions: usize,
) -> anyhow::Result<()> {
    use crate::protocol::Transaction;
    use crate::transport::{Endpoint, Transport};
    let line = LineSettings::new(run.baud, Parity::None, 2);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let endpoint = Endpoint::Serial {
            path: harness.pty().to_string_lossy().into_owned(),
            line,
            frame_timeout: Duration::ZERO,
        };
        let mut transport = Transport::open(&endpoint)
            .await
            .map_err(|err| anyhow::anyhow!("{err}"))?;
        transport.block_short_waits();
        let transactions_of: Vec<Transaction> = (1..=run.devices)
            .map(|address| {
                Transaction::to_device(
                    &line,
                    Request::classic(
                        address,
                        RequestPdu::ReadInputRegisters {
                            start: 0,
                            count: layout.registers,
                        },
                    ),
                    Duration::from_millis(100),
                )
            })
            .collect();
        for transaction in transactions_of.iter().cycle().take(16) {
            transport
                .transact(transaction)
                .await
                .map_err(|err| anyhow::anyhow!("{err}"))?;
        }
        let window = Window::open()?;
        for transaction in transactions_of.iter().cycle().take(transactions) {
            let (outcome, _) = transport
                .transact(transaction)
                .await
                .map_err(|err| anyhow::anyhow!("{err}"))?;
            run.answered += usize::from(matches!(
                outcome,
                crate::protocol::TransactionOutcome::Reply(_)
            ));
            run.transactions += 1;
        }
        window.close_into(run)
    })
}

struct Plan {
    line: LineSettings,
    reply_len: usize,
    one_sleep: bool,
}

impl Plan {
    /// One transaction; true if the reply came whole with a good CRC.
    fn transact(&self, port: &mut File, request: &[u8]) -> anyhow::Result<bool> {
        let gap = self.line.frame_gap();
        let written = now()?;
        port.write_all(request)?;
        // A device takes a request as ended after 3.5 characters of silence, then answers.
        let mut reply_end = self.line.wire_time(request.len())
            + gap
            + TURNAROUND
            + self.line.wire_time(self.reply_len)
            + READ_SLACK;
        if self.one_sleep {
            reply_end += gap;
        }
        sleep_until(written + reply_end)?;
        let mut reply = [0u8; 256];
        let mut got = 0;
        let give_up = written + reply_end + REPLY_WAIT;
        while got < self.reply_len {
            match port.read(&mut reply[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(err) if err.kind() == std::io::ErrorKind::WouldBlock => {
                    let left = give_up.saturating_sub(now()?);
                    let timeout = PollTimeout::try_from(left.as_millis().max(1) as i32)
                        .unwrap_or(PollTimeout::ZERO);
                    let mut fds = [PollFd::new(port.as_fd(), PollFlags::POLLIN)];
                    if left.is_zero() || poll(&mut fds, timeout)? == 0 {
                        break;
                    }
                }
                Err(err) => return Err(err.into()),
            }
        }
        if !self.one_sleep {
            sleep_until(now()? + gap)?;
        }
        let mut waiting: nix::libc::c_int = 0;
        // SAFETY: FIONREAD writes one int through the pointer, which outlives the call.
        unsafe { input_queue_len(std::os::fd::AsRawFd::as_raw_fd(port), &mut waiting) }?;
        if waiting > 0 {
            termios::tcflush(port.as_fd(), termios::FlushArg::TCIFLUSH)?;
        }
        Ok(got == self.reply_len && crate::protocol::crc::crc_is_valid(&reply[..got]))
    }
}

fn open_raw(path: &Path, baud: u32) -> anyhow::Result<File> {
    let port = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(nix::libc::O_NONBLOCK | nix::libc::O_NOCTTY)
        .open(path)?;
    let mut settings = termios::tcgetattr(port.as_fd())?;
    termios::cfmakeraw(&mut settings);
    let rate = match baud {
        9600 => BaudRate::B9600,
        19200 => BaudRate::B19200,
        _ => BaudRate::B115200,
    };
    termios::cfsetspeed(&mut settings, rate)?;
    settings.control_flags |= ControlFlags::CSTOPB | ControlFlags::CLOCAL | ControlFlags::CREAD;
    termios::tcsetattr(port.as_fd(), SetArg::TCSANOW, &settings)?;
    Ok(port)
}

fn now() -> anyhow::Result<Duration> {
    Ok(Duration::from(clock_gettime(ClockId::CLOCK_MONOTONIC)?))
}

fn sleep_until(at: Duration) -> anyhow::Result<()> {
    let at = TimeSpec::from_duration(at);
    loop {
        match clock_nanosleep(
            ClockId::CLOCK_MONOTONIC,
            ClockNanosleepFlags::TIMER_ABSTIME,
            &at,
        ) {
            Err(nix::errno::Errno::EINTR) => continue,
            other => return Ok(other.map(drop)?),
        }
    }
}

/// This thread's CPU clock and voluntary context switches.
fn thread_usage() -> anyhow::Result<(Duration, u64)> {
    let cpu = Duration::from(clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID)?);
    let usage = getrusage(UsageWho::RUSAGE_THREAD)?;
    Ok((
        cpu,
        u64::try_from(usage.voluntary_context_switches()).unwrap_or(0),
    ))
}
