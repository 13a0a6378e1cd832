//! `config/Load`: the service's config file as wb-mqtt-serial hands it out, and the device types
//! of its template library. Other services read it: wb-mqtt-dali waits for this method to be
//! advertised before it starts and finds its WB-MDALI gateways in `config.ports[].devices[]`;
//! scripts list the templates from `types`. Pure, but for the files it is handed.

use std::collections::BTreeMap;

use serde_json::{json, Map, Value};

use crate::config::library::ListedTemplate;

/// wb-mqtt-serial's schema of the ports section, sent as `schema` when its package is installed.
pub const WB_PORTS_SCHEMA: &str = "/usr/share/wb-mqtt-serial/wb-mqtt-serial-ports.schema.json";
/// wb-mqtt-serial's translations of the template groups' names, used when installed.
pub const WB_GROUP_NAMES: &str = "/usr/share/wb-mqtt-serial/groups.json";

/// Sections of rtu2mqtt's own config that carry credentials (the broker's password, the status
/// page's password hash): never sent to every client of the broker. wb-mqtt-serial's config
/// has neither.
const PRIVATE_SECTIONS: [&str; 2] = ["mqtt", "http"];

const WB_GROUP: &str = "g-wb";
const WB_OLD_GROUP: &str = "g-wb-old";
const CUSTOM_GROUP: &str = "g-custom";

/// What the conversion needs of a device's template.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TemplateShape {
    /// The names of its channels.
    pub channels: Vec<String>,
    /// It has subdevices: its parameters go under `parameters`.
    pub subdevices: bool,
    /// The ids of its parameters (object form).
    pub parameters: Vec<String>,
}

impl TemplateShape {
    pub fn of(template: &Value) -> Self {
        let device = template.get("device").unwrap_or(&Value::Null);
        Self {
            channels: device
                .get("channels")
                .and_then(Value::as_array)
                .into_iter()
                .flatten()
                .filter_map(|channel| channel.get("name").and_then(Value::as_str))
                .map(str::to_owned)
                .collect(),
            subdevices: device.get("subdevices").is_some(),
            parameters: device
                .get("parameters")
                .and_then(Value::as_object)
                .into_iter()
                .flatten()
                .map(|(id, _)| id.clone())
                .collect(),
        }
    }
}

/// The `device_type`s of the config's devices.
pub fn device_types_used(root: &Value) -> Vec<&str> {
    root.get("ports")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .filter_map(|port| port.get("devices").and_then(Value::as_array))
        .flatten()
        .filter_map(|device| device.get("device_type").and_then(Value::as_str))
        .collect()
}

/// The config as wb-mqtt-serial's `MakeJsonForConfed` returns it: `poll_interval` renamed
/// `read_rate_limit_ms` (ports and devices), a device's `slave_id` as a string (left out when
/// empty), and of a device's channels only those its template declares or that carry their own
/// `address`/`consists_of`. `templates` has the shape of each device type's template (a
/// device whose template is not there is left as written). A template with subdevices also
/// gets its parameters moved under `parameters`; its channels are left as written
/// (wb-mqtt-serial regroups them for its editor, which rtu2mqtt does not serve).
pub fn config_for_clients(mut root: Value, templates: &BTreeMap<String, TemplateShape>) -> Value {
    if let Some(fields) = root.as_object_mut() {
        for section in PRIVATE_SECTIONS {
            fields.remove(section);
        }
    }
    let ports = root
        .get_mut("ports")
        .and_then(Value::as_array_mut)
        .into_iter()
        .flatten();
    for port in ports {
        rename_poll_interval(port);
        let devices = port
            .get_mut("devices")
            .and_then(Value::as_array_mut)
            .into_iter()
            .flatten();
        for device in devices {
            let Some(template) = device
                .get("device_type")
                .and_then(Value::as_str)
                .and_then(|device_type| templates.get(device_type))
            else {
                continue;
            };
            rename_poll_interval(device);
            let Some(fields) = device.as_object_mut() else {
                continue;
            };
            if template.subdevices {
                move_parameters(fields, template);
            } else {
                keep_known_channels(fields, template);
            }
            match fields.get("slave_id") {
                Some(Value::Number(number)) => {
                    let text = number.to_string();
                    fields.insert("slave_id".into(), Value::String(text));
                }
                Some(Value::String(text)) if text.is_empty() => {
                    fields.remove("slave_id");
                }
                _ => {}
            }
        }
    }
    root
}

fn rename_poll_interval(node: &mut Value) {
    let Some(fields) = node.as_object_mut() else {
        return;
    };
    if let Some(interval) = fields.remove("poll_interval") {
        fields.entry("read_rate_limit_ms").or_insert(interval);
    }
}

/// wb-mqtt-serial's `UpdateDeviceChannels`: channels of older templates, unknown to this one,
/// are dropped; the `channels` key goes when none is left.
fn keep_known_channels(device: &mut Map<String, Value>, template: &TemplateShape) {
    let Some(channels) = device.remove("channels") else {
        return;
    };
    let kept: Vec<Value> = channels
        .as_array()
        .into_iter()
        .flatten()
        .filter(|channel| {
            channel.get("address").is_some()
                || channel.get("consists_of").is_some()
                || channel
                    .get("name")
                    .and_then(Value::as_str)
                    .is_some_and(|name| template.channels.iter().any(|known| known == name))
        })
        .cloned()
        .collect();
    if !kept.is_empty() {
        device.insert("channels".into(), Value::Array(kept));
    }
}

/// Parameters the template declares (object form) move from the device into `parameters`.
fn move_parameters(device: &mut Map<String, Value>, template: &TemplateShape) {
    for id in &template.parameters {
        if let Some(value) = device.remove(id) {
            let parameters = device
                .entry("parameters")
                .or_insert_with(|| Value::Object(Map::new()));
            if let Some(parameters) = parameters.as_object_mut() {
                parameters.insert(id.clone(), value);
            }
        }
    }
}

/// `types`: the device types in groups, as wb-mqtt-serial's `GetDeviceTypes` orders them: the
/// Wiren Board group, the old Wiren Board group, then every other group by its (translated)
/// name, a template without a group in the custom group, which is always there (last when no
/// template is in it); within a group by title. `group_names` is wb-mqtt-serial's
/// `groups.json` (`{lang: {group: name}}`). wb-mqtt-serial also lists its protocols in the
/// custom group (`protocol:…`, for devices without a template); rtu2mqtt does not.
pub fn device_types(types: &[ListedTemplate], group_names: &Value, lang: &str) -> Value {
    let group_name = |group: &str| -> String {
        group_names
            .get(lang)
            .and_then(|names| names.get(group))
            .and_then(Value::as_str)
            .filter(|name| !name.is_empty())
            .unwrap_or(group)
            .to_owned()
    };
    let mut by_group: BTreeMap<&str, Vec<&ListedTemplate>> = BTreeMap::new();
    for listed in types {
        let group = match listed.listing.group.as_str() {
            "" => CUSTOM_GROUP,
            group => group,
        };
        by_group.entry(group).or_default().push(listed);
    }
    let type_json = |listed: &ListedTemplate| {
        let listing = &listed.listing;
        let mut entry = json!({
            "name": listing.title(lang, &listed.device_type),
            "deprecated": listed.deprecated,
            "type": listed.device_type,
            "protocol": listing.protocol,
            "mqtt-id": listing.mqtt_id,
        });
        if !listing.hardware.is_empty() {
            let hardware: Vec<Value> = listing
                .hardware
                .iter()
                .map(|(signature, fw)| match fw {
                    Some(fw) => json!({"signature": signature, "fw": fw}),
                    None => json!({"signature": signature}),
                })
                .collect();
            entry["hw"] = Value::Array(hardware);
        }
        entry
    };
    let group_json = |group: &str, members: Vec<&ListedTemplate>| {
        let mut members = members;
        members.sort_by(|a, b| {
            let a_title = a.listing.title(lang, &a.device_type);
            a_title.cmp(b.listing.title(lang, &b.device_type))
        });
        let types: Vec<Value> = members.into_iter().map(type_json).collect();
        json!({"name": group_name(group), "types": types})
    };
    let wb = by_group.remove(WB_GROUP).unwrap_or_default();
    let wb_old = by_group.remove(WB_OLD_GROUP).unwrap_or_default();
    let custom_missing = !by_group.contains_key(CUSTOM_GROUP);
    let mut others: Vec<Value> = by_group
        .into_iter()
        .map(|(group, members)| group_json(group, members))
        .collect();
    others.sort_by(|a, b| a["name"].as_str().cmp(&b["name"].as_str()));
    let mut groups = vec![group_json(WB_GROUP, wb), group_json(WB_OLD_GROUP, wb_old)];
    groups.extend(others);
    if custom_missing {
        groups.push(group_json(CUSTOM_GROUP, Vec::new()));
    }
    Value::Array(groups)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A library of these templates (a title, a group and an id each, and more given), as
    /// the list of device types sees it.
    fn library(templates: &[(&str, Value)]) -> Vec<ListedTemplate> {
        let mut library = crate::config::TemplateLibrary::default();
        for (device_type, extra) in templates {
            let mut template = json!({
                "device_type": device_type,
                "device": {"name": device_type, "id": device_type.to_lowercase(), "channels": []}
            });
            for (key, value) in extra.as_object().unwrap() {
                template[key] = value.clone();
            }
            let path = std::path::PathBuf::from(format!("config-{device_type}.json"));
            let source = crate::config::parse::SourceText::from_text(&path, &template.to_string());
            library.insert(crate::config::TemplateFile::from_source(source).unwrap());
        }
        library.listings()
    }

    #[test]
    fn the_config_reads_as_wb_mqtt_serial_hands_it_out() {
        let config = json!({
            "debug": false,
            "mqtt": {"host": "127.0.0.1", "password": "secret"},
            "http": {"listen": "0.0.0.0:8080", "user": "admin", "password_hash": "$2b$x"},
            "ports": [{
                "path": "/dev/ttyRS485-1", "poll_interval": 20,
                "devices": [
                    {"device_type": "WB-MDALI", "slave_id": 12, "poll_interval": 5,
                     "read_rate_limit_ms": 50, "bus_1_mode": 1,
                     "channels": [
                         {"name": "Bus 1 Status", "enabled": false},
                         {"name": "Gone from the template", "enabled": false},
                         {"name": "Own register", "address": 5, "reg_type": "holding"}
                     ]},
                    {"device_type": "WB-MDALI", "slave_id": "", "id": "dali_b",
                     "channels": [{"name": "Gone from the template"}]},
                    {"device_type": "no-such-template", "slave_id": 7, "poll_interval": 9},
                    {"device_type": "heater", "slave_id": "3", "mode": 2,
                     "channels": [{"name": "Anything"}]},
                    {"slave_id": 4, "protocol": "modbus", "channels": []}
                ]
            }]
        });
        assert_eq!(
            device_types_used(&config),
            ["WB-MDALI", "WB-MDALI", "no-such-template", "heater"]
        );
        let templates: BTreeMap<String, TemplateShape> = [
            (
                "WB-MDALI",
                json!({"device": {"channels": [{"name": "Bus 1 Status"}]}}),
            ),
            (
                "heater",
                json!({"device": {
                    "parameters": {"mode": {"address": 1}},
                    "subdevices": [],
                    "channels": []
                }}),
            ),
        ]
        .into_iter()
        .map(|(device_type, template)| (device_type.to_owned(), TemplateShape::of(&template)))
        .collect();
        let out = config_for_clients(config, &templates);
        assert_eq!(out.get("mqtt"), None, "credentials never go out");
        assert_eq!(out.get("http"), None);
        assert_eq!(out["debug"], false);
        let port = &out["ports"][0];
        assert_eq!(port["read_rate_limit_ms"], 20);
        assert_eq!(port.get("poll_interval"), None);
        let devices = port["devices"].as_array().unwrap();
        assert_eq!(
            devices[0],
            json!({"device_type": "WB-MDALI", "slave_id": "12", "read_rate_limit_ms": 50,
            "bus_1_mode": 1,
            "channels": [
                {"name": "Bus 1 Status", "enabled": false},
                {"name": "Own register", "address": 5, "reg_type": "holding"}
            ]})
        );
        assert_eq!(
            devices[1],
            json!({"device_type": "WB-MDALI", "id": "dali_b"})
        );
        // No template: as written.
        assert_eq!(
            devices[2],
            json!({"device_type": "no-such-template", "slave_id": 7, "poll_interval": 9})
        );
        assert_eq!(
            devices[3],
            json!({"device_type": "heater", "slave_id": "3", "parameters": {"mode": 2},
                   "channels": [{"name": "Anything"}]})
        );
        assert_eq!(
            devices[4],
            json!({"slave_id": 4, "protocol": "modbus", "channels": []})
        );
        // Anything else is no config, and is handed back as it is.
        assert_eq!(config_for_clients(json!([1]), &templates), json!([1]));
    }

    /// The `name` of each entry of a list.
    fn names(list: &Value) -> Vec<&str> {
        list.as_array()
            .unwrap()
            .iter()
            .map(|entry| entry["name"].as_str().unwrap())
            .collect()
    }

    #[test]
    fn device_types_are_grouped_and_ordered_as_wb_mqtt_serial_lists_them() {
        let types = library(&[
            ("zeta", json!({"title": "Zeta meter", "group": "g-meters"})),
            (
                "WB-MR6C",
                json!({"title": "WB-MR6C", "group": "g-wb",
                       "hw": [{"signature": "WBMR6C", "fw": "1.2.0"},
                              {"signature": "MR6C", "fw": ""}],
                       "device": {"name": "MR6C", "id": "wb-mr6c", "channels": [],
                                  "translations": {"ru": {"WB-MR6C": "Реле WB-MR6C"}}}}),
            ),
            (
                "WB-MAP3",
                json!({"title": "WB-MAP3 old", "group": "g-wb-old", "deprecated": true}),
            ),
            ("alpha", json!({"title": "Alpha"})),
            ("WB-MAI6", json!({"title": "WB-MAI6", "group": "g-wb"})),
            ("untitled", json!({})),
        ]);
        let group_names = json!({"ru": {"g-wb": "Wiren Board", "g-meters": "Счётчики"}});
        let listed = device_types(&types, &group_names, "en");
        assert_eq!(names(&listed), ["g-wb", "g-wb-old", "g-custom", "g-meters"]);
        assert_eq!(
            listed[0]["types"],
            json!([
                {"name": "WB-MAI6", "deprecated": false, "type": "WB-MAI6",
                 "protocol": "modbus", "mqtt-id": "wb-mai6"},
                {"name": "WB-MR6C", "deprecated": false, "type": "WB-MR6C",
                 "protocol": "modbus", "mqtt-id": "wb-mr6c",
                 "hw": [{"signature": "WBMR6C", "fw": "1.2.0"}, {"signature": "MR6C"}]}
            ])
        );
        assert_eq!(listed[1]["types"][0]["deprecated"], true);
        // No title: the device type names it (wb-mqtt-serial's GetTranslations gives an empty
        // title no translation, and GetTitle falls back to the type).
        assert_eq!(names(&listed[2]["types"]), ["Alpha", "untitled"]);
        // In Russian: translated titles and group names; the groups sorted by those.
        let listed = device_types(&types, &group_names, "ru");
        assert_eq!(
            names(&listed),
            ["Wiren Board", "g-wb-old", "g-custom", "Счётчики"]
        );
        assert_eq!(listed[0]["types"][1]["name"], "Реле WB-MR6C");
        assert_eq!(
            listed[0]["types"][0]["name"], "WB-MAI6",
            "English when not translated"
        );
        // The Wiren Board groups and the custom group are there even when empty, the custom
        // group last then.
        let meters: Vec<ListedTemplate> = types
            .iter()
            .filter(|listed| listed.device_type == "zeta")
            .cloned()
            .collect();
        assert_eq!(
            device_types(&meters, &Value::Null, "en"),
            json!([{"name": "g-wb", "types": []}, {"name": "g-wb-old", "types": []},
                   {"name": "g-meters", "types": [
                       {"name": "Zeta meter", "deprecated": false, "type": "zeta",
                        "protocol": "modbus", "mqtt-id": "zeta"}]},
                   {"name": "g-custom", "types": []}])
        );
    }
}
