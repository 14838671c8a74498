"""A line-based text format for recorded MAXON SERIAL V2 traffic.

One record per line, fields separated by blanks::

    # epos-link capture v1
    # source: EPOS4 Communication Guide rel7290, 2.2.9, Table 2-5
    0.000000 TX 90 02 60 02 01 B0 30 00 2E 62
    0.001302 RX 90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C

* ``#`` starts a comment (whole line or after the bytes); blank lines are ignored;
* the first field is the time in seconds since the start of the recording;
* the second is the direction: ``TX`` host to device, ``RX`` device to host;
* the rest are the bytes as they crossed the wire (stuffed), two hex digits
  each, spaces optional (``9002600201B030002E62`` is accepted too).

A record holds whatever one read or write carried, so a frame may span
several records, and one record several frames. The module is pure: it reads
and writes text streams handed to it and never looks at a clock.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import IO, Iterable, Iterator, Union

from .errors import EposError

HEADER = "# epos-link capture v1"


class CaptureFormatError(EposError, ValueError):
    """A capture file line that does not follow the format."""


class Direction(str, Enum):
    TX = "TX"  # host -> device
    RX = "RX"  # device -> host


@dataclass(frozen=True)
class Record:
    time: float
    direction: Direction
    data: bytes


@dataclass
class Capture:
    records: list[Record] = field(default_factory=list)
    comments: list[str] = field(default_factory=list)

    def stream(self, direction: Direction) -> bytes:
        """All bytes sent in one direction, concatenated."""
        return b"".join(r.data for r in self.records if r.direction is direction)


EXCERPT = 40  # characters of a bad input quoted in an error message
# The longest line the line readers hand on (tools/follow.py cuts a longer one, so
# memory stays bounded on input without newlines); no record comes near it.
MAX_LINE = 1 << 20


def excerpt(text: str, limit: int = EXCERPT) -> str:
    """``text`` quoted for an error message, cut to ``limit`` characters and its length
    said: an error line stays one short line whatever the input (a 6 MB line, say)."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


def parse_hex(text: str) -> bytes:
    """Hex digits with optional blanks, ``0x`` prefixes, commas or colons between bytes."""
    cleaned = text.replace(",", " ").replace(":", " ")
    parts = []
    for token in cleaned.split():
        if token[:2] in ("0x", "0X"):
            token = token[2:]
        parts.append(token)
    joined = "".join(parts)
    try:
        return bytes.fromhex(joined)
    except ValueError:
        raise CaptureFormatError(f"not hex bytes: {excerpt(text.strip())}") from None


def parse_line(line: str, lineno: int = 0) -> Record | str | None:
    """A Record, a comment text, or None for a blank line."""
    stripped = line.strip()
    if not stripped:
        return None
    if stripped.startswith("#"):
        return stripped[1:].strip()
    body = stripped.split("#", 1)[0]
    fields = body.split(None, 2)
    where = f"line {lineno}: " if lineno else ""
    if len(fields) < 2:
        raise CaptureFormatError(f"{where}expected 'TIME TX|RX HEX', got {excerpt(stripped)}")
    try:
        time = float(fields[0])
    except ValueError:
        raise CaptureFormatError(f"{where}bad time {excerpt(fields[0])}") from None
    if not math.isfinite(time):  # float() takes "nan" and "inf": no time of a recording
        raise CaptureFormatError(f"{where}bad time {fields[0]!r}: not a finite number") from None
    try:
        direction = Direction(fields[1].upper())
    except ValueError:
        raise CaptureFormatError(f"{where}direction must be TX or RX, got {excerpt(fields[1])}"
                                 ) from None
    try:
        data = parse_hex(fields[2]) if len(fields) > 2 else b""
    except CaptureFormatError as exc:
        raise CaptureFormatError(f"{where}{exc}") from None
    return Record(time, direction, data)


def read_capture(source: Union[str, IO[str], Iterable[str]]) -> Capture:
    """Parse a capture from text, an open text file, or an iterable of lines."""
    lines = source.splitlines() if isinstance(source, str) else source
    capture = Capture()
    for lineno, line in enumerate(lines, 1):
        item = parse_line(line, lineno)
        if isinstance(item, Record):
            capture.records.append(item)
        elif isinstance(item, str):
            capture.comments.append(item)
    return capture


def format_record(record: Record) -> str:
    return f"{record.time:.6f} {record.direction.value} {record.data.hex(' ').upper()}".rstrip()


class CaptureWriter:
    """Writes records to a text stream, one line each, flushed as they come."""

    def __init__(self, stream: IO[str], *, comments: Iterable[str] = ()) -> None:
        self._stream = stream
        stream.write(HEADER + "\n")
        for text in comments:
            self.comment(text)

    def comment(self, text: str) -> None:
        for line in text.splitlines() or [""]:
            self._stream.write(f"# {line}".rstrip() + "\n")
        self._stream.flush()

    def write(self, time: float, direction: Direction | str, data: bytes) -> None:
        self._stream.write(format_record(Record(time, Direction(direction), bytes(data))) + "\n")
        self._stream.flush()


def iter_records(capture: Capture, direction: Direction) -> Iterator[Record]:
    return (r for r in capture.records if r.direction is direction)
