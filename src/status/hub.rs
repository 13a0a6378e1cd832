//! The ports the status server can show, and the views built from them when someone asks: the
//! JSON of `/api/status`, the Prometheus text of `/metrics`, a device's decoded frames.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use serde_json::{json, Value};
use tokio::sync::mpsc;
use tokio::time::Instant;

use super::stats::{ErrorCounts, PortStats, LATENCY_BOUNDS_MS};
use crate::device::ResolvedDevice;
use crate::device_updates::ControlWrite;
use crate::port::TransactionOutcome;

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What the page asks a port task to do (taken between transactions).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortCommand {
    /// Hold or resume the polling of the port's `device`-th device.
    Suspend { device: usize, suspended: bool },
}

impl PortCommand {
    /// The device it is for: a newer command for the same device replaces a waiting one.
    fn device(&self) -> usize {
        match self {
            Self::Suspend { device, .. } => *device,
        }
    }
}

/// One port as the status page shows it: what it was configured with, and its counters, which
/// its port task updates.
#[derive(Debug)]
pub struct PortStatus {
    pub name: String,
    /// The port's settings (its config section without the devices).
    pub settings: Value,
    pub devices: Vec<Arc<ResolvedDevice>>,
    /// The port task's clock starts here: the stats' times count from it.
    pub epoch: Instant,
    pub stats: Mutex<PortStats>,
    /// At most one per device, the latest: while the port is closed its task takes none, and
    /// clicks must neither pile up nor be replayed when it reopens.
    commands: Mutex<Vec<PortCommand>>,
    /// Commands are waiting: the port task looks at the lock only then.
    commands_pending: AtomicBool,
}

impl PortStatus {
    pub fn new(name: &str, settings: Value, devices: Vec<Arc<ResolvedDevice>>) -> Self {
        let ids: Vec<(String, u8)> = devices
            .iter()
            .map(|device| (device.id.clone(), device.slave_id))
            .collect();
        Self {
            name: name.to_string(),
            settings,
            devices,
            epoch: Instant::now(),
            stats: Mutex::new(PortStats::new(&ids)),
            commands: Mutex::new(Vec::new()),
            commands_pending: AtomicBool::new(false),
        }
    }

    /// Queues `command` in place of one still waiting for the same device.
    fn push_command(&self, command: PortCommand) {
        let mut commands = lock(&self.commands);
        commands.retain(|waiting| waiting.device() != command.device());
        commands.push(command);
        drop(commands);
        self.commands_pending.store(true, Ordering::Release);
    }

    /// The commands since the last call (the port task's side).
    pub fn take_commands(&self) -> Vec<PortCommand> {
        if !self.commands_pending.swap(false, Ordering::Acquire) {
            return Vec::new();
        }
        std::mem::take(&mut *lock(&self.commands))
    }

    /// Runs `change` on the counters (the port task's one way in).
    pub fn record<R>(&self, change: impl FnOnce(&mut PortStats) -> R) -> R {
        change(&mut lock(&self.stats))
    }

    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }
}

/// Everything the status server shows; shared by the port tasks (which register here) and the
/// server. Exists only when the server is configured.
#[derive(Debug)]
pub struct StatusHub {
    started: Instant,
    ports: Mutex<Vec<Arc<PortStatus>>>,
    /// Where writes from the page go: the queue MQTT `/on` writes go to.
    writes: Mutex<Option<mpsc::Sender<ControlWrite>>>,
    /// The running ports' bus queues: a scan from the page goes through them as an RPC does.
    directory: Mutex<Option<crate::daemon::PortDirectory>>,
}

impl Default for StatusHub {
    fn default() -> Self {
        Self::new()
    }
}

/// Why a write from the page was not queued.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WriteRefused {
    UnknownDevice,
    UnknownControl,
    ReadOnly,
    NotRunning,
}

impl StatusHub {
    pub fn new() -> Self {
        Self {
            started: Instant::now(),
            ports: Mutex::new(Vec::new()),
            writes: Mutex::new(None),
            directory: Mutex::new(None),
        }
    }

    pub fn set_port_directory(&self, directory: crate::daemon::PortDirectory) {
        *lock(&self.directory) = Some(directory);
    }

    /// A Fast Modbus scan of the port named `port` (as the page shows it), through its bus queue
    /// as the RPC `port/Scan` runs it: between the daemon's own transactions, at the port's
    /// settings. The report as the RPC returns it, or what went wrong in words.
    pub async fn scan(&self, port: &str) -> Result<Value, String> {
        let directory = lock(&self.directory)
            .clone()
            .ok_or("the bus side is not running")?;
        let access = lock(&directory)
            .values()
            .find(|access| access.name == port)
            .cloned()
            .ok_or_else(|| format!("no running port `{port}`"))?;
        let config = &access.resolved.config;
        let params = match (&config.path, &config.address) {
            (Some(path), _) => json!({"path": path}),
            (None, Some(address)) => {
                json!({"ip": address, "port": config.port.unwrap_or_default()})
            }
            (None, None) => return Err(format!("port `{port}` has neither a path nor an address")),
        };
        let method = crate::rpc::params::parse_method("port", "Scan", &params)
            .map_err(|err| err.to_string())?;
        crate::rpc::methods::execute(&directory, method)
            .await
            .map_err(|err| err.to_string())
    }

    pub fn add_port(&self, port: Arc<PortStatus>) {
        lock(&self.ports).push(port);
    }

    pub fn remove_port(&self, port: &Arc<PortStatus>) {
        lock(&self.ports).retain(|p| !Arc::ptr_eq(p, port));
    }

    pub fn set_writes(&self, writes: mpsc::Sender<ControlWrite>) {
        *lock(&self.writes) = Some(writes);
    }

    fn ports(&self) -> Vec<Arc<PortStatus>> {
        lock(&self.ports).clone()
    }

    /// Queues a write to a control as MQTT's `…/on` would.
    pub fn write(&self, device: &str, control: &str, value: &str) -> Result<(), WriteRefused> {
        let ports = self.ports();
        let channel = ports
            .iter()
            .flat_map(|port| port.devices.iter())
            .find(|d| d.id == device)
            .ok_or(WriteRefused::UnknownDevice)?
            .channels
            .iter()
            .find(|c| c.id == control)
            .cloned()
            .ok_or(WriteRefused::UnknownControl)?;
        if channel.readonly {
            return Err(WriteRefused::ReadOnly);
        }
        let writes = lock(&self.writes).clone().ok_or(WriteRefused::NotRunning)?;
        writes
            .try_send(ControlWrite {
                device_id: device.to_string(),
                control_id: control.to_string(),
                payload: value.to_string(),
            })
            .map_err(|_| WriteRefused::NotRunning)
    }

    /// Holds or resumes the polling of a device; false for an unknown device.
    pub fn suspend(&self, device: &str, suspended: bool) -> bool {
        for port in self.ports() {
            if let Some(index) = port.devices.iter().position(|d| d.id == device) {
                port.push_command(PortCommand::Suspend {
                    device: index,
                    suspended,
                });
                return true;
            }
        }
        false
    }

    /// The JSON the page shows (`/api/status`).
    pub fn snapshot(&self) -> Value {
        let ports: Vec<Value> = self.ports().iter().map(|port| port_json(port)).collect();
        json!({
            "version": env!("CARGO_PKG_VERSION"),
            "uptime_s": self.started.elapsed().as_secs(),
            "latency_bounds_ms": LATENCY_BOUNDS_MS,
            "ports": ports,
        })
    }

    /// A device's recent frames, decoded as `rtu2mqtt decode` does; `None` for an unknown device.
    pub fn frames(&self, device_id: &str) -> Option<Value> {
        for port in self.ports() {
            let Some(index) = port.devices.iter().position(|d| d.id == device_id) else {
                continue;
            };
            let now = port.now();
            let frames: Vec<_> = port.record(|stats| {
                stats
                    .devices
                    .get(index)
                    .map(|d| d.frames.iter().cloned().collect())
                    .unwrap_or_default()
            });
            let list: Vec<Value> = frames
                .iter()
                .rev()
                .map(|frame| {
                    let request = crate::cli::decode::explain_request(&frame.request);
                    let request_hex = frame.request.encode().map(|b| hex(&b)).unwrap_or_default();
                    let (reply, reply_hex) = match &frame.outcome {
                        TransactionOutcome::Reply(reply) => (
                            crate::cli::decode::explain_reply(reply),
                            reply.encode().map(|b| hex(&b)).unwrap_or_default(),
                        ),
                        TransactionOutcome::NoReply => (
                            crate::cli::decode::Reading {
                                summary: "no reply (timeout)".to_string(),
                                details: Vec::new(),
                            },
                            String::new(),
                        ),
                        TransactionOutcome::Garbled => (
                            crate::cli::decode::Reading {
                                summary: "bytes without a valid frame (bad CRC or collision)"
                                    .to_string(),
                                details: Vec::new(),
                            },
                            String::new(),
                        ),
                    };
                    json!({
                        "ago_ms": now.saturating_sub(frame.at).as_millis() as u64,
                        "took_ms": frame.took.as_secs_f64() * 1000.0,
                        "request": request.summary,
                        "request_details": request.details,
                        "request_hex": request_hex,
                        "reply": reply.summary,
                        "reply_details": reply.details,
                        "reply_hex": reply_hex,
                    })
                })
                .collect();
            return Some(json!({"device": device_id, "port": port.name, "frames": list}));
        }
        None
    }

    /// Prometheus text exposition format (version 0.0.4).
    pub fn metrics(&self) -> String {
        let ports = self.ports();
        let mut out = String::new();
        let views: Vec<(Arc<PortStatus>, PortStats, Duration)> = ports
            .iter()
            .map(|port| {
                let stats = port.record(|s| s.copy_without_frames());
                (Arc::clone(port), stats, port.now())
            })
            .collect();
        let mut family =
            |name: &str, kind: &str, help: &str, samples: &mut dyn FnMut(&mut String)| {
                let _ = writeln!(out, "# HELP {name} {help}");
                let _ = writeln!(out, "# TYPE {name} {kind}");
                samples(&mut out);
            };
        family(
            "rtu2mqtt_port_open",
            "gauge",
            "1 while the port is open.",
            &mut |out| {
                for (port, stats, _) in &views {
                    sample(
                        out,
                        "rtu2mqtt_port_open",
                        &[("port", &port.name)],
                        u64::from(stats.open) as f64,
                    );
                }
            },
        );
        family(
            "rtu2mqtt_transactions_total",
            "counter",
            "Requests sent on the bus (with their replies or timeouts).",
            &mut |out| {
                for (port, stats, _) in &views {
                    sample(
                        out,
                        "rtu2mqtt_transactions_total",
                        &[("port", &port.name)],
                        stats.totals.transactions as f64,
                    );
                }
            },
        );
        family(
            "rtu2mqtt_event_rounds_total",
            "counter",
            "Fast Modbus event requests sent.",
            &mut |out| {
                for (port, stats, _) in &views {
                    sample(
                        out,
                        "rtu2mqtt_event_rounds_total",
                        &[("port", &port.name)],
                        stats.totals.event_rounds as f64,
                    );
                }
            },
        );
        family(
            "rtu2mqtt_errors_total",
            "counter",
            "Failed transactions by kind: timeout, bad_crc, exception, another_master (a reply not \
             taken: another master had just asked the device).",
            &mut |out| {
                for (port, stats, _) in &views {
                    error_samples(
                        out,
                        "rtu2mqtt_errors_total",
                        &[("port", &port.name)],
                        &stats.totals.errors,
                    );
                }
            },
        );
        family(
            "rtu2mqtt_bus_busy_seconds_total",
            "counter",
            "Time the line was busy with transactions.",
            &mut |out| {
                for (port, stats, _) in &views {
                    sample(
                        out,
                        "rtu2mqtt_bus_busy_seconds_total",
                        &[("port", &port.name)],
                        stats.totals.busy.as_secs_f64(),
                    );
                }
            },
        );
        family(
            "rtu2mqtt_bus_utilisation_ratio",
            "gauge",
            "Share of the last 10 s the line was busy (0..1).",
            &mut |out| {
                for (port, stats, now) in &views {
                    let ratio = stats.rates(*now).bus_utilisation_percent / 100.0;
                    sample(
                        out,
                        "rtu2mqtt_bus_utilisation_ratio",
                        &[("port", &port.name)],
                        ratio,
                    );
                }
            },
        );
        family(
            "rtu2mqtt_event_round_trip_seconds",
            "histogram",
            "From the first event request that could have carried a change to its hand-over to MQTT.",
            &mut |out| {
                for (port, stats, _) in &views {
                    let name = "rtu2mqtt_event_round_trip_seconds";
                    let histogram = &stats.event_latency;
                    for (bound, count) in LATENCY_BOUNDS_MS.iter().zip(histogram.counts.iter()) {
                        let le = format!("{}", *bound as f64 / 1000.0);
                        sample(out, &format!("{name}_bucket"), &[("port", &port.name), ("le", &le)], *count as f64);
                    }
                    sample(out, &format!("{name}_bucket"), &[("port", &port.name), ("le", "+Inf")], histogram.count as f64);
                    sample(out, &format!("{name}_sum"), &[("port", &port.name)], histogram.sum.as_secs_f64());
                    sample(out, &format!("{name}_count"), &[("port", &port.name)], histogram.count as f64);
                }
            },
        );
        family(
            "rtu2mqtt_device_online",
            "gauge",
            "1 while the device answers.",
            &mut |out| {
                for (port, stats, _) in &views {
                    for (device, dstats) in port.devices.iter().zip(&stats.devices) {
                        sample(
                            out,
                            "rtu2mqtt_device_online",
                            &[("port", &port.name), ("device", &device.id)],
                            u64::from(dstats.online) as f64,
                        );
                    }
                }
            },
        );
        family(
            "rtu2mqtt_device_transactions_total",
            "counter",
            "Requests to the device (event rounds it won included).",
            &mut |out| {
                for (port, stats, _) in &views {
                    for (device, dstats) in port.devices.iter().zip(&stats.devices) {
                        sample(
                            out,
                            "rtu2mqtt_device_transactions_total",
                            &[("port", &port.name), ("device", &device.id)],
                            dstats.transactions as f64,
                        );
                    }
                }
            },
        );
        family(
            "rtu2mqtt_device_errors_total",
            "counter",
            "Failed requests to the device by kind: timeout, bad_crc, exception, another_master.",
            &mut |out| {
                for (port, stats, _) in &views {
                    for (device, dstats) in port.devices.iter().zip(&stats.devices) {
                        error_samples(
                            out,
                            "rtu2mqtt_device_errors_total",
                            &[("port", &port.name), ("device", &device.id)],
                            &dstats.errors,
                        );
                    }
                }
            },
        );
        family(
            "rtu2mqtt_device_response_time_seconds",
            "gauge",
            "The device's learned (smoothed) time to the first byte of a reply.",
            &mut |out| {
                for (port, stats, _) in &views {
                    for (device, dstats) in port.devices.iter().zip(&stats.devices) {
                        if let Some(learned) = dstats
                            .schedule
                            .as_ref()
                            .and_then(|s| s.learned_response_time)
                        {
                            sample(
                                out,
                                "rtu2mqtt_device_response_time_seconds",
                                &[("port", &port.name), ("device", &device.id)],
                                learned.as_secs_f64(),
                            );
                        }
                    }
                }
            },
        );
        out
    }
}

/// `name{labels} value`, with label values escaped as the format requires.
fn sample(out: &mut String, name: &str, labels: &[(&str, &str)], value: f64) {
    out.push_str(name);
    if !labels.is_empty() {
        out.push('{');
        for (i, (key, value)) in labels.iter().enumerate() {
            if i > 0 {
                out.push(',');
            }
            let escaped = value
                .replace('\\', "\\\\")
                .replace('"', "\\\"")
                .replace('\n', "\\n");
            let _ = write!(out, "{key}=\"{escaped}\"");
        }
        out.push('}');
    }
    let _ = writeln!(out, " {value}");
}

fn error_samples(out: &mut String, name: &str, labels: &[(&str, &str)], errors: &ErrorCounts) {
    for (kind, count) in [
        ("timeout", errors.timeout),
        ("bad_crc", errors.bad_crc),
        ("exception", errors.exception),
        ("another_master", errors.another_master),
    ] {
        let mut all = labels.to_vec();
        all.push(("kind", kind));
        sample(out, name, &all, count as f64);
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn errors_json(errors: &ErrorCounts) -> Value {
    json!({"timeout": errors.timeout, "bad_crc": errors.bad_crc, "exception": errors.exception,
           "another_master": errors.another_master})
}

fn millis(duration: Duration) -> f64 {
    (duration.as_secs_f64() * 10_000.0).round() / 10.0
}

fn port_json(port: &PortStatus) -> Value {
    let now = port.now();
    // The lock is held only to copy what the page shows.
    let stats = port.record(|stats| stats.copy_without_frames());
    let (open, totals, rates, latency, devices) = (
        stats.open,
        stats.totals,
        stats.rates(now),
        stats.event_latency,
        stats.devices,
    );
    let devices: Vec<Value> = port
        .devices
        .iter()
        .zip(devices.iter())
        .map(|(device, stats)| {
            let mut channels: Vec<_> = device.channels.iter().collect();
            channels.sort_by_key(|c| c.order);
            let controls: Vec<Value> = channels
                .iter()
                .map(|channel| {
                    let state = stats.controls.get(&channel.id);
                    json!({
                        "id": channel.id,
                        "type": channel.control_type,
                        "units": channel.units,
                        "readonly": channel.readonly,
                        "value": state.and_then(|s| s.value.clone()),
                        "flags": state.map(|s| s.errors.to_string()).unwrap_or_default(),
                        "source": state.and_then(|s| s.value.as_ref().map(|_| if s.from_event { "event" } else { "poll" })),
                    })
                })
                .collect();
            let schedule = stats.schedule.as_ref();
            json!({
                "id": device.id,
                "name": device.name,
                "slave_id": device.slave_id,
                "type": device.device_type,
                "online": stats.online,
                "last_seen_ms_ago": stats.last_seen.map(|seen| now.saturating_sub(seen).as_millis() as u64),
                "response_time_ms": schedule.and_then(|s| s.learned_response_time).map(millis),
                "response_timeout_ms": schedule.map(|s| millis(s.response_timeout)),
                "events_enabled": schedule.is_some_and(|s| s.events_active),
                "setup": schedule.map(|s| s.setup),
                "suspended": schedule.is_some_and(|s| s.suspended),
                "transactions": stats.transactions,
                "errors": errors_json(&stats.errors),
                "controls": controls,
            })
        })
        .collect();
    // Per bucket (not cumulative) for the page's bars.
    let mut per_bucket = Vec::with_capacity(latency.counts.len());
    let mut below = 0;
    for count in latency.counts {
        per_bucket.push(count.saturating_sub(below));
        below = count;
    }
    json!({
        "name": port.name,
        "settings": port.settings,
        "open": open,
        "bus_utilisation_percent": (rates.bus_utilisation_percent * 10.0).round() / 10.0,
        "transactions_per_second": (rates.transactions_per_second * 10.0).round() / 10.0,
        "event_rounds_per_second": (rates.event_rounds_per_second * 10.0).round() / 10.0,
        "transactions": totals.transactions,
        "event_rounds": totals.event_rounds,
        "errors": errors_json(&totals.errors),
        "another_master_ms_ago": totals
            .another_master_at
            .map(|at| now.saturating_sub(at).as_millis() as u64),
        "event_latency": {
            "buckets": per_bucket,
            "count": latency.count,
            "mean_ms": if latency.count > 0 {
                (latency.sum.as_secs_f64() * 1000.0 / latency.count as f64 * 10.0).round() / 10.0
            } else {
                0.0
            },
        },
        "devices": devices,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TemplateFile;
    use crate::device::resolve_template_device;

    fn device(template: &str, slave_id: u8) -> Arc<ResolvedDevice> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(format!("templates/{template}.json"));
        let file = TemplateFile::load(&path).unwrap_or_else(|e| panic!("{e}"));
        Arc::new(
            resolve_template_device(&file, &json!({ "slave_id": slave_id }))
                .unwrap_or_else(|e| panic!("{e}")),
        )
    }

    fn hub_with_one_port() -> (StatusHub, Arc<PortStatus>, String, String) {
        let relay = device("rtu2mqtt-relay6", 20);
        let climate = device("rtu2mqtt-climate", 21);
        let (relay_id, climate_id) = (relay.id.clone(), climate.id.clone());
        let port = Arc::new(PortStatus::new(
            "/dev/ttyRS485-1",
            json!({}),
            vec![relay, climate],
        ));
        let hub = StatusHub::new();
        hub.add_port(Arc::clone(&port));
        (hub, port, relay_id, climate_id)
    }

    /// While the port cannot open, its task takes no commands: clicks on suspend / resume must
    /// not pile up (memory) nor be replayed when it reopens; the latest per device waits.
    #[test]
    fn only_the_latest_suspend_per_device_waits_for_the_port() {
        let (hub, port, relay, climate) = hub_with_one_port();
        for click in 0..1000 {
            assert!(hub.suspend(&relay, click % 2 == 0));
        }
        assert!(hub.suspend(&climate, true));
        assert!(hub.suspend(&relay, true));
        assert!(hub.suspend(&climate, false));
        assert!(!hub.suspend("no_such_device", true));
        let mut taken = port.take_commands();
        taken.sort_by_key(|PortCommand::Suspend { device, .. }| *device);
        assert_eq!(
            taken,
            [
                PortCommand::Suspend {
                    device: 0,
                    suspended: true
                },
                PortCommand::Suspend {
                    device: 1,
                    suspended: false
                },
            ]
        );
        // Taken: nothing waits, and a new click is taken next time.
        assert_eq!(port.take_commands(), []);
        assert!(hub.suspend(&climate, true));
        assert_eq!(
            port.take_commands(),
            [PortCommand::Suspend {
                device: 1,
                suspended: true
            }]
        );
    }
}
