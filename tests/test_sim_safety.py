"""Option codes 605Ah..605Eh and the safety observables of a drive (issue 10, item 3).

Drives here run in EPOS4 default units with a 15-pulse encoder: 60 increments
per revolution, so 1 rpm = 1 inc/s and 1 rpm/s = 1 inc/s^2, and the numbers
below can be checked by hand. Profile velocity 1000 rpm, deceleration
10000 rpm/s (a stop from 1000 rpm takes 0.1 s over 50 inc), quick stop
deceleration 10000 rpm/s, coasting 2000 rpm/s (from 1000 rpm: 0.5 s, 250 inc).
"""
from __future__ import annotations

import pytest

from epos_link.cia402 import State, state_from_statusword
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.od import ObjectStore, load_object_dictionary
from epos_link.simulator.safety import MAX_EVENTS, EventKind

OD = load_object_dictionary(1)
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP = 0x06, 0x07, 0x0F, 0x00, 0x0B
NEW_SET_POINT, IMMEDIATE, HALT = 0x10, 0x20, 0x100
VOLTAGE, TARGET_REACHED = 0x0010, 0x0400


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def enabled(mode: Mode = Mode.PROFILE_POSITION) -> Drive:
    d = Drive(ObjectStore(OD))
    write(d, 0x3010, 15, 1)  # 60 inc/rev: 1 rpm = 1 inc/s (module docstring)
    d.set_mode(mode)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    return d


def moving_pv(velocity: int = 1000) -> Drive:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x60FF, velocity)
    d.advance(1.0)  # at speed since 0.1 s; position 50 + 900
    assert d.velocity == velocity
    return d


def start_move(d: Drive, target: int, bits: int = 0) -> None:
    write(d, 0x607A, target)
    d.write_controlword(ENABLE | NEW_SET_POINT | bits)
    d.write_controlword(ENABLE | bits)


def test_epos4_default_option_codes() -> None:
    d = Drive(ObjectStore(OD))
    values = {i: d.store.read_value(i) for i in (0x605A, 0x605B, 0x605C, 0x605D, 0x605E)}
    # maxon's EDS for firmware 0110h: 605Ah 6, 605Bh 0, 605Ch 1, 605Eh 2 (605Dh is
    # not in that EDS; 1 as the Firmware Specification quoted in simulator/drive.py)
    assert values == {0x605A: 6, 0x605B: 0, 0x605C: 1, 0x605D: 1, 0x605E: 2}


def test_shutdown_while_moving_cuts_the_drive_function_and_is_recorded() -> None:
    d = moving_pv()
    d.write_controlword(SHUTDOWN)  # 605Bh = 0: disable drive function, no ramp
    assert d.state is State.READY_TO_SWITCH_ON
    assert d.statusword & VOLTAGE == 0
    [stop] = d.unsafe_stops
    assert stop.kind is EventKind.UNSAFE_STOP and stop.velocity == 1000.0 and stop.time == 1.0
    assert "transition 8" in stop.detail
    d.advance(0.25)  # the drive cannot brake: the axis coasts on
    assert d.velocity == 500 and d.position == 950 + 188
    d.advance(1.0)
    assert d.velocity == 0 and d.position == 950 + 250


def test_shutdown_with_slow_down_option_ramps_first() -> None:
    d = moving_pv()
    write(d, 0x605B, 1)
    d.write_controlword(SHUTDOWN)
    assert d.state is State.OPERATION_ENABLED
    d.advance(0.1 + 1e-6)
    assert d.state is State.READY_TO_SWITCH_ON and d.position == 1000
    assert list(d.unsafe_stops) == []


def test_disable_operation_ramps_on_6084_and_shows_operation_enabled_until_standstill() -> None:
    d = moving_pv()
    write(d, 0x6084, 5000)  # 0.2 s from 1000 rpm
    d.write_controlword(SWITCH_ON)  # 605Ch = 1 (default)
    for dt in (0.0, 0.1, 0.099):
        d.advance(dt)
        assert state_from_statusword(d.statusword) is State.OPERATION_ENABLED
        assert d.statusword & TARGET_REACHED == 0 and d.velocity > 0
    d.advance(0.002)
    assert d.state is State.SWITCHED_ON and d.velocity == 0
    assert d.position == 950 + 100
    assert d.history[-1][1] == 5
    assert list(d.unsafe_stops) == []


def test_disable_operation_with_option_0_cuts_at_once() -> None:
    d = moving_pv()
    write(d, 0x605C, 0)
    d.write_controlword(SWITCH_ON)
    assert d.state is State.SWITCHED_ON and len(d.unsafe_stops) == 1


def test_disable_voltage_while_moving_is_an_unsafe_stop() -> None:
    d = moving_pv()
    d.write_controlword(DISABLE_VOLTAGE)
    assert d.state is State.SWITCH_ON_DISABLED
    assert [e.detail for e in d.unsafe_stops] == ["transition 9 to SWITCH_ON_DISABLED"]


def test_at_rest_nothing_is_unsafe() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    for cw in (SHUTDOWN, ENABLE, SWITCH_ON, ENABLE, DISABLE_VOLTAGE):
        d.write_controlword(cw)
    assert list(d.unsafe_stops) == [] and d.motion_starts == 0


def test_commands_during_the_disable_ramp() -> None:
    d = enabled()
    start_move(d, 5000)
    d.advance(1.0)
    d.write_controlword(SWITCH_ON)
    d.write_controlword(SWITCH_ON)  # the same request again: the ramp goes on
    d.write_controlword(ENABLE)  # enable operation is ignored while the ramp runs
    write(d, 0x607A, -100)
    d.write_controlword(ENABLE | NEW_SET_POINT)  # not accepted either
    assert d.statusword & 0x1000 == 0 and d.motion_starts == 1
    d.write_controlword(SWITCH_ON)
    d.advance(0.05)
    d.write_controlword(QUICK_STOP)  # replaces the pending transition
    assert d.state is State.QUICK_STOP_ACTIVE
    d.advance(1.0)
    # 605Ah = 6: at rest, and it stays in QUICK STOP ACTIVE with the power stage on
    assert d.state is State.QUICK_STOP_ACTIVE and d.velocity == 0
    assert list(d.unsafe_stops) == []


def test_a_fault_during_the_disable_ramp_ends_it_for_good() -> None:
    d = moving_pv()
    d.write_controlword(SWITCH_ON)  # ramp pending
    d.inject_fault("following_error")
    d.advance(1.0)
    d.write_controlword(0x80)  # fault reset
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    write(d, 0x60FF, 100)
    d.advance(1.0)
    assert d.state is State.OPERATION_ENABLED and d.velocity == 100  # no stale transition 5


@pytest.mark.parametrize(("option", "stop_time"), [(1, 0.1), (2, 0.02)])
def test_halt_option_code(option: int, stop_time: float) -> None:
    d = moving_pv()
    write(d, 0x605D, option)
    write(d, 0x6085, 50000)
    d.write_controlword(ENABLE | HALT)
    d.advance(stop_time - 1e-6)
    assert d.velocity_increments > 0
    d.advance(2e-6)
    assert d.velocity_increments == 0 and d.state is State.OPERATION_ENABLED


@pytest.mark.parametrize(("option", "unsafe"), [(0, True), (1, False), (2, False)])
def test_fault_reaction_option_code(option: int, unsafe: bool) -> None:
    d = moving_pv()
    write(d, 0x605E, option)
    d.inject_fault("following_error")
    assert bool(d.unsafe_stops) is unsafe
    d.advance(1.0)
    assert d.state is State.FAULT


# -- motion starts --------------------------------------------------------------------


def test_each_accepted_set_point_is_one_motion_start() -> None:
    d = enabled()
    start_move(d, 1000)
    assert d.motion_starts == 1
    d.advance(0.5)
    start_move(d, 2000)  # buffered: accepted, counted
    start_move(d, 3000)  # buffer full: refused, not counted
    assert d.motion_starts == 2
    start_move(d, 100, IMMEDIATE)
    assert d.motion_starts == 3
    d.advance(10.0)
    assert d.motion_starts == 3 and d.position == 100
    starts = [e.detail for e in d.events if e.kind is EventKind.MOTION_START]
    assert starts == ["set-point 1000", "set-point 2000", "set-point 100"]


def test_releasing_halt_resumes_and_counts() -> None:
    d = enabled()
    start_move(d, 1000)
    d.advance(0.3)
    d.write_controlword(ENABLE | HALT)
    d.advance(1.0)
    assert d.motion_starts == 1 and d.velocity == 0
    d.write_controlword(ENABLE)  # the pending target is resumed
    assert d.motion_starts == 2 and d.events[-1].detail == "halt released"


def test_stopped_velocity_move_restarting_is_visible() -> None:
    """Issue 10 finding 2: halt keeps 60FFh; re-enabling restarts the motion."""
    d = moving_pv()
    assert d.motion_starts == 1
    d.write_controlword(ENABLE | HALT)  # "stop"
    d.advance(1.0)
    d.write_controlword(SWITCH_ON | HALT)  # disable
    d.write_controlword(ENABLE)  # enable, halt cleared: runs again at the old speed
    assert d.motion_starts == 2
    d.advance(1.0)
    assert d.velocity == 1000
    write(d, 0x60FF, 2000)  # faster: not a new start
    write(d, 0x60FF, 0)
    d.advance(1.0)
    assert d.motion_starts == 2
    write(d, 0x60FF, 10)  # from rest to motion: a start
    assert d.motion_starts == 3


def test_mode_change_and_quick_stop_return_count_when_they_start_motion() -> None:
    d = enabled()
    write(d, 0x60FF, 500)
    d.set_mode(Mode.PROFILE_VELOCITY)
    assert d.motion_starts == 1
    write(d, 0x605A, 6)
    d.write_controlword(QUICK_STOP)
    d.advance(1.0)
    d.write_controlword(ENABLE)  # transition 16: 60FFh still 500
    assert d.motion_starts == 2 and d.events[-1].kind is EventKind.MOTION_START


def test_resets_while_moving() -> None:
    d = moving_pv()
    d.reset_node()
    assert d.resets_while_moving == 1
    assert [e.kind for e in d.events][-2:] == [EventKind.NMT_RESET, EventKind.RESET_WHILE_MOVING]
    d.advance(5.0)  # coasted to rest
    d.reset_node()
    d.power_cycle()
    assert d.resets_while_moving == 1
    assert d.events[-1].kind is EventKind.POWER_CYCLE


def test_event_log_is_bounded() -> None:
    d = enabled()
    for k in range(MAX_EVENTS + 10):
        start_move(d, k, IMMEDIATE)
    assert d.motion_starts == MAX_EVENTS + 10 and len(d.events) == MAX_EVENTS
