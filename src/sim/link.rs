//! The receive loop shared by the transports: read bytes with timestamps and the master's port
//! settings, put them on the wire, let the bus answer the frames that end in silence, hand what
//! the devices put on the wire to the pacer (again whenever a collision changes it).

use std::io;
use std::time::Duration;

use crate::protocol::hex;

use super::line::{MasterLine, ReceivedRequest};
use super::pacing::Pacer;
use super::runtime::SimRuntime;
use super::transmission::Transmission;
use super::wire::Wire;

/// The master's side of a link, as the simulator reads it.
pub trait LinkReader {
    /// Waits up to `timeout` for bytes: `Ok(None)` on timeout, `Ok(Some(0))` when the peer closed.
    fn read_timeout(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<Option<usize>>;
    /// The settings the master's bytes were sent with.
    fn master_line(&self) -> MasterLine;
}

/// How often the loop looks at the stop flag when the line is idle.
const IDLE_POLL: Duration = Duration::from_millis(50);

/// Serves requests until the peer closes, the runtime stops, the links are cut (their
/// generation is no longer `generation`, the one the link was opened under), or reading fails.
pub fn serve(
    reader: &mut dyn LinkReader,
    pacer: &Pacer,
    runtime: &SimRuntime,
    generation: u64,
) -> io::Result<()> {
    super::pacing::raise_to_realtime();
    let mut wire = Wire::new();
    let mut buf = [0u8; 512];
    let respond = |request: &ReceivedRequest| {
        let transmission = runtime.with_bus(|bus, _| bus.handle(request));
        if !transmission.is_empty() {
            tracing::debug!("sim: -> {}", hex(&transmission.bytes()));
        }
        transmission
    };
    while !runtime.stopped() && runtime.link_generation() == generation {
        let now = runtime.clock.now();
        let timeout = wire
            .silence_deadline()
            .into_iter()
            .chain(other_master_at(&wire, runtime, reader.master_line()))
            .map(|deadline| deadline.saturating_sub(now))
            .fold(IDLE_POLL, Duration::min);
        let mut changed = match reader.read_timeout(&mut buf, timeout)? {
            Some(0) => return Ok(()),
            Some(len) => {
                let at = runtime.clock.now();
                let line = reader.master_line();
                let bytes = buf.get(..len).unwrap_or(&[]);
                tracing::debug!("sim: <- {} ({:?} at {:?})", hex(bytes), line, at);
                let write = wire.master_writes(bytes, at, line, respond);
                if write.collided {
                    tracing::debug!("sim: request collided with a reply on the wire");
                }
                write.collided || write.answered
            }
            None => wire.on_silence(runtime.clock.now(), respond),
        };
        if other_master_at(&wire, runtime, reader.master_line())
            .is_some_and(|at| at <= runtime.clock.now())
        {
            changed |= other_master_turn(&mut wire, runtime, reader.master_line(), respond);
        }
        if changed {
            pacer.replace(&wire.received());
        }
    }
    Ok(())
}

/// When the second master, if any, sends next: when it is due, or once the wire has been
/// quiet for a frame gap if it listens before it talks.
fn other_master_at(wire: &Wire, runtime: &SimRuntime, line: MasterLine) -> Option<Duration> {
    let (due, listens) = runtime.other_master_due()?;
    Some(if listens {
        due.max(wire.quiet_at(line))
    } else {
        due
    })
}

/// The second master's request, if it is due (the `other_master` control command): on the
/// wire now. True if it changed what the master receives.
fn other_master_turn(
    wire: &mut Wire,
    runtime: &SimRuntime,
    line: MasterLine,
    respond: impl FnMut(&ReceivedRequest) -> Transmission,
) -> bool {
    let Some((frame, at)) = runtime.with_bus(|bus, now| Some((bus.other_master_turn(now)?, now)))
    else {
        return false;
    };
    tracing::debug!("sim: another master sends {}", hex(&frame));
    if wire.other_master_sends(&frame, at, line, respond) {
        tracing::debug!("sim: the other master's request collided");
    }
    true
}
