//! A served device between its port and MQTT: the last word of every register read, each
//! control's error flags; port events in, [`DeviceUpdate`]s out; `/on` payloads in, register
//! writes out.

use std::collections::HashMap;
use std::sync::Arc;

use tracing::{debug, warn};

use crate::device::model::{ResolvedChannel, ResolvedDevice, WriteFunction};
use crate::device::Reading;
use crate::port::{PortEvent, RegisterSpan, RegisterWrite};
use crate::protocol::RegisterType;
use crate::updates::{DeviceUpdate, ErrorFlags};

#[derive(Debug)]
pub struct DeviceModel {
    pub device: Arc<ResolvedDevice>,
    /// This device's index on its port (the scheduler's device number).
    index: usize,
    words: HashMap<(RegisterType, u16), u16>,
    errors: Vec<ErrorFlags>,
}

/// Why a `/on` payload was not written.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WriteRejected {
    #[error("no control `{0}` on this device")]
    UnknownControl(String),
    #[error("control `{0}` is read-only")]
    ReadOnly(String),
    #[error("{0}")]
    BadValue(String),
}

impl DeviceModel {
    pub fn new(device: Arc<ResolvedDevice>, index: usize) -> Self {
        let errors = vec![ErrorFlags::default(); device.channels.len()];
        Self {
            device,
            index,
            words: HashMap::new(),
            errors,
        }
    }

    pub fn id(&self) -> &str {
        &self.device.id
    }

    /// Applies one port event about this device.
    pub fn apply(&mut self, event: PortEvent, out: &mut Vec<DeviceUpdate>) {
        match event {
            PortEvent::Values { span, values, .. } => {
                for (offset, value) in values.iter().enumerate() {
                    let address = span
                        .start
                        .wrapping_add(u16::try_from(offset).unwrap_or(u16::MAX));
                    self.words.insert((span.register_type, address), *value);
                }
                self.publish_channels(|register| spans_overlap(register, &span), false, out);
            }
            PortEvent::EventValue {
                register_type,
                address,
                payload,
                ..
            } => {
                let value = payload
                    .iter()
                    .rev()
                    .fold(0u64, |acc, &b| (acc << 8) | u64::from(b));
                let width = self
                    .device
                    .channels
                    .iter()
                    .flat_map(|c| c.registers.iter().filter_map(|r| r.read))
                    .find(|r| r.reg_type == register_type && r.address == address)
                    .map_or(1, |r| r.count.max(1));
                // Wider values arrive as one little-endian number; registers hold big-endian words.
                for i in 0..width {
                    let shift = 16 * u32::from(width - 1 - i);
                    let word = if shift >= 64 {
                        0
                    } else {
                        (value >> shift) as u16
                    };
                    self.words
                        .insert((register_type, address.wrapping_add(i)), word);
                }
                let span = RegisterSpan::new(register_type, address, width);
                self.publish_channels(|register| spans_overlap(register, &span), true, out);
            }
            PortEvent::ReadFailed {
                span, unsupported, ..
            } => {
                if unsupported {
                    debug!(device = %self.device.id, ?span, "register not supported by the device");
                }
                self.set_flags(|c| reads_span(c, &span), |flags| flags.read = true, out);
            }
            PortEvent::PeriodMissed { span, missed, .. } => {
                self.set_flags(
                    |c| reads_span(c, &span),
                    |flags| flags.period_missed = missed,
                    out,
                );
            }
            PortEvent::WriteDone {
                register_type,
                address,
                ..
            } => {
                self.set_flags(
                    |c| writes_register(c, register_type, address),
                    |flags| flags.write = false,
                    out,
                );
            }
            PortEvent::WriteFailed {
                register_type,
                address,
                ..
            } => {
                self.set_flags(
                    |c| writes_register(c, register_type, address),
                    |flags| flags.write = true,
                    out,
                );
            }
            PortEvent::Online { .. } => out.push(DeviceUpdate::Online {
                device_id: self.device.id.clone(),
                online: true,
            }),
            PortEvent::Offline { .. } => out.push(DeviceUpdate::Online {
                device_id: self.device.id.clone(),
                online: false,
            }),
            PortEvent::Rebooted { .. } => {}
        }
    }

    fn publish_channels(
        &mut self,
        touched: impl Fn(&crate::device::model::RegisterRef) -> bool,
        always_publish: bool,
        out: &mut Vec<DeviceUpdate>,
    ) {
        let device = Arc::clone(&self.device);
        for (index, channel) in device.channels.iter().enumerate() {
            if !channel
                .registers
                .iter()
                .filter_map(|r| r.read)
                .any(|r| touched(&r))
            {
                continue;
            }
            let Some(words) = self.channel_words(channel) else {
                continue;
            };
            let parts: Vec<&[u16]> = words.iter().map(Vec::as_slice).collect();
            let reading = channel.decode(&parts);
            let flags = self.errors.get(index).copied().unwrap_or_default();
            match reading {
                Ok(Reading::Value(value)) => {
                    // Clear `r` before the good value, as wb-mqtt-serial does.
                    if flags.read {
                        self.update_flags(
                            index,
                            ErrorFlags {
                                read: false,
                                ..flags
                            },
                            out,
                        );
                    }
                    out.push(DeviceUpdate::Value {
                        device_id: device.id.clone(),
                        control_id: channel.id.clone(),
                        value,
                        always_publish,
                    });
                }
                Ok(Reading::DeviceError | Reading::Unsupported) => {
                    self.update_flags(
                        index,
                        ErrorFlags {
                            read: true,
                            ..flags
                        },
                        out,
                    );
                }
                Err(err) => {
                    warn!(device = %device.id, control = %channel.id, %err, "cannot decode the value");
                    self.update_flags(
                        index,
                        ErrorFlags {
                            read: true,
                            ..flags
                        },
                        out,
                    );
                }
            }
        }
    }

    /// The words of every register of the channel, when all have been read.
    fn channel_words(&self, channel: &ResolvedChannel) -> Option<Vec<Vec<u16>>> {
        channel
            .registers
            .iter()
            .map(|register| {
                let read = register.read?;
                (0..read.count.max(1))
                    .map(|i| {
                        self.words
                            .get(&(read.reg_type, read.address.wrapping_add(i)))
                            .copied()
                    })
                    .collect::<Option<Vec<u16>>>()
            })
            .collect()
    }

    fn set_flags(
        &mut self,
        matches: impl Fn(&ResolvedChannel) -> bool,
        change: impl Fn(&mut ErrorFlags),
        out: &mut Vec<DeviceUpdate>,
    ) {
        let device = Arc::clone(&self.device);
        for (index, channel) in device.channels.iter().enumerate() {
            if matches(channel) {
                let mut flags = self.errors.get(index).copied().unwrap_or_default();
                change(&mut flags);
                self.update_flags(index, flags, out);
            }
        }
    }

    fn update_flags(&mut self, index: usize, flags: ErrorFlags, out: &mut Vec<DeviceUpdate>) {
        let Some(current) = self.errors.get_mut(index) else {
            return;
        };
        if *current == flags {
            return;
        }
        *current = flags;
        if let Some(channel) = self.device.channels.get(index) {
            out.push(DeviceUpdate::ControlError {
                device_id: self.device.id.clone(),
                control_id: channel.id.clone(),
                errors: flags,
            });
        }
    }

    /// The register writes for a `/on` payload, checked against the control's limits.
    pub fn write(
        &self,
        control_id: &str,
        payload: &str,
    ) -> Result<Vec<RegisterWrite>, WriteRejected> {
        let channel = self
            .device
            .channel(control_id)
            .ok_or_else(|| WriteRejected::UnknownControl(control_id.to_owned()))?;
        if channel.readonly {
            return Err(WriteRejected::ReadOnly(control_id.to_owned()));
        }
        let current: Vec<Option<Vec<u16>>> = channel
            .registers
            .iter()
            .map(|register| {
                let target = register.write.or(register.read)?;
                (0..target.count.max(1))
                    .map(|i| {
                        self.words
                            .get(&(target.reg_type, target.address.wrapping_add(i)))
                            .copied()
                    })
                    .collect()
            })
            .collect();
        let current_refs: Vec<Option<&[u16]>> = current.iter().map(|c| c.as_deref()).collect();
        let encoded = channel
            .encode(payload, &current_refs)
            .map_err(|err| WriteRejected::BadValue(err.to_string()))?;
        let mut writes = Vec::new();
        for (register, values) in channel.registers.iter().zip(encoded) {
            let Some(target) = register.write.or(register.read) else {
                continue;
            };
            if !target.reg_type.is_writable() {
                return Err(WriteRejected::ReadOnly(control_id.to_owned()));
            }
            if register.write_function == WriteFunction::Single && values.len() > 1 {
                for (i, value) in values.into_iter().enumerate() {
                    let address = target
                        .address
                        .wrapping_add(u16::try_from(i).unwrap_or(u16::MAX));
                    writes.push(RegisterWrite {
                        device: self.index,
                        register_type: target.reg_type,
                        address,
                        values: vec![value],
                        force_multiple: false,
                    });
                }
            } else {
                writes.push(RegisterWrite {
                    device: self.index,
                    register_type: target.reg_type,
                    address: target.address,
                    values,
                    force_multiple: register.write_function == WriteFunction::Multiple,
                });
            }
        }
        Ok(writes)
    }

    /// Marks `w` on a control after a rejected `/on` payload.
    pub fn write_rejected(&mut self, control_id: &str, out: &mut Vec<DeviceUpdate>) {
        self.set_flags(|c| c.id == control_id, |flags| flags.write = true, out);
    }
}

fn spans_overlap(register: &crate::device::model::RegisterRef, span: &RegisterSpan) -> bool {
    let start = u32::from(register.address);
    let end = start + u32::from(register.count.max(1));
    register.reg_type == span.register_type && start < span.end() && u32::from(span.start) < end
}

fn reads_span(channel: &ResolvedChannel, span: &RegisterSpan) -> bool {
    channel
        .registers
        .iter()
        .filter_map(|r| r.read)
        .any(|r| spans_overlap(&r, span))
}

fn writes_register(channel: &ResolvedChannel, register_type: RegisterType, address: u16) -> bool {
    channel
        .registers
        .iter()
        .filter_map(|r| r.write.or(r.read))
        .any(|r| r.reg_type == register_type && r.address == address)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TemplateFile;
    use crate::device::resolve_template_device;

    fn relay() -> DeviceModel {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("templates/rtu2mqtt-relay6.json");
        let template = TemplateFile::load(&path).unwrap();
        let device =
            resolve_template_device(&template, &serde_json::json!({"slave_id": 20})).unwrap();
        DeviceModel::new(Arc::new(device), 0)
    }

    fn values(out: &[DeviceUpdate]) -> Vec<(String, String, bool)> {
        out.iter()
            .filter_map(|u| match u {
                DeviceUpdate::Value {
                    control_id,
                    value,
                    always_publish,
                    ..
                } => Some((control_id.clone(), value.clone(), *always_publish)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn read_values_become_control_values() {
        let mut model = relay();
        let mut out = Vec::new();
        let span = RegisterSpan::new(RegisterType::Coil, 0, 2);
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![1, 0],
            },
            &mut out,
        );
        assert_eq!(
            values(&out),
            vec![
                ("K1".into(), "1".into(), false),
                ("K2".into(), "0".into(), false)
            ]
        );
        // u32 serial number, big-endian words.
        let mut out = Vec::new();
        let span = RegisterSpan::new(RegisterType::Input, 270, 2);
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![0xFE40, 0x00AC],
            },
            &mut out,
        );
        assert_eq!(
            values(&out),
            vec![("Serial".into(), "4265607340".into(), false)]
        );
    }

    #[test]
    fn event_values_are_always_published() {
        let mut model = relay();
        let mut out = Vec::new();
        let event = PortEvent::EventValue {
            device: 0,
            register_type: RegisterType::Input,
            address: 32,
            payload: vec![0x2C, 0x01],
        };
        model.apply(event, &mut out);
        assert_eq!(
            values(&out),
            vec![("Input 1 counter".into(), "300".into(), true)]
        );
    }

    #[test]
    fn read_error_is_cleared_before_the_next_value() {
        let mut model = relay();
        let span = RegisterSpan::new(RegisterType::Coil, 0, 1);
        let mut out = Vec::new();
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span,
                unsupported: false,
            },
            &mut out,
        );
        model.apply(
            PortEvent::ReadFailed {
                device: 0,
                span,
                unsupported: false,
            },
            &mut out,
        );
        model.apply(
            PortEvent::Values {
                device: 0,
                span,
                values: vec![1],
            },
            &mut out,
        );
        let kinds: Vec<String> = out
            .iter()
            .map(|u| match u {
                DeviceUpdate::ControlError {
                    control_id, errors, ..
                } => format!("{control_id} error '{errors}'"),
                DeviceUpdate::Value {
                    control_id, value, ..
                } => format!("{control_id} = {value}"),
                other => format!("{other:?}"),
            })
            .collect();
        assert_eq!(kinds, ["K1 error 'r'", "K1 error ''", "K1 = 1"]);
    }

    #[test]
    fn writes_are_encoded_and_checked() {
        let model = relay();
        assert_eq!(
            model.write("K3", "1"),
            Ok(vec![RegisterWrite {
                device: 0,
                register_type: RegisterType::Coil,
                address: 2,
                values: vec![1],
                force_multiple: false,
            }])
        );
        assert!(matches!(
            model.write("K3", "on"),
            Err(WriteRejected::BadValue(_))
        ));
        assert_eq!(
            model.write("Serial", "1"),
            Err(WriteRejected::ReadOnly("Serial".into()))
        );
        assert_eq!(
            model.write("nope", "1"),
            Err(WriteRejected::UnknownControl("nope".into()))
        );
    }
}
