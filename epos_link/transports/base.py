"""The transport interface: the only thing the client knows about a link.

A transport moves bytes and nothing else: no framing, no retries. Reads take a
timeout so every wait is bounded; a failed link raises :class:`TransportError`.
"""
from __future__ import annotations

import abc
from types import TracebackType
from typing import Optional, Type


class Transport(abc.ABC):
    """Write bytes; read with a deadline; discard stale input; close."""

    url: str = ""

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of ``data`` or raise TransportError."""

    @abc.abstractmethod
    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Return 1..max_bytes bytes as soon as any are available, or b"" when
        ``timeout`` seconds pass with nothing received."""

    def read_some(self, max_bytes: int, timeout: float, wanted: int = 1) -> bytes:
        """:meth:`read`, knowing that at least ``wanted`` more bytes are due (the
        known rest of a frame). A link that knows its wire speed may wait for
        them instead of waking up for every byte; by default this is :meth:`read`."""
        return self.read(max_bytes, timeout)

    def reset_input(self) -> None:
        """Discard whatever has been received and not yet read."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the link; idempotent."""

    def reopen(self) -> None:
        """Re-establish a link after a TransportError (unplug and replug)."""
        raise NotImplementedError(f"{type(self).__name__} cannot reopen")

    def __enter__(self) -> "Transport":
        return self

    def __exit__(self, exc_type: Optional[Type[BaseException]], exc: Optional[BaseException],
                 tb: Optional[TracebackType]) -> None:
        self.close()
