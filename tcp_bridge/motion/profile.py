"""The bridge's own trajectory generator for axes in a cyclic mode (PSI spec 3.2). Pure.

A drive in cyclic synchronous position mode (CiA 402-2 mode 8, CSP) has no
profile generator of its own: it follows each target position 607Ah as it
comes, every cycle. So for an internal axis in CSP the bridge computes the
profile and :mod:`.cyclic` samples it once per cycle. The rules this module
keeps:

* **never a step**: position and velocity are continuous; between two samples
  ``dt`` apart the velocity of axis *i* changes by at most its acceleration
  ``a_i * dt`` (or its stop deceleration), the position by at most
  ``v_i * dt``;
* **limits**: axis *i* never exceeds its velocity ``v_i`` (PSI 05, bounded
  by 26) nor its acceleration ``a_i`` (06, bounded by 27); a stop ramps at
  28's deceleration;
* **a line**: every move is a straight line in axis space (a single axis
  move is a line of one axis). All axes share one scalar progress ``s(t)``
  running from 0 to 1, and axis *i* stands at ``start_i + delta_i * s(t)``.
  ``s`` is a trapezoid (triangle when there is no room to cruise) whose
  limits are the tightest of all axes: ``v_s = min(v_i / |delta_i|)``,
  ``a_s = min(a_i / |delta_i|)``. So the axis that needs longest sets the
  duration, the others are slowed in proportion, all start and arrive
  together and their progress fractions are equal at every instant;
* **ends exactly at the target**: from the end time on, :meth:`Line.sample`
  answers the targets themselves, not a float sum near them.

**Chosen** (command 90 says only "0 = stop"): a stop keeps the axes on their
line. :meth:`Line.stop_at` ramps ``s`` down with
``d_s = min(d_i / |delta_i|)`` (``d_i`` each axis's 28), so no axis brakes
harder than its 28 and all come to rest together, on the line. If the
remaining distance is shorter than that ramp needs (the profile was already
braking at 06, steeper than 28), the stop brakes just hard enough to stop at
the target, which is never harder than the move's own deceleration; a stop
never passes the target.

A trapezoid, not an S-curve: PSI names no jerk parameter.

A velocity move (S00=3 of an axis in cyclic synchronous velocity, CSV, mode 9)
is a :class:`VelocityRamp`: the velocity set-point 60FFh ramps linearly from
where it is to 05 (bounded by 26) at 06 (bounded by 27) and is held there; a
stop ramps it to 0 at 28. The same rule: between two samples ``dt`` apart it
changes by at most ``rate * dt`` (never a step), and a stop starts from the
set-point of that moment.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Optional, Sequence, Tuple

__all__ = ["AxisLimits", "Line", "Ramp", "Segment", "VelocityRamp", "fractions", "plan_line"]


@dataclass(frozen=True)
class AxisLimits:
    """One axis's limits, in its drive's units (increments, per s, per s^2)."""

    velocity: float
    acceleration: float
    stop_deceleration: float

    def __post_init__(self) -> None:
        for name in ("velocity", "acceleration", "stop_deceleration"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive and finite, not {value!r}")


@dataclass(frozen=True)
class Segment:
    """Constant acceleration ``a`` from ``t0`` (progress ``s0``, rate ``v0``) to ``t1``."""

    t0: float
    s0: float
    v0: float
    a: float
    t1: float

    def at(self, t: float) -> Tuple[float, float]:
        tau = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        return self.s0 + self.v0 * tau + 0.5 * self.a * tau * tau, self.v0 + self.a * tau


@dataclass(frozen=True)
class Ramp:
    """A scalar progress profile: consecutive segments, at rest at both ends."""

    segments: Tuple[Segment, ...]
    start: float
    final: float  # the progress it comes to rest at

    @cached_property
    def end_time(self) -> float:
        return self.segments[-1].t1 if self.segments else self.start

    def sample(self, t: float) -> Tuple[float, float]:
        """(progress, rate) at ``t``; at rest on ``final`` from the end time on."""
        if t >= self.end_time:
            return self.final, 0.0
        for seg in self.segments:
            if t < seg.t1:
                return seg.at(t)
        return self.final, 0.0  # pragma: no cover - t < end_time found a segment


def _trapezoid(t0: float, v: float, a: float) -> Ramp:
    """Progress 0 to 1 from rest to rest, rate at most ``v``, acceleration at most ``a``."""
    if v * v / a >= 1.0:  # no room to cruise: a triangle
        t_acc = math.sqrt(1.0 / a)
        peak = a * t_acc
        return Ramp((Segment(t0, 0.0, 0.0, a, t0 + t_acc),
                     Segment(t0 + t_acc, 0.5, peak, -a, t0 + 2 * t_acc)), t0, 1.0)
    t_acc = v / a
    s_acc = 0.5 * v * t_acc
    t_cruise = (1.0 - 2 * s_acc) / v
    t1, t2 = t0 + t_acc, t0 + t_acc + t_cruise
    return Ramp((Segment(t0, 0.0, 0.0, a, t1), Segment(t1, s_acc, v, 0.0, t2),
                 Segment(t2, 1.0 - s_acc, v, -a, t2 + t_acc)), t0, 1.0)


@dataclass(frozen=True)
class Line:
    """Axes moving together on a straight line: ``start_i + (end_i - start_i) * s(t)``."""

    starts: Tuple[float, ...]
    ends: Tuple[float, ...]  # the line's far end (s = 1): the move's targets
    ramp: Ramp
    stop_rate: float  # d_s: the scalar deceleration of a stop (see the module doc)

    @cached_property
    def deltas(self) -> Tuple[float, ...]:
        # Computed once, like _axes and Ramp.end_time: sample() needs them every cycle
        # and a test samples a line tens of thousands of times (a frozen dataclass's
        # fields never change; cached_property writes the instance's __dict__ directly).
        return tuple(e - a for a, e in zip(self.starts, self.ends))

    @property
    def targets(self) -> Tuple[float, ...]:
        """Where the axes come to rest: the ends exactly, or short of them after a stop."""
        if self.ramp.final == 1.0:
            return self.ends
        return tuple(a + d * self.ramp.final for a, d in zip(self.starts, self.deltas))

    @property
    def end_time(self) -> float:
        return self.ramp.end_time

    def finished(self, t: float) -> bool:
        return t >= self.end_time

    def fraction(self, t: float) -> float:
        """The progress ``s(t)`` along the whole line (0 at its start, 1 at its end)."""
        return self.ramp.sample(t)[0]

    @cached_property
    def _axes(self) -> Tuple[Tuple[float, float], ...]:
        return tuple(zip(self.starts, self.deltas))

    @cached_property
    def _at_rest(self) -> Tuple[Tuple[float, float], ...]:
        return tuple((target, 0.0) for target in self.targets)

    def sample(self, t: float) -> Tuple[Tuple[float, float], ...]:
        """(position, velocity) of every axis at ``t``."""
        ramp = self.ramp
        if t >= ramp.end_time:
            return self._at_rest
        s, rate = ramp.sample(t)
        return tuple([(a + d * s, d * rate) for a, d in self._axes])

    def positions(self, t: float) -> Tuple[float, ...]:
        return tuple(p for p, _ in self.sample(t))

    def stop_at(self, t: float) -> "Line":
        """The same line, ramping down from its state at ``t`` (module doc: chosen)."""
        if t >= self.end_time:
            return self
        s, rate = self.ramp.sample(t)
        if rate <= 0.0:  # not moving yet (or any more): rest where it is
            return Line(self.starts, self.ends, Ramp((), t, s), self.stop_rate)
        remaining = self.ramp.final - s
        if remaining <= 0.0:  # at the end within rounding: rest on the targets
            return Line(self.starts, self.ends, Ramp((), t, self.ramp.final), self.stop_rate)
        decel = self.stop_rate
        if rate * rate / (2 * decel) > remaining:
            decel = rate * rate / (2 * remaining)  # brake just enough to stop at the target
        duration = rate / decel
        s_end = min(s + 0.5 * rate * duration, self.ramp.final)
        return Line(self.starts, self.ends,
                    Ramp((Segment(t, s, rate, -decel, t + duration),), t, s_end), self.stop_rate)


def plan_line(starts: Sequence[float], targets: Sequence[float],
              limits: Sequence[AxisLimits], t0: float) -> Line:
    """The line from ``starts`` to ``targets`` (from rest to rest), starting at ``t0``."""
    if not len(starts) == len(targets) == len(limits) or not starts:
        raise ValueError("one start, target and limit per axis, at least one axis")
    deltas = [float(b) - float(a) for a, b in zip(starts, targets)]
    moving = [(abs(d), lim) for d, lim in zip(deltas, limits) if d != 0.0]
    if not moving:
        return Line(tuple(map(float, starts)), tuple(map(float, targets)), Ramp((), t0, 1.0),
                    1.0)  # nothing to move: at rest on the targets at once
    v = min(lim.velocity / d for d, lim in moving)
    a = min(lim.acceleration / d for d, lim in moving)
    stop = min(lim.stop_deceleration / d for d, lim in moving)
    return Line(tuple(map(float, starts)), tuple(map(float, targets)), _trapezoid(t0, v, a), stop)


def fractions(line: Line, positions: Sequence[float]) -> Tuple[Optional[float], ...]:
    """Each axis's progress along ``line`` from its positions (None for an axis that
    does not move): what a test compares."""
    out = []
    for a, d, p in zip(line.starts, line.deltas, positions):
        out.append(None if d == 0.0 else (p - a) / d)
    return tuple(out)


@dataclass(frozen=True)
class VelocityRamp:
    """One axis's velocity set-point: ``v0`` at ``t0``, linearly towards ``target`` at
    ``rate`` (per s), then held; :meth:`stop_at` ramps it to 0 at ``stop_rate``."""

    t0: float
    v0: float
    target: float
    rate: float
    stop_rate: float
    stopping: bool = False  # a stop ramp: the run ends once it is at 0

    def __post_init__(self) -> None:
        for name in ("rate", "stop_rate"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive and finite, not {value!r}")
        if not (math.isfinite(self.v0) and math.isfinite(self.target)):
            raise ValueError("velocities must be finite")

    @property
    def ramp_end(self) -> float:
        """When the set-point arrives at ``target``."""
        return self.t0 + abs(self.target - self.v0) / self.rate

    @property
    def end_time(self) -> float:
        """When the run ends: a stop's ramp end; a move that holds its velocity never ends."""
        return self.ramp_end if self.stopping else math.inf

    @property
    def targets(self) -> Tuple[float, ...]:
        return (self.target,)

    def velocity(self, t: float) -> float:
        if t >= self.ramp_end:
            return self.target  # exactly the target from the ramp's end on
        if t <= self.t0:
            return self.v0
        delta = self.target - self.v0
        step = self.rate * (t - self.t0)
        if step >= abs(delta):
            return self.target
        return self.v0 + math.copysign(step, delta)

    def velocities(self, t: float) -> Tuple[float, ...]:
        return (self.velocity(t),)

    def finished(self, t: float) -> bool:
        return self.stopping and t >= self.ramp_end

    def stop_at(self, t: float) -> "VelocityRamp":
        """From the set-point at ``t`` to 0 at the stop rate (never a step)."""
        if self.finished(t):
            return self
        return VelocityRamp(max(t, self.t0), self.velocity(t), 0.0, self.stop_rate,
                            self.stop_rate, stopping=True)
