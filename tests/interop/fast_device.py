#!/usr/bin/python3
"""An independent bus of 1-3 Fast Modbus devices on one serial port (a pty).

Written from shared/protocol/fast-modbus.md (§ numbers below) and tests/data/vectors.json only,
as another team would, to check rtu2mqtt against it. Needs python3-serial (pyserial).

    fast_device.py --port /tmp/ttyA --line "9600 8N2" \
        --device 20:0xFE4000AC:WBMCM8 --device 241:0xFED2A3A6:WBMR6C

Each device has coils, discrete inputs, holding and input registers 0..99 (all of them can send
events once a master enables them with 0x18) and the Wiren Board standard registers of §5.

stdin: JSON lines, one command each, e.g.
    {"id": 1, "cmd": "set", "device": 20, "type": "holding", "address": 3, "value": 77}
    {"id": 2, "cmd": "toggle", "device": 20, "type": "discrete", "address": 0}
    {"id": 3, "cmd": "get", "device": 20, "type": "coil", "address": 1}
    {"id": 4, "cmd": "reboot", "device": 20}
    {"id": 5, "cmd": "state", "device": 20}      (event settings, pending events, flag)
    {"id": 6, "cmd": "stats"}                     (timing: how late the bytes went out)
    {"id": 7, "cmd": "batch", "commands": [{…}, {…}]}   (several changes at one instant)
    {"id": 8, "cmd": "lose_ack", "device": 20, "then_set": {"type": "holding", "address": 4, "value": 1}}
        (test fault: the next confirmation for device 20 is not heard; the change in then_set
        is made at that moment, so the packet sent again under the same flag carries it too)
Options: --legacy-code ADDRESS (that device is old firmware: its Fast Modbus replies carry the
deprecated code 0x60, §2), --no-events ADDRESS:TYPE:REG (that register cannot send events: its
bit stays 0 in the 0x18 reply, §6), --count-pending ADDRESS (event_count = every event the
device holds, also those that did not fit the packet). Devices may share an address: each
answers, and the replies collide (wired AND), as on a real pair. --wide
ADDRESS:TYPE:REG:WORDS[:little]: a value over WORDS registers (word order big, or little): one
event at REG carries the whole value as a little-endian number; without it every register is
an event source of its own (2-byte payloads). --registers-only ADDRESS: that device refuses a
0x18 with a range of another type than the four register tables (exception 3).
--deaf-when-excluded ADDRESS: that device reads nothing of a 0x10 whose min_address excludes it
(the other reading of §3), its confirmation included. --refuses-events ADDRESS: that device
answers every 0x18 with exception 1 under its own reply code ("events_refused" in the log).
"device" is the Modbus address or {"serial": N}. Replies: {"id":…, "ok": true, …}.
stdout also carries the log, one JSON object a line with a "log" key: "rx" (every frame heard,
hex), "tx" (every reply, hex with its 0xFF fillers), "confirmed" (a 0x11 packet confirmed),
"events_config" (a 0x18 request taken), "reboot". The first line is {"ready": …}.

Timing (§3): the first arbitration window opens device_wait() after the end of the request
(max(3.5 characters, 800 us in whole bits)); windows last max(13 bits, 12 bits + 50 us in
whole bits). Each 0xFF filler is written at its window's start and each byte of a frame at its
own character time, by busy-waiting on time.monotonic(). Python on a loaded machine is
sometimes late: a late byte goes out as soon as possible (the schedule is absolute, so the
lateness does not add up), which keeps the whole reply inside the reply timeout whenever the
lateness stays below the master's margin; "stats" reports the worst lateness seen. With
--realtime (SCHED_FIFO, root) the bytes keep their windows (tens of µs late at 115200).

Where the document is ambiguous, this device chose (docs/reliability.md, "Independent peers"):
- a request ends when its bytes make a complete request of a known layout with a good CRC, or
  at 3.5 characters of silence; it ended on the wire its length in characters after its first
  byte arrived (a pty delivers a frame at once);
- the wait before the first window counts 3.5 of the line's own characters (11 bits at 8N2);
- the first packet after power-on carries flag 0; a count-only packet is confirmed like any;
- event_count is the events carried (all held with --count-pending); max_data_len limits
  data_len; events go high priority first, the reboot event last;
- every register is an event source of its own unless --wide makes a value of several;
- every device takes the confirmation of every 0x10, min_address or not (but with
  --deaf-when-excluded);
- the reboot event (type 15, id 0) is accepted in 0x18 ranges (refused: --registers-only).
"""

import argparse
import gc
import json
import os
import select
import sys
import time

import serial

sys.dont_write_bytecode = True  # no __pycache__ beside the scripts
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fastmodbus_common import *  # noqa: E402,F401,F403
from fastmodbus_common import Line, arbitrate, classic_request_length, request_pdu_length, with_crc, crc_ok, hexs, encode_event  # noqa: E402

GENERIC = range(0, 100)  # registers 0..99 of every table


def out(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


class ModbusException(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class Device:
    def __init__(self, address, serial_number, model, firmware, line):
        self.address = address
        self.serial = serial_number
        self.model = model
        self.firmware = firmware
        self.line = line
        self.tables = {t: {a: 0 for a in GENERIC} for t in ("coil", "discrete", "holding", "input")}
        self.scanned = False
        # Old firmware (§2): its Fast Modbus replies carry the deprecated code 0x60.
        self.legacy_code = False
        # Registers that cannot send events: their bit stays 0 in the 0x18 reply (§6).
        self.no_events = set()
        # event_count of a 0x11 packet: the events in it, or (count_pending) all it holds (§6:
        # "never trust event_count to equal the number of parsed events").
        self.count_pending = False
        # Wide values (§6: "more for wide values"): base register -> (words, word order). One
        # event at the base register carries the whole value, little-endian; the other
        # registers of the value are no event sources of their own.
        self.wide = {}
        # A stricter reading of 0x18 ("<reg_type(1)>", "Priority per register"): a range of any
        # other type than the four register tables is refused with exception 3.
        self.registers_only = False
        # Test fault: the next confirmation for this device is lost (not heard); `lost_then`
        # is a change made at that moment, which the re-sent packet then carries as well.
        self.lose_ack = False
        self.lost_then = None
        # The other reading of §3 (min_address "excludes devices below it"): this device reads
        # nothing of a 0x10 that excludes it, its confirmation included.
        self.deaf_when_excluded = False
        # A device without events that answers 0x18 with exception 1 under its own reply code
        # (0xE0 for old firmware, §2).
        self.refuses_events = False
        self.power_on()

    def power_on(self):
        """§6 Reboot handling: event settings back at their defaults (all off but the reboot
        event), the reboot event pending."""
        self.enabled = {}  # (type code, id) -> priority 1 low / 2 high
        self.reboot_event_enabled = True
        self.pending = {}  # (type code, id) -> [priority, seq]
        self.seq = 0
        self.next_flag = 0  # the first packet after power-on carries flag 0 (seed trace)
        self.unconfirmed = None  # (flag, {key: seq}) of the last packet sent
        self.pending[(EV_SYSTEM, 0)] = [1, self.bump()]

    def bump(self):
        self.seq += 1
        return self.seq

    def reply_fc(self, request_fc):
        return LEGACY_FAST_FC if self.legacy_code else request_fc

    # ---- registers ----
    def standard_holding(self, reg):
        """§5 standard Wiren Board holding registers; None when reg is not one of them."""
        if reg == 110:
            return self.line.baud // 100
        if reg == 111:
            return {"N": 0, "O": 1, "E": 2}[self.line.parity]
        if reg == 112:
            return self.line.stop_bits
        if reg == 128:
            return self.address
        if 200 <= reg <= 219:
            return text_reg(self.model, reg - 200)
        if 250 <= reg <= 265:
            return text_reg(self.firmware, reg - 250)
        if reg == 270:
            return self.serial >> 16
        if reg == 271:
            return self.serial & 0xFFFF
        if 290 <= reg <= 301:
            return text_reg(self.model, reg - 290)
        return None

    def read(self, table, reg):
        if reg in GENERIC:
            return self.tables[table][reg]
        if table == "holding" or (table == "input" and reg in (270, 271)):
            value = self.standard_holding(reg)
            if value is not None:
                return value
        raise ModbusException(2)

    def write(self, table, reg, value, origin):
        """A master's write (origin "master") or the physical world (origin "control")."""
        if reg in GENERIC:
            self.set_value(table, reg, value)
            return None
        if table == "holding" and origin == "master":
            if reg == 128:
                if not 1 <= value <= 247:
                    raise ModbusException(3)
                return ("address", value)  # takes effect after the reply
            if reg in (110, 111, 112):
                return None  # accepted, kept at the bus's settings (one line per bus here)
        raise ModbusException(2)

    def wide_base(self, table, reg):
        for (t, base), (words, _) in self.wide.items():
            if t == table and base <= reg < base + words:
                return base
        return None

    def set_value(self, table, reg, value):
        old = self.tables[table][reg]
        self.tables[table][reg] = value
        base = self.wide_base(table, reg)
        key = (TYPE_CODES[table], reg if base is None else base)
        if old != value and key in self.enabled:
            # §6: a change of a register whose events are enabled is kept until confirmed.
            self.pending[key] = [self.enabled[key], self.bump()]

    # ---- events (§6) ----
    def event_marker(self):
        if any(p == 2 for p, _ in self.pending.values()):
            return MARKER_EVENT_HIGH
        if self.pending:
            return MARKER_EVENT_LOW
        return MARKER_EVENT_NONE

    def take_ack(self, ack_address, ack_flag):
        """§6 Acknowledgement: the master confirms a packet by putting this device's address
        and that flag into the next 0x10 request; only then are those events dropped."""
        if self.unconfirmed is None or ack_address != self.address:
            return None
        flag, sent = self.unconfirmed
        if ack_flag != flag:
            return None
        if self.lose_ack:
            self.lose_ack = False
            if self.lost_then:
                table, reg, value = self.lost_then
                self.set_value(table, reg, value)
                self.lost_then = None
            return "lost"
        for key, seq in sent.items():
            entry = self.pending.get(key)
            if entry is not None and entry[1] == seq:  # unchanged since sent
                del self.pending[key]
        self.unconfirmed = None
        self.next_flag = flag ^ 1
        return flag

    def event_payload(self, key):
        ev_type, ev_id = key
        if ev_type == EV_SYSTEM:
            return b""
        table = TYPE_NAMES[ev_type]
        value = self.tables[table][ev_id]
        if ev_type in (EV_COIL, EV_DISCRETE):
            return bytes([value & 0xFF])
        wide = self.wide.get((table, ev_id))
        if wide:
            words, order = wide
            regs = [self.tables[table][ev_id + i] for i in range(words)]
            if order == "little":
                regs.reverse()
            number = 0
            for word in regs:
                number = (number << 16) | word
            return number.to_bytes(2 * words, "little")  # the value, little-endian
        return (value & 0xFFFF).to_bytes(2, "little")

    def build_packet(self, max_data_len, fc=FAST_FC):
        """The 0x11 reply. An unconfirmed packet is sent again under its flag, with newer
        events added; events that do not fit max_data_len wait for the next round; if not
        even one fits, the count goes with no payload."""
        flag = self.unconfirmed[0] if self.unconfirmed is not None else self.next_flag
        keys = sorted(self.pending, key=lambda k: (-self.pending[k][0], k[0] == EV_SYSTEM, k))
        data = b""
        sent = {}
        for key in keys:
            event = encode_event(key[0], key[1], self.event_payload(key))
            if len(data) + len(event) > max_data_len:
                continue
            data += event
            sent[key] = self.pending[key][1]
        count = len(sent) if sent and not self.count_pending else len(keys)
        self.unconfirmed = (flag, sent)
        body = bytes([self.address, self.reply_fc(fc), SUB_EVENTS, flag, count, len(data)]) + data
        return with_crc(body), flag, sent

    def configure_events(self, ranges):
        """§6 0x18: priority per register, 0 disabled; one bitmask per range, LSB first."""
        masks = []
        for ev_type, start, priorities in ranges:
            bits = 0
            for i, priority in enumerate(priorities):
                reg = start + i
                key = (ev_type, reg)
                supported = (ev_type in (EV_COIL, EV_DISCRETE, EV_HOLDING, EV_INPUT) and reg in GENERIC and key not in self.no_events) or key == (EV_SYSTEM, 0)
                if supported and ev_type in (EV_HOLDING, EV_INPUT):
                    base = self.wide_base(TYPE_NAMES[ev_type], reg)
                    supported = base is None or base == reg
                if not supported:
                    continue
                if key == (EV_SYSTEM, 0):
                    self.reboot_event_enabled = priority > 0
                    if priority == 0:
                        self.pending.pop(key, None)
                elif priority == 0:
                    self.enabled.pop(key, None)
                    self.pending.pop(key, None)
                else:
                    self.enabled[key] = min(priority, 2)
                if priority > 0:
                    bits |= 1 << i
            masks.append(bits.to_bytes((len(priorities) + 7) // 8, "little"))
        return masks

    def state(self):
        return {
            "address": self.address,
            "serial": self.serial,
            "enabled": sorted([TYPE_NAMES[t], a, p] for (t, a), p in self.enabled.items()),
            "pending": sorted([TYPE_NAMES[t], a] for (t, a) in self.pending),
            "next_flag": self.next_flag,
            "unconfirmed": None if self.unconfirmed is None else self.unconfirmed[0],
            "scanned": self.scanned,
        }


def collide(frames):
    """Several drivers on the pair at once: a 0 bit from any of them wins (wired AND); the
    longer frame's tail goes out alone."""
    merged = bytearray(max(len(f) for f in frames))
    for i in range(len(merged)):
        byte = 0xFF
        for f in frames:
            if i < len(f):
                byte &= f[i]
        merged[i] = byte
    return bytes(merged)


def text_reg(text, index):
    """§5: one ASCII character per register, zero padded."""
    return ord(text[index]) if index < len(text) else 0


def classic(device, pdu, broadcast=False):
    """A classic request PDU (fc + body) → reply PDU. Raises ModbusException."""
    fc = pdu[0]
    after = []
    if fc in (0x01, 0x02, 0x03, 0x04):
        if len(pdu) != 5:
            raise ModbusException(3)
        start, count = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        limit = 2000 if fc in (0x01, 0x02) else 125  # §1 read limits
        if not 1 <= count <= limit:
            raise ModbusException(3)
        table = {1: "coil", 2: "discrete", 3: "holding", 4: "input"}[fc]
        values = [device.read(table, start + i) for i in range(count)]
        if fc in (0x01, 0x02):
            data = bytearray((count + 7) // 8)
            for i, v in enumerate(values):
                if v:
                    data[i // 8] |= 1 << (i % 8)
            return bytes([fc, len(data)]) + bytes(data), after
        data = b"".join((v & 0xFFFF).to_bytes(2, "big") for v in values)
        return bytes([fc, len(data)]) + data, after
    if fc == 0x05:
        reg, raw = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        if raw not in (0xFF00, 0x0000):
            raise ModbusException(3)
        device.read("coil", reg)
        device.write("coil", reg, 1 if raw == 0xFF00 else 0, "master")
        return bytes(pdu[:5]), after
    if fc == 0x06:
        reg, value = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        device.read("holding", reg)
        change = device.write("holding", reg, value, "master")
        if change:
            after.append(change)
        return bytes(pdu[:5]), after
    if fc == 0x0F:
        start, count, nbytes = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big"), pdu[5]
        if not 1 <= count <= 1968 or nbytes != (count + 7) // 8 or len(pdu) != 6 + nbytes:
            raise ModbusException(3)
        for i in range(count):
            device.read("coil", start + i)
        for i in range(count):
            device.write("coil", start + i, (pdu[6 + i // 8] >> (i % 8)) & 1, "master")
        return bytes(pdu[:5]), after
    if fc == 0x10:
        start, count, nbytes = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big"), pdu[5]
        if not 1 <= count <= 123 or nbytes != 2 * count or len(pdu) != 6 + nbytes:
            raise ModbusException(3)
        for i in range(count):
            device.read("holding", start + i)
        for i in range(count):
            change = device.write("holding", start + i, int.from_bytes(pdu[6 + 2 * i : 8 + 2 * i], "big"), "master")
            if change:
                after.append(change)
        return bytes(pdu[:5]), after
    raise ModbusException(1)


def classic_reply(device, pdu):
    try:
        reply, after = classic(device, pdu)
    except ModbusException as e:
        return bytes([pdu[0] | 0x80, e.code]), []
    return reply, after


class Bus:
    def __init__(self, port, line, devices):
        self.line = line
        self.devices = devices
        self.port = port
        self.fd = port.fileno()
        self.buf = bytearray()
        self.last_rx = None
        # When the first byte of the buffer started on the wire. A master writes a whole frame
        # to a pty at once and it arrives at once, but on a line its characters take their time:
        # the request ends len x char after its first byte (a reply before that would come
        # before the master has finished sending).
        self.frame_start = None
        self.garbage = False
        self.late = []  # lateness of every scheduled write, seconds
        # Busy-wait only this close to a byte's time, sleep before (a SCHED_FIFO process wakes
        # within some tens of µs; a normal one may wake milliseconds late).
        self.spin = 0.002
        self.log_queue = []

    def find(self, ref):
        for d in self.devices:
            if isinstance(ref, dict) and "serial" in ref:
                if d.serial == int(str(ref["serial"]), 0):
                    return d
            elif d.address == ref:
                return d
        raise KeyError("no device %r" % (ref,))

    # ---- transmit ----
    def send_at(self, schedule):
        """schedule: [(monotonic time, bytes)], in order. Busy-waits to each time (sleeps
        while more than `spin` away); whatever is due by then goes out in one write, so a late
        byte takes the ones due behind it along instead of making them later still."""
        i = 0
        while i < len(schedule):
            when = schedule[i][0]
            while True:
                left = when - time.monotonic()
                if left <= 0:
                    break
                if left > self.spin:
                    time.sleep(left - 0.75 * self.spin)
            now = time.monotonic()
            chunk = bytearray()
            while i < len(schedule) and schedule[i][0] <= now:
                chunk += schedule[i][1]
                self.late.append(now - schedule[i][0])
                i += 1
            os.write(self.fd, chunk)

    def frame_schedule(self, start, frame):
        """Each byte of a frame at its own character time (§1), as a UART sends it."""
        return [(start + i * self.line.char, frame[i : i + 1]) for i in range(len(frame))]

    def reply_classic(self, end, frame):
        # A device knows the frame has ended after 3.5 characters of silence (§1).
        start = end + 3.5 * self.line.char
        self.send_at(self.frame_schedule(start, frame))
        self.log({"log": "tx", "hex": hexs(frame)})

    def reply_arbitrated(self, end, contenders, bits, make_frame, legacy=False):
        """contenders: [(word, device)]. Plays the windows (§3) and the winner's frame."""
        filled, winners = arbitrate(contenders, bits)
        if legacy:
            wait, window = 44 * self.line.bit, 20 * self.line.bit  # §3 legacy 0x60 scan
        else:
            wait, window = self.line.device_wait(), self.line.window()
        first = end + wait
        schedule = [(first + k * window, b"\xff") for k in filled]
        frame = collide([make_frame(d) for _, d in winners])
        if len(winners) > 1:
            # Equal words (a shared address in an events round): both send, the frames collide.
            self.log({"log": "collision", "devices": [d.serial for _, d in winners]})
        schedule += self.frame_schedule(first + bits * window, frame)
        self.send_at(schedule)
        self.log({"log": "tx", "hex": hexs(b"\xff" * len(filled) + frame), "fillers": len(filled)})

    def log(self, obj):
        self.log_queue.append(obj)

    def flush_log(self):
        for obj in self.log_queue:
            out(obj)
        self.log_queue = []

    # ---- receive ----
    def expected_length(self):
        b = self.buf
        if len(b) < 2:
            return None
        if b[1] in (FAST_FC, LEGACY_FAST_FC):
            if len(b) < 3:
                return None
            sub = b[2]
            if b[0] == BROADCAST_FAST:
                if sub in (SUB_SCAN_START, SUB_SCAN_CONTINUE):
                    return 5
                if sub == SUB_EVENTS_REQUEST:
                    return 9
                if sub == SUB_BY_SERIAL:
                    n = request_pdu_length(bytes(b[7:]))
                    if n is None:
                        return None
                    return -1 if n < 0 else 7 + n + 2
                return -1
            if sub == SUB_EVENTS_CONFIG:
                if len(b) < 4:
                    return None
                return 4 + b[3] + 2
            return -1
        return classic_request_length(b)

    def poll_frame(self, now):
        """A frame ends when the bytes so far make a complete request of a known layout with
        a good CRC (a device can tell without waiting), or at 3.5 characters of silence."""
        if not self.buf:
            return None
        silent = self.last_rx is not None and now - self.last_rx >= self.line.frame_gap()
        if not self.garbage:
            n = self.expected_length()
            if n is not None and n > 0 and len(self.buf) >= n:
                frame = bytes(self.buf[:n])
                if crc_ok(frame):
                    del self.buf[:n]
                    return frame, self.take_end(n)
                self.garbage = True
        if silent:
            frame = bytes(self.buf)
            end = self.take_end(len(frame))
            self.buf.clear()
            self.garbage = False
            if crc_ok(frame):
                return frame, end
            self.log({"log": "rx_garbage", "hex": hexs(frame)})
        return None

    def take_end(self, n):
        """When the frame of the buffer's first n bytes ended on the wire: n characters after
        its first byte started, and not before its last byte arrived."""
        end = max(self.last_rx, self.frame_start + n * self.line.char)
        self.frame_start = end  # a frame right behind it started when this one ended
        return end

    def handle(self, frame, end):
        self.log({"log": "rx", "hex": hexs(frame)})
        addr, fc = frame[0], frame[1]
        body = frame[:-2]
        if addr == BROADCAST_FAST and fc in (FAST_FC, LEGACY_FAST_FC):
            self.handle_fast_broadcast(body, end)
            return
        if addr == 0:
            # Broadcast: writes execute, nobody answers.
            for d in self.devices:
                if body[1] in (0x05, 0x06, 0x0F, 0x10):
                    classic_reply(d, body[1:])
            return
        targets = [d for d in self.devices if d.address == addr]
        if not targets:
            return
        frames, afters = [], []
        for device in targets:
            if fc in (FAST_FC, LEGACY_FAST_FC) and len(body) >= 3 and body[2] == SUB_EVENTS_CONFIG:
                frames.append(self.events_config(device, body))
                continue
            reply, after = classic_reply(device, body[1:])
            frames.append(with_crc(bytes([addr]) + reply))
            afters.append((device, after))
        if len(targets) > 1:
            # A shared address (§4: duplicates exist until resolved): every device answers.
            self.log({"log": "collision", "devices": [d.serial for d in targets]})
        self.reply_classic(end, collide(frames))
        for device, after in afters:
            self.apply_after(device, after)

    def apply_after(self, device, after):
        for what, value in after:
            if what == "address":
                device.address = value
                self.log({"log": "address", "serial": device.serial, "address": value})

    def events_config(self, device, body):
        """The reply frame to a 0x18 request."""
        if device.refuses_events:
            self.log({"log": "events_refused", "address": device.address})
            return with_crc(bytes([device.address, device.reply_fc(body[1]) | 0x80, 1]))
        list_len = body[3]
        data = body[4:]
        ranges = []
        i = 0
        try:
            if list_len != len(data):
                raise ModbusException(3)
            while i < len(data):
                if i + 4 > len(data):
                    raise ModbusException(3)
                ev_type, start, count = data[i], int.from_bytes(data[i + 1 : i + 3], "big"), data[i + 3]
                priorities = list(data[i + 4 : i + 4 + count])
                if len(priorities) != count:
                    raise ModbusException(3)
                if device.registers_only and ev_type not in (EV_COIL, EV_DISCRETE, EV_HOLDING, EV_INPUT):
                    raise ModbusException(3)
                ranges.append((ev_type, start, priorities))
                i += 4 + count
        except ModbusException as e:
            return with_crc(bytes([device.address, body[1] | 0x80, e.code]))
        masks = device.configure_events(ranges)
        payload = b"".join(masks)
        self.log(
            {
                "log": "events_config",
                "address": device.address,
                "ranges": [[TYPE_NAMES.get(t, t), s, p] for t, s, p in ranges],
                "masks": [list(m) for m in masks],
            }
        )
        return with_crc(bytes([device.address, device.reply_fc(body[1]), SUB_EVENTS_CONFIG, len(payload)]) + payload)

    def handle_fast_broadcast(self, body, end):
        fc, sub = body[1], body[2]
        if sub in (SUB_SCAN_START, SUB_SCAN_CONTINUE) and len(body) == 3:
            if sub == SUB_SCAN_START:
                for d in self.devices:
                    d.scanned = False
            contenders = []
            for d in self.devices:
                marker = MARKER_SCAN_SCANNED if d.scanned else MARKER_SCAN_UNSCANNED
                contenders.append(((marker << 28) | (d.serial & 0x0FFFFFFF), d))

            def scan_frame(d):
                if d.scanned:
                    return with_crc(bytes([BROADCAST_FAST, d.reply_fc(fc), SUB_SCAN_END]))
                d.scanned = True
                return with_crc(bytes([BROADCAST_FAST, d.reply_fc(fc), SUB_SCAN_REPLY]) + d.serial.to_bytes(4, "big") + bytes([d.address]))

            self.reply_arbitrated(end, contenders, SCAN_WINDOWS, scan_frame, legacy=(fc == LEGACY_FAST_FC))
        elif sub == SUB_BY_SERIAL and len(body) >= 8:
            serial_number = int.from_bytes(body[3:7], "big")
            for d in self.devices:
                if d.serial == serial_number:
                    reply, after = classic_reply(d, body[7:])
                    frame = with_crc(bytes([BROADCAST_FAST, d.reply_fc(fc), SUB_BY_SERIAL_REPLY]) + body[3:7] + reply)
                    self.reply_classic(end, frame)
                    self.apply_after(d, after)
        elif sub == SUB_EVENTS_REQUEST and len(body) == 7:
            min_address, max_len, ack_address, ack_flag = body[3], body[4], body[5], body[6]
            for d in self.devices:
                if d.deaf_when_excluded and d.address < min_address:
                    continue
                confirmed = d.take_ack(ack_address, ack_flag)
                if confirmed == "lost":
                    self.log({"log": "ack_lost", "address": d.address, "flag": ack_flag})
                elif confirmed is not None:
                    self.log({"log": "confirmed", "address": d.address, "flag": confirmed})
            contenders = []
            for d in self.devices:
                if d.address < min_address:
                    continue  # §3: min_address excludes devices below it
                contenders.append(((d.event_marker() << 8) | d.address, d))
            if not contenders:
                return

            def events_frame(d):
                if d.event_marker() == MARKER_EVENT_NONE:
                    return with_crc(bytes([BROADCAST_FAST, d.reply_fc(fc), SUB_NO_EVENTS]))
                frame, flag, sent = d.build_packet(max_len, fc)
                self.log(
                    {
                        "log": "event_packet",
                        "address": d.address,
                        "flag": flag,
                        "event_count": frame[4],
                        "events": [[TYPE_NAMES[t], i] for (t, i) in sent],
                    }
                )
                return frame

            self.reply_arbitrated(end, contenders, EVENT_WINDOWS, events_frame)

    def control(self, cmd):
        name = cmd.get("cmd")
        if name == "ping":
            return {}
        if name == "batch":
            # several changes at one instant (no request can come between them)
            return {"replies": [self.control(c) for c in cmd["commands"]]}
        if name == "stats":
            late = sorted(self.late)
            return {
                "writes": len(late),
                "late_max_us": round(late[-1] * 1e6) if late else 0,
                "late_p99_us": round(late[int(len(late) * 0.99)] * 1e6) if late else 0,
            }
        device = self.find(cmd["device"])
        if name == "set":
            values = cmd["value"] if isinstance(cmd["value"], list) else [cmd["value"]]
            for i, v in enumerate(values):
                device.set_value(cmd["type"], int(cmd["address"]) + i, int(v))
            return {}
        if name == "toggle":
            table, reg = cmd["type"], int(cmd["address"])
            value = 0 if device.tables[table][reg] else 1
            device.set_value(table, reg, value)
            return {"value": value}
        if name == "get":
            return {"value": device.read(cmd["type"], int(cmd["address"]))}
        if name == "reboot":
            device.power_on()
            self.log({"log": "reboot", "address": device.address})
            return {}
        if name == "state":
            return device.state()
        if name == "lose_ack":
            device.lose_ack = True
            then = cmd.get("then_set")
            device.lost_then = (then["type"], int(then["address"]), int(then["value"])) if then else None
            return {}
        raise KeyError("unknown command %r" % name)

    def run(self):
        stdin = sys.stdin.fileno()
        stdin_open = True
        pending_in = b""
        while True:
            if self.buf:
                wait = max(0.0, self.last_rx + self.line.frame_gap() - time.monotonic()) + 1e-4
            else:
                wait = None
            fds = [self.fd] + ([stdin] if stdin_open else [])
            readable, _, _ = select.select(fds, [], [], wait)
            if self.fd in readable:
                try:
                    data = os.read(self.fd, 4096)
                except OSError:
                    data = b""
                if data:
                    now = time.monotonic()
                    if not self.buf:
                        # a frame's first bytes: a master writes a frame at once, so it
                        # started on the wire about now
                        self.frame_start = now
                    self.buf += data
                    self.last_rx = now
            now = time.monotonic()
            while True:
                got = self.poll_frame(now)
                if got is None:
                    break
                frame, end = got
                self.handle(frame, end)
            self.flush_log()
            if stdin_open and stdin in readable:
                chunk = os.read(stdin, 65536)
                if not chunk:
                    stdin_open = False  # keep serving the bus
                pending_in += chunk
                while b"\n" in pending_in:
                    line, pending_in = pending_in.split(b"\n", 1)
                    if not line.strip():
                        continue
                    try:
                        cmd = json.loads(line)
                    except ValueError as e:
                        out({"ok": False, "error": str(e)})
                        continue
                    try:
                        reply = self.control(cmd)
                        reply["ok"] = True
                    except (KeyError, ValueError, TypeError, ModbusException) as e:
                        reply = {"ok": False, "error": repr(e)}
                    if "id" in cmd:
                        reply["id"] = cmd["id"]
                    self.flush_log()
                    out(reply)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", required=True, help="serial port or pty path")
    parser.add_argument("--line", default="9600 8N2", help='e.g. "115200 8N2"')
    parser.add_argument(
        "--device",
        action="append",
        required=True,
        help="ADDRESS:SERIAL[:MODEL[:FIRMWARE]], serial decimal or 0x hex; 1 to 3 of them",
    )
    parser.add_argument("--legacy-code", action="append", default=[], type=lambda s: int(s, 0), metavar="ADDRESS", help="this device replies under the deprecated code 0x60 (old firmware)")
    parser.add_argument("--no-events", action="append", default=[], metavar="ADDRESS:TYPE:REG", help="this register of this device cannot send events")
    parser.add_argument("--registers-only", action="append", default=[], type=lambda s: int(s, 0), metavar="ADDRESS", help="this device refuses a 0x18 with a range of another type than 1..4 (exception 3)")
    parser.add_argument("--deaf-when-excluded", action="append", default=[], type=lambda s: int(s, 0), metavar="ADDRESS", help="this device reads nothing of a 0x10 whose min_address excludes it, its confirmation included")
    parser.add_argument("--refuses-events", action="append", default=[], type=lambda s: int(s, 0), metavar="ADDRESS", help="this device answers every 0x18 with exception 1 under its reply code")
    parser.add_argument("--realtime", action="store_true", help="ask for SCHED_FIFO (root): windows kept more closely; falls back quietly")
    parser.add_argument("--wide", action="append", default=[], metavar="ADDRESS:TYPE:REG:WORDS[:little]", help="a value of WORDS registers from REG (word order big unless little): one event carries it whole")
    parser.add_argument("--count-pending", action="append", default=[], type=lambda s: int(s, 0), metavar="ADDRESS", help="event_count of this device's packets: every event it holds, not only those in the packet")
    args = parser.parse_args()
    line = Line(args.line)
    devices = []
    for spec in args.device:
        parts = spec.split(":")
        address, serial_number = int(parts[0], 0), int(parts[1], 0)
        model = parts[2] if len(parts) > 2 else "PYFAST"
        firmware = parts[3] if len(parts) > 3 else "1.0.0"
        devices.append(Device(address, serial_number, model, firmware, line))
    by_address = {d.address: d for d in devices}
    for address in args.legacy_code:
        by_address[address].legacy_code = True
    for spec in args.wide:
        parts = spec.split(":")
        order = parts[4] if len(parts) > 4 else "big"
        by_address[int(parts[0], 0)].wide[(parts[1], int(parts[2], 0))] = (int(parts[3]), order)
    for address in args.registers_only:
        by_address[address].registers_only = True
    for address in args.deaf_when_excluded:
        by_address[address].deaf_when_excluded = True
    for address in args.refuses_events:
        by_address[address].refuses_events = True
    for address in args.count_pending:
        by_address[address].count_pending = True
    for spec in args.no_events:
        address, table, reg = spec.split(":")
        by_address[int(address, 0)].no_events.add((TYPE_CODES[table], int(reg, 0)))
    if not 1 <= len(devices) <= 3:
        parser.error("1 to 3 devices")
    if len({d.serial & 0x0FFFFFFF for d in devices}) != len(devices):
        parser.error("serials must differ in their lower 28 bits (§3)")
    parity = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}[line.parity]
    port = serial.Serial(
        args.port,
        baudrate=line.baud,
        parity=parity,
        stopbits=serial.STOPBITS_TWO if line.stop_bits == 2 else serial.STOPBITS_ONE,
        bytesize=8,
        timeout=0,
    )
    gc.disable()  # no collector pauses in the middle of a window
    realtime = False
    if args.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            realtime = True
        except (OSError, AttributeError):
            pass
    out(
        {
            "ready": True,
            "line": str(line),
            "wait_us": round(line.device_wait() * 1e6, 1),
            "window_us": round(line.window() * 1e6, 2),
            "realtime": realtime,
            "devices": [{"address": d.address, "serial": d.serial, "model": d.model, "legacy_code": d.legacy_code} for d in devices],
        }
    )
    bus = Bus(port, line, devices)
    if realtime:
        bus.spin = 0.0004
    bus.run()


if __name__ == "__main__":
    main()
