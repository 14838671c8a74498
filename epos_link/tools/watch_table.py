"""The table of ``epos-link watch``: its rows, what each value means, and fixed-width lines.

Pure: no clock, no terminal, no link (tests/test_watch_table.py checks the imports).
:mod:`epos_link.tools.watch` reads the objects, hands each reading in with the time
it was taken on a monotonic clock that it owns (tests pass their own numbers), and
draws the lines made here.

One line per object, in five columns::

    OBJECT       NAME                    VALUE                                 UNIT   AGE   RATE
    0x6041/0x00  Statusword              0x0637 operation enabled, voltage...         0.3s  3.9/s

* VALUE is decoded where a standard says what the number means, as every tool of
  this package does (:func:`epos_link.tools.objects.meaning`): the statusword
  6041h as hex with its CiA 402 state and set flags (CiA 402-2 6.4.1.4); the modes
  of operation 6060h/6061h as number and mode (CiA 402-2 6.3.1, "Modes of
  operation"); the error register 1001h as hex and its set bits (CiA 301 7.5.2.2);
  the error code 603Fh as hex and the EPOS4 name of the error (EPOS4 Firmware
  Specification 7.2, :data:`epos_link.codes.DEVICE_ERRORS`). Other integers are
  decimal, strings quoted, byte strings hex. A read that failed shows ``! `` and
  the error (``! timeout``, ``! 0x06020000 Object does not exist error``) until
  a read succeeds again: a stale number is never shown as if it were current.
* UNIT: ``inc`` (increments) for positions, the velocity unit of 60A9h for
  velocities (``rpm``, ``0.1 rpm``...; EPOS4 Firmware Specification "SI unit
  velocity", maxon's prefixes as in :mod:`epos_link.simulator.units`), else blank:
  the EDS carries no units.
* AGE (**chosen**): the time since the value last *changed*, that is since the
  first read that returned the value shown. A value that holds still ages (how
  long has the drive been in this state?); a moving one stays near 0. How fresh
  the reading is, RATE says. ``-`` before the first successful read. One table
  on its own (``--once``) gives ages as of each row's read: 0.0s.
* RATE: successful reads per second of this row over the last
  :data:`RATE_WINDOW` seconds, ``(n - 1) / (t_last - t_first)`` of the n reads in
  the window; ``-`` until two reads.

Widths (**chosen**): fixed OBJECT, UNIT, AGE and RATE columns; NAME as wide as the
longest name but shrunk (cut, ending in ``~``) before VALUE drops below
:data:`VALUE_MIN`; VALUE as wide as the widest value shown so far (it grows,
never shrinks, so columns do not jump about), within what the terminal leaves.
Every line is cut to the terminal width, so a narrow terminal never wraps and the
screen can be redrawn in place.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Optional, Sequence, Union

from ..cia402 import describe_statusword
from ..codes import describe_device_error
from ..simulator.units import VELOCITY_PREFIXES, VELOCITY_UNIT_RPM

Value = Union[int, float, bool, str, bytes]

RATE_WINDOW = 5.0  # seconds of reads a row's rate is taken over
VALUE_MIN = 30     # VALUE keeps this many columns while NAME can give some up
NAME_MIN = 12
GAP = "  "
ADDRESS_WIDTH = len("0x6041/0x00")
UNIT_WIDTH = len("0.001 rpm")
AGE_WIDTH = 6
RATE_WIDTH = 7

STATUSWORD = 0x6041
MODES_OF_OPERATION = (0x6060, 0x6061)
ERROR_REGISTER = 0x1001
ERROR_CODE = 0x603F
# Positions in increments (CiA 402-2 6.5: position units; the EPOS4 has no factor
# group, so they are encoder increments): demand, internal, actual, target,
# following error actual value.
POSITION_OBJECTS = frozenset({0x6062, 0x6063, 0x6064, 0x607A, 0x60F4})
# Velocities in the unit of 60A9h: demand, actual, profile velocity, max profile
# velocity, target velocity (EPOS4 Firmware Specification, the objects' units).
VELOCITY_OBJECTS = frozenset({0x606B, 0x606C, 0x6081, 0x607F, 0x60FF})

# CiA 402-2 6.3.1 "Modes of operation" (6060h) value definitions; an EPOS4 has
# pp, pv, hm, csp, csv and cst (EPOS4 Firmware Specification 6060h).
MODE_NAMES: dict[int, str] = {
    0: "no mode", 1: "profile position (pp)", 2: "velocity (vl)", 3: "profile velocity (pv)",
    4: "profile torque (tq)", 6: "homing (hm)", 7: "interpolated position (ip)",
    8: "cyclic sync position (csp)", 9: "cyclic sync velocity (csv)",
    10: "cyclic sync torque (cst)",
}

# CiA 301 7.5.2.2, Table "Structure of the error register" (1001h); bit 6 is reserved.
ERROR_REGISTER_BITS: tuple[tuple[int, str], ...] = (
    (0x01, "generic"), (0x02, "current"), (0x04, "voltage"), (0x08, "temperature"),
    (0x10, "communication"), (0x20, "device profile"), (0x80, "manufacturer"),
)


@dataclass(frozen=True)
class Watched:
    """One object on the screen: where it is, its name in the dictionary, its unit."""

    index: int
    subindex: int
    name: str
    unit: str = ""

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}/0x{self.subindex:02X}"


class Row:
    """What the screen knows about one object: its last value or error, when the value
    last changed, and the times of its recent reads."""

    def __init__(self, watched: Watched, window: float = RATE_WINDOW) -> None:
        self.watched = watched
        self.window = window
        self.value: Optional[Value] = None
        self.error: Optional[str] = None
        self.changed_at: Optional[float] = None
        self.read_at: Optional[float] = None  # the last successful read
        self.reads = 0
        self.widest = 0  # the longest VALUE this row has shown
        self._times: deque[float] = deque()

    def reading(self, value: Value, now: float) -> None:
        """A successful read at ``now``."""
        if self.changed_at is None or value != self.value:
            self.changed_at = now
        self.value = value
        self.error = None
        self.read_at = now
        self.reads += 1
        self._times.append(now)
        self._forget(now)
        self.widest = max(self.widest, len(self.shown_value()))

    def failure(self, text: str, now: float) -> None:
        """A read that failed at ``now``: the row shows ``text`` until a read succeeds."""
        self.error = text
        self._forget(now)
        self.widest = max(self.widest, len(self.shown_value()))

    def _forget(self, now: float) -> None:
        while self._times and self._times[0] < now - self.window:
            self._times.popleft()

    def age(self, now: Optional[float]) -> Optional[float]:
        """Seconds since the value changed, at ``now``; ``now=None``: as of the last read."""
        at = self.read_at if now is None else now
        if self.changed_at is None or at is None:
            return None
        return max(0.0, at - self.changed_at)

    def rate(self, now: Optional[float]) -> Optional[float]:
        if now is not None:
            self._forget(now)
        if len(self._times) < 2 or self._times[-1] <= self._times[0]:
            return None
        return (len(self._times) - 1) / (self._times[-1] - self._times[0])

    def shown_value(self) -> str:
        if self.error is not None:
            return f"! {self.error}"
        if self.value is None:
            return ""
        return format_value(self.watched.index, self.watched.subindex, self.value)


def format_value(index: int, subindex: int, value: Value) -> str:
    """A value as the VALUE column shows it (see the module docstring)."""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int) and subindex == 0:
        if index == STATUSWORD:
            return f"0x{value & 0xFFFF:04X} {describe_statusword(value)}"
        if index in MODES_OF_OPERATION:
            name = MODE_NAMES.get(value, "manufacturer-specific" if value < 0 else "reserved")
            return f"{value} {name}"
        if index == ERROR_REGISTER:
            bits = [name for bit, name in ERROR_REGISTER_BITS if value & bit]
            return f"0x{value & 0xFF:02X}" + (f" {', '.join(bits)}" if bits else "")
        if index == ERROR_CODE:
            return f"0x{value & 0xFFFF:04X} {describe_device_error(value & 0xFFFF)}"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return value.hex(" ").upper() if value else "(empty)"


def velocity_unit(si_unit: int) -> str:
    """The unit a 60A9h value names: rpm with maxon's prefix 10^0..10^-3 (``rpm``,
    ``0.1 rpm``...); ``?`` for a value an EPOS4 would not hold."""
    prefix = (si_unit >> 24) & 0xFF
    if si_unit & 0x00FFFFFF != VELOCITY_UNIT_RPM or prefix not in VELOCITY_PREFIXES:
        return "?"
    exponent = VELOCITY_PREFIXES[prefix]
    return "rpm" if exponent == 0 else f"{10.0 ** exponent:g} rpm"


def unit_of(index: int, subindex: int, velocity: str) -> str:
    """The UNIT of an object, given the velocity unit (:func:`velocity_unit`)."""
    if subindex != 0:
        return ""
    if index in POSITION_OBJECTS:
        return "inc"
    if index in VELOCITY_OBJECTS:
        return velocity
    return ""


def format_age(age: Optional[float]) -> str:
    """``-``, ``0.3s`` (under 10 s), ``42s``, ``12m``, ``5h``: at most 6 characters."""
    if age is None:
        return "-"
    if age < 9.95:
        return f"{age:.1f}s"
    if age < 599.5:
        return f"{age:.0f}s"
    if age < 35970:
        return f"{age / 60:.0f}m"
    return f"{min(age / 3600, 99999):.0f}h"


def format_rate(rate: Optional[float]) -> str:
    """``-`` or reads per second, ``12.5/s``; at most 7 characters."""
    if rate is None:
        return "-"
    return f"{rate:.1f}/s" if rate < 999.95 else f"{min(rate, 99999):.0f}/s"


def fit(text: str, width: int) -> str:
    """``text`` in exactly ``width`` columns: padded, or cut ending in ``~``."""
    if width <= 0:
        return ""
    if len(text) <= width:
        return text.ljust(width)
    return text[:width - 1] + "~"


def columns(names: Sequence[str], widest: int, width: int) -> tuple[int, int]:
    """The widths of NAME and VALUE for values up to ``widest`` characters on a
    terminal ``width`` columns wide."""
    fixed = ADDRESS_WIDTH + UNIT_WIDTH + AGE_WIDTH + RATE_WIDTH + 5 * len(GAP)
    longest = max([len("NAME"), *map(len, names)])
    value = max(len("VALUE"), widest)
    name = max(NAME_MIN, min(longest, width - fixed - min(value, VALUE_MIN)))
    return name, max(1, min(value, width - fixed - name))


def render(rows: Sequence[Row], now: Optional[float], width: int, title: str = "") -> list[str]:
    """The screen: the title (if any), a header and one line per row, each line at
    most ``width`` characters, trailing blanks removed. ``now=None`` gives each row's
    age as of its own last read (``--once``: 0.0s, whatever the reads took)."""
    name_w, value_w = columns([r.watched.name for r in rows], max([0, *(r.widest for r in rows)]), width)

    def line(address: str, name: str, value: str, unit: str, age: str, rate: str) -> str:
        text = GAP.join([fit(address, ADDRESS_WIDTH), fit(name, name_w), fit(value, value_w),
                         fit(unit, UNIT_WIDTH), age.rjust(AGE_WIDTH), rate.rjust(RATE_WIDTH)])
        return text[:width].rstrip()

    out = [title[:width]] if title else []
    out.append(line("OBJECT", "NAME", "VALUE", "UNIT", "AGE", "RATE"))
    for row in rows:
        w = row.watched
        out.append(line(w.address, w.name, row.shown_value(), w.unit,
                        format_age(row.age(now)), format_rate(row.rate(now))))
    return out


__all__ = ["ERROR_REGISTER_BITS", "MODE_NAMES", "RATE_WINDOW", "Row", "Value", "Watched", "columns",
           "fit", "format_age", "format_rate", "format_value", "render", "unit_of", "velocity_unit"]
