//! The one way into a running port from outside its scheduler (MQTT RPC, the status page's
//! scan): a queue of single transactions that the port task serves between its own. One task
//! still owns the bus; Fast Modbus event polls keep their slots, because the port task never
//! serves two queued transactions in a row while its scheduler has something to send.
//!
//! A caller that needs a sequence (a scan: start, continue, continue, ...) sends one transaction
//! at a time and decides the next from the reply. A scan holds the port's scan lease
//! ([`BusQueue::scan_lease`]) from its start to its last read by serial number, so two scans
//! never interleave (a scan start makes every device un-scanned again: the other scan would
//! lose devices); the scheduler's own transactions still go between a scan's. The same queue
//! carries the operator's holds on a device's polling (`device/SetPoll`), which take no bus
//! time.

use std::sync::Arc;

use thiserror::Error;
use tokio::sync::{mpsc, oneshot, Mutex, OwnedMutexGuard};

use crate::port::{Transaction, TransactionOutcome};
use crate::protocol::LineSettings;
use crate::transport::raw::RawRequest;

/// Queued transactions a port holds at most; more are refused at once (the caller reports a
/// busy port rather than wait behind a pile of work).
pub const BUS_QUEUE_DEPTH: usize = 16;

/// What a running port is asked to do.
pub enum QueuedJob {
    Transaction(QueuedTransaction),
    /// Bytes out and back as they are (`port/Load` without a protocol).
    Raw(QueuedRaw),
    /// Hold the polling of the port's `device`-th device for `hold_for`, counted from when the
    /// port task takes the job (`None`: resume it).
    HoldPolling {
        device: usize,
        hold_for: Option<std::time::Duration>,
        done: oneshot::Sender<()>,
    },
}

/// One transaction asked of a running port.
pub struct QueuedTransaction {
    /// Port settings to send it at; `None` (or the port's own) keeps the port as it is. Other
    /// settings reopen the serial port at them for the transaction, and at the port's own
    /// before the scheduler's next one.
    pub line: Option<LineSettings>,
    pub transaction: Transaction,
    pub reply: oneshot::Sender<Result<TransactionOutcome, BusQueueError>>,
}

/// One raw transfer asked of a running port: no frame is parsed, the answer is what came.
pub struct QueuedRaw {
    /// As for [`QueuedTransaction::line`].
    pub line: Option<LineSettings>,
    pub request: RawRequest,
    pub reply: oneshot::Sender<Result<Vec<u8>, BusQueueError>>,
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
    sender: mpsc::Sender<QueuedJob>,
    /// Held by the scan running on this port (see [`BusQueue::scan_lease`]).
    scans: Arc<Mutex<()>>,
    /// Per configured device of the port (by its index): the serial number the port's identity
    /// read got last, for the RPC to tell which of several devices at one address is the one
    /// the service polls.
    identified: Arc<std::sync::Mutex<Vec<Option<u32>>>>,
}

/// The right to run a Fast Modbus scan on a port; the next scan starts when it is dropped.
pub type ScanLease = OwnedMutexGuard<()>;

/// The receiving side, owned by the port task.
pub type BusQueueReceiver = mpsc::Receiver<QueuedJob>;

impl BusQueue {
    pub fn new() -> (Self, BusQueueReceiver) {
        let (sender, receiver) = mpsc::channel(BUS_QUEUE_DEPTH);
        let scans = Arc::new(Mutex::new(()));
        let identified = Arc::default();
        (
            Self {
                sender,
                scans,
                identified,
            },
            receiver,
        )
    }

    /// The port task read the serial number of its `device`-th device.
    pub fn note_serial(&self, device: usize, serial: u32) {
        let mut identified = self
            .identified
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if identified.len() <= device {
            identified.resize(device + 1, None);
        }
        identified[device] = Some(serial);
    }

    /// The serial number last read from the port's `device`-th device (None: not read yet, or
    /// the device has none).
    pub fn identified_serial(&self, device: usize) -> Option<u32> {
        self.identified
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(device)
            .copied()
            .flatten()
    }

    /// Waits until no other scan runs on this port (scans are served in the order they
    /// asked), then holds the port for a scan: a scan chain (start, continue …, and the reads
    /// by serial number of what it found) runs whole, as wb-mqtt-serial runs a scan as one
    /// task. Only scans wait for each other; the scheduler and other queued requests go on
    /// between the scan's transactions. Dropping the future (a total_timeout) gives up the
    /// turn.
    pub async fn scan_lease(&self) -> ScanLease {
        Arc::clone(&self.scans).lock_owned().await
    }

    /// Sends `transaction` (at `line`, or the port's own settings) between the port's own
    /// transactions and waits for its outcome. Dropping the future (a timeout) withdraws the
    /// transaction if it has not started.
    pub async fn transact(
        &self,
        line: Option<LineSettings>,
        transaction: Transaction,
    ) -> Result<TransactionOutcome, BusQueueError> {
        let (reply, outcome) = oneshot::channel();
        self.send(QueuedJob::Transaction(QueuedTransaction {
            line,
            transaction,
            reply,
        }))?;
        outcome.await.unwrap_or(Err(BusQueueError::Stopped))
    }

    /// Sends `request`'s bytes as they are (at `line`, or the port's own settings) between the
    /// port's own transactions and returns what came back.
    pub async fn transfer_raw(
        &self,
        line: Option<LineSettings>,
        request: RawRequest,
    ) -> Result<Vec<u8>, BusQueueError> {
        let (reply, answer) = oneshot::channel();
        self.send(QueuedJob::Raw(QueuedRaw {
            line,
            request,
            reply,
        }))?;
        answer.await.unwrap_or(Err(BusQueueError::Stopped))
    }

    /// Holds the polling of the port's `device`-th device for `hold_for` from now (again from
    /// now if it was held already), or resumes it (`None`); returns once the port task has
    /// done it.
    pub async fn hold_polling(
        &self,
        device: usize,
        hold_for: Option<std::time::Duration>,
    ) -> Result<(), BusQueueError> {
        let (done, applied) = oneshot::channel();
        self.send(QueuedJob::HoldPolling {
            device,
            hold_for,
            done,
        })?;
        applied.await.map_err(|_| BusQueueError::Stopped)
    }

    fn send(&self, job: QueuedJob) -> Result<(), BusQueueError> {
        self.sender.try_send(job).map_err(|err| match err {
            mpsc::error::TrySendError::Full(_) => BusQueueError::Full,
            mpsc::error::TrySendError::Closed(_) => BusQueueError::Stopped,
        })
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
    fn identified_serials_are_kept_per_device_for_every_clone() {
        let (queue, _receiver) = BusQueue::new();
        let rpc_side = queue.clone();
        assert_eq!(rpc_side.identified_serial(2), None);
        queue.note_serial(2, 0xFE00_0010);
        assert_eq!(rpc_side.identified_serial(2), Some(0xFE00_0010));
        assert_eq!(rpc_side.identified_serial(0), None);
        queue.note_serial(2, 0xFE00_0011);
        assert_eq!(rpc_side.identified_serial(2), Some(0xFE00_0011));
    }

    #[tokio::test]
    async fn a_second_scan_waits_for_the_first_to_end() {
        let (queue, _receiver) = BusQueue::new();
        let first = queue.scan_lease().await;
        let other = queue.clone();
        let second = tokio::spawn(async move { other.scan_lease().await });
        // Not granted while the first scan holds the port (one thread: the spawned task has
        // run up to its wait) ...
        for _ in 0..10 {
            tokio::task::yield_now().await;
        }
        assert!(!second.is_finished());
        drop(first);
        // ... and granted once it ends.
        drop(second.await.unwrap());
        // Other ports scan on their own.
        let (elsewhere, _receiver) = BusQueue::new();
        let _held = queue.scan_lease().await;
        drop(elsewhere.scan_lease().await);
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
        let Some(QueuedJob::Transaction(first)) = receiver.recv().await else {
            panic!("a transaction was queued");
        };
        first.reply.send(Ok(TransactionOutcome::NoReply)).unwrap();
        drop(receiver);
        let mut outcomes = Vec::new();
        for caller in waiting {
            outcomes.push(caller.await.unwrap());
        }
        assert_eq!(outcomes.iter().filter(|o| o.is_ok()).count(), 1);
        assert!(outcomes.contains(&Err(BusQueueError::Stopped)));
    }
}
