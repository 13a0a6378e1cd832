#!/usr/bin/python3
"""A Modbus device played by pymodbus (Debian's python3-pymodbus 3.0), for tests/interop_device.rs.

The stack under test (rtu2mqtt) is the master; this is an independent slave. Modes:
  rtu-serial  pymodbus's serial server with the RTU framer on a serial port (a pty of socat)
  tcp         Modbus TCP (MBAP) on 127.0.0.1, a free port
  rtu-tcp     RTU frames over TCP (pymodbus's TCP server with the RTU framer)

The datastore (zero-based addresses, as on the wire) is given as JSON with --store:
  {"coils": [...], "discrete": [...], "holding": [...], "input": [...]}
Every table starts at address 0 and ends with its list: a request past the end is answered with
exception 2 (illegal data address). Only --unit answers; other unit ids get no reply (with
--gateway: exception 0x0B, gateway target failed to respond).

Lines on stdout are JSON: first {"event": "ready"} (serial) or {"event": "listening",
"port": N} (TCP), then one reply per command read on stdin (one JSON object a line):
  {"cmd": "get", "table": "holding", "address": A, "count": N} -> {"ok": true, "values": [...]}
  {"cmd": "set", "table": "holding", "address": A, "values": [...]} -> {"ok": true}
  {"cmd": "writes"} -> {"ok": true, "writes": [{"fc": 16, "address": A, "values": [...]}, ...]}
    (every write request carried out so far, with its function code)
The end of stdin ends the server. PYMODBUS_DEBUG=1 in the environment logs pymodbus's frames on
stderr.
"""

import argparse
import asyncio
import json
import logging
import os
import sys
import threading

from device_commands import answer, out
import pymodbus_version  # noqa: F401 (stops on a pymodbus it was not written for)

import pymodbus
from pymodbus.datastore import (
    ModbusSequentialDataBlock,
    ModbusServerContext,
    ModbusSlaveContext,
)
from pymodbus.server import StartAsyncSerialServer, StartAsyncTcpServer
from pymodbus.transaction import ModbusRtuFramer, ModbusSocketFramer

TABLES = {"coils": "c", "discrete": "d", "holding": "h", "input": "i"}
# The function codes pymodbus's datastore is called with for each table (reads).
READ_FC = {"coils": 1, "discrete": 2, "holding": 3, "input": 4}


class RecordingSlave(ModbusSlaveContext):
    """A slave context that records each write request with its function code."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.writes = []

    def setValues(self, fc_as_hex, address, values):  # noqa: N802 (pymodbus's name)
        self.writes.append(
            {"fc": fc_as_hex, "address": address, "values": [int(v) for v in values]}
        )
        super().setValues(fc_as_hex, address, values)


def block(values):
    return ModbusSequentialDataBlock(0, [int(v) for v in values])


def handle(slave, line):
    def store(table):
        return slave.store[TABLES[table]]

    return answer(
        line,
        lambda table, address, count: store(table).getValues(address, count),
        lambda table, address, values: store(table).setValues(address, values),
        lambda: slave.writes,
    )


def control(loop, slave, done):
    """Reads commands on stdin (a thread); each runs on the server's loop, between requests."""
    for line in sys.stdin:
        if not line.strip():
            continue
        future = asyncio.run_coroutine_threadsafe(run_one(slave, line), loop)
        out(future.result())
    loop.call_soon_threadsafe(done.set)


async def run_one(slave, line):
    return handle(slave, line)


async def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=["rtu-serial", "tcp", "rtu-tcp"], required=True)
    parser.add_argument("--port", help="serial port (rtu-serial)")
    parser.add_argument("--baud", type=int, default=9600)
    parser.add_argument("--parity", default="N")
    parser.add_argument("--stopbits", type=int, default=2)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument(
        "--gateway",
        action="store_true",
        help="answer other unit ids with exception 0x0B (gateway target failed to respond), "
        "as a Modbus TCP gateway does for a device behind it that is not there",
    )
    parser.add_argument("--store", required=True, help="the datastore as JSON")
    args = parser.parse_args()
    if os.environ.get("PYMODBUS_DEBUG"):
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr, format="%(asctime)s.%(msecs)03d %(message)s", datefmt="%H:%M:%S")
        logging.getLogger("pymodbus").setLevel(logging.DEBUG)

    store = json.loads(args.store)
    slave = RecordingSlave(
        co=block(store["coils"]),
        di=block(store["discrete"]),
        hr=block(store["holding"]),
        ir=block(store["input"]),
        # Addresses as on the wire: pymodbus adds 1 to every address otherwise.
        zero_mode=True,
    )
    # single=False: only --unit answers (single=True would answer every unit id). The framer
    # drops a request to a unit id the context does not have, unanswered, unless the context has
    # unit 0 (or 255): then every request passes, and one to an unknown unit is answered with
    # exception 0x0B (pymodbus's ignore_missing_slaves=False; without unit 0 it has no effect).
    slaves = {args.unit: slave}
    if args.gateway:
        slaves[0] = slave
    context = ModbusServerContext(slaves=slaves, single=False)

    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    if args.mode == "rtu-serial":
        # StartAsyncSerialServer's default framer is ASCII: RTU must be named.
        server = await StartAsyncSerialServer(
            context=context,
            framer=ModbusRtuFramer,
            port=args.port,
            baudrate=args.baud,
            bytesize=8,
            parity=args.parity,
            stopbits=args.stopbits,
            defer_start=True,
        )
        await server.start()
        if server.transport is None:
            raise SystemExit(f"cannot open {args.port}")
        line = server.transport.serial
        out(
            {
                "event": "ready",
                "port": args.port,
                "baudrate": line.baudrate,
                "bytesize": line.bytesize,
                "parity": line.parity,
                "stopbits": line.stopbits,
                "pymodbus": pymodbus.__version__,
            }
        )
        serving = None
    else:
        framer = ModbusSocketFramer if args.mode == "tcp" else ModbusRtuFramer
        server = await StartAsyncTcpServer(
            context=context,
            framer=framer,
            address=("127.0.0.1", 0),
            defer_start=True,
        )
        serving = asyncio.create_task(server.serve_forever())
        await server.serving
        port = server.server.sockets[0].getsockname()[1]
        out({"event": "listening", "port": port, "pymodbus": pymodbus.__version__})

    threading.Thread(target=control, args=(loop, slave, done), daemon=True).start()
    await done.wait()
    await server.shutdown()
    if serving is not None:
        serving.cancel()


if __name__ == "__main__":
    asyncio.run(main())
