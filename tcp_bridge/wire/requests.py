"""Requests, client -> gateway (PSI spec 2.2.1 and 2.3.1), parsed strictly.

::

    write:  <axis> S|s <cmd> = <value> CR     33 53 30 32 3D 31 32 0D   "3S02=12"
    read:   <axis> R|r <cmd> CR               33 52 30 32 0D            "3R02"

    axis  1..60, one or two decimal digits         (spec 3: up to 60 axes)
    cmd   one or two decimal digits, "02" == "2"   (spec 4: two-digit table)
    value decimal ([+-]digits[.digits]) or 0x-hex; kept as text, the plan
          (tcp_bridge.tables.units.parse_value) decides what it means

A garbled line must never move an axis: anything that is not exactly a request
raises :class:`~tcp_bridge.errors.InvalidCommand` carrying the header that
could be recognised, left to right (:func:`recognise_header`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar, Final, Optional, Tuple, Union

from ..errors import InvalidCommand, LineTooLong

MAX_AXIS: Final = 60  # spec 3: "the system supports up to 60 axes"


_REQUEST_RE: Final = re.compile(rb"([0-9]{1,2})([SsRr])([0-9]{1,2})(?:=(.*))?", re.DOTALL)
# The value of a write: decimal with optional sign and fraction, or unsigned
# 0x-hex (command 80 takes "0xXXXXSSLL"). No exponent, no spaces.
NUMBER_RE: Final = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)|0[xX][0-9a-fA-F]+")
_AXIS_HEAD_RE: Final = re.compile(rb"([0-9]{1,2})(?![0-9])")
# A command number is only recognised when followed by "=" or the end of the
# line: "3S0 2=1" could mean command 0 or 2, so it is echoed as "?".
_CMD_HEAD_RE: Final = re.compile(rb"([0-9]{1,2})(?:=|\Z)")

Header = Tuple[Optional[int], Optional[str], Optional[int]]


def _check_header(axis: int, cmd: int) -> None:
    if not 1 <= axis <= MAX_AXIS:
        raise InvalidCommand(f"unknown axis {axis}", axis=axis)
    if not 0 <= cmd <= 99:
        raise InvalidCommand(f"command {cmd} is not 0..99", axis=axis)


@dataclass(frozen=True)
class ReadRequest:
    """``<axis>R<cmd>`` (spec 2.3.1)."""

    axis: int
    cmd: int
    kind: ClassVar[str] = "R"

    def __post_init__(self) -> None:
        _check_header(self.axis, self.cmd)


@dataclass(frozen=True)
class WriteRequest:
    """``<axis>S<cmd>=<value>`` (spec 2.2.1). ``value`` is the text as sent."""

    axis: int
    cmd: int
    value: str
    kind: ClassVar[str] = "S"

    def __post_init__(self) -> None:
        _check_header(self.axis, self.cmd)
        if not NUMBER_RE.fullmatch(self.value):
            raise InvalidCommand(
                f"bad value {self.value!r}: not a decimal or 0x-hex number",
                axis=self.axis, kind="S", cmd=self.cmd,
            )


Request = Union[ReadRequest, WriteRequest]


def recognise_header(line: bytes) -> Header:
    """The ``(axis, kind, cmd)`` recognisable at the start of ``line``, left to right.

    A part is ``None`` when it, or a part before it, cannot be recognised. The
    axis is returned even when out of range, so "99R02" is answered "99 R 2" CAN.
    """
    m = _AXIS_HEAD_RE.match(line)
    if m is None:
        return None, None, None
    axis = int(m[1])
    rest = line[m.end():]
    if rest[:1] not in (b"S", b"s", b"R", b"r"):
        return axis, None, None
    kind = rest[:1].upper().decode("ascii")
    c = _CMD_HEAD_RE.match(rest, 1)
    return axis, kind, (int(c[1]) if c else None)


def parse_request(line: bytes) -> Request:
    """Parse one request line (without its CR); raise :class:`InvalidCommand`.

    Strict on purpose: a garbled line must never move an axis. The raised error
    carries the recognisable header (see :func:`recognise_header`).
    """
    axis, kind, cmd = recognise_header(line)

    def invalid(why: str) -> InvalidCommand:
        return InvalidCommand(f"{why}: {line!r}", axis=axis, kind=kind, cmd=cmd)

    if not line:
        raise invalid("empty request")
    if not line.isascii():
        raise invalid("non-ASCII byte in request")
    m = _REQUEST_RE.fullmatch(line)
    if m is None:
        raise invalid("not <axis>S<cmd>=<value> or <axis>R<cmd>")
    value = m[4]
    if not 1 <= int(m[1]) <= MAX_AXIS:
        raise invalid(f"unknown axis {int(m[1])} (1..{MAX_AXIS})")
    if m[2] in (b"R", b"r"):
        if value is not None:
            raise invalid("a read request carries no value")
        return ReadRequest(int(m[1]), int(m[3]))
    if value is None:
        raise invalid("a write request needs =<value>")
    text = value.decode("ascii")
    if not NUMBER_RE.fullmatch(text):
        raise invalid(f"bad value {text!r}: not a decimal or 0x-hex number")
    return WriteRequest(int(m[1]), int(m[3]), text)


def format_request(request: Request) -> bytes:
    """Encode a request as in spec 2.2.1 / 2.3.1, command with two digits ("3S02=12")."""
    if isinstance(request, WriteRequest):
        return f"{request.axis}S{request.cmd:02d}={request.value}\r".encode("ascii")
    return f"{request.axis}R{request.cmd:02d}\r".encode("ascii")


Line = Union[bytes, LineTooLong]
"""An item of :meth:`~tcp_bridge.wire.lines.LineSplitter.feed`: a request line, or the
marker of an overlong one."""


# Clients poll the same few lines over and over ("3R10"): a request is immutable,
# so the parse of a line is kept. Bounded; a line that fails is never kept (an
# exception is not cached), so junk costs a parse each time and no memory.
_parse_known = lru_cache(maxsize=512)(parse_request)


def parse_item(item: Line) -> Request:
    """:func:`parse_request` for a splitter item; a :class:`LineTooLong` is raised."""
    if isinstance(item, LineTooLong):
        raise item
    return _parse_known(item)

