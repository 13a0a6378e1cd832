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
/// The model's registers on firmware that has no longer model text.
const SHORT_MODEL_REGISTERS: u16 = 6;

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
    /// What was answered; a part refused (the device has no such register) or unanswered is
    /// `None`.
    pub identity: DeviceIdentity,
    pub serial: Option<u32>,
    /// The parts that got no answer (noise, a timeout, busy, a full queue, a stopped port):
    /// unknown, not absent. Their last known values stand, and the read is tried again.
    pub unanswered: Unanswered,
}

/// Which parts of an identity read got no answer.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Unanswered {
    pub serial: bool,
    pub model: bool,
    pub firmware: bool,
}

impl IdentityRead {
    /// A read that got no answer at all.
    pub fn nothing() -> Self {
        Self {
            unanswered: Unanswered {
                serial: true,
                model: true,
                firmware: true,
            },
            ..Self::default()
        }
    }

    /// Every part the plan names was answered, with values or a refusal.
    pub fn complete(&self) -> bool {
        self.unanswered == Unanswered::default()
    }

    /// `known` (what was read before) with what this read answered in its place.
    pub fn over(&self, known: &DeviceIdentity) -> DeviceIdentity {
        let pick = |unanswered: bool, new: &Option<String>, old: &Option<String>| {
            if unanswered { old } else { new }.clone()
        };
        DeviceIdentity {
            model: pick(self.unanswered.model, &self.identity.model, &known.model),
            serial_number: pick(
                self.unanswered.serial,
                &self.identity.serial_number,
                &known.serial_number,
            ),
            firmware: pick(
                self.unanswered.firmware,
                &self.identity.firmware,
                &known.firmware,
            ),
        }
    }
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

/// Reads what `plan` names through `queue`, at the port's own settings: each part on its own,
/// so that one that never answers (a register an old firmware ignores) does not keep the
/// others, the firmware that gates channels above all, from being read. What a device refuses
/// stays unknown; what gets no answer is marked so.
pub async fn read_identity(
    queue: &BusQueue,
    line: LineSettings,
    plan: &IdentityPlan,
) -> IdentityRead {
    let mut read = IdentityRead::default();
    if let Some((register_type, start, count)) = plan.serial {
        match read_words(queue, line, plan, register_type, start, count).await {
            Answer::Values(words) => {
                read.serial = serial_of(&words);
                read.identity.serial_number = read.serial.map(|s| s.to_string());
            }
            Answer::Refused => {}
            Answer::Nothing => read.unanswered.serial = true,
        }
    }
    if plan.texts {
        // Older firmware has the model in 6 registers only, and refuses a read of 20
        // (wb-mqtt-serial reads 6 after any error).
        let mut model =
            read_words(queue, line, plan, RegisterType::Holding, MODEL.0, MODEL.1).await;
        if matches!(model, Answer::Refused) {
            model = read_words(
                queue,
                line,
                plan,
                RegisterType::Holding,
                MODEL.0,
                SHORT_MODEL_REGISTERS,
            )
            .await;
        }
        match model {
            Answer::Values(words) => read.identity.model = standard_text(&words),
            Answer::Refused => {}
            Answer::Nothing => read.unanswered.model = true,
        }
        let (start, count) = FIRMWARE;
        match read_words(queue, line, plan, RegisterType::Holding, start, count).await {
            Answer::Values(words) => read.identity.firmware = standard_text(&words),
            Answer::Refused => {}
            Answer::Nothing => read.unanswered.firmware = true,
        }
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

    /// A read by (first register, count), and its answer: values or an exception.
    type ScriptedRead = ((u16, u16), Result<Vec<u16>, ExceptionCode>);

    /// A port that answers each read of `plan`'s device from `answers`, by the read's first
    /// register and count: values, an exception, or nothing when the read is not listed.
    /// Returns what the identity read got and the registers asked, in order.
    async fn read_from(
        plan: &IdentityPlan,
        answers: Vec<ScriptedRead>,
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
                let RequestBody::Classic(RequestPdu::ReadHoldingRegisters { start, count }) =
                    job.transaction.request.body
                else {
                    panic!("not a holding register read: {:?}", job.transaction.request);
                };
                asked.push(start);
                let outcome = match answers.iter().find(|(read, _)| *read == (start, count)) {
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
                (SERIAL, Ok(vec![0xFE00, 0x0099])),
                (MODEL, Ok(text("WBMR6C", MODEL.1))),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(read.complete());
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
                (SERIAL, Ok(vec![0xFE00, 0x0099])),
                (MODEL, Err(ExceptionCode::ILLEGAL_DATA_ADDRESS)),
                (
                    (MODEL.0, SHORT_MODEL_REGISTERS),
                    Err(ExceptionCode::ILLEGAL_DATA_ADDRESS),
                ),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, MODEL.0, FIRMWARE.0]);
        assert!(read.complete());
        assert_eq!(read.identity.model, None);
        assert_eq!(read.serial, Some(0xFE00_0099));
    }

    /// The serial number got no answer (noise, a loaded bus): not complete, marked unanswered
    /// (its last known value stands, and the read is tried again). Before, a model and firmware
    /// read without it were published as the whole identity, the serial number dropped and a
    /// replaced device never noticed. The other parts are still read: the firmware gates
    /// channels, and a register an old firmware never answers must not keep it unread.
    #[tokio::test]
    async fn a_part_that_got_no_answer_is_marked_and_the_others_read() {
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (MODEL, Ok(text("WBMR6C", MODEL.1))),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(!read.complete());
        assert_eq!(
            read.unanswered,
            Unanswered {
                serial: true,
                model: false,
                firmware: false
            }
        );
        assert_eq!(read.identity.firmware.as_deref(), Some("1.26.0"));
        let known = DeviceIdentity {
            model: Some("old".into()),
            serial_number: Some("4261412896".into()),
            firmware: Some("1.0".into()),
        };
        assert_eq!(
            read.over(&known),
            DeviceIdentity {
                model: Some("WBMR6C".into()),
                serial_number: Some("4261412896".into()),
                firmware: Some("1.26.0".into()),
            },
            "the serial number as known, the rest as read"
        );
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (SERIAL, Ok(vec![0xFE00, 0x0099])),
                (MODEL, Ok(text("WBMR6C", MODEL.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, FIRMWARE.0]);
        assert!(!read.complete(), "the firmware got no answer");
        assert!(read.unanswered.firmware);
        // Busy is no answer either: the device has the register, just not now.
        let (read, _) = read_from(
            &wb_plan(),
            vec![
                (SERIAL, Ok(vec![0xFE00, 0x0099])),
                (MODEL, Err(ExceptionCode::BUSY)),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert!(!read.complete(), "the model was busy");
        assert!(read.unanswered.model);
        // A device failure on the serial number every time: the firmware is read all the same.
        let (read, _) = read_from(
            &wb_plan(),
            vec![
                (SERIAL, Err(ExceptionCode::DEVICE_FAILURE)),
                (MODEL, Ok(text("WBMR6C", MODEL.1))),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(read.identity.firmware.as_deref(), Some("1.26.0"));
    }

    /// Older firmware has 6 registers of model text and refuses a read of 20: the 6 are read
    /// then, as wb-mqtt-serial reads them.
    #[tokio::test]
    async fn a_model_refused_as_20_registers_is_read_as_6() {
        let (read, asked) = read_from(
            &wb_plan(),
            vec![
                (SERIAL, Ok(vec![0xFE00, 0x0099])),
                (MODEL, Err(ExceptionCode::ILLEGAL_DATA_ADDRESS)),
                (
                    (MODEL.0, SHORT_MODEL_REGISTERS),
                    Ok(text("MR6C", SHORT_MODEL_REGISTERS)),
                ),
                (FIRMWARE, Ok(text("1.26.0", FIRMWARE.1))),
            ],
        )
        .await;
        assert_eq!(asked, [SERIAL.0, MODEL.0, MODEL.0, FIRMWARE.0]);
        assert!(read.complete());
        assert_eq!(read.identity.model.as_deref(), Some("MR6C"));
    }
}
