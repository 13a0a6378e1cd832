#!/usr/bin/python3
"""A Modbus device played by libmodbus (Debian's libmodbus5, the C stack behind mbpoll and many
Linux devices), for tests/interop_device.rs: RTU on a serial port (`--mode rtu-serial`), or
Modbus TCP on 127.0.0.1, a free port (`--mode tcp`; libmodbus's TCP server answers every unit
id, as many Modbus TCP devices do).

The stack under test (rtu2mqtt) is the master; this is an independent slave. libmodbus's own
server does the work: `modbus_receive` reads and checks a request (it drops one for another
slave id unanswered), `modbus_reply` answers it from a `modbus_mapping_t`, with exception 2
(illegal data address) past a table's end and exception 1 for a function it does not serve.
Python only loads the library (ctypes, no compiler needed) and relays the test's commands.

Speaks the same lines as pymodbus_server.py (--store, stdin commands, stdout JSON): first
{"event": "ready", "baudrate": B, "stopbits": S, ...} with the settings read back from the
port's termios after libmodbus set them (serial) or {"event": "listening", "port": N} (TCP),
then one reply per command:
  {"cmd": "get", "table": "holding", "address": A, "count": N} -> {"ok": true, "values": [...]}
  {"cmd": "set", "table": "holding", "address": A, "values": [...]} -> {"ok": true}
  {"cmd": "writes"} -> {"ok": true, "writes": [{"fc": 16, "address": A, "values": [...]}, ...]}
    (every write request libmodbus carried out, with its function code, read from the request
    as libmodbus received it)
The end of stdin ends the server. LIBMODBUS_DEBUG=1 in the environment has libmodbus print its
frames (on stdout, so only for a run by hand).
"""

import argparse
import ctypes
import errno
import json
import os
import socket
import sys
import termios
import threading

from device_commands import answer, out

LIBRARY = "libmodbus.so.5"
# MODBUS_RTU_MAX_ADU_LENGTH
MAX_ADU = 256
# Errors of libmodbus's own (bad CRC, bad data, ...) are numbered from here (modbus.h).
MODBUS_ENOBASE = 112345678
WRITE_FUNCTIONS = (5, 6, 15, 16)


class Mapping(ctypes.Structure):
    """modbus_mapping_t of libmodbus 3.1 (modbus.h)."""

    _fields_ = [
        ("nb_bits", ctypes.c_int),
        ("start_bits", ctypes.c_int),
        ("nb_input_bits", ctypes.c_int),
        ("start_input_bits", ctypes.c_int),
        ("nb_input_registers", ctypes.c_int),
        ("start_input_registers", ctypes.c_int),
        ("nb_registers", ctypes.c_int),
        ("start_registers", ctypes.c_int),
        ("tab_bits", ctypes.POINTER(ctypes.c_uint8)),
        ("tab_input_bits", ctypes.POINTER(ctypes.c_uint8)),
        ("tab_input_registers", ctypes.POINTER(ctypes.c_uint16)),
        ("tab_registers", ctypes.POINTER(ctypes.c_uint16)),
    ]


def load():
    try:
        lib = ctypes.CDLL(LIBRARY, use_errno=True)
    except OSError:
        sys.exit(f"{LIBRARY} is missing: apt-get install libmodbus5")
    lib.modbus_new_rtu.restype = ctypes.c_void_p
    lib.modbus_new_rtu.argtypes = [
        ctypes.c_char_p,
        ctypes.c_int,
        ctypes.c_char,
        ctypes.c_int,
        ctypes.c_int,
    ]
    for name in ("modbus_set_slave", "modbus_set_debug"):
        getattr(lib, name).argtypes = [ctypes.c_void_p, ctypes.c_int]
    for name in ("modbus_connect", "modbus_get_socket", "modbus_get_header_length"):
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    lib.modbus_new_tcp.restype = ctypes.c_void_p
    lib.modbus_new_tcp.argtypes = [ctypes.c_char_p, ctypes.c_int]
    lib.modbus_tcp_listen.argtypes = [ctypes.c_void_p, ctypes.c_int]
    lib.modbus_tcp_accept.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int)]
    lib.modbus_mapping_new.restype = ctypes.POINTER(Mapping)
    lib.modbus_mapping_new.argtypes = [ctypes.c_int] * 4
    lib.modbus_receive.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint8)]
    lib.modbus_reply.argtypes = [
        ctypes.c_void_p,
        ctypes.POINTER(ctypes.c_uint8),
        ctypes.c_int,
        ctypes.POINTER(Mapping),
    ]
    lib.modbus_strerror.restype = ctypes.c_char_p
    lib.modbus_strerror.argtypes = [ctypes.c_int]
    return lib


def version(lib):
    parts = ("major", "minor", "micro")
    return ".".join(str(ctypes.c_uint.in_dll(lib, f"libmodbus_version_{p}").value) for p in parts)


class Device:
    def __init__(self, lib, ctx, store, checksum):
        self.lib = lib
        self.ctx = ctx
        # Bytes after the PDU: the CRC on a serial line, none over TCP.
        self.checksum = checksum
        self.lock = threading.Lock()
        self.writes = []
        sizes = [len(store[t]) for t in ("coils", "discrete", "holding", "input")]
        self.mapping = lib.modbus_mapping_new(*sizes)
        if not self.mapping:
            sys.exit("modbus_mapping_new failed")
        m = self.mapping.contents
        self.tables = {
            "coils": (m.tab_bits, m.nb_bits),
            "discrete": (m.tab_input_bits, m.nb_input_bits),
            "holding": (m.tab_registers, m.nb_registers),
            "input": (m.tab_input_registers, m.nb_input_registers),
        }
        for table, values in store.items():
            self.set(table, 0, values)

    def get(self, table, address, count):
        tab, size = self.tables[table]
        if address < 0 or address + count > size:
            raise ValueError(f"{table} has {size} entries")
        return [int(tab[address + i]) for i in range(count)]

    def set(self, table, address, values):
        tab, size = self.tables[table]
        if address < 0 or address + len(values) > size:
            raise ValueError(f"{table} has {size} entries")
        for i, value in enumerate(values):
            tab[address + i] = int(value)

    def record_write(self, query, length):
        """The write a request asks for, if libmodbus will carry it out (in the table)."""
        header = self.lib.modbus_get_header_length(self.ctx)
        pdu = bytes(query[header : length - self.checksum])
        if len(pdu) < 5 or pdu[0] not in WRITE_FUNCTIONS:
            return
        fc = pdu[0]
        address = int.from_bytes(pdu[1:3], "big")
        if fc == 5:
            values = [1 if pdu[3:5] == b"\xff\x00" else 0]
        elif fc == 6:
            values = [int.from_bytes(pdu[3:5], "big")]
        elif fc == 15:
            count = int.from_bytes(pdu[3:5], "big")
            data = pdu[6:]
            values = [(data[i // 8] >> (i % 8)) & 1 for i in range(count)]
        else:
            count = int.from_bytes(pdu[3:5], "big")
            data = pdu[6:]
            values = [int.from_bytes(data[2 * i : 2 * i + 2], "big") for i in range(count)]
        table = "coils" if fc in (5, 15) else "holding"
        if address + len(values) <= self.tables[table][1]:
            self.writes.append({"fc": fc, "address": address, "values": values})

    def serve(self):
        query = (ctypes.c_uint8 * MAX_ADU)()
        while True:
            # Blocks in C (the GIL released) until a whole request is in.
            length = self.lib.modbus_receive(self.ctx, query)
            if length == 0:
                # A request for another slave id, dropped unanswered. libmodbus then takes the
                # next frame, for up to its response timeout (0.5 s), for that slave's reply.
                continue
            if length < 0:
                error = ctypes.get_errno()
                if error >= MODBUS_ENOBASE or error in (errno.ETIMEDOUT, errno.EINTR):
                    # A bad frame (CRC, length) or no reply to a request for another slave:
                    # the device waits for the next request.
                    continue
                # The line is gone (the test stopped the cable) or the client hung up.
                return self.lib.modbus_strerror(error).decode()
            with self.lock:
                self.record_write(query, length)
                self.lib.modbus_reply(self.ctx, query, length, self.mapping)


def handle(device, line):
    with device.lock:
        return answer(line, device.get, device.set, lambda: device.writes)


def control(device):
    for line in sys.stdin:
        if line.strip():
            out(handle(device, line))
    # The serving thread sits in modbus_receive: end the process, not the thread.
    os._exit(0)


BAUDS = {getattr(termios, f"B{b}"): b for b in (9600, 19200, 38400, 57600, 115200)}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=["rtu-serial", "tcp"], required=True)
    parser.add_argument("--port", help="serial port (rtu-serial)")
    parser.add_argument("--baud", type=int, default=9600)
    parser.add_argument("--parity", default="N")
    parser.add_argument("--stopbits", type=int, default=2)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument("--store", required=True, help="the datastore as JSON")
    args = parser.parse_args()

    lib = load()
    store = json.loads(args.store)
    if args.mode == "tcp":
        serve_tcp(lib, args, store)
        return
    ctx = lib.modbus_new_rtu(
        args.port.encode(), args.baud, args.parity.encode(), 8, args.stopbits
    )
    if not ctx:
        sys.exit(f"modbus_new_rtu refused {args.port} {args.baud} {args.parity} {args.stopbits}")
    lib.modbus_set_debug(ctx, 1 if os.environ.get("LIBMODBUS_DEBUG") else 0)
    lib.modbus_set_slave(ctx, args.unit)
    if lib.modbus_connect(ctx) != 0:
        error = lib.modbus_strerror(ctypes.get_errno()).decode()
        sys.exit(f"cannot open {args.port}: {error}")
    device = Device(lib, ctx, store, checksum=2)

    # What libmodbus set the line to, read back from the port itself.
    attrs = termios.tcgetattr(lib.modbus_get_socket(ctx))
    out(
        {
            "event": "ready",
            "port": args.port,
            "baudrate": BAUDS.get(attrs[4]),
            "stopbits": 2 if attrs[2] & termios.CSTOPB else 1,
            "libmodbus": version(lib),
        }
    )
    threading.Thread(target=control, args=(device,), daemon=True).start()
    sys.exit(f"modbus_receive: {device.serve()}")


def serve_tcp(lib, args, store):
    """libmodbus's TCP server on 127.0.0.1, a free port; one client at a time, the next one
    accepted when it hangs up (a master reconnecting)."""
    ctx = lib.modbus_new_tcp(b"127.0.0.1", 0)
    if not ctx:
        sys.exit("modbus_new_tcp failed")
    lib.modbus_set_debug(ctx, 1 if os.environ.get("LIBMODBUS_DEBUG") else 0)
    lib.modbus_set_slave(ctx, args.unit)
    listening = lib.modbus_tcp_listen(ctx, 1)
    if listening < 0:
        sys.exit(f"modbus_tcp_listen: {lib.modbus_strerror(ctypes.get_errno()).decode()}")
    with socket.socket(fileno=os.dup(listening)) as sock:
        port = sock.getsockname()[1]
    device = Device(lib, ctx, store, checksum=0)
    out({"event": "listening", "port": port, "libmodbus": version(lib)})
    threading.Thread(target=control, args=(device,), daemon=True).start()
    server = ctypes.c_int(listening)
    while True:
        if lib.modbus_tcp_accept(ctx, ctypes.byref(server)) < 0:
            sys.exit(f"modbus_tcp_accept: {lib.modbus_strerror(ctypes.get_errno()).decode()}")
        device.serve()
        os.close(lib.modbus_get_socket(ctx))


if __name__ == "__main__":
    main()
