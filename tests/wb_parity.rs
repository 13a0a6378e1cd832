//! wb-mqtt-serial's own test suite as an oracle: each test here restates one expectation of a
//! wb-mqtt-serial test (named in its comment as `Suite.Test`, from the `test/` directory of
//! github.com/wirenboard/wb-mqtt-serial: the `.cpp` sources, `configs/*.json` and the gold
//! `.dat` files of what they printed) and checks rtu2mqtt does the same.
//!
//! Configs are written the wb-mqtt-serial way (channels inline in the device) and resolved with
//! the crate's own loader, so the keys (`format`, `scale`, `round_to`, `on_value`,
//! `error_value`, `address` with bit fields, `holding_single` …) are checked too. Values are
//! checked on the channel (`ResolvedChannel::decode` / `encode`, what the device model uses),
//! and where the bus or the error flags matter, on the device model (`DeviceModel`), which
//! turns port events into published values and `/on` payloads into register writes.
//!
//! Where rtu2mqtt differs on purpose (a value that does not fit its format is refused, not cut;
//! a string is written to its full size), the test asserts rtu2mqtt's behaviour and its
//! comment says what wb-mqtt-serial does and why (docs/migrating.md, "What differs").

use std::path::Path;
use std::sync::Arc;

use rtu2mqtt::config::load::load_config_source;
use rtu2mqtt::config::parse::SourceText;
use rtu2mqtt::config::TemplateLibrary;
use rtu2mqtt::device::{resolve_config, Reading, RegisterType, ResolvedChannel, ResolvedDevice};
use rtu2mqtt::device_updates::{DeviceUpdate, Repeats};
use rtu2mqtt::gateway::device_model::DeviceModel;
use rtu2mqtt::port::{PortEvent, RegisterSpan, RegisterWrite};
use serde_json::{json, Value};

// ---------------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------------

/// One Modbus device (slave 1) with `channels` inline, resolved as the daemon would.
fn device_with(channels: Value) -> ResolvedDevice {
    device_with_settings(channels, json!({}))
}

fn device_with_settings(channels: Value, settings: Value) -> ResolvedDevice {
    let mut device = json!({"name": "Parity", "id": "parity", "slave_id": 1, "channels": channels});
    if let (Some(device), Some(settings)) = (device.as_object_mut(), settings.as_object()) {
        for (key, value) in settings {
            device.insert(key.clone(), value.clone());
        }
    }
    let config =
        json!({"ports": [{"path": "/dev/ttyPARITY", "baud_rate": 9600, "devices": [device]}]});
    let source = SourceText::from_text(Path::new("wb_parity.json"), &config.to_string());
    let loaded = load_config_source(source, false).expect("config loads");
    let mut ports = resolve_config(&loaded, &TemplateLibrary::default()).expect("config resolves");
    ports.remove(0).devices.remove(0)
}

/// The only channel of a device made of `channel`.
fn channel(channel: Value) -> ResolvedChannel {
    let device = device_with(json!([channel]));
    device.channels[0].clone()
}

fn holding(address: u32, format: &str) -> Value {
    json!({"name": "v", "reg_type": "holding", "address": address, "format": format, "type": "value"})
}

fn with(mut base: Value, extra: Value) -> Value {
    if let (Some(base), Some(extra)) = (base.as_object_mut(), extra.as_object()) {
        for (key, value) in extra {
            base.insert(key.clone(), value.clone());
        }
    }
    base
}

/// The text a channel publishes for the words of its (single) register.
fn read(channel: &ResolvedChannel, words: &[u16]) -> String {
    match channel.decode(&[words]).expect("decodes") {
        Reading::Value(text) => text,
        other => panic!("expected a value, got {other:?}"),
    }
}

/// The words a channel writes for `payload` (single register), over registers holding zeros
/// (as wb-mqtt-serial's tests' fake device holds them when a format narrower than its registers,
/// or a bit field, is merged into them).
fn write(channel: &ResolvedChannel, payload: &str) -> Vec<u16> {
    let zeros = vec![0u16; channel.registers[0].codec.word_count as usize];
    let mut encoded = channel
        .encode(payload, &[Some(&zeros)])
        .unwrap_or_else(|err| panic!("`{payload}` is refused: {err}"));
    encoded.remove(0)
}

fn float_words(value: f32) -> Vec<u16> {
    let bits = value.to_bits();
    vec![(bits >> 16) as u16, bits as u16]
}

/// The device model of `device`, reporting every value.
fn model(device: ResolvedDevice) -> DeviceModel {
    DeviceModel::new(Arc::new(device), 0, Repeats::All)
}

fn values_read(
    model: &mut DeviceModel,
    register_type: RegisterType,
    start: u16,
    words: Vec<u16>,
) -> Vec<DeviceUpdate> {
    let mut out = Vec::new();
    let count = u16::try_from(words.len()).unwrap();
    model.apply(
        PortEvent::Values {
            device: 0,
            span: RegisterSpan::new(register_type, start, count),
            values: words.into(),
        },
        &mut out,
    );
    out
}

/// (control, value) of every value update.
fn published(updates: &[DeviceUpdate]) -> Vec<(String, String)> {
    updates
        .iter()
        .filter_map(|update| match update {
            DeviceUpdate::Value {
                control_id, value, ..
            } => Some((control_id.to_string(), value.to_string())),
            _ => None,
        })
        .collect()
}

/// (control, error flags text) of every error update.
fn errors(updates: &[DeviceUpdate]) -> Vec<(String, String)> {
    updates
        .iter()
        .filter_map(|update| match update {
            DeviceUpdate::ControlError {
                control_id, errors, ..
            } => Some((control_id.clone(), errors.to_string())),
            _ => None,
        })
        .collect()
}

/// (address, values, force_multiple) of every register write.
/// The requests of `list` as they go on the wire, in order: first register, words, and
/// whether 0x0F/0x10 is forced.
fn writes(list: &[RegisterWrite]) -> Vec<(u16, Vec<u16>, bool)> {
    list.iter()
        .flat_map(|w| {
            (0..w.request_count()).map(move |sent| {
                let (address, values) = w.request(sent);
                (address, values.to_vec(), w.force_multiple)
            })
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Formats: TSerialClientTest (test/serial_client_test.cpp), whole registers, big endian
// ---------------------------------------------------------------------------------------------

/// TSerialClientTest.Poll: u8 and u16 values read as their decimal text.
#[test]
fn u16_and_u8_read_as_decimal() {
    assert_eq!(read(&channel(holding(22, "u16")), &[4242]), "4242");
    assert_eq!(read(&channel(holding(33, "u16")), &[42000]), "42000");
    assert_eq!(read(&channel(holding(1, "u8")), &[1]), "1");
}

/// TSerialClientTest.Write: "1" and "4242" written to u16 registers as 1 and 4242.
#[test]
fn u16_write_plain_integers() {
    let ch = channel(holding(20, "u16"));
    assert_eq!(write(&ch, "1"), vec![1]);
    assert_eq!(write(&ch, "4242"), vec![4242]);
}

/// TSerialClientTest.U8: u8 takes the low byte of the register (0x2010 → 16, 0x2011 → 17) and
/// "10" is written as 10.
#[test]
fn u8_reads_low_byte_and_writes_value() {
    let ch = channel(holding(20, "u8"));
    assert_eq!(read(&ch, &[10]), "10");
    assert_eq!(read(&ch, &[0x2010]), "16");
    assert_eq!(read(&ch, &[0x2011]), "17");
    assert_eq!(write(&ch, "10"), vec![10]);
}

/// TSerialClientTest.U8 has "257" written to a u8 cut to its low byte (the register gets 1).
/// rtu2mqtt refuses it instead (`w`, nothing written): 1 is not the value asked for, and a
/// gateway must not write a wrong value (docs/migrating.md, "What differs").
#[test]
fn u8_write_out_of_range_is_refused_not_wrapped() {
    let ch = channel(holding(20, "u8"));
    let err = ch
        .encode("257", &[None])
        .expect_err("257 does not fit a u8");
    assert!(err.to_string().contains("out of range for u8"), "{err}");
}

/// TSerialClientTest.S8: 254 → "-2", 253 → "-3"; "-2" written as 254.
#[test]
fn s8_sign_and_write() {
    let ch = channel(holding(20, "s8"));
    assert_eq!(read(&ch, &[10]), "10");
    assert_eq!(read(&ch, &[254]), "-2");
    assert_eq!(read(&ch, &[253]), "-3");
    assert_eq!(write(&ch, "10"), vec![10]);
    assert_eq!(write(&ch, "-2"), vec![254]);
}

/// TSerialClientTest.Char8: 65 → "A", 66 → "B"; "!" written as 33.
#[test]
fn char8_read_and_write() {
    let ch = channel(holding(20, "char8"));
    assert_eq!(read(&ch, &[65]), "A");
    assert_eq!(read(&ch, &[66]), "B");
    assert_eq!(write(&ch, "!"), vec![33]);
}

/// TSerialClientTest.S64: 00AA 00BB 00CC 00DD → 0x00AA00BB00CC00DD, FFFF×4 → "-1"; "10" →
/// 0 0 0 10; "-2" → FFFF FFFF FFFF FFFE.
#[test]
fn s64_read_and_write() {
    let ch = channel(holding(20, "s64"));
    assert_eq!(
        read(&ch, &[0x00AA, 0x00BB, 0x00CC, 0x00DD]),
        0x00AA_00BB_00CC_00DDu64.to_string()
    );
    assert_eq!(read(&ch, &[0xFFFF; 4]), "-1");
    assert_eq!(write(&ch, "10"), vec![0, 0, 0, 10]);
    assert_eq!(write(&ch, "-2"), vec![0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE]);
}

/// TSerialClientTest.U64: FFFF×4 → "18446744073709551615"; "10" → 0 0 0 10; "-2" is written as
/// FFFF FFFF FFFF FFFE and reads back "18446744073709551614".
#[test]
fn u64_read_and_write() {
    let ch = channel(holding(20, "u64"));
    assert_eq!(
        read(&ch, &[0x00AA, 0x00BB, 0x00CC, 0x00DD]),
        0x00AA_00BB_00CC_00DDu64.to_string()
    );
    assert_eq!(read(&ch, &[0xFFFF; 4]), "18446744073709551615");
    assert_eq!(write(&ch, "10"), vec![0, 0, 0, 10]);
    let words = write(&ch, "-2");
    assert_eq!(words, vec![0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE]);
    assert_eq!(read(&ch, &words), "18446744073709551614");
}

/// TSerialClientTest.S32: 00AA 00BB → 0x00AA00BB, FFFF FFFF → "-1"; "10" → 0 10; "-2" →
/// FFFF FFFE; scale 0.001: "-0.123" → FFFF FF85, and FFFF FF85 reads "-0.123".
#[test]
fn s32_read_write_and_scaled() {
    let ch = channel(holding(20, "s32"));
    assert_eq!(read(&ch, &[0x00AA, 0x00BB]), 0x00AA_00BBu32.to_string());
    assert_eq!(read(&ch, &[0xFFFF, 0xFFFF]), "-1");
    assert_eq!(write(&ch, "10"), vec![0, 10]);
    assert_eq!(write(&ch, "-2"), vec![0xFFFF, 0xFFFE]);
    let scaled = channel(with(holding(24, "s32"), json!({"scale": 0.001})));
    assert_eq!(write(&scaled, "-0.123"), vec![0xFFFF, 0xFF85]);
    assert_eq!(read(&scaled, &[0xFFFF, 0xFF85]), "-0.123");
}

/// TSerialClientTest.S24: 002A 00BB → 0x002A00BB, 00FF FFFF → "-1"; "-2" → 00FF FFFE;
/// scale 0.001: "-0.123" → 00FF FF85 and reads back "-0.123".
#[test]
fn s24_read_write_and_scaled() {
    let ch = channel(holding(20, "s24"));
    assert_eq!(read(&ch, &[0x002A, 0x00BB]), 0x002A_00BBu32.to_string());
    assert_eq!(read(&ch, &[0x00FF, 0xFFFF]), "-1");
    assert_eq!(write(&ch, "10"), vec![0, 10]);
    assert_eq!(write(&ch, "-2"), vec![0x00FF, 0xFFFE]);
    let scaled = channel(with(holding(24, "s24"), json!({"scale": 0.001})));
    assert_eq!(write(&scaled, "-0.123"), vec![0x00FF, 0xFF85]);
    assert_eq!(read(&scaled, &[0x00FF, 0xFF85]), "-0.123");
}

/// TSerialClientTest.U32: 00AA 00BB → 0x00AA00BB, FFFF FFFF → 4294967295; "10" → 0 10; "-1"
/// (overflow) → FFFF FFFF.
#[test]
fn u32_read_and_write_negative_wraps() {
    let ch = channel(holding(20, "u32"));
    assert_eq!(read(&ch, &[0x00AA, 0x00BB]), 0x00AA_00BBu32.to_string());
    assert_eq!(read(&ch, &[0xFFFF, 0xFFFF]), "4294967295");
    assert_eq!(write(&ch, "10"), vec![0, 10]);
    assert_eq!(write(&ch, "-1"), vec![0xFFFF, 0xFFFF]);
}

/// TSerialClientTest.U32 has "4294967296" (overflow) written as 0 0. rtu2mqtt refuses it, as
/// any value that does not fit its format (see the u8 case above).
#[test]
fn u32_write_overflow_is_refused_not_wrapped() {
    let ch = channel(holding(20, "u32"));
    let err = ch
        .encode("4294967296", &[None])
        .expect_err("2^32 does not fit a u32");
    assert!(err.to_string().contains("out of range for u32"), "{err}");
    assert_eq!(write(&ch, "4294967295"), vec![0xFFFF, 0xFFFF]);
}

/// TSerialClientTest.BCD32: 1234 5678 → "12345678"; "12345678" → 1234 5678; "567890" → 0056 7890.
#[test]
fn bcd32_read_and_write() {
    let ch = channel(holding(20, "bcd32"));
    assert_eq!(read(&ch, &[0x1234, 0x5678]), "12345678");
    assert_eq!(write(&ch, "12345678"), vec![0x1234, 0x5678]);
    assert_eq!(write(&ch, "567890"), vec![0x0056, 0x7890]);
    assert_eq!(read(&ch, &[0x0056, 0x7890]), "567890");
}

/// TSerialClientTest.BCD24: 0034 5678 → "345678"; "567890" → 0056 7890.
#[test]
fn bcd24_read_and_write() {
    let ch = channel(holding(20, "bcd24"));
    assert_eq!(read(&ch, &[0x0034, 0x5678]), "345678");
    assert_eq!(write(&ch, "567890"), vec![0x0056, 0x7890]);
}

/// TSerialClientTest.BCD16 / BCD8: 0x1234 → "1234" and back; 0x12 → "12" and back.
#[test]
fn bcd16_and_bcd8_read_and_write() {
    let ch16 = channel(holding(20, "bcd16"));
    assert_eq!(read(&ch16, &[0x1234]), "1234");
    assert_eq!(write(&ch16, "1234"), vec![0x1234]);
    let ch8 = channel(holding(20, "bcd8"));
    assert_eq!(read(&ch8, &[0x12]), "12");
    assert_eq!(write(&ch8, "12"), vec![0x12]);
}

/// TSerialClientTest.Float32: 45D2 0000 → "6720", 449D 8000 → "1260"; "10" → 4120 0000;
/// "-0.00123" → BAA1 37F4 and reads back "-0.00123"; scale 100: "-0.123" → BAA1 37F4 and
/// 449D 8000 reads "126000".
#[test]
fn float_read_write_and_scaled() {
    let ch = channel(holding(20, "float"));
    assert_eq!(read(&ch, &[0x45D2, 0x0000]), "6720");
    assert_eq!(read(&ch, &[0x449D, 0x8000]), "1260");
    assert_eq!(write(&ch, "10"), vec![0x4120, 0x0000]);
    assert_eq!(write(&ch, "-0.00123"), vec![0xBAA1, 0x37F4]);
    assert_eq!(read(&ch, &[0xBAA1, 0x37F4]), "-0.00123");
    let scaled = channel(with(holding(24, "float"), json!({"scale": 100})));
    assert_eq!(write(&scaled, "-0.123"), vec![0xBAA1, 0x37F4]);
    assert_eq!(read(&scaled, &[0xBAA1, 0x37F4]), "-0.123");
    assert_eq!(read(&scaled, &[0x449D, 0x8000]), "126000");
}

/// TSerialClientTest.Double64: 40BA401F7CED9168 → "6720.123", 4093B148B4395810 → "1260.321";
/// "10.9999" → 4025 FFF2 E48E 8A72; "-0.00123" → BF54 26FE 718A 86D7 (also scale 100 with
/// "-0.123"); scale 100: 4093B00000000000 reads "126000".
#[test]
fn double_read_write_and_scaled() {
    let ch = channel(holding(20, "double"));
    assert_eq!(read(&ch, &[0x40BA, 0x401F, 0x7CED, 0x9168]), "6720.123");
    assert_eq!(read(&ch, &[0x4093, 0xB148, 0xB439, 0x5810]), "1260.321");
    assert_eq!(write(&ch, "10.9999"), vec![0x4025, 0xFFF2, 0xE48E, 0x8A72]);
    assert_eq!(read(&ch, &[0x4025, 0xFFF2, 0xE48E, 0x8A72]), "10.9999");
    assert_eq!(write(&ch, "-0.00123"), vec![0xBF54, 0x26FE, 0x718A, 0x86D7]);
    assert_eq!(read(&ch, &[0xBF54, 0x26FE, 0x718A, 0x86D7]), "-0.00123");
    let scaled = channel(with(holding(24, "double"), json!({"scale": 100})));
    assert_eq!(
        write(&scaled, "-0.123"),
        vec![0xBF54, 0x26FE, 0x718A, 0x86D7]
    );
    assert_eq!(read(&scaled, &[0xBF54, 0x26FE, 0x718A, 0x86D7]), "-0.123");
    assert_eq!(read(&scaled, &[0x4093, 0xB000, 0x0000, 0x0000]), "126000");
}

/// TSerialClientTest.offset: s16 with scale 3 and offset -15: "-87" is written as 0xFFE8 (-24)
/// and reads back "-87".
#[test]
fn scale_and_offset_write_and_read() {
    let ch = channel(with(holding(24, "s16"), json!({"scale": 3, "offset": -15})));
    assert_eq!(write(&ch, "-87"), vec![0xFFE8]);
    assert_eq!(read(&ch, &[0xFFE8]), "-87");
}

/// TSerialClientTest.Round / TSerialClientIntegrationTest.Round (configs/config-test.json,
/// device RoundTest): what a float with `round_to` publishes: 12.345 shows as "12.35" (0.01),
/// "12" (1), "10" (10), "12.4" (0.2), 12.344 as "12.34" (0.01).
#[test]
fn round_to_rounds_published_float() {
    let cases = [
        (0.01, 12.345f32, "12.35"),
        (1.0, 12.345, "12"),
        (10.0, 12.345, "10"),
        (0.2, 12.345, "12.4"),
        (0.01, 12.344, "12.34"),
    ];
    for (round_to, stored, shown) in cases {
        let ch = channel(with(holding(0, "float"), json!({"round_to": round_to})));
        assert_eq!(
            read(&ch, &float_words(stored)),
            shown,
            "round_to {round_to}"
        );
    }
}

/// TSerialClientTest.Round / TSerialClientIntegrationTest.Round: the value written from `/on`
/// is rounded to `round_to` too: "12.345" puts 12.35f (0.01), 12f (1), 10f (10), 12.4f (0.2)
/// in the registers, "12.344" puts 12.34f (0.01).
#[test]
fn round_to_rounds_written_float() {
    let cases = [
        (0.01, "12.345", 12.35f32),
        (1.0, "12.345", 12.0),
        (10.0, "12.345", 10.0),
        (0.2, "12.345", 12.4),
        (0.01, "12.344", 12.34),
    ];
    for (round_to, payload, stored) in cases {
        let ch = channel(with(holding(0, "float"), json!({"round_to": round_to})));
        assert_eq!(
            write(&ch, payload),
            float_words(stored),
            "round_to {round_to}"
        );
    }
}

/// TSerialClientTest.String: format `string` holds one character per register (low byte):
/// 'H' 'e' 'l' … '!' then 0 reads "Hello, world!", 'a' 'b' 'c' 'd' reads "abcd"; "computer"
/// is written as one character per register followed by 0.
#[test]
fn string_one_char_per_register() {
    let ch = channel(with(holding(20, "string"), json!({"string_data_size": 32})));
    let mut words: Vec<u16> = "Hello, world!".bytes().map(u16::from).collect();
    words.resize(32, 0);
    assert_eq!(read(&ch, &words), "Hello, world!");
    let mut abcd: Vec<u16> = "abcd".bytes().map(u16::from).collect();
    abcd.resize(32, 0);
    assert_eq!(read(&ch, &abcd), "abcd");
    let written = write(&ch, "computer");
    let expected: Vec<u16> = "computer".bytes().map(u16::from).collect();
    assert_eq!(written[..8], expected[..]);
    assert_eq!(written[8], 0);
}

/// TModbusTest.ReadString: a 16-register `string` reads "2.4.2-rc1" whether the rest is
/// zeros, a zero then other characters, or 0xFFFF, and "2.4.2-rc12345678" when full.
#[test]
fn string_read_stops_at_zero_or_ff() {
    let ch = channel(with(
        holding(120, "string"),
        json!({"string_data_size": 16}),
    ));
    let text: Vec<u16> = "2.4.2-rc1".bytes().map(u16::from).collect();
    let mut zeros = text.clone();
    zeros.resize(16, 0);
    let mut trash = text.clone();
    trash.push(0);
    trash.resize(16, 0x31);
    let mut ff = text.clone();
    ff.resize(16, 0xFFFF);
    let full: Vec<u16> = "2.4.2-rc12345678".bytes().map(u16::from).collect();
    assert_eq!(read(&ch, &zeros), "2.4.2-rc1");
    assert_eq!(read(&ch, &trash), "2.4.2-rc1");
    assert_eq!(read(&ch, &ff), "2.4.2-rc1");
    assert_eq!(read(&ch, &full), "2.4.2-rc12345678");
}

/// TModbusTest.ReadString8: an 8-register `string8` (two characters per register, high byte
/// first) reads "2.4.2-rc1" with trailing zeros, a zero then trash (AA BB CC DD EE FF), or
/// trailing 0xFF, and "2.4.2-rc12345678" when full. Eight registers is `string_data_size` 8:
/// wb-mqtt-serial reads `string_data_size` registers of a `string8` as of a `string`
/// (`TRegisterConfig::Get16BitWidth`, `src/register.cpp`: the data width, size × 8 bits, / 8).
#[test]
fn string8_read_stops_at_zero_or_ff() {
    let ch = channel(with(
        holding(142, "string8"),
        json!({"string_data_size": 8}),
    ));
    let pack = |bytes: &[u8]| -> Vec<u16> {
        bytes
            .chunks(2)
            .map(|pair| (u16::from(pair[0]) << 8) | u16::from(pair[1]))
            .collect()
    };
    let mut zeros = b"2.4.2-rc1".to_vec();
    zeros.resize(16, 0);
    let mut trash = b"2.4.2-rc1".to_vec();
    trash.extend_from_slice(&[0, 0xAA, 0xBB, 0xCC, 0xDD, 0xEE, 0xFF]);
    let mut ff = b"2.4.2-rc1".to_vec();
    ff.resize(16, 0xFF);
    assert_eq!(read(&ch, &pack(&zeros)), "2.4.2-rc1");
    assert_eq!(read(&ch, &pack(&trash)), "2.4.2-rc1");
    assert_eq!(read(&ch, &pack(&ff)), "2.4.2-rc1");
    assert_eq!(read(&ch, &pack(b"2.4.2-rc12345678")), "2.4.2-rc12345678");
}

/// TModbusTest.WriteString has "Lateralus" to a 16-register `string` (holding_multi at 120) as
/// one 0x10 write of the 9 characters only, which leaves the end of a longer earlier text in the
/// device ("Lateralus" over "Lateralus Undertow" reads back as the longer one). rtu2mqtt writes
/// the text and zeros to the string's full size, so it reads back as written
/// (docs/migrating.md, "What differs").
#[test]
fn string_write_fills_the_whole_string() {
    let device = device_with(
        json!([{"name": "s", "reg_type": "holding_multi", "address": 120,
        "format": "string", "string_data_size": 16, "type": "text"}]),
    );
    let model = model(device);
    let list = model.write("s", "Lateralus").expect("write accepted");
    let mut expected: Vec<u16> = "Lateralus".bytes().map(u16::from).collect();
    expected.resize(16, 0);
    assert_eq!(writes(&list), vec![(120, expected, true)]);
}

/// TModbusTest.WriteString8 has "Lateralus" to an 8-register `string8` (holding_multi at 142)
/// as 5 registers (4C61 7465 7261 6C75 7300); rtu2mqtt writes the same and zeros to the 8.
#[test]
fn string8_write_fills_the_whole_string() {
    let device = device_with(
        json!([{"name": "s", "reg_type": "holding_multi", "address": 142,
        "format": "string8", "string_data_size": 8, "type": "text"}]),
    );
    let model = model(device);
    let list = model.write("s", "Lateralus").expect("write accepted");
    assert_eq!(
        writes(&list),
        vec![(
            142,
            vec![0x4C61, 0x7465, 0x7261, 0x6C75, 0x7300, 0, 0, 0],
            true
        )]
    );
}

/// A `string8` channel of `string_data_size` N reads N registers and shows up to 2N characters,
/// as wb-mqtt-serial reads it (`LoadRegisterBitsAddress` in `src/serial_config.cpp` makes the
/// width N × 8 bits; `TRegisterConfig::Get16BitWidth` in `src/register.cpp` reads that / 8
/// registers for either string format; `GetStringRegisterValue` in `src/modbus_common.cpp`
/// takes two characters from each). rtu2mqtt read N / 2 registers ("ABCD" of "ABCDEFGH"), and
/// refused a text of more than N characters.
#[test]
fn string8_reads_string_data_size_registers() {
    let device = device_with(json!([
        {"name": "s8", "reg_type": "input", "address": 100, "format": "string8",
         "string_data_size": 4, "type": "text"},
        {"name": "t", "reg_type": "holding", "address": 200, "format": "string8",
         "string_data_size": 4, "type": "text"}
    ]));
    let s8 = device.channel("s8").expect("channel");
    let read_at = s8.registers[0].read.expect("read");
    assert_eq!((read_at.address, read_at.count), (100, 4));
    let mut model = model(device);
    let out = values_read(
        &mut model,
        RegisterType::Input,
        100,
        vec![0x4142, 0x4344, 0x4546, 0x4748],
    );
    assert_eq!(
        published(&out),
        vec![("s8".to_string(), "ABCDEFGH".to_string())]
    );
    let list = model
        .write("t", "ABCDEFG")
        .expect("8 characters fit 4 registers");
    assert_eq!(
        writes(&list),
        vec![(200, vec![0x4142, 0x4344, 0x4546, 0x4700], false)]
    );
    assert!(model.write("t", "ABCDEFGHI").is_err());
}

/// `word_order: little_endian` on a string: wb-mqtt-serial reverses the words of any value
/// (`GetRegisterValue` in `src/modbus_common.cpp`) before `GetStringRegisterValue` reads the
/// characters, and reverses the words it writes (`ComposeRawMultipleWriteRequestData`), so the
/// first characters are in the last register. rtu2mqtt read and wrote strings in address order
/// whatever the word order.
#[test]
fn string_word_order_little_endian_reverses_the_registers() {
    let device = device_with(json!([
        {"name": "s8", "reg_type": "holding", "address": 200, "format": "string8",
         "string_data_size": 2, "word_order": "little_endian", "type": "text"},
        {"name": "s", "reg_type": "holding", "address": 300, "format": "string",
         "string_data_size": 3, "word_order": "little_endian", "type": "text"}
    ]));
    let s = device.channel("s").expect("channel");
    assert_eq!(read(s, &[0x43, 0x42, 0x41]), "ABC");
    let s8 = device.channel("s8").expect("channel");
    assert_eq!(read(s8, &[0x4142, 0x4344]), "CDAB");
    let model = model(device);
    let list = model.write("s8", "CDAB").expect("write accepted");
    assert_eq!(writes(&list), vec![(200, vec![0x4142, 0x4344], false)]);
    let list = model.write("s", "AB").expect("write accepted");
    assert_eq!(writes(&list), vec![(300, vec![0, 0x42, 0x41], false)]);
}

/// A `u8` whose address gives a field wider than 8 bits (`"300:0:16"`): wb-mqtt-serial prints
/// a `u8` as `Get<uint8_t>` of the field (`ConvertFromRawValue`, `src/register.cpp`: a cast),
/// its low 8 bits, and writes the value cut to 8 bits (`GetRawValue`: `& 0xff`). rtu2mqtt
/// published the whole 16-bit field (0x2010 as 8208).
#[test]
fn u8_with_a_wider_field_reads_its_low_byte() {
    let ch = channel(
        json!({"name": "v", "reg_type": "holding", "address": "300:0:16",
        "format": "u8", "type": "value"}),
    );
    assert_eq!(read(&ch, &[0x2010]), "16");
    assert_eq!(read(&ch, &[0x00FF]), "255");
    // The field is 16 bits: a write keeps nothing of the old high byte, and takes what a `u8`
    // holds (a larger value is refused, as any value outside its format).
    let words = ch.encode("200", &[Some(&[0xAB12])]).expect("fits a u8");
    assert_eq!(words, vec![vec![0x00C8]]);
    assert!(ch.encode("256", &[Some(&[0])]).is_err());
}

/// 8- and 24-bit formats are merged into their registers on a write: wb-mqtt-serial writes a
/// `u8` / `s8` / `char8` / `bcd8` over the cached register, replacing its low 8 bits only
/// (`ComposeRawSingleWriteRequestData` in `src/modbus_common.cpp`: `mask = GetLSBMask(8)`), and a
/// `u24` / `s24` / `bcd24` over its two cached registers, replacing 24 bits
/// (`ComposeNumberWriteRequestWords`: `~(GetLSBMask(GetDataWidth()) << offset)`). rtu2mqtt wrote
/// whole registers, zeroing the high byte (a second channel at `"5:8:8"`, flags, a mode).
#[test]
fn narrow_formats_keep_the_rest_of_their_registers_on_write() {
    let device = device_with(json!([
        {"name": "Low", "reg_type": "holding", "address": 5, "format": "u8", "type": "value"},
        {"name": "High", "reg_type": "holding", "address": "5:8:8", "type": "value"},
        {"name": "Char", "reg_type": "holding", "address": 6, "format": "char8", "type": "text"},
        {"name": "Signed", "reg_type": "holding", "address": 7, "format": "s8", "type": "value"},
        {"name": "Bcd", "reg_type": "holding", "address": 8, "format": "bcd8", "type": "value"},
        {"name": "Wide", "reg_type": "holding", "address": 10, "format": "u24", "type": "value"},
        {"name": "Low first", "reg_type": "holding", "address": 12, "format": "s24",
         "word_order": "little_endian", "type": "value"}
    ]));
    let mut model = model(device);
    // Before its register is read nothing is written, as for a bit field (its other bits are
    // not known yet).
    assert!(model.write("Low", "10").is_err());
    values_read(
        &mut model,
        RegisterType::Holding,
        5,
        vec![
            0x2010, 0x7700, 0x6600, 0x5500, 0, 0xAB12, 0x3456, 0xCDEF, 0x99AA,
        ],
    );
    let one = |model: &DeviceModel, control: &str, payload: &str| {
        let list = model.write(control, payload).expect("accepted");
        assert_eq!(list.len(), 1, "{list:?}");
        (
            list[0].address,
            list[0].values.clone(),
            list[0].defined.clone(),
        )
    };
    assert_eq!(one(&model, "Low", "10"), (5, vec![0x200A], vec![0x00FF]));
    assert_eq!(one(&model, "Char", "A"), (6, vec![0x7741], vec![0x00FF]));
    assert_eq!(one(&model, "Signed", "-2"), (7, vec![0x66FE], vec![0x00FF]));
    assert_eq!(one(&model, "Bcd", "42"), (8, vec![0x5542], vec![0x00FF]));
    assert_eq!(
        one(&model, "Wide", "1"),
        (10, vec![0xAB00, 0x0001], vec![0x00FF, 0xFFFF])
    );
    // Little endian: the low word first, the top byte in the second register.
    assert_eq!(
        one(&model, "Low first", "-1"),
        (12, vec![0xFFFF, 0x99FF], vec![0xFFFF, 0x00FF])
    );
}

// ---------------------------------------------------------------------------------------------
// on_value / off_value, error_value: TSerialClientIntegrationTest (configs/config-test.json)
// ---------------------------------------------------------------------------------------------

fn relay_on_off() -> ResolvedChannel {
    channel(
        json!({"name": "Relay 1", "reg_type": "holding", "address": "0x00", "type": "switch",
        "on_value": 500, "off_value": 200}),
    )
}

/// TSerialClientIntegrationTest.OnValue / OffValue: "1" on Relay 1 (on_value 500, off_value
/// 200) writes 500, "0" writes 200.
#[test]
fn on_value_and_off_value_written() {
    let ch = relay_on_off();
    assert_eq!(write(&ch, "1"), vec![500]);
    assert_eq!(write(&ch, "0"), vec![200]);
}

/// TSerialClientIntegrationTest.OnValue / OffValue (gold .dat): register 500 publishes "1",
/// 200 publishes "0".
#[test]
fn on_value_and_off_value_read() {
    let ch = relay_on_off();
    assert_eq!(read(&ch, &[500]), "1");
    assert_eq!(read(&ch, &[200]), "0");
}

/// TSerialClientIntegrationTest.ErrorValue (and its gold .dat): with `error_value` set per
/// format (0x7FFF for s16/u16, 0x7F for s8/u8, 0x7FFFFF for s24/u24, 0x7FFFFFFF for s32/u32/
/// float, 0x7FFFFFFFFFFFFFFF for s64/u64/double) the raw registers equal to it give the read
/// error `r` and no value.
#[test]
fn error_value_gives_read_error_for_every_format() {
    let cases: &[(&str, &str, &[u16])] = &[
        ("s16", "0x7FFF", &[0x7FFF]),
        ("u16", "0x7FFF", &[0x7FFF]),
        ("s8", "0x7F", &[0x7F]),
        ("u8", "0x7F", &[0x7F]),
        ("s24", "0x7FFFFF", &[0x7F, 0xFFFF]),
        ("u24", "0x7FFFFF", &[0x7F, 0xFFFF]),
        ("s32", "0x7FFFFFFF", &[0x7FFF, 0xFFFF]),
        ("u32", "0x7FFFFFFF", &[0x7FFF, 0xFFFF]),
        (
            "s64",
            "0x7FFFFFFFFFFFFFFF",
            &[0x7FFF, 0xFFFF, 0xFFFF, 0xFFFF],
        ),
        (
            "u64",
            "0x7FFFFFFFFFFFFFFF",
            &[0x7FFF, 0xFFFF, 0xFFFF, 0xFFFF],
        ),
        (
            "double",
            "0x7FFFFFFFFFFFFFFF",
            &[0x7FFF, 0xFFFF, 0xFFFF, 0xFFFF],
        ),
        ("float", "0x7FFFFFFF", &[0x7FFF, 0xFFFF]),
    ];
    for (format, error_value, words) in cases {
        let device = device_with(json!([{"name": format, "reg_type": "holding", "address": 0,
            "format": format, "error_value": error_value}]));
        let mut model = model(device);
        // First a good read (all zeros), as the test's first LoopOnce.
        let first = values_read(&mut model, RegisterType::Holding, 0, vec![0; words.len()]);
        assert_eq!(
            published(&first),
            vec![(format.to_string(), "0".to_string())],
            "{format}"
        );
        let updates = values_read(&mut model, RegisterType::Holding, 0, words.to_vec());
        assert_eq!(published(&updates), vec![], "{format}: no value published");
        assert_eq!(
            errors(&updates),
            vec![(format.to_string(), "r".to_string())],
            "{format}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Modbus: TModbusIntegrationTest (configs/config-modbus-test.json, gold .dat files)
// ---------------------------------------------------------------------------------------------

fn modbus_sample() -> ResolvedDevice {
    // The channels of wb-mqtt-serial's configs/config-modbus-test.json, shared with
    // tests/wb_parity_bus.rs.
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/wb_parity/modbus-sample-channels.json");
    let channels: Value =
        serde_json::from_str(&std::fs::read_to_string(path).expect("the fixture")).expect("JSON");
    device_with(channels)
}

/// TModbusIntegrationTest.Poll (gold .dat): holding 4…9 = 10 20 30 1 2 3 publish RGB
/// "10;20;30", White "1", RGB_All "2", White1 "3"; holding 18 = 4 publishes Voltage "4".
#[test]
fn poll_publishes_rgb_and_plain_registers() {
    let mut model = model(modbus_sample());
    let updates = values_read(
        &mut model,
        RegisterType::Holding,
        4,
        vec![10, 20, 30, 1, 2, 3],
    );
    let mut got = published(&updates);
    got.sort();
    let mut expected = vec![
        ("RGB".to_string(), "10;20;30".to_string()),
        ("White".to_string(), "1".to_string()),
        ("RGB_All".to_string(), "2".to_string()),
        ("White1".to_string(), "3".to_string()),
    ];
    expected.sort();
    assert_eq!(got, expected);
    let updates = values_read(&mut model, RegisterType::Holding, 18, vec![4]);
    assert_eq!(published(&updates), vec![("Voltage".into(), "4".into())]);
}

/// TModbusIntegrationTest.Poll (gold .dat): s64 0102 0304 0506 0708 → "72623859790382856";
/// float 0000 0015 → "2.942727e-44"; holding u16 0x15 → "21"; input u16 0x66 → "102".
#[test]
fn poll_publishes_s64_denormal_float_u16() {
    let mut model = model(modbus_sample());
    let updates = values_read(
        &mut model,
        RegisterType::Holding,
        30,
        vec![0x0102, 0x0304, 0x0506, 0x0708],
    );
    assert_eq!(
        published(&updates),
        vec![("Holding S64".into(), "72623859790382856".into())]
    );
    let updates = values_read(&mut model, RegisterType::Holding, 50, vec![0x0000, 0x0015]);
    assert_eq!(
        published(&updates),
        vec![("Holding Float".into(), "2.942727e-44".into())]
    );
    let updates = values_read(&mut model, RegisterType::Holding, 70, vec![0x15]);
    assert_eq!(
        published(&updates),
        vec![("Holding U16".into(), "21".into())]
    );
    let updates = values_read(&mut model, RegisterType::Input, 40, vec![0x66]);
    assert_eq!(
        published(&updates),
        vec![("Input U16".into(), "102".into())]
    );
}

/// TModbusIntegrationTest.Poll (gold .dat): coils 0…1 read 0b10 publish Coil 0 "0", Coil 1 "1";
/// discrete 20 read 1 publishes "1".
#[test]
fn poll_publishes_coils_and_discrete() {
    let mut model = model(modbus_sample());
    let updates = values_read(&mut model, RegisterType::Coil, 0, vec![0, 1]);
    assert_eq!(
        published(&updates),
        vec![
            ("Coil 0".to_string(), "0".to_string()),
            ("Coil 1".to_string(), "1".to_string())
        ]
    );
    let updates = values_read(&mut model, RegisterType::DiscreteInput, 20, vec![1]);
    assert_eq!(published(&updates), vec![("Discrete 0".into(), "1".into())]);
}

/// TModbusIntegrationTest.Write: Coil 0 "1" → coil 0 on; RGB "10;20;30" → holding 4, 5, 6 =
/// 10, 20, 30; Holding S64 "81985529216486895" → one write of 0123 4567 89AB CDEF at 30;
/// Holding U16 "3905" → 0x0F41 at 70; Holding U64 Multi "81985529216486895" → 0x10 of
/// 0123 4567 89AB CDEF at 95.
#[test]
fn write_coil_rgb_s64_u16_u64_multi() {
    let model = model(modbus_sample());
    assert_eq!(
        writes(&model.write("Coil 0", "1").unwrap()),
        vec![(0, vec![1], false)]
    );
    assert_eq!(
        writes(&model.write("RGB", "10;20;30").unwrap()),
        vec![
            (4, vec![10], false),
            (5, vec![20], false),
            (6, vec![30], false)
        ]
    );
    assert_eq!(
        writes(&model.write("Holding S64", "81985529216486895").unwrap()),
        vec![(30, vec![0x0123, 0x4567, 0x89AB, 0xCDEF], false)]
    );
    assert_eq!(
        writes(&model.write("Holding U16", "3905").unwrap()),
        vec![(70, vec![0x0F41], false)]
    );
    assert_eq!(
        writes(
            &model
                .write("Holding U64 Multi", "81985529216486895")
                .unwrap()
        ),
        vec![(95, vec![0x0123, 0x4567, 0x89AB, 0xCDEF], true)]
    );
}

/// TModbusTest.HoldingSingleMulti: `holding_multi` u16 0x0123 goes out as 0x10 (one register);
/// `holding_single` u16 0x0F41 as 0x06.
#[test]
fn holding_single_and_multi_functions_for_u16() {
    let model = model(modbus_sample());
    assert_eq!(
        writes(&model.write("Holding U16 Multi", "291").unwrap()),
        vec![(99, vec![0x0123], true)]
    );
    assert_eq!(
        writes(&model.write("Holding U16 Single", "3905").unwrap()),
        vec![(94, vec![0x0F41], false)]
    );
}

/// TModbusTest.HoldingSingleMulti / TModbusIntegrationTest.Write
/// (EnqueueHoldingSingleWriteU64Response): `holding_single` u64 0x0001020304050607
/// ("283686952306183") is written as four 0x06 writes, last register first: 93 = 0x0607,
/// 92 = 0x0405, 91 = 0x0203, 90 = 0x0001.
#[test]
fn holding_single_u64_writes_last_register_first() {
    let model = model(modbus_sample());
    assert_eq!(
        writes(
            &model
                .write("Holding U64 Single", "283686952306183")
                .unwrap()
        ),
        vec![
            (93, vec![0x0607], false),
            (92, vec![0x0405], false),
            (91, vec![0x0203], false),
            (90, vec![0x0001], false)
        ]
    );
}

/// The part of the previous test that agrees: the same four 0x06 writes with the same values,
/// whatever their order.
#[test]
fn holding_single_u64_is_four_single_writes() {
    let model = model(modbus_sample());
    let mut got = writes(
        &model
            .write("Holding U64 Single", "283686952306183")
            .unwrap(),
    );
    got.sort();
    assert_eq!(
        got,
        vec![
            (90, vec![0x0001], false),
            (91, vec![0x0203], false),
            (92, vec![0x0405], false),
            (93, vec![0x0607], false)
        ]
    );
}

// ---------------------------------------------------------------------------------------------
// Bit fields: TModbusBitmasksIntegrationTest (configs/config-modbus-bitmasks-test.json)
// ---------------------------------------------------------------------------------------------

fn bitmasks() -> ResolvedDevice {
    device_with_settings(
        json!([
            {"name": "U8:0:8", "reg_type": "holding", "address": "70:0:8", "type": "value", "format": "u8"},
            {"name": "U16:8", "reg_type": "holding", "address": "70:8:16", "type": "value", "format": "u16"},
            {"name": "U8:0", "reg_type": "holding", "address": "72:0:1", "type": "value", "format": "u8"},
            {"name": "U8:1", "reg_type": "holding", "address": "72:1:1", "type": "value", "format": "u8"},
            {"name": "U8:2", "reg_type": "holding", "address": "72:2:1", "type": "value", "format": "u8"}
        ]),
        json!({"max_read_registers": 1}),
    )
}

/// TModbusBitmasksIntegrationTest.Poll (gold .dat): "70:0:8" u8 reading 0x0500 → "0";
/// "70:8:16" u16 spans two registers: 0A0B 0C0D → 0x0B0C = "2828"; "72:0:1", "72:1:1",
/// "72:2:1" reading 0x0005 → "1", "0", "1".
#[test]
fn bit_fields_read() {
    let device = bitmasks();
    let spans: Vec<(u16, u16)> = device
        .channels
        .iter()
        .map(|c| {
            let read = c.registers[0].read.unwrap();
            (read.address, read.count)
        })
        .collect();
    assert_eq!(spans, vec![(70, 1), (70, 2), (72, 1), (72, 1), (72, 1)]);
    let ch = |i: usize| device.channels[i].clone();
    assert_eq!(read(&ch(0), &[0x0500]), "0");
    assert_eq!(read(&ch(1), &[0x0A0B, 0x0C0D]), "2828");
    assert_eq!(read(&ch(2), &[0x0005]), "1");
    assert_eq!(read(&ch(3), &[0x0005]), "0");
    assert_eq!(read(&ch(4), &[0x0005]), "1");
}

/// TModbusBitmasksIntegrationTest.SingleWrite (gold .dat): after holding 72 read 0x0005, "1"
/// on "U8:1" (72:1:1) writes 0x0007 to 72 with 0x06 (`01 06 00 48 00 07`).
#[test]
fn bit_field_write_keeps_other_bits() {
    let mut model = model(bitmasks());
    values_read(&mut model, RegisterType::Holding, 72, vec![0x0005]);
    assert_eq!(
        writes(&model.write("U8:1", "1").unwrap()),
        vec![(72, vec![0x0007], false)]
    );
}

// ---------------------------------------------------------------------------------------------
// Word order, events, error flags
// ---------------------------------------------------------------------------------------------

/// TSerialClientIntegrationTest.WordSwap (configs/config-test.json, device WordsLETest): u64
/// with `word_order` little_endian: "123" is written as 123 0 0 0 (lowest word first).
#[test]
fn little_endian_word_order_u64_write_and_read() {
    let ch = channel(with(
        holding(0, "u64"),
        json!({"word_order": "little_endian"}),
    ));
    assert_eq!(write(&ch, "123"), vec![123, 0, 0, 0]);
    assert_eq!(read(&ch, &[123, 0, 0, 0]), "123");
}

/// TModbusExtTest.ReadEventsWithConfirmation: an event for input register 464 (0x01D0) with
/// the 2-byte payload 04 00 carries the value 4 (little-endian payload).
#[test]
fn fast_modbus_event_payload_is_little_endian() {
    let device = device_with(json!([{"name": "In", "reg_type": "input", "address": 464,
        "format": "u16", "type": "value"}]));
    let mut model = model(device);
    let mut out = Vec::new();
    model.apply(
        PortEvent::EventValue {
            device: 0,
            register_type: RegisterType::Input,
            address: 464,
            payload: vec![0x04, 0x00],
        },
        &mut out,
    );
    model.flush_events(&mut out);
    assert_eq!(published(&out), vec![("In".into(), "4".into())]);
}

/// TSerialClientIntegrationTest.Errors (gold .dat): a failed read of White sets meta/error
/// "r"; a failed write on top of it makes "rw"; the next good read leaves "w" and publishes
/// the value read.
#[test]
fn error_flags_r_then_rw_then_w() {
    let device = device_with(
        json!([{"name": "White", "reg_type": "holding", "address": 7,
        "type": "dimmer", "max": "0xff"}]),
    );
    let mut model = model(device);
    let mut out = Vec::new();
    model.apply(
        PortEvent::ReadFailed {
            device: 0,
            span: RegisterSpan::new(RegisterType::Holding, 7, 1),
            unsupported: false,
        },
        &mut out,
    );
    assert_eq!(errors(&out), vec![("White".into(), "r".into())]);
    let mut out = Vec::new();
    model.apply(
        PortEvent::WriteFailed {
            device: 0,
            register_type: RegisterType::Holding,
            address: 7,
            permanent: false,
        },
        &mut out,
    );
    assert_eq!(errors(&out), vec![("White".into(), "rw".into())]);
    let out = values_read(&mut model, RegisterType::Holding, 7, vec![0]);
    assert_eq!(errors(&out), vec![("White".into(), "w".into())]);
    assert_eq!(published(&out), vec![("White".into(), "0".into())]);
}

/// TModbusTest.WriteHoldingRegiterWithWriteAddress: a u16 read at 110 with `write_address`
/// 115 writes 0x119C to 115 (`06 00 73 11 9C`).
#[test]
fn write_address_takes_the_write() {
    let device = device_with(json!([{"name": "A", "reg_type": "holding", "address": 110,
        "write_address": 115, "format": "u16", "type": "value"}]));
    let model = model(device);
    assert_eq!(
        writes(&model.write("A", "4508").unwrap()),
        vec![(115, vec![0x119C], false)]
    );
}

/// TModbusTest.ReadHoldingRegiterWithOffsetWriteOptions / WriteHoldingRegiterWithOffsetWriteOptions:
/// a 3-bit field at bit 2 of holding 111 (write address 116): 0x0014 at 111 reads 5, and 5 is
/// written to 116 as 0x0014 (`06 00 74 00 14`), the other bits 0 as nothing is known of 116.
#[test]
fn bit_field_with_write_address_written_over_zeros() {
    let device = device_with(
        json!([{"name": "B", "reg_type": "holding", "address": "111:2:3",
        "write_address": "116:2:3", "format": "u16", "type": "value"}]),
    );
    let mut model = model(device);
    let out = values_read(&mut model, RegisterType::Holding, 111, vec![0x0014]);
    assert_eq!(published(&out), vec![("B".into(), "5".into())]);
    assert_eq!(
        writes(&model.write("B", "5").expect("write accepted")),
        vec![(116, vec![0x0014], false)]
    );
}

/// What wb-mqtt-serial's register cache gives the test above beyond one write: a second field of
/// the same write-only register goes over the first field's bits as written, not over zeros.
/// And a field in a register that is read waits for the read (wb-mqtt-serial would write
/// zeros over the unread bits; rtu2mqtt refuses until it knows them).
#[test]
fn bit_fields_of_a_write_only_register_keep_each_other() {
    let device = device_with(json!([
        {"name": "Low", "reg_type": "holding", "address": "111:2:3",
         "write_address": "116:2:3", "format": "u16", "type": "value"},
        {"name": "High", "reg_type": "holding", "address": "112:8:2",
         "write_address": "116:8:2", "format": "u16", "type": "value"},
        {"name": "Shared", "reg_type": "holding", "address": "120:4:4", "format": "u16",
         "type": "value"}
    ]));
    let mut model = model(device);
    let first = model.write("Low", "5").expect("write accepted");
    assert_eq!(writes(&first), vec![(116, vec![0x0014], false)]);
    // The scheduler hands a done write back as its words (`PortScheduler`'s `WriteDone`).
    values_read(&mut model, RegisterType::Holding, 116, vec![0x0014]);
    assert_eq!(
        writes(&model.write("High", "3").expect("write accepted")),
        vec![(116, vec![0x0314], false)]
    );
    assert!(
        model.write("Shared", "1").is_err(),
        "120 is read: its other bits first"
    );
    values_read(&mut model, RegisterType::Holding, 120, vec![0xF00F]);
    assert_eq!(
        writes(&model.write("Shared", "1").expect("write accepted")),
        vec![(120, vec![0xF01F], false)]
    );
}

/// Setup items are written as wb-mqtt-serial writes them on connect (`WriteSetupRegisters`:
/// each through its register cache): a bit field goes over what the items before it wrote to
/// the register, so two fields of one register both hold, and a field after a whole-register
/// item keeps that item's other bits.
#[test]
fn bit_field_setup_items_of_one_register_keep_each_other() {
    let device = device_with_settings(
        json!([holding(100, "u16")]),
        json!({"setup": [
            {"title": "low", "address": "100:0:4", "value": 3},
            {"title": "high", "address": "100:4:4", "value": 5},
            {"title": "word", "address": 101, "value": 4660},
            {"title": "bit", "address": "101:15:1", "value": 1}
        ]}),
    );
    let words: Vec<(u16, Vec<u16>)> = device
        .setup
        .iter()
        .map(|item| (item.register.address, item.words.clone()))
        .collect();
    assert_eq!(
        words,
        vec![
            (100, vec![0x0003]),
            (100, vec![0x0053]),
            (101, vec![0x1234]),
            (101, vec![0x9234]),
        ]
    );
    // The bits no item so far defines: on a reconnect they come from the register's last
    // read, as from wb-mqtt-serial's cache (the scheduler's `setup_words`).
    let kept: Vec<Vec<u16>> = device.setup.iter().map(|i| i.kept_bits.clone()).collect();
    assert_eq!(kept, vec![vec![0xFFF0], vec![0xFF00], vec![], vec![]]);
}
