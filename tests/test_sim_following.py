"""Following error from dynamics and the position window (CiA 402-2 6065h..6068h).

The lag model (monitors.py, chosen): a blocked axis (Drive.block_axis or
2100h = 7) stays where it is (6064h) while the demand (6062h) goes on.
|6062h - 6064h| > 6065h for 6066h ms raises 8611h; pp target reached needs
|607Ah - 6064h| <= 6067h for 6068h ms once the demand has arrived.

15-pulse encoder: 60 increments per revolution, 1 rpm = 1 inc/s. 6081h =
100 rpm, 6083h/6084h = 1000 rpm/s: a move ramps over 5 increments in 0.1 s.
"""
from __future__ import annotations

import pytest
from canopen import SdoAbortedError

from epos_link.cia402 import State
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.od import ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, START, FAULT_RESET = 0x06, 0x0F, 0x10, 0x80
TARGET_REACHED, BIT13 = 0x0400, 0x2000


def drive(mode: Mode = Mode.PROFILE_POSITION) -> Drive:
    d = Drive(ObjectStore(OD))
    s = d.store
    s.write_value(0x3010, 1, 15)
    s.write_value(0x6081, 0, 100)
    s.write_value(0x6083, 0, 1000)
    s.write_value(0x6084, 0, 1000)
    s.write_value(0x6065, 0, 50)  # following error window, increments
    d.set_mode(mode)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    return d


def move(d: Drive, target: int) -> None:
    d.store.write_value(0x607A, 0, target)
    d.write_controlword(ENABLE | START)
    d.write_controlword(ENABLE)


def fault_time(d: Drive) -> float:
    return next(t for t, number, _ in d.history if number == 13)


def test_the_eds_has_6066h_and_6068h_as_cia_402_defines_them() -> None:
    s = Drive(ObjectStore(OD)).store
    for index in (0x6066, 0x6068):  # UNSIGNED16, ms, rw
        assert s.get_int(index) == 0
        s.write_value(index, 0, 65535)
        with pytest.raises(SdoAbortedError):
            s.write(index, 0, b"\x00\x00\x01\x00")  # 65536 does not fit


def test_an_unblocked_move_ends_exactly_on_target_with_demand_equal_actual() -> None:
    d = drive()
    move(d, 1000)
    d.advance(2.0)
    assert d.store.read_value(0x6062) == d.store.read_value(0x6064)
    d.advance(20.0)
    assert d.position == 1000 and d.statusword & TARGET_REACHED
    assert d.store.read_value(0x6062) == 1000


def test_a_blocked_axis_lags_and_trips_8611h_when_6065h_is_exceeded() -> None:
    d = drive()
    move(d, 1000)
    d.advance(1.0)  # at 100 inc/s, 95 increments out
    d.block_axis()
    assert d.position == 95 and d.velocity == 0
    d.advance(0.4)
    assert d.store.read_value(0x6064) == 95 and d.store.read_value(0x6062) == 135  # lag 40
    assert d.state is State.OPERATION_ENABLED  # 40 <= 50
    d.advance(0.2)
    assert d.state is State.FAULT and d.store.get_int(0x603F) == 0x8611
    assert fault_time(d) == pytest.approx(1.5)  # lag 50 + a hair: at once (6066h = 0)
    assert d.statusword & BIT13  # pp: following error
    assert d.store.read_value(0x6062) == d.store.read_value(0x6064) == 95  # power off: loop idle


def test_6066h_is_a_time_out_the_error_must_last() -> None:
    d = drive()
    d.store.write_value(0x6066, 0, 300)  # ms
    move(d, 1000)
    d.advance(1.0)
    d.block_axis()
    d.advance(0.7)  # above the window since 1.5 s
    assert d.state is State.OPERATION_ENABLED
    d.advance(0.2)
    assert d.state is State.FAULT and fault_time(d) == pytest.approx(1.8)


def test_an_error_that_ends_before_the_time_out_does_not_fault() -> None:
    d = drive()
    d.store.write_value(0x6066, 0, 300)
    move(d, 1000)
    d.advance(1.0)
    d.block_axis()
    d.advance(0.7)
    d.release_axis()  # the axis moves again: the demand starts over from it
    assert d.store.read_value(0x6062) == d.store.read_value(0x6064) == 95
    d.advance(30.0)
    assert d.state is State.OPERATION_ENABLED and d.position == 1000
    assert d.statusword & TARGET_REACHED


def test_blocked_near_the_target_target_reached_needs_the_position_window() -> None:
    d = drive()
    move(d, 1000)
    d.advance(10.0 - 0.3)  # the demand decelerates; 6067h = 10 increments
    d.block_axis()
    d.advance(5.0)
    lag = 1000 - d.position
    assert 10 < lag <= 50 and d.state is State.OPERATION_ENABLED
    assert d.store.read_value(0x6062) == 1000
    assert d.statusword & TARGET_REACHED == 0  # the demand is there, the axis is not
    d.store.write_value(0x6067, 0, 60)  # a window that takes it in: reached at the next arrival
    d.release_axis()
    d.advance(5.0)
    assert d.position == 1000 and d.statusword & TARGET_REACHED


def test_6068h_delays_target_reached() -> None:
    d = drive()
    d.store.write_value(0x6068, 0, 250)  # ms
    move(d, 100)
    end = 0.1 + 0.9 + 0.1  # ramp over 5, 90 increments at 100 inc/s, ramp over 5
    d.advance(end + 0.2)
    assert d.position == 100 and d.statusword & TARGET_REACHED == 0
    d.advance(0.1)
    assert d.statusword & TARGET_REACHED


def test_6065h_all_ones_switches_the_monitor_off() -> None:
    d = drive()
    d.store.write_value(0x6065, 0, 0xFFFFFFFF)
    move(d, 1000)
    d.advance(1.0)
    d.block_axis()
    d.advance(30.0)
    assert d.state is State.OPERATION_ENABLED and d.position == 95


def test_a_blocked_homing_ends_in_a_homing_error() -> None:
    d = drive(Mode.HOMING)
    d.store.write_value(0x6098, 0, 18)
    d.write_controlword(ENABLE | START)
    d.advance(0.5)
    d.block_axis()
    d.advance(5.0)
    assert d.state is State.FAULT and d.store.get_int(0x603F) == 0x8611


def test_block_and_release_through_2100h() -> None:
    d = drive()
    move(d, 1000)
    d.advance(1.0)
    d.store.write(0x2100, 0, b"\x07\x00\x00\x00")
    assert d.blocked
    d.store.write(0x2100, 0, b"\x08\x00\x00\x00")
    assert not d.blocked
    d.advance(30.0)
    assert d.position == 1000


def test_a_velocity_move_is_not_monitored_for_following_error() -> None:
    d = drive(Mode.PROFILE_VELOCITY)
    d.store.write_value(0x60FF, 0, 100)
    d.advance(1.0)
    d.block_axis()
    d.advance(10.0)
    assert d.state is State.OPERATION_ENABLED and d.velocity == 0
