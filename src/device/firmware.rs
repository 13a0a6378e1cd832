//! Firmware versions as wb-mqtt-serial orders them, for a template's `fw` (the oldest firmware
//! that has a channel): parts split on `.`, the shorter padded with zeros ("2.1" = "2.1.0"); a
//! part `N-rcM` ranks below `N` and `N+wbM` above it; any other text in a part counts as 0; an
//! empty version is older than any.

use std::cmp::Ordering;

/// Where a release candidate and a build suffix rank against a plain part.
const SUFFIX_OFFSET: i64 = 1 << 32;

/// One `.`-separated part: its number, then `-rcM` below a plain part, `+wbM` above it.
fn part_key(part: &str) -> (u64, i64) {
    let number = |text: &str| text.parse::<u64>().ok();
    let rank = |text: &str| number(text).map(|m| i64::try_from(m.min(1 << 31)).unwrap_or(0));
    if let Some((base, suffix)) = part.split_once("-rc") {
        if let (Some(base), Some(m)) = (number(base), rank(suffix)) {
            return (base, m - SUFFIX_OFFSET);
        }
    }
    if let Some((base, suffix)) = part.split_once("+wb") {
        if let (Some(base), Some(m)) = (number(base), rank(suffix)) {
            return (base, m + SUFFIX_OFFSET);
        }
    }
    (number(part).unwrap_or(0), 0)
}

/// How version `a` compares with `b`.
pub fn compare_versions(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.trim(), b.trim());
    match (a.is_empty(), b.is_empty()) {
        (true, true) => return Ordering::Equal,
        (true, false) => return Ordering::Less,
        (false, true) => return Ordering::Greater,
        (false, false) => {}
    }
    let a: Vec<(u64, i64)> = a.split('.').map(part_key).collect();
    let b: Vec<(u64, i64)> = b.split('.').map(part_key).collect();
    let padding = std::iter::repeat((0, 0));
    a.iter()
        .copied()
        .chain(padding.clone())
        .zip(b.iter().copied().chain(padding))
        .take(a.len().max(b.len()))
        .map(|(x, y)| x.cmp(&y))
        .find(|ordering| ordering.is_ne())
        .unwrap_or(Ordering::Equal)
}

/// Whether a device with `firmware` (as it reports it; `None` or empty when unknown) has what
/// needs at least `required`. Unknown firmware is taken as new enough, as wb-mqtt-serial does.
pub fn firmware_has(firmware: Option<&str>, required: &str) -> bool {
    match firmware.map(str::trim).filter(|f| !f.is_empty()) {
        Some(firmware) => compare_versions(firmware, required) != Ordering::Less,
        None => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_order_as_wb_mqtt_serial_orders_them() {
        let ascending = [
            "",
            "1.2",
            "1.2.3-rc1",
            "1.2.3-rc10",
            "1.2.3",
            "1.2.3+wb1",
            "1.2.3+wb10",
            "1.2.4",
            "1.10",
            "2",
        ];
        for pair in ascending.windows(2) {
            assert_eq!(
                compare_versions(pair[0], pair[1]),
                Ordering::Less,
                "{pair:?}"
            );
            assert_eq!(
                compare_versions(pair[1], pair[0]),
                Ordering::Greater,
                "{pair:?}"
            );
        }
        assert_eq!(compare_versions("2.1", "2.1.0"), Ordering::Equal);
        assert_eq!(compare_versions("3-beta.1", "0.1"), Ordering::Equal);
    }

    #[test]
    fn unknown_firmware_is_new_enough() {
        assert!(firmware_has(Some("1.26.0"), "1.26"));
        assert!(!firmware_has(Some("1.26.0"), "1.26.1"));
        assert!(!firmware_has(Some("3.8.0-rc1"), "3.8.0"));
        assert!(firmware_has(None, "9.0"));
        assert!(firmware_has(Some(" "), "9.0"));
    }
}
