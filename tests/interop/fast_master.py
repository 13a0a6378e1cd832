#!/usr/bin/python3
"""An independent Fast Modbus master, written from shared/protocol/fast-modbus.md only.

    fast_master.py --port /tmp/ttyA --line "115200 8N2" scan
    fast_master.py --port P --line L read --serial 0xFE4000AC --type holding --reg 200 --count 20
    fast_master.py --port P --line L session     (JSON-line commands on stdin, one reply a line)

Session commands (each answered by one JSON line with "ok"; an "id" is echoed):
    {"cmd": "scan"}                                   → {"devices": [{"serial", "address"}…]}
    {"cmd": "read", "serial": N, "type": "holding", "reg": R, "count": C}   (0x08 wrapping 0x01..0x04)
    {"cmd": "write", "serial": N, "type": "holding"|"coil", "reg": R, "value": V}  (0x08 wrapping 0x06/0x05)
    {"cmd": "read_address", "address": A, "type": …, "reg": R, "count": C}  (classic)
    {"cmd": "enable", "address": A, "ranges": [{"type": "discrete", "reg": 0, "priorities": [2, 1]}…]}
                                                      → {"masks": [[…]…], "enabled": [[type, reg]…]}
    {"cmd": "poll", "until_idle": true, "max_polls": N}    poll until a "no events" reply
    {"cmd": "poll", "until": {"address": A, "type": T, "id": I, "value": V}, "timeout_s": S}
                                                      → {"events": [...], "polls": N, "replies": {...}}
Every event request (0x10) confirms the packet before it (§6); a reboot event makes the master
re-send that device's 0x18 settings and read the event registers once (§6 Reboot handling).

Timing (§3): reply timeout = max(3.5 chars, 12 bits + 800 us) + N windows, counted from the end
of the request on the wire, plus the reply frame's own characters, plus --margin-ms for the
latency of the port (a pty, a USB adapter, this interpreter).
"""

import argparse
import json
import os
import select
import sys
import time

import serial

sys.dont_write_bytecode = True  # no __pycache__ beside the scripts
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fastmodbus_common import *  # noqa: E402,F401,F403
from fastmodbus_common import Line, with_crc, crc_ok, hexs, reply_pdu_length, decode_events  # noqa: E402

FC_READ = {"coil": 0x01, "discrete": 0x02, "holding": 0x03, "input": 0x04}


class NoReply(Exception):
    pass


class BadReply(Exception):
    pass


class Master:
    def __init__(self, port_path, line, margin):
        self.line = line
        self.margin = margin
        parity = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}[line.parity]
        self.port = serial.Serial(
            port_path,
            baudrate=line.baud,
            parity=parity,
            stopbits=serial.STOPBITS_TWO if line.stop_bits == 2 else serial.STOPBITS_ONE,
            bytesize=8,
            timeout=0,
        )
        self.fd = self.port.fileno()
        self.last_rx = None
        self.trace = []  # (direction, hex) of every exchange, for the caller
        # events state (§6)
        self.last_flag = {}  # address -> flag of the last packet taken
        self.ack = (0, 0)
        self.min_address = 0
        self.event_settings = {}  # address -> ranges last sent with 0x18

    # ---- wire ----
    def send(self, frame):
        # §1: 3.5 characters of silence before a frame.
        if self.last_rx is not None:
            quiet = self.last_rx + self.line.frame_gap()
            while time.monotonic() < quiet:
                time.sleep(max(0.0, quiet - time.monotonic()))
        self.port.reset_input_buffer()
        os.write(self.fd, frame)
        self.trace.append(["tx", hexs(frame)])
        # the end of the request on the wire
        return time.monotonic() + len(frame) * self.line.char

    def receive(self, request_end, first_deadline, frame_length):
        """Reads one reply. Leading 0xFF bytes are skipped (§2). first_deadline: by when the
        reply frame must have started (after the request's end); frame_length(buf) tells the
        length of the frame from its first bytes (None: need more; raises BadReply)."""
        buf = bytearray()
        fillers = 0
        deadline = request_end + first_deadline + self.margin
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.trace.append(["rx", hexs(b"\xff" * fillers + bytes(buf)), "timeout"])
                raise NoReply("no complete reply (%d fillers, %s)" % (fillers, hexs(buf)))
            readable, _, _ = select.select([self.fd], [], [], left)
            if not readable:
                continue
            data = os.read(self.fd, 4096)
            if not data:
                continue
            self.last_rx = time.monotonic()
            for b in data:
                if not buf and b == 0xFF:
                    fillers += 1
                    continue
                if not buf:
                    # the frame has started: it must end within its own characters
                    deadline = max(deadline, self.last_rx + 256 * self.line.char + self.margin)
                buf.append(b)
            n = frame_length(bytes(buf)) if buf else None
            if n is not None and len(buf) >= n:
                frame = bytes(buf[:n])
                self.trace.append(["rx", hexs(b"\xff" * fillers + frame)])
                if not crc_ok(frame):
                    raise BadReply("bad CRC: %s" % hexs(frame))
                return frame, fillers

    def transact(self, frame, windows, frame_length, max_reply, legacy=False):
        end = self.send(frame)
        if legacy:
            first = (44 + windows * 20) * self.line.bit  # §3: legacy 0x60 scan timing
        elif windows:
            first = self.line.reply_timeout(windows)
        else:
            first = 3.5 * self.line.char + 0.05  # classic: 50 ms of device turnaround
        first += max_reply * self.line.char
        return self.receive(end, first, frame_length)

    # ---- scan (§4) ----
    def scan(self, legacy=False):
        """legacy: under the deprecated code 0x60, with its timing (§3)."""
        devices = []
        fc_seen = set()
        fc = LEGACY_FAST_FC if legacy else FAST_FC
        end, end_fillers = False, None
        request = with_crc(bytes([BROADCAST_FAST, fc, SUB_SCAN_START]))
        for _ in range(250):
            try:
                frame, fillers = self.transact(request, SCAN_WINDOWS, scan_length, 9, legacy)
            except NoReply:
                break  # nothing at these settings (or the end)
            fc_seen.add(frame[1])
            if frame[2] == SUB_SCAN_END:
                end, end_fillers = True, fillers
                break
            devices.append(
                {
                    "serial": int.from_bytes(frame[3:7], "big"),
                    "address": frame[7],
                    "fillers": fillers,
                    "function": frame[1],
                }
            )
            request = with_crc(bytes([BROADCAST_FAST, fc, SUB_SCAN_CONTINUE]))
        else:
            raise BadReply("no end of scan after 250 devices")
        return {"devices": devices, "end_of_scan": end, "end_fillers": end_fillers, "functions": sorted(fc_seen)}

    # ---- by serial (§5) ----
    def by_serial(self, serial_number, pdu):
        request = with_crc(bytes([BROADCAST_FAST, FAST_FC, SUB_BY_SERIAL]) + serial_number.to_bytes(4, "big") + pdu)
        frame, _ = self.transact(request, 0, by_serial_length, 7 + 256)
        if frame[0] != BROADCAST_FAST or frame[1] not in (FAST_FC, LEGACY_FAST_FC) or frame[2] != SUB_BY_SERIAL_REPLY:
            raise BadReply("not a 0x09 reply: %s" % hexs(frame))
        got = int.from_bytes(frame[3:7], "big")
        if got != serial_number:
            raise BadReply("reply from serial %d, asked %d" % (got, serial_number))
        return frame[7:-2]

    def read(self, serial_number, table, reg, count):
        fc = FC_READ[table]
        reply = self.by_serial(serial_number, bytes([fc]) + reg.to_bytes(2, "big") + count.to_bytes(2, "big"))
        return decode_read(fc, reply, count)

    def write(self, serial_number, table, reg, value):
        if table == "coil":
            pdu = bytes([0x05]) + reg.to_bytes(2, "big") + (b"\xff\x00" if value else b"\x00\x00")
        else:
            pdu = bytes([0x06]) + reg.to_bytes(2, "big") + (value & 0xFFFF).to_bytes(2, "big")
        reply = self.by_serial(serial_number, pdu)
        if reply[0] & 0x80:
            return {"exception": reply[1]}
        if reply != pdu:
            raise BadReply("write echo differs: %s" % hexs(reply))
        return {}

    def read_address(self, address, table, reg, count):
        fc = FC_READ[table]
        request = with_crc(bytes([address, fc]) + reg.to_bytes(2, "big") + count.to_bytes(2, "big"))
        frame, _ = self.transact(request, 0, lambda b: classic_length(b), 256)
        if frame[0] != address:
            raise BadReply("reply from %d" % frame[0])
        return decode_read(fc, frame[1:-2], count)

    # ---- events (§6) ----
    def enable(self, address, ranges):
        """ranges: [{"type": name, "reg": R, "priorities": [p…]}]"""
        body = b""
        for r in ranges:
            prios = bytes(r["priorities"])
            body += bytes([TYPE_CODES[r["type"]]]) + int(r["reg"]).to_bytes(2, "big") + bytes([len(prios)]) + prios
        request = with_crc(bytes([address, FAST_FC, SUB_EVENTS_CONFIG, len(body)]) + body)
        frame, _ = self.transact(request, 0, config_length, 256)
        if frame[0] != address:
            raise BadReply("0x18 reply from %d" % frame[0])
        if frame[1] & 0x80:
            return {"exception": frame[2]}
        data = frame[4:-2]
        if frame[3] != len(data):
            raise BadReply("0x18 reply length %d, %d bytes" % (frame[3], len(data)))
        masks, enabled, i = [], [], 0
        for r in ranges:
            n = (len(r["priorities"]) + 7) // 8
            mask = data[i : i + n]
            if len(mask) != n:
                raise BadReply("0x18 reply too short for its ranges")
            i += n
            masks.append(list(mask))
            for k in range(len(r["priorities"])):
                if (mask[k // 8] >> (k % 8)) & 1:
                    enabled.append([r["type"], int(r["reg"]) + k])
        self.event_settings[address] = ranges
        return {"masks": masks, "enabled": enabled}

    def poll_once(self, max_len=0xFF, withhold_ack=False):
        """One 0x10 round. Returns ("events", address, flag, count, events, duplicate, reboot,
        fillers) / ("none", fillers) / ("silence",). withhold_ack: this request carries no
        confirmation (as if it had been lost); the one after it does."""
        ack_address, ack_flag = (0, 0) if withhold_ack else self.ack
        request = with_crc(bytes([BROADCAST_FAST, FAST_FC, SUB_EVENTS_REQUEST, self.min_address, max_len, ack_address, ack_flag]))
        try:
            frame, fillers = self.transact(request, EVENT_WINDOWS, events_length, 256)
        except NoReply:
            self.min_address = 0
            return ("silence",)
        if frame[2] == SUB_NO_EVENTS:
            if not withhold_ack:
                self.ack = (0, 0)  # the confirmation went out with this request
            self.min_address = 0
            return ("none", fillers)
        address, flag, count, data_len = frame[0], frame[3], frame[4], frame[5]
        events = decode_events(frame[6 : 6 + data_len])
        reboot = any(e["type_code"] == EV_SYSTEM and e["id"] == 0 for e in events)
        # §6: a repeated flag means our confirmation was lost: the events come again (values
        # are idempotent: take the latest). A reboot event is taken whatever the flag.
        duplicate = (not reboot) and self.last_flag.get(address) == flag
        self.last_flag[address] = flag
        self.ack = (address, flag)
        # §3: min_address keeps a chatty low address from starving the others.
        self.min_address = (address + 1) % 248
        return ("events", address, flag, count, events, duplicate, reboot, fillers)

    def after_reboot(self, address):
        """§6 Reboot handling: re-send the 0x18 settings, read the event registers once."""
        ranges = self.event_settings.get(address)
        if not ranges:
            return None
        enabled = self.enable(address, ranges)
        values = []
        for r in ranges:
            vals = self.read_address(address, r["type"], int(r["reg"]), len(r["priorities"]))
            values.append({"type": r["type"], "reg": int(r["reg"]), "values": vals})
        return {"reenabled": enabled, "read": values}

    def poll(self, until=None, until_idle=False, timeout_s=10.0, max_polls=10000):
        """Polls until an event matching `until` has come (and every packet is confirmed:
        polling goes on to a "no events" reply to a request with min_address 0), or, with
        until_idle, just until such a reply."""
        deadline = time.monotonic() + timeout_s
        found, rounds, replies = [], 0, {"events": 0, "none": 0, "silence": 0}
        reboots = []
        matched = until is None
        while rounds < max_polls and time.monotonic() < deadline:
            rounds += 1
            asked_from = self.min_address
            result = self.poll_once()
            replies[result[0]] += 1
            if result[0] == "events":
                _, address, flag, count, events, duplicate, reboot, fillers = result
                for e in events:
                    e.update({"address": address, "flag": flag, "duplicate": duplicate, "event_count": count})
                    found.append(e)
                    if until and matches(e, until):
                        matched = True
                if reboot:
                    done = self.after_reboot(address)
                    reboots.append({"address": address, "handled": done})
            elif result[0] == "none" and asked_from == 0 and (until_idle or matched) and self.ack == (0, 0):
                return {"events": found, "polls": rounds, "replies": replies, "reboots": reboots, "matched": matched, "idle": True}
            time.sleep(0.005)
        return {"events": found, "polls": rounds, "replies": replies, "reboots": reboots, "matched": matched, "idle": False}


def matches(event, until):
    for key in ("address", "type", "id", "value"):
        if key in until and event.get(key) != until[key]:
            return False
    return True


def decode_read(fc, reply, count):
    if reply[0] & 0x80:
        return {"exception": reply[1]}
    data = reply[2 : 2 + reply[1]]
    if fc in (0x01, 0x02):
        return [(data[i // 8] >> (i % 8)) & 1 for i in range(count)]
    return [int.from_bytes(data[2 * i : 2 * i + 2], "big") for i in range(count)]


def scan_length(b):
    if len(b) < 3:
        return None
    if b[0] != BROADCAST_FAST or b[1] not in (FAST_FC, LEGACY_FAST_FC):
        raise BadReply("not a scan reply: %s" % hexs(b))
    if b[2] == SUB_SCAN_REPLY:
        return 3 + 4 + 1 + 2
    if b[2] == SUB_SCAN_END:
        return 5
    raise BadReply("scan sub-command %02X" % b[2])


def by_serial_length(b):
    if len(b) < 8:
        return None
    n = reply_pdu_length(b[7:])
    if n is None:
        return None
    if n < 0:
        raise BadReply("unknown function in 0x09: %s" % hexs(b))
    return 7 + n + 2


def classic_length(b):
    if len(b) < 2:
        return None
    n = reply_pdu_length(b[1:])
    if n is None:
        return None
    if n < 0:
        raise BadReply("unknown reply: %s" % hexs(b))
    return 1 + n + 2


def config_length(b):
    if len(b) < 3:
        return None
    if b[1] & 0x80:
        return 5
    if len(b) < 4:
        return None
    return 4 + b[3] + 2


def events_length(b):
    if len(b) < 3:
        return None
    if b[1] not in (FAST_FC, LEGACY_FAST_FC):
        raise BadReply("not an events reply: %s" % hexs(b))
    if b[2] == SUB_NO_EVENTS:
        return 5
    if b[2] == SUB_EVENTS:
        if len(b) < 6:
            return None
        return 6 + b[5] + 2
    raise BadReply("events sub-command %02X" % b[2])


def run_command(master, cmd):
    name = cmd["cmd"]
    if name == "scan":
        return master.scan(legacy=bool(cmd.get("legacy")))
    if name == "read":
        return {"values": master.read(int(str(cmd["serial"]), 0), cmd["type"], int(cmd["reg"]), int(cmd.get("count", 1)))}
    if name == "write":
        return master.write(int(str(cmd["serial"]), 0), cmd["type"], int(cmd["reg"]), int(cmd["value"]))
    if name == "read_address":
        return {"values": master.read_address(int(cmd["address"]), cmd["type"], int(cmd["reg"]), int(cmd.get("count", 1)))}
    if name == "enable":
        return master.enable(int(cmd["address"]), cmd["ranges"])
    if name == "poll":
        return master.poll(
            until=cmd.get("until"),
            until_idle=bool(cmd.get("until_idle")),
            timeout_s=float(cmd.get("timeout_s", 10)),
            max_polls=int(cmd.get("max_polls", 10000)),
        )
    if name == "poll_once":
        if "min_address" in cmd:
            master.min_address = int(cmd["min_address"])
        result = master.poll_once(max_len=int(cmd.get("max_len", 0xFF)), withhold_ack=bool(cmd.get("withhold_ack")))
        if result[0] == "none":
            return {"reply": "none", "fillers": result[1]}
        if result[0] != "events":
            return {"reply": result[0]}
        _, address, flag, count, events, duplicate, reboot, fillers = result
        return {"reply": "events", "address": address, "flag": flag, "event_count": count, "events": events, "duplicate": duplicate, "reboot": reboot, "fillers": fillers}
    if name == "state":
        return {"last_flag": master.last_flag, "ack": list(master.ack), "min_address": master.min_address}
    if name == "trace":
        trace, master.trace = master.trace, []
        return {"trace": trace}
    raise KeyError("unknown command %r" % name)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", required=True)
    parser.add_argument("--line", default="9600 8N2")
    parser.add_argument("--margin-ms", type=float, default=30.0, help="added to every reply timeout")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scan")
    read = sub.add_parser("read")
    read.add_argument("--serial", required=True)
    read.add_argument("--type", default="holding", choices=sorted(FC_READ))
    read.add_argument("--reg", type=lambda s: int(s, 0), required=True)
    read.add_argument("--count", type=int, default=1)
    sub.add_parser("session")
    args = parser.parse_args()
    master = Master(args.port, Line(args.line), args.margin_ms / 1000.0)
    if args.command == "scan":
        print(json.dumps(master.scan()))
        return
    if args.command == "read":
        print(json.dumps({"values": master.read(int(args.serial, 0), args.type, args.reg, args.count)}))
        return
    print(json.dumps({"ready": True, "line": str(master.line)}), flush=True)
    for raw in sys.stdin:
        if not raw.strip():
            continue
        cmd = json.loads(raw)
        try:
            reply = run_command(master, cmd)
            reply["ok"] = True
        except (NoReply, BadReply, KeyError, ValueError) as e:
            reply = {"ok": False, "error": "%s: %s" % (type(e).__name__, e)}
        if "id" in cmd:
            reply["id"] = cmd["id"]
        print(json.dumps(reply), flush=True)


if __name__ == "__main__":
    main()
