//! Numbers printed the way wb-mqtt-serial prints them (C `%.15g`, `%.7g` for float32), so
//! dashboards and rules that compare value strings see the same text.

/// C's `%.{precision}g`: `precision` significant digits, trailing zeros removed, exponent form
/// below 1e-4 or from 10^precision on.
pub fn format_g(value: f64, precision: usize) -> String {
    if value.is_nan() {
        return "nan".to_string();
    }
    if value.is_infinite() {
        return if value > 0.0 { "inf" } else { "-inf" }.to_string();
    }
    if value == 0.0 {
        return if value.is_sign_negative() { "-0" } else { "0" }.to_string();
    }
    let precision = precision.max(1);
    // Rounding to `precision` significant digits decides the exponent, as in C.
    let scientific = format!("{:.*e}", precision - 1, value);
    let (mantissa, exponent) = match scientific.split_once('e') {
        Some((m, e)) => (m, e.parse::<i32>().unwrap_or(0)),
        None => (scientific.as_str(), 0),
    };
    if exponent < -4 || exponent >= precision as i32 {
        let mantissa = trim_fraction(mantissa);
        let sign = if exponent < 0 { '-' } else { '+' };
        format!("{mantissa}e{sign}{:02}", exponent.abs())
    } else {
        let decimals = (precision as i32 - 1 - exponent).max(0) as usize;
        trim_fraction(&format!("{:.*}", decimals, value)).to_string()
    }
}

fn trim_fraction(text: &str) -> &str {
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.')
    } else {
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_c_percent_g() {
        let cases: &[(f64, usize, &str)] = &[
            (0.0, 15, "0"),
            (1.0, 15, "1"),
            (-1.5, 15, "-1.5"),
            (230.5, 7, "230.5"),
            (234.60699462890625, 7, "234.607"),
            (3196.2, 15, "3196.2"),
            (0.1 + 0.2, 15, "0.3"),
            (25.5, 15, "25.5"),
            (1e-5, 15, "1e-05"),
            (0.0001, 15, "0.0001"),
            (123456789012345678.0, 15, "1.23456789012346e+17"),
            (1e15, 15, "1e+15"),
            (999999999999999.0, 15, "999999999999999"),
            (12345678.0, 7, "1.234568e+07"),
            (0.000123, 7, "0.000123"),
            (-273.15, 15, "-273.15"),
        ];
        for (value, precision, expected) in cases {
            assert_eq!(
                format_g(*value, *precision),
                *expected,
                "{value} %.{precision}g"
            );
        }
    }

    #[test]
    fn special_values() {
        assert_eq!(format_g(f64::NAN, 15), "nan");
        assert_eq!(format_g(f64::INFINITY, 15), "inf");
        assert_eq!(format_g(f64::NEG_INFINITY, 7), "-inf");
    }
}
