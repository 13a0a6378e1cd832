//! The MQTT RPC envelope, as wb-mqtt-serial (libwbmqtt's RPC server) speaks it: requests on
//! `/rpc/v1/wb-mqtt-serial/<service>/<method>/<client>` carrying `{"id": …, "params": {…}}`,
//! replies on the same topic + `/reply` carrying `{"id": …, "result": …, "error": null}` or
//! `{"id": …, "result": null, "error": {"code": …, "message": …}}`. Pure: no IO.

use serde_json::{json, Value};

/// The driver name in the topics (wb-mqtt-serial's, so Wiren Board's tools find us).
pub const DRIVER: &str = "wb-mqtt-serial";
/// Every request topic starts with this.
pub const TOPIC_ROOT: &str = "/rpc/v1/wb-mqtt-serial";
/// What the server subscribes to: every method of every service, any client.
pub const REQUEST_FILTER: &str = "/rpc/v1/wb-mqtt-serial/+/+/+";

/// JSON-RPC error codes used by libwbmqtt's RPC server.
pub mod code {
    /// The payload is no JSON object.
    pub const PARSE_ERROR: i64 = -32700;
    /// Anything else: bad params, unknown method, a port that cannot do it, bus errors.
    pub const SERVER_ERROR: i64 = -32000;
    /// `total_timeout` (default 10 s) passed before the work was done.
    pub const REQUEST_TIMEOUT: i64 = -32600;
}

/// A method's address in the topic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestTopic {
    pub service: String,
    pub method: String,
    pub client: String,
}

impl RequestTopic {
    /// `None` for topics that are no request (replies, the advertised method topics, others).
    pub fn parse(topic: &str) -> Option<Self> {
        let rest = topic.strip_prefix(TOPIC_ROOT)?.strip_prefix('/')?;
        let mut parts = rest.split('/');
        let (service, method, client) = (parts.next()?, parts.next()?, parts.next()?);
        if parts.next().is_some() || [service, method, client].iter().any(|p| p.is_empty()) {
            return None;
        }
        Some(Self {
            service: service.to_owned(),
            method: method.to_owned(),
            client: client.to_owned(),
        })
    }

    pub fn request_topic(&self) -> String {
        format!(
            "{TOPIC_ROOT}/{}/{}/{}",
            self.service, self.method, self.client
        )
    }

    pub fn reply_topic(&self) -> String {
        format!("{}/reply", self.request_topic())
    }

    /// `service/method`, as the docs and logs name it.
    pub fn name(&self) -> String {
        format!("{}/{}", self.service, self.method)
    }
}

/// The retained topic that tells clients a method is served (libwbmqtt publishes `1` there).
pub fn advertised_topic(service: &str, method: &str) -> String {
    format!("{TOPIC_ROOT}/{service}/{method}")
}

/// A JSON-RPC error: the code and what an integrator reads.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RpcError {
    pub code: i64,
    pub message: String,
}

impl RpcError {
    pub fn server(message: impl Into<String>) -> Self {
        Self {
            code: code::SERVER_ERROR,
            message: message.into(),
        }
    }

    pub fn parse(message: impl Into<String>) -> Self {
        Self {
            code: code::PARSE_ERROR,
            message: message.into(),
        }
    }

    pub fn timeout(message: impl Into<String>) -> Self {
        Self {
            code: code::REQUEST_TIMEOUT,
            message: message.into(),
        }
    }
}

/// What a server answers for a port or device it does not serve: rtu2mqtt's words and
/// wb-mqtt-serial's (`RPC_WRONG_PORT`). Both answer every request on these topics when they run
/// side by side (a meter port left on wb-mqtt-serial, docs/migrating.md).
const NOT_SERVED_HERE: [&str; 3] = [
    "is not served by this rtu2mqtt",
    "Requested port doesn't exist",
    "SerialClient wasn't found for requested port",
];

/// How the message of a request that ran out of its `total_timeout` begins (code -32600, which
/// `port/Load` also gives for a device that did not answer).
pub const TOTAL_TIMEOUT_MESSAGE: &str = "RPC request timeout";

impl RpcError {
    /// A `port/Load` the device did not answer (wb-mqtt-serial's E_RPC_REQUEST_TIMEOUT), as
    /// against a request that ran out of its `total_timeout` (same code).
    pub fn is_no_reply(&self) -> bool {
        self.code == code::REQUEST_TIMEOUT && !self.message.starts_with(TOTAL_TIMEOUT_MESSAGE)
    }

    /// Whether the server said the port or device is not one it serves, so that another server
    /// on the same topics may still answer.
    pub fn is_not_served_here(&self) -> bool {
        NOT_SERVED_HERE
            .iter()
            .any(|words| self.message.contains(words))
    }
}

impl std::fmt::Display for RpcError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (code {})", self.message, self.code)
    }
}

/// A parsed request: its id (echoed in the reply, any JSON value) and params (an object;
/// absent or null params read as `{}`).
#[derive(Debug, Clone, PartialEq)]
pub struct RpcRequest {
    pub id: Value,
    pub params: Value,
}

/// Reads a request payload. On failure the id is still returned when it could be read, so
/// the error reply can carry it.
pub fn parse_request(payload: &[u8]) -> Result<RpcRequest, (Value, RpcError)> {
    let text = std::str::from_utf8(payload).map_err(|_| {
        (
            Value::Null,
            RpcError::parse("the request is not UTF-8 text"),
        )
    })?;
    let value: Value = serde_json::from_str(text).map_err(|err| {
        (
            Value::Null,
            RpcError::parse(format!("the request is not JSON: {err}")),
        )
    })?;
    let Value::Object(mut object) = value else {
        return Err((
            Value::Null,
            RpcError::parse("the request must be a JSON object {\"id\": …, \"params\": {…}}"),
        ));
    };
    let id = object.remove("id").unwrap_or(Value::Null);
    let params = match object.remove("params") {
        None | Some(Value::Null) => json!({}),
        Some(params @ Value::Object(_)) => params,
        Some(_) => return Err((id, RpcError::server("\"params\" must be a JSON object"))),
    };
    Ok(RpcRequest { id, params })
}

/// The reply payload for a result or an error.
pub fn reply_payload(id: &Value, outcome: &Result<Value, RpcError>) -> String {
    let reply = match outcome {
        Ok(result) => json!({ "id": id, "result": result, "error": null }),
        Err(error) => json!({
            "id": id,
            "result": null,
            "error": { "code": error.code, "message": error.message },
        }),
    };
    reply.to_string()
}

/// Reads a reply payload (the CLI's side): the result, or the error it carries.
pub fn parse_reply(payload: &[u8]) -> Result<(Value, Result<Value, RpcError>), RpcError> {
    let value: Value = serde_json::from_slice(payload)
        .map_err(|err| RpcError::parse(format!("the reply is not JSON: {err}")))?;
    let id = value.get("id").cloned().unwrap_or(Value::Null);
    match value.get("error") {
        None | Some(Value::Null) => {
            Ok((id, Ok(value.get("result").cloned().unwrap_or(Value::Null))))
        }
        Some(error) => Ok((
            id,
            Err(RpcError {
                code: error
                    .get("code")
                    .and_then(Value::as_i64)
                    .unwrap_or(code::SERVER_ERROR),
                message: error
                    .get("message")
                    .and_then(Value::as_str)
                    .unwrap_or("(no message)")
                    .to_owned(),
            }),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_topics_parse_and_replies_go_beside_them() {
        let topic = RequestTopic::parse("/rpc/v1/wb-mqtt-serial/port/Load/cli-42").unwrap();
        assert_eq!(topic.service, "port");
        assert_eq!(topic.method, "Load");
        assert_eq!(topic.client, "cli-42");
        assert_eq!(
            topic.reply_topic(),
            "/rpc/v1/wb-mqtt-serial/port/Load/cli-42/reply"
        );
        assert_eq!(topic.name(), "port/Load");
        for not_a_request in [
            "/rpc/v1/wb-mqtt-serial/port/Load/cli-42/reply",
            "/rpc/v1/wb-mqtt-serial/port/Load",
            "/rpc/v1/wb-mqtt-serial/port//x",
            "/rpc/v1/other-driver/port/Load/x",
            "/devices/x/controls/y",
        ] {
            assert_eq!(RequestTopic::parse(not_a_request), None, "{not_a_request}");
        }
        assert_eq!(
            advertised_topic("port", "Scan"),
            "/rpc/v1/wb-mqtt-serial/port/Scan"
        );
    }

    #[test]
    fn requests_parse_with_their_id_and_params() {
        let request =
            parse_request(br#"{"id": 7, "params": {"path": "/dev/ttyRS485-1"}}"#).unwrap();
        assert_eq!(request.id, json!(7));
        assert_eq!(request.params["path"], "/dev/ttyRS485-1");
        // Params may be left out; ids may be strings.
        let request = parse_request(br#"{"id": "a"}"#).unwrap();
        assert_eq!(request.id, json!("a"));
        assert_eq!(request.params, json!({}));
    }

    #[test]
    fn bad_payloads_are_parse_errors_and_keep_the_id_when_they_can() {
        for payload in [&b"not json"[..], b"[1,2]", b"\xff\xfe", b"", b"{\"id\": 1"] {
            let (id, error) = parse_request(payload).unwrap_err();
            assert_eq!(id, Value::Null);
            assert_eq!(error.code, code::PARSE_ERROR, "{payload:?}");
        }
        let (id, error) = parse_request(br#"{"id": 3, "params": [1]}"#).unwrap_err();
        assert_eq!(id, json!(3));
        assert_eq!(error.code, code::SERVER_ERROR);
    }

    #[test]
    fn silence_and_a_total_timeout_share_a_code_and_are_told_apart() {
        let silence = RpcError::timeout("Port IO error: no reply from slave 99 on …");
        assert!(silence.is_no_reply());
        let total = RpcError::timeout(format!("{TOTAL_TIMEOUT_MESSAGE}: port/Load took longer"));
        assert!(!total.is_no_reply());
        assert!(!RpcError::server("Port IO error: no reply").is_no_reply());
    }

    #[test]
    fn replies_have_the_shape_of_libwbmqtt() {
        let ok = reply_payload(&json!(5), &Ok(json!({"response": "0001"})));
        assert_eq!(ok, r#"{"id":5,"result":{"response":"0001"},"error":null}"#);
        let failed = reply_payload(&json!("x"), &Err(RpcError::timeout("RPC request timeout")));
        assert_eq!(
            failed,
            r#"{"id":"x","result":null,"error":{"code":-32600,"message":"RPC request timeout"}}"#
        );
        let (id, outcome) = parse_reply(failed.as_bytes()).unwrap();
        assert_eq!(id, json!("x"));
        assert_eq!(outcome.unwrap_err().code, code::REQUEST_TIMEOUT);
        let (_, outcome) = parse_reply(ok.as_bytes()).unwrap();
        assert_eq!(outcome.unwrap()["response"], "0001");
    }
}
