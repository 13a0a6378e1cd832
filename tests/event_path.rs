//! The Fast Modbus event path against what the protocol (or wb-mqtt-serial, the reference
//! master) requires, through the public scheduler and parser: each test failed on the code
//! before its fix (docs/reliability.md, "Defects found by review": events lost or delayed).

use std::time::Duration;

use rtu2mqtt::port::{
    DevicePlan, EventMode, HealthPolicy, MergeLimits, NextStep, PlannedRead, PortEvent,
    PortScheduler, PortSettings, RegisterSpan, Transaction, TransactionOutcome,
};
use rtu2mqtt::protocol::{
    crc16, parse_hex, Event, EventPacket, EventPoll, EventPriority, EventSource, FastReply,
    FastRequest, LineSettings, Parity, ParseError, ParseStatus, RegisterType, Reply, ReplyParser,
    Request, RequestBody, RequestPdu, ResponsePdu,
};

fn ms(ms: u64) -> Duration {
    Duration::from_millis(ms)
}

fn with_crc(hex: &str) -> Vec<u8> {
    let mut frame = parse_hex(hex).unwrap();
    let crc = crc16(&frame);
    frame.extend(crc.to_le_bytes());
    frame
}

fn sporadic(register_type: RegisterType, start: u16, count: u16) -> PlannedRead {
    PlannedRead {
        span: RegisterSpan::new(register_type, start, count),
        period: None,
        rate_limit: None,
        events: EventMode::Sporadic,
        min_firmware: None,
    }
}

fn device(address: u8, reads: Vec<PlannedRead>) -> DevicePlan {
    DevicePlan {
        name: format!("dev{address}"),
        address,
        response_timeout: Duration::from_millis(500),
        merge: MergeLimits {
            max_read_registers: 0,
            max_register_hole: 0,
            max_bit_hole: 0,
            min_read_registers: 1,
        },
        health: HealthPolicy::default(),
        reads,
        setup: Vec::new(),
        continuous_read: false,
        write_retry_time: Duration::from_secs(600),
    }
}

/// A device that answers everything as asked: reads give zeros, 0x18 enables every register,
/// event polls find nothing.
fn healthy(request: &Request) -> TransactionOutcome {
    let address = request.address;
    match &request.body {
        RequestBody::Fast(FastRequest::PollEvents(_)) => {
            TransactionOutcome::Reply(Reply::fast(0xFD, FastReply::NoEvents))
        }
        RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) => {
            let masks = ranges
                .iter()
                .flat_map(|r| vec![0xFFu8; r.mask_len()])
                .collect();
            TransactionOutcome::Reply(Reply::fast(address, FastReply::EventsConfigured { masks }))
        }
        RequestBody::Fast(_) => TransactionOutcome::NoReply,
        RequestBody::Classic(pdu) => TransactionOutcome::Reply(Reply::classic(
            address,
            match pdu {
                RequestPdu::ReadCoils { count, .. } => ResponsePdu::ReadCoils {
                    packed: vec![0; usize::from(*count).div_ceil(8)],
                },
                RequestPdu::ReadDiscreteInputs { count, .. } => ResponsePdu::ReadDiscreteInputs {
                    packed: vec![0; usize::from(*count).div_ceil(8)],
                },
                RequestPdu::ReadHoldingRegisters { count, .. } => {
                    ResponsePdu::ReadHoldingRegisters {
                        values: vec![0; usize::from(*count)],
                    }
                }
                RequestPdu::ReadInputRegisters { count, .. } => ResponsePdu::ReadInputRegisters {
                    values: vec![0; usize::from(*count)],
                },
                other => panic!("unexpected request {other:?}"),
            },
        )),
    }
}

/// Drives the scheduler on a fake clock: each transaction takes its estimated time (at least
/// 1 ms). Returns every transaction sent (with its time) and every port event.
fn run(
    scheduler: &mut PortScheduler,
    end: Duration,
    mut respond: impl FnMut(&Request) -> TransactionOutcome,
) -> (Vec<(Duration, Transaction)>, Vec<PortEvent>) {
    let mut now = Duration::ZERO;
    let mut sent = Vec::new();
    let mut events = Vec::new();
    while now < end {
        match scheduler.next(now) {
            NextStep::Transmit(transaction) => {
                sent.push((now, transaction.clone()));
                let outcome = respond(&transaction.request);
                now += transaction.estimated.max(ms(1));
                events.extend(scheduler.complete(now, outcome));
            }
            NextStep::Wait { until } => now = until.max(now + Duration::from_micros(1)),
        }
    }
    (sent, events)
}

fn polls(sent: &[(Duration, Transaction)]) -> Vec<EventPoll> {
    sent.iter()
        .filter_map(|(_, t)| match &t.request.body {
            RequestBody::Fast(FastRequest::PollEvents(poll)) => Some(*poll),
            _ => None,
        })
        .collect()
}

fn event_setups(sent: &[(Duration, Transaction)]) -> Vec<Vec<rtu2mqtt::protocol::EventRange>> {
    sent.iter()
        .filter_map(|(_, t)| match &t.request.body {
            RequestBody::Fast(FastRequest::ConfigureEvents { ranges }) => Some(ranges.clone()),
            _ => None,
        })
        .collect()
}

// ------------------------------------------------------------------------------------------
// Finding 1: a CRC-valid event packet with one bad event length is thrown away whole, with its
// sender and flag: it can never be confirmed, so the device sends it again on every poll.
// wb-mqtt-serial (modbus_ext_common.cpp, ReadEvents) takes `state.SlaveId`/`state.Flag` from
// the packet header *before* IterateOverEvents throws "invalid event data size", so its next
// 0x10 confirms the packet (and the events before the bad one are applied).
// ------------------------------------------------------------------------------------------

#[test]
fn a_crc_valid_event_packet_with_a_bad_event_length_is_still_a_confirmable_frame() {
    let poll = Request::poll_events(EventPoll {
        min_address: 0,
        max_data_len: 248,
        ack_address: 0,
        ack_flag: 0,
    });
    // Device 241, flag 1, 2 events, data_len 9: coil 0 = 1 (5 bytes), then a system event whose
    // payload_len says 5 but 0 bytes are left in the data. The frame's CRC is right.
    let mut frame = vec![0xFF, 0xFF];
    frame.extend(with_crc("F1 46 11 01 02 09 01 01 0000 01 05 0F 0000"));
    let mut parser = ReplyParser::for_request(&poll);
    let mut statuses = vec![parser.feed(&frame)];
    while !matches!(statuses.last(), Some(ParseStatus::NeedMore)) {
        statuses.push(parser.poll());
    }
    let frame_found = statuses.iter().find_map(|s| match s {
        ParseStatus::Frame(parsed) => Some(parsed.reply.clone()),
        _ => None,
    });
    assert!(
        frame_found.is_some(),
        "the packet's sender and flag must survive so that the next 0x10 confirms it \
         (otherwise the device repeats it forever and, at high priority, wins every \
         arbitration): got {statuses:?}"
    );
    let reply = frame_found.unwrap();
    assert_eq!(reply.address, 241);
    let rtu2mqtt::protocol::ReplyBody::Fast {
        reply: FastReply::Events(packet),
        ..
    } = reply.body
    else {
        panic!("not an event packet");
    };
    assert_eq!(packet.flag, 1);
    assert!(!statuses
        .iter()
        .any(|s| matches!(s, ParseStatus::Error(ParseError::Malformed(_)))));
}

/// What the transport makes of `bytes` in answer to `request`: the first frame the reply parser
/// finds, else garbage.
fn outcome_of(request: &Request, bytes: &[u8]) -> TransactionOutcome {
    let mut parser = ReplyParser::for_request(request);
    let mut status = parser.feed(bytes);
    loop {
        match status {
            ParseStatus::Frame(parsed) => return TransactionOutcome::Reply(parsed.reply),
            ParseStatus::NeedMore => return TransactionOutcome::Garbled,
            ParseStatus::Error(_) => status = parser.poll(),
        }
    }
}

/// The consequence on the bus: device 5 sends, until it is confirmed, a packet with a bad event
/// length (and a high-priority event, so it wins every round it takes part in); device 9 has a
/// packet waiting. The bad packet is confirmed, its good event delivered, the rotation moves
/// past device 5 and device 9's event comes. (Before the fix the transport called it garbled:
/// no ack, `min_address` 0 for good, device 9 never heard.)
#[test]
fn a_packet_with_a_bad_event_length_is_confirmed_and_the_next_device_gets_its_turn() {
    let settings = PortSettings::for_line(LineSettings::new(115_200, Parity::None, 2));
    let mut scheduler = PortScheduler::new(
        settings,
        vec![
            device(5, vec![sporadic(RegisterType::Coil, 0, 1)]),
            device(9, vec![sporadic(RegisterType::Coil, 0, 1)]),
        ],
    );
    // Coil 0 = 1, then a system event whose payload_len (5) overruns data_len.
    let mut bad = vec![0xFF];
    bad.extend(with_crc("05 46 11 01 02 09 01 01 0000 01 05 0F 0000"));
    let nine = Reply::fast(
        9,
        FastReply::Events(EventPacket {
            flag: 0,
            event_count: 1,
            events: vec![Event {
                source: EventSource::Register(RegisterType::Coil),
                id: 0,
                payload: vec![1],
            }],
        }),
    )
    .encode()
    .unwrap();
    let nothing = Reply::fast(0xFD, FastReply::NoEvents).encode().unwrap();
    let (mut five_pending, mut nine_pending) = (true, true);
    let (sent, events) = run(&mut scheduler, ms(2000), |request| match &request.body {
        RequestBody::Fast(FastRequest::PollEvents(poll)) => {
            five_pending &= (poll.ack_address, poll.ack_flag) != (5, 1);
            nine_pending &= (poll.ack_address, poll.ack_flag) != (9, 0);
            let bytes = if five_pending && poll.min_address <= 5 {
                &bad
            } else if nine_pending && poll.min_address <= 9 {
                &nine
            } else {
                &nothing
            };
            outcome_of(request, bytes)
        }
        _ => healthy(request),
    });
    let polls = polls(&sent);
    assert!(
        !five_pending,
        "device 5's packet never confirmed: {:?}",
        &polls[..5.min(polls.len())]
    );
    assert!(!nine_pending, "device 9 never heard");
    let coil_events: Vec<usize> = events
        .iter()
        .filter_map(|event| match event {
            PortEvent::EventValue {
                device,
                register_type: RegisterType::Coil,
                address: 0,
                payload,
            } if payload == &vec![1] => Some(*device),
            _ => None,
        })
        .collect();
    assert_eq!(
        coil_events,
        vec![0, 1],
        "the event before the bad one, then device 9's"
    );
}

// ------------------------------------------------------------------------------------------
// Finding 2: one lost or garbled reply to the 0x18 event setup turns events off for the device
// until it reboots or goes offline (it is polled instead, at round-robin pace), although the
// request may well have reached it. wb-mqtt-serial rethrows a transient error from
// TEventsEnabler ("Failed to enable events: ..."), so the device's preparation fails and is
// tried again; only an exception reply (TSerialDevicePermanentRegisterException) is final.
// ------------------------------------------------------------------------------------------

#[test]
fn a_garbled_reply_to_the_event_setup_is_tried_again_under_the_back_off() {
    let settings = PortSettings::for_line(LineSettings::new(115_200, Parity::None, 2));
    let mut scheduler = PortScheduler::new(
        settings,
        vec![device(20, vec![sporadic(RegisterType::Coil, 0, 1)])],
    );
    let mut setups = 0;
    let (sent, _) = run(&mut scheduler, ms(10_000), |request| match &request.body {
        RequestBody::Fast(FastRequest::ConfigureEvents { .. }) => {
            setups += 1;
            if setups == 1 {
                // Noise on the reply (or a late adapter): one bad CRC.
                TransactionOutcome::Garbled
            } else {
                healthy(request)
            }
        }
        _ => healthy(request),
    });
    assert!(
        event_setups(&sent).len() >= 2,
        "one garbled 0x18 reply: the setup was never sent again in 10 s ({} sent), events stay \
         off for good (reports: {:?})",
        event_setups(&sent).len(),
        scheduler.device_report(0, ms(10_000))
    );
    let report = scheduler.device_report(0, ms(10_000)).unwrap();
    assert!(report.events_active, "{report:?}");
    assert_eq!(
        event_setups(&sent).len(),
        2,
        "tried again once, then answered"
    );
}

// ------------------------------------------------------------------------------------------
// Finding 3: events for a register no channel enables are confirmed and dropped, but never
// turned off. wb-mqtt-serial (serial_client_events_reader.cpp, ProcessRegisterChangeEvent ->
// RegsToDisable -> DisableEventsFromRegs) sends a 0x18 with priority 0 for each such register
// after the poll loop. Registers enabled by an earlier config (before a reload) or by another
// master keep costing a packet (and an arbitration win) per change for ever.
// ------------------------------------------------------------------------------------------

#[test]
fn events_of_a_register_no_channel_reads_are_turned_off_once() {
    let settings = PortSettings::for_line(LineSettings::new(115_200, Parity::None, 2));
    let mut scheduler = PortScheduler::new(
        settings,
        vec![device(20, vec![sporadic(RegisterType::Coil, 0, 1)])],
    );
    let mut flag = 0u8;
    let (sent, _) = run(&mut scheduler, ms(2000), |request| match &request.body {
        RequestBody::Fast(FastRequest::PollEvents(poll)) => {
            if poll.ack_address == 20 {
                flag ^= 1;
            }
            // Holding 999 changes all the time: nobody asked for its events.
            TransactionOutcome::Reply(Reply::fast(
                20,
                FastReply::Events(EventPacket {
                    flag,
                    event_count: 1,
                    events: vec![Event {
                        source: EventSource::Register(RegisterType::Holding),
                        id: 999,
                        payload: vec![0x34, 0x12],
                    }],
                }),
            ))
        }
        _ => healthy(request),
    });
    let disabled = event_setups(&sent)
        .iter()
        .filter(|ranges| {
            ranges.iter().any(|r| {
                r.source == EventSource::Register(RegisterType::Holding)
                    && r.start == 999
                    && r.priorities == vec![EventPriority::Disabled]
            })
        })
        .count();
    assert!(
        disabled > 0,
        "{} packets about holding 999 confirmed, no 0x18 turning it off",
        polls(&sent).iter().filter(|p| p.ack_address == 20).count()
    );
    // This device goes on sending them: turned off once per connection, not for ever.
    assert_eq!(disabled, 1);
    assert_eq!(
        event_setups(&sent).len(),
        2,
        "the event setup and the one turning 999 off"
    );
}

// ------------------------------------------------------------------------------------------
// Finding 4: "If the events do not fit max_data_len, the device sends what fits and keeps the
// rest for the next round; if not even one fits, it sends the count with no payload"
// (fast-modbus.md §6). The master's max_data_len is fixed per port (event_interval_ms may be
// set down to 5 ms; the floor is 6 bytes): an event wider than it (a u32 needs 8 bytes, a u64
// 12) is never delivered. The packet "count N, no events" is confirmed and asked again, for
// ever; the value stays stale (events-only channels are not polled).
// ------------------------------------------------------------------------------------------

#[test]
fn an_event_that_does_not_fit_the_budget_is_asked_for_with_the_largest_once() {
    let mut settings = PortSettings::for_line(LineSettings::new(9600, Parity::None, 2));
    // A short event interval for low latency at 9600: 20 ms = 17 characters, 9 bytes of data.
    settings.event_interval = ms(20);
    let mut scheduler = PortScheduler::new(
        settings,
        vec![device(20, vec![sporadic(RegisterType::Input, 60, 4)])],
    );
    let mut flag = 0u8;
    let (sent, events) = run(&mut scheduler, ms(3000), |request| match &request.body {
        RequestBody::Fast(FastRequest::PollEvents(poll)) => {
            if poll.ack_address == 20 {
                flag ^= 1;
            }
            // Input 60..63 (a u64 counter) changed: 4 + 8 = 12 bytes of event data.
            let events = if poll.max_data_len >= 12 {
                vec![Event {
                    source: EventSource::Register(RegisterType::Input),
                    id: 60,
                    payload: vec![1, 0, 0, 0, 0, 0, 0, 0],
                }]
            } else {
                Vec::new()
            };
            TransactionOutcome::Reply(Reply::fast(
                20,
                FastReply::Events(EventPacket {
                    flag,
                    event_count: 1,
                    events,
                }),
            ))
        }
        _ => healthy(request),
    });
    let budgets: Vec<u8> = polls(&sent).iter().map(|p| p.max_data_len).collect();
    assert!(
        budgets.iter().any(|&b| b >= 12),
        "{} polls, every one with max_data_len {:?}: the 12-byte event is never delivered",
        budgets.len(),
        budgets.first()
    );
    assert!(events.iter().any(|event| matches!(
        event,
        PortEvent::EventValue { register_type: RegisterType::Input, address: 60, payload, .. }
            if payload.len() == 8
    )));
    // The largest budget once after each packet in which nothing fitted, then the port's again.
    assert!(budgets.contains(&9));
    assert!(
        budgets.windows(2).all(|pair| pair[0] == 9 || pair[1] == 9),
        "{budgets:?}"
    );
    // A poll with the largest budget waits for the longest reply it may bring.
    let line = LineSettings::new(9600, Parity::None, 2);
    for (_, transaction) in &sent {
        if let RequestBody::Fast(FastRequest::PollEvents(poll)) = &transaction.request.body {
            let longest = line.wire_time(transaction.request.max_reply_len());
            assert!(
                transaction.reply_timeout > longest,
                "budget {}: reply timeout {:?}, the longest reply takes {longest:?}",
                poll.max_data_len,
                transaction.reply_timeout
            );
        }
    }
}
