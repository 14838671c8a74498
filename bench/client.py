"""Client stack time and link utilisation: ``python bench/client.py [-n 3000] [--throttled-n 400]``.

A responder in a separate process (so it does not share our GIL) plays the
EPOS4 for the guide's ReadObject "Home Position" example (2.2.9, Tables 2-5
and 2-6: 10 request bytes, 15 answer bytes with one stuffed DLE), over a TCP
socket (``socket://127.0.0.1:PORT``) and over a pseudo-terminal opened like a
serial port (``/dev/pts/N``).

1. Instant responder: median wall time per ``EposClient.read_object`` round
   trip, minus the median of a bare round trip (``os.write``/``os.read`` or
   ``send``/``recv`` of the same bytes, no framing, no checks) over the same
   kind of link: that difference is the time our stack adds. CPU time per call
   (``time.process_time``) is shown too. Goal: under 0.2 ms.
2. Throttled to 115200 baud 8N1: the responder releases each answer byte when
   it would have arrived on the wire (request bytes, then answer bytes, at
   10 bits per byte from the request's first byte; the device's processing
   time is taken as zero). Transactions/s achieved over the wire-limited
   maximum. Goal: at least 90 %.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import select
import socket
import statistics
import sys
import time
import tty
from pathlib import Path
from typing import Callable

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from epos_link.client import EposClient  # noqa: E402
from epos_link.transports import open_transport  # noqa: E402

# Guide 2.2.9, transmission and reception order as printed.
REQUEST = bytes.fromhex("90 02 60 02 01 B0 30 00 2E 62")
ANSWER = bytes.fromhex("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")
VALUE = bytes.fromhex("01 90 00 00")
BAUD = 115200
BITS_PER_BYTE = 10  # start, 8 data, stop (guide 2.2.6)
BYTE_TIME = BITS_PER_BYTE / BAUD


# --- the responder (child process) -------------------------------------------

def _serve(recv: Callable[[], bytes], send: Callable[[bytes], object], baud: int) -> None:
    byte_time = BITS_PER_BYTE / baud if baud else 0.0
    buf = b""
    t0 = 0.0
    clock = time.perf_counter
    while True:
        data = recv()
        if not data:
            return
        if not buf:
            t0 = clock()  # the request's first byte
        buf += data
        while len(buf) >= len(REQUEST):
            if buf[:len(REQUEST)] != REQUEST:
                buf = buf[1:]
                continue
            buf = buf[len(REQUEST):]
            if not byte_time:
                send(ANSWER)
                continue
            # Release byte i of the answer when it would have arrived on the wire.
            for i in range(len(ANSWER)):
                due = t0 + (len(REQUEST) + i + 1) * byte_time
                while clock() < due:
                    pass  # busy wait: sleep() is far coarser than 87 us
                send(ANSWER[i:i + 1])
            t0 = clock()


def _socket_responder(conn_ready: "mp.connection.Connection", baud: int) -> None:
    server = socket.create_server(("127.0.0.1", 0))
    conn_ready.send(server.getsockname()[1])
    while True:
        conn, _ = server.accept()
        if os.fork():  # one process per connection: the bare and the client link side by side
            conn.close()
            continue
        server.close()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            _serve(lambda: conn.recv(4096), conn.sendall, baud)
        except OSError:
            pass
        os._exit(0)


def _pty_responder(master: int, baud: int) -> None:
    def recv() -> bytes:
        try:
            return os.read(master, 4096)
        except OSError:
            return b""
    _serve(recv, lambda b: os.write(master, b), baud)


class Link:
    """A responder process and the URL to reach it."""

    def __init__(self, kind: str, baud: int = 0) -> None:
        ctx = mp.get_context("fork")
        self.kind = kind
        self._fds: list[int] = []
        if kind == "socket":
            mine, theirs = ctx.Pipe()
            self.proc = ctx.Process(target=_socket_responder, args=(theirs, baud), daemon=True)
            self.proc.start()
            self.port = mine.recv()
            self.url = f"socket://127.0.0.1:{self.port}"
        else:
            master, slave = os.openpty()
            tty.setraw(slave)
            self._fds = [master, slave]
            self.url = os.ttyname(slave)
            self.proc = ctx.Process(target=_pty_responder, args=(master, baud), daemon=True)
            self.proc.start()

    def bare_round_trip(self) -> Callable[[], None]:
        """A round trip with no stack at all: write the request, read len(ANSWER) bytes."""
        need = len(ANSWER)
        if self.kind == "socket":
            sock = socket.create_connection(("127.0.0.1", self.port))
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

            def trip() -> None:
                sock.sendall(REQUEST)
                got = 0
                while got < need:
                    got += len(sock.recv(need - got))
            return trip
        fd = os.open(self.url, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        self._fds.append(fd)

        def trip_fd() -> None:
            os.write(fd, REQUEST)
            got = 0
            while got < need:
                select.select((fd,), (), (), 1.0)
                got += len(os.read(fd, need - got))
        return trip_fd

    def close(self) -> None:
        self.proc.terminate()
        self.proc.join(2)
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass


# --- measurements -------------------------------------------------------------

def timed(call: Callable[[], object], n: int) -> tuple[list[float], float]:
    """Wall time of each call, and CPU time per call."""
    times = []
    clock = time.perf_counter
    cpu0 = time.process_time()
    for _ in range(n):
        t = clock()
        call()
        times.append(clock() - t)
    return times, (time.process_time() - cpu0) / n


def stack_time(kind: str, n: int, rounds: int) -> dict[str, float]:
    link = Link(kind)
    try:
        bare = link.bare_round_trip()
        client = EposClient(open_transport(link.url))
        assert client.read_object(1, 0x30B0, 0) == VALUE

        def read() -> None:
            client.read_object(1, 0x30B0, 0)

        for _ in range(200):  # warm up both paths
            bare()
            read()
        bare_t: list[float] = []
        ours_t: list[float] = []
        bare_cpu: list[float] = []
        ours_cpu: list[float] = []
        for _ in range(rounds):  # interleaved, so drift hits both alike
            t, c = timed(bare, n // rounds)
            bare_t += t
            bare_cpu.append(c)
            t, c = timed(read, n // rounds)
            ours_t += t
            ours_cpu.append(c)
        client.close()
    finally:
        link.close()
    return {"bare": statistics.median(bare_t), "ours": statistics.median(ours_t),
            "bare_cpu": statistics.median(bare_cpu), "ours_cpu": statistics.median(ours_cpu)}


def throughput(kind: str, n: int) -> dict[str, float]:
    link = Link(kind, BAUD)
    try:
        client = EposClient(open_transport(link.url, baudrate=BAUD))
        for _ in range(20):
            client.read_object(1, 0x30B0, 0)
        t = time.perf_counter()
        for _ in range(n):
            client.read_object(1, 0x30B0, 0)
        elapsed = time.perf_counter() - t
        client.close()
    finally:
        link.close()
    wire_max = 1 / ((len(REQUEST) + len(ANSWER)) * BYTE_TIME)
    return {"tps": n / elapsed, "max": wire_max}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=3000, help="round trips per link for the stack time")
    ap.add_argument("--rounds", type=int, default=6, help="interleaved blocks of bare/client trips")
    ap.add_argument("--throttled-n", type=int, default=400, help="round trips per throttled link")
    args = ap.parse_args()
    print(f"ReadObject round trips (guide 2.2.9 frames: {len(REQUEST)} + {len(ANSWER)} bytes), "
          f"responder in another process\n")
    print("1. instant responder, medians per round trip")
    print(f"   {'link':<8}{'bare':>10}{'client':>10}{'stack adds':>12}{'cpu bare':>10}{'cpu client':>12}")
    for kind in ("socket", "pty"):
        r = stack_time(kind, args.n, args.rounds)
        print(f"   {kind:<8}{r['bare'] * 1e3:8.3f}ms{r['ours'] * 1e3:8.3f}ms"
              f"{(r['ours'] - r['bare']) * 1e3:10.3f}ms{r['bare_cpu'] * 1e3:8.3f}ms"
              f"{r['ours_cpu'] * 1e3:10.3f}ms")
    print("   goal: stack adds under 0.200 ms (maxon's library: 10-20 ms per call reported)\n")
    print(f"2. throttled to {BAUD} baud 8N1 ({BITS_PER_BYTE} bits per byte, device time 0)")
    for kind in ("socket", "pty"):
        r = throughput(kind, args.throttled_n)
        print(f"   {kind:<8}{r['tps']:8.1f} transactions/s of {r['max']:.1f} wire-limited "
              f"= {r['tps'] / r['max'] * 100:5.1f} %")
    print("   goal: at least 90 %")


if __name__ == "__main__":
    main()
