"""How a move starts, and how the bridge knows that it did (safety rule 2 and 4).

A move is prepared with writes that start nothing (mode, target, bit 4 low),
then started by exactly one write per axis, the *start write*, and proven by
reading the drive: profile position by the set-point acknowledge (sw bit 12,
CiA 402-2 6.7.1), homing by its status bits 13/12/10 (6.6), profile velocity by
60FFh and the controlword read back (6.9 has no handshake). If the answer to a
start write is lost, the write may or may not have arrived: the drive is read
back until that is known, and only a node silent for the whole bound leaves
the outcome unknown. A move NAK'd once a start write had gone out is reported
with what the drive showed after the halt (:mod:`.outcome`: "outcome unknown").

A garbled answer is a lost one: the epos_link client retries a transfer whose
answer fails its CRC or framing (``CrcError``, ``EposTimeoutError``) once, then
raises, and :class:`~tcp_bridge.bus.sdo.SdoPort` turns that into
:class:`~tcp_bridge.bus.sdo.NodeSilent`. So every transfer of a move is tried
again within its bound: before the start write because each step there is
idempotent and starts nothing, after it because the drive is read back until
it says whether it took the move.

A relative move (PSI 00=2) goes its distance from where the axis stands: the
bridge adds it to the position demand value 6062h and starts an absolute
move. CiA 402-2 6.7 lets cw bit 6 count from the *preceding target* (60F2h
relative option 00, the default), which after a halted move is where that
move would have ended, not where the axis stopped. 6062h is CiA 402-2's own
alternative (60F2h option 01, "relative to the position demand value"): at
rest after a finished move it equals that move's target exactly, so steps add
up without the following error (60F4h) that 6064h would add to each step;
after a halt it is where the halt ramp ended. 60F2h itself is optional in
CiA 402-2 and no public maxon source at hand lists it for the EPOS4, so the
bridge does not rely on it. A drive that refuses 6062h is read at 6064h.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial
from typing import (TYPE_CHECKING, Callable, Final, List, Optional, Sequence, Tuple, TypeVar,
                    Union)

from ..cia402_words import (CONTROLWORD, MODES_DISPLAY, TARGET_POSITION, TARGET_VELOCITY, Cw,
                            Deadline, Mode, Sw)
from ..errors import DeviceFailure, OutcomeUnknown
from ..bus.sdo import NodeSilent
from .outcome import NotStarted, report_failed_start

if TYPE_CHECKING:
    from .drive import Cia402
    from .together import Together

log = logging.getLogger("tcp_bridge.motion")

T = TypeVar("T")
POSITION_DEMAND: Final = 0x6062  # CiA 402-2 6.7: the trajectory generator's output
POSITION_ACTUAL: Final = 0x6064
SOFTWARE_POSITION_LIMIT: Final = 0x607D  # sub 1 min, sub 2 max (CiA 402-2 6.5.2)


@dataclass(frozen=True)
class PositionMove:
    target: int
    relative: bool
    # Position demand 6062h before the start write (set by _prepare): a NAK'd move
    # whose drive has left it had started (tcp_bridge.motion.outcome).
    origin: Optional[int] = None


@dataclass(frozen=True)
class VelocityMove:
    velocity: int


@dataclass(frozen=True)
class HomingMove:
    pass


Move = Union[PositionMove, VelocityMove, HomingMove]


def _pp_base(what: PositionMove) -> int:
    return Cw.ENABLE_OPERATION | Cw.CHANGE_SET_IMMEDIATELY | (Cw.RELATIVE if what.relative else 0)


class MoveStarts:
    """The move half of :class:`~tcp_bridge.motion.Cia402` (mixed in there).

    Its methods take ``self: "Cia402"``: they use the whole drive. mypy cannot
    check a mixin's self type against a subclass defined later, hence the
    ``type: ignore[misc]`` on each signature (the bodies are checked).
    """

    def move(self: "Cia402", moves: Sequence[Tuple["Cia402", Move]],  # type: ignore[misc]
             together: Optional["Together"] = None) -> None:
        """Start ``moves`` (pairs of drive and move) in one bus job.

        Used alone for one axis and together for a master and its slaves on the
        same bus: every axis must be enabled, then each is prepared, then the
        start writes go out back to back, so the axes start within a few SDO
        round trips of each other. Each drive's ``moving_ack`` (R86) is 0 from
        here and 1 once it accepted its move. Raises on the first failure; once
        a start write has gone out, every axis of the move is halted first, or
        owes a halt if it is silent (rule 4: NAK leaves nothing moving).

        ``together``: the profile line or master/slave move these drives are part
        of (:mod:`.together`); each joins it once it accepted its move. A motion
        that another member already ended is not started here.
        """
        for drive, _ in moves:
            drive.moving_ack = 0  # spec 86: 0 before the move ...
            drive.together = None  # ... which ends its part in any earlier motion
        if together is not None and together.ended_by is not None:
            ender, why = together.ended_by
            raise NotStarted(f"{self.port.name}: not started: {ender.port.name} left the "
                             f"line ({why})")
        deadline = Deadline(self._clock, self.timing.ack_timeout)  # the whole move's bound
        # Retries before the start write end half-way, so that a move they let start
        # still has half the bound to be proven (read back) before its answer is due.
        retries = Deadline(self._clock, self.timing.ack_timeout / 2)
        for drive, _ in moves:
            # Every axis can move, or none is touched.
            drive._again(drive.require_enabled, retries)
            drive._again(drive.ensure_supervised, retries)  # issue 23: never unwatched
        prepared: List[Tuple["Cia402", Move]] = [
            (drive, drive._again(partial(drive._prepare, what, deadline), retries))
            for drive, what in moves]
        sent = False
        accepted = 0
        try:
            for i, (drive, what) in enumerate(prepared):
                sent = True
                drive._start(what, deadline)
                accepted = i + 1
                drive.moving_ack = 1  # ... and 1 once the drive accepted it
                if together is not None:
                    together.join(drive)
            for drive, what in prepared:
                drive._finish(what, deadline)
        except BaseException as exc:
            if together is not None:
                together.abandon()  # the request is NAK: its halts are the job's (plan.job)
            if sent:
                for drive, _ in prepared:
                    drive.halt_or_owe()
                if isinstance(exc, Exception):
                    report_failed_start(prepared, accepted, exc)
            raise

    def _again(self: "Cia402", step: Callable[[], T], deadline: Deadline) -> T:  # type: ignore[misc]
        """``step``, a read or a write that starts nothing and may be repeated, tried
        again after a lost or garbled answer until ``deadline``, then NodeSilent."""
        while True:
            try:
                return step()
            except NodeSilent as exc:
                if deadline.expired():
                    raise
                log.info("%s: no usable answer (%s); trying again", self.port.name, exc)
                self._sleep(max(self.timing.poll_interval, 0.01))

    def _prepare(self: "Cia402", what: Move, deadline: Deadline) -> Move:  # type: ignore[misc]
        """Everything before the start write: idempotent, starts nothing. Returns the
        move to start: a relative one becomes absolute, from where the axis stands."""
        if isinstance(what, PositionMove):
            self.set_mode(Mode.PROFILE_POSITION, deadline)
            origin = self._standing_position()
            what = PositionMove(origin + what.target if what.relative else what.target,
                                relative=False, origin=origin)
            self._within_limits(what.target)
            halt = self.port.read(CONTROLWORD, 0) & Cw.HALT
            self.port.write(TARGET_POSITION, 0, what.target)
            # Bit 4 low (keeping halt as it is), so that the start write is an edge.
            self.write_while_enabled(_pp_base(what) | halt)
            self.wait_status(lambda sw: not sw & Sw.OP_MODE_12, deadline.time_left(),
                             "set-point acknowledge low")
        elif isinstance(what, VelocityMove):
            if self.port.read(MODES_DISPLAY, 0) != Mode.PROFILE_VELOCITY:
                self.set_mode(Mode.PROFILE_VELOCITY, deadline)  # halts first: rule 2
        else:
            self.set_mode(Mode.HOMING, deadline)
            self.write_while_enabled(Cw.ENABLE_OPERATION | Cw.HALT)  # bit 4 low
        return what

    def _within_limits(self: "Cia402", target: int) -> None:  # type: ignore[misc]
        """Refuse (NAK, nothing started) a target beyond the drive's 607Dh.

        What an EPOS4 does with such a target is in no public maxon source:
        CiA 402-2 6.5.2 lets a drive clamp it, and the EPOS4 error table has
        8A82h "software position limit". Clamped, the axis would stop short and
        R82 would say "reached" at the limit; faulted, the move would end in a
        fault. Neither is what the client asked, so the bridge never sends it:
        the limits are read from the drive (whoever wrote them), and min >= max
        (limits switched off) or a drive without 607Dh lets every target pass.
        The simulator's choice (clamp) is in epos_link/simulator/setpoints.py.
        """
        try:
            low = self.port.read(SOFTWARE_POSITION_LIMIT, 1)
            high = self.port.read(SOFTWARE_POSITION_LIMIT, 2)
        except NodeSilent:
            raise
        except DeviceFailure:  # an abort: no software limits on this drive
            return
        if low < high and not low <= target <= high:
            raise DeviceFailure(f"{self.port.name}: target {target} is beyond the software "
                                f"position limits 607Dh ({low}..{high}); the move was not started")

    def _standing_position(self: "Cia402") -> int:  # type: ignore[misc]
        """Where a relative move counts from: 6062h, else 6064h (see the module doc)."""
        try:
            return self.port.read(POSITION_DEMAND, 0)
        except NodeSilent:
            raise
        except DeviceFailure:  # an abort: this drive has no 6062h
            return self.port.read(POSITION_ACTUAL, 0)

    def _start(self: "Cia402", what: Move, deadline: Deadline) -> None:  # type: ignore[misc]
        """The start write(s) of ``what``, and the proof that the drive took them."""
        if isinstance(what, VelocityMove):
            # Running unhalted, the new 60FFh is itself the start; halted, the
            # release of halt is. Both are read back if an answer is lost.
            try:
                halted = self._again(lambda: self.port.read(CONTROLWORD, 0), deadline) & Cw.HALT
                # Issue 30 finding 6: the state is read just before 60FFh goes out, as
                # before every controlword with enable operation (write_while_enabled). A
                # drive in QUICK STOP ACTIVE gets nothing but what keeps it there (CiA
                # 402-2 6.4.1: with 605Ah = 5..8, the EPOS4 default 6, it stays there at
                # rest), and a running move's new speed is not one it takes.
                self._again(self.require_enabled, deadline)
            except DeviceFailure as exc:  # before any write of the move's start
                raise NotStarted(str(exc)) from exc
            self._write_confirmed(TARGET_VELOCITY, what.velocity, deadline)
            if halted:
                self._write_confirmed(CONTROLWORD, Cw.ENABLE_OPERATION, deadline)
            else:
                # The 60FFh write starts nothing by itself in a drive that left
                # OPERATION ENABLED in the round trip since that read (CiA 402-2 6.9:
                # the profile velocity generator runs only there); the reply says what
                # the drive does, so it is read once more (rule 4).
                self._again(self.require_enabled, deadline)
            return
        word = (_pp_base(what) | Cw.NEW_SET_POINT if isinstance(what, PositionMove)
                else Cw.ENABLE_OPERATION | Cw.NEW_SET_POINT)  # edge, halt released
        try:
            self.write_while_enabled(word)
        except NodeSilent as exc:
            log.warning("%s: no answer to the move's start write (%s); reading back",
                        self.port.name, exc)
            self._resolve_edge(what, word, deadline)
            return
        except DeviceFailure as exc:  # not enabled (not written), or the write's abort
            raise NotStarted(str(exc)) from exc
        sw = self._await_acceptance(what, deadline)
        if isinstance(what, HomingMove) and sw & Sw.OP_MODE_13:
            raise DeviceFailure(f"{self.port.name}: homing error (statusword 0x{sw:04X})")

    def _await_acceptance(self: "Cia402", what: Move, deadline: Deadline) -> int:  # type: ignore[misc]
        """Poll the statusword after an answered start write until the drive shows it took
        the move; a lost or garbled poll is read again (the move may be running)."""
        while True:
            try:
                sw = self.statusword()
            except NodeSilent as exc:
                self._silent(exc, deadline)
                continue
            if _accepted(what, sw):
                return sw
            if deadline.expired():
                seen = ("set-point acknowledge" if isinstance(what, PositionMove)
                        else "homing started")
                raise DeviceFailure(f"{self.port.name}: {seen} not seen within "
                                    f"{self.timing.ack_timeout:g} s (statusword 0x{sw:04X})")
            self._sleep(self.timing.poll_interval)

    def _resolve_edge(self: "Cia402", what: Move, word: int, deadline: Deadline) -> None:  # type: ignore[misc]
        """Rule 4: after a lost answer to an edge of bit 4, read back until it is known."""
        while True:
            try:
                cw = self.port.read(CONTROLWORD, 0)
                sw = self.statusword()
            except NodeSilent as exc:
                self._silent(exc, deadline)
                continue
            arrived = (cw & 0xFFFF) == word
            if arrived and _accepted(what, sw):
                log.warning("%s: the start write had arrived; the move started", self.port.name)
                return
            if deadline.expired():
                # Read after the last write of the word: not there means it never took effect.
                failure = DeviceFailure if arrived else NotStarted
                raise failure(f"{self.port.name}: the move did not start (controlword "
                              f"0x{cw:04X}, statusword 0x{sw:04X})")
            if not arrived:
                # It never arrived: nothing started, so sending it again is the first start.
                try:
                    self.write_while_enabled(word)
                except NodeSilent:
                    pass  # read back again
                except DeviceFailure as exc:  # refused or aborted: still nothing started
                    raise NotStarted(str(exc)) from exc
                continue
            self._sleep(self.timing.poll_interval)

    def _write_confirmed(self: "Cia402", index: int, value: int, deadline: Deadline) -> None:  # type: ignore[misc]
        """Write an object whose write may start motion; after a lost answer, read it
        back (writing again only when it certainly did not arrive)."""
        def send() -> None:
            if index == CONTROLWORD:
                self.write_while_enabled(value)  # it carries enable operation
            else:
                self.port.write(index, 0, value)

        try:
            send()
            return
        except NodeSilent as exc:
            log.warning("%s: no answer to the start write of 0x%04X (%s); reading back",
                        self.port.name, index, exc)
        mask = 0xFFFF if index == CONTROLWORD else -1
        while True:
            try:
                held = self.port.read(index, 0)
            except NodeSilent as exc:
                self._silent(exc, deadline)
                continue
            if held & mask == value & mask:
                log.warning("%s: the start write of 0x%04X had arrived", self.port.name, index)
                return
            if deadline.expired():
                raise NotStarted(f"{self.port.name}: 0x{index:04X} holds {held}, not "
                                 f"{value}: the move did not start")
            try:
                send()
                return
            except NodeSilent:
                continue

    def _silent(self: "Cia402", exc: Exception, deadline: Deadline) -> None:  # type: ignore[misc]
        if deadline.expired():
            raise OutcomeUnknown(f"{self.port.name}: outcome unknown: the node stayed silent "
                                 f"after the move's start write ({exc}); the axis may be "
                                 "moving") from exc
        self._sleep(max(self.timing.poll_interval, 0.01))

    def _finish(self: "Cia402", what: Move, deadline: Deadline) -> None:  # type: ignore[misc]
        """Profile position handshake clean-up (bit 4 low); the move runs regardless.

        Not for homing, where bit 4 falling would interrupt the homing (CiA 402-2
        6.6.1.1), nor for profile velocity, which has no handshake. Repeating it
        is harmless, so a lost answer is tried again until ``deadline``.
        """
        if not isinstance(what, PositionMove):
            return
        try:
            # Only while enabled: a quick stop since the start must not be undone.
            self._again(partial(self.write_while_enabled, _pp_base(what)), deadline)
        except DeviceFailure as exc:
            log.warning("%s: set-point handshake not closed (%s); the next move closes it",
                        self.port.name, exc)


def _accepted(what: Move, sw: int) -> bool:
    if isinstance(what, PositionMove):
        return bool(sw & Sw.OP_MODE_12)  # set-point acknowledge
    # Homing: in progress (13/12/10 = 0/0/0), attained (x/1/x) or error (1/x/x).
    return bool(sw & (Sw.OP_MODE_12 | Sw.OP_MODE_13)) or not sw & Sw.TARGET_REACHED


__all__ = ["HomingMove", "Move", "MoveStarts", "OutcomeUnknown", "PositionMove", "VelocityMove"]
