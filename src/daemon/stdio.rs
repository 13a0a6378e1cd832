//! Device updates as JSON lines on stdout, control writes as JSON lines on stdin: the bus side
//! without a broker, for tests, debugging and scripting.
//!
//! Out: `{"added":"relay6_20"}`, `{"device":"relay6_20","control":"K1","value":"1"}`,
//! `{"device":…,"control":…,"error":"r"}`, `{"device":…,"online":false}`, `{"removed":…}`.
//! In: `{"device":"relay6_20","control":"K1","value":"1"}`.

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
        let parsed: Result<serde_json::Value, _> = serde_json::from_str(&line);
        let field = |v: &serde_json::Value, key: &str| {
            v.get(key).and_then(|f| f.as_str()).map(str::to_owned)
        };
        match parsed {
            Ok(v) => match (
                field(&v, "device"),
                field(&v, "control"),
                field(&v, "value"),
            ) {
                (Some(device_id), Some(control_id), Some(payload)) => {
                    if writes
                        .send(ControlWrite {
                            device_id,
                            control_id,
                            payload,
                        })
                        .await
                        .is_err()
                    {
                        return;
                    }
                }
                _ => warn!(%line, "a write needs \"device\", \"control\" and \"value\" strings"),
            },
            Err(err) => warn!(%line, %err, "not a JSON line"),
        }
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
}
