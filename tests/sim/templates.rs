//! Every shipped template and every wb-format fixture (tests/data/wb-templates) builds a simulated
//! device through the shared template loader, with the registers a master would use; the example
//! bus file loads and matches the example daemon config.

use std::path::{Path, PathBuf};
use std::process::Command;

use rtu2mqtt::config::TemplateFile;
use rtu2mqtt::protocol::RegisterType;
use rtu2mqtt::sim::bus_file::{build_device, load_bus, DeviceEntry, TemplateSource};
use rtu2mqtt::sim::from_template::template_registers;
use rtu2mqtt::sim::VirtualDevice;
use serde_json::json;

const COIL: RegisterType = RegisterType::Coil;
const DISCRETE: RegisterType = RegisterType::DiscreteInput;
const HOLDING: RegisterType = RegisterType::Holding;
const INPUT: RegisterType = RegisterType::Input;

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn json_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .filter(|path| path.extension().is_some_and(|ext| ext == "json"))
        .collect();
    files.sort();
    files
}

/// A device at address 20 built from the template file, as the bus file would.
fn device(template: &Path) -> VirtualDevice {
    let entry: DeviceEntry = serde_json::from_value(json!({
        "name": "d", "template": template, "address": 20, "serial": "0xFE000020"
    }))
    .unwrap();
    let mut templates = TemplateSource::new(Path::new("."), Path::new("."));
    build_device(&entry, &mut templates).unwrap_or_else(|e| panic!("{}: {e}", template.display()))
}

/// Asserts that a register exists, and whether it is writable and event-capable (width).
#[track_caller]
fn assert_register(
    device: &VirtualDevice,
    reg_type: RegisterType,
    address: u16,
    writable: bool,
    event_width: Option<u8>,
) {
    let registers = device.registers();
    let cell = registers
        .cell(reg_type, address)
        .unwrap_or_else(|| panic!("{}: no {reg_type:?} {address}", device.template));
    assert_eq!(
        cell.writable, writable,
        "{}: {reg_type:?} {address} writable",
        device.template
    );
    assert_eq!(
        registers.event_width(reg_type, address),
        event_width,
        "{}: {reg_type:?} {address} events",
        device.template
    );
}

#[test]
fn every_template_builds_a_device() {
    let mut files = json_files(&repo("templates"));
    let shipped = files.len();
    files.extend(json_files(&repo("tests/data/wb-templates")));
    assert_eq!(shipped, 6);
    assert!(
        files.len() >= shipped + 4,
        "the wb-format fixtures are found"
    );
    for file in &files {
        let template = TemplateFile::load(file).unwrap_or_else(|e| panic!("{e}"));
        let registers = template_registers(&template, 20).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(registers.device_type, template.device_type());
        assert_eq!(registers.limited, None, "{}", file.display());
        let device = device(file);
        // Wiren Board standard registers, on every device.
        assert_register(&device, HOLDING, 128, true, None);
        assert_register(&device, HOLDING, 270, false, None);
        assert_eq!(device.registers().get(HOLDING, 128), Some(20));
        let template_defined: usize = [COIL, DISCRETE, HOLDING, INPUT]
            .iter()
            .map(|t| registers.registers.iter(*t).count())
            .sum();
        assert!(template_defined > 0, "{}", file.display());
    }
}

#[test]
fn shipped_templates() {
    let relay = device(&repo("templates/rtu2mqtt-relay6.json"));
    assert_eq!(relay.template, "rtu2mqtt-relay6");
    for coil in 0..6 {
        assert_register(&relay, COIL, coil, true, Some(1));
    }
    assert!(relay.registers().get(COIL, 6).is_none());
    // Parameter in0_mode.
    assert_register(&relay, HOLDING, 16, true, None);

    let meter = device(&repo("templates/rtu2mqtt-energy-meter.json"));
    for address in [0x00, 0x01, 0x06, 0x07, 0x46, 0x47, 0x156, 0x157] {
        assert_register(&meter, INPUT, address, false, None);
    }
    assert!(meter.registers().get(INPUT, 0x02).is_none());

    let climate = device(&repo("templates/rtu2mqtt-climate.json"));
    assert_register(&climate, INPUT, 4, false, Some(1));
    assert_register(&climate, INPUT, 8, false, Some(1));
    assert_register(&climate, INPUT, 9, false, Some(2));
    assert_register(&climate, INPUT, 10, false, None);
    assert_register(&climate, COIL, 0, true, None);
    // Parameters co2_sensor_enabled (a coil) and motion_filter_time_const_s; disabled channel
    // Uptime.
    assert_register(&climate, COIL, 3, true, None);
    assert_register(&climate, HOLDING, 282, true, None);
    assert_register(&climate, INPUT, 105, false, None);

    let counter = device(&repo("templates/rtu2mqtt-counter8.json"));
    assert_register(&counter, DISCRETE, 7, false, Some(1));
    assert_register(&counter, INPUT, 60, false, Some(2));
    assert_register(&counter, INPUT, 75, false, None);
    // Disabled press counter channels can still be enabled by a master.
    assert_register(&counter, INPUT, 471, false, Some(1));
    assert_register(&counter, HOLDING, 27, true, None);

    let dimmer = device(&repo("templates/rtu2mqtt-dimmer.json"));
    assert_register(&dimmer, HOLDING, 0, true, Some(1));
    assert_register(&dimmer, COIL, 2, true, Some(1));
    assert_register(&dimmer, HOLDING, 60, true, None);
}

#[test]
fn wb_format_fixtures() {
    let fixture = |name: &str| device(&repo("tests/data/wb-templates").join(name));
    let meter = fixture("config-test-meter.json");
    assert_register(&meter, INPUT, 0x1410, false, Some(2));
    assert_register(&meter, INPUT, 0, false, None);
    assert_register(&meter, INPUT, 1, false, None);
    let sensor = fixture("config-test-wb-sensor.json");
    assert_register(&sensor, INPUT, 4, false, None);
    assert_register(&sensor, INPUT, 280, false, Some(1));
    // A disabled channel (Dew Point).
    assert_register(&sensor, INPUT, 367, false, None);
    assert_register(&sensor, COIL, 0, true, None);
    // A subdevice with its default choice: in1_sensor's channels.
    let inputs = fixture("config-test-wb-inputs.json");
    assert_register(&inputs, INPUT, 7, false, None);
    assert_register(&inputs, DISCRETE, 16, false, None);
}

fn daemon_devices(config: &Path) -> Vec<(u8, String)> {
    let text = std::fs::read_to_string(config).unwrap();
    let config: serde_json::Value =
        serde_json::from_str(&rtu2mqtt::config::jsonc::strip_comments(&text)).unwrap();
    let ports = config["ports"].as_array().unwrap();
    assert_eq!(ports.len(), 1);
    assert_eq!(ports[0]["path"], "/tmp/ttyRS485-sim");
    ports[0]["devices"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            (
                d["slave_id"].as_u64().unwrap() as u8,
                d["device_type"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
fn example_sim_bus_and_daemon_config() {
    let config = repo("config/examples/sim-daemon.json");
    let out = Command::new(env!("CARGO_BIN_EXE_rtu2mqtt"))
        .arg("check-config")
        .arg("-c")
        .arg(&config)
        .arg("--templates")
        .arg(repo("templates"))
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success() && text.contains(": ok"), "{text}");

    let (_, devices) = load_bus(&repo("config/examples/sim-bus.json"), &repo("templates"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(devices.len() >= 5);
    let mut on_bus: Vec<(u8, String)> = devices
        .iter()
        .map(|d| (d.address(), d.template.clone()))
        .collect();
    on_bus.sort();
    let mut configured = daemon_devices(&config);
    configured.sort();
    assert_eq!(on_bus, configured);
    let mut serials: Vec<u32> = devices.iter().map(|d| d.serial & 0x0FFF_FFFF).collect();
    serials.sort();
    serials.dedup();
    assert_eq!(
        serials.len(),
        devices.len(),
        "serials must differ in 28 bits"
    );
    for device in &devices {
        assert_eq!(device.line().to_string(), "115200 8N2", "{}", device.name);
    }
    let by_address = |address: u8| devices.iter().find(|d| d.address() == address).unwrap();
    assert!(!by_address(30).fast);
    assert_eq!(by_address(21).registers().get(INPUT, 4), Some(2150));
    assert_eq!(by_address(21).registers().get(INPUT, 8), Some(600));
    // The templates' "Serial" channel (input 270..271) reads the serial number.
    let relay = by_address(20).registers();
    assert_eq!(relay.read_range(INPUT, 270, 2), Some(vec![0xFE00, 0x0014]));
}
