//! The control interface's IO: JSON lines on a Unix socket (one thread per connection) and,
//! optionally, on stdin/stdout. A connection that sends `{"cmd":"watch"}` then receives the
//! change log, one JSON line per register change, until it closes.

use std::io::{self, BufRead, BufReader, Write};
use std::os::unix::fs::FileTypeExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::Path;
use std::sync::mpsc;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use super::control::execute_line;
use super::runtime::SimRuntime;

/// Binds `path` (replacing only a stale socket, never another kind of file) with mode 0600, and
/// serves connections until the runtime stops. The socket can change registers and inject
/// faults: only its owner may use it.
pub fn spawn_control_socket(path: &Path, runtime: Arc<SimRuntime>) -> io::Result<JoinHandle<()>> {
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if !meta.file_type().is_socket() {
            return Err(io::Error::new(
                io::ErrorKind::AlreadyExists,
                format!(
                    "{} already exists and is not a socket; remove it or choose another --control path",
                    path.display()
                ),
            ));
        }
        std::fs::remove_file(path)?;
    }
    // The mode is set by the umask at bind time; a chmod afterwards would leave a window.
    let previous = nix::sys::stat::umask(nix::sys::stat::Mode::from_bits_truncate(0o177));
    let bound = UnixListener::bind(path);
    nix::sys::stat::umask(previous);
    let listener = bound?;
    listener.set_nonblocking(true)?;
    std::thread::Builder::new()
        .name("sim-control".into())
        .spawn(move || {
            while !runtime.stopped() {
                match listener.accept() {
                    Ok((stream, _)) => {
                        let runtime = Arc::clone(&runtime);
                        let spawned = std::thread::Builder::new()
                            .name("sim-control-conn".into())
                            .spawn(move || {
                                if let Err(err) = serve_connection(stream, &runtime) {
                                    tracing::debug!("sim: control connection: {err}");
                                }
                            });
                        if let Err(err) = spawned {
                            tracing::warn!("sim: control: {err}");
                        }
                    }
                    Err(err) if err.kind() == io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(20));
                    }
                    Err(err) => {
                        tracing::warn!("sim: control: accept: {err}");
                        std::thread::sleep(Duration::from_millis(100));
                    }
                }
            }
        })
}

fn serve_connection(stream: UnixStream, runtime: &SimRuntime) -> io::Result<()> {
    stream.set_nonblocking(false)?;
    let mut writer = stream.try_clone()?;
    let reader = BufReader::new(stream);
    if let Some(changes) = serve_lines(reader, &mut writer, runtime)? {
        stream_changes(&mut writer, runtime, &changes)?;
    }
    Ok(())
}

/// Answers command lines; when the peer asks to `watch`, returns the change log's receiver,
/// registered before the reply went out so that no change made after the reply is missed.
pub fn serve_lines(
    reader: impl BufRead,
    writer: &mut dyn Write,
    runtime: &SimRuntime,
) -> io::Result<Option<mpsc::Receiver<String>>> {
    for line in reader.lines() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        let mut outcome = runtime.with_bus(|bus, now| execute_line(bus, now, &line));
        // `stats` also reports the pacers' timing error, which lives outside the bus.
        if let Some(fields) = outcome.reply.as_object_mut() {
            if fields.contains_key("reply_bytes") {
                fields.insert("pacing".into(), super::runtime::PACING_ERROR.to_json());
            }
        }
        let changes = outcome.watch.then(|| {
            let (sender, receiver) = mpsc::channel();
            runtime.log.watch(sender);
            receiver
        });
        writeln!(writer, "{}", outcome.reply)?;
        writer.flush()?;
        if changes.is_some() {
            return Ok(changes);
        }
    }
    Ok(None)
}

fn stream_changes(
    writer: &mut dyn Write,
    runtime: &SimRuntime,
    receiver: &mpsc::Receiver<String>,
) -> io::Result<()> {
    while !runtime.stopped() {
        match receiver.recv_timeout(Duration::from_millis(200)) {
            Ok(line) => {
                writeln!(writer, "{line}")?;
                writer.flush()?;
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
    }
    Ok(())
}

/// Control commands on stdin, replies on stdout.
pub fn spawn_stdin_control(runtime: Arc<SimRuntime>) -> io::Result<JoinHandle<()>> {
    std::thread::Builder::new()
        .name("sim-stdin".into())
        .spawn(move || {
            let stdin = io::stdin();
            let mut stdout = io::stdout();
            match serve_lines(stdin.lock(), &mut stdout, &runtime) {
                Ok(Some(changes)) => {
                    if let Err(err) = stream_changes(&mut stdout, &runtime, &changes) {
                        tracing::debug!("sim: stdin control: {err}");
                    }
                }
                Ok(None) => {}
                Err(err) => tracing::debug!("sim: stdin control: {err}"),
            }
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{LineSettings, Parity, RegisterType};
    use crate::sim::runtime::ChangeLog;
    use crate::sim::{Bus, DeviceSpec, RegisterMap, VirtualDevice};

    /// Makes a change the moment the `watch` reply is written, as a peer acting on the reply
    /// (or a script, or the master) may.
    struct ChangeOnReply<'a> {
        runtime: &'a SimRuntime,
        written: Vec<u8>,
    }

    impl Write for ChangeOnReply<'_> {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.written.extend_from_slice(buf);
            Ok(buf.len())
        }

        fn flush(&mut self) -> io::Result<()> {
            self.runtime.with_bus(|bus, now| {
                bus.write_register(0, RegisterType::Coil, 0, &[1], now)
                    .map_err(|code| io::Error::other(code.to_string()))
            })
        }
    }

    #[test]
    fn a_change_right_after_the_watch_reply_is_streamed() {
        let mut registers = RegisterMap::new();
        registers.define(RegisterType::Coil, 0, 1, true);
        let device = VirtualDevice::new(DeviceSpec {
            name: "a".into(),
            template: "-".into(),
            serial: 1,
            address: 20,
            line: LineSettings::new(9600, Parity::None, 2),
            fast: true,
            turnaround: Duration::ZERO,
            model: "M".into(),
            firmware: "1".into(),
            signature: "s".into(),
            registers,
        });
        let runtime = SimRuntime::new(Bus::new(vec![device], 1), ChangeLog::new(None));
        let mut writer = ChangeOnReply {
            runtime: &runtime,
            written: Vec::new(),
        };
        let changes = serve_lines(&b"{\"cmd\":\"watch\"}\n"[..], &mut writer, &runtime)
            .unwrap()
            .expect("watching");
        assert!(String::from_utf8_lossy(&writer.written).contains("\"ok\":true"));
        let line = changes
            .try_recv()
            .expect("the change made right after the reply");
        assert!(line.contains("\"origin\":\"control\""), "{line}");
    }
}
