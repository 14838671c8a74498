"""The EPOS4's own data recorder (objects 31E0h-31E9h): its facts, pure.

Used by ``epos-link record --on-drive`` (:mod:`epos_link.tools.record_on_drive`) and
by the simulator's model of the recorder (:mod:`epos_link.simulator.data_recorder`),
so that both follow the same facts and a test of this module tests them for both.

**Source.** maxon's device description files (XDD) for the EPOS4, public in
eltra-ch/eltra-sdk, ``samples/Maxon/Epos4/EposMasterConsole/xdd/``:
``EPOS4_0110h_6150h_0000h_0000h.xdd``, ``EPOS4_0150h_6150h_0000h_0000h.xdd``,
``EPOS4_0160h_6750h_FF00h_00D0h.xdd`` (firmware 0110h, 0150h, 0160h). In each, the
``parameterList`` entries ``PARAM_InternalRecorder*`` (index 0x31E0 .. 0x31E9) give
the objects, types, access, defaults and ranges below, and the ``dataTypeList``
enum ``ERecorderTriggerMode`` the 16 trigger modes with their conditions:

==========  =====================================================  =================
object      XDD label                                              type, range
==========  =====================================================  =================
31E0h:1-4   Internal data recorder variable index 1..4             u32 rw, hex
31E1h:01    Internal data recorder sampling period                 u16 rw, default
            (unit: multiplier 0.01 ms, rounding increment 0.4)     120, 40..65534
31E1h:02    Internal data recorder max number of samples           u16 rw, 1..500
31E2h:01    ... trigger variable index                             u32 rw, hex
31E2h:02    ... trigger mode (ERecorderTriggerMode)                u8 rw, 0..15
31E2h:03/4  ... trigger high value / low value                     u32 rw
31E2h:05    ... trigger mask                                       u32 rw, FFFFFFFFh
31E2h:06    ... trigger number of preceding samples                u16 rw, 0..499
                                                                   (0110h: 0..1999)
31E4h:01    Internal data recorder controlword                     u16 rw, hex
31E4h:02    Internal data recorder statusword                      u16 ro, hex
31E5h:01    ... number of recorded samples                         u16 ro
31E5h:02    Internal recorder buffer timestamp                     u32 ro
31E5h:03    Internal data recorder snapshot                        octets (20) ro
31E6h-31E9h ... buffer variable 1..4 complete (:01), part 1 (:02)  octets (2000) ro
==========  =====================================================  =================

So the period counts in 10 us (0.01 ms; 40 = 0.4 ms, the fastest), a channel holds
at most 500 samples, and a buffer of 2000 bytes is 500 samples of 4 bytes: int32.

**Not in the XDD** (its controlword, statusword and variable index carry no bit or
field description), taken from issue 34, which states them as the recorder's
layout, and marked so wherever they are used: a variable is named ``(index << 16) |
(subindex << 8)`` in 31E0h and 31E2h:01 (the form of a PDO mapping entry without
its length byte, CiA 301 7.5.2.36); the controlword is 0 stop, 1 start, 3 start
and force the trigger; the statusword's bit 0 is "running", bit 1 "triggered".
What needs a check on a real EPOS4 is listed in docs/epos-link.md ("The EPOS4's own
data recorder").

**Chosen** (the XDD is silent; the simulator does the same, so they agree): the
trigger variable is masked (31E2h:05) and compared as a signed 32-bit number with
the high and low values taken as signed 32-bit numbers; values are signed 32-bit
samples, a smaller variable sign- or zero-extended by its own type; the buffer is
in time order, oldest first, with the trigger sample at index "preceding samples".
"""
from __future__ import annotations

import math
import struct
from enum import IntEnum, IntFlag
from typing import Optional, Sequence

VARIABLE_INDEX = 0x31E0  # subindex 1..4: the variables of the 4 channels
CONFIGURATION = 0x31E1
PERIOD_SUB, MAX_SAMPLES_SUB = 1, 2
TRIGGER = 0x31E2
TRIGGER_VARIABLE, TRIGGER_MODE, TRIGGER_HIGH, TRIGGER_LOW, TRIGGER_MASK, PRECEDING = 1, 2, 3, 4, 5, 6
CONTROL = 0x31E4
CONTROLWORD_SUB, STATUSWORD_SUB = 1, 2
DATA = 0x31E5
RECORDED_SUB, TIMESTAMP_SUB, SNAPSHOT_SUB = 1, 2, 3
BUFFERS = (0x31E6, 0x31E7, 0x31E8, 0x31E9)  # channel 1..4
COMPLETE_SUB, PART1_SUB = 1, 2
CHANNELS = 4
MAX_SAMPLES = 500  # 31E1h:02 1..500; 2000-byte buffers of int32
SAMPLE_SIZE = 4
PERIOD_UNIT = 10e-6  # seconds: the XDD's multiplier 0.01 ms
PERIOD_MIN, PERIOD_MAX = 40, 65534  # 31E1h:01: 0.4 ms .. 655.34 ms
PRECEDING_MAX = 499  # 31E2h:06 (firmware 0150h, 0160h)
SNAPSHOT_SIZE = 20


class TriggerMode(IntEnum):
    """31E2h:02, the XDD's ERecorderTriggerMode (value, name and condition as there)."""

    IS_VALUE = 0                        # v == high
    OVER_VALUE = 1                      # v > high
    UNDER_VALUE = 2                     # v < high
    RISING_OVER_VALUE = 3               # v > high && prev <= high
    FALLING_UNDER_VALUE = 4             # v < high && prev >= high
    RISING_OVER_OR_FALLING_UNDER_VALUE = 5
    RISING_TO_VALUE = 6                 # v == high && prev < high
    FALLING_TO_VALUE = 7                # v == high && prev > high
    RISING_OR_FALLING_TO_VALUE = 8
    RISING_EDGE = 9                     # v == high && prev == low
    FALLING_EDGE = 10                   # v == low && prev == high
    BOTH_EDGES = 11
    ENTER_RANGE = 12                    # IN_RANGE && (prev > high || prev < low)
    EXIT_RANGE = 13                     # OUT_OF_RANGE && low <= prev <= high
    IN_RANGE = 14                       # low <= v <= high
    OUT_OF_RANGE = 15                   # v < low || v > high


class Control(IntEnum):
    """31E4h:01 (issue 34; not described in the XDD)."""

    STOP = 0
    START = 1
    START_FORCED = 3  # start, and force the trigger


class RecorderStatus(IntFlag):
    """31E4h:02 (issue 34; not described in the XDD)."""

    RUNNING = 1 << 0
    TRIGGERED = 1 << 1


def encode_variable(index: int, subindex: int) -> int:
    """A variable as 31E0h and 31E2h:01 name it: ``(index << 16) | (subindex << 8)``."""
    if not (0 <= index <= 0xFFFF and 0 <= subindex <= 0xFF):
        raise ValueError(f"no object 0x{index:X}/0x{subindex:X}")
    return (index << 16) | (subindex << 8)


def decode_variable(value: int) -> Optional[tuple[int, int]]:
    """(index, subindex) of a 31E0h value; None for 0 (channel not used). ValueError when
    the low byte is not 0 (the encoding has none)."""
    if value == 0:
        return None
    if value & 0xFF:
        raise ValueError(f"0x{value:08X}: the low byte of a variable index is 0")
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF


def period_units(seconds: float) -> int:
    """31E1h:01 for a period in seconds; ValueError if not a whole number of 10 us in
    0.4 ms .. 655.34 ms."""
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError("the period must be a positive number of seconds")
    units = round(seconds / PERIOD_UNIT)
    if abs(units * PERIOD_UNIT - seconds) > 1e-9:
        raise ValueError(f"{seconds:g} s is not a whole number of 10 us (the recorder's unit)")
    if not PERIOD_MIN <= units <= PERIOD_MAX:
        raise ValueError(f"{seconds:g} s is outside the recorder's 0.4 ms .. 655.34 ms")
    return units


def signed32(value: int) -> int:
    """A 32-bit pattern as a signed number (two's complement)."""
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value & 0x80000000 else value


def unsigned32(value: int) -> int:
    """A signed number as the u32 pattern that 31E2h:03/04 hold."""
    if not -(1 << 31) <= value < (1 << 32):
        raise ValueError(f"{value} does not fit 32 bits")
    return value & 0xFFFFFFFF


def triggered(mode: TriggerMode, previous: Optional[int], value: int, high: int, low: int,
              mask: int = 0xFFFFFFFF) -> bool:
    """Whether a sample ``value`` (after ``previous``, None for the first) fires ``mode``;
    the conditions of the XDD's ERecorderTriggerMode, on masked signed values."""
    v = signed32(value & mask)
    h, lo = signed32(high), signed32(low)
    p = None if previous is None else signed32(previous & mask)
    if mode is TriggerMode.IS_VALUE:
        return v == h
    if mode is TriggerMode.OVER_VALUE:
        return v > h
    if mode is TriggerMode.UNDER_VALUE:
        return v < h
    if mode is TriggerMode.IN_RANGE:
        return lo <= v <= h
    if mode is TriggerMode.OUT_OF_RANGE:
        return v < lo or v > h
    if p is None:  # every other mode compares with the previous sample
        return False
    if mode is TriggerMode.RISING_OVER_VALUE:
        return v > h and p <= h
    if mode is TriggerMode.FALLING_UNDER_VALUE:
        return v < h and p >= h
    if mode is TriggerMode.RISING_OVER_OR_FALLING_UNDER_VALUE:
        return (v > h and p <= h) or (v < h and p >= h)
    if mode is TriggerMode.RISING_TO_VALUE:
        return v == h and p < h
    if mode is TriggerMode.FALLING_TO_VALUE:
        return v == h and p > h
    if mode is TriggerMode.RISING_OR_FALLING_TO_VALUE:
        return v == h and p != h
    if mode is TriggerMode.RISING_EDGE:
        return v == h and p == lo
    if mode is TriggerMode.FALLING_EDGE:
        return v == lo and p == h
    if mode is TriggerMode.BOTH_EDGES:
        return (v == h and p == lo) or (v == lo and p == h)
    if mode is TriggerMode.ENTER_RANGE:
        return lo <= v <= h and (p > h or p < lo)
    if mode is TriggerMode.EXIT_RANGE:
        return (v < lo or v > h) and lo <= p <= h
    raise ValueError(f"trigger mode {mode!r}")


def encode_buffer(samples: Sequence[int]) -> bytes:
    """A channel's buffer: one little-endian int32 per sample (CiA 301 byte order)."""
    return b"".join(struct.pack("<i", signed32(s)) for s in samples)


def decode_buffer(data: bytes) -> list[int]:
    """The samples of a 31E6h-31E9h buffer; ValueError if its length is not 4 x n."""
    if len(data) % SAMPLE_SIZE:
        raise ValueError(f"a recorder buffer of {len(data)} bytes is not whole int32 samples")
    return [v for (v,) in struct.iter_unpack("<i", data)]


__all__ = ["BUFFERS", "CHANNELS", "CONFIGURATION", "CONTROL", "Control", "DATA", "MAX_SAMPLES",
           "PERIOD_MAX", "PERIOD_MIN", "PERIOD_UNIT", "PRECEDING", "PRECEDING_MAX",
           "RecorderStatus", "TRIGGER", "TriggerMode", "VARIABLE_INDEX", "decode_buffer",
           "decode_variable", "encode_buffer", "encode_variable", "period_units", "signed32",
           "triggered", "unsigned32"]
