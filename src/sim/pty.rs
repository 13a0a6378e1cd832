//! Pseudo-terminal transport. The master (the daemon, a test) opens the pty's slave through a
//! stable symlink and sets its port settings with termios as on a real serial port; the simulator
//! holds the pty master and reads those settings with `tcgetattr` on it (Linux returns the slave's
//! termios there).
//!
//! What is detected: the baud rate, CSTOPB (2 stop bits: they time the master's frames, a device
//! hears a master whatever its stop bits, see `MasterLine::matches`) and PARODD. The Linux pty driver clears
//! PARENB and forces CS8 whenever the slave's termios are set, so "no parity" and "even parity"
//! look alike: a master with PARODD clear is heard by devices with parity none or even, and one
//! with PARODD set only by devices with odd parity. Data bits are always 8.
//!
//! The simulator keeps the slave open itself, so the pty never hangs up when the master closes
//! and reopens it.

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::termios::{self, BaudRate, ControlFlags, SetArg};
use nix::sys::time::TimeSpec;

use crate::protocol::{LineSettings, Parity};

use super::line::{MasterLine, ObservedParity};
use super::link::{serve, LinkReader};
use super::pacing::Pacer;
use super::runtime::SimRuntime;

/// An open pty with its symlink.
pub struct PtyLink {
    master: File,
    _slave: OwnedFd,
    pub slave_path: PathBuf,
    pub link: PathBuf,
    /// The settings a new pty gets after the link was cut.
    initial: LineSettings,
}

fn nix_err(err: nix::Error) -> io::Error {
    io::Error::from(err)
}

impl PtyLink {
    /// Opens a pty, sets its slave to raw `initial` settings, and points `link` at the slave
    /// (replacing only a stale simulator link there; any other file is left alone, with an error).
    pub fn open(link: &Path, initial: LineSettings) -> io::Result<Self> {
        let pty = nix::pty::openpty(None, None).map_err(nix_err)?;
        let mut settings = termios::tcgetattr(&pty.slave).map_err(nix_err)?;
        termios::cfmakeraw(&mut settings);
        settings.control_flags |= ControlFlags::CLOCAL | ControlFlags::CREAD;
        settings
            .control_flags
            .set(ControlFlags::CSTOPB, initial.stop_bits == 2);
        settings
            .control_flags
            .set(ControlFlags::PARODD, initial.parity == Parity::Odd);
        let baud = baud_rate(initial.baud).unwrap_or(BaudRate::B9600);
        termios::cfsetspeed(&mut settings, baud).map_err(nix_err)?;
        termios::tcsetattr(&pty.slave, SetArg::TCSANOW, &settings).map_err(nix_err)?;
        let slave_path = nix::unistd::ttyname(pty.slave.as_fd()).map_err(nix_err)?;
        let flags = fcntl(&pty.master, FcntlArg::F_GETFL).map_err(nix_err)?;
        let flags = OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK;
        fcntl(&pty.master, FcntlArg::F_SETFL(flags)).map_err(nix_err)?;
        if std::fs::symlink_metadata(link).is_ok() {
            // Only a stale link of an earlier simulator (into /dev/pts) is replaced; anything
            // else there may be someone's file, which `ln -sf` semantics would destroy.
            let stale_pty_link =
                std::fs::read_link(link).is_ok_and(|target| target.starts_with("/dev/pts/"));
            if !stale_pty_link {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "{} already exists and is not a simulator's pty link; remove it or choose another --pty path",
                        link.display()
                    ),
                ));
            }
            std::fs::remove_file(link)?;
        }
        std::os::unix::fs::symlink(&slave_path, link)?;
        Ok(Self {
            master: File::from(pty.master),
            _slave: pty.slave,
            slave_path,
            link: link.to_path_buf(),
            initial,
        })
    }

    /// Serves the pty on two threads (receive loop, pacer) until the runtime stops. When the
    /// links are cut (the `link_down` control command) the pty goes away as an unplugged USB
    /// adapter does: symlink removed, both ends closed, so the master's open descriptor fails;
    /// once the links are up again a new pty appears behind the same symlink.
    pub fn spawn(self, runtime: Arc<SimRuntime>) -> io::Result<JoinHandle<()>> {
        std::thread::Builder::new()
            .name("sim-pty".into())
            .spawn(move || {
                let link = self.link.clone();
                let initial = self.initial;
                let mut pty = Some(self);
                while let Some(open) = pty.take() {
                    let generation = runtime.link_generation();
                    if runtime.link_up() {
                        if let Err(err) = open.serve(&runtime, generation) {
                            tracing::error!("sim: pty: {err}");
                            return;
                        }
                    } else {
                        drop(open);
                    }
                    if runtime.stopped() {
                        return;
                    }
                    tracing::info!("sim: pty {} gone (link cut)", link.display());
                    while !runtime.link_up() && !runtime.stopped() {
                        std::thread::sleep(LINK_POLL);
                    }
                    if runtime.stopped() {
                        return;
                    }
                    while pty.is_none() && !runtime.stopped() {
                        match PtyLink::open(&link, initial) {
                            Ok(reopened) => {
                                tracing::info!(
                                    "sim: pty {} back -> {}",
                                    link.display(),
                                    reopened.slave_path.display()
                                );
                                pty = Some(reopened);
                            }
                            Err(err) => {
                                tracing::error!("sim: pty {}: {err}; trying again", link.display());
                                std::thread::sleep(LINK_POLL * 25);
                            }
                        }
                    }
                }
            })
    }

    /// Serves this pty until the runtime stops or the links' generation moves on; the pty is
    /// closed and its symlink removed when this returns.
    fn serve(self, runtime: &SimRuntime, generation: u64) -> io::Result<()> {
        let mut writer = self.master.try_clone()?;
        let (pacer, pacer_thread) = Pacer::spawn(
            "pty",
            runtime.clock,
            runtime.receiver,
            Box::new(move |bytes| write_all_nonblocking(&mut writer, bytes)),
        )?;
        let mut reader = PtyReader {
            master: &self.master,
        };
        let served = serve(&mut reader, &pacer, runtime, generation);
        pacer.close();
        let _ = pacer_thread.join();
        drop(self);
        served
    }
}

/// How often a cut pty looks whether it may come back.
const LINK_POLL: Duration = Duration::from_millis(20);

impl Drop for PtyLink {
    fn drop(&mut self) {
        remove_link(&self.link, &self.slave_path);
    }
}

/// Removes `link` if it still points at `target`.
pub fn remove_link(link: &Path, target: &Path) {
    if std::fs::read_link(link).is_ok_and(|points_to| points_to == target) {
        let _ = std::fs::remove_file(link);
    }
}

/// A full slave input queue (nobody reading) loses bytes, like a bus nobody listens to.
fn write_all_nonblocking(file: &mut File, bytes: &[u8]) -> io::Result<()> {
    match file.write_all(bytes) {
        Err(err) if err.kind() == io::ErrorKind::WouldBlock => {
            tracing::debug!("sim: pty: nobody reads, {} byte(s) lost", bytes.len());
            Ok(())
        }
        other => other,
    }
}

struct PtyReader<'a> {
    master: &'a File,
}

impl LinkReader for PtyReader<'_> {
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<Option<usize>> {
        // ppoll, not poll: a frame gap at 115200 is 334 µs, and poll counts in whole ms.
        let mut fds = [PollFd::new(self.master.as_fd(), PollFlags::POLLIN)];
        match ppoll(&mut fds, Some(TimeSpec::from_duration(timeout)), None) {
            Ok(0) | Err(nix::Error::EINTR) => return Ok(None),
            Ok(_) => {}
            Err(err) => return Err(nix_err(err)),
        }
        match self.master.read(buf) {
            Ok(len) => Ok(Some(len)),
            Err(err)
                if matches!(
                    err.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                ) =>
            {
                Ok(None)
            }
            // EIO: no slave open at the moment (cannot happen while we hold one); keep serving.
            Err(err) if err.raw_os_error() == Some(nix::libc::EIO) => {
                std::thread::sleep(Duration::from_millis(10));
                Ok(None)
            }
            Err(err) => Err(err),
        }
    }

    fn master_line(&self) -> MasterLine {
        match termios::tcgetattr(self.master) {
            Ok(settings) => {
                let flags = settings.control_flags;
                let parity = if flags.contains(ControlFlags::PARENB) {
                    ObservedParity::Known(if flags.contains(ControlFlags::PARODD) {
                        Parity::Odd
                    } else {
                        Parity::Even
                    })
                } else if flags.contains(ControlFlags::PARODD) {
                    ObservedParity::Known(Parity::Odd)
                } else {
                    ObservedParity::NoneOrEven
                };
                MasterLine {
                    baud: master_baud(self.master),
                    // The pty forces CS8 (see the top of this file).
                    data_bits: 8,
                    stop_bits: if flags.contains(ControlFlags::CSTOPB) {
                        2
                    } else {
                        1
                    },
                    parity,
                }
            }
            Err(err) => {
                tracing::warn!("sim: pty: tcgetattr: {err}");
                MasterLine {
                    baud: 0,
                    data_bits: 8,
                    stop_bits: 1,
                    parity: ObservedParity::NoneOrEven,
                }
            }
        }
    }
}

/// The master's baud rate. Masters that set it with `termios2` (serialport, tokio-serial: any
/// rate via BOTHER) leave a speed no `BaudRate` constant names, and `cfgetospeed` of nix panics
/// on those; the kernel's `termios2` has the rate as a plain number whichever way it was set.
fn master_baud(master: &File) -> u32 {
    use std::os::fd::AsRawFd;
    // SAFETY: TCGETS2 fills a `termios2` (zero-initialised, correctly sized) for a tty fd we own
    // for the duration of the call; on failure the struct is left untouched and ignored.
    let mut settings: nix::libc::termios2 = unsafe { std::mem::zeroed() };
    let rc = unsafe { nix::libc::ioctl(master.as_raw_fd(), nix::libc::TCGETS2, &mut settings) };
    if rc == 0 && settings.c_ospeed > 0 {
        return settings.c_ospeed;
    }
    match termios::tcgetattr(master) {
        Ok(attrs) => {
            let raw = nix::libc::speed_t::from(
                attrs.control_flags.bits() as nix::libc::speed_t & nix::libc::CBAUD,
            );
            BaudRate::try_from(raw).map_or(0, baud_value)
        }
        Err(_) => 0,
    }
}

const BAUD_RATES: [(u32, BaudRate); 16] = [
    (300, BaudRate::B300),
    (600, BaudRate::B600),
    (1200, BaudRate::B1200),
    (2400, BaudRate::B2400),
    (4800, BaudRate::B4800),
    (9600, BaudRate::B9600),
    (19200, BaudRate::B19200),
    (38400, BaudRate::B38400),
    (57600, BaudRate::B57600),
    (115_200, BaudRate::B115200),
    (230_400, BaudRate::B230400),
    (460_800, BaudRate::B460800),
    (500_000, BaudRate::B500000),
    (576_000, BaudRate::B576000),
    (921_600, BaudRate::B921600),
    (1_000_000, BaudRate::B1000000),
];

/// The termios constant of a baud rate.
pub fn baud_rate(baud: u32) -> Option<BaudRate> {
    BAUD_RATES
        .iter()
        .find(|(b, _)| *b == baud)
        .map(|&(_, rate)| rate)
}

/// The baud rate of a termios constant (0 when unknown: no device matches).
pub fn baud_value(rate: BaudRate) -> u32 {
    BAUD_RATES
        .iter()
        .find(|(_, r)| *r == rate)
        .map_or(0, |&(b, _)| b)
}
