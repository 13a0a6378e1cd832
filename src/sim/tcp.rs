//! RTU over TCP: a listener whose connections carry raw RTU frames. The line settings are the
//! listener's (a TCP gateway's serial side); devices with other settings never hear it.

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use crate::protocol::LineSettings;

use super::line::MasterLine;
use super::link::{serve, LinkReader};
use super::pacing::Pacer;
use super::runtime::SimRuntime;

/// Binds `address` and serves every connection on its own threads until the runtime stops.
pub fn spawn_listener(
    address: &str,
    line: LineSettings,
    runtime: Arc<SimRuntime>,
) -> io::Result<(SocketAddr, JoinHandle<()>)> {
    let listener = TcpListener::bind(address)?;
    listener.set_nonblocking(true)?;
    let local = listener.local_addr()?;
    let handle = std::thread::Builder::new()
        .name("sim-tcp".into())
        .spawn(move || {
            while !runtime.stopped() {
                match listener.accept() {
                    Ok((stream, peer)) => {
                        tracing::info!("sim: tcp: {peer} connected");
                        let runtime = Arc::clone(&runtime);
                        if let Err(err) = spawn_connection(stream, line, runtime) {
                            tracing::warn!("sim: tcp: {peer}: {err}");
                        }
                    }
                    Err(err) if err.kind() == io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(20));
                    }
                    Err(err) => {
                        tracing::warn!("sim: tcp: accept: {err}");
                        std::thread::sleep(Duration::from_millis(100));
                    }
                }
            }
        })?;
    Ok((local, handle))
}

fn spawn_connection(
    stream: TcpStream,
    line: LineSettings,
    runtime: Arc<SimRuntime>,
) -> io::Result<()> {
    stream.set_nonblocking(false)?;
    stream.set_nodelay(true)?;
    let mut writer = stream.try_clone()?;
    let (pacer, pacer_thread) = Pacer::spawn(
        "tcp",
        runtime.clock,
        Box::new(move |bytes| writer.write_all(bytes)),
    )?;
    std::thread::Builder::new()
        .name("sim-tcp-conn".into())
        .spawn(move || {
            let mut reader = TcpReader {
                stream,
                line: MasterLine::exact(line),
            };
            if let Err(err) = serve(&mut reader, &pacer, &runtime) {
                tracing::debug!("sim: tcp connection: {err}");
            }
            pacer.close();
            let _ = pacer_thread.join();
        })?;
    Ok(())
}

struct TcpReader {
    stream: TcpStream,
    line: MasterLine,
}

impl LinkReader for TcpReader {
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<Option<usize>> {
        self.stream
            .set_read_timeout(Some(timeout.max(Duration::from_micros(100))))?;
        match self.stream.read(buf) {
            Ok(len) => Ok(Some(len)),
            Err(err)
                if matches!(
                    err.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) =>
            {
                Ok(None)
            }
            Err(err) => Err(err),
        }
    }

    fn master_line(&self) -> MasterLine {
        self.line
    }
}
