"""Software position limits 607Dh in profile velocity mode: the 8A82h fault.

The EPOS4 error table (Firmware Specification 7.2, as public EPOS4 code
transcribes it) lists 8A82h "Software position limit error" with the fault
reaction (605Eh). A pv move is not clamped like a pp target: it faults where
the actual position passes 607Dh, and the fault reaction stops it.

15-pulse encoder: 60 increments per revolution, 1 rpm = 1 inc/s. 60FFh =
100 rpm on 6083h = 1000 rpm/s: 0.1 s of ramp over 5 increments, then 100
inc/s, so the axis passes 500 at 0.1 + 495 / 100 = 5.05 s.
"""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.cia402 import State
from epos_link.simulator.clock import VirtualClock
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.motion import first_beyond, plan_position, plan_velocity
from epos_link.simulator.od import ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, FAULT_RESET = 0x06, 0x0F, 0x80
CROSSING = 0.1 + 495 / 100


def pv_drive(lo: int = -500, hi: int = 500, **kwargs: object) -> Drive:
    d = Drive(ObjectStore(OD), **kwargs)  # type: ignore[arg-type]
    s = d.store
    s.write_value(0x3010, 1, 15)
    s.write_value(0x6083, 0, 1000)
    s.write_value(0x6085, 0, 50000)
    s.write_value(0x607D, 1, lo)
    s.write_value(0x607D, 2, hi)
    d.set_mode(Mode.PROFILE_VELOCITY)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    return d


def fault_time(d: Drive) -> float:
    return next(t for t, number, _ in d.history if number == 13)  # 13: fault


@pytest.mark.parametrize("direction", [1, -1])
def test_a_velocity_move_faults_where_it_passes_a_software_limit(direction: int) -> None:
    d = pv_drive()
    d.store.write_value(0x60FF, 0, 100 * direction)
    d.advance(5.0)
    assert d.state is State.OPERATION_ENABLED and d.position == 495 * direction
    d.advance(1.0)
    assert d.state is State.FAULT
    assert d.store.get_int(0x603F) == 0x8A82 and d.store.get_int(0x1003, 1) == 0x8A82
    assert fault_time(d) == pytest.approx(CROSSING)  # at the crossing, not at the step's end
    assert d.velocity == 0 and d.position == 500 * direction  # stopped on 6085h (0.1 inc)


def test_one_large_step_finds_the_same_instant() -> None:
    d = pv_drive()
    d.store.write_value(0x60FF, 0, 100)
    d.advance(60.0)
    assert fault_time(d) == pytest.approx(CROSSING) and d.position == 500


def test_with_a_clock_the_fault_is_at_the_crossing() -> None:
    clock = VirtualClock()
    d = pv_drive(clock=clock)
    d.store.write_value(0x60FF, 0, 100)
    clock.advance(7.0)
    assert d.store.read_value(0x6041) & 0x0008  # statusword: fault
    assert fault_time(d) == pytest.approx(CROSSING)


def test_moving_back_inside_is_allowed_further_out_is_not() -> None:
    d = pv_drive()
    d.store.write_value(0x60FF, 0, 100)
    d.advance(6.0)
    d.write_controlword(FAULT_RESET)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)  # 60FFh is still +100: the axis would go further out
    assert d.state is State.FAULT and d.store.get_int(0x1003, 0) == 2
    d.write_controlword(FAULT_RESET)
    d.store.write_value(0x60FF, 0, -100)  # back inside: no fault
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    d.advance(1.0)
    assert d.state is State.OPERATION_ENABLED and d.position < 500
    d.store.write_value(0x60FF, 0, 100)
    d.advance(2.0)
    assert d.state is State.FAULT and d.store.get_int(0x603F) == 0x8A82


def test_switched_off_limits_do_not_fault() -> None:
    d = pv_drive(lo=500, hi=500)  # min >= max: off (as for pp targets)
    d.store.write_value(0x60FF, 0, 100)
    d.advance(10.0)
    assert d.state is State.OPERATION_ENABLED and d.position == 995


def test_a_pp_target_beyond_the_limit_is_clamped_not_faulted() -> None:
    d = pv_drive()
    d.set_mode(Mode.PROFILE_POSITION)
    d.store.write_value(0x607A, 0, 1000)
    d.write_controlword(ENABLE | 0x10)
    d.advance(30.0)
    assert d.state is State.OPERATION_ENABLED and d.position == 500


@settings(max_examples=200, deadline=None)
@given(st.floats(-1000, 1000), st.floats(-500, 500), st.floats(-2000, 2000), st.floats(1, 1000),
       st.floats(1, 5000), st.floats(-1500, 1500), st.sampled_from([1, -1]), st.booleans())
def test_first_beyond_is_the_first_outward_passage(p0: float, v0: float, target: float, vmax: float,
                                                   acc: float, level: float, direction: int,
                                                   velocity_mode: bool) -> None:
    profile = (plan_velocity(0.0, p0, v0, target / 4, acc, acc) if velocity_mode
               else plan_position(0.0, p0, v0, target, vmax, acc, acc))
    horizon = profile.end_time + 1.0
    found = first_beyond(profile, level, direction, 0.0, horizon)
    tol = 1e-6 * (1 + abs(level) + abs(p0) + abs(target))

    def outward(t: float) -> bool:
        p, v = profile.state_at(t)
        return direction * (p - level) > tol and direction * v > 0

    samples = [horizon * i / 400 for i in range(401)]
    if found is None:
        assert not any(outward(t) for t in samples)
    else:
        p, _ = profile.state_at(found)
        assert direction * (p - level) >= -tol
        assert not any(outward(t) for t in samples if t < found - 1e-9)
