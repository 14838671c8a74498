"""Frames of a conversation, with object names, typed values and answer times.

:class:`LinkDecoder` is the pure core that ``monitor``, ``decode`` and
``export`` share. It is fed timed chunks of bytes as they crossed the wire
(``TX`` host to device, ``RX`` device to host) and gives back one
:class:`FrameEvent` per frame or per run of bytes that is not a frame, each
with the wire bytes it covers, so nothing is ever hidden.

Policy:

* Each direction has its own resynchronising :class:`~epos_link.framing.FrameDecoder`;
  a garbled frame is reported (CRC, stuffing, truncation) and decoding goes on.
* An answer carries no address (guide 2.1): it is paired with the last request
  seen in the other direction (the device answers one request at a time,
  guide 2.2.1), which gives it its node, object and layout, and the time from
  the end of the request to the end of the answer.
* Values are decoded by the object's type in the dictionary
  (:mod:`epos_link.tools.objects`): a WriteObject's value, a ReadObject
  answer's value, and for segmented transfers the whole value once the last
  segment has passed. Segment data kept for that is bounded by
  :data:`MAX_TRANSFER`; a longer transfer is shown without its value.
* Objects missing from the dictionary are shown by index, their data in hex.
  A damaged frame (bad CRC, bad layout) is never given a value.

No clocks: times are whatever the caller passes in.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from ..capture import Direction
from ..messages import (
    InitiateSegmentedRead,
    InitiateSegmentedWrite,
    Message,
    ReadObject,
    SegmentRead,
    SegmentWrite,
    WriteObject,
)
from .decode import Decoded, Pairing, StreamDecoder, hex_index, hex_subindex
from .objects import ObjectDirectory, ObjectInfo, Value, meaning

MAX_TRANSFER = 64 * 1024


@dataclass
class FrameEvent:
    """One frame (or run of non-frame bytes) with what the conversation tells about it."""

    time: float
    direction: Optional[str]
    decoded: Decoded
    obj: Optional[ObjectInfo] = None      # the object addressed (answers: their request's)
    node: Optional[int] = None
    index: Optional[int] = None
    subindex: Optional[int] = None
    value: Optional[Value] = None         # decoded by the object's type, when known
    value_text: Optional[str] = None
    latency: Optional[float] = None       # answers: seconds from the end of their request
    answers: Optional[str] = None         # answers: the name of the request answered
    meaning: Optional[str] = None         # what the value means (objects.meaning): a CiA 402 state

    @property
    def raw(self) -> bytes:
        return self.decoded.raw

    @property
    def is_frame(self) -> bool:
        return self.decoded.opcode is not None

    @property
    def faulty(self) -> bool:
        """Not a frame, a damaged frame, or an answer with an error code."""
        d = self.decoded
        return bool(d.problem) or d.crc_ok is False or bool(d.error_code)

    def as_json(self, time_value: Optional[float] = None) -> dict[str, Any]:
        out: dict[str, Any] = {"time": round(self.time if time_value is None else time_value, 6)}
        out.update(self.decoded.as_json())
        if self.node is not None and out.get("node") is None:
            out["node"], out["index"], out["subindex"] = (self.node, hex_index(self.index),
                                                          hex_subindex(self.subindex))
        if self.obj is not None:
            out["object"] = self.obj.name
            if self.obj.type is not None:
                out["type"] = self.obj.type.name
        if self.value is not None:
            out["value"] = self.value.hex() if isinstance(self.value, bytes) else self.value
        if self.meaning is not None:
            out["meaning"] = self.meaning
        if self.answers is not None:
            out["answers"] = self.answers
        if self.latency is not None:
            out["latency_ms"] = round(self.latency * 1000.0, 3)
        out["raw"] = self.raw.hex()
        return out


@dataclass
class _Transfer:
    """A segmented transfer in progress: its object and the bytes seen so far."""

    node: int
    index: int
    subindex: int
    length: Optional[int] = None
    data: bytearray = field(default_factory=bytearray)
    overflow: bool = False

    def add(self, chunk: bytes) -> None:
        if len(self.data) + len(chunk) > MAX_TRANSFER:
            self.overflow = True
            return
        self.data += chunk


class Conversation(Pairing):
    """Pairs answers with requests and remembers segmented transfers (see module doc)."""

    def __init__(self) -> None:
        super().__init__()
        self.request_time: Optional[float] = None
        self.transfer: Optional[_Transfer] = None
        self.answered: Optional[Message] = None  # the request the last answer was decoded against

    def update(self, direction: Optional[str], request: Optional[Message]) -> None:
        if direction == Direction.RX.value:
            self.answered = self.last_request
        super().update(direction, request)
        if direction != Direction.TX.value or request is None:
            return
        if isinstance(request, (InitiateSegmentedRead, InitiateSegmentedWrite)):
            self.transfer = _Transfer(request.node, request.index, request.subindex)
            if isinstance(request, InitiateSegmentedWrite):
                self.transfer.length = request.length
        elif not isinstance(request, (SegmentRead, SegmentWrite)):
            self.transfer = None


class LinkDecoder:
    """Feed ``(time, direction, bytes)``; get :class:`FrameEvent` lists back."""

    def __init__(self, directory: Optional[ObjectDirectory] = None) -> None:
        self.directory = directory
        self.conversation = Conversation()
        self.streams = {d.value: StreamDecoder(d.value) for d in Direction}

    def feed(self, time: float, direction: Direction | str, data: bytes) -> list[FrameEvent]:
        d = Direction(direction).value
        out = []
        for line in self.streams[d].feed(bytes(data), self.conversation):
            out.append(self._annotate(time, d, line))
        return out

    def close(self, time: float) -> list[FrameEvent]:
        out = []
        for d, stream in self.streams.items():
            for line in stream.close(self.conversation):
                out.append(self._annotate(time, d, line))
        return out

    # --- annotation -----------------------------------------------------------

    def _lookup(self, node: int, index: int, subindex: int, event: FrameEvent) -> None:
        event.node, event.index, event.subindex = node, index, subindex
        if self.directory is not None:
            event.obj = self.directory.find(index, subindex)

    def _set_value(self, event: FrameEvent, data: bytes, *, exact: bool = False) -> None:
        """``exact``: a whole segmented transfer, which must be the type's size."""
        typ = event.obj.type if event.obj is not None else None
        if typ is None or event.decoded.crc_ok is False or event.decoded.problem:
            return  # a damaged frame's bytes are no value
        if exact and typ.size is not None and len(data) != typ.size:
            return  # the transfer does not fit the dictionary's type: show the bytes only
        try:
            event.value = typ.decode(data)
        except Exception:  # too few bytes for the type: show the hex only
            return
        event.value_text = typ.format(event.value)
        note = meaning(event.index or 0, event.subindex or 0, event.value)
        if note is not None:
            event.value_text += f" [{note}]"
            event.meaning = note

    def _annotate(self, time: float, direction: str, line: Decoded) -> FrameEvent:
        conv = self.conversation
        event = FrameEvent(time, direction, line)
        if line.opcode is None:
            return event
        if direction == Direction.TX.value:
            self._annotate_request(event, line)
            conv.request_time = time
            return event
        self._annotate_answer(event, line)
        return event

    def _annotate_request(self, event: FrameEvent, line: Decoded) -> None:
        conv = self.conversation
        req = conv.last_request
        if line.index is not None and line.node is not None:
            self._lookup(line.node, line.index, line.subindex or 0, event)
            if isinstance(req, WriteObject):
                self._set_value(event, bytes(req.data))
        elif isinstance(req, SegmentWrite) and conv.transfer is not None:
            t = conv.transfer
            self._lookup(t.node, t.index, t.subindex, event)
            t.add(bytes(req.data))
            if req.last and not t.overflow:
                self._set_value(event, bytes(t.data), exact=True)
        elif isinstance(req, SegmentRead) and conv.transfer is not None:
            t = conv.transfer
            self._lookup(t.node, t.index, t.subindex, event)

    def _annotate_answer(self, event: FrameEvent, line: Decoded) -> None:
        conv = self.conversation
        req = conv.answered
        if req is None:
            return
        event.answers = type(req).__name__
        if conv.request_time is not None:
            event.latency = max(0.0, event.time - conv.request_time)
        if isinstance(req, (ReadObject, WriteObject, InitiateSegmentedRead, InitiateSegmentedWrite)):
            self._lookup(req.node, req.index, req.subindex, event)
        elif conv.transfer is not None:
            t = conv.transfer
            self._lookup(t.node, t.index, t.subindex, event)
        if line.error_code:
            conv.transfer = None
            return
        if isinstance(req, ReadObject):
            self._set_value(event, line.data)
        elif isinstance(req, (InitiateSegmentedRead, SegmentRead)) and conv.transfer is not None:
            t = conv.transfer
            if isinstance(req, InitiateSegmentedRead):
                t.length = line.extra.get("object_length")
            t.add(line.data)
            done = bool(line.extra.get("last")) or (t.length is not None and len(t.data) >= t.length > 0)
            if done and not t.overflow:
                self._set_value(event, bytes(t.data[:t.length] if t.length else t.data), exact=True)


__all__ = ["Conversation", "FrameEvent", "LinkDecoder", "MAX_TRANSFER"]
