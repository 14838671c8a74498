"""How the simulated axis moves: the motion profile the drive's state calls for.

Part of :class:`~epos_link.simulator.drive.Drive` (a mixin, for the size of
the module only): the drive's state machine decides *what* the axis should
do; this module plans *how* (CiA 402-2 6.6, 6.7, 6.9 and the ramps of 6.4),
runs the events that a profile's end brings, and counts motion starts. Rates
come from the dictionary in EPOS4 units and are converted once, here, with
:mod:`~epos_link.simulator.units`:

=====================  =======================================================
OPERATION ENABLED      605Bh/605Ch ramp pending: stop on 6084h; homing: legs
                       on 609Ah; csp: to 607Ah, halt or not; halt: 6084h or,
                       605Dh = 2, 6085h; pp: to the target; pv: to 60FFh
                       (limited by 607Fh, 6080h)
QUICK STOP ACTIVE      605Ah 1/5: 6084h, else 6085h
FAULT REACTION ACTIVE  605Eh 1: 6084h, 2: 6085h (power stage on)
any other state        power stage off: coast on ``coast_deceleration``
=====================  =======================================================

Cyclic synchronous position (csp, mode 8): the master's 607Ah is the position
demand at once. A real csp drive has no trajectory generator and expects a
new set-point every sync period; the simulator, **chosen**, lets its position
loop follow a set-point (even a jump) at the drive's maxima, 607Fh/6080h and
60C5h, instead of tripping a following error, clamped to 607Dh like a pp target.

Cyclic synchronous velocity (csv, mode 9): the master's 60FFh is the velocity
demand at once, halt not evaluated (CiA 402-2 csv uses no mode specific bits of
the controlword). **Chosen**, as for csp: the velocity loop follows a new
set-point (even a step) within the drive's acceleration limit 60C5h, limited to
607Fh/6080h (sw bit 11 while limited); passing 607Dh raises 8A82h as in pv.
"""
from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING

from ..cia402 import CW, T_FAULT_REACTION_DONE, T_QUICK_STOP_DONE, T_SELF_TEST_DONE, State
from .homing import HomingStatus, Leg, VirtualSwitches, plan_homing
from .monitors import Monitors
from .motion import Kind, Profile, hold, plan_position, plan_stop, plan_velocity
from .objects import Mode
from .od import ObjectStore
from .safety import EventKind
from .units import Units

__all__ = ["Kinematics"]


class Kinematics(Monitors):
    """The motion half of :class:`~epos_link.simulator.drive.Drive`."""

    # Set by Drive (its __init__ and _power_up).
    store: ObjectStore
    switches: VirtualSwitches
    coast_deceleration: float
    _now: float
    _state: State
    _mode: Mode
    _cw: int
    _profile: Profile
    _offset: float
    _target: float | None
    _buffer: float | None
    _last_target: int | None
    _target_reached: bool
    _clamped: bool
    _homed: bool
    _homing_status: HomingStatus
    _legs: deque[Leg]
    _following_error: bool
    _powered_at_fault: bool
    _pending: tuple[int, State] | None
    _goal: bool
    _self_test_until: float

    if TYPE_CHECKING:  # provided by Drive
        @property
        def units(self) -> Units: ...

        @property
        def velocity_increments(self) -> float: ...

        def _physical(self) -> float: ...

        def _record(self, kind: EventKind, detail: str, velocity: float) -> None: ...

        def _transition(self, number: int, state: State) -> None: ...

        def _interrupt(self) -> None: ...

        def _update_ack(self) -> None: ...

        def _clamp_position(self, target: int) -> tuple[int, bool]: ...


    # -- motion starts -----------------------------------------------------------------------

    def _moving_goal(self) -> bool:
        """Whether the drive is heading for motion of its own (not a ramp to rest)."""
        if self._state is not State.OPERATION_ENABLED or self._pending is not None:
            return False
        if self._mode is Mode.CYCLIC_SYNC_POSITION:  # halt is not evaluated in csp
            return self._target is not None and not self._target_reached
        if self._mode is Mode.CYCLIC_SYNC_VELOCITY:  # nor in csv
            return self._csv_goal()[0] != 0.0
        if self._cw & CW.HALT:
            return False
        if self._mode is Mode.PROFILE_POSITION:
            return self._target is not None and not self._target_reached
        if self._mode is Mode.PROFILE_VELOCITY:
            return self._velocity_goal()[0] != 0.0
        return self._homing_status is HomingStatus.RUNNING

    def _track_goal(self, reason: str) -> None:
        goal = self._moving_goal()
        if goal and not self._goal:
            self._record(EventKind.MOTION_START, reason, self.velocity_increments)
        self._goal = goal

    def _home(self) -> None:
        """Homing start (CiA 402-2 6.6): plan the legs, or complete at once (35, 37)."""
        if self._cw & CW.HALT:
            return
        self._interrupt()
        self._following_error = False
        s, u = self.store, self.units
        legs = plan_homing(
            s.get_int(0x6098), self._physical(), self.switches,
            increments_per_revolution=u.increments_per_revolution,
            switch_speed=u.velocity_to_inc_s(max(s.get_int(0x6099, 1), 1)),
            zero_speed=u.velocity_to_inc_s(max(s.get_int(0x6099, 2), 1)),
            acceleration=u.acceleration_to_inc_s2(max(s.get_int(0x609A), 1)),
            offset_move=float(s.get_int(0x30B1)))
        self._homed = False
        if not legs:
            self._finish_homing()
            return
        self._legs.extend(legs)
        self._homing_status = HomingStatus.RUNNING
        self._record(EventKind.MOTION_START, f"homing method {s.get_int(0x6098)}", self.velocity_increments)
        self._goal = True
        self._plan()

    def _finish_homing(self) -> None:
        self._offset = self.store.get_int(0x30B0) - self._physical()
        self._homing_status = HomingStatus.DONE
        self._homed = True
        self._last_target = None

    # -- profiles ----------------------------------------------------------------------------

    def _rates(self, u: Units) -> tuple[float, float, float, float]:
        """(profile velocity, acceleration, deceleration, quick stop deceleration) in inc/s, inc/s^2."""
        s = self.store
        a_max = max(s.get_int(0x60C5), 1)
        v = min(s.get_int(0x6081), s.get_int(0x607F), s.get_int(0x6080))
        acc, dec, qs = (min(max(s.get_int(i), 1), a_max) for i in (0x6083, 0x6084, 0x6085))
        to_a = u.acceleration_to_inc_s2
        return u.velocity_to_inc_s(max(v, 0)), to_a(acc), to_a(dec), to_a(qs)

    def _follow_set_point(self) -> None:
        """csp: 607Ah (clamped to 607Dh) is the position demand from now on."""
        target, self._clamped = self._clamp_position(self.store.get_int(0x607A))
        physical = target - self._offset
        if physical != self._target:
            # Already there (e.g. enabled on 607Ah = the position): nothing to move.
            at_rest_on_it = physical == self._physical() and self.velocity_increments == 0.0
            self._target, self._target_reached = physical, at_rest_on_it

    def _csp_limits(self, u: Units) -> tuple[float, float]:
        """(velocity in inc/s, acceleration in inc/s^2) a csp set-point is followed at."""
        s = self.store
        v = min(s.get_int(0x607F), s.get_int(0x6080))
        return u.velocity_to_inc_s(max(v, 1)), u.acceleration_to_inc_s2(max(s.get_int(0x60C5), 1))

    def _velocity_goal(self) -> tuple[float, bool]:
        """pv goal velocity in inc/s (0 unless enabled and not halted) and whether it was limited."""
        if self._state is not State.OPERATION_ENABLED or self._cw & CW.HALT or self._pending is not None:
            return 0.0, False
        v_max = min(self.store.get_int(0x607F), self.store.get_int(0x6080))
        vt = self.store.get_int(0x60FF)
        goal = min(max(vt, -v_max), v_max)
        return self.units.velocity_to_inc_s(goal), goal != vt

    def _csv_goal(self) -> tuple[float, bool]:
        """csv: 60FFh (limited to 607Fh/6080h) in inc/s, whether it was limited; halt ignored."""
        if self._state is not State.OPERATION_ENABLED or self._pending is not None:
            return 0.0, False
        v_max = min(self.store.get_int(0x607F), self.store.get_int(0x6080))
        vt = self.store.get_int(0x60FF)
        goal = min(max(vt, -v_max), v_max)
        return self.units.velocity_to_inc_s(goal), goal != vt

    def _plan(self) -> None:
        """Replace the motion profile by the one the current state and mode call for."""
        t = self._now
        p, v = self._profile.state_at(t)
        u = self.units
        v_max, acc, dec, qs_dec = self._rates(u)
        st = self._state
        if st is State.OPERATION_ENABLED:
            halted = bool(self._cw & CW.HALT)
            if self._pending is not None:
                self._profile = plan_stop(t, p, v, dec)  # 605Bh/605Ch = 1: slow down ramp
            elif self._mode is Mode.HOMING:
                a = u.acceleration_to_inc_s2(max(self.store.get_int(0x609A), 1))
                if self._legs and not halted:
                    leg = self._legs[0]
                    self._profile = plan_position(t, p, v, leg.target, leg.speed, a, a)
                else:
                    self._profile = plan_stop(t, p, v, a)
            elif self._mode is Mode.CYCLIC_SYNC_POSITION:
                self._follow_set_point()
                assert self._target is not None
                v_csp, a_max = self._csp_limits(u)
                self._profile = plan_position(t, p, v, self._target, v_csp, a_max, a_max)
            elif self._mode is Mode.CYCLIC_SYNC_VELOCITY:
                goal, self._clamped = self._csv_goal()
                a_max = self._csp_limits(u)[1]
                self._profile = plan_velocity(t, p, v, goal, a_max, a_max)
            elif halted:
                self._profile = plan_stop(t, p, v, qs_dec if self.store.get_int(0x605D) == 2 else dec)
            elif self._mode is Mode.PROFILE_POSITION and self._target is not None \
                    and not self._target_reached:
                self._profile = plan_position(t, p, v, self._target, v_max, acc, dec)
            elif self._mode is Mode.PROFILE_VELOCITY:
                goal, self._clamped = self._velocity_goal()
                self._profile = plan_velocity(t, p, v, goal, acc, dec)
            else:
                self._profile = plan_stop(t, p, v, dec)
        elif st is State.QUICK_STOP_ACTIVE:
            slow_down_ramp = self.store.get_int(0x605A) in (1, 5)
            self._profile = plan_stop(t, p, v, dec if slow_down_ramp else qs_dec)
        elif st is State.FAULT_REACTION_ACTIVE and self._powered_at_fault:
            self._profile = plan_stop(t, p, v, dec if self.store.get_int(0x605E) == 1 else qs_dec)
        elif v != 0.0 and self._blocked_at is None:  # power stage off: the axis coasts
            self._profile = plan_stop(t, p, v, u.acceleration_to_inc_s2(max(self.coast_deceleration, 1e-9)))
        else:
            self._profile = hold(t, p)

    def _run_until(self, t: float) -> None:
        """Run the events due up to ``t`` in order: self-test end, the monitors'
        events (:mod:`~epos_link.simulator.monitors`), ends of ramps."""
        while True:
            if self._state is State.NOT_READY_TO_SWITCH_ON and self._self_test_until <= t:
                self._now = max(self._now, self._self_test_until)
                self._transition(*T_SELF_TEST_DONE)
                continue
            profile = self._profile
            ends = profile.kind in (Kind.POSITION, Kind.STOP) and profile.end_time <= t
            event = self._next_monitor_event(min(t, profile.end_time) if ends else t)
            if event is not None:
                self._now = max(self._now, event[0])
                event[1]()
                continue
            if ends:
                self._now = max(self._now, profile.end_time)
                self._profile_ended(profile)
                continue
            return

    def _profile_ended(self, profile: Profile) -> None:
        self._profile = hold(profile.end_time, profile.final_position)
        st = self._state
        if st is State.OPERATION_ENABLED and self._pending is not None:
            number, state = self._pending
            self._pending = None
            self._transition(number, state)  # at rest now: 605Bh/605Ch ramp done
            self._plan()
        elif profile.kind is Kind.POSITION and st is State.OPERATION_ENABLED:
            if self._mode is Mode.HOMING and self._legs:
                leg = self._legs.popleft()
                if leg.fails:  # at the end stop, no switch found (homing)
                    self._legs.clear()
                    self._homing_status = HomingStatus.ERROR
                elif self._legs:
                    self._plan()
                else:
                    self._finish_homing()
            elif self._buffer is not None:
                self._target, self._buffer = self._buffer, None
                self._update_ack()
                self._plan()
            else:
                self._arrived()  # target reached, at once or after the position window time
        elif st is State.QUICK_STOP_ACTIVE and self.store.get_int(0x605A) not in (5, 6, 7, 8):
            self._transition(*T_QUICK_STOP_DONE)
        elif st is State.FAULT_REACTION_ACTIVE:
            self._transition(*T_FAULT_REACTION_DONE)
        self._goal = self._moving_goal()
