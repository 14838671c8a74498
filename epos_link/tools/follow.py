"""Lines of text as they arrive: a growing file (``tail -F``) or a pipe.

Both sources are generators of complete lines (without the newline); a last
line without a newline is given when the input ends. Every wait is bounded:

* :func:`follow_file` polls the file every ``poll`` seconds once it has read
  all there is, and ends after ``idle_exit`` seconds without growth (never,
  when None: the caller stops it, Ctrl-C). A file that shrinks was truncated
  or replaced: the generator yields :data:`RESTART` and reads it from the start.
* :func:`stream_lines` reads a file descriptor with ``select`` and a timeout,
  so it returns each line as soon as its newline arrives, ends at end of
  input, and after ``idle_exit`` seconds of silence when that is set.

Lines longer than ``max_line`` characters are cut into pieces of that size
(memory stays bounded on input that has no newlines). ``clock`` and ``sleep``
can be replaced, so tests need no real waiting.
"""
from __future__ import annotations

import os
import select
import time
from typing import Callable, Iterator, Optional, Union

from ..capture import MAX_LINE

RESTART = object()
"""Yielded by :func:`follow_file` when the file was truncated or replaced."""


Line = Union[str, object]


def _split(buf: bytes, max_line: int) -> tuple[list[bytes], bytes]:
    *lines, rest = buf.split(b"\n")
    while len(rest) > max_line:
        lines.append(rest[:max_line])
        rest = rest[max_line:]
    return lines, rest


def _text(line: bytes) -> str:
    return line.decode("utf-8").rstrip("\r")  # UnicodeDecodeError: not a text capture


def follow_file(path: str, *, poll: float = 0.2, idle_exit: Optional[float] = None,
                clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                max_line: int = MAX_LINE) -> Iterator[Line]:
    """The lines of ``path``, then the lines appended to it (see the module doc)."""
    fh = open(path, "rb")
    try:
        buf = b""
        last_growth = clock()
        while True:
            chunk = fh.read(65536)
            if chunk:
                lines, buf = _split(buf + chunk, max_line)
                for line in lines:
                    yield _text(line)
                last_growth = clock()
                continue
            try:
                stat = os.stat(path)
                replaced = stat.st_ino != os.fstat(fh.fileno()).st_ino
            except FileNotFoundError:
                stat, replaced = None, False
            if stat is not None and (replaced or stat.st_size < fh.tell()):
                fh.close()
                fh = open(path, "rb")
                buf = b""
                last_growth = clock()
                yield RESTART
                continue
            if idle_exit is not None and clock() - last_growth >= idle_exit:
                if buf:
                    yield _text(buf)
                return
            sleep(poll)
    finally:
        fh.close()


def stream_lines(fd: int, *, poll: float = 0.2, idle_exit: Optional[float] = None,
                 clock: Callable[[], float] = time.monotonic, max_line: int = MAX_LINE) -> Iterator[str]:
    """The lines read from ``fd`` as they arrive, until end of input (or idle)."""
    buf = b""
    last = clock()
    while True:
        try:
            ready, _, _ = select.select([fd], [], [], poll)
        except (OSError, ValueError):  # not selectable (Windows pipes): plain blocking reads
            ready = [fd]
        if not ready:
            if idle_exit is not None and clock() - last >= idle_exit:
                break
            continue
        data = os.read(fd, 65536)
        if not data:
            break
        last = clock()
        lines, buf = _split(buf + data, max_line)
        for line in lines:
            yield _text(line)
    if buf:
        yield _text(buf)


__all__ = ["RESTART", "follow_file", "stream_lines"]
