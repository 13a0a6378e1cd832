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
//! and reopens it. That open slave would also keep what the devices send while no master has the
//! port open, and what a master left unread when it closed, for the next master to read as if
//! it had just come (libmodbus, which does not flush on opening, read the reply to a request of a
//! master killed mid-transaction as the answer to its own). A real port does not: its input
//! starts empty at each first open, and nothing is received while it is closed. So the
//! simulator watches the slave's device node for opens and closes (inotify) and, while nobody
//! else has it open, drops the devices' bytes and what was left in the slave's input
//! ([`Listeners`]).

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::{AsFd, AsRawFd, FromRawFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::termios::{self, BaudRate, ControlFlags, FlushArg, SetArg};
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
    /// Who else has the slave open, and whether the devices' bytes reach anyone.
    listeners: Listeners,
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
        // Watched before the symlink exists: no master can open it unseen.
        let listeners = Listeners::watch(&slave_path, pty.slave.try_clone()?);
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
            listeners,
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
    fn serve(mut self, runtime: &SimRuntime, generation: u64) -> io::Result<()> {
        let mut writer = self.master.try_clone()?;
        let gate = Arc::clone(&self.listeners.gate);
        let (pacer, pacer_thread) = Pacer::spawn(
            "pty",
            runtime.clock,
            runtime.receiver,
            Box::new(move |bytes| deliver(&gate, &mut writer, bytes)),
        )?;
        let mut reader = PtyReader {
            master: &self.master,
            listeners: &mut self.listeners,
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

/// Hands bytes to the master, or drops them while nobody has the slave open (see [`Listeners`]).
fn deliver(gate: &Mutex<Gate>, master: &mut File, bytes: &[u8]) -> io::Result<()> {
    // Held across the write: a close's flush comes wholly before or after it.
    let gate = lock_gate(gate);
    if !gate.open {
        tracing::debug!(
            "sim: pty: nobody has the port open, {} byte(s) lost",
            bytes.len()
        );
        return Ok(());
    }
    write_all_nonblocking(master, bytes)
}

fn lock_gate(gate: &Mutex<Gate>) -> MutexGuard<'_, Gate> {
    gate.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Whether the devices' bytes reach a master.
struct Gate {
    /// Someone besides the simulator has the slave open.
    open: bool,
    /// The simulator's own slave descriptor, to flush its input.
    slave: OwnedFd,
}

/// Who has the pty's slave open besides the simulator, from inotify's open and close events on
/// its device node (a file description's last close is one event, whoever holds copies of
/// it). When the last one closes, what is left unread in the slave's input is flushed, and
/// until the next open the devices' bytes are dropped: a real serial port's input starts empty
/// at each first open and nothing is received while it is closed (the kernel frees a tty's
/// buffers at its last close; the UART's receiver is off). The events are read by the link's
/// reader thread before it reads the master's bytes: a master's open is queued before it can
/// write a request, so the reply to it is never dropped. Without inotify (no instance left),
/// bytes always go in, as before.
struct Listeners {
    inotify: Option<OwnedFd>,
    /// Opens minus closes seen.
    openers: usize,
    gate: Arc<Mutex<Gate>>,
}

impl Listeners {
    fn watch(slave_path: &Path, slave: OwnedFd) -> Self {
        let inotify = watch_opens(slave_path)
            .inspect_err(|err| {
                tracing::warn!(
                    "sim: pty: cannot watch {} for opens ({err}): bytes sent while no master has it open will reach the next one",
                    slave_path.display()
                );
            })
            .ok();
        let gate = Gate {
            open: inotify.is_none(),
            slave,
        };
        Self {
            inotify,
            openers: 0,
            gate: Arc::new(Mutex::new(gate)),
        }
    }

    fn inotify_fd(&self) -> Option<std::os::fd::BorrowedFd<'_>> {
        self.inotify.as_ref().map(AsFd::as_fd)
    }

    /// Reads the pending open and close events and opens or shuts the gate.
    fn update(&mut self) {
        if let Err(err) = self.read_events() {
            tracing::warn!("sim: pty: watching for opens failed ({err}); bytes go in from now on");
            self.inotify = None;
            lock_gate(&self.gate).open = true;
        }
    }

    fn read_events(&mut self) -> io::Result<()> {
        let Some(inotify) = &self.inotify else {
            return Ok(());
        };
        let was_open = self.openers > 0;
        // The last opener closed, whoever opened it again since (a close and an open read
        // together): what it left unread goes.
        let mut last_closed = false;
        let mut buf = [0u8; 1024];
        loop {
            let len = match nix::unistd::read(inotify, &mut buf) {
                Ok(0) | Err(nix::Error::EAGAIN) => break,
                Ok(len) => len,
                Err(nix::Error::EINTR) => continue,
                Err(err) => return Err(nix_err(err)),
            };
            for mask in event_masks(buf.get(..len).unwrap_or(&[])) {
                let openers = count_openers(self.openers, mask);
                last_closed |= self.openers > 0 && openers == 0;
                self.openers = openers;
            }
        }
        let open = self.openers > 0;
        if open == was_open && !last_closed {
            return Ok(());
        }
        let mut gate = lock_gate(&self.gate);
        if last_closed {
            if let Err(err) = termios::tcflush(&gate.slave, FlushArg::TCIFLUSH) {
                tracing::warn!("sim: pty: flushing the input of a closed port: {err}");
            }
        }
        gate.open = open;
        tracing::debug!(
            "sim: pty: {}",
            match (last_closed, open) {
                (true, true) => "closed, input dropped, opened again",
                (true, false) => "closed, input dropped",
                _ => "opened",
            }
        );
        Ok(())
    }
}

/// An inotify instance (non-blocking) watching `path` for opens and closes.
fn watch_opens(path: &Path) -> io::Result<OwnedFd> {
    use nix::libc;
    // SAFETY: plain FFI call; a non-negative result is a new descriptor we then own.
    let fd = unsafe { libc::inotify_init1(libc::IN_NONBLOCK | libc::IN_CLOEXEC) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `fd` was just returned by inotify_init1 and is owned by nobody else.
    let inotify = unsafe { OwnedFd::from_raw_fd(fd) };
    let path = std::ffi::CString::new(path.as_os_str().as_bytes())
        .map_err(|err| io::Error::new(io::ErrorKind::InvalidInput, err))?;
    let mask = libc::IN_OPEN | libc::IN_CLOSE_WRITE | libc::IN_CLOSE_NOWRITE;
    // SAFETY: a valid inotify descriptor and a NUL-terminated path that outlives the call.
    let watch = unsafe { libc::inotify_add_watch(inotify.as_raw_fd(), path.as_ptr(), mask) };
    if watch < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(inotify)
}

/// The masks of the inotify events in `bytes` (each a 16-byte header and `len` name bytes).
fn event_masks(bytes: &[u8]) -> Vec<u32> {
    let field = |at: usize| {
        bytes
            .get(at..at + 4)
            .and_then(|b| <[u8; 4]>::try_from(b).ok())
            .map(u32::from_ne_bytes)
    };
    let mut masks = Vec::new();
    let mut at = 0;
    while let (Some(mask), Some(name_len)) = (field(at + 4), field(at + 12)) {
        masks.push(mask);
        at += 16 + usize::try_from(name_len).unwrap_or(usize::MAX - 16);
    }
    masks
}

/// The openers after one event. Lost events (the queue overflowed) leave the count unknown:
/// taken as open, the old behaviour, until the next close.
fn count_openers(openers: usize, mask: u32) -> usize {
    use nix::libc;
    if mask & libc::IN_Q_OVERFLOW != 0 {
        openers.max(1)
    } else if mask & libc::IN_OPEN != 0 {
        openers + 1
    } else if mask & (libc::IN_CLOSE_WRITE | libc::IN_CLOSE_NOWRITE) != 0 {
        openers.saturating_sub(1)
    } else {
        openers
    }
}

struct PtyReader<'a> {
    master: &'a File,
    listeners: &'a mut Listeners,
}

impl LinkReader for PtyReader<'_> {
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<Option<usize>> {
        // ppoll, not poll: a frame gap at 115200 is 334 µs, and poll counts in whole ms.
        let (master_ready, watch_ready) = {
            let inotify = self.listeners.inotify_fd();
            let master = self.master.as_fd();
            let mut fds = [
                PollFd::new(master, PollFlags::POLLIN),
                PollFd::new(inotify.unwrap_or(master), PollFlags::POLLIN),
            ];
            let watched = if inotify.is_some() { 2 } else { 1 };
            let fds = fds.get_mut(..watched).unwrap_or_default();
            match ppoll(fds, Some(TimeSpec::from_duration(timeout)), None) {
                Ok(0) | Err(nix::Error::EINTR) => return Ok(None),
                Ok(_) => {}
                Err(err) => return Err(nix_err(err)),
            }
            let ready = |fd: Option<&PollFd>| {
                fd.and_then(PollFd::revents)
                    .is_some_and(|events| !events.is_empty())
            };
            (ready(fds.first()), ready(fds.get(1)))
        };
        // Opens and closes first: a master's open comes before its request, so when the
        // request is readable the open's event is too (poll reports every ready descriptor).
        if watch_ready {
            self.listeners.update();
        }
        if !master_ready {
            return Ok(None);
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::OpenOptionsExt;
    use std::time::Instant;

    fn open_port(path: &Path) -> File {
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(path)
            .expect("the pty opens")
    }

    /// Reads `port` until what arrived ends with `end` (a pty hands bytes over through a kernel
    /// work queue).
    fn read_through(port: &mut File, end: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut got = Vec::new();
        let mut buf = [0u8; 64];
        while !got.ends_with(end.as_bytes()) {
            let so_far = String::from_utf8_lossy(&got);
            assert!(Instant::now() < deadline, "only {so_far:?} arrived");
            let mut fds = [PollFd::new(port.as_fd(), PollFlags::POLLIN)];
            let _ = ppoll(
                &mut fds,
                Some(TimeSpec::from_duration(Duration::from_millis(50))),
                None,
            );
            if let Ok(len) = port.read(&mut buf) {
                got.extend_from_slice(buf.get(..len).unwrap_or(&[]));
            }
        }
        String::from_utf8(got).unwrap()
    }

    /// libmodbus opens a port without flushing it: after a master was killed with a reply on
    /// its way, the next one read that reply as the answer to its own request. A real port's
    /// input starts empty at each first open and receives nothing while closed.
    #[test]
    fn bytes_left_or_sent_while_nobody_has_the_pty_open_never_reach_the_next_master() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("tty");
        let mut pty = PtyLink::open(&link, LineSettings::WIREN_BOARD_DEFAULT).unwrap();
        let gate = Arc::clone(&pty.listeners.gate);
        let mut master = pty.master.try_clone().unwrap();
        let mut send = |pty: &mut PtyLink, bytes: &[u8]| {
            pty.listeners.update();
            deliver(&gate, &mut master, bytes).unwrap();
        };
        send(&mut pty, b"before anyone opened it;");
        let mut first = open_port(&link);
        send(&mut pty, b"to the first;");
        assert_eq!(read_through(&mut first, "first;"), "to the first;");
        // A second master has it open too: the first one's close is not the last.
        let mut second = open_port(&link);
        send(&mut pty, b"unread by the first;");
        drop(first);
        send(&mut pty, b"to the second;");
        assert_eq!(
            read_through(&mut second, "to the second;"),
            "unread by the first;to the second;"
        );
        send(&mut pty, b"left unread;");
        drop(second);
        send(&mut pty, b"while closed;");
        let mut third = open_port(&link);
        send(&mut pty, b"to the third;");
        assert_eq!(read_through(&mut third, "third;"), "to the third;");
        // Closed and opened again before the simulator looks: a new first open all the same.
        send(&mut pty, b"left by the third;");
        drop(third);
        let mut fourth = open_port(&link);
        send(&mut pty, b"to the fourth;");
        assert_eq!(read_through(&mut fourth, "fourth;"), "to the fourth;");
    }

    #[test]
    fn inotify_event_masks_are_read_from_their_headers() {
        let mut bytes = Vec::new();
        for (mask, name) in [
            (nix::libc::IN_OPEN, &b""[..]),
            (nix::libc::IN_CLOSE_WRITE, b"abcd"),
        ] {
            bytes.extend_from_slice(&1i32.to_ne_bytes());
            bytes.extend_from_slice(&mask.to_ne_bytes());
            bytes.extend_from_slice(&0u32.to_ne_bytes());
            bytes.extend_from_slice(&(name.len() as u32).to_ne_bytes());
            bytes.extend_from_slice(name);
        }
        let masks = event_masks(&bytes);
        assert_eq!(masks, [nix::libc::IN_OPEN, nix::libc::IN_CLOSE_WRITE]);
        let openers = masks.iter().fold(0, |n, &mask| count_openers(n, mask));
        assert_eq!(openers, 0);
        assert_eq!(count_openers(0, nix::libc::IN_CLOSE_NOWRITE), 0);
        assert_eq!(count_openers(0, nix::libc::IN_Q_OVERFLOW), 1);
    }
}
