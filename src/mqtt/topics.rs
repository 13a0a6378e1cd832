//! Topic names: the Wiren Board tree under an optional prefix, and the driver's own topics.

/// A topic prefix or client id that cannot be part of a topic.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TopicError {
    #[error("mqtt.topic_prefix `{0}` must not contain the MQTT wildcards `+` or `#`")]
    WildcardInPrefix(String),
    #[error("mqtt.homeassistant.prefix `{0}` must be a non-empty topic level without `+`, `#`")]
    BadDiscoveryPrefix(String),
}

/// Where rtu2mqtt's topics live. With `topic_prefix` = `site1` the WB layout moves under
/// `site1/devices/...`, so several controllers can share one broker.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicScheme {
    /// Prepended verbatim to `/devices/...` (trailing slashes removed).
    prefix: String,
    /// The client id with characters that do not belong in a topic level replaced.
    driver_node: String,
}

impl TopicScheme {
    pub fn new(topic_prefix: &str, client_id: &str) -> Result<Self, TopicError> {
        if topic_prefix.contains(['+', '#']) {
            return Err(TopicError::WildcardInPrefix(topic_prefix.to_string()));
        }
        Ok(Self {
            prefix: topic_prefix.trim_end_matches('/').to_string(),
            driver_node: topic_level(client_id),
        })
    }

    /// `<prefix>/devices/<dev>`.
    pub fn device(&self, device_id: &str) -> String {
        joined(&[&self.prefix, "/devices/", device_id])
    }

    pub fn device_meta(&self, device_id: &str, sub: Option<&str>) -> String {
        match sub {
            Some(sub) => joined(&[&self.prefix, "/devices/", device_id, "/meta/", sub]),
            None => joined(&[&self.prefix, "/devices/", device_id, "/meta"]),
        }
    }

    /// `<prefix>/devices/<dev>/controls/<ctl>`: the value topic.
    pub fn control(&self, device_id: &str, control_id: &str) -> String {
        self.under_control(device_id, control_id, &[])
    }

    pub fn control_meta(&self, device_id: &str, control_id: &str, sub: Option<&str>) -> String {
        match sub {
            Some(sub) => self.under_control(device_id, control_id, &["/meta/", sub]),
            None => self.under_control(device_id, control_id, &["/meta"]),
        }
    }

    /// Where clients ask to set a control.
    pub fn control_on(&self, device_id: &str, control_id: &str) -> String {
        self.under_control(device_id, control_id, &["/on"])
    }

    /// The control's topic followed by `tail`, built at its exact length.
    fn under_control(&self, device_id: &str, control_id: &str, tail: &[&str]) -> String {
        let mut topic = joined(&[
            &self.prefix,
            "/devices/",
            device_id,
            "/controls/",
            control_id,
        ]);
        topic.reserve_exact(tail.iter().map(|part| part.len()).sum());
        tail.iter().for_each(|part| topic.push_str(part));
        topic
    }

    /// The driver's own status: retained `online` while connected, `offline` as last will and
    /// on a clean exit. `<prefix>/rtu2mqtt/<client id>/status`.
    pub fn driver_status(&self) -> String {
        format!("{}/rtu2mqtt/{}/status", self.prefix, self.driver_node)
    }

    /// Retained `online` / `offline` per device, for Home Assistant's availability: unlike
    /// `meta/error`, whose "no error" is an empty (so never retained) payload, it is always
    /// there for a subscriber to read.
    pub fn device_availability(&self, device_id: &str) -> String {
        format!(
            "{}/rtu2mqtt/{}/availability/{device_id}",
            self.prefix, self.driver_node
        )
    }

    /// Retained list of the devices this driver publishes (JSON array of ids): read back at
    /// start to clear what a device dropped from the config left on the broker.
    pub fn driver_devices(&self) -> String {
        format!("{}/rtu2mqtt/{}/devices", self.prefix, self.driver_node)
    }

    /// Non-retained markers the driver sends itself to know that the broker has delivered the
    /// retained messages of its earlier subscriptions.
    pub fn driver_sweep_marker(&self) -> String {
        format!("{}/rtu2mqtt/{}/sweep", self.prefix, self.driver_node)
    }

    /// The client id as it appears in topics and Home Assistant ids.
    pub fn driver_node(&self) -> &str {
        &self.driver_node
    }
}

/// The parts one after the other, in a string of exactly their length: a device's topics are
/// held by the thousand (the retained state queued after a connect), so the slack that
/// `format!` leaves (up to half of a 40-byte topic) adds up.
fn joined(parts: &[&str]) -> String {
    let mut topic = String::with_capacity(parts.iter().map(|part| part.len()).sum());
    for part in parts {
        topic.push_str(part);
    }
    topic
}

/// `text` as one topic level / HA id: anything but ASCII letters, digits, `_` and `-` becomes
/// `_`; empty becomes `_`.
pub fn topic_level(text: &str) -> String {
    let level: String = text
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if level.is_empty() {
        "_".to_string()
    } else {
        level
    }
}

/// A Home Assistant discovery prefix (`homeassistant` by default) after checking it.
pub fn discovery_prefix(prefix: &str) -> Result<String, TopicError> {
    let trimmed = prefix.trim_matches('/');
    if trimmed.is_empty() || trimmed.contains(['+', '#']) {
        return Err(TopicError::BadDiscoveryPrefix(prefix.to_string()));
    }
    Ok(trimmed.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_layout_starts_with_a_slash() {
        let topics = TopicScheme::new("", "rtu2mqtt").unwrap();
        assert_eq!(
            topics.control("relay6", "K1"),
            "/devices/relay6/controls/K1"
        );
        assert_eq!(
            topics.control_meta("relay6", "K1", Some("error")),
            "/devices/relay6/controls/K1/meta/error"
        );
        assert_eq!(
            topics.control_on("relay6", "K1"),
            "/devices/relay6/controls/K1/on"
        );
        assert_eq!(topics.device_meta("relay6", None), "/devices/relay6/meta");
        assert_eq!(topics.driver_status(), "/rtu2mqtt/rtu2mqtt/status");
    }

    #[test]
    fn prefix_keeps_controllers_apart() {
        let topics = TopicScheme::new("site1/", "ctl a+b").unwrap();
        assert_eq!(topics.device("d"), "site1/devices/d");
        assert_eq!(topics.driver_status(), "site1/rtu2mqtt/ctl_a_b/status");
        assert!(TopicScheme::new("a/#", "x").is_err());
    }

    #[test]
    fn discovery_prefix_is_checked() {
        assert_eq!(discovery_prefix("homeassistant/").unwrap(), "homeassistant");
        assert!(discovery_prefix("").is_err());
        assert!(discovery_prefix("ha/+").is_err());
    }
}
