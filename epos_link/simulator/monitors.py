"""What the simulated EPOS4 watches while it moves: software limits, following
error, position window. Part of :class:`~epos_link.simulator.drive.Drive` (a
mixin, like :mod:`~epos_link.simulator.kinematics`).

Each monitor answers one question for the run loop (``Kinematics._run_until``):
when, before a horizon, is its next event? The profiles are closed form
(:mod:`~epos_link.simulator.motion`), so the instants are exact
(:func:`~epos_link.simulator.motion.first_beyond`), whatever the step size.

Demand and actual (6062h, 6064h). The motion profile is the position demand
(the trajectory generator's output). The axis follows it exactly, so a
normal move ends exactly on its target, unless the axis is **blocked**
(:meth:`Drive.block_axis`, or 2100h = 7; released by
:meth:`Drive.release_axis` or 2100h = 8): then the actual position stays
where the axis was blocked while the demand goes on. This lag model is
**chosen**: a jammed load or an obstacle, the case CiA 402-2 names first
for a following error ("a drive is blocked"). On release the axis is free
again where it stands, and the demand starts over from there (the drive
re-plans from the actual position, at rest). With the power stage off the
position loop is not running: 6062h reads the actual position.

=====================  ====================================================================
software position      pv, csv, OPERATION ENABLED, 607Dh min < max: where the actual position
limit (8A82h)          passes a limit moving outwards, the fault "software position limit
                       error" (EPOS4 error table, Firmware Specification 7.2 as public
                       EPOS4 code transcribes it: reaction = 605Eh). **Chosen**: only pv/csv
                       (pp and csp targets are clamped to 607Dh, homing references the
                       axis); an axis already beyond a limit faults once it moves further.
following error        pp, homing, csp, OPERATION ENABLED: |6062h - 6064h| > 6065h
(8611h)                "following error window" continuously for 6066h "following error
                       time out" ms (CiA 402-2 6065h/6066h) raises 8611h; statusword bit
                       13 in pp/csp, homing error in homing. 6065h = FFFFFFFFh switches
                       the monitor off (CiA 402-2 6065h). **Chosen**: 6066h defaults to 0
                       (at once): our sources give no EPOS4 value; pv and csv (velocity
                       loops) are not monitored.
position window        pp: target reached (bit 10) once the demand has reached the
                       target and |607Ah - 6064h| <= 6067h "position window" has held for
                       6068h "position window time" ms (CiA 402-2 6067h/6068h); 6067h =
                       FFFFFFFFh switches the window off (reached at the profile's end).
                       **Chosen**: the window time starts when the demand arrives (the
                       actual does not move after that in this model), and 6068h
                       defaults to 0, so an unblocked move is reached at its end.
=====================  ====================================================================
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from ..cia402 import State
from .motion import Profile, first_beyond, hold
from .objects import Mode
from .od import ObjectStore

__all__ = ["Monitors", "OFF"]

OFF = 0xFFFFFFFF  # 6065h / 6067h: monitor switched off (CiA 402-2)
_MARGIN = 0.5  # increments: half the counter's resolution, against float ties at the window edge
_FOLLOWING_MODES = (Mode.PROFILE_POSITION, Mode.HOMING, Mode.CYCLIC_SYNC_POSITION)

Event = tuple[float, Callable[[], None]]


class Monitors:
    """The monitors half of :class:`~epos_link.simulator.drive.Drive`."""

    store: ObjectStore
    _now: float
    _state: State
    _mode: Mode
    _profile: Profile
    _offset: float
    _target: float | None
    _target_reached: bool
    _blocked_at: float | None  # physical position of a blocked axis
    _error_since: float | None  # since when the following error exceeds 6065h
    _settle_at: float | None  # when the position window time is over

    if TYPE_CHECKING:  # provided by Drive
        @property
        def position(self) -> int: ...

        def sync(self) -> None: ...

        def _plan(self) -> None: ...

        def _run_until(self, t: float) -> None: ...

        def _powered(self) -> bool: ...

        def _physical(self) -> float: ...

        def _demand(self) -> float: ...

        def _software_limits(self) -> tuple[int, int] | None: ...

        def _raise_fault(self, kind: str) -> None: ...

        def _track_goal(self, reason: str) -> None: ...

    # -- the blocked axis ------------------------------------------------------------------

    @property
    def blocked(self) -> bool:
        """Whether the axis is blocked (:meth:`block_axis`)."""
        return self._blocked_at is not None

    def block_axis(self) -> None:
        """Jam the axis where it is now: 6064h stays, 6062h goes on (monitors.py, **chosen**)."""
        self.sync()
        if self._blocked_at is None:
            self._blocked_at = self._physical()
            self._plan()
            self._run_until(self._now)

    def release_axis(self) -> None:
        """Free a blocked axis; the drive re-plans from where it stands, at rest."""
        self.sync()
        if self._blocked_at is not None:
            self._profile = hold(self._now, self._blocked_at)
            self._blocked_at = None
            self._plan()
            self._run_until(self._now)

    # -- the run loop's question -------------------------------------------------------------

    def _next_monitor_event(self, horizon: float) -> Event | None:
        """The earliest monitor event in [now, horizon], with what it does."""
        events = [e for e in (self._limit_event(horizon), self._following_event(horizon),
                              self._settle_event(horizon)) if e is not None]
        return min(events, key=lambda e: e[0]) if events else None

    # -- software position limits ----------------------------------------------------------

    def _limit_event(self, horizon: float) -> Event | None:
        if self._state is not State.OPERATION_ENABLED \
                or self._mode not in (Mode.PROFILE_VELOCITY, Mode.CYCLIC_SYNC_VELOCITY):
            return None
        limits = self._software_limits()
        if limits is None or self._blocked_at is not None:  # a blocked axis passes nothing
            return None
        lo, hi = (limit - self._offset for limit in limits)  # the counter's limits on the axis
        times = [x for x in (first_beyond(self._profile, hi, 1, self._now, horizon),
                             first_beyond(self._profile, lo, -1, self._now, horizon)) if x is not None]
        if not times:
            return None
        return min(times), lambda: self._raise_fault("software_limit")

    # -- following error -------------------------------------------------------------------

    def _following_event(self, horizon: float) -> Event | None:
        b = self._blocked_at
        if b is None or self._state is not State.OPERATION_ENABLED or self._mode not in _FOLLOWING_MODES:
            self._error_since = None
            return None
        window = self.store.get_int(0x6065)
        if window == OFF:
            self._error_since = None
            return None
        p, now = self._profile, self._now
        if self._error_since is None:
            if abs(self._demand() - b) > window + _MARGIN:  # e.g. 6065h lowered meanwhile
                return now, self._following_error_begins
            times = [x for x in (first_beyond(p, b + window, 1, now, horizon),
                                 first_beyond(p, b - window, -1, now, horizon)) if x is not None]
            return (min(times), self._following_error_begins) if times else None
        due = self._error_since + self.store.get_int(0x6066) / 1000.0
        above = self._demand() > b  # the side the error is on; it cannot change without a way back
        back = first_beyond(p, b + window, -1, now, min(horizon, due)) if above \
            else first_beyond(p, b - window, 1, now, min(horizon, due))
        if back is not None and back < due:
            return back, self._following_error_ends
        if due <= horizon:
            return max(due, now), self._following_error_fault
        return None

    def _following_error_begins(self) -> None:
        self._error_since = self._now

    def _following_error_ends(self) -> None:
        self._error_since = None

    def _following_error_fault(self) -> None:
        self._error_since = None
        self._raise_fault("following_error")

    # -- position window -------------------------------------------------------------------

    def _arrived(self) -> None:
        """The pp demand reached the target: target reached now, after 6068h, or not yet."""
        assert self._target is not None
        window = self.store.get_int(0x6067)
        if window != OFF and abs(self._target - self._physical()) > window:
            self._settle_at = None  # outside the window: not reached (a blocked axis)
            return
        delay = self.store.get_int(0x6068) / 1000.0
        if delay <= 0.0:
            self._target_reached = True
        else:
            self._settle_at = self._now + delay

    def _settle_event(self, horizon: float) -> Event | None:
        at = self._settle_at
        if at is None or at > horizon:
            return None
        return max(at, self._now), self._settled

    def _settled(self) -> None:
        self._settle_at = None
        if self._state is State.OPERATION_ENABLED and self._mode is Mode.PROFILE_POSITION \
                and self._target is not None:
            self._target_reached = True
            self._track_goal("target reached")
