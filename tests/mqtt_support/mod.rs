//! Shared by the `mqtt_*` integration tests: a real mosquitto on a free loopback port, an
//! in-process MQTT task fed through its channels, and helpers that read the broker's state.
#![allow(dead_code)]

use rtu2mqtt::child::StopWithParent;
use std::collections::BTreeMap;
use std::future::Future;
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rtu2mqtt::config::config_file::MqttConfig;
use rtu2mqtt::config::TemplateFile;
use rtu2mqtt::device::{resolve_template_device, ResolvedDevice};
use rtu2mqtt::device_updates::{ControlWrite, DeviceUpdate};
use rtu2mqtt::mqtt::{run_mqtt_reporting, MqttError, MqttSettings};
use rtu2mqtt::service::ServiceHealth;
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::{json, Value};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;

/// A program of the mosquitto packages, wherever `PATH` has it (as `scripts/test` accepts it),
/// or in /usr/sbin where Debian puts the broker (not on a user's PATH). Missing: the test
/// fails loudly, saying what to install.
pub fn mosquitto_program(name: &str) -> PathBuf {
    std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .chain([PathBuf::from("/usr/sbin"), PathBuf::from("/usr/bin")])
        .map(|dir| dir.join(name))
        .find(|path| path.is_file())
        .unwrap_or_else(|| {
            panic!("the MQTT integration tests need {name} (apt-get install mosquitto mosquitto-clients)")
        })
}

/// Ports tried before a broker start is given up (another process may take a free port first).
const PORT_ATTEMPTS: usize = 5;
pub const TIMEOUT: Duration = Duration::from_secs(15);

/// A mosquitto process for one test; killed when dropped.
pub struct Mosquitto {
    child: Option<Child>,
    pub port: u16,
    dir: tempfile::TempDir,
    /// `user:password` when anonymous clients are refused.
    credentials: Option<(String, String)>,
    /// Keeps its retained messages on disk across a [`Self::stop`] and [`Self::start_again`].
    persistent: bool,
}

impl Mosquitto {
    /// A broker on a free port. The port is free when asked for, but is released before
    /// mosquitto binds it: if another process takes it meanwhile, mosquitto exits and another
    /// port is tried.
    pub fn start() -> Self {
        Self::start_on_a_free_port(None)
    }

    /// A broker on `port` (a test that needs the port before the broker exists).
    pub fn start_on(port: u16) -> Self {
        let mut broker = Self::new(port, None);
        broker.launch();
        broker
    }

    /// A broker that takes only `user` with `password`.
    pub fn start_with_password(user: &str, password: &str) -> Self {
        Self::start_on_a_free_port(Some((user.into(), password.into())))
    }

    /// A broker that keeps its retained messages across a restart (persistence on, as on a
    /// Wiren Board controller): [`Self::stop`] saves them, [`Self::start_again`] loads them.
    pub fn start_persistent() -> Self {
        let mut broker = Self::new(free_port(), None);
        broker.persistent = true;
        // Started as root, mosquitto drops to its own user: let it write its database.
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(broker.dir.path(), std::fs::Permissions::from_mode(0o777))
            .expect("temp dir permissions");
        broker.launch();
        broker
    }

    fn new(port: u16, credentials: Option<(String, String)>) -> Self {
        Self {
            child: None,
            port,
            dir: tempfile::tempdir().expect("temp dir"),
            credentials,
            persistent: false,
        }
    }

    fn start_on_a_free_port(credentials: Option<(String, String)>) -> Self {
        for _ in 1..PORT_ATTEMPTS {
            let mut broker = Self::new(free_port(), credentials.clone());
            if broker.try_launch().is_ok() {
                return broker;
            }
        }
        let mut broker = Self::new(free_port(), credentials);
        broker.launch();
        broker
    }

    fn launch(&mut self) {
        if let Err(status) = self.try_launch() {
            panic!("mosquitto exited at start ({status}) on port {}", self.port);
        }
    }

    /// Starts mosquitto and waits until it listens; Err: it exited at start (its port taken).
    fn try_launch(&mut self) -> Result<(), std::process::ExitStatus> {
        let config = self.dir.path().join("mosquitto.conf");
        let access = match &self.credentials {
            None => "allow_anonymous true\n".to_string(),
            Some((user, password)) => {
                let file = self.dir.path().join("passwords");
                let status = Command::new(mosquitto_program("mosquitto_passwd"))
                    .arg("-b")
                    .arg("-c")
                    .arg(&file)
                    .arg(user)
                    .arg(password)
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .status()
                    .unwrap_or_else(|e| panic!("cannot run mosquitto_passwd: {e}"));
                assert!(status.success(), "mosquitto_passwd failed: {status}");
                format!("allow_anonymous false\npassword_file {}\n", file.display())
            }
        };
        std::fs::write(
            &config,
            format!(
                "listener {} 127.0.0.1\n{access}{}\n{}",
                self.port,
                if self.persistent {
                    format!(
                        "persistence true\npersistence_location {}/",
                        self.dir.path().display()
                    )
                } else {
                    "persistence false".to_string()
                },
                std::env::var("MOSQUITTO_LOG")
                    .map(|f| format!("log_type all\nlog_dest file {f}\n"))
                    .unwrap_or_default()
            ),
        )
        .expect("write mosquitto.conf");
        let mosquitto = mosquitto_program("mosquitto");
        let child = Command::new(&mosquitto)
            .stop_with_parent()
            .arg("-c")
            .arg(&config)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", mosquitto.display()));
        self.child = Some(child);
        let deadline = Instant::now() + TIMEOUT;
        loop {
            let exited = self
                .child
                .as_mut()
                .and_then(|child| child.try_wait().ok().flatten());
            if let Some(status) = exited {
                self.child = None;
                return Err(status);
            }
            // Listening, and it is ours: the process is still there.
            if TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                return Ok(());
            }
            assert!(
                Instant::now() < deadline,
                "mosquitto did not listen on {}",
                self.port
            );
            // A condition poll: each round asks again; the pause only paces it.
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Kills the broker (its retained messages are lost: no persistence).
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Stops the broker with SIGTERM and waits for it: a persistent broker saves its retained
    /// messages first.
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            )
            .expect("SIGTERM to mosquitto");
            let _ = child.wait();
        }
    }

    /// Starts a stopped broker again on the same port (a persistent one with what it saved).
    pub fn start_again(&mut self) {
        self.launch();
    }

    /// Starts it again on the same port.
    pub fn restart(&mut self) {
        self.kill();
        self.launch();
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        self.kill();
    }
}

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

/// Polls `check` until it returns Some, or panics after `TIMEOUT` naming `what`.
pub async fn wait_for<T, F, Fut>(what: &str, mut check: F) -> T
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Option<T>>,
{
    let deadline = Instant::now() + TIMEOUT;
    loop {
        if let Some(found) = check().await {
            return found;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// Waits until the broker's retained state is exactly `expected`; after `TIMEOUT`, panics
/// naming what the last state read had missing, different or extra.
pub async fn wait_for_retained(port: u16, expected: &BTreeMap<String, String>, what: &str) {
    let deadline = Instant::now() + TIMEOUT;
    loop {
        let state = retained(port).await;
        if state.as_ref() == Some(expected) {
            return;
        }
        if Instant::now() >= deadline {
            let Some(state) = state else {
                panic!("timed out waiting for {what}: the broker's retained state was unreadable");
            };
            let differences: Vec<String> = expected
                .iter()
                .filter(|(topic, value)| state.get(*topic) != Some(value))
                .map(|(topic, value)| {
                    format!("{topic}: want {value:?}, got {:?}", state.get(topic))
                })
                .chain(
                    state
                        .iter()
                        .filter(|(topic, _)| !expected.contains_key(*topic))
                        .map(|(topic, value)| format!("{topic}: not wanted, got {value:?}")),
                )
                .collect();
            panic!("timed out waiting for {what}: {differences:#?}");
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

static CLIENTS: AtomicU32 = AtomicU32::new(0);

fn test_client(port: u16) -> (AsyncClient, rumqttc::EventLoop) {
    let id = format!(
        "test-{}-{}",
        std::process::id(),
        CLIENTS.fetch_add(1, Ordering::Relaxed)
    );
    let mut options = MqttOptions::new(id, "127.0.0.1", port);
    options.set_max_packet_size(1 << 20, 1 << 20);
    AsyncClient::new(options, 64)
}

/// What the broker holds retained right now: a fresh client subscribes to `#` and reads the
/// retained messages up to a marker it publishes itself. None when the broker is unreachable.
pub async fn retained(port: u16) -> Option<BTreeMap<String, String>> {
    let (client, mut eventloop) = test_client(port);
    let marker = format!(
        "rtu2mqtt-test/marker/{}",
        CLIENTS.fetch_add(1, Ordering::Relaxed)
    );
    let read = async {
        let mut state = BTreeMap::new();
        loop {
            match eventloop.poll().await.ok()? {
                Event::Incoming(Packet::ConnAck(_)) => {
                    client.subscribe("#", QoS::AtLeastOnce).await.ok()?;
                }
                Event::Incoming(Packet::SubAck(_)) => {
                    client
                        .publish(marker.as_str(), QoS::AtLeastOnce, false, "x")
                        .await
                        .ok()?;
                }
                Event::Incoming(Packet::Publish(p)) if p.topic == marker => break,
                Event::Incoming(Packet::Publish(p)) if p.retain => {
                    state.insert(p.topic, String::from_utf8_lossy(&p.payload).into_owned());
                }
                _ => {}
            }
        }
        let _ = client.disconnect().await;
        Some(state)
    };
    tokio::time::timeout(Duration::from_secs(5), read)
        .await
        .ok()
        .flatten()
}

/// Publishes one message from a test client.
pub async fn publish(port: u16, topic: &str, payload: &str, retain: bool) {
    let (client, mut eventloop) = test_client(port);
    client
        .publish(topic, QoS::AtLeastOnce, retain, payload)
        .await
        .expect("queue publish");
    let done = async {
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::PubAck(_))) => break,
                Ok(_) => {}
                Err(e) => panic!("test publisher: {e}"),
            }
        }
        let _ = client.disconnect().await;
        let _ = eventloop.poll().await;
    };
    tokio::time::timeout(TIMEOUT, done)
        .await
        .expect("publish acknowledged");
}

/// A live subscriber that records every message of `filter` with its retain flag.
pub struct Recorder {
    pub messages: Arc<std::sync::Mutex<Vec<(String, String, bool)>>>,
    task: JoinHandle<()>,
}

impl Recorder {
    pub async fn start(port: u16, filter: &str) -> Self {
        let (client, mut eventloop) = test_client(port);
        let messages = Arc::new(std::sync::Mutex::new(Vec::new()));
        let sink = messages.clone();
        let filter = filter.to_string();
        let (subscribed_tx, subscribed) = oneshot::channel();
        let task = tokio::spawn(async move {
            let mut subscribed_tx = Some(subscribed_tx);
            loop {
                match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::ConnAck(_))) => {
                        let _ = client.subscribe(filter.as_str(), QoS::AtLeastOnce).await;
                    }
                    Ok(Event::Incoming(Packet::SubAck(_))) => {
                        if let Some(tx) = subscribed_tx.take() {
                            let _ = tx.send(());
                        }
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        sink.lock().unwrap().push((
                            p.topic,
                            String::from_utf8_lossy(&p.payload).into_owned(),
                            p.retain,
                        ));
                    }
                    Ok(_) => {}
                    Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
                }
            }
        });
        tokio::time::timeout(TIMEOUT, subscribed)
            .await
            .expect("recorder subscribed")
            .expect("recorder task alive");
        Self { messages, task }
    }

    pub fn count(&self, topic_part: &str) -> usize {
        self.messages
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, _, _)| t.contains(topic_part))
            .count()
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// The MQTT task under test, driven like the daemon drives it.
pub struct MqttUnderTest {
    pub updates: mpsc::Sender<DeviceUpdate>,
    pub writes: mpsc::Receiver<ControlWrite>,
    shutdown: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), MqttError>>>,
}

pub fn settings(port: u16) -> MqttSettings {
    MqttSettings {
        broker: MqttConfig {
            host: "127.0.0.1".into(),
            port,
            keepalive_s: 5,
            ..MqttConfig::default()
        },
        max_unchanged_interval: -1,
    }
}

impl MqttUnderTest {
    pub fn start(settings: MqttSettings) -> Self {
        Self::start_reporting(settings, None)
    }

    /// [`Self::start`] reporting the broker's state into `health`, as the daemon runs it.
    pub fn start_reporting(settings: MqttSettings, health: Option<Arc<ServiceHealth>>) -> Self {
        Self::start_with(settings, health, Vec::new())
    }

    /// [`Self::start_reporting`] with `first` in the update queue before the task starts, as
    /// the daemon starts it (every device's `Added` is there before the first connect).
    pub fn start_with(
        settings: MqttSettings,
        health: Option<Arc<ServiceHealth>>,
        first: Vec<DeviceUpdate>,
    ) -> Self {
        let (updates, updates_rx) = mpsc::channel(64.max(first.len()));
        for update in first {
            updates
                .try_send(update)
                .expect("room for the first updates");
        }
        let (writes_tx, writes) = mpsc::channel(16);
        let (shutdown, shutdown_rx) = oneshot::channel::<()>();
        let stopped = async move {
            let _ = shutdown_rx.await;
        };
        let task = tokio::spawn(run_mqtt_reporting(
            settings, updates_rx, writes_tx, stopped, health,
        ));
        Self {
            updates,
            writes,
            shutdown: Some(shutdown),
            task: Some(task),
        }
    }

    pub async fn send(&self, update: DeviceUpdate) {
        tokio::time::timeout(TIMEOUT, self.updates.send(update))
            .await
            .expect("the MQTT task takes updates")
            .expect("the MQTT task is running");
    }

    pub fn is_running(&self) -> bool {
        self.task.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Clean shutdown (what SIGTERM does in the daemon); waits for the task.
    pub async fn stop(mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(task) = self.task.take() {
            tokio::time::timeout(TIMEOUT, task)
                .await
                .expect("the MQTT task stops in time")
                .expect("the MQTT task did not panic")
                .expect("the MQTT task ends cleanly");
        }
    }
}

impl Drop for MqttUnderTest {
    fn drop(&mut self) {
        if let Some(task) = self.task.take() {
            task.abort();
        }
    }
}

pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// Plays the bus side for one write: the device model checks and encodes it (as the port task
/// does); a refused payload sets `w`, an accepted one is "written" and clears it. Returns
/// whether it was accepted.
pub async fn bus_side_takes(
    mqtt: &MqttUnderTest,
    model: &mut rtu2mqtt::gateway::device_model::DeviceModel,
    write: &ControlWrite,
) -> bool {
    let mut out = Vec::new();
    let accepted = match model.take_write(&write.control_id, &write.payload, &mut out) {
        Ok(register_writes) => {
            for register_write in register_writes {
                model.apply(
                    rtu2mqtt::port::PortEvent::WriteDone {
                        device: register_write.device,
                        register_type: register_write.register_type,
                        address: register_write.address,
                    },
                    &mut out,
                );
            }
            true
        }
        Err(_) => false,
    };
    for update in out {
        mqtt.send(update).await;
    }
    accepted
}

pub fn template_device(template: &str, slave_id: u8) -> Arc<ResolvedDevice> {
    let file = TemplateFile::load(&repo(&format!("templates/{template}.json")))
        .unwrap_or_else(|e| panic!("{e}"));
    Arc::new(
        resolve_template_device(&file, &json!({ "slave_id": slave_id }))
            .unwrap_or_else(|e| panic!("{e}")),
    )
}

pub fn value(device: &str, control: &str, text: &str) -> DeviceUpdate {
    DeviceUpdate::Value {
        device_id: device.into(),
        control_id: control.into(),
        value: text.into(),
        from_event: false,
        changed: true,
    }
}

/// `topic<TAB>payload` per line, sorted: the golden form of the broker's retained state.
pub fn render_state(state: &BTreeMap<String, String>) -> String {
    state.iter().map(|(t, p)| format!("{t}\t{p}\n")).collect()
}

/// Waits until the broker's retained state renders exactly as `tests/golden/<name>`; on timeout
/// fails with the first differing line. Waiting for the whole state (not one topic) matters: a
/// value published while a snapshot is being read reaches it live, without the retain flag, and
/// shows only in the next snapshot.
pub async fn assert_broker_matches_golden(port: u16, name: &str) {
    // What to wait for: the snapshot's body (after its `---` header).
    let path = repo(&format!("tests/golden/{name}.snap"));
    let snapshot = std::fs::read_to_string(&path).unwrap_or_default();
    let expected = snapshot
        .splitn(3, "---\n")
        .nth(2)
        .unwrap_or_default()
        .to_string();
    let deadline = Instant::now() + TIMEOUT;
    loop {
        let actual = retained(port).await.map(|s| render_state(&s));
        if let Some(actual) = actual {
            if actual == expected || Instant::now() >= deadline {
                assert_golden(name, &actual);
                return;
            }
        }
        assert!(
            Instant::now() < deadline,
            "timed out reading the broker's retained state"
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// Compares with the snapshot `tests/golden/<name>.snap`. A change is reviewed, never written
/// by the test: `cargo insta review` (or `INSTA_UPDATE=new`, then compare the `.snap.new` file).
pub fn assert_golden(name: &str, actual: &str) {
    insta::with_settings!({
        snapshot_path => repo("tests/golden"),
        prepend_module_to_snapshot => false,
        omit_expression => true,
    }, {
        insta::assert_snapshot!(name, actual);
    });
}

static RPC_CALLS: AtomicU32 = AtomicU32::new(0);

/// Publishes `payload` on `/rpc/v1/wb-mqtt-serial/<service>/<method>/<client>` and returns the
/// reply payload, as a Wiren Board RPC client does.
pub async fn rpc_raw(port: u16, service: &str, method: &str, payload: &str) -> String {
    let client_id = format!(
        "rpc-test-{}-{}",
        std::process::id(),
        RPC_CALLS.fetch_add(1, Ordering::Relaxed)
    );
    let request_topic = format!("/rpc/v1/wb-mqtt-serial/{service}/{method}/{client_id}");
    let reply_topic = format!("{request_topic}/reply");
    let (client, mut eventloop) =
        AsyncClient::new(MqttOptions::new(&client_id, "127.0.0.1", port), 16);
    let exchange = async {
        loop {
            match eventloop.poll().await.expect("test RPC client connection") {
                Event::Incoming(Packet::ConnAck(_)) => {
                    client
                        .subscribe(reply_topic.as_str(), QoS::AtLeastOnce)
                        .await
                        .unwrap();
                }
                Event::Incoming(Packet::SubAck(_)) => {
                    client
                        .publish(request_topic.as_str(), QoS::AtLeastOnce, false, payload)
                        .await
                        .unwrap();
                }
                Event::Incoming(Packet::Publish(reply)) if reply.topic == reply_topic => {
                    return String::from_utf8(reply.payload.to_vec()).unwrap();
                }
                _ => {}
            }
        }
    };
    let reply = tokio::time::timeout(TIMEOUT, exchange)
        .await
        .unwrap_or_else(|_| panic!("no reply to {service}/{method} {payload}"));
    let _ = client.disconnect().await;
    reply
}

pub async fn rpc(port: u16, service: &str, method: &str, params: Value) -> Value {
    let payload = json!({"id": 1, "params": params}).to_string();
    let reply = rpc_raw(port, service, method, &payload).await;
    serde_json::from_str(&reply).unwrap_or_else(|e| panic!("reply {reply:?}: {e}"))
}
