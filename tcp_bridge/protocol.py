"""The wire protocol of the PSI TCP-IP to CANopen gateway (rev 2.3), without I/O.

Requests, client -> gateway (spec 2.2.1 and 2.3.1)::

    write:  <axis> S|s <cmd> = <value> CR     33 53 30 32 3D 31 32 0D   "3S02=12"
    read:   <axis> R|r <cmd> CR               33 52 30 32 0D            "3R02"

    axis  1..60, one or two decimal digits         (spec 3: up to 60 axes)
    cmd   one or two decimal digits, "02" == "2"   (spec 4: two-digit table)
    value decimal ([+-]digits[.digits]) or 0x-hex; kept as text, the command
          layer (tcp_bridge.units.parse_value) decides what it means

Replies, gateway -> client, always exactly 30 bytes (spec 2.2.2 and 2.3.2)::

    +------+----+-----+----+-----+----------+--------+----+------------+
    | axis | SP | S/R | SP | cmd | [=value] | status | CR | NUL ... 30 |
    +------+----+-----+----+-----+----------+--------+----+------------+
    "3 S 2"      ACK CR + 23 NUL   33 20 53 20 32 06 0D 00 ...   (2.2.2)
    "3 R 2=12.8" ACK CR + 18 NUL   33 20 52 20 32 3D 31 32 2E 38 06 0D 00 ...
    status: ACK 0x06 executed, NAK 0x15 not executed, CAN 0x18 not valid

The command number is echoed without leading zeros, as in the byte tables of
2.2.2 and 2.3.2 (the prose example "3 S 02" disagrees; the tables are exact,
and :func:`decode_reply` accepts both).

Invalid requests are answered CAN with whatever header could be recognised,
left to right; a part that could not be recognised is echoed as ``?``. The spec
has no rule for this case, and a client waiting for one reply per request must
get one, so a wholly unrecognisable line is answered ``"? ? ?"<CAN><CR>``.
Empty lines are not answered at all (see :class:`LineSplitter`).
"""
from __future__ import annotations

import math
import re
from functools import lru_cache
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Context, Decimal
from enum import IntEnum
from typing import ClassVar, Final, Optional, Tuple, Union

from .errors import InvalidCommand, LineTooLong, MalformedReply, ReplyOverflow

REPLY_SIZE: Final = 30  # spec 2.2.2: "The MasterMACS returns always data of 30 bytes"
MAX_AXIS: Final = 60  # spec 3: "the system supports up to 60 axes"
DEFAULT_MAX_LINE: Final = 64
CR: Final = 0x0D
# Longest reply header "60 R 99=" (8) plus status and CR (2): the value budget
# that fits every axis and command.
MAX_VALUE_LEN: Final = REPLY_SIZE - 8 - 2


class Status(IntEnum):
    """The status byte closing every reply (spec 2.2.2)."""

    ACK = 0x06  # executed (for a read, a returned value also means ACK, 2.3.2)
    NAK = 0x15  # not executed: the drive did not answer
    CAN = 0x18  # the command is not valid / not permitted


# --- requests ----------------------------------------------------------------

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


# --- line splitting ----------------------------------------------------------

Line = Union[bytes, LineTooLong]
"""An item of :meth:`LineSplitter.feed`: a request line, or the marker of an overlong one."""

_TERMINATOR_RE: Final = re.compile(rb"[\r\n]")


class LineSplitter:
    """Cut a TCP byte stream into request lines; bounded memory, no I/O.

    ``feed(data)`` returns the items completed by ``data``, in stream order:
    ``bytes`` (a line, terminator removed) or a :class:`LineTooLong` instance.
    Recovery cases, each giving exactly one item so the caller sends exactly
    one reply:

    * CR ends a request (spec 2.2.1). A bare LF also ends one (tolerant clients),
      so CRLF and LFCR are a terminator plus an empty line, which is dropped:
    * Empty lines are dropped: they carry no header to answer, and answering
      them would shift every following reply of a CRLF client by one.
    * NUL bytes at the start of a line are dropped: spec 2.2.1 allows a
      fixed-size telegram padded with 0x00 after the CR. NUL inside a line is
      kept, so the line is rejected by :func:`parse_request`.
    * A line longer than ``max_line`` bytes yields one :class:`LineTooLong`
      as soon as the limit is passed; its bytes are dropped up to the next
      CR or LF, and splitting resumes after it.
    """

    def __init__(self, max_line: int = DEFAULT_MAX_LINE) -> None:
        # The longest header "60S99=" must fit, so a LineTooLong can echo it.
        if max_line < 8:
            raise ValueError(f"max_line must be at least 8, not {max_line}")
        self.max_line = max_line
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> list[Line]:
        data = bytes(data)
        if (data[-1:] == b"\r" and not self._buf and not self._discarding
                and 1 < len(data) <= self.max_line + 1 and data.find(b"\r") == len(data) - 1
                and b"\n" not in data and data[0] != 0):
            return [data[:-1]]  # one whole request, the usual case: what the loop below gives
        items: list[Line] = []
        start = 0
        for m in _TERMINATOR_RE.finditer(data):
            self._take(data[start:m.start()], items)
            if not self._discarding and self._buf:
                items.append(bytes(self._buf))
            self._buf.clear()
            self._discarding = False
            start = m.end()
        self._take(data[start:], items)
        return items

    def _take(self, piece: bytes, items: list[Line]) -> None:
        if self._discarding:
            return
        if not self._buf:
            piece = piece.lstrip(b"\x00")
        self._buf += piece[: self.max_line + 1 - len(self._buf)]  # never hold more
        if len(self._buf) > self.max_line:
            head = bytes(self._buf[: self.max_line])
            axis, kind, cmd = recognise_header(head)
            items.append(LineTooLong(
                f"request longer than {self.max_line} bytes: {head[:16]!r}...",
                head=head, limit=self.max_line, axis=axis, kind=kind, cmd=cmd,
            ))
            self._buf.clear()
            self._discarding = True


# Clients poll the same few lines over and over ("3R10"): a request is immutable,
# so the parse of a line is kept. Bounded; a line that fails is never kept (an
# exception is not cached), so junk costs a parse each time and no memory.
_parse_known = lru_cache(maxsize=512)(parse_request)


def parse_item(item: Line) -> Request:
    """:func:`parse_request` for a splitter item; a :class:`LineTooLong` is raised."""
    if isinstance(item, LineTooLong):
        raise item
    return _parse_known(item)


# --- replies -----------------------------------------------------------------

_REPLY_RE: Final = re.compile(
    rb"([0-9]{1,2}|\?) ([SsRr?]) ([0-9]{1,2}|\?)(?:=([\x20-\x7e]+))?([\x06\x15\x18])\r"
)
_DECIMAL_CONTEXT: Final = Context(prec=200)  # wide enough for any quantize below
_ACK_CR: Final = bytes((Status.ACK, CR))  # how a read's reply ends (spec 2.3.2)


@dataclass(frozen=True)
class Reply:
    """One 30-byte reply (spec 2.2.2 / 2.3.2). ``None`` header parts print as ``?``.

    ``value`` is the text after ``=``; it only exists in an ACK to a read.
    """

    axis: Optional[int]
    kind: Optional[str]
    cmd: Optional[int]
    status: Status
    value: Optional[str] = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", Status(self.status))
        header = (self.axis, self.kind, self.cmd)
        if None in header and self.status is Status.ACK:
            raise ValueError("an ACK reply needs a complete header")
        if (self.kind is None and self.cmd is not None) or (
            self.axis is None and self.kind is not None
        ):
            raise ValueError(f"header parts are recognised left to right: {header}")
        for part in (self.axis, self.cmd):
            if part is not None and not 0 <= part <= 99:
                raise ValueError(f"axis and command are 0..99, not {part}")
        if self.kind not in (None, "S", "R"):
            raise ValueError(f"kind must be 'S' or 'R', not {self.kind!r}")
        if self.value is not None:
            if self.kind != "R" or self.status is not Status.ACK:
                raise ValueError("only an ACK to a read carries a value (spec 2.3.2)")
            if not self.value or not all(0x20 <= ord(c) <= 0x7E for c in self.value):
                raise ValueError(f"value must be printable ASCII: {self.value!r}")
        if len(self._body()) + 2 > REPLY_SIZE:
            raise ReplyOverflow(f"reply {self._body()!r} longer than {REPLY_SIZE} bytes")

    def _body(self) -> str:
        parts = ("?" if p is None else str(p) for p in (self.axis, self.kind, self.cmd))
        body = " ".join(parts)
        return body if self.value is None else f"{body}={self.value}"

    def encode(self) -> bytes:
        raw = self._body().encode("ascii") + bytes((self.status, CR))
        return raw.ljust(REPLY_SIZE, b"\x00")


def format_value(value: Union[int, float], max_len: int = MAX_VALUE_LEN) -> str:
    """Decimal text of ``value`` in at most ``max_len`` characters, never an exponent.

    Integers print as integers. Floats print with at most 15 significant digits
    (what a double holds exactly, so 0.1 + 0.2 prints "0.3") and no needless
    zeros: 12.0 -> "12", 1e-7 -> "0.0000001". When too long, fraction digits are
    rounded away; an integer part that does not fit raises :class:`ReplyOverflow`.
    """
    if isinstance(value, bool) or isinstance(value, int):
        text = str(int(value))
        if len(text) > max_len:
            raise ReplyOverflow(f"{text} has more than {max_len} characters")
        return text
    if not math.isfinite(value):
        raise ReplyOverflow(f"{value!r} has no decimal form")
    d = Decimal(format(value, ".15g"))
    if len(_plain(d.to_integral_value(context=_DECIMAL_CONTEXT))) > max_len:
        raise ReplyOverflow(f"integer part of {value!r} has more than {max_len} characters")
    exponent = d.as_tuple().exponent
    assert isinstance(exponent, int)  # finite, checked above
    for places in range(min(max_len, max(0, -exponent)), -1, -1):
        q = d.quantize(Decimal(1).scaleb(-places), ROUND_HALF_EVEN, _DECIMAL_CONTEXT)
        text = _plain(q)
        if len(text) <= max_len:
            return text
    raise ReplyOverflow(f"{value!r} does not fit into {max_len} characters")


def _plain(d: Decimal) -> str:
    text = format(d, "f")
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def format_write_reply(axis: int, cmd: int, status: Status) -> bytes:
    """``"<axis> S <cmd>"`` + status + CR, NUL-padded to 30 bytes (spec 2.2.2)."""
    return Reply(axis, "S", cmd, status).encode()


def format_read_status(axis: int, cmd: int, status: Status) -> bytes:
    """``"<axis> R <cmd>"`` + status + CR: a read answered without value (spec 2.3.2)."""
    return Reply(axis, "R", cmd, status).encode()


def format_read_reply(axis: int, cmd: int, value: Union[int, float, str]) -> bytes:
    """``"<axis> R <cmd>=<value>"`` + ACK + CR (spec 2.3.2); floats via :func:`format_value`.

    The value gets whatever room this header leaves in the 30 bytes.
    """
    if type(value) is int and 0 <= axis <= 99 and 0 <= cmd <= 99:
        # The status poll's path (issue 10: it runs between one answer and the next
        # request on the bus): the bytes Reply would make, without its checks, which
        # an int and a valid header cannot fail except by length.
        raw = f"{axis} R {cmd}={value}".encode("ascii") + _ACK_CR
        if len(raw) <= REPLY_SIZE:
            return raw.ljust(REPLY_SIZE, b"\x00")
    if type(value) is float:
        return _float_read_reply(axis, cmd, value)
    return _read_reply(axis, cmd, value)


def _read_reply(axis: int, cmd: int, value: Union[int, float, str]) -> bytes:
    if not isinstance(value, str):
        room = REPLY_SIZE - len(f"{axis} R {cmd}=") - 2
        value = format_value(value, room)
    return Reply(axis, "R", cmd, Status.ACK, value).encode()


# A position or velocity polled at rest is the same float poll after poll, and its
# decimal text costs ~10 us: the replies are kept (bounded; a failure is not kept).
_float_read_reply = lru_cache(maxsize=1024)(_read_reply)


def format_status_reply(request: Request, status: Status) -> bytes:
    """The value-less reply to ``request`` with ``status``."""
    return Reply(request.axis, request.kind, request.cmd, status).encode()


def status_for(exc: BaseException) -> Status:
    """CAN for :class:`InvalidCommand` (the command is not valid), NAK for any other failure."""
    return Status.CAN if isinstance(exc, InvalidCommand) else Status.NAK


def format_error_reply(exc: BaseException, request: Optional[Request] = None) -> bytes:
    """The one reply for a failed request: status from :func:`status_for`, header
    from ``request`` if it was parsed, else from what ``exc`` recognised."""
    status = status_for(exc)
    if request is not None:
        return format_status_reply(request, status)
    if isinstance(exc, InvalidCommand):
        return Reply(exc.axis, exc.kind, exc.cmd, status).encode()
    return Reply(None, None, None, status).encode()


def decode_reply(data: bytes) -> Reply:
    """Decode one 30-byte reply; raise :class:`MalformedReply` unless it is exact.

    Tolerated, because the spec shows them: a two-digit command ("3 S 02", 2.2.2
    prose) and a lower-case kind echoed from an "s"/"r" request.
    """
    data = bytes(data)
    if len(data) != REPLY_SIZE:
        raise MalformedReply(f"a reply is {REPLY_SIZE} bytes, not {len(data)}: {data!r}")
    end = data.find(b"\r") + 1
    if end == 0 or data[end:].strip(b"\x00"):
        raise MalformedReply(f"reply not closed by CR and NUL padding: {data!r}")
    m = _REPLY_RE.fullmatch(data, 0, end)
    if m is None:
        raise MalformedReply(f"not '<axis> <S|R> <cmd>[=value]<status><CR>': {data!r}")
    axis, kind, cmd, value, status = m.groups()
    try:
        return Reply(
            None if axis == b"?" else int(axis),
            None if kind == b"?" else kind.decode("ascii").upper(),
            None if cmd == b"?" else int(cmd),
            Status(status[0]),
            None if value is None else value.decode("ascii"),
        )
    except ValueError as exc:  # includes ReplyOverflow, which cannot happen at 30 bytes
        raise MalformedReply(f"{exc}: {data!r}") from exc
