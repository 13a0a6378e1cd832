//! The Fast Modbus event packets a port received, as they came (address, flag, events), for
//! `rtu2mqtt events` through the running service (RPC `port/EventLog`). Packets are kept only
//! while someone watches: a port nobody watches pays one uncontended lock per packet, and no
//! memory.

use std::collections::VecDeque;
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
    /// Packets from the one asked for on that are no longer kept.
    pub lost: u64,
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
#[derive(Debug, Default)]
pub struct EventLog {
    state: Mutex<LogState>,
    recorded: Notify,
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
        if state.watched_until.is_none_or(|until| now > until) {
            state.watched_until = None;
            return;
        }
        let seq = state.next;
        state.next += 1;
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

    /// The packets from seq `from` on (`None`: only those to come), waiting up to `wait` for
    /// the first; starts or extends recording. A `from` the log never reached (the port was
    /// restarted since, and numbers from 0 again) reads from the oldest packet kept.
    pub async fn read(&self, from: Option<u64>, wait: Duration) -> LogPage {
        let deadline = tokio::time::Instant::now() + wait;
        let mut from = from;
        loop {
            let recorded = self.recorded.notified();
            tokio::pin!(recorded);
            // Registered before looking, so that a packet recorded in between wakes it.
            recorded.as_mut().enable();
            let page = self.page(Instant::now(), from, wait);
            if !page.packets.is_empty() {
                return page;
            }
            // "Only those to come" means those after the first look, on every later look too.
            from = Some(from.unwrap_or(page.next));
            if tokio::time::timeout_at(deadline, recorded).await.is_err() {
                return self.page(Instant::now(), from, wait);
            }
        }
    }

    /// What `read` returns at `now` without waiting; renews the lease past `wait`.
    fn page(&self, now: Instant, from: Option<u64>, wait: Duration) -> LogPage {
        let mut state = self.state();
        state.watched_until = Some(now + wait + WATCH_LEASE);
        let oldest = state.packets.front().map_or(state.next, |p| p.seq);
        let from = match from {
            Some(from) if from <= state.next => from,
            Some(_) => oldest,
            None => state.next,
        };
        LogPage {
            packets: state
                .packets
                .iter()
                .filter(|p| p.seq >= from)
                .cloned()
                .collect(),
            next: state.next,
            lost: oldest.saturating_sub(from),
        }
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
        // The first read starts the recording: nothing from before it, nothing to come yet.
        let page = log.read(None, Duration::ZERO).await;
        assert_eq!((page.packets.len(), page.next, page.lost), (0, 0, 0));
        log.record(Instant::now(), 20, &packet(1, 2, 1));
        log.record(Instant::now(), 21, &packet(0, 3, 0));
        let page = log.read(Some(page.next), Duration::ZERO).await;
        assert_eq!(registers(&page), [2, 3]);
        assert_eq!(
            page.packets
                .iter()
                .map(|p| (p.seq, p.address, p.flag))
                .collect::<Vec<_>>(),
            [(0, 20, 1), (1, 21, 0)]
        );
        assert_eq!((page.next, page.lost), (2, 0));
        // Read again from where it ended: nothing new.
        let again = log.read(Some(page.next), Duration::ZERO).await;
        assert_eq!((again.packets.len(), again.next), (0, 2));
        // Nobody read for longer than the lease: the next packet is not kept, nor any after.
        let later = Instant::now() + WATCH_LEASE + Duration::from_secs(1);
        log.record(later, 20, &packet(1, 4, 1));
        log.record(Instant::now(), 20, &packet(0, 5, 1));
        assert_eq!(log.read(Some(2), Duration::ZERO).await.packets, []);
    }

    #[tokio::test]
    async fn a_watcher_too_slow_is_told_how_many_packets_it_missed() {
        let log = EventLog::default();
        let start = log.read(None, Duration::ZERO).await;
        let extra = 44;
        for i in 0..KEPT_PACKETS + extra {
            log.record(Instant::now(), 20, &packet(0, i as u16, 1));
        }
        let page = log.read(Some(start.next), Duration::ZERO).await;
        assert_eq!(page.packets.len(), KEPT_PACKETS);
        assert_eq!(page.packets[0].events[0].id, extra as u16);
        assert_eq!(page.lost, extra as u64);
        assert_eq!(page.next, (KEPT_PACKETS + extra) as u64);
    }

    #[tokio::test]
    async fn a_from_beyond_the_log_reads_what_a_restarted_port_kept() {
        let log = EventLog::default();
        log.read(None, Duration::ZERO).await;
        log.record(Instant::now(), 20, &packet(0, 7, 1));
        // A watcher that was at 500 of the port's log before a restart.
        let page = log.read(Some(500), Duration::ZERO).await;
        assert_eq!(registers(&page), [7]);
        assert_eq!((page.next, page.lost), (1, 0));
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
        let start = log.read(None, Duration::ZERO).await;
        let from = (!from_the_start).then_some(start.next);
        let reader = tokio::spawn({
            let log = Arc::clone(&log);
            async move { log.read(from, Duration::from_secs(30)).await }
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
        let empty = log.read(Some(page.next), Duration::from_millis(1)).await;
        assert_eq!((empty.packets.len() as u64, empty.next), (0, page.next));
    }
}
