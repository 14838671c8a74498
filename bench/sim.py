"""Simulator throughput and memory: ``python bench/sim.py [--runs 5] [-n 20000] [--paced-only]``.

1. ReadObject requests/s served over the in-process ``sim://`` transport, raw
   frames (the simulator's own cost) and through ``EposClient`` (the full stack);
   medians of several runs. Goal: at least 5,000 requests/s.
2. Memory over 100,000 requests: Python heap traced with tracemalloc at
   checkpoints; it must stay flat (no growth with the request count).
3. Fault injection: 1,000 reads with 5% of reply bytes corrupted, and the
   retries the client needed.
4. ``--baud`` pacing: ReadObject/s through EposClient over a pty paced at
   115200 baud, as a fraction of the rate the wire allows (request and answer
   bytes at 10 bits each); medians of several runs.
"""
from __future__ import annotations

import argparse
import gc
import statistics
import time
import tracemalloc

from epos_link.client import EposClient
from epos_link.messages import ReadObject
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.transport import SimTransport


def raw_rate(sim: Epos4Simulator, n: int) -> float:
    link = SimTransport(sim)
    frame = ReadObject(0, 0x6041, 0).encode()
    t0 = time.perf_counter()
    for _ in range(n):
        link.write(frame)
        link.read(64, 0.5)
    return n / (time.perf_counter() - t0)


def client_rate(sim: Epos4Simulator, n: int) -> float:
    client = EposClient(SimTransport(sim))
    t0 = time.perf_counter()
    for _ in range(n):
        client.read_object(0, 0x6041, 0)
    return n / (time.perf_counter() - t0)


def memory(sim: Epos4Simulator, total: int, step: int) -> list[tuple[int, int]]:
    link = SimTransport(sim)
    frame = ReadObject(0, 0x6064, 0).encode()
    points = []
    gc.collect()
    tracemalloc.start()
    for done in range(0, total + 1, step):
        if done:
            for _ in range(step):
                link.write(frame)
                link.read(64, 0.5)
        gc.collect()
        # Count the stack's memory only, not this loop's list or tracemalloc's own.
        snap = tracemalloc.take_snapshot().filter_traces(
            [tracemalloc.Filter(False, __file__), tracemalloc.Filter(False, tracemalloc.__file__)])
        points.append((done, sum(stat.size for stat in snap.statistics("filename"))))
    tracemalloc.stop()
    return points


def faults(reads: int, corrupt: float) -> None:
    from epos_link.transports import open_transport

    with Epos4Simulator(1) as sim:
        transport = open_transport(f"sim://?corrupt={corrupt}&seed=1", simulator=sim)
        with EposClient(transport, timeout=0.02, retries=25) as client:
            for _ in range(reads):
                client.read_object(0, 0x6041, 0)
            stats = client.stats
    print(f"{reads} ReadObject with {corrupt:.0%} of reply bytes corrupted: all completed, "
          f"{stats.retries} retries ({stats.retries / reads:.2f} per read); causes {stats.failures}")


def paced(baud: int, reads: int, runs: int) -> None:
    from epos_link.messages import ReadObjectAnswer
    from epos_link.simulator.link import BITS_PER_BYTE, LinkOptions, PtyLink

    wire_bytes = len(ReadObject(0, 0x6041, 0).encode()) + len(ReadObjectAnswer(0, bytes(4)).encode())
    wire_rate = baud / BITS_PER_BYTE / wire_bytes
    rates = []
    with Epos4Simulator(1) as sim:
        link = PtyLink(sim, LinkOptions(baud=baud)).start()
        try:
            with EposClient.open(link.path, timeout=0.5) as client:
                for _ in range(runs):
                    t0 = time.perf_counter()
                    for _ in range(reads):
                        client.read_object(0, 0x6041, 0)
                    rates.append(reads / (time.perf_counter() - t0))
        finally:
            link.close()
    rate = statistics.median(rates)
    print(f"ReadObject over a pty paced at {baud} baud, median of {runs} runs of {reads}: "
          f"{rate:.0f}/s; the wire allows {wire_rate:.0f}/s ({wire_bytes} bytes of 10 bits): "
          f"{rate / wire_rate:.0%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("-n", type=int, default=20000)
    ap.add_argument("--memory-requests", type=int, default=100000)
    ap.add_argument("--paced-only", action="store_true", help="only part 4, the --baud pacing")
    args = ap.parse_args()
    if args.paced_only:
        paced(115200, 500, args.runs)
        return
    with Epos4Simulator(1) as sim:
        raw = statistics.median(raw_rate(sim, args.n) for _ in range(args.runs))
        full = statistics.median(client_rate(sim, args.n) for _ in range(args.runs))
        print(f"ReadObject over sim://, medians of {args.runs} runs of {args.n}:")
        print(f"  simulator alone (raw frames)  {raw:10.0f} requests/s  ({1e6 / raw:6.1f} us each)")
        print(f"  through EposClient            {full:10.0f} requests/s  ({1e6 / full:6.1f} us each)")
        print(f"  goal: at least 5,000 requests/s -> {'met' if raw >= 5000 else 'NOT met'}")
        points = memory(sim, args.memory_requests, args.memory_requests // 10)
        print(f"memory over {args.memory_requests} requests (tracemalloc, after gc):")
        for done, size in points:
            print(f"  after {done:7d} requests: {size / 1024:8.1f} KiB")
        growth = points[-1][1] - points[1][1]
        print(f"  growth from {points[1][0]} to {points[-1][0]} requests: {growth / 1024:+.1f} KiB")
    faults(1000, 0.05)
    paced(115200, 500, args.runs)


if __name__ == "__main__":
    main()
