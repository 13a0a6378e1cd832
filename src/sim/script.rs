//! Timed scenarios (`--script FILE`): one control command per line, with timing fields.
//!
//! ```text
//! // toggle coil 0 of device 20 every 100 ms, 50 times, starting 1 s after start-up
//! {"at_ms": 1000, "every_ms": 100, "count": 50, "cmd": "toggle", "device": 20, "type": "coil", "address": 0}
//! {"at_ms": 3000, "cmd": "reboot", "device": 20}
//! ```
//! `at_ms` (default 0) counts from start-up; `every_ms` repeats the command, `count` times
//! (forever without `count`). Empty lines and lines starting with `//` or `#` are skipped.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::io;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use serde_json::Value;

use super::control::{execute, ControlCommand};
use super::runtime::SimRuntime;

#[derive(Debug, Clone)]
pub struct ScriptStep {
    pub at: Duration,
    pub every: Option<Duration>,
    pub count: Option<u64>,
    pub command: ControlCommand,
}

pub fn parse_script(text: &str) -> Result<Vec<ScriptStep>, String> {
    let mut steps = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with("//") || line.starts_with('#') {
            continue;
        }
        let bad = |message: String| format!("script line {}: {message}", number + 1);
        let mut value: Value = serde_json::from_str(line).map_err(|e| bad(e.to_string()))?;
        let fields = value
            .as_object_mut()
            .ok_or_else(|| bad("not a JSON object".into()))?;
        let mut take_ms = |key: &str| -> Result<Option<u64>, String> {
            match fields.remove(key) {
                None => Ok(None),
                Some(v) => v
                    .as_u64()
                    .map(Some)
                    .ok_or_else(|| bad(format!("{key} is not a whole number"))),
            }
        };
        let at = take_ms("at_ms")?.unwrap_or(0);
        let every = take_ms("every_ms")?.filter(|&ms| ms > 0);
        let count = take_ms("count")?;
        let command: ControlCommand =
            serde_json::from_value(value).map_err(|e| bad(e.to_string()))?;
        steps.push(ScriptStep {
            at: Duration::from_millis(at),
            every: every.map(Duration::from_millis),
            count,
            command,
        });
    }
    Ok(steps)
}

/// Runs the steps on their own thread; failed commands are logged.
pub fn spawn_script(
    steps: Vec<ScriptStep>,
    runtime: Arc<SimRuntime>,
) -> io::Result<JoinHandle<()>> {
    std::thread::Builder::new()
        .name("sim-script".into())
        .spawn(move || {
            // (due, step index, runs so far)
            let mut queue: BinaryHeap<Reverse<(Duration, usize, u64)>> = steps
                .iter()
                .enumerate()
                .map(|(i, step)| Reverse((step.at, i, 0)))
                .collect();
            while let Some(Reverse((due, index, runs))) = queue.pop() {
                while runtime.clock.now() < due {
                    if runtime.stopped() {
                        return;
                    }
                    std::thread::sleep(
                        due.saturating_sub(runtime.clock.now())
                            .min(Duration::from_millis(50)),
                    );
                }
                let Some(step) = steps.get(index) else {
                    continue;
                };
                let outcome = runtime.with_bus(|bus, now| execute(bus, now, &step.command));
                if outcome.reply.get("ok") != Some(&Value::Bool(true)) {
                    tracing::warn!("sim: script: {:?}: {}", step.command.cmd, outcome.reply);
                }
                let runs = runs + 1;
                if let Some(every) = step.every {
                    if step.count.is_none_or(|count| runs < count) {
                        queue.push(Reverse((due + every, index, runs)));
                    }
                }
            }
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_steps() {
        let steps = parse_script(
            "// comment\n\n{\"at_ms\": 5, \"every_ms\": 100, \"count\": 3, \"cmd\": \"toggle\", \"device\": 20, \"type\": \"coil\", \"address\": 0}\n{\"cmd\":\"reboot\",\"device\":\"x\"}",
        )
        .unwrap();
        assert_eq!(steps.len(), 2);
        assert_eq!(steps[0].every, Some(Duration::from_millis(100)));
        assert_eq!(steps[0].command.cmd, "toggle");
        assert_eq!(steps[1].at, Duration::ZERO);
        assert!(parse_script("{\"at_ms\": -1, \"cmd\": \"x\"}").is_err());
        assert!(parse_script("[1]").is_err());
    }
}
