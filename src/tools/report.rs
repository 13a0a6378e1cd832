//! What a scan found, and how duplicate addresses are resolved: pure data, no IO.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use crate::protocol::LineSettings;

use super::plan::same_on_the_wire;

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
    /// The device's port settings: the baud rate and parity it answered at (the first in scan
    /// order), with the stop bits it reported (holding 112). The wire does not show stop bits:
    /// while the device has not reported them, they are the 2 the scan sent with, which a device
    /// at 1 or 2 understands (`stop_bits_known` false).
    pub line: LineSettings,
    /// The device reported its port settings (holding 110..112), and they are where it answered.
    pub stop_bits_known: bool,
    /// What holding 110..112 say when the device answered elsewhere (Wiren Board devices apply
    /// new port settings at their next start).
    pub registers_say: Option<LineSettings>,
    /// Further settings it answered at (a pty cannot tell parity none from even; on a real bus
    /// this means a misbehaving device or adapter). Never one that differs only in stop bits.
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
    /// The settings transmitted at.
    pub settings_tried: Vec<LineSettings>,
    /// The stop-bit counts each transmission covers (empty: 1 and 2).
    pub stop_bits_covered: Vec<u8>,
    /// Devices left out because they reported stop bits the scan was not asked for.
    pub other_stop_bits: usize,
    /// Addresses probed one by one with a classic request (`scan --classic`).
    pub classic_probes: usize,
    /// The scan went through the running service (MQTT RPC), not the port.
    pub through_service: bool,
    /// Serial numbers that keep their address when they share it: the devices the running
    /// service polls there (its identity read named them), so a fix moves the others.
    pub keep: BTreeSet<u32>,
}

/// Devices that share an address at one setting (stop bits aside: both hear the same request):
/// only one of them can be polled.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Duplicate {
    /// The settings of the first of them.
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
    /// The device's settings as the scan knows them (`9600 8N?` while its stop bits are not
    /// known): `line` is the setting the scan heard it at, which for stop bits says nothing.
    #[serde(skip)]
    pub settings: String,
}

/// The plan for a bus with duplicates: changes, and what cannot be fixed by serial number.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AddressPlan {
    pub changes: Vec<AddressChange>,
    pub unresolved: Vec<String>,
}

/// Whether a serial number read from a device's registers (the service's identity read) is
/// the one a scan gave: the same number, or its lower 24 bits (a WB-MAP meter's, as
/// wb-mqtt-serial reports it).
pub fn same_serial(read: u32, scanned: u32) -> bool {
    read == scanned || read == scanned & 0x00FF_FFFF
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

impl FoundDevice {
    fn new(serial: Option<u32>, address: u8, line: LineSettings, fast: bool) -> Self {
        Self {
            serial,
            address,
            line,
            stop_bits_known: false,
            registers_say: None,
            also_at: Vec::new(),
            fast,
            identity: Identity::default(),
        }
    }

    /// Answered at `line` (stop bits aside).
    pub fn answers_at(&self, line: &LineSettings) -> bool {
        same_on_the_wire(&self.line, line) || self.also_at.iter().any(|l| same_on_the_wire(l, line))
    }

    /// The settings as text: `9600 8N1`, or `9600 8N?` while the stop bits are not known.
    pub fn settings_text(&self) -> String {
        let text = self.line.to_string();
        if self.stop_bits_known {
            return text;
        }
        match text.strip_suffix(|c: char| c.is_ascii_digit()) {
            Some(rest) => format!("{rest}?"),
            None => text,
        }
    }

    /// Takes the port settings the device reports (holding 110..112). Where it answered decides
    /// baud rate and parity; when the registers name one of those settings, they are the
    /// device's (and its stop bits known), else they are kept aside as `registers_say`.
    pub fn take_reported(&mut self, reported: LineSettings) {
        if same_on_the_wire(&self.line, &reported) {
            self.line = reported;
            self.stop_bits_known = true;
        } else if let Some(index) = self
            .also_at
            .iter()
            .position(|l| same_on_the_wire(l, &reported))
        {
            // A pty cannot tell parity none from even: the registers say which one it is.
            let first = std::mem::replace(&mut self.line, reported);
            self.also_at.remove(index);
            self.also_at.insert(0, first);
            self.stop_bits_known = true;
        } else {
            self.registers_say = Some(reported);
        }
    }
}

impl ScanReport {
    /// Records a Fast Modbus device seen at `line`; true when it is new (not seen before at any
    /// setting). A device seen again at settings that differ only in stop bits is not "also at"
    /// them: they are one setting on the wire.
    pub fn add_fast(&mut self, line: LineSettings, serial: u32, address: u8) -> bool {
        if let Some(known) = self.devices.iter_mut().find(|d| d.serial == Some(serial)) {
            if !known.answers_at(&line) {
                known.also_at.push(line);
            }
            return false;
        }
        self.devices
            .push(FoundDevice::new(Some(serial), address, line, true));
        true
    }

    /// The number of port settings the transmissions covered: each baud rate and parity sent
    /// at (once, or again after trouble) covers every stop-bit count asked for.
    pub fn settings_covered(&self) -> usize {
        let per_transmission = match self.stop_bits_covered.len() {
            0 => 2,
            n => n,
        };
        let mut on_the_wire: Vec<&LineSettings> = Vec::new();
        for line in &self.settings_tried {
            if !on_the_wire.iter().any(|l| same_on_the_wire(l, line)) {
                on_the_wire.push(line);
            }
        }
        on_the_wire.len() * per_transmission
    }

    /// Leaves out the devices that reported stop bits other than `wanted` (empty: keeps all);
    /// those that did not report them stay (they may use any).
    pub fn keep_stop_bits(&mut self, wanted: &[u8]) {
        if wanted.is_empty() {
            return;
        }
        let before = self.devices.len();
        self.devices
            .retain(|d| !d.stop_bits_known || wanted.contains(&d.line.stop_bits));
        self.other_stop_bits += before - self.devices.len();
    }

    /// Records a device that answered a classic request at `address`; false when a device
    /// already known at this setting has that address (a Fast Modbus device answers classic
    /// requests too), or one with its serial number is known at another setting (it is "also
    /// at" this one).
    pub fn add_classic(&mut self, line: LineSettings, address: u8, serial: Option<u32>) -> bool {
        if let Some(known) = self
            .devices
            .iter_mut()
            .find(|d| serial.is_some() && d.serial == serial)
        {
            if !known.answers_at(&line) {
                known.also_at.push(line);
            }
            return false;
        }
        let known = self.devices.iter().any(|d| {
            d.address == address && d.answers_at(&line) && (serial.is_none() || d.serial == serial)
        });
        if known {
            return false;
        }
        self.devices
            .push(FoundDevice::new(serial, address, line, false));
        true
    }

    /// Addresses that more than one device uses at the same setting (stop bits aside: devices
    /// that differ only in them hear the same requests and answer together).
    pub fn duplicates(&self) -> Vec<Duplicate> {
        let mut groups: BTreeMap<(u32, u8, char, u8), Duplicate> = BTreeMap::new();
        for (index, device) in self.devices.iter().enumerate() {
            let line = device.line;
            groups
                .entry((
                    line.baud,
                    line.data_bits,
                    line.parity.letter(),
                    device.address,
                ))
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
    /// number), else one the service polls there ([`Self::keep`]), else the lowest serial
    /// number (so the plan is the same on every run). Addresses
    /// in use at any setting count as taken, so devices stay unique if the bus is later moved to
    /// one setting.
    pub fn plan_addresses(&self, range: (u8, u8)) -> AddressPlan {
        self.plan_addresses_avoiding(range, &BTreeSet::new())
    }

    /// [`plan_addresses`](Self::plan_addresses), also keeping off `occupied`: addresses where
    /// something the scan did not list answers (a device without Fast Modbus).
    pub fn plan_addresses_avoiding(&self, range: (u8, u8), occupied: &BTreeSet<u8>) -> AddressPlan {
        let mut taken: BTreeSet<u8> = self.devices.iter().map(|d| d.address).collect();
        taken.extend(occupied.iter().copied());
        let mut plan = AddressPlan::default();
        for duplicate in self.duplicates() {
            let mut members: Vec<&FoundDevice> = duplicate
                .devices
                .iter()
                .filter_map(|&i| self.devices.get(i))
                .collect();
            members.sort_by_key(|d| {
                let polled = d.serial.is_some_and(|serial| self.keep.contains(&serial));
                (d.serial.is_some(), !polled, d.serial)
            });
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
                            settings: device.settings_text(),
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
    fn stop_bits_are_one_setting_on_the_wire() {
        let n1 = LineSettings::new(9600, Parity::None, 1);
        let mut report = ScanReport::default();
        assert!(report.add_fast(SLOW, 7, 20));
        // The same device heard again by a master at 8N1: not "also at" 8N1.
        assert!(!report.add_fast(n1, 7, 20));
        assert!(report.devices[0].also_at.is_empty());
        assert_eq!(report.devices[0].settings_text(), "9600 8N?");
        report.devices[0].take_reported(n1);
        assert_eq!(report.devices[0].line, n1);
        assert!(report.devices[0].stop_bits_known);
        assert_eq!(report.devices[0].settings_text(), "9600 8N1");
        // Another device at address 20 with two stop bits answers the same requests.
        report.add_fast(SLOW, 8, 20);
        report.devices[1].take_reported(SLOW);
        let duplicates = report.duplicates();
        assert_eq!(duplicates.len(), 1);
        assert_eq!(duplicates[0].devices, vec![0, 1]);
        assert!(!report.add_classic(SLOW, 20, None));
    }

    #[test]
    fn registers_decide_between_settings_a_pty_cannot_tell_apart() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 7, 20);
        report.add_fast(EVEN, 7, 20);
        let even_one_stop_bit = LineSettings::new(9600, Parity::Even, 1);
        report.devices[0].take_reported(even_one_stop_bit);
        assert_eq!(report.devices[0].line, even_one_stop_bit);
        assert_eq!(report.devices[0].also_at, vec![SLOW]);
        assert_eq!(report.devices[0].registers_say, None);
        // Registers naming a setting it did not answer at are kept aside, not believed.
        report.add_fast(FAST, 9, 21);
        report.devices[1].take_reported(SLOW);
        assert_eq!(report.devices[1].line, FAST);
        assert!(!report.devices[1].stop_bits_known);
        assert_eq!(report.devices[1].registers_say, Some(SLOW));
    }

    #[test]
    fn a_stop_bit_filter_keeps_devices_that_did_not_say() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 1, 20);
        report.add_fast(SLOW, 2, 21);
        report.add_fast(SLOW, 3, 22);
        report.devices[0].take_reported(LineSettings::new(9600, Parity::None, 1));
        report.devices[1].take_reported(SLOW);
        report.keep_stop_bits(&[1]);
        let serials: Vec<Option<u32>> = report.devices.iter().map(|d| d.serial).collect();
        assert_eq!(serials, vec![Some(1), Some(3)]);
        assert_eq!(report.other_stop_bits, 1);
        report.settings_tried = vec![SLOW, FAST, LineSettings::new(115_200, Parity::None, 1)];
        assert_eq!(report.settings_covered(), 4);
        report.stop_bits_covered = vec![1];
        assert_eq!(report.settings_covered(), 2);
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
    fn a_classic_device_answering_at_two_settings_is_one_device() {
        let mut report = ScanReport::default();
        assert!(report.add_classic(SLOW, 40, Some(9)));
        assert!(!report.add_classic(EVEN, 40, Some(9)));
        assert!(!report.add_classic(LineSettings::new(9600, Parity::None, 1), 40, Some(9)));
        assert_eq!(report.devices.len(), 1);
        assert_eq!(report.devices[0].also_at, vec![EVEN]);
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
                    to: 3,
                    settings: "9600 8N?".into(),
                },
                AddressChange {
                    serial: 9,
                    line: SLOW,
                    from: 1,
                    to: 4,
                    settings: "9600 8N?".into(),
                },
            ]
        );
        assert!(plan.unresolved.is_empty());
    }

    #[test]
    fn a_serial_read_from_registers_matches_the_scanned_one_or_its_lower_24_bits() {
        assert!(same_serial(0xFE00_0010, 0xFE00_0010));
        assert!(same_serial(0x12_3456, 0xFE12_3456));
        assert!(!same_serial(0xFE00_0011, 0xFE00_0010));
    }

    #[test]
    fn the_device_the_service_polls_keeps_its_address_whatever_its_serial() {
        let mut report = ScanReport::default();
        report.add_fast(SLOW, 5, 10);
        report.add_fast(SLOW, 9, 10);
        report.add_fast(SLOW, 7, 10);
        report.keep.insert(9);
        let plan = report.plan_addresses((1, 247));
        let moved: Vec<u32> = plan.changes.iter().map(|c| c.serial).collect();
        assert_eq!(moved, vec![5, 7]);
        // A polled serial elsewhere changes nothing here.
        report.keep = BTreeSet::from([42]);
        let moved: Vec<u32> = report
            .plan_addresses((1, 247))
            .changes
            .iter()
            .map(|c| c.serial)
            .collect();
        assert_eq!(moved, vec![7, 9]);
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
