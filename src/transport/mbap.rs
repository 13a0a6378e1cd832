//! Modbus TCP framing: `transaction id(2) protocol 0(2) length(2) unit id(1) PDU`, no CRC.
//! Requests are built as RTU frames by the protocol core and re-wrapped here; replies are decoded
//! from their unit id and PDU ([`Reply::decode_pdu`]): TCP checks the bytes, there is no CRC.

use crate::protocol::{DecodeError, Reply};

const HEADER_LEN: usize = 7;

#[derive(Debug, Default)]
pub struct MbapCodec {
    transaction_id: u16,
    received: Vec<u8>,
}

impl MbapCodec {
    /// The MBAP frame for an RTU frame (address, PDU, CRC). A new transaction id each time.
    pub fn wrap(&mut self, rtu_frame: &[u8]) -> Vec<u8> {
        self.transaction_id = self.transaction_id.wrapping_add(1);
        self.received.clear();
        let (unit, pdu) = match rtu_frame.split_first() {
            Some((&unit, rest)) => (
                unit,
                rest.get(..rest.len().saturating_sub(2)).unwrap_or(&[]),
            ),
            None => (0, &[][..]),
        };
        let length = u16::try_from(pdu.len() + 1).unwrap_or(u16::MAX);
        let mut out = Vec::with_capacity(HEADER_LEN + pdu.len());
        out.extend_from_slice(&self.transaction_id.to_be_bytes());
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&length.to_be_bytes());
        out.push(unit);
        out.extend_from_slice(pdu);
        out
    }

    /// Takes received bytes; returns every complete reply to the last request, decoded (replies
    /// to older transaction ids are dropped).
    pub fn unwrap(&mut self, bytes: &[u8]) -> Vec<Result<Reply, DecodeError>> {
        self.received.extend_from_slice(bytes);
        let mut replies = Vec::new();
        while let Some(header) = self.received.get(..HEADER_LEN) {
            let transaction_id = u16::from_be_bytes([header[0], header[1]]);
            let protocol_id = u16::from_be_bytes([header[2], header[3]]);
            let length = usize::from(u16::from_be_bytes([header[4], header[5]]));
            let unit = header[6];
            if protocol_id != 0 || length == 0 || length > 254 {
                // Not MBAP: resynchronise byte by byte.
                self.received.drain(..1);
                continue;
            }
            let total = HEADER_LEN + length - 1;
            let Some(pdu) = self.received.get(HEADER_LEN..total) else {
                break;
            };
            if transaction_id == self.transaction_id {
                replies.push(Reply::decode_pdu(unit, pdu));
            }
            self.received.drain(..total);
        }
        replies
    }

    /// True while part of a frame is buffered.
    pub fn has_partial_frame(&self) -> bool {
        !self.received.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{Reply, Request, RequestPdu, ResponsePdu};

    #[test]
    fn wraps_and_unwraps() {
        let mut codec = MbapCodec::default();
        let request = Request::classic(
            20,
            RequestPdu::ReadHoldingRegisters {
                start: 128,
                count: 1,
            },
        );
        let wire = codec.wrap(&request.encode().unwrap());
        assert_eq!(wire, vec![0, 1, 0, 0, 0, 6, 20, 3, 0, 128, 0, 1]);
        let reply = [0, 1, 0, 0, 0, 5, 20, 3, 2, 0, 20];
        // In two pieces, after a stale reply to transaction 0.
        let stale = [0, 0, 0, 0, 0, 5, 20, 3, 2, 0, 99];
        assert!(codec.unwrap(&stale).is_empty());
        assert!(codec.unwrap(&reply[..4]).is_empty());
        let replies = codec.unwrap(&reply[4..]);
        let expected = Reply::classic(20, ResponsePdu::ReadHoldingRegisters { values: vec![20] });
        assert_eq!(replies, vec![Ok(expected)]);
        assert!(!codec.has_partial_frame());
    }

    #[test]
    fn garbage_never_panics_and_yields_no_reply() {
        let mut codec = MbapCodec::default();
        codec.wrap(&[1, 3, 0, 0, 0, 1, 0, 0]);
        for len in 0..64u8 {
            let bytes: Vec<u8> = (0..len).map(|i| i.wrapping_mul(37)).collect();
            assert!(codec.unwrap(&bytes).is_empty());
        }
    }
}
