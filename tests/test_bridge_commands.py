"""Tests of tcp_bridge.tables.commands (the rev 2.3 command table) and tcp_bridge.tables.units.

Expected table contents are transcribed by hand from section 4 of
shared/seeds/PSI_TCP_Interface_Documentation.txt; numbers in the unit tests
are worked out by hand in the comments.
"""
from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tcp_bridge.tables.commands import (
    COMMANDS,
    INT32,
    CommandKind,
    ObjectRef,
    SdoSelector,
    ValueType,
    lookup,
    resolve,
)
from tcp_bridge.errors import InvalidCommand
from tcp_bridge.wire import ReadRequest, WriteRequest, format_error_reply
from tcp_bridge.tables.units import Scaling, parse_value, stored_parameter

# Spec 4, "Read/Write" column.
RIGHTS = {
    0: "W", 2: "RW", 4: "RW", 5: "RW", 6: "RW", 7: "RW", 9: "RW", 10: "R", 11: "R", 12: "R",
    13: "R", 14: "R", 15: "R", 16: "W", 17: "W", 18: "R", 19: "RW", 20: "RW", 21: "RW",
    22: "RW", 23: "RW", 24: "RW", 25: "RW", 26: "RW", 27: "RW", 28: "RW", 29: "RW", 30: "RW",
    31: "R", 32: "R", 33: "R", 34: "R", 40: "RW", 41: "RW", 42: "RW", 43: "RW", 50: "R",
    52: "RW", 53: "RW", 54: "RW", 56: "RW", 60: "RW", 61: "R", 62: "RW", 63: "RW", 80: "RW",
    81: "RW", 82: "R", 83: "R", 84: "R", 85: "W", 86: "RW", 90: "W", 91: "RW", 99: "R",
}

# Spec 4, "Internal parameter" column; the starred ones are stored scaled.
PARAMETERS = {
    2: 6, 5: 7, 6: 8, 19: 2, 20: 10, 21: 11, 22: 12, 23: 13, 24: 14, 25: 15, 26: 16, 27: 17,
    28: 18, 29: 19, 30: 20, 31: 21, 32: 22, 40: 25, 41: 26, 42: 27, 43: 28, 53: 30, 54: 31,
    56: 32, 60: 35, 62: 36, 63: 37, 80: 38,
}
STARRED = {2, 5, 6, 23, 24, 25, 26, 27, 28, 41, 42, 43}

# Spec 4, "SDO (ACK/NAK)" column, objects as printed (parentheses dropped).
OBJECTS = {
    0: (0x6040, 0), 2: (0x607A, 0), 4: (0x6040, 0), 5: (0x6081, 0), 6: (0x6083, 0),
    7: (0x6060, 0), 9: (0x605A, 0), 10: (0x6041, 0), 12: (0x6064, 0), 13: (0x6067, 0),
    14: (0x606C, 0), 15: (0x6061, 0), 17: (0x6040, 0), 23: (0x607D, 2), 24: (0x607D, 1),
    26: (0x607F, 0), 27: (0x60C5, 0), 28: (0x6085, 0), 33: (0x607D, 2), 34: (0x607D, 1),
    40: (0x6098, 0), 41: (0x6099, 1), 42: (0x6099, 2), 43: (0x609A, 0), 50: (0x60FD, 0),
    52: (0x60FE, 1), 53: (0x60FE, 2), 61: (0x6064, 0), 62: (0x6065, 0), 63: (0x200D, 0),
    82: (0x6041, 0), 83: (0x6041, 0), 84: (0x6041, 0),
}


def can_reply(header: bytes) -> bytes:
    return (header + b"\x18\r").ljust(30, b"\0")


# --- the table -----------------------------------------------------------------

def test_every_command_of_rev_2_3_and_no_other() -> None:
    assert sorted(COMMANDS) == sorted(RIGHTS)


@pytest.mark.parametrize("number,rights", sorted(RIGHTS.items()))
def test_read_write_rights(number: int, rights: str) -> None:
    spec = COMMANDS[number]
    assert spec.number == number
    assert (spec.readable, spec.writable) == ("R" in rights, "W" in rights)
    assert spec.allows("R") == spec.readable and spec.allows("s") == spec.writable


def test_internal_parameters() -> None:
    got = {n: c.parameter for n, c in COMMANDS.items() if c.parameter is not None}
    assert got == PARAMETERS


def test_scaled_commands_are_the_starred_parameters() -> None:
    assert {n for n, c in COMMANDS.items() if c.scaled} == STARRED


def test_user_unit_commands() -> None:
    # 14 has no unit in the spec's table; the bridge reads it in the unit of 05
    # (issue 10: R14 in user units, so a velocity move reads back its own speed).
    assert {n for n, c in COMMANDS.items() if c.user_units} == STARRED | {12, 13, 14, 33, 34}
    for c in COMMANDS.values():
        assert c.user_units == c.unit.startswith("UserUnits")
        assert (c.value_type is ValueType.FLOAT) == c.user_units


def test_offset_and_inversion() -> None:
    # 12, 33, 34 say so; 02 because its value goes to 0x607A through the same
    # conversion. 25 is the offset itself and is not offset.
    assert {n for n, c in COMMANDS.items() if c.offset_inversion} == {2, 12, 33, 34}


def test_objects() -> None:
    got = {n: (c.index, c.subindex) for n, c in COMMANDS.items() if c.obj is not None}
    assert got == OBJECTS
    assert COMMANDS[6].also_obj == ObjectRef(0x6084)  # "0x6083 (0x6084)"
    assert str(COMMANDS[23].obj) == "0x607D/2"


def test_display_limits_swap_objects_when_inverted() -> None:
    # Spec 4: 33 "0x607D/2 (0x607D/1)", 34 "0x607D/1 (0x607D/2)".
    assert COMMANDS[33].object_for(1) == ObjectRef(0x607D, 2)
    assert COMMANDS[33].object_for(-1) == ObjectRef(0x607D, 1)
    assert COMMANDS[34].object_for(1) == ObjectRef(0x607D, 1)
    assert COMMANDS[34].object_for(-1) == ObjectRef(0x607D, 2)
    assert COMMANDS[12].object_for(-1) == ObjectRef(0x6064)


def test_kinds() -> None:
    def of(kind: CommandKind) -> set:
        return {n for n, c in COMMANDS.items() if c.kind is kind}

    assert of(CommandKind.SEQUENCE) == {0, 4, 7}  # "This command is a whole sequence"
    assert of(CommandKind.STATUS_BIT) == {82, 83, 84}  # "Direct status-bit access"
    assert of(CommandKind.ACTION) == {16, 17, 85, 90}
    assert of(CommandKind.INTERNAL) == {86, 91, 99}
    assert {COMMANDS[n].bit for n in (82, 83, 84)} == {10, 11, 3}


def test_needs_sdo() -> None:
    no_sdo = {n for n, c in COMMANDS.items() if not c.needs_sdo}
    assert no_sdo == {16, 19, 20, 21, 22, 25, 29, 30, 31, 32, 54, 56, 60, 80, 86, 90, 91, 99}
    for c in COMMANDS.values():
        if c.obj is not None:
            assert c.needs_sdo


def test_table_is_consistent() -> None:
    for c in COMMANDS.values():
        assert c.readable or c.writable
        assert (c.bit is not None) == (c.kind is CommandKind.STATUS_BIT)
        low, high = c.value_range
        assert all(low <= v <= high for v in c.choices or ())
        assert c.scaled <= (c.parameter is not None)


def test_choices() -> None:
    assert COMMANDS[0].choices == {1, 2, 3, 8, 9}
    assert COMMANDS[7].choices == {1, 3, 6}
    assert COMMANDS[22].choices == COMMANDS[30].choices == {1, -1}
    assert COMMANDS[90].choices == {0, 1, 2}


# --- lookup and rights -----------------------------------------------------------

def test_lookup() -> None:
    assert lookup(2).name == "Target Position"
    with pytest.raises(InvalidCommand) as info:
        lookup(3)
    assert info.value.cmd == 3


def test_spec_222_status_is_not_writable() -> None:
    # Spec 2.2.2: 3 S 10<CAN><CR> (STATUS is not writable)
    with pytest.raises(InvalidCommand) as info:
        resolve(WriteRequest(3, 10, "1"))
    assert format_error_reply(info.value) == can_reply(b"3 S 10")


def test_spec_232_move_is_not_readable() -> None:
    # Spec 2.3.2: 3 R 0<CAN><CR> (MOVE is not readable)
    with pytest.raises(InvalidCommand) as info:
        resolve(ReadRequest(3, 0))
    assert format_error_reply(info.value) == can_reply(b"3 R 0")


def test_resolve() -> None:
    assert resolve(ReadRequest(3, 2)) is COMMANDS[2]
    assert resolve(WriteRequest(3, 0, "1")) is COMMANDS[0]
    with pytest.raises(InvalidCommand) as info:
        resolve(ReadRequest(7, 3))
    assert format_error_reply(info.value) == can_reply(b"7 R 3")


def test_sdo_selector() -> None:
    # Spec 4, command 80: 0xXXXXSSLL = index, subindex, length
    sel = SdoSelector.from_value(0x607A0004)
    assert sel == SdoSelector(0x607A, 0x00, 4)
    assert sel.to_value() == 0x607A0004
    assert SdoSelector.from_value(0x60990102) == SdoSelector(0x6099, 1, 2)
    for bad in (0x607A0000, 0x607A0005, -1, 2**32):
        with pytest.raises(InvalidCommand):
            SdoSelector.from_value(bad)


# --- units -------------------------------------------------------------------------

def test_user_unit_values() -> None:
    assert Scaling(1000).to_drive(12.819) == 12819
    assert Scaling(100).to_drive(-0.5) == -50
    assert Scaling(1000).from_drive(12819) == 12.819
    assert Scaling(100).from_drive(1282) == 12.82
    assert Scaling(1).from_drive(-7) == -7.0
    assert stored_parameter(12.819, 1000) == 12819


def test_rounding_is_decimal_and_half_away_from_zero() -> None:
    # 1.0005 * 1000 is 1000.4999999999999 in binary, 1000.5 in decimal -> 1001.
    assert Scaling(1000).to_drive(1.0005) == 1001
    assert Scaling(1000).to_drive(-1.0005) == -1001
    assert Scaling(10).to_drive(0.25) == 3
    assert Scaling(10).to_drive(0.24) == 2


def test_position_conversion() -> None:
    axis = Scaling(factor=1000, inversion=-1, offset=10.0)
    # drive = round((12.5 - 10) * 1000) * -1 = -2500
    assert axis.position_to_drive(12.5) == -2500
    # user = -2500 * -1 / 1000 + 10 = 12.5
    assert axis.position_from_drive(-2500) == 12.5
    # user = 123 * 1 / 10 + -5.5 = 6.8 (decimal, not 6.800000000000001)
    assert Scaling(10, 1, -5.5).position_from_drive(123) == 6.8
    assert Scaling(10, 1, -5.5).position_to_drive(6.8) == 123


def test_display_limits() -> None:
    # 0x607D/1 = -5000, 0x607D/2 = 20000, factor 100
    assert Scaling(100).display_limits(-5000, 20000) == (200.0, -50.0)
    # inverted: positive from /1: 5000/100 = 50; negative from /2: -200
    assert Scaling(100, -1).display_limits(-5000, 20000) == (50.0, -200.0)
    # inverted with offset 10: 50 + 10 = 60; -200 + 10 = -190
    assert Scaling(100, -1, 10.0).display_limits(-5000, 20000) == (60.0, -190.0)


def test_int32_limits() -> None:
    assert Scaling(1000).to_drive(2147483.647) == INT32[1]
    assert Scaling(1000).to_drive(-2147483.648) == INT32[0]
    with pytest.raises(InvalidCommand):
        Scaling(1000).to_drive(2147483.648)
    # -2^31 inverted would be +2^31: out of range after the sign is applied.
    assert Scaling(1, 1).position_to_drive(-(2**31)) == INT32[0]
    with pytest.raises(InvalidCommand):
        Scaling(1, -1).position_to_drive(-(2**31))
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(InvalidCommand):
            Scaling(10).to_drive(bad)


@pytest.mark.parametrize("kwargs", [
    {"factor": 0}, {"factor": -10}, {"factor": 1.5}, {"factor": True},
    {"inversion": 0}, {"inversion": 2}, {"offset": math.nan},
])
def test_scaling_validates(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        Scaling(**kwargs)


@given(raw=st.integers(INT32[0] + 1, INT32[1]), factor=st.sampled_from([1, 10, 100, 1000, 3]),
       inversion=st.sampled_from([1, -1]), offset_raw=st.integers(-10**6, 10**6))
def test_position_round_trip(raw: int, factor: int, inversion: int, offset_raw: int) -> None:
    axis = Scaling(factor, inversion, offset_raw / factor)
    user = axis.position_from_drive(raw)
    if abs(user - axis.offset) * factor < 2**31:
        assert axis.position_to_drive(user) == raw


# --- value parsing -------------------------------------------------------------

@pytest.mark.parametrize("cmd,text,value", [
    (2, "12.5", 12.5),
    (2, "-3", -3.0),
    (2, "+.5", 0.5),
    (4, "1", 1),
    (4, "1.0", 1),  # a client printing with %f
    (22, "-1", -1),
    (0, "9", 9),
    (9, "-32768", -32768),
    (80, "0x607A0004", 0x607A0004),
    (80, "4294967295", 2**32 - 1),
    (52, "0XFF", 255),
    (81, "-5", -5),
])
def test_parse_value(cmd: int, text: str, value: object) -> None:
    got = parse_value(COMMANDS[cmd], text)
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize("cmd,text", [
    (2, "0x10"),  # user units are decimal
    (4, "1.5"),
    (4, "2"),  # not a choice
    (7, "2"),
    (0, "4"),
    (9, "40000"),  # 0x605A is INTEGER16
    (40, "128"),  # homing method is INTEGER8
    (80, "4294967296"),
    (29, "61"),
    (99, "1"),  # read-only text
    (2, "1e5"),
    (2, "nan"),
    (2, "inf"),
    (2, ""),
    (2, " 1"),
    (10, "1x"),
])
def test_parse_value_rejects(cmd: int, text: str) -> None:
    with pytest.raises(InvalidCommand) as info:
        parse_value(COMMANDS[cmd], text)
    assert info.value.cmd == cmd


def test_huge_user_value_is_rejected_after_scaling() -> None:
    value = parse_value(COMMANDS[2], "9" * 40)
    assert value == 1e40
    with pytest.raises(InvalidCommand):
        Scaling(1).to_drive(value)


def test_velocity_and_acceleration_commands_are_marked() -> None:
    # They convert by the drive's units (rpm, rpm/s on an EPOS4), the rest by the factor.
    from tcp_bridge.tables.commands import Quantity
    assert {n for n, c in COMMANDS.items() if c.quantity is Quantity.VELOCITY} == {5, 14, 26, 41, 42}
    assert {n for n, c in COMMANDS.items()
            if c.quantity is Quantity.ACCELERATION} == {6, 27, 28, 43}
