"""EPOS4 default units (issue 10, item 1): increments, rpm, rpm/s, the encoder objects.

Expected numbers are worked out by hand from the defaults the EDS declares
(500-pulse encoder = 2000 increments per revolution; profile velocity
1000 rpm; acceleration 10000 rpm/s): 1 rpm = 2000/60 inc/s.
"""
from __future__ import annotations

import pytest
from canopen import SdoAbortedError
from hypothesis import given
from hypothesis import strategies as st

from epos_link.cia402 import State
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.drive import Drive, Mode, VirtualClock
from epos_link.simulator.od import ObjectStore, load_object_dictionary
from epos_link.simulator.units import (
    VELOCITY_PREFIXES,
    Units,
    increments_per_revolution,
    velocity_exponent,
)

OD = load_object_dictionary(1)
ENABLE, NEW_SET_POINT = 0x000F, 0x0010
RANGE = 0x06090030
READ_ONLY = 0x06010002


def make() -> Drive:
    return Drive(ObjectStore(OD))


def enabled(mode: Mode = Mode.PROFILE_POSITION) -> Drive:
    d = make()
    d.set_mode(mode)
    d.write_controlword(0x0006)
    d.write_controlword(ENABLE)
    assert d.state is State.OPERATION_ENABLED
    return d


def read(d: Drive, index: int, sub: int = 0) -> object:
    return d.store.read_value(index, sub)


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def start_move(d: Drive, target: int) -> None:
    write(d, 0x607A, target)
    d.write_controlword(ENABLE | NEW_SET_POINT)
    d.write_controlword(ENABLE)


def test_default_unit_objects() -> None:
    d = make()
    assert read(d, 0x60A9) == 0x00B44700  # rpm (EPOS4 default)
    assert read(d, 0x60AA) == 0x00C00300  # rpm/s, fixed
    assert read(d, 0x3010, 1) == 500
    assert read(d, 0x3000, 5) == 2000  # 4 x pulses, quadrature
    assert d.increments_per_revolution == 2000
    assert increments_per_revolution(d.store) == 2000


def test_resolution_is_read_only_and_follows_the_encoder() -> None:
    d = make()
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x3000, 4096, 5)
    assert info.value.code == READ_ONLY
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x60AA, 0x00C00300)
    assert info.value.code == READ_ONLY
    write(d, 0x3010, 1024, 1)
    assert read(d, 0x3000, 5) == 4096 and d.increments_per_revolution == 4096


def test_default_move_of_a_few_thousand_increments_is_quick() -> None:
    """1000 rpm = 33333 inc/s, 10000 rpm/s = 333333 inc/s^2: 4000 inc take 0.22 s."""
    d = enabled()
    start_move(d, 4000)
    d.update(0.1)  # end of the acceleration: 1000 rpm, 1667 inc travelled
    assert (d.position, d.velocity, read(d, 0x606C)) == (1667, 1000, 1000)
    d.update(0.22 - 1e-6)
    assert d.statusword & 0x0400 == 0
    d.update(0.22 + 1e-6)
    assert d.position == 4000 and d.statusword & 0x0400


def test_profile_velocity_mode_in_rpm() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x60FF, 600)  # 600 rpm = 20000 inc/s, reached after 0.06 s
    d.update(1.06)
    assert read(d, 0x606C) == 600
    assert d.velocity_increments == pytest.approx(20000)
    assert d.position == round(0.5 * 20000 * 0.06 + 20000 * 1.0)


@pytest.mark.parametrize(("prefix", "exponent"), sorted(VELOCITY_PREFIXES.items()))
def test_velocity_unit_prefixes(prefix: int, exponent: int) -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x60A9, (prefix << 24) | 0x00B44700)
    assert read(d, 0x60A9) == (prefix << 24) | 0x00B44700
    for limit in (0x607F, 0x6080):  # the limits are velocities too: 4000 rpm in the new unit
        write(d, limit, 4000 * 10 ** -exponent)
    write(d, 0x60FF, 600 * 10 ** -exponent)  # 600 rpm in the unit 10^exponent rpm
    d.advance(1.0)
    assert d.velocity_increments == pytest.approx(20000)
    assert read(d, 0x606C) == 600 * 10 ** -exponent


@pytest.mark.parametrize("value", [
    0x01B44700, 0xF9B44700, 0x80B44700,  # prefixes the EPOS4 does not take
    0xFCB44700, 0xFBB44700, 0xFAB44700,  # below milli-rpm: not in maxon's velocity notation
    0x00B44800, 0x00B54700, 0x00000000, 0xFAB44701,  # not rpm
])
def test_velocity_unit_refuses_what_the_epos4_refuses(value: int) -> None:
    d = make()
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x60A9, value)
    assert info.value.code == RANGE
    assert read(d, 0x60A9) == 0x00B44700


def test_velocity_notation_is_maxons() -> None:
    # EPOS Command Library Definitions.h: VN_STANDARD 0, VN_DECI -1, VN_CENTI -2, VN_MILLI -3.
    assert dict(VELOCITY_PREFIXES) == {0x00: 0, 0xFF: -1, 0xFE: -2, 0xFD: -3}


def test_milli_rpm_reinterprets_stored_velocities() -> None:
    """Chosen (units.py): 60A9h does not rescale the velocity objects."""
    d = enabled()
    write(d, 0x60A9, 0xFDB44700)
    assert d.velocity_increments == 0.0
    write(d, 0x6081, 1_000)  # 1 rpm; 607Fh/6080h = 50000 now mean 50 rpm
    for limit in (0x607F, 0x6080):
        write(d, limit, 4_000_000)
    start_move(d, 100)
    d.advance(1.0)
    assert d.velocity_increments == pytest.approx(2000 / 60) and read(d, 0x606C) == 1_000


def test_max_motor_speed_limits_profile_velocity() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x6080, 300)
    write(d, 0x60FF, 2000)
    d.advance(1.0)
    assert read(d, 0x606C) == 300
    assert d.statusword & 0x0800  # internal limit active: velocity limited


def test_simulator_helper_and_clock() -> None:
    clock = VirtualClock()
    with Epos4Simulator(1, [2], clock=clock) as sim:
        assert sim.increments_per_revolution(1) == 2000
        sim.drive(2).store.write_value(0x3010, 1, 256)
        assert sim.increments_per_revolution(2) == 1024


@given(st.integers(1, 2_500_000), st.sampled_from(sorted(VELOCITY_PREFIXES)),
       st.floats(-1e6, 1e6, allow_nan=False))
def test_conversions_round_trip(pulses: int, prefix: int, velocity: float) -> None:
    u = Units(4 * pulses, velocity_exponent((prefix << 24) | 0x00B44700))
    inc_s = u.velocity_to_inc_s(velocity)
    assert inc_s == pytest.approx(velocity * 10.0 ** VELOCITY_PREFIXES[prefix] * 4 * pulses / 60)
    assert u.velocity_from_inc_s(inc_s) == pytest.approx(velocity, rel=1e-12, abs=1e-9)
    assert u.acceleration_to_inc_s2(60.0) == pytest.approx(4 * pulses)
