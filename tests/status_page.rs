//! The status page and `/metrics` with real processes: `rtu2mqtt sim` on a pty, `rtu2mqtt run`
//! with the `http` section, mosquitto, and headless Chromium (Debian's `chromium`, installed by
//! scripts/test) loading the page as a browser would.

#[path = "daemon_support/mod.rs"]
mod daemon_support;
#[path = "mqtt_support/mod.rs"]
mod mqtt_support;
#[path = "sim_support/mod.rs"]
mod sim_support;

use rtu2mqtt::child::StopWithParent;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use daemon_support::{repo, DaemonProcess};
use mqtt_support::{free_port, Mosquitto};
use serde_json::{json, Value};
use sim_support::SimProcess;

/// Everything a test waits for comes within this, or the test fails naming it.
const DEADLINE: Duration = Duration::from_secs(60);

fn bus(line: &str) -> String {
    format!(
        r#"{{"devices": [
  {{"name": "relay", "template": "rtu2mqtt-relay6", "address": 20, "serial": "0xFE000020", "line": "{line}"}},
  {{"name": "climate", "template": "rtu2mqtt-climate", "address": 21, "serial": "0xFE000021", "line": "{line}",
   "values": {{"input:4": 2150}}}}
]}}"#
    )
}

struct Setup {
    _broker: Option<Mosquitto>,
    sim: SimProcess,
    daemon: DaemonProcess,
    http_port: u16,
    _dir: tempfile::TempDir,
}

/// Simulator at `baud` 8N2, the daemon with the status page on a free loopback port, and, with
/// `broker`, mosquitto (else `--stdio`).
fn start(baud: u32, broker: bool, http: Value) -> Setup {
    let broker = broker.then(Mosquitto::start);
    let dir = tempfile::tempdir().unwrap();
    let bus_file = dir.path().join("bus.json");
    std::fs::write(&bus_file, bus(&format!("{baud} 8N2"))).unwrap();
    let sim = SimProcess::start_with(&bus_file, &repo("templates"), &[]);
    let http_port = free_port();
    let mut http = http;
    http["listen"] = json!(format!("127.0.0.1:{http_port}"));
    let devices = json!([
        {"device_type": "rtu2mqtt-relay6", "slave_id": 20},
        {"device_type": "rtu2mqtt-climate", "slave_id": 21}
    ]);
    let mut config = json!({
        "http": http,
        "ports": [{"path": sim.pty, "baud_rate": baud, "stop_bits": 2, "devices": devices}]
    });
    let daemon = match &broker {
        Some(broker) => {
            config["mqtt"] =
                json!({"host": "127.0.0.1", "port": broker.port, "client_id": "rtu2mqtt-status"});
            DaemonProcess::start(&config, &[], Stdio::null(), Stdio::null())
        }
        None => DaemonProcess::start(&config, &["--stdio"], Stdio::piped(), Stdio::null()),
    };
    Setup {
        _broker: broker,
        sim,
        daemon,
        http_port,
        _dir: dir,
    }
}

/// One HTTP/1.1 request on a fresh connection: (status code, headers, body).
fn http(
    port: u16,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> Option<(u16, String, String)> {
    let mut stream = TcpStream::connect(("127.0.0.1", port)).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .ok()?;
    let mut request = format!(
        "{method} {path} HTTP/1.1\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    if !headers
        .iter()
        .any(|(name, _)| name.eq_ignore_ascii_case("host"))
    {
        request.push_str(&format!("Host: 127.0.0.1:{port}\r\n"));
    }
    for (name, value) in headers {
        request.push_str(&format!("{name}: {value}\r\n"));
    }
    request.push_str("\r\n");
    request.push_str(body);
    stream.write_all(request.as_bytes()).ok()?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).ok()?;
    let text = String::from_utf8_lossy(&response).into_owned();
    let (head, body) = text.split_once("\r\n\r\n")?;
    let status = head.split(' ').nth(1)?.parse().ok()?;
    Some((status, head.to_string(), body.to_string()))
}

fn get(port: u16, path: &str) -> Option<(u16, String)> {
    http(port, "GET", path, &[], "").map(|(status, _, body)| (status, body))
}

/// Polls `check` until it gives Some; fails naming `what` (and showing the daemon's log) after
/// [`DEADLINE`].
fn wait_for<T>(what: &str, daemon: &DaemonProcess, mut check: impl FnMut() -> Option<T>) -> T {
    let started = Instant::now();
    loop {
        if let Some(found) = check() {
            return found;
        }
        assert!(
            started.elapsed() < DEADLINE,
            "gave up waiting for {what}\n--- daemon log ---\n{}",
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn status(port: u16) -> Option<Value> {
    let (code, body) = get(port, "/api/status")?;
    (code == 200).then(|| serde_json::from_str(&body).ok())?
}

fn control_value(status: &Value, device: &str, control: &str) -> Option<String> {
    status["ports"]
        .as_array()?
        .iter()
        .flat_map(|port| port["devices"].as_array().into_iter().flatten())
        .find(|d| d["id"] == device)?["controls"]
        .as_array()?
        .iter()
        .find(|c| c["id"] == control)?["value"]
        .as_str()
        .map(str::to_string)
}

fn chromium() -> PathBuf {
    let found = ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .iter()
        .map(PathBuf::from)
        .find(|path| path.exists());
    found.expect(
        "the status page test needs headless Chromium at /usr/bin/chromium \
         (apt-get install chromium; scripts/test installs it)",
    )
}

/// Headless Chromium driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`:
/// JSON messages ended by NUL on fds 3 and 4), so the test asks the live page what it shows
/// instead of guessing when it is ready.
struct Browser {
    child: std::process::Child,
    to_browser: std::fs::File,
    from_browser: std::sync::mpsc::Receiver<Value>,
    next_id: u64,
    _profile: tempfile::TempDir,
}

impl Browser {
    fn launch() -> Self {
        use nix::fcntl::{fcntl, FcntlArg, OFlag};
        use nix::unistd::{dup2_raw, pipe2};
        use std::os::fd::{AsRawFd, BorrowedFd};
        use std::os::unix::process::CommandExt;

        let profile = tempfile::tempdir().unwrap();
        // Close-on-exec, so that no other test's child inherits them and holds them open.
        let (browser_reads, test_writes) = pipe2(OFlag::O_CLOEXEC).unwrap();
        let (test_reads, browser_writes) = pipe2(OFlag::O_CLOEXEC).unwrap();
        let (input, output) = (browser_reads.as_raw_fd(), browser_writes.as_raw_fd());
        let mut command = Command::new(chromium());
        command.stop_with_parent();
        command
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--disable-extensions",
                "--hide-scrollbars",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        // SAFETY: between fork and exec only fcntl and dup2 run (async-signal-safe); the new
        // descriptors 3 and 4 are the child's own, forgotten so that nothing closes them.
        unsafe {
            command.pre_exec(move || {
                let to_io = |err: nix::errno::Errno| std::io::Error::from_raw_os_error(err as i32);
                // First above 10, so that moving one onto 3 or 4 cannot clobber the other.
                let input =
                    fcntl(BorrowedFd::borrow_raw(input), FcntlArg::F_DUPFD(10)).map_err(to_io)?;
                let output =
                    fcntl(BorrowedFd::borrow_raw(output), FcntlArg::F_DUPFD(10)).map_err(to_io)?;
                std::mem::forget(dup2_raw(BorrowedFd::borrow_raw(input), 3).map_err(to_io)?);
                std::mem::forget(dup2_raw(BorrowedFd::borrow_raw(output), 4).map_err(to_io)?);
                Ok(())
            });
        }
        let child = command.spawn().expect("chromium starts");
        drop((browser_reads, browser_writes));
        let (sender, from_browser) = std::sync::mpsc::channel();
        let mut reader = std::io::BufReader::new(std::fs::File::from(test_reads));
        std::thread::spawn(move || {
            use std::io::BufRead;
            let mut message = Vec::new();
            while reader.read_until(0, &mut message).is_ok_and(|n| n > 0) {
                if message.last() == Some(&0) {
                    message.pop();
                }
                if let Ok(value) = serde_json::from_slice(&message) {
                    if sender.send(value).is_err() {
                        break;
                    }
                }
                message.clear();
            }
        });
        Self {
            child,
            to_browser: std::fs::File::from(test_writes),
            from_browser,
            next_id: 1,
            _profile: profile,
        }
    }

    /// Sends a command (to a page when `session` is given) and returns its result.
    fn call(&mut self, session: Option<&str>, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        let mut message = json!({"id": id, "method": method, "params": params});
        if let Some(session) = session {
            message["sessionId"] = json!(session);
        }
        let mut bytes = message.to_string().into_bytes();
        bytes.push(0);
        self.to_browser
            .write_all(&bytes)
            .expect("chromium takes commands");
        let deadline = Instant::now() + DEADLINE;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let reply = self
                .from_browser
                .recv_timeout(left)
                .unwrap_or_else(|_| panic!("chromium did not answer {method}"));
            if reply["id"] == id {
                assert!(reply.get("error").is_none(), "{method}: {reply}");
                return reply["result"].clone();
            }
        }
    }

    /// Evaluates `expression` in the page; its value.
    fn evaluate(&mut self, session: &str, expression: &str) -> Value {
        let result = self.call(
            Some(session),
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true}),
        );
        result["result"]["value"].clone()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Headless Chromium loads the page; its script receives the server-sent snapshots and fills
/// in the values. The test asks the page what it shows until the temperature is there, then
/// changes the temperature in the simulator and sees the open page follow, without a reload.
#[test]
fn the_page_shows_devices_and_live_values_in_headless_chromium() {
    chromium(); // fail at once, and loudly, when Chromium is missing
    let setup = start(115_200, true, json!({}));
    let port = setup.http_port;
    // The server and the bus are up: the API has the temperature the simulator holds.
    let value = wait_for("the temperature in /api/status", &setup.daemon, || {
        control_value(&status(port)?, "climate_21", "Temperature")
    });
    assert_eq!(value, "21.5");

    let mut browser = Browser::launch();
    let url = format!("http://127.0.0.1:{port}/");
    let target = browser.call(None, "Target.createTarget", json!({"url": url}));
    let session = browser.call(
        None,
        "Target.attachToTarget",
        json!({"targetId": target["targetId"], "flatten": true}),
    )["sessionId"]
        .as_str()
        .unwrap()
        .to_string();
    browser.call(
        Some(&session),
        "Emulation.setDeviceMetricsOverride",
        json!({"width": 1280, "height": 1000, "deviceScaleFactor": 1, "mobile": false}),
    );
    let shown = |browser: &mut Browser| {
        browser
            .evaluate(
                &session,
                r#"document.querySelector('[data-control="climate_21/Temperature"]')?.textContent ?? """#,
            )
            .as_str()
            .unwrap_or_default()
            .to_string()
    };
    wait_for("the temperature in the page", &setup.daemon, || {
        shown(&mut browser).starts_with("21.5").then_some(())
    });
    let dom = browser
        .evaluate(&session, "document.documentElement.outerHTML")
        .as_str()
        .unwrap()
        .to_string();
    for device in ["relay6_20", "climate_21"] {
        assert!(
            dom.contains(&format!(r#"data-device="{device}""#)),
            "{device} missing from the page:\n{dom}"
        );
    }
    assert!(
        dom.contains(">online<"),
        "no device online in the page:\n{dom}"
    );

    // Live: the open page follows a change on the bus.
    setup
        .sim
        .control(json!({"cmd": "set", "device": 21, "type": "input", "address": 4, "value": 2333}));
    wait_for(
        "the new temperature in the open page",
        &setup.daemon,
        || shown(&mut browser).starts_with("23.3").then_some(()),
    );

    // A screenshot, as the README shows it (kept when STATUS_PAGE_SCREENSHOT names a file).
    let shot = browser.call(
        Some(&session),
        "Page.captureScreenshot",
        json!({"format": "png"}),
    );
    use base64::Engine as _;
    let png = base64::engine::general_purpose::STANDARD
        .decode(shot["data"].as_str().unwrap())
        .unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "the screenshot is a PNG");
    if let Some(keep) = std::env::var_os("STATUS_PAGE_SCREENSHOT") {
        std::fs::write(keep, &png).unwrap();
    }
    drop(browser);

    // The page's write button posts this: it takes the MQTT `/on` path to the device.
    let (code, _, body) = http(
        port,
        "POST",
        "/api/write",
        &[("content-type", "application/json"), ("x-rtu2mqtt", "1")],
        r#"{"device": "relay6_20", "control": "K2", "value": "1"}"#,
    )
    .unwrap();
    assert_eq!(code, 202, "{body}");
    wait_for("K2 on in the simulator", &setup.daemon, || {
        let reply = setup
            .sim
            .control(json!({"cmd": "get", "device": 20, "type": "coil", "address": 1}));
        (reply["value"] == 1).then_some(())
    });
    wait_for("K2 = 1 on the page", &setup.daemon, || {
        (control_value(&status(port)?, "relay6_20", "K2")? == "1").then_some(())
    });
    // Without the header a form of another web site could send, the write is refused.
    let (code, _, _) = http(
        port,
        "POST",
        "/api/write",
        &[],
        r#"{"device": "relay6_20", "control": "K2", "value": "0"}"#,
    )
    .unwrap();
    assert_eq!(code, 403);
    // A device or control the gateway does not have is named as such.
    for (request, answer) in [
        (
            r#"{"device": "nope", "control": "K2", "value": "1"}"#,
            "no device `nope` on this gateway",
        ),
        (
            r#"{"device": "relay6_20", "control": "K9", "value": "1"}"#,
            "no control `K9` on device `relay6_20`",
        ),
    ] {
        let (code, _, body) = http(
            port,
            "POST",
            "/api/write",
            &[("content-type", "application/json"), ("x-rtu2mqtt", "1")],
            request,
        )
        .unwrap();
        assert_eq!((code, body.trim()), (404, answer));
    }
    // The frames log decodes what went to and came from the relay.
    let (code, body) = get(port, "/api/frames?device=relay6_20").unwrap();
    assert_eq!(code, 200);
    let frames: Value = serde_json::from_str(&body).unwrap();
    let frames = frames["frames"].as_array().unwrap();
    assert!(!frames.is_empty());
    assert!(
        frames
            .iter()
            .any(|f| f["request"].as_str().is_some_and(|r| r.contains("20"))),
        "{frames:?}"
    );
}

/// One sample of the Prometheus text format.
#[derive(Debug, Clone, PartialEq)]
struct Sample {
    name: String,
    labels: BTreeMap<String, String>,
    value: f64,
}

/// Parses the text exposition format strictly enough to catch what Prometheus would reject:
/// metric and label names, quoting and escapes, numeric values, a TYPE before a family's samples,
/// histogram buckets cumulative and ending in +Inf equal to _count.
fn parse_metrics(text: &str) -> Result<Vec<Sample>, String> {
    let valid_name = |name: &str| {
        !name.is_empty()
            && name.chars().enumerate().all(|(i, c)| {
                c.is_ascii_alphabetic() || c == '_' || c == ':' || (i > 0 && c.is_ascii_digit())
            })
    };
    let mut types: BTreeMap<String, String> = BTreeMap::new();
    let mut samples = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let at = |problem: &str| format!("line {}: {problem}: {line}", number + 1);
        if line.is_empty() {
            continue;
        }
        if let Some(rest) = line.strip_prefix("# TYPE ") {
            let (name, kind) = rest
                .split_once(' ')
                .ok_or_else(|| at("TYPE without a type"))?;
            if !["counter", "gauge", "histogram", "summary", "untyped"].contains(&kind) {
                return Err(at("unknown type"));
            }
            if types.insert(name.to_string(), kind.to_string()).is_some() {
                return Err(at("TYPE given twice"));
            }
            continue;
        }
        if line.starts_with('#') {
            continue;
        }
        let name_end = line.find(['{', ' ']).ok_or_else(|| at("no value"))?;
        let name = &line[..name_end];
        if !valid_name(name) {
            return Err(at("bad metric name"));
        }
        let mut labels = BTreeMap::new();
        let mut rest = &line[name_end..];
        if let Some(inner) = rest.strip_prefix('{') {
            let mut chars = inner.char_indices().peekable();
            let consumed = loop {
                let key_start = chars
                    .peek()
                    .map(|(i, _)| *i)
                    .ok_or_else(|| at("open labels"))?;
                if inner[key_start..].starts_with('}') {
                    break key_start + 1;
                }
                let eq = inner[key_start..]
                    .find("=\"")
                    .ok_or_else(|| at("label without =\""))?;
                let key = &inner[key_start..key_start + eq];
                if !valid_name(key) || key.contains(':') {
                    return Err(at("bad label name"));
                }
                while chars.peek().is_some_and(|(i, _)| *i < key_start + eq + 2) {
                    chars.next();
                }
                let mut value = String::new();
                loop {
                    match chars.next().ok_or_else(|| at("unterminated label value"))? {
                        (_, '\\') => match chars.next().ok_or_else(|| at("dangling escape"))?.1 {
                            'n' => value.push('\n'),
                            '\\' => value.push('\\'),
                            '"' => value.push('"'),
                            _ => return Err(at("bad escape")),
                        },
                        (_, '"') => break,
                        (_, c) => value.push(c),
                    }
                }
                labels.insert(key.to_string(), value);
                match chars.next().ok_or_else(|| at("open labels"))? {
                    (_, ',') => {}
                    (i, '}') => break i + 1,
                    _ => return Err(at("labels not separated by commas")),
                }
            };
            rest = &inner[consumed..];
        }
        let value_text = rest
            .strip_prefix(' ')
            .ok_or_else(|| at("no space before the value"))?;
        let value: f64 = match value_text {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            "NaN" => f64::NAN,
            other => other.parse().map_err(|_| at("value is not a number"))?,
        };
        let family = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|suffix| {
                name.strip_suffix(suffix)
                    .filter(|base| types.get(*base).is_some_and(|t| t == "histogram"))
            })
            .unwrap_or(name);
        if !types.contains_key(family) {
            return Err(at("sample before its TYPE line"));
        }
        samples.push(Sample {
            name: name.to_string(),
            labels,
            value,
        });
    }
    // Histograms: per label set, buckets cumulative, the last one +Inf and equal to _count.
    for (family, _) in types.iter().filter(|(_, kind)| *kind == "histogram") {
        let bucket_name = format!("{family}_bucket");
        let count_name = format!("{family}_count");
        for count in samples.iter().filter(|s| s.name == count_name) {
            let buckets: Vec<&Sample> = samples
                .iter()
                .filter(|s| {
                    s.name == bucket_name
                        && s.labels
                            .iter()
                            .filter(|(k, _)| *k != "le")
                            .eq(count.labels.iter())
                })
                .collect();
            let last = buckets.last().ok_or(format!("{family}: no buckets"))?;
            if last.labels.get("le").map(String::as_str) != Some("+Inf")
                || last.value != count.value
            {
                return Err(format!("{family}: the +Inf bucket must equal _count"));
            }
            if buckets.windows(2).any(|pair| pair[0].value > pair[1].value) {
                return Err(format!("{family}: buckets are not cumulative"));
            }
        }
    }
    Ok(samples)
}

fn metric(samples: &[Sample], name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    samples
        .iter()
        .find(|s| {
            s.name == name
                && labels
                    .iter()
                    .all(|(k, v)| s.labels.get(*k).map(String::as_str) == Some(*v))
        })
        .map(|s| s.value)
}

fn metrics(port: u16) -> Option<Vec<Sample>> {
    let (code, body) = get(port, "/metrics")?;
    assert_eq!(code, 200);
    Some(parse_metrics(&body).unwrap_or_else(|err| panic!("{err}\n{body}")))
}

#[test]
fn the_metrics_parser_rejects_what_prometheus_would() {
    let good = "# TYPE a_total counter\na_total{port=\"x \\\"y\\\"\",kind=\"t\"} 3\n";
    let samples = parse_metrics(good).unwrap();
    assert_eq!(samples[0].labels["port"], "x \"y\"");
    for bad in [
        "a_total 3\n",                                   // no TYPE
        "# TYPE a_total counter\na_total{port=\"x} 3\n", // unterminated
        "# TYPE a_total counter\na_total{port=x} 3\n",   // unquoted
        "# TYPE a_total counter\na_total three\n",       // not a number
        "# TYPE 1a counter\n1a 1\n",                     // bad name
        "# TYPE h histogram\nh_bucket{le=\"1\"} 2\nh_bucket{le=\"+Inf\"} 1\nh_count 1\n", // not cumulative
    ] {
        assert!(parse_metrics(bad).is_err(), "accepted: {bad}");
    }
}

/// Bad CRCs, then silence, from the climate sensor: the port's and the device's counters of
/// that kind move, the others stay.
fn errors_count_by_kind(baud: u32) {
    let setup = start(baud, false, json!({}));
    let port = setup.http_port;
    let labels = |kind: &'static str| [("device", "climate_21"), ("kind", kind)];
    let before = wait_for(
        "the climate sensor online in /metrics",
        &setup.daemon,
        || {
            let samples = metrics(port)?;
            (metric(
                &samples,
                "rtu2mqtt_device_online",
                &[("device", "climate_21")],
            )? == 1.0)
                .then_some(samples)
        },
    );
    assert!(metric(&before, "rtu2mqtt_transactions_total", &[]).unwrap() > 0.0);
    let port_name = before
        .iter()
        .find(|s| s.name == "rtu2mqtt_transactions_total")
        .map(|s| s.labels["port"].clone())
        .unwrap();
    assert!(port_name.contains(&baud.to_string()), "{port_name}");

    setup
        .sim
        .control(json!({"cmd": "faults", "device": 21, "corrupt_crc": 1.0}));
    let after_crc = wait_for("bad CRC counted", &setup.daemon, || {
        let samples = metrics(port)?;
        (metric(&samples, "rtu2mqtt_device_errors_total", &labels("bad_crc"))?
            > metric(&before, "rtu2mqtt_device_errors_total", &labels("bad_crc"))?
            && metric(&samples, "rtu2mqtt_errors_total", &[("kind", "bad_crc")])? > 0.0)
            .then_some(samples)
    });
    setup
        .sim
        .control(json!({"cmd": "faults", "device": 21, "drop": 1.0}));
    wait_for("timeouts counted", &setup.daemon, || {
        let samples = metrics(port)?;
        (metric(&samples, "rtu2mqtt_device_errors_total", &labels("timeout"))?
            > metric(
                &after_crc,
                "rtu2mqtt_device_errors_total",
                &labels("timeout"),
            )?)
        .then_some(())
    });
    // The relay had neither fault: none of its replies was garbled.
    let samples = metrics(port).unwrap();
    assert_eq!(
        metric(
            &samples,
            "rtu2mqtt_device_errors_total",
            &[("device", "relay6_20"), ("kind", "bad_crc")]
        ),
        Some(0.0)
    );
    // The status JSON counts the same.
    let status = status(port).unwrap();
    let climate = status["ports"][0]["devices"]
        .as_array()
        .unwrap()
        .iter()
        .find(|d| d["id"] == "climate_21")
        .unwrap()
        .clone();
    assert!(climate["errors"]["bad_crc"].as_u64().unwrap() > 0);
    assert!(climate["errors"]["timeout"].as_u64().unwrap() > 0);
    assert_eq!(status["ports"][0]["another_master_ms_ago"], Value::Null);

    // A second master on the pair reads the climate sensor every 100 ms (waiting for silence
    // first: on a bus this busy one that does not is mostly garbled): replies near its
    // requests are counted as not taken, and the port says when it was last heard.
    setup.sim.control(json!({"cmd": "faults", "device": 21}));
    let other = setup
        .sim
        .control(json!({"cmd": "other_master", "device": 21, "type": "input",
                                         "address": 0, "count": 2, "every_ms": 100,
                                         "listen": true}));
    assert_eq!(other["ok"], true, "{other}");
    wait_for("replies counted as another master's", &setup.daemon, || {
        // The other master really got answers (the run proves nothing otherwise).
        let sim = setup.sim.control(json!({"cmd": "stats"}));
        if sim["other_master_answered"].as_u64()? == 0 {
            return None;
        }
        let samples = metrics(port)?;
        (metric(
            &samples,
            "rtu2mqtt_device_errors_total",
            &labels("another_master"),
        )? > 0.0
            && metric(
                &samples,
                "rtu2mqtt_errors_total",
                &[("kind", "another_master")],
            )? > 0.0)
            .then_some(())
    });
    let status = crate::status(port).unwrap();
    assert!(
        status["ports"][0]["another_master_ms_ago"]
            .as_u64()
            .is_some(),
        "{status}"
    );
    setup.sim.control(json!({"cmd": "other_master"}));
}

#[test]
fn metrics_parse_and_errors_count_when_the_simulator_injects_faults_at_115200() {
    errors_count_by_kind(115_200);
}

#[test]
fn metrics_parse_and_errors_count_when_the_simulator_injects_faults_at_9600() {
    errors_count_by_kind(9600);
}

#[test]
fn a_password_guards_the_page_when_configured() {
    // bcrypt of "s3cret" made by glibc's crypt(3), cost 5 (quick in a debug build).
    let hash = "$2b$05$dCQ30UB4jly1BFDuIxBRAuNZQfUjMqCDKeE1BLR1sstX/KO5QMpFK";
    let setup = start(
        115_200,
        false,
        json!({"user": "admin", "password_hash": hash}),
    );
    let port = setup.http_port;
    let (code, head, _) = wait_for("the status server", &setup.daemon, || {
        http(port, "GET", "/metrics", &[], "")
    });
    assert_eq!(code, 401);
    assert!(
        head.to_ascii_lowercase()
            .contains("www-authenticate: basic"),
        "{head}"
    );
    // admin:s3cret and admin:wrong in base64.
    let (code, _, _) = http(
        port,
        "GET",
        "/metrics",
        &[("authorization", "Basic YWRtaW46czNjcmV0")],
        "",
    )
    .unwrap();
    assert_eq!(code, 200);
    let (code, _, _) = http(
        port,
        "GET",
        "/metrics",
        &[("authorization", "Basic YWRtaW46d3Jvbmc=")],
        "",
    )
    .unwrap();
    assert_eq!(code, 401);
}

#[test]
fn without_a_password_only_loopback_names_are_served() {
    let setup = start(115_200, false, json!({}));
    let port = setup.http_port;
    wait_for("the status server", &setup.daemon, || get(port, "/metrics"));
    // A page of another site whose name resolves to 127.0.0.1 (DNS rebinding) sends its own Host.
    let (code, _, _) = http(
        port,
        "GET",
        "/api/status",
        &[("host", "evil.example:80")],
        "",
    )
    .unwrap();
    assert_eq!(code, 403);
}

#[test]
fn suspend_holds_a_devices_polling_and_resume_brings_it_back() {
    let setup = start(115_200, false, json!({}));
    let port = setup.http_port;
    let transactions = |samples: &[Sample], device: &str| {
        metric(
            samples,
            "rtu2mqtt_device_transactions_total",
            &[("device", device)],
        )
    };
    wait_for("both devices polled", &setup.daemon, || {
        let samples = metrics(port)?;
        (transactions(&samples, "relay6_20")? > 0.0 && transactions(&samples, "climate_21")? > 0.0)
            .then_some(())
    });
    let hold = |suspended: bool| {
        let body = json!({"device": "relay6_20", "suspended": suspended}).to_string();
        let (code, _, answer) =
            http(port, "POST", "/api/suspend", &[("x-rtu2mqtt", "1")], &body).unwrap();
        assert_eq!(code, 202, "{answer}");
    };
    let relay_suspended = || {
        status(port)?["ports"][0]["devices"]
            .as_array()?
            .iter()
            .find(|d| d["id"] == "relay6_20")?["suspended"]
            .as_bool()
    };
    hold(true);
    wait_for("the relay held", &setup.daemon, || {
        relay_suspended()?.then_some(())
    });
    // Counted from a little later: a relay transaction under way when the hold came, or the
    // event packet of its power-on report (events still go while polling is held), may still
    // be counted after the hold shows.
    let shown = metrics(port).unwrap();
    let held = wait_for("10 requests to the climate sensor", &setup.daemon, || {
        let samples = metrics(port)?;
        (transactions(&samples, "climate_21")? >= transactions(&shown, "climate_21")? + 10.0)
            .then_some(samples)
    });
    // The climate sensor is polled on and on; the relay not once more.
    let after = wait_for(
        "30 more requests to the climate sensor",
        &setup.daemon,
        || {
            let samples = metrics(port)?;
            (transactions(&samples, "climate_21")? >= transactions(&held, "climate_21")? + 30.0)
                .then_some(samples)
        },
    );
    assert_eq!(
        transactions(&after, "relay6_20"),
        transactions(&held, "relay6_20")
    );
    hold(false);
    wait_for("the relay polled again", &setup.daemon, || {
        let samples = metrics(port)?;
        (transactions(&samples, "relay6_20")? > transactions(&held, "relay6_20")?).then_some(())
    });
    assert_eq!(relay_suspended(), Some(false));
}

#[test]
fn an_open_page_does_not_hold_the_daemons_exit() {
    let mut setup = start(115_200, false, json!({}));
    let port = setup.http_port;
    wait_for("the status server", &setup.daemon, || get(port, "/metrics"));
    // An open page: the live stream, its first snapshot read.
    let mut stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream.set_read_timeout(Some(DEADLINE)).unwrap();
    write!(
        stream,
        "GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    let mut seen = Vec::new();
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(&seen).contains("event: status") {
        let len = stream.read(&mut buf).expect("the live stream sends");
        assert!(len > 0, "the live stream ended early");
        seen.extend_from_slice(&buf[..len]);
    }
    let exit = setup.daemon.terminate();
    assert!(exit.success(), "{exit:?}\n{}", setup.daemon.log());
    // The stream ended with the daemon.
    while let Ok(len) = stream.read(&mut buf) {
        if len == 0 {
            break;
        }
    }
}

/// `rtu2mqtt demo` serves the page and prints where.
#[test]
fn the_demo_prints_the_status_page_url_and_serves_it() {
    use std::io::BufRead;
    let mut demo = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .stop_with_parent()
        .args(["demo", "--no-broker"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = std::io::BufReader::new(demo.stderr.take().unwrap());
    let (sender, lines) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            if sender.send(line).is_err() {
                break;
            }
        }
    });
    let deadline = Instant::now() + DEADLINE;
    let url = loop {
        let line = lines
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            .expect("the demo prints the status page's URL");
        if let Some(rest) = line.trim_start().strip_prefix("status:") {
            break rest.split_whitespace().next().unwrap().to_string();
        }
    };
    let port: u16 = url
        .strip_prefix("http://127.0.0.1:")
        .and_then(|rest| rest.trim_end_matches('/').parse().ok())
        .unwrap_or_else(|| panic!("{url}"));
    let started = Instant::now();
    let devices = loop {
        let count = status(port).and_then(|s| s["ports"][0]["devices"].as_array().map(Vec::len));
        if let Some(count) = count {
            break count;
        }
        assert!(
            started.elapsed() < DEADLINE,
            "the demo's page did not answer at {url}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(devices, 5);
    let pid = nix::unistd::Pid::from_raw(demo.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGINT).unwrap();
    let _ = demo.wait();
}

/// The page's scan button: a Fast Modbus scan through the running port's bus queue (the RPC
/// `port/Scan`), while the daemon keeps serving the bus.
#[test]
fn a_scan_from_the_page_finds_the_devices_through_the_running_port() {
    let setup = start(115_200, false, json!({}));
    let port = setup.http_port;
    let port_name = wait_for("the port open", &setup.daemon, || {
        let status = status(port)?;
        let first = &status["ports"][0];
        (first["open"] == true).then(|| first["name"].as_str().map(str::to_string))?
    });
    let body = json!({"port": port_name}).to_string();
    let (code, _, answer) = http(port, "POST", "/api/scan", &[("x-rtu2mqtt", "1")], &body).unwrap();
    assert_eq!(code, 200, "{answer}");
    let report: Value = serde_json::from_str(&answer).unwrap();
    let serials: Vec<&str> = report["devices"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|d| d["sn"].as_str())
        .collect();
    // 0xFE000020 and 0xFE000021, the simulator's serial numbers.
    assert_eq!(serials, ["4261412896", "4261412897"], "{report}");

    // The scan's requests count with the scheduler's own. With both devices' polling held,
    // only event requests go out besides them.
    for device in ["relay6_20", "climate_21"] {
        let body = json!({"device": device, "suspended": true}).to_string();
        let (code, _, _) =
            http(port, "POST", "/api/suspend", &[("x-rtu2mqtt", "1")], &body).unwrap();
        assert_eq!(code, 202);
    }
    wait_for("both devices held", &setup.daemon, || {
        let status = status(port)?;
        status["ports"][0]["devices"]
            .as_array()?
            .iter()
            .all(|d| d["suspended"] == true)
            .then_some(())
    });
    let not_event_rounds = || {
        let samples = metrics(port).unwrap();
        metric(&samples, "rtu2mqtt_transactions_total", &[]).unwrap()
            - metric(&samples, "rtu2mqtt_event_rounds_total", &[]).unwrap()
    };
    let before = not_event_rounds();
    let (code, _, answer) = http(port, "POST", "/api/scan", &[("x-rtu2mqtt", "1")], &body).unwrap();
    assert_eq!(code, 200, "{answer}");
    // Scan start, a continue per device, the end: four at least.
    assert!(not_event_rounds() >= before + 4.0);
    // Another name is refused in words.
    let (code, _, answer) = http(
        port,
        "POST",
        "/api/scan",
        &[("x-rtu2mqtt", "1")],
        r#"{"port": "/dev/nothing"}"#,
    )
    .unwrap();
    assert_eq!(code, 502);
    assert!(answer.contains("no running port"), "{answer}");
}
