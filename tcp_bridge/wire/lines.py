"""Line splitting of the TCP byte stream (PSI spec 2.2.1), bounded memory, no I/O."""
from __future__ import annotations

import re
from typing import Final

from ..errors import LineTooLong
from .requests import Line, recognise_header

DEFAULT_MAX_LINE: Final = 64


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

