//! What a client of the status page may hold (src/status/limits.rs): a request head that never
//! ends is dropped, and connections without a password cannot take the daemon's file
//! descriptors (its serial port then could not be opened). Both failed before the limits. And
//! wrong passwords sent together are answered at once, not queued for bcrypt (src/status/auth.rs).

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use daemon_support::{repo, DaemonProcess};
use mqtt_support::free_port;
use serde_json::{json, Value};
use sim_support::SimProcess;

/// bcrypt of "s3cret" at cost 4 (made with bcrypt::hash; valid for the config check).
fn hash() -> String {
    bcrypt::hash("s3cret", 4).unwrap()
}

fn config(port_path: &Path, http: Value) -> Value {
    json!({
        "http": http,
        "ports": [{"path": port_path, "baud_rate": 9600, "stop_bits": 2,
                   "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]
    })
}

fn wait_for_listen(port: u16) {
    let started = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "page never listened"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A daemon whose status page asks for `admin` / `s3cret`, on a port that does not exist;
/// returns it, once its page listens, with the page's port (and the directory to keep).
fn daemon_with_password() -> (DaemonProcess, u16, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let http_port = free_port();
    let http = json!({"listen": format!("127.0.0.1:{http_port}"), "user": "admin",
                      "password_hash": hash()});
    let daemon = DaemonProcess::start(
        &config(&dir.path().join("none"), http),
        &["--stdio"],
        Stdio::null(),
        Stdio::null(),
    );
    wait_for_listen(http_port);
    (daemon, http_port, dir)
}

fn basic(user: &str, password: &str) -> String {
    use base64::Engine as _;
    format!(
        "Basic {}",
        base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"))
    )
}

/// One GET with a 5 s read timeout: the status code, or None.
fn get(port: u16, path: &str, auth: Option<&str>) -> Option<u16> {
    answer(send_get(port, path, auth)?).map(|(code, _)| code)
}

/// Sends a GET without waiting for the answer.
fn send_get(port: u16, path: &str, auth: Option<&str>) -> Option<TcpStream> {
    let address = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let mut stream = TcpStream::connect_timeout(&address, Duration::from_secs(5)).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    let mut request =
        format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n");
    if let Some(auth) = auth {
        request.push_str(&format!("Authorization: {auth}\r\n"));
    }
    request.push_str("\r\n");
    stream.write_all(request.as_bytes()).ok()?;
    Some(stream)
}

/// The status code and the whole answer of a request sent with [`send_get`].
fn answer(mut stream: TcpStream) -> Option<(u16, String)> {
    let mut response = Vec::new();
    stream.read_to_end(&mut response).ok()?;
    let text = String::from_utf8_lossy(&response).into_owned();
    let code = text.split(' ').nth(1)?.parse().ok()?;
    Some((code, text))
}

/// Slowloris: a client that sends part of its request head and then nothing holds its connection
/// (a task and a file descriptor of the daemon) for ever. axum::serve sets no hyper timer, so
/// hyper's default 30 s header-read timeout never applies. No password needed: the guard runs
/// only once the head is complete.
#[test]
fn a_request_head_that_never_ends_is_dropped() {
    let (daemon, http_port, _dir) = daemon_with_password();
    let mut stream = TcpStream::connect(("127.0.0.1", http_port)).unwrap();
    stream
        .write_all(format!("GET / HTTP/1.1\r\nHost: 127.0.0.1:{http_port}\r\nX-Slow: a").as_bytes())
        .unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(40)))
        .unwrap();
    let started = Instant::now();
    let mut buffer = [0u8; 256];
    let outcome = stream.read(&mut buffer);
    let waited = started.elapsed();
    assert!(
        waited < Duration::from_secs(39),
        "the daemon still held a half-sent request head after {waited:?} ({outcome:?})\n{}",
        daemon.log()
    );
}

/// File-descriptor exhaustion without the password: idle TCP connections are never limited nor
/// closed, so someone on the LAN who does not know the password opens enough of them and the
/// daemon has no descriptor left: it cannot open (or reopen) its serial port, so the bus stops.
/// Here the port appears after the flood (as a USB adapter that was replugged, or a port that
/// failed and is reopened); it never opens.
#[test]
fn idle_connections_without_a_password_cannot_stop_the_bus() {
    let dir = tempfile::tempdir().unwrap();
    let http_port = free_port();
    let http = json!({"listen": format!("127.0.0.1:{http_port}"), "user": "admin",
                      "password_hash": hash()});
    let tty = dir.path().join("tty");
    let daemon = DaemonProcess::start_with_file_limit(&config(&tty, http), &["--stdio"], 128);
    wait_for_listen(http_port);
    // Well over the limit: nothing sent on them, no password.
    let flood: Vec<TcpStream> = (0..160)
        .filter_map(|_| {
            let address = std::net::SocketAddr::from(([127, 0, 0, 1], http_port));
            TcpStream::connect_timeout(&address, Duration::from_secs(2)).ok()
        })
        .collect();
    let open = flood.len();
    // The port appears (the simulator's pty under the configured path).
    let bus = dir.path().join("bus.json");
    std::fs::write(
        &bus,
        r#"{"devices": [{"name": "relay", "template": "rtu2mqtt-relay6", "address": 20,
             "serial": "0xFE000020", "line": "9600 8N2"}]}"#,
    )
    .unwrap();
    let sim = SimProcess::start_with(&bus, &repo("templates"), &[]);
    std::os::unix::fs::symlink(&sim.pty, &tty).unwrap();
    let started = Instant::now();
    while !daemon.log().contains("port open") && started.elapsed() < Duration::from_secs(25) {
        std::thread::sleep(Duration::from_millis(200));
    }
    let opened = daemon.log().contains("port open");
    let page = get(http_port, "/api/status", Some(&basic("admin", "s3cret")));
    drop(flood);
    assert!(
        opened,
        "with {open} idle connections open (no password), the port never opened; the page \
         answered {page:?}\n--- daemon log (tail) ---\n{}",
        daemon.log_tail(8)
    );
}

/// Wrong passwords queued: each costs a bcrypt check (slow on purpose, on a blocking thread) and
/// one that arrived while another ran waited its turn, so a burst of guesses kept the CPU from
/// the buses and a real login waited behind all of them. Now one check runs at a time and the
/// others are answered at once with 429 and `Retry-After`; a browser that logged in before is
/// not held up. The test hash's cost 4 is named in the log, once.
#[test]
fn wrong_passwords_sent_together_are_answered_at_once_not_queued() {
    let (daemon, http_port, _dir) = daemon_with_password();
    let good = basic("admin", "s3cret");
    assert_eq!(get(http_port, "/api/status", Some(&good)), Some(200));
    // All sent before any answer is read.
    let guesses: Vec<TcpStream> = (0..20)
        .filter_map(|i| {
            send_get(
                http_port,
                "/metrics",
                Some(&basic("admin", &format!("guess{i}"))),
            )
        })
        .collect();
    assert_eq!(guesses.len(), 20);
    // The browser that logged in before, during the burst.
    assert_eq!(get(http_port, "/api/status", Some(&good)), Some(200));
    let answers: Vec<(u16, String)> = guesses.into_iter().filter_map(answer).collect();
    let codes: Vec<u16> = answers.iter().map(|(code, _)| *code).collect();
    assert_eq!(answers.len(), 20, "answers: {codes:?}");
    assert!(
        codes.iter().all(|code| [401, 429].contains(code)),
        "answers: {codes:?}"
    );
    let busy: Vec<&String> = answers
        .iter()
        .filter(|(code, _)| *code == 429)
        .map(|(_, text)| text)
        .collect();
    assert!(
        !busy.is_empty(),
        "20 wrong passwords sent together were all checked in turn (answers {codes:?})"
    );
    for text in busy {
        let retry_after = text
            .lines()
            .find_map(|line| {
                line.to_ascii_lowercase()
                    .strip_prefix("retry-after: ")
                    .map(str::to_string)
            })
            .and_then(|value| value.trim().parse::<u64>().ok());
        assert!(retry_after.is_some_and(|s| s >= 1), "{text}");
    }
    assert_eq!(
        daemon.log().matches("cheap to guess").count(),
        1,
        "{}",
        daemon.log_tail(8)
    );
}
