//! The CLI's side of the RPC: one call to the running daemon over the broker, with a reply
//! timeout that tells the integrator what to check.

use std::time::Duration;

use rumqttc::{AsyncClient, Event, Packet, QoS};
use serde_json::{json, Value};
use thiserror::Error;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use super::message::{parse_reply, RpcError, TOPIC_ROOT};
use crate::config::config_file::MqttConfig;
use crate::mqtt::client::connection_options;

/// Why a call got no result.
#[derive(Debug, Error)]
pub enum CallError {
    #[error("MQTT settings: {0}")]
    Settings(String),
    #[error("cannot reach the MQTT broker {broker}: {reason}")]
    Broker { broker: String, reason: String },
    #[error(
        "no reply from the rtu2mqtt service over MQTT (broker {broker}) within {} s: is the \
         service running (systemctl status rtu2mqtt) and connected to this broker?",
        .waited.as_secs()
    )]
    NoReply { broker: String, waited: Duration },
    #[error("the service refused: {0}")]
    Refused(RpcError),
}

/// Extra time given to a reply beyond the request's own `total_timeout` (broker round trips).
const REPLY_MARGIN: Duration = Duration::from_secs(3);
/// How long a call still waits for another server after one said the port is not its own
/// ([`RpcError::is_not_served_here`]), before any server has listed the port: a port nobody
/// serves (a typo) is said soon. Once one has ([`RpcSession::port_is_served`]), the call's
/// own timeout applies (a site tools audit: a scan through the service, beside another
/// server, was reported as "not served" after 2 s).
const OTHER_SERVER_GRACE: Duration = Duration::from_secs(2);
/// How long connecting to the broker and subscribing may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// What the connection driver reports.
enum Incoming {
    Connected,
    Subscribed,
    Message { topic: String, payload: Vec<u8> },
    Failed(String),
}

/// One broker connection for a series of calls (a scan over 48 settings is 24 calls).
pub struct RpcSession {
    client: AsyncClient,
    incoming: mpsc::Receiver<Incoming>,
    driver: JoinHandle<()>,
    client_id: String,
    broker: String,
    next_id: u64,
    /// A server on the broker listed the port these calls are for (`ports/Load`): another
    /// server's "not my port" is then no answer however long the right one takes (a scan of a
    /// setting takes seconds), only its own reply or the call's timeout is.
    port_served: bool,
}

impl RpcSession {
    /// Connects and subscribes to this session's replies.
    pub async fn connect(broker: &MqttConfig) -> Result<Self, CallError> {
        let address = format!("{}:{}", broker.host, broker.port);
        let client_id = format!("rtu2mqtt-cli-{}", std::process::id());
        let options = connection_options(broker, &client_id)
            .map_err(|err| CallError::Settings(err.to_string()))?;
        let (client, mut eventloop) = AsyncClient::new(options, 16);
        // Small requests, each waited for: no Nagle delay.
        eventloop.network_options.set_tcp_nodelay(true);
        let (sender, incoming) = mpsc::channel(16);
        let driver = tokio::spawn(async move {
            loop {
                let report = match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::ConnAck(_))) => Incoming::Connected,
                    Ok(Event::Incoming(Packet::SubAck(_))) => Incoming::Subscribed,
                    Ok(Event::Incoming(Packet::Publish(publish))) => Incoming::Message {
                        topic: publish.topic,
                        payload: publish.payload.to_vec(),
                    },
                    Ok(_) => continue,
                    Err(err) => {
                        let _ = sender.send(Incoming::Failed(err.to_string())).await;
                        return;
                    }
                };
                if sender.send(report).await.is_err() {
                    return;
                }
            }
        });
        let mut session = Self {
            client,
            incoming,
            driver,
            client_id,
            broker: address,
            next_id: 1,
            port_served: false,
        };
        let filter = format!("{TOPIC_ROOT}/+/+/{}/reply", session.client_id);
        let setup = async {
            session.expect(|i| matches!(i, Incoming::Connected)).await?;
            session
                .client
                .subscribe(filter.as_str(), QoS::AtLeastOnce)
                .await
                .map_err(|err| broker_error(&session.broker, err))?;
            session.expect(|i| matches!(i, Incoming::Subscribed)).await
        };
        match tokio::time::timeout(CONNECT_TIMEOUT, setup).await {
            Ok(result) => result?,
            Err(_) => {
                return Err(broker_error(
                    &session.broker,
                    format!("no answer within {} s", CONNECT_TIMEOUT.as_secs()),
                ))
            }
        }
        Ok(session)
    }

    async fn expect(&mut self, wanted: impl Fn(&Incoming) -> bool) -> Result<(), CallError> {
        loop {
            match self.incoming.recv().await {
                Some(Incoming::Failed(reason)) => return Err(broker_error(&self.broker, reason)),
                Some(incoming) if wanted(&incoming) => return Ok(()),
                Some(_) => {}
                None => return Err(broker_error(&self.broker, "the connection ended")),
            }
        }
    }

    /// A server listed the port the calls are for: see [`Self::port_served`].
    pub fn port_is_served(&mut self) {
        self.port_served = true;
    }

    /// Calls `service/method` with `params` and waits for its reply. `total_timeout` is sent
    /// in the params (when they have none) and bounds the wait.
    pub async fn call(
        &mut self,
        service: &str,
        method: &str,
        params: Value,
        total_timeout: Duration,
    ) -> Result<Value, CallError> {
        self.call_answered_by(
            service,
            method,
            params,
            total_timeout,
            |outcome| !matches!(outcome, Err(error) if error.is_not_served_here()),
        )
        .await
    }

    /// As [`Self::call`], for the reply that `answers`: another server of these topics on the
    /// broker (wb-mqtt-serial kept for a meter port, docs/rpc.md) answers every request too,
    /// usually first ("not my port", or its own `ports/Load`). A reply that does not answer is
    /// kept while the one that does may still come, [`OTHER_SERVER_GRACE`] at most, and is the
    /// outcome when none does.
    pub async fn call_answered_by(
        &mut self,
        service: &str,
        method: &str,
        mut params: Value,
        total_timeout: Duration,
        answers: impl Fn(&Result<Value, RpcError>) -> bool,
    ) -> Result<Value, CallError> {
        if params.get("total_timeout").is_none() {
            params["total_timeout"] =
                json!(u64::try_from(total_timeout.as_millis()).unwrap_or(u64::MAX));
        }
        let id = self.next_id;
        self.next_id += 1;
        let request_topic = format!("{TOPIC_ROOT}/{service}/{method}/{}", self.client_id);
        let reply_topic = format!("{request_topic}/reply");
        let request = json!({ "id": id, "params": params }).to_string();
        // QoS 0: a broker without TCP_NODELAY (mosquitto's default) would otherwise hold the
        // reply behind its PUBACK to us for a delayed-ACK time (some 40 ms a call); a lost
        // request ends in the reply timeout like a lost reply.
        self.client
            .publish(request_topic.as_str(), QoS::AtMostOnce, false, request)
            .await
            .map_err(|err| broker_error(&self.broker, err))?;
        let waited = total_timeout + REPLY_MARGIN;
        let deadline = tokio::time::Instant::now() + waited;
        let broker = self.broker.clone();
        let mut kept: Option<Result<Value, RpcError>> = None;
        // When the grace after the first reply that does not answer ends (counted from that
        // reply, not from every message since).
        let mut grace_ends = deadline;
        loop {
            let until = if kept.is_some() && !self.port_served {
                grace_ends
            } else {
                deadline
            };
            let Ok(incoming) = tokio::time::timeout_at(until, self.incoming.recv()).await else {
                return match kept {
                    Some(outcome) => outcome.map_err(CallError::Refused),
                    None => Err(CallError::NoReply { broker, waited }),
                };
            };
            match incoming {
                Some(Incoming::Message { topic, payload }) if topic == reply_topic => {
                    let (reply_id, outcome) = parse_reply(&payload).map_err(CallError::Refused)?;
                    // A late reply to an earlier call (it timed out here) is not this one's.
                    if reply_id != json!(id) {
                        continue;
                    }
                    if answers(&outcome) {
                        return outcome.map_err(CallError::Refused);
                    }
                    if kept.is_none() {
                        grace_ends = deadline.min(tokio::time::Instant::now() + OTHER_SERVER_GRACE);
                        kept = Some(outcome);
                    }
                }
                Some(Incoming::Failed(reason)) => return Err(broker_error(&broker, reason)),
                Some(_) => {}
                None => return Err(broker_error(&broker, "the connection ended")),
            }
        }
    }
}

impl Drop for RpcSession {
    fn drop(&mut self) {
        let _ = self.client.try_disconnect();
        self.driver.abort();
    }
}

/// One call on its own connection.
pub async fn call(
    broker: &MqttConfig,
    service: &str,
    method: &str,
    params: Value,
    total_timeout: Duration,
) -> Result<Value, CallError> {
    RpcSession::connect(broker)
        .await?
        .call(service, method, params, total_timeout)
        .await
}

fn broker_error(broker: &str, reason: impl std::fmt::Display) -> CallError {
    CallError::Broker {
        broker: broker.to_owned(),
        reason: reason.to_string(),
    }
}
