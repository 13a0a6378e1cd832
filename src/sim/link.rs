//! The receive loop shared by the transports: read bytes with timestamps and the master's port
//! settings, cut them into requests, let the bus answer, hand the answer to the pacer.

use std::io;
use std::time::Duration;

use crate::protocol::hex;

use super::line::{MasterLine, RequestAssembler};
use super::pacing::Pacer;
use super::runtime::SimRuntime;

/// The master's side of a link, as the simulator reads it.
pub trait LinkReader {
    /// Waits up to `timeout` for bytes: `Ok(None)` on timeout, `Ok(Some(0))` when the peer closed.
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<Option<usize>>;
    /// The settings the master's bytes were sent with.
    fn master_line(&self) -> MasterLine;
}

/// How often the loop looks at the stop flag when the line is idle.
const IDLE_POLL: Duration = Duration::from_millis(50);

/// Serves requests until the peer closes, the runtime stops, or reading fails.
pub fn serve(reader: &mut dyn LinkReader, pacer: &Pacer, runtime: &SimRuntime) -> io::Result<()> {
    super::pacing::raise_to_realtime();
    let mut assembler = RequestAssembler::new();
    let mut buf = [0u8; 512];
    while !runtime.stopped() {
        let now = runtime.clock.now();
        let timeout = assembler.silence_deadline().map_or(IDLE_POLL, |deadline| {
            deadline.saturating_sub(now).min(IDLE_POLL)
        });
        let requests = match reader.read_timeout(&mut buf, timeout)? {
            Some(0) => return Ok(()),
            Some(len) => {
                let at = runtime.clock.now();
                let line = reader.master_line();
                let bytes = buf.get(..len).unwrap_or(&[]);
                tracing::debug!("sim: <- {} ({:?} at {:?})", hex(bytes), line, at);
                assembler.receive(bytes, at, line)
            }
            None => match assembler.silence_deadline() {
                Some(deadline) if runtime.clock.now() >= deadline => assembler.on_silence(),
                _ => Vec::new(),
            },
        };
        for request in requests {
            let transmission = runtime.with_bus(|bus, _| bus.handle(&request));
            if !transmission.is_empty() {
                tracing::debug!("sim: -> {}", hex(&transmission.bytes()));
                pacer.schedule(&transmission);
            }
        }
    }
    Ok(())
}
