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
  A link that failed shows ``! link down`` in every row, and why, once, in a
  status line under the title (``render(status=...)``, :func:`link_cause`).
* UNIT: ``inc`` (increments) for positions, the velocity unit of 60A9h for
  velocities (``rpm``, ``0.1 rpm``...; EPOS4 Firmware Specification "SI unit
  velocity", maxon's prefixes as in :mod:`epos_link.simulator.units`), else blank:
  the EDS carries no units.
* AGE (**chosen**): the time since the value last *changed*, that is since the
  first read that returned the value shown. A value that holds still ages (how
  long has the drive been in this state?); a moving one stays near 0; while reads
  fail it goes on growing from the last value read. How fresh the reading is,
  RATE says. ``-`` before the first successful read. One table on its own
  (``--once``) gives ages as of each row's read: 0.0s.
* RATE: *successful* reads per second of this row over the last
  :data:`RATE_WINDOW` seconds: the successes among the reads tried in the
  window, over the time from the last read tried before it to the last one
  tried; ``-`` until two reads were tried. While reads fail it falls to 0.0/s.

Widths (**chosen**): a number is never cut. A cut number is easily misread
(``1867~`` of 1867234), so VALUE always holds every row's first word, the number
(:func:`essential`), whole. To make room, in this order: NAME shrinks to
:data:`NAME_MIN`; RATE goes, then AGE, then UNIT (UNIT first when no row has a
unit); then NAME. On a terminal too narrow even for that, a number that does not
fit shows as ``#####``, as spreadsheets do, never in part. What follows the
number (the decoded state, an error's name) is cut only where one of its parts
ends, ending in ``~`` (``0x0637 operation enabled~``), never inside a word. With
room to spare, VALUE is as wide as the widest value shown so far (it grows, never
shrinks, so columns do not jump about), and NAME as wide as the longest name,
shrinking (cut, ending in ``~``) down to :data:`NAME_MIN` before VALUE drops below
:data:`VALUE_MIN`. OBJECT, UNIT, AGE and RATE have fixed widths. No line is wider
than the terminal, so a narrow terminal never wraps and the screen can be
redrawn in place.
"""
from __future__ import annotations

import re
import textwrap
from collections import deque
from dataclasses import dataclass
from itertools import islice
from typing import Optional, Sequence, Union

from ..cia402 import describe_statusword
from ..codes import describe_device_error
from ..simulator.units import VELOCITY_PREFIXES, VELOCITY_UNIT_RPM

Value = Union[int, float, bool, str, bytes]

LINK_DOWN = "link down"  # what each row shows while the link is down; the status line says why
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
        self.needed = 0  # the longest first word (number) this row has shown
        # Each read tried: (when, succeeded). The rate counts the successes over the
        # time the attempts span, so a row whose reads fail sees its rate fall to 0.
        self._times: deque[tuple[float, bool]] = deque()

    def reading(self, value: Value, now: float) -> None:
        """A successful read at ``now``."""
        if self.changed_at is None or value != self.value:
            self.changed_at = now
        self.value = value
        self.error = None
        self.read_at = now
        self.reads += 1
        self._attempt(now, True)

    def failure(self, text: str, now: float) -> None:
        """A read that failed at ``now``: the row shows ``text`` until a read succeeds.
        The value's age goes on from its last change; the rate counts no read."""
        self.error = text
        self._attempt(now, False)

    def _attempt(self, now: float, ok: bool) -> None:
        self._times.append((now, ok))
        self._forget(now)
        shown = self.shown_value()
        self.widest = max(self.widest, len(shown))
        self.needed = max(self.needed, essential(shown))

    def _forget(self, now: float) -> None:
        # The newest attempt before the window stays: it starts the span of the
        # first one inside it (and a --period longer than the window still has a rate).
        while len(self._times) > 1 and self._times[1][0] < now - self.window:
            self._times.popleft()

    def age(self, now: Optional[float]) -> Optional[float]:
        """Seconds since the value changed, at ``now``; ``now=None``: as of the last read."""
        at = self.read_at if now is None else now
        if self.changed_at is None or at is None:
            return None
        return max(0.0, at - self.changed_at)

    def rate(self, now: Optional[float]) -> Optional[float]:
        """Successful reads per second: those after the first attempt kept, over the
        time from it to the last attempt; None before two attempts."""
        if now is not None:
            self._forget(now)
        if len(self._times) < 2 or self._times[-1][0] <= self._times[0][0]:
            return None
        ok = sum(good for _, good in islice(self._times, 1, None))
        return ok / (self._times[-1][0] - self._times[0][0])

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


def essential(value: str) -> int:
    """How much of a VALUE cell is never cut: its first word, the number (``0x0637``
    of ``0x0637 operation enabled...``, ``1867234``), with the ``! `` of a failure
    (``! 0x06020000``, ``! timeout``)."""
    start = 2 if value.startswith("! ") else 0
    end = value.find(" ", start)
    return len(value) if end < 0 else end


def fit_value(value: str, width: int) -> str:
    """A VALUE cell in exactly ``width`` columns. What follows the number is cut only
    where a part of it ends (after the number, at a comma), ending in ``~``, so no
    number and no state is shown in part (``switch on~`` of ``switch on disabled``
    would name another state); a number too wide for the column is ``#####``."""
    if len(value) <= width:
        return value.ljust(width)
    keep = essential(value)
    if keep > width:
        return "#" * width
    ends = [keep, *(i for i, c in enumerate(value) if c == "," and keep < i < width)]
    end = max(i for i in ends if i < width) if keep < width else keep
    return (value[:end] + ("~" if end < width else "")).ljust(width)


@dataclass(frozen=True)
class Layout:
    """The widths of NAME (0: not shown) and VALUE, and which of UNIT, AGE and RATE show."""

    name: int
    value: int
    unit: bool = True
    age: bool = True
    rate: bool = True


def columns(names: Sequence[str], widest: int, width: int, needed: int = 0, units: bool = True) -> Layout:
    """The columns for values up to ``widest`` characters whose numbers (:func:`essential`)
    are up to ``needed`` on a terminal ``width`` columns wide; ``units``: some row has one.

    The numbers come first: NAME shrinks to :data:`NAME_MIN`, then RATE and AGE go,
    then NAME, then UNIT (the unit belongs to the number: rpm or 0.1 rpm is a factor
    of ten; OBJECT names the row as well as NAME does), until VALUE holds every
    number whole; UNIT goes first when no row has a unit. With room to spare,
    VALUE grows to ``widest`` while NAME keeps its longest name, giving way only
    down to :data:`NAME_MIN` and only while VALUE is under :data:`VALUE_MIN`."""
    longest = max([len("NAME"), *map(len, names)])
    want = max(len("VALUE"), widest)
    need = max(len("VALUE"), needed)
    widths = {"unit": UNIT_WIDTH, "age": AGE_WIDTH, "rate": RATE_WIDTH}
    shown = dict.fromkeys(widths, True)
    steps = [(None, False), *([] if units else [("unit", False)]), ("rate", False), ("age", False),
             (None, True), ("unit", True)]
    layout = Layout(0, 1)
    for drop, squeeze in steps:
        if drop is not None:
            shown[drop] = False
        # NAME and VALUE share what OBJECT, the gaps and the other columns leave
        room = width - ADDRESS_WIDTH - 2 * len(GAP) - sum(widths[c] + len(GAP) for c in shown if shown[c])
        if squeeze:
            name = min(longest, room - need)
            if name < NAME_MIN // 2:  # a name of a few letters says little: no NAME, nor its gap
                name, room = 0, room + len(GAP)
        else:
            name = max(NAME_MIN, min(longest, room - min(want, VALUE_MIN)))
        layout = Layout(name, max(1, min(want, room - name)), **shown)
        if layout.value >= need:
            break
    return layout  # the last one tried: numbers too wide for it show as #####


def render(rows: Sequence[Row], now: Optional[float], width: int, title: str = "",
           status: str = "") -> list[str]:
    """The screen: the title (if any), the status (if any, wrapped, never cut), a
    header and one line per row, each line at most ``width`` characters, trailing
    blanks removed. ``now=None`` gives each row's age as of its own last read
    (``--once``: 0.0s, whatever the reads took)."""
    cols = columns([r.watched.name for r in rows], max([0, *(r.widest for r in rows)]), width,
                   max([0, *(r.needed for r in rows)]), any(r.watched.unit for r in rows))

    def line(address: str, name: str, value: str, unit: str, age: str, rate: str, head: bool = False) -> str:
        cells = [fit(address, ADDRESS_WIDTH)]
        if cols.name:
            cells.append(fit(name, cols.name))
        cells.append(fit(value, cols.value) if head else fit_value(value, cols.value))
        if cols.unit:
            cells.append(fit(unit, UNIT_WIDTH))
        if cols.age:
            cells.append(age.rjust(AGE_WIDTH))
        if cols.rate:
            cells.append(rate.rjust(RATE_WIDTH))
        return GAP.join(cells)[:width].rstrip()

    out = [title[:width]] if title else []
    out.extend(textwrap.wrap(status, max(1, width), break_long_words=True, break_on_hyphens=False))
    out.append(line("OBJECT", "NAME", "VALUE", "UNIT", "AGE", "RATE", head=True))
    for row in rows:
        w = row.watched
        out.append(line(w.address, w.name, row.shown_value(), w.unit,
                        format_age(row.age(now)), format_rate(row.rate(now))))
    return out


def link_cause(message: str, url: str) -> str:
    """Why the link failed, from a :class:`~epos_link.errors.TransportError`'s text,
    without the URL the title shows (``cannot open socket://...: Connection refused``:
    ``connection refused``; ``read from X failed: [Errno 104] Connection reset by
    peer``: ``connection reset by peer``)."""
    at = message.rfind(url) if url else -1
    if at >= 0:
        rest = message[at + len(url):]
        colon = rest.find(": ")
        message = rest[colon + 2:] if colon >= 0 else rest.strip().removeprefix("is ")
    message = re.sub(r"^\[Errno -?\d+\] ", "", message.strip())
    if message[:1].isupper() and message[1:2].islower():  # "Connection refused", not "EPOS4"
        message = message[0].lower() + message[1:]
    return message or "the link failed"


__all__ = ["ERROR_REGISTER_BITS", "LINK_DOWN", "MODE_NAMES", "RATE_WINDOW", "Layout", "Row", "Value", "Watched",
           "columns", "essential", "fit", "fit_value", "format_age", "format_rate", "format_value",
           "link_cause", "render", "unit_of", "velocity_unit"]
