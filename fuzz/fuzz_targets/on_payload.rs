//! `/on` payload handling on arbitrary bytes, for every writable control of the shipped
//! templates: the planner's mapping to a write, then the device model's check (type, limits,
//! size, UTF-8) and encoding into register writes. Never a panic; an accepted payload is short, and its writes
//! stay inside the control's registers with coil values 0 or 1.
#![no_main]

use std::path::Path;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use libfuzzer_sys::fuzz_target;
use rtu2mqtt::config::TemplateFile;
use rtu2mqtt::gateway::device_model::DeviceModel;
use rtu2mqtt::device::{resolve_template_device, ResolvedDevice};
use rtu2mqtt::mqtt::{
    PlannerSettings, PublicationPlanner, TopicScheme, UnchangedPolicy, WriteOutcome,
};
use rtu2mqtt::protocol::RegisterType;
use rtu2mqtt::device_updates::{DeviceUpdate, Repeats};

const TEMPLATES: [&str; 6] = [
    "rtu2mqtt-relay6",
    "rtu2mqtt-dimmer",
    "rtu2mqtt-climate",
    "rtu2mqtt-counter8",
    "rtu2mqtt-energy-meter",
    "rtu2mqtt-generic",
];

struct Target {
    device: Arc<ResolvedDevice>,
    /// (control id, its `/on` topic) of every writable control.
    writable: Vec<(String, String)>,
}

fn targets() -> &'static Vec<Target> {
    static TARGETS: OnceLock<Vec<Target>> = OnceLock::new();
    TARGETS.get_or_init(|| {
        let topics = TopicScheme::new("", "rtu2mqtt").expect("default topics");
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../templates");
        TEMPLATES
            .iter()
            .enumerate()
            .filter_map(|(i, name)| {
                let file = TemplateFile::load(&dir.join(format!("{name}.json"))).ok()?;
                let slave_id = 10 + i as u64;
                let device =
                    resolve_template_device(&file, &serde_json::json!({ "slave_id": slave_id }))
                        .ok()?;
                let writable = device
                    .channels
                    .iter()
                    .filter(|c| !c.readonly)
                    .map(|c| (c.id.clone(), topics.control_on(&device.id, &c.id)))
                    .collect();
                Some(Target {
                    device: Arc::new(device),
                    writable,
                })
            })
            .collect()
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&selector, payload)) = data.split_first() else {
        return;
    };
    let targets = targets();
    let all: Vec<(&Target, &(String, String))> = targets
        .iter()
        .flat_map(|t| t.writable.iter().map(move |w| (t, w)))
        .collect();
    let Some(&(target, (control_id, on_topic))) = all.get(usize::from(selector) % all.len().max(1))
    else {
        return;
    };
    let mut planner = PublicationPlanner::new(PlannerSettings {
        topics: TopicScheme::new("", "rtu2mqtt").expect("default topics"),
        unchanged: UnchangedPolicy::OnChange,
        discovery: None,
        clear_discovery_on_exit: false,
    });
    planner.handle(
        DeviceUpdate::Added(Arc::clone(&target.device)),
        Instant::now(),
    );
    let write = match planner.on_message(on_topic, payload, false) {
        WriteOutcome::Accepted(write) => write,
        _ => return,
    };
    assert_eq!(&write.control_id, control_id);
    let model = DeviceModel::new(Arc::clone(&target.device), 0, Repeats::All);
    let Ok(writes) = model.write(&write.control_id, &write.payload) else {
        return;
    };
    assert!(write.payload.len() <= 4096, "accepted a long payload");
    let channel = target
        .device
        .channel(control_id)
        .expect("the control exists");
    for register_write in writes {
        let inside = channel
            .registers
            .iter()
            .filter_map(|r| r.write.or(r.read))
            .any(|r| {
                r.reg_type == register_write.register_type
                    && register_write.address >= r.address
                    && u32::from(register_write.address) + register_write.values.len() as u32
                        <= u32::from(r.address) + u32::from(r.count.max(1))
            });
        assert!(
            inside,
            "write outside the control's registers: {register_write:?}"
        );
        if register_write.register_type == RegisterType::Coil {
            assert!(
                register_write.values.iter().all(|&v| v <= 1),
                "coil value not 0/1"
            );
        }
    }
});
