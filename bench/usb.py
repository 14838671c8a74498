"""ReadObject over the emulated USB bus (``epos-link sim --usb``):
``python bench/usb.py [--requests 300] [--runs 3]``.

A client process under ``umockdev-wrapper`` (real pyusb and libusb, the
``libusb-package`` build) reads 0x1000/0 from the simulated EPOS4 in a loop;
the unit is served from this process. Printed per run and as medians over runs:

* round trip of one ReadObject (p50, p90) and requests per second;
* the CPU the testbed helper and the client spend while the client waits 1 s on a
  read that never gets an answer (a silent simulator): what the held reap saves
  against libusb spinning on an emulated node that always polls ready.

Nothing is asserted; the figures say what emulated USB costs next to the pty/TCP
links (``bench/sim.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from typing import Any

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import LinkOptions
from epos_link.simulator.usb_link import UsbLink, unavailable_reason

CLIENT = r"""
import json, sys, time
from epos_link.client import EposClient
from epos_link.errors import EposTimeoutError
n = int(sys.argv[1])
with EposClient.open("usb://", timeout=2.0, retries=0, late_answer_timeout=0.01) as c:
    c.read_object(0, 0x1000, 0)
    times = []
    for _ in range(n):
        t = time.perf_counter()
        c.read_object(0, 0x1000, 0)
        times.append(time.perf_counter() - t)
    print(json.dumps({"times": times}), flush=True)
    sys.stdin.readline()               # the bench silences the simulator now
    cpu = time.process_time()
    try:
        c.read_object(0, 0x1000, 0, timeout=1.0)
    except EposTimeoutError:
        pass
    print(json.dumps({"client_cpu": time.process_time() - cpu}), flush=True)
    sys.stdin.readline()
"""


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_run(link: UsbLink, requests: int) -> dict[str, Any]:
    env = dict(os.environ, **link.environment)
    proc = subprocess.Popen(link.command([sys.executable, "-c", CLIENT, str(requests)]), text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        times = json.loads(proc.stdout.readline())["times"]
        link.servers[0].options.silent = True
        helper_cpu = cpu_seconds(link.proc.pid)
        proc.stdin.write("\n")
        proc.stdin.flush()
        client_cpu = json.loads(proc.stdout.readline())["client_cpu"]
        helper_cpu = cpu_seconds(link.proc.pid) - helper_cpu
        proc.stdin.write("\n")
        proc.stdin.flush()
        proc.wait(30)
    finally:
        link.servers[0].options.silent = False
        if proc.poll() is None:
            proc.kill()
    times.sort()
    return {"p50_ms": 1000 * statistics.median(times), "p90_ms": 1000 * times[int(0.9 * len(times))],
            "per_s": len(times) / sum(times), "helper_cpu_ms": 1000 * helper_cpu,
            "client_cpu_ms": 1000 * client_cpu}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=300)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    reason = unavailable_reason()
    if reason:
        print(f"bench/usb.py: the USB testbed is unavailable: {reason}", file=sys.stderr)
        return 2
    sim = Epos4Simulator(1, [])
    link = UsbLink([sim], ["BENCH0001"], LinkOptions()).start()
    rows = []
    try:
        for run in range(args.runs):
            row = one_run(link, args.requests)
            rows.append(row)
            print(f"run {run + 1}: ReadObject p50 {row['p50_ms']:.2f} ms, p90 {row['p90_ms']:.2f} ms, "
                  f"{row['per_s']:.0f}/s; 1 s wait for a silent device: helper "
                  f"{row['helper_cpu_ms']:.0f} ms CPU, client {row['client_cpu_ms']:.0f} ms CPU")
    finally:
        link.close()
        sim.close()
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(f"median of {args.runs} runs ({args.requests} requests each): ReadObject p50 "
          f"{med['p50_ms']:.2f} ms, p90 {med['p90_ms']:.2f} ms, {med['per_s']:.0f}/s; "
          f"1 s wait: helper {med['helper_cpu_ms']:.0f} ms CPU, client {med['client_cpu_ms']:.0f} ms CPU")
    return 0


if __name__ == "__main__":
    sys.exit(main())
