"""The bridge's Channel Access motor records (issue 33): ``python bench/epics_records.py [-n 30]``.

``tcp-bridge serve --simulate --epics BENCH:`` runs as a subprocess on a free CA port
(loopback only), a pyepics client in this process:

1. **put-to-completion latency of a zero-length move**: ``caput(BENCH:m2.VAL, <where
   it is>, wait=True)`` ``-n`` times. Each is a whole motor-record cycle: DMOV 1 -> 0,
   a fresh readback through the PSI pipeline (the drive decides whether it is a move),
   DMOV 0 -> 1, the monitors sent, then the put's completion.
2. **monitor update rate**: RBV monitor events per second while the axis moves at
   a constant 5 mm/s for 4 s (a subscriber is what makes the record poll).

Goals (**chosen**): zero-length put-to-completion p50 < 100 ms (a delay an operator
would notice); RBV updates while moving >= 4 per second (a readback that looks live
on a screen). The record polls every MOVING_PERIOD (0.1 s) start to start while the
axis moves, so 10 per second at best: the second ratio printed is of that pace.
Figures, ratios and the verdicts are printed; nothing is asserted.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tcp_bridge.epics.readback import MOVING_PERIOD  # noqa: E402
from tests.epics_harness import Served, ca_env  # noqa: E402

GOAL_P50_MS = 100.0
GOAL_RATE = 4.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=30, help="zero-length puts (default 30)")
    args = parser.parse_args()
    env = ca_env()
    os.environ.update({k: v for k, v in env.items() if k.startswith("EPICS_")})
    import epics  # after the environment: libca reads it when its context is made

    served = Served(["--simulate", "--axes", "2"], prefix="BENCH:", env=env)
    try:
        pv = "BENCH:m2"
        assert epics.caput(f"{pv}.CNEN", 1, wait=True, timeout=30) == 1
        here = epics.caget(f"{pv}.RBV", use_monitor=False)
        times = []
        for _ in range(args.n):
            t = time.perf_counter()
            assert epics.caput(f"{pv}.VAL", here, wait=True, timeout=30) == 1
            times.append((time.perf_counter() - t) * 1000)
        times.sort()
        p50 = statistics.median(times)
        p99 = times[min(len(times) - 1, int(len(times) * 0.99))]
        print(f"zero-length move, put-to-completion over {args.n} puts: p50 {p50:.1f} ms, "
              f"p99 {p99:.1f} ms; goal p50 < {GOAL_P50_MS:g} ms: "
              f"{'met' if p50 < GOAL_P50_MS else 'NOT met'} ({p50 / GOAL_P50_MS:.2f} of it)")

        stamps = []
        monitor = epics.PV(f"{pv}.RBV", auto_monitor=True,
                           callback=lambda **kw: stamps.append(time.perf_counter()))
        monitor.wait_for_connection(10)
        epics.caput(f"{pv}.VELO", 5.0, wait=True)
        epics.caput(f"{pv}.ACCL", 0.01, wait=True)
        epics.caput(f"{pv}.VAL", here + 30.0)  # no wait: 6 s of travel
        time.sleep(1.0)  # past the ramp
        start = len(stamps)
        time.sleep(4.0)
        rate = (len(stamps) - start) / 4.0
        epics.caput(f"{pv}.STOP", 1, wait=True)
        pace = 1.0 / MOVING_PERIOD
        print(f"RBV monitor updates while moving at 5 mm/s: {rate:.1f} per second; "
              f"goal >= {GOAL_RATE:g}/s: {'met' if rate >= GOAL_RATE else 'NOT met'} "
              f"({rate / GOAL_RATE:.2f} of it; {rate / pace:.2f} of the {pace:g}/s poll pace)")
    finally:
        served.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
