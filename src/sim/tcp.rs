//! TCP listeners: RTU over TCP (connections carry raw RTU frames, paced on the wire like the pty)
//! and Modbus TCP (MBAP frames through a gateway, [`super::mbap`]). The line settings are the
//! listener's (a TCP gateway's serial side); devices with other settings never hear it.

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use crate::protocol::{hex, LineSettings};

use super::line::MasterLine;
use super::link::{serve, LinkReader};
use super::mbap;
use super::pacing::{Pacer, Receiver};
use super::runtime::SimRuntime;

/// What a connection carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TcpMode {
    /// Raw RTU frames, bytes paced as on the wire.
    RtuOverTcp,
    /// MBAP frames through a Modbus TCP gateway.
    ModbusTcp,
}

/// Binds `address` and serves every connection on its own threads until the runtime stops.
pub fn spawn_listener(
    address: &str,
    line: LineSettings,
    runtime: Arc<SimRuntime>,
) -> io::Result<(SocketAddr, JoinHandle<()>)> {
    spawn(address, line, runtime, TcpMode::RtuOverTcp)
}

/// Binds `address` and serves every connection in `mode` until the runtime stops.
pub fn spawn(
    address: &str,
    line: LineSettings,
    runtime: Arc<SimRuntime>,
    mode: TcpMode,
) -> io::Result<(SocketAddr, JoinHandle<()>)> {
    let listener = TcpListener::bind(address)?;
    listener.set_nonblocking(true)?;
    let local = listener.local_addr()?;
    let handle = std::thread::Builder::new()
        .name("sim-tcp".into())
        .spawn(move || {
            while !runtime.stopped() {
                match listener.accept() {
                    Ok((stream, peer)) if !runtime.link_up() => {
                        // The gateway is away: the connection ends at once.
                        tracing::info!("sim: tcp: {peer} refused (link down)");
                        drop(stream);
                    }
                    Ok((stream, peer)) => {
                        tracing::info!("sim: tcp: {peer} connected");
                        let runtime = Arc::clone(&runtime);
                        let spawned = match mode {
                            TcpMode::RtuOverTcp => spawn_connection(stream, line, runtime),
                            TcpMode::ModbusTcp => spawn_gateway_connection(stream, line, runtime),
                        };
                        if let Err(err) = spawned {
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
    let generation = runtime.link_generation();
    let mut writer = stream.try_clone()?;
    let (pacer, pacer_thread) = Pacer::spawn(
        "tcp",
        runtime.clock,
        Receiver::default(),
        Box::new(move |bytes| writer.write_all(bytes)),
    )?;
    std::thread::Builder::new()
        .name("sim-tcp-conn".into())
        .spawn(move || {
            let mut reader = TcpReader {
                stream,
                line: MasterLine::exact(line),
            };
            if let Err(err) = serve(&mut reader, &pacer, &runtime, generation) {
                tracing::debug!("sim: tcp connection: {err}");
            }
            pacer.close();
            let _ = pacer_thread.join();
        })?;
    Ok(())
}

/// A Modbus TCP gateway's connection: one request at a time, as gateways serialise their line.
fn spawn_gateway_connection(
    stream: TcpStream,
    line: LineSettings,
    runtime: Arc<SimRuntime>,
) -> io::Result<()> {
    stream.set_nonblocking(false)?;
    stream.set_nodelay(true)?;
    std::thread::Builder::new()
        .name("sim-mbap-conn".into())
        .spawn(move || {
            if let Err(err) = serve_gateway(stream, line, &runtime) {
                tracing::debug!("sim: modbus tcp connection: {err}");
            }
        })?;
    Ok(())
}

fn serve_gateway(
    mut stream: TcpStream,
    line: LineSettings,
    runtime: &SimRuntime,
) -> io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_millis(50)))?;
    let generation = runtime.link_generation();
    let master = MasterLine::exact(line);
    let mut buffer = Vec::new();
    let mut chunk = [0u8; 512];
    while !runtime.stopped() && runtime.link_generation() == generation {
        let request = match mbap::take_request(&mut buffer) {
            Ok(Some(request)) => request,
            Ok(None) => {
                match stream.read(&mut chunk) {
                    Ok(0) => return Ok(()),
                    Ok(len) => buffer.extend_from_slice(chunk.get(..len).unwrap_or(&[])),
                    Err(err)
                        if matches!(
                            err.kind(),
                            io::ErrorKind::WouldBlock
                                | io::ErrorKind::TimedOut
                                | io::ErrorKind::Interrupted
                        ) => {}
                    Err(err) => return Err(err),
                }
                continue;
            }
            Err(err) => {
                tracing::warn!("sim: modbus tcp: {err}; closing the connection");
                return Ok(());
            }
        };
        tracing::debug!("sim: mbap <- {}", hex(&request.rtu_frame));
        let (sent_at, transmission) =
            runtime.with_bus(|bus, now| (now, bus.exchange(&request.rtu_frame, master, now)));
        // The gateway waits until the reply has crossed its serial line, or gives up.
        let give_up = sent_at + line.wire_time(request.rtu_frame.len()) + mbap::GATEWAY_TIMEOUT;
        let (heard, ready_at) = match transmission.end() {
            Some(end) if end <= give_up => (transmission.bytes(), end),
            _ => (Vec::new(), give_up),
        };
        std::thread::sleep(ready_at.saturating_sub(runtime.clock.now()));
        if let Some(reply) = mbap::reply(&request, &heard) {
            tracing::debug!("sim: mbap -> {}", hex(&reply));
            stream.write_all(&reply)?;
        }
    }
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
