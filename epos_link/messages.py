"""Requests and answers of the EPOS4 USB & RS232 command reference (guide 2.1).

Every message is a frozen dataclass that validates its fields when built and
knows its own data field layout (``payload()`` / ``from_payload()``); words
and long words are little endian (guide 2.2.5). The same classes serve a host
(encode requests, decode answers) and a device (decode requests, encode
answers). Answers all have op code 0x00 and start with a DWORD error code
(guide chapter 6); an answer carrying a non-zero error code may be shorter
than the success layout, so decoders accept the error code alone.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, ClassVar, Union

from .codes import MAX_SEGMENT, OpCode
from .errors import LocalProtocolError, MessageFormatError
from .framing import Frame, encode_frame

_ADDR = struct.Struct("<BHB")  # node id, index, subindex (guide 2.1.1.1)
_U32 = struct.Struct("<I")


def _check(cond: bool, what: str) -> None:
    if not cond:
        raise LocalProtocolError(what)


def _check_address(node: int, index: int, subindex: int) -> None:
    _check(0 <= node <= 0xFF, f"node id {node!r} is not a byte")
    _check(0 <= index <= 0xFFFF, f"index {index!r} is not a word")
    _check(0 <= subindex <= 0xFF, f"subindex {subindex!r} is not a byte")


def _pad(data: bytes) -> bytes:
    """A dummy byte when the length is odd: the data field is made of words."""
    return data + b"\x00" if len(data) % 2 else data


class Message:
    """Common behaviour: the op code and the frame of a message."""

    opcode: ClassVar[int]

    def payload(self) -> bytes:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    def encode(self) -> bytes:
        """The complete wire frame, sync and stuffing included."""
        return encode_frame(self.opcode, self.payload())


def _expect(data: bytes, size: int, name: str) -> None:
    if len(data) != size:
        raise MessageFormatError(f"{name}: {len(data)} data bytes, expected {size}", data)


# --- requests ---------------------------------------------------------------

@dataclass(frozen=True)
class _Addressed(Message):
    node: int
    index: int
    subindex: int

    def __post_init__(self) -> None:
        _check_address(self.node, self.index, self.subindex)

    def payload(self) -> bytes:
        return _ADDR.pack(self.node, self.index, self.subindex)

    @classmethod
    def from_payload(cls, data: bytes):  # type: ignore[no-untyped-def]
        _expect(data, 4, cls.__name__)
        return cls(*_ADDR.unpack(data))


@dataclass(frozen=True)
class ReadObject(_Addressed):
    """0x60: read an object of up to 4 bytes (guide 2.1.1.1)."""

    opcode: ClassVar[int] = OpCode.READ_OBJECT


@dataclass(frozen=True)
class InitiateSegmentedRead(_Addressed):
    """0x81: start reading an object of any size (guide 2.1.1.2)."""

    opcode: ClassVar[int] = OpCode.INITIATE_SEGMENTED_READ


@dataclass(frozen=True)
class SegmentRead(Message):
    """0x62: read the next segment; ControlByte bit 0 is the toggle bit (guide 2.1.1.3)."""

    toggle: bool
    opcode: ClassVar[int] = OpCode.SEGMENT_READ

    def payload(self) -> bytes:
        return bytes((int(self.toggle), 0))  # ControlByte, dummy byte

    @classmethod
    def from_payload(cls, data: bytes) -> "SegmentRead":
        _expect(data, 2, cls.__name__)
        return cls(bool(data[0] & 0x01))


@dataclass(frozen=True)
class WriteObject(_Addressed):
    """0x68: write an object of up to 4 bytes; the data field is always 4 bytes (guide 2.1.2.1)."""

    data: bytes = field(default=b"\x00" * 4)
    opcode: ClassVar[int] = OpCode.WRITE_OBJECT

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(isinstance(self.data, bytes) and len(self.data) == 4,
               "WriteObject carries exactly 4 data bytes (pad smaller values)")

    def payload(self) -> bytes:
        return super().payload() + self.data

    @classmethod
    def from_payload(cls, data: bytes) -> "WriteObject":
        _expect(data, 8, cls.__name__)
        node, index, subindex = _ADDR.unpack(data[:4])
        return cls(node, index, subindex, data=bytes(data[4:]))


@dataclass(frozen=True)
class InitiateSegmentedWrite(_Addressed):
    """0x69: announce a segmented write of ``length`` bytes (guide 2.1.2.2)."""

    length: int = 0
    opcode: ClassVar[int] = OpCode.INITIATE_SEGMENTED_WRITE

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(0 <= self.length <= 0xFFFFFFFF, f"length {self.length!r} is not a DWORD")

    def payload(self) -> bytes:
        return super().payload() + _U32.pack(self.length)

    @classmethod
    def from_payload(cls, data: bytes) -> "InitiateSegmentedWrite":
        _expect(data, 8, cls.__name__)
        node, index, subindex = _ADDR.unpack(data[:4])
        return cls(node, index, subindex, length=_U32.unpack(data[4:])[0])


@dataclass(frozen=True)
class SegmentWrite(Message):
    """0x6A: Length, ControlByte (bit 0 toggle, bit 1 last), data, dummy when odd (guide 2.1.2.3)."""

    data: bytes
    toggle: bool
    last: bool
    opcode: ClassVar[int] = OpCode.SEGMENT_WRITE

    def __post_init__(self) -> None:
        _check(len(self.data) <= MAX_SEGMENT, f"a segment holds at most {MAX_SEGMENT} bytes")

    def payload(self) -> bytes:
        control = int(self.toggle) | (int(self.last) << 1)
        return _pad(bytes((len(self.data), control)) + self.data)

    @classmethod
    def from_payload(cls, data: bytes) -> "SegmentWrite":
        if len(data) < 2:
            raise MessageFormatError("SegmentWrite: shorter than Length and ControlByte", data)
        length, control = data[0], data[1]
        _expect(data, len(_pad(bytes(2 + length))), cls.__name__)
        return cls(bytes(data[2:2 + length]), bool(control & 1), bool(control & 2))


@dataclass(frozen=True)
class SendNMTService(Message):
    """0x70: WORD node id, WORD command specifier (NMT, guide Table 3-14)."""

    node: int
    command: int
    opcode: ClassVar[int] = OpCode.SEND_NMT_SERVICE

    def __post_init__(self) -> None:
        _check(0 <= self.node <= 0xFFFF, f"node id {self.node!r} is not a word")
        _check(0 <= self.command <= 0xFFFF, f"command {self.command!r} is not a word")

    def payload(self) -> bytes:
        return struct.pack("<HH", self.node, self.command)

    @classmethod
    def from_payload(cls, data: bytes) -> "SendNMTService":
        _expect(data, 4, cls.__name__)
        return cls(*struct.unpack("<HH", data))


Request = Union[ReadObject, InitiateSegmentedRead, SegmentRead, WriteObject,
                InitiateSegmentedWrite, SegmentWrite, SendNMTService]

REQUEST_TYPES: dict[int, Any] = {
    cls.opcode: cls
    for cls in (ReadObject, InitiateSegmentedRead, SegmentRead, WriteObject,
                InitiateSegmentedWrite, SegmentWrite, SendNMTService)
}


# --- answers ----------------------------------------------------------------

@dataclass(frozen=True)
class Answer(Message):
    """Any answer: the error code and the bytes after it, when the request is unknown."""

    error_code: int
    data: bytes = b""
    opcode: ClassVar[int] = OpCode.ANSWER

    def __post_init__(self) -> None:
        _check(0 <= self.error_code <= 0xFFFFFFFF, "error code is a DWORD")

    def payload(self) -> bytes:
        return _U32.pack(self.error_code) + _pad(self.data)

    @classmethod
    def from_payload(cls, data: bytes) -> "Answer":
        if len(data) < 4:
            raise MessageFormatError("answer shorter than its error code", data)
        return cls(_U32.unpack_from(data)[0], bytes(data[4:]))


def _error_only(data: bytes, name: str) -> int | None:
    """The error code of a short error answer, or None if ``data`` is longer."""
    if len(data) < 4:
        raise MessageFormatError(f"{name}: shorter than its error code", data)
    code = _U32.unpack_from(data)[0]
    return code if code and len(data) == 4 else None


@dataclass(frozen=True)
class ReadObjectAnswer(Answer):
    """Error code and 4 data bytes; smaller objects are padded (guide 2.1.1.1)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(len(self.data) == 4 or (self.error_code != 0 and not self.data),
               "ReadObject answers carry 4 data bytes")

    @classmethod
    def from_payload(cls, data: bytes) -> "ReadObjectAnswer":
        code = _error_only(data, cls.__name__)
        if code is not None:
            return cls(code, b"")
        _expect(data, 8, cls.__name__)
        return cls(_U32.unpack_from(data)[0], bytes(data[4:]))


@dataclass(frozen=True)
class InitiateSegmentedReadAnswer(Message):
    """Error code, object length (DWORD), Length (BYTE), first data bytes (guide 2.1.1.2).

    The first segment may be empty: the data then arrive by SegmentRead.
    """

    error_code: int
    object_length: int = 0
    data: bytes = b""
    opcode: ClassVar[int] = OpCode.ANSWER

    def __post_init__(self) -> None:
        _check(len(self.data) <= MAX_SEGMENT, f"a segment holds at most {MAX_SEGMENT} bytes")

    def payload(self) -> bytes:
        head = struct.pack("<IIB", self.error_code, self.object_length, len(self.data))
        return _pad(head + self.data)

    @classmethod
    def from_payload(cls, data: bytes) -> "InitiateSegmentedReadAnswer":
        code = _error_only(data, cls.__name__)
        if code is not None:
            return cls(code)
        if len(data) < 9:
            raise MessageFormatError(f"{cls.__name__}: {len(data)} bytes, at least 9 expected", data)
        code, total, length = struct.unpack_from("<IIB", data)
        _expect(data, len(_pad(bytes(9 + length))), cls.__name__)
        return cls(code, total, bytes(data[9:9 + length]))


@dataclass(frozen=True)
class SegmentReadAnswer(Message):
    """Error code, Length, ControlByte (bit 0 toggle, bit 1 last), data, dummy (guide 2.1.1.3)."""

    error_code: int
    data: bytes = b""
    toggle: bool = False
    last: bool = False
    opcode: ClassVar[int] = OpCode.ANSWER

    def __post_init__(self) -> None:
        _check(len(self.data) <= MAX_SEGMENT, f"a segment holds at most {MAX_SEGMENT} bytes")

    def payload(self) -> bytes:
        control = int(self.toggle) | (int(self.last) << 1)
        return _pad(struct.pack("<IBB", self.error_code, len(self.data), control) + self.data)

    @classmethod
    def from_payload(cls, data: bytes) -> "SegmentReadAnswer":
        code = _error_only(data, cls.__name__)
        if code is not None:
            return cls(code)
        if len(data) < 6:
            raise MessageFormatError(f"{cls.__name__}: {len(data)} bytes, at least 6 expected", data)
        code, length, control = struct.unpack_from("<IBB", data)
        _expect(data, len(_pad(bytes(6 + length))), cls.__name__)
        return cls(code, bytes(data[6:6 + length]), bool(control & 1), bool(control & 2))


@dataclass(frozen=True)
class StatusAnswer(Message):
    """An answer that is only the error code: WriteObject, InitiateSegmentedWrite, SendNMTService."""

    error_code: int
    opcode: ClassVar[int] = OpCode.ANSWER

    def payload(self) -> bytes:
        return _U32.pack(self.error_code)

    @classmethod
    def from_payload(cls, data: bytes) -> "StatusAnswer":
        _expect(data, 4, cls.__name__)
        return cls(_U32.unpack(data)[0])


@dataclass(frozen=True)
class SegmentWriteAnswer(Message):
    """Error code, Length written, ControlByte with the toggle bit (guide 2.1.2.3)."""

    error_code: int
    length_written: int = 0
    toggle: bool = False
    opcode: ClassVar[int] = OpCode.ANSWER

    def payload(self) -> bytes:
        return struct.pack("<IBB", self.error_code, self.length_written, int(self.toggle))

    @classmethod
    def from_payload(cls, data: bytes) -> "SegmentWriteAnswer":
        code = _error_only(data, cls.__name__)
        if code is not None:
            return cls(code)
        _expect(data, 6, cls.__name__)
        code, length, control = struct.unpack("<IBB", data)
        return cls(code, length, bool(control & 1))


# The guide's names for the answers, per request.
WriteObjectAnswer = InitiateSegmentedWriteAnswer = SendNMTServiceAnswer = StatusAnswer

ANSWER_TYPES: dict[type, type] = {
    ReadObject: ReadObjectAnswer,
    InitiateSegmentedRead: InitiateSegmentedReadAnswer,
    SegmentRead: SegmentReadAnswer,
    WriteObject: StatusAnswer,
    InitiateSegmentedWrite: StatusAnswer,
    SegmentWrite: SegmentWriteAnswer,
    SendNMTService: StatusAnswer,
}

AnyAnswer = Union[Answer, ReadObjectAnswer, InitiateSegmentedReadAnswer, SegmentReadAnswer,
                  StatusAnswer, SegmentWriteAnswer]


def decode_request(frame: Frame) -> Request:
    """The request carried by ``frame``; unknown op codes raise MessageFormatError."""
    cls = REQUEST_TYPES.get(frame.opcode)
    if cls is None:
        raise MessageFormatError(f"unknown op code 0x{frame.opcode:02X}", frame.data)
    request: Request = cls.from_payload(frame.data)
    return request


def decode_answer(frame: Frame, request: "type | Message | None" = None) -> AnyAnswer:
    """The answer in ``frame``, laid out as the answer to ``request`` (a request
    instance or class); a generic :class:`Answer` when the request is unknown."""
    if frame.opcode != OpCode.ANSWER:
        raise MessageFormatError(f"op code 0x{frame.opcode:02X} is not an answer (0x00)",
                                 frame.data)
    req_type = request if isinstance(request, type) or request is None else type(request)
    cls = ANSWER_TYPES.get(req_type, Answer) if req_type is not None else Answer
    return cls.from_payload(frame.data)  # type: ignore[no-any-return, attr-defined]
