//! The CLI's side of the RPC: one call to the running daemon over the broker, with a reply
//! timeout that tells the integrator what to check.

use std::time::Duration;

use rumqttc::{AsyncClient, Event, Packet, QoS};
use serde_json::{json, Value};
use thiserror::Error;

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

/// Calls `service/method` with `params` and waits for its reply. `total_timeout` is sent in
/// the params (when they have none) and bounds the wait.
pub async fn call(
    broker: &MqttConfig,
    service: &str,
    method: &str,
    mut params: Value,
    total_timeout: Duration,
) -> Result<Value, CallError> {
    let address = format!("{}:{}", broker.host, broker.port);
    let client_id = format!("rtu2mqtt-cli-{}", std::process::id());
    let options = connection_options(broker, &client_id)
        .map_err(|err| CallError::Settings(err.to_string()))?;
    if params.get("total_timeout").is_none() {
        params["total_timeout"] =
            json!(u64::try_from(total_timeout.as_millis()).unwrap_or(u64::MAX));
    }
    let request_topic = format!("{TOPIC_ROOT}/{service}/{method}/{client_id}");
    let reply_topic = format!("{request_topic}/reply");
    let request = json!({ "id": 1, "params": params }).to_string();
    let (client, mut eventloop) = AsyncClient::new(options, 16);
    let waited = total_timeout + REPLY_MARGIN;
    let exchange = async {
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    client
                        .subscribe(reply_topic.as_str(), QoS::AtLeastOnce)
                        .await
                        .map_err(|err| broker_error(&address, err))?;
                }
                Ok(Event::Incoming(Packet::SubAck(_))) => {
                    client
                        .publish(
                            request_topic.as_str(),
                            QoS::AtLeastOnce,
                            false,
                            request.clone(),
                        )
                        .await
                        .map_err(|err| broker_error(&address, err))?;
                }
                Ok(Event::Incoming(Packet::Publish(publish))) if publish.topic == reply_topic => {
                    let (_, outcome) = parse_reply(&publish.payload).map_err(CallError::Refused)?;
                    return outcome.map_err(CallError::Refused);
                }
                Ok(_) => {}
                Err(err) => return Err(broker_error(&address, err)),
            }
        }
    };
    let outcome = tokio::time::timeout(waited, exchange).await;
    let _ = client.try_disconnect();
    outcome.unwrap_or(Err(CallError::NoReply {
        broker: address,
        waited,
    }))
}

fn broker_error(broker: &str, reason: impl std::fmt::Display) -> CallError {
    CallError::Broker {
        broker: broker.to_owned(),
        reason: reason.to_string(),
    }
}
