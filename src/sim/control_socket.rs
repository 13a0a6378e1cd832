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
    if serve_lines(reader, &mut writer, runtime)? {
        stream_changes(&mut writer, runtime)?;
    }
    Ok(())
}

/// Answers command lines; returns true when the peer asked to `watch`.
pub fn serve_lines(
    reader: impl BufRead,
    writer: &mut dyn Write,
    runtime: &SimRuntime,
) -> io::Result<bool> {
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
        writeln!(writer, "{}", outcome.reply)?;
        writer.flush()?;
        if outcome.watch {
            return Ok(true);
        }
    }
    Ok(false)
}

fn stream_changes(writer: &mut dyn Write, runtime: &SimRuntime) -> io::Result<()> {
    let (sender, receiver) = mpsc::channel();
    runtime.log.watch(sender);
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
                Ok(true) => {
                    if let Err(err) = stream_changes(&mut stdout, &runtime) {
                        tracing::debug!("sim: stdin control: {err}");
                    }
                }
                Ok(false) => {}
                Err(err) => tracing::debug!("sim: stdin control: {err}"),
            }
        })
}
