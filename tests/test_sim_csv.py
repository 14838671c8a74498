"""Cyclic synchronous velocity mode (csv, 6060h = 9) of the simulated drive.

What a csv drive does, as CiA 402-2 describes the mode (the same "use of
controlword and statusword" as csp, which drive manuals quote, e.g. Nanotec N5
"Cyclic Synchronous Velocity"): the master's 60FFh is the input of the velocity
loop at once, no ramp of its own from 6083h/6084h; halt is not evaluated;
statusword bit 10 is reserved, bit 12 "drive follows the command value", bit
13 reserved. The simulator's own choice (epos_link/simulator/kinematics.py): the
velocity loop follows within the acceleration limit 60C5h, limited to 607Fh.

Units as in test_sim_drive.py: 60 increments per revolution, 1 rpm = 1 inc/s.
"""
from __future__ import annotations

from epos_link.cia402 import State
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.od import ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, HALT = 0x06, 0x0F, 0x100
TARGET_REACHED, INTERNAL_LIMIT, BIT12, BIT13 = 0x0400, 0x0800, 0x1000, 0x2000
CSV, CSP = 9, 8


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def csv_drive(*, enable: bool = True) -> Drive:
    d = Drive(ObjectStore(OD))
    write(d, 0x3010, 15, 1)  # 60 inc/rev: 1 rpm = 1 inc/s
    write(d, 0x607F, 1000)  # velocity limit 1000 inc/s ...
    write(d, 0x60C5, 10000)  # ... acceleration limit 10000 inc/s^2
    write(d, 0x6083, 10)  # pv's own ramps, slow: csv must not use them
    write(d, 0x6084, 10)
    write(d, 0x6060, CSV)
    if enable:
        d.write_controlword(SHUTDOWN)
        d.write_controlword(ENABLE)
        assert d.state is State.OPERATION_ENABLED
    return d


def test_csv_is_accepted_displayed_and_listed_in_6502h() -> None:
    d = csv_drive(enable=False)
    assert d.store.read_value(0x6061) == CSV and d.mode is Mode.CYCLIC_SYNC_VELOCITY
    assert d.store.get_int(0x6502) & 0x100  # CiA 402-2 6502h bit 8: csv


def test_entering_csv_with_60ffh_zero_moves_nothing() -> None:
    d = csv_drive()
    d.advance(1.0)
    assert d.velocity == 0 and d.position == 0 and d.motion_starts == 0
    assert d.statusword & BIT12  # the drive follows the command value


def test_a_target_velocity_is_followed_at_once_within_60c5h() -> None:
    d = csv_drive()
    write(d, 0x60FF, 500)
    d.advance(0.02)  # 0.02 s at 10000 inc/s^2: 200 inc/s (not pv's 6083h = 10 rpm/s)
    assert 150 <= d.velocity <= 250
    d.advance(0.1)
    assert d.velocity == 500 and d.motion_starts == 1
    assert d.statusword & TARGET_REACHED == 0  # bit 10 is reserved in csv
    assert d.statusword & BIT13 == 0
    write(d, 0x60FF, 0)
    d.advance(0.1)
    assert d.velocity == 0
    stopped = d.position
    d.advance(1.0)
    assert d.position == stopped  # held at rest


def test_a_target_beyond_607fh_is_limited_and_shows_bit_11() -> None:
    d = csv_drive()
    write(d, 0x60FF, -5000)
    d.advance(1.0)
    assert d.velocity == -1000 and d.statusword & INTERNAL_LIMIT


def test_halt_is_not_evaluated_in_csv() -> None:
    d = csv_drive()
    d.write_controlword(ENABLE | HALT)
    write(d, 0x60FF, 300)
    d.advance(1.0)
    assert d.velocity == 300


def test_a_quick_stop_stops_a_csv_move_and_60ffh_does_not_restart_it() -> None:
    d = csv_drive()
    write(d, 0x60FF, 600)
    d.advance(0.5)
    d.write_controlword(0x02)  # quick stop
    d.advance(2.0)
    assert d.velocity == 0
    write(d, 0x60FF, 700)  # set-points go on arriving: not enabled, nothing moves
    d.advance(1.0)
    assert d.velocity == 0


def test_software_limits_fault_a_csv_move_as_in_pv() -> None:
    d = csv_drive()
    write(d, 0x607D, -100, 1)
    write(d, 0x607D, 200, 2)
    write(d, 0x60FF, 500)
    d.advance(2.0)
    assert d.state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
    assert d.store.get_int(0x603F) == 0x8A82


def test_from_csv_back_to_csp_on_the_actual_position_moves_nothing() -> None:
    d = csv_drive()
    write(d, 0x60FF, 400)
    d.advance(0.5)
    write(d, 0x60FF, 0)
    d.advance(0.5)
    here = d.position
    assert d.velocity == 0 and here > 0
    write(d, 0x607A, here)
    write(d, 0x6060, CSP)
    d.advance(0.5)
    assert d.position == here and d.velocity == 0
    write(d, 0x607A, here + 300)
    d.advance(2.0)
    assert d.position == here + 300
