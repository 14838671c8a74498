"""The power state machine of the simulated drive: 6040h controlword, 6060h modes of
operation, device control commands and faults.

Part of :class:`~epos_link.simulator.drive.Drive` (a mixin, for the size of
the module only). This half decides *what* the drive does: the transitions
0..16 of CiA 402-2 V4.0 6.4.1 (table in :mod:`epos_link.cia402`), the option
codes of 6.4.1.3 that pick a transition's reaction, a mode change (6.3) and the
faults (:mod:`~epos_link.simulator.faults`, EMCY through ``Drive.on_error``).
*How* the axis then moves (which ramp, and the end of a 605Bh/605Ch ramp, which
makes the pending transition) is :mod:`~epos_link.simulator.kinematics`. The
choices a client may notice (option code defaults, what a 605Bh/605Ch ramp
ignores, one-shot faults) are listed in :mod:`~epos_link.simulator.drive`.

* Transitions 5 (605Ch) and 8 (605Bh) of a moving axis, with option 1 "slow
  down ramp", wait in ``_pending`` while the axis stops on 6084h; the run loop
  makes them at standstill. The same request again lets the ramp go on; another
  way out of OPERATION ENABLED replaces the pending transition.
* 605Ah: option 0 "disable drive function" ends a quick stop at once
  (transition 11, then 12); transition 16 back to OPERATION ENABLED exists only
  for the "stay in quick stop" options 5..8.
* 605Eh: a fault whose reaction is the fault reaction, on a powered drive with
  605Eh not 0, keeps the power stage on during FAULT REACTION ACTIVE;
  otherwise the drive passes FAULT REACTION ACTIVE at once (transitions 13 and
  14 together), with its power stage off.
* Transitions 5, 8, 9, 11 and 12, a fault, a mode change, and halt or a
  falling bit 4 during homing (6.6.1.1) drop the pp move and stop a homing in
  progress. A power stage switched off while the axis moves is recorded in
  :attr:`Drive.safety`.
* Transition 15 (fault reset) clears 603Fh, 1001h and 60FDh and sends the EMCY
  "error reset" 0000h (CiA 301 Table 21).
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from canopen import SdoAbortedError

from ..cia402 import (
    CW,
    POWERED_STATES,
    T_FAULT,
    T_FAULT_REACTION_DONE,
    T_QUICK_STOP_DONE,
    TRANSITIONS,
    Command,
    State,
    decode_command,
)
from .faults import FAULTS, FaultSpec, Reaction, push_history
from .homing import HomingStatus, Leg
from .objects import Mode
from .od import ABORT_RANGE, ObjectStore, Value
from .safety import EventKind

__all__ = ["StateMachine"]

_RAMPED_DISABLE = {5: 0x605C, 8: 0x605B}  # transition -> its option code object


class StateMachine:
    """The state machine half of :class:`~epos_link.simulator.drive.Drive`."""

    # Set by Drive (its __init__ and _power_up).
    store: ObjectStore
    history: deque[tuple[float, int, State]]
    on_error: Callable[[int, int], None] | None
    _now: float
    _state: State
    _mode: Mode
    _cw: int
    _target: float | None
    _buffer: float | None
    _last_target: int | None
    _settle_at: float | None
    _clamped: bool
    _homing_status: HomingStatus
    _legs: deque[Leg]
    _following_error: bool
    _fault: FaultSpec | None
    _powered_at_fault: bool
    _pending: tuple[int, State] | None
    _in_event: bool

    if TYPE_CHECKING:  # provided by Drive
        @property
        def velocity_increments(self) -> float: ...

        def sync(self) -> None: ...

        def _record(self, kind: EventKind, detail: str, velocity: float) -> None: ...

        def _plan(self) -> None: ...

        def _run_until(self, t: float) -> None: ...

        def _track_goal(self, reason: str) -> None: ...

        def _home(self) -> None: ...

        def _accept_set_point(self, cw: int) -> None: ...

        def _update_ack(self) -> None: ...

    # -- commands ----------------------------------------------------------------------

    def inject_fault(self, kind: str) -> None:
        """Raise a fault now; ``kind`` is a key of :data:`FAULTS` (e.g. ``"sto"``)."""
        try:
            spec = FAULTS[kind]
        except KeyError:
            raise ValueError(f"unknown fault kind {kind!r}; expected one of {sorted(FAULTS)}") from None
        self.sync()
        self._fault = spec
        st = self.store
        st.set(0x603F, 0, spec.error_code)
        st.set(0x1001, 0, st.get_int(0x1001) | spec.error_register)
        st.set(0x60FD, 0, st.get_int(0x60FD) | spec.digital_inputs)
        push_history(st, spec.error_code)
        self._error_event(spec.error_code)
        self._record(EventKind.FAULT, f"0x{spec.error_code:04X} {spec.name}", self.velocity_increments)
        if kind == "following_error":
            self._following_error = True
            if self._mode is Mode.HOMING and self._homing_status is HomingStatus.RUNNING:
                self._homing_status = HomingStatus.ERROR
        if self._state in (State.FAULT_REACTION_ACTIVE, State.FAULT):
            return
        self._powered_at_fault = (self._state in POWERED_STATES and spec.reaction is Reaction.FAULT_REACTION
                                  and self.store.get_int(0x605E) != 0)
        self._interrupt()
        self._transition(*T_FAULT)
        if not self._powered_at_fault:
            self._transition(*T_FAULT_REACTION_DONE)  # power stage off at once: no reaction ramp
        self._plan()
        self._run_until(self._now)

    # -- internals: state machine ------------------------------------------------------

    def _powered(self) -> bool:
        st = self._state
        return st in POWERED_STATES or (st is State.FAULT_REACTION_ACTIVE and self._powered_at_fault)

    def _transition(self, number: int, state: State) -> None:
        was_powered, v = self._powered(), self.velocity_increments
        self.history.append((self._now, number, state))
        self._state = state
        self._pending = None  # any transition ends a 605Bh/605Ch ramp (or is its end)
        if number in (5, 8, 9, 11, 12):
            self._interrupt()  # leaving operation: the move and homing are dropped
        if number == 15:
            self._fault = None
            self._following_error = False
            self._clamped = False
            if self._homing_status is HomingStatus.ERROR:
                self._homing_status = HomingStatus.IDLE
            for index in (0x603F, 0x1001, 0x60FD):
                self.store.set(index, 0, 0)
            self._error_event(0x0000)  # CiA 301 Table 21: "error reset or no error"
        if was_powered and not self._powered() and v != 0.0:
            self._record(EventKind.UNSAFE_STOP, f"transition {number} to {state.name}", v)
        if number == 11 and self.store.get_int(0x605A) == 0:  # disable drive function at once
            self._transition(*T_QUICK_STOP_DONE)

    def on_controlword(self, value: Value) -> None:
        assert isinstance(value, int)
        cw = value & 0xFFFF
        previous, self._cw = self._cw, cw
        state_before, pending_before = self._state, self._pending
        command = decode_command(cw, previous)
        if command is not None:
            self._command(command)
        rising, falling = cw & ~previous, previous & ~cw
        # CiA 402-2 6.6.1.1: halt (bit 8) and a falling "homing operation start"
        # (bit 4, 1 -> 0) interrupt a homing; the axis stops on 609Ah and a new
        # start (bit 4 0 -> 1) is needed. The statusword then reads 0/0/1 at rest.
        interrupted = (rising & CW.HALT or falling & CW.NEW_SET_POINT) \
            and self._homing_status is HomingStatus.RUNNING
        if interrupted:
            self._interrupt()
        if self._state is not state_before or self._pending != pending_before \
                or (cw ^ previous) & CW.HALT or interrupted:
            self._plan()
        if rising & CW.NEW_SET_POINT and self._state is State.OPERATION_ENABLED and self._pending is None:
            if self._mode is Mode.PROFILE_POSITION:
                self._accept_set_point(cw)
            elif self._mode is Mode.HOMING:
                self._home()
        self._update_ack()
        self._track_goal("halt released" if previous & ~cw & CW.HALT else "controlword")
        self._run_until(self._now)

    def _command(self, command: Command) -> None:
        steps = TRANSITIONS.get((self._state, command), ())
        if self._pending is not None and steps:
            if steps[0][0] == self._pending[0]:
                return  # the same request again: the ramp goes on
            self._pending = None  # another way out of OPERATION ENABLED replaces it
        for number, state in steps:
            if number == 16 and self.store.get_int(0x605A) not in (5, 6, 7, 8):
                return  # 16 exists only for the "stay in quick stop" option codes
            option = _RAMPED_DISABLE.get(number)
            if option is not None and self.store.get_int(option) == 1 and self.velocity_increments != 0.0:
                self._pending = (number, state)  # slow down on 6084h, then the transition
                self._interrupt()
                return
            self._transition(number, state)

    def on_mode(self, value: Value) -> None:
        if not isinstance(value, int) or value not in Mode._value2member_map_:
            raise SdoAbortedError(ABORT_RANGE)  # 6060h: only the modes of 6502h
        mode = Mode(value)
        if mode is not self._mode:
            self._mode = mode
            self._interrupt()
            self._plan()
            self._track_goal("mode change")
            self._run_until(self._now)

    def device_control(self, command: Command) -> None:
        """A device control command that does not come from 6040h: the reaction to a
        lost connection (CiA 402-2 6007h: 2 disable voltage, 3 quick stop). The
        controlword keeps its value; the transition and its ramp run as for 6040h."""
        self.sync()
        state_before, pending_before = self._state, self._pending
        self._command(command)
        if self._state is not state_before or self._pending != pending_before:
            self._plan()
        self._track_goal(command.value)
        self._run_until(self._now)

    def _error_event(self, code: int) -> None:
        if self.on_error is not None:
            self.on_error(code, self.store.get_int(0x1001))

    # -- internals: modes ------------------------------------------------------------------

    def _interrupt(self) -> None:
        """Drop the pp move and stop a homing in progress (it reads "interrupted")."""
        # An interrupted move keeps target reached = 0; a finished one keeps 1.
        self._target = None
        self._buffer = None
        self._last_target = None
        self._settle_at = None
        if self._homing_status is HomingStatus.RUNNING:
            self._homing_status = HomingStatus.IDLE
        self._legs.clear()

    def _raise_fault(self, kind: str) -> None:
        """A fault the model itself detects, at ``self._now`` (not the clock's time)."""
        self._in_event = True
        try:
            self.inject_fault(kind)
        finally:
            self._in_event = False
