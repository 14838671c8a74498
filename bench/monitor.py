"""What ``epos-link monitor`` adds to a round trip: ``python bench/monitor.py [-n 400] [--runs 5]``.

Two simulated EPOS4s serve on TCP in separate processes (``epos-link sim``);
an ``EposClient`` reads 0x6081 of node 1 ``-n`` times, first directly, then (from the
other simulator) through ``epos-link monitor --tcp`` (a separate process printing its lines to
/dev/null, recording a capture and pcapng to a temporary folder, as a user
would). Per run the median and 99th percentile of the round-trip times are
taken; the figures are the medians over ``--runs`` runs. The difference is the
monitor's cost: two extra TCP hops on loopback plus its copy. Figures only,
no assertions.
"""
from __future__ import annotations

import argparse
import os
import select
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from epos_link.client import EposClient  # noqa: E402


def start(*args: str, out: "int | None" = None) -> tuple[subprocess.Popen, str]:  # type: ignore[type-arg]
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 30)
    if not ready:
        proc.kill()
        raise SystemExit(f"{args[0]} did not start")
    line = proc.stdout.readline()  # type: ignore[union-attr]
    return proc, line.split("listening on ", 1)[1].strip()


def round_trips(url: str, n: int) -> list[float]:
    times = []
    with EposClient.open(url) as client:
        client.read_object(1, 0x6081, 0)  # warm up
        for _ in range(n):
            t = time.perf_counter()
            client.read_object(1, 0x6081, 0)
            times.append(time.perf_counter() - t)
    return times


def p99(values: list[float]) -> float:
    return sorted(values)[int(0.99 * (len(values) - 1))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=400, help="round trips per run (default 400)")
    ap.add_argument("--runs", type=int, default=5, help="runs per setup (default 5)")
    args = ap.parse_args()
    # The simulator serves one host at a time: one for the direct client, one behind the monitor.
    sim, sim_url = start("sim", "--tcp", "127.0.0.1:0")
    sim2, sim2_url = start("sim", "--tcp", "127.0.0.1:0")
    tmp = tempfile.mkdtemp(prefix="epos-bench-")
    mon, mon_url = start("monitor", sim2_url, "--tcp", "127.0.0.1:0", "--record", os.path.join(tmp, "cap.txt"),
                         "--pcapng", os.path.join(tmp, "cap.pcapng"))
    # The monitor's lines would fill the pipe: read them away in the background.
    drain = subprocess.Popen(["cat"], stdin=mon.stdout, stdout=subprocess.DEVNULL)
    try:
        rows = {"direct": [], "through monitor": []}  # type: dict[str, list[tuple[float, float]]]
        for _ in range(args.runs):  # interleaved, so load changes hit both alike
            for name, url in (("direct", sim_url), ("through monitor", mon_url)):
                t = round_trips(url, args.n)
                rows[name].append((statistics.median(t), p99(t)))
    finally:
        for proc in (mon, sim, sim2):
            proc.terminate()
            proc.wait(30)
        drain.wait(30)
    print(f"{args.n} ReadObject round trips x {args.runs} runs, medians over runs (ms)")
    print(f"{'':<18}{'p50':>8}{'p99':>8}")
    med = {}
    for name, runs in rows.items():
        med[name] = (statistics.median(r[0] for r in runs) * 1e3, statistics.median(r[1] for r in runs) * 1e3)
        print(f"{name:<18}{med[name][0]:8.3f}{med[name][1]:8.3f}")
    print(f"{'monitor adds':<18}{med['through monitor'][0] - med['direct'][0]:8.3f}"
          f"{med['through monitor'][1] - med['direct'][1]:8.3f}")
    print("(at 115200 baud the request and answer alone take 2.2 ms on the wire)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
