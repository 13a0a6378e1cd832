//! A serial port (a real RS-485 adapter or the simulator's pseudo-terminal) under tokio, watched
//! only while the transport waits for bytes it cannot time.
//!
//! A line delivers a reply a few bytes at a time. Registered with the reactor all the time, the
//! port would wake the daemon for every few bytes, and every wake-up costs a round through the
//! kernel (and on a tty a read that finds nothing costs a wait for the kernel's receive worker).
//! So the port is registered only while the transport waits for bytes it cannot time; between
//! the first byte of a reply of known length and its expected end
//! ([`Exchange::reply_complete_at`](super::exchange::Exchange::reply_complete_at)) the transport
//! sleeps on a timerfd (tokio's timers round to milliseconds, several characters at 115200) and
//! then reads the rest at once. Once the exchange has learned how long after its request a kind
//! of reply is complete, the transport does not even wait for the first byte: it sleeps until
//! the reply should be complete and reads it in one go
//! ([`Exchange::batch_read_at`](super::exchange::Exchange::batch_read_at)): one wake-up per
//! reply. The silence before a request is not watched either: the transport sleeps through it
//! and asks the kernel once at its end whether anything came meanwhile
//! ([`SerialLink::quiet_until`]); if nothing did, the input needs no flush, and what did is read
//! (another master's request may be among it).

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::{AsFd, AsRawFd, FromRawFd, IntoRawFd, OwnedFd, RawFd};

use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::sys::termios::{tcflush, FlushArg};
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;
use tokio::time::Instant;

use crate::protocol::{self, LineSettings};

// How many received bytes wait to be read (FIONREAD, `int *`).
nix::ioctl_read_bad!(input_queue_len, nix::libc::FIONREAD, nix::libc::c_int);

/// The port's descriptor as the reactor sees it while it is watched (the port itself stays with
/// [`SerialLink`], which outlives every registration).
struct WatchedFd(RawFd);

impl AsRawFd for WatchedFd {
    fn as_raw_fd(&self) -> RawFd {
        self.0
    }
}

/// A timerfd as the reactor sees it.
struct Timer(TimerFd);

impl AsRawFd for Timer {
    fn as_raw_fd(&self) -> RawFd {
        self.0.as_fd().as_raw_fd()
    }
}

/// Registers `fd` with the reactor for `interest`.
fn register<T: AsRawFd>(fd: T, interest: Interest) -> io::Result<AsyncFd<T>> {
    // SAFETY: the descriptors registered here are the link's port and timer, which the link keeps
    // open, unchanged, for longer than any registration (see the field order of `SerialLink`).
    Ok(unsafe { AsyncFd::register_with_interest(fd, interest) }?)
}

/// The longest wait that blocks the thread when the link may block
/// ([`SerialLink::block_short_waits`]); longer ones go through the reactor, where the port
/// task's other work (a shutdown, a reload) can end them.
const BLOCKING_WAIT_LIMIT: std::time::Duration = std::time::Duration::from_millis(50);

pub struct SerialLink {
    /// Declared before `port`: a registration is removed before the port is closed.
    watch: Option<AsyncFd<WatchedFd>>,
    timer: AsyncFd<Timer>,
    port: File,
    /// Waits of up to [`BLOCKING_WAIT_LIMIT`] block the thread (see [`Self::block_short_waits`]).
    blocking_waits: bool,
}

impl SerialLink {
    /// Opens and sets up the port (raw, exclusive, the line's settings), non-blocking.
    pub fn open(path: &str, line: &LineSettings) -> io::Result<Self> {
        let port = serialport::new(path, line.baud)
            .data_bits(match line.data_bits {
                5 => serialport::DataBits::Five,
                6 => serialport::DataBits::Six,
                7 => serialport::DataBits::Seven,
                _ => serialport::DataBits::Eight,
            })
            .parity(match line.parity {
                protocol::Parity::None => serialport::Parity::None,
                protocol::Parity::Even => serialport::Parity::Even,
                protocol::Parity::Odd => serialport::Parity::Odd,
            })
            .stop_bits(if line.stop_bits == 2 {
                serialport::StopBits::Two
            } else {
                serialport::StopBits::One
            })
            .open_native()
            .map_err(io::Error::from)?;
        // SAFETY: `into_raw_fd` gives up the descriptor without closing it; nothing else owns it.
        let port = File::from(unsafe { OwnedFd::from_raw_fd(port.into_raw_fd()) });
        fcntl(&port, FcntlArg::F_SETFL(OFlag::O_NONBLOCK))?;
        let timer = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )?;
        Ok(Self {
            watch: None,
            timer: register(Timer(timer), Interest::READABLE)?,
            port,
            blocking_waits: false,
        })
    }

    /// From now on, waits of up to [`BLOCKING_WAIT_LIMIT`] block the calling thread: a
    /// `clock_nanosleep` or a `ppoll`, one system call and one wake-up, instead of arming the
    /// link's timerfd and waking through the reactor (two system calls and the reactor's
    /// rounds: ~45 µs more per transaction here, docs/performance.md). Only for a link whose
    /// port task has its thread and runtime to itself: a blocked thread runs nothing else.
    /// A blocked wait returns no `Pending`: the transport yields by itself in a transaction
    /// that goes on ([`super::Transport::transact`]), so that a shutdown still ends it.
    pub fn block_short_waits(&mut self) {
        self.blocking_waits = true;
    }

    /// Whether [`Self::block_short_waits`] was called.
    #[cfg(test)]
    pub fn blocks_short_waits(&self) -> bool {
        self.blocking_waits
    }

    /// A wait until `at` blocks the thread.
    fn blocks_until(&self, at: Instant) -> bool {
        self.blocking_waits && at.saturating_duration_since(Instant::now()) <= BLOCKING_WAIT_LIMIT
    }

    /// The port is the end of a pseudo-terminal (a Unix 98 pty, `/dev/pts/N`, whatever link
    /// names it), not a UART or an adapter: no wire times its bytes. Told by the device's major
    /// number, as the kernel assigns it (136–143).
    pub fn is_pseudo_terminal(&self) -> bool {
        nix::sys::stat::fstat(&self.port)
            .is_ok_and(|stat| is_pty_slave_major(nix::sys::stat::major(stat.st_rdev)))
    }

    /// Throws away what the line delivered and nobody read yet.
    /// Empties the input before a request: what came since the line was last read is read
    /// into `buffer` (another master's request may be among it) and the count returned; what a
    /// full buffer leaves is flushed. One `read` when nothing came, as one `tcflush` was.
    pub fn take_input(&mut self, buffer: &mut [u8]) -> io::Result<usize> {
        // A registration from the last transaction would carry its readiness over.
        self.watch = None;
        match self.read_now(buffer)? {
            None | Some(0) => Ok(0),
            Some(count) => {
                tcflush(&self.port, FlushArg::TCIFLUSH).map_err(io::Error::from)?;
                Ok(count)
            }
        }
    }

    pub async fn write_all(&mut self, mut bytes: &[u8]) -> io::Result<()> {
        while !bytes.is_empty() {
            match self.port.write(bytes) {
                Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                Ok(written) => bytes = bytes.get(written..).unwrap_or(&[]),
                Err(err) if err.kind() == io::ErrorKind::WouldBlock => {
                    // The transmit buffer is full (never for a Modbus frame on a sane driver).
                    let writable = register(WatchedFd(self.port.as_raw_fd()), Interest::WRITABLE)?;
                    writable.writable().await?.clear_ready();
                }
                Err(err) if err.kind() == io::ErrorKind::Interrupted => {}
                Err(err) => return Err(err),
            }
        }
        Ok(())
    }

    /// Waits until bytes arrive and reads them (one read: a tty hands over all it has), or gives
    /// up at `deadline` (`Ok(None)`). Timed by the link's own
    /// timerfd: a tokio timer that is earlier than the runtime's next wake-up makes the runtime
    /// wake itself through its eventfd first, two system calls more per transaction.
    pub async fn read_until(
        &mut self,
        deadline: Instant,
        buffer: &mut [u8],
    ) -> io::Result<Option<usize>> {
        if self.blocks_until(deadline) {
            return self.read_blocking(deadline, buffer);
        }
        if !self.arm_timer(deadline)? {
            return self.read_now(buffer);
        }
        if self.watch.is_none() {
            self.watch = Some(register(
                WatchedFd(self.port.as_raw_fd()),
                Interest::READABLE,
            )?);
        }
        let (Some(watch), timer, port) = (&self.watch, &self.timer, &self.port) else {
            return Err(io::ErrorKind::Other.into());
        };
        loop {
            tokio::select! {
                biased;
                ready = watch.readable() => {
                    let mut ready = ready?;
                    let mut reader = port;
                    match reader.read(buffer) {
                        Err(err) if err.kind() == io::ErrorKind::WouldBlock => ready.clear_ready(),
                        Err(err) if err.kind() == io::ErrorKind::Interrupted => {}
                        Ok(count) => {
                            // A tty read returns everything there is (unless the buffer is
                            // full): the next call waits for the next edge rather than paying
                            // for a read that finds nothing, the costly kind on a tty.
                            if count < buffer.len() {
                                ready.clear_ready();
                            }
                            return Ok(Some(count));
                        }
                        Err(err) => return Err(err),
                    }
                }
                ready = timer.readable() => {
                    ready?.clear_ready();
                    if Instant::now() >= deadline {
                        return Ok(None);
                    }
                }
            }
        }
    }

    /// [`Self::read_until`], blocking the thread.
    fn read_blocking(&mut self, deadline: Instant, buffer: &mut [u8]) -> io::Result<Option<usize>> {
        // Asked first, read then: bytes this wait is for have mostly not come yet, and a read
        // that finds nothing is the costly kind on a tty.
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return self.read_now(buffer);
            }
            let mut fds = [nix::poll::PollFd::new(
                self.port.as_fd(),
                nix::poll::PollFlags::POLLIN,
            )];
            match nix::poll::ppoll(&mut fds, Some(TimeSpec::from_duration(left)), None) {
                Ok(0) | Err(nix::errno::Errno::EINTR) => {}
                Ok(_) => {
                    if let Some(count) = self.read_now(buffer)? {
                        return Ok(Some(count));
                    }
                }
                Err(err) => return Err(err.into()),
            }
        }
    }

    /// Sets the timer to expire at `at`; false (and nothing set) when `at` has passed.
    fn arm_timer(&mut self, at: Instant) -> io::Result<bool> {
        let left = at.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Ok(false);
        }
        // Setting the timer also forgets an expiry nobody waited for.
        self.timer
            .get_ref()
            .0
            .set(
                Expiration::OneShot(TimeSpec::from_duration(left)),
                TimerSetTimeFlags::empty(),
            )
            .map_err(io::Error::from)?;
        Ok(true)
    }

    /// Sleeps until `at` without watching the line (bytes that arrive meanwhile wake nobody),
    /// then reads whatever has arrived: `Ok(None)` when nothing has.
    pub async fn read_at(&mut self, at: Instant, buffer: &mut [u8]) -> io::Result<Option<usize>> {
        self.watch = None;
        self.sleep_until(at).await?;
        self.read_now(buffer)
    }

    /// Sleeps until `at` without watching the line, then tells whether it stayed quiet: `None`
    /// when nothing arrived meanwhile (the input is then empty: no flush needed before a
    /// request); the count of bytes read into `buffer` when something did (another master's
    /// request may be among them: the exchange looks). The silence before a request checked
    /// once at its end: one `ioctl` instead of a registration with the reactor and its removal.
    pub async fn quiet_until(
        &mut self,
        at: Instant,
        buffer: &mut [u8],
    ) -> io::Result<Option<usize>> {
        self.watch = None;
        self.sleep_until(at).await?;
        let mut pending: nix::libc::c_int = 0;
        // SAFETY: FIONREAD writes one int through the pointer, which outlives the call.
        let counted = unsafe { input_queue_len(self.port.as_raw_fd(), &mut pending) };
        if counted.is_err() {
            // A driver that cannot count its input: flushed, and taken as quiet, as before the
            // silence was checked at its end.
            tcflush(&self.port, FlushArg::TCIFLUSH).map_err(io::Error::from)?;
            return Ok(None);
        }
        if pending == 0 {
            return Ok(None);
        }
        // What a full buffer leaves is flushed before the request is written.
        Ok(Some(self.read_now(buffer)?.unwrap_or(0)))
    }

    /// Reads whatever has arrived, without waiting: `Ok(None)` when nothing has.
    fn read_now(&mut self, buffer: &mut [u8]) -> io::Result<Option<usize>> {
        loop {
            match (&self.port).read(buffer) {
                Ok(count) => return Ok(Some(count)),
                Err(err) if err.kind() == io::ErrorKind::WouldBlock => return Ok(None),
                Err(err) if err.kind() == io::ErrorKind::Interrupted => {}
                Err(err) => return Err(err),
            }
        }
    }

    /// Sleeps until `at`, to within the kernel's timer slack.
    async fn sleep_until(&mut self, at: Instant) -> io::Result<()> {
        if self.blocks_until(at) {
            return sleep_blocking(at);
        }
        if !self.arm_timer(at)? {
            return Ok(());
        }
        loop {
            let mut ready = self.timer.readable().await?;
            // Readiness left over from an earlier expiry: not this one.
            ready.clear_ready();
            if Instant::now() >= at {
                return Ok(());
            }
        }
    }
}

/// Blocks the thread until `at`.
fn sleep_blocking(at: Instant) -> io::Result<()> {
    loop {
        let left = at.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Ok(());
        }
        match nix::time::clock_nanosleep(
            nix::time::ClockId::CLOCK_MONOTONIC,
            nix::time::ClockNanosleepFlags::empty(),
            &TimeSpec::from_duration(left),
        ) {
            Ok(_) | Err(nix::errno::Errno::EINTR) => {}
            Err(err) => return Err(err.into()),
        }
    }
}

/// The majors of Unix 98 pseudo-terminal slaves (`UNIX98_PTY_SLAVE_MAJOR` and the seven after
/// it, Documentation/admin-guide/devices.txt).
fn is_pty_slave_major(major: u64) -> bool {
    (136..=143).contains(&major)
}

#[cfg(test)]
mod tests {
    use std::os::fd::AsFd;
    use std::time::Duration;

    use super::*;
    use crate::protocol::Parity;

    /// A pseudo-terminal: the port's end opened as the transport opens a serial port, and the
    /// other end, where the "devices" write.
    fn pty() -> (SerialLink, File) {
        let pty = nix::pty::openpty(None, None).expect("a pty");
        let path = nix::unistd::ttyname(pty.slave.as_fd()).expect("its name");
        let line = LineSettings::new(9600, Parity::None, 2);
        let link = SerialLink::open(&path.to_string_lossy(), &line).expect("opens");
        drop(pty.slave);
        (link, File::from(pty.master))
    }

    #[tokio::test]
    async fn a_pty_is_told_from_a_serial_port() {
        let (link, _devices) = pty();
        assert!(link.is_pseudo_terminal());
        // A tty of another kind (/dev/ttyS*, ttyUSB*, ttyAMA*: majors 4, 188, 204) is not.
        assert!(!is_pty_slave_major(4));
        assert!(!is_pty_slave_major(188));
        assert!(!is_pty_slave_major(204));
    }

    /// A link that may block waits out a short wait on the thread: a task of the same runtime
    /// does not run meanwhile (here the "device" that would answer at once, so nothing comes
    /// before the deadline); a wait beyond the limit goes through the reactor, where it does.
    #[test]
    fn short_waits_block_the_thread_and_long_ones_do_not() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("a runtime");
        runtime.block_on(async {
            let (mut link, mut devices) = pty();
            link.block_short_waits();
            let answer = tokio::spawn(async move {
                devices.write_all(&[0x14, 0x03, 0x02]).expect("written");
                devices
            });
            let mut buffer = [0u8; 16];
            let short = Instant::now() + BLOCKING_WAIT_LIMIT / 2;
            assert_eq!(
                link.read_until(short, &mut buffer).await.expect("io"),
                None,
                "the answering task ran during a wait that blocks"
            );
            let long = Instant::now() + Duration::from_secs(30);
            assert_eq!(
                link.read_until(long, &mut buffer).await.expect("io"),
                Some(3)
            );
            assert!(Instant::now() < long, "the bytes ended the wait");
            assert_eq!(&buffer[..3], &[0x14, 0x03, 0x02]);
            let _devices = answer.await.expect("the task ran");
        });
    }

    /// The blocking waits keep the link's rules: bytes that came during a blocked silence are
    /// noticed and read; a blocked read returns what came, or nothing at its deadline.
    #[tokio::test]
    async fn blocked_waits_notice_bytes_as_the_reactor_does() {
        let (mut link, mut devices) = pty();
        link.block_short_waits();
        let silence = Duration::from_millis(40);
        let end = Instant::now() + silence;
        let mut buffer = [0u8; 16];
        assert_eq!(link.quiet_until(end, &mut buffer).await.expect("io"), None);
        assert!(Instant::now() >= end, "the silence was not waited out");
        devices.write_all(&[0x01, 0x03]).expect("written");
        assert_eq!(
            link.quiet_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            Some(2)
        );
        assert_eq!(
            link.quiet_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            None
        );
        let deadline = Instant::now() + silence;
        assert_eq!(
            link.read_until(deadline, &mut buffer).await.expect("io"),
            None
        );
        assert!(Instant::now() >= deadline, "gave up before its deadline");
        devices.write_all(&[0x05, 0x06]).expect("written");
        assert_eq!(
            link.read_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            Some(2)
        );
        devices.write_all(&[0x07]).expect("written");
        assert_eq!(
            link.read_at(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            Some(1)
        );
        assert_eq!(buffer[0], 0x07);
    }

    #[tokio::test]
    async fn bytes_during_the_silence_before_a_request_are_noticed_and_read() {
        let (mut link, mut devices) = pty();
        let silence = Duration::from_millis(200);
        let mut buffer = [0u8; 16];
        assert_eq!(
            link.quiet_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            None
        );
        devices.write_all(&[0x01, 0x03, 0x02]).expect("written");
        assert_eq!(
            link.quiet_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            Some(3),
            "the bytes that came during the silence"
        );
        assert_eq!(buffer[..3], [0x01, 0x03, 0x02]);
        // They were read: the line is quiet again, and nothing is left to read.
        assert_eq!(
            link.quiet_until(Instant::now() + silence, &mut buffer)
                .await
                .expect("io"),
            None
        );
        assert_eq!(link.read_now(&mut buffer).expect("io"), None);
    }
}
