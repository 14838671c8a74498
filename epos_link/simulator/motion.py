"""Trapezoidal motion profiles in closed form (CiA 402-2 section 6.7 "Profile position",
6.9 "Profile velocity", and the quick-stop/halt ramps of 6.4).

A :class:`Profile` is planned once, from a start time, position and velocity,
as a short list of constant-acceleration :class:`Segment` s followed by an
endless constant-velocity tail. Evaluating it at any time is exact
(``p = p0 + v0*t + a*t**2/2``), so one large time step lands on the same
position as a thousand small ones: there is no integration drift. Positions
and velocities are floats here; the drive rounds them for 6064h/606Ch.

Rates are magnitudes: ``acc`` applies while speed grows, ``dec`` while it
shrinks (CiA 402-2 6083h/6084h). A position move that starts towards its
target too fast to stop in time, or moving away from it, first stops on the
``dec`` ramp and then comes back.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

__all__ = ["Kind", "Profile", "Segment", "first_beyond", "hold", "plan_position", "plan_stop", "plan_velocity"]


class Kind(Enum):
    """What a profile is for; the drive uses it to decide what its end means."""

    HOLD = "hold"  # standing still, nothing pending
    POSITION = "position"  # pp move to ``target``; ends at rest on it
    VELOCITY = "velocity"  # pv ramp; the tail keeps the target velocity
    STOP = "stop"  # halt, quick stop or fault reaction ramp; ends at rest


@dataclass(frozen=True)
class Segment:
    """Constant acceleration from ``start`` for ``duration`` seconds."""

    start: float
    duration: float
    position: float
    velocity: float
    acceleration: float

    @property
    def end(self) -> float:
        return self.start + self.duration

    def at(self, t: float) -> tuple[float, float]:
        return self._after(min(max(t - self.start, 0.0), self.duration))

    def end_state(self) -> tuple[float, float]:
        """(position, velocity) at the end, from the duration itself (no time rounding)."""
        return self._after(self.duration)

    def _after(self, dt: float) -> tuple[float, float]:
        a = self.acceleration
        return (self.position + self.velocity * dt + 0.5 * a * dt * dt,
                self.velocity + a * dt)


@dataclass(frozen=True)
class Profile:
    """Segments, then from ``end_time`` on: ``final_velocity`` from ``final_position``."""

    kind: Kind
    segments: tuple[Segment, ...]
    end_time: float
    final_position: float
    final_velocity: float
    target: float | None = None

    def state_at(self, t: float) -> tuple[float, float]:
        """(position, velocity) at time ``t``; times before the start clamp to it."""
        for seg in self.segments:
            if t < seg.end:
                return seg.at(t)
        dt = max(t - self.end_time, 0.0)
        return self.final_position + self.final_velocity * dt, self.final_velocity

    def done(self, t: float) -> bool:
        """True once the ramps are over (the tail has begun)."""
        return t >= self.end_time


class _Builder:
    def __init__(self, t: float, p: float, v: float) -> None:
        self.t, self.p, self.v = t, p, v
        self.segments: list[Segment] = []

    def ramp(self, a: float, duration: float) -> None:
        # Skips NaN, and ramps too short to move the clock (t + duration == t):
        # they would change the speed at an instant no one can observe.
        if not duration > 0.0 or self.t + duration == self.t:
            return
        seg = Segment(self.t, duration, self.p, self.v, a)
        self.segments.append(seg)
        self.t = seg.end
        self.p, self.v = seg.end_state()

    def ramp_to_velocity(self, v_target: float, acc: float, dec: float) -> None:
        """Change velocity to ``v_target``: ``dec`` towards zero, ``acc`` away from it."""
        if self.v != 0.0 and (v_target == 0.0 or (v_target > 0.0) != (self.v > 0.0)
                              or abs(v_target) < abs(self.v)):
            # Slowing down: to the target if it has the same sign, else to rest.
            same_sign = v_target != 0.0 and (v_target > 0.0) == (self.v > 0.0)
            stop_at = v_target if same_sign else 0.0
            self.ramp(-math.copysign(dec, self.v), abs(self.v - stop_at) / dec)
            self.v = stop_at
        if abs(v_target) > abs(self.v):
            self.ramp(math.copysign(acc, v_target), abs(v_target - self.v) / acc)
        self.v = v_target

    def finish(self, kind: Kind, final_position: float, final_velocity: float,
               target: float | None = None) -> Profile:
        return Profile(kind, tuple(self.segments), self.t, final_position, final_velocity, target)


def _check_rates(*rates: float) -> None:
    for rate in rates:
        if not rate > 0.0:
            raise ValueError(f"acceleration/deceleration must be positive, got {rate!r}")


def hold(t: float, position: float) -> Profile:
    """Standing still at ``position`` from ``t`` on."""
    return Profile(Kind.HOLD, (), t, position, 0.0)


def plan_stop(t: float, position: float, velocity: float, dec: float) -> Profile:
    """Decelerate to rest at ``dec`` (halt, quick stop, fault reaction)."""
    _check_rates(dec)
    b = _Builder(t, position, velocity)
    b.ramp_to_velocity(0.0, dec, dec)
    return b.finish(Kind.STOP, b.p, 0.0)


def plan_velocity(t: float, position: float, velocity: float, v_target: float,
                  acc: float, dec: float) -> Profile:
    """Ramp to ``v_target`` and keep it (profile velocity mode)."""
    _check_rates(acc, dec)
    b = _Builder(t, position, velocity)
    b.ramp_to_velocity(v_target, acc, dec)
    return b.finish(Kind.VELOCITY, b.p, float(v_target))


def plan_position(t: float, position: float, velocity: float, target: float,
                  v_max: float, acc: float, dec: float) -> Profile:
    """A trapezoid (or triangle) from the current state to rest on ``target``.

    ``v_max`` is the profile velocity (already limited by 607Fh). With
    ``v_max <= 0`` the axis cannot move: the result stops and never arrives.
    """
    _check_rates(acc, dec)
    if not v_max > 0.0:
        stop = plan_stop(t, position, velocity, dec)
        return Profile(Kind.STOP, stop.segments, stop.end_time, stop.final_position, 0.0)
    b = _Builder(t, position, velocity)
    d = target - b.p
    if b.v != 0.0:
        towards = d != 0.0 and (d > 0.0) == (b.v > 0.0)
        if not towards or b.v * b.v / (2.0 * dec) > abs(d):
            b.ramp_to_velocity(0.0, dec, dec)  # stop first, then come back
            d = target - b.p
    if d != 0.0:
        s = math.copysign(1.0, d)
        dist = abs(d)
        u = abs(b.v)  # speed towards the target
        if u > v_max:
            # 607Fh/6081h were lowered during the move: slow to v_max first.
            b.ramp(-s * dec, (u - v_max) / dec)
            dist -= (u * u - v_max * v_max) / (2.0 * dec)
            u = v_max
            b.ramp(0.0, (dist - u * u / (2.0 * dec)) / u)
            b.ramp(-s * dec, u / dec)
        else:
            d_acc = (v_max * v_max - u * u) / (2.0 * acc)
            d_dec = v_max * v_max / (2.0 * dec)
            if d_acc + d_dec <= dist:  # trapezoid
                b.ramp(s * acc, (v_max - u) / acc)
                b.ramp(0.0, (dist - d_acc - d_dec) / v_max)
                b.ramp(-s * dec, v_max / dec)
            else:  # triangle: peak speed where the two ramps meet
                peak = math.sqrt((dist + u * u / (2.0 * acc)) / (1.0 / (2.0 * acc) + 1.0 / (2.0 * dec)))
                peak = max(peak, u)
                b.ramp(s * acc, (peak - u) / acc)
                b.ramp(-s * dec, peak / dec)
    # Rest exactly on the target; the ramps above end within rounding of it.
    return b.finish(Kind.POSITION, float(target), 0.0, float(target))


def first_beyond(profile: Profile, level: float, direction: int, t0: float, t1: float) -> float | None:
    """The first time in [t0, t1] at which the axis is at or beyond ``level`` on the
    ``direction`` side (+1: above, -1: below) while moving further that way; None if never.

    Exact, per constant-acceleration piece: the roots of ``p(t) = level`` and the
    instant the velocity turns outwards, whichever comes first.
    """
    s = 1.0 if direction > 0 else -1.0
    pieces = [(seg.start, seg.end, seg.position, seg.velocity, seg.acceleration)
              for seg in profile.segments]
    pieces.append((profile.end_time, math.inf, profile.final_position, profile.final_velocity, 0.0))
    for start, end, p, v, a in pieces:
        lo, hi = max(t0, start), min(t1, end)
        if lo > hi:
            continue
        # Normalised: q = s * (position - level) >= 0 beyond the level, u = outward speed.
        dt0 = lo - start
        q0 = s * (p + v * dt0 + 0.5 * a * dt0 * dt0 - level)
        u0, b = s * (v + a * dt0), s * a
        found = _first_outward(q0, u0, b, hi - lo)
        if found is not None:
            return lo + found
    return None


def _first_outward(q0: float, u0: float, b: float, span: float) -> float | None:
    """Least tau in [0, span] with q(tau) = q0 + u0 tau + b tau^2/2 >= 0 and q'(tau) > 0 (or
    q' = 0 turning positive)."""
    if q0 >= 0.0 and (u0 > 0.0 or (u0 == 0.0 and b > 0.0)):
        return 0.0
    candidates: list[float] = []
    if b > 0.0 and u0 < 0.0:  # the velocity turns outwards at -u0/b
        tv = -u0 / b
        if q0 + u0 * tv + 0.5 * b * tv * tv >= 0.0:
            candidates.append(tv)
    if b == 0.0:
        if u0 > 0.0 and q0 < 0.0:
            candidates.append(-q0 / u0)
    else:
        disc = u0 * u0 - 2.0 * b * q0
        if disc >= 0.0:
            r = math.sqrt(disc)
            for tau in ((-u0 - r) / b, (-u0 + r) / b):
                if tau >= 0.0 and u0 + b * tau > 0.0:
                    candidates.append(tau)
    hits = [tau for tau in candidates if 0.0 <= tau <= span]
    return min(hits) if hits else None
