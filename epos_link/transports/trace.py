"""Record any transport's traffic in the capture format of :mod:`epos_link.capture`.

pyserial's ``spy://`` is the model: a wrapper that logs each write and each
non-empty read as it happens, here one ``TX``/``RX`` line per call with the
time since the wrapper was made (``time.monotonic``). The file replays with
``replay://FILE`` and decodes with ``epos-link decode FILE``.

Bytes discarded by ``reset_input`` never reach the host, so they are not in
the trace; a failed write or read and a reopen leave a ``#`` comment.
"""
from __future__ import annotations

import threading
import time
from typing import IO, Callable, Iterable, Optional

from ..capture import CaptureWriter, Direction
from ..errors import TransportError
from .base import Transport


class TracingTransport(Transport):
    """Wraps ``inner`` and writes its traffic to ``stream``."""

    def __init__(self, inner: Transport, stream: IO[str], *, comments: Iterable[str] = (),
                 close_stream: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.inner = inner
        self.url = inner.url
        self._stream = stream
        self._close_stream = close_stream
        self._clock = clock
        self._start = clock()
        self._lock = threading.Lock()  # several threads may share a transport
        self._writer = CaptureWriter(stream, comments=comments)

    def _now(self) -> float:
        return self._clock() - self._start

    def _record(self, direction: Direction, data: bytes) -> None:
        with self._lock:
            self._writer.write(self._now(), direction, data)

    def _comment(self, text: str) -> None:
        with self._lock:
            self._writer.comment(f"{self._now():.6f} {text}")

    def write(self, data: bytes) -> None:
        try:
            self.inner.write(data)
        except TransportError as exc:
            self._comment(f"TX failed ({exc}): {bytes(data).hex(' ').upper()}")
            raise
        self._record(Direction.TX, data)

    def read(self, max_bytes: int, timeout: float) -> bytes:
        return self.read_some(max_bytes, timeout)

    def read_some(self, max_bytes: int, timeout: float, wanted: int = 1) -> bytes:
        try:
            data = self.inner.read_some(max_bytes, timeout, wanted)
        except TransportError as exc:
            self._comment(f"RX failed: {exc}")
            raise
        if data:
            self._record(Direction.RX, data)
        return data

    def reset_input(self) -> None:
        self.inner.reset_input()

    def reopen(self) -> None:
        self.inner.reopen()
        self._comment("link reopened")

    def close(self) -> None:
        try:
            self.inner.close()
        finally:
            if self._close_stream and not self._stream.closed:
                self._stream.close()


def trace_to_file(inner: Transport, path: str, *, comments: Optional[Iterable[str]] = None) -> TracingTransport:
    """Wrap ``inner`` so its traffic goes to the capture file ``path`` (overwritten)."""
    try:
        stream = open(path, "w", encoding="utf-8")
    except OSError as exc:
        raise TransportError(f"cannot write trace {path}: {exc}") from exc
    header = [f"source: epos-link trace of {inner.url}, recorded "
              f"{time.strftime('%Y-%m-%d %H:%M:%S')}"]
    return TracingTransport(inner, stream, comments=[*header, *(comments or ())], close_stream=True)


__all__ = ["TracingTransport", "trace_to_file"]
