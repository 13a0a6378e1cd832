//! A Modbus TCP gateway in front of the virtual bus, sans-IO: MBAP frames in (`transaction id(2)
//! protocol 0(2) length(2) unit id(1) PDU`, no CRC), RTU frames onto the gateway's serial line
//! (unit id = slave address, CRC added), the reply heard on the line back into MBAP with the
//! transaction id echoed. A reply that does not come (or comes garbled) is answered as gateways do:
//! exception 0x0B, "gateway target device failed to respond".

use std::time::Duration;

use crate::protocol::crc::{append_crc, crc_is_valid};
use crate::protocol::parser::ARBITRATION_FILLER;

const HEADER_LEN: usize = 7;
/// Longest MBAP length field: unit id + a 253-byte PDU.
const MAX_LENGTH: usize = 254;
/// How long the gateway waits for the device after the request has left its serial port.
pub const GATEWAY_TIMEOUT: Duration = Duration::from_millis(300);
const GATEWAY_TARGET_FAILED: u8 = 0x0B;

/// One request as the gateway received it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MbapRequest {
    pub transaction_id: u16,
    pub unit: u8,
    /// Unit id, PDU, CRC: what goes onto the serial line.
    pub rtu_frame: Vec<u8>,
}

/// What was wrong with the bytes a client sent (a gateway closes such a connection).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MbapError {
    #[error("not Modbus TCP: protocol id {0} (must be 0)")]
    Protocol(u16),
    #[error("MBAP length {0} out of range 2..=254")]
    Length(usize),
}

/// Takes the first complete request off `buffer`: `Ok(None)` until one is complete.
pub fn take_request(buffer: &mut Vec<u8>) -> Result<Option<MbapRequest>, MbapError> {
    let Some(header) = buffer.get(..HEADER_LEN) else {
        return Ok(None);
    };
    let transaction_id = u16::from_be_bytes([header[0], header[1]]);
    let protocol_id = u16::from_be_bytes([header[2], header[3]]);
    let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
    let unit = header[6];
    if protocol_id != 0 {
        return Err(MbapError::Protocol(protocol_id));
    }
    if !(2..=MAX_LENGTH).contains(&length) {
        return Err(MbapError::Length(length));
    }
    let total = HEADER_LEN + length - 1;
    let Some(pdu) = buffer.get(HEADER_LEN..total) else {
        return Ok(None);
    };
    let mut rtu_frame = Vec::with_capacity(length + 2);
    rtu_frame.push(unit);
    rtu_frame.extend_from_slice(pdu);
    append_crc(&mut rtu_frame);
    buffer.drain(..total);
    Ok(Some(MbapRequest {
        transaction_id,
        unit,
        rtu_frame,
    }))
}

/// The MBAP reply to `request` given the bytes the gateway heard on its serial line. None for a
/// broadcast (unit 0): nobody answers one.
pub fn reply(request: &MbapRequest, heard: &[u8]) -> Option<Vec<u8>> {
    if request.unit == 0 {
        return None;
    }
    let frame = match heard.iter().position(|&b| b != ARBITRATION_FILLER) {
        Some(start) => heard.get(start..).unwrap_or(&[]),
        None => &[],
    };
    let (unit, pdu) = if frame.len() >= 4 && crc_is_valid(frame) {
        let pdu = frame.get(1..frame.len() - 2).unwrap_or(&[]);
        (frame.first().copied().unwrap_or(request.unit), pdu.to_vec())
    } else {
        let function = request.rtu_frame.get(1).copied().unwrap_or(0);
        (request.unit, vec![function | 0x80, GATEWAY_TARGET_FAILED])
    };
    let length = u16::try_from(pdu.len() + 1).unwrap_or(u16::MAX);
    let mut out = Vec::with_capacity(HEADER_LEN + pdu.len());
    out.extend_from_slice(&request.transaction_id.to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&length.to_be_bytes());
    out.push(unit);
    out.extend_from_slice(&pdu);
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::parse_hex;

    fn hex(text: &str) -> Vec<u8> {
        parse_hex(text).unwrap()
    }

    #[test]
    fn requests_are_cut_from_the_stream_and_get_a_crc() {
        let mut buffer = hex("12 34 00 00 00 06 14 03 00 80 00 01  00 07 00 00");
        let request = take_request(&mut buffer).unwrap().unwrap();
        assert_eq!(request.transaction_id, 0x1234);
        assert_eq!(request.rtu_frame, hex("14 03 00 80 00 01 87 27"));
        assert_eq!(buffer, hex("00 07 00 00"));
        assert_eq!(take_request(&mut buffer), Ok(None));
        let mut bad = hex("00 01 00 05 00 06 14 03 00 80 00 01");
        assert_eq!(take_request(&mut bad), Err(MbapError::Protocol(5)));
        let mut empty = hex("00 01 00 00 00 01 14");
        assert_eq!(take_request(&mut empty), Err(MbapError::Length(1)));
    }

    #[test]
    fn replies_echo_the_transaction_and_drop_the_crc() {
        let mut buffer = hex("12 34 00 00 00 06 14 03 00 80 00 01");
        let request = take_request(&mut buffer).unwrap().unwrap();
        assert_eq!(
            reply(&request, &hex("14 03 02 00 14 B5 88")),
            Some(hex("12 34 00 00 00 05 14 03 02 00 14"))
        );
        // Fillers before the frame are not part of it.
        assert_eq!(
            reply(&request, &hex("FF FF 14 03 02 00 14 B5 88")),
            Some(hex("12 34 00 00 00 05 14 03 02 00 14"))
        );
        // Silence or garbage: exception 0x0B from the gateway.
        let failed = Some(hex("12 34 00 00 00 03 14 83 0B"));
        assert_eq!(reply(&request, &[]), failed);
        assert_eq!(reply(&request, &hex("14 03 02 00 14 B5 77")), failed);
        let mut broadcast = hex("00 01 00 00 00 06 00 06 00 80 00 01");
        let broadcast = take_request(&mut broadcast).unwrap().unwrap();
        assert_eq!(reply(&broadcast, &[]), None);
    }
}
