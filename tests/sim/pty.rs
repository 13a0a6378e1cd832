//! End-to-end: the real simulator on a pseudo-terminal, the protocol core as master, byte-exact
//! replies. Timing is not asserted here (not even in `pacing.rs`): the machine is shared.

use std::path::Path;
use std::time::Duration;

use crate::sim_support::{data, ff, hex, with_crc, SimProcess, FAST};
use rtu2mqtt::protocol::{
    arbitrate, ArbitrationWord, EventPoll, EventPriority, EventRange, EventSource, EventUrgency,
    FastReply, LineSettings, Parity, RegisterType, Reply, ReplyBody, Request, RequestPdu,
};
use serde_json::json;

/// The filler bytes of a round among these words.
fn fillers(words: &[ArbitrationWord]) -> Vec<u8> {
    ff(arbitrate(words).unwrap().filler_bytes())
}

fn frame(reply: Reply) -> Vec<u8> {
    reply.encode().unwrap()
}

#[test]
fn classic_reads_writes_and_exceptions() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    let read_address = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert_eq!(port.transact(&read_address).0, hex("14 03 02 00 14 B5 88"));
    let write = Request::classic(
        241,
        RequestPdu::WriteSingleCoil {
            address: 1,
            value: true,
        },
    );
    assert_eq!(port.transact(&write).0, write.encode().unwrap());
    let read = Request::classic(241, RequestPdu::ReadCoils { start: 0, count: 4 });
    assert_eq!(port.transact(&read).0, with_crc("F1 01 01 02"));
    let many = Request::classic(
        40,
        RequestPdu::WriteMultipleRegisters {
            start: 2,
            values: vec![7, 8],
        },
    );
    assert_eq!(port.transact(&many).0, with_crc("28 10 00 02 00 02"));
    let coils = Request::classic(
        40,
        RequestPdu::WriteMultipleCoils {
            start: 8,
            values: vec![true; 9],
        },
    );
    assert_eq!(port.transact(&coils).0, with_crc("28 0F 00 08 00 09"));
    let regs = Request::classic(40, RequestPdu::ReadHoldingRegisters { start: 1, count: 3 });
    assert_eq!(
        port.transact(&regs).0,
        with_crc("28 03 06 00 00 00 07 00 08")
    );
    let bits = Request::classic(
        40,
        RequestPdu::ReadCoils {
            start: 8,
            count: 10,
        },
    );
    assert_eq!(port.transact(&bits).0, with_crc("28 01 02 FF 01"));
    let discrete = Request::classic(241, RequestPdu::ReadDiscreteInputs { start: 0, count: 2 });
    assert_eq!(port.transact(&discrete).0, with_crc("F1 02 01 00"));
    let input = Request::classic(
        20,
        RequestPdu::ReadInputRegisters {
            start: 270,
            count: 2,
        },
    );
    // The template's "Serial" channel reads the serial number (0xFE4000AC).
    assert_eq!(port.transact(&input).0, with_crc("14 04 04 FE 40 00 AC"));
    let model = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 200,
            count: 6,
        },
    );
    assert_eq!(
        port.transact(&model).0,
        with_crc("14 03 0C 00 57 00 42 00 4D 00 43 00 4D 00 38")
    );
    // Exceptions: unknown register, read-only register, bad value, unknown function, bad count.
    let unknown = Request::classic(
        20,
        RequestPdu::ReadHoldingRegisters {
            start: 1000,
            count: 1,
        },
    );
    assert_eq!(port.transact(&unknown).0, with_crc("14 83 02"));
    let read_only = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 200,
            value: 1,
        },
    );
    assert_eq!(port.transact(&read_only).0, with_crc("14 86 02"));
    let bad_parity = Request::classic(
        20,
        RequestPdu::WriteSingleRegister {
            address: 111,
            value: 9,
        },
    );
    assert_eq!(port.transact(&bad_parity).0, with_crc("14 86 03"));
    let any = Request::classic(20, RequestPdu::ReadCoils { start: 0, count: 1 });
    assert_eq!(
        port.transact_raw(&with_crc("14 2B 0E 01 00"), &any).0,
        with_crc("14 AB 01")
    );
    assert_eq!(
        port.transact_raw(&with_crc("14 04 00 00 00 7E"), &any).0,
        with_crc("14 84 03")
    );
    assert_eq!(
        port.transact_raw(&with_crc("14 01 00 00 07 D1"), &any).0,
        with_crc("14 81 03")
    );
    // Silence (nobody at an address, devices at other settings) is proved on virtual time in
    // src/sim/bus_tests.rs; here the settings the pty reports pick who answers.
    let slow = Request::classic(50, RequestPdu::ReadCoils { start: 0, count: 1 });
    let classic_fast = Request::configure_events(
        70,
        vec![EventRange::registers(
            RegisterType::Coil,
            0,
            vec![EventPriority::High],
        )],
    );
    assert_eq!(port.transact(&classic_fast).0, with_crc("46 C6 01"));
    // At 9600 8N2 the slow device answers, with its own settings.
    port.set_line(LineSettings::new(9600, Parity::None, 2));
    assert_eq!(port.transact(&slow).0, with_crc("32 01 01 00"));
    // Odd parity is visible through the pty.
    port.set_line(LineSettings::new(115_200, Parity::Odd, 2));
    let odd = Request::classic(
        60,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert_eq!(port.transact(&odd).0, with_crc("3C 03 02 00 3C"));
}

fn scan_word(serial: u32, scanned: bool) -> ArbitrationWord {
    ArbitrationWord::scan(serial, scanned)
}

#[test]
fn scan_finds_five_devices_in_serial_order() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    // The five fast devices at 115200 8N2, by the low 28 bits of their serials.
    let mut devices = [
        (0xFED2_A3A6u32, 241u8),
        (0xFE40_00AC, 20),
        (0xF000_0003, 30),
        (233_000_005, 40),
        (0xFE00_0001, 10),
    ];
    devices.sort_by_key(|&(serial, _)| serial & 0x0FFF_FFFF);
    let mut scanned = vec![false; devices.len()];
    for (round, &(serial, address)) in devices.iter().enumerate() {
        let request = if round == 0 {
            Request::scan_start()
        } else {
            Request::scan_continue()
        };
        let words: Vec<ArbitrationWord> = devices
            .iter()
            .zip(&scanned)
            .map(|(&(s, _), &done)| scan_word(s, done))
            .collect();
        let expected = [
            fillers(&words),
            frame(Reply::fast(
                0xFD,
                FastReply::ScanFound {
                    serial,
                    modbus_address: address,
                },
            )),
        ]
        .concat();
        assert_eq!(port.transact(&request).0, expected, "round {round}");
        scanned[round] = true;
    }
    let words: Vec<ArbitrationWord> = devices.iter().map(|&(s, _)| scan_word(s, true)).collect();
    let end = [fillers(&words), hex("FD 46 04 D3 93")].concat();
    assert_eq!(port.transact(&Request::scan_continue()).0, end);
    // Other settings: only the device configured for them.
    port.set_line(LineSettings::new(9600, Parity::None, 2));
    let slow = [
        fillers(&[scan_word(0xFE00_0050, false)]),
        frame(Reply::fast(
            0xFD,
            FastReply::ScanFound {
                serial: 0xFE00_0050,
                modbus_address: 50,
            },
        )),
    ]
    .concat();
    assert_eq!(port.transact(&Request::scan_start()).0, slow);
    port.set_line(LineSettings::new(115_200, Parity::Odd, 2));
    let (_, reply) = port.transact(&Request::scan_start());
    let found = reply.unwrap().reply;
    assert_eq!(
        found,
        Reply::fast(
            0xFD,
            FastReply::ScanFound {
                serial: 0xFE00_0060,
                modbus_address: 60
            }
        )
    );
    assert!(matches!(
        port.transact(&Request::scan_continue())
            .1
            .unwrap()
            .reply
            .body,
        ReplyBody::Fast {
            reply: FastReply::ScanEnd,
            ..
        }
    ));
}

#[test]
fn by_serial_read_and_address_change() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    let model = hex("FD 46 08 FE 40 00 AC 03 00 C8 00 14 91 BA");
    let request = Request::decode(&model).unwrap();
    let (bytes, _) = port.transact_raw(&model, &request);
    assert_eq!(&bytes[..7], &hex("FD 46 09 FE 40 00 AC"));
    assert_eq!(
        &bytes[7..21],
        &hex("03 28 00 57 00 42 00 4D 00 43 00 4D 00 38")
    );
    assert_eq!(bytes.len(), 7 + 2 + 40 + 2);
    let set = hex("FD 46 08 FE 40 00 AC 06 00 80 00 C8 DC 35");
    let request = Request::decode(&set).unwrap();
    assert_eq!(
        port.transact_raw(&set, &request).0,
        hex("FD 46 09 FE 40 00 AC 06 00 80 00 C8 8D F0")
    );
    let new = Request::classic(
        200,
        RequestPdu::ReadHoldingRegisters {
            start: 128,
            count: 1,
        },
    );
    assert_eq!(port.transact(&new).0, with_crc("C8 03 02 00 C8"));
    assert_eq!(
        sim.control(
            json!({"cmd": "get", "serial": "0xFE4000AC", "type": "holding", "address": 128})
        )["value"],
        200
    );
}

#[test]
fn configure_events_with_mixed_bitmasks() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    let request = Request::configure_events(
        241,
        vec![
            // K1–K3 send events, K4 cannot, 4 and 5 do not exist.
            EventRange::registers(RegisterType::Coil, 0, vec![EventPriority::High; 6]),
            EventRange::registers(
                RegisterType::DiscreteInput,
                0,
                vec![EventPriority::Low, EventPriority::Disabled],
            ),
            EventRange::registers(RegisterType::Input, 32, vec![EventPriority::Low]),
            EventRange::registers(RegisterType::Input, 123, vec![EventPriority::Low]),
            EventRange {
                source: EventSource::System,
                start: 0,
                priorities: vec![EventPriority::Disabled],
            },
        ],
    );
    assert_eq!(
        port.transact(&request).0,
        with_crc("F1 46 18 05 07 01 01 00 00")
    );
}

fn poll(min_address: u8, max_data_len: u8, ack_address: u8, ack_flag: u8) -> Request {
    Request::poll_events(EventPoll {
        min_address,
        max_data_len,
        ack_address,
        ack_flag,
    })
}

/// Confirms every pending packet (the reboot events after start-up) until "no events".
fn drain_events(port: &mut crate::sim_support::MasterPort) {
    let mut ack = (0, 0);
    for _ in 0..20 {
        let (_, reply) = port.transact(&poll(0, 0xFF, ack.0, ack.1));
        match reply.map(|r| r.reply) {
            Some(Reply {
                address,
                body:
                    ReplyBody::Fast {
                        reply: FastReply::Events(packet),
                        ..
                    },
            }) => {
                ack = (address, packet.flag);
            }
            Some(Reply {
                body:
                    ReplyBody::Fast {
                        reply: FastReply::NoEvents,
                        ..
                    },
                ..
            }) => return,
            other => panic!("unexpected reply {other:?}"),
        }
    }
    panic!("events never drained");
}

fn event_word(urgency: EventUrgency, address: u8) -> ArbitrationWord {
    ArbitrationWord::event(urgency, address)
}

/// The devices taking part in event rounds at 115200 8N2.
const EVENT_ADDRESSES: [u8; 5] = [10, 20, 30, 40, 241];

fn round(active: &[(u8, EventUrgency)], min_address: u8) -> Vec<u8> {
    let words: Vec<ArbitrationWord> = EVENT_ADDRESSES
        .iter()
        .filter(|&&a| a >= min_address)
        .map(|&a| {
            let urgency = active
                .iter()
                .find(|(x, _)| *x == a)
                .map_or(EventUrgency::Nothing, |(_, u)| *u);
            event_word(urgency, a)
        })
        .collect();
    fillers(&words)
}

#[test]
fn events_ack_lost_ack_min_address_and_truncation() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    drain_events(&mut port);
    let enable = |address, register_type, start, priorities| {
        Request::configure_events(
            address,
            vec![EventRange::registers(register_type, start, priorities)],
        )
    };
    assert_eq!(
        port.transact(&enable(
            241,
            RegisterType::Coil,
            0,
            vec![EventPriority::High; 3]
        ))
        .0,
        with_crc("F1 46 18 01 07")
    );
    assert_eq!(
        port.transact(&enable(
            20,
            RegisterType::Input,
            471,
            vec![EventPriority::Low]
        ))
        .0,
        with_crc("14 46 18 01 01")
    );
    assert_eq!(
        port.transact(&enable(10, RegisterType::Coil, 0, vec![EventPriority::Low]))
            .0,
        with_crc("0A 46 18 01 01")
    );
    sim.control(
        json!({"cmd": "set", "device": 241, "type": "coil", "address": 0, "value": [1, 1, 1]}),
    );
    sim.control(json!({"cmd": "set", "device": 20, "type": "input", "address": 471, "value": 1}));
    sim.control(json!({"cmd": "set", "device": 10, "type": "coil", "address": 0, "value": 1}));
    let high241 = (241, EventUrgency::High);
    let low20 = (20, EventUrgency::Low);
    let low10 = (10, EventUrgency::Low);
    // The high-priority relay wins; 12 bytes of event data fit two coil events (flag 1: its
    // reboot packet had flag 0).
    let first = [
        round(&[high241, low20, low10], 0),
        with_crc("F1 46 11 01 02 0A 01 01 00 00 01 01 01 00 01 01"),
    ]
    .concat();
    assert_eq!(port.transact(&poll(0, 12, 0, 0)).0, first);
    // Lost: the master confirms nothing; the same packet again, same flag.
    assert_eq!(port.transact(&poll(0, 12, 0, 0)).0, first);
    // Confirmed: the rest of the relay's events, flag toggled.
    let rest = [
        round(&[high241, low20, low10], 0),
        with_crc("F1 46 11 00 01 05 01 01 00 02 01"),
    ]
    .concat();
    assert_eq!(port.transact(&poll(0, 12, 241, 1)).0, rest);
    // A wrong flag is no confirmation.
    assert_eq!(port.transact(&poll(0, 12, 241, 1)).0, rest);
    // Confirmed; min_address 11 keeps device 10 out, so 20 comes before it.
    let counter = [
        round(&[low20], 11),
        with_crc("14 46 11 01 01 06 02 04 01 D7 01 00"),
    ]
    .concat();
    assert_eq!(port.transact(&poll(11, 0xFF, 241, 0)).0, counter);
    let nothing_above = [round(&[], 21), hex("FD 46 12 52 5D")].concat();
    assert_eq!(port.transact(&poll(21, 0xFF, 20, 1)).0, nothing_above);
    let ten = [
        round(&[low10], 0),
        with_crc("0A 46 11 01 01 05 01 01 00 00 01"),
    ]
    .concat();
    assert_eq!(port.transact(&poll(0, 0xFF, 0, 0)).0, ten);
    // Not even one event fits: only the count.
    sim.control(json!({"cmd": "set", "device": 10, "type": "coil", "address": 0, "value": 0}));
    let count_only = [round(&[low10], 0), with_crc("0A 46 11 01 01 00")].concat();
    assert_eq!(port.transact(&poll(0, 4, 0, 0)).0, count_only);
    let ten_again = [
        round(&[low10], 0),
        with_crc("0A 46 11 01 01 05 01 01 00 00 00"),
    ]
    .concat();
    assert_eq!(port.transact(&poll(0, 0xFF, 0, 0)).0, ten_again);
    let quiet = [round(&[], 0), hex("FD 46 12 52 5D")].concat();
    assert_eq!(port.transact(&poll(0, 0xFF, 10, 1)).0, quiet);
}

#[test]
fn reboot_event_after_every_start() {
    let sim = SimProcess::start("bus.json", &[]);
    let mut port = sim.master(FAST);
    // At power-on every device reports "rebooted", lowest address first.
    let reboot = |address: u8| with_crc(&format!("{address:02X} 46 11 00 01 04 00 0F 00 00"));
    let all_low: Vec<(u8, EventUrgency)> = EVENT_ADDRESSES
        .iter()
        .map(|&a| (a, EventUrgency::Low))
        .collect();
    assert_eq!(
        port.transact(&poll(0, 0xFF, 0, 0)).0,
        [round(&all_low, 0), reboot(10)].concat()
    );
    drain_events(&mut port);
    let enable = Request::configure_events(
        30,
        vec![EventRange::registers(
            RegisterType::Coil,
            0,
            vec![EventPriority::High],
        )],
    );
    assert_eq!(port.transact(&enable).0, with_crc("1E 46 18 01 01"));
    sim.control(json!({"cmd": "reboot", "device": 30}));
    // Settings are gone: a coil change sends nothing; the reboot event comes, flag 0.
    sim.control(json!({"cmd": "set", "device": 30, "type": "coil", "address": 0, "value": 1}));
    let expected = [round(&[(30, EventUrgency::Low)], 0), reboot(30)].concat();
    assert_eq!(port.transact(&poll(0, 0xFF, 0, 0)).0, expected);
    assert_eq!(
        port.transact(&poll(0, 0xFF, 30, 0)).0,
        [round(&[], 0), hex("FD 46 12 52 5D")].concat()
    );
    // Unplugged devices take no part in arbitration; replugged they are back. (That they stay
    // silent is proved on virtual time in src/sim/bus_tests.rs.)
    sim.control(json!({"cmd": "unplug", "device": 10}));
    let others: Vec<ArbitrationWord> = [20, 30, 40, 241]
        .iter()
        .map(|&address| event_word(EventUrgency::Nothing, address))
        .collect();
    assert_eq!(
        port.transact(&poll(0, 0xFF, 0, 0)).0,
        [fillers(&others), hex("FD 46 12 52 5D")].concat()
    );
    sim.control(json!({"cmd": "replug", "device": 10}));
    let read = Request::classic(10, RequestPdu::ReadCoils { start: 0, count: 1 });
    assert_eq!(port.transact(&read).0, with_crc("0A 01 01 00"));
}

#[test]
fn shared_address_corrupts_classic_replies_and_scan_lists_both() {
    let sim = SimProcess::start("shared-address.json", &[]);
    let mut port = sim.master(FAST);
    let read = Request::classic(
        20,
        RequestPdu::ReadInputRegisters {
            start: 123,
            count: 1,
        },
    );
    // Both answer in step: the wire carries the AND of the two replies, byte for byte.
    port.send(&read.encode().unwrap());
    let garbage: Vec<u8> = port
        .read_until(Duration::from_secs(2), |all| all.len() >= 7)
        .into_iter()
        .flat_map(|(_, bytes)| bytes)
        .collect();
    let merged: Vec<u8> = with_crc("14 04 02 0C E4")
        .iter()
        .zip(with_crc("14 04 02 13 88"))
        .map(|(a, b)| a & b)
        .collect();
    assert_eq!(garbage, merged);
    let words = [scan_word(0xFE40_00AC, false), scan_word(0xFED2_A3A6, false)];
    let first = [
        fillers(&words),
        frame(Reply::fast(
            0xFD,
            FastReply::ScanFound {
                serial: 0xFE40_00AC,
                modbus_address: 20,
            },
        )),
    ]
    .concat();
    assert_eq!(port.transact(&Request::scan_start()).0, first);
    let words = [scan_word(0xFE40_00AC, true), scan_word(0xFED2_A3A6, false)];
    let second = [
        fillers(&words),
        frame(Reply::fast(
            0xFD,
            FastReply::ScanFound {
                serial: 0xFED2_A3A6,
                modbus_address: 20,
            },
        )),
    ]
    .concat();
    assert_eq!(port.transact(&Request::scan_continue()).0, second);
    // Resolve the collision by serial; then both answer cleanly.
    let set = Request::by_serial(
        0xFED2_A3A6,
        RequestPdu::WriteSingleRegister {
            address: 128,
            value: 21,
        },
    );
    assert!(port.transact(&set).1.is_some());
    assert_eq!(port.transact(&read).0, with_crc("14 04 02 0C E4"));
    let other = Request::classic(
        21,
        RequestPdu::ReadInputRegisters {
            start: 123,
            count: 1,
        },
    );
    assert_eq!(port.transact(&other).0, with_crc("15 04 02 13 88"));
}

/// Runs `sim` with the given pty and control paths and returns its exit status and stderr; it
/// must refuse at start, so it is expected to end by itself.
fn sim_refusing(pty: &Path, control: &Path) -> (std::process::ExitStatus, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .arg("sim")
        .arg("--bus")
        .arg(data("bus.json"))
        .arg("--templates")
        .arg(data(""))
        .arg("--pty")
        .arg(pty)
        .arg("--control")
        .arg(control)
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    (
        out.status,
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn sim_never_replaces_a_file_that_is_not_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let victim = dir.path().join("victim.txt");
    std::fs::write(&victim, "precious").unwrap();

    // A planted link at the pty path, pointing at someone's file.
    let pty = dir.path().join("ttyRS485-sim");
    std::os::unix::fs::symlink(&victim, &pty).unwrap();
    let (status, stderr) = sim_refusing(&pty, &dir.path().join("control.sock"));
    assert!(!status.success(), "{stderr}");
    assert!(stderr.contains("not a simulator's pty link"), "{stderr}");
    assert_eq!(std::fs::read_link(&pty).unwrap(), victim);

    // A regular file at the control socket path.
    let control = dir.path().join("control.sock");
    std::fs::write(&control, "not a socket").unwrap();
    let (status, stderr) = sim_refusing(&dir.path().join("tty2"), &control);
    assert!(!status.success(), "{stderr}");
    assert!(stderr.contains("is not a socket"), "{stderr}");
    assert_eq!(std::fs::read_to_string(&control).unwrap(), "not a socket");
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "precious");
}

#[test]
fn control_socket_is_private_to_its_owner() {
    use std::os::unix::fs::PermissionsExt;
    let sim = SimProcess::start("bus.json", &[]);
    let mode = std::fs::metadata(&sim.control)
        .unwrap()
        .permissions()
        .mode();
    assert_eq!(
        mode & 0o777,
        0o600,
        "control socket mode {:o}",
        mode & 0o777
    );
}
