"""The bridge's safety rule and the CiA 402 sequences: the one place that moves a drive.

Every controlword the bridge writes, every NMT reset it sends and every move
it starts goes through :class:`Cia402`. Commands cite this module
(:mod:`tcp_bridge.operations`: 00, 04, 07, 16, 17, 85 and the slave moves of
29/30 and 90). Synchronous code for a bus worker thread; every wait polls the
statusword (6041h) and is bounded by a :class:`Deadline`; running out of time
raises :class:`~tcp_bridge.errors.DeviceFailure`, answered NAK. References:
CiA 402-2 V4.0 section 6.4 (6.4.1.3 controlword, 6.4.1.4 statusword, state
table), 6.6 homing, 6.7 profile position, 6.9 profile velocity; CiA 301 7.2.8
(NMT); PSI gateway spec rev 2.3, command table (section 4).

The safety rule
===============

1. **The bridge never lowers the state of an axis that reports OPERATION
   ENABLED, and never sends it an NMT reset, unless a client asked for exactly
   that**: S04=0 (disable) or S16 (reset node). (S17, fault reset, acts only on
   a drive in FAULT, which is not enabled.) Even then a moving axis is first
   brought to rest with halt (cw bit 8, profile deceleration 6084h) and the
   bridge waits for standstill (sw bit 10 with halt set) within
   ``ack_timeout``; if it does not come to rest the request is NAK and the axis
   stays enabled and halted. Disable is then Disable Operation (07h) before
   Shutdown (06h): on an EPOS4, Shutdown switches the drive function off without
   a ramp (605Bh = 0), Disable Operation ramps first (605Ch = 1). The guard is
   :meth:`Cia402._lower`, which every lowering goes through.
2. **Motion starts only on a move command** (S00=1, 2, 3, 9; S90). Enable
   enters OPERATION ENABLED with halt set; stop (S00=8) sets halt and clears the
   target velocity 60FFh; a mode change (S07, or a move in another mode) halts
   first and leaves halt set. A move releases halt in the same controlword
   write that gives the drive its *own* new set-point, so no earlier target or
   velocity is ever resumed.
3. **A power cycle is detected from evidence, never from a timeout**: the
   statusword shows SWITCH ON DISABLED or NOT READY TO SWITCH ON after the
   bridge last saw the drive powered (READY TO SWITCH ON or above) without
   having asked for that; the drive no longer holds the parameter values the
   bridge wrote; or (CAN backend) the node's boot-up message arrived. After one,
   the next enable does what spec 04 says ("If PowerCycle then NodeReset and
   WriteParameter before enable sequence"): NMT reset, wait for the node, write
   the parameters, enable. An axis in OPERATION ENABLED is never reset by it.
4. **A move's answer tells the truth.** ACK means the drive accepted the move:
   profile position acknowledged the new set-point (sw bit 12 after the rising
   edge of cw bit 4); profile velocity has the new target velocity with halt
   released; homing shows "in progress" or "attained". NAK means the move did
   not start. When the answer to the write that starts a move is lost (the
   node was silent, so the write may or may not have arrived), the bridge reads
   the statusword and the controlword back before it answers; only if the node
   stays silent for the whole ``ack_timeout`` is the outcome unknown, and then
   the reply is NAK and the log says "outcome unknown". Writes before the
   start write are idempotent and start nothing, so a NAK from them is true.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from enum import Enum
from typing import Callable, Final, Optional, Protocol, Sequence, Tuple, Union

from epos_link.cia402 import State, state_from_statusword

from .cia402_words import (CONTROLWORD, MODES_DISPLAY, MODES_OF_OPERATION, STATUSWORD,
                           TARGET_POSITION, TARGET_VELOCITY, Cw, Deadline, Mode, Sw, Timing,
                           decode_state)
from .errors import DeviceFailure
from .sdo import NodeSilent, SdoPort

log = logging.getLogger(__name__)

class Why(Enum):
    """Who asked for a lowering of the state (rule 1)."""

    CLIENT_DISABLE = "S04=0"
    CLIENT_RESET_NODE = "S16"
    POWER_CYCLE = "enable after a power cycle"  # never allowed on an enabled axis


CLIENT_REQUESTS: Final = frozenset({Why.CLIENT_DISABLE, Why.CLIENT_RESET_NODE})
# States from which a fall back to SWITCH ON DISABLED is evidence of a power cycle.
_POWERED: Final = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                             State.OPERATION_ENABLED})
_BOOT_STATES: Final = frozenset({State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON})


class SafetyRefusal(DeviceFailure):
    """The bridge refused to lower the state of an enabled axis (rule 1)."""


class OutcomeUnknown(DeviceFailure):
    """The node went silent after a write that starts a move (rule 4)."""


class Restore(Protocol):
    """What enable needs to know about the parameters the bridge keeps (rule 3)."""

    def differs(self) -> Optional[str]:
        """Why the drive no longer holds the bridge's values, None if it does."""

    def write(self) -> None:
        """Write every stored drive parameter (spec 85)."""

    def ignore_differences(self) -> None:
        """From now on :meth:`differs` answers None."""


@dataclass(frozen=True)
class PositionMove:
    target: int
    relative: bool


@dataclass(frozen=True)
class VelocityMove:
    velocity: int


@dataclass(frozen=True)
class HomingMove:
    pass


Move = Union[PositionMove, VelocityMove, HomingMove]


class Cia402:
    """The sequences of one drive, through its :class:`~tcp_bridge.sdo.SdoPort`.

    It watches every statusword the port reads (polls of R10, R04, R82 too), so
    a drive that falls back to SWITCH ON DISABLED is noticed whoever read it.
    """

    def __init__(self, port: SdoPort, timing: Timing = Timing(), *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.port = port
        self.timing = timing
        self._clock = clock
        self._sleep = sleep
        self._last_state: Optional[State] = None
        self.power_cycle_evidence: Optional[str] = None
        self.restore_pending = False  # reset by us: the parameters go back before enable
        self._own_reset_until = float("-inf")  # boot-ups before this are our own reset's
        watch = getattr(port, "watch", None)
        if watch is not None:
            watch(STATUSWORD, self._observe)

    # -- observation -------------------------------------------------------------

    def _observe(self, statusword: int) -> None:
        state = state_from_statusword(statusword)
        if state is None:
            return
        if state in _BOOT_STATES and self._last_state in _POWERED:
            self.note_power_cycle(f"the drive fell back from {self._last_state.name} "
                                  f"to {state.name}")
        self._last_state = state

    def note_power_cycle(self, why: str) -> None:
        """Evidence of a power cycle (rule 3): the next enable restores the drive."""
        if self.power_cycle_evidence is None:
            log.warning("%s: power cycle detected: %s", self.port.name, why)
        self.power_cycle_evidence = why

    def note_bootup(self) -> None:
        """A boot-up message (CAN backend; canopen's heartbeat callback, state 0)."""
        if self._clock() < self._own_reset_until:
            return  # the boot-up that answers the bridge's own NMT reset
        self.note_power_cycle("boot-up message received")

    def _expect(self, state: Optional[State]) -> None:
        # The bridge itself is about to take the drive there: not evidence.
        self._last_state = state

    def statusword(self) -> int:
        sw = self.port.read(STATUSWORD, 0)
        if getattr(self.port, "watch", None) is None:
            self._observe(sw)
        return sw

    def state(self) -> State:
        return decode_state(self.statusword())

    def wait_status(self, done: Callable[[int], bool], timeout: float, what: str) -> int:
        """Poll 6041h until ``done(statusword)``; DeviceFailure after ``timeout`` seconds."""
        deadline = self._clock() + timeout
        while True:
            sw = self.statusword()
            if done(sw):
                return sw
            if self._clock() >= deadline:
                raise DeviceFailure(f"{self.port.name}: {what} not seen within {timeout:g} s "
                                    f"(statusword 0x{sw:04X})")
            self._sleep(self.timing.poll_interval)

    def require_enabled(self) -> int:
        sw = self.statusword()
        state = decode_state(sw)
        if state is not State.OPERATION_ENABLED:
            raise DeviceFailure(f"{self.port.name}: not enabled ({state.name})")
        return sw

    # -- rule 1: lowering ----------------------------------------------------------

    def _lower(self, why: Why, deadline: Deadline) -> State:
        """The guard every lowering passes: refuse on an enabled axis unless a client
        asked; bring an enabled axis to rest first. Returns the state found."""
        state = self.state()
        if state is State.OPERATION_ENABLED:
            if why not in CLIENT_REQUESTS:
                raise SafetyRefusal(f"{self.port.name}: refused ({why.value}): the axis is "
                                    "enabled and no client asked to disable or reset it")
            self.bring_to_rest(deadline)
        elif state is State.QUICK_STOP_ACTIVE:
            # Still on its quick stop ramp, maybe: let it finish (sw bit 10).
            self.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                             "end of quick stop")
        return state

    def bring_to_rest(self, deadline: Deadline) -> None:
        """Halt (cw bit 8) and wait for standstill (sw bit 10) within ``deadline``."""
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.HALT)
        self.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                         "standstill after halt (the axis stays enabled and halted)")

    def disable(self) -> None:
        """S04=0: at rest first, then Disable Operation (07h), then Shutdown (06h)."""
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        state = self._lower(Why.CLIENT_DISABLE, deadline)
        if state is State.OPERATION_ENABLED:
            self._step(Cw.SWITCH_ON, State.SWITCHED_ON, deadline)  # disable operation
            state = State.SWITCHED_ON
        if state is State.SWITCHED_ON:
            self._step(Cw.SHUTDOWN, State.READY_TO_SWITCH_ON, deadline)
        elif state is State.QUICK_STOP_ACTIVE:  # at rest (_lower): disable voltage
            self._expect(None)
            self._step(Cw.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED, deadline)
        # not ready, switch on disabled, ready, fault: the drive function is already off

    def reset_node(self, why: Why, wait: bool = False) -> None:
        """NMT reset node (S16, or enable after a power cycle with ``wait``).

        NMT is unconfirmed (CiA 301 7.2.8.3.2.1): S16 answers once it is sent;
        the power-cycle path waits for the node to boot (:meth:`wait_for_node`).
        Either way the next enable writes the parameters back first.
        """
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        self._lower(why, deadline)
        self._expect(None)
        grace = self.timing.reset_delay + self.timing.reset_timeout + 1.0
        self._own_reset_until = self._clock() + grace
        self.port.nmt_reset()
        self.power_cycle_evidence = None
        self.restore_pending = True
        if wait:
            self.wait_for_node()
            self._own_reset_until = self._clock() + 1.0  # its boot-up may still be in flight

    def fault_reset(self) -> None:
        """S17: rising edge of cw bit 7 (transition 15), then cw 00h; no-op without a fault."""
        sw = self.statusword()
        if decode_state(sw) is State.FAULT_REACTION_ACTIVE:
            sw = self.wait_status(lambda s: decode_state(s) is State.FAULT,
                                  self.timing.state_timeout, "FAULT after fault reaction")
        if not sw & Sw.FAULT:
            return  # a reset must never disable a running axis
        self._expect(None)
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)  # bit 7 low: the edge is ours
        self.port.write(CONTROLWORD, 0, Cw.FAULT_RESET)
        self.wait_status(lambda s: not s & Sw.FAULT, self.timing.state_timeout,
                         "fault cleared")
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)

    def wait_for_node(self) -> None:
        """After an NMT reset: wait ``reset_delay``, then poll until the node shows the
        state a drive boots into (SWITCH ON DISABLED, or FAULT if it boots faulty).

        Powered states would be the node before the reset took effect, and a
        silent node is still booting; both are waited out within ``reset_timeout``.
        """
        self._sleep(self.timing.reset_delay)
        deadline = self._clock() + self.timing.reset_timeout
        booted = (State.SWITCH_ON_DISABLED, State.FAULT)
        while True:
            try:
                state = self.state()
                if state in booted:
                    return
                why = f"still {state.name}"
            except DeviceFailure as exc:
                why = str(exc)
            if self._clock() >= deadline:
                raise DeviceFailure(f"{self.port.name}: not back {self.timing.reset_timeout:g} s "
                                    f"after NMT reset ({why})")
            self._sleep(max(self.timing.poll_interval, 0.01))

    # -- enable ----------------------------------------------------------------------

    def enable(self, restore: Optional[Restore] = None) -> None:
        """S04=1: to OPERATION ENABLED with halt set, one checked step at a time.

        An enabled axis is left exactly as it is. After a power cycle (rule 3)
        the node is reset and the parameters written first.
        """
        state = self.state()
        if state is State.OPERATION_ENABLED:
            return
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            raise DeviceFailure(f"{self.port.name}: in {state.name}; reset it (S17) first")
        if self.power_cycle_evidence is None and not self.restore_pending and restore is not None:
            differs = restore.differs()
            if differs is not None:
                self.note_power_cycle(differs)
        if self.power_cycle_evidence is not None:
            self.reset_node(Why.POWER_CYCLE, wait=True)
        if self.restore_pending:
            if restore is not None:
                restore.write()
                still = restore.differs()
                if still is not None:
                    # A drive that does not keep a value as written would look
                    # power cycled at every enable: trust only the other evidence.
                    log.warning("%s: after writing the parameters, %s; parameter values "
                                "are no longer taken as evidence of a power cycle",
                                self.port.name, still)
                    restore.ignore_differences()
            self.restore_pending = False
        self._enable_steps(Deadline(self._clock, self.timing.ack_timeout))

    def _enable_steps(self, deadline: Deadline) -> None:
        # Halt rides along on every step (bit 8 is ignored outside OPERATION
        # ENABLED), so the drive arrives there halted: rule 2.
        steps = {
            State.SWITCH_ON_DISABLED: (Cw.SHUTDOWN, State.READY_TO_SWITCH_ON),
            State.READY_TO_SWITCH_ON: (Cw.SWITCH_ON, State.SWITCHED_ON),
            State.SWITCHED_ON: (Cw.ENABLE_OPERATION, State.OPERATION_ENABLED),
            State.QUICK_STOP_ACTIVE: (Cw.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        }
        state = self.state()
        for _ in range(8):  # at most 4 steps are ever needed; the rest is slack
            if state is State.OPERATION_ENABLED:
                return
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise DeviceFailure(f"{self.port.name}: in {state.name}; reset it (S17) first")
            if state is State.NOT_READY_TO_SWITCH_ON:  # self test: wait, it moves by itself
                state = decode_state(self.wait_status(
                    lambda sw: decode_state(sw) is not State.NOT_READY_TO_SWITCH_ON,
                    deadline.time_left(self.timing.state_timeout), "end of self test"))
                continue
            command, target = steps[state]
            if target is State.SWITCH_ON_DISABLED:
                self._expect(None)
            state = self._step(command | Cw.HALT, target, deadline)
        raise DeviceFailure(f"{self.port.name}: enable did not reach OPERATION_ENABLED")

    def _step(self, command: int, target: State, deadline: Deadline) -> State:
        self.port.write(CONTROLWORD, 0, command)
        return decode_state(self.wait_status(
            lambda sw: decode_state(sw) is target, deadline.time_left(self.timing.state_timeout),
            target.name))

    # -- modes -----------------------------------------------------------------------

    def set_mode(self, mode: int, deadline: Optional[Deadline] = None) -> None:
        """S07 and moves: write 6060h and wait until 6061h shows it (CiA 402-2 6.3).

        A mode change of an enabled axis halts it first and leaves halt set (rule 2).
        """
        deadline = deadline or Deadline(self._clock, self.timing.ack_timeout)
        if self.port.read(MODES_DISPLAY, 0) == mode:
            return
        if decode_state(self.statusword()) is State.OPERATION_ENABLED:
            self.bring_to_rest(deadline)
        self.port.write(MODES_OF_OPERATION, 0, mode)
        timeout = deadline.time_left(self.timing.state_timeout)
        stop_at = Deadline(self._clock, timeout)
        while self.port.read(MODES_DISPLAY, 0) != mode:
            if stop_at.expired():
                raise DeviceFailure(f"{self.port.name}: mode {mode} not displayed in 6061h "
                                    f"within {timeout:g} s")
            self._sleep(self.timing.poll_interval)

    # -- rule 2: stop ---------------------------------------------------------------

    def halt(self) -> None:
        """S00=8: halt (cw bit 8) in any mode and clear the target velocity.

        Halt stays set until the next move. An axis that is not enabled is not
        moving. 60FFh is cleared as well, so that even a controlword written by
        someone else cannot resume a velocity move; a drive without 60FFh (no
        profile velocity mode) refuses that write, which does not matter.
        """
        if self.state() is not State.OPERATION_ENABLED:
            return
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.HALT)
        try:
            self.port.write(TARGET_VELOCITY, 0, 0)
        except NodeSilent:
            raise
        except DeviceFailure:
            pass  # the drive has no 60FFh: halt alone holds it

    # -- rule 4: moves ----------------------------------------------------------------

    def move(self, moves: Sequence[Tuple["Cia402", Move]], on_accept: Callable[[int], None]
             ) -> None:
        """Start ``moves`` (this drive's first; pairs of drive and move) in one job.

        Used alone for one axis and together for a master and its slaves on the
        same bus: each axis is prepared, then the start writes go out back to
        back, so the axes start within a few SDO round trips of each other.
        ``on_accept(i)`` is called when axis ``i`` accepted its move (R86).
        Raises on the first failure; once a start write has gone out, every
        axis of the move is halted first (rule 4: NAK leaves nothing moving).
        """
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        for drive, _ in moves:
            drive.require_enabled()  # every axis can move, or none is touched
        for drive, what in moves:
            drive._prepare(what, deadline)
        sent = False
        try:
            for i, (drive, what) in enumerate(moves):
                sent = True
                drive._start(what, deadline)
                on_accept(i)
            for drive, what in moves:
                drive._finish(what)
        except BaseException:
            if sent:
                # A start write went out: a drive may take it late, or one axis
                # of several runs alone. Halt them all, so NAK leaves none moving.
                for drive, _ in moves:
                    try:
                        drive.halt()
                    except DeviceFailure as exc:
                        log.error("%s: halt after a failed move failed: %s",
                                  drive.port.name, exc)
            raise

    def _prepare(self, what: Move, deadline: Deadline) -> None:
        """Everything before the start write: idempotent, moves nothing."""
        if isinstance(what, PositionMove):
            self.set_mode(Mode.PROFILE_POSITION, deadline)
            halt = self.port.read(CONTROLWORD, 0) & Cw.HALT
            self.port.write(TARGET_POSITION, 0, what.target)
            # Bit 4 low (keeping halt as it is), so that the start write is an edge.
            self.port.write(CONTROLWORD, 0, self._pp_base(what) | halt)
            self.wait_status(lambda sw: not sw & Sw.OP_MODE_12, deadline.time_left(),
                             "set-point acknowledge low")
        elif isinstance(what, VelocityMove):
            if self.port.read(MODES_DISPLAY, 0) != Mode.PROFILE_VELOCITY:
                self.set_mode(Mode.PROFILE_VELOCITY, deadline)  # halts first: rule 2
            self.port.write(TARGET_VELOCITY, 0, what.velocity)
        else:
            self.set_mode(Mode.HOMING, deadline)
            self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.HALT)  # bit 4 low

    @staticmethod
    def _pp_base(what: PositionMove) -> int:
        return Cw.ENABLE_OPERATION | Cw.CHANGE_SET_IMMEDIATELY | (
            Cw.RELATIVE if what.relative else 0)

    def _start_word(self, what: Move) -> int:
        if isinstance(what, PositionMove):
            return self._pp_base(what) | Cw.NEW_SET_POINT  # edge, halt released
        if isinstance(what, VelocityMove):
            return Cw.ENABLE_OPERATION  # halt released: runs at the new 60FFh
        return Cw.ENABLE_OPERATION | Cw.NEW_SET_POINT  # homing operation start

    def _accepted(self, what: Move, sw: int) -> bool:
        if isinstance(what, PositionMove):
            return bool(sw & Sw.OP_MODE_12)  # set-point acknowledge
        if isinstance(what, VelocityMove):
            return True  # decided by the controlword read back
        # Homing: in progress (13/12/10 = 0/0/0), attained (x/1/x) or error (1/x/x).
        return bool(sw & (Sw.OP_MODE_12 | Sw.OP_MODE_13)) or not sw & Sw.TARGET_REACHED

    def _start(self, what: Move, deadline: Deadline) -> None:
        """The one write that starts the move, and the proof that the drive took it."""
        word = self._start_word(what)
        try:
            self.port.write(CONTROLWORD, 0, word)
        except NodeSilent as exc:
            # The answer was lost: the write may or may not have arrived. Find out.
            log.warning("%s: no answer to the move's start write (%s); reading back",
                        self.port.name, exc)
            self._resolve_start(what, word, deadline)
            return
        if isinstance(what, VelocityMove):
            return
        sw = self.wait_status(lambda s: self._accepted(what, s), deadline.time_left(),
                              "set-point acknowledge" if isinstance(what, PositionMove)
                              else "homing started")
        if isinstance(what, HomingMove) and sw & Sw.OP_MODE_13:
            raise DeviceFailure(f"{self.port.name}: homing error (statusword 0x{sw:04X})")

    def _resolve_start(self, what: Move, word: int, deadline: Deadline) -> None:
        """Rule 4: after a lost answer, read back until the outcome is known."""
        while True:
            try:
                cw = self.port.read(CONTROLWORD, 0)
                sw = self.statusword()
            except NodeSilent as exc:
                if deadline.expired():
                    raise OutcomeUnknown(
                        f"{self.port.name}: outcome unknown: the node stayed silent after the "
                        f"move's start write ({exc}); the axis may be moving") from exc
                self._sleep(max(self.timing.poll_interval, 0.01))
                continue
            arrived = (cw & 0xFFFF) == word
            if arrived and self._accepted(what, sw):
                log.warning("%s: the start write had arrived; the move started", self.port.name)
                return
            if not arrived:
                if deadline.expired():
                    raise DeviceFailure(f"{self.port.name}: the move did not start "
                                        f"(controlword 0x{cw:04X})")
                # It never arrived: nothing started, so sending it again is the first start.
                try:
                    self.port.write(CONTROLWORD, 0, word)
                except NodeSilent:
                    pass  # loop: read back again
                continue
            if deadline.expired():
                raise DeviceFailure(f"{self.port.name}: start write arrived but the drive did "
                                    f"not accept it (statusword 0x{sw:04X})")
            self._sleep(self.timing.poll_interval)

    def _finish(self, what: Move) -> None:
        """Handshake clean-up after acceptance: bit 4 low. The move runs whatever happens.

        Not for homing, where bit 4 falling would interrupt the homing (CiA 402-2
        6.6.1.1), nor for profile velocity, which has no handshake.
        """
        if not isinstance(what, PositionMove):
            return
        word = self._start_word(what) & ~Cw.NEW_SET_POINT
        try:
            self.port.write(CONTROLWORD, 0, word)
        except DeviceFailure as exc:
            log.warning("%s: set-point handshake not closed (%s); the next move closes it",
                        self.port.name, exc)


__all__ = ["CLIENT_REQUESTS", "CONTROLWORD", "Cia402", "Cw", "Deadline", "HomingMove",
           "MODES_DISPLAY", "Mode", "OutcomeUnknown", "PositionMove", "Restore",
           "STATUSWORD", "SafetyRefusal", "State", "Sw", "TARGET_VELOCITY", "Timing",
           "VelocityMove", "Why", "decode_state"]
