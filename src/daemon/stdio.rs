//! Device updates as JSON lines on stdout, control writes as JSON lines on stdin: the bus side
//! without a broker, for tests, debugging and scripting.
//!
//! Out: `{"added":"relay6_20"}`, `{"device":"relay6_20","control":"K1","value":"1"}`,
//! `{"device":…,"control":…,"error":"r"}`, `{"device":…,"online":false}`, `{"removed":…}`.
//! In: `{"device":"relay6_20","control":"K1","value":"1"}` (the value may also be a JSON number
//! or boolean).

use serde_json::json;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::sync::mpsc;
use tracing::warn;

use crate::device_updates::{ControlWrite, DeviceUpdate, Repeats};

/// The values this sink needs the device models to report besides the changes: every event
/// value, which it prints.
pub const REPEATS: Repeats = Repeats::Events;

pub fn update_line(update: &DeviceUpdate) -> serde_json::Value {
    match update {
        DeviceUpdate::Added(device) => json!({ "added": device.id }),
        DeviceUpdate::Identity {
            device_id,
            identity,
        } => json!({
            "device": device_id,
            "model": identity.model,
            "serial_number": identity.serial_number,
            "firmware": identity.firmware,
        }),
        DeviceUpdate::Removed { device_id } => json!({ "removed": device_id }),
        DeviceUpdate::Value {
            device_id,
            control_id,
            value,
            from_event,
            ..
        } => {
            json!({ "device": &**device_id, "control": &**control_id, "value": &**value, "event": from_event })
        }
        DeviceUpdate::ControlError {
            device_id,
            control_id,
            errors,
        } => {
            json!({ "device": device_id, "control": control_id, "error": errors.to_string() })
        }
        DeviceUpdate::Online { device_id, online } => {
            json!({ "device": device_id, "online": online })
        }
        DeviceUpdate::BusServed { device_id } => json!({ "device": device_id, "bus_served": true }),
    }
}

/// Prints every update until the queue closes; like MQTT, a value read again unchanged is not
/// printed again (event values always are).
pub async fn print_updates(mut updates: mpsc::Receiver<DeviceUpdate>) {
    let mut stdout = tokio::io::stdout();
    while let Some(update) = updates.recv().await {
        if !printed(&update) {
            continue;
        }
        let line = format!("{}\n", update_line(&update));
        if stdout.write_all(line.as_bytes()).await.is_err() || stdout.flush().await.is_err() {
            return;
        }
    }
}

/// Whether the stdout sink prints `update`: all but a value read again unchanged (whether it
/// changed is the device model's to say).
fn printed(update: &DeviceUpdate) -> bool {
    !matches!(
        update,
        DeviceUpdate::Value {
            from_event: false,
            changed: false,
            ..
        }
    )
}

/// Reads control writes from stdin until it closes.
pub async fn read_writes(writes: mpsc::Sender<ControlWrite>) {
    let mut lines = BufReader::new(tokio::io::stdin()).lines();
    while let Ok(Some(line)) = lines.next_line().await {
        match write_of_line(&line) {
            Ok(write) => {
                if writes.send(write).await.is_err() {
                    return;
                }
            }
            Err(why) => warn!(%line, "{why}"),
        }
    }
}

/// One input line as a control write. The value is the `/on` payload: a string as it is, a
/// number or boolean as its text (`1`, `22.5`; `true` is `1`), so that a script need not quote
/// numbers.
fn write_of_line(line: &str) -> Result<ControlWrite, String> {
    let parsed: serde_json::Value =
        serde_json::from_str(line).map_err(|err| format!("not a JSON line: {err}"))?;
    let text = |key: &str| parsed.get(key).and_then(|f| f.as_str()).map(str::to_owned);
    let payload = match parsed.get("value") {
        Some(serde_json::Value::String(text)) => Some(text.clone()),
        Some(serde_json::Value::Number(number)) => Some(number.to_string()),
        Some(serde_json::Value::Bool(on)) => Some(if *on { "1" } else { "0" }.to_owned()),
        _ => None,
    };
    match (text("device"), text("control"), payload) {
        (Some(device_id), Some(control_id), Some(payload)) => Ok(ControlWrite {
            device_id,
            control_id,
            payload,
        }),
        _ => Err(
            "a write needs \"device\" and \"control\" strings and a \"value\" (a string, number \
             or boolean)"
                .to_owned(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(from_event: bool, changed: bool) -> DeviceUpdate {
        DeviceUpdate::Value {
            device_id: "relay6_20".into(),
            control_id: "K1".into(),
            value: "1".into(),
            from_event,
            changed,
        }
    }

    #[test]
    fn changes_and_every_event_value_are_printed() {
        assert!(printed(&value(false, true)));
        assert!(printed(&value(true, true)));
        assert!(printed(&value(true, false)), "an event repeating the value");
        assert!(!printed(&value(false, false)), "a read repeating the value");
        assert_eq!(
            update_line(&value(true, false)).to_string(),
            r#"{"device":"relay6_20","control":"K1","value":"1","event":true}"#
        );
    }

    #[test]
    fn a_write_value_may_be_a_string_a_number_or_a_boolean() {
        let payload = |line: &str| write_of_line(line).map(|w| w.payload);
        assert_eq!(
            payload(r#"{"device":"relay6_20","control":"K3","value":"1"}"#),
            Ok("1".to_owned())
        );
        assert_eq!(
            payload(r#"{"device":"relay6_20","control":"K3","value":1}"#),
            Ok("1".to_owned())
        );
        assert_eq!(
            payload(r#"{"device":"d","control":"T","value":22.5}"#),
            Ok("22.5".to_owned())
        );
        assert_eq!(
            payload(r#"{"device":"d","control":"T","value":-3}"#),
            Ok("-3".to_owned())
        );
        assert_eq!(
            payload(r#"{"device":"d","control":"K1","value":true}"#),
            Ok("1".to_owned())
        );
        assert_eq!(
            payload(r#"{"device":"d","control":"K1","value":false}"#),
            Ok("0".to_owned())
        );
        let write = write_of_line(r#"{"device":"relay6_20","control":"K3","value":1}"#).unwrap();
        assert_eq!(
            (write.device_id.as_str(), write.control_id.as_str()),
            ("relay6_20", "K3")
        );
        assert!(payload(r#"{"device":"d","control":"K1","value":null}"#)
            .unwrap_err()
            .contains("a \"value\""));
        assert!(payload(r#"{"device":"d","value":"1"}"#).is_err());
        assert!(payload("K1=1").unwrap_err().contains("not a JSON line"));
    }
}
