"""Pure state machines of the segmented transfers (guide 2.1.1.2, 2.1.1.3, 2.1.2.2, 2.1.2.3).

No I/O, no clocks: a machine hands out the next request and consumes the
decoded answer, so the client (the only place with time and retries) drives it
and a test can drive it with hand-written answers. A machine is single use: a
transfer that fails part-way is restarted from the beginning with a new
machine, never resumed, because the device's toggle state is unknown after a
lost answer.

Segmented read::

    host                                    device
    InitiateSegmentedRead(node, idx, sub) ->
                                          <- error, object length, Length, first bytes
                                             (Length may be 0: all data come by SegmentRead)
    SegmentRead(toggle=0)                 ->
                                          <- error, Length, Control(toggle=0, last), bytes
    SegmentRead(toggle=1)                 ->
                                          <- ...                until the last-segment bit

Segmented write (not forwarded by the gateway, guide 2.1.2.2)::

    InitiateSegmentedWrite(node, idx, sub, length) ->
                                          <- error
    SegmentWrite(bytes, toggle=0, last)   ->
                                          <- error, Length written, Control(toggle=0)
    SegmentWrite(bytes, toggle=1, last)   -> ...                until last was sent

The toggle bit starts at 0 and alternates on every segment; the answer echoes
it (CiA 301 segment protocol, which the gateway maps to). Errors:

* a non-zero error code in any answer     -> :class:`DeviceError` (final state)
* an answer whose toggle bit is wrong     -> :class:`ToggleBitError`
* more bytes than announced, the last bit before all announced bytes, an empty
  segment without the last bit, a Length written that is not the segment's
  length                                  -> :class:`SegmentLengthError`

Both are :class:`RemoteProtocolError`: the peer broke the protocol, so the
client may restart the whole transfer.
"""
from __future__ import annotations

from enum import IntEnum
from typing import Optional, Union

from .codes import MAX_SEGMENT
from .errors import DeviceError, LocalProtocolError, RemoteProtocolError
from .messages import (
    InitiateSegmentedRead,
    InitiateSegmentedReadAnswer,
    InitiateSegmentedWrite,
    SegmentRead,
    SegmentReadAnswer,
    SegmentWrite,
    SegmentWriteAnswer,
    StatusAnswer,
)

DEFAULT_MAX_LENGTH = 16 * 1024 * 1024
"""Largest object a segmented read accepts unless told otherwise (memory stays bounded)."""


class ToggleBitError(RemoteProtocolError):
    """A segment answer whose toggle bit is not the one of the request (guide 2.1.1.3, 2.1.2.3)."""


class SegmentLengthError(RemoteProtocolError):
    """Segment lengths that do not add up to the announced object length."""


class TransferState(IntEnum):
    """Where a transfer is; states are data, the transitions live in ``receive``."""

    IDLE = 0        # start() not called yet
    INITIATING = 1  # the Initiate request is out
    SEGMENTS = 2    # segment requests are going out
    DONE = 3
    FAILED = 4


ReadAnswer = Union[InitiateSegmentedReadAnswer, SegmentReadAnswer]
WriteAnswer = Union[StatusAnswer, SegmentWriteAnswer]


def _check_address(node: int, index: int, subindex: int) -> None:
    # Building the Initiate request validates the ranges; do it up front so a
    # bad address fails at construction, not at start().
    InitiateSegmentedRead(node, index, subindex)


class _Transfer:
    """What both directions share: the state and the outstanding request."""

    def __init__(self, node: int, index: int, subindex: int) -> None:
        _check_address(node, index, subindex)
        self.node = node
        self.index = index
        self.subindex = subindex
        self.state = TransferState.IDLE
        self.segments = 0  # segment exchanges completed, for diagnostics
        self._toggle = False

    @property
    def done(self) -> bool:
        return self.state is TransferState.DONE

    def where(self) -> str:
        """The address of the transfer, for messages."""
        return f"node {self.node} 0x{self.index:04X}/0x{self.subindex:02X}"

    def _start(self) -> None:
        if self.state is not TransferState.IDLE:
            raise LocalProtocolError("a transfer machine is single use: start() was already called")
        self.state = TransferState.INITIATING

    def _expect(self, answer: object, cls: type) -> None:
        if self.state not in (TransferState.INITIATING, TransferState.SEGMENTS):
            raise LocalProtocolError(f"no answer expected in state {self.state.name}")
        if not isinstance(answer, cls):
            raise LocalProtocolError(
                f"expected {cls.__name__} in state {self.state.name}, got {type(answer).__name__}")
        code = answer.error_code  # type: ignore[attr-defined]
        if code:
            self.state = TransferState.FAILED
            raise DeviceError(code, self.where())

    def _fail(self, exc: RemoteProtocolError) -> RemoteProtocolError:
        self.state = TransferState.FAILED
        return exc


class SegmentedRead(_Transfer):
    """InitiateSegmentedRead, then SegmentRead until the last-segment bit.

    ``object_length`` 0 in the Initiate answer with no bytes means an empty
    object: the transfer ends there. Objects announced larger than
    ``max_length`` are refused before any segment is read.
    """

    def __init__(self, node: int, index: int, subindex: int, *,
                 max_length: int = DEFAULT_MAX_LENGTH) -> None:
        super().__init__(node, index, subindex)
        self.max_length = max_length
        self.object_length: Optional[int] = None
        self._data = bytearray()

    @property
    def data(self) -> bytes:
        if self.state is not TransferState.DONE:
            raise LocalProtocolError(f"the read is not complete (state {self.state.name})")
        return bytes(self._data)

    def start(self) -> InitiateSegmentedRead:
        self._start()
        return InitiateSegmentedRead(self.node, self.index, self.subindex)

    def receive(self, answer: ReadAnswer) -> Optional[SegmentRead]:
        """Consume the answer to the last request; the next request, or None when done."""
        if self.state is TransferState.INITIATING:
            self._expect(answer, InitiateSegmentedReadAnswer)
            assert isinstance(answer, InitiateSegmentedReadAnswer)
            return self._initiated(answer)
        self._expect(answer, SegmentReadAnswer)
        assert isinstance(answer, SegmentReadAnswer)
        return self._segment(answer)

    def _initiated(self, answer: InitiateSegmentedReadAnswer) -> Optional[SegmentRead]:
        total = answer.object_length
        if total > self.max_length:
            self.state = TransferState.FAILED
            raise LocalProtocolError(
                f"{self.where()}: object of {total} bytes exceeds max_length {self.max_length}")
        self.object_length = total
        # The guide's answer may already carry the first chunk (Length > 0).
        self._data += answer.data
        if len(self._data) > total:
            raise self._fail(SegmentLengthError(
                f"{self.where()}: first answer carries {len(self._data)} bytes of a "
                f"{total}-byte object", answer.data))
        if len(self._data) == total:
            self.state = TransferState.DONE
            return None
        self.state = TransferState.SEGMENTS
        return SegmentRead(self._toggle)

    def _segment(self, answer: SegmentReadAnswer) -> Optional[SegmentRead]:
        if answer.toggle != self._toggle:
            raise self._fail(ToggleBitError(
                f"{self.where()}: segment {self.segments} answered with toggle "
                f"{int(answer.toggle)}, expected {int(self._toggle)}"))
        total = self.object_length
        assert total is not None
        self._data += answer.data
        self.segments += 1
        got = len(self._data)
        if got > total:
            raise self._fail(SegmentLengthError(
                f"{self.where()}: {got} bytes received of a {total}-byte object", answer.data))
        if answer.last:
            if got != total:
                raise self._fail(SegmentLengthError(
                    f"{self.where()}: last segment after {got} of {total} bytes", answer.data))
            self.state = TransferState.DONE
            return None
        if not answer.data:
            # Each segment must make progress, or a broken device could keep us
            # reading forever.
            raise self._fail(SegmentLengthError(
                f"{self.where()}: empty segment without the last-segment bit"))
        self._toggle = not self._toggle
        return SegmentRead(self._toggle)


class SegmentedWrite(_Transfer):
    """InitiateSegmentedWrite with the total length, then SegmentWrite until the last bit.

    ``segment_size`` is the data bytes per SegmentWrite, 1..255 (guide 2.1.2.3:
    "Length (max. 255 bytes)"). An empty ``data`` sends one empty last segment.
    """

    def __init__(self, node: int, index: int, subindex: int, data: bytes, *,
                 segment_size: int = MAX_SEGMENT) -> None:
        super().__init__(node, index, subindex)
        if not 1 <= segment_size <= MAX_SEGMENT:
            raise LocalProtocolError(f"segment_size must be 1..{MAX_SEGMENT}, got {segment_size!r}")
        self.data = bytes(data)
        self.segment_size = segment_size
        self._offset = 0        # bytes acknowledged so far
        self._sent: Optional[SegmentWrite] = None

    @property
    def written(self) -> int:
        """Bytes the device has acknowledged."""
        return self._offset

    def start(self) -> InitiateSegmentedWrite:
        self._start()
        return InitiateSegmentedWrite(self.node, self.index, self.subindex, length=len(self.data))

    def receive(self, answer: WriteAnswer) -> Optional[SegmentWrite]:
        """Consume the answer to the last request; the next request, or None when done."""
        if self.state is TransferState.INITIATING:
            self._expect(answer, StatusAnswer)
            self.state = TransferState.SEGMENTS
            return self._next_segment()
        self._expect(answer, SegmentWriteAnswer)
        assert isinstance(answer, SegmentWriteAnswer) and self._sent is not None
        sent = self._sent
        if answer.toggle != sent.toggle:
            raise self._fail(ToggleBitError(
                f"{self.where()}: segment {self.segments} acknowledged with toggle "
                f"{int(answer.toggle)}, expected {int(sent.toggle)}"))
        if answer.length_written != len(sent.data):
            raise self._fail(SegmentLengthError(
                f"{self.where()}: device wrote {answer.length_written} of the "
                f"{len(sent.data)} bytes of segment {self.segments}"))
        self._offset += len(sent.data)
        self.segments += 1
        if sent.last:
            self.state = TransferState.DONE
            return None
        self._toggle = not self._toggle
        return self._next_segment()

    def _next_segment(self) -> SegmentWrite:
        chunk = self.data[self._offset:self._offset + self.segment_size]
        last = self._offset + len(chunk) >= len(self.data)
        self._sent = SegmentWrite(chunk, self._toggle, last)
        return self._sent


__all__ = [
    "DEFAULT_MAX_LENGTH", "SegmentLengthError", "SegmentedRead", "SegmentedWrite",
    "ToggleBitError", "TransferState",
]
