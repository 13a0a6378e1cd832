use super::*;

fn codec(format: RegisterFormat) -> ValueCodec {
    ValueCodec::plain(format)
}

fn ordered(format: RegisterFormat, word_order: WordOrder, byte_order: ByteOrder) -> ValueCodec {
    ValueCodec {
        word_order,
        byte_order,
        ..codec(format)
    }
}

fn value(reading: Reading) -> String {
    match reading {
        Reading::Value(text) => text,
        other => panic!("expected a value, got {other:?}"),
    }
}

/// Words as the device sends them, from the big-endian word list, for a word/byte order.
fn arrange(be_words: &[u16], word_order: WordOrder, byte_order: ByteOrder) -> Vec<u16> {
    let mut words: Vec<u16> = be_words.to_vec();
    if byte_order == ByteOrder::LittleEndian {
        words.iter_mut().for_each(|w| *w = w.swap_bytes());
    }
    if word_order == WordOrder::LittleEndian {
        words.reverse();
    }
    words
}

/// (format, big-endian words, published text): one known pattern per numeric format.
fn known_patterns() -> Vec<(RegisterFormat, Vec<u16>, &'static str)> {
    use RegisterFormat::*;
    vec![
        (U8, vec![0x00FE], "254"),
        (S8, vec![0x00FE], "-2"),
        (U16, vec![0xFFFE], "65534"),
        (S16, vec![0xFFFE], "-2"),
        (U24, vec![0x0012, 0x3456], "1193046"),
        (S24, vec![0x00FF, 0xFFFE], "-2"),
        (U32, vec![0x1234, 0x5678], "305419896"),
        (S32, vec![0xFFFF, 0xFFFF], "-1"),
        (
            U64,
            vec![0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE],
            "18446744073709551614",
        ),
        (S64, vec![0xFFFF, 0xFFFF, 0xFFFF, 0xFF85], "-123"),
        (Float, vec![0x4366, 0x8000], "230.5"),
        (Double, vec![0x406C, 0xD000, 0x0000, 0x0000], "230.5"),
        (Char8, vec![0x0041], "A"),
        (Bcd8, vec![0x0042], "42"),
        (Bcd16, vec![0x1234], "1234"),
        (Bcd24, vec![0x0012, 0x3456], "123456"),
        (Bcd32, vec![0x1234, 0x5678], "12345678"),
    ]
}

#[test]
fn every_numeric_format_in_every_word_and_byte_order() {
    let orders = [
        (WordOrder::BigEndian, ByteOrder::BigEndian),
        (WordOrder::BigEndian, ByteOrder::LittleEndian),
        (WordOrder::LittleEndian, ByteOrder::BigEndian),
        (WordOrder::LittleEndian, ByteOrder::LittleEndian),
    ];
    for (format, be_words, text) in known_patterns() {
        for (word_order, byte_order) in orders {
            let codec = ordered(format, word_order, byte_order);
            let wire = arrange(&be_words, word_order, byte_order);
            let label = format!("{} {word_order:?} {byte_order:?}", format.name());
            assert_eq!(value(codec.decode(&wire).unwrap()), text, "decode {label}");
            let written = codec.encode(text, Some(&wire)).unwrap();
            assert_eq!(
                codec.decode(&written).unwrap(),
                Reading::Value(text.to_string()),
                "round trip {label}"
            );
            if !codec.is_partial() {
                assert_eq!(written, wire, "encode {label}");
            }
        }
    }
}

#[test]
fn float_230_5_in_both_word_orders() {
    let big = ordered(
        RegisterFormat::Float,
        WordOrder::BigEndian,
        ByteOrder::BigEndian,
    );
    assert_eq!(value(big.decode(&[0x4366, 0x8000]).unwrap()), "230.5");
    assert_eq!(big.encode("230.5", None).unwrap(), vec![0x4366, 0x8000]);
    let little = ordered(
        RegisterFormat::Float,
        WordOrder::LittleEndian,
        ByteOrder::BigEndian,
    );
    assert_eq!(value(little.decode(&[0x8000, 0x4366]).unwrap()), "230.5");
    assert_eq!(little.encode("230.5", None).unwrap(), vec![0x8000, 0x4366]);
    let swapped = ordered(
        RegisterFormat::Float,
        WordOrder::BigEndian,
        ByteOrder::LittleEndian,
    );
    assert_eq!(swapped.encode("230.5", None).unwrap(), vec![0x6643, 0x0080]);
}

#[test]
fn float_prints_seven_significant_digits() {
    // 234.607 is not exact in float32; wb-mqtt-serial prints it with %.7g.
    let bits = 234.607f32.to_bits();
    let codec = codec(RegisterFormat::Float);
    assert_eq!(
        value(codec.decode(&[(bits >> 16) as u16, bits as u16]).unwrap()),
        "234.607"
    );
}

#[test]
fn scaled_float_prints_seven_significant_digits() {
    // wb-mqtt-serial's `ToScaledTextValue<float>` prints %.7g after scale and offset too.
    let bits = 1.1f32.to_bits();
    let words = [(bits >> 16) as u16, bits as u16];
    let scaled = ValueCodec {
        scale: 10.0,
        ..codec(RegisterFormat::Float)
    };
    assert_eq!(value(scaled.decode(&words).unwrap()), "11");
    let bits = 123456.7f32.to_bits();
    let kilo = ValueCodec {
        scale: 0.001,
        ..codec(RegisterFormat::Float)
    };
    assert_eq!(
        value(kilo.decode(&[(bits >> 16) as u16, bits as u16]).unwrap()),
        "123.4567"
    );
    // A double keeps 15.
    let double = ValueCodec {
        scale: 0.1,
        ..codec(RegisterFormat::Double)
    };
    let bits = 1.0f64.to_bits();
    let words: Vec<u16> = (0..4).rev().map(|i| (bits >> (16 * i)) as u16).collect();
    assert_eq!(value(double.decode(&words).unwrap()), "0.1");
}

#[test]
fn scale_offset_and_round_to() {
    let temperature = ValueCodec {
        scale: 0.01,
        ..codec(RegisterFormat::S16)
    };
    assert_eq!(value(temperature.decode(&[2345]).unwrap()), "23.45");
    assert_eq!(
        value(temperature.decode(&[(-1234i16) as u16]).unwrap()),
        "-12.34"
    );
    assert_eq!(
        temperature.encode("-12.34", None).unwrap(),
        vec![(-1234i16) as u16]
    );

    let rounded = ValueCodec {
        scale: 1.52588e-07,
        round_to: 0.001,
        ..codec(RegisterFormat::U32)
    };
    // 230.123 V as the WB-MAP3E reports Urms.
    let raw = (230.123f64 / 1.52588e-07).round() as u32;
    assert_eq!(
        value(rounded.decode(&[(raw >> 16) as u16, raw as u16]).unwrap()),
        "230.123"
    );

    let offset = ValueCodec {
        offset: -4261412864.0,
        ..codec(RegisterFormat::U32)
    };
    assert_eq!(value(offset.decode(&[0xFE00, 0x1234]).unwrap()), "4660");

    let step = ValueCodec {
        round_to: 0.5,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(step.decode(&[7]).unwrap()), "7");
    let step = ValueCodec {
        scale: 0.1,
        round_to: 0.5,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(step.decode(&[27]).unwrap()), "2.5");
}

#[test]
fn integers_without_scale_print_exactly() {
    let counter = codec(RegisterFormat::U64);
    let words = [0x0123, 0x4567, 0x89AB, 0xCDEF];
    assert_eq!(value(counter.decode(&words).unwrap()), "81985529216486895");
    assert_eq!(
        counter.encode("81985529216486895", None).unwrap(),
        words.to_vec()
    );
}

#[test]
fn bit_fields_read_and_merge_on_write() {
    let field = ValueCodec {
        bit_shift: 4,
        bit_width: 1,
        ..codec(RegisterFormat::U8)
    };
    assert!(field.is_partial());
    assert_eq!(value(field.decode(&[0b1_0000]).unwrap()), "1");
    assert_eq!(value(field.decode(&[0b0_1111]).unwrap()), "0");
    assert_eq!(field.encode("1", Some(&[0x0F0F])).unwrap(), vec![0x0F1F]);
    assert_eq!(field.encode("0", Some(&[0xFFFF])).unwrap(), vec![0xFFEF]);
    assert_eq!(field.encode("1", None), Err(CodecError::NeedsCurrentWords));
    assert!(matches!(
        field.encode("2", Some(&[0])),
        Err(CodecError::OutOfRange { .. })
    ));

    let nibble = ValueCodec {
        bit_shift: 8,
        bit_width: 4,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(nibble.decode(&[0x0A00]).unwrap()), "10");
    let low_byte = codec(RegisterFormat::U8);
    assert_eq!(value(low_byte.decode(&[0xAB12]).unwrap()), "18");
}

/// 8- and 24-bit formats do not fill their registers: a write replaces the format's bits and
/// keeps the others, as wb-mqtt-serial merges them into its register cache
/// (`ComposeRawSingleWriteRequestData`, `ComposeNumberWriteRequestWords`).
#[test]
fn narrow_formats_merge_into_their_registers() {
    for format in [
        RegisterFormat::U8,
        RegisterFormat::S8,
        RegisterFormat::Char8,
        RegisterFormat::Bcd8,
    ] {
        let narrow = codec(format);
        assert!(narrow.is_partial(), "{}", format.name());
        assert_eq!(narrow.field_mask_words(), vec![0x00FF], "{}", format.name());
        assert_eq!(narrow.encode("1", None), Err(CodecError::NeedsCurrentWords));
    }
    assert_eq!(
        codec(RegisterFormat::U8)
            .encode("10", Some(&[0x2010]))
            .unwrap(),
        vec![0x200A]
    );
    assert_eq!(
        codec(RegisterFormat::S8)
            .encode("-2", Some(&[0x7F00]))
            .unwrap(),
        vec![0x7FFE]
    );
    for format in [
        RegisterFormat::U24,
        RegisterFormat::S24,
        RegisterFormat::Bcd24,
    ] {
        let wide = codec(format);
        assert!(wide.is_partial(), "{}", format.name());
        assert_eq!(
            wide.field_mask_words(),
            vec![0x00FF, 0xFFFF],
            "{}",
            format.name()
        );
    }
    assert_eq!(
        codec(RegisterFormat::U24)
            .encode("1", Some(&[0xAB12, 0x3456]))
            .unwrap(),
        vec![0xAB00, 0x0001]
    );
    let low_first = ValueCodec {
        word_order: WordOrder::LittleEndian,
        ..codec(RegisterFormat::U24)
    };
    assert_eq!(
        low_first.encode("1", Some(&[0x3456, 0xAB12])).unwrap(),
        vec![0x0001, 0xAB00]
    );
    for format in [
        RegisterFormat::U16,
        RegisterFormat::S16,
        RegisterFormat::U32,
        RegisterFormat::Float,
        RegisterFormat::U64,
        RegisterFormat::Double,
    ] {
        assert!(!codec(format).is_partial(), "{}", format.name());
    }
    // A field wider than a `u8` reads as the `u8` it is (wb-mqtt-serial's `Get<uint8_t>`).
    let wide_u8 = ValueCodec {
        bit_width: 16,
        ..codec(RegisterFormat::U8)
    };
    assert_eq!(value(wide_u8.decode(&[0x2010]).unwrap()), "16");
}

#[test]
fn narrow_signed_field_takes_its_sign_from_the_format() {
    // wb-mqtt-serial cuts the field out unsigned and converts it as the format's whole width
    // (`Get<int16_t>`), so a 4-bit `s16` field never reads negative.
    let nibble = ValueCodec {
        bit_shift: 0,
        bit_width: 4,
        ..codec(RegisterFormat::S16)
    };
    assert_eq!(value(nibble.decode(&[0x000F]).unwrap()), "15");
    assert_eq!(value(nibble.decode(&[0xFFF8]).unwrap()), "8");
    // What it shows can be written back; -1 is still written as its two's complement.
    assert_eq!(nibble.encode("15", Some(&[0xFFF0])).unwrap(), vec![0xFFFF]);
    assert_eq!(nibble.encode("-1", Some(&[0])).unwrap(), vec![0x000F]);
    assert!(nibble.encode("16", Some(&[0])).is_err());
    // A field as wide as the format keeps its sign; `s8` takes the low byte of a wider field.
    let byte = ValueCodec {
        bit_shift: 8,
        bit_width: 8,
        ..codec(RegisterFormat::S8)
    };
    assert_eq!(value(byte.decode(&[0xFF00]).unwrap()), "-1");
    let wide = ValueCodec {
        bit_width: 16,
        ..codec(RegisterFormat::S8)
    };
    assert_eq!(value(wide.decode(&[0x01FF]).unwrap()), "-1");
}

#[test]
fn inverted_on_off_values_on_a_bit_field() {
    // ONOKOM "Timer: Heater": 55:3:1 with on_value 0, off_value 1.
    let heater = ValueCodec {
        bit_shift: 3,
        bit_width: 1,
        on_value: Some(0),
        off_value: Some(1),
        ..codec(RegisterFormat::U8)
    };
    assert_eq!(value(heater.decode(&[0b1000]).unwrap()), "0");
    assert_eq!(value(heater.decode(&[0]).unwrap()), "1");
    assert_eq!(heater.encode("1", Some(&[0xFFFF])).unwrap(), vec![0xFFF7]);
}

#[test]
fn on_off_values_on_whole_registers() {
    let switch = ValueCodec {
        on_value: Some(0xFF),
        off_value: Some(0x10),
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(switch.decode(&[0xFF]).unwrap()), "1");
    assert_eq!(value(switch.decode(&[0x10]).unwrap()), "0");
    assert_eq!(value(switch.decode(&[5]).unwrap()), "5");
    assert_eq!(switch.encode("1", None).unwrap(), vec![0xFF]);
    assert_eq!(switch.encode("0", None).unwrap(), vec![0x10]);
}

/// wb-mqtt-serial (`TDeviceChannel::GetTextValue`, `TSerialPortDriver::SetValueToChannel`)
/// compares the published text with the decimal `on_value` and writes `on_value` as a value
/// text, through scale and offset.
#[test]
fn on_off_values_are_in_the_channels_units() {
    // Scale 0.1: on_value 10 is raw 100 on the wire.
    let scaled = ValueCodec {
        scale: 0.1,
        on_value: Some(10),
        off_value: Some(0),
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(scaled.decode(&[100]).unwrap()), "1");
    assert_eq!(value(scaled.decode(&[10]).unwrap()), "1");
    assert_eq!(value(scaled.decode(&[0]).unwrap()), "0");
    assert_eq!(value(scaled.decode(&[105]).unwrap()), "10.5");
    assert_eq!(scaled.encode("1", None).unwrap(), vec![100]);
    assert_eq!(scaled.encode("0", None).unwrap(), vec![0]);
    assert_eq!(scaled.encode("2", None).unwrap(), vec![20]);

    // Scale -1, offset 1 (an inverted status): on_value 1 is raw 0.
    let inverted = ValueCodec {
        scale: -1.0,
        offset: 1.0,
        on_value: Some(1),
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(value(inverted.decode(&[0]).unwrap()), "1");
    assert_eq!(inverted.encode("1", None).unwrap(), vec![0]);

    // s16 with on_value 65535: the read is "-1" and never matches; the write is 0xFFFF.
    let signed = ValueCodec {
        on_value: Some(0xFFFF),
        off_value: Some(0),
        ..codec(RegisterFormat::S16)
    };
    assert_eq!(value(signed.decode(&[0xFFFF]).unwrap()), "-1");
    assert_eq!(value(signed.decode(&[0]).unwrap()), "0");
    assert_eq!(signed.encode("1", None).unwrap(), vec![0xFFFF]);
    // … while an ordinary value keeps its range check.
    assert!(signed.encode("65535", None).is_err());

    // Only the exact decimal text matches, as C++'s `std::to_string` prints the number.
    assert!(is_decimal_text_of("10", 10) && is_decimal_text_of("-3", -3));
    for text in ["10.0", "1e1", "010", "+10", "-0", ""] {
        assert!(
            !is_decimal_text_of(text, if text == "-0" { 0 } else { 10 }),
            "{text}"
        );
    }

    // A coil with scale and offset: "1" written as on_value 2 through offset 2 is 0, off.
    let coil = ValueCodec {
        offset: 2.0,
        on_value: Some(2),
        ..ValueCodec::bit()
    };
    assert_eq!(value(coil.decode(&[0]).unwrap()), "1");
    assert_eq!(coil.encode("1", None).unwrap(), vec![0]);
    assert_eq!(coil.encode("3", None).unwrap(), vec![1]);

    // An on_value wider than a 1-bit field is cut to it, as wb-mqtt-serial masks the write;
    // the read (0 or 1) never matches it.
    let bit_field = ValueCodec {
        bit_shift: 2,
        bit_width: 1,
        on_value: Some(3),
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(bit_field.encode("1", Some(&[0])).unwrap(), vec![0b100]);
    assert_eq!(value(bit_field.decode(&[0b100]).unwrap()), "1");
}

#[test]
fn error_and_unsupported_values_are_compared_raw() {
    let temperature = ValueCodec {
        scale: 0.01,
        error_value: Some(0x7FFF),
        ..codec(RegisterFormat::S16)
    };
    assert_eq!(temperature.decode(&[0x7FFF]).unwrap(), Reading::DeviceError);
    let peak = ValueCodec {
        word_order: WordOrder::LittleEndian,
        unsupported_value: Some(0xFFFE_FFFE),
        error_value: Some(0x7FFF_FFFF),
        ..codec(RegisterFormat::S32)
    };
    assert_eq!(
        peak.decode(&[0xFFFE, 0xFFFE]).unwrap(),
        Reading::Unsupported
    );
    assert_eq!(
        peak.decode(&[0xFFFF, 0x7FFF]).unwrap(),
        Reading::DeviceError
    );
    assert_eq!(value(peak.decode(&[0xFFFF, 0xFFFF]).unwrap()), "-1");
}

#[test]
fn bcd_rejects_bad_nibbles_and_out_of_range_writes() {
    let bcd = codec(RegisterFormat::Bcd16);
    assert_eq!(bcd.decode(&[0x12A4]), Err(CodecError::InvalidBcd(0x12A4)));
    assert_eq!(bcd.encode("59", None).unwrap(), vec![0x0059]);
    assert!(matches!(
        bcd.encode("10000", None),
        Err(CodecError::OutOfRange { .. })
    ));
    assert!(matches!(
        bcd.encode("-1", None),
        Err(CodecError::OutOfRange { .. })
    ));
}

#[test]
fn strings_one_and_two_characters_per_register() {
    let one = ValueCodec {
        word_count: 6,
        ..codec(RegisterFormat::String)
    };
    let words = [0x0034, 0x002E, 0x0033, 0x0036, 0x0000, 0x0041];
    assert_eq!(value(one.decode(&words).unwrap()), "4.36");
    assert_eq!(
        one.encode("4.36", None).unwrap(),
        vec![0x34, 0x2E, 0x33, 0x36, 0, 0]
    );

    let two = ValueCodec {
        word_count: 3,
        ..codec(RegisterFormat::String8)
    };
    assert_eq!(
        value(two.decode(&[0x5742, 0x2D4D, 0x5200]).unwrap()),
        "WB-MR"
    );
    assert_eq!(value(two.decode(&[0x4142, 0xFFFF, 0x4344]).unwrap()), "AB");
    assert_eq!(
        two.encode("WB-MR", None).unwrap(),
        vec![0x5742, 0x2D4D, 0x5200]
    );
    assert!(matches!(
        two.encode("1234567", None),
        Err(CodecError::StringTooLong { .. })
    ));

    let swapped = ValueCodec {
        byte_order: ByteOrder::LittleEndian,
        ..two
    };
    assert_eq!(
        value(swapped.decode(&[0x4257, 0x4D2D, 0x0052]).unwrap()),
        "WB-MR"
    );
}

/// A char8 read shows the byte as the character of that code point; writing back what was
/// read must give the same byte, never the first byte of its UTF-8 form.
#[test]
fn char8_writes_back_the_byte_it_read() {
    let char8 = codec(RegisterFormat::Char8);
    for byte in [0x41u16, 0x20, 0x7F, 0x80, 0xE9, 0xFF] {
        let text = value(char8.decode(&[byte]).unwrap());
        assert_eq!(
            char8.encode(&text, Some(&[0])).unwrap(),
            vec![byte],
            "{text:?}"
        );
    }
    assert_eq!(char8.encode("é", Some(&[0])).unwrap(), vec![0xE9]);
    assert_eq!(char8.encode("AB", Some(&[0])).unwrap(), vec![0x41]);
    assert_eq!(char8.encode(" ", Some(&[0])).unwrap(), vec![0x20]);
    assert!(matches!(
        char8.encode("Ж", Some(&[0])),
        Err(CodecError::NotOneByteCharacter(_))
    ));
}

#[test]
fn writes_check_the_format_range() {
    let cases: &[(RegisterFormat, &str, bool)] = &[
        (RegisterFormat::U16, "65535", true),
        (RegisterFormat::U16, "65536", false),
        // Negative values on unsigned formats are written as two's complement, as by
        // wb-mqtt-serial; below the signed minimum of the width they are refused.
        (RegisterFormat::U16, "-1", true),
        (RegisterFormat::U16, "-32768", true),
        (RegisterFormat::U16, "-32769", false),
        (RegisterFormat::S16, "-32768", true),
        (RegisterFormat::S16, "32768", false),
        (RegisterFormat::U8, "256", false),
        (RegisterFormat::S8, "-128", true),
        (RegisterFormat::U32, "4294967295", true),
        (RegisterFormat::U32, "4294967296", false),
        (RegisterFormat::S64, "-9223372036854775808", true),
        (RegisterFormat::U64, "18446744073709551616", false),
        (RegisterFormat::Float, "1e39", false),
    ];
    for (format, text, ok) in cases {
        let codec = codec(*format);
        let zeros = vec![0; codec.word_count as usize];
        let result = codec.encode(text, Some(&zeros));
        assert_eq!(result.is_ok(), *ok, "{} {text}: {result:?}", format.name());
    }
    let err = codec(RegisterFormat::U16)
        .encode("70000", None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("-32768 … 65535"), "{err}");
    assert_eq!(
        codec(RegisterFormat::U16).encode("-1", None).unwrap(),
        vec![0xFFFF]
    );
    assert_eq!(
        codec(RegisterFormat::U8)
            .encode("-1", Some(&[0xAB00]))
            .unwrap(),
        vec![0xABFF]
    );
    assert_eq!(
        codec(RegisterFormat::U16).encode("abc", None),
        Err(CodecError::NotANumber("abc".into()))
    );
}

#[test]
fn scaled_writes_round_to_the_nearest_raw_value() {
    let power = ValueCodec {
        scale: 0.1,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(power.encode("12.34", None).unwrap(), vec![123]);
    assert_eq!(power.encode("0x10", None).unwrap(), vec![160]);
    let offset = ValueCodec {
        offset: -40.0,
        scale: 0.5,
        ..codec(RegisterFormat::U8)
    };
    assert_eq!(offset.encode("-20", Some(&[0])).unwrap(), vec![40]);
    assert!(offset.encode("200", Some(&[0])).is_err());
    // Danfoss EKC 204A1's r36: `u16`, scale 0.1, -15 … -3 °C; -15 is raw -150.
    let differential = ValueCodec {
        scale: 0.1,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(differential.encode("-15", None).unwrap(), vec![0xFF6A]);
    assert_eq!(differential.encode("-3.5", None).unwrap(), vec![0xFFDD]);
}

/// `round_to` applies to what is written too, before scale and offset are undone, as in
/// wb-mqtt-serial (`TSerialClientTest.Round`): to every text on a float or double format, and
/// to a fraction on an integer format (its integer texts take wb-mqtt-serial's integer path).
#[test]
fn written_values_are_rounded_to_round_to() {
    let float = ValueCodec {
        round_to: 0.01,
        ..codec(RegisterFormat::Float)
    };
    assert_eq!(float.encode("12.345", None).unwrap(), vec![0x4145, 0x999A]);
    assert_eq!(
        float.encode("12.344", None).unwrap(),
        float.encode("12.34", None).unwrap()
    );
    let tens = ValueCodec {
        round_to: 10.0,
        ..codec(RegisterFormat::Double)
    };
    assert_eq!(
        tens.encode("12.345", None).unwrap(),
        tens.encode("10", None).unwrap()
    );
    let half = ValueCodec {
        scale: 0.1,
        round_to: 0.5,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(half.encode("2.7", None).unwrap(), vec![25]);
    assert_eq!(half.encode("2.8", None).unwrap(), vec![30]);
    assert_eq!(half.encode("3", None).unwrap(), vec![30]);
    let steps = ValueCodec {
        round_to: 10.0,
        ..codec(RegisterFormat::U16)
    };
    assert_eq!(steps.encode("12", None).unwrap(), vec![12]);
    assert_eq!(steps.encode("12.0", None).unwrap(), vec![10]);
}

/// A float or double that is not finite, as given or once scale and offset are undone, is
/// refused: no infinity or NaN reaches the device for a text that asked for a number.
#[test]
fn non_finite_float_writes_are_refused() {
    for format in [RegisterFormat::Float, RegisterFormat::Double] {
        let plain = codec(format);
        for text in ["nan", "NaN", "inf", "-inf", "infinity", "1e400"] {
            assert!(
                plain.encode(text, None).is_err(),
                "{} {text}",
                format.name()
            );
        }
        let tiny_scale = ValueCodec {
            scale: 1e-10,
            ..codec(format)
        };
        assert!(
            tiny_scale.encode("1e300", None).is_err(),
            "{} 1e300 / 1e-10",
            format.name()
        );
        assert!(tiny_scale.encode("1", None).is_ok(), "{}", format.name());
    }
}

#[test]
fn coils_are_single_bits() {
    let coil = ValueCodec::bit();
    assert_eq!(value(coil.decode(&[1]).unwrap()), "1");
    assert_eq!(value(coil.decode(&[0]).unwrap()), "0");
    assert_eq!(coil.encode("1", None).unwrap(), vec![1]);
    assert_eq!(coil.encode("0", None).unwrap(), vec![0]);
    assert_eq!(
        coil.decode(&[]),
        Err(CodecError::WordCount {
            expected: 1,
            got: 0
        })
    );
}

#[test]
fn wrong_word_counts_are_errors_not_panics() {
    for format in RegisterFormat::ALL {
        let codec = codec(format);
        let too_many = vec![0u16; codec.word_count as usize + 1];
        assert!(codec.decode(&too_many).is_err(), "{}", format.name());
        assert!(codec.decode(&[]).is_err(), "{}", format.name());
    }
}

mod properties {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn decoding_never_panics_nor_gives_an_empty_number(words in proptest::collection::vec(any::<u16>(), 0..6), shift in 0u32..70, width in 0u32..70, fmt in 0usize..19) {
            let format = RegisterFormat::ALL[fmt];
            let codec = ValueCodec { bit_shift: shift, bit_width: width, word_count: words.len() as u32, ..ValueCodec::plain(format) };
            // An empty retained payload would delete the value on the broker.
            let textual = matches!(format, RegisterFormat::String | RegisterFormat::String8 | RegisterFormat::Char8);
            if let Ok(Reading::Value(text)) = codec.decode(&words) {
                prop_assert!(textual || !text.is_empty(), "{} gave an empty value", format.name());
            }
            let _ = codec.encode("12", Some(&words));
        }

        /// Whatever the payload and the register layout, a write is words or a refusal: the
        /// words are as many as the registers, and a bit field's write changes no other bit.
        #[test]
        fn encoding_never_panics_and_keeps_the_other_bits(
            text in prop_oneof![
                "[-+0-9.eExXa-fA-F ]{0,24}",
                Just("nan".to_string()),
                Just("-0".to_string()),
                Just("1e400".to_string()),
                Just("18446744073709551616".to_string()),
            ],
            current in proptest::collection::vec(any::<u16>(), 4),
            shift in 0u32..64, width in 0u32..65, fmt in 0usize..19,
            scale in prop_oneof![Just(1.0), Just(0.1), Just(-3.0), Just(0.0), Just(1e-300)],
            round_to in prop_oneof![Just(0.0), Just(0.5), Just(1e-300)],
            little_words in any::<bool>(), little_bytes in any::<bool>(),
        ) {
            let format = RegisterFormat::ALL[fmt];
            // A field within 64 bits, as the resolver allows.
            let width = width % (65 - shift);
            let count = format.registers().max((shift + width).div_ceil(16)).clamp(1, 4);
            let codec = ValueCodec {
                bit_shift: shift,
                bit_width: if width == 0 { format.value_bits() } else { width },
                word_count: count,
                scale,
                round_to,
                word_order: if little_words { WordOrder::LittleEndian } else { WordOrder::BigEndian },
                byte_order: if little_bytes { ByteOrder::LittleEndian } else { ByteOrder::BigEndian },
                ..ValueCodec::plain(format)
            };
            let current = &current[..count as usize];
            if let Ok(words) = codec.encode(&text, Some(current)) {
                prop_assert_eq!(words.len(), count as usize);
                if codec.is_partial() {
                    for ((word, old), mask) in words.iter().zip(current).zip(codec.field_mask_words()) {
                        prop_assert_eq!(word & !mask, old & !mask);
                    }
                }
            }
        }

        #[test]
        fn integer_round_trip(raw in any::<u32>(), little_words in any::<bool>(), little_bytes in any::<bool>()) {
            let codec = ValueCodec {
                word_order: if little_words { WordOrder::LittleEndian } else { WordOrder::BigEndian },
                byte_order: if little_bytes { ByteOrder::LittleEndian } else { ByteOrder::BigEndian },
                ..ValueCodec::plain(RegisterFormat::U32)
            };
            let words = codec.encode(&raw.to_string(), None).unwrap();
            prop_assert_eq!(codec.decode(&words).unwrap(), Reading::Value(raw.to_string()));
        }
    }
}
