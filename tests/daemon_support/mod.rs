//! Runs the real `rtu2mqtt run` for end-to-end tests: config in a temp dir, the repository's
//! templates, stderr to a log that is printed when the test fails; killed when dropped.
#![allow(dead_code)]

use rtu2mqtt::child::StopWithParent;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};

use serde_json::Value;

pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

pub struct DaemonProcess {
    pub child: Child,
    dir: tempfile::TempDir,
}

impl DaemonProcess {
    /// `extra` goes after `run` (e.g. `--stdio`); stdin and stdout are set by the caller.
    pub fn start(config: &Value, extra: &[&str], stdin: Stdio, stdout: Stdio) -> Self {
        Self::start_with_env(config, extra, stdin, stdout, &[])
    }

    /// [`start`](Self::start) with extra environment variables (e.g. `RUST_LOG`).
    pub fn start_with_env(
        config: &Value,
        extra: &[&str],
        stdin: Stdio,
        stdout: Stdio,
        env: &[(&str, &str)],
    ) -> Self {
        Self::spawn(
            Command::new(env!("CARGO_BIN_EXE_rtu2mqtt")),
            config,
            extra,
            stdin,
            stdout,
            env,
        )
    }

    /// [`start`](Self::start) under `prlimit --nofile=N`: the daemon may hold at most `nofile`
    /// file descriptors (a small number makes running out of them quick to reach).
    pub fn start_with_file_limit(config: &Value, extra: &[&str], nofile: u32) -> Self {
        let mut prlimit = Command::new("prlimit");
        prlimit
            .arg(format!("--nofile={nofile}:{nofile}"))
            .arg("--")
            .arg(env!("CARGO_BIN_EXE_rtu2mqtt"));
        Self::spawn(prlimit, config, extra, Stdio::null(), Stdio::null(), &[])
    }

    fn spawn(
        mut command: Command,
        config: &Value,
        extra: &[&str],
        stdin: Stdio,
        stdout: Stdio,
        env: &[(&str, &str)],
    ) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let config_path = dir.path().join("config.json");
        std::fs::write(&config_path, config.to_string()).unwrap();
        let child = command
            .stop_with_parent()
            .arg("run")
            .args(extra)
            .arg("--templates")
            .arg(repo("templates"))
            .arg("-c")
            .arg(&config_path)
            .envs(env.iter().copied())
            .stdin(stdin)
            .stdout(stdout)
            .stderr(std::fs::File::create(dir.path().join("daemon.log")).unwrap())
            .spawn()
            .unwrap();
        Self { child, dir }
    }

    /// What the daemon has logged so far (stderr).
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("daemon.log")).unwrap_or_default()
    }

    /// The last `lines` lines of the daemon's log, newest first (for failure messages).
    pub fn log_tail(&self, lines: usize) -> String {
        let log = self.log();
        log.lines().rev().take(lines).collect::<Vec<_>>().join("\n")
    }

    /// SIGTERM, as systemd stops the service; returns the exit status.
    pub fn terminate(&mut self) -> ExitStatus {
        let pid = nix::unistd::Pid::from_raw(self.child.id() as i32);
        nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
        self.child.wait().unwrap()
    }
}

impl Drop for DaemonProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if std::thread::panicking() {
            let log =
                std::fs::read_to_string(self.dir.path().join("daemon.log")).unwrap_or_default();
            eprintln!("--- daemon log ---\n{log}");
        }
    }
}
