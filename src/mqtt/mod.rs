//! MQTT side: the Wiren Board topic layout, Home Assistant discovery, `/on` writes, and the
//! client task that owns the broker connection.
//!
//! Everything but [`client`] is pure: [`PublicationPlanner`] turns [`DeviceUpdate`]s (and the
//! time, passed in) into [`MqttAction`]s, and `/on` messages into [`ControlWrite`]s; the client
//! task only moves those to and from rumqttc. See `docs/mqtt.md` for the layout.
//!
//! [`DeviceUpdate`]: crate::device_updates::DeviceUpdate
//! [`ControlWrite`]: crate::device_updates::ControlWrite

pub mod client;
pub mod discovery;
pub mod layout;
pub mod outbox;
pub mod pending_writes;
pub mod planner;
pub mod sweep;
pub mod throttle;
pub mod topics;

pub use client::{run_mqtt, run_mqtt_reporting, MqttError, MqttSettings};
pub use planner::{PlannerSettings, PublicationPlanner, UnchangedPolicy, WriteOutcome};
pub use topics::TopicScheme;

pub use rumqttc::QoS;

/// One MQTT publish the driver wants on the broker.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Publication {
    pub topic: String,
    pub payload: String,
    pub retain: bool,
    pub qos: QoS,
}

impl Publication {
    /// Retained, QoS 1: how every meta, error and value topic is published.
    pub fn retained(topic: impl Into<String>, payload: impl Into<String>) -> Self {
        Self {
            topic: topic.into(),
            payload: payload.into(),
            retain: true,
            qos: QoS::AtLeastOnce,
        }
    }

    /// Not retained, QoS 1 (pushbutton presses).
    pub fn transient(topic: impl Into<String>, payload: impl Into<String>) -> Self {
        Self {
            retain: false,
            ..Self::retained(topic, payload)
        }
    }

    /// The empty retained payload that deletes `topic` from the broker.
    pub fn removal(topic: impl Into<String>) -> Self {
        Self::retained(topic, "")
    }
}

/// What the client task must do on the broker, in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MqttAction {
    Publish(Publication),
    /// Subscribe (QoS 1) to a writable control's `/on` topic.
    Subscribe(String),
    Unsubscribe(String),
}
