"""EPOS4 error codes, inputs and the error history (issue 10, items 6, 7, 8).

Expected codes are the EPOS4 Firmware Specification's error table (7.2), as
public EPOS4 code transcribes it: 0x8A80 negative limit switch, 0x8A81
positive limit switch, 0x8A82 software position limit, 0x8A88 STO, 0x8611
following error. 60FDh bits from CiA 402-2: 0 negative, 1 positive limit
switch, 2 home switch.
"""
from __future__ import annotations

import pytest
from canopen import SdoAbortedError
from canopen.objectdictionary import datatypes

from epos_link.cia402 import State
from epos_link.codes import DEVICE_ERRORS, describe_device_error
from epos_link.simulator.drive import Drive, Mode
from epos_link.simulator.faults import HISTORY_DEPTH, SIMULATOR_COMMANDS
from epos_link.simulator.od import SAVE_SIGNATURE, ObjectStore, load_object_dictionary

OD = load_object_dictionary(1)
SHUTDOWN, ENABLE, FAULT_RESET = 0x06, 0x0F, 0x80
VOLTAGE, INTERNAL_LIMIT, BIT13 = 0x0010, 0x0800, 0x2000
RANGE = 0x06090030


def write(d: Drive, index: int, value: int, sub: int = 0) -> None:
    d.store.write_value(index, sub, value)


def read(d: Drive, index: int, sub: int = 0) -> object:
    return d.store.read_value(index, sub)


def moving() -> Drive:
    d = Drive(ObjectStore(OD))
    d.set_mode(Mode.PROFILE_VELOCITY)
    d.write_controlword(SHUTDOWN)
    d.write_controlword(ENABLE)
    write(d, 0x60FF, 1000)
    d.advance(1.0)
    return d


@pytest.mark.parametrize(("kind", "code", "register", "inputs", "extra"), [
    ("limit_negative", 0x8A80, 0x81, 0x1, INTERNAL_LIMIT),
    ("limit_positive", 0x8A81, 0x81, 0x2, INTERNAL_LIMIT),
    ("software_limit", 0x8A82, 0x81, 0x0, INTERNAL_LIMIT),
    ("following_error", 0x8611, 0x81, 0x0, 0),
])
def test_faults_with_fault_reaction(kind: str, code: int, register: int, inputs: int, extra: int) -> None:
    d = moving()
    d.inject_fault(kind)
    assert d.state is State.FAULT_REACTION_ACTIVE  # 605Eh = 2: quick stop ramp, power on
    assert d.statusword & VOLTAGE and d.statusword & INTERNAL_LIMIT == extra
    assert list(d.unsafe_stops) == []
    d.advance(1.0)
    assert d.state is State.FAULT and d.velocity == 0
    assert (read(d, 0x603F), read(d, 0x1001), read(d, 0x60FD)) == (code, register, inputs)
    assert read(d, 0x1003, 1) == code and read(d, 0x1003, 0) == 1
    d.write_controlword(FAULT_RESET)
    assert d.state is State.SWITCH_ON_DISABLED
    assert (read(d, 0x603F), read(d, 0x1001), read(d, 0x60FD)) == (0, 0, 0)
    assert d.statusword & INTERNAL_LIMIT == 0
    assert read(d, 0x1003, 1) == code  # the history survives a fault reset


def test_sto_disables_the_power_stage_at_once() -> None:
    d = moving()
    d.inject_fault("sto")
    assert d.state is State.FAULT and d.statusword & VOLTAGE == 0  # reaction "d"
    assert (read(d, 0x603F), read(d, 0x1001), read(d, 0x60FD)) == (0x8A88, 0x01, 0)
    [stop] = d.unsafe_stops
    assert stop.velocity > 0 and d.velocity == 1000  # coasting, not braked
    assert d.statusword & INTERNAL_LIMIT == 0  # STO is not a limit switch


def test_names_come_from_the_epos4_table() -> None:
    assert DEVICE_ERRORS[0x8A80] == "Negative limit switch error"
    assert DEVICE_ERRORS[0x8A81] == "Positive limit switch error"
    assert DEVICE_ERRORS[0x8A82] == "Software position limit error"
    assert DEVICE_ERRORS[0x8A88] == "STO error"
    assert describe_device_error(0x1234) == "Unknown device error 0x1234"


@pytest.mark.parametrize(("value", "code"), [(1, 0x8A81), (2, 0x8A80), (3, 0x8611), (4, 0x8A82), (5, 0x8A88)])
def test_simulator_command_faults(value: int, code: int) -> None:
    d = Drive(ObjectStore(OD))
    d.store.write(0x2100, 0, value.to_bytes(4, "little"))
    assert d.state is State.FAULT and read(d, 0x603F) == code


def test_simulator_command_range() -> None:
    assert sorted(SIMULATOR_COMMANDS) == [1, 2, 3, 4, 5, 6, 7, 8]
    d = Drive(ObjectStore(OD))
    for value in (0, 9):
        with pytest.raises(SdoAbortedError) as info:
            d.store.write(0x2100, 0, value.to_bytes(4, "little"))
        assert info.value.code == RANGE


# -- statusword bit 11 versus the limit switch inputs (item 8) -----------------------------


def test_velocity_limit_sets_bit_11_but_no_input() -> None:
    d = moving()
    write(d, 0x60FF, 60000)  # above 607Fh = 50000 rpm
    d.advance(10.0)
    assert d.statusword & INTERNAL_LIMIT  # EPOS4: internal limit, e.g. velocity limited
    assert read(d, 0x60FD) == 0  # no limit switch is active: R83 must read 60FDh


def test_limit_switch_sets_input_and_bit_11() -> None:
    d = moving()
    d.inject_fault("limit_positive")
    assert read(d, 0x60FD) == 0x2 and d.statusword & INTERNAL_LIMIT


# -- 1003h error history (item 6) ------------------------------------------------------------


def test_error_history_newest_first_and_bounded() -> None:
    d = Drive(ObjectStore(OD))
    codes = {"limit_negative": 0x8A80, "limit_positive": 0x8A81, "software_limit": 0x8A82,
             "sto": 0x8A88, "following_error": 0x8611}
    kinds = ["limit_negative", "sto", "following_error", "software_limit", "limit_positive",
             "sto", "limit_negative", "software_limit", "following_error", "sto"]
    for kind in kinds:
        d.inject_fault(kind)
        d.write_controlword(FAULT_RESET)
        d.write_controlword(0)
    assert read(d, 0x1003, 0) == HISTORY_DEPTH == 8  # as the EDS declares: subs 1..8
    assert [read(d, 0x1003, s) for s in range(1, 9)] == [codes[k] for k in reversed(kinds)][:8]


def test_error_history_clear_with_zero_only() -> None:
    d = Drive(ObjectStore(OD))
    d.inject_fault("sto")
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x1003, 1)
    assert info.value.code == RANGE
    with pytest.raises(SdoAbortedError) as info:
        write(d, 0x1003, 0x1234, 1)  # the entries are read-only
    assert info.value.code == 0x06010002
    d.store.write(0x1003, 0, b"\x00\x00\x00\x00")  # a 4-byte WriteObject of 0 (zero padding)
    assert read(d, 0x1003, 0) == 0 and read(d, 0x1003, 1) == 0


def test_error_history_is_not_a_saved_parameter() -> None:
    d = Drive(ObjectStore(OD))
    d.inject_fault("sto")
    write(d, 0x1010, SAVE_SIGNATURE, 1)
    assert not any(k.startswith("0x1003") for k in d.store.saved)
    d.power_cycle()
    assert read(d, 0x1003, 0) == 0


def test_homing_objects_real_clients_write() -> None:
    d = Drive(ObjectStore(OD))
    assert OD[0x30B1].data_type == datatypes.INTEGER32  # home offset move distance [inc]
    assert OD[0x30B2].data_type == datatypes.UNSIGNED32  # current threshold [mA]
    write(d, 0x30B1, -622080)
    write(d, 0x30B2, 1500)
    assert (read(d, 0x30B1), read(d, 0x30B2)) == (-622080, 1500)
