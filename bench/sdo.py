"""canopen ``node.sdo[...].raw`` through the EPOS4 gateway path versus canopen on a
virtual CAN bus: ``python bench/sdo.py [--runs 5] [-n 300]``.

Both read the statusword of the same simulated drives. Paths measured:

* canopen RemoteNode on the python-can virtual bus (no epos_link at all);
* connect_node over a pty to the simulated EPOS4, the EPOS4 itself (node 0);
* connect_node over a pty, a drive behind the gateway (node 2: serial + SDO on CAN).

Prints the median time per read of several runs and the ratios to canopen.
The link is not throttled, so this is software cost, not wire time.
"""
from __future__ import annotations

import argparse
import logging
import statistics
import time
from typing import Callable

import canopen

from epos_link import canopen_adapter
from epos_link.client import EposClient
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import PtyLink
from epos_link.simulator.od import EDS_PATH


def per_call(fn: Callable[[], object], n: int, runs: int) -> float:
    fn()
    samples = []
    for _ in range(runs):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n)
    return statistics.median(samples)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("-n", type=int, default=300)
    args = ap.parse_args()
    logging.getLogger("canopen").setLevel(logging.ERROR)
    # Software cost only: the simulated bus's frame time (222 us per transfer) is off.
    with Epos4Simulator(1, [2], can_bitrate=None) as sim:
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface="virtual", channel=sim.channel, receive_own_messages=False)
        can_node = canopen.RemoteNode(2, str(EDS_PATH))
        net.add_node(can_node)
        link = PtyLink(sim).start()
        client = EposClient.open(link.path)
        own = canopen_adapter.connect_node(client, 0)
        behind = canopen_adapter.connect_node(client, 2)
        t_can = per_call(lambda: can_node.sdo["Statusword"].raw, args.n, args.runs)
        t_own = per_call(lambda: own.sdo["Statusword"].raw, args.n, args.runs)
        t_behind = per_call(lambda: behind.sdo["Statusword"].raw, args.n, args.runs)
        client.close()
        link.close()
        net.disconnect()
    print(f"node.sdo['Statusword'].raw, median of {args.runs} runs x {args.n} reads:")
    print(f"  canopen on virtual CAN bus (node 2)        {t_can * 1e3:7.3f} ms")
    print(f"  gateway path, EPOS4 itself (node 0, pty)   {t_own * 1e3:7.3f} ms   "
          f"ratio {t_own / t_can:5.2f}")
    print(f"  gateway path, drive behind it (node 2)     {t_behind * 1e3:7.3f} ms   "
          f"ratio {t_behind / t_can:5.2f}")


if __name__ == "__main__":
    main()
