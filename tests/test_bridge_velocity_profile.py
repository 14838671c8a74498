"""The velocity ramp of a CSV move (issue 26, tcp_bridge/motion/profile.py): pure.

Properties: the set-point is continuous (between two samples dt apart it
changes by at most rate * dt, before and after a stop at any instant), it
never leaves the range between its start and its target, it is the target
exactly from the ramp's end on, and a stop comes to 0 at the stop rate.
"""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcp_bridge.motion.profile import VelocityRamp

speeds = st.floats(-5000.0, 5000.0, allow_nan=False)
rates = st.floats(1.0, 1e5, allow_nan=False)
DT = 0.001


def samples(ramp: VelocityRamp, t0: float, t1: float) -> list[float]:
    n = int((t1 - t0) / DT) + 1
    return [ramp.velocity(t0 + i * DT) for i in range(n + 1)]


@settings(max_examples=200, deadline=None)
@given(speeds, speeds, rates, rates, st.floats(0.0, 1.0))
def test_the_set_point_never_steps_and_a_stop_ramps_it_to_zero(
        v0: float, target: float, rate: float, stop_rate: float, when: float) -> None:
    ramp = VelocityRamp(0.0, v0, target, rate, stop_rate)
    end = min(ramp.ramp_end, 2.0)
    seen = samples(ramp, 0.0, end)
    assert all(abs(b - a) <= rate * DT * (1 + 1e-9) + 1e-9 for a, b in zip(seen, seen[1:]))
    lo, hi = min(v0, target), max(v0, target)
    assert all(lo - 1e-9 <= v <= hi + 1e-9 for v in seen)
    assert ramp.velocity(ramp.ramp_end) == target and not ramp.finished(1e9)
    t_stop = when * end
    stop = ramp.stop_at(t_stop)
    assert math.isclose(stop.velocity(t_stop), ramp.velocity(t_stop), abs_tol=1e-9)  # no step
    tail = samples(stop, t_stop, min(stop.ramp_end, t_stop + 2.0))
    limit = max(rate, stop_rate)
    whole = [ramp.velocity(t_stop - DT)] + tail
    assert all(abs(b - a) <= limit * DT * (1 + 1e-9) + 1e-9 for a, b in zip(whole, whole[1:]))
    assert stop.stopping and stop.finished(stop.ramp_end) and stop.velocity(stop.ramp_end) == 0.0
    assert math.isclose(stop.ramp_end - t_stop, abs(ramp.velocity(t_stop)) / stop_rate,
                        rel_tol=1e-9, abs_tol=1e-12)


def test_a_move_holds_its_velocity_until_stopped() -> None:
    ramp = VelocityRamp(1.0, 0.0, 200.0, 400.0, 800.0)
    assert ramp.velocity(1.25) == 100.0 and ramp.velocity(1.5) == 200.0
    assert ramp.velocity(100.0) == 200.0 and ramp.end_time == math.inf
    stop = ramp.stop_at(2.0)
    assert stop.velocity(2.125) == 100.0 and stop.end_time == 2.25 and stop.finished(2.25)
    assert stop.stop_at(3.0) is stop  # a finished stop stays as it is


def test_rates_must_be_positive_and_finite() -> None:
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError):
            VelocityRamp(0.0, 0.0, 1.0, bad, 1.0)
        with pytest.raises(ValueError):
            VelocityRamp(0.0, 0.0, 1.0, 1.0, bad)
    with pytest.raises(ValueError):
        VelocityRamp(0.0, 0.0, math.inf, 1.0, 1.0)
