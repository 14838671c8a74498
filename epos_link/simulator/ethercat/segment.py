"""A line of simulated EtherCAT slaves: a frame in, the frame as it comes back out. Pure.

Each datagram of a frame passes the slaves in order, as on a real segment
(ETG.1000.4 5.4): auto-increment addresses count up at each slave, configured
addresses match one station, broadcasts reach all, logical ones go through
each FMMU; the working counter sums what every slave did. The last slave's
open port 1 sends the frame back, so the reply is the processed frame.

The ESC also sets bit 1 of the first source MAC byte ("locally administered")
on a frame it processed (Beckhoff ESC datasheet, section I, "frame
processing"); SOEM uses that to tell which port a frame came back through.
DL status 0x0110 tells the master the topology (ports 0 and 1 open with
communication, the last slave's port 1 closed), from which SOEM finds each
slave's parent.
"""
from __future__ import annotations

from typing import Optional, Sequence

from .esc import DL_STATUS
from .frame import FrameError, build_frame, parse_frame
from .slave import EthercatSlave

__all__ = ["Segment"]


def _dl_status(last: bool) -> int:
    # bit 0 PDI operational; bits 4/5 link on ports 0/1; per port two bits: loop
    # closed, communication (ports 2 and 3 are not implemented: closed, none).
    status = 0x0001 | 0x0010 | 0x0200 | 0x1000 | 0x4000
    return status | (0x0400 if last else 0x0020 | 0x0800)


class Segment:
    """The slaves in wiring order; :meth:`handle` is one pass of a frame."""

    def __init__(self, slaves: Sequence[EthercatSlave]) -> None:
        if not slaves:
            raise ValueError("a segment has at least one slave")
        self.slaves = list(slaves)
        for n, slave in enumerate(self.slaves):
            slave.esc.set_u16(DL_STATUS, _dl_status(n == len(self.slaves) - 1))

    def handle(self, frame: bytes, now: float) -> Optional[bytes]:
        """The frame as it returns to the master, or None for a frame an ESC drops."""
        try:
            ethernet, datagrams = parse_frame(frame)
        except FrameError:
            return None
        for slave in self.slaves:
            slave.tick(now)
        for dg in datagrams:
            for slave in self.slaves:
                slave.process(dg, now)
        ethernet = ethernet[:6] + bytes([ethernet[6] | 0x02]) + ethernet[7:]
        return build_frame(ethernet, datagrams)

    def tick(self, now: float) -> None:
        for slave in self.slaves:
            slave.tick(now)
