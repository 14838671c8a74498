"""How a frame looks on one line: timestamps as candump's ``-t``, colours, hex.

::

    (000.104212) TX ReadObject                     node 1 0x6064/0x00 Position actual value crc ok
    (000.104977) RX Answer(ReadObject)             node 1 0x6064/0x00 Position actual value = 1000 (0x000003E8) ok crc ok 0.765 ms

Policy:

* Timestamps (candump ``-t``): ``a`` absolute Unix time, ``d`` delta to the
  previous line, ``z`` zero-based from the first byte (the default); ``A``
  absolute with the date.
* Colours only on a terminal, and never when ``NO_COLOR`` is set to anything
  (https://no-color.org): TX cyan, RX green, red for error codes, CRC faults,
  stuffing faults and bytes that are not a frame. Piped output is plain.
* ``-x`` appends the wire bytes in hex. Bytes that are not a frame always show
  their hex: they are never hidden.

Pure: takes events and returns strings.
"""
from __future__ import annotations

import datetime
import os
from typing import IO, Mapping, Optional

from ..codes import describe_error
from .frames import FrameEvent

TIME_MODES = ("a", "A", "d", "z")
NAME_WIDTH = len("Answer(InitiateSegmentedWrite)")

RESET = "\x1b[0m"
COLOURS = {"TX": "\x1b[36m", "RX": "\x1b[32m", None: "\x1b[33m"}
RED = "\x1b[1;31m"
DIM = "\x1b[2m"


def use_colour(stream: IO[str], env: Mapping[str, str] = os.environ) -> bool:
    """Colour when ``stream`` is a terminal and NO_COLOR is unset or empty."""
    if env.get("NO_COLOR"):
        return False
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class Clock:
    """Formats event times in one of candump's ``-t`` modes."""

    def __init__(self, mode: str = "z", start_wall: float = 0.0) -> None:
        if mode not in TIME_MODES:
            raise ValueError(f"time mode {mode!r} is not one of {', '.join(TIME_MODES)}")
        self.mode = mode
        self.start_wall = start_wall  # Unix time of event time 0
        self._last: Optional[float] = None

    def value(self, t: float) -> float:
        """The number shown: absolute, delta or zero-based seconds."""
        if self.mode in ("a", "A"):
            return self.start_wall + t
        if self.mode == "d":
            delta = 0.0 if self._last is None else t - self._last
            self._last = t
            return delta
        return t

    def text(self, t: float) -> str:
        v = self.value(t)
        if self.mode == "A":
            stamp = datetime.datetime.fromtimestamp(v).strftime("%Y-%m-%d %H:%M:%S.%f")
            return f"({stamp})"
        if self.mode == "a":
            return f"({v:.6f})"
        return f"({v:010.6f})"


def _object_text(event: FrameEvent) -> str:
    if event.index is None:
        return ""
    text = f"node {event.node} 0x{event.index:04X}/0x{event.subindex:02X}"
    if event.obj is not None:
        text += f" {event.obj.name}"
    return text


def format_event(event: FrameEvent, clock: Optional[Clock], *, colour: bool = False,
                 hex_bytes: bool = False) -> str:
    """One line for a frame or for bytes that are not a frame; ``monitor`` and ``decode``
    both print this. ``clock`` None: bytes without times (``decode`` of bare hex), no
    timestamp column."""
    d = event.decoded
    direction = event.direction or "--"
    parts = ([clock.text(event.time)] if clock is not None else []) + [direction]
    bad = event.faulty
    if d.opcode is None:
        parts.append(f"not a frame: {d.problem} [{d.raw.hex(' ').upper()}]")
        return _paint(" ".join(parts), RED if colour else None)
    name = f"Answer({event.answers})" if event.answers else d.name
    parts.append(f"{name:<{NAME_WIDTH}}")
    where = _object_text(event)
    if where:
        parts.append(where)
    elif d.node is not None:
        parts.append(f"node {d.node}")
    if event.value_text is not None:
        parts.append(f"= {event.value_text}")
    elif d.data and not d.error_code:
        parts.append(f"data [{d.data.hex(' ').upper()}]")
    for key, val in d.extra.items():
        parts.append(f"{key}={val}")
    if d.error_code is not None:
        parts.append("ok" if d.error_code == 0 else f"error 0x{d.error_code:08X} {describe_error(d.error_code)}")
    parts.append("crc ok" if d.crc_ok else "CRC BAD")
    if d.problem:
        parts.append(f"({d.problem})")
    if event.latency is not None:
        parts.append(f"{event.latency * 1000.0:.3f} ms")
    line = " ".join(parts)
    if hex_bytes:
        line += f"  [{event.raw.hex(' ').upper()}]"
    if not colour:
        return line
    return _paint(line, RED if bad else COLOURS.get(event.direction))


def _paint(text: str, code: Optional[str]) -> str:
    return f"{code}{text}{RESET}" if code else text


__all__ = ["Clock", "TIME_MODES", "format_event", "use_colour"]
