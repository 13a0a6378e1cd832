//! Who a device is: model, serial number and firmware version, read when it comes online or
//! reports a restart, from Wiren Board's standard registers (WB devices) or the template's
//! serial number channel. Published in the device meta and Home Assistant's device entry; a
//! serial number that changed at the same address means another device took its place.
//!
//! The reads go through the port's [`BusQueue`] like RPC requests, so they never hold the bus
//! longer than one transaction.

use std::time::Duration;

use super::bus_queue::BusQueue;
use crate::device::model::ResolvedDevice;
use crate::device_updates::DeviceIdentity;
use crate::port::{Transaction, TransactionOutcome};
use crate::protocol::timing::ADAPTER_LATENCY_ALLOWANCE;
use crate::protocol::{
    LineSettings, RegisterType, Reply, ReplyBody, Request, RequestPdu, ResponsePdu,
};
use crate::tools::values::standard_text;

/// Wiren Board's standard holding registers.
const MODEL: (u16, u16) = (200, 20);
const FIRMWARE: (u16, u16) = (250, 16);
const SERIAL: (u16, u16) = (270, 2);

/// The registers that tell who one device is, and how to ask it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IdentityPlan {
    pub address: u8,
    /// Holding registers with the model and firmware texts (WB devices).
    pub texts: bool,
    /// Where the serial number is: type, first register, count (1 or 2; big-endian words).
    pub serial: Option<(RegisterType, u16, u16)>,
    pub response_timeout: Duration,
}

/// What to read for `device`; `None` when neither the template nor the WB registers say who
/// it is. `response_lag`: what the port adds to every device's response timeout (a TCP
/// gateway's 500 ms, as for the device's polled reads).
pub fn identity_plan(device: &ResolvedDevice, response_lag: Duration) -> Option<IdentityPlan> {
    let template_serial = device
        .serial_number
        .as_ref()
        .and_then(|register| register.read)
        .filter(|r| !r.reg_type.is_bit() && (1..=2).contains(&r.count))
        .map(|r| (r.reg_type, r.address, r.count));
    let serial =
        template_serial.or(device
            .is_wb
            .then_some((RegisterType::Holding, SERIAL.0, SERIAL.1)));
    if !device.is_wb && serial.is_none() {
        return None;
    }
    Some(IdentityPlan {
        address: device.slave_id,
        texts: device.is_wb,
        serial,
        response_timeout: device.timing.response_timeout.saturating_add(response_lag),
    })
}

/// What a device said about itself; `serial` as a number, to notice a replacement.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct IdentityRead {
    pub identity: DeviceIdentity,
    pub serial: Option<u32>,
}

impl IdentityRead {
    pub fn is_empty(&self) -> bool {
        self.identity == DeviceIdentity::default()
    }
}

/// The serial number of a register read: one word, or two big-endian words.
pub fn serial_of(words: &[u16]) -> Option<u32> {
    match words {
        [one] => Some(u32::from(*one)),
        [high, low] => Some((u32::from(*high) << 16) | u32::from(*low)),
        _ => None,
    }
}

/// Reads what `plan` names through `queue`, at the port's own settings. What a device does not
/// answer stays unknown; a stopped port gives an empty read.
pub async fn read_identity(
    queue: &BusQueue,
    line: LineSettings,
    plan: &IdentityPlan,
) -> IdentityRead {
    let mut read = IdentityRead::default();
    if let Some((register_type, start, count)) = plan.serial {
        if let Some(words) = read_words(queue, line, plan, register_type, start, count).await {
            read.serial = serial_of(&words);
            read.identity.serial_number = read.serial.map(|s| s.to_string());
        }
    }
    if plan.texts {
        let (start, count) = MODEL;
        read.identity.model = read_words(queue, line, plan, RegisterType::Holding, start, count)
            .await
            .and_then(|words| standard_text(&words));
        let (start, count) = FIRMWARE;
        read.identity.firmware = read_words(queue, line, plan, RegisterType::Holding, start, count)
            .await
            .and_then(|words| standard_text(&words));
    }
    read
}

async fn read_words(
    queue: &BusQueue,
    line: LineSettings,
    plan: &IdentityPlan,
    register_type: RegisterType,
    start: u16,
    count: u16,
) -> Option<Vec<u16>> {
    let pdu = match register_type {
        RegisterType::Input => RequestPdu::ReadInputRegisters { start, count },
        _ => RequestPdu::ReadHoldingRegisters { start, count },
    };
    let transaction = read_transaction(
        line,
        Request::classic(plan.address, pdu),
        plan.response_timeout,
    );
    match queue.transact(None, transaction).await.ok()? {
        TransactionOutcome::Reply(Reply {
            address,
            body:
                ReplyBody::Classic(
                    ResponsePdu::ReadHoldingRegisters { values }
                    | ResponsePdu::ReadInputRegisters { values },
                ),
        }) if address == plan.address && values.len() == usize::from(count) => Some(values),
        _ => None,
    }
}

/// Timeouts of one read: the device's response timeout (at least 100 ms) and what a USB
/// adapter adds, then the whole reply.
fn read_transaction(
    line: LineSettings,
    request: Request,
    response_timeout: Duration,
) -> Transaction {
    let timeout = response_timeout.max(Duration::from_millis(100)) + ADAPTER_LATENCY_ALLOWANCE;
    Transaction::to_device(&line, request, timeout)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Behind a TCP gateway the identity reads wait the gateway's lag too, as the device's
    /// polled reads do: a WB device whose firmware was never read never gets its `fw` channels.
    #[test]
    fn identity_reads_behind_a_tcp_gateway_wait_its_lag() {
        use std::path::Path;
        let config = serde_json::json!({"ports": [{"port_type": "tcp", "address": "10.0.0.5",
            "port": 23, "devices": [{"device_type": "rtu2mqtt-relay6", "slave_id": 20}]}]});
        let loaded = crate::config::load::load_config_source(
            crate::config::parse::SourceText::from_text(Path::new("c.json"), &config.to_string()),
            false,
        )
        .unwrap();
        let library = crate::config::library::TemplateLibrary::load_dirs(&[Path::new(env!(
            "CARGO_MANIFEST_DIR"
        ))
        .join("templates")]);
        let port = crate::device::resolve_config(&loaded, &library)
            .unwrap()
            .remove(0);
        let plan = crate::gateway::port_plan::port_plan(&port, true);
        let device = &port.devices[0];
        let identity = identity_plan(device, plan.settings.response_lag).unwrap();
        assert_eq!(
            identity.response_timeout,
            device.timing.response_timeout + Duration::from_millis(500)
        );
    }

    #[test]
    fn serial_numbers_from_one_or_two_words() {
        assert_eq!(serial_of(&[0xFE00, 0x0020]), Some(0xFE00_0020));
        assert_eq!(serial_of(&[1234]), Some(1234));
        assert_eq!(serial_of(&[]), None);
        assert_eq!(serial_of(&[1, 2, 3]), None);
    }

    #[test]
    fn an_empty_read_is_empty() {
        assert!(IdentityRead::default().is_empty());
        let read = IdentityRead {
            identity: DeviceIdentity {
                firmware: Some("1.2".into()),
                ..DeviceIdentity::default()
            },
            serial: None,
        };
        assert!(!read.is_empty());
    }
}
