"""The test's commands to a device helper (pymodbus_server.py, libmodbus_server.py), shared so
both stacks answer them alike. One JSON object a line on stdin, one JSON answer a line on stdout:
  {"cmd": "get", "table": "holding", "address": A, "count": N} -> {"ok": true, "values": [...]}
  {"cmd": "set", "table": "holding", "address": A, "values": [...]} -> {"ok": true}
  {"cmd": "writes"} -> {"ok": true, "writes": [{"fc": 16, "address": A, "values": [...]}, ...]}
"""

import json
import sys


def out(message):
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


def answer(line, get, set_values, writes):
    """The answer to one command line; `get(table, address, count)`, `set_values(table,
    address, values)` and `writes()` reach the device's store. A bad command is answered, never
    fatal."""
    try:
        request = json.loads(line)
        cmd = request["cmd"]
        if cmd == "get":
            values = get(request["table"], request["address"], request.get("count", 1))
            return {"ok": True, "values": [int(v) for v in values]}
        if cmd == "set":
            set_values(request["table"], request["address"], request["values"])
            return {"ok": True}
        if cmd == "writes":
            return {"ok": True, "writes": list(writes())}
        return {"ok": False, "error": f"unknown cmd {cmd!r}"}
    except Exception as exc:
        return {"ok": False, "error": repr(exc)}
