//! The whole chain as separate processes, for benchmarks and end-to-end tests: a real mosquitto on
//! a free 127.0.0.1 port, `rtu2mqtt sim` on a pty (with its control socket), `rtu2mqtt run`
//! against both, and an MQTT subscriber that stamps every message on arrival.
//!
//! Everything is stamped on CLOCK_MONOTONIC: the simulator's change log (`watch` on the control
//! socket, `mono_ns`) and the subscriber's arrivals, so that change → publication latencies are
//! differences of readings of one clock. Processes are stopped (SIGTERM, then SIGKILL) and the
//! scratch directory removed when the [`Harness`] drops.

use crate::child::StopWithParent;
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use serde_json::{json, Value};

/// Where Debian and Ubuntu install the broker.
pub const DEFAULT_MOSQUITTO: &str = "/usr/sbin/mosquitto";
/// The broker's password file tool, for brokers that refuse anonymous clients.
pub const DEFAULT_MOSQUITTO_PASSWD: &str = "/usr/bin/mosquitto_passwd";
/// How long a process may take to come up (broker listening, simulator `ready`).
const START_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a process may take to exit after SIGTERM before it is killed.
const STOP_TIMEOUT: Duration = Duration::from_secs(3);

/// CLOCK_MONOTONIC in nanoseconds: the clock of the simulator's change log.
pub fn monotonic_ns() -> u64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC).map_or(0, |ts| {
        u64::try_from(ts.tv_sec()).unwrap_or(0) * 1_000_000_000
            + u64::try_from(ts.tv_nsec()).unwrap_or(0)
    })
}

/// One register change from the simulator's change log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Change {
    pub mono_ns: u64,
    /// Modbus address of the device.
    pub address: u8,
    /// `coil`, `discrete`, `holding` or `input`.
    pub register_type: String,
    pub register: u16,
    pub value: u16,
    /// `control` (the harness or a script) or `master` (a write request from the daemon).
    pub origin: String,
}

impl Change {
    fn from_json(line: &str) -> Option<Self> {
        let value: Value = serde_json::from_str(line).ok()?;
        Some(Self {
            mono_ns: value["mono_ns"].as_u64()?,
            address: u8::try_from(value["address"].as_u64()?).ok()?,
            register_type: value["type"].as_str()?.to_string(),
            register: u16::try_from(value["register"].as_u64()?).ok()?,
            value: u16::try_from(value["value"].as_u64()?).ok()?,
            origin: value["origin"].as_str().unwrap_or("").to_string(),
        })
    }
}

/// One MQTT message as the subscriber received it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Publication {
    /// When the subscriber got it (CLOCK_MONOTONIC).
    pub mono_ns: u64,
    pub topic: String,
    pub payload: String,
    pub retain: bool,
}

/// CPU time and memory of a process, from /proc.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ProcessStats {
    /// CPU time of all its threads (live and exited), to the nanosecond.
    pub cpu: Duration,
    /// Peak resident set (VmHWM), in KiB.
    pub peak_rss_kib: u64,
    /// Resident set now (VmRSS), in KiB.
    pub rss_kib: u64,
    /// The private part of the resident set now (RssAnon: heap, stacks), in KiB. VmHWM and
    /// VmRSS also count the binary's code pages (file-backed, shared, ~9 MB for a build with
    /// the `bench` feature), which the daemon's own memory use does not change.
    pub anon_rss_kib: u64,
    /// Times its threads went to sleep (voluntary context switches, summed over the live
    /// threads): each is a wake-up paid later.
    pub sleeps: u64,
}

/// Reads /proc/<pid>/stat and /proc/<pid>/status. None when the process is gone.
pub fn process_stats(pid: u32) -> Option<ProcessStats> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may contain spaces) in parentheses.
    let rest = stat.get(stat.rfind(')')? + 2..)?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line, 12 and 13 after the name.
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib = |key: &str| {
        status
            .lines()
            .find_map(|line| line.strip_prefix(key))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    Some(ProcessStats {
        cpu: process_cpu_clock(pid).unwrap_or_else(|| ticks_to_duration(utime + stime)),
        peak_rss_kib: kib("VmHWM:"),
        rss_kib: kib("VmRSS:"),
        anon_rss_kib: kib("RssAnon:"),
        sleeps: voluntary_switches(pid),
    })
}

fn voluntary_switches(pid: u32) -> u64 {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return 0;
    };
    tasks
        .flatten()
        .filter_map(|task| std::fs::read_to_string(task.path().join("status")).ok())
        .filter_map(|status| {
            status
                .lines()
                .find_map(|line| line.strip_prefix("voluntary_ctxt_switches:"))
                .and_then(|v| v.trim().parse::<u64>().ok())
        })
        .sum()
}

/// The process's CPU clock (the sum of utime and stime of all its threads, kept by the
/// scheduler in nanoseconds). The ticks of /proc/<pid>/stat are 10 ms: a scenario's window of
/// a few seconds at under 1 % of a core is only a handful of them.
fn process_cpu_clock(pid: u32) -> Option<Duration> {
    let pid = nix::unistd::Pid::from_raw(i32::try_from(pid).ok()?);
    let clock = nix::time::clock_getcpuclockid(pid).ok()?;
    let now = nix::time::clock_gettime(clock).ok()?;
    Some(Duration::from(now))
}

fn ticks_to_duration(ticks: u64) -> Duration {
    // SAFETY: sysconf only reads a system constant.
    let per_second = unsafe { nix::libc::sysconf(nix::libc::_SC_CLK_TCK) };
    let per_second = u64::try_from(per_second)
        .ok()
        .filter(|&t| t > 0)
        .unwrap_or(100);
    Duration::from_nanos(ticks.saturating_mul(1_000_000_000) / per_second)
}

/// Polls `check` every `every` until it returns Some or `timeout` passes.
pub fn wait_until<T>(
    timeout: Duration,
    every: Duration,
    mut check: impl FnMut() -> Option<T>,
) -> Option<T> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(found) = check() {
            return Some(found);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(every);
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What to run: the binary, the broker, the bus and the templates both sides use.
#[derive(Debug, Clone)]
pub struct HarnessOptions {
    /// The `rtu2mqtt` binary (`std::env::current_exe()` in `bench`, `CARGO_BIN_EXE_rtu2mqtt` in
    /// tests).
    pub binary: PathBuf,
    pub mosquitto: PathBuf,
    /// The simulator's bus file (docs/sim.md).
    pub bus: Value,
    /// Template files written to the scratch directory and given to both processes as
    /// `--templates`: (file name, template JSON).
    pub templates: Vec<(String, Value)>,
    /// `RUST_LOG` of the daemon and the simulator (their stderr goes to files in the scratch
    /// directory); None keeps their defaults.
    pub log_filter: Option<String>,
    /// A TLS listener on the broker beside the plain one (which the harness's own subscriber
    /// keeps using); its port is [`Harness::mqtt_tls_port`].
    pub broker_tls: Option<BrokerTls>,
    /// More arguments for `rtu2mqtt sim` (e.g. `--tcp 127.0.0.1:0`); what it then listens on
    /// is in its banner ([`Harness::sim_listening`]).
    pub sim_args: Vec<String>,
}

impl HarnessOptions {
    pub fn new(binary: impl Into<PathBuf>, bus: Value, templates: Vec<(String, Value)>) -> Self {
        Self {
            binary: binary.into(),
            mosquitto: PathBuf::from(DEFAULT_MOSQUITTO),
            bus,
            templates,
            // For looking into a run: BENCH_LOG=rtu2mqtt=debug logs every frame.
            log_filter: std::env::var("BENCH_LOG").ok(),
            broker_tls: None,
            // The controller's UART as the daemon leaves it (rx_trig_bytes 1): a frame's end
            // is handed over at its stop bit.
            sim_args: vec!["--rx-fifo-trigger".to_owned(), "1".to_owned()],
        }
    }
}

/// The broker's side of a TLS listener (PEM files).
#[derive(Debug, Clone)]
pub struct BrokerTls {
    /// The CA that signed the client certificates the broker asks for.
    pub ca_file: PathBuf,
    pub cert_file: PathBuf,
    pub key_file: PathBuf,
}

/// A scratch directory removed on drop (the library has no tempfile).
struct ScratchDir(PathBuf);

impl ScratchDir {
    fn create() -> anyhow::Result<Self> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let path = std::env::temp_dir().join(format!(
            "rtu2mqtt-harness-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&path).with_context(|| format!("creating {}", path.display()))?;
        Ok(Self(path))
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        // BENCH_KEEP_SCRATCH=1 leaves the logs, configs and bus file for a post-mortem.
        if std::env::var_os("BENCH_KEEP_SCRATCH").is_some() {
            eprintln!("kept {}", self.0.display());
            return;
        }
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// SIGTERM, wait a little, then SIGKILL.
fn stop_child(child: &mut Child) {
    if let Ok(Some(_)) = child.try_wait() {
        return;
    }
    if let Ok(pid) = i32::try_from(child.id()) {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(pid),
            nix::sys::signal::Signal::SIGTERM,
        );
    }
    let deadline = Instant::now() + STOP_TIMEOUT;
    while Instant::now() < deadline {
        if let Ok(Some(_)) = child.try_wait() {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = child.kill();
    let _ = child.wait();
}

/// The control connection: one command line out, one reply line back.
struct ControlConnection {
    writer: UnixStream,
    reader: BufReader<UnixStream>,
}

/// Broker, simulator, subscriber and (after [`Harness::start_daemon`]) the daemon.
pub struct Harness {
    binary: PathBuf,
    mosquitto: PathBuf,
    dir: ScratchDir,
    broker: Child,
    mqtt_port: u16,
    /// The TLS listener's port and its lines of mosquitto.conf (kept for restarts).
    mqtt_tls: Option<(u16, String)>,
    sim: Child,
    /// The simulator's banner, up to `ready`.
    sim_banner: Vec<String>,
    pty: PathBuf,
    control_path: PathBuf,
    control: Mutex<ControlConnection>,
    daemon: Option<Child>,
    daemon_started_ns: u64,
    /// `RUST_LOG` of the daemon (see [`HarnessOptions::log_filter`]).
    log_filter: Option<String>,
    /// Template directories searched by the daemon before the harness's own (which wins).
    extra_template_dirs: Vec<PathBuf>,
    changes: Arc<Mutex<Vec<Change>>>,
    publications: Arc<Mutex<Vec<Publication>>>,
    subscriber: rumqttc::Client,
    stopping: Arc<AtomicBool>,
}

impl Harness {
    /// Starts the broker, the simulator (waits for `ready`), the change-log watcher and the
    /// subscriber (waits for its subscription to be acknowledged). The daemon is not started.
    pub fn start(options: &HarnessOptions) -> anyhow::Result<Self> {
        let dir = ScratchDir::create()?;
        let templates = dir.0.join("templates");
        std::fs::create_dir_all(&templates)?;
        for (name, template) in &options.templates {
            std::fs::write(
                templates.join(name),
                serde_json::to_string_pretty(template)?,
            )?;
        }
        let bus_path = dir.0.join("bus.json");
        std::fs::write(&bus_path, serde_json::to_string_pretty(&options.bus)?)?;

        let mqtt_tls = match &options.broker_tls {
            Some(tls) => {
                let port = free_port()?;
                Some((port, tls_listener(port, tls)))
            }
            None => None,
        };
        let extra = mqtt_tls.as_ref().map_or("", |(_, lines)| lines.as_str());
        let (broker, mqtt_port) = start_broker(&options.mosquitto, &dir.0, extra)?;
        let stopping = Arc::new(AtomicBool::new(false));
        let pty = dir.0.join("ttyRS485-sim");
        let control_path = dir.0.join("control.sock");
        let mut sim_command = Command::new(&options.binary);
        sim_command.stop_with_parent();
        sim_command
            .arg("sim")
            .arg("--bus")
            .arg(&bus_path)
            .arg("--templates")
            .arg(&templates)
            .arg("--pty")
            .arg(&pty)
            .arg("--control")
            .arg(&control_path)
            .args(&options.sim_args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(dir.0.join("sim.log"))?);
        if let Some(filter) = &options.log_filter {
            sim_command.env("RUST_LOG", filter);
        }
        let mut sim = sim_command
            .spawn()
            .with_context(|| format!("starting {} sim", options.binary.display()))?;
        let sim_banner = match wait_for_ready(&mut sim) {
            Ok(banner) => banner,
            Err(err) => {
                stop_child(&mut sim);
                let mut broker = broker;
                stop_child(&mut broker);
                let log = std::fs::read_to_string(dir.0.join("sim.log")).unwrap_or_default();
                bail!("{err}\n--- simulator log ---\n{log}");
            }
        };

        let changes = Arc::new(Mutex::new(Vec::new()));
        let control = connect_control(&control_path)?;
        watch_changes(&control_path, Arc::clone(&changes), Arc::clone(&stopping))?;
        let publications = Arc::new(Mutex::new(Vec::new()));
        let subscriber = subscribe(mqtt_port, Arc::clone(&publications), Arc::clone(&stopping))?;

        Ok(Self {
            binary: options.binary.clone(),
            log_filter: options.log_filter.clone(),
            extra_template_dirs: Vec::new(),
            mosquitto: options.mosquitto.clone(),
            dir,
            broker,
            mqtt_port,
            mqtt_tls,
            sim,
            sim_banner,
            pty,
            control_path,
            control: Mutex::new(control),
            daemon: None,
            daemon_started_ns: 0,
            changes,
            publications,
            subscriber,
            stopping,
        })
    }

    pub fn mqtt_port(&self) -> u16 {
        self.mqtt_port
    }

    /// The broker's TLS listener ([`HarnessOptions::broker_tls`]).
    pub fn mqtt_tls_port(&self) -> Option<u16> {
        self.mqtt_tls.as_ref().map(|(port, _)| *port)
    }

    fn broker_extra(&self) -> String {
        self.mqtt_tls
            .as_ref()
            .map_or_else(String::new, |(_, lines)| lines.clone())
    }

    /// The pty symlink the daemon's port opens.
    pub fn pty(&self) -> &Path {
        &self.pty
    }

    /// Where the simulator listens for `kind` (`tcp`, `modbus-tcp`: the banner's
    /// `tcp 127.0.0.1:40123 (115200 8N2)` line gives `127.0.0.1:40123`).
    pub fn sim_listening(&self, kind: &str) -> Option<String> {
        self.sim_banner.iter().find_map(|line| {
            let rest = line.strip_prefix(kind)?.strip_prefix(' ')?;
            rest.split_whitespace().next().map(str::to_string)
        })
    }

    pub fn control_socket(&self) -> &Path {
        &self.control_path
    }

    /// The scratch directory (daemon.log, sim.log, templates, bus.json, config.json).
    pub fn dir(&self) -> &Path {
        &self.dir.0
    }

    pub fn templates_dir(&self) -> PathBuf {
        self.dir.0.join("templates")
    }

    /// Puts a template library of a controller's size ([`super::library`]) on the daemon's
    /// search path, before the harness's own templates; returns its size in bytes. For the
    /// daemons started after it.
    pub fn add_template_library(&mut self) -> anyhow::Result<u64> {
        let dir = self.dir.0.join("library");
        let bytes = super::library::write_template_library(&dir)?;
        self.extra_template_dirs.push(dir);
        Ok(bytes)
    }

    /// A daemon config with this harness's broker: `ports` as given, `extra` top-level keys
    /// (e.g. `fast_modbus`) merged in.
    pub fn daemon_config(&self, ports: Value, extra: Value) -> Value {
        let mut config = json!({
            "mqtt": {"host": "127.0.0.1", "port": self.mqtt_port, "client_id": "rtu2mqtt-harness"},
            "max_unchanged_interval": -1,
            "ports": ports,
        });
        if let (Some(fields), Value::Object(extra)) = (config.as_object_mut(), extra) {
            fields.extend(extra);
        }
        config
    }

    /// Starts `rtu2mqtt run` with `config` (stderr to daemon.log). Stops a running one first.
    pub fn start_daemon(&mut self, config: &Value) -> anyhow::Result<()> {
        self.stop_daemon();
        let config_path = self.dir.0.join("config.json");
        std::fs::write(&config_path, serde_json::to_string_pretty(config)?)?;
        self.daemon_started_ns = monotonic_ns();
        let mut command = Command::new(&self.binary);
        command.stop_with_parent();
        if let Some(filter) = &self.log_filter {
            command.env("RUST_LOG", filter);
        }
        command.arg("run");
        for dir in &self.extra_template_dirs {
            command.arg("--templates").arg(dir);
        }
        let child = command
            .arg("--templates")
            .arg(self.templates_dir())
            .arg("-c")
            .arg(&config_path)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(self.dir.0.join("daemon.log"))?)
            .spawn()
            .with_context(|| format!("starting {} run", self.binary.display()))?;
        self.daemon = Some(child);
        Ok(())
    }

    /// SIGTERM (as systemd stops it), SIGKILL after a few seconds.
    pub fn stop_daemon(&mut self) {
        if let Some(mut child) = self.daemon.take() {
            stop_child(&mut child);
        }
    }

    /// When the daemon was started (CLOCK_MONOTONIC ns).
    pub fn daemon_started_ns(&self) -> u64 {
        self.daemon_started_ns
    }

    pub fn daemon_pid(&self) -> Option<u32> {
        self.daemon.as_ref().map(Child::id)
    }

    /// Has the daemon exited (and with what)?
    pub fn daemon_exit(&mut self) -> Option<std::process::ExitStatus> {
        self.daemon
            .as_mut()
            .and_then(|c| c.try_wait().ok().flatten())
    }

    pub fn sim_pid(&self) -> u32 {
        self.sim.id()
    }

    pub fn daemon_stats(&self) -> Option<ProcessStats> {
        process_stats(self.daemon_pid()?)
    }

    pub fn sim_stats(&self) -> Option<ProcessStats> {
        process_stats(self.sim.id())
    }

    /// The daemon's stderr so far.
    pub fn daemon_log(&self) -> String {
        std::fs::read_to_string(self.dir.0.join("daemon.log")).unwrap_or_default()
    }

    /// Sends one control command; its reply, or an error when it says `"ok": false`.
    pub fn control(&self, command: &Value) -> anyhow::Result<Value> {
        let mut connection = lock(&self.control);
        writeln!(connection.writer, "{command}")?;
        connection.writer.flush()?;
        let mut line = String::new();
        if connection.reader.read_line(&mut line)? == 0 {
            bail!("the simulator closed its control socket");
        }
        let reply: Value = serde_json::from_str(&line)
            .with_context(|| format!("control reply {line:?} is not JSON"))?;
        if reply["ok"] != Value::Bool(true) {
            bail!("control command {command} failed: {reply}");
        }
        Ok(reply)
    }

    /// The simulator's `stats` (requests served, registers read, pacing error).
    pub fn bus_stats(&self) -> anyhow::Result<Value> {
        self.control(&json!({"cmd": "stats"}))
    }

    /// Registers of one device as the simulator holds them now (`get` with `count`).
    pub fn registers(
        &self,
        device: u8,
        register_type: &str,
        address: u16,
        count: u16,
    ) -> anyhow::Result<Vec<u16>> {
        let reply = self.control(&json!({
            "cmd": "get", "device": device, "type": register_type, "address": address,
            "count": count,
        }))?;
        reply["values"]
            .as_array()
            .context("`get` without values")?
            .iter()
            .map(|v| {
                v.as_u64()
                    .and_then(|v| u16::try_from(v).ok())
                    .context("not a register value")
            })
            .collect()
    }

    /// Kills the broker (SIGKILL, as a crash: no persistence, its retained state is gone).
    pub fn kill_broker(&mut self) {
        let _ = self.broker.kill();
        let _ = self.broker.wait();
    }

    /// Starts a fresh broker on the same port (after [`Harness::kill_broker`]); the harness's
    /// subscriber reconnects and subscribes again by itself.
    pub fn restart_broker(&mut self) -> anyhow::Result<()> {
        self.kill_broker();
        let access = format!("allow_anonymous true\n{}", self.broker_extra());
        self.broker = launch_broker(&self.mosquitto, &self.dir.0, self.mqtt_port, &access)?;
        Ok(())
    }

    /// Starts a fresh broker on the same port that takes only `user` with `password` (the
    /// harness's own subscriber is anonymous and stays out).
    pub fn restart_broker_with_password(
        &mut self,
        user: &str,
        password: &str,
    ) -> anyhow::Result<()> {
        self.kill_broker();
        let file = self.dir.0.join("mosquitto.passwords");
        let status = Command::new(DEFAULT_MOSQUITTO_PASSWD)
            .arg("-b")
            .arg("-c")
            .arg(&file)
            .arg(user)
            .arg(password)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .with_context(|| format!("running {DEFAULT_MOSQUITTO_PASSWD}"))?;
        if !status.success() {
            bail!("{DEFAULT_MOSQUITTO_PASSWD} failed: {status}");
        }
        let access = format!(
            "allow_anonymous false\npassword_file {}\n{}",
            file.display(),
            self.broker_extra()
        );
        self.broker = launch_broker(&self.mosquitto, &self.dir.0, self.mqtt_port, &access)?;
        Ok(())
    }

    /// The broker's retained state (topic → payload) as a new subscriber receives it: collected
    /// until no message came for `quiet`.
    pub fn retained_snapshot(
        &self,
        quiet: Duration,
    ) -> anyhow::Result<std::collections::BTreeMap<String, String>> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let mut options = rumqttc::MqttOptions::new(
            format!(
                "rtu2mqtt-harness-snapshot-{}-{}",
                std::process::id(),
                COUNTER.fetch_add(1, Ordering::Relaxed)
            ),
            "127.0.0.1",
            self.mqtt_port,
        );
        options.set_max_packet_size(1 << 20, 1 << 20);
        let (client, mut connection) = rumqttc::Client::new(options, 64);
        client.subscribe("#", rumqttc::QoS::AtMostOnce)?;
        let mut state = std::collections::BTreeMap::new();
        let mut subscribed = false;
        let deadline = Instant::now() + START_TIMEOUT;
        loop {
            match connection.recv_timeout(quiet) {
                Ok(Ok(rumqttc::Event::Incoming(rumqttc::Packet::Publish(message)))) => {
                    if message.retain {
                        let payload = String::from_utf8_lossy(&message.payload).into_owned();
                        if payload.is_empty() {
                            state.remove(&message.topic);
                        } else {
                            state.insert(message.topic, payload);
                        }
                    }
                }
                Ok(Ok(rumqttc::Event::Incoming(rumqttc::Packet::SubAck(_)))) => subscribed = true,
                Ok(Ok(_)) => {}
                Ok(Err(err)) => bail!("snapshot subscriber: {err}"),
                Err(_) if subscribed => break,
                Err(_) => {}
            }
            if Instant::now() > deadline {
                bail!("the broker did not send its retained state");
            }
        }
        let _ = client.disconnect();
        Ok(state)
    }

    /// Open file descriptors of the daemon (/proc/<pid>/fd); None when it is not running.
    pub fn daemon_open_fds(&self) -> Option<usize> {
        let pid = self.daemon_pid()?;
        Some(std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count())
    }

    /// Every change logged so far.
    pub fn changes(&self) -> Vec<Change> {
        lock(&self.changes).clone()
    }

    /// Every message received so far.
    pub fn publications(&self) -> Vec<Publication> {
        lock(&self.publications).clone()
    }

    /// Messages received so far (cheaper than cloning them).
    pub fn publication_count(&self) -> usize {
        lock(&self.publications).len()
    }

    /// Runs `f` on the messages received so far without copying them.
    pub fn with_publications<R>(&self, f: impl FnOnce(&[Publication]) -> R) -> R {
        f(&lock(&self.publications))
    }
}

impl Drop for Harness {
    fn drop(&mut self) {
        self.stopping.store(true, Ordering::SeqCst);
        self.stop_daemon();
        let _ = self.subscriber.disconnect();
        stop_child(&mut self.sim);
        stop_child(&mut self.broker);
    }
}

/// mosquitto.conf lines of a TLS listener on `port` that requires a client certificate.
fn tls_listener(port: u16, tls: &BrokerTls) -> String {
    // Started as root, mosquitto would drop to its own user, which cannot read 0600 keys (ours:
    // the key file's owner is who made it).
    let made_by_root = std::fs::metadata(&tls.key_file)
        .is_ok_and(|meta| std::os::unix::fs::MetadataExt::uid(&meta) == 0);
    let user = if made_by_root { "user root\n" } else { "" };
    format!(
        "{user}listener {port} 127.0.0.1\ncafile {}\ncertfile {}\nkeyfile {}\n\
         require_certificate true\n",
        tls.ca_file.display(),
        tls.cert_file.display(),
        tls.key_file.display()
    )
}

/// `extra`: more mosquitto.conf lines (listeners) after the plain listener's.
fn start_broker(mosquitto: &Path, dir: &Path, extra: &str) -> anyhow::Result<(Child, u16)> {
    if !mosquitto.exists() {
        bail!(
            "{} not found: the harness needs a real MQTT broker (apt-get install mosquitto)",
            mosquitto.display()
        );
    }
    let port = free_port()?;
    let access = format!("allow_anonymous true\n{extra}");
    let child = launch_broker(mosquitto, dir, port, &access)?;
    Ok((child, port))
}

/// Starts mosquitto on `port` without persistence, with `access` lines (anonymous or a password
/// file), and waits until it listens.
fn launch_broker(mosquitto: &Path, dir: &Path, port: u16, access: &str) -> anyhow::Result<Child> {
    let config = dir.join("mosquitto.conf");
    std::fs::write(
        &config,
        format!("listener {port} 127.0.0.1\n{access}persistence false\n"),
    )?;
    let mut child = Command::new(mosquitto)
        .stop_with_parent()
        .arg("-c")
        .arg(&config)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {}", mosquitto.display()))?;
    let deadline = Instant::now() + START_TIMEOUT;
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        if let Ok(Some(status)) = child.try_wait() {
            bail!("mosquitto exited at start ({status}) on port {port}");
        }
        if Instant::now() > deadline {
            stop_child(&mut child);
            bail!("mosquitto did not listen on 127.0.0.1:{port}");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(child)
}

/// Reads the simulator's banner up to `ready` (returned); keeps draining its stdout afterwards.
fn wait_for_ready(sim: &mut Child) -> anyhow::Result<Vec<String>> {
    let stdout = sim.stdout.take().context("simulator stdout")?;
    let (sender, receiver) = mpsc::channel();
    std::thread::Builder::new()
        .name("harness-sim-stdout".into())
        .spawn(move || {
            let mut banner = Vec::new();
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if line == "ready" {
                    let _ = sender.send(std::mem::take(&mut banner));
                } else if banner.len() < 1000 {
                    banner.push(line);
                }
            }
        })?;
    receiver
        .recv_timeout(START_TIMEOUT)
        .context("the simulator did not print `ready`")
}

fn connect_control(path: &Path) -> anyhow::Result<ControlConnection> {
    let writer = UnixStream::connect(path)
        .with_context(|| format!("connecting to the control socket {}", path.display()))?;
    let reader = BufReader::new(writer.try_clone()?);
    Ok(ControlConnection { writer, reader })
}

/// A second control connection that asks to `watch` and collects the change log.
fn watch_changes(
    path: &Path,
    changes: Arc<Mutex<Vec<Change>>>,
    stopping: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let mut connection = connect_control(path)?;
    writeln!(connection.writer, "{}", json!({"cmd": "watch"}))?;
    let mut reply = String::new();
    connection.reader.read_line(&mut reply)?;
    if !reply.contains("\"ok\":true") {
        bail!("the simulator refused to watch: {reply}");
    }
    std::thread::Builder::new()
        .name("harness-watch".into())
        .spawn(move || {
            let mut line = String::new();
            loop {
                line.clear();
                match connection.reader.read_line(&mut line) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {
                        if let Some(change) = Change::from_json(line.trim()) {
                            lock(&changes).push(change);
                        } else if !stopping.load(Ordering::SeqCst) {
                            tracing::debug!("harness: change log line not understood: {line}");
                        }
                    }
                }
            }
        })?;
    Ok(())
}

/// Subscribes to `#` and stamps each message on arrival; returns once the broker acknowledged.
fn subscribe(
    port: u16,
    publications: Arc<Mutex<Vec<Publication>>>,
    stopping: Arc<AtomicBool>,
) -> anyhow::Result<rumqttc::Client> {
    let mut options = rumqttc::MqttOptions::new(
        format!("rtu2mqtt-harness-{}-{port}", std::process::id()),
        "127.0.0.1",
        port,
    );
    options.set_keep_alive(Duration::from_secs(30));
    options.set_max_packet_size(1 << 20, 1 << 20);
    let (client, mut connection) = rumqttc::Client::new(options, 64);
    client
        .subscribe("#", rumqttc::QoS::AtMostOnce)
        .context("subscribing")?;
    // A clean session forgets the subscription when the broker restarts: subscribe again on
    // every connection after the first (not on the first: the retained state would come twice).
    let resubscriber = client.clone();
    let mut connections = 0_u32;
    let (subscribed, acknowledged) = mpsc::channel();
    std::thread::Builder::new()
        .name("harness-mqtt".into())
        .spawn(move || {
            for event in connection.iter() {
                match event {
                    Ok(rumqttc::Event::Incoming(rumqttc::Packet::Publish(message))) => {
                        let mono_ns = monotonic_ns();
                        lock(&publications).push(Publication {
                            mono_ns,
                            topic: message.topic,
                            payload: String::from_utf8_lossy(&message.payload).into_owned(),
                            retain: message.retain,
                        });
                    }
                    Ok(rumqttc::Event::Incoming(rumqttc::Packet::SubAck(_))) => {
                        let _ = subscribed.send(());
                    }
                    Ok(rumqttc::Event::Incoming(rumqttc::Packet::ConnAck(_))) => {
                        connections += 1;
                        if connections > 1 {
                            let _ = resubscriber.try_subscribe("#", rumqttc::QoS::AtMostOnce);
                        }
                    }
                    Ok(_) => {}
                    Err(_) if stopping.load(Ordering::SeqCst) => break,
                    Err(err) => {
                        tracing::debug!("harness: subscriber: {err}");
                        std::thread::sleep(Duration::from_millis(100));
                    }
                }
            }
        })?;
    acknowledged
        .recv_timeout(START_TIMEOUT)
        .context("the broker did not acknowledge the subscription")?;
    Ok(client)
}
