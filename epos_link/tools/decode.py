"""``epos-link decode``: show MAXON SERIAL V2 frames in hex input or a capture file.

Hex comes from the arguments (with or without spaces, in one or several
arguments) or from standard input; ``--file`` (or a single argument naming an
existing file) reads a capture in the format of :mod:`epos_link.capture`.
Every frame gives one line; a frame with a bad CRC is still decoded and marked;
bytes that are not a frame are reported, never dropped.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, field
from typing import Any, Iterator, Optional

from ..capture import Capture, CaptureFormatError, Direction, parse_hex, read_capture
from ..codes import describe_error, opcode_name, OpCode
from ..errors import CrcError, RemoteProtocolError
from ..framing import NEED_DATA, Frame, FrameDecoder
from ..messages import (
    InitiateSegmentedReadAnswer,
    InitiateSegmentedWrite,
    Message,
    SegmentRead,
    SegmentReadAnswer,
    SegmentWrite,
    SegmentWriteAnswer,
    SendNMTService,
    WriteObject,
    decode_answer,
    decode_request,
)


@dataclass
class Decoded:
    """One line of output: a frame, or a run of bytes that is not a frame."""

    direction: Optional[str]
    opcode: Optional[int]
    name: str
    node: Optional[int] = None
    index: Optional[int] = None
    subindex: Optional[int] = None
    data: bytes = b""
    error_code: Optional[int] = None
    crc_ok: Optional[bool] = None
    extra: dict[str, Any] = field(default_factory=dict)
    problem: Optional[str] = None  # set when the bytes are not a (well-formed) frame
    raw: bytes = b""

    def as_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "direction": self.direction, "opcode": self.opcode, "name": self.name,
            "node": self.node, "index": self.index, "subindex": self.subindex,
            "data": self.data.hex(), "error_code": self.error_code, "crc_ok": self.crc_ok,
        }
        if self.error_code is not None:
            out["error_name"] = describe_error(self.error_code)
        out.update(self.extra)
        if self.problem:
            out["problem"] = self.problem
            out["raw"] = self.raw.hex()
        return out

    def as_text(self) -> str:
        head = f"{self.direction or '--'} "
        if self.opcode is None:
            return f"{head}not a frame: {self.problem} [{_hex(self.raw)}]"
        parts = [f"{self.name} (0x{self.opcode:02X})"]
        if self.node is not None:
            parts.append(f"node={self.node}")
        if self.index is not None:
            parts.append(f"index=0x{self.index:04X} subindex=0x{self.subindex:02X}")
        if self.error_code is not None:
            parts.append(f"error=0x{self.error_code:08X} ({describe_error(self.error_code)})")
        parts.extend(f"{k}={v}" for k, v in self.extra.items())
        parts.append(f"data=[{_hex(self.data)}]")
        parts.append("crc=ok" if self.crc_ok else "crc=BAD")
        if self.problem:
            parts.append(f"problem: {self.problem}")
        return head + " ".join(parts)


def _hex(data: bytes) -> str:
    return data.hex(" ").upper()


def describe_frame(frame: Frame, direction: Optional[str],
                   request: Optional[Message] = None) -> tuple[Decoded, Optional[Message]]:
    """Decode one frame into a line; returns the request it carried, if any."""
    out = Decoded(direction, frame.opcode, opcode_name(frame.opcode), crc_ok=frame.crc_ok)
    as_answer = frame.opcode == OpCode.ANSWER or direction == Direction.RX.value
    try:
        if as_answer:
            ans = decode_answer(frame, request) if frame.opcode == OpCode.ANSWER else None
            if ans is None:
                out.problem = "an RX frame whose op code is not an answer (0x00)"
                out.data = bytes(frame.data)
                return out, None
            out.name = type(ans).__name__ if request is not None else "Answer"
            out.error_code = ans.error_code
            if isinstance(ans, InitiateSegmentedReadAnswer):
                out.extra["object_length"] = ans.object_length
            if isinstance(ans, (SegmentReadAnswer, SegmentWriteAnswer)):
                out.extra["toggle"] = int(ans.toggle)
            if isinstance(ans, SegmentReadAnswer):
                out.extra["last"] = int(ans.last)
            if isinstance(ans, SegmentWriteAnswer):
                out.extra["length_written"] = ans.length_written
            payload = getattr(ans, "data", None)
            out.data = bytes(payload if payload is not None else frame.data[4:])
            return out, None
        req = decode_request(frame)
    except RemoteProtocolError as exc:
        out.problem = str(exc)
        out.data = bytes(frame.data)
        return out, None
    if hasattr(req, "index"):
        out.node, out.index, out.subindex = req.node, req.index, req.subindex  # type: ignore[union-attr]
        out.data = bytes(frame.data[4:])
    else:
        out.data = bytes(frame.data)
    if isinstance(req, SendNMTService):
        out.node = req.node
        out.extra["command"] = f"0x{req.command:02X}"
    if isinstance(req, (SegmentRead, SegmentWrite)):
        out.extra["toggle"] = int(req.toggle)
    if isinstance(req, SegmentWrite):
        out.extra["last"] = int(req.last)
        out.data = bytes(req.data)
    if isinstance(req, InitiateSegmentedWrite):
        out.extra["length"] = req.length
    if isinstance(req, WriteObject):
        out.data = bytes(req.data)
    return out, req


FEED_SLICE = 64 * 1024


class StreamDecoder:
    """Decodes the byte stream of one direction, remembering the last request."""

    def __init__(self, direction: Optional[str]) -> None:
        self.direction = direction
        self.decoder = FrameDecoder()

    def _drain(self, pair: "Pairing") -> Iterator[Decoded]:
        while True:
            try:
                item = self.decoder.next_frame()
                if item is NEED_DATA:
                    return
                line, req = describe_frame(item, self.direction, pair.request_for(self.direction))  # type: ignore[arg-type]
                pair.update(self.direction, req)
                yield line
            except CrcError as exc:
                frame = exc.frame
                assert isinstance(frame, Frame)
                line, req = describe_frame(frame, self.direction, pair.request_for(self.direction))
                pair.update(self.direction, req)
                yield line
            except RemoteProtocolError as exc:
                yield Decoded(self.direction, None, "not a frame", problem=str(exc), raw=exc.raw)

    def feed(self, data: bytes, pair: "Pairing") -> Iterator[Decoded]:
        # In slices, drained in between: the decoder bounds what it holds.
        for start in range(0, len(data), FEED_SLICE):
            self.decoder.feed(data[start:start + FEED_SLICE])
            yield from self._drain(pair)

    def close(self, pair: "Pairing") -> Iterator[Decoded]:
        self.decoder.close()
        yield from self._drain(pair)


class Pairing:
    """Pairs each RX answer with the TX request before it, so answers decode fully."""

    def __init__(self) -> None:
        self.last_request: Optional[Message] = None

    def request_for(self, direction: Optional[str]) -> Optional[Message]:
        return self.last_request if direction == Direction.RX.value else None

    def update(self, direction: Optional[str], request: Optional[Message]) -> None:
        if direction == Direction.TX.value:
            self.last_request = request
        elif direction == Direction.RX.value:
            self.last_request = None


def decode_capture(capture: Capture) -> Iterator[Decoded]:
    streams = {d: StreamDecoder(d.value) for d in Direction}
    pair = Pairing()
    for record in capture.records:
        yield from streams[record.direction].feed(record.data, pair)
    for stream in streams.values():
        yield from stream.close(pair)


def decode_bytes(data: bytes, *, responses: bool = False) -> Iterator[Decoded]:
    stream = StreamDecoder(Direction.RX.value if responses else None)
    pair = Pairing()
    yield from stream.feed(data, pair)
    yield from stream.close(pair)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("hex", nargs="*", help="frame bytes in hex (spaces optional); "
                        "omit to read hex from standard input")
    parser.add_argument("-f", "--file", help="a capture file (epos-link capture format)")
    parser.add_argument("--responses", action="store_true",
                        help="decode the frames as answers (device to host)")
    parser.add_argument("--json", action="store_true", help="one JSON object per frame")


def _load(args: argparse.Namespace) -> Iterator[Decoded]:
    if args.file:
        with open(args.file, encoding="utf-8") as fh:
            return decode_capture(read_capture(fh))
    if len(args.hex) == 1 and os.path.isfile(args.hex[0]):
        with open(args.hex[0], encoding="utf-8") as fh:
            return decode_capture(read_capture(fh))
    text = " ".join(args.hex) if args.hex else sys.stdin.read()
    if any(line.split()[1:2] in (["TX"], ["RX"]) for line in text.splitlines()):
        return decode_capture(read_capture(text))
    return decode_bytes(parse_hex(text), responses=args.responses)


def run(args: argparse.Namespace) -> int:
    try:
        lines = list(_load(args))
    except UnicodeDecodeError:
        print("epos-link decode: the file is not text: a capture file is hex text "
              "(see epos_link/capture.py)", file=sys.stderr)
        return 2
    except (OSError, CaptureFormatError) as exc:
        print(f"epos-link decode: {exc}", file=sys.stderr)
        return 2
    if not lines:
        print("epos-link decode: no bytes to decode", file=sys.stderr)
        return 2
    for line in lines:
        print(json.dumps(line.as_json()) if args.json else line.as_text())
    damaged = any(line.problem or line.crc_ok is False for line in lines)
    return 1 if damaged else 0


__all__ = ["Decoded", "decode_bytes", "decode_capture", "describe_frame", "add_arguments", "run"]
