//! The rtu2mqtt config file: MQTT broker, global switches, and the ports with their devices.
//!
//! Port and device keys are those of wb-mqtt-serial (reference §1.1–1.3), so a `ports` section
//! can be carried over from `/etc/wb-mqtt-serial.conf`. Unknown keys at the top level, on a port
//! or a device are warnings (wb-mqtt-serial ignores them; at device level a key may be the value
//! of a template parameter); in the `mqtt` and `http` sections they are errors (typos).

use std::path::PathBuf;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::template::{with_device_settings, ChannelSpec, SetupItemSpec};
use super::values::{SerialInt, SlaveId};

/// The whole config file.
///
/// Unknown keys here and on a port are ignored with a warning (`check-config --strict` makes them
/// errors), as wb-mqtt-serial ignores them: a config it runs may carry them. This schema flags
/// them, so that an editor shows the typos.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[schemars(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub mqtt: MqttConfig,
    /// -1: publish only changes; 0: publish every read; N > 0: republish unchanged values after
    /// N s (values below 5 are raised to 5).
    #[serde(default = "default_max_unchanged_interval")]
    pub max_unchanged_interval: i64,
    /// Use the Fast Modbus extension (events, scan) where devices support it. A site's
    /// security policy may forbid it: then every register is polled.
    #[serde(default = "yes")]
    pub fast_modbus: bool,
    /// Low-priority channel reads per second (channels without `read_period_ms`), split across
    /// ports in proportion to their channels. No limit when absent (wb-mqtt-serial defaults to
    /// 800, 100 on a single CPU, to spare its CPU).
    pub rate_limit: Option<u32>,
    /// Verbose logs (the command line's log level wins).
    #[serde(default)]
    pub debug: bool,
    /// More template directories, searched after the system and user ones (`--templates` wins).
    #[serde(default)]
    pub template_dirs: Vec<PathBuf>,
    #[serde(default)]
    pub ports: Vec<PortConfig>,
    /// The built-in status page and Prometheus metrics (docs/status-page.md). Off when absent;
    /// `"http": {}` serves them on 127.0.0.1:8080.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub http: Option<HttpConfig>,
}

/// The status page's HTTP server.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct HttpConfig {
    /// Address and port to listen on. Only a loopback address (127.0.0.1, ::1) may go without
    /// `user` and `password_hash`: the page can write controls.
    #[serde(default = "default_http_listen")]
    pub listen: String,
    /// Basic-auth user name (required with `password_hash`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub user: Option<String>,
    /// bcrypt hash of the password (`$2b$…`): `rtu2mqtt hash-password` prints one, as does
    /// `htpasswd -nbB user PASSWORD` (the part after the colon).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub password_hash: Option<String>,
}

/// The status page's default address: this machine only.
pub const DEFAULT_HTTP_LISTEN: &str = "127.0.0.1:8080";

fn default_http_listen() -> String {
    DEFAULT_HTTP_LISTEN.to_string()
}

impl Config {
    /// The device paths of the enabled serial ports.
    pub fn serial_port_paths(&self) -> impl Iterator<Item = &str> {
        self.ports
            .iter()
            .filter(|port| port.enabled && port.port_type == PortType::Serial)
            .filter_map(|port| port.path.as_deref())
    }
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            listen: default_http_listen(),
            user: None,
            password_hash: None,
        }
    }
}

impl HttpConfig {
    /// What is wrong with this section, as (key, problem) for the integrator; empty when fine.
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut problems = Vec::new();
        match self.listen.parse::<std::net::SocketAddr>() {
            Err(_) => problems.push((
                "listen",
                format!(
                    "`{}` is not an address and port: write e.g. \"127.0.0.1:8080\" or \"0.0.0.0:8080\"",
                    self.listen
                ),
            )),
            Ok(address) if !address.ip().is_loopback() && self.password_hash.is_none() => {
                problems.push((
                    "listen",
                    format!(
                        "{address} is reachable from other machines and the page can write \
                         controls: add `user` and `password_hash` (rtu2mqtt hash-password \
                         prints one), or listen on 127.0.0.1"
                    ),
                ))
            }
            Ok(_) => {}
        }
        match (&self.user, &self.password_hash) {
            (Some(_), None) => problems.push((
                "user",
                "a user needs its `password_hash` (rtu2mqtt hash-password prints one)".into(),
            )),
            (None, Some(_)) => {
                problems.push(("password_hash", "a password hash needs its `user`".into()))
            }
            _ => {}
        }
        if let Some(hash) = &self.password_hash {
            let bcrypt = ["$2a$", "$2b$", "$2x$", "$2y$"]
                .iter()
                .any(|prefix| hash.starts_with(prefix))
                && hash.len() == 60;
            if !bcrypt {
                problems.push((
                    "password_hash",
                    "not a bcrypt hash (60 characters starting with $2b$): produce one with \
                     `rtu2mqtt hash-password` or `htpasswd -nbB user PASSWORD`; never put the \
                     password itself here"
                        .into(),
                ));
            }
        }
        problems
    }
}

fn default_max_unchanged_interval() -> i64 {
    -1
}

fn yes() -> bool {
    true
}

/// MQTT broker connection.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// The broker's host name or IP address alone, without a scheme or a port: `localhost`,
    /// `192.168.1.10`, `broker.example.com`. TLS is set with `tls`, the port with `port`.
    #[serde(default = "default_host")]
    #[schemars(
        length(min = 1),
        regex(pattern = r"^([^/:\s\[\]]+|[^/:\s\[\]]*:[^/:\s\[\]]*:[^/\s\[\]]*)$")
    )]
    pub host: String,
    /// The broker's TCP port: 1883, usually 8883 with TLS.
    #[serde(default = "default_mqtt_port")]
    #[schemars(range(min = 1))]
    pub port: u16,
    #[serde(default = "default_client_id")]
    pub client_id: String,
    pub user: Option<String>,
    pub password: Option<String>,
    /// TLS to the broker; absent = plain TCP.
    pub tls: Option<TlsConfig>,
    /// Keep-alive interval in s.
    #[serde(default = "default_keepalive")]
    pub keepalive_s: u16,
    /// Prepended to every topic (`/devices/...` stays the WB layout after it), so several
    /// controllers can share one broker: `site1` gives `site1/devices/...`. Empty by default.
    #[serde(default)]
    pub topic_prefix: String,
    /// On a clean exit (SIGTERM), delete every retained topic of the devices, as
    /// wb-mqtt-serial does. Default true.
    #[serde(default = "yes")]
    pub clear_on_exit: bool,
    /// Home Assistant MQTT discovery.
    #[serde(default)]
    pub homeassistant: HomeAssistantConfig,
}

/// Home Assistant MQTT discovery: every device and control appears in HA without a bridge.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HomeAssistantConfig {
    /// Publish discovery configs (retained). Default true; turn off when a WB→HA bridge
    /// already maps the devices, or they appear twice.
    #[serde(default = "yes")]
    pub enabled: bool,
    /// HA's discovery prefix (HA's own default is `homeassistant`).
    #[serde(default = "default_discovery_prefix")]
    pub prefix: String,
    /// Also delete the discovery configs on a clean exit. Default false: HA would forget the
    /// entities (names, areas, dashboards) on every restart; they show as unavailable instead.
    #[serde(default)]
    pub clear_on_exit: bool,
}

impl Default for HomeAssistantConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            prefix: default_discovery_prefix(),
            clear_on_exit: false,
        }
    }
}

fn default_discovery_prefix() -> String {
    "homeassistant".to_string()
}

impl Default for MqttConfig {
    fn default() -> Self {
        Self {
            host: default_host(),
            port: default_mqtt_port(),
            client_id: default_client_id(),
            user: None,
            password: None,
            tls: None,
            keepalive_s: default_keepalive(),
            topic_prefix: String::new(),
            clear_on_exit: true,
            homeassistant: HomeAssistantConfig::default(),
        }
    }
}

fn default_host() -> String {
    "localhost".to_string()
}
fn default_mqtt_port() -> u16 {
    1883
}
fn default_client_id() -> String {
    "rtu2mqtt".to_string()
}
fn default_keepalive() -> u16 {
    60
}

/// PEM files for TLS to the broker.
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// CA certificate(s) that signed the broker's certificate.
    pub ca_file: Option<PathBuf>,
    /// Client certificate and key, when the broker asks for one.
    pub cert_file: Option<PathBuf>,
    pub key_file: Option<PathBuf>,
}

/// How the port reaches the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, JsonSchema)]
pub enum PortType {
    /// A local RS-485 serial port.
    #[default]
    #[serde(rename = "serial")]
    Serial,
    /// RTU frames over a TCP socket (a transparent serial gateway).
    #[serde(rename = "tcp")]
    Tcp,
    /// Modbus TCP (MBAP header).
    #[serde(rename = "modbus tcp")]
    ModbusTcp,
}

/// Serial parity: the protocol's type, written `N`, `E` or `O` in the config.
pub use crate::protocol::Parity;

/// `parity` as the config writes it (`N`, `E`, `O`, as wb-mqtt-serial does).
mod parity_letter {
    use super::Parity;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(parity: &Parity, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(match parity {
            Parity::None => "N",
            Parity::Even => "E",
            Parity::Odd => "O",
        })
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Parity, D::Error> {
        match String::deserialize(deserializer)?.as_str() {
            "N" => Ok(Parity::None),
            "E" => Ok(Parity::Even),
            "O" => Ok(Parity::Odd),
            other => Err(serde::de::Error::unknown_variant(other, &["N", "E", "O"])),
        }
    }

    pub fn schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({ "type": "string", "enum": ["N", "E", "O"] })
    }

    pub fn none() -> Parity {
        Parity::None
    }
}

/// One bus. Unknown keys are warnings (see [`Config`]).
#[derive(Debug, Clone, Deserialize, Serialize, JsonSchema)]
#[schemars(deny_unknown_fields)]
pub struct PortConfig {
    #[serde(default)]
    pub port_type: PortType,
    #[serde(default = "yes")]
    pub enabled: bool,
    /// Serial: device path, e.g. `/dev/ttyRS485-1` or `/dev/serial/by-id/...`.
    pub path: Option<String>,
    /// Serial: bits per second, 110…4000000 (default 9600). `check-config` warns about a rate
    /// other than 110, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400,
    /// 460800 or 921600: most likely a typo.
    #[serde(default = "default_baud_rate")]
    #[schemars(range(min = MIN_BAUD_RATE, max = MAX_BAUD_RATE))]
    pub baud_rate: u32,
    #[serde(default = "parity_letter::none", with = "parity_letter")]
    #[schemars(schema_with = "parity_letter::schema")]
    pub parity: Parity,
    /// Serial: 5, 6, 7 or 8 (default 8).
    #[serde(default = "default_data_bits")]
    #[schemars(range(min = 5, max = 8))]
    pub data_bits: u8,
    /// Serial: 1 or 2. Default 1, whatever the parity (as in wb-mqtt-serial).
    #[serde(default = "default_stop_bits")]
    #[schemars(range(min = 1, max = 2))]
    pub stop_bits: u8,
    /// TCP and Modbus TCP: host name or IP address of the gateway …
    pub address: Option<String>,
    /// … and its TCP port.
    pub port: Option<u16>,
    /// Modbus TCP: the gateway is a WB-MGE v.3, which passes Fast Modbus through.
    #[serde(default)]
    pub connected_to_mge: bool,
    /// `false`: no Fast Modbus on this bus (every register polled), whatever the site-wide
    /// `fast_modbus` says; the site-wide `false` turns it off on every port. For a bus with a
    /// device whose Modbus stack frames requests by length instead of by silence (libmodbus's
    /// server): the event polls' broadcast frames and arbitration bytes throw it out of step,
    /// and it misses the requests that follow them.
    pub fast_modbus: Option<bool>,
    /// Minimum response timeout for every device on this port, in ms (default 500).
    #[schemars(range(min = -1, max = 60000))]
    pub response_timeout_ms: Option<i64>,
    /// Default frame (inter-byte) timeout of this port's devices, in ms.
    #[schemars(range(min = -1, max = 10000))]
    pub frame_timeout_ms: Option<i64>,
    /// Default pause before each request, in µs.
    #[schemars(range(min = -1, max = 1000000))]
    pub guard_interval_us: Option<i64>,
    /// Default minimum interval between reads of one register (deprecated upstream).
    #[schemars(range(min = -1, max = 172800000))]
    pub read_rate_limit_ms: Option<i64>,
    /// Longest time between two Fast Modbus event requests, in ms. Default by baud rate: 50 ms
    /// at 115200 and above, 100 ms from 38400, 200 ms below. Events are polled sooner whenever
    /// the bus has nothing else to do.
    #[schemars(range(min = 5, max = 10000))]
    pub event_interval_ms: Option<u64>,
    #[schemars(range(min = -1, max = 172800000))]
    pub poll_interval: Option<i64>,
    /// TCP connect timeout in ms.
    #[serde(default = "default_connect_timeout")]
    pub connect_timeout_ms: u64,
    /// Reopen the port after this long without a successful exchange (ms; -1 never) …
    #[serde(default = "default_connection_timeout")]
    #[schemars(range(min = -1, max = 3600000))]
    pub connection_timeout_ms: i64,
    /// … and this many failed poll cycles (-1 never).
    #[serde(default = "default_connection_fail_cycles")]
    pub connection_max_fail_cycles: i64,
    #[serde(default)]
    pub devices: Vec<DeviceConfig>,
}

/// The baud rates the loader takes; outside them a `baud_rate` is no serial speed at all.
pub const MIN_BAUD_RATE: u32 = 110;
pub const MAX_BAUD_RATE: u32 = 4_000_000;

fn default_baud_rate() -> u32 {
    9600
}
fn default_data_bits() -> u8 {
    8
}
fn default_stop_bits() -> u8 {
    1
}
fn default_connect_timeout() -> u64 {
    5000
}
fn default_connection_timeout() -> i64 {
    5000
}
fn default_connection_fail_cycles() -> i64 {
    2
}

impl PortConfig {
    /// How the port is named in messages and duplicate checks: path, or address:port.
    pub fn describe(&self) -> String {
        match self.port_type {
            PortType::Serial => self.path.clone().unwrap_or_default(),
            _ => format!(
                "{}:{}",
                self.address.as_deref().unwrap_or(""),
                self.port.unwrap_or(0)
            ),
        }
    }
}

with_device_settings! {
    /// A device on a port. Keys other than these are values of the template's parameters
    /// (checked against the template when the config is resolved).
    #[derive(Debug, Clone, Default, Deserialize, Serialize, JsonSchema)]
    pub struct DeviceConfig {
        /// Modbus address (unit id on Modbus TCP): a number, a decimal string or "0x..".
        pub slave_id: Option<SlaveId>,
        /// Template name (`device_type` in the template file).
        pub device_type: Option<String>,
        /// MQTT device id (default: template id + "_" + slave_id).
        pub id: Option<String>,
        /// Device title (default: template name + " " + slave_id).
        pub name: Option<String>,
        /// A disabled device is not loaded at all.
        pub enabled: Option<bool>,
        /// Setup registers written on connect, before the template's.
        pub setup: Option<Vec<SetupItemSpec>>,
        /// Overrides of template channels (matched by `name`), or extra channels.
        pub channels: Option<Vec<ChannelSpec>>,
    }
}
