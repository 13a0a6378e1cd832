//! The whole gateway on virtual time, in one process: the port scheduler, the reply parser, the
//! simulator's pure [`Bus`], the device models and the MQTT planner, on a fake clock, with no
//! threads, no pty and no broker. A scenario runs in milliseconds and is exact: "no reply" and
//! "published within" are facts of the virtual wire, not of a busy machine.
//!
//! The wire between scheduler and bus is [`VirtualGateway::transact`]: the request goes on the
//! bus at `now`, the bus says which bytes come back and when (wire times of
//! `protocol::timing`), and the transport's own state machine (`transport::exchange`) decides
//! what counts as the reply, as it does on a real line.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use super::device_model::{apply_port_events, DeviceModel};
use super::port_plan::port_plan;
use crate::config::parse::SourceText;
use crate::config::TemplateLibrary;
use crate::mqtt::TopicScheme;
use crate::mqtt::{MqttAction, PlannerSettings, PublicationPlanner, UnchangedPolicy, WriteOutcome};
use crate::port::{Action, Outcome, PortScheduler, ReplyTiming, Transaction};
use crate::protocol::{LineSettings, RegisterType};
use crate::sim::bus::Bus;
use crate::sim::bus_file::{build_device, parse_line, DeviceEntry, TemplateSource};
use crate::sim::MasterLine;
use crate::transport::exchange::{Exchange, LinkConfig};
use crate::updates::{ControlWrite, DeviceUpdate};

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// One MQTT publication, at a virtual time.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Published {
    pub at: Duration,
    pub topic: String,
    pub payload: String,
}

pub struct VirtualGateway {
    /// Virtual time since start.
    pub now: Duration,
    epoch: Instant,
    line: LineSettings,
    scheduler: PortScheduler,
    models: Vec<DeviceModel>,
    planner: PublicationPlanner,
    pub bus: Bus,
    /// The broker's retained topics.
    pub retained: BTreeMap<String, String>,
    /// Every publication, in order.
    pub published: Vec<Published>,
    /// What the sinks were handed (the stdout sink prints these).
    pub updates: Vec<(Duration, DeviceUpdate)>,
    /// Since when the port has been unusable (`None`: it works).
    port_closed_since: Option<Duration>,
}

impl VirtualGateway {
    /// A port at `line` ("115200 8N2") with the shipped templates `devices` (template, slave
    /// id) on it, configured and simulated alike; Fast Modbus on.
    pub fn new(line: &str, devices: &[(&str, u8)]) -> Self {
        Self::with_fast_modbus(line, devices, true)
    }

    /// [`Self::new`] with the site-wide Fast Modbus switch (`fast_modbus` in the config).
    pub fn with_fast_modbus(line: &str, devices: &[(&str, u8)], fast_modbus: bool) -> Self {
        let settings = parse_line(line).expect("a line like 115200 8N2");
        let mut templates = TemplateSource::new(&repo("templates"), &repo("templates"));
        let simulated = devices
            .iter()
            .map(|&(template, address)| {
                let entry: DeviceEntry = serde_json::from_value(json!({
                    "template": template,
                    "address": address,
                    "serial": 0xFE00_0000u32 + u32::from(address),
                    "line": line,
                }))
                .expect("a bus entry");
                build_device(&entry, &mut templates).expect("a simulated device")
            })
            .collect();
        let config = json!({
            "ports": [{
                "path": "/dev/virtual",
                "baud_rate": settings.baud,
                "parity": settings.parity.letter().to_string(),
                "data_bits": settings.data_bits,
                "stop_bits": settings.stop_bits,
                "devices": devices
                    .iter()
                    .map(|(template, address)| json!({"device_type": template, "slave_id": address}))
                    .collect::<Vec<Value>>(),
            }]
        });
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("virtual.json"), &config.to_string()),
            false,
        )
        .expect("the config loads");
        let library = TemplateLibrary::load_dirs(&[repo("templates")]);
        let port = crate::device::resolve_config(&loaded, &library)
            .expect("the config resolves")
            .remove(0);
        let plan = port_plan(&port, fast_modbus);
        let mut gateway = Self {
            now: Duration::ZERO,
            epoch: Instant::now(),
            line: plan.settings.line,
            scheduler: PortScheduler::new(plan.settings, plan.devices),
            models: Vec::new(),
            planner: PublicationPlanner::new(PlannerSettings {
                topics: TopicScheme::new("", "rtu2mqtt").expect("default topics"),
                unchanged: UnchangedPolicy::OnChange,
                discovery: None,
                clear_discovery_on_exit: false,
            }),
            bus: Bus::new(simulated, 1),
            retained: BTreeMap::new(),
            published: Vec::new(),
            updates: Vec::new(),
            port_closed_since: None,
        };
        for (index, device) in port.devices.into_iter().enumerate() {
            let device = Arc::new(device);
            gateway.sink(vec![DeviceUpdate::Added(Arc::clone(&device))]);
            gateway.models.push(DeviceModel::new(device, index));
        }
        gateway
    }

    /// Runs the gateway until `now + duration`.
    pub fn run_for(&mut self, duration: Duration) {
        let end = self.now + duration;
        while self.now < end {
            if let Some(since) = self.port_closed_since {
                // As the port task does while it cannot open the port: wake every 500 ms.
                let events = self.scheduler.port_unavailable(self.now, since);
                self.hand_to_models(events);
                self.now = (self.now + Duration::from_millis(500)).min(end);
                continue;
            }
            match self.scheduler.next(self.now) {
                Action::Transmit(transaction) => {
                    let (outcome, timing, done) = self.transact(&transaction);
                    self.now = done;
                    let events = self.scheduler.complete_timed(self.now, outcome, timing);
                    self.hand_to_models(events);
                }
                Action::Wait { until } => {
                    self.now = until.clamp(self.now + Duration::from_micros(1), end);
                }
            }
        }
    }

    /// Runs until `topic` holds `payload` (retained), at most `limit`; returns when it did.
    pub fn run_until(&mut self, topic: &str, payload: &str, limit: Duration) -> Option<Duration> {
        let end = self.now + limit;
        while self.now < end {
            if self.retained.get(topic).map(String::as_str) == Some(payload) {
                return Some(self.now);
            }
            self.run_for(Duration::from_millis(1));
        }
        (self.retained.get(topic).map(String::as_str) == Some(payload)).then_some(self.now)
    }

    /// The port cannot be opened from now on (`false`), or works again.
    pub fn set_port_usable(&mut self, usable: bool) {
        self.port_closed_since = if usable { None } else { Some(self.now) };
    }

    /// A client publishes `payload` on `/devices/<device>/controls/<control>/on`; the write
    /// goes the way the daemon routes it (planner, then the device's model, then the queue).
    pub fn publish_on(&mut self, device: &str, control: &str, payload: &[u8]) {
        let topic = format!("/devices/{device}/controls/{control}/on");
        let WriteOutcome::Accepted(write) = self.planner.on_message(&topic, payload, false) else {
            return;
        };
        self.write(write);
    }

    /// As the port task takes a write: the model checks and encodes it, the scheduler queues it.
    fn write(&mut self, write: ControlWrite) {
        let Some(model) = self.models.iter_mut().find(|m| m.id() == write.device_id) else {
            return;
        };
        let mut updates = Vec::new();
        if let Ok(register_writes) =
            model.take_write(&write.control_id, &write.payload, &mut updates)
        {
            for register_write in register_writes {
                self.scheduler.queue_write(self.now, register_write);
            }
        }
        self.sink(updates);
    }

    /// The physical world changes a register of the simulated device at `address`.
    pub fn change(&mut self, address: u8, register_type: RegisterType, start: u16, values: &[u16]) {
        let index = self.device_index(address);
        self.bus
            .write_register(index, register_type, start, values, self.now)
            .expect("a register the device has");
    }

    /// A register of the simulated device at `address`.
    pub fn register(&self, address: u8, register_type: RegisterType, at: u16) -> Option<u16> {
        let device = self.bus.devices().get(self.device_index(address))?;
        device.registers().get(register_type, at)
    }

    pub fn set_plugged(&mut self, address: u8, plugged: bool) {
        let index = self.device_index(address);
        if let Some(device) = self.bus.device_mut(index) {
            device.plugged = plugged;
        }
    }

    /// The simulated device restarts: its event settings are gone.
    pub fn reboot(&mut self, address: u8) {
        let index = self.device_index(address);
        if let Some(device) = self.bus.device_mut(index) {
            device.reboot();
        }
    }

    /// Payloads published on `topic` since `since`, in order.
    pub fn published_on(&self, topic: &str, since: Duration) -> Vec<&str> {
        self.published
            .iter()
            .filter(|p| p.topic == topic && p.at >= since)
            .map(|p| p.payload.as_str())
            .collect()
    }

    fn device_index(&self, address: u8) -> usize {
        self.bus
            .devices()
            .iter()
            .position(|d| d.address() == address)
            .expect("a simulated device at that address")
    }

    fn hand_to_models(&mut self, events: Vec<crate::port::PortEvent>) {
        let mut updates = Vec::new();
        apply_port_events(&mut self.models, events, &mut updates);
        self.sink(updates);
    }

    fn sink(&mut self, updates: Vec<DeviceUpdate>) {
        for update in updates {
            self.updates.push((self.now, update.clone()));
            for action in self.planner.handle(update, self.epoch + self.now) {
                if let MqttAction::Publish(publication) = action {
                    if publication.retain {
                        if publication.payload.is_empty() {
                            self.retained.remove(&publication.topic);
                        } else {
                            self.retained
                                .insert(publication.topic.clone(), publication.payload.clone());
                        }
                    }
                    self.published.push(Published {
                        at: self.now,
                        topic: publication.topic,
                        payload: publication.payload,
                    });
                }
            }
        }
    }

    /// One transaction on the virtual wire: what came back, its timing, and when the line is
    /// free again. The transport's own state machine ([`Exchange`]) decides, as on a real line.
    fn transact(&mut self, transaction: &Transaction) -> (Outcome, ReplyTiming, Duration) {
        let start = self.now;
        let mut exchange = Exchange::new(LinkConfig::serial(self.line));
        let transmit = match exchange.start(transaction) {
            Ok(()) => exchange.poll_transmit(start),
            Err(_) => None,
        };
        let Some(transmit) = transmit else {
            return (Outcome::NoReply, ReplyTiming::default(), start);
        };
        let transmission = self
            .bus
            .exchange(&transmit.bytes, MasterLine::exact(self.line), start);
        exchange.handle_sent(start);
        let mut arrivals = transmission.arrivals().into_iter().peekable();
        let mut now = start;
        loop {
            if let Some((outcome, timing)) = exchange.poll_outcome() {
                return (outcome, timing, now);
            }
            let Some(timeout) = exchange.poll_timeout() else {
                return (Outcome::NoReply, ReplyTiming::default(), now);
            };
            match arrivals.peek() {
                Some(&(at, byte)) if at < timeout => {
                    now = now.max(at);
                    exchange.handle_bytes(now, &[byte]);
                    arrivals.next();
                }
                _ => {
                    now = now.max(timeout);
                    exchange.handle_timeout(now);
                }
            }
        }
    }
}
