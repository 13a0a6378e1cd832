//! The HTTP side: the page, its JSON and live stream, the frames log, writes, and `/metrics`.
//!
//! Nothing is computed between requests: every view is built from the ports' counters when it
//! is asked for. The live stream sends one snapshot a second per open page.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use axum::body::Bytes;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode, Uri};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tracing::{info, warn};

use super::auth::{BasicAuth, Verdict};
use super::hub::{StatusHub, WriteRefused};
use crate::config::config_file::HttpConfig;

const PAGE: &str = include_str!("page.html");
/// How often an open page gets a new snapshot.
const LIVE_INTERVAL: Duration = Duration::from_secs(1);
/// The header a write must carry: a cross-site form cannot send it, so another web site open
/// in the integrator's browser cannot write controls through the page's address.
pub const WRITE_HEADER: &str = "x-rtu2mqtt";

#[derive(Clone)]
struct AppState {
    hub: Arc<StatusHub>,
    auth: Option<Arc<BasicAuth>>,
    /// Host headers accepted without authentication (the loopback names of the listen port):
    /// a web page whose own name resolves to 127.0.0.1 (DNS rebinding) is refused.
    local_hosts: Vec<String>,
    shutdown: watch::Receiver<bool>,
}

/// The status server, bound and ready to serve.
pub struct StatusServer {
    listener: TcpListener,
    state: AppState,
}

impl StatusServer {
    /// Binds the configured address (checked by the config loader: a non-loopback address has
    /// a password), or takes `prebound`, a socket already bound to it.
    pub async fn bind(
        config: &HttpConfig,
        prebound: Option<std::net::TcpListener>,
        hub: Arc<StatusHub>,
        shutdown: watch::Receiver<bool>,
    ) -> anyhow::Result<Self> {
        let address: SocketAddr = config.listen.parse().with_context(|| {
            format!(
                "http.listen `{}` is not an address and port (e.g. 127.0.0.1:8080)",
                config.listen
            )
        })?;
        let listener = match prebound {
            Some(listener) => {
                listener.set_nonblocking(true)?;
                TcpListener::from_std(listener)?
            }
            None => TcpListener::bind(address).await.with_context(|| {
                format!("the status page cannot listen on {address}: is another program using the port? Change http.listen")
            })?,
        };
        let port = listener
            .local_addr()
            .map(|a| a.port())
            .unwrap_or(address.port());
        let auth = match (&config.user, &config.password_hash) {
            (Some(user), Some(hash)) => Some(Arc::new(BasicAuth::new(user, hash))),
            _ => None,
        };
        let local_hosts = local_hosts(port);
        Ok(Self {
            listener,
            state: AppState {
                hub,
                auth,
                local_hosts,
                shutdown,
            },
        })
    }

    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.listener.local_addr().ok()
    }

    /// Serves until the shutdown signal; open live streams end with it.
    pub async fn serve(self) {
        let address = self.local_addr();
        let state = self.state;
        let mut stop = state.shutdown.clone();
        let app = Router::new()
            .route("/", get(page))
            .route("/api/status", get(status))
            .route("/api/events", get(live))
            .route("/api/frames", get(frames))
            .route("/api/write", post(write))
            .route("/api/suspend", post(suspend))
            .route("/api/scan", post(scan))
            .route("/metrics", get(metrics))
            .layer(middleware::from_fn_with_state(state.clone(), guard))
            .with_state(state);
        if let Some(address) = address {
            info!(url = %format!("http://{address}/"), "status page serving");
        }
        let served = axum::serve(super::limits::LimitedListener::new(self.listener), app)
            .with_graceful_shutdown(async move {
                let _ = stop.wait_for(|stop| *stop).await;
            })
            .await;
        if let Err(err) = served {
            warn!(%err, "the status page stopped");
        }
    }
}

/// Authentication, or without it, requests addressed to this machine's loopback names only.
async fn guard(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let headers = request.headers();
    match &state.auth {
        Some(auth) => {
            let header = headers
                .get(header::AUTHORIZATION)
                .and_then(|v| v.to_str().ok());
            match auth.check(header).await {
                Verdict::Accepted => {}
                Verdict::Refused => {
                    return (
                        StatusCode::UNAUTHORIZED,
                        [(
                            header::WWW_AUTHENTICATE,
                            HeaderValue::from_static("Basic realm=\"rtu2mqtt\", charset=\"UTF-8\""),
                        )],
                        "user name and password needed (http.user / http.password_hash)\n",
                    )
                        .into_response();
                }
                Verdict::Busy { retry_after } => {
                    let seconds = retry_after.as_secs();
                    return (
                        StatusCode::TOO_MANY_REQUESTS,
                        [(header::RETRY_AFTER, HeaderValue::from(seconds))],
                        format!(
                            "another password check is running (one at a time, slower after \
                             wrong passwords); try again in {seconds} s\n"
                        ),
                    )
                        .into_response();
                }
            }
        }
        None => {
            let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
            if host.is_some_and(|host| {
                !state
                    .local_hosts
                    .iter()
                    .any(|h| h.eq_ignore_ascii_case(host))
            }) {
                return (
                    StatusCode::FORBIDDEN,
                    "this status page answers on its loopback address only (127.0.0.1, localhost)\n",
                )
                    .into_response();
            }
        }
    }
    next.run(request).await
}

/// The `Host` headers of a loopback request to `port`: with the port, and without it on 80,
/// where a browser leaves it out.
fn local_hosts(port: u16) -> Vec<String> {
    let names = ["127.0.0.1", "localhost", "[::1]"];
    let mut hosts: Vec<String> = names.iter().map(|host| format!("{host}:{port}")).collect();
    if port == 80 {
        hosts.extend(names.iter().map(|host| (*host).to_string()));
    }
    hosts
}

async fn page() -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        PAGE,
    )
        .into_response()
}

fn json_response(value: &serde_json::Value) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        value.to_string(),
    )
        .into_response()
}

async fn status(State(state): State<AppState>) -> Response {
    json_response(&state.hub.snapshot())
}

async fn metrics(State(state): State<AppState>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        state.hub.metrics(),
    )
        .into_response()
}

/// One query parameter, percent-decoded.
fn query_param(uri: &Uri, name: &str) -> Option<String> {
    uri.query()?.split('&').find_map(|pair| {
        let (key, value) = pair.split_once('=')?;
        (key == name).then(|| percent_decode(value))
    })
}

fn percent_decode(text: &str) -> String {
    let hex = |byte: u8| char::from(byte).to_digit(16);
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let escaped = match bytes.get(i..i + 3) {
            Some([b'%', high, low]) => hex(*high).zip(hex(*low)).map(|(h, l)| (h * 16 + l) as u8),
            _ => None,
        };
        match (escaped, bytes[i]) {
            (Some(byte), _) => {
                out.push(byte);
                i += 3;
                continue;
            }
            (None, b'+') => out.push(b' '),
            (None, other) => out.push(other),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

async fn frames(State(state): State<AppState>, uri: Uri) -> Response {
    let Some(device) = query_param(&uri, "device") else {
        return (StatusCode::BAD_REQUEST, "add ?device=<device id>\n").into_response();
    };
    match state.hub.frames(&device) {
        Some(frames) => json_response(&frames),
        None => (
            StatusCode::NOT_FOUND,
            format!("no device `{device}` on any port\n"),
        )
            .into_response(),
    }
}

/// The JSON body of a POST from the page; refused without [`WRITE_HEADER`].
fn page_post(headers: &HeaderMap, body: &[u8]) -> Result<serde_json::Value, (StatusCode, String)> {
    if !headers.contains_key(WRITE_HEADER) {
        return Err((
            StatusCode::FORBIDDEN,
            format!("a write needs the `{WRITE_HEADER}` header (the page sends it)\n"),
        ));
    }
    serde_json::from_slice::<serde_json::Value>(body).map_err(|_| {
        (
            StatusCode::BAD_REQUEST,
            "the body must be JSON\n".to_string(),
        )
    })
}

/// `{"device": …, "suspended": true|false}`: holds or resumes the device's polling.
async fn suspend(State(state): State<AppState>, headers: HeaderMap, body: Bytes) -> Response {
    let request = match page_post(&headers, &body) {
        Ok(request) => request,
        Err(refused) => return refused.into_response(),
    };
    let (Some(device), Some(suspended)) =
        (request["device"].as_str(), request["suspended"].as_bool())
    else {
        return (
            StatusCode::BAD_REQUEST,
            "give device and suspended (true or false)\n",
        )
            .into_response();
    };
    if state.hub.suspend(device, suspended) {
        info!(%device, suspended, "polling hold from the status page");
        (StatusCode::ACCEPTED, "queued\n").into_response()
    } else {
        (
            StatusCode::NOT_FOUND,
            format!("no device `{device}` on any port\n"),
        )
            .into_response()
    }
}

/// `{"port": <name as in /api/status>}`: a Fast Modbus scan through the port's bus queue (the
/// RPC `port/Scan`); answers when the scan is done with its report.
async fn scan(State(state): State<AppState>, headers: HeaderMap, body: Bytes) -> Response {
    let request = match page_post(&headers, &body) {
        Ok(request) => request,
        Err(refused) => return refused.into_response(),
    };
    let Some(port) = request["port"].as_str() else {
        return (
            StatusCode::BAD_REQUEST,
            "give port (its name as /api/status shows it)\n",
        )
            .into_response();
    };
    info!(%port, "scan from the status page");
    match state.hub.scan(port).await {
        Ok(report) => json_response(&report),
        Err(problem) => (StatusCode::BAD_GATEWAY, format!("{problem}\n")).into_response(),
    }
}

/// `{"device": …, "control": …, "value": …}`: queued as an MQTT `/on` write would be.
async fn write(State(state): State<AppState>, headers: HeaderMap, body: Bytes) -> Response {
    let request = match page_post(&headers, &body) {
        Ok(request) => request,
        Err(refused) => return refused.into_response(),
    };
    let field = |name: &str| match &request[name] {
        serde_json::Value::String(text) => Some(text.clone()),
        serde_json::Value::Number(number) => Some(number.to_string()),
        serde_json::Value::Bool(flag) => Some(if *flag { "1" } else { "0" }.to_string()),
        _ => None,
    };
    let (Some(device), Some(control), Some(value)) =
        (field("device"), field("control"), field("value"))
    else {
        return (StatusCode::BAD_REQUEST, "give device, control and value\n").into_response();
    };
    match state.hub.write(&device, &control, &value) {
        Ok(()) => {
            info!(%device, %control, %value, "write from the status page");
            (StatusCode::ACCEPTED, "queued\n").into_response()
        }
        Err(WriteRefused::UnknownDevice) => (
            StatusCode::NOT_FOUND,
            format!("no device `{device}` on this gateway\n"),
        )
            .into_response(),
        Err(WriteRefused::UnknownControl) => (
            StatusCode::NOT_FOUND,
            format!("no control `{control}` on device `{device}`\n"),
        )
            .into_response(),
        Err(WriteRefused::ReadOnly) => (
            StatusCode::CONFLICT,
            format!("`{device}/{control}` is read-only\n"),
        )
            .into_response(),
        Err(WriteRefused::NotRunning) => (
            StatusCode::SERVICE_UNAVAILABLE,
            "the bus side is not taking writes right now; try again\n",
        )
            .into_response(),
    }
}

/// Server-sent events: a `status` event with the snapshot every second until the page closes
/// or the daemon stops.
async fn live(State(state): State<AppState>) -> Response {
    let hub = Arc::clone(&state.hub);
    let stop = state.shutdown.clone();
    let ticks = tokio::time::interval(LIVE_INTERVAL);
    let stream = futures_util::stream::unfold(
        (hub, stop, ticks),
        |(hub, mut stop, mut ticks)| async move {
            if *stop.borrow() {
                return None;
            }
            tokio::select! {
                _ = ticks.tick() => {}
                _ = stop.changed() => return None,
            }
            let event = Event::default()
                .event("status")
                .data(hub.snapshot().to_string());
            Some((Ok::<_, std::convert::Infallible>(event), (hub, stop, ticks)))
        },
    );
    Sse::new(stream)
        .keep_alive(KeepAlive::default())
        .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_loads_nothing_from_elsewhere() {
        // Works on a site without internet: no scripts, styles, fonts or images by URL.
        for needle in ["http://", "https://", "//cdn", "src=", "@import", "url("] {
            assert!(!PAGE.contains(needle), "the page refers to {needle}");
        }
        // Its own requests are relative, so it also works behind a reverse proxy's sub-path.
        assert!(PAGE.contains(r#"new EventSource("api/events")"#));
    }

    /// A browser leaves the port out of `Host` on port 80.
    #[test]
    fn loopback_hosts_include_the_bare_names_on_port_80() {
        assert!(local_hosts(80).iter().any(|h| h == "localhost"));
        assert!(local_hosts(80).iter().any(|h| h == "localhost:80"));
        assert!(!local_hosts(8080).iter().any(|h| h == "localhost"));
    }

    #[test]
    fn query_parameters_are_decoded() {
        let uri: Uri = "/api/frames?x=1&device=wb%2Dmr6c_12&y".parse().unwrap();
        assert_eq!(query_param(&uri, "device").as_deref(), Some("wb-mr6c_12"));
        assert_eq!(query_param(&uri, "z"), None);
        assert_eq!(percent_decode("a%2"), "a%2");
        assert_eq!(percent_decode("%zz"), "%zz");
        assert_eq!(percent_decode("%"), "%");
    }
}
