//! What flows between the bus side (port tasks and the device model) and the MQTT side, so each
//! is built and tested without the other.

use std::fmt;
use std::sync::Arc;

use crate::device::ResolvedDevice;

/// From the bus side to MQTT.
#[derive(Debug, Clone)]
pub enum DeviceUpdate {
    /// A device is served: publish its meta and every control's meta (and its HA discovery).
    Added(Arc<ResolvedDevice>),
    /// What the device told about itself (scan, standard registers), for HA and device meta.
    Identity {
        device_id: String,
        identity: DeviceIdentity,
    },
    /// Remove every retained topic of the device (clean shutdown, or dropped from the config).
    Removed { device_id: String },
    /// A control's value, formatted the Wiren Board way, after a good read or event that
    /// changed it, and after those that repeat it when [`Repeats`] asks for them.
    /// `from_event`: it came by a Fast Modbus event (for logs and the stdout sink). `changed`:
    /// it differs from the value the device model reported before (always true for the first).
    /// MQTT publishes on change either way, as wb-mqtt-serial does: a device repeating an
    /// unconfirmed packet, or an event after the poll that already read the value, must not
    /// publish it twice. The texts are shared, not copied: the ids with the device model, a
    /// value read again with the one reported before.
    Value {
        device_id: Arc<str>,
        control_id: Arc<str>,
        value: Arc<str>,
        from_event: bool,
        changed: bool,
    },
    /// A control's error flags (the whole set, not a change).
    ControlError {
        device_id: String,
        control_id: String,
        errors: ErrorFlags,
    },
    /// The device answers again (`true`) or stopped answering.
    Online { device_id: String, online: bool },
    /// The device's bus is this gateway's: its port opened here (or cannot be opened for a
    /// reason other than another program holding it). Until then its Wiren Board topics may be
    /// another gateway's (wb-mqtt-serial still running on that port): they are not deleted for
    /// it, at exit or when a reload drops it.
    BusServed { device_id: String },
}

/// Which values the device model reports when they repeat the one it reported before (a
/// change is always reported): what its sinks need beyond the changes, chosen where the models
/// are built. Most reads repeat every value; those not needed are not even decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Repeats {
    /// None: MQTT publishing changes only (`max_unchanged_interval` -1); the status page.
    None,
    /// Values brought by events: the stdout sink prints each.
    Events,
    /// Every value: MQTT publishing unchanged values again (`max_unchanged_interval` 0 or N).
    All,
}

impl Repeats {
    /// Whether a value that repeats the last one is reported. A pushbutton's every value is
    /// (MQTT publishes each: a press), whatever the sinks asked for.
    pub fn report(self, from_event: bool, pushbutton: bool) -> bool {
        pushbutton
            || match self {
                Self::None => false,
                Self::Events => from_event,
                Self::All => true,
            }
    }
}

/// Facts a device reports about itself.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DeviceIdentity {
    pub model: Option<String>,
    pub serial_number: Option<String>,
    pub firmware: Option<String>,
}

/// The error flags of a control's `meta/error`: `r` read failed, `w` write failed, `p` read
/// period missed; published in that order, empty when none is set.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct ErrorFlags {
    pub read: bool,
    pub write: bool,
    pub period_missed: bool,
}

impl fmt::Display for ErrorFlags {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (set, letter) in [
            (self.read, "r"),
            (self.write, "w"),
            (self.period_missed, "p"),
        ] {
            if set {
                f.write_str(letter)?;
            }
        }
        Ok(())
    }
}

/// From MQTT to the bus side: a client asked to set a control (`…/controls/<id>/on`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ControlWrite {
    pub device_id: String,
    pub control_id: String,
    pub payload: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_print_in_order() {
        assert_eq!(ErrorFlags::default().to_string(), "");
        let all = ErrorFlags {
            read: true,
            write: true,
            period_missed: true,
        };
        assert_eq!(all.to_string(), "rwp");
        assert_eq!(
            ErrorFlags {
                write: true,
                ..Default::default()
            }
            .to_string(),
            "w"
        );
    }
}
