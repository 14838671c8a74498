"""Replies, gateway -> client: always exactly 30 bytes (PSI spec 2.2.2 and 2.3.2).

::

    +------+----+-----+----+-----+----------+--------+----+------------+
    | axis | SP | S/R | SP | cmd | [=value] | status | CR | NUL ... 30 |
    +------+----+-----+----+-----+----------+--------+----+------------+
    "3 S 2"      ACK CR + 23 NUL   33 20 53 20 32 06 0D 00 ...   (2.2.2)
    "3 R 2=12.8" ACK CR + 18 NUL   33 20 52 20 32 3D 31 32 2E 38 06 0D 00 ...
    status: ACK 0x06 executed, NAK 0x15 not executed, CAN 0x18 not valid

The command number is echoed without leading zeros, as in the byte tables of
2.2.2 and 2.3.2 (the prose example "3 S 02" disagrees; the tables are exact,
and :func:`decode_reply` accepts both). A reply is formatted after the outcome
of its request is known (:func:`format_error_reply` is the one reply for a
failure).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Context, Decimal
from enum import IntEnum
from functools import lru_cache
from typing import TYPE_CHECKING, Final, Optional, Union

from ..errors import InvalidCommand, MalformedReply, ReplyOverflow

if TYPE_CHECKING:
    from .requests import Request

REPLY_SIZE: Final = 30  # spec 2.2.2: "The MasterMACS returns always data of 30 bytes"
CR: Final = 0x0D
# Longest reply header "60 R 99=" (8) plus status and CR (2): the value budget
# that fits every axis and command.
MAX_VALUE_LEN: Final = REPLY_SIZE - 8 - 2


class Status(IntEnum):
    """The status byte closing every reply (spec 2.2.2)."""

    ACK = 0x06  # executed (for a read, a returned value also means ACK, 2.3.2)
    NAK = 0x15  # not executed: the drive did not answer
    CAN = 0x18  # the command is not valid / not permitted



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
