"""Every fact of the EPOS4's data recorder that we use (epos_link/data_recorder.py), and
the simulator's model of it (epos_link/simulator/data_recorder.py) following them.

Issue 34, must show 2: "a test of every XDD fact used (encoding, period unit, trigger
modes, control and status bits)". The expected values are written out here from
the sources (maxon's XDD, eltra-ch/eltra-sdk samples/Maxon/Epos4/EposMasterConsole/
xdd/EPOS4_0160h_6750h_FF00h_00D0h.xdd, ``ERecorderTriggerMode`` and the
``PARAM_InternalRecorder*`` parameters; issue 34 for the variable encoding and the
control and status values, which the XDD does not describe), not computed by the
code under test.
"""
from __future__ import annotations

import struct
from typing import Any

import pytest
from canopen import SdoAbortedError

from epos_link import data_recorder as f
from epos_link.data_recorder import Control, RecorderStatus, TriggerMode, triggered
from epos_link.simulator.clock import VirtualClock
from epos_link.simulator.drive import Drive
from epos_link.simulator.od import load_object_dictionary

# --- the facts ------------------------------------------------------------------------


def test_objects_and_sizes_as_the_xdd_gives_them() -> None:
    assert (f.VARIABLE_INDEX, f.CONFIGURATION, f.TRIGGER, f.CONTROL, f.DATA) == (
        0x31E0, 0x31E1, 0x31E2, 0x31E4, 0x31E5)
    assert f.BUFFERS == (0x31E6, 0x31E7, 0x31E8, 0x31E9) and f.CHANNELS == 4
    # 31E1h:02 1..500; a buffer is 2000 bytes: 500 int32 samples.
    assert f.MAX_SAMPLES == 500 and f.MAX_SAMPLES * f.SAMPLE_SIZE == 2000
    assert (f.PERIOD_MIN, f.PERIOD_MAX, f.PRECEDING_MAX) == (40, 65534, 499)


def test_variable_encoding_index_16_subindex_8() -> None:
    assert f.encode_variable(0x6064, 0x00) == 0x60640000
    assert f.encode_variable(0x1018, 0x04) == 0x10180400
    assert f.encode_variable(0x30D1, 0x02) == 0x30D10200
    assert f.decode_variable(0x60640000) == (0x6064, 0)
    assert f.decode_variable(0x10180400) == (0x1018, 4)
    assert f.decode_variable(0) is None  # channel not used
    with pytest.raises(ValueError):
        f.decode_variable(0x60640020)  # a PDO-style length byte is not this encoding
    with pytest.raises(ValueError):
        f.encode_variable(0x10000, 0)


def test_period_unit_is_10_us() -> None:
    # 31E1h:01: unit multiplier 0.01 ms, default 120 (1.2 ms), 40..65534.
    assert f.PERIOD_UNIT == pytest.approx(10e-6)
    assert f.period_units(0.001) == 100
    assert f.period_units(0.0012) == 120
    assert f.period_units(0.0004) == 40
    assert f.period_units(0.65534) == 65534
    for bad in (0.00039, 0.0003, 0.65535, 0.001005, 0.0, -0.001):
        with pytest.raises(ValueError):
            f.period_units(bad)


def test_control_and_status_values() -> None:
    assert [int(c) for c in (Control.STOP, Control.START, Control.START_FORCED)] == [0, 1, 3]
    assert int(RecorderStatus.RUNNING) == 0x0001 and int(RecorderStatus.TRIGGERED) == 0x0002


def test_sixteen_trigger_modes_numbered_as_in_the_xdd() -> None:
    assert [(m.name, m.value) for m in TriggerMode] == [
        ("IS_VALUE", 0), ("OVER_VALUE", 1), ("UNDER_VALUE", 2), ("RISING_OVER_VALUE", 3),
        ("FALLING_UNDER_VALUE", 4), ("RISING_OVER_OR_FALLING_UNDER_VALUE", 5),
        ("RISING_TO_VALUE", 6), ("FALLING_TO_VALUE", 7), ("RISING_OR_FALLING_TO_VALUE", 8),
        ("RISING_EDGE", 9), ("FALLING_EDGE", 10), ("BOTH_EDGES", 11), ("ENTER_RANGE", 12),
        ("EXIT_RANGE", 13), ("IN_RANGE", 14), ("OUT_OF_RANGE", 15)]


M = TriggerMode
HIGH, LOW = 10, -10
# (mode, previous, value, fires): the XDD's condition of each mode, at and around its edges.
CASES = [
    (M.IS_VALUE, None, 10, True), (M.IS_VALUE, 5, 11, False),
    (M.OVER_VALUE, None, 11, True), (M.OVER_VALUE, 0, 10, False),
    (M.UNDER_VALUE, None, 9, True), (M.UNDER_VALUE, 0, 10, False),
    (M.RISING_OVER_VALUE, 10, 11, True), (M.RISING_OVER_VALUE, 11, 12, False),
    (M.RISING_OVER_VALUE, 9, 10, False), (M.RISING_OVER_VALUE, None, 11, False),
    (M.FALLING_UNDER_VALUE, 10, 9, True), (M.FALLING_UNDER_VALUE, 9, 8, False),
    (M.FALLING_UNDER_VALUE, 11, 10, False),
    (M.RISING_OVER_OR_FALLING_UNDER_VALUE, 10, 11, True),
    (M.RISING_OVER_OR_FALLING_UNDER_VALUE, 10, 9, True),
    (M.RISING_OVER_OR_FALLING_UNDER_VALUE, 12, 13, False),
    (M.RISING_TO_VALUE, 9, 10, True), (M.RISING_TO_VALUE, 11, 10, False),
    (M.RISING_TO_VALUE, 10, 10, False),
    (M.FALLING_TO_VALUE, 11, 10, True), (M.FALLING_TO_VALUE, 9, 10, False),
    (M.RISING_OR_FALLING_TO_VALUE, 9, 10, True), (M.RISING_OR_FALLING_TO_VALUE, 11, 10, True),
    (M.RISING_OR_FALLING_TO_VALUE, 10, 10, False),
    (M.RISING_EDGE, -10, 10, True), (M.RISING_EDGE, -9, 10, False), (M.RISING_EDGE, 10, -10, False),
    (M.FALLING_EDGE, 10, -10, True), (M.FALLING_EDGE, -10, 10, False),
    (M.BOTH_EDGES, -10, 10, True), (M.BOTH_EDGES, 10, -10, True), (M.BOTH_EDGES, 0, 10, False),
    (M.ENTER_RANGE, 11, 10, True), (M.ENTER_RANGE, -11, -10, True), (M.ENTER_RANGE, 0, 1, False),
    (M.ENTER_RANGE, 11, 12, False),
    (M.EXIT_RANGE, 10, 11, True), (M.EXIT_RANGE, -10, -11, True), (M.EXIT_RANGE, 11, 12, False),
    (M.EXIT_RANGE, 0, 1, False),
    (M.IN_RANGE, None, -10, True), (M.IN_RANGE, None, 10, True), (M.IN_RANGE, None, 11, False),
    (M.OUT_OF_RANGE, None, -11, True), (M.OUT_OF_RANGE, None, 11, True),
    (M.OUT_OF_RANGE, None, 0, False),
]


@pytest.mark.parametrize("mode, previous, value, fires", CASES)
def test_trigger_modes(mode: TriggerMode, previous: int | None, value: int, fires: bool) -> None:
    high, low = f.unsigned32(HIGH), f.unsigned32(LOW)  # 31E2h:03/04 are u32 objects
    raw = f.unsigned32(value)
    prev = None if previous is None else f.unsigned32(previous)
    assert triggered(mode, prev, raw, high, low) is fires


def test_every_mode_has_a_case() -> None:
    assert {c[0] for c in CASES} == set(TriggerMode)


def test_mask_selects_bits_before_the_comparison() -> None:
    # The statusword's set-point acknowledge (bit 12) rising, whatever the other bits do.
    assert triggered(M.RISING_EDGE, 0x0237, 0x1637, 0x1000, 0, mask=0x1000)
    assert not triggered(M.RISING_EDGE, 0x1237, 0x1637, 0x1000, 0, mask=0x1000)


def test_buffers_are_little_endian_int32() -> None:
    data = struct.pack("<3i", 0, -1, 20000)
    assert f.decode_buffer(data) == [0, -1, 20000]
    assert f.encode_buffer([0, -1, 20000]) == data
    assert f.encode_buffer([0xFFFF_FFFF]) == struct.pack("<i", -1)
    with pytest.raises(ValueError):
        f.decode_buffer(b"\0\0\0")


# --- the simulator's recorder, by the same facts ------------------------------------------


def test_the_simulated_dictionary_has_the_objects_of_the_xdd() -> None:
    od: Any = load_object_dictionary(2)
    assert od[0x31E1][1].default == 120 and (od[0x31E1][1].min, od[0x31E1][1].max) == (40, 65534)
    assert od[0x31E1][2].default == 500 and od[0x31E2][5].default == 0xFFFFFFFF
    assert od[0x31E2][6].max == 499 and od[0x31E4][2].access_type == "ro"
    assert [od[i][0].default for i in range(0x31E0, 0x31EA) if i != 0x31E3] == [4, 2, 6, 2, 3,
                                                                              2, 2, 2, 2]


def _bytes(value: object) -> bytes:
    assert isinstance(value, bytes)
    return value


def _drive() -> tuple[Drive, VirtualClock]:
    clock = VirtualClock(10.0)
    return Drive(store=None, clock=clock), clock


def _configure(drive: Drive, *, period: int = 100, samples: int = 20, preceding: int = 3,
               trigger: int = 0x60410000, mode: TriggerMode = M.RISING_EDGE, high: int = 0x1000,
               low: int = 0, mask: int = 0x1000) -> None:
    s = drive.store
    s.write_value(f.VARIABLE_INDEX, 1, f.encode_variable(0x6064, 0))
    s.write_value(f.VARIABLE_INDEX, 2, f.encode_variable(0x6041, 0))
    s.write_value(f.CONFIGURATION, 1, period)
    s.write_value(f.CONFIGURATION, 2, samples)
    for sub, value in ((1, trigger), (2, int(mode)), (3, high), (4, low), (5, mask), (6, preceding)):
        s.write_value(f.TRIGGER, sub, value)


def _enable_and_move(drive: Drive, clock: VirtualClock, target: int = 20000) -> float:
    for cw in (0x06, 0x07, 0x0F):
        drive.write_controlword(cw)
        clock.advance(0.005)
    drive.store.write_value(0x607A, 0, target)
    drive.write_controlword(0x1F)
    return clock()


def test_a_start_runs_until_the_buffer_is_full_with_the_trigger_at_preceding() -> None:
    drive, clock = _drive()
    _configure(drive, preceding=3, samples=20)
    s = drive.store
    s.write_value(f.CONTROL, 1, Control.START)
    assert s.read_value(f.CONTROL, 2) == RecorderStatus.RUNNING
    _enable_and_move(drive, clock)
    clock.advance(0.002)
    assert s.read_value(f.CONTROL, 2) == RecorderStatus.RUNNING | RecorderStatus.TRIGGERED
    clock.advance(0.1)
    assert s.read_value(f.CONTROL, 2) == RecorderStatus.TRIGGERED  # done: not running
    assert s.read_value(f.DATA, 1) == 20
    status = f.decode_buffer(_bytes(s.read_value(f.BUFFERS[1], 1)))
    assert [bool(w & 0x1000) for w in status] == [False] * 3 + [True] * 17
    positions = f.decode_buffer(_bytes(s.read_value(f.BUFFERS[0], 1)))
    assert positions[:4] == [0, 0, 0, 0] and positions[-1] > positions[4] > 0
    assert s.read_value(f.BUFFERS[2], 1) == b""  # channel 3 not used


def test_samples_are_exactly_one_period_apart_in_the_drives_time() -> None:
    drive, clock = _drive()
    _configure(drive, period=100, samples=50, preceding=0, trigger=f.encode_variable(0x6064, 0),
               mode=M.OVER_VALUE, high=0, mask=0xFFFFFFFF)
    s = drive.store
    started = _enable_and_move(drive, clock)
    s.write_value(f.CONTROL, 1, Control.START_FORCED)  # at `started`: the first sample
    for _ in range(7):  # the host polls at odd moments; the drive samples on its own grid
        clock.advance(0.0173)
        s.read_value(f.CONTROL, 2)
    positions = f.decode_buffer(_bytes(s.read_value(f.BUFFERS[0], 1)))
    assert len(positions) == 50
    reference, ref_clock = _drive()
    t0 = _enable_and_move(reference, ref_clock)
    assert t0 == started
    expected = []
    for k in range(50):
        ref_clock.now = t0 + k * 0.001
        expected.append(reference.store.read_value(0x6064, 0))
    assert positions == expected


def test_forced_start_triggers_at_once_and_stop_keeps_what_was_recorded() -> None:
    drive, clock = _drive()
    _configure(drive, preceding=0, samples=500)
    s = drive.store
    s.write_value(f.CONTROL, 1, Control.START_FORCED)
    clock.advance(0.0105)
    assert s.read_value(f.CONTROL, 2) == RecorderStatus.RUNNING | RecorderStatus.TRIGGERED
    s.write_value(f.CONTROL, 1, Control.STOP)
    assert s.read_value(f.CONTROL, 2) == RecorderStatus.TRIGGERED
    assert s.read_value(f.DATA, 1) == 11  # t = 0, 1, ..., 10 ms
    clock.advance(0.1)
    assert s.read_value(f.DATA, 1) == 11


def test_refusals() -> None:
    drive, clock = _drive()
    s = drive.store
    for index, sub, value in ((f.VARIABLE_INDEX, 1, 0x60640020),  # a length byte
                              (f.VARIABLE_INDEX, 1, 0x5FFF0000),  # no such object
                              (f.VARIABLE_INDEX, 1, 0x10080000),  # a string
                              (f.CONFIGURATION, 1, 39), (f.CONFIGURATION, 2, 501),
                              (f.TRIGGER, 2, 16), (f.TRIGGER, 6, 500), (f.CONTROL, 1, 2)):
        with pytest.raises(SdoAbortedError) as refused:
            s.write_value(index, sub, value)
        assert refused.value.code == 0x06090030, (hex(index), sub, value)
    with pytest.raises(SdoAbortedError) as refused:
        s.write_value(f.CONTROL, 2, 0)
    assert refused.value.code == 0x06010002  # read only
    s.write_value(f.CONTROL, 1, Control.START)
    with pytest.raises(SdoAbortedError) as refused:
        s.write_value(f.CONFIGURATION, 1, 200)  # not while it runs
    assert refused.value.code == 0x08000022
    s.write_value(f.CONTROL, 1, Control.STOP)
    s.write_value(f.CONFIGURATION, 1, 200)
