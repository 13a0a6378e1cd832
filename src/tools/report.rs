//! What a scan found, and how duplicate addresses are resolved: pure data, no IO.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use crate::protocol::LineSettings;

/// Model, firmware and signature as read from the Wiren Board standard registers (absent when a
/// device does not have them).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Identity {
    pub model: Option<String>,
    pub firmware: Option<String>,
    pub signature: Option<String>,
}

/// One device on the bus.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FoundDevice {
    /// Known for Fast Modbus devices (and classic ones with the standard serial register).
    pub serial: Option<u32>,
    pub address: u8,
    /// The first setting (in scan order) the device answered at.
    pub line: LineSettings,
    /// Further settings it answered at (a pty cannot tell parity none from even; on a real bus
    /// this means a misbehaving device or adapter).
    pub also_at: Vec<LineSettings>,
    /// Answers Fast Modbus (0x46) requests.
    pub fast: bool,
    pub identity: Identity,
}

/// A setting at which something went wrong; the scan went on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SettingProblem {
    pub line: LineSettings,
    pub what: String,
}

#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ScanReport {
    pub devices: Vec<FoundDevice>,
    pub problems: Vec<SettingProblem>,
    pub settings_tried: Vec<LineSettings>,
}

/// Devices that share an address at one setting: only one of them can be polled.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Duplicate {
    pub line: LineSettings,
    pub address: u8,
    /// Indices into [`ScanReport::devices`].
    pub devices: Vec<usize>,
}

/// One proposed address change, made by serial number.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct AddressChange {
    pub serial: u32,
    #[serde(serialize_with = "serialize_line")]
    pub line: LineSettings,
    pub from: u8,
    pub to: u8,
}

/// The plan for a bus with duplicates: changes, and what cannot be fixed by serial number.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AddressPlan {
    pub changes: Vec<AddressChange>,
    pub unresolved: Vec<String>,
}

pub fn serialize_line<S: serde::Serializer>(
    line: &LineSettings,
    serializer: S,
) -> Result<S::Ok, S::Error> {
    serializer.collect_str(line)
}

/// `4265607340 (0xFE4000AC)`: the decimal of the sticker and the hex of the docs.
pub fn serial_text(serial: u32) -> String {
    format!("{serial} (0x{serial:08X})")
}

impl ScanReport {
    /// Records a Fast Modbus device seen at `line`; true when it is new (not seen before at any
    /// setting).
    pub fn add_fast(&mut self, line: LineSettings, serial: u32, address: u8) -> bool {
        if let Some(known) = self.devices.iter_mut().find(|d| d.serial == Some(serial)) {
            if known.line != line && !known.also_at.contains(&line) {
                known.also_at.push(line);
            }
            return false;
        }
        self.devices.push(FoundDevice {
            serial: Some(serial),
            address,
            line,
            also_at: Vec::new(),
            fast: true,
            identity: Identity::default(),
        });
        true
    }

    /// Records a device that answered a classic request at `address`; false when a device
    /// already known at this setting has that address (a Fast Modbus device answers classic
    /// requests too).
    pub fn add_classic(&mut self, line: LineSettings, address: u8, serial: Option<u32>) -> bool {
        let known = self.devices.iter().any(|d| {
            d.address == address
                && (d.line == line || d.also_at.contains(&line))
                && (serial.is_none() || d.serial == serial)
        });
        if known {
            return false;
        }
        self.devices.push(FoundDevice {
            serial,
            address,
            line,
            also_at: Vec::new(),
            fast: false,
            identity: Identity::default(),
        });
        true
    }

    /// Addresses that more than one device uses at the same setting.
    pub fn duplicates(&self) -> Vec<Duplicate> {
        let mut groups: BTreeMap<(String, u8), Duplicate> = BTreeMap::new();
        for (index, device) in self.devices.iter().enumerate() {
            groups
                .entry((device.line.to_string(), device.address))
                .or_insert_with(|| Duplicate {
                    line: device.line,
                    address: device.address,
                    devices: Vec::new(),
                })
                .devices
                .push(index);
        }
        groups
            .into_values()
            .filter(|g| g.devices.len() > 1)
            .collect()
    }

    /// Devices that answered at more than one setting.
    pub fn multi_setting(&self) -> impl Iterator<Item = &FoundDevice> {
        self.devices.iter().filter(|d| !d.also_at.is_empty())
    }

    /// Free addresses for the second and later devices of every duplicate, lowest first within
    /// `range`. The device that keeps the address: a classic one (it cannot be moved by serial
    /// number), else the lowest serial number (so the plan is the same on every run). Addresses
    /// in use at any setting count as taken, so devices stay unique if the bus is later moved to
    /// one setting.
    pub fn plan_addresses(&self, range: (u8, u8)) -> AddressPlan {
        let mut taken: BTreeSet<u8> = self.devices.iter().map(|d| d.address).collect();
        let mut plan = AddressPlan::default();
        for duplicate in self.duplicates() {
            let mut members: Vec<&FoundDevice> = duplicate
                .devices
                .iter()
                .filter_map(|&i| self.devices.get(i))
                .collect();
            members.sort_by_key(|d| (d.serial.is_some(), d.serial));
            let classic = members.iter().filter(|d| d.serial.is_none()).count();
            if classic > 1 {
                plan.unresolved.push(format!(
                    "{classic} devices without a known serial number share address {} at {}: \
                     give them distinct addresses one at a time (only one connected)",
                    duplicate.address, duplicate.line
                ));
            }
            for device in members.iter().skip(1) {
                let Some(serial) = device.serial else {
                    continue;
                };
                let free = (range.0..=range.1).find(|a| !taken.contains(a));
                match free {
                    Some(to) => {
                        taken.insert(to);
                        plan.changes.push(AddressChange {
                            serial,
                            line: device.line,
                            from: device.address,
                            to,
                        });
                    }
                    None => plan.unresolved.push(format!(
                        "no free address left in {}-{} for the device with serial {}",
                        range.0,
                        range.1,
                        serial_text(serial)
                    )),
                }
            }
        }
        plan
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Parity;

    const SLOW: LineSettings = LineSettings::new(9600, Parity::None, 2);
    const FAST: LineSettings = LineSettings::new(115_200, Parity::None, 2);
    const EVEN: LineSettings = LineSettings::new(9600, Parity::Even, 2);

    #[test]
    fn a_device_seen_twice_is_one_device_with_a_second_setting() {
        let mut report = ScanReport::default();
        assert!(report.add_fast(SLOW, 7, 20));
        assert!(!report.add_fast(EVEN, 7, 20));
        assert!(!report.add_fast(EVEN, 7, 20));
        assert_eq!(report.devices.len(), 1);
        assert_eq!(report.devices[0].line, SLOW);
        assert_eq!(report.devices[0].also_at, vec![EVEN]);
        assert_eq!(report.multi_setting().count(), 1);
        assert!(report.duplicates().is_empty());
    }

    #[test]
    fn classic_answers_of_known_fast_devices_are_not_new_devices() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 7, 20);
        assert!(!report.add_classic(SLOW, 20, None));
        assert_eq!(report.devices.len(), 1);
        assert!(report.add_classic(SLOW, 21, None));
        assert!(!report.devices[report.devices.len() - 1].fast);
    }

    #[test]
    fn duplicates_are_per_setting() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 1, 20);
        report.add_fast(SLOW, 2, 20);
        report.add_fast(FAST, 3, 20);
        let duplicates = report.duplicates();
        assert_eq!(duplicates.len(), 1);
        assert_eq!(duplicates[0].line, SLOW);
        assert_eq!(duplicates[0].devices, vec![0, 1]);
    }

    #[test]
    fn the_plan_moves_all_but_the_lowest_serial_to_free_addresses() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 9, 1);
        report.add_fast(SLOW, 5, 1);
        report.add_fast(SLOW, 7, 1);
        report.add_fast(FAST, 8, 2);
        let plan = report.plan_addresses((1, 247));
        assert_eq!(
            plan.changes,
            vec![
                AddressChange {
                    serial: 7,
                    line: SLOW,
                    from: 1,
                    to: 3
                },
                AddressChange {
                    serial: 9,
                    line: SLOW,
                    from: 1,
                    to: 4
                },
            ]
        );
        assert!(plan.unresolved.is_empty());
    }

    #[test]
    fn a_classic_device_keeps_its_address_and_a_full_range_is_reported() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 5, 10);
        report.add_classic(SLOW, 10, None);
        // The classic one is already known at this address: it counts as the fast device.
        assert_eq!(report.devices.len(), 1);
        report.add_fast(SLOW, 6, 10);
        let plan = report.plan_addresses((10, 10));
        assert!(plan.changes.is_empty());
        assert_eq!(plan.unresolved.len(), 1, "{:?}", plan.unresolved);
        assert!(plan.unresolved[0].contains("no free address"));
    }
}
