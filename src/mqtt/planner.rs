//! The publication planner: what to publish for each [`DeviceUpdate`], given everything
//! published so far. Pure (the time comes in as an argument), so every rule of the layout —
//! `max_unchanged_interval`, removal, republishing after a reconnect — is tested without a
//! broker. Values, their changes and the error flags are the device model's
//! (`gateway::device_model`); this side only maps them to topics.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tracing::debug;

use super::discovery::{self, DiscoverySettings};
use super::layout;
use super::topics::TopicScheme;
use super::{MqttAction, Publication};
use crate::device::{ResolvedChannel, ResolvedDevice};
use crate::device_updates::{ControlWrite, DeviceIdentity, DeviceUpdate, ErrorFlags, Repeats};

/// When an unchanged value is published again (config `max_unchanged_interval`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnchangedPolicy {
    /// -1 (default): only changes.
    OnChange,
    /// 0: every read.
    EveryRead,
    /// N > 0: also after N s without a publish (at least 5 s, as in wb-mqtt-serial).
    After(Duration),
}

impl UnchangedPolicy {
    pub fn from_config(max_unchanged_interval: i64) -> Self {
        match max_unchanged_interval {
            i64::MIN..=-1 => Self::OnChange,
            0 => Self::EveryRead,
            n => Self::After(Duration::from_secs(n.max(5) as u64)),
        }
    }

    /// The values the device models must report besides the changes for this policy: the
    /// repeats it publishes again (all, checked here against the time), or none.
    pub fn repeats(self) -> Repeats {
        match self {
            Self::OnChange => Repeats::None,
            Self::EveryRead | Self::After(_) => Repeats::All,
        }
    }
}

/// What the planner needs to know.
#[derive(Debug, Clone)]
pub struct PlannerSettings {
    pub topics: TopicScheme,
    pub unchanged: UnchangedPolicy,
    /// Home Assistant discovery; None when disabled.
    pub discovery: Option<DiscoverySettings>,
    /// Also delete the discovery configs on a clean exit (HA then forgets the entities).
    pub clear_discovery_on_exit: bool,
}

/// The result of an `/on` message.
#[derive(Debug, Clone, PartialEq)]
pub enum WriteOutcome {
    /// Not a topic of a writable control.
    NotOurs,
    /// A retained `/on` message held by the broker, delivered when the driver subscribes (at
    /// start or after a reconnect): replaying it would repeat an old command, so it is ignored.
    /// (A retained `/on` published while the driver runs arrives live, without the retain flag
    /// (MQTT 3.1.1 §3.3.1.3), and is carried out like any other write.)
    IgnoredRetained,
    /// An empty payload: a client deleting a retained `/on` message. No command, and no bad
    /// write either.
    IgnoredEmpty,
    /// Hand `write` to the bus side, whose device model checks the payload (and sets `w` when
    /// it refuses it). Bytes that are not UTF-8 arrive there as U+FFFD, which it refuses.
    Accepted(ControlWrite),
}

/// What is published for one control (republished after a reconnect).
#[derive(Debug, Default)]
struct PublishedControl {
    /// Where its channel is in the device's channel list (found without comparing ids).
    channel: usize,
    /// Its channel is a pushbutton: every value is published, changed or not (known here so
    /// that a repeated value is passed over without looking at the channel).
    pushbutton: bool,
    value: Option<Arc<str>>,
    last_published: Option<Instant>,
    errors: ErrorFlags,
    published_errors: String,
    /// Its value was read by a port that restarted while the device was offline (a reload):
    /// not published again (after a reconnect, or as the device is announced again) until a
    /// read brings a value, which also clears the `r` kept from then.
    held: bool,
}

#[derive(Debug)]
struct PublishedDevice {
    device: Arc<ResolvedDevice>,
    identity: DeviceIdentity,
    /// What its port last said: online, offline, or nothing yet (not heard from). Its
    /// `meta/error` is `r` only while offline; its availability `online` only while online.
    online: Option<bool>,
    /// Its port has been this gateway's ([`DeviceUpdate::BusServed`]): its Wiren Board topics
    /// are deleted with it; before, only what is this gateway's own (discovery configs).
    bus_served: bool,
    controls: IdMap<PublishedControl>,
}

/// Turns [`DeviceUpdate`]s into broker actions and remembers the published state.
#[derive(Debug)]
pub struct PublicationPlanner {
    settings: PlannerSettings,
    /// By id. Hashed: every value looks its device up. Everything published for all devices
    /// goes in the order of their ids ([`Self::device_order`]).
    devices: IdMap<PublishedDevice>,
    /// `/on` topic → (device id, control id), for writable controls.
    on_topics: HashMap<String, (String, String)>,
}

impl PublicationPlanner {
    pub fn new(settings: PlannerSettings) -> Self {
        Self {
            settings,
            devices: IdMap::default(),
            on_topics: HashMap::new(),
        }
    }

    pub fn topics(&self) -> &TopicScheme {
        &self.settings.topics
    }

    /// Home Assistant's status topic, when discovery is on.
    pub fn discovery_status_topic(&self) -> Option<String> {
        self.settings.discovery.as_ref().map(|d| d.status_topic())
    }

    /// What to do on the broker for `update`, received at `now`.
    pub fn handle(&mut self, update: DeviceUpdate, now: Instant) -> Vec<MqttAction> {
        match update {
            DeviceUpdate::Added(device) => self.add_device(device),
            DeviceUpdate::Identity {
                device_id,
                identity,
            } => self.set_identity(&device_id, identity),
            DeviceUpdate::Removed { device_id } => self.remove_device(&device_id),
            DeviceUpdate::Value {
                device_id,
                control_id,
                value,
                from_event: _,
                changed,
            } => self.set_value(&device_id, &control_id, value, changed, now),
            DeviceUpdate::ControlError {
                device_id,
                control_id,
                errors,
            } => self.set_errors(&device_id, &control_id, errors),
            DeviceUpdate::Online { device_id, online } => self.set_online(&device_id, online),
            DeviceUpdate::BusServed { device_id } => {
                if let Some(state) = self.devices.get_mut(&device_id) {
                    state.bus_served = true;
                }
                Vec::new()
            }
        }
    }

    fn add_device(&mut self, device: Arc<ResolvedDevice>) -> Vec<MqttAction> {
        let mut out = Vec::new();
        let mut previous = self.devices.remove(&device.id);
        if let Some(old) = &previous {
            // A config change: delete what the new device no longer has.
            let keep: std::collections::HashSet<String> =
                self.device_topics(&device).into_iter().collect();
            for topic in self.own_device_topics(old) {
                if !keep.contains(&topic) {
                    out.push(MqttAction::Publish(Publication::removal(topic)));
                }
            }
            let new_discovery = self.discovery_topics(&device);
            for topic in self.discovery_topics(&old.device) {
                if !new_discovery.contains(&topic) {
                    out.push(MqttAction::Publish(Publication::removal(topic)));
                }
            }
            for channel in old
                .device
                .channels
                .iter()
                .filter(|c| layout::is_writable(c))
            {
                let still = device.channel(&channel.id).is_some_and(layout::is_writable);
                if !still {
                    let topic = self.settings.topics.control_on(&device.id, &channel.id);
                    self.on_topics.remove(&topic);
                    out.push(MqttAction::Unsubscribe(topic));
                }
            }
        }
        // Announced again when its port restarts (a reload) while its old port knew it offline:
        // the daemon starts its new device model as known offline, with `r` on every readable
        // control (`DeviceModel::known_offline`).
        let was_offline = previous.as_ref().is_some_and(|p| p.online == Some(false));
        let mut controls = IdMap::default();
        for channel in &device.channels {
            let mut state = previous
                .as_mut()
                .and_then(|p| p.controls.remove(&channel.id))
                .unwrap_or_default();
            // A device is announced again when its port restarts (a reload): its new device
            // model reports only what it sets or clears itself, so a flag kept here that the
            // model does not hold would never be cleared. Every control starts with the flags
            // its new model starts with: empty, as wb-mqtt-serial starts it, and set again as
            // the model learns (a device never heard from goes offline at its first failure);
            // but a device known offline keeps `r` on its readable controls, as its new model
            // does, until a read succeeds, and its old values are not sent again as if fresh.
            state.errors = ErrorFlags {
                read: was_offline && channel.is_read(),
                ..ErrorFlags::default()
            };
            state.held |= was_offline && channel.is_read();
            controls.insert(channel.id.clone(), state);
        }
        // The first channel of an id is the one values go to.
        for (index, channel) in device.channels.iter().enumerate().rev() {
            if let Some(control) = controls.get_mut(&channel.id) {
                control.channel = index;
                control.pushbutton = layout::is_pushbutton(channel);
            }
        }
        let (identity, online, bus_served) = previous
            .map(|p| (p.identity, p.online, p.bus_served))
            .unwrap_or((DeviceIdentity::default(), None, false));
        let mut state = PublishedDevice {
            device: device.clone(),
            identity,
            online,
            bus_served,
            controls,
        };
        out.extend(self.device_actions(&mut state, false));
        for channel in device.channels.iter().filter(|c| layout::is_writable(c)) {
            let topic = self.settings.topics.control_on(&device.id, &channel.id);
            self.on_topics
                .insert(topic.clone(), (device.id.clone(), channel.id.clone()));
        }
        self.devices.insert(device.id.clone(), state);
        out
    }

    /// Subscriptions, meta, errors, (with `values`) the last values, and discovery configs of
    /// one device, in the order a reader should see them.
    fn device_actions(&self, state: &mut PublishedDevice, values: bool) -> Vec<MqttAction> {
        let topics = &self.settings.topics;
        let device = state.device.clone();
        let mut out = Vec::new();
        for channel in device.channels.iter().filter(|c| layout::is_writable(c)) {
            out.push(MqttAction::Subscribe(
                topics.control_on(&device.id, &channel.id),
            ));
        }
        let mut publications = layout::device_meta(topics, &device, &state.identity);
        publications.push(layout::device_error(
            topics,
            &device.id,
            state.online != Some(false),
        ));
        if self.settings.discovery.is_some() {
            publications.push(availability(topics, &device.id, state.online == Some(true)));
        }
        for channel in &device.channels {
            publications.extend(layout::control_meta(topics, &device.id, channel));
            let control = state.controls.entry(channel.id.clone()).or_default();
            control.published_errors = control.errors.to_string();
            publications.push(layout::control_error(
                topics,
                &device.id,
                &channel.id,
                &control.published_errors,
            ));
            if let (true, false, false, Some(value)) = (
                values,
                layout::is_pushbutton(channel),
                control.held,
                &control.value,
            ) {
                publications.push(layout::control_value(topics, &device.id, channel, value));
            }
        }
        publications.extend(self.discovery_configs(&device, &state.identity));
        out.extend(publications.into_iter().map(MqttAction::Publish));
        out
    }

    fn discovery_configs(
        &self,
        device: &ResolvedDevice,
        identity: &DeviceIdentity,
    ) -> Vec<Publication> {
        let Some(settings) = &self.settings.discovery else {
            return Vec::new();
        };
        discovery::device_configs(settings, &self.settings.topics, device, identity)
            .into_iter()
            .map(|c| Publication::retained(c.topic, c.payload.to_string()))
            .collect()
    }

    /// The discovery configs' topics of `device` (none with discovery off).
    fn discovery_topics(&self, device: &ResolvedDevice) -> Vec<String> {
        let Some(settings) = &self.settings.discovery else {
            return Vec::new();
        };
        device
            .channels
            .iter()
            .filter_map(|c| discovery::config_topic(settings, &self.settings.topics, &device.id, c))
            .collect()
    }

    fn device_topics(&self, device: &ResolvedDevice) -> Vec<String> {
        let mut topics = layout::device_topics(&self.settings.topics, device);
        if self.settings.discovery.is_none() {
            let availability = self.settings.topics.device_availability(&device.id);
            topics.retain(|t| *t != availability);
        }
        topics
    }

    /// The device's topics that are this gateway's to delete: all of them once its bus has been
    /// served here; before, only its availability topic (in the driver's own tree): the Wiren
    /// Board tree may be another gateway's that holds the port.
    fn own_device_topics(&self, state: &PublishedDevice) -> Vec<String> {
        let mut topics = self.device_topics(&state.device);
        if !state.bus_served {
            let availability = self.settings.topics.device_availability(&state.device.id);
            topics.retain(|t| *t == availability);
        }
        topics
    }

    fn set_identity(&mut self, device_id: &str, identity: DeviceIdentity) -> Vec<MqttAction> {
        let Some(state) = self.devices.get(device_id) else {
            debug!(device_id, "identity of a device not announced yet, ignored");
            return Vec::new();
        };
        if state.identity == identity {
            return Vec::new();
        }
        let mut publications = layout::device_meta(&self.settings.topics, &state.device, &identity);
        publications.extend(self.discovery_configs(&state.device, &identity));
        if let Some(state) = self.devices.get_mut(device_id) {
            state.identity = identity;
        }
        publications.into_iter().map(MqttAction::Publish).collect()
    }

    fn remove_device(&mut self, device_id: &str) -> Vec<MqttAction> {
        let Some(state) = self.devices.remove(device_id) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for channel in state
            .device
            .channels
            .iter()
            .filter(|c| layout::is_writable(c))
        {
            let topic = self.settings.topics.control_on(device_id, &channel.id);
            self.on_topics.remove(&topic);
            out.push(MqttAction::Unsubscribe(topic));
        }
        out.extend(self.removal(&state, true));
        out
    }

    /// Empty retained payloads for every topic of a device (discovery configs included when
    /// `with_discovery`).
    fn removal(&self, state: &PublishedDevice, with_discovery: bool) -> Vec<MqttAction> {
        let mut topics = Vec::new();
        if with_discovery {
            topics.extend(self.discovery_topics(&state.device));
        }
        topics.extend(self.own_device_topics(state));
        topics
            .into_iter()
            .map(|t| MqttAction::Publish(Publication::removal(t)))
            .collect()
    }

    fn set_value(
        &mut self,
        device_id: &str,
        control_id: &str,
        value: Arc<str>,
        changed: bool,
        now: Instant,
    ) -> Vec<MqttAction> {
        let topics = &self.settings.topics;
        let unchanged_policy = self.settings.unchanged;
        let Some((device, control)) = lookup_control(&mut self.devices, device_id, control_id)
        else {
            debug!(
                device_id,
                control_id, "value of an unknown control, ignored"
            );
            return Vec::new();
        };
        let mut out = Vec::new();
        if control.held {
            // The first value since its port restarted with the device offline. Its new model
            // cleared the `r` it started with before this value; should it not have (it did not
            // start as known offline), the value clears it here, before the value goes out.
            control.held = false;
            if control.errors.read {
                control.errors.read = false;
                out.extend(error_if_changed(topics, device_id, control_id, control));
            }
        }
        let due = match unchanged_policy {
            UnchangedPolicy::OnChange => false,
            UnchangedPolicy::EveryRead => true,
            UnchangedPolicy::After(interval) => control
                .last_published
                .is_none_or(|t| now.saturating_duration_since(t) >= interval),
        };
        if changed || due || control.pushbutton {
            let Some(channel) = channel_of(device, control, control_id) else {
                debug!(
                    device_id,
                    control_id, "value of a control without a channel, ignored"
                );
                return Vec::new();
            };
            out.push(MqttAction::Publish(layout::control_value(
                topics, device_id, channel, &value,
            )));
            control.last_published = Some(now);
        }
        control.value = Some(value);
        out
    }

    fn set_errors(
        &mut self,
        device_id: &str,
        control_id: &str,
        errors: ErrorFlags,
    ) -> Vec<MqttAction> {
        let topics = &self.settings.topics;
        let Some((_, control)) = lookup(&mut self.devices, device_id, control_id) else {
            debug!(
                device_id,
                control_id, "errors of an unknown control, ignored"
            );
            return Vec::new();
        };
        control.errors = errors;
        error_if_changed(topics, device_id, control_id, control)
            .into_iter()
            .collect()
    }

    fn set_online(&mut self, device_id: &str, online: bool) -> Vec<MqttAction> {
        let with_availability = self.settings.discovery.is_some();
        let topics = &self.settings.topics;
        let Some(state) = self.devices.get_mut(device_id) else {
            debug!(device_id, "state of an unknown device, ignored");
            return Vec::new();
        };
        let before = state.online.replace(online);
        let mut out = Vec::new();
        // `meta/error` is empty until the device is found offline, as wb-mqtt-serial has it.
        if (before != Some(false)) != online {
            out.push(MqttAction::Publish(layout::device_error(
                topics, device_id, online,
            )));
        }
        // The availability is `offline` until the device has answered once.
        if with_availability && (before == Some(true)) != online {
            out.push(MqttAction::Publish(availability(topics, device_id, online)));
        }
        out
    }

    /// An `/on` message: mapped to the control's write, or ignored.
    pub fn on_message(&self, topic: &str, payload: &[u8], retained: bool) -> WriteOutcome {
        let Some((device_id, control_id)) = self.on_topics.get(topic).cloned() else {
            return WriteOutcome::NotOurs;
        };
        if payload.is_empty() {
            return WriteOutcome::IgnoredEmpty;
        }
        if retained {
            return WriteOutcome::IgnoredRetained;
        }
        WriteOutcome::Accepted(ControlWrite {
            device_id,
            control_id,
            payload: String::from_utf8_lossy(payload).into_owned(),
        })
    }

    /// Everything to (re)do after connecting: subscriptions, then every retained topic with
    /// its current payload (a restarted broker may have lost them all). All devices at once:
    /// the client builds it one device at a time ([`Self::device_order`],
    /// [`Self::device_snapshot`]) so that only one device's actions are held.
    pub fn snapshot(&mut self) -> Vec<MqttAction> {
        let ids = self.device_order();
        ids.iter().flat_map(|id| self.device_snapshot(id)).collect()
    }

    /// Everything to (re)do for one device after connecting, from its current state; nothing
    /// for a device no longer served.
    pub fn device_snapshot(&mut self, device_id: &str) -> Vec<MqttAction> {
        let Some(mut state) = self.devices.remove(device_id) else {
            return Vec::new();
        };
        let out = self.device_actions(&mut state, true);
        self.devices.insert(device_id.to_owned(), state);
        out
    }

    /// Every discovery config again (Home Assistant announced itself `online`).
    pub fn discovery_snapshot(&self) -> Vec<MqttAction> {
        self.device_order()
            .iter()
            .flat_map(|id| self.device_discovery(id))
            .collect()
    }

    /// One device's discovery configs; nothing for a device no longer served.
    pub fn device_discovery(&self, device_id: &str) -> Vec<MqttAction> {
        self.devices.get(device_id).map_or_else(Vec::new, |s| {
            self.discovery_configs(&s.device, &s.identity)
                .into_iter()
                .map(MqttAction::Publish)
                .collect()
        })
    }

    /// Clean exit: delete every retained topic of every device (discovery configs only when
    /// `clear_discovery_on_exit`).
    pub fn clear_all(&self) -> Vec<MqttAction> {
        self.device_order()
            .iter()
            .flat_map(|id| self.device_clear(id))
            .collect()
    }

    /// [`Self::clear_all`] for one device.
    pub fn device_clear(&self, device_id: &str) -> Vec<MqttAction> {
        let with_discovery = self.settings.clear_discovery_on_exit;
        self.devices
            .get(device_id)
            .map_or_else(Vec::new, |s| self.removal(s, with_discovery))
    }

    /// The ids of the devices, in the order everything published for all of them goes.
    pub fn device_order(&self) -> Vec<String> {
        let mut ids: Vec<String> = self.devices.keys().cloned().collect();
        ids.sort_unstable();
        ids
    }

    /// The ids of the devices served.
    pub fn device_ids(&self) -> std::collections::BTreeSet<String> {
        self.devices.keys().cloned().collect()
    }

    /// Writable controls' `/on` topics.
    pub fn subscriptions(&self) -> Vec<String> {
        let mut topics: Vec<String> = self.on_topics.keys().cloned().collect();
        topics.sort();
        topics
    }
}

impl super::sweep::Served for PublicationPlanner {
    fn device_ids(&self) -> std::collections::BTreeSet<String> {
        PublicationPlanner::device_ids(self)
    }

    fn has_control(&self, device_id: &str, control_id: &str) -> bool {
        self.devices
            .get(device_id)
            .is_some_and(|state| state.controls.contains_key(control_id))
    }

    fn has_discovery_config(&self, device_id: &str, topic: &str) -> bool {
        let (Some(settings), Some(state)) = (&self.settings.discovery, self.devices.get(device_id))
        else {
            return false;
        };
        state.device.channels.iter().any(|channel| {
            discovery::config_topic(settings, &self.settings.topics, device_id, channel)
                .is_some_and(|t| t == topic)
        })
    }
}

/// By device or control id, hashed with [`IdHasher`].
type IdMap<V> = HashMap<String, V, BuildHasherDefault<IdHasher>>;

/// FxHash's multiply-rotate, 8 bytes at a time: every value looks its device and control up by
/// id (twice SipHash's rounds over short ids, per value, before). The ids come from the
/// config, not from the network, so SipHash's protection against crafted keys buys nothing
/// here; `/on` topics, which do come from the network, keep it.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct IdHasher(u64);

impl IdHasher {
    fn add(&mut self, word: u64) {
        self.0 = (self.0.rotate_left(5) ^ word).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

impl Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        let mut chunks = bytes.chunks_exact(8);
        for chunk in &mut chunks {
            let mut word = [0; 8];
            word.copy_from_slice(chunk);
            self.add(u64::from_le_bytes(word));
        }
        let rest = chunks.remainder();
        if !rest.is_empty() {
            let mut word = [0; 8];
            word[..rest.len()].copy_from_slice(rest);
            self.add(u64::from_le_bytes(word));
        }
    }

    fn write_u8(&mut self, n: u8) {
        self.add(u64::from(n));
    }

    fn write_usize(&mut self, n: usize) {
        self.add(n as u64);
    }
}

fn lookup<'a>(
    devices: &'a mut IdMap<PublishedDevice>,
    device_id: &str,
    control_id: &str,
) -> Option<(&'a ResolvedChannel, &'a mut PublishedControl)> {
    let (device, control) = lookup_control(devices, device_id, control_id)?;
    let channel = channel_of(device, control, control_id)?;
    Some((channel, control))
}

/// The device and the published state of one of its controls; its channel is looked at only
/// when needed ([`channel_of`]): most values repeat the last one and publish nothing.
fn lookup_control<'a>(
    devices: &'a mut IdMap<PublishedDevice>,
    device_id: &str,
    control_id: &str,
) -> Option<(&'a ResolvedDevice, &'a mut PublishedControl)> {
    let state = devices.get_mut(device_id)?;
    let control = state.controls.get_mut(control_id)?;
    Some((&state.device, control))
}

fn channel_of<'a>(
    device: &'a ResolvedDevice,
    control: &PublishedControl,
    control_id: &str,
) -> Option<&'a ResolvedChannel> {
    match device.channels.get(control.channel) {
        Some(channel) if channel.id == control_id => Some(channel),
        _ => device.channels.iter().find(|c| c.id == control_id),
    }
}

fn error_if_changed(
    topics: &TopicScheme,
    device_id: &str,
    control_id: &str,
    control: &mut PublishedControl,
) -> Option<MqttAction> {
    let letters = control.errors.to_string();
    if letters == control.published_errors {
        return None;
    }
    control.published_errors = letters;
    Some(MqttAction::Publish(layout::control_error(
        topics,
        device_id,
        control_id,
        &control.published_errors,
    )))
}

fn availability(topics: &TopicScheme, device_id: &str, online: bool) -> Publication {
    Publication::retained(
        topics.device_availability(device_id),
        if online { "online" } else { "offline" },
    )
}

#[cfg(test)]
#[path = "planner_tests.rs"]
mod tests;
