//! The Fast Modbus event packets a port received, as they came (address, flag, events), for
//! `rtu2mqtt events` through the running service (RPC `port/EventLog`). Packets are kept only
//! while someone watches: a port nobody watches pays one uncontended lock per packet, and no
//! memory.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use tokio::sync::Notify;

use crate::protocol::fast::{Event, EventPacket};

/// Packets kept between two reads of a watcher; older ones are counted as lost to it.
pub const KEPT_PACKETS: usize = 256;

/// How long a read keeps the log recording after it returns: a watcher reads again long before.
const WATCH_LEASE: Duration = Duration::from_secs(10);

/// One packet as it came from the bus.
#[derive(Debug, Clone, PartialEq)]
pub struct LoggedPacket {
    /// Numbers every packet the port recorded, from 0; a read asks for those after one.
    pub seq: u64,
    /// When it was received (wall clock, for the watcher's display).
    pub unix_ms: u64,
    pub address: u8,
    pub flag: u8,
    pub events: Vec<Event>,
}

/// What a read returns: the packets from the one asked for on, and where to go on from.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LogPage {
    pub packets: Vec<LoggedPacket>,
    /// The `from` of the next read.
    pub next: u64,
    /// Packets from the one asked for on that are no longer kept (or came while nobody
    /// watched).
    pub lost: u64,
    /// Which log this is: a port restarted by a reload starts another, numbered from 0.
    pub log: u64,
    /// The read named another log: it read this one from its oldest packet, and what came
    /// between the two is unknown.
    pub restarted: bool,
}

#[derive(Debug, Default)]
struct LogState {
    packets: VecDeque<LoggedPacket>,
    /// The seq the next recorded packet gets.
    next: u64,
    /// Recording while a watcher has read within the lease.
    watched_until: Option<Instant>,
}

/// One port's log; shared by its port task (which records) and the RPC server (which reads).
#[derive(Debug)]
pub struct EventLog {
    id: u64,
    state: Mutex<LogState>,
    recorded: Notify,
}

impl Default for EventLog {
    fn default() -> Self {
        // Logs of the process numbered apart, so that a reader can tell a restarted port's.
        static LOGS: AtomicU64 = AtomicU64::new(1);
        Self {
            id: LOGS.fetch_add(1, Ordering::Relaxed),
            state: Mutex::default(),
            recorded: Notify::new(),
        }
    }
}

impl EventLog {
    fn state(&self) -> std::sync::MutexGuard<'_, LogState> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Records a packet from `address`, if someone watches at `now`.
    pub fn record(&self, now: Instant, address: u8, packet: &EventPacket) {
        let mut state = self.state();
        // Numbered even when not kept, so that a watcher back after its lease ran out is told
        // how many it missed.
        let seq = state.next;
        state.next += 1;
        if state.watched_until.is_none_or(|until| now > until) {
            state.watched_until = None;
            state.packets = VecDeque::new();
            return;
        }
        if state.packets.len() == KEPT_PACKETS {
            state.packets.pop_front();
        }
        state.packets.push_back(LoggedPacket {
            seq,
            unix_ms: unix_ms(SystemTime::now()),
            address,
            flag: packet.flag,
            events: packet.events.clone(),
        });
        drop(state);
        self.recorded.notify_waiters();
    }

    /// The packets from seq `from` of log `log` on (`None`: only those to come; another log:
    /// this one's oldest kept), waiting up to `wait` for the first; starts or extends
    /// recording.
    pub async fn read(&self, from: Option<u64>, log: Option<u64>, wait: Duration) -> LogPage {
        let deadline = tokio::time::Instant::now() + wait;
        let (mut from, mut log) = (from, log);
        let mut restarted = false;
        loop {
            let recorded = self.recorded.notified();
            tokio::pin!(recorded);
            // Registered before looking, so that a packet recorded in between wakes it.
            recorded.as_mut().enable();
            let (mut page, asked) = self.page(Instant::now(), from, log, wait);
            restarted |= page.restarted;
            page.restarted = restarted;
            if !page.packets.is_empty() {
                return page;
            }
            // Later looks ask for what the first one settled on ("only those to come" means
            // those after the first look).
            (from, log) = (Some(asked), Some(self.id));
            if tokio::time::timeout_at(deadline, recorded).await.is_err() {
                let (mut page, _) = self.page(Instant::now(), from, log, wait);
                page.restarted = restarted;
                return page;
            }
        }
    }

    /// What `read` returns at `now` without waiting, and the seq it read from; renews the
    /// lease past `wait`.
    fn page(
        &self,
        now: Instant,
        from: Option<u64>,
        log: Option<u64>,
        wait: Duration,
    ) -> (LogPage, u64) {
        let mut state = self.state();
        state.watched_until = Some(now + wait + WATCH_LEASE);
        let oldest = state.packets.front().map_or(state.next, |p| p.seq);
        let restarted = log.is_some_and(|log| log != self.id);
        let from = match from {
            _ if restarted => oldest,
            Some(from) if from <= state.next => from,
            // Beyond this log's end: a log of before a restart, its id not given.
            Some(_) => oldest,
            None => state.next,
        };
        let page = LogPage {
            packets: state
                .packets
                .iter()
                .filter(|p| p.seq >= from)
                .cloned()
                .collect(),
            next: state.next,
            lost: oldest.saturating_sub(from),
            log: self.id,
            restarted,
        };
        (page, from)
    }
}

fn unix_ms(time: SystemTime) -> u64 {
    time.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::fast::EventSource;
    use crate::protocol::RegisterType;
    use std::sync::Arc;

    fn packet(flag: u8, register: u16, value: u8) -> EventPacket {
        EventPacket {
            flag,
            event_count: 1,
            events: vec![Event {
                source: EventSource::Register(RegisterType::DiscreteInput),
                id: register,
                payload: vec![value],
            }],
        }
    }

    fn registers(page: &LogPage) -> Vec<u16> {
        page.packets.iter().map(|p| p.events[0].id).collect()
    }

    #[tokio::test]
    async fn packets_are_kept_only_while_someone_watches() {
        let log = EventLog::default();
        log.record(Instant::now(), 20, &packet(0, 1, 1));
        // The first read starts the recording: nothing from before it (numbered all the same),
        // nothing to come yet.
        let page = log.read(None, None, Duration::ZERO).await;
        assert_eq!((page.packets.len(), page.next, page.lost), (0, 1, 0));
        log.record(Instant::now(), 20, &packet(1, 2, 1));
        log.record(Instant::now(), 21, &packet(0, 3, 0));
        let page = log.read(Some(page.next), None, Duration::ZERO).await;
        assert_eq!(registers(&page), [2, 3]);
        assert_eq!(
            page.packets
                .iter()
                .map(|p| (p.seq, p.address, p.flag))
                .collect::<Vec<_>>(),
            [(1, 20, 1), (2, 21, 0)]
        );
        assert_eq!((page.next, page.lost), (3, 0));
        // Read again from where it ended: nothing new.
        let again = log.read(Some(page.next), None, Duration::ZERO).await;
        assert_eq!((again.packets.len(), again.next), (0, 3));
        // Nobody read for longer than the lease: the packets are not kept (those kept are
        // dropped), but counted, so the watcher back later is told how many it missed.
        let later = Instant::now() + WATCH_LEASE + Duration::from_secs(1);
        log.record(later, 20, &packet(1, 4, 1));
        log.record(Instant::now(), 20, &packet(0, 5, 1));
        assert!(log.state().packets.is_empty());
        let back = log.read(Some(again.next), None, Duration::ZERO).await;
        assert_eq!((back.packets.len(), back.next, back.lost), (0, 5, 2));
    }

    #[tokio::test]
    async fn a_watcher_too_slow_is_told_how_many_packets_it_missed() {
        let log = EventLog::default();
        let start = log.read(None, None, Duration::ZERO).await;
        let extra = 44;
        for i in 0..KEPT_PACKETS + extra {
            log.record(Instant::now(), 20, &packet(0, i as u16, 1));
        }
        let page = log.read(Some(start.next), None, Duration::ZERO).await;
        assert_eq!(page.packets.len(), KEPT_PACKETS);
        assert_eq!(page.packets[0].events[0].id, extra as u16);
        assert_eq!(page.lost, extra as u64);
        assert_eq!(page.next, (KEPT_PACKETS + extra) as u64);
    }

    #[tokio::test]
    async fn a_read_of_another_log_reads_what_a_restarted_port_kept() {
        let before = EventLog::default();
        let log = EventLog::default();
        assert_ne!(before.id, log.id);
        log.read(None, None, Duration::ZERO).await;
        for register in [7, 8] {
            log.record(Instant::now(), 20, &packet(0, register, 1));
        }
        // A watcher that was at 1 of the port's log before a restart: the new log's 0 is not
        // skipped, and it is told the log changed.
        let page = log.read(Some(1), Some(before.id), Duration::ZERO).await;
        assert_eq!(registers(&page), [7, 8]);
        assert_eq!(
            (page.next, page.lost, page.log, page.restarted),
            (2, 0, log.id, true)
        );
        // Without the log's id, a `from` beyond the log's end reads from its oldest too.
        let page = log.read(Some(500), None, Duration::ZERO).await;
        assert_eq!(registers(&page), [7, 8]);
        // The same log: no restart.
        let page = log.read(Some(1), Some(log.id), Duration::ZERO).await;
        assert_eq!((registers(&page), page.restarted), (vec![8], false));
    }

    #[tokio::test]
    async fn a_read_waits_for_the_next_packet() {
        for from_the_start in [false, true] {
            a_read_waits_for_the_next_packet_from(from_the_start).await;
        }
    }

    /// `from_the_start`: the read asks for "only those to come" (no `from`) and waits.
    async fn a_read_waits_for_the_next_packet_from(from_the_start: bool) {
        let log = Arc::new(EventLog::default());
        let start = log.read(None, None, Duration::ZERO).await;
        let from = (!from_the_start).then_some(start.next);
        let reader = tokio::spawn({
            let log = Arc::clone(&log);
            async move { log.read(from, None, Duration::from_secs(30)).await }
        });
        // Recorded until the reader has it: it may start waiting before or after a record.
        for _ in 0..1000 {
            log.record(Instant::now(), 20, &packet(0, 9, 1));
            tokio::task::yield_now().await;
            if reader.is_finished() {
                break;
            }
        }
        assert!(reader.is_finished(), "the waiting read never got a packet");
        let page = reader.await.unwrap();
        assert_eq!(page.packets[0].events[0].id, 9);
        // With nothing to come, a read ends after its wait, empty.
        let empty = log
            .read(Some(page.next), None, Duration::from_millis(1))
            .await;
        assert_eq!((empty.packets.len() as u64, empty.next), (0, page.next));
    }
}
