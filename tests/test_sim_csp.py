"""Cyclic synchronous position mode (csp, 6060h = 8) of the simulated drive.

What a csp drive does, as CiA 402-2 describes the mode and drive manuals quote
it (Parker SLVD-N 13.1.11.2, Nanotec N5 "Cyclic Synchronous Position"): the
master's 607Ah is the input of the position loop at once, no controlword bit
4 handshake; the mode "uses no mode specific bits of the controlword" (halt is
not evaluated); statusword bit 10 is reserved, bit 12 "drive follows the
command value", bit 13 following error; bit 11 when 607Dh limits the demand.
The simulator's own choice (epos_link/simulator/kinematics.py): a set-point is
followed at the drive's maxima 607Fh/6080h and 60C5h.

Units as in test_sim_drive.py: 60 increments per revolution, 1 rpm = 1 inc/s.
"""
from __future__ import annotations

from epos_link.cia402 import State
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.od import ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, NEW_SET_POINT, HALT = 0x06, 0x0F, 0x10, 0x100
TARGET_REACHED, INTERNAL_LIMIT, BIT12, BIT13 = 0x0400, 0x0800, 0x1000, 0x2000
CSP = 8


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def csp_drive(*, enable: bool = True) -> Drive:
    d = Drive(ObjectStore(OD))
    write(d, 0x3010, 15, 1)  # 60 inc/rev: 1 rpm = 1 inc/s
    write(d, 0x607F, 1000)  # follows at 1000 inc/s ...
    write(d, 0x60C5, 10000)  # ... and 10000 inc/s^2
    write(d, 0x6060, CSP)
    if enable:
        d.write_controlword(SHUTDOWN)
        d.write_controlword(ENABLE)
        assert d.state is State.OPERATION_ENABLED
    return d


def test_csp_is_accepted_and_displayed() -> None:
    d = csp_drive(enable=False)
    assert d.store.read_value(0x6061) == CSP and d.mode is Mode.CYCLIC_SYNC_POSITION
    assert d.store.get_int(0x6502) & 0x80  # CiA 402-2 6502h bit 7: csp


def test_a_new_target_is_followed_at_once_without_the_bit_4_handshake() -> None:
    d = csp_drive()
    assert d.statusword & BIT12  # the drive follows the command value
    write(d, 0x607A, 600)
    d.advance(0.05)
    assert 0 < d.position < 600 and d.velocity > 0
    d.advance(2.0)
    assert d.position == 600 and d.velocity == 0
    assert d.motion_starts == 1
    assert d.statusword & TARGET_REACHED == 0  # bit 10 is reserved in csp


def test_a_set_point_is_followed_at_the_drive_maxima() -> None:
    d = csp_drive()
    write(d, 0x607A, 100_000)
    d.advance(1.0)  # 0.1 s at 10000 inc/s^2 up to 1000 inc/s, then 1000 inc/s
    assert d.velocity == 1000 and abs(d.position - 950) <= 1


def test_halt_is_not_evaluated_in_csp() -> None:
    d = csp_drive()
    d.write_controlword(ENABLE | HALT)
    write(d, 0x607A, 300)
    d.advance(2.0)
    assert d.position == 300  # halt did not stop it: csp has no halt


def test_the_bit_4_handshake_is_not_needed_and_changes_nothing() -> None:
    d = csp_drive()
    write(d, 0x607A, 300)
    d.write_controlword(ENABLE | NEW_SET_POINT)  # a pp master's habit: no second move
    d.advance(2.0)
    assert d.position == 300 and d.motion_starts == 1


def test_a_target_written_before_enable_is_followed_on_enable() -> None:
    d = csp_drive(enable=False)
    d.write_controlword(SHUTDOWN)
    write(d, 0x607A, 300)
    d.advance(1.0)
    assert d.position == 0  # not enabled: the power stage is off
    d.write_controlword(ENABLE)
    d.advance(2.0)
    assert d.position == 300 and d.motion_starts == 1


def test_software_limits_clamp_the_demand() -> None:
    d = csp_drive()
    write(d, 0x607D, -100, 1)
    write(d, 0x607D, 200, 2)
    write(d, 0x607A, 5000)
    d.advance(2.0)
    assert d.position == 200 and d.statusword & INTERNAL_LIMIT
    write(d, 0x607A, 100)
    d.advance(2.0)
    assert d.position == 100 and not d.statusword & INTERNAL_LIMIT


def test_leaving_csp_stops_the_axis() -> None:
    d = csp_drive()
    write(d, 0x607A, 100_000)
    d.advance(1.0)
    write(d, 0x6060, 1)  # profile position: no set-point yet, the axis stops on 6084h
    d.advance(1.0)
    assert d.velocity == 0 and d.position < 2000
    stopped = d.position
    write(d, 0x607A, 0)  # in pp a target alone moves nothing
    d.advance(1.0)
    assert d.position == stopped


def test_following_error_shows_in_bit_13() -> None:
    d = csp_drive()
    d.inject_fault("following_error")
    assert d.statusword & BIT13
