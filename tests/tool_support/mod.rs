//! Runs a site tool of the real binary (`rtu2mqtt read`, `scan`, …) to its end.
#![allow(dead_code)]

use std::process::Command;

/// How a tool run ended: its exit code (-1 when killed by a signal) and what it printed.
pub struct Run {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

/// `rtu2mqtt <args>`, waited for.
pub fn tool(args: &[&str]) -> Run {
    let output = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .args(args)
        .output()
        .expect("the binary runs");
    Run {
        code: output.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&output.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&output.stderr).into_owned(),
    }
}
