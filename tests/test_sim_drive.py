"""The CiA 402 drive model, its state machine and its motion profiles, in virtual time.

Expected statuswords are built from the state coding table of CiA 402-2
6.4.1.4 plus bit 4 (voltage enabled, here: power stage on), never read back
from the model; bit 9 (remote) is 0: a drive alone is never NMT Operational.

Units: the drives of this module have a 15-pulse encoder, 60 increments per
revolution, so that 1 rpm = 1 inc/s and 1 rpm/s = 1 inc/s^2 and the
kinematics below can be worked out by hand in increments. Expected move
times use the EDS defaults: profile velocity 1000 rpm, acceleration and
deceleration 10000 rpm/s; quick stop deceleration is set to 50000 rpm/s.
The EPOS4 default units themselves are tested in test_sim_units.py.
"""
from __future__ import annotations

import math

import pytest
from canopen import SdoAbortedError
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.cia402 import (
    STATE_BITS,
    TRANSITIONS,
    Command,
    State,
    decode_command,
    state_from_statusword,
)
from epos_link.simulator.drive import FAULTS, Drive, Mode, VirtualClock
from epos_link.simulator.homing import VirtualSwitches
from epos_link.simulator.safety import EventKind
from epos_link.simulator.motion import Kind, plan_position, plan_stop, plan_velocity
from epos_link.simulator.od import ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)

SHUTDOWN, SWITCH_ON, ENABLE = 0x0006, 0x0007, 0x000F
DISABLE_VOLTAGE, QUICK_STOP, FAULT_RESET = 0x0000, 0x000B, 0x0080
NEW_SET_POINT, IMMEDIATE, RELATIVE, HALT = 0x0010, 0x0020, 0x0040, 0x0100

REMOTE, VOLTAGE = 0x0200, 0x0010
TARGET_REACHED, INTERNAL_LIMIT, BIT12, BIT13, REFERENCED = 0x0400, 0x0800, 0x1000, 0x2000, 0x8000
EPS = 1e-9


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def make(**kwargs: object) -> Drive:
    d = Drive(ObjectStore(OD), **kwargs)  # type: ignore[arg-type]
    write(d, 0x3010, 15, 1)  # 15 pulses: 60 inc/rev, 1 rpm = 1 inc/s (module docstring)
    write(d, 0x6085, 50000)
    return d


def read(d: Drive, index: int, sub: int = 0) -> object:
    return d.store.read_value(index, sub)


def enabled(mode: Mode = Mode.PROFILE_POSITION, **kwargs: object) -> Drive:
    d = make(**kwargs)
    d.set_mode(mode)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    assert d.state is State.OPERATION_ENABLED
    return d


def start_move(d: Drive, target: int, bits: int = 0) -> None:
    """Profile position set-point with the bit 4 handshake (CiA 402-2 6.7.1)."""
    write(d, 0x607A, target)
    d.write_controlword(ENABLE | NEW_SET_POINT | bits)
    d.write_controlword(ENABLE | bits)


def transitions_of(d: Drive, since: int) -> list[int]:
    return [number for _, number, _ in list(d.history)[since:]]


def reach(d: Drive, state: State) -> None:
    """Drive ``d`` (fresh) into ``state`` by controlword writes and faults."""
    steps = {
        State.SWITCH_ON_DISABLED: [],
        State.READY_TO_SWITCH_ON: [SHUTDOWN],
        State.SWITCHED_ON: [SHUTDOWN, SWITCH_ON],
        State.OPERATION_ENABLED: [SHUTDOWN, ENABLE],
        State.QUICK_STOP_ACTIVE: [SHUTDOWN, ENABLE],
        State.FAULT: [],
    }[state]
    for cw in steps:
        d.write_controlword(cw)
    if state is State.QUICK_STOP_ACTIVE:
        write(d, 0x605A, 6)  # stay in quick stop
        d.write_controlword(QUICK_STOP)
    if state is State.FAULT:
        d.inject_fault("limit_negative")
    assert d.state is state


# -- CiA 402 tables -----------------------------------------------------------------


@pytest.mark.parametrize(("cw", "prev", "command"), [
    (0x0006, 0, Command.SHUTDOWN), (0x000E, 0, Command.SHUTDOWN),
    (0x0007, 0, Command.SWITCH_ON), (0x000F, 0, Command.ENABLE_OPERATION),
    (0x0000, 0, Command.DISABLE_VOLTAGE), (0x0005, 0, Command.DISABLE_VOLTAGE),
    (0x000D, 0, Command.DISABLE_VOLTAGE), (0x0002, 0, Command.QUICK_STOP),
    (0x000B, 0, Command.QUICK_STOP), (0x0080, 0, Command.FAULT_RESET),
    (0x008F, 0x000F, Command.FAULT_RESET), (0x0080, 0x0080, None), (0x0086, 0x0080, None),
    (0x011F, 0, Command.ENABLE_OPERATION),  # bits 4..15 do not change the command
])
def test_decode_command(cw: int, prev: int, command: Command | None) -> None:
    assert decode_command(cw, prev) is command


@pytest.mark.parametrize("state", list(State))
def test_state_coding_round_trip(state: State) -> None:
    for extra in (0x0000, 0x0010, 0x0200, 0x0610, 0xFF90):  # non-coding bits do not matter
        assert state_from_statusword(STATE_BITS[state] | extra) is state


def test_every_commanded_transition_number_is_in_the_table() -> None:
    numbers = {n for steps in TRANSITIONS.values() for n, _ in steps}
    assert numbers == {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16}


# -- statusword per state ----------------------------------------------------------------


@pytest.mark.parametrize(("state", "statusword"), [
    (State.SWITCH_ON_DISABLED, 0x0040),  # x1xx 0000
    (State.READY_TO_SWITCH_ON, 0x0021),  # x01x 0001
    (State.SWITCHED_ON, 0x0023),  # x01x 0011
    (State.OPERATION_ENABLED, 0x0037),  # x01x 0111, voltage enabled, target not reached
    (State.QUICK_STOP_ACTIVE, 0x0417),  # x00x 0111, stopped: bit 10 (option 6)
    (State.FAULT, 0x0808),  # x0xx 1000, negative limit switch: internal limit active
])
def test_statusword_per_state(state: State, statusword: int) -> None:
    d = make()
    reach(d, state)
    assert d.statusword == statusword
    assert read(d, 0x6041) == statusword
    assert state_from_statusword(statusword) is state


def test_statusword_not_ready_and_fault_reaction() -> None:
    d = make(self_test_time=0.5)
    assert d.state is State.NOT_READY_TO_SWITCH_ON
    assert d.statusword == 0x0000  # x0xx 0000
    d = enabled()
    start_move(d, 1000)
    d.advance(0.5)
    d.inject_fault("following_error")
    assert d.state is State.FAULT_REACTION_ACTIVE
    assert d.statusword == 0x000F | VOLTAGE | BIT13  # x0xx 1111, following error


def test_remote_and_warning_bits_follow_attributes() -> None:
    d = make()
    assert d.statusword & REMOTE == 0  # after power-up: NMT pre-operational
    d.remote = True
    d.warning = True
    assert d.statusword == 0x0040 | 0x0080 | REMOTE


# -- every transition number ------------------------------------------------------------


def test_transitions_0_and_1_at_power_up() -> None:
    d = make(start=3.0)
    assert [(t, n) for t, n, _ in d.history] == [(3.0, 0), (3.0, 1)]
    d = make(self_test_time=0.25)
    assert transitions_of(d, 0) == [0]
    d.write_controlword(SHUTDOWN)  # no command is taken before the self-test ends
    d.advance(0.2)
    assert d.state is State.NOT_READY_TO_SWITCH_ON
    d.advance(0.1)
    assert transitions_of(d, 0) == [0, 1]
    assert d.history[-1][0] == pytest.approx(0.25)


@pytest.mark.parametrize(("start", "cw", "numbers", "end"), [
    (State.SWITCH_ON_DISABLED, SHUTDOWN, [2], State.READY_TO_SWITCH_ON),
    (State.READY_TO_SWITCH_ON, SWITCH_ON, [3], State.SWITCHED_ON),
    (State.READY_TO_SWITCH_ON, ENABLE, [3, 4], State.OPERATION_ENABLED),
    (State.SWITCHED_ON, ENABLE, [4], State.OPERATION_ENABLED),
    (State.OPERATION_ENABLED, SWITCH_ON, [5], State.SWITCHED_ON),  # disable operation
    (State.SWITCHED_ON, SHUTDOWN, [6], State.READY_TO_SWITCH_ON),
    (State.READY_TO_SWITCH_ON, DISABLE_VOLTAGE, [7], State.SWITCH_ON_DISABLED),
    (State.READY_TO_SWITCH_ON, QUICK_STOP, [7], State.SWITCH_ON_DISABLED),
    (State.OPERATION_ENABLED, SHUTDOWN, [8], State.READY_TO_SWITCH_ON),
    (State.OPERATION_ENABLED, DISABLE_VOLTAGE, [9], State.SWITCH_ON_DISABLED),
    (State.SWITCHED_ON, DISABLE_VOLTAGE, [10], State.SWITCH_ON_DISABLED),
    (State.SWITCHED_ON, QUICK_STOP, [10], State.SWITCH_ON_DISABLED),
    (State.OPERATION_ENABLED, QUICK_STOP, [11], State.QUICK_STOP_ACTIVE),  # 605Ah=6 (maxon)
    (State.QUICK_STOP_ACTIVE, DISABLE_VOLTAGE, [12], State.SWITCH_ON_DISABLED),
    (State.FAULT, FAULT_RESET, [15], State.SWITCH_ON_DISABLED),
    (State.QUICK_STOP_ACTIVE, ENABLE, [16], State.OPERATION_ENABLED),  # 605Ah=6
])
def test_commanded_transitions(start: State, cw: int, numbers: list[int], end: State) -> None:
    d = make()
    reach(d, start)
    before = len(d.history)
    d.write_controlword(cw)
    assert transitions_of(d, before) == numbers
    assert d.state is end


def test_with_605ah_2_a_quick_stop_at_rest_ends_in_switch_on_disabled() -> None:
    """CiA 402's default option (not the EPOS4's): transition 12 follows 11 at once."""
    d = make()
    write(d, 0x605A, 2)
    reach(d, State.OPERATION_ENABLED)
    before = len(d.history)
    d.write_controlword(QUICK_STOP)
    assert transitions_of(d, before) == [11, 12] and d.state is State.SWITCH_ON_DISABLED


@pytest.mark.parametrize(("start", "cw"), [
    (State.SWITCH_ON_DISABLED, SWITCH_ON), (State.SWITCH_ON_DISABLED, ENABLE),
    (State.SWITCH_ON_DISABLED, QUICK_STOP), (State.SWITCHED_ON, SWITCH_ON),
    (State.OPERATION_ENABLED, ENABLE), (State.QUICK_STOP_ACTIVE, SHUTDOWN),
    (State.QUICK_STOP_ACTIVE, SWITCH_ON), (State.FAULT, SHUTDOWN), (State.FAULT, ENABLE),
])
def test_commands_ignored_where_the_table_has_no_transition(start: State, cw: int) -> None:
    d = make()
    reach(d, start)
    before = len(d.history)
    d.write_controlword(cw)
    assert transitions_of(d, before) == [] and d.state is start


def test_transitions_13_and_14() -> None:
    d = make()
    d.inject_fault("following_error")  # at rest: the reaction is over at once
    assert transitions_of(d, 2) == [13, 14] and d.state is State.FAULT
    d = enabled()
    start_move(d, 1000)
    d.advance(0.5)
    before = len(d.history)
    d.inject_fault("limit_positive")
    assert transitions_of(d, before) == [13]
    d.advance(0.02 - 1e-6)  # 1000 inc/s at 50000 inc/s^2: 20 ms
    assert d.state is State.FAULT_REACTION_ACTIVE
    d.advance(2e-6)
    assert transitions_of(d, before) == [13, 14]
    assert d.history[-1][0] == pytest.approx(0.52)
    assert d.position == 460  # 450 + 1000 * 0.02 / 2


def test_transition_16_needs_option_code_5_to_8() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x605A, 2)
    write(d, 0x60FF, 1000)
    d.advance(1.0)
    d.write_controlword(QUICK_STOP)
    assert d.state is State.QUICK_STOP_ACTIVE
    before = len(d.history)
    d.write_controlword(ENABLE)  # 16 not allowed with option 2
    assert transitions_of(d, before) == [] and d.state is State.QUICK_STOP_ACTIVE
    d.advance(0.1)
    assert transitions_of(d, before) == [12]


def test_fault_reset_needs_a_rising_edge_of_bit_7() -> None:
    d = make()
    d.inject_fault("following_error")
    d.write_controlword(FAULT_RESET)
    assert d.state is State.SWITCH_ON_DISABLED
    d.inject_fault("following_error")
    d.write_controlword(FAULT_RESET)  # still set: no edge
    assert d.state is State.FAULT
    d.write_controlword(FAULT_RESET | SHUTDOWN)  # bit 7 held: no command at all
    assert d.state is State.FAULT
    d.write_controlword(0)
    d.write_controlword(FAULT_RESET | SHUTDOWN)  # the edge resets, the low bits wait
    assert d.state is State.SWITCH_ON_DISABLED
    d.write_controlword(SHUTDOWN)
    assert d.state is State.READY_TO_SWITCH_ON


# -- profile position -----------------------------------------------------------------------


def test_target_reached_is_zero_after_power_up_until_a_first_target() -> None:
    d = enabled()
    assert d.statusword & TARGET_REACHED == 0
    d.advance(5.0)
    assert d.statusword & TARGET_REACHED == 0
    start_move(d, 0)  # already there
    assert d.statusword == 0x0437


def test_trapezoid_move_timing_and_positions() -> None:
    d = enabled()
    start_move(d, 1000)
    # accel 0.1 s over 50 inc, cruise 900 inc in 0.9 s, decel 0.1 s over 50 inc
    samples = {0.05: (13, 500), 0.1: (50, 1000), 0.6: (550, 1000), 1.05: (988, 500)}
    for t, (position, velocity) in samples.items():
        d.update(t)
        assert (d.position, d.velocity) == (position, velocity), t
        assert d.statusword & TARGET_REACHED == 0
    d.update(1.1 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(1.1 + 1e-6)
    assert d.statusword == 0x0437
    assert (read(d, 0x6064), read(d, 0x6062), read(d, 0x606C)) == (1000, 1000, 0)


def test_triangle_move_timing() -> None:
    d = enabled()
    start_move(d, -50)
    end = 2 * math.sqrt(50 / 10000)  # peak 707 inc/s < 1000: no cruise
    d.update(end / 2)
    assert d.position == -25
    assert d.velocity == -707
    d.update(end - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(end + 1e-6)
    assert d.position == -50 and d.statusword & TARGET_REACHED


def test_asymmetric_ramps_and_limits() -> None:
    d = enabled()
    write(d, 0x6084, 5000)  # decel 0.2 s over 100 inc; cruise 850 inc
    start_move(d, 1000)
    d.update(1.15 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(1.15 + 1e-6)
    assert d.position == 1000
    d = enabled()
    write(d, 0x6081, 5000)
    write(d, 0x607F, 2000)  # profile velocity limited by max profile velocity
    write(d, 0x60C5, 4000)  # and accelerations by max acceleration
    start_move(d, 10000)
    d.update(0.5)
    assert d.velocity == 2000
    d2 = enabled()
    write(d2, 0x60C5, 4000)
    start_move(d2, 10000)
    d2.update(0.05)
    assert d2.velocity == 200  # 4000 inc/s^2 * 0.05 s


def test_large_steps_equal_small_steps() -> None:
    coarse, fine = enabled(), enabled()
    for d in (coarse, fine):
        start_move(d, 12345)
    for k in range(1, 1400):
        fine.advance(0.001)
        if k % 97 == 0:
            coarse.update(fine.now)
            assert (coarse.position, coarse.velocity) == (fine.position, fine.velocity)
    coarse.update(20.0)
    fine.update(20.0)
    assert coarse.position == fine.position == 12345


def test_relative_moves() -> None:
    d = enabled()
    start_move(d, 200, RELATIVE)  # no preceding target: relative to the demand position 0
    d.advance(2.0)
    assert d.position == 200
    start_move(d, -500, RELATIVE)
    d.advance(2.0)
    assert d.position == -300
    start_move(d, 1000)  # absolute
    d.advance(0.5)
    start_move(d, 100, RELATIVE | IMMEDIATE)  # relative to the preceding target 1000
    d.advance(3.0)
    assert d.position == 1100


def test_set_point_acknowledge_handshake() -> None:
    d = enabled()
    write(d, 0x607A, 1000)
    d.write_controlword(ENABLE | NEW_SET_POINT)
    assert d.statusword & BIT12
    d.advance(0.3)
    assert d.statusword & BIT12  # stays while bit 4 stays set
    d.write_controlword(ENABLE)
    assert d.statusword & BIT12 == 0


def test_set_point_ignored_outside_operation_enabled() -> None:
    d = make()
    d.write_controlword(SHUTDOWN)
    d.write_controlword(SWITCH_ON)
    write(d, 0x607A, 1000)
    d.write_controlword(SWITCH_ON | NEW_SET_POINT)
    assert d.statusword & BIT12 == 0
    d.write_controlword(ENABLE | NEW_SET_POINT)  # bit 4 already set: no edge
    d.advance(2.0)
    assert d.position == 0 and d.statusword & BIT12 == 0


def test_buffered_set_point_without_change_immediately() -> None:
    d = enabled()
    start_move(d, 1000)
    d.advance(0.5)
    write(d, 0x607A, 2000)
    d.write_controlword(ENABLE | NEW_SET_POINT)
    d.write_controlword(ENABLE)
    assert d.statusword & BIT12  # buffered: acknowledge held while the buffer is full
    write(d, 0x607A, -5000)
    d.write_controlword(ENABLE | NEW_SET_POINT)  # buffer full: refused
    d.write_controlword(ENABLE)
    d.update(1.1 + 1e-6)  # first move ends, the buffered one starts at once
    assert d.position == 1000 and d.statusword & (BIT12 | TARGET_REACHED) == 0
    d.update(2.2 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(2.2 + 1e-6)
    assert d.position == 2000 and d.statusword & TARGET_REACHED


def test_change_set_immediately() -> None:
    d = enabled()
    start_move(d, 1000)
    d.update(0.5)  # at 450, 1000 inc/s
    start_move(d, 600, IMMEDIATE)  # 150 inc left: cruise 100, decel 50
    d.update(0.7 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(0.7 + 1e-6)
    assert d.position == 600 and d.statusword & TARGET_REACHED
    start_move(d, 1000)
    d.update(0.9)
    start_move(d, 0, IMMEDIATE)  # reverse: stop first (at 0.9 + ...), come back
    d.update(10.0)
    assert d.position == 0


def test_overshooting_target_stops_then_returns() -> None:
    d = enabled()
    start_move(d, 1000)
    d.update(0.5)
    start_move(d, 460, IMMEDIATE)  # needs 50 inc to stop: stops at 500 at 0.6
    d.update(0.6)
    assert (d.position, d.velocity) == (500, 0)
    end = 0.6 + 2 * math.sqrt(40 / 10000)
    d.update(end - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(end + 1e-6)
    assert d.position == 460


def test_halt_and_resume() -> None:
    d = enabled()
    start_move(d, 1000)
    d.update(0.5)
    d.write_controlword(ENABLE | HALT)
    d.update(0.55)
    assert d.statusword & TARGET_REACHED == 0
    d.update(0.6)
    assert (d.position, d.velocity) == (500, 0)
    assert d.statusword & TARGET_REACHED  # halted and at rest (CiA 402-2 bit 10)
    d.write_controlword(ENABLE)  # resume to 1000: 0.1 + 0.4 + 0.1 s
    assert d.statusword & TARGET_REACHED == 0
    d.update(1.2 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(1.2 + 1e-6)
    assert d.position == 1000


def test_software_position_limits_clamp_target() -> None:
    d = enabled()
    write(d, 0x607D, -100, 1)
    write(d, 0x607D, 500, 2)
    start_move(d, 1000)
    assert d.statusword & INTERNAL_LIMIT
    d.advance(3.0)
    assert d.position == 500
    start_move(d, -1000)
    d.advance(3.0)
    assert d.position == -100
    start_move(d, 200)
    assert d.statusword & INTERNAL_LIMIT == 0
    write(d, 0x607D, 500, 1)  # min >= max: limits off
    start_move(d, 5000)
    d.advance(10.0)
    assert d.position == 5000


def test_disable_operation_ramps_down_then_drops_target() -> None:
    d = enabled()
    start_move(d, 1000)
    d.update(0.5)  # at 450, 1000 inc/s
    d.write_controlword(SWITCH_ON)  # 605Ch = 1: slow down on 6084h first, then transition 5
    assert d.state is State.OPERATION_ENABLED
    d.update(0.6 - 1e-6)
    assert d.state is State.OPERATION_ENABLED
    d.update(0.6 + 1e-6)
    assert d.state is State.SWITCHED_ON and (d.position, d.velocity) == (500, 0)
    d.write_controlword(ENABLE)
    d.advance(5.0)
    assert d.position == 500 and d.statusword & TARGET_REACHED == 0
    assert list(d.unsafe_stops) == [] and d.motion_starts == 1


# -- profile velocity ----------------------------------------------------------------------


def test_profile_velocity() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    assert read(d, 0x6061) == 3
    assert d.statusword & (TARGET_REACHED | BIT12) == TARGET_REACHED | BIT12  # speed = 0
    write(d, 0x60FF, 2000)
    d.update(0.1)
    assert d.velocity == 1000 and d.statusword & (TARGET_REACHED | BIT12) == 0
    d.update(0.2)
    assert d.velocity == 2000 and d.statusword & TARGET_REACHED
    d.update(1.2)
    assert d.position == 200 + 2000
    write(d, 0x60FF, -1000)  # 0.2 s down to 0, 0.1 s up to -1000
    d.update(1.5 - 1e-6)
    assert d.statusword & TARGET_REACHED == 0
    d.update(1.5)
    assert d.velocity == -1000 and d.statusword & TARGET_REACHED


def test_profile_velocity_halt_and_limit() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x60FF, 1000)
    d.advance(1.0)
    d.write_controlword(ENABLE | HALT)
    d.advance(0.1)
    assert d.velocity == 0 and d.statusword & (TARGET_REACHED | BIT12) == TARGET_REACHED | BIT12
    d.write_controlword(ENABLE)
    d.advance(0.1)
    assert d.velocity == 1000
    write(d, 0x60FF, -10**6)  # above 607Fh = 50000
    d.advance(10.0)
    assert d.velocity == -50000 and d.statusword & INTERNAL_LIMIT


# -- homing -----------------------------------------------------------------------------------


def test_homing_sets_home_position() -> None:
    d = enabled(Mode.HOMING)
    write(d, 0x30B0, 1234)
    write(d, 0x607C, 77)  # home offset: stored, not applied (see drive docstring)
    assert d.statusword == 0x0437  # bits 13,12,10 = 0,0,1: not started
    d.write_controlword(ENABLE | NEW_SET_POINT)
    assert read(d, 0x6064) == 1234
    assert d.statusword == 0x0437 | BIT12 | REFERENCED  # homing attained, target reached
    d.write_controlword(ENABLE)
    d.set_mode(Mode.PROFILE_POSITION)
    start_move(d, 10, RELATIVE)  # relative to the new position
    d.advance(1.0)
    assert d.position == 1244


def test_homing_does_not_start_while_halted() -> None:
    d = enabled(Mode.HOMING)
    write(d, 0x30B0, 99)
    d.write_controlword(ENABLE | HALT | NEW_SET_POINT)
    assert d.position == 0 and d.statusword & BIT12 == 0


# -- modes --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [0, 2, 4, 5, 7, -1, 10])
def test_unsupported_modes_are_out_of_range(mode: int) -> None:
    d = make()
    with pytest.raises(SdoAbortedError) as info:
        d.set_mode(mode)
    assert info.value.code == 0x06090030
    assert read(d, 0x6061) == 1


def test_mode_change_stops_the_move() -> None:
    d = enabled()
    start_move(d, 1000)
    d.update(0.5)
    d.set_mode(Mode.PROFILE_VELOCITY)  # 60FFh = 0: ramp down on 6084h
    assert read(d, 0x6061) == 3
    d.update(0.6)
    assert (d.position, d.velocity) == (500, 0)
    d.set_mode(Mode.PROFILE_POSITION)  # the old target was dropped
    d.advance(2.0)
    assert d.position == 500 and d.statusword & TARGET_REACHED == 0


# -- quick stop ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("option", "stop_time", "final", "stays"), [
    (1, 0.1, State.SWITCH_ON_DISABLED, False),  # profile deceleration
    (2, 0.02, State.SWITCH_ON_DISABLED, False),  # quick stop deceleration
    (5, 0.1, State.QUICK_STOP_ACTIVE, True),
    (6, 0.02, State.QUICK_STOP_ACTIVE, True),
])
def test_quick_stop_options(option: int, stop_time: float, final: State, stays: bool) -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x605A, option)
    write(d, 0x60FF, 1000)
    d.advance(1.0)
    d.write_controlword(QUICK_STOP)
    assert d.state is State.QUICK_STOP_ACTIVE
    assert d.statusword == 0x0017  # x00x 0111, still moving
    d.advance(stop_time - 1e-6)
    assert d.state is State.QUICK_STOP_ACTIVE and d.statusword & TARGET_REACHED == 0
    d.advance(2e-6)
    assert d.state is final and d.velocity == 0
    assert d.position == round(50 + 900 + 1000 * stop_time / 2)  # ramp up 50, cruise 900, ramp down
    if stays:
        assert d.statusword == 0x0417 | BIT12  # stopped: bit 10; pv bit 12: speed = 0
        d.write_controlword(ENABLE)
        assert d.state is State.OPERATION_ENABLED
        assert d.history[-1][1] == 16


def test_quick_stop_option_0_disables_at_once() -> None:
    d = enabled(Mode.PROFILE_VELOCITY)
    write(d, 0x605A, 0)
    write(d, 0x60FF, 1000)
    d.advance(1.0)
    before = len(d.history)
    d.write_controlword(QUICK_STOP)
    assert transitions_of(d, before) == [11, 12]
    # the power stage is off: the axis coasts on (2000 rpm/s), the drive records it
    assert d.velocity == 1000 and len(d.unsafe_stops) == 1
    d.advance(0.25)
    assert d.velocity == 500


# -- faults ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(("kind", "code", "inputs", "status_extra"), [
    ("limit_positive", 0x8A81, 0x2, INTERNAL_LIMIT),  # EPOS4 error table (faults.py)
    ("limit_negative", 0x8A80, 0x1, INTERNAL_LIMIT),
    ("following_error", 0x8611, 0x0, BIT13),
])
def test_fault_injection_and_reset(kind: str, code: int, inputs: int, status_extra: int) -> None:
    d = enabled()
    start_move(d, 1000)
    d.advance(0.5)
    d.inject_fault(kind)
    assert d.statusword == 0x001F | status_extra  # fault reaction, power stage on
    d.advance(1.0)
    assert d.state is State.FAULT and d.statusword == 0x0008 | status_extra
    assert (read(d, 0x603F), read(d, 0x1001), read(d, 0x60FD)) == (code, 0x81, inputs)
    assert d.position == 460
    d.write_controlword(FAULT_RESET)
    assert d.state is State.SWITCH_ON_DISABLED and d.statusword == 0x0040
    assert (read(d, 0x603F), read(d, 0x1001), read(d, 0x60FD)) == (0, 0, 0)


def test_fault_via_simulator_command_object() -> None:
    d = enabled()
    d.store.write(0x2100, 0, b"\x03\x00\x00\x00")
    assert d.state is State.FAULT and read(d, 0x603F) == 0x8611
    with pytest.raises(SdoAbortedError) as info:
        d.store.write(0x2100, 0, b"\x09\x00\x00\x00")
    assert info.value.code == 0x06090030


def test_second_fault_keeps_state_and_updates_code() -> None:
    d = make()
    d.inject_fault("limit_positive")
    before = len(d.history)
    d.inject_fault("following_error")
    assert transitions_of(d, before) == [] and read(d, 0x603F) == 0x8611
    with pytest.raises(ValueError):
        d.inject_fault("overheating")
    assert set(FAULTS) == {"limit_positive", "limit_negative", "following_error", "software_limit", "sto",
                           "heartbeat"}


# -- time -------------------------------------------------------------------------------------------


def test_virtual_clock_drives_store_reads() -> None:
    clock = VirtualClock(10.0)
    d = enabled(clock=clock)
    start_move(d, 1000)
    clock.advance(0.6)
    assert read(d, 0x6064) == 550  # the read caught up with the clock
    clock.advance(1.0)
    assert read(d, 0x6041) == 0x0437
    with pytest.raises(ValueError):
        clock.advance(-1)


def test_update_rules() -> None:
    d = make()
    with pytest.raises(ValueError):
        d.update()
    with pytest.raises(ValueError):
        d.advance(-0.1)
    d.update(5.0)
    d.update(4.0)  # earlier: ignored
    assert d.now == 5.0


def test_power_cycle_restores_saved_parameters() -> None:
    d = enabled()
    write(d, 0x6081, 2000)
    d.store.write(0x1010, 1, b"save")
    write(d, 0x6081, 3000)
    start_move(d, 1000)
    d.advance(2.0)
    d.power_cycle()
    assert d.state is State.SWITCH_ON_DISABLED and d.position == 0
    assert transitions_of(d, len(d.history) - 2) == [0, 1]
    assert read(d, 0x6081) == 2000 and d.statusword == 0x0040


# -- motion profiles in isolation ----------------------------------------------------------------


rates = st.floats(1.0, 1e5)


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-5e3, 5e3), st.floats(-1e6, 1e6),
       st.floats(1.0, 5e3), rates, rates)
def test_position_profile_properties(p0: float, v0: float, target: float,
                                     v_max: float, acc: float, dec: float) -> None:
    prof = plan_position(2.0, p0, v0, target, v_max, acc, dec)
    assert prof.kind is Kind.POSITION
    p_start, v_start = prof.state_at(2.0)
    assert p_start == pytest.approx(p0)
    # A ramp too short to move the clock (2.0 + d == 2.0) is skipped (_Builder.ramp):
    # the speed may jump by what it would have changed, dec * d < dec * 4.5e-16.
    assert v_start == pytest.approx(v0, abs=max(acc, dec) * 5e-16 + 1e-12)
    assert prof.state_at(prof.end_time + 1.0) == (target, 0.0)
    t = 2.0
    for seg in prof.segments:
        assert seg.start == pytest.approx(t) and seg.duration > 0
        assert abs(seg.acceleration) <= max(acc, dec) * (1 + EPS)
        # speed never above the larger of the start speed and the profile velocity
        assert abs(seg.velocity) <= max(abs(v0), v_max) * (1 + 1e-6) + 1e-6
        t = seg.end
    if prof.segments:  # the ramps end at rest on the target, up to float rounding
        travel = sum(abs(s.velocity) * s.duration + 0.5 * abs(s.acceleration) * s.duration ** 2
                     for s in prof.segments)
        swing = sum(abs(s.acceleration) * s.duration for s in prof.segments)
        p_end, v_end = prof.segments[-1].end_state()
        assert p_end == pytest.approx(target, abs=1e-9 * (travel + abs(p0) + abs(target)) + 1e-9)
        assert v_end == pytest.approx(0.0, abs=1e-9 * (swing + abs(v0)) + 1e-9)


@settings(max_examples=200, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-5e3, 5e3), st.floats(-5e3, 5e3), rates, rates)
def test_velocity_and_stop_profiles(p0: float, v0: float, vt: float, acc: float, dec: float) -> None:
    prof = plan_velocity(0.0, p0, v0, vt, acc, dec)
    assert prof.state_at(prof.end_time + 3.0)[1] == vt
    stop = plan_stop(0.0, p0, v0, dec)
    assert stop.end_time == pytest.approx(abs(v0) / dec)
    assert stop.state_at(stop.end_time)[1] == 0.0


# -- any controlword sequence keeps a valid state ------------------------------------------------

COMMON_WORDS = [0x00, 0x02, 0x06, 0x07, 0x0F, 0x1F, 0x3F, 0x5F, 0x10F, 0x80, 0x86, 0x0B]
actions = st.one_of(
    st.tuples(st.just("cw"), st.one_of(st.sampled_from(COMMON_WORDS), st.integers(0, 0xFFFF))),
    st.tuples(st.just("dt"), st.floats(0.0, 2.0)),
    st.tuples(st.just("mode"), st.integers(-2, 10)),
    st.tuples(st.just("target"), st.integers(-(1 << 31), (1 << 31) - 1)),
    st.tuples(st.just("velocity"), st.integers(-60000, 60000)),
    st.tuples(st.just("option"), st.integers(-1, 9)),
    st.tuples(st.just("shutdown_option"), st.integers(-1, 2)),
    st.tuples(st.just("disable_option"), st.integers(-1, 2)),
    st.tuples(st.just("method"), st.sampled_from([-4, -1, 1, 2, 7, 17, 18, 23, 33, 34, 35, 37, 3])),
    st.tuples(st.just("fault"), st.sampled_from(sorted(FAULTS))),
    st.tuples(st.just("reset"), st.sampled_from(["power_cycle", "reset_node"])),
)


@settings(max_examples=250, deadline=None)
@given(st.lists(actions, max_size=40))
def test_any_sequence_keeps_a_valid_state(steps: list[tuple[str, object]]) -> None:
    d = make()
    d.switches = VirtualSwitches(-300.0, 300.0, 50.0, -400.0, 400.0)  # reachable in 2 s steps
    index = {"mode": 0x6060, "target": 0x607A, "velocity": 0x60FF, "option": 0x605A,
             "shutdown_option": 0x605B, "disable_option": 0x605C, "method": 0x6098}
    for kind, value in steps:
        try:
            if kind == "fault":
                assert isinstance(value, str)
                d.inject_fault(value)
            elif kind == "reset":
                getattr(d, str(value))()
            elif kind == "dt":
                assert isinstance(value, float)
                d.advance(value)
            elif kind == "cw":
                assert isinstance(value, int)
                d.store.write(0x6040, 0, value.to_bytes(2, "little"))
            else:
                assert isinstance(value, int)
                d.store.write_value(index[kind], 0, value)
        except SdoAbortedError as exc:
            assert exc.code == 0x06090030  # only range errors are possible here
        assert isinstance(d.state, State)
        sw = d.store.read_value(0x6041)
        assert isinstance(sw, int)
        assert state_from_statusword(sw) is d.state
        assert -(1 << 31) <= d.position < (1 << 31)
        assert d.store.read_value(0x6061) in (1, 3, 6, 8, 9)
        # the power stage is on exactly in the states that drive the motor
        powered = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
        assert not sw & VOLTAGE or d.state in (*powered, State.FAULT_REACTION_ACTIVE)
        assert d.state not in powered or sw & VOLTAGE
        assert all(e.velocity != 0.0 for e in d.unsafe_stops)
        assert d.motion_starts == sum(1 for e in d.events if e.kind is EventKind.MOTION_START) \
            or len(d.events) == d.events.maxlen
