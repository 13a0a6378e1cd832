"""Shared wire helpers of the independent Fast Modbus peers (fast_device.py, fast_master.py).

Written from shared/protocol/fast-modbus.md and tests/data/vectors.json only: nothing here
comes from rtu2mqtt's code. Section numbers (§) are those of fast-modbus.md.
"""

import math
import re

BROADCAST_FAST = 0xFD  # §1: "the reserved address 0xFD (253)"
FAST_FC = 0x46  # §2: function code of the extension
LEGACY_FAST_FC = 0x60  # §2: "deprecated but still appears in replies from old firmware"

SUB_SCAN_START = 0x01
SUB_SCAN_CONTINUE = 0x02
SUB_SCAN_REPLY = 0x03
SUB_SCAN_END = 0x04
SUB_BY_SERIAL = 0x08
SUB_BY_SERIAL_REPLY = 0x09
SUB_EVENTS_REQUEST = 0x10
SUB_EVENTS = 0x11
SUB_NO_EVENTS = 0x12
SUB_EVENTS_CONFIG = 0x18

# §6: event types
EV_COIL = 1
EV_DISCRETE = 2
EV_HOLDING = 3
EV_INPUT = 4
EV_SYSTEM = 15

TYPE_NAMES = {EV_COIL: "coil", EV_DISCRETE: "discrete", EV_HOLDING: "holding", EV_INPUT: "input", EV_SYSTEM: "system"}
TYPE_CODES = {name: code for code, name in TYPE_NAMES.items()}

# §3: arbitration markers
MARKER_SCAN_UNSCANNED = 0b0110
MARKER_SCAN_SCANNED = 0b1111
MARKER_EVENT_HIGH = 0b0100
MARKER_EVENT_LOW = 0b0110
MARKER_EVENT_NONE = 0b1111

SCAN_WINDOWS = 32  # §3 Timing: N = 32 for scan
EVENT_WINDOWS = 12  # N = 12 for events


def crc16(data):
    """§1: polynomial 0xA001 (reflected 0x8005), init 0xFFFF, no final xor."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            if crc & 1:
                crc = (crc >> 1) ^ 0xA001
            else:
                crc >>= 1
    return crc


def with_crc(body):
    body = bytes(body)
    crc = crc16(body)
    return body + bytes([crc & 0xFF, crc >> 8])  # low byte first


def crc_ok(frame):
    return len(frame) >= 4 and crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))


def hexs(data):
    return " ".join("%02X" % b for b in data)


class Line:
    """Port settings and the timing that follows from them (§1, §3 Timing)."""

    def __init__(self, text):
        match = re.fullmatch(r"\s*(\d+)\s+8([NEOneo])([12])\s*", text)
        if not match:
            raise ValueError("line settings like '9600 8N2' expected, got %r" % text)
        self.baud = int(match.group(1))
        self.parity = match.group(2).upper()
        self.stop_bits = int(match.group(3))
        self.bit = 1.0 / self.baud
        # §1: start + 8 data + optional parity + 1 or 2 stop bits.
        self.char_bits = 1 + 8 + (0 if self.parity == "N" else 1) + self.stop_bits
        self.char = self.char_bits * self.bit

    def __str__(self):
        return "%d 8%s%d" % (self.baud, self.parity, self.stop_bits)

    def ceil_bits(self, seconds):
        """A duration rounded up to whole bits, in bits."""
        return math.ceil(seconds * self.baud - 1e-9)

    def frame_gap(self):
        """§1: 3.5 characters of silence, fixed 1.75 ms above 19200 baud."""
        return 1.75e-3 if self.baud > 19200 else 3.5 * self.char

    def window(self):
        """§3 Timing: 12 bits plus a reserve of >= 50 us rounded up to whole bits, and at
        least 13 bits: max(13 bits, 12 bits + ceil_bits(50 us))."""
        return max(13, 12 + self.ceil_bits(50e-6)) * self.bit

    def device_wait(self):
        """§3 Timing, device side: 'wait before the first window: at least 3.5 characters and
        at least 800 us'. A device opens its first window at the smallest wait allowed: 800 us
        in whole bits (the article's 807 us at 115200), or 3.5 of its own characters when that
        is longer (4.01 ms at 9600 8N2)."""
        return max(3.5 * self.char, self.ceil_bits(800e-6) * self.bit)

    def master_wait(self):
        """§3 Timing, master side: the protocol formula's max(3.5 chars, 12 bits + 800 us)."""
        return max(3.5 * self.char, 12 * self.bit + 800e-6)

    def reply_timeout(self, windows):
        """§3: reply timeout = wait + window x N (the larger, protocol formula)."""
        return self.master_wait() + windows * self.window()


def arbitrate(contenders, bits):
    """§3: one window per bit of the arbitration word, MSB first; 0 is dominant (a 0xFF
    byte at the window's start), 1 is recessive (listen; hearing a byte = lost). Returns
    (windows with a 0xFF on the wire, the contenders still in at the end)."""
    active = list(contenders)
    filled = []
    for k in range(bits):
        shift = bits - 1 - k
        zeros = [c for c in active if not (c[0] >> shift) & 1]
        if zeros:
            filled.append(k)
            active = zeros
    return filled, active


def classic_request_length(data):
    """Length of a classic request frame (address + PDU + CRC) from its first bytes, or None
    while too short to tell; -1 for an unknown function (delimited by silence)."""
    if len(data) < 2:
        return None
    fc = data[1]
    if fc in (0x01, 0x02, 0x03, 0x04, 0x05, 0x06):
        return 8
    if fc in (0x0F, 0x10):
        if len(data) < 7:
            return None
        return 7 + data[6] + 2
    return -1


def request_pdu_length(pdu):
    """Length of a classic request PDU (fc + body) from its first bytes, None if too short,
    -1 when unknown."""
    if not pdu:
        return None
    fc = pdu[0]
    if fc in (0x01, 0x02, 0x03, 0x04, 0x05, 0x06):
        return 5
    if fc in (0x0F, 0x10):
        if len(pdu) < 6:
            return None
        return 6 + pdu[5]
    return -1


def reply_pdu_length(pdu):
    """Length of a classic reply PDU (fc + body), None if too short, -1 when unknown."""
    if not pdu:
        return None
    fc = pdu[0]
    if fc & 0x80:
        return 2
    if fc in (0x01, 0x02, 0x03, 0x04):
        if len(pdu) < 2:
            return None
        return 2 + pdu[1]
    if fc in (0x05, 0x06, 0x0F, 0x10):
        return 5
    return -1


def encode_event(ev_type, ev_id, payload):
    """§6: <payload_len(1)> <type(1)> <id(2, BE)> <payload(payload_len, little-endian)>."""
    return bytes([len(payload), ev_type, ev_id >> 8, ev_id & 0xFF]) + bytes(payload)


def decode_events(data):
    """Events of a 0x11 reply, parsed by data_len (§6: never trust event_count)."""
    events = []
    i = 0
    while i < len(data):
        if i + 4 > len(data):
            raise ValueError("truncated event header at %d" % i)
        plen, ev_type, ev_id = data[i], data[i + 1], (data[i + 2] << 8) | data[i + 3]
        payload = data[i + 4 : i + 4 + plen]
        if len(payload) != plen:
            raise ValueError("truncated event payload at %d" % i)
        value = int.from_bytes(payload, "little") if plen else None
        events.append(
            {
                "type": TYPE_NAMES.get(ev_type, ev_type),
                "type_code": ev_type,
                "id": ev_id,
                "payload": list(payload),
                "value": value,
            }
        )
        i += 4 + plen
    return events


def selftest(vectors_path):
    """Checks these helpers against tests/data/vectors.json and the arbitration table of §3.
    Prints one line per check; raises AssertionError on the first failure."""
    import json

    with open(vectors_path) as f:
        vectors = json.load(f)["vectors"]
    checks = 0
    for v in vectors:
        raw = bytes.fromhex(v["hex"].replace(" ", ""))
        frame = raw[v["leading_ff"] :]
        assert all(b == 0xFF for b in raw[: v["leading_ff"]]), v["name"]
        assert crc_ok(frame), "CRC of %s" % v["name"]
        assert with_crc(frame[:-2]) == frame, v["name"]
        m = v["meaning"]
        if m.get("sub") == SUB_EVENTS:
            events = decode_events(frame[6 : 6 + frame[5]])
            assert [(e["type_code"], e["id"], e["payload"]) for e in events] == [
                (e["type"], e["id"], e["payload"]) for e in m["events"]
            ], v["name"]
            rebuilt = b"".join(encode_event(e["type"], e["id"], bytes(e["payload"])) for e in m["events"])
            assert rebuilt == frame[6:-2], v["name"]
        checks += 1
    scan = lambda marker, sn: ((marker << 28) | (sn & 0x0FFFFFFF), sn)  # noqa: E731
    ev = lambda marker, addr: ((marker << 8) | addr, addr)  # noqa: E731
    mcm8, mr6c = 0xFE4000AC, 0xFED2A3A6
    table = [
        ([scan(0b0110, mcm8), scan(0b0110, mr6c)], 32, mcm8, 22),
        ([scan(0b1111, mcm8), scan(0b0110, mr6c)], 32, mr6c, 15),
        ([scan(0b1111, mcm8), scan(0b1111, mr6c)], 32, mcm8, 20),
        ([ev(0b0100, 241), ev(0b0110, 20)], 12, 241, 6),
        ([ev(0b1111, 241), ev(0b0110, 20)], 12, 20, 8),
        ([ev(0b1111, 241), ev(0b1111, 20)], 12, 20, 6),
    ]
    for contenders, bits, winner, fillers in table:
        filled, left = arbitrate(contenders, bits)
        assert len(filled) == fillers and [c[1] for c in left] == [winner], (contenders, filled, left)
        checks += 1
    fast = Line("115200 8N2")
    assert abs(fast.device_wait() - 807.29e-6) < 0.1e-6, fast.device_wait()
    assert abs(fast.window() - 156.25e-6) < 0.01e-6, fast.window()
    assert abs(fast.char - 95.5e-6) < 0.1e-6, fast.char
    assert abs(Line("9600 8N2").char - 1.146e-3) < 1e-6
    checks += 4
    print("ok %d" % checks)


if __name__ == "__main__":
    import sys

    selftest(sys.argv[1])
