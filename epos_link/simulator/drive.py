"""A CiA 402 servo drive model behind an :class:`~epos_link.simulator.od.ObjectStore`.

Pure: no clocks, threads or I/O. Time is a float the caller passes in
(``update(now)`` / ``advance(dt)``), or a callable given as ``clock`` that the
store calls before every SDO access (``time.monotonic`` for real time, a
:class:`VirtualClock` for tests and fast simulation).

What is modelled (CiA 402-2 V4.0 sections in brackets):

* the power state machine with transitions 0..16 [6.4.1], see
  :mod:`~epos_link.simulator.cia402`; quick stop per 605Ah [6.4.1.3]; faults
  enter FAULT_REACTION_ACTIVE, ramp down on 6085h, then FAULT [6.4.1.1];
* profile position mode 1 [6.7]: absolute/relative (cw bit 6), new set-point
  (bit 4) with the set-point acknowledge handshake (sw bit 12) and a one-entry
  buffer, change set immediately (bit 5), halt (bit 8), target reached (bit 10);
* profile velocity mode 3 [6.9]: 60FFh with 6083h/6084h ramps, bit 10 =
  velocity reached, bit 12 = speed is zero;
* homing mode 6 [6.6]: starts on a rising edge of bit 4 and completes at
  once for every method: 6064h becomes 30B0h (home position) and sw bits 12
  and 10 are set. 607Ch (home offset) is stored but unused, as on the EPOS4
  where it is a move distance from the home switch and the method-35/37
  ("actual position") homing ignores it; the simulator has no switches.
* trapezoidal profiles in closed form (:mod:`~epos_link.simulator.motion`),
  velocity 6081h <= 607Fh, accelerations 6083h/6084h/6085h <= 60C5h.

Decisions a client may notice:

* 607Dh software limits clamp a pp target (CiA 402-2 6.5.2) and set sw bit 11
  until the next unclamped set-point. Min >= max switches them off. Profile
  velocity mode does not watch them.
* A relative target (cw bit 6) is relative to the preceding target; after
  power-up, homing, a mode change or an interrupted move it is relative to
  the position demand value.
* Releasing halt resumes the pp move to the pending target.
* Leaving OPERATION_ENABLED by disable operation, shutdown or disable voltage
  stops the axis where it is (no inertia is modelled); quick stop ramps.
  Quick stop option codes 3, 4, 7, 8 behave like 2 and 6.
* Statusword bit 4 (voltage enabled) is 1 in OPERATION_ENABLED and
  QUICK_STOP_ACTIVE, and in FAULT_REACTION_ACTIVE when the fault came from
  one of them. Bit 9 (remote) is ``Drive.remote``, True unless a simulator
  clears it; on an EPOS4 it follows NMT Operational (guide Table 3-13).
  Bit 15 (maxon: position referenced to home) is set after a homing.
* Injected faults are one-shot: a fault reset always succeeds. They set
  603Fh, 1001h and, for limit switches, the 60FDh input bits and sw bit 11
  until the reset. A following error also sets sw bit 13 (pp: following
  error, hm: homing error) until the reset.
* Homing never shows "in progress": in hm, sw bit 10 is 1, and bit 12
  (homing attained) is 1 once a homing has completed since power-up.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

from canopen import SdoAbortedError

from ..cia402 import (
    CW,
    POWERED_STATES,
    STATE_BITS,
    SW,
    T_FAULT,
    T_FAULT_REACTION_DONE,
    T_INITIALISED,
    T_QUICK_STOP_DONE,
    T_SELF_TEST_DONE,
    TRANSITIONS,
    Command,
    State,
    decode_command,
)
from .motion import Kind, Profile, hold, plan_position, plan_stop, plan_velocity
from .od import ABORT_RANGE, ObjectStore, Value, load_object_dictionary

__all__ = ["FAULTS", "Drive", "FaultSpec", "Mode", "SIMULATOR_COMMANDS", "VirtualClock"]

_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


class Mode(IntEnum):
    """Supported modes of operation, 6060h (CiA 402-2 6.3.1); 6502h = 0x25."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6


@dataclass(frozen=True)
class FaultSpec:
    """What an injected fault leaves in the dictionary until a fault reset."""

    # 603Fh. maxon-like codes as we remember the EPOS4 Firmware Specification's
    # error table; that manual is not among our sources, so check before relying on them.
    error_code: int
    error_register: int  # 1001h bits, CiA 301 7.5.2.2: bit 0 generic, bit 7 manufacturer (maxon: motion error)
    digital_inputs: int  # 60FDh bits (CiA 402-2 60FDh: bit 0 negative, bit 1 positive limit switch)


FAULTS: dict[str, FaultSpec] = {
    "limit_positive": FaultSpec(0x8A89, 0x81, 0x0000_0002),
    "limit_negative": FaultSpec(0x8A88, 0x81, 0x0000_0001),
    "following_error": FaultSpec(0x8611, 0x81, 0x0000_0000),
}

# Values of the write-only 2100h "Simulator command" (see epos4.eds).
SIMULATOR_COMMANDS: dict[int, str] = {1: "limit_positive", 2: "limit_negative", 3: "following_error"}


class VirtualClock:
    """A clock that moves only when told to; pass it as ``Drive(clock=...)``."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = float(start)

    def __call__(self) -> float:
        return self.now

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError("time cannot run backwards")
        self.now += dt
        return self.now


def _wrap_i32(value: float) -> int:
    """Round to the nearest integer and wrap into INTEGER32 like an encoder counter."""
    n = math.floor(value + 0.5)
    return (n - _I32_MIN) % (1 << 32) + _I32_MIN


class Drive:
    """The CiA 402 drive: state machine, modes and motion, served through ``store``.

    ``store`` defaults to a fresh store over the shipped EDS (node 1). With
    ``clock`` the drive catches up with ``clock()`` before every store access;
    without it, time moves only by ``update``/``advance``. ``self_test_time``
    delays transition 1 so NOT_READY_TO_SWITCH_ON can be observed.
    """

    def __init__(self, store: ObjectStore | None = None, *,
                 clock: Callable[[], float] | None = None, start: float | None = None,
                 self_test_time: float = 0.0) -> None:
        self.store = store if store is not None else ObjectStore(load_object_dictionary())
        self.clock = clock
        self.remote = True
        self.warning = False
        # (time, transition number, new state), newest last.
        self.history: deque[tuple[float, int, State]] = deque(maxlen=256)
        self._self_test_time = float(self_test_time)
        self._install_hooks()
        self._power_up(start if start is not None else (clock() if clock is not None else 0.0))
        if clock is not None:
            self.store.before_access = self.sync

    # -- time ------------------------------------------------------------------------

    @property
    def now(self) -> float:
        """Time of the last update."""
        return self._now

    def update(self, now: float | None = None) -> None:
        """Advance the model to ``now`` (default: ``clock()``). Earlier times are ignored."""
        if now is None:
            if self.clock is None:
                raise ValueError("update() needs a time when the drive has no clock")
            now = self.clock()
        if now < self._now:
            return
        self._run_until(now)
        self._now = now

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError("time cannot run backwards")
        self.update(self._now + dt)

    def sync(self) -> None:
        """Catch up with the clock, if there is one (the store's ``before_access``)."""
        if self.clock is not None:
            self.update(self.clock())

    def power_cycle(self, now: float | None = None) -> None:
        """NMT reset node: parameters back to the saved ones, state machine from transition 0."""
        self.store.reset()
        self._power_up(self._now if now is None else now)

    # -- observation -----------------------------------------------------------------

    @property
    def state(self) -> State:
        return self._state

    @property
    def mode(self) -> Mode:
        return self._mode

    @property
    def controlword(self) -> int:
        return self._cw

    @property
    def position(self) -> int:
        """6064h (and 6062h: the demand equals the actual value in this model)."""
        return _wrap_i32(self._profile.state_at(self._now)[0])

    @property
    def velocity(self) -> int:
        """606Ch."""
        return int(math.floor(self._profile.state_at(self._now)[1] + 0.5))

    @property
    def statusword(self) -> int:
        """6041h, CiA 402-2 6.4.1.4 and the mode-specific bits of 6.6/6.7/6.9."""
        st = self._state
        sw = STATE_BITS[st]
        if st in POWERED_STATES or (st is State.FAULT_REACTION_ACTIVE and self._powered_at_fault):
            sw |= SW.VOLTAGE_ENABLED
        if self.warning:
            sw |= SW.WARNING
        if self.remote:
            sw |= SW.REMOTE
        velocity = self._profile.state_at(self._now)[1]
        halted = st is State.OPERATION_ENABLED and bool(self._cw & CW.HALT)
        if st is State.QUICK_STOP_ACTIVE:
            reached = velocity == 0.0  # "quick stop finished, drive halted" (6.4.1.4, bit 10)
        elif self._mode is Mode.PROFILE_POSITION:
            reached = (halted and velocity == 0.0) or self._target_reached
        elif self._mode is Mode.PROFILE_VELOCITY:
            reached = velocity == self._velocity_goal()[0]
        else:
            reached = True  # homing is never "in progress": it completes at once
        if reached:
            sw |= SW.TARGET_REACHED
        if self._clamped or (self._fault is not None and self._fault.digital_inputs):
            sw |= SW.INTERNAL_LIMIT_ACTIVE
        if self._mode is Mode.PROFILE_POSITION:
            bit12, bit13 = self._ack, self._following_error
        elif self._mode is Mode.PROFILE_VELOCITY:
            bit12, bit13 = velocity == 0.0, False
        else:
            bit12, bit13 = self._homed, self._following_error
        if bit12:
            sw |= SW.OP_MODE_12
        if bit13:
            sw |= SW.OP_MODE_13
        if self._homed:
            sw |= SW.POSITION_REFERENCED
        return int(sw)

    # -- commands ----------------------------------------------------------------------

    def write_controlword(self, controlword: int) -> None:
        """Checked write of 6040h through the store (same path as an SDO download)."""
        self.store.write_value(0x6040, 0, controlword)

    def set_mode(self, mode: int) -> None:
        """Checked write of 6060h through the store."""
        self.store.write_value(0x6060, 0, int(mode))

    def inject_fault(self, kind: str) -> None:
        """Raise a fault now: ``"limit_positive"``, ``"limit_negative"`` or ``"following_error"``."""
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
        if kind == "following_error":
            self._following_error = True
        if self._state in (State.FAULT_REACTION_ACTIVE, State.FAULT):
            return
        self._powered_at_fault = self._state in POWERED_STATES
        self._abort_move()
        self._transition(*T_FAULT)
        self._plan()
        self._run_until(self._now)

    # -- internals: power-up and hooks -------------------------------------------------

    def _power_up(self, t: float) -> None:
        self._now = float(t)
        self._cw = 0
        self._profile: Profile = hold(self._now, 0.0)
        self._target: int | None = None  # pp target being approached (or reached)
        self._buffer: int | None = None  # pp set-point waiting for the current move
        self._last_target: int | None = None  # base of relative set-points
        self._target_reached = False  # 0 after power-up until a first target is reached
        self._ack = False
        self._clamped = False
        self._homed = False
        self._following_error = False
        self._fault: FaultSpec | None = None
        self._powered_at_fault = False
        mode = self.store.get_int(0x6060)
        self._mode = Mode(mode) if mode in Mode._value2member_map_ else Mode.PROFILE_POSITION
        self._self_test_until = self._now + self._self_test_time
        self._state = State.NOT_READY_TO_SWITCH_ON
        self._transition(*T_INITIALISED)
        self._run_until(self._now)

    def _install_hooks(self) -> None:
        s = self.store
        s.add_read_hook(0x6041, 0, lambda: self.statusword)
        s.add_read_hook(0x6061, 0, lambda: int(self._mode))
        s.add_read_hook(0x6062, 0, lambda: self.position)
        s.add_read_hook(0x6064, 0, lambda: self.position)
        s.add_read_hook(0x606C, 0, lambda: self.velocity)
        s.add_write_hook(0x6040, 0, self._on_controlword)
        s.add_write_hook(0x6060, 0, self._on_mode)
        s.add_write_hook(0x60FF, 0, self._on_target_velocity)
        s.add_write_hook(0x2100, 0, self._on_simulator_command)

    # -- internals: state machine ------------------------------------------------------

    def _transition(self, number: int, state: State) -> None:
        self.history.append((self._now, number, state))
        self._state = state
        if number in (5, 8, 9, 12):
            self._abort_move()  # leaving operation: the pp move is dropped
        elif number == 11:
            self._abort_move()
            if self._quick_stop_option() == 0:  # 605Ah = 0: disable drive function at once
                self._transition(*T_QUICK_STOP_DONE)
        elif number == 15:
            self._fault = None
            self._following_error = False
            self._clamped = False
            self.store.set(0x603F, 0, 0)
            self.store.set(0x1001, 0, 0)
            self.store.set(0x60FD, 0, 0)

    def _on_controlword(self, value: Value) -> None:
        assert isinstance(value, int)
        cw = value & 0xFFFF
        previous, self._cw = self._cw, cw
        state_before = self._state
        command = decode_command(cw, previous)
        if command is not None:
            self._command(command)
        if self._state is not state_before or (cw ^ previous) & CW.HALT:
            self._plan()
        rising = cw & ~previous
        if rising & CW.NEW_SET_POINT and self._state is State.OPERATION_ENABLED:
            if self._mode is Mode.PROFILE_POSITION:
                self._accept_set_point(cw)
            elif self._mode is Mode.HOMING:
                self._home()
        self._update_ack()
        self._run_until(self._now)

    def _command(self, command: Command) -> None:
        for number, state in TRANSITIONS.get((self._state, command), ()):
            if number == 16 and self._quick_stop_option() not in (5, 6, 7, 8):
                return  # 16 exists only for the "stay in quick stop" option codes
            self._transition(number, state)

    def _quick_stop_option(self) -> int:
        return self.store.get_int(0x605A)

    def _on_mode(self, value: Value) -> None:
        if not isinstance(value, int) or value not in Mode._value2member_map_:
            raise SdoAbortedError(ABORT_RANGE)  # 6060h: only the modes of 6502h
        mode = Mode(value)
        if mode is not self._mode:
            self._mode = mode
            self._abort_move()
            self._plan()
            self._run_until(self._now)

    def _on_target_velocity(self, value: Value) -> None:
        self.store.set(0x60FF, 0, value)
        if self._mode is Mode.PROFILE_VELOCITY and self._state is State.OPERATION_ENABLED:
            self._plan()

    def _on_simulator_command(self, value: Value) -> None:
        kind = SIMULATOR_COMMANDS.get(value) if isinstance(value, int) else None
        if kind is None:
            raise SdoAbortedError(ABORT_RANGE)
        self.inject_fault(kind)

    # -- internals: modes ------------------------------------------------------------------

    def _abort_move(self) -> None:
        # An interrupted move keeps target reached = 0; a finished one keeps 1.
        self._target = None
        self._buffer = None
        self._last_target = None

    def _accept_set_point(self, cw: int) -> None:
        """Profile position set-point on a rising edge of cw bit 4 (CiA 402-2 6.7.1)."""
        target = self.store.get_int(0x607A)
        if cw & CW.ABS_REL:
            base = self._last_target if self._last_target is not None else self.position
            target += base
        target, clamped = self._clamp_position(target)
        busy = self._target is not None and not self._target_reached
        if cw & CW.CHANGE_SET_IMMEDIATELY or not busy:
            self._target, self._buffer = target, None
            self._target_reached = False
            self._plan()
        elif self._buffer is None:
            self._buffer = target  # single set-point buffer: started when this move ends
        else:
            return  # buffer full: set-point not accepted, no acknowledge
        self._last_target = target
        self._clamped = clamped
        self._ack = True

    def _update_ack(self) -> None:
        # Set-point acknowledge drops once the master clears bit 4 and the buffer is free.
        if not self._cw & CW.NEW_SET_POINT and self._buffer is None:
            self._ack = False

    def _clamp_position(self, target: int) -> tuple[int, bool]:
        lo, hi = self.store.get_int(0x607D, 1), self.store.get_int(0x607D, 2)
        if lo >= hi:
            lo, hi = _I32_MIN, _I32_MAX  # limits switched off
        clamped = min(max(target, max(lo, _I32_MIN)), min(hi, _I32_MAX))
        return clamped, clamped != target

    def _home(self) -> None:
        """Homing (CiA 402-2 6.6): completes at once, position := 30B0h home position."""
        if self._cw & CW.HALT:
            return
        self._abort_move()
        self._following_error = False
        self._profile = hold(self._now, float(self.store.get_int(0x30B0)))
        self._homed = True

    # -- internals: motion -------------------------------------------------------------------

    def _rates(self) -> tuple[float, float, float, float]:
        """(profile velocity, acceleration, deceleration, quick stop deceleration), limited."""
        s = self.store
        a_max = max(s.get_int(0x60C5), 1)
        v = min(s.get_int(0x6081), s.get_int(0x607F))
        acc = min(max(s.get_int(0x6083), 1), a_max)
        dec = min(max(s.get_int(0x6084), 1), a_max)
        qs = min(max(s.get_int(0x6085), 1), a_max)
        return float(max(v, 0)), float(acc), float(dec), float(qs)

    def _velocity_goal(self) -> tuple[float, bool]:
        """pv goal velocity (0 unless enabled and not halted) and whether 607Fh clamped it."""
        if self._state is not State.OPERATION_ENABLED or self._cw & CW.HALT:
            return 0.0, False
        v_max = self.store.get_int(0x607F)
        vt = self.store.get_int(0x60FF)
        goal = min(max(vt, -v_max), v_max)
        return float(goal), goal != vt

    def _plan(self) -> None:
        """Replace the motion profile by the one the current state and mode call for."""
        t = self._now
        p, v = self._profile.state_at(t)
        v_max, acc, dec, qs_dec = self._rates()
        st = self._state
        if st is State.OPERATION_ENABLED:
            if self._mode is Mode.HOMING:
                dec = float(max(self.store.get_int(0x609A), 1))
            if self._cw & CW.HALT:
                self._profile = plan_stop(t, p, v, dec)
            elif self._mode is Mode.PROFILE_POSITION and self._target is not None \
                    and not self._target_reached:
                self._profile = plan_position(t, p, v, self._target, v_max, acc, dec)
            elif self._mode is Mode.PROFILE_VELOCITY:
                goal, self._clamped = self._velocity_goal()
                self._profile = plan_velocity(t, p, v, goal, acc, dec)
            else:
                self._profile = plan_stop(t, p, v, dec)
        elif st is State.QUICK_STOP_ACTIVE:
            slow_down_ramp = self._quick_stop_option() in (1, 5)
            self._profile = plan_stop(t, p, v, dec if slow_down_ramp else qs_dec)
        elif st is State.FAULT_REACTION_ACTIVE:
            self._profile = plan_stop(t, p, v, qs_dec)
        else:
            self._profile = hold(t, p)  # power stage off: no inertia is modelled

    def _run_until(self, t: float) -> None:
        """Run the events due up to ``t`` in order: self-test end, ends of ramps."""
        while True:
            if self._state is State.NOT_READY_TO_SWITCH_ON and self._self_test_until <= t:
                self._now = max(self._now, self._self_test_until)
                self._transition(*T_SELF_TEST_DONE)
                continue
            profile = self._profile
            if profile.kind in (Kind.POSITION, Kind.STOP) and profile.end_time <= t:
                self._now = max(self._now, profile.end_time)
                self._profile_ended(profile)
                continue
            return

    def _profile_ended(self, profile: Profile) -> None:
        self._profile = hold(profile.end_time, profile.final_position)
        st = self._state
        if profile.kind is Kind.POSITION and st is State.OPERATION_ENABLED:
            if self._buffer is not None:
                self._target, self._buffer = self._buffer, None
                self._update_ack()
                self._plan()
            else:
                self._target_reached = True
        elif st is State.QUICK_STOP_ACTIVE and self._quick_stop_option() not in (5, 6, 7, 8):
            self._transition(*T_QUICK_STOP_DONE)
        elif st is State.FAULT_REACTION_ACTIVE:
            self._transition(*T_FAULT_REACTION_DONE)
