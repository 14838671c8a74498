"""Set-points of the simulated drive: 607Ah and 60FFh writes, the profile position
set-point handshake (CiA 402-2 6.7.1: cw bit 4, sw bit 12, a one-entry buffer)
and the software position limits 607Dh that clamp a pp or csp target.

Part of :class:`~epos_link.simulator.drive.Drive` (a mixin, for the size of
the module only). Decisions a client may notice (**chosen** where the
manuals are silent):

* 607Dh software limits clamp a pp or csp target (CiA 402-2 6.5.2; for csp
  as Nanotec N5 describes it, bit 11 "demand position above or below the
  limit values set in 607Dh") and set sw bit 11 until the next unclamped
  set-point; min >= max switches them off. A profile velocity move is not
  clamped: where it passes a limit the drive raises 8A82h "software position
  limit error" with the fault reaction (EPOS4 error table; see
  :mod:`~epos_link.simulator.monitors`). Profile
  velocity clamped by 607Fh/6080h also sets bit 11 (EPOS4: bit 11 "internal
  limit active" includes velocity limiting). Limit switch inputs are in 60FDh.
* A relative target (cw bit 6) is relative to the preceding target; after
  power-up, homing, a mode change or an interrupted move it is relative to
  the position demand value.
* **Chosen**, in this one place, for a pp target beyond 607Dh: the EPOS4
  documentation we have does not say whether it is clamped or refused with a
  fault. The simulator clamps it (as CiA 402-2 6.5.2 describes) and sets
  bit 11. Safe either way for a client: target reached (bit 10) ends the
  move, a fault ends it too, and where the axis is comes from 6064h, not
  from the target asked for (the bridge reads 12 from 6064h).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from ..cia402 import CW, State
from .objects import Mode
from .od import ObjectStore, Value
from .safety import EventKind

__all__ = ["SetPoints"]

_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


class SetPoints:
    """The set-point half of :class:`~epos_link.simulator.drive.Drive`."""

    store: ObjectStore
    _now: float
    _state: State
    _mode: Mode
    _cw: int
    _offset: float
    _pending: tuple[int, State] | None
    _target: float | None
    _buffer: float | None
    _last_target: int | None
    _target_reached: bool
    _settle_at: float | None
    _ack: bool
    _clamped: bool
    _goal: bool

    if TYPE_CHECKING:  # provided by Drive
        @property
        def position(self) -> int: ...

        @property
        def velocity_increments(self) -> float: ...

        def _plan(self) -> None: ...

        def _track_goal(self, reason: str) -> None: ...

        def _run_until(self, t: float) -> None: ...

        def _moving_goal(self) -> bool: ...

        def _record(self, kind: EventKind, detail: str, velocity: float) -> None: ...

    def on_target_position(self, value: Value) -> None:
        """607Ah: a set-point for pp at the next cw bit 4; in csp, followed at once."""
        self.store.set(0x607A, 0, value)
        if self._mode is Mode.CYCLIC_SYNC_POSITION and self._state is State.OPERATION_ENABLED \
                and self._pending is None:
            self._plan()
            self._track_goal("target position (csp)")
            self._run_until(self._now)

    def on_target_velocity(self, value: Value) -> None:
        """60FFh: the pv target (ramped on 6083h/6084h); in csv, followed at once."""
        self.store.set(0x60FF, 0, value)
        if self._mode in (Mode.PROFILE_VELOCITY, Mode.CYCLIC_SYNC_VELOCITY) \
                and self._state is State.OPERATION_ENABLED:
            self._plan()
            self._track_goal("target velocity")
            if self._mode is Mode.CYCLIC_SYNC_VELOCITY:
                self._run_until(self._now)

    def _accept_set_point(self, cw: int) -> None:
        """Profile position set-point on a rising edge of cw bit 4 (CiA 402-2 6.7.1)."""
        target = self.store.get_int(0x607A)
        if cw & CW.ABS_REL:
            base = self._last_target if self._last_target is not None else self.position
            target += base
        target, clamped = self._clamp_position(target)
        physical = target - self._offset
        busy = self._target is not None and not self._target_reached
        if cw & CW.CHANGE_SET_IMMEDIATELY or not busy:
            self._target, self._buffer = physical, None
            self._target_reached = False
            self._settle_at = None
            self._plan()
        elif self._buffer is None:
            self._buffer = physical  # single set-point buffer: started when this move ends
        else:
            return  # buffer full: set-point not accepted, no acknowledge
        self._last_target = target
        self._clamped = clamped
        self._ack = True
        self._record(EventKind.MOTION_START, f"set-point {target}", self.velocity_increments)
        self._goal = self._moving_goal()

    def _update_ack(self) -> None:
        # Set-point acknowledge drops once the master clears bit 4 and the buffer is free.
        if not self._cw & CW.NEW_SET_POINT and self._buffer is None:
            self._ack = False

    def _software_limits(self) -> tuple[int, int] | None:
        """607Dh (min, max) in the counter's frame; None when min >= max switches them off."""
        lo, hi = self.store.get_int(0x607D, 1), self.store.get_int(0x607D, 2)
        return None if lo >= hi else (lo, hi)

    def _clamp_position(self, target: int) -> tuple[int, bool]:
        lo, hi = self._software_limits() or (_I32_MIN, _I32_MAX)
        clamped = min(max(target, max(lo, _I32_MIN)), min(hi, _I32_MAX))
        return clamped, clamped != target
