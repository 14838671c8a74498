"""Drives that move as one motion in their own profile modes (issue 30, "a line is one motion").

A line of command 90 on internal axes with ``profile = "drive"`` (each drive in
profile position mode, CiA 402-2 6.7) and a master with its slave (29/30) on
profile axes start together; each drive then runs its own trajectory. Should one
of them leave OPERATION ENABLED by itself (its quick stop input, a fault such as
8611h following error, its 6007h reaction), stop answering, or be halted by a
client's stop, the others would run on to their targets alone: the tool leaves
its straight line, a gantry racks. So the drives of such a move form a
:class:`Together`, and the first of them that leaves the motion ends it for all:

* **What is watched**: every statusword the bridge reads from a member
  (:meth:`tcp_bridge.motion.Cia402.observe`, whoever read it: a client's R10 or
  R82 poll, the PDO-fed status, a move's own reads) and, so that a motion nobody
  polls is watched too, the statusword :class:`Watch` reads between jobs on each
  bus worker (``poll_period``; through :meth:`~tcp_bridge.bus.sdo.SdoPort.read_status`,
  so a canopen bus with ``pdo = true`` answers from its TPDO and costs no SDO).
  A member is lost when that read finds its node silent.
* **What ends it**: a member whose state is anything but OPERATION ENABLED (CiA
  402-2 6.4.1), a lost member, or a client's stop of one member (S00=8, S90=0,
  S04=0: :mod:`tcp_bridge.plan.moves` ends it as it halts every member in the
  stop's own job). The end is recorded once: the member that ended it gets R86 =
  0 (its move was not made; the others' moves were accepted) and one ERROR line
  names it and why.
* **What the others do**: each is halted (cw bit 8, at its profile deceleration
  6084h: :meth:`~tcp_bridge.motion.Cia402.halt`) by its own bus worker, the next
  time that worker is between jobs (:meth:`Watch.maintain`), so no bus is ever
  touched from another bus's thread. A member that a new move took since is no
  longer a member (:meth:`join` of that move replaced it) and is left alone.
* **When it is over**: once every member has joined and shows target reached
  (statusword bit 10: a profile position move or a homing that ended), nothing
  more is watched. A velocity pair (S00=3) has no end of its own: it is watched
  until a stop or a new move.

The halts of the others are the drives' profile ramps, not one line (each
drive's trajectory generator is its own; a line on one profile is what CSP is
for, :mod:`.cyclic`).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Callable, List, Optional, Sequence, Set, Tuple

from epos_link.cia402 import State, state_from_statusword

from ..bus.sdo import NodeSilent
from ..cia402_words import STATUSWORD, Sw
from ..errors import DeviceFailure

if TYPE_CHECKING:
    from .drive import Cia402

log = logging.getLogger("tcp_bridge.motion")

POLL_PERIOD = 0.02  # s: a statusword read per member between jobs, no more often


class Together:
    """The drives of one profile line or master/slave move (module doc)."""

    def __init__(self, members: Sequence["Cia402"], *, ends_at_target: bool = True) -> None:
        self.members: Tuple["Cia402", ...] = tuple(members)
        self.ends_at_target = ends_at_target
        self._lock = threading.Lock()  # members are watched from their own bus threads
        self._running: Set[int] = set()  # id() of members whose move was accepted
        self._reached: Set[int] = set()
        self.ended_by: Optional[Tuple["Cia402", str]] = None
        self.over = False  # ended, or every member reached its target

    def join(self, drive: "Cia402") -> None:
        """``drive`` accepted its share of the move (its bus thread, after the start)."""
        drive.together = self
        with self._lock:
            self._running.add(id(drive))

    def seen(self, drive: "Cia402", statusword: int) -> None:
        """A statusword of ``drive`` (:meth:`~tcp_bridge.motion.Cia402.observe`)."""
        if self.over:
            return
        state = state_from_statusword(statusword)
        if state is not State.OPERATION_ENABLED:
            self.end(drive, f"{state.name if state else 'unknown state'}, "
                            f"statusword 0x{statusword:04X}")
            return
        if not self.ends_at_target or id(drive) not in self._running:
            return
        if statusword & Sw.TARGET_REACHED:
            with self._lock:
                self._reached.add(id(drive))
                if len(self._reached) == len(self.members):
                    self.over = True  # the whole motion arrived: nothing to watch

    def abandon(self) -> None:
        """The move failed (NAK): its request halts what it started; nothing to watch."""
        self.over = True

    def end(self, drive: "Cia402", why: str, *, by_client: bool = False) -> bool:
        """``drive`` left the motion (``why``): record it once; False if already over.
        ``by_client``: a client's stop of that one member, whose move was made (R86
        stays), logged as a warning; otherwise the drive left by itself (R86 = 0)."""
        with self._lock:
            if self.over:
                return False
            self.over = True
            self.ended_by = (drive, why)
        if not by_client:
            drive.moving_ack = 0  # spec 86: its move was not made
        others = [m.port.name for m in self.members if m is not drive]
        log.log(logging.WARNING if by_client else logging.ERROR, "%s left its line (%s)%s",
                drive.port.name, why,
                f"; halting {', '.join(others)} on that line" if others else "")
        return True


class Watch:
    """The statusword watch of one bus's members, run by its bus worker between jobs."""

    def __init__(self, drives: Sequence["Cia402"], period: float = POLL_PERIOD,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.drives = list(drives)
        self.period = period
        self._clock = clock
        self._next = float("-inf")

    def maintain(self) -> Optional[float]:
        """Halt members of ended motions, read the statusword of running ones when due;
        seconds until the next read, None when nothing is watched."""
        watched: List["Cia402"] = []
        for drive in self.drives:
            together = drive.together
            if together is None:
                continue
            if together.over:
                drive.together = None
                if together.ended_by is not None and together.ended_by[0] is not drive:
                    self._halt(drive, together)
                continue
            watched.append(drive)
        if not watched:
            return None
        now = self._clock()
        if now < self._next:
            return self._next - now
        self._next = now + self.period
        for drive in watched:
            together = drive.together
            if together is None or together.over:
                continue
            try:
                drive.observe(drive.port.read_status(STATUSWORD, 0))
            except NodeSilent as exc:
                together.end(drive, f"lost: {exc}")
            except DeviceFailure as exc:
                log.warning("%s: statusword not read while on a line (%s)", drive.port.name, exc)
        # A motion that ended in these reads: its other members here are halted at once.
        return 0.0 if any(d.together is not None and d.together.over for d in watched) \
            else self.period

    @staticmethod
    def _halt(drive: "Cia402", together: Together) -> None:
        # halt_or_owe logs a failure itself; a silent drive owes its halt (rule 4).
        drive.halt_or_owe()


__all__ = ["POLL_PERIOD", "Together", "Watch"]
