"""PSI latency under status page load: ``python bench/status_page.py [--seconds 10]``.

Issue 35. ``tcp-bridge serve --simulate --axes 3 --http 127.0.0.1:0`` runs as
its own process. PSI clients (``--clients``, each its own connection, in a
second process) poll ``R10``/``R12`` of the axes back to back and record each
round trip; first with the page idle, then while a third process hammers the
page: ``--page-rate`` requests a second in all (the issue measured 450-880), from
``--loaders`` threads, each GET ``/api/axes``, ``/api/history`` and ``/`` in turn,
each a new connection, plus ``--streams`` event streams that read. The page shares the bridge's event loop with the PSI ports; its budget
(tcp_bridge/status/slots.py) is what keeps the PSI clients' p99 down.

Printed: PSI requests/s, p50/p99 without and with page load, the ratio, and the
page requests answered per second. Goal: PSI p99 under load within twice its
unloaded value. Medians over ``--runs`` runs.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, List, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from tcp_bridge.wire import REPLY_SIZE  # noqa: E402

GOAL_RATIO = 2.0


def start_bridge() -> Tuple[subprocess.Popen, int, Tuple[str, int]]:
    log = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate", "--axes", "3",
         "--port", "0", "--maintenance-port", "-1", "--http", "127.0.0.1:0",
         "--max-connections", "64", "--max-per-host", "64"],
        stdout=subprocess.PIPE, stderr=log, text=True, cwd=ROOT)
    port = http = None
    while port is None or http is None:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        if not line:
            log.seek(0)
            raise RuntimeError(f"the bridge did not start: {log.read()}")
        if "listening on 127.0.0.1:" in line:
            port = int(line.split("127.0.0.1:")[1].split()[0])
        if "status page at http://" in line:
            host_port = line.split("http://")[1].strip().rstrip("/")
            host, _, p = host_port.rpartition(":")
            http = (host, int(p))
    return proc, port, http


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def psi_client(port: int, axis: int, until: float, out: Any) -> None:
    lines = [f"{axis}R10\r".encode(), f"{axis}R12\r".encode()]
    samples: List[float] = []
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        i = 0
        while time.monotonic() < until:
            t = time.perf_counter()
            sock.sendall(lines[i % 2])
            _recv_exact(sock, REPLY_SIZE)
            samples.append(time.perf_counter() - t)
            i += 1
    out.extend(samples)


def psi_process(port: int, clients: int, seconds: float, queue: Any) -> None:
    until = time.monotonic() + seconds
    results: List[List[float]] = [[] for _ in range(clients)]
    threads = [threading.Thread(target=psi_client, args=(port, 1 + i % 3, until, results[i]))
               for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    queue.put([s for r in results for s in r])


def http_get(address: Tuple[str, int], path: str) -> bool:
    try:
        with socket.create_connection(address, timeout=10) as sock:
            sock.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
            data = b""
            while chunk := sock.recv(65536):
                data += chunk
        return data.startswith(b"HTTP/1.1 200")
    except OSError:
        return False


def loader_process(address: Tuple[str, int], loaders: int, streams: int, seconds: float,
                   rate: float, queue: Any) -> None:
    start = time.monotonic()
    until = start + seconds
    answered = [0] * loaders
    sent = [0] * loaders

    def load(i: int) -> None:
        paths = ["/api/axes", "/api/history", "/"]
        every = loaders / rate  # this thread's share of the offered rate
        n = 0
        while True:
            due = start + (i / loaders + n) * every
            now = time.monotonic()
            if due >= until or now >= until:  # a thread behind its schedule stops too
                return
            if due > now:
                time.sleep(due - now)
            sent[i] += 1
            if http_get(address, paths[n % 3]):
                answered[i] += 1
            n += 1

    def stream() -> None:
        try:
            with socket.create_connection(address, timeout=10) as sock:
                sock.sendall(b"GET /api/stream HTTP/1.1\r\nHost: x\r\n\r\n")
                sock.settimeout(1.0)
                while time.monotonic() < until:
                    try:
                        if not sock.recv(65536):
                            return
                    except socket.timeout:
                        pass
        except OSError:
            pass
    threads = [threading.Thread(target=load, args=(i,)) for i in range(loaders)]
    threads += [threading.Thread(target=stream) for _ in range(streams)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    queue.put((sum(sent), sum(answered), time.monotonic() - start))


def p(samples: List[float], q: float) -> float:
    s = sorted(samples)
    return s[min(len(s) - 1, int(q * len(s)))] * 1000


def run_once(args: argparse.Namespace) -> Tuple[float, float, float, float, float, float]:
    proc, port, http = start_bridge()
    ctx = multiprocessing.get_context("spawn")
    try:
        time.sleep(1.0)  # the sampler's first samples, the probes
        q: Any = ctx.Queue()
        idle = ctx.Process(target=psi_process, args=(port, args.clients, args.seconds, q))
        idle.start()
        quiet = q.get()
        idle.join()
        q2: Any = ctx.Queue()
        pages: Any = ctx.Queue()
        loaded = ctx.Process(target=psi_process, args=(port, args.clients, args.seconds, q2))
        loader = ctx.Process(target=loader_process,
                             args=(http, args.loaders, args.streams, args.seconds + 1,
                                   args.page_rate, pages))
        loader.start()
        time.sleep(0.5)
        loaded.start()
        busy = q2.get()
        sent, answered, took = pages.get()
        loaded.join()
        loader.join()
    finally:
        proc.terminate()
        proc.wait(30)
    return (len(quiet) / args.seconds, p(quiet, 0.5), p(quiet, 0.99), p(busy, 0.5),
            p(busy, 0.99), answered / took, sent / took)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--loaders", type=int, default=16)
    parser.add_argument("--page-rate", type=float, default=600.0)
    parser.add_argument("--streams", type=int, default=8)
    args = parser.parse_args()
    print(f"PSI: {args.clients} clients polling R10/R12 of 3 simulated axes; page load: "
          f"{args.page_rate:g} requests/s from {args.loaders} threads (GET /api/axes, "
          f"/api/history, /, a connection each) and "
          f"{args.streams} streams; {args.seconds:g} s each, median of {args.runs} runs; "
          f"goal: p99 with page load <= {GOAL_RATIO:g}x without")
    rows = []
    for i in range(args.runs):
        row = run_once(args)
        rows.append(row)
        print(f"run {i + 1}: PSI {row[0]:.0f} req/s, p50/p99 {row[1]:.2f}/{row[2]:.2f} ms idle, "
              f"{row[3]:.2f}/{row[4]:.2f} ms under page load ({row[4] / row[2]:.2f}x); page "
              f"{row[6]:.0f} req/s sent, {row[5]:.0f} answered", flush=True)
    med = [statistics.median(r[k] for r in rows) for k in range(7)]
    ratio = statistics.median(r[4] / r[2] for r in rows)
    print(f"median: p99 {med[2]:.2f} ms idle, {med[4]:.2f} ms under page load: {ratio:.2f}x; "
          f"page {med[5]:.0f} req/s answered")
    print(f"goal: p99 under page load <= {GOAL_RATIO:g}x idle: "
          f"{'met' if ratio <= GOAL_RATIO else 'NOT met'}")


if __name__ == "__main__":
    main()
