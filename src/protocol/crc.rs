//! CRC16 as used by Modbus RTU: polynomial 0xA001 (reflected 0x8005), initial value 0xFFFF,
//! no final xor, sent low byte first.

const fn build_table() -> [u16; 256] {
    let mut table = [0u16; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = i as u16;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
}

static TABLE: [u16; 256] = build_table();

/// The Modbus CRC16 of `bytes`.
pub fn crc16(bytes: &[u8]) -> u16 {
    bytes.iter().fold(0xFFFF, |crc, &byte| {
        (crc >> 8) ^ TABLE[usize::from((crc ^ u16::from(byte)) & 0xFF)]
    })
}

/// Appends the CRC of everything in `frame` to it, low byte first.
pub fn append_crc(frame: &mut Vec<u8>) {
    let crc = crc16(frame);
    frame.extend_from_slice(&crc.to_le_bytes());
}

/// True when the last two bytes of `frame` are the CRC of the bytes before them.
pub fn crc_is_valid(frame: &[u8]) -> bool {
    match frame.len().checked_sub(2) {
        Some(body_len) if body_len > 0 => {
            let (body, crc) = frame.split_at(body_len);
            crc16(body).to_le_bytes() == crc
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        assert_eq!(
            crc16(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x01]).to_le_bytes(),
            [0x84, 0x0A]
        );
        assert_eq!(crc16(&[0xFD, 0x46, 0x01]).to_le_bytes(), [0x13, 0x90]);
    }

    #[test]
    fn validity() {
        assert!(crc_is_valid(&[0xFD, 0x46, 0x12, 0x52, 0x5D]));
        assert!(!crc_is_valid(&[0xFD, 0x46, 0x12, 0x52, 0x5E]));
        assert!(!crc_is_valid(&[0x52, 0x5D]));
        assert!(!crc_is_valid(&[]));
    }
}
