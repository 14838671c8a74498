"""Homing that takes time and travels at the homing speeds (issue 10, item 4).

Statusword bits 13/12/10 from the CiA 402-2 6.6 table: in progress 0/0/0,
interrupted or not started 0/0/1, completed 0/1/1, error 1/0/x.

The drive has a 15-pulse encoder (60 increments per revolution, so 1 rpm =
1 inc/s) and the EDS homing defaults: 100 rpm switch search, 10 rpm zero
search, 1000 rpm/s homing acceleration. A stop from 100 inc/s at 1000
inc/s^2 takes 0.1 s over 5 inc. Its virtual switches are set per test.
"""
from __future__ import annotations

import pytest
from canopen import SdoAbortedError
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.cia402 import State
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.homing import (
    SUPPORTED_METHODS,
    WITH_INDEX,
    HomingStatus,
    VirtualSwitches,
    plan_homing,
)
from epos_link.simulator.od import ObjectStore, load_object_dictionary
from epos_link.simulator.safety import EventKind

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, START, HALT = 0x06, 0x0F, 0x10, 0x100
BITS = 0x2000 | 0x1000 | 0x0400  # 13, 12, 10
IN_PROGRESS, IDLE, COMPLETED = 0x0000, 0x0400, 0x1400
REFERENCED = 0x8000


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def homing_drive(method: int, **switches: float) -> Drive:
    d = Drive(ObjectStore(OD), switches=VirtualSwitches(**switches))
    write(d, 0x3010, 15, 1)  # 60 inc/rev
    write(d, 0x30B0, 1234)  # home position
    write(d, 0x6098, method)
    d.set_mode(Mode.HOMING)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    return d


def start(d: Drive) -> None:
    d.write_controlword(ENABLE | START)


SWITCHES = dict(negative_limit=-500.0, positive_limit=500.0, home_switch=200.0,
                negative_stop=-600.0, positive_stop=600.0)


def test_not_started_reads_0_0_1() -> None:
    d = homing_drive(18, **SWITCHES)
    assert d.statusword & BITS == IDLE and d.homing_status is HomingStatus.IDLE


def test_positive_limit_switch_method_18() -> None:
    """Search: 0 -> 505 at 100 inc/s (0.1 s ramps, 4.95 s cruise); edge: 505 -> 500 at 10 inc/s."""
    d = homing_drive(18, **SWITCHES)
    start(d)
    assert d.statusword & BITS == IN_PROGRESS and d.statusword & REFERENCED == 0
    d.update(1.0)
    assert d.store.read_value(0x606C) == 100  # speed for switch search, rpm
    assert d.position == 95
    d.update(5.1)  # past the switch at 5.05 s, decelerating
    assert 500 < d.position < 505 and d.statusword & BITS == IN_PROGRESS
    d.update(5.15 + 0.2)
    assert d.store.read_value(0x606C) == -10  # speed for zero search, back to the edge
    d.update(5.15 + 0.51 - 1e-6)
    assert d.statusword & BITS == IN_PROGRESS
    d.update(5.15 + 0.51 + 1e-6)
    assert d.statusword & BITS == COMPLETED and d.statusword & REFERENCED
    assert d.position == 1234 and d.velocity == 0
    assert d.motion_starts == 1 and d.events[-1].detail == "homing method 18"


@pytest.mark.parametrize(("method", "end"), [
    (17, -500.0), (18, 500.0),  # limit switch edges
    (1, -480.0), (2, 480.0),  # first index pulse back inside from the limit switch
    (-3, 600.0), (-4, -600.0),  # end stops (current threshold)
    (-1, 540.0), (-2, -540.0),  # end stop, then the index back inside (maxon's "_AND_INDEX")
    (7, 180.0), (23, 200.0),  # home switch (positive side of 0) with / without index
    (33, -60.0), (34, 60.0),  # index only, at zero search speed
])
def test_methods_end_where_the_switches_are(method: int, end: float) -> None:
    d = homing_drive(method, **SWITCHES)
    start(d)
    d.advance(60.0)
    assert d.homing_status is HomingStatus.DONE and d.position == 1234
    assert d.axis_position == pytest.approx(end)  # the counter moved, the axis is at the switch
    d.write_controlword(ENABLE)
    d.set_mode(Mode.PROFILE_POSITION)
    write(d, 0x607A, 1234 - round(end))  # back to where the axis started
    d.write_controlword(ENABLE | START)
    d.advance(60.0)
    assert d.axis_position == pytest.approx(0.0, abs=1e-6) and d.position == 1234 - round(end)


def test_home_offset_move_distance() -> None:
    d = homing_drive(17, **SWITCHES)
    write(d, 0x30B1, -100)  # from the switch edge at -500 on to -600, then counter := 30B0
    start(d)
    d.advance(60.0)
    assert d.position == 1234 and d.axis_position == pytest.approx(-600.0)


def test_actual_position_methods_complete_at_once() -> None:
    for method in (35, 37):
        d = homing_drive(method)
        start(d)
        assert d.statusword & BITS == COMPLETED and d.position == 1234
        assert d.motion_starts == 0  # no motion


def test_halt_interrupts_homing() -> None:
    d = homing_drive(18, **SWITCHES)
    start(d)
    d.advance(1.0)
    d.write_controlword(ENABLE | START | HALT)
    assert d.homing_status is HomingStatus.IDLE
    d.advance(0.05)
    assert d.velocity > 0 and d.statusword & BITS == 0  # decelerating: bit 10 waits for rest
    d.advance(0.1)
    assert d.velocity == 0 and d.statusword & BITS == IDLE  # interrupted: 0/0/1
    d.write_controlword(ENABLE)  # releasing halt does not resume a homing
    d.advance(10.0)
    assert d.position == 100 and d.homing_status is HomingStatus.IDLE
    start(d)
    assert d.motion_starts == 2
    d.advance(60.0)
    assert d.statusword & BITS == COMPLETED


def test_a_falling_start_bit_interrupts_homing() -> None:
    # CiA 402-2 6.6.1.1: controlword bit 4 "homing operation start", 1 -> 0
    # interrupts the homing: the axis stops on 609Ah, 0/0/1 at rest.
    d = homing_drive(18, **SWITCHES)
    start(d)
    d.advance(1.0)
    d.write_controlword(ENABLE)
    assert d.homing_status is HomingStatus.IDLE
    d.advance(0.05)
    assert d.velocity > 0 and d.statusword & BITS == 0  # decelerating: bit 10 waits for rest
    d.advance(0.1)
    assert d.velocity == 0 and d.statusword & BITS == IDLE  # interrupted: 0/0/1, not attained
    assert d.statusword & REFERENCED == 0
    d.advance(10.0)
    assert d.position == 100  # it stays where it stopped
    start(d)  # a new rising edge starts it again, from here
    d.advance(60.0)
    assert d.statusword & BITS == COMPLETED and d.motion_starts == 2


@pytest.mark.parametrize("method,missing,stop", [
    (18, "positive_limit", 600), (17, "negative_limit", -600), (2, "positive_limit", 600),
    (7, "home_switch", 600), (23, "home_switch", 600), (11, "home_switch", -600),
    (27, "home_switch", -600)])
def test_a_switch_that_is_not_fitted_makes_homing_fail(method: int, missing: str,
                                                       stop: int) -> None:
    # The search runs on to the end stop, where the axis stops: "homing error
    # occurred, velocity is 0" = 1/0/1 (CiA 402-2 6.6 table); not referenced.
    d = homing_drive(method, **SWITCHES)
    setattr(d.switches, missing, None)
    start(d)
    d.advance(0.5)
    assert d.statusword & BITS == IN_PROGRESS and d.velocity != 0
    d.advance(30.0)
    assert d.homing_status is HomingStatus.ERROR
    assert d.velocity == 0 and d.statusword & BITS == 0x2000 | 0x0400
    assert d.statusword & REFERENCED == 0
    assert d.position == stop  # the counter was not set to 30B0h
    assert d.state is State.OPERATION_ENABLED  # chosen: no fault (homing.py)
    d.write_controlword(ENABLE)  # bit 4 back to 0: the error stays until a new start
    assert d.statusword & BITS == 0x2000 | 0x0400
    setattr(d.switches, missing, 500.0 if stop > 0 else -500.0)
    start(d)  # a new start clears it
    assert d.statusword & BITS == IN_PROGRESS


def test_homing_error_on_following_error() -> None:
    d = homing_drive(18, **SWITCHES)
    start(d)
    d.advance(1.0)
    d.inject_fault("following_error")
    assert d.statusword & 0x2000 and d.statusword & 0x1000 == 0  # 1/0/x: homing error
    d.advance(1.0)
    assert d.state is State.FAULT


def test_mode_change_and_disable_interrupt_homing() -> None:
    d = homing_drive(18, **SWITCHES)
    start(d)
    d.advance(1.0)
    d.set_mode(Mode.PROFILE_POSITION)
    assert d.homing_status is HomingStatus.IDLE
    d.advance(1.0)
    assert d.velocity == 0 and d.position < 200


def test_unsupported_methods_are_refused() -> None:
    d = Drive(ObjectStore(OD))
    for method in (0, 3, 15, 19, 31, 36):
        with pytest.raises(SdoAbortedError) as info:
            write(d, 0x6098, method)
        assert info.value.code == 0x06090030


# maxon's EPOS Command Library, Definitions.h "Homing method" (HM_*), and 37.
MAXON_METHODS = {35, 17, 1, 18, 2, 23, 7, 27, 11, -3, -1, -4, -2, 34, 33, 37}


@pytest.mark.parametrize("method", [8, 9, 10, 12, 13, 14, 24, 25, 26, 28, 29, 30])
def test_cia402_methods_maxon_does_not_list_are_refused(method: int) -> None:
    d = Drive(ObjectStore(OD))
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x6098, method)
    assert info.value.code == 0x06090030
    assert d.store.get_int(0x6098) != method


def test_exactly_maxons_methods_are_accepted() -> None:
    d = Drive(ObjectStore(OD))
    accepted = set()
    for method in range(-128, 128):
        try:
            write(d, 0x6098, method)
        except SdoAbortedError:
            continue
        accepted.add(method)
    assert accepted == MAXON_METHODS == set(SUPPORTED_METHODS)


def test_homing_in_default_units_travels_in_rpm() -> None:
    d = Drive(ObjectStore(OD))  # 2000 inc/rev: 100 rpm = 3333.3 inc/s
    write(d, 0x6098, 18)
    d.set_mode(Mode.HOMING)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    start(d)
    d.advance(1.0)
    assert d.store.read_value(0x606C) == 100
    assert d.velocity_increments == pytest.approx(2000 * 100 / 60)
    d.advance(10.0)  # the default switch is 5 revolutions away: 3 s at 100 rpm
    assert d.homing_status is HomingStatus.DONE
    assert [e.kind for e in d.events] == [EventKind.MOTION_START]


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(sorted(SUPPORTED_METHODS)), st.floats(-5000, 5000), st.integers(4, 10000),
       st.floats(1, 1e5), st.floats(1, 1e4), st.floats(1, 1e6), st.integers(-1000, 1000))
def test_plan_homing_properties(method: int, position: float, ipr: int, v1: float, v2: float,
                                acc: float, offset: int) -> None:
    sw = VirtualSwitches(-6000.0, 6000.0, 100.0, -7000.0, 7000.0, index_phase=3.0)
    legs = plan_homing(method, position, sw, increments_per_revolution=ipr, switch_speed=v1,
                       zero_speed=v2, acceleration=acc, offset_move=float(offset))
    if method in (35, 37):
        assert legs == []
        return
    assert legs and all(leg.speed in (v1, v2) for leg in legs)
    found = legs[-2] if offset else legs[-1]  # where the home is found, before the offset move
    if offset:
        assert legs[-1].target == pytest.approx(found.target + offset)
    if method in WITH_INDEX:
        k = (found.target - sw.index_phase) / ipr
        assert k == pytest.approx(round(k), abs=1e-6) and found.speed == v2
    elif method in (17, 18, -3, -4) or method >= 23:
        expected = {17: sw.negative_limit, 18: sw.positive_limit, -3: sw.positive_stop,
                    -4: sw.negative_stop}.get(method, sw.home_switch)
        assert found.target == expected
