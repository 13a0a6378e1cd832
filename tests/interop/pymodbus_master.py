#!/usr/bin/python3
"""A pymodbus 3.0 master for tests/interop_master.rs: an independent Modbus master driving
`rtu2mqtt sim`.

Usage: pymodbus_master.py CONFIG_JSON
  {"serial": PATH, "baud": 9600}             RTU on a serial port (8N2)
  {"tcp": "127.0.0.1:PORT", "framer": "socket"|"rtu"}  Modbus TCP, or RTU over TCP

Prints {"ready": true} once connected, then reads one JSON operation per line on stdin and
prints one JSON result per line:
  {"op": "read", "table": "coil"|"discrete"|"input"|"holding", "address", "count", "unit"}
  {"op": "write_coil"|"write_register", "address", "value", "unit"}
  {"op": "write_coils"|"write_registers", "address", "values", "unit"}
  {"op": "readwrite", "read_address", "read_count", "write_address", "values", "unit"}  (0x17)
  {"op": "device_id", "unit"}          0x2B/0x0E, basic objects
  {"op": "diag_query", "data", "unit"} 0x08/0x0000 (return query data)
  {"op": "report_slave_id", "unit"}    0x11
  {"op": "mask_write", "address", "and_mask", "or_mask", "unit"}  0x16
Results: {"bits": [...]}, {"registers": [...]}, {"address", "value"} or {"address", "count"}
(write echoes), {"function", "exception"} (an exception reply), {"broadcast": true} (unit 0:
sent, no reply awaited), {"error": "..."} (no or no valid reply). Each result also has
"warnings": what pymodbus logged at WARNING or above meanwhile (e.g. bytes it found waiting
before a request and threw away).

pymodbus 3.0.0 quirks worked around here: the client's `timeout` is cast to int (0.5 becomes 0,
a non-blocking read that never sees a reply), so it is 1; `readwrite_registers` ignores `slave=`
(its kwargs go to the request, which takes `unit=`) and would send to unit 0, a broadcast.
"""

import json
import logging
import sys

import pymodbus_version  # noqa: F401 (stops on a pymodbus it was not written for)

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.diag_message import ReturnQueryDataRequest
from pymodbus.framer.rtu_framer import ModbusRtuFramer
from pymodbus.framer.socket_framer import ModbusSocketFramer
from pymodbus.mei_message import ReadDeviceInformationRequest
from pymodbus.other_message import ReportSlaveIdRequest
from pymodbus.pdu import ExceptionResponse


class Collect(logging.Handler):
    def __init__(self):
        super().__init__(level=logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def connect(config):
    common = {"timeout": 1, "retries": 0, "broadcast_enable": True}
    if "serial" in config:
        client = ModbusSerialClient(
            port=config["serial"],
            framer=ModbusRtuFramer,
            baudrate=config["baud"],
            bytesize=8,
            parity="N",
            stopbits=2,
            **common,
        )
    else:
        host, port = config["tcp"].rsplit(":", 1)
        framer = ModbusRtuFramer if config.get("framer") == "rtu" else ModbusSocketFramer
        client = ModbusTcpClient(host, port=int(port), framer=framer, **common)
    if not client.connect():
        raise SystemExit(f"pymodbus_master: cannot connect: {config}")
    return client


def result_of(response):
    if isinstance(response, bytes):
        return {"broadcast": True}
    if isinstance(response, ExceptionResponse):
        return {"function": response.original_code, "exception": response.exception_code}
    if response is None or response.isError():
        return {"error": str(response)}
    if hasattr(response, "bits"):
        return {"bits": [int(bit) for bit in response.bits]}
    if hasattr(response, "registers"):
        return {"registers": list(response.registers)}
    if hasattr(response, "count"):
        return {"address": response.address, "count": response.count}
    if hasattr(response, "value"):
        return {"address": response.address, "value": int(response.value)}
    return {"response": str(response)}


def run(client, op):
    unit = op["unit"]
    name = op["op"]
    if name == "read":
        read = {
            "coil": client.read_coils,
            "discrete": client.read_discrete_inputs,
            "input": client.read_input_registers,
            "holding": client.read_holding_registers,
        }[op["table"]]
        response = read(op["address"], op["count"], slave=unit)
        result = result_of(response)
        if "bits" in result:
            # A reply carries whole bytes of bits: keep those asked for.
            result["bits"] = result["bits"][: op["count"]]
        return result
    if name == "write_coil":
        return result_of(client.write_coil(op["address"], bool(op["value"]), slave=unit))
    if name == "write_coils":
        values = [bool(v) for v in op["values"]]
        return result_of(client.write_coils(op["address"], values, slave=unit))
    if name == "write_register":
        return result_of(client.write_register(op["address"], op["value"], slave=unit))
    if name == "write_registers":
        return result_of(client.write_registers(op["address"], op["values"], slave=unit))
    if name == "readwrite":
        return result_of(
            client.readwrite_registers(
                read_address=op["read_address"],
                read_count=op["read_count"],
                write_address=op["write_address"],
                write_registers=op["values"],
                unit=unit,
            )
        )
    if name == "device_id":
        return result_of(client.execute(ReadDeviceInformationRequest(read_code=1, object_id=0, unit=unit)))
    if name == "diag_query":
        return result_of(client.execute(ReturnQueryDataRequest(op["data"], unit=unit)))
    if name == "report_slave_id":
        return result_of(client.execute(ReportSlaveIdRequest(unit=unit)))
    if name == "mask_write":
        return result_of(
            client.mask_write_register(
                address=op["address"], and_mask=op["and_mask"], or_mask=op["or_mask"], unit=unit
            )
        )
    return {"error": f"unknown op {name}"}


def main():
    collect = Collect()
    logging.getLogger().addHandler(collect)
    client = connect(json.loads(sys.argv[1]))
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        if not line.strip():
            continue
        collect.messages.clear()
        try:
            result = run(client, json.loads(line))
        except Exception as err:  # reported to the test, which fails on it
            result = {"error": f"{type(err).__name__}: {err}"}
        result["warnings"] = list(collect.messages)
        print(json.dumps(result), flush=True)
    client.close()


if __name__ == "__main__":
    main()
