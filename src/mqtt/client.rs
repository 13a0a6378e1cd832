//! The MQTT client task: owns the broker connection (rumqttc), feeds it what the
//! [`PublicationPlanner`] decides, and hands `/on` writes to the bus side.
//!
//! Never blocks the bus side: updates are taken as they come, and while the broker is away
//! nothing queues up — the planner keeps the latest state, and after every (re)connect the
//! whole retained state is published again (a restarted broker may have lost it), one device
//! at a time as the client takes it ([`Waiting`]). Between connects, an outbox with one entry
//! per topic absorbs bursts the client cannot take yet.

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rumqttc::{
    AsyncClient, ClientError, Event, EventLoop, LastWill, MqttOptions, Outgoing, Packet, QoS,
    Transport,
};
use tokio::sync::mpsc;
use tracing::{debug, info, warn};

use super::discovery::DiscoverySettings;
use super::outbox::{log_unsendable, next_from_backlog, unsendable, Owed, Waiting};
use super::pending_writes::PendingWrites;
use super::planner::{PlannerSettings, PublicationPlanner, UnchangedPolicy, WriteOutcome};
use super::sweep::Sweeper;
use super::throttle::{BirthCoalescer, LogBudget, LogDecision};
use super::topics::{discovery_prefix, TopicError, TopicScheme};
use super::{MqttAction, Publication};
use crate::config::config_file::{Config, MqttConfig, TlsConfig};
use crate::device_updates::{ControlWrite, DeviceUpdate};
use crate::service::{BrokerState, ServiceHealth};

/// Requests rumqttc buffers between this task and its connection.
const CLIENT_QUEUE: usize = 256;
/// Events from the connection driver (incoming messages, connects).
const EVENT_QUEUE: usize = 256;
/// How long to wait before offering the client more when its queue was full.
/// Updates taken from the bus side at once: a read of many values comes as many updates, and
/// one pass of the select loop per update cost more than the update itself.
const UPDATE_BATCH: usize = 128;
const RETRY_FULL_QUEUE: Duration = Duration::from_millis(10);
const FIRST_RECONNECT_DELAY: Duration = Duration::from_millis(500);
const MAX_RECONNECT_DELAY: Duration = Duration::from_secs(30);
/// A connection that lasted this long was a good one: the reconnect delay starts over after it.
pub(crate) const STABLE_CONNECTION: Duration = Duration::from_secs(10);
/// Short-lived connections in a row after which the log names the likely cause.
const SHORT_LIVED_BEFORE_HINT: u32 = 3;
/// Longest wait on exit for the broker to take the last publications.
const EXIT_FLUSH_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest packet sent (rumqttc's default of 10 KiB is too small for some configs); larger
/// publications are refused by the outbox, not sent.
pub(crate) const MAX_OUTGOING_PACKET: usize = 256 * 1024;
/// Largest packet accepted: the largest MQTT 3.1.1 allows (remaining length 268,435,455 and a
/// 5-byte fixed header). rumqttc drops the connection on a larger incoming packet, and MQTT
/// 3.1.1 has no way to tell the broker a smaller limit, so any lower value lets any client
/// disconnect the driver with one big `/on` message (or, retained, keep it reconnecting).
/// Such a payload is held only while it is refused; `message_size_limit` in the broker's
/// config keeps it off the network altogether.
const MAX_INCOMING_PACKET: usize = 268_435_455 + 5;
/// The most of an incoming payload kept: more than any `/on` payload accepted, enough for the
/// device record of hundreds of devices.
const MAX_KEPT_PAYLOAD: usize = 64 * 1024;
/// `/on` writes dropped because the bus side has stopped, logged per minute; the rest counted.
const DROPPED_WRITE_LOG_LINES: u32 = 10;
/// Where Debian keeps the system CAs, used when TLS is on without `ca_file`.
const SYSTEM_CA_FILE: &str = "/etc/ssl/certs/ca-certificates.crt";

/// Why the MQTT task could not start.
#[derive(Debug, thiserror::Error)]
pub enum MqttError {
    #[error(transparent)]
    Topic(#[from] TopicError),
    #[error("cannot read {what} `{path}`: {source}")]
    ReadFile {
        what: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("mqtt.tls: cert_file and key_file go together; set both or neither")]
    IncompleteClientCert,
    #[error("mqtt.tls is set, but this build of rtu2mqtt has no TLS (cargo feature `tls`)")]
    TlsNotBuilt,
}

/// Everything the MQTT task takes from the config.
#[derive(Debug, Clone)]
pub struct MqttSettings {
    pub broker: MqttConfig,
    /// Top-level `max_unchanged_interval` (-1 changes only, 0 every read, N seconds).
    pub max_unchanged_interval: i64,
}

impl MqttSettings {
    pub fn from_config(config: &Config) -> Self {
        Self {
            broker: config.mqtt.clone(),
            max_unchanged_interval: config.max_unchanged_interval,
        }
    }

    /// The planner's settings (topic prefix and discovery prefix checked).
    pub fn planner_settings(&self) -> Result<PlannerSettings, MqttError> {
        let topics = TopicScheme::new(&self.broker.topic_prefix, &self.broker.client_id)?;
        let ha = &self.broker.homeassistant;
        let discovery = if ha.enabled {
            Some(DiscoverySettings {
                prefix: discovery_prefix(&ha.prefix)?,
            })
        } else {
            None
        };
        Ok(PlannerSettings {
            topics,
            unchanged: UnchangedPolicy::from_config(self.max_unchanged_interval),
            discovery,
            clear_discovery_on_exit: ha.clear_on_exit,
        })
    }
}

/// What the connection driver reports.
#[derive(Debug)]
enum ConnectionEvent {
    Connected,
    Disconnected,
    /// `payload` is cut after [`MAX_KEPT_PAYLOAD`] bytes (an `/on` payload that long is
    /// refused anyway); `size` is its real length.
    Message {
        topic: String,
        payload: Vec<u8>,
        size: usize,
        retain: bool,
    },
}

/// Runs the MQTT side until `shutdown` completes or every `updates` sender is dropped.
///
/// `updates` come from the bus side (send `Added` for each device first); checked `/on`
/// writes go out on `writes` (never awaited: while its queue is full, the latest write per control
/// waits in [`PendingWrites`], so no write is lost and the broker is still served). On
/// exit, with `mqtt.clear_on_exit`, every retained topic of the devices is deleted; the
/// driver status becomes `offline` either way.
pub async fn run_mqtt(
    settings: MqttSettings,
    updates: mpsc::Receiver<DeviceUpdate>,
    writes: mpsc::Sender<ControlWrite>,
    shutdown: impl Future<Output = ()>,
) -> Result<(), MqttError> {
    run_mqtt_reporting(settings, updates, writes, shutdown, None).await
}

/// [`run_mqtt`] that also reports the broker's state (connected or not) into `health`, for
/// systemd's readiness and status line.
pub async fn run_mqtt_reporting(
    settings: MqttSettings,
    mut updates: mpsc::Receiver<DeviceUpdate>,
    writes: mpsc::Sender<ControlWrite>,
    shutdown: impl Future<Output = ()>,
    health: Option<Arc<ServiceHealth>>,
) -> Result<(), MqttError> {
    let planner_settings = settings.planner_settings()?;
    let mut sweeper = Sweeper::new(
        planner_settings.topics.clone(),
        planner_settings
            .discovery
            .as_ref()
            .map(|d| d.prefix.clone()),
    );
    let mut planner = PublicationPlanner::new(planner_settings);
    let status_topic = planner.topics().driver_status();
    let options = mqtt_options(&settings.broker, &status_topic)?;
    let broker = format!("{}:{}", settings.broker.host, settings.broker.port);
    let (client, eventloop) = AsyncClient::new(options, CLIENT_QUEUE);
    let (events_tx, mut events) = mpsc::channel(EVENT_QUEUE);
    let connection = tokio::spawn(drive_connection(
        eventloop,
        events_tx,
        broker.clone(),
        health,
    ));
    let ha_status = planner.discovery_status_topic();

    let mut waiting = Waiting::default();
    let mut connected = false;
    let mut births = BirthCoalescer::default();
    let mut dropped_log = LogBudget::new(DROPPED_WRITE_LOG_LINES);
    let mut pending_writes = PendingWrites::default();
    let mut update_batch = Vec::with_capacity(UPDATE_BATCH);
    tokio::pin!(shutdown);
    loop {
        let birth_due = births.due().map(tokio::time::Instant::from_std);
        tokio::select! {
            biased;
            () = &mut shutdown => break,
            event = events.recv() => match event {
                Some(ConnectionEvent::Connected) => {
                    connected = true;
                    births.resent_now(Instant::now());
                    let mut first = vec![MqttAction::Publish(Publication::retained(&status_topic, "online"))];
                    first.extend(ha_status.iter().map(|topic| MqttAction::Subscribe(topic.clone())));
                    first.extend(sweeper.connected());
                    waiting.connected(first, planner.device_order());
                    debug!(devices = waiting.backlog.len(), "republishing the retained state");
                }
                Some(ConnectionEvent::Disconnected) => {
                    connected = false;
                    sweeper.disconnected();
                    waiting.clear();
                }
                Some(ConnectionEvent::Message { topic, payload, size, retain }) => {
                    let is_ha_status = ha_status.as_deref() == Some(topic.as_str());
                    if let Some(actions) = sweeper.on_message(&topic, &payload, retain, &planner) {
                        waiting.outbox.extend(actions);
                    } else if is_ha_status {
                        // Any client may publish this: many births give one resend.
                        if payload == b"online" {
                            births.birth(Instant::now());
                        }
                    } else {
                        let message = OnMessage { topic: &topic, payload: &payload, size, retain };
                        let bus = WriteTarget { writes: &writes, pending: &mut pending_writes, dropped_log: &mut dropped_log };
                        on_message(&mut planner, bus, message);
                    }
                }
                None => break,
            },
            received = updates.recv_many(&mut update_batch, UPDATE_BATCH) => {
                if received == 0 {
                    debug!("the bus side closed its update channel");
                    break;
                }
                let now = Instant::now();
                for update in update_batch.drain(..) {
                    let devices_changed = matches!(update, DeviceUpdate::Added(_) | DeviceUpdate::Removed { .. });
                    if !connected {
                        planner.handle(update, now);
                        continue;
                    }
                    waiting.update(&mut planner, update, now);
                    if devices_changed && sweeper.is_done() {
                        waiting.outbox.push(MqttAction::Publish(sweeper.record(&planner.device_ids())));
                    }
                    // Offered one update at a time, as they came: two values of one topic
                    // in a batch are both offered, not merged in the outbox.
                    waiting.offer(&mut planner, MAX_OUTGOING_PACKET, |action| try_request(&client, action));
                }
            },
            permit = writes.reserve(), if !pending_writes.is_empty() => match permit {
                Ok(permit) => {
                    if let Some(write) = pending_writes.pop() {
                        permit.send(write);
                    }
                }
                Err(_) => {
                    warn!(dropped = pending_writes.len(), "writes dropped: the bus side has stopped");
                    pending_writes.clear();
                }
            },
            () = tokio::time::sleep(RETRY_FULL_QUEUE), if connected && !waiting.is_empty() => {}
            () = sleep_until_some(birth_due) => {
                if births.take_due(Instant::now()) && connected {
                    info!("Home Assistant is online: sending discovery configs");
                    for id in planner.device_order() {
                        waiting.backlog.add(&id, Owed::Discovery);
                    }
                }
            }
        }
        if connected {
            waiting.offer(&mut planner, MAX_OUTGOING_PACKET, |action| {
                try_request(&client, action)
            });
        }
    }

    // Keep the connection driver running but stop listening to it: it must go on polling
    // until our DISCONNECT is written.
    drop(events);
    if connected {
        let clear_on_exit = settings.broker.clear_on_exit;
        // The devices to delete, one at a time after what still waits.
        let mut clearing = if clear_on_exit {
            waiting
                .backlog
                .before_clearing(!settings.broker.homeassistant.clear_on_exit);
            planner.device_order()
        } else {
            Vec::new()
        }
        .into_iter();
        let mut offline = Some(MqttAction::Publish(Publication::retained(
            &status_topic,
            "offline",
        )));
        // Every publication is tried: one the client refuses must not keep the others (the
        // `offline` status last of all) from the broker.
        let Waiting {
            mut outbox,
            mut backlog,
        } = waiting;
        let flush = async {
            let mut failed = 0usize;
            loop {
                while let Some(action) = outbox.pop() {
                    if let Some(reason) = unsendable(&action, MAX_OUTGOING_PACKET) {
                        log_unsendable(&action, reason);
                        failed += 1;
                    } else if send(&client, action).await.is_err() {
                        failed += 1;
                    }
                }
                if let Some(actions) = next_from_backlog(&mut backlog, &mut planner) {
                    outbox.extend(actions);
                } else if let Some(id) = clearing.next() {
                    outbox.extend(planner.device_clear(&id));
                } else if let Some(offline) = offline.take() {
                    outbox.push(offline);
                } else {
                    break;
                }
            }
            let _ = client.disconnect().await;
            failed
        };
        let stop_connection = connection.abort_handle();
        let flushed = tokio::time::timeout(EXIT_FLUSH_TIMEOUT, async {
            let failed = flush.await;
            let _ = connection.await;
            failed
        })
        .await;
        stop_connection.abort();
        match flushed {
            Err(_) => warn!(%broker, "the broker did not take the last publications in time"),
            Ok(0) => info!(
                clear_on_exit = settings.broker.clear_on_exit,
                "MQTT: disconnected"
            ),
            Ok(failed) => warn!(
                %broker,
                failed,
                "MQTT: disconnected, but some of the last publications could not be sent"
            ),
        }
    } else {
        warn!(%broker, "not connected to the broker at exit: its retained topics stay as they are");
        connection.abort();
    }
    Ok(())
}

/// Sleeps until `deadline`; forever when there is none.
async fn sleep_until_some(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// A message on one of our subscriptions.
struct OnMessage<'a> {
    topic: &'a str,
    payload: &'a [u8],
    size: usize,
    retain: bool,
}

/// Where accepted `/on` writes go: the bus side, or, while its queue is full, the pending
/// writes.
struct WriteTarget<'a> {
    writes: &'a mpsc::Sender<ControlWrite>,
    pending: &'a mut PendingWrites,
    dropped_log: &'a mut LogBudget,
}

fn on_message(planner: &mut PublicationPlanner, bus: WriteTarget<'_>, message: OnMessage<'_>) {
    let OnMessage {
        topic,
        payload,
        size,
        retain,
    } = message;
    match planner.on_message(topic, payload, retain) {
        WriteOutcome::NotOurs => debug!(topic, "message on a topic that is no write, ignored"),
        WriteOutcome::IgnoredRetained => {
            debug!(topic, "retained /on message (an old command), ignored")
        }
        WriteOutcome::IgnoredEmpty => {
            debug!(
                topic,
                "empty /on message (a client clearing a retained command), ignored"
            )
        }
        WriteOutcome::Accepted(write) => {
            debug!(device_id = %write.device_id, control_id = %write.control_id, size, "write");
            // Behind waiting writes, a write waits too: the order of controls is kept.
            if !bus.pending.is_empty() {
                if bus.pending.push(write) {
                    debug!("an older write to the same control was still waiting: superseded");
                }
                return;
            }
            match bus.writes.try_send(write) {
                Ok(()) => {}
                Err(mpsc::error::TrySendError::Full(write)) => {
                    debug!("the bus side is busy: the write waits");
                    bus.pending.push(write);
                }
                Err(mpsc::error::TrySendError::Closed(write)) => {
                    let now = Instant::now();
                    match bus.dropped_log.check(now) {
                        LogDecision::Log {
                            suppressed_before: 0,
                        } => warn!(
                            device_id = %write.device_id,
                            control_id = %write.control_id,
                            "write dropped: the bus side has stopped"
                        ),
                        LogDecision::Log { suppressed_before } => warn!(
                            device_id = %write.device_id,
                            control_id = %write.control_id,
                            suppressed_before,
                            "write dropped: the bus side has stopped"
                        ),
                        LogDecision::Skip => {}
                    }
                }
            }
        }
    }
}

/// Hands `action` to the client if its queue has room.
fn try_request(client: &AsyncClient, action: &MqttAction) -> bool {
    let result = match action {
        MqttAction::Publish(p) => {
            client.try_publish(p.topic.as_str(), p.qos, p.retain, p.payload.as_bytes())
        }
        MqttAction::Subscribe(topic) => client.try_subscribe(topic.as_str(), QoS::AtLeastOnce),
        MqttAction::Unsubscribe(topic) => client.try_unsubscribe(topic.as_str()),
    };
    match result {
        Ok(()) => true,
        Err(error) => {
            if !matches!(error, ClientError::TryRequest(_)) {
                debug!(%error, "MQTT client refused a request");
            }
            false
        }
    }
}

async fn send(client: &AsyncClient, action: MqttAction) -> Result<(), ClientError> {
    match action {
        MqttAction::Publish(p) => {
            client
                .publish(p.topic, p.qos, p.retain, p.payload.into_bytes())
                .await
        }
        MqttAction::Subscribe(topic) => client.subscribe(topic, QoS::AtLeastOnce).await,
        MqttAction::Unsubscribe(topic) => client.unsubscribe(topic).await,
    }
}

/// Polls rumqttc's event loop for the whole run: reconnects with a growing delay, and reports
/// connects and incoming messages. After writing our DISCONNECT it goes on reading until the
/// broker closes the connection: closing a socket with unread data (our last PUBACKs) makes
/// the kernel send a reset, and the broker then drops the publications it has not read yet.
async fn drive_connection(
    mut eventloop: EventLoop,
    events: mpsc::Sender<ConnectionEvent>,
    broker: String,
    health: Option<Arc<ServiceHealth>>,
) {
    let report = |state: BrokerState| {
        if let Some(health) = &health {
            health.set_broker(state);
        }
    };
    let mut delay = FIRST_RECONNECT_DELAY;
    let mut connected_at: Option<tokio::time::Instant> = None;
    let mut failures: u32 = 0;
    // Connections in a row that the broker closed soon after accepting them.
    let mut short_lived: u32 = 0;
    let mut disconnecting = false;
    loop {
        let event = eventloop.poll().await;
        if disconnecting && event.is_err() {
            return;
        }
        match event {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                info!(%broker, "connected to the MQTT broker");
                report(BrokerState::Connected);
                connected_at = Some(tokio::time::Instant::now());
                failures = 0;
                let _ = events.send(ConnectionEvent::Connected).await;
            }
            Ok(Event::Incoming(Packet::Publish(publish))) => {
                let size = publish.payload.len();
                let kept = size.min(MAX_KEPT_PAYLOAD);
                let _ = events
                    .send(ConnectionEvent::Message {
                        topic: publish.topic,
                        payload: publish.payload.get(..kept).unwrap_or_default().to_vec(),
                        size,
                        retain: publish.retain,
                    })
                    .await;
            }
            Ok(Event::Outgoing(Outgoing::Disconnect)) => disconnecting = true,
            Ok(_) => {}
            Err(error) => {
                if let Some(since) = connected_at.take() {
                    // The delay starts over only after a connection that held: a broker that
                    // closes each connection at once (another client took our client id, and
                    // ours takes it back) must not be reconnected to, and everything
                    // republished, twice a second.
                    if since.elapsed() >= STABLE_CONNECTION {
                        delay = FIRST_RECONNECT_DELAY;
                        short_lived = 0;
                    } else {
                        short_lived = short_lived.saturating_add(1);
                    }
                    warn!(%broker, %error, retry_in = ?delay, "lost the MQTT broker; reconnecting");
                    if short_lived == SHORT_LIVED_BEFORE_HINT {
                        warn!(%broker,
                            "the broker closed {SHORT_LIVED_BEFORE_HINT} connections in a row soon \
                             after accepting them: another client with the same mqtt.client_id \
                             may be connected (a second rtu2mqtt, a `rtu2mqtt run` beside the \
                             service?); give each gateway its own mqtt.client_id");
                    }
                    // Told to the client task before the health: whoever sees the broker
                    // unreachable there knows the task hears it before any later update.
                    let _ = events.send(ConnectionEvent::Disconnected).await;
                    report(BrokerState::Unreachable);
                    // The reconnects that follow start a new series: their first failure (a
                    // refusal of our credentials, say) is told at warning level again.
                    failures = 0;
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(MAX_RECONNECT_DELAY);
                    continue;
                }
                report(BrokerState::Unreachable);
                if let Some(refusal) = refusal_text(&error) {
                    if failures == 0 {
                        warn!(%broker, "{refusal}; retrying");
                    } else {
                        debug!(%broker, failures, "{refusal}");
                    }
                } else if failures == 0 {
                    warn!(%broker, %error, "cannot reach the MQTT broker; retrying");
                } else {
                    debug!(%broker, %error, failures, "MQTT broker still unreachable");
                }
                failures = failures.saturating_add(1);
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(MAX_RECONNECT_DELAY);
            }
        }
    }
}

/// What to tell the integrator when the broker answered but refused the connection (the
/// broker is reachable: the fix is in the config or the broker's ACLs, not the network).
pub(crate) fn refusal_text(error: &rumqttc::ConnectionError) -> Option<&'static str> {
    use rumqttc::ConnectReturnCode as Code;
    let rumqttc::ConnectionError::ConnectionRefused(code) = error else {
        return None;
    };
    Some(match code {
        Code::BadUserNamePassword => {
            "the MQTT broker refused the user name or password: check mqtt.user and mqtt.password"
        }
        // What mosquitto 2 answers to a wrong password too.
        Code::NotAuthorized => {
            "the MQTT broker refused the user name or password (not authorised): check mqtt.user, mqtt.password and the broker's password file"
        }
        Code::BadClientId => "the MQTT broker refused the client id: check mqtt.client_id",
        Code::RefusedProtocolVersion => "the MQTT broker does not speak MQTT 3.1.1",
        Code::ServiceUnavailable => "the MQTT broker is up but not accepting clients",
        Code::Success => return None,
    })
}

/// rumqttc options: client id, credentials, keep-alive, last will, TLS.
fn mqtt_options(config: &MqttConfig, status_topic: &str) -> Result<MqttOptions, MqttError> {
    let mut options = connection_options(config, &config.client_id)?;
    options.set_last_will(LastWill::new(
        status_topic,
        "offline",
        QoS::AtLeastOnce,
        true,
    ));
    Ok(options)
}

/// Broker, credentials, keep-alive and TLS of `config`, under `client_id`, without a last will
/// (also used by the MQTT RPC server's connection and the CLI's RPC client).
pub fn connection_options(config: &MqttConfig, client_id: &str) -> Result<MqttOptions, MqttError> {
    let mut options = MqttOptions::new(client_id, &config.host, config.port);
    options.set_keep_alive(Duration::from_secs(u64::from(config.keepalive_s)));
    options.set_clean_session(true);
    options.set_max_packet_size(MAX_INCOMING_PACKET, MAX_OUTGOING_PACKET);
    if let Some(user) = &config.user {
        options.set_credentials(user, config.password.clone().unwrap_or_default());
    }
    if let Some(tls) = &config.tls {
        options.set_transport(tls_transport(tls)?);
    }
    Ok(options)
}

#[cfg(feature = "tls")]
fn tls_transport(tls: &TlsConfig) -> Result<Transport, MqttError> {
    let read = |what: &'static str, path: &PathBuf| {
        std::fs::read(path).map_err(|source| MqttError::ReadFile {
            what,
            path: path.clone(),
            source,
        })
    };
    let ca_path = tls
        .ca_file
        .clone()
        .unwrap_or_else(|| PathBuf::from(SYSTEM_CA_FILE));
    let ca = read("CA file", &ca_path)?;
    let client_auth = match (&tls.cert_file, &tls.key_file) {
        (Some(cert), Some(key)) => {
            Some((read("client certificate", cert)?, read("client key", key)?))
        }
        (None, None) => None,
        _ => return Err(MqttError::IncompleteClientCert),
    };
    // rustls is built with ring only (see Cargo.toml); it must be the process default before
    // rumqttc builds its client config. A second install is refused harmlessly.
    let _ = rustls::crypto::ring::default_provider().install_default();
    Ok(Transport::tls(ca, client_auth, None))
}

#[cfg(not(feature = "tls"))]
fn tls_transport(_tls: &TlsConfig) -> Result<Transport, MqttError> {
    let _ = SYSTEM_CA_FILE;
    Err(MqttError::TlsNotBuilt)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tls_settings_are_checked_up_front() {
        let mut config = MqttConfig {
            tls: Some(TlsConfig {
                ca_file: Some(PathBuf::from("/nonexistent/ca.pem")),
                cert_file: None,
                key_file: None,
            }),
            ..MqttConfig::default()
        };
        let error = mqtt_options(&config, "s").err().map(|e| e.to_string());
        #[cfg(feature = "tls")]
        assert!(error.is_some_and(|e| e.contains("/nonexistent/ca.pem")));
        #[cfg(not(feature = "tls"))]
        assert!(error.is_some_and(|e| e.contains("no TLS")));
        config.tls = None;
        assert!(mqtt_options(&config, "s").is_ok());
    }

    #[test]
    fn bad_prefixes_are_refused() {
        let mut settings = MqttSettings {
            broker: MqttConfig::default(),
            max_unchanged_interval: -1,
        };
        assert!(settings.planner_settings().is_ok());
        settings.broker.topic_prefix = "a/+".into();
        assert!(settings.planner_settings().is_err());
        settings.broker.topic_prefix = String::new();
        settings.broker.homeassistant.prefix = "#".into();
        assert!(settings.planner_settings().is_err());
        settings.broker.homeassistant.enabled = false;
        assert!(settings.planner_settings().is_ok());
    }
}
