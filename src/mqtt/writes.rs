//! `/on` payloads: checked against the control type and the channel's codec before anything
//! goes to the bus. A bad payload is refused with a reason; nothing is written.

use crate::device::{CodecError, ResolvedChannel};

/// Why an `/on` payload was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WriteRejection {
    #[error("the control is read-only")]
    ReadOnly,
    #[error("the payload is not UTF-8 text")]
    NotText,
    #[error("a {control_type} takes {expected}, got `{payload}`")]
    BadFormat {
        control_type: String,
        expected: &'static str,
        payload: String,
    },
    #[error("{0}")]
    Codec(#[from] CodecError),
}

/// Longest payload looked at; anything longer is refused before parsing.
pub const MAX_PAYLOAD: usize = 4096;

/// Checks an `/on` payload for `channel`; returns the text to hand to the bus side (trimmed).
pub fn check_write(channel: &ResolvedChannel, payload: &[u8]) -> Result<String, WriteRejection> {
    if channel.readonly {
        return Err(WriteRejection::ReadOnly);
    }
    if payload.len() > MAX_PAYLOAD {
        return Err(bad(channel, "a short text", "(too long)"));
    }
    let text = std::str::from_utf8(payload)
        .map_err(|_| WriteRejection::NotText)?
        .trim();
    match channel.control_type.as_str() {
        "switch" | "alarm" => {
            if text != "0" && text != "1" {
                return Err(bad(channel, "0 or 1", text));
            }
        }
        "pushbutton" => {
            if text != "1" {
                return Err(bad(channel, "1", text));
            }
        }
        "range" | "dimmer" => {
            let integral = text
                .parse::<f64>()
                .is_ok_and(|v| v.is_finite() && v.fract() == 0.0);
            if !integral {
                return Err(bad(channel, "an integer", text));
            }
        }
        "rgb" => {
            let parts: Vec<&str> = text.split(';').collect();
            let colour = parts.len() == 3 && parts.iter().all(|p| p.trim().parse::<u8>().is_ok());
            if !colour {
                return Err(bad(channel, "R;G;B with each part 0…255", text));
            }
        }
        "text" | "w1-id" => {}
        // `value`, `unixtime` and the deprecated typed values are numbers.
        _ => {
            let parts_are_numbers = text
                .split(';')
                .all(|p| p.trim().parse::<f64>().is_ok_and(f64::is_finite));
            if !parts_are_numbers {
                return Err(bad(channel, "a number", text));
            }
        }
    }
    // The codec checks limits, format range, string length and on/off mapping. Bit fields need
    // the register's other bits to build the words: zeros do for a check, the bus side merges
    // with the real contents.
    let zeros: Vec<Vec<u16>> = channel
        .registers
        .iter()
        .map(|r| vec![0u16; (r.codec.word_count as usize).min(256)])
        .collect();
    let current: Vec<Option<&[u16]>> = zeros.iter().map(|w| Some(w.as_slice())).collect();
    channel.encode(text, &current)?;
    Ok(text.to_string())
}

fn bad(channel: &ResolvedChannel, expected: &'static str, payload: &str) -> WriteRejection {
    let mut shown: String = payload.chars().take(64).collect();
    if shown.len() < payload.len() {
        shown.push('…');
    }
    WriteRejection::BadFormat {
        control_type: channel.control_type.clone(),
        expected,
        payload: shown,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::{ChannelRegister, RegisterFormat, ValueCodec};
    use crate::mqtt::layout::tests::channel;

    fn rgb() -> ResolvedChannel {
        let mut c = channel("RGB", "rgb");
        let register = c.registers[0].clone();
        c.registers = vec![register.clone(), register.clone(), register];
        c
    }

    #[test]
    fn switch_takes_only_0_and_1() {
        let k1 = channel("K1", "switch");
        assert_eq!(check_write(&k1, b"1").unwrap(), "1");
        assert_eq!(check_write(&k1, b" 0\n").unwrap(), "0");
        for bad in [&b"2"[..], b"on", b"", b"\xff"] {
            assert!(check_write(&k1, bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn range_respects_limits_and_integers() {
        let mut level = channel("Level", "range");
        level.min = Some(0.0);
        level.max = Some(100.0);
        assert!(check_write(&level, b"42").is_ok());
        assert!(check_write(&level, b"101").is_err());
        assert!(check_write(&level, b"4.5").is_err());
        assert!(check_write(&level, b"-1").is_err());
    }

    #[test]
    fn value_must_be_a_number_in_format_range() {
        let setpoint = channel("Setpoint", "value");
        assert!(check_write(&setpoint, b"12").is_ok());
        assert!(check_write(&setpoint, b"abc").is_err());
        assert!(check_write(&setpoint, b"NaN").is_err());
        // u16 cannot hold it.
        assert!(matches!(
            check_write(&setpoint, b"70000"),
            Err(WriteRejection::Codec(_))
        ));
    }

    #[test]
    fn rgb_needs_three_parts() {
        assert!(check_write(&rgb(), b"255;0;10").is_ok());
        assert!(check_write(&rgb(), b"255;0").is_err());
        assert!(check_write(&rgb(), b"256;0;0").is_err());
    }

    #[test]
    fn readonly_and_bit_fields() {
        let mut input = channel("Input", "switch");
        input.readonly = true;
        assert_eq!(check_write(&input, b"1"), Err(WriteRejection::ReadOnly));

        let mut flag = channel("Flag", "switch");
        flag.registers = vec![ChannelRegister {
            codec: ValueCodec {
                bit_shift: 3,
                bit_width: 1,
                ..ValueCodec::plain(RegisterFormat::U16)
            },
            ..flag.registers[0].clone()
        }];
        assert!(check_write(&flag, b"1").is_ok());
    }

    #[test]
    fn huge_payloads_are_refused() {
        let text = channel("Text", "text");
        assert!(check_write(&text, &vec![b'a'; MAX_PAYLOAD + 1]).is_err());
    }
}
