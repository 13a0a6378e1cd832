//! The transport's exchange (the request's silence, the reply window, the echo and
//! other-master watch) over many transactions, fed arbitrary bytes at arbitrary times as the
//! serial transport feeds it: never a panic, and every transaction ends in a bounded number of
//! steps once the bytes run out (a master must never hang on what a bus sends it).
#![no_main]

use std::time::Duration;

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::protocol::{
    EventPoll, EventPriority, EventRange, LineSettings, Parity, RegisterType, Request,
    RequestPdu, Transaction,
};
use rtu2mqtt::transport::exchange::{Exchange, LinkConfig};

struct Input<'a>(&'a [u8]);

impl Input<'_> {
    fn byte(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&first, rest)) => {
                self.0 = rest;
                first
            }
            None => 0,
        }
    }

    fn bytes(&mut self, len: usize) -> &[u8] {
        let (taken, rest) = self.0.split_at(len.min(self.0.len()));
        self.0 = rest;
        taken
    }

    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

fn request_for(selector: u8) -> Request {
    let range = EventRange::registers(RegisterType::Coil, 0, vec![EventPriority::High; 9]);
    match selector % 9 {
        0 => Request::classic(20, RequestPdu::ReadInputRegisters { start: 0, count: 60 }),
        1 => Request::classic(20, RequestPdu::ReadHoldingRegisters { start: 128, count: 3 }),
        2 => Request::classic(21, RequestPdu::ReadCoils { start: 0, count: 11 }),
        3 => Request::classic(20, RequestPdu::WriteSingleRegister { address: 1, value: 2 }),
        4 => Request::scan_start(),
        5 => Request::by_serial(0xFE40_00AC, RequestPdu::ReadInputRegisters { start: 0, count: 2 }),
        6 => Request::poll_events(EventPoll {
            min_address: 0,
            max_data_len: 255,
            ack_address: 0,
            ack_flag: 0,
        }),
        7 => Request::configure_events(20, vec![range]),
        _ => Request::classic(0, RequestPdu::WriteSingleCoil { address: 0, value: true }),
    }
}

fuzz_target!(|data: &[u8]| {
    let mut input = Input(data);
    let line = match input.byte() % 3 {
        0 => LineSettings::new(9600, Parity::None, 2),
        1 => LineSettings::new(115_200, Parity::None, 2),
        _ => LineSettings::new(19_200, Parity::Even, 1),
    };
    let flags = input.byte();
    let mut config = LinkConfig::serial(line);
    if flags & 1 != 0 {
        config = config.on_pseudo_terminal();
    }
    if flags & 2 != 0 {
        config = config.with_receive_fifo(8);
    }
    let mut exchange = Exchange::new(config);
    let mut now = Duration::ZERO;
    for _ in 0..64 {
        if input.is_empty() {
            break;
        }
        let request = request_for(input.byte());
        let timing = input.byte();
        let response_timeout = Duration::from_millis(1 + u64::from(timing % 64));
        let request_time = line.wire_time(request.encoded_len());
        let transaction = Transaction {
            request_time,
            reply_timeout: response_timeout + line.wire_time(request.max_reply_len()),
            first_byte_timeout: (timing & 0x40 == 0).then_some(response_timeout),
            late_window: if timing & 0x80 != 0 { response_timeout } else { Duration::ZERO },
            estimated: request_time + response_timeout,
            request,
        };
        if exchange.start(&transaction).is_err() {
            continue;
        }
        // Once the input is spent only timeouts come: the transaction must end soon after.
        let mut steps_without_input = 0;
        loop {
            if input.is_empty() {
                steps_without_input += 1;
                assert!(steps_without_input < 1_000, "a transaction that never ends");
            }
            if exchange.poll_transmit(now).is_some() {
                exchange.handle_sent(now);
            }
            if exchange.poll_outcome().is_some() {
                break;
            }
            let op = input.byte();
            let chunk = usize::from(op >> 3);
            let later = Duration::from_micros(u64::from(input.byte()) * 97);
            if exchange.awaits_transmit() {
                // Bytes heard in the silence before the request, or the silence kept.
                if op & 1 != 0 {
                    now += later;
                    let bytes = input.bytes(chunk).to_vec();
                    exchange.handle_bytes(now, &bytes);
                    exchange.line_was_busy(now);
                } else {
                    now = now.max(exchange.transmit_at());
                }
                continue;
            }
            if let (Some(at), true) = (exchange.batch_read_at(), op & 2 != 0) {
                now = now.max(at);
                let bytes = input.bytes(chunk).to_vec();
                exchange.handle_batch(now, &bytes);
                continue;
            }
            let Some(timeout) = exchange.poll_timeout() else {
                break;
            };
            if op & 4 != 0 && !input.is_empty() && now + later < timeout {
                now += later;
                let bytes = input.bytes(chunk.max(1)).to_vec();
                exchange.handle_bytes(now, &bytes);
            } else {
                now = now.max(timeout);
                exchange.handle_timeout(now);
            }
        }
    }
});
