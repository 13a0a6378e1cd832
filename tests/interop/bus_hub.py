#!/usr/bin/python3
"""One RS-485 bus joining several serial ports, for tests that put devices of different stacks
on one line (tests/interop_device.rs: our simulator's Fast Modbus devices beside a libmodbus
device, the daemon as the master).

A half-duplex bus is a broadcast medium: whatever one station sends, every other station hears.
The hub passes every byte read from one port on to all the others, and keeps the one rule of a
wire that a pseudo-terminal lacks: one transmission at a time, each taking its bytes' wire time
at --baud 8N2 (11 bits a character). A station that writes while the wire is busy (a device
stack that answers the moment it has read a request, which on a pty is before the request
could have crossed a line) goes on the wire when it is free. A joined port (the simulator, which
times what it hears by itself) gets a transmission when it goes on the wire; a new port (a pty
without a wire) when its last byte has crossed it, as a UART hands a frame's end over, so that
station hears a frame end when it ends on the wire and keeps its silences from there. No
collisions: the stations take turns (a master and the devices it asks).

  --join PATH     a port that already exists (the simulator's pty), opened as a station would
                  and set to --baud 8N2 (the simulator hears a request only at its devices'
                  settings)
  --new LINK      a new pty pair: the hub keeps the master side, LINK is a symlink to the other
                  end for a station to open (repeatable)

Prints {"event": "ready"} once every port is open; the end of stdin ends the hub.
"""

import argparse
import fcntl
import heapq
import json
import os
import select
import sys
import termios
import threading
import time
import tty


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--join", action="append", default=[])
    parser.add_argument("--new", action="append", default=[])
    parser.add_argument("--baud", type=int, default=9600)
    args = parser.parse_args()
    speed = getattr(termios, f"B{args.baud}")

    ports = []
    for path in args.join:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB)) | termios.CS8 | termios.CSTOPB
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        ports.append(fd)
    for link in args.new:
        master, slave = os.openpty()
        tty.setraw(slave)
        # The station opens the slave by its name; the hub keeps its own copy open so that the
        # pty does not hang up between the station's opens.
        name = os.ttyname(slave)
        if os.path.lexists(link):
            os.unlink(link)
        os.symlink(name, link)
        ports.append(master)

    def stop_on_eof():
        for _ in sys.stdin:
            pass
        os._exit(0)

    for fd in ports:
        # A station that is not reading (not started yet, or gone) must not stop the bus: its
        # bytes are dropped when its queue is full, as a receiver that is off hears nothing.
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) | os.O_NONBLOCK)
    threading.Thread(target=stop_on_eof, daemon=True).start()
    sys.stdout.write(json.dumps({"event": "ready"}) + "\n")
    sys.stdout.flush()

    char_time = 11 / args.baud
    timed_by_the_station = set(ports[: len(args.join)])
    wire_free = 0.0
    # (when the port hears it, order, to which port, bytes)
    pending = []
    order = 0
    while True:
        now = time.monotonic()
        while pending and pending[0][0] <= now:
            _, _, port, data = heapq.heappop(pending)
            try:
                os.write(port, data)
            except OSError:
                pass
        timeout = max(0.0, pending[0][0] - now) if pending else None
        readable, _, _ = select.select(ports, [], [], timeout)
        now = time.monotonic()
        for fd in readable:
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if not data:
                # The other side of this port is gone for good (a joined port whose pty master
                # closed: the simulator ended): EIO or end of file from now on, and select()
                # reports it readable every time. Stop listening to it, or the loop spins.
                ports.remove(fd)
                continue
            start = max(now, wire_free)
            wire_free = start + len(data) * char_time
            for port in ports:
                if port != fd:
                    heard = start if port in timed_by_the_station else wire_free
                    order += 1
                    heapq.heappush(pending, (heard, order, port, data))


if __name__ == "__main__":
    main()
