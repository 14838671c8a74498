"""``epos-link decode``: show MAXON SERIAL V2 frames in hex input or a capture file.

Hex comes from the arguments (with or without spaces, in one or several
arguments) or from standard input; ``--file`` (or a single argument naming an
existing file) reads a capture in the format of :mod:`epos_link.capture`.
Standard input is decoded line by line as it arrives (a capture or hex), and
``--follow FILE`` decodes a capture that is still growing
(:mod:`epos_link.tools.follow`, bounded waits, ``--idle-exit``). Captures are
decoded with names and values from the object dictionary
(:mod:`epos_link.tools.frames`).
Every frame gives one line, as ``monitor`` prints it
(:func:`epos_link.tools.view.format_event`; a capture's lines with its
timestamps); a frame with a bad CRC is still decoded and marked; bytes that
are not a frame are reported, never dropped.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, field
from typing import Any, Iterator, Optional

from ..capture import (MAX_LINE, Capture, CaptureFormatError, Direction, Record, parse_hex,
                       parse_line)
from ..codes import describe_error, opcode_name, OpCode
from ..errors import CrcError, EposError, RemoteProtocolError
from ..framing import NEED_DATA, Frame, FrameDecoder, encode_frame
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
            "node": self.node, "index": hex_index(self.index), "subindex": hex_subindex(self.subindex),
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


def hex_index(index: Optional[int]) -> Optional[str]:
    """JSON shows indexes as the text does, ``"0x6041"``: an index in decimal (24641)
    is read by nobody."""
    return None if index is None else f"0x{index:04X}"


def hex_subindex(subindex: Optional[int]) -> Optional[str]:
    return None if subindex is None else f"0x{subindex:02X}"


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
                # Stuffing is deterministic: a good frame's wire bytes are its encoding.
                line.raw = encode_frame(item.opcode, item.data)  # type: ignore[union-attr]
                pair.update(self.direction, req)
                yield line
            except CrcError as exc:
                frame = exc.frame
                assert isinstance(frame, Frame)
                line, req = describe_frame(frame, self.direction, pair.request_for(self.direction))
                line.raw = exc.raw
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
    from .common import positive_float  # the link helpers, not needed to decode

    parser.add_argument("hex", nargs="*", help="frame bytes in hex (spaces optional); "
                        "omit to read hex or a capture from standard input, decoded as it arrives")
    parser.add_argument("-f", "--file", help="a capture file (epos-link capture format)")
    parser.add_argument("--follow", metavar="FILE",
                        help="decode a capture file and then what is appended to it, as tail -F")
    parser.add_argument("--idle-exit", type=positive_float, metavar="SECONDS",
                        help="with --follow or standard input: stop after SECONDS without new bytes")
    parser.add_argument("--responses", action="store_true",
                        help="decode the frames as answers (device to host)")
    parser.add_argument("--eds", metavar="FILE",
                        help="object dictionary for names and values (default: the shipped EPOS4 EDS)")
    parser.add_argument("--json", action="store_true", help="one JSON object per frame")
    parser.add_argument("-x", dest="hex_bytes", action="store_true", help="add the wire bytes in hex")


class LineDecoder:
    """Decodes lines of text: a capture (``TIME TX|RX HEX``) or plain hex, told
    apart by the first line that is neither blank nor a comment."""

    def __init__(self, eds: Optional[str], responses: bool) -> None:
        self.eds = eds
        self.responses = responses
        self.restart()

    def restart(self) -> None:
        self.mode: Optional[str] = None
        self.link: Optional[Any] = None
        self.stream = StreamDecoder(Direction.RX.value if self.responses else None)
        self.pair = Pairing()
        self.last_time = 0.0
        self.lineno = 0

    def line(self, text: str) -> Iterator[Any]:
        self.lineno += 1
        body = text.split("#", 1)[0].strip()
        if not body:
            return
        if self.mode is None:
            self.mode = "capture" if body.split()[1:2] in (["TX"], ["RX"], ["tx"], ["rx"]) else "hex"
            if self.mode == "capture":
                from .frames import LinkDecoder
                from .objects import load_directory

                self.link = LinkDecoder(load_directory(self.eds))
        if self.mode == "hex":
            yield from self.stream.feed(parse_hex(body), self.pair)
            return
        if len(text) >= MAX_LINE:
            # follow.py cuts a longer line to bound memory; hex continues across
            # the cut, a capture record cannot (no record is that long: one read
            # or write each).
            raise CaptureFormatError(f"line {self.lineno}: longer than {MAX_LINE} characters, "
                                     "which no capture record is")
        record = parse_line(text, self.lineno)
        if isinstance(record, Record):
            self.last_time = record.time
            yield from self.link.feed(record.time, record.direction, record.data)  # type: ignore[union-attr]

    def close(self) -> Iterator[Any]:
        if self.mode == "capture":
            yield from self.link.close(self.last_time)  # type: ignore[union-attr]
        elif self.mode == "hex":
            yield from self.stream.close(self.pair)


def _as_decoded(item: Any) -> Decoded:
    return item if isinstance(item, Decoded) else item.decoded


class TextLines:
    """Lines as ``monitor`` prints them (:func:`epos_link.tools.view.format_event`):
    a capture's frames with their timestamps (zero-based, as the capture counts
    them), bare hex without (it has no times), both with object names."""

    def __init__(self, eds: Optional[str], hex_bytes: bool) -> None:
        from .view import Clock, use_colour

        self.eds = eds
        self.hex_bytes = hex_bytes
        self.clock = Clock("z")
        self.colour = use_colour(sys.stdout)

    def __call__(self, item: Any) -> str:
        from .frames import FrameEvent
        from .objects import load_directory
        from .view import format_event

        if isinstance(item, FrameEvent):
            return format_event(item, self.clock, colour=self.colour, hex_bytes=self.hex_bytes)
        event = FrameEvent(0.0, item.direction, item, node=item.node, index=item.index,
                           subindex=item.subindex)
        if item.index is not None:
            event.obj = load_directory(self.eds).find(item.index, item.subindex or 0)
        return format_event(event, None, colour=self.colour, hex_bytes=self.hex_bytes)


def _lines(args: argparse.Namespace) -> Iterator[Any]:
    """The source of text lines the arguments name."""
    from .follow import follow_file, stream_lines

    if args.follow:
        return follow_file(args.follow, idle_exit=args.idle_exit)
    path = args.file or (args.hex[0] if len(args.hex) == 1 and os.path.isfile(args.hex[0]) else None)
    if not path and len(args.hex) == 1 and ("/" in args.hex[0] or "." in args.hex[0] or os.sep in args.hex[0]):
        # Hex has no "/" or ".": this names a file that is not there, and
        # "not hex bytes" would send the user the wrong way.
        raise FileNotFoundError(f"{args.hex[0]}: no such file")
    if path:
        return follow_file(path, idle_exit=0.0)  # a plain read to the end, line by line
    if args.hex:
        return iter(" ".join(args.hex).splitlines())
    return stream_lines(sys.stdin.fileno(), idle_exit=args.idle_exit)


def run(args: argparse.Namespace) -> int:
    from .follow import RESTART

    prog = "epos-link decode"
    decoder = LineDecoder(args.eds, args.responses)
    text = TextLines(args.eds, args.hex_bytes)
    count = damaged = 0

    def emit(item: Any) -> None:
        nonlocal count, damaged
        d = _as_decoded(item)
        count += 1
        damaged += bool(d.problem or d.crc_ok is False)
        print(json.dumps(item.as_json()) if args.json else text(item), flush=True)

    try:
        for line in _lines(args):
            if line is RESTART:
                print(f"{prog}: {args.follow} was truncated or replaced: decoding it from the start",
                      file=sys.stderr)
                for item in decoder.close():
                    emit(item)
                decoder.restart()
                continue
            for item in decoder.line(line):  # type: ignore[arg-type]
                emit(item)
        for item in decoder.close():
            emit(item)
    except UnicodeDecodeError:
        print(f"{prog}: the input is not text: a capture file is hex text "
              "(see epos_link/capture.py)", file=sys.stderr)
        return 2
    except (OSError, CaptureFormatError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    except EposError as exc:  # a bad --eds
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if not count:
        print(f"{prog}: no bytes to decode", file=sys.stderr)
        return 2
    return 1 if damaged else 0


__all__ = ["Decoded", "LineDecoder", "Pairing", "StreamDecoder", "decode_bytes", "decode_capture",
           "describe_frame", "add_arguments", "run"]
