"""The pure core of ``epos-link record``: columns, sampling schedule, triggers, the
pre-trigger ring buffer, the CSV file and the statusword's state trace.

No clocks and no I/O: times are floats the caller passes in (the host's
monotonic clock in :mod:`epos_link.tools.record`, a virtual clock in tests), and
the CSV is written to any text stream.

Policy:

* **Schedule.** With a period ``p`` the samples are due at ``t0 + k*p``, ``t0``
  being the first sample's time. A sample that ends after the next slot (the
  link is slower than the period) does not make the sampler hurry: the slots
  already past are skipped and counted (``missed``), so the intervals stay
  multiples of ``p``. With ``p = 0`` the next sample is due at once: as fast as
  the link allows.
* **Triggers.** ``now``: the first sample. A threshold ``OBJECT>LEVEL``
  (``<``): the first sample at or beyond the level whose predecessor was
  below it (above it): a crossing, as an oscilloscope's edge trigger; a value
  that is already beyond the level when recording starts waits for the next
  crossing. ``move``: a move starts, as the statusword shows it (CiA 402-2
  6.4.1.4; **chosen**, no public source defines "a move starts" from the
  statusword): in OPERATION ENABLED, bit 12 rises (in profile position mode the
  set-point acknowledge of a new target, CiA 402-2 6.6.1.2) or bit 10 "target
  reached" falls (a new target or velocity in pp and pv). A statusword pulse shorter than the sample
  interval can be missed (a master that clears its new set-point bit as soon
  as the acknowledge comes); a threshold on the position or velocity then
  triggers instead.
* **Time base.** The trigger sample is time 0; samples before it have negative
  times. ``pre`` seconds before the trigger are kept, in a ring buffer of at
  most :data:`MAX_PRE_SAMPLES` samples; after the trigger the recorder takes
  samples until ``duration`` seconds have passed (the last sample is the first
  at or after it) or :data:`MAX_SAMPLES` were taken.
* **Interrupted** before any trigger (Ctrl-C): the samples kept are written with
  times counted from the last one (**chosen**: as if the interrupt were the trigger).
"""
from __future__ import annotations

import csv
import math
from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Iterable, Optional, Sequence, TextIO, Union

from ..cia402 import SW, State, state_from_statusword, state_text

Value = Union[int, float, bool, str, bytes]
MAX_PRE_SAMPLES = 100_000   # the ring buffer's bound, whatever --pre asks
MAX_SAMPLES = 1_000_000     # samples after the trigger: 24 MB of CSV for 3 objects
STATUSWORD = (0x6041, 0)
EPSILON = 1e-9  # seconds: times on a grid (k * period) compare equal through rounding
SET_POINT_ACKNOWLEDGE = 1 << 12  # pp mode (CiA 402-2 6.6.1.2, statusword bit 12)

# Units of objects whose unit the EPOS4 fixes (EPOS4 Firmware Specification, as quoted in
# epos_link/simulator/units.py): positions in increments of the main sensor, accelerations
# in rpm/s (60AAh, fixed); CiA 402-2 6.9.2: torque and current in thousandths of the rated
# value. Velocities take the unit of 60A9h, read once (VELOCITY_OBJECTS).
FIXED_UNITS: dict[int, str] = {
    0x6062: "inc", 0x6063: "inc", 0x6064: "inc", 0x607A: "inc", 0x60F4: "inc", 0x30B0: "inc",
    0x6083: "rpm/s", 0x6084: "rpm/s", 0x6085: "rpm/s", 0x609A: "rpm/s", 0x60C5: "rpm/s",
    0x6071: "‰ rated torque", 0x6074: "‰ rated torque", 0x6077: "‰ rated torque",
    0x6078: "‰ rated current",
}
VELOCITY_OBJECTS = frozenset({0x606B, 0x606C, 0x60FF, 0x6081, 0x607F, 0x6080, 0x30D3})
SI_UNIT_VELOCITY = 0x60A9
# 60A9h: a power-of-ten prefix byte over rpm (0x00B44700); maxon's velocity notation
# (Definitions.h VN_STANDARD .. VN_MILLI), see epos_link/simulator/units.py.
_VELOCITY_PREFIX = {0x00: "rpm", 0xFF: "0.1 rpm", 0xFE: "0.01 rpm", 0xFD: "0.001 rpm"}


def velocity_unit(si_unit: int) -> str:
    """The unit a 60A9h value names; ``""`` for one we cannot read (nothing guessed)."""
    if si_unit & 0x00FFFFFF != 0x00B44700:
        return ""
    return _VELOCITY_PREFIX.get((si_unit >> 24) & 0xFF, "")


def unit_of(index: int, velocity: str = "") -> str:
    if index in VELOCITY_OBJECTS:
        return velocity
    return FIXED_UNITS.get(index, "")


@dataclass(frozen=True)
class Channel:
    """One recorded object: its CSV column name (the dictionary's name, lower case) and unit."""

    index: int
    subindex: int
    name: str
    unit: str = ""

    @property
    def header(self) -> str:
        return f"{self.name} [{self.unit}]" if self.unit else self.name

    @property
    def is_statusword(self) -> bool:
        return (self.index, self.subindex) == STATUSWORD


def column_name(name: Optional[str], index: int, subindex: int) -> str:
    return name.lower() if name else f"0x{index:04X}/0x{subindex:02X}"


# --- the schedule --------------------------------------------------------------------


class Schedule:
    """When the next sample is due (see the module docstring)."""

    def __init__(self, period: float) -> None:
        if not (period >= 0 and math.isfinite(period)):
            raise ValueError("the period must be 0 or more seconds")
        self.period = period
        self._t0: Optional[float] = None
        self._slot = 0
        self.missed = 0

    def due(self, now: float) -> float:
        if self._t0 is None or self.period == 0:
            return now
        return self._t0 + self._slot * self.period

    def taken(self, start: float, end: float) -> None:
        """A sample that started at ``start`` (its slot) ended at ``end``."""
        if self.period == 0:
            return
        if self._t0 is None:
            self._t0 = start
        # The next slot not yet past at the end of this sample; a tiny tolerance so a
        # sample that ends exactly on a slot does not skip it through rounding.
        next_slot = max(self._slot + 1, math.ceil((end - self._t0) / self.period - 1e-9))
        self.missed += next_slot - self._slot - 1
        self._slot = next_slot


# --- triggers ------------------------------------------------------------------------


Row = Sequence[Value]


@dataclass(frozen=True)
class Immediate:
    def fires(self, previous: Optional[Row], row: Row) -> bool:
        return True

    def describe(self, channels: Sequence[Channel]) -> str:
        return "now"


@dataclass(frozen=True)
class Crossing:
    """The value of column ``column`` crosses ``level``: upwards (``rising``) or downwards."""

    column: int
    level: float
    rising: bool

    def fires(self, previous: Optional[Row], row: Row) -> bool:
        if previous is None:
            return False
        before, now = previous[self.column], row[self.column]
        if not isinstance(before, (int, float)) or not isinstance(now, (int, float)):
            return False
        if self.rising:
            return before < self.level <= now
        return before > self.level >= now

    def describe(self, channels: Sequence[Channel]) -> str:
        return f"{channels[self.column].name} {'rises to' if self.rising else 'falls to'} {self.level:g}"


@dataclass(frozen=True)
class MoveStart:
    """A move starts, as the statusword in column ``column`` shows it (module docstring)."""

    column: int

    def fires(self, previous: Optional[Row], row: Row) -> bool:
        if previous is None:
            return False
        before, now = previous[self.column], row[self.column]
        if not isinstance(before, int) or not isinstance(now, int):
            return False
        if state_from_statusword(now) is not State.OPERATION_ENABLED:
            return False
        acknowledged = bool(now & SET_POINT_ACKNOWLEDGE and not before & SET_POINT_ACKNOWLEDGE)
        left_target = bool(before & SW.TARGET_REACHED and not now & SW.TARGET_REACHED)
        return acknowledged or left_target

    def describe(self, channels: Sequence[Channel]) -> str:
        return "a move starting, on the statusword"


Trigger = Union[Immediate, Crossing, MoveStart]


# --- the recorder --------------------------------------------------------------------


class Phase(Enum):
    WAITING = "waiting for the trigger"
    RECORDING = "recording"
    DONE = "done"


@dataclass(frozen=True)
class Sample:
    time: float  # the host's clock (record.py: monotonic, middle of the row's reads)
    values: tuple[Value, ...]


class Recorder:
    """Samples in, a bounded recording out: the trigger, the ring buffer before it."""

    def __init__(self, trigger: Trigger, duration: float, pre: float = 0.0, *,
                 max_pre: int = MAX_PRE_SAMPLES, max_samples: int = MAX_SAMPLES) -> None:
        if not duration >= 0 or not pre >= 0:
            raise ValueError("duration and pre-trigger time must be 0 or more seconds")
        self.trigger = trigger
        self.duration = duration
        self.pre = pre
        self.max_samples = max_samples
        self.phase = Phase.WAITING
        self.trigger_time: Optional[float] = None
        self.before: deque[Sample] = deque(maxlen=max(max_pre, 1))
        self.after: list[Sample] = []
        self.truncated = False  # stopped by max_samples
        self._previous: Optional[Row] = None

    def add(self, sample: Sample) -> Phase:
        if self.phase is Phase.WAITING:
            if self.trigger.fires(self._previous, sample.values):
                self.trigger_time = sample.time
                self.phase = Phase.RECORDING
                # Only what lies within `pre` of the trigger is kept.
                while self.before and self.before[0].time < sample.time - self.pre - EPSILON:
                    self.before.popleft()
            else:
                self._previous = sample.values
                self.before.append(sample)
                while self.before and self.before[0].time < sample.time - self.pre - EPSILON:
                    self.before.popleft()
                return self.phase
        if self.phase is Phase.RECORDING:
            self.after.append(sample)
            assert self.trigger_time is not None
            if sample.time - self.trigger_time >= self.duration - EPSILON:
                self.phase = Phase.DONE
            elif len(self.after) >= self.max_samples:
                self.truncated = True
                self.phase = Phase.DONE
        return self.phase

    @property
    def samples(self) -> list[Sample]:
        return [*self.before, *self.after]

    @property
    def origin(self) -> Optional[float]:
        """Time 0: the trigger, or (never triggered) the last sample kept."""
        if self.trigger_time is not None:
            return self.trigger_time
        return self.before[-1].time if self.before else None

    def rows(self) -> list[tuple[float, tuple[Value, ...]]]:
        origin = self.origin
        if origin is None:
            return []
        return [(s.time - origin, s.values) for s in self.samples]


# --- output --------------------------------------------------------------------------


def state_of(value: Value) -> Optional[State]:
    return state_from_statusword(value) if isinstance(value, int) else None


def headers(channels: Sequence[Channel]) -> list[str]:
    """``time [s]``, one column per object and, after a statusword, its state."""
    out = ["time [s]"]
    for ch in channels:
        out.append(ch.header)
        if ch.is_statusword:
            out.append(f"{ch.name} state")
    return out


def _cell(value: Value) -> str:
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, bytes):
        return value.hex()
    return str(value)


def write_csv(out: TextIO, channels: Sequence[Channel],
              rows: Iterable[tuple[float, Sequence[Value]]]) -> int:
    """The recording as CSV (RFC 4180 quoting, ``\\n`` line ends); returns the rows written."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(headers(channels))
    count = 0
    for t, values in rows:
        line = [f"{t:.6f}"]
        for ch, value in zip(channels, values):
            line.append(_cell(value))
            if ch.is_statusword:
                line.append(state_text(state_of(value)))
        writer.writerow(line)
        count += 1
    return count


def median_interval(times: Sequence[float]) -> Optional[float]:
    gaps = sorted(b - a for a, b in zip(times, times[1:]))
    if not gaps:
        return None
    mid = len(gaps) // 2
    return gaps[mid] if len(gaps) % 2 else (gaps[mid - 1] + gaps[mid]) / 2


__all__ = ["Channel", "Crossing", "FIXED_UNITS", "Immediate", "MAX_PRE_SAMPLES", "MAX_SAMPLES",
           "MoveStart", "Phase", "Recorder", "Sample", "Schedule", "Trigger", "VELOCITY_OBJECTS",
           "column_name", "headers", "median_interval", "state_of", "unit_of", "velocity_unit",
           "write_csv"]
