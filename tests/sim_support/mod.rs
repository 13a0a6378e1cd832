//! Drives the real `rtu2mqtt sim` binary: starts it on a pty in a temp dir, waits for its "ready"
//! line, opens the pty as a master would (termios), and exchanges frames built by the protocol
//! core. The child is killed when the guard drops.
#![allow(dead_code)]

use rtu2mqtt::child::StopWithParent;
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios::{self, BaudRate, ControlFlags, FlushArg, SetArg};
use rtu2mqtt::protocol::{LineSettings, Parity, ParseStatus, ParsedReply, ReplyParser, Request};
use serde_json::Value;

pub const FAST: LineSettings = LineSettings::new(115_200, Parity::None, 2);

pub fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/sim")
        .join(name)
}

pub struct SimProcess {
    child: Child,
    pub dir: tempfile::TempDir,
    pub pty: PathBuf,
    pub control: PathBuf,
    pub stdout: Receiver<String>,
    banner: Vec<String>,
}

impl SimProcess {
    pub fn start(bus_file: &str, extra: &[&str]) -> Self {
        Self::start_with(&data(bus_file), &data(""), extra)
    }

    /// A bus file and template directory anywhere.
    pub fn start_with(bus_file: &Path, templates: &Path, extra: &[&str]) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let pty = dir.path().join("ttyRS485-sim");
        let control = dir.path().join("control.sock");
        let mut child = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
            .stop_with_parent()
            .arg("sim")
            .arg("--bus")
            .arg(bus_file)
            .arg("--templates")
            .arg(templates)
            .arg("--pty")
            .arg(&pty)
            .arg("--control")
            .arg(&control)
            .args(extra)
            .stdout(Stdio::piped())
            .stdin(Stdio::null())
            .spawn()
            .unwrap();
        let (sender, stdout) = mpsc::channel();
        let out = child.stdout.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if sender.send(line).is_err() {
                    break;
                }
            }
        });
        let mut process = Self {
            child,
            dir,
            pty,
            control,
            stdout,
            banner: Vec::new(),
        };
        loop {
            match process.stdout.recv_timeout(Duration::from_secs(30)) {
                Ok(line) if line == "ready" => break,
                Ok(line) => process.banner.push(line),
                Err(err) => panic!("the simulator did not get ready: {err}"),
            }
        }
        process
    }

    /// The lines printed before "ready".
    pub fn banner(&self) -> &[String] {
        &self.banner
    }

    /// Sends one control command, returns its reply.
    pub fn control(&self, command: Value) -> Value {
        let mut stream = UnixStream::connect(&self.control).unwrap();
        writeln!(stream, "{command}").unwrap();
        let mut line = String::new();
        BufReader::new(stream).read_line(&mut line).unwrap();
        let reply: Value = serde_json::from_str(&line).unwrap();
        assert_eq!(reply["ok"], Value::Bool(true), "{command} → {reply}");
        reply
    }

    pub fn master(&self, line: LineSettings) -> MasterPort {
        MasterPort::open(&self.pty, line)
    }
}

impl Drop for SimProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The daemon's end of the pty.
pub struct MasterPort {
    file: File,
    line: LineSettings,
    /// When bytes were last read: a request keeps 3.5 characters of silence after them, as
    /// any RTU master must (the simulator's devices take a request sooner for the end of the
    /// frame they heard).
    last_read: Option<Instant>,
}

fn baud(baud: u32) -> BaudRate {
    match baud {
        1200 => BaudRate::B1200,
        2400 => BaudRate::B2400,
        4800 => BaudRate::B4800,
        9600 => BaudRate::B9600,
        19200 => BaudRate::B19200,
        38400 => BaudRate::B38400,
        57600 => BaudRate::B57600,
        _ => BaudRate::B115200,
    }
}

impl MasterPort {
    pub fn open(path: &Path, line: LineSettings) -> Self {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(path)
            .unwrap();
        let mut port = Self {
            file,
            line,
            last_read: None,
        };
        port.set_line(line);
        port
    }

    pub fn set_line(&mut self, line: LineSettings) {
        self.line = line;
        let mut settings = termios::tcgetattr(&self.file).unwrap();
        termios::cfmakeraw(&mut settings);
        let flags = &mut settings.control_flags;
        flags.insert(ControlFlags::CLOCAL | ControlFlags::CREAD);
        flags.set(ControlFlags::CSTOPB, line.stop_bits == 2);
        flags.set(ControlFlags::PARENB, line.parity != Parity::None);
        flags.set(ControlFlags::PARODD, line.parity == Parity::Odd);
        termios::cfsetspeed(&mut settings, baud(line.baud)).unwrap();
        termios::tcsetattr(&self.file, SetArg::TCSANOW, &settings).unwrap();
    }

    /// Bytes that arrive within `timeout`, each read with its arrival time; stops early when
    /// `done` says the bytes so far are complete.
    pub fn read_until(
        &mut self,
        timeout: Duration,
        mut done: impl FnMut(&[u8]) -> bool,
    ) -> Vec<(Instant, Vec<u8>)> {
        let deadline = Instant::now() + timeout;
        let mut chunks = Vec::new();
        let mut all = Vec::new();
        let mut buf = [0u8; 512];
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            let millis = u16::try_from(left.as_millis().max(1)).unwrap_or(u16::MAX);
            let mut fds = [PollFd::new(self.file.as_fd(), PollFlags::POLLIN)];
            if poll(&mut fds, PollTimeout::from(millis)).unwrap_or(0) == 0 {
                continue;
            }
            match self.file.read(&mut buf) {
                Ok(len) if len > 0 => {
                    let at = Instant::now();
                    self.last_read = Some(at);
                    chunks.push((at, buf[..len].to_vec()));
                    all.extend_from_slice(&buf[..len]);
                    if done(&all) {
                        break;
                    }
                }
                _ => {}
            }
        }
        chunks
    }

    pub fn send(&mut self, frame: &[u8]) {
        // The RTU frame gap (a protocol rule, not a wait for anything).
        if let Some(last_read) = self.last_read {
            let quiet_from = last_read + self.line.frame_gap();
            std::thread::sleep(quiet_from.saturating_duration_since(Instant::now()));
        }
        termios::tcflush(&self.file, FlushArg::TCIFLUSH).unwrap();
        self.file.write_all(frame).unwrap();
    }

    /// Plays a master that keeps no frame gap of its own: its next request goes out as soon as
    /// it is written (libmodbus works so).
    pub fn forget_last_read(&mut self) {
        self.last_read = None;
    }

    /// Sends `request` and returns every byte read until a reply to it is complete, and the reply.
    pub fn transact(&mut self, request: &Request) -> (Vec<u8>, Option<ParsedReply>) {
        self.transact_raw(&request.encode().unwrap(), request)
    }

    pub fn transact_raw(
        &mut self,
        frame: &[u8],
        request: &Request,
    ) -> (Vec<u8>, Option<ParsedReply>) {
        self.send(frame);
        let mut parser = ReplyParser::for_request(request);
        let mut reply = None;
        let chunks = self.read_until(Duration::from_secs(2), |all| {
            parser.clear();
            parser.push(all);
            loop {
                match parser.poll() {
                    ParseStatus::Frame(parsed) => {
                        reply = Some(parsed);
                        return true;
                    }
                    ParseStatus::NeedMore => return false,
                    ParseStatus::Error(_) => {}
                }
            }
        });
        (
            chunks.into_iter().flat_map(|(_, bytes)| bytes).collect(),
            reply,
        )
    }
}

pub fn hex(text: &str) -> Vec<u8> {
    rtu2mqtt::protocol::parse_hex(text).unwrap()
}

pub fn with_crc(text: &str) -> Vec<u8> {
    let mut frame = hex(text);
    let crc = rtu2mqtt::protocol::crc16(&frame);
    frame.extend_from_slice(&crc.to_le_bytes());
    frame
}

pub fn ff(count: usize) -> Vec<u8> {
    vec![0xFF; count]
}
