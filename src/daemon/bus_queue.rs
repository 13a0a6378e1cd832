//! The one way into a running port from outside its scheduler (MQTT RPC, the status page's
//! scan): a queue of single transactions that the port task serves between its own. One task
//! still owns the bus; Fast Modbus event polls keep their slots, because the port task never
//! serves two queued transactions in a row while its scheduler has something to send.
//!
//! A caller that needs a sequence (a scan: start, continue, continue, ...) sends one transaction
//! at a time and decides the next from the reply.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use thiserror::Error;
use tokio::sync::{mpsc, oneshot};

use crate::port::{Outcome, Transaction};
use crate::protocol::LineSettings;

/// Queued transactions a port holds at most; more are refused at once (the caller reports a
/// busy port rather than wait behind a pile of work).
pub const BUS_QUEUE_DEPTH: usize = 16;

/// One transaction asked of a running port.
pub struct QueuedTransaction {
    /// Port settings to send it at; `None` (or the port's own) keeps the port as it is. Other
    /// settings reopen the serial port at them for the transaction, and at the port's own
    /// before the scheduler's next one.
    pub line: Option<LineSettings>,
    pub transaction: Transaction,
    pub reply: oneshot::Sender<Result<Outcome, BusQueueError>>,
}

/// Why a queued transaction got no outcome.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum BusQueueError {
    #[error("the port has {BUS_QUEUE_DEPTH} requests queued already; try again shortly")]
    Full,
    #[error("the port task has stopped (shutdown or reload)")]
    Stopped,
    #[error("the port is not open: {0}")]
    PortClosed(String),
    #[error("the port cannot be set to {line}: {reason}")]
    Settings { line: String, reason: String },
}

/// The sending side, cloned by whoever needs the bus.
#[derive(Clone, Debug)]
pub struct BusQueue {
    sender: mpsc::Sender<QueuedTransaction>,
    control: PortControl,
}

/// Requests to the port's scheduler that are no bus transaction (RPC `device/SetPoll`: hold or
/// resume a device's polling). The port task takes them before its scheduler's next
/// transaction; checking costs one atomic load when there is none.
#[derive(Clone, Debug, Default)]
pub struct PortControl {
    pending: Arc<AtomicBool>,
    /// (device index on the port, suspended), in order.
    commands: Arc<Mutex<Vec<(usize, bool)>>>,
}

impl PortControl {
    /// Holds (`true`) or resumes (`false`) the polling of the port's `device`-th device.
    pub fn suspend(&self, device: usize, suspended: bool) {
        self.commands
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push((device, suspended));
        self.pending.store(true, Ordering::Release);
    }

    /// The commands sent since the last call, in order.
    pub fn take(&self) -> Vec<(usize, bool)> {
        if !self.pending.swap(false, Ordering::AcqRel) {
            return Vec::new();
        }
        std::mem::take(
            &mut *self
                .commands
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        )
    }
}

/// The receiving side, owned by the port task.
pub type BusQueueReceiver = mpsc::Receiver<QueuedTransaction>;

impl BusQueue {
    pub fn new() -> (Self, BusQueueReceiver) {
        let (sender, receiver) = mpsc::channel(BUS_QUEUE_DEPTH);
        let control = PortControl::default();
        (Self { sender, control }, receiver)
    }

    /// The port's scheduler commands (shared by every clone of this queue).
    pub fn control(&self) -> &PortControl {
        &self.control
    }

    /// Sends `transaction` (at `line`, or the port's own settings) between the port's own
    /// transactions and waits for its outcome. Dropping the future (a timeout) withdraws the
    /// transaction if it has not started.
    pub async fn transact(
        &self,
        line: Option<LineSettings>,
        transaction: Transaction,
    ) -> Result<Outcome, BusQueueError> {
        let (reply, outcome) = oneshot::channel();
        self.sender
            .try_send(QueuedTransaction {
                line,
                transaction,
                reply,
            })
            .map_err(|err| match err {
                mpsc::error::TrySendError::Full(_) => BusQueueError::Full,
                mpsc::error::TrySendError::Closed(_) => BusQueueError::Stopped,
            })?;
        outcome.await.unwrap_or(Err(BusQueueError::Stopped))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Request;
    use std::time::Duration;

    fn transaction() -> Transaction {
        Transaction {
            request: Request::scan_start(),
            request_time: Duration::ZERO,
            reply_timeout: Duration::from_millis(10),
            first_byte_timeout: None,
            late_window: Duration::ZERO,
            estimated: Duration::from_millis(10),
        }
    }

    #[test]
    fn control_commands_come_out_once_and_in_order() {
        let (queue, _receiver) = BusQueue::new();
        assert!(queue.control().take().is_empty());
        let other = queue.clone();
        other.control().suspend(2, true);
        queue.control().suspend(0, true);
        queue.control().suspend(2, false);
        assert_eq!(
            queue.control().take(),
            vec![(2, true), (0, true), (2, false)]
        );
        assert!(other.control().take().is_empty());
    }

    #[tokio::test]
    async fn a_stopped_port_and_a_full_queue_answer_at_once() {
        let (queue, receiver) = BusQueue::new();
        drop(receiver);
        assert_eq!(
            queue.transact(None, transaction()).await,
            Err(BusQueueError::Stopped)
        );

        let (queue, mut receiver) = BusQueue::new();
        let mut waiting = Vec::new();
        for _ in 0..BUS_QUEUE_DEPTH {
            let queue = queue.clone();
            waiting.push(tokio::spawn(async move {
                queue.transact(None, transaction()).await
            }));
        }
        // Let every spawned caller queue its transaction.
        while receiver.len() < BUS_QUEUE_DEPTH {
            tokio::task::yield_now().await;
        }
        assert_eq!(
            queue.transact(None, transaction()).await,
            Err(BusQueueError::Full)
        );
        let first = receiver.recv().await.unwrap();
        first.reply.send(Ok(Outcome::NoReply)).unwrap();
        drop(receiver);
        let mut outcomes = Vec::new();
        for caller in waiting {
            outcomes.push(caller.await.unwrap());
        }
        assert_eq!(outcomes.iter().filter(|o| o.is_ok()).count(), 1);
        assert!(outcomes.contains(&Err(BusQueueError::Stopped)));
    }
}
