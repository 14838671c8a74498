"""Soak: ``python bench/soak.py [--clients 16] [--axes 8] [--duration 600]``.

Runs ``tcp-bridge serve --simulate --axes M`` as its own process (the simulated
EPOS4 is axis 1, the others are drives behind its CAN gateway) and N TCP
clients against it for the given time, the way EPICS and NICOS use a
MasterMACS:

* the first ``min(N, M)`` clients each *own* one axis: they enable it, then
  move it back and forth by relative moves (``S02=±1``, ``S00=2``), wait for
  ``R82`` = 1 and read the position ``R12``. A relative move makes a move that
  ran twice (or ran after a NAK) visible: the position would be off by a step.
  A move counts as *completed exactly* when ``R12`` is the expected position
  to the increment (position factor 1000: 0.001 mm);
* the other clients poll every axis (``R12``, ``R10``, ``R82``, ``R86``).

Every request must be answered ACK with its own header within ``--timeout``.
Anything else is counted by kind: ``lost`` (no reply in time, or the
connection closed), ``mismatch`` (a reply with another request's header),
``NAK``/``CAN`` (refused), ``not exact`` (a move that ended elsewhere: lost,
run twice, or lied about). The exit status is 1 if any request was lost or
any move was not exact, 2 for a bad argument, else 0.

Reported: requests served and per second, errors by kind, p50/p99/max
latency (round trip of one request, from a log-bucket histogram: about 2%
resolution, bounded memory), moves started and completed exactly, and the
server process's resident memory (VmRSS) and open file descriptors before the
clients come, with them at the start and at the end, and after they leave
(Linux ``/proc``). The suite runs a 20-second version
(``tests/test_soak.py``).
"""
from __future__ import annotations

import argparse
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from tcp_bridge.errors import MalformedReply  # noqa: E402
from tcp_bridge.wire import REPLY_SIZE, Reply, Status, decode_reply  # noqa: E402

STEP = 1.0  # mm per relative move
TOLERANCE = 0.0005  # mm: half an increment at position factor 1000
MOVE_DEADLINE = 30.0  # s: a 1 mm move takes ~0.1 s; R82 must show 1 within this


# --- latency histogram ------------------------------------------------------------------


class Histogram:
    """Round-trip times in log-spaced buckets (ratio 1.02) from 10 us to 100 s."""

    RATIO = 1.02
    LOW = 1e-5

    def __init__(self) -> None:
        self.counts: Counter[int] = Counter()
        self.n = 0
        self.max = 0.0

    def add(self, seconds: float) -> None:
        bucket = max(0, int(math.log(max(seconds, self.LOW) / self.LOW, self.RATIO)))
        self.counts[bucket] += 1
        self.n += 1
        self.max = max(self.max, seconds)

    def merge(self, other: "Histogram") -> None:
        self.counts.update(other.counts)
        self.n += other.n
        self.max = max(self.max, other.max)

    def quantile(self, q: float) -> float:
        if not self.n:
            return math.nan
        rank = q * (self.n - 1)
        seen = 0
        for bucket in sorted(self.counts):
            seen += self.counts[bucket]
            if seen > rank:
                return self.LOW * self.RATIO ** (bucket + 0.5)  # the bucket's middle
        return self.max


# --- the bridge process -----------------------------------------------------------------


class Server:
    """``tcp-bridge serve --simulate`` in its own process; its RSS and descriptors."""

    def __init__(self, axes: int, connections: int) -> None:
        self.log = tempfile.TemporaryFile(mode="w+")  # never a pipe that could fill up
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate", "--axes", str(axes),
             "--port", "0", "--maintenance-port", "-1", "--max-connections", str(connections),
             # every client of the soak is on this host: let it take every slot
             "--max-per-host", str(connections)],
            stdout=subprocess.PIPE, stderr=self.log, text=True, cwd=ROOT)
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if "listening on 127.0.0.1:" not in line:
            self.stop()
            raise RuntimeError(f"the bridge did not start: {line!r} {self.errors()!r}")
        self.port = int(line.split("127.0.0.1:")[1].split()[0])

    def rss(self) -> int:
        """Resident memory in bytes (VmRSS)."""
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS")

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))

    def errors(self) -> str:
        self.log.seek(0)
        return self.log.read()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        return self.proc.returncode


# --- clients ----------------------------------------------------------------------------


@dataclass
class Tally:
    requests: int = 0
    errors: Counter = field(default_factory=Counter)
    moves_started: int = 0
    moves_exact: int = 0
    latency: Histogram = field(default_factory=Histogram)
    details: List[str] = field(default_factory=list)  # the first few problems, for the report

    def problem(self, kind: str, detail: str) -> None:
        self.errors[kind] += 1
        if len(self.details) < 10:
            self.details.append(f"{kind}: {detail}")

    def merge(self, other: "Tally") -> None:
        self.requests += other.requests
        self.errors.update(other.errors)
        self.moves_started += other.moves_started
        self.moves_exact += other.moves_exact
        self.latency.merge(other.latency)
        self.details.extend(other.details[:10 - len(self.details)])


class Lost(Exception):
    """No reply: the connection closed or the reply did not come in time."""


class Client(threading.Thread):
    def __init__(self, port: int, axes: List[int], own: Optional[int], timeout: float,
                 pause: float, ready: threading.Barrier, stop: threading.Event) -> None:
        super().__init__(daemon=True, name=f"soak-client-{own or 'poll'}")
        self.port, self.axes, self.own = port, axes, own
        self.timeout, self.pause = timeout, pause
        self.ready, self.stopping = ready, stop
        self.tally = Tally()

    def ask(self, sock: socket.socket, line: str) -> Optional[Reply]:
        """One request; the reply if it was ACK with the request's own header, else None."""
        start = time.perf_counter()
        sock.sendall(line.encode() + b"\r")
        data = b""
        while len(data) < REPLY_SIZE:
            try:
                chunk = sock.recv(REPLY_SIZE - len(data))
            except socket.timeout:
                raise Lost(f"{line}: no reply within {self.timeout:g} s") from None
            if not chunk:
                raise Lost(f"{line}: connection closed after {len(data)} bytes")
            data += chunk
        self.tally.latency.add(time.perf_counter() - start)
        self.tally.requests += 1
        try:
            reply = decode_reply(data)
        except MalformedReply as exc:
            self.tally.problem("mismatch", f"{line}: {exc}")
            return None
        head = line.split("=")[0]
        axis, kind, cmd = int(head[:-3]), head[-3], int(head[-2:])
        if (reply.axis, reply.kind, reply.cmd) != (axis, kind, cmd):
            self.tally.problem("mismatch", f"{line}: reply {data!r}")
            return None
        if reply.status is not Status.ACK:
            self.tally.problem(reply.status.name, line)
            return None
        return reply

    def run(self) -> None:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=self.timeout) as sock:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                position = self.setup(sock)
                self.ready.wait(self.timeout)
                while not self.stopping.is_set():
                    if self.own is not None and position is not None:
                        position = self.move(sock, position)
                    else:
                        self.poll(sock)
        except Lost as exc:
            self.tally.problem("lost", str(exc))
        except (OSError, threading.BrokenBarrierError) as exc:
            self.tally.problem("lost", f"connection: {exc}")

    def setup(self, sock: socket.socket) -> Optional[float]:
        if self.own is None:
            return None
        a = self.own
        for line in (f"{a}S05=50", f"{a}S06=500", f"{a}S04=1"):  # mm/s, mm/s^2, enable
            if self.ask(sock, line) is None:
                return None
        reply = self.ask(sock, f"{a}R12")
        return float(reply.value) if reply is not None and reply.value else None

    def move(self, sock: socket.socket, position: float) -> float:
        a = self.own
        step = STEP if int(round(position)) % 2 == 0 else -STEP
        if self.ask(sock, f"{a}S02={step:g}") is None or self.ask(sock, f"{a}S00=2") is None:
            return self.resync(sock, position)
        self.tally.moves_started += 1
        deadline = time.monotonic() + MOVE_DEADLINE
        while True:
            reply = self.ask(sock, f"{a}R82")
            if reply is not None and reply.value == "1":
                break
            if time.monotonic() > deadline:
                self.tally.problem("not exact", f"axis {a}: R82 never became 1")
                return self.resync(sock, position)
            self.sleep()
        reply = self.ask(sock, f"{a}R12")
        expected = position + step
        if reply is None or reply.value is None:
            return self.resync(sock, position)
        got = float(reply.value)
        if abs(got - expected) <= TOLERANCE:
            self.tally.moves_exact += 1
        else:
            self.tally.problem("not exact", f"axis {a}: at {got:g} after a move to {expected:g}")
        self.sleep()
        return got

    def resync(self, sock: socket.socket, position: float) -> float:
        """After a failed request: where the axis really is, to go on from there."""
        reply = self.ask(sock, f"{self.own}R12")
        return float(reply.value) if reply is not None and reply.value else position

    def poll(self, sock: socket.socket) -> None:
        for a in self.axes:
            for cmd in ("R12", "R10", "R82", "R86"):
                if self.stopping.is_set():
                    return
                self.ask(sock, f"{a}{cmd}")
                self.sleep()

    def sleep(self) -> None:
        if self.pause:
            self.stopping.wait(self.pause)


# --- the run ----------------------------------------------------------------------------


@dataclass
class Report:
    clients: int
    axes: int
    duration: float
    tally: Tally
    rss: Dict[str, int]  # "before", "start", "end", "after"
    fds: Dict[str, int]
    server_exit: int
    server_log: str

    @property
    def lost(self) -> int:
        return self.tally.errors["lost"]

    @property
    def not_exact(self) -> int:
        return self.tally.errors["not exact"]

    @property
    def ok(self) -> bool:
        return self.lost == 0 and self.not_exact == 0 and not self.tally.errors

    def lines(self) -> List[str]:
        t, h = self.tally, self.tally.latency
        mb = {k: v / 2**20 for k, v in self.rss.items()}
        errors = ", ".join(f"{k} {v}" for k, v in sorted(t.errors.items())) or "none"
        out = [
            f"soak: {self.clients} clients, {self.axes} axes, {self.duration:.1f} s, "
            "tcp-bridge serve --simulate",
            f"requests served: {t.requests} ({t.requests / self.duration:.0f}/s); "
            f"errors by kind: {errors}",
            f"latency: p50 {h.quantile(0.5) * 1e3:.2f} ms, p99 {h.quantile(0.99) * 1e3:.2f} ms, "
            f"max {h.max * 1e3:.1f} ms",
            f"moves: started {t.moves_started}, completed exactly {t.moves_exact}",
            f"server RSS: {mb['before']:.1f} MB before the clients, {mb['start']:.1f} MB at "
            f"start, {mb['end']:.1f} MB at end, {mb['after']:.1f} MB after they left",
            f"server descriptors: {self.fds['before']} before the clients, {self.fds['start']} "
            f"at start, {self.fds['end']} at end, {self.fds['after']} after they left",
        ]
        out += [f"  {d}" for d in t.details]
        return out


def run(clients: int = 16, axes: int = 8, duration: float = 600.0, *, pause: float = 0.001,
        timeout: float = 30.0, say: Callable[[str], None] = lambda s: None) -> Report:
    server = Server(axes, max(64, clients + 8))
    try:
        time.sleep(0.5)  # let the bridge settle before the first figure
        rss, fds = {"before": server.rss()}, {"before": server.fds()}
        stop = threading.Event()
        ready = threading.Barrier(clients + 1)
        owners = list(range(1, axes + 1))
        workers = [Client(server.port, owners, owners[i] if i < len(owners) else None,
                          timeout, pause, ready, stop) for i in range(clients)]
        for w in workers:
            w.start()
        ready.wait(timeout * 2)  # every client connected, movers enabled
        rss["start"], fds["start"] = server.rss(), server.fds()
        say(f"soak: {clients} clients on 127.0.0.1:{server.port}, {duration:g} s")
        started = time.monotonic()
        while not stop.wait(min(30.0, max(0.0, started + duration - time.monotonic()))):
            if time.monotonic() >= started + duration:
                break
            done = sum(w.tally.requests for w in workers)
            say(f"  {time.monotonic() - started:5.0f} s: {done} requests, RSS "
                f"{server.rss() / 2**20:.1f} MB, {server.fds()} descriptors")
        rss["end"], fds["end"] = server.rss(), server.fds()
        elapsed = time.monotonic() - started
        stop.set()
        for w in workers:
            w.join(timeout * 2)
        # Connections closed: wait (bounded) for the server to close its side too.
        deadline = time.monotonic() + 10
        while server.fds() > fds["before"] and time.monotonic() < deadline:
            time.sleep(0.05)
        rss["after"], fds["after"] = server.rss(), server.fds()
        tally = Tally()
        for w in workers:
            tally.merge(w.tally)
    finally:
        code = server.stop()
    return Report(clients, axes, elapsed, tally, rss, fds, code, server.errors())


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="bench/soak.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--clients", type=int, default=16)
    p.add_argument("--axes", type=int, default=8)
    p.add_argument("--duration", type=float, default=600.0, metavar="SECONDS")
    p.add_argument("--pause", type=float, default=0.001, metavar="SECONDS",
                   help="pause of each client between requests (default 0.001)")
    args = p.parse_args(argv)
    if not (args.clients >= 1 and 1 <= args.axes <= 60 and args.duration > 0 and args.pause >= 0):
        p.error("need --clients >= 1, --axes 1..60, --duration > 0, --pause >= 0")
    report = run(args.clients, args.axes, args.duration, pause=args.pause,
                 say=lambda s: print(s, flush=True))
    for line in report.lines():
        print(line)
    warnings = [l for l in report.server_log.splitlines() if l.strip()]
    print(f"server exit status {report.server_exit}; {len(warnings)} lines on its stderr")
    for line in warnings[:10]:
        print(f"  {line}")
    if report.lost or report.not_exact:
        print("FAILED: requests lost or moves not exact", file=sys.stderr)
        return 1
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
