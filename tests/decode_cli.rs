//! `rtu2mqtt decode`: explains a frame and exits 0, or says what the CRC would be and exits 1.

use std::process::Command;

fn decode(hex: &str) -> (bool, String) {
    let output = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .arg("decode")
        .args(hex.split(' '))
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8(output.stdout).unwrap(),
    )
}

#[test]
fn an_event_frame_with_filler_is_explained() {
    let (ok, text) = decode("FF FF FF FF FF FF F1 46 11 00 02 09 01 01 00 00 01 00 0F 00 00 10 64");
    assert!(ok, "{text}");
    assert!(text.contains("events of address 241: 2 event(s)"), "{text}");
    assert!(text.contains("coil 0 = 1"), "{text}");
    assert!(text.contains("the device restarted"), "{text}");
    // Read as a request it would be rejected; the reply reading is the one that makes sense.
    assert!(!text.contains("rejects it"), "{text}");
    assert!(
        text.contains("after 6 arbitration filler byte(s)"),
        "{text}"
    );
}

#[test]
fn a_bad_crc_fails_and_names_the_right_one() {
    let (ok, text) = decode("14 03 00 80 00 01 87 28");
    assert!(!ok, "{text}");
    assert!(text.contains("not a valid frame"), "{text}");
    assert!(text.contains("it would be 87 27"), "{text}");
}

/// Bytes that are no hex are bad input: exit 2 (tools.md), not 1 (a frame that fails its check).
#[test]
fn input_that_is_not_hex_exits_2() {
    for input in ["zz", "14 03 0"] {
        let output = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
            .arg("decode")
            .arg(input)
            .output()
            .unwrap();
        assert_eq!(output.status.code(), Some(2), "{input}: {output:?}");
        assert!(
            String::from_utf8_lossy(&output.stderr).contains("hex"),
            "{output:?}"
        );
    }
}
