//! Which port settings a scan transmits at, and in what order: the settings devices ship with
//! first, so a scan interrupted early has still covered the likely ones. 24 transmissions (8 baud
//! rates × 3 parities) cover all 48 settings: the stop bits are not visible on the wire.

use crate::protocol::{LineSettings, Parity};

/// Baud rates, most common on Wiren Board installations first.
pub const BAUD_ORDER: [u32; 8] = [9600, 115_200, 19200, 38400, 57600, 4800, 2400, 1200];

/// Parities, most common first (none: the factory setting).
pub const PARITY_ORDER: [Parity; 3] = [Parity::None, Parity::Even, Parity::Odd];

/// The stop bits every scan request goes out with. A UART receiver checks only the first stop
/// bit, whatever number it is set to (16550-compatible datasheets: "the receiver will ignore all
/// stop bits beyond the first"; a few UARTs can be set to check both): a request sent with 2 is
/// heard by devices set to 1 or 2, and a
/// master set to 2 hears replies sent with 1 or 2. The stop bits are not visible on the wire,
/// so one transmission per baud rate and parity covers both; 2 rather than 1 because then only
/// the master's receiver has to check just the first stop bit, not every device's (the scan
/// sends a troubled setting again with 1, for a port whose receiver checks both).
pub const TRANSMIT_STOP_BITS: u8 = 2;

/// What the command line restricts; empty lists mean "all".
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PlanFilter {
    pub bauds: Vec<u32>,
    pub parities: Vec<Parity>,
    pub stop_bits: Vec<u8>,
}

impl PlanFilter {
    /// The stop-bit counts the scan reports devices at (each transmission reaches them all).
    pub fn stop_bits_covered(&self) -> Vec<u8> {
        [1, 2]
            .into_iter()
            .filter(|n| self.stop_bits.is_empty() || self.stop_bits.contains(n))
            .collect()
    }
}

/// The settings to transmit at, in order: one per baud rate and parity, parity none first and
/// within it 9600 and 115200 first. Each goes out with [`TRANSMIT_STOP_BITS`] (it covers devices
/// at 1 and 2 stop bits alike), or with the one stop-bit count the filter names (what the user
/// asked for; devices at the other count hear it too, and the scan reports those that say they
/// use the named one). A baud rate outside the usual eight is tried too when asked for.
pub fn scan_plan(filter: &PlanFilter) -> Vec<LineSettings> {
    let stop_bits = match filter.stop_bits.as_slice() {
        [one] => *one,
        _ => TRANSMIT_STOP_BITS,
    };
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
    for parity in PARITY_ORDER {
        if !filter.parities.is_empty() && !filter.parities.contains(&parity) {
            continue;
        }
        for &baud in &bauds {
            plan.push(LineSettings::new(baud, parity, stop_bits));
        }
    }
    plan
}

/// Same baud rate, data bits and parity: what a receiver checks. Two settings that differ only
/// in stop bits are one setting on the wire (see [`TRANSMIT_STOP_BITS`]).
pub fn same_on_the_wire(a: &LineSettings, b: &LineSettings) -> bool {
    a.baud == b.baud && a.data_bits == b.data_bits && a.parity == b.parity
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

/// Parses a baud rate the config would take ([`MIN_BAUD_RATE`]..=[`MAX_BAUD_RATE`]): a typo
/// such as 0 or 1 would time every reply in minutes (and 0 hangs a real port up).
pub fn parse_baud(text: &str) -> Result<u32, String> {
    use crate::config::config_file::{MAX_BAUD_RATE, MIN_BAUD_RATE};
    let baud: u32 = text
        .trim()
        .parse()
        .map_err(|_| format!("baud rate {text:?}: a number such as 9600 or 115200"))?;
    if (MIN_BAUD_RATE..=MAX_BAUD_RATE).contains(&baud) {
        Ok(baud)
    } else {
        Err(format!(
            "baud rate {baud}: out of {MIN_BAUD_RATE}..{MAX_BAUD_RATE} (usual: {})",
            crate::protocol::timing::usual_baud_rates_text()
        ))
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
    fn all_48_settings_in_24_transmissions_most_common_first() {
        let filter = PlanFilter::default();
        let plan = scan_plan(&filter);
        assert_eq!(plan.len(), 24);
        assert_eq!(filter.stop_bits_covered(), vec![1, 2]);
        assert_eq!(plan[0], LineSettings::new(9600, Parity::None, 2));
        assert_eq!(plan[1], LineSettings::new(115_200, Parity::None, 2));
        assert_eq!(plan[2], LineSettings::new(19200, Parity::None, 2));
        assert_eq!(plan[8], LineSettings::new(9600, Parity::Even, 2));
        assert_eq!(plan[16], LineSettings::new(9600, Parity::Odd, 2));
        assert!(plan.iter().all(|l| l.stop_bits == TRANSMIT_STOP_BITS));
        for (i, a) in plan.iter().enumerate() {
            assert!(
                !plan[i + 1..].iter().any(|b| same_on_the_wire(a, b)),
                "{a} twice"
            );
        }
    }

    #[test]
    fn filters_restrict_and_odd_bauds_are_kept() {
        let filter = PlanFilter {
            bauds: vec![115_200, 250_000],
            parities: vec![Parity::None],
            stop_bits: vec![1],
        };
        // One stop bit asked for: sent with one, and only that count is reported.
        assert_eq!(
            scan_plan(&filter),
            vec![
                LineSettings::new(115_200, Parity::None, 1),
                LineSettings::new(250_000, Parity::None, 1)
            ]
        );
        assert_eq!(filter.stop_bits_covered(), vec![1]);
        let both = PlanFilter {
            stop_bits: vec![2, 1],
            ..filter
        };
        assert_eq!(
            scan_plan(&both)[0],
            LineSettings::new(115_200, Parity::None, 2)
        );
        assert_eq!(both.stop_bits_covered(), vec![1, 2]);
    }

    #[test]
    fn stop_bits_are_not_on_the_wire() {
        let n1 = LineSettings::new(9600, Parity::None, 1);
        assert!(same_on_the_wire(
            &n1,
            &LineSettings::new(9600, Parity::None, 2)
        ));
        assert!(!same_on_the_wire(
            &n1,
            &LineSettings::new(9600, Parity::Even, 1)
        ));
        assert!(!same_on_the_wire(
            &n1,
            &LineSettings::new(19200, Parity::None, 1)
        ));
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
