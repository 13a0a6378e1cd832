//! From a merged device (see `merge`) to the flat [`ResolvedDevice`]: register addresses with
//! subdevice shift and stride, codecs, control meta, event flags and setup writes.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use serde_json::Value;

use super::codec::ValueCodec;
use super::model::*;
use super::number_text::format_g;
use crate::config::config_file::PortConfig;
use crate::config::error::Problem;
use crate::config::format::RegisterFormat;
use crate::config::load::duration_problem;
use crate::config::template::{
    ChannelSpec, RegisterKind, SetupItemSpec, SetupValue, TemplateDevice,
};
use crate::config::values::{AddressSpec, MAX_BIT_SHIFT};

/// A resolve error with the `__origin` of the channel or setup item it concerns.
#[derive(Debug, Clone)]
pub struct ResolveError {
    pub origin: String,
    pub problem: Problem,
}

/// Something the resolver did differently from what a template says, as wb-mqtt-serial does it
/// (with the `__origin` of the channel or key it concerns).
#[derive(Debug, Clone)]
pub struct ResolveWarning {
    pub origin: String,
    pub message: String,
}

/// The largest subdevice or module shift: more moves every register off the 0…65535 map.
const MAX_SHIFT: u64 = 65_535;

/// Longest device id or channel name: they become MQTT topic levels, which a broker limits
/// (65,535 bytes per topic); real names are short.
pub const MAX_NAME_BYTES: usize = 200;

/// Why a device id or control id cannot be an MQTT topic level, if it cannot: `+` and `#` are
/// wildcards (a publish to them fails), `/` would move the value to another topic (a
/// read-only channel named `K2/on` would write K2), NUL is not allowed in topics.
pub fn topic_level_problem(what: &str, name: &str) -> Option<String> {
    let bad = name
        .chars()
        .find(|c| matches!(c, '+' | '#' | '/' | '\0'))
        .map(|c| {
            if c == '\0' {
                "NUL".to_string()
            } else {
                format!("`{c}`")
            }
        });
    if let Some(bad) = bad {
        return Some(format!(
            "{what} `{}` contains {bad}, which cannot be part of an MQTT topic; rename it (letters, digits, spaces, `-`, `_`, `(`, `)` are fine)",
            name.escape_debug()
        ));
    }
    if name.len() > MAX_NAME_BYTES {
        return Some(format!(
            "{what} is {} bytes long; at most {MAX_NAME_BYTES} bytes are allowed",
            name.len()
        ));
    }
    None
}

/// Channel names that also give the device's serial number register.
const SERIAL_NUMBER_NAMES: [&str; 3] = ["Serial", "serial_number", "Serial NO"];

/// Where addresses of the current (sub)device start, and how names are prefixed.
#[derive(Clone, Default)]
struct Context {
    base: i64,
    stride: u32,
    /// MQTT id prefix (subdevice slot ids or names), joined with a space.
    id_prefix: String,
    /// Title prefix per language.
    title_prefix: BTreeMap<String, String>,
}

/// Inputs besides the merged device.
pub struct ResolveInput<'a> {
    pub merged: &'a Value,
    pub port: &'a PortConfig,
    pub slave_id: u8,
    /// The module number of a `modbus_io` slave_id ("address:module").
    pub module: Option<i128>,
    pub is_wb_template: bool,
    pub hw: Vec<crate::config::template::HardwareSignature>,
    pub device_type: Option<String>,
}

/// What devices made from one template with the same overrides have in common, resolved once
/// and shared (see [`SharedVec`]): their channels, setup items and serial number register.
#[derive(Clone)]
struct SharedParts {
    channels: SharedVec<ResolvedChannel>,
    setup: SharedVec<SetupItem>,
    serial_number: Option<ChannelRegister>,
    /// Channels left out, reported for every device that uses these parts.
    warnings: Vec<ResolveWarning>,
}

/// The channels and setup already resolved while resolving one config, by [`shared_key`]: a bus of
/// 32 identical modules holds one copy of their channels, not 32.
#[derive(Default)]
pub struct SharedResolutions {
    by_key: HashMap<String, SharedParts>,
}

/// Keys of a merged device that differ from device to device without changing its channels or
/// setup: they are left out of [`shared_key`].
const PER_DEVICE_KEYS: [&str; 3] = ["id", "name", "slave_id"];

/// What the channels and setup of a device are made of: the merged device without its
/// per-device keys and without `__origin` (where each setting came from, for error messages:
/// two devices with the same overrides have them at different config paths), and the
/// `modbus_io` module (it shifts every address). Everything else stays in, so a setting that
/// differs always gives a device its own resolution.
fn shared_key(merged: &Value, module: Option<i128>) -> String {
    fn without_origins(value: &Value) -> Value {
        match value {
            Value::Object(map) => Value::Object(
                map.iter()
                    .filter(|(key, _)| key.as_str() != "__origin")
                    .map(|(key, value)| (key.clone(), without_origins(value)))
                    .collect(),
            ),
            Value::Array(items) => Value::Array(items.iter().map(without_origins).collect()),
            other => other.clone(),
        }
    }
    let mut parts = match without_origins(merged) {
        Value::Object(map) => map,
        _ => serde_json::Map::new(),
    };
    for key in PER_DEVICE_KEYS {
        parts.remove(key);
    }
    let module = module.map(|m| m.to_string()).unwrap_or_default();
    format!("{module}:{}", Value::Object(parts))
}

/// Resolves a merged device: its channels, setup and timing. Besides the device, returns
/// warnings: channels left out because their register cannot be built, enum titles not
/// published, as wb-mqtt-serial does.
pub fn resolve_device(
    input: &ResolveInput,
    shared: &mut SharedResolutions,
) -> Result<(ResolvedDevice, Vec<ResolveWarning>), Vec<ResolveError>> {
    let device: TemplateDevice = serde_json::from_value(input.merged.clone()).map_err(|err| {
        vec![ResolveError {
            origin: String::new(),
            problem: Problem::Invalid(format!("merged device: {err}")),
        }]
    })?;
    let mut duration_errors: Vec<ResolveError> = crate::config::device_durations!(&device)
        .into_iter()
        .filter_map(|(key, value)| duration_problem(key, value))
        .map(|problem| ResolveError {
            origin: String::new(),
            problem,
        })
        .collect();
    if !duration_errors.is_empty() {
        return Err(std::mem::take(&mut duration_errors));
    }
    let root = Context {
        base: match modbus_io_shift(&device, input.module) {
            Ok(shift) => shift,
            Err(problem) => {
                return Err(vec![ResolveError {
                    origin: String::new(),
                    problem,
                }])
            }
        },
        ..Context::default()
    };
    let key = shared_key(input.merged, input.module);
    let parts = match shared.by_key.get(&key) {
        Some(parts) => parts.clone(),
        None => {
            let parts = resolve_parts(&device, &root)?;
            shared.by_key.insert(key, parts.clone());
            parts
        }
    };
    let is_wb = input.is_wb_template || device.enable_wb_continuous_read == Some(true);
    let timing = timing(&device, input.port, is_wb);
    let device = ResolvedDevice {
        id: device.id.clone().unwrap_or_default(),
        name: device.name.clone().unwrap_or_default(),
        device_type: input.device_type.clone(),
        slave_id: input.slave_id,
        modbus_io: input.module.is_some(),
        is_wb,
        hw: input.hw.clone(),
        timing,
        channels: parts.channels,
        setup: parts.setup,
        serial_number: parts.serial_number,
    };
    Ok((device, parts.warnings))
}

/// Makes each bit-field setup item write its field over what the items before it wrote to
/// the same registers (zeros where nothing was), as wb-mqtt-serial composes them over its
/// register cache when it sets a device up: two parameters in one register
/// (`"100:0:4"`, `"100:4:4"`) both hold, where each written over zeros would undo the other.
/// And notes the bits no item so far defines ([`SetupItem::kept_bits`]): on a reconnect
/// wb-mqtt-serial's cache holds what polling last read of the register, and the scheduler
/// takes those bits from there as it does.
fn compose_bit_field_setup(setup: &mut [SetupItem]) {
    let mut written: BTreeMap<(RegisterType, u16), u16> = BTreeMap::new();
    let mut defined: BTreeMap<(RegisterType, u16), u16> = BTreeMap::new();
    for item in setup.iter_mut() {
        let register = item.register;
        let addresses: Vec<(RegisterType, u16)> = (0..item.codec.word_count)
            .map(|i| (register.reg_type, register.address.wrapping_add(i as u16)))
            .collect();
        if item.codec.is_partial() {
            let current: Vec<u16> = addresses
                .iter()
                .map(|at| written.get(at).copied().unwrap_or(0))
                .collect();
            if let Ok(words) = item.codec.encode(&item.value, Some(&current)) {
                item.words = words;
            }
        }
        for ((at, &word), mask) in addresses
            .iter()
            .zip(&item.words)
            .zip(item.codec.field_mask_words())
        {
            written.insert(*at, word);
            *defined.entry(*at).or_insert(0) |= mask;
        }
        item.kept_bits = addresses
            .iter()
            .map(|at| !defined.get(at).copied().unwrap_or(0))
            .collect();
        if item.kept_bits.iter().all(|&kept| kept == 0) {
            item.kept_bits.clear();
        }
    }
}

/// Channels, setup items and the serial number register of a merged device.
fn resolve_parts(
    device: &TemplateDevice,
    root: &Context,
) -> Result<SharedParts, Vec<ResolveError>> {
    let mut walker = Walker {
        translations: device.translations.clone().unwrap_or_default(),
        channels: Vec::new(),
        setup: Vec::new(),
        serial_number: None,
        errors: Vec::new(),
        warnings: Vec::new(),
    };
    walker.setup_items(device.setup.as_deref().unwrap_or(&[]), root);
    walker.channels(device.channels.as_deref().unwrap_or(&[]), root);
    if !walker.errors.is_empty() {
        return Err(walker.errors);
    }
    let mut setup = walker.setup;
    if device.preserve_setup_order != Some(true) {
        setup.sort_by_key(|s| {
            (
                s.register.reg_type,
                s.register.address,
                s.register.bit_shift,
            )
        });
    }
    let mut seen = std::collections::BTreeSet::new();
    setup.retain(|s| {
        let fresh = seen.insert((
            s.register.reg_type,
            s.register.address,
            s.register.bit_shift,
        ));
        if !fresh {
            tracing::warn!(
                "setup item `{}`: its register is already written by another item; skipped",
                s.title
            );
        }
        fresh
    });
    compose_bit_field_setup(&mut setup);
    let mut channels = walker.channels;
    for (i, channel) in channels.iter_mut().enumerate() {
        channel.order = i as u32 + 1;
    }
    Ok(SharedParts {
        channels: SharedVec::new(channels),
        setup: SharedVec::new(setup),
        serial_number: walker.serial_number,
        warnings: walker.warnings,
    })
}

fn ms(value: i64) -> Duration {
    Duration::from_millis(value.max(0) as u64)
}

/// The register shift of a `modbus_io` device (a WBIO module behind a WB-MIO, `slave_id`
/// "address:module"), as wb-mqtt-serial computes it: modules 1…4, 5…8 … share the 4 register
/// windows, so shift = ((module - 1) % 4 + 1) × the template's `stride` + its `shift`.
fn modbus_io_shift(device: &TemplateDevice, module: Option<i128>) -> Result<i64, Problem> {
    let is_modbus_io = device
        .protocol
        .as_deref()
        .is_some_and(|p| p.starts_with("modbus_io"));
    match (is_modbus_io, module) {
        (false, None) => Ok(0),
        (false, Some(_)) => Err(Problem::Invalid(
            "slave_id \"address:module\" is only for modbus_io templates (WBIO modules behind a WB-MIO); give the device's plain address".into(),
        )),
        (true, None) => Err(Problem::Invalid(
            "this is a modbus_io template (a WBIO module behind a WB-MIO): write slave_id as \"address:module\", e.g. \"1:2\" for the second module behind the WB-MIO at address 1".into(),
        )),
        (true, Some(module)) => {
            let window = i64::try_from((module - 1).rem_euclid(4) + 1).unwrap_or(1);
            let stride = device.stride.unwrap_or(0);
            let shift = i64::try_from(device.shift.map(|s| s.value()).unwrap_or(0)).ok();
            window
                .checked_mul(stride)
                .zip(shift)
                .and_then(|(a, b)| a.checked_add(b))
                .filter(|s| s.unsigned_abs() <= MAX_SHIFT)
                .ok_or_else(|| {
                    Problem::Invalid(format!(
                        "the module shift (stride {stride}, shift {:?}) is out of range",
                        device.shift.map(|s| s.value())
                    ))
                })
        }
    }
}

fn timing(device: &TemplateDevice, port: &PortConfig, is_wb: bool) -> DeviceTiming {
    let response = match (port.response_timeout_ms, device.response_timeout_ms) {
        (None, None) => 500,
        (p, d) => p.unwrap_or(-1).max(d.unwrap_or(-1)).max(0),
    };
    let frame = device
        .frame_timeout_ms
        .or(port.frame_timeout_ms)
        .filter(|v| *v >= 0)
        .unwrap_or(20);
    let guard = device
        .guard_interval_us
        .filter(|v| *v != 0)
        .or(port.guard_interval_us)
        .unwrap_or(0);
    let optional = |v: Option<i64>, default: i64| match v.unwrap_or(default) {
        n if n < 0 => None,
        n => Some(n),
    };
    let small = |v: Option<i64>, default: u16| {
        v.map(|n| n.clamp(0, i64::from(u16::MAX)) as u16)
            .unwrap_or(default)
    };
    let rate_limit = device
        .read_rate_limit_ms
        .or(device.poll_interval)
        .or(port.read_rate_limit_ms)
        .or(port.poll_interval);
    DeviceTiming {
        response_timeout: ms(response),
        frame_timeout: ms(frame),
        force_frame_timeout: device.force_frame_timeout.unwrap_or(false),
        guard_interval: Duration::from_micros(guard.max(0) as u64),
        min_request_interval: ms(device.min_request_interval.unwrap_or(0)),
        device_timeout: optional(device.device_timeout_ms, 3000).map(ms),
        device_max_fail_cycles: optional(device.device_max_fail_cycles, 2)
            .map(|n| n.min(i64::from(u32::MAX)) as u32),
        max_write_fail_time: Duration::from_secs(
            device.max_write_fail_time_s.unwrap_or(600).max(0) as u64,
        ),
        max_read_registers: small(device.max_read_registers, 1),
        min_read_registers: small(device.min_read_registers, 1),
        max_write_registers: small(device.max_write_registers, if is_wb { 123 } else { 1 }),
        max_reg_hole: small(device.max_reg_hole, 0),
        max_bit_hole: small(device.max_bit_hole, 0),
        enable_wb_continuous_read: device.enable_wb_continuous_read.unwrap_or(false),
        continue_polling_on_illegal_modbus_exception: device
            .continue_polling_on_illegal_modbus_exception
            .unwrap_or(false),
        read_rate_limit: rate_limit.filter(|v| *v >= 0).map(ms),
    }
}

struct Walker {
    translations: BTreeMap<String, BTreeMap<String, String>>,
    channels: Vec<ResolvedChannel>,
    setup: Vec<SetupItem>,
    serial_number: Option<ChannelRegister>,
    errors: Vec<ResolveError>,
    warnings: Vec<ResolveWarning>,
}

/// The register-describing fields shared by channels, `consists_of` entries and setup items.
struct RegisterFields<'a> {
    reg_type: Option<RegisterKind>,
    address: Option<AddressSpec>,
    write_address: Option<AddressSpec>,
    format: Option<RegisterFormat>,
    word_order: Option<crate::config::format::WordOrder>,
    byte_order: Option<crate::config::format::ByteOrder>,
    string_data_size: Option<u32>,
    scale: Option<f64>,
    offset: Option<f64>,
    round_to: Option<f64>,
    spec: Option<&'a ChannelSpec>,
}

impl<'a> RegisterFields<'a> {
    fn of_channel(spec: &'a ChannelSpec) -> Self {
        Self {
            reg_type: spec.reg_type,
            address: spec.address,
            write_address: spec.write_address,
            format: spec.format,
            word_order: spec.word_order,
            byte_order: spec.byte_order,
            string_data_size: spec.string_data_size,
            scale: spec.scale,
            offset: spec.offset,
            round_to: spec.round_to,
            spec: Some(spec),
        }
    }

    /// A `string`/`string8` format without a size: the register has no length, whatever its
    /// table (wb-mqtt-serial checks it before looking at coils).
    fn unloadable_string(&self) -> Option<Problem> {
        let format = self.format.filter(|f| f.is_string())?;
        if self.string_data_size.is_some_and(|size| size > 0) {
            return None;
        }
        Some(Problem::Invalid(format!(
            "format `{}` needs `string_data_size` (characters)",
            format.name()
        )))
    }

    /// An address whose bit shift is above what wb-mqtt-serial takes (`"5:300:1"`), with the
    /// key that gives it.
    fn oversized_bit_shift(&self) -> Option<(&'static str, Problem)> {
        [
            ("address", self.address),
            ("write_address", self.write_address),
        ]
        .into_iter()
        .find_map(|(key, address)| {
            let address = address.filter(|a| a.bit_shift > MAX_BIT_SHIFT)?;
            Some((
                key,
                Problem::Invalid(format!(
                    "bit shift {} in `{key}` is above {MAX_BIT_SHIFT}",
                    address.bit_shift
                )),
            ))
        })
    }

    /// An address whose bit shift is at or beyond the width of the value's format
    /// (`"400:16:8"` on a `u16`, a shift of 8 on a `u8`), with the key that gives it:
    /// wb-mqtt-serial's `TRegisterConfig` refuses it ("bit offset must not exceed 16 bits").
    /// Strings take no shift.
    fn shift_beyond_format(&self) -> Option<(&'static str, Problem)> {
        let reg_type = self.reg_type.unwrap_or(RegisterKind::Holding);
        let bit_table = matches!(reg_type, RegisterKind::Coil | RegisterKind::Discrete);
        let format = self.format.unwrap_or(if bit_table {
            RegisterFormat::U8
        } else {
            RegisterFormat::U16
        });
        if format.is_string() {
            return None;
        }
        let width = format.value_bits();
        [
            ("address", self.address),
            ("write_address", self.write_address),
        ]
        .into_iter()
        .find_map(|(key, address)| {
            let address = address.filter(|a| a.bit_shift >= width)?;
            Some((
                key,
                Problem::Invalid(format!(
                    "bit shift {} in `{key}` is not below the {width} bits of format `{}` \
                     (wb-mqtt-serial: \"bit offset must not exceed {width} bits\")",
                    address.bit_shift,
                    format.name()
                )),
            ))
        })
    }

    fn of_setup(item: &SetupItemSpec) -> RegisterFields<'static> {
        RegisterFields {
            reg_type: item.reg_type,
            address: item.address,
            write_address: item.write_address,
            format: item.format,
            word_order: item.word_order,
            byte_order: item.byte_order,
            string_data_size: None,
            scale: item.scale,
            offset: item.offset,
            round_to: None,
            spec: None,
        }
    }
}

impl Walker {
    fn error(&mut self, origin: &Option<String>, suffix: &str, problem: Problem) {
        let origin = origin.clone().unwrap_or_default();
        self.errors.push(ResolveError {
            origin: format!("{origin}{suffix}"),
            problem,
        });
    }

    fn channels(&mut self, specs: &[ChannelSpec], context: &Context) {
        for spec in specs {
            if spec.name.is_empty() {
                self.error(
                    &spec.origin,
                    "",
                    Problem::Invalid("a channel needs a `name`".into()),
                );
                continue;
            }
            let enabled = spec.enabled.unwrap_or(true) || spec.hidden == Some(true);
            if spec.device_type.is_none() && spec.one_of.is_some() {
                if spec.channels.is_some() || spec.setup.is_some() {
                    self.error(
                        &spec.origin,
                        "",
                        Problem::Invalid(format!(
                            "subdevice slot `{}` has no subdevice chosen, so its settings have nowhere to go; add \"device_type\": one of {}",
                            spec.name,
                            spec.one_of.as_deref().unwrap_or(&[]).join(", ")
                        )),
                    );
                }
                continue;
            }
            if spec.device_type.is_some() {
                if enabled {
                    self.subdevice(spec, context);
                }
                continue;
            }
            if SERIAL_NUMBER_NAMES.contains(&spec.name.as_str()) {
                if let Ok(register) = self.register(&RegisterFields::of_channel(spec), context) {
                    self.serial_number = Some(register);
                }
            }
            if enabled {
                self.simple_channel(spec, context);
            }
        }
    }

    fn subdevice(&mut self, slot: &ChannelSpec, context: &Context) {
        let id = slot.id.clone().unwrap_or_else(|| slot.name.clone());
        let shift = slot.shift.map(|s| s.value()).unwrap_or(0);
        // Checked: a huge `shift` must be an error, not a wrapped address.
        let Some(base) = i64::try_from(shift)
            .ok()
            .filter(|s| s.unsigned_abs() <= MAX_SHIFT)
            .and_then(|s| context.base.checked_add(s))
        else {
            self.error(
                &slot.origin,
                ".shift",
                Problem::Invalid(format!(
                    "shift {shift} is out of range: registers are 0…65535, so a shift is at most ±{MAX_SHIFT}"
                )),
            );
            return;
        };
        let mut inner = Context {
            base,
            stride: slot.stride.unwrap_or(0),
            id_prefix: join(&context.id_prefix, &id),
            title_prefix: context.title_prefix.clone(),
        };
        if slot.id.as_deref() != Some("") {
            for (lang, title) in self.title_map(&slot.name, context) {
                inner.title_prefix.insert(lang, title);
            }
        }
        self.setup_items(slot.setup.as_deref().unwrap_or(&[]), &inner);
        self.channels(slot.channels.as_deref().unwrap_or(&[]), &inner);
    }

    /// Title per language: the translation of `name` (English: the name itself), after the
    /// translated subdevice prefix.
    fn titles(&self, name: &str, context: &Context) -> Titles {
        self.title_map(name, context).into_iter().collect()
    }

    fn title_map(&self, name: &str, context: &Context) -> BTreeMap<String, String> {
        let mut out = BTreeMap::new();
        out.insert("en".to_string(), name.to_string());
        for (lang, table) in &self.translations {
            if let Some(text) = table.get(name) {
                out.insert(lang.clone(), text.clone());
            }
        }
        for lang in context.title_prefix.keys() {
            out.entry(lang.clone()).or_insert_with(|| name.to_string());
        }
        for (lang, title) in out.iter_mut() {
            let prefix = context
                .title_prefix
                .get(lang)
                .or_else(|| context.title_prefix.get("en"));
            if let Some(prefix) = prefix {
                *title = format!("{prefix} {title}");
            }
        }
        out
    }

    fn simple_channel(&mut self, spec: &ChannelSpec, context: &Context) {
        let mut registers = Vec::new();
        match &spec.consists_of {
            Some(parts) if !parts.is_empty() => {
                for (i, part) in parts.iter().enumerate() {
                    match self.register(&RegisterFields::of_channel(part), context) {
                        Ok(register) => registers.push(register),
                        Err(problem) => {
                            self.error(&spec.origin, &format!(".consists_of[{i}]"), problem)
                        }
                    }
                }
            }
            _ => {
                let fields = RegisterFields::of_channel(spec);
                // wb-mqtt-serial's `LoadSimpleChannel` (`src/serial_config.cpp`) catches what
                // `LoadRegisterConfig` throws for a channel's register, warns that the channel
                // "is ignored" and loads the rest of the device. Of what its config schema lets
                // through, that is a `string` without `string_data_size`; the parts of
                // `consists_of` and setup items are not caught there and stay errors here.
                if let Some(problem) = fields.unloadable_string() {
                    self.warnings.push(ResolveWarning {
                        origin: spec.origin.clone().unwrap_or_default(),
                        message: format!(
                            "channel `{}` is ignored, as wb-mqtt-serial ignores it: {problem}",
                            spec.name
                        ),
                    });
                    return;
                }
                // wb-mqtt-serial's `LoadRegisterBitsAddress` throws for a bit shift above 255
                // inside the same `try`, and `TRegisterConfig` for one at or beyond the format's
                // width, so such a channel is left out too.
                if let Some((key, problem)) = fields
                    .oversized_bit_shift()
                    .or_else(|| fields.shift_beyond_format())
                {
                    self.warnings.push(ResolveWarning {
                        origin: format!("{}.{key}", spec.origin.as_deref().unwrap_or_default()),
                        message: format!(
                            "channel `{}` is ignored, as wb-mqtt-serial ignores it: {problem}",
                            spec.name
                        ),
                    });
                    return;
                }
                match self.register(&fields, context) {
                    Ok(register) => registers.push(register),
                    Err(problem) => self.error(&spec.origin, "", problem),
                }
            }
        }
        if spec.consists_of.is_some() && (spec.on_value.is_some() || spec.off_value.is_some()) {
            // wb-mqtt-serial's `LoadSimpleChannel` takes them for a channel of one register
            // only, and refuses them on more ("on_value is allowed only for single-valued
            // controls").
            if registers.len() != 1 {
                let key = if spec.on_value.is_some() {
                    ".on_value"
                } else {
                    ".off_value"
                };
                self.error(
                    &spec.origin,
                    key,
                    Problem::Invalid(
                        "`on_value`/`off_value` are allowed only on a channel of one register"
                            .into(),
                    ),
                );
                return;
            }
            for register in &mut registers {
                register.codec.on_value = spec.on_value.map(|v| v.value());
                register.codec.off_value = spec.off_value.map(|v| v.value());
            }
        }
        let Some(first) = registers.first() else {
            return;
        };
        let first_kind = spec
            .consists_of
            .as_ref()
            .and_then(|p| p.first())
            .and_then(|p| p.reg_type)
            .or(spec.reg_type);
        let default_type = match first_kind.unwrap_or(RegisterKind::Holding) {
            RegisterKind::Coil | RegisterKind::Discrete => "switch",
            _ => "value",
        };
        let mut control_type = spec
            .control_type
            .clone()
            .unwrap_or_else(|| default_type.to_string());
        let mut write_only = first.read.is_none();
        if control_type == "wo-switch" || control_type == "pushbutton" {
            write_only = true;
            if control_type == "wo-switch" {
                control_type = "switch".to_string();
            }
        }
        if write_only {
            for register in &mut registers {
                register.read = None;
            }
        }
        let readonly = registers.iter().any(|r| r.write.is_none());
        let mut max = spec.max.map(|m| m.0);
        if max.is_none() && (control_type == "range" || control_type == "dimmer") {
            max = Some(65535.0);
        }
        let events = if spec.sporadic == Some(true) {
            EventMode::Sporadic
        } else if spec.semi_sporadic == Some(true) {
            EventMode::SemiSporadic
        } else {
            EventMode::Polled
        };
        let enum_titles = self.enum_titles(spec, context);
        let id = join(&context.id_prefix, spec.id.as_deref().unwrap_or(&spec.name));
        if let Some(message) = topic_level_problem("channel name", &id) {
            self.error(&spec.origin, "", Problem::Invalid(message));
            return;
        }
        if let Some(period) = spec.read_period_ms {
            if let Some(problem) = duration_problem("read_period_ms", period) {
                self.error(&spec.origin, ".read_period_ms", problem);
                return;
            }
        }
        let round_to = spec.round_to.filter(|r| *r > 0.0);
        self.channels.push(ResolvedChannel {
            title: self.titles(&spec.name, context),
            id,
            name: spec.name.clone(),
            registers,
            control_type,
            units: spec.units.clone(),
            min: spec.min.map(|m| m.0),
            max,
            precision: if spec.consists_of.is_some() {
                None
            } else {
                round_to
            },
            readonly,
            write_only,
            order: 0,
            enum_titles,
            events,
            read_period: spec.read_period_ms.filter(|v| *v >= 0).map(ms),
            read_rate_limit: spec
                .read_rate_limit_ms
                .or(spec.poll_interval)
                .filter(|v| *v >= 0)
                .map(ms),
            fw: spec.fw.clone(),
            hidden: spec.hidden.unwrap_or(false),
            group: spec.group.clone(),
        });
    }

    fn enum_titles(&mut self, spec: &ChannelSpec, context: &Context) -> Vec<EnumTitle> {
        let (Some(values), Some(titles)) = (&spec.enum_values, &spec.enum_titles) else {
            return Vec::new();
        };
        if values.len() != titles.len() {
            // wb-mqtt-serial's `LoadSimpleChannel` pairs them only when the lengths agree and
            // otherwise warns and publishes no titles: pairing by position would title values
            // with the wrong words if one list lost an entry in the middle.
            self.warnings.push(ResolveWarning {
                origin: format!("{}.enum_titles", spec.origin.as_deref().unwrap_or_default()),
                message: format!(
                    "channel `{}`: `enum` has {} values and `enum_titles` {} titles; no titles are published, as wb-mqtt-serial publishes none",
                    spec.name,
                    values.len(),
                    titles.len()
                ),
            });
            return Vec::new();
        }
        // wb-mqtt-serial translates enum titles with the channel's context
        // (`Translate(title, true, context)` in `LoadSimpleChannel`), so inside a subdevice
        // they carry its name as a prefix ("Boiler On"), as the channel's title does, and the
        // control's meta publishes them so (`TSerialPortDriver`, `SetEnumValueTitles`).
        values
            .iter()
            .zip(titles)
            .map(|(value, title)| EnumTitle {
                value: match value {
                    Value::String(text) => text.clone(),
                    // `1.0` is the value published as `1` (values are written with %.15g).
                    Value::Number(number) if number.is_f64() => {
                        format_g(number.as_f64().unwrap_or_default(), 15)
                    }
                    other => other.to_string(),
                },
                title: self.titles(title, context),
            })
            .collect()
    }

    fn setup_items(&mut self, items: &[SetupItemSpec], context: &Context) {
        for item in items {
            let fields = RegisterFields::of_setup(item);
            let register = match self.register(&fields, context) {
                Ok(register) => register,
                Err(problem) => {
                    self.error(&item.origin, "", problem);
                    continue;
                }
            };
            let Some(target) = register.write.or(register.read) else {
                continue;
            };
            if !matches!(target.reg_type, RegisterType::Holding | RegisterType::Coil) {
                self.warnings.push(ResolveWarning {
                    origin: item.origin.clone().unwrap_or_default(),
                    message: format!(
                        "a setup item on {} cannot be written (only holding registers and coils \
                         can): it is left out",
                        match target.reg_type {
                            RegisterType::Input => "an input register",
                            _ => "a discrete input",
                        }
                    ),
                });
                continue;
            }
            let value = match &item.value {
                Some(SetupValue::Number(n)) => format_g(*n, 15),
                Some(SetupValue::Text(text)) => text.clone(),
                None => {
                    self.error(
                        &item.origin,
                        "",
                        Problem::Invalid("a setup item needs `value`".into()),
                    );
                    continue;
                }
            };
            let current = vec![0u16; register.codec.word_count as usize];
            match register.codec.encode(&value, Some(&current)) {
                Ok(words) => self.setup.push(SetupItem {
                    title: join_title(
                        &context.id_prefix,
                        item.title.as_deref().unwrap_or("<unnamed>"),
                    ),
                    register: target,
                    write_function: register.write_function,
                    value,
                    words,
                    kept_bits: Vec::new(),
                    codec: register.codec,
                    parameter_id: item.id.clone(),
                }),
                Err(err) => self.error(
                    &item.origin,
                    "",
                    Problem::Invalid(format!("setup value: {err}")),
                ),
            }
        }
    }

    /// Resolves one register value: table, addresses (with shift and stride), codec.
    fn register(
        &self,
        fields: &RegisterFields,
        context: &Context,
    ) -> Result<ChannelRegister, Problem> {
        let kind = fields.reg_type.unwrap_or(RegisterKind::Holding);
        let reg_type = match kind {
            RegisterKind::Coil => RegisterType::Coil,
            RegisterKind::Discrete => RegisterType::DiscreteInput,
            RegisterKind::Input | RegisterKind::PressCounter => RegisterType::Input,
            _ => RegisterType::Holding,
        };
        let format = fields.format.unwrap_or(if reg_type.is_bit() {
            RegisterFormat::U8
        } else {
            RegisterFormat::U16
        });
        let read_address = fields.address.filter(|a| a.register.is_some());
        let write_address = fields.write_address.filter(|a| a.register.is_some());
        let Some(layout_address) = read_address.or(write_address) else {
            return Err(Problem::Invalid(
                "needs `address` (or `write_address` for a write-only channel)".into(),
            ));
        };
        if let Some((_, problem)) = fields
            .oversized_bit_shift()
            .or_else(|| fields.shift_beyond_format())
        {
            return Err(problem);
        }
        let mut codec = ValueCodec::plain(format);
        codec.word_order = fields.word_order.unwrap_or_default();
        codec.byte_order = fields.byte_order.unwrap_or_default();
        codec.scale = fields.scale.unwrap_or(1.0);
        codec.offset = fields.offset.unwrap_or(0.0);
        codec.round_to = fields.round_to.unwrap_or(0.0);
        if reg_type.is_bit() {
            codec = ValueCodec {
                scale: codec.scale,
                offset: codec.offset,
                round_to: codec.round_to,
                ..ValueCodec::bit()
            };
        } else if format.is_string() {
            let Some(size) = fields.string_data_size.filter(|s| *s > 0) else {
                return Err(Problem::Invalid(format!(
                    "format `{}` needs `string_data_size` (characters)",
                    format.name()
                )));
            };
            // `string_data_size` registers for both formats: wb-mqtt-serial takes it as a
            // width of `size × 8` bits and reads `GetDataWidth() / 8` registers of a string
            // (`TRegisterConfig::Get16BitWidth`), one character in each for `string` and two for
            // `string8`, so a `string8` of size N shows up to 2N characters.
            codec.word_count = size;
            codec.bit_width = size.saturating_mul(8);
        } else {
            codec.bit_shift = layout_address.bit_shift;
            if let Some(width) = layout_address.bit_width {
                codec.bit_width = width;
            }
            codec.word_count = format
                .registers()
                .max((codec.bit_shift + codec.bit_width).div_ceil(16))
                .max(1);
            if codec.word_count > 4 || codec.bit_shift + codec.bit_width > 64 {
                return Err(Problem::Invalid(format!(
                    "bit field {}:{} does not fit a 64-bit value",
                    codec.bit_shift, codec.bit_width
                )));
            }
        }
        if let Some(spec) = fields.spec {
            let mask = if codec.bit_width >= 64 {
                u64::MAX
            } else {
                (1u64 << codec.bit_width) - 1
            };
            // Compared with the field as read, whole: a marker wider than the field (32-bit
            // markers on narrower fields, as some library templates give) never matches, as in
            // wb-mqtt-serial (`TRegister::SetValue` compares the raw values); cut to the field's
            // width it would take a real reading (70000 on 16 bits is 4464) for an error.
            let raw = |v: Option<crate::config::values::SerialInt>| v.map(|v| v.value() as u64);
            // wb-mqtt-serial rejects these unless they are raw register content: not negative
            // and not wider than the value (at least 32 bits are accepted, as its schema
            // allows).
            let widest = mask.max(u64::from(u32::MAX));
            for (key, value) in [
                ("error_value", spec.error_value),
                ("unsupported_value", spec.unsupported_value),
            ] {
                if let Some(value) = value.map(|v| v.value()) {
                    if value < 0 || value > i128::from(widest) {
                        return Err(Problem::Invalid(format!(
                            "{key} {value} is not raw register content of this {}-bit value: give \
                             the raw words as read, 0…{widest} ({widest:#X}; wider than the value, \
                             it never matches)",
                            codec.bit_width
                        )));
                    }
                }
            }
            codec.error_value = raw(spec.error_value);
            codec.unsupported_value = raw(spec.unsupported_value);
            // Not masked: wb-mqtt-serial compares and writes them in the channel's units.
            codec.on_value = spec.on_value.map(|v| v.value());
            codec.off_value = spec.off_value.map(|v| v.value());
        }
        let byte_width = if format.is_string() {
            2
        } else {
            format.registers().max(1) * 2
        };
        // Checked arithmetic throughout: a huge address, shift or stride in a config must be an
        // error, never an address that wrapped around to a valid-looking register.
        let stride_offset = context
            .stride
            .checked_mul(byte_width)
            .map(|v| i64::from(v.div_ceil(2)))
            .ok_or_else(|| {
                Problem::Invalid(format!("stride {} is out of range", context.stride))
            })?;
        let count = codec.word_count;
        let place = |spec: AddressSpec| -> Result<RegisterRef, Problem> {
            let register = spec.register.unwrap_or(0);
            let address = context
                .base
                .checked_add(register)
                .and_then(|a| a.checked_add(stride_offset))
                .ok_or(Problem::AddressOutOfRange {
                    address: register,
                    count,
                })?;
            let last = address.checked_add(i64::from(count) - 1);
            if address < 0 || last.is_none_or(|last| last > 65535) {
                return Err(Problem::AddressOutOfRange { address, count });
            }
            Ok(RegisterRef {
                reg_type,
                address: address as u16,
                count: count as u16,
                bit_shift: codec.bit_shift,
                bit_width: codec.bit_width,
            })
        };
        let read = read_address.map(place).transpose()?;
        let spec_readonly = fields
            .spec
            .is_some_and(|s| s.readonly == Some(true) || s.channel_readonly == Some(true));
        let forced_readonly = matches!(
            kind,
            RegisterKind::Input | RegisterKind::Discrete | RegisterKind::PressCounter
        );
        let write = if forced_readonly || spec_readonly {
            None
        } else {
            write_address.or(read_address).map(place).transpose()?
        };
        Ok(ChannelRegister {
            read,
            write,
            write_function: match kind {
                RegisterKind::HoldingSingle => WriteFunction::Single,
                RegisterKind::HoldingMulti => WriteFunction::Multiple,
                _ => WriteFunction::Auto,
            },
            codec,
            press_counter: kind == RegisterKind::PressCounter,
        })
    }
}

fn join(prefix: &str, name: &str) -> String {
    match (prefix.is_empty(), name.is_empty()) {
        (true, _) => name.to_string(),
        (false, true) => prefix.to_string(),
        (false, false) => format!("{prefix} {name}"),
    }
}

fn join_title(prefix: &str, title: &str) -> String {
    join(prefix, title)
}
