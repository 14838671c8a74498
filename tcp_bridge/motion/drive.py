"""One drive's CiA 402 power sequences under the safety rule (see :mod:`tcp_bridge.motion`).

:class:`Cia402` holds enable, mode changes and stop, each bounded and checked
on the statusword, and what the bridge knows about power cycles. Mixed into it:
disable and NMT reset with the guard :meth:`Cia402._lower` that every lowering
passes (rule 1) from :mod:`.lowering`, fault reset and the wait for a node that
an NMT reset restarts from :mod:`.recovery`, the start of a move from
:mod:`.start`.

The rules as this module enforces them:

* rule 1: an enabled axis is left exactly as it is by enable; a drive on its
  quick stop ramp is let finish before enable goes on;
* rule 2: enable enters OPERATION ENABLED with halt set (it rides along on every
  step) and refuses a drive in a mode outside the allowed ones (a cyclic mode
  would follow its set-point objects at once); a mode change of an enabled axis
  halts it first and leaves halt set; stop (S00=8) sets halt and clears 60FFh;
* rule 3: a fall back to SWITCH ON DISABLED from a powered state, in any
  statusword the port reads, makes the next enable check and write the stored
  parameters; a boot-up that does not answer the bridge's own reset, or values
  that differ after such a fall back, are evidence of a power cycle, and the
  next enable then resets the node (:mod:`.lowering`: never an enabled one),
  waits for it and writes the parameters first;
* rule 4: a halt that failed after a move is owed and sent before the next
  command to that axis.
"""
from __future__ import annotations

import logging
import time
from typing import Callable, Final, FrozenSet, List, Optional, Protocol

from epos_link.cia402 import State, state_from_statusword

from ..cia402_words import (CONTROLWORD, MODES_DISPLAY, MODES_OF_OPERATION, STATUSWORD,
                            TARGET_VELOCITY, Cw, Deadline, Timing, decode_state)
from ..errors import DeviceFailure
from ..bus.sdo import NodeSilent, SdoPort
from .lowering import CLIENT_REQUESTS, Lowering, SafetyRefusal, Why
from .nmt_stopped import answering
from .recovery import Recovery
from .start import MoveStarts, OutcomeUnknown
from .supervision import Supervision
from .together import Together

log = logging.getLogger("tcp_bridge.motion")

VELOCITY_ACTUAL: Final = 0x606C

# States from which a fall back to SWITCH ON DISABLED is worth a look (rule 3).
_POWERED: Final = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                             State.OPERATION_ENABLED})
_BOOT_STATES: Final = frozenset({State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON})


class Restore(Protocol):
    """What enable needs of the parameters the bridge keeps (rule 3)."""

    def differs(self) -> Optional[str]:
        """Why the drive no longer holds the values the bridge wrote, None if it does."""

    def write(self) -> None:
        """Write every stored drive parameter (spec 85)."""

    def ignore_differences(self) -> None:
        """From now on :meth:`differs` answers None."""


class Cia402(MoveStarts, Lowering, Recovery):
    """The sequences of one drive, through its :class:`~tcp_bridge.bus.sdo.SdoPort`.

    It looks at every statusword it reads, and at those its callers read and hand it
    (:meth:`observe`: polls of R10, R82, R83, R84 too), so a drive that falls back
    to SWITCH ON DISABLED is noticed whoever read it.
    ``listeners`` are called with ``"suspect"`` (the drive may have lost its
    RAM values: read units again) and ``"reset"`` (it has: forget what was
    written to it). ``coasting`` tells whether the axis still moves while
    its power stage is off (606Ch); without it, 606Ch is read raw.
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
        self.restore_pending = True  # the first enable writes the stored parameters
        self.fell_back = False  # seen falling to SWITCH ON DISABLED since the last enable
        self.halt_owed = False  # a move's outcome was unknown and its halt not yet sent
        self.listeners: List[Callable[[str], None]] = []
        self.coasting: Callable[[], bool] = lambda: self.port.read(VELOCITY_ACTUAL, 0) != 0
        self._own_reset_until = float("-inf")  # boot-ups before this are our own reset's
        # The drive's heartbeat consumer (heartbeat_ms on a canopen bus), None without.
        self.supervision: Optional[Supervision] = None
        # Internal axis in CSP (tcp_bridge.plan.cyclic_moves): its own way to come to rest.
        self.rest: Optional[Callable[[Deadline], None]] = None
        # Spec 86 "moving acknowledgement": 0 before a move, 1 once this drive accepted
        # it (:mod:`.start`), 0 again if it left a line it was on (:mod:`.together`).
        self.moving_ack = 0
        # The profile line or master/slave move this drive's running move is part of.
        self.together: Optional[Together] = None

    # -- observation (rule 3) -----------------------------------------------------

    def observe(self, statusword: int) -> None:
        """A statusword someone else read from this drive (a client's status poll)."""
        self._observe(statusword)

    def _observe(self, statusword: int) -> None:
        state = state_from_statusword(statusword)
        if state is None:
            return
        if state in _BOOT_STATES and self._last_state in _POWERED:
            log.warning("%s: the drive fell back from %s to %s (a power cycle, or a quick "
                        "stop input): the next enable checks and writes its parameters",
                        self.port.name, self._last_state.name, state.name)
            self.restore_pending = True
            self.fell_back = True
            self._tell("suspect")
        self._last_state = state
        together = self.together
        if together is not None:  # a line is one motion (issue 30): whoever read it
            together.seen(self, statusword)

    def note_power_cycle(self, why: str) -> None:
        """Evidence of a power cycle: the next enable resets and restores the drive."""
        if self.power_cycle_evidence is None:
            log.warning("%s: power cycle detected: %s", self.port.name, why)
        self.power_cycle_evidence = why
        self._tell("suspect")

    def note_bootup(self) -> None:
        """A boot-up message (CAN backend; canopen's heartbeat callback, state 0)."""
        if self._clock() < self._own_reset_until:
            return  # the boot-up that answers the bridge's own NMT reset
        self.note_power_cycle("boot-up message received")

    def _tell(self, event: str) -> None:
        if self.supervision is not None:  # a power-up or reset may have cleared 1016h
            self.supervision.stale()
        for listener in self.listeners:
            listener(event)

    def _expect(self, state: Optional[State]) -> None:
        # The bridge itself is about to take the drive there: nothing to look at.
        self._last_state = state

    def statusword(self) -> int:
        sw = self.port.read(STATUSWORD, 0)
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

    def write_while_enabled(self, word: int, state: Optional[State] = None) -> None:
        """Write a controlword that carries "enable operation" (every move step, halt
        and handshake does) only while the drive shows OPERATION ENABLED.

        In QUICK STOP ACTIVE with 605Ah = 5..8 (the EPOS4's default is 6, maxon's
        EDS) that command is CiA 402-2 transition 16, back to OPERATION ENABLED: a
        quick stop that another master, an input or the drive's heartbeat reaction
        started while a move was being prepared would be undone, and the move
        started anyway. Read just before the write, the state leaves one SDO round
        trip for that race instead of the whole preparation; raises DeviceFailure
        (the request's NAK) and writes nothing in any other state. ``state``: the
        state the caller has just read for its own decision, so it is not read twice.
        """
        state = self.state() if state is None else state
        if state is not State.OPERATION_ENABLED:
            raise DeviceFailure(f"{self.port.name}: {state.name} (statusword read before a "
                                "controlword with enable operation): not written, nothing "
                                "started")
        self.port.write(CONTROLWORD, 0, word)

    def require_enabled(self) -> int:
        sw = self.statusword()
        state = decode_state(sw)
        if state is not State.OPERATION_ENABLED:
            raise DeviceFailure(f"{self.port.name}: not enabled ({state.name})")
        return sw

    # -- enable (rules 1 to 3) -----------------------------------------------------------

    def enable(self, restore: Optional[Restore] = None,
               modes: Optional[FrozenSet[int]] = None) -> None:
        """S04=1: to OPERATION ENABLED with halt set, one checked step at a time.

        An enabled axis is left exactly as it is. A drive in a mode outside
        ``modes`` (a cyclic mode left by another tool, or one spec 31 does not
        allow) is not enabled: in a cyclic mode it would follow its set-point
        objects at once (rule 2). After a power cycle (rule 3) the node is reset
        and the parameters written first.
        """
        state = self.state()
        if state is State.OPERATION_ENABLED:
            self.ensure_supervised()  # enabled by someone else: watched from now on
            return
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            raise DeviceFailure(f"{self.port.name}: in {state.name}; reset it (S17) first")
        if modes is not None:
            mode = self.port.read(MODES_DISPLAY, 0)
            if mode not in modes and mode != 0:  # 0: no mode, nothing can move
                log.error("%s: not enabled: the drive is in mode %d (6061h), not one of the "
                          "profile modes %s; set one with S07 first", self.port.name, mode,
                          sorted(modes))
                raise DeviceFailure(f"{self.port.name}: not enabled in mode {mode}")
        if state is State.QUICK_STOP_ACTIVE:
            self._end_of_quick_stop(Deadline(self._clock, self.timing.ack_timeout))
        if self.power_cycle_evidence is None and restore is not None:
            differs = restore.differs()
            if differs is not None and self.fell_back:
                self.note_power_cycle(f"{differs}, after a fall back to SWITCH ON DISABLED")
            elif differs is not None:
                # One changed value is not evidence (another master, a studio may
                # write it): no reset, only the bridge's values written back.
                log.warning("%s: %s, but the drive never fell back to SWITCH ON DISABLED: "
                            "not a power cycle; the stored parameters are written again",
                            self.port.name, differs)
                self.restore_pending = True
        if self.power_cycle_evidence is not None:
            self.reset_node(Why.POWER_CYCLE, wait=True)
        if self.restore_pending and restore is not None:
            restore.write()
            still = restore.differs()
            if still is not None:
                # A drive that does not keep a value as written would look power
                # cycled at every enable: from now on trust the other evidence only.
                log.warning("%s: after writing the parameters, %s; parameter values are no "
                            "longer taken as evidence of a power cycle", self.port.name, still)
                restore.ignore_differences()
        self.restore_pending = False
        self.fell_back = False
        self.ensure_supervised()  # after a reset above, which clears it
        self._enable_steps(Deadline(self._clock, self.timing.ack_timeout))

    def ensure_supervised(self) -> None:
        """Before enable and before a move: the drive's heartbeat consumer, if the bus
        table asks for one, set up once per power-up (:mod:`.supervision`); raises
        DeviceFailure (NAK) when the drive refuses it."""
        if self.supervision is not None:
            self.supervision.ensure(self.port)

    def supervise_if_enabled(self) -> None:
        """At start-up (issue 30 finding 4): a drive found in OPERATION ENABLED or on its
        quick stop ramp (a bridge restarted under a running move, another master) has
        its heartbeat consumer set up at once, before any request about it runs (a
        job the engine queues on the bus before serving). Without it the drive would
        run unwatched until a client's S04=1 or move, and a bridge killed meanwhile
        would leave it turning. A drive that refuses is logged as unsupervised (and
        ``tcp-bridge check`` shows it so, from 1016h); DeviceFailure then."""
        if self.supervision is None:
            return
        state = self.state()
        if state not in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            return  # nothing can move before a client's S04=1, which sets it up
        try:
            self.ensure_supervised()
        except DeviceFailure as exc:
            log.error("%s: found in %s at start-up and UNSUPERVISED: its heartbeat "
                      "consumer could not be set up (%s); if the bridge dies, it keeps its "
                      "last command", self.port.name, state.name, exc)
            raise
        log.info("%s: found in %s at start-up: its heartbeat consumer is on",
                 self.port.name, state.name)

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
            if state is State.QUICK_STOP_ACTIVE:
                self._end_of_quick_stop(deadline)  # rule 1: no power cut while it moves
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

    # -- modes and stop (rule 2) ----------------------------------------------------------

    def set_mode(self, mode: int, deadline: Optional[Deadline] = None) -> None:
        """S07 and moves: write 6060h and wait until 6061h shows it (CiA 402-2 6.3).

        A mode change of an enabled axis halts it first and leaves halt set.
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

    def halt(self) -> None:
        """S00=8: halt (cw bit 8) in any mode and clear the target velocity.

        Halt stays set until the next move. An axis that is not enabled is not
        driven. 60FFh is cleared as well, so that even a controlword written by
        someone else cannot resume a velocity move; a drive without 60FFh (no
        profile velocity mode) refuses that write, which does not matter. A node
        that another master put in NMT Stopped is made to answer first
        (:mod:`.nmt_stopped`): a stop must reach a moving axis.
        """
        if answering(self.port, self.state) is not State.OPERATION_ENABLED:
            self.halt_owed = False
            return
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.HALT)
        self.halt_owed = False
        try:
            self.port.write(TARGET_VELOCITY, 0, 0)
        except NodeSilent:
            raise
        except DeviceFailure:
            pass  # the drive has no 60FFh: halt alone holds it

    def halt_or_owe(self) -> None:
        """Halt after a failed move; a silent drive owes the halt (rule 4)."""
        try:
            self.halt()
        except DeviceFailure as exc:
            self.halt_owed = True
            log.error("%s: halt after a failed move failed (%s); it is sent before the next "
                      "command to this axis", self.port.name, exc)

    def settle(self) -> None:
        """Before any command to this axis: send a halt it owes (rule 4)."""
        if self.halt_owed:
            log.warning("%s: sending the halt owed since a move's outcome was unknown",
                        self.port.name)
            self.halt()


__all__ = ["CLIENT_REQUESTS", "Cia402", "OutcomeUnknown", "Restore", "SafetyRefusal", "State",
           "Why"]
