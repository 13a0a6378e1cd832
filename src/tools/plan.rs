//! Which port settings a scan tries, and in what order: the settings devices ship with first, so
//! a scan interrupted early has still covered the likely ones.

use crate::protocol::{LineSettings, Parity};

/// Baud rates, most common on Wiren Board installations first.
pub const BAUD_ORDER: [u32; 8] = [9600, 115_200, 19200, 38400, 57600, 4800, 2400, 1200];

/// Character framings, most common first: 8N2 (the factory setting), then 8N1, 8E1, ...
pub const FRAMING_ORDER: [(Parity, u8); 6] = [
    (Parity::None, 2),
    (Parity::None, 1),
    (Parity::Even, 1),
    (Parity::Odd, 1),
    (Parity::Even, 2),
    (Parity::Odd, 2),
];

/// What the command line restricts; empty lists mean "all".
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PlanFilter {
    pub bauds: Vec<u32>,
    pub parities: Vec<Parity>,
    pub stop_bits: Vec<u8>,
}

/// The settings to try, in order: each framing over the baud rates, 8N2 at 9600 and 115200 first.
/// A baud rate outside the usual eight is tried too when asked for.
pub fn scan_plan(filter: &PlanFilter) -> Vec<LineSettings> {
    let mut bauds: Vec<u32> = BAUD_ORDER
        .iter()
        .copied()
        .filter(|b| filter.bauds.is_empty() || filter.bauds.contains(b))
        .collect();
    for extra in &filter.bauds {
        if !bauds.contains(extra) {
            bauds.push(*extra);
        }
    }
    let mut plan = Vec::new();
    for (parity, stop_bits) in FRAMING_ORDER {
        if !filter.parities.is_empty() && !filter.parities.contains(&parity) {
            continue;
        }
        if !filter.stop_bits.is_empty() && !filter.stop_bits.contains(&stop_bits) {
            continue;
        }
        for &baud in &bauds {
            plan.push(LineSettings::new(baud, parity, stop_bits));
        }
    }
    plan
}

/// Parses `N`, `E`, `O` (or none/even/odd).
pub fn parse_parity(text: &str) -> Result<Parity, String> {
    match text.to_ascii_lowercase().as_str() {
        "n" | "none" => Ok(Parity::None),
        "e" | "even" => Ok(Parity::Even),
        "o" | "odd" => Ok(Parity::Odd),
        _ => Err(format!("parity {text:?}: use N, E or O")),
    }
}

/// Parses `1-247` (inclusive) or a single address.
pub fn parse_range(text: &str) -> Result<(u8, u8), String> {
    let (low, high) = text.split_once('-').unwrap_or((text, text));
    let parse = |part: &str| -> Result<u8, String> {
        part.trim()
            .parse::<u8>()
            .ok()
            .filter(|a| (1..=247).contains(a))
            .ok_or_else(|| format!("address range {text:?}: addresses are 1..247"))
    };
    let (low, high) = (parse(low)?, parse(high)?);
    if low > high {
        return Err(format!(
            "address range {text:?}: the first is above the last"
        ));
    }
    Ok((low, high))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_48_settings_most_common_first() {
        let plan = scan_plan(&PlanFilter::default());
        assert_eq!(plan.len(), 48);
        assert_eq!(plan[0], LineSettings::new(9600, Parity::None, 2));
        assert_eq!(plan[1], LineSettings::new(115_200, Parity::None, 2));
        assert_eq!(plan[2], LineSettings::new(19200, Parity::None, 2));
        assert_eq!(plan[8], LineSettings::new(9600, Parity::None, 1));
        let mut unique = plan.clone();
        unique.dedup();
        assert_eq!(unique.len(), 48);
        for (i, a) in plan.iter().enumerate() {
            assert!(!plan[i + 1..].contains(a), "{a} twice");
        }
    }

    #[test]
    fn filters_restrict_and_odd_bauds_are_kept() {
        let filter = PlanFilter {
            bauds: vec![115_200, 250_000],
            parities: vec![Parity::None],
            stop_bits: vec![2],
        };
        assert_eq!(
            scan_plan(&filter),
            vec![
                LineSettings::new(115_200, Parity::None, 2),
                LineSettings::new(250_000, Parity::None, 2)
            ]
        );
    }

    #[test]
    fn ranges_and_parities_parse() {
        assert_eq!(parse_range("1-247"), Ok((1, 247)));
        assert_eq!(parse_range("17"), Ok((17, 17)));
        assert!(parse_range("0-10").is_err());
        assert!(parse_range("20-10").is_err());
        assert!(parse_range("1-248").is_err());
        assert_eq!(parse_parity("e"), Ok(Parity::Even));
        assert!(parse_parity("x").is_err());
    }
}
