//! The MQTT side of the RPC server: its own broker connection (so the device publications and
//! RPC never wait for each other), the advertised method topics, one task per request, bounded
//! by the request's `total_timeout` and by [`MAX_REQUESTS_AT_ONCE`] (more wait their turn
//! within their `total_timeout`, up to [`MAX_REQUESTS_WAITING`]).

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{AsyncClient, Event, Packet, QoS};
use tokio::sync::Semaphore;
use tracing::{debug, info, warn};

use super::message::{
    advertised_topic, parse_request, reply_payload, RequestTopic, RpcError, REQUEST_FILTER,
    TOTAL_TIMEOUT_MESSAGE,
};
use super::methods::{execute_with_templates, without_unknown_device_id, DeviceTemplates};
use super::params::{parse_method, SERVED};
use crate::config::config_file::MqttConfig;
use crate::daemon::PortDirectory;
use crate::mqtt::client::{
    connection_options, refusal_text, MAX_OUTGOING_PACKET, STABLE_CONNECTION,
};
use crate::mqtt::MqttError;

/// Requests served at the same time; more wait for one to end, within their `total_timeout`,
/// as wb-mqtt-serial queues them (wb-device-manager scans every port at once, each port's
/// requests one after another). Each holds a task and, while it waits for the bus, a slot of a
/// port's queue.
pub const MAX_REQUESTS_AT_ONCE: usize = 8;
/// Requests waiting for their turn besides those served; more get an error at once (a client
/// that floods the broker must not pile up tasks and payloads without end).
pub const MAX_REQUESTS_WAITING: usize = 64;
/// The most of a request payload read (a request is a few hundred bytes).
const MAX_REQUEST_BYTES: usize = 64 * 1024;
/// The wait before reconnecting, doubled after each failure in a row up to the most: a broker
/// that refuses us must not be asked every 2 s for ever.
const FIRST_RECONNECT_DELAY: Duration = Duration::from_secs(2);
const MAX_RECONNECT_DELAY: Duration = Duration::from_secs(30);
const EXIT_FLUSH_TIMEOUT: Duration = Duration::from_secs(2);
/// A PUBLISH packet's bytes besides its topic and payload (fixed header, topic length).
const PUBLISH_OVERHEAD: usize = 8;

/// Serves wb-mqtt-serial's RPC for the ports in `ports` until `shutdown` completes.
pub async fn run_rpc_server(
    broker: MqttConfig,
    ports: PortDirectory,
    templates: DeviceTemplates,
    shutdown: impl Future<Output = ()>,
) -> Result<(), MqttError> {
    let client_id = format!("{}-rpc", broker.client_id);
    let options = connection_options(&broker, &client_id)?;
    let (client, mut eventloop) = AsyncClient::new(options, 64);
    // A reply is one small packet that a caller waits for: Nagle's algorithm with the peer's
    // delayed ACK would hold it some 40 ms.
    eventloop.network_options.set_tcp_nodelay(true);
    let slots = Arc::new(Semaphore::new(MAX_REQUESTS_AT_ONCE));
    let admitted = Arc::new(Semaphore::new(MAX_REQUESTS_AT_ONCE + MAX_REQUESTS_WAITING));
    let address = format!("{}:{}", broker.host, broker.port);
    let mut unreachable_told = false;
    let mut ever_connected = false;
    let mut reconnect_delay = FIRST_RECONNECT_DELAY;
    let mut connected_at: Option<tokio::time::Instant> = None;
    tokio::pin!(shutdown);
    loop {
        let event = tokio::select! {
            () = &mut shutdown => break,
            event = eventloop.poll() => event,
        };
        match event {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                unreachable_told = false;
                ever_connected = true;
                connected_at = Some(tokio::time::Instant::now());
                info!(broker = %address, "MQTT RPC: serving /rpc/v1/wb-mqtt-serial/…");
                let _ = client.try_subscribe(REQUEST_FILTER, QoS::AtLeastOnce);
                for (service, method) in SERVED {
                    let _ = client.try_publish(
                        advertised_topic(service, method),
                        QoS::AtLeastOnce,
                        true,
                        "1",
                    );
                }
            }
            Ok(Event::Incoming(Packet::Publish(publish))) => {
                if publish.retain {
                    // A request left retained on the broker is old: nobody waits for its reply.
                    continue;
                }
                let Some(topic) = RequestTopic::parse(&publish.topic) else {
                    continue;
                };
                let payload = publish.payload;
                let client = client.clone();
                let ports = Arc::clone(&ports);
                let templates = templates.clone();
                let slots = Arc::clone(&slots);
                match Arc::clone(&admitted).try_acquire_owned() {
                    Ok(admission) => {
                        tokio::spawn(async move {
                            let (id, outcome) =
                                serve_in_turn(&ports, &templates, &topic, &payload, Some(slots))
                                    .await;
                            send_reply(&client, &topic, &id, &outcome).await;
                            drop(admission);
                        });
                    }
                    Err(_) => {
                        let id = parse_request(&payload).map(|r| r.id).unwrap_or_default();
                        let busy = Err(RpcError::server(format!(
                            "{} RPC requests are running or waiting already; try again when one \
                             is done",
                            MAX_REQUESTS_AT_ONCE + MAX_REQUESTS_WAITING
                        )));
                        tokio::spawn(async move { send_reply(&client, &topic, &id, &busy).await });
                    }
                }
            }
            Ok(_) => {}
            Err(error) => {
                // The delay starts over only after a connection that held (see the MQTT
                // client's rule: a client id taken by another client closes each at once).
                if connected_at
                    .take()
                    .is_some_and(|since| since.elapsed() >= STABLE_CONNECTION)
                {
                    reconnect_delay = FIRST_RECONNECT_DELAY;
                }
                if !unreachable_told {
                    if let Some(refusal) = refusal_text(&error) {
                        warn!(broker = %address, "MQTT RPC: {refusal}; retrying");
                    } else if ever_connected {
                        warn!(broker = %address, %error, "MQTT RPC: lost the broker; reconnecting");
                    } else {
                        warn!(broker = %address, %error, "MQTT RPC: cannot reach the broker; retrying");
                    }
                    unreachable_told = true;
                }
                tokio::select! {
                    () = &mut shutdown => break,
                    () = tokio::time::sleep(reconnect_delay) => {}
                }
                reconnect_delay = (reconnect_delay * 2).min(MAX_RECONNECT_DELAY);
            }
        }
    }
    // The advertised method topics stay, `clear_on_exit` or not: they are wb-mqtt-serial's
    // names, shared with any other server of them on the broker (wb-mqtt-serial itself, kept
    // for a meter port), whose clients would otherwise find its methods gone.
    let _ = client.try_disconnect();
    // Let the connection write what is queued (until the broker closes it, or 2 s).
    let _ = tokio::time::timeout(EXIT_FLUSH_TIMEOUT, async {
        while eventloop.poll().await.is_ok() {}
    })
    .await;
    Ok(())
}

/// One request, from its payload to the outcome (never panics, whatever the payload).
pub async fn serve(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    topic: &RequestTopic,
    payload: &[u8],
) -> (serde_json::Value, Result<serde_json::Value, RpcError>) {
    serve_in_turn(ports, templates, topic, payload, None).await
}

/// [`serve`], the request run once it holds one of `slots` (when given), the wait counted in
/// its `total_timeout`.
async fn serve_in_turn(
    ports: &PortDirectory,
    templates: &DeviceTemplates,
    topic: &RequestTopic,
    payload: &[u8],
    slots: Option<Arc<Semaphore>>,
) -> (serde_json::Value, Result<serde_json::Value, RpcError>) {
    if payload.len() > MAX_REQUEST_BYTES {
        return (
            serde_json::Value::Null,
            Err(RpcError::parse(format!(
                "the request is {} bytes; at most {MAX_REQUEST_BYTES} are read",
                payload.len()
            ))),
        );
    }
    let request = match parse_request(payload) {
        Ok(request) => request,
        Err((id, error)) => return (id, Err(error)),
    };
    let fallback = without_unknown_device_id(ports, &request.params);
    if fallback.is_some() {
        debug!(method = %topic.name(), client = %topic.client,
            "device_id names no configured device: the request goes to the port it names");
    }
    let params = fallback.as_ref().unwrap_or(&request.params);
    let method = match parse_method(&topic.service, &topic.method, params) {
        Ok(method) => method,
        Err(error) => {
            debug!(method = %topic.name(), client = %topic.client, %error, "RPC request refused");
            return (request.id, Err(error));
        }
    };
    let total_timeout = method.total_timeout();
    debug!(method = %topic.name(), client = %topic.client, params = %request.params, "RPC request");
    let in_turn = async {
        let _slot = match slots {
            Some(slots) => Some(
                slots
                    .acquire_owned()
                    .await
                    .map_err(|_| RpcError::server("the RPC server is stopping"))?,
            ),
            None => None,
        };
        execute_with_templates(ports, templates, method).await
    };
    let outcome = match tokio::time::timeout(total_timeout, in_turn).await {
        Ok(outcome) => outcome,
        Err(_) => Err(RpcError::timeout(format!(
            "{TOTAL_TIMEOUT_MESSAGE}: {} took longer than total_timeout ({} ms)",
            topic.name(),
            total_timeout.as_millis()
        ))),
    };
    if let Err(error) = &outcome {
        debug!(method = %topic.name(), %error, "RPC request failed");
    }
    (request.id, outcome)
}

async fn send_reply(
    client: &AsyncClient,
    topic: &RequestTopic,
    id: &serde_json::Value,
    outcome: &Result<serde_json::Value, RpcError>,
) {
    let mut payload = reply_payload(id, outcome);
    // A packet the client would refuse drops the connection, and every reply in flight with
    // it: the caller gets an error instead (a config/Load of a very large config, say).
    let reply_topic = topic.reply_topic();
    if payload.len() + reply_topic.len() + PUBLISH_OVERHEAD > MAX_OUTGOING_PACKET {
        let too_large = Err(RpcError::server(format!(
            "the reply is {} bytes; at most {} are sent",
            payload.len(),
            MAX_OUTGOING_PACKET - reply_topic.len() - PUBLISH_OVERHEAD
        )));
        payload = reply_payload(id, &too_large);
    }
    // QoS 0: with QoS 1 the broker's PUBACK would be the last packet to us before the next
    // request, and a broker without TCP_NODELAY (mosquitto's default) holds that request
    // until our delayed ACK (some 40 ms a call). A reply is lost only with the connection,
    // which the caller's timeout covers.
    if let Err(error) = client
        .publish(reply_topic.clone(), QoS::AtMostOnce, false, payload)
        .await
    {
        debug!(%error, topic = %reply_topic, "RPC reply not sent");
    }
}
