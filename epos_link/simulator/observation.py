"""What a client reads from the simulated drive: 6041h statusword, 6064h, 606Ch and
the rest of :class:`~epos_link.simulator.drive.Drive`'s read-only view.

Part of :class:`~epos_link.simulator.drive.Drive` (a mixin, for the size of
the module only). The statusword follows CiA 402-2 6.4.1.4 and the mode
specific bits of 6.6 (homing), 6.7 (pp), 6.9 (pv), csp and csv; the choices about
its bits are listed in :mod:`~epos_link.simulator.drive`.
"""
from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

from ..cia402 import CW, STATE_BITS, SW, State
from .faults import FaultSpec
from .homing import HomingStatus
from .objects import Mode
from .od import ObjectStore
from .safety import DriveEvent, SafetyLog
from .units import Units, units_of

__all__ = ["Observation", "wrap_i32"]

_I32_MIN = -(1 << 31)


def wrap_i32(value: float) -> int:
    """Round to the nearest integer and wrap into INTEGER32 like an encoder counter."""
    n = math.floor(value + 0.5)
    return (n - _I32_MIN) % (1 << 32) + _I32_MIN


class Observation:
    """The read-only half of :class:`~epos_link.simulator.drive.Drive`."""

    store: ObjectStore
    safety: SafetyLog
    remote: bool
    warning: bool
    _now: float
    _state: State
    _mode: Mode
    _cw: int
    _offset: float
    _pending: tuple[int, State] | None
    _target_reached: bool
    _ack: bool
    _following_error: bool
    _clamped: bool
    _fault: FaultSpec | None
    _homed: bool
    _homing_status: HomingStatus
    _blocked_at: float | None

    if TYPE_CHECKING:  # provided by Drive
        from .motion import Profile
        _profile: Profile

        def _physical(self) -> float: ...

        def _demand(self) -> float: ...

        def _powered(self) -> bool: ...

        def _velocity_goal(self) -> tuple[float, bool]: ...

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
    def units(self) -> Units:
        return units_of(self.store)

    @property
    def increments_per_revolution(self) -> int:
        """Main sensor increments per motor revolution (3000h:05 = 4 x 3010h:01)."""
        return self.units.increments_per_revolution

    @property
    def position(self) -> int:
        """6064h position actual value."""
        return wrap_i32(self._physical() + self._offset)

    @property
    def demand_position(self) -> int:
        """6062h position demand value: the profile's position while the position loop
        runs (power stage on); with it off, the actual position (monitors.py)."""
        if not self._powered():
            return self.position
        return wrap_i32(self._demand() + self._offset)

    @property
    def axis_position(self) -> float:
        """Where the axis physically is, in increments from where it was at the first power-up.

        Unlike 6064h it is not moved by homing or power cycles: tests use it
        to see whether the axis really moved.
        """
        return self._physical()

    @property
    def velocity(self) -> int:
        """606Ch, in the unit of 60A9h (rpm by default)."""
        return int(math.floor(self.units.velocity_from_inc_s(self.velocity_increments) + 0.5))

    @property
    def velocity_increments(self) -> float:
        """The axis velocity in increments per second (0 while blocked)."""
        if self._blocked_at is not None:
            return 0.0
        return self._profile.state_at(self._now)[1]

    @property
    def homing_status(self) -> HomingStatus:
        return self._homing_status

    @property
    def events(self) -> deque[DriveEvent]:
        return self.safety.events

    @property
    def motion_starts(self) -> int:
        return self.safety.motion_starts

    @property
    def unsafe_stops(self) -> deque[DriveEvent]:
        return self.safety.unsafe_stops

    @property
    def resets_while_moving(self) -> int:
        return self.safety.resets_while_moving

    @property
    def statusword(self) -> int:
        """6041h, CiA 402-2 6.4.1.4 and the mode-specific bits of 6.6/6.7/6.9."""
        st = self._state
        sw = STATE_BITS[st]
        if self._powered():
            sw |= SW.VOLTAGE_ENABLED
        if self.warning:
            sw |= SW.WARNING
        if self.remote:
            sw |= SW.REMOTE
        velocity = self.velocity_increments
        at_rest = velocity == 0.0
        halted = st is State.OPERATION_ENABLED and bool(self._cw & CW.HALT)
        bit12 = bit13 = False
        if st is State.QUICK_STOP_ACTIVE or self._pending is not None:
            reached = at_rest  # "quick stop finished, drive halted" (6.4.1.4, bit 10)
        elif self._mode is Mode.PROFILE_POSITION:
            reached = (halted and at_rest) or self._target_reached
        elif self._mode is Mode.PROFILE_VELOCITY:
            reached = velocity == self._velocity_goal()[0]
        else:
            reached = False
        if self._mode is Mode.PROFILE_POSITION:
            bit12, bit13 = self._ack, self._following_error
        elif self._mode is Mode.PROFILE_VELOCITY:
            bit12 = at_rest
        elif self._mode is Mode.CYCLIC_SYNC_POSITION:
            # csp: bit 10 reserved, 12 "drive follows the command value" (607Ah is
            # the input of the position loop), 13 following error.
            bit12 = st is State.OPERATION_ENABLED and self._pending is None
            bit13 = self._following_error
        elif self._mode is Mode.CYCLIC_SYNC_VELOCITY:
            # csv: bit 10 reserved, 12 "drive follows the command value" (60FFh is
            # the input of the velocity loop), 13 reserved (no following error in csv).
            bit12 = st is State.OPERATION_ENABLED and self._pending is None
        else:  # homing, CiA 402-2 6.6 table: bits 13/12/10
            status = self._homing_status
            bit13 = status is HomingStatus.ERROR
            bit12 = status is HomingStatus.DONE
            if status is not HomingStatus.RUNNING and st is not State.QUICK_STOP_ACTIVE:
                reached = status is HomingStatus.DONE or at_rest
        if reached:
            sw |= SW.TARGET_REACHED
        if self._clamped or (self._fault is not None and self._fault.internal_limit):
            sw |= SW.INTERNAL_LIMIT_ACTIVE
        if bit12:
            sw |= SW.OP_MODE_12
        if bit13:
            sw |= SW.OP_MODE_13
        if self._homed:
            sw |= SW.POSITION_REFERENCED
        return int(sw)
