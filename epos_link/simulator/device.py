"""The device side of MAXON SERIAL V2, pure: bytes from the host in, answer frames out.

An EPOS4 answers every request with exactly one frame and handles one command at
a time (guide 2.2.1). This class owns the frame decoder, the segmented-transfer
state of both directions and the gateway decision of guide chapter 5 (node 0 or
the device's own id: execute; any other id: forward). Object access is delegated
to an :class:`ObjectAccess`, which raises :class:`Abort` with a CiA 301 code.

Malformed input, per guide 2.2.3.1: a bad CRC is answered with the CRC error
0x05040004 and an unknown op code with 0x0F00FFBF (illegal command). Bytes that
do not form a frame (junk, bad stuffing, cut frames) get no answer: the host
times out, as with the real device.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Protocol

from ..codes import MAX_SEGMENT, ErrorCode
from ..errors import CrcError, MessageFormatError, RemoteProtocolError
from ..framing import NEED_DATA, FrameDecoder
from ..messages import (
    InitiateSegmentedRead,
    InitiateSegmentedReadAnswer,
    InitiateSegmentedWrite,
    Message,
    ReadObject,
    ReadObjectAnswer,
    Request,
    SegmentRead,
    SegmentReadAnswer,
    SegmentWrite,
    SegmentWriteAnswer,
    SendNMTService,
    StatusAnswer,
    WriteObject,
    decode_request,
)


FEED_SLICE = 64 * 1024


class Abort(Exception):
    """An object access failed with a CiA 301 abort code."""

    def __init__(self, code: int) -> None:
        super().__init__(f"0x{code:08X}")
        self.code = code


class ObjectAccess(Protocol):
    """Where requests end up: the local object dictionary or the CAN gateway."""

    def read(self, node: int, index: int, subindex: int) -> bytes: ...

    def write(self, node: int, index: int, subindex: int, data: bytes, *,
              expedited: bool) -> None: ...

    def nmt(self, node: int, command: int) -> None: ...


@dataclass
class _SegmentedRead:
    data: bytes
    offset: int
    toggle: bool  # the toggle bit the next SegmentRead must carry


@dataclass
class _SegmentedWrite:
    node: int
    index: int
    subindex: int
    length: int
    buffer: bytearray
    toggle: bool


def _abort_code(exc: BaseException) -> int:
    code = getattr(exc, "code", None)
    return code if isinstance(code, int) else ErrorCode.GENERAL_ERROR


class DeviceProtocol:
    """Feed host bytes with :meth:`receive`; it returns the answer frames to send."""

    def __init__(self, access: ObjectAccess, *, node_id: int = 1,
                 segment_size: int = MAX_SEGMENT, initiate_carries_data: bool = True,
                 on_error: Optional[Callable[[RemoteProtocolError], None]] = None) -> None:
        if not 1 <= segment_size <= MAX_SEGMENT:
            raise ValueError(f"segment_size must be 1..{MAX_SEGMENT}")
        self.access = access
        self.node_id = node_id
        self.segment_size = segment_size
        # The guide's InitiateSegmentedRead answer has room for a first chunk; a
        # device may also send none and deliver everything by SegmentRead.
        self.initiate_carries_data = initiate_carries_data
        self.on_error = on_error
        self.decoder = FrameDecoder()
        self._read: Optional[_SegmentedRead] = None
        self._write: Optional[_SegmentedWrite] = None
        self.requests = 0

    def reset(self) -> None:
        """Forget partial frames (the device's frame timeout of guide 2.2.7)."""
        self.decoder.reset()

    def receive(self, data: bytes) -> list[bytes]:
        out: list[bytes] = []
        # In slices, answered in between: the decoder bounds what it holds.
        for start in range(0, len(data), FEED_SLICE):
            self.decoder.feed(data[start:start + FEED_SLICE])
            self._answer(out)
        return out

    def _answer(self, out: list[bytes]) -> None:
        while True:
            try:
                frame = self.decoder.next_frame()
            except CrcError as exc:
                self._report(exc)
                out.append(StatusAnswer(ErrorCode.CRC_ERROR).encode())
                continue
            except RemoteProtocolError as exc:
                self._report(exc)
                continue
            if frame is NEED_DATA:
                return
            try:
                request = decode_request(frame)  # type: ignore[arg-type]
            except MessageFormatError as exc:
                self._report(exc)
                out.append(StatusAnswer(ErrorCode.ILLEGAL_COMMAND).encode())
                continue
            out.append(self.handle(request).encode())

    def _report(self, exc: RemoteProtocolError) -> None:
        if self.on_error is not None:
            self.on_error(exc)

    def _local(self, node: int) -> bool:
        return node in (0, self.node_id)

    def handle(self, request: Request) -> Message:
        """The answer to one decoded request."""
        self.requests += 1
        try:
            if isinstance(request, ReadObject):
                data = self.access.read(request.node, request.index, request.subindex)
                return ReadObjectAnswer(0, (data + bytes(4))[:4])
            if isinstance(request, WriteObject):
                self.access.write(request.node, request.index, request.subindex,
                                  request.data, expedited=True)
                return StatusAnswer(0)
            if isinstance(request, InitiateSegmentedRead):
                return self._initiate_read(request)
            if isinstance(request, SegmentRead):
                return self._segment_read(request)
            if isinstance(request, InitiateSegmentedWrite):
                return self._initiate_write(request)
            if isinstance(request, SegmentWrite):
                return self._segment_write(request)
            if isinstance(request, SendNMTService):
                self.access.nmt(request.node, request.command)
                return StatusAnswer(0)
        except Abort as exc:
            return self._error_answer(request, exc.code)
        except Exception as exc:  # an access backend failing must not kill the device
            return self._error_answer(request, _abort_code(exc))
        return StatusAnswer(ErrorCode.ILLEGAL_COMMAND)  # pragma: no cover - all types handled

    @staticmethod
    def _error_answer(request: Request, code: int) -> Message:
        # Answers keep the layout of their request, zero-filled, so a host
        # that reads a fixed Len still parses them.
        if isinstance(request, ReadObject):
            return ReadObjectAnswer(code, bytes(4))
        if isinstance(request, InitiateSegmentedRead):
            return InitiateSegmentedReadAnswer(code)
        if isinstance(request, SegmentRead):
            return SegmentReadAnswer(code)
        if isinstance(request, SegmentWrite):
            return SegmentWriteAnswer(code)
        return StatusAnswer(code)

    def _initiate_read(self, req: InitiateSegmentedRead) -> Message:
        self._read = None
        data = self.access.read(req.node, req.index, req.subindex)
        first = data[:self.segment_size] if self.initiate_carries_data else b""
        self._read = _SegmentedRead(data, len(first), toggle=False)
        return InitiateSegmentedReadAnswer(0, len(data), first)

    def _segment_read(self, req: SegmentRead) -> Message:
        state = self._read
        if state is None:
            raise Abort(ErrorCode.GENERAL_ERROR)  # no segmented read in progress
        if req.toggle != state.toggle:
            self._read = None
            raise Abort(ErrorCode.TOGGLE_ERROR)
        chunk = state.data[state.offset:state.offset + self.segment_size]
        state.offset += len(chunk)
        last = state.offset >= len(state.data)
        answer = SegmentReadAnswer(0, chunk, toggle=state.toggle, last=last)
        state.toggle = not state.toggle
        if last:
            self._read = None
        return answer

    def _initiate_write(self, req: InitiateSegmentedWrite) -> Message:
        self._write = None
        if not self._local(req.node):
            # Guide 2.1.2.2: "Note that gateway communication is not supported."
            raise Abort(ErrorCode.ILLEGAL_COMMAND)
        self._write = _SegmentedWrite(req.node, req.index, req.subindex, req.length,
                                      bytearray(), toggle=False)
        return StatusAnswer(0)

    def _segment_write(self, req: SegmentWrite) -> Message:
        state = self._write
        if state is None:
            raise Abort(ErrorCode.GENERAL_ERROR)
        if req.toggle != state.toggle:
            self._write = None
            raise Abort(ErrorCode.TOGGLE_ERROR)
        state.buffer += req.data
        if len(state.buffer) > state.length:
            self._write = None
            raise Abort(ErrorCode.SERVICE_PARAMETER_ERROR)
        answer = SegmentWriteAnswer(0, len(req.data), toggle=state.toggle)
        state.toggle = not state.toggle
        if req.last:
            self._write = None
            if len(state.buffer) != state.length:
                raise Abort(ErrorCode.SERVICE_PARAMETER_ERROR)
            self.access.write(state.node, state.index, state.subindex, bytes(state.buffer),
                              expedited=False)
        return answer
