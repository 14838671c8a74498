"""A transport that plays a recorded conversation as the device.

``replay://path/to/capture.txt`` (format of :mod:`epos_link.capture`). The
records are a script, walked in order:

* the host's writes must match the ``TX`` bytes exactly (record boundaries do
  not matter, the bytes do); anything else raises :class:`ReplayMismatchError`
  at once, naming the record and both byte strings;
* ``RX`` records become readable once every ``TX`` byte before them has been
  written; a read returns at most the rest of one record, so a record split
  over several lines models a reply that arrives in pieces;
* when the next record is ``TX`` (the device waits) or the script has ended,
  the device is silent and reads time out;
* ``reset_input`` discards ``RX`` records that are readable and not yet read,
  as a real port discards stale input.

Recorded times are ignored: replies are available as soon as they are due.
:class:`ReplayMismatchError` is an ``AssertionError``, not a communication
error, so a client never retries it away.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Optional

from ..capture import Capture, Direction, Record, read_capture
from ..errors import EposError, TransportError
from .base import Transport


class ReplayMismatchError(EposError, AssertionError):
    """The host did not send what the recording says it sent."""


def _hex(data: bytes) -> str:
    return data.hex(" ").upper() or "(nothing)"


class ReplayTransport(Transport):
    """Plays ``capture`` as the device; see the module docstring for the rules."""

    def __init__(self, capture: Capture, *, url: str = "replay://") -> None:
        self.url = url
        self._records: list[Record] = [r for r in capture.records if r.data]
        self._pos = 0     # the current record
        self._offset = 0  # bytes of it already consumed
        self._cond = threading.Condition()
        self._closed = False

    @property
    def at_end(self) -> bool:
        """True when every record has been played."""
        return self._pos >= len(self._records)

    def remaining(self) -> list[Record]:
        """Records not (completely) played yet."""
        return self._records[self._pos:]

    def check_complete(self) -> None:
        """Raise :class:`ReplayMismatchError` unless the whole script was played."""
        if not self.at_end:
            rec = self._records[self._pos]
            raise ReplayMismatchError(
                f"{self.url}: record {self._pos + 1} of {len(self._records)} not played: "
                f"{rec.direction.value} {_hex(rec.data[self._offset:])}")

    def _current(self) -> Optional[Record]:
        return self._records[self._pos] if self._pos < len(self._records) else None

    def _advance(self, count: int) -> None:
        self._offset += count
        if self._offset >= len(self._records[self._pos].data):
            self._pos += 1
            self._offset = 0

    def write(self, data: bytes) -> None:
        with self._cond:
            if self._closed:
                raise TransportError(f"{self.url} is closed")
            sent = 0
            while sent < len(data):
                rec = self._current()
                rest = bytes(data[sent:])
                if rec is None:
                    raise ReplayMismatchError(
                        f"{self.url}: host sent {_hex(rest)} after the end of the recording")
                if rec.direction is Direction.RX:
                    raise ReplayMismatchError(
                        f"{self.url}: host sent {_hex(rest)} while record {self._pos + 1} has the "
                        f"device send {_hex(rec.data[self._offset:])}")
                expected = rec.data[self._offset:]
                count = min(len(expected), len(rest))
                if rest[:count] != expected[:count]:
                    raise ReplayMismatchError(
                        f"{self.url}: record {self._pos + 1} expects the host to send "
                        f"{_hex(expected)}, host sent {_hex(rest)}")
                self._advance(count)
                sent += count
            self._cond.notify_all()

    def read(self, max_bytes: int, timeout: float) -> bytes:
        deadline = time.monotonic() + max(timeout, 0.0)
        with self._cond:
            while True:
                if self._closed:
                    raise TransportError(f"{self.url} is closed")
                rec = self._current()
                if rec is not None and rec.direction is Direction.RX:
                    chunk = rec.data[self._offset:self._offset + max_bytes]
                    self._advance(len(chunk))
                    return chunk
                left = deadline - time.monotonic()
                if left <= 0:
                    return b""
                self._cond.wait(left)

    def reset_input(self) -> None:
        with self._cond:
            while (rec := self._current()) is not None and rec.direction is Direction.RX:
                self._advance(len(rec.data) - self._offset)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def reopen(self) -> None:
        with self._cond:
            self._closed = False


def open_replay(url: str, **_options: Any) -> ReplayTransport:
    """``replay://PATH``: PATH relative to the working directory, or absolute (``replay:///abs``).

    Link options such as ``baudrate`` mean nothing to a recording and are ignored.
    """
    path = url.split("://", 1)[1] if "://" in url else url
    if not path:
        raise TransportError("replay:// needs a capture file: replay://path/to/capture.txt")
    try:
        with open(path, encoding="utf-8") as fh:
            capture = read_capture(fh)
    except (OSError, UnicodeDecodeError) as exc:
        raise TransportError(f"cannot open {url}: {exc}") from exc
    return ReplayTransport(capture, url=url)


__all__ = ["ReplayMismatchError", "ReplayTransport", "open_replay"]
