"""What a NAK'd move did: "outcome unknown" in the log, with what the drive showed (issue 35).

A move is NAK'd for one of two kinds of reason, and the client must be able to
tell them apart, since a client that sends a NAK'd move again moves twice if
the first one ran:

* **Nothing started**: the failure came before any start write went out, or the
  drive proves the start write never took effect (:class:`NotStarted`: it was
  refused before it was written, answered with an abort, or read back without
  the new word). A plain NAK; sending the move again is the first start.
* **Outcome unknown**: a start write went out and then the answers failed (a
  garbled or lost answer after the start write until the move's bound ran out,
  :class:`~tcp_bridge.motion.OutcomeUnknown`; no set-point acknowledge seen in
  time), or one axis of a multi-axis move failed after another had started.
  Every axis of the move is halted first (rule 4), then each axis whose start
  write went out is read back (position actual 6064h, position demand 6062h,
  statusword 6041h), and one WARNING line says ``outcome unknown``, why, and
  what each drive showed. R86 (spec: "Moving Acknowledgement, 0 = not started,
  1 = started") is set to 1 for an axis whose position demand value 6062h has
  left where it stood before the start write (CiA 402-2 6.7: the trajectory
  generator's output moves only once a set-point was taken), so a client that
  reads R86 and R12 after the NAK can decide whether to send the move again.

Reading back must not hold up the NAK (a drive that owes its halt gets it only
with the next command): each object is read once (the port itself tries a
garbled answer again, :func:`~tcp_bridge.bus.sdo.retry_garbled`), a drive stops
being read at its first failure, and a drive that owes its halt is not read at
all (its node is silent). What could not be read says so in the same line.
Nothing here writes to a drive: the halt is
:meth:`~tcp_bridge.motion.Cia402.halt_or_owe`'s.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING, List, Optional, Sequence, Tuple

from epos_link.cia402 import describe_statusword

from ..cia402_words import STATUSWORD
from ..errors import DeviceFailure

if TYPE_CHECKING:
    from .drive import Cia402
    from .start import Move

log = logging.getLogger("tcp_bridge.motion")

POSITION_ACTUAL = 0x6064
POSITION_DEMAND = 0x6062  # CiA 402-2 6.7: the trajectory generator's output


class NotStarted(DeviceFailure):
    """The drive shows that a move's start write did not take effect: nothing started."""


def _shown(drive: "Cia402", origin: Optional[int]) -> Tuple[str, bool]:
    """What ``drive`` shows now, for the log line, and whether it has left ``origin``
    (its position demand before the start write; None: not known)."""
    if drive.halt_owed:
        return "not read: its node is silent (the halt is sent before its next command)", False
    wanted = [(POSITION_ACTUAL, "position"), (STATUSWORD, "statusword")]
    if origin is not None:
        wanted.insert(1, (POSITION_DEMAND, "position demand"))
    parts: List[str] = []
    started = False
    for index, name in wanted:
        try:
            value = drive.port.read(index, 0)
        except DeviceFailure as exc:
            parts.append(f"{name} not read ({exc})")
            break
        if index == STATUSWORD:
            parts.append(f"statusword 0x{value:04X} ({describe_statusword(value)})")
        elif index == POSITION_DEMAND:
            started = value != origin
            parts.append(f"position demand {value} (6062h; {origin} before the start write: "
                         f"{'it started' if started else 'it did not start'})")
        else:
            parts.append(f"position {value} (6064h)")
    return ", ".join(parts), started


def report_failed_start(prepared: Sequence[Tuple["Cia402", "Move"]], accepted: int,
                        failure: BaseException) -> None:
    """After a move failed once its first start write had gone out, and every axis was
    halted: log what is known (module docstring). ``accepted`` axes had taken their
    move; the next one is the one whose start failed."""
    unknown = accepted if not isinstance(failure, NotStarted) else None
    if accepted == 0 and unknown is None:
        return  # the drive proves nothing started: a plain NAK
    seen: List[str] = []
    for i, (drive, what) in enumerate(prepared[:accepted + 1]):
        if i == accepted and unknown is None:
            continue
        origin = getattr(what, "origin", None)
        shown, started = _shown(drive, origin)
        if i < accepted:
            seen.append(f"{drive.port.name} had started its move and was halted: {shown}")
            continue
        if started:
            drive.moving_ack = 1  # R86 = 1: the drive took the set-point
        seen.append(f"{drive.port.name} {'started' if started else 'may have started'} its "
                    f"move and was halted: {shown}")
    log.warning("%s: outcome unknown: the move is answered NAK (%s); %s",
                prepared[0][0].port.name, failure, "; ".join(seen))


__all__ = ["NotStarted", "report_failed_start"]
