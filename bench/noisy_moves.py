"""Moves under reply corruption: ``python bench/noisy_moves.py [--moves 240] [--corrupt 0.05]``.

Issue 35. The bridge serves the simulated EPOS4 through the real ``epos`` path
(``tests/bridge_sim.py``: EposClient over MAXON SERIAL V2, in-process), with
each byte of the EPOS4's answers corrupted with probability ``--corrupt`` (the
faults of ``epos-link sim --corrupt``). One client makes relative 1 mm moves
of drive 2 (``2S00=2``), waiting for rest after each, and compares every answer
with what the simulated drive did:

* an ACK'd move must have moved exactly one step and started once;
* a NAK'd move that moved must be logged "outcome unknown" with the position
  read back (6064h) and have R86 = 1 afterwards (tcp_bridge/motion/outcome.py);
* no move may start twice.

The bound and the client's timeout are a quarter of the defaults (ack_timeout
0.5 s, client timeout 0.1 s; ``--ack-timeout``, ``--client-timeout``), so that a
garbled answer costs as much of the bound as with the defaults, in a quarter of
the time. Exit status 1 if a goal is missed.
"""
from __future__ import annotations

import argparse
import logging
import os
import re
import sys
import time
from typing import List

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from epos_link.simulator.link import LinkOptions  # noqa: E402
from tcp_bridge.wire import Status  # noqa: E402
from tests.bridge_sim import SimBridge  # noqa: E402

FACTOR = 1000
TARGET_REACHED = 0x0400


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: List[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=240)
    parser.add_argument("--corrupt", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=35)
    parser.add_argument("--ack-timeout", type=float, default=0.5)
    parser.add_argument("--client-timeout", type=float, default=0.1)
    args = parser.parse_args()
    lines = Lines()
    logging.getLogger("tcp_bridge").addHandler(lines)
    logging.getLogger("tcp_bridge").setLevel(logging.WARNING)
    b = SimBridge(drives=(2,), timing={"ack_timeout": args.ack_timeout},
                  client_timeout=args.client_timeout)
    acks = naks = nak_moved = nak_moved_logged = nak_moved_r86 = twice = inexact = 0
    nak_still = nak_still_logged = 0
    start = time.monotonic()
    try:
        b.ok("2S04=1", "2S05=50", "2S06=1000", "2S02=1")
        b.transport.add_noise(LinkOptions(corrupt=args.corrupt, seed=args.seed))

        def at_rest() -> bool:
            return bool(b.now(2).statusword & TARGET_REACHED) and b.velocity(2) == 0
        for i in range(args.moves):
            position, starts = b.position(2), b.now(2).motion_starts
            mark = len(lines.lines)
            status = b.ask("2S00=2").status
            b.wait_until(at_rest, why="drive 2 never came to rest")
            step, started = b.position(2) - position, b.now(2).motion_starts - starts
            twice += started > 1
            if status is Status.ACK:
                acks += 1
                inexact += (step, started) != (FACTOR, 1)
                continue
            naks += 1
            logged = [t for t in lines.lines[mark:]
                      if "outcome unknown" in t and re.search(r"position -?\d+ \(6064h\)", t)]
            b.wait_until(lambda: b.engine.guards["can1"].health.refusal(2) is None,
                         why="the bus was never served again")
            if started:
                nak_moved += 1
                nak_moved_logged += bool(logged)
                r86 = b.ask("2R86")
                nak_moved_r86 += r86.status is Status.ACK and r86.value == "1"
            else:
                nak_still += 1
                nak_still_logged += bool(logged)
    finally:
        b.close()
    print(f"{args.moves} relative moves, {args.corrupt:.0%} of reply bytes corrupted (seed "
          f"{args.seed}), ack_timeout {args.ack_timeout:g} s, client timeout "
          f"{args.client_timeout:g} s, {time.monotonic() - start:.0f} s")
    print(f"ACK {acks} (not exactly one step: {inexact}); NAK {naks}: moved {nak_moved} "
          f"(logged 'outcome unknown' with the position: {nak_moved_logged}; R86 = 1 after: "
          f"{nak_moved_r86}), did not move {nak_still} (of which logged 'outcome unknown': "
          f"{nak_still_logged}); started twice: {twice}")
    met = (inexact == 0 and twice == 0 and nak_moved_logged == nak_moved
           and nak_moved_r86 == nak_moved)
    print(f"goal: every NAK'd move that moved logged 'outcome unknown' with the position "
          f"and R86 = 1, every ACK one exact step, nothing started twice: "
          f"{'met' if met else 'NOT met'}")
    sys.exit(0 if met else 1)


if __name__ == "__main__":
    main()
