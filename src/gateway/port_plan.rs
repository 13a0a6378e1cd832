//! From a resolved port (config + templates) to what its scheduler needs: line timing, one
//! register-level plan per device, and where the bus is.

use std::time::Duration;

use crate::config::config_file::{PortConfig, PortType};
use crate::device::model::{ResolvedDevice, ResolvedPort, SetupItem, WriteFunction};
use crate::port::plan::TCP_RESPONSE_LAG;
use crate::port::{
    DevicePlan, GuardIntervals, HealthPolicy, MergeLimits, PlannedRead, PortSettings, SetupWrite,
    MIN_LATE_REPLY_HOLDOFF,
};
use crate::protocol::{LineSettings, Parity, RegisterType};
use crate::transport::exchange::DEFAULT_FRAME_TIMEOUT;
use crate::transport::Endpoint;

/// Everything one port task needs.
#[derive(Debug, Clone)]
pub struct PortPlan {
    pub name: String,
    pub endpoint: Endpoint,
    pub settings: PortSettings,
    pub devices: Vec<DevicePlan>,
    /// When a TCP gateway's connection is closed and opened again (none: never, and for serial
    /// ports).
    pub reconnect: Option<ReconnectRule>,
}

/// wb-mqtt-serial's rule for a connection that stopped answering without closing
/// (`TPortOpenCloseLogic`): closed and reopened once no transaction has succeeded for `after`
/// (`connection_timeout_ms`, default 5 s) and over `failed_cycles` transactions
/// (`connection_max_fail_cycles`, default 2). Either at -1 turns it off.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReconnectRule {
    pub after: Duration,
    pub failed_cycles: u32,
}

fn reconnect_rule(port: &PortConfig) -> Option<ReconnectRule> {
    if port.port_type == PortType::Serial {
        return None;
    }
    let after = u64::try_from(port.connection_timeout_ms).ok()?;
    let failed_cycles = u32::try_from(port.connection_max_fail_cycles).ok()?;
    Some(ReconnectRule {
        after: Duration::from_millis(after),
        failed_cycles,
    })
}

/// Serial settings of a port; TCP gateways are modelled at 9600 8N2 as wb-mqtt-serial does.
pub fn line_settings(port: &PortConfig) -> LineSettings {
    match port.port_type {
        PortType::Serial => LineSettings {
            baud: port.baud_rate,
            data_bits: port.data_bits,
            parity: port.parity,
            stop_bits: port.stop_bits,
        },
        PortType::Tcp | PortType::ModbusTcp => LineSettings::new(9600, Parity::None, 2),
    }
}

/// The pause a reply may make between two bytes (on a TCP link before the TCP lag; on a serial
/// line where it is longer than the line's own allowance): the longest frame timeout of the
/// port's devices (each the device's `frame_timeout_ms`, else the port's, else 20 ms). A longer
/// pause than a device needs costs nothing on a reply that completes; it only delays giving up
/// a broken one, within its reply timeout.
fn frame_timeout(port: &ResolvedPort) -> Duration {
    port.devices
        .iter()
        .map(|device| device.timing.frame_timeout)
        .max()
        .unwrap_or_else(|| {
            port.config
                .frame_timeout_ms
                .filter(|ms| *ms >= 0)
                .map_or(DEFAULT_FRAME_TIMEOUT, |ms| Duration::from_millis(ms as u64))
        })
}

fn endpoint(port: &ResolvedPort) -> Endpoint {
    let frame_timeout = frame_timeout(port);
    let port = &port.config;
    let address = format!(
        "{}:{}",
        port.address.as_deref().unwrap_or("127.0.0.1"),
        port.port.unwrap_or(502)
    );
    let connect_timeout = Duration::from_millis(port.connect_timeout_ms);
    match port.port_type {
        PortType::Serial => Endpoint::Serial {
            path: port.path.clone().unwrap_or_default(),
            line: line_settings(port),
            frame_timeout,
        },
        PortType::Tcp => Endpoint::RtuOverTcp {
            address,
            connect_timeout,
            frame_timeout,
        },
        PortType::ModbusTcp => Endpoint::ModbusTcp {
            address,
            connect_timeout,
            frame_timeout,
        },
    }
}

/// Whether the port polls Fast Modbus events: `site` is the site-wide switch, which a port's
/// own `fast_modbus: false` narrows; Modbus TCP gateways pass the extension only when they say
/// so (`connected_to_mge`).
pub fn fast_modbus_on(port: &PortConfig, site: bool) -> bool {
    site && port.fast_modbus != Some(false)
        && (port.port_type != PortType::ModbusTcp || port.connected_to_mge)
}

/// What a port adds to every device's configured response timeout: a TCP gateway's
/// [`TCP_RESPONSE_LAG`], nothing on a serial line.
pub fn response_lag(port: &PortConfig) -> Duration {
    if port.port_type == PortType::Serial {
        Duration::ZERO
    } else {
        TCP_RESPONSE_LAG
    }
}

/// `fast_modbus` is the site-wide switch (see [`fast_modbus_on`]).
pub fn port_plan(port: &ResolvedPort, fast_modbus: bool) -> PortPlan {
    let line = line_settings(&port.config);
    let mut settings = PortSettings::for_line(line);
    settings.fast_modbus = fast_modbus_on(&port.config, fast_modbus);
    if let Some(interval) = port.config.event_interval_ms {
        settings.event_interval = Duration::from_millis(interval.clamp(5, 10_000));
    }
    settings.low_priority_reads_per_second = port.low_priority_read_limit;
    settings.response_lag = response_lag(&port.config);
    settings.guard_intervals = GuardIntervals(
        port.devices
            .iter()
            .filter(|d| !d.timing.guard_interval.is_zero())
            .map(|d| (d.slave_id, d.timing.guard_interval))
            .collect(),
    );
    let endpoint = endpoint(port);
    PortPlan {
        name: endpoint.name(),
        endpoint,
        settings,
        devices: port.devices.iter().map(device_plan).collect(),
        reconnect: reconnect_rule(&port.config),
    }
}

pub fn device_plan(device: &ResolvedDevice) -> DevicePlan {
    let mut reads: Vec<PlannedRead> = Vec::new();
    for channel in &device.channels {
        let events = channel.events;
        // Only a device whose firmware is read can be held to a minimum (as wb-mqtt-serial:
        // other devices' channels are all taken as supported).
        let min_firmware = channel.fw.clone().filter(|_| device.is_wb);
        for register in channel.registers.iter().filter_map(|r| r.read) {
            let read = PlannedRead {
                span: register.span(),
                period: channel.read_period,
                rate_limit: device.read_rate_limit(channel),
                events,
                min_firmware: min_firmware.clone(),
            };
            // Bit fields of one register share a read, held to the oldest firmware any of them
            // needs (none when one needs none).
            let shared = reads.iter_mut().find(|r| {
                r.span == read.span
                    && r.period == read.period
                    && r.rate_limit == read.rate_limit
                    && r.events == read.events
            });
            match shared {
                Some(shared) => {
                    shared.min_firmware = match (shared.min_firmware.take(), read.min_firmware) {
                        (Some(a), Some(b)) => Some(std::cmp::min_by(a, b, |a, b| {
                            crate::device::firmware::compare_versions(a, b)
                        })),
                        _ => None,
                    }
                }
                None => reads.push(read),
            }
        }
    }
    // Kept by the scheduler for as long as the port runs.
    reads.shrink_to_fit();
    // Coils and holding registers, in the items' order (wb-mqtt-serial writes coils with 0x05
    // as it writes holding registers): the resolver leaves out, with a warning, items on the
    // tables that cannot be written.
    let setup = device
        .setup
        .iter()
        .filter(|s| !s.words.is_empty())
        .flat_map(setup_writes)
        .collect();
    let defaults = HealthPolicy::default();
    DevicePlan {
        write_retry_time: device.timing.max_write_fail_time,
        name: device.id.clone(),
        address: device.slave_id,
        response_timeout: device.timing.response_timeout,
        merge: MergeLimits {
            max_read_registers: device.timing.max_read_registers,
            max_register_hole: device.timing.max_reg_hole,
            max_bit_hole: device.timing.max_bit_hole,
            min_read_registers: device.timing.min_read_registers,
        },
        // Unset (-1 in the config) means: never disconnect for that reason.
        health: HealthPolicy {
            max_fail_cycles: device.timing.device_max_fail_cycles.unwrap_or(u32::MAX),
            device_timeout: device.timing.device_timeout.unwrap_or(Duration::MAX),
            late_reply_holdoff: (device.timing.response_timeout * 2).max(MIN_LATE_REPLY_HOLDOFF),
            ..defaults
        },
        reads,
        setup,
        continuous_read: device.timing.enable_wb_continuous_read,
    }
}

/// The writes of one setup item, with the function its `reg_type` asks for, as wb-mqtt-serial
/// writes setup registers (`WriteRegister`): `holding_multi` 0x10 even for one register,
/// `holding_single` one 0x06 per register, the last register first, `holding` 0x06 for one
/// register and 0x10 for several, `coil` 0x05 (0/1 as 0000/FF00).
fn setup_writes(item: &SetupItem) -> Vec<SetupWrite> {
    let address = item.register.address;
    let register_type = item.register.reg_type;
    // A coil is one bit: nothing of it to keep from a read.
    let kept_bits = |kept: Vec<u16>| {
        if register_type == RegisterType::Coil {
            Vec::new()
        } else {
            kept
        }
    };
    match item.write_function {
        WriteFunction::Single if item.words.len() > 1 => item
            .words
            .iter()
            .enumerate()
            .rev()
            .map(|(i, &word)| SetupWrite {
                register_type,
                address: address.wrapping_add(u16::try_from(i).unwrap_or(u16::MAX)),
                values: vec![word],
                force_multiple: false,
                kept_bits: kept_bits(
                    item.kept_bits
                        .get(i)
                        .map(|&kept| vec![kept])
                        .unwrap_or_default(),
                ),
            })
            .collect(),
        function => vec![SetupWrite {
            register_type,
            address,
            values: item.words.clone(),
            force_multiple: function == WriteFunction::Multiple,
            kept_bits: kept_bits(item.kept_bits.clone()),
        }],
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use serde_json::{json, Value};

    use super::*;
    use crate::config::parse::SourceText;
    use crate::config::TemplateLibrary;
    use crate::port::EventMode;
    use crate::protocol::Parity;

    /// The first port of a config with `port` (a relay module at 20 added to its devices).
    fn resolved(mut port: Value) -> ResolvedPort {
        port["devices"] = json!([{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]);
        let config = json!({ "ports": [port] });
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        let templates = Path::new(env!("CARGO_MANIFEST_DIR")).join("templates");
        let library = TemplateLibrary::load_dirs(&[templates]);
        crate::device::resolve_config(&loaded, &library)
            .unwrap()
            .remove(0)
    }

    #[test]
    fn a_serial_port_keeps_its_line_settings() {
        let port = resolved(json!({
            "path": "/dev/ttyRS485-1", "baud_rate": 19200, "parity": "E", "stop_bits": 1
        }));
        let plan = port_plan(&port, true);
        assert_eq!(
            plan.settings.line,
            LineSettings::new(19200, Parity::Even, 1)
        );
        assert!(plan.settings.fast_modbus);
        assert_eq!(plan.name, "/dev/ttyRS485-1 (19200 8E1)");
    }

    /// TCP gateways are modelled at 9600 8N2 as wb-mqtt-serial does; Modbus TCP passes Fast
    /// Modbus only when the gateway says it does (`connected_to_mge`).
    #[test]
    fn gateways_are_modelled_at_9600_and_fast_modbus_needs_mge() {
        let tcp = resolved(json!({"port_type": "tcp", "address": "10.0.0.5", "port": 23}));
        let plan = port_plan(&tcp, true);
        assert_eq!(plan.settings.line, LineSettings::new(9600, Parity::None, 2));
        assert!(plan.settings.fast_modbus);
        let modbus_tcp = json!({"port_type": "modbus tcp", "address": "10.0.0.5", "port": 502});
        assert!(
            !port_plan(&resolved(modbus_tcp.clone()), true)
                .settings
                .fast_modbus
        );
        let mut mge = modbus_tcp;
        mge["connected_to_mge"] = json!(true);
        assert!(port_plan(&resolved(mge.clone()), true).settings.fast_modbus);
        assert!(
            !port_plan(&resolved(mge), false).settings.fast_modbus,
            "the site-wide switch wins"
        );
    }

    /// A port's own `fast_modbus: false` turns the extension off there only; its `true` does
    /// not override the site-wide `false`.
    #[test]
    fn a_port_can_turn_fast_modbus_off_for_its_bus() {
        let port =
            |value: Value| resolved(json!({"path": "/dev/ttyRS485-1", "fast_modbus": value}));
        assert!(!port_plan(&port(json!(false)), true).settings.fast_modbus);
        assert!(port_plan(&port(json!(true)), true).settings.fast_modbus);
        assert!(port_plan(&port(Value::Null), true).settings.fast_modbus);
        assert!(!port_plan(&port(json!(true)), false).settings.fast_modbus);
    }

    /// On TCP gateways: the configured frame timeout (the longest of the devices') with the TCP
    /// lag the transport adds, wb-mqtt-serial's response lag on every device's timeout, and its
    /// reconnection rule; none of these on a serial port.
    #[test]
    fn tcp_gateways_carry_their_timeouts_and_reconnection_rule() {
        let tcp = resolved(
            json!({"port_type": "tcp", "address": "10.0.0.5", "port": 23,
            "frame_timeout_ms": 70, "connection_timeout_ms": 2000,
            "connection_max_fail_cycles": 3}),
        );
        let plan = port_plan(&tcp, true);
        let Endpoint::RtuOverTcp { frame_timeout, .. } = plan.endpoint else {
            panic!("{:?}", plan.endpoint);
        };
        // The relay module's template sets its own.
        assert_eq!(frame_timeout, tcp.devices[0].timing.frame_timeout);
        let mut no_devices = tcp.clone();
        no_devices.devices.clear();
        let Endpoint::RtuOverTcp { frame_timeout, .. } = port_plan(&no_devices, true).endpoint
        else {
            unreachable!()
        };
        assert_eq!(frame_timeout, Duration::from_millis(70));
        assert_eq!(plan.settings.response_lag, TCP_RESPONSE_LAG);
        assert_eq!(
            plan.reconnect,
            Some(ReconnectRule {
                after: Duration::from_secs(2),
                failed_cycles: 3
            })
        );
        let mut defaults =
            resolved(json!({"port_type": "modbus tcp", "address": "10.0.0.5", "port": 502}));
        defaults.devices.clear();
        let defaults = port_plan(&defaults, true);
        let Endpoint::ModbusTcp { frame_timeout, .. } = defaults.endpoint else {
            panic!("{:?}", defaults.endpoint);
        };
        assert_eq!(frame_timeout, DEFAULT_FRAME_TIMEOUT);
        assert_eq!(
            defaults.reconnect,
            Some(ReconnectRule {
                after: Duration::from_secs(5),
                failed_cycles: 2
            })
        );
        let never = resolved(
            json!({"port_type": "tcp", "address": "10.0.0.5", "port": 23,
            "connection_timeout_ms": -1}),
        );
        assert_eq!(port_plan(&never, true).reconnect, None);
        let serial = port_plan(&resolved(json!({"path": "/dev/ttyRS485-1"})), true);
        assert_eq!(serial.reconnect, None);
        assert_eq!(serial.settings.response_lag, Duration::ZERO);
    }

    /// `read_rate_limit_ms` (or the old `poll_interval`) of a port or device reaches every
    /// read of its devices; a channel's own wins (wb-mqtt-serial's order).
    #[test]
    fn read_rate_limits_reach_the_reads() {
        let limits = |port: &ResolvedPort| -> Vec<Option<Duration>> {
            port.devices
                .iter()
                .flat_map(|d| device_plan(d).reads)
                .map(|r| r.rate_limit)
                .collect()
        };
        let port = resolved(json!({"path": "/dev/x"}));
        assert!(limits(&port).iter().all(Option::is_none));
        let port = resolved(json!({"path": "/dev/x", "poll_interval": 1000}));
        let all = limits(&port);
        assert!(!all.is_empty());
        assert!(
            all.iter().all(|l| *l == Some(Duration::from_secs(1))),
            "{all:?}"
        );
        let mut config = json!({"path": "/dev/x", "read_rate_limit_ms": 200});
        config["devices"] = json!([{"device_type": "rtu2mqtt-relay6", "slave_id": 20,
            "channels": [{"name": "K1", "read_rate_limit_ms": 5000}]}]);
        let loaded = crate::config::load::load_config_source(
            SourceText::from_text(Path::new("c.json"), &json!({"ports": [config]}).to_string()),
            false,
        )
        .unwrap();
        let library =
            TemplateLibrary::load_dirs(&[Path::new(env!("CARGO_MANIFEST_DIR")).join("templates")]);
        let port = crate::device::resolve_config(&loaded, &library)
            .unwrap()
            .remove(0);
        let all = limits(&port);
        assert!(all.contains(&Some(Duration::from_secs(5))), "{all:?}");
        assert!(all.contains(&Some(Duration::from_millis(200))), "{all:?}");
    }

    /// A serial port's replies may pause its slowest device's `frame_timeout_ms` between bytes,
    /// as wb-mqtt-serial reads a frame.
    #[test]
    fn a_serial_port_carries_its_devices_frame_timeout() {
        let mut port = resolved(json!({"path": "/dev/ttyRS485-1"}));
        let Endpoint::Serial { frame_timeout, .. } = port_plan(&port, true).endpoint else {
            unreachable!()
        };
        assert_eq!(frame_timeout, port.devices[0].timing.frame_timeout);
        port.devices[0].timing.frame_timeout = Duration::from_millis(60);
        let Endpoint::Serial { frame_timeout, .. } = port_plan(&port, true).endpoint else {
            unreachable!()
        };
        assert_eq!(frame_timeout, Duration::from_millis(60));
    }

    #[test]
    fn the_event_interval_is_bounded() {
        let port = |ms: u64| resolved(json!({"path": "/dev/x", "event_interval_ms": ms}));
        assert_eq!(
            port_plan(&port(1), true).settings.event_interval,
            Duration::from_millis(5)
        );
        assert_eq!(
            port_plan(&port(60_000), true).settings.event_interval,
            Duration::from_secs(10)
        );
    }

    /// Bit fields of one register with different `fw` share a read held to the oldest of
    /// them, or to none when one needs none; a device whose firmware is not read (no `hw`) is
    /// held to nothing.
    #[test]
    fn a_shared_read_needs_the_oldest_firmware_of_its_channels() {
        let template = |hw: bool| {
            let mut template = json!({"device_type": "fw-bits", "device": {"name": "B", "id": "b",
            "channels": [
                {"name": "A", "reg_type": "holding", "address": "5:0:1", "type": "switch", "fw": "2.0"},
                {"name": "B", "reg_type": "holding", "address": "5:1:1", "type": "switch", "fw": "1.5.0"},
                {"name": "C", "reg_type": "holding", "address": "6:0:1", "type": "switch", "fw": "2.0"},
                {"name": "D", "reg_type": "holding", "address": "6:1:1", "type": "switch"}
            ]}});
            if hw {
                template["hw"] = json!([{"signature": "B"}]);
            }
            crate::config::TemplateFile::from_source(SourceText::from_text(
                Path::new("fw-bits.json"),
                &template.to_string(),
            ))
            .unwrap()
        };
        let needs = |hw: bool, address: u16| {
            let device = crate::device::configure::resolve_template_device(
                &template(hw),
                &json!({"slave_id": 1}),
            )
            .unwrap();
            device_plan(&device)
                .reads
                .into_iter()
                .find(|r| r.span.start == address)
                .expect("read")
                .min_firmware
        };
        assert_eq!(needs(true, 5), Some("1.5.0".to_owned()));
        assert_eq!(needs(true, 6), None);
        assert_eq!(needs(false, 5), None);
    }

    #[test]
    fn a_device_plan_reads_each_register_once_with_its_event_mode() {
        let port = resolved(json!({"path": "/dev/x"}));
        let plan = port_plan(&port, true);
        let device = &plan.devices[0];
        assert_eq!((device.name.as_str(), device.address), ("relay6_20", 20));
        let k1 = device
            .reads
            .iter()
            .find(|r| r.span == crate::port::RegisterSpan::new(RegisterType::Coil, 0, 1))
            .expect("K1 is read");
        assert_eq!(k1.events, EventMode::Sporadic);
        let mut spans: Vec<_> = device.reads.iter().map(|r| r.span).collect();
        let count = spans.len();
        spans.sort();
        spans.dedup();
        assert_eq!(spans.len(), count, "no register read twice");
        assert!(device.setup.iter().all(|s| !s.values.is_empty()));
    }

    /// Setup registers are written with the function of their `reg_type`, as wb-mqtt-serial
    /// writes them (`TModbusTest.HoldingSingleMulti`: the last register first).
    #[test]
    fn setup_writes_use_the_function_of_their_register_type() {
        let template = json!({"device_type": "setup-functions", "device": {"name": "S", "id": "s",
            "setup": [
                {"title": "single", "reg_type": "holding_single", "address": 10, "format": "u32", "value": 65538},
                {"title": "multi", "reg_type": "holding_multi", "address": 20, "value": 7},
                {"title": "plain", "reg_type": "holding", "address": 30, "format": "u32", "value": 65538},
                {"title": "one", "address": 40, "value": 9}
            ],
            "channels": []}});
        let template = crate::config::TemplateFile::from_source(SourceText::from_text(
            Path::new("setup-functions.json"),
            &template.to_string(),
        ))
        .unwrap();
        let device =
            crate::device::configure::resolve_template_device(&template, &json!({"slave_id": 1}))
                .unwrap();
        let writes: Vec<(u16, Vec<u16>, bool)> = device_plan(&device)
            .setup
            .into_iter()
            .map(|w| (w.address, w.values, w.force_multiple))
            .collect();
        assert_eq!(
            writes,
            vec![
                (11, vec![2], false),
                (10, vec![1], false),
                (20, vec![7], true),
                (30, vec![1, 2], false),
                (40, vec![9], false),
            ]
        );
    }

    /// Setup items on coils are written (0x05), in the items' order among the holding
    /// registers' (ONOKOM TCL-1-MB-B's parameters are coils 92, 94, 95 and 100); an item on a
    /// read-only table is not.
    #[test]
    fn coil_setup_items_are_written_in_order() {
        let template = json!({"device_type": "coil-setup", "device": {"name": "C", "id": "c",
            "preserve_setup_order": true,
            "setup": [
                {"title": "swing", "reg_type": "coil", "address": 92, "value": 1},
                {"title": "mode", "reg_type": "holding", "address": 10, "value": 3},
                {"title": "beep", "reg_type": "coil", "address": 94, "value": 0},
                {"title": "input", "reg_type": "input", "address": 5, "value": 1}
            ],
            "channels": []}});
        let template = crate::config::TemplateFile::from_source(SourceText::from_text(
            Path::new("coil-setup.json"),
            &template.to_string(),
        ))
        .unwrap();
        let (device, warnings) = crate::device::configure::resolve_template_device_with_warnings(
            &template,
            &json!({"slave_id": 1}),
        )
        .unwrap();
        // The input register cannot be written: left out by the resolver, which says so.
        assert!(
            warnings.iter().any(|w| w
                .to_string()
                .contains("a setup item on an input register cannot be written")),
            "{warnings:?}"
        );
        assert_eq!(device.setup.len(), 3);
        let writes: Vec<(RegisterType, u16, Vec<u16>, Vec<u16>)> = device_plan(&device)
            .setup
            .into_iter()
            .map(|w| (w.register_type, w.address, w.values, w.kept_bits))
            .collect();
        assert_eq!(
            writes,
            vec![
                (RegisterType::Coil, 92, vec![1], vec![]),
                (RegisterType::Holding, 10, vec![3], vec![]),
                (RegisterType::Coil, 94, vec![0], vec![]),
            ]
        );
    }
}
