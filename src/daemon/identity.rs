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
    /// Every register the plan names was answered, with values or an exception (a device
    /// that has no such register). A read that got nothing for one of them (noise, a timeout,
    /// a full queue, a stopped port) is not complete: what it has may be half of the truth
    /// (a model without the serial number of a device that replaced another), so it is not
    /// used, and the read is tried again.
    pub complete: bool,
}

/// How one register read of an identity went.
enum Answer {
    Values(Vec<u16>),
    /// Illegal function, address or value: the device has no such register, and asking again
    /// will not change that.
    Refused,
    /// Nothing that answers it: it may go better next time.
    Nothing,
}

/// The serial number of a register read: one word, or two big-endian words.
pub fn serial_of(words: &[u16]) -> Option<u32> {
    match words {
        [one] => Some(u32::from(*one)),
        [high, low] => Some((u32::from(*high) << 16) | u32::from(*low)),
        _ => None,
    }
}

/// Reads what `plan` names through `queue`, at the port's own settings. What a device refuses
/// stays unknown; the first register that gets no answer ends the read, not complete (an
/// offline device costs one timeout, not three).
pub async fn read_identity(
    queue: &BusQueue,
    line: LineSettings,
    plan: &IdentityPlan,
) -> IdentityRead {
    enum Part {
        Serial,
        Model,
        Firmware,
    }
    let mut parts = Vec::with_capacity(3);
    if let Some(serial) = plan.serial {
        parts.push((Part::Serial, serial));
    }
    if plan.texts {
        parts.push((Part::Model, (RegisterType::Holding, MODEL.0, MODEL.1)));
        parts.push((
            Part::Firmware,
            (RegisterType::Holding, FIRMWARE.0, FIRMWARE.1),
        ));
    }
    let mut read = IdentityRead::default();
    for (part, (register_type, start, count)) in parts {
        let words = match read_words(queue, line, plan, register_type, start, count).await {
            Answer::Values(words) => Some(words),
            Answer::Refused => None,
            Answer::Nothing => return read,
        };
        let words = words.as_deref();
        match part {
            Part::Serial => {
                read.serial = words.and_then(serial_of);
                read.identity.serial_number = read.serial.map(|s| s.to_string());
            }
            Part::Model => read.identity.model = words.and_then(standard_text),
            Part::Firmware => read.identity.firmware = words.and_then(standard_text),
        }
    }
    read.complete = true;
    read
}

async fn read_words(
    queue: &BusQueue,
    line: LineSettings,
    plan: &IdentityPlan,
    register_type: RegisterType,
    start: u16,
    count: u16,
) -> Answer {
    let pdu = match register_type {
        RegisterType::Input => RequestPdu::ReadInputRegisters { start, count },
        _ => RequestPdu::ReadHoldingRegisters { start, count },
    };
    let transaction = read_transaction(
        line,
        Request::classic(plan.address, pdu),
        plan.response_timeout,
    );
    match queue.transact(None, transaction).await {
        Ok(TransactionOutcome::Reply(Reply {
            address,
            body:
                ReplyBody::Classic(
                    ResponsePdu::ReadHoldingRegisters { values }
                    | ResponsePdu::ReadInputRegisters { values },
                ),
        })) if address == plan.address && values.len() == usize::from(count) => {
            Answer::Values(values)
        }
        Ok(TransactionOutcome::Reply(Reply {
            address,
            body: ReplyBody::Classic(ResponsePdu::Exception { code, .. }),
        })) if address == plan.address && code.is_permanent() => Answer::Refused,
        // Busy, a device failure, another reply, nothing at all: it may go better next time.
        _ => Answer::Nothing,
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
    use crate::protocol::ExceptionCode;

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

    /// A port that answers each read of `plan`'s device from `answers`, by the read's first
    /// register: values, an exception, or nothing when the register is not listed.
    /// Returns what the identity read got and the registers asked, in order.
    async fn read_from(
        plan: &IdentityPlan,
        answers: Vec<(u16, Result<Vec<u16>, ExceptionCode>)>,
    ) -> (IdentityRead, Vec<u16>) {
        use super::super::bus_queue::QueuedJob;
        use crate::protocol::RequestBody;
        let (queue, mut jobs) = BusQueue::new();
        let port = tokio::spawn(async move {
            let mut asked = Vec::new();
            while let Some(job) = jobs.recv().await {
                let QueuedJob::Transaction(job) = job else {
                    continue;
                };
                let RequestBody::Classic(RequestPdu::ReadHoldingRegisters { start, .. }) =
                    job.transaction.request.body
                else {
                    panic!("not a holding register read: {:?}", job.transaction.request);
                };
                asked.push(start);
                let outcome = match answers.iter().find(|(first, _)| *first == start) {
                    Some((_, Ok(values))) => TransactionOutcome::Reply(Reply {
                        address: job.transaction.request.address,
                        body: ReplyBody::Classic(ResponsePdu::ReadHoldingRegisters {
                            values: values.clone(),
                        }),
                    }),
                    Some((_, Err(code))) => TransactionOutcome::Reply(Reply {
                        address: job.transaction.request.address,
                        body: ReplyBody::Classic(ResponsePdu::Exception {
                            function: 3,
                            code: *code,
                        }),
                    }),
                    None => TransactionOutcome::NoReply,
                };
                let _ = job.reply.send(Ok(outcome));
            }
            asked
        });
        let read = read_identity(&queue, LineSettings::WIREN_BOARD_DEFAULT, plan).await;
        drop(queue);
        (read, port.await.unwrap())
    }

    fn wb_plan() -> IdentityPlan {
        IdentityPlan {
            address: 20,
            texts: true,
            serial: Some((RegisterType::Holding, SERIAL.0, SERIAL.1)),
            response_timeout: Duration::from_millis(100),
        }
    }

    /// Words of a standard text register block (one character per register, zero-padded).
    fn text(value: &str, registers: u16) -> Vec<u16> {
        let mut words: Vec<u16> = value.bytes().map(u16::from).collect();
        words.resize(usize::from(registers), 0);
        words
    }

    #[tokio::test]
    async fn an_identity_answered_in_full_is_complete() {
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (SERIAL.0, Ok(vec![0xFE00, 0x0099])),
                (MODEL.0, Ok(text("WBMR6C", MODEL.1))),
                (FIRMWARE.0, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(read.complete);
        assert_eq!(read.serial, Some(0xFE00_0099));
        assert_eq!(read.identity.serial_number.as_deref(), Some("4261413017"));
        assert_eq!(read.identity.model.as_deref(), Some("WBMR6C"));
        assert_eq!(read.identity.firmware.as_deref(), Some("1.26.0"));
    }

    /// A register the device refuses (it has none) is an answer: the read is complete without
    /// it, and not tried again for it.
    #[tokio::test]
    async fn a_refused_register_leaves_the_read_complete() {
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (SERIAL.0, Ok(vec![0xFE00, 0x0099])),
                (MODEL.0, Err(ExceptionCode::ILLEGAL_DATA_ADDRESS)),
                (FIRMWARE.0, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(read.complete);
        assert_eq!(read.identity.model, None);
        assert_eq!(read.serial, Some(0xFE00_0099));
    }

    /// The serial number got no answer (noise, a loaded bus): the read ends there, not
    /// complete. A model and firmware read without it would have been published as the whole
    /// identity, the serial number dropped and a replaced device never noticed.
    #[tokio::test]
    async fn a_register_that_got_no_answer_ends_the_read_incomplete() {
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (MODEL.0, Ok(text("WBMR6C", MODEL.1))),
                (FIRMWARE.0, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0], "an unanswered device costs one timeout");
        assert!(!read.complete);
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (SERIAL.0, Ok(vec![0xFE00, 0x0099])),
                (MODEL.0, Ok(text("WBMR6C", MODEL.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(!read.complete, "the firmware got no answer");
        // Busy is no answer either: the device has the register, just not now.
        let (read, _) = read_from(
            &wb_plan(),
            vec![
                (SERIAL.0, Ok(vec![0xFE00, 0x0099])),
                (MODEL.0, Err(ExceptionCode::BUSY)),
                (FIRMWARE.0, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert!(!read.complete, "the model was busy");
    }
}
