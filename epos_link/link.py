"""Link: one request at a time over one :class:`Transport`, with its deadline,
retries and late answers. :class:`epos_link.client.EposClient` builds on it.

This module and :mod:`epos_link.client` are the only places with clocks, retries
and locks; framing, messages and the segmented-transfer state machines are pure.

Exchanges (guide 2.2.1: the EPOS4 is a slave and answers every request, one at
a time):

* one request in flight per client: a lock covers a whole call, retries and
  every segment of a segmented transfer included, so threads sharing a client
  never interleave frames;
* before each request the transport's stale input is discarded;
* each request has its own deadline, by default the device's 500 ms frame
  timeout (guide 2.2.7, objects 0x2005/0x2006).

Errors and retries:

* communication errors (:class:`RemoteProtocolError`, :class:`EposTimeoutError`,
  :class:`TransportError`) and a device answering "CRC error" (0x05040004,
  our request arrived damaged) are retried, ``retries`` times (default 1);
  after a :class:`TransportError` the next attempt first reopens the link;
* a caller may name more device errors to retry (the client's segmented
  transfers add "Toggle error", see :mod:`epos_link.client`);
* any other :class:`DeviceError` and every :class:`LocalProtocolError` are final.

Late answers: answers carry no request id, so an answer that comes after its
request timed out could be taken for the next request's. A request that timed
out in silence (no byte at all came back) leaves the link "out of step": before
the next request the client waits up to ``late_answer_timeout`` (default
500 ms, the device's frame timeout) for that late answer and drops it. A
timeout with garbage received means the answer came and was damaged, so there
is nothing to wait for; its :class:`EposTimeoutError` says so (``heard``), so a
caller can tell a damaged answer from silence. (What that costs a node scan:
see :mod:`epos_link.client`.)
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Callable, Optional, Type, TypeVar, cast

from .codes import ErrorCode, OpCode
from .errors import (
    CrcError,
    DeviceError,
    EposTimeoutError,
    JunkBytesError,
    MessageFormatError,
    RemoteProtocolError,
    TransportError,
    TruncatedFrameError,
)
from .framing import NEED_DATA, Frame, FrameDecoder
from .messages import ReadObjectAnswer
from .transports.base import Transport

# The retry, reopen and late-answer records keep the logger name they had when this
# code was part of epos_link.client, so logging set up for the client still shows them.
_log = logging.getLogger("epos_link.client")
T = TypeVar("T")
L = TypeVar("L", bound="Link")

DEFAULT_TIMEOUT = 0.5  # guide 2.2.7: RS232/USB frame timeout, 500 ms by default
DEFAULT_RETRIES = 1
READ_CHUNK = 4096  # one read takes whatever has arrived, up to a few frames
# The shortest answer frame: DLE STX, op code, length, the 4-byte error code that
# every answer starts with, CRC (guide 2.2.2 frame, 2.1 answers).
MIN_ANSWER_FRAME = 10
# An answer's frame size where the guide fixes it: ReadObject answers Len 4 words,
# error answers included (2.1.1.1; fixtures/client_error_answer.txt). Other answers
# vary (segmented) or are the shortest (10 bytes).
_ANSWER_FRAME: dict[type, int] = {ReadObjectAnswer: 14}
# The first wait for an answer ends this many bytes before its end. A thread that
# slept through the whole exchange (2 ms at 115200 Bd) wakes up slower than one
# that woke just before the last bytes came: status polls (node.sdo.upload in a
# loop) on the simulator in its own process over a pty at 115200 Bd, 427 against
# 438 ReadObject/s (medians of 6 runs of 2 s, waiting for 14 against 12 bytes
# first). An adapter that hands over a whole answer in one USB packet has it all
# at the first wake-up anyway.
WAKE_EARLY = 2

# "CRC error": the device got our request damaged; sending it again is right.
_RETRY_CODES = frozenset({ErrorCode.CRC_ERROR})


@dataclass
class ClientStats:
    """What the link cost: calls made, retries spent, and the errors that caused them."""

    calls: int = 0
    retries: int = 0
    failures: dict[str, int] = field(default_factory=dict)  # error type name -> count

    def failed(self, exc: BaseException) -> None:
        name = type(exc).__name__
        self.failures[name] = self.failures.get(name, 0) + 1


class Link:
    """One request at a time over ``transport``; closing it closes the transport."""

    def __init__(self, transport: Transport, *, timeout: float = DEFAULT_TIMEOUT,
                 retries: int = DEFAULT_RETRIES,
                 late_answer_timeout: float = DEFAULT_TIMEOUT) -> None:
        if timeout <= 0:
            raise ValueError("timeout must be positive")
        if retries < 0:
            raise ValueError("retries must be 0 or more")
        self.transport = transport
        self.timeout = timeout
        self.retries = retries
        self._lock = threading.Lock()
        self._decoder = FrameDecoder()
        self._needs_reopen = False
        self._late_answer_due = False
        self.late_answer_timeout = late_answer_timeout
        self.stats = ClientStats()
        # Called (on the calling thread) each time the client starts to wait on the
        # link: once a request frame has been written (its answer takes at least the
        # request's wire time), and before it waits for a late answer. A caller may
        # use that time (tcp_bridge.bus.workers hands a finished reply to its event loop).
        self.on_wait: Optional[Callable[[], None]] = None

    # --- context and life cycle ----------------------------------------------

    def close(self) -> None:
        self.transport.close()

    def __enter__(self: L) -> L:
        return self

    def __exit__(self, exc_type: Optional[Type[BaseException]], exc: Optional[BaseException],
                 tb: Optional[TracebackType]) -> None:
        self.close()

    # --- one exchange, one call ----------------------------------------------

    def _exchange(self, frame: bytes, answer_type: Any, timeout: float, what: str = "") -> Any:
        """Send one request frame and return its decoded answer; no retries here.

        ``what`` names the request in a timeout message."""
        transport, decoder = self.transport, self._decoder
        on_wait = self.on_wait
        if self._late_answer_due:
            if on_wait is not None:
                on_wait()
            self._swallow_late_answer()
        transport.reset_input()
        decoder.reset()
        transport.write(frame)
        if on_wait is not None:
            on_wait()
        # What to wait for before looking (SerialTransport.read_some): the answer's
        # size where the guide fixes it, and never more than that, since a frame the
        # decoder opened on noise may claim more than the real answer that follows.
        first = _ANSWER_FRAME.get(answer_type, MIN_ANSWER_FRAME) - WAKE_EARLY
        deadline = time.monotonic() + timeout
        read, next_frame, feed = transport.read_some, decoder.next_frame, decoder.feed
        heard = False
        while True:
            try:
                item = next_frame()
            except (JunkBytesError, TruncatedFrameError):
                # Noise before the answer, or a DLE STX in it: the decoder has
                # already resynchronised on the next frame, which may be ours.
                continue
            if item is NEED_DATA:
                left = deadline - time.monotonic()
                if left <= 0:
                    held = decoder.pending
                    # Silence, not garbage: the device may still answer (a gateway
                    # waiting for an absent node's SDO takes its own time).
                    self._late_answer_due = not heard
                    raise EposTimeoutError(
                        f"{what or 'request'}: no answer within {timeout:g} s"
                        + (f" ({held} bytes of an incomplete answer)" if held else ""),
                        heard=heard)
                data = read(READ_CHUNK, left, min(decoder.wanted, first) if heard else first)
                if data:
                    heard = True
                    feed(data)
                continue
            got = cast(Frame, item)
            if got.opcode != OpCode.ANSWER:
                raise MessageFormatError(
                    f"op code 0x{got.opcode:02X} where an answer (0x00) was expected", got.data)
            return answer_type.from_payload(got.data)

    def _swallow_late_answer(self) -> None:
        """Wait (at most ``late_answer_timeout``) for the answer to a request that
        timed out in silence, and drop it.

        The device answers every request (guide 2.2.1) and answers carry no
        request id, so a late answer would otherwise be taken for the next
        request's: after a silent timeout the link is out of step until it comes.
        """
        self._late_answer_due = False
        decoder = self._decoder
        deadline = time.monotonic() + self.late_answer_timeout
        while True:
            try:
                if decoder.next_frame() is not NEED_DATA:
                    _log.debug("dropped a late answer")
                    return
            except (CrcError, TruncatedFrameError, MessageFormatError):
                return  # the late answer came, damaged: the link is in step again
            except RemoteProtocolError:
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                return
            data = self.transport.read(READ_CHUNK, left)
            if data:
                decoder.feed(data)

    def _call(self, op: Callable[[float], T], timeout: Optional[float], retries: Optional[int],
              retry_codes: frozenset[int] = _RETRY_CODES) -> T:
        """Run ``op(timeout)`` under the lock, retrying communication errors."""
        t = self.timeout if timeout is None else timeout
        attempts = 1 + (self.retries if retries is None else retries)
        with self._lock:
            last: Optional[BaseException] = None
            self.stats.calls += 1
            for attempt in range(attempts):
                if attempt:
                    assert last is not None
                    self.stats.retries += 1
                    self.stats.failed(last)
                    _log.debug("retry %d/%d after %s", attempt, attempts - 1, last)
                try:
                    if self._needs_reopen:
                        self._reopen()
                    return op(t)
                except TransportError as exc:
                    self._needs_reopen = True
                    last = exc
                except (RemoteProtocolError, EposTimeoutError) as exc:
                    last = exc
                except DeviceError as exc:
                    if exc.code not in retry_codes:
                        raise
                    last = exc
            assert last is not None
            self.stats.failed(last)
            raise last

    def _reopen(self) -> None:
        try:
            self.transport.reopen()
        except NotImplementedError as exc:
            raise TransportError(f"{self.transport.url}: the link failed and cannot be reopened") from exc
        self._needs_reopen = False
        _log.info("reopened %s", self.transport.url)


__all__ = ["DEFAULT_RETRIES", "DEFAULT_TIMEOUT", "WAKE_EARLY", "ClientStats", "Link"]
