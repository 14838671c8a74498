"""messages.py: layouts of guide 2.1, both directions, and round trips."""
from __future__ import annotations

import pytest
from hypothesis import given, strategies as st

from epos_link.codes import ERROR_TABLE, ErrorCode, describe_error
from epos_link.errors import DeviceError, LocalProtocolError, MessageFormatError
from epos_link.framing import Frame, decode_frames
from epos_link.messages import (
    Answer,
    InitiateSegmentedRead,
    InitiateSegmentedReadAnswer,
    InitiateSegmentedWrite,
    ReadObject,
    ReadObjectAnswer,
    SegmentRead,
    SegmentReadAnswer,
    SegmentWrite,
    SegmentWriteAnswer,
    SendNMTService,
    StatusAnswer,
    WriteObject,
    decode_answer,
    decode_request,
)
from tests.reference import GUIDE_ANSWER, GUIDE_REQUEST, reference_frame


def test_guide_read_object_request() -> None:
    assert ReadObject(node=1, index=0x30B0, subindex=0).encode() == GUIDE_REQUEST
    (frame,) = decode_frames(GUIDE_REQUEST)
    assert decode_request(frame) == ReadObject(1, 0x30B0, 0)


def test_guide_answer() -> None:
    (frame,) = decode_frames(GUIDE_ANSWER)
    ans = decode_answer(frame, ReadObject)
    assert ans == ReadObjectAnswer(0, bytes.fromhex("01 90 00 00"))
    assert ans.encode() == GUIDE_ANSWER


# Payload layouts written from the guide's tables (2.1.1.x, 2.1.2.x), byte by byte.
LAYOUTS = [
    (InitiateSegmentedRead(2, 0x1008, 0), 0x81, "02 08 10 00"),
    (SegmentRead(toggle=True), 0x62, "01 00"),
    (SegmentRead(toggle=False), 0x62, "00 00"),
    (WriteObject(1, 0x6040, 0, bytes.fromhex("06 00 00 00")), 0x68, "01 40 60 00 06 00 00 00"),
    (InitiateSegmentedWrite(0, 0x2100, 1, length=300), 0x69, "00 00 21 01 2C 01 00 00"),
    (SegmentWrite(b"abc", toggle=False, last=True), 0x6A, "03 02 61 62 63 00"),
    (SegmentWrite(b"ab", toggle=True, last=False), 0x6A, "02 01 61 62"),
    (SendNMTService(2, 0x81), 0x70, "02 00 81 00"),
    (InitiateSegmentedReadAnswer(0, 5, b"EPOS4"), 0x00, "00 00 00 00 05 00 00 00 05 45 50 4F 53 34"),
    (InitiateSegmentedReadAnswer(0, 5, b""), 0x00, "00 00 00 00 05 00 00 00 00 00"),
    (SegmentReadAnswer(0, b"EPOS", toggle=False, last=False), 0x00, "00 00 00 00 04 00 45 50 4F 53"),
    (SegmentReadAnswer(0, b"4", toggle=True, last=True), 0x00, "00 00 00 00 01 03 34 00"),
    (StatusAnswer(0x06010002), 0x00, "02 00 01 06"),
    (SegmentWriteAnswer(0, 3, toggle=True), 0x00, "00 00 00 00 03 01"),
]


@pytest.mark.parametrize("msg,opcode,payload", LAYOUTS, ids=[repr(m) for m, _, _ in LAYOUTS])
def test_layouts(msg, opcode: int, payload: str) -> None:  # type: ignore[no-untyped-def]
    data = bytes.fromhex(payload)
    assert msg.payload() == data
    assert msg.encode() == reference_frame(opcode, data)
    (frame,) = decode_frames(reference_frame(opcode, data))
    if opcode:
        assert decode_request(frame) == msg
    else:
        assert decode_answer(frame, {InitiateSegmentedReadAnswer: InitiateSegmentedRead,
                                     SegmentReadAnswer: SegmentRead, StatusAnswer: WriteObject,
                                     SegmentWriteAnswer: SegmentWrite}[type(msg)]) == msg


@pytest.mark.parametrize("request_type", [ReadObject, InitiateSegmentedRead, SegmentRead, SegmentWrite])
def test_short_error_answers_are_accepted(request_type: type) -> None:
    (frame,) = decode_frames(reference_frame(0x00, bytes.fromhex("00 00 02 06")))
    ans = decode_answer(frame, request_type)
    assert ans.error_code == 0x06020000


def test_generic_answer_without_context() -> None:
    (frame,) = decode_frames(GUIDE_ANSWER)
    assert decode_answer(frame) == Answer(0, bytes.fromhex("01 90 00 00"))


@pytest.mark.parametrize("payload", ["", "00 00", "00 00 00 00 01 00"])
def test_malformed_answers_raise(payload: str) -> None:
    frame = Frame(0x00, bytes.fromhex(payload), 0)
    with pytest.raises(MessageFormatError):
        decode_answer(frame, ReadObject)


def test_unknown_request_opcode() -> None:
    with pytest.raises(MessageFormatError):
        decode_request(Frame(0x55, b"", 0))


def test_answer_is_not_a_request_opcode() -> None:
    with pytest.raises(MessageFormatError):
        decode_answer(Frame(0x60, b"\x00" * 8, 0), ReadObject)


@pytest.mark.parametrize("build", [
    lambda: ReadObject(256, 0, 0), lambda: ReadObject(1, 0x10000, 0), lambda: ReadObject(1, 0, 256),
    lambda: WriteObject(1, 0x6040, 0, b"\x06"), lambda: SegmentWrite(bytes(256), False, False),
    lambda: InitiateSegmentedWrite(0, 0, 0, length=-1),
])
def test_invalid_fields_are_refused(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(LocalProtocolError):
        build()


addr = st.tuples(st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(0, 255))
requests = st.one_of(
    addr.map(lambda a: ReadObject(*a)),
    addr.map(lambda a: InitiateSegmentedRead(*a)),
    st.booleans().map(SegmentRead),
    st.tuples(addr, st.binary(min_size=4, max_size=4)).map(lambda t: WriteObject(*t[0], data=t[1])),
    st.tuples(addr, st.integers(0, 2**32 - 1)).map(lambda t: InitiateSegmentedWrite(*t[0], length=t[1])),
    st.builds(SegmentWrite, st.binary(max_size=255), st.booleans(), st.booleans()),
    st.builds(SendNMTService, st.integers(0, 0xFFFF), st.integers(0, 0xFFFF)),
)
code = st.integers(0, 2**32 - 1)
answers = st.one_of(
    st.tuples(code, st.binary(min_size=4, max_size=4)).map(lambda t: (ReadObject, ReadObjectAnswer(*t))),
    st.builds(InitiateSegmentedReadAnswer, code, st.integers(0, 2**32 - 1), st.binary(max_size=255))
    .map(lambda a: (InitiateSegmentedRead, a)),
    st.builds(SegmentReadAnswer, code, st.binary(max_size=255), st.booleans(), st.booleans())
    .map(lambda a: (SegmentRead, a)),
    st.builds(SegmentWriteAnswer, code, st.integers(0, 255), st.booleans()).map(lambda a: (SegmentWrite, a)),
    st.builds(StatusAnswer, code).map(lambda a: (WriteObject, a)),
)


@given(requests)
def test_request_round_trip(msg) -> None:  # type: ignore[no-untyped-def]
    (frame,) = decode_frames(msg.encode())
    assert decode_request(frame) == msg


@given(answers)
def test_answer_round_trip(pair) -> None:  # type: ignore[no-untyped-def]
    request_type, msg = pair
    (frame,) = decode_frames(msg.encode())
    assert decode_answer(frame, request_type) == msg


def test_error_table_is_the_guides() -> None:
    # Table 6-21 has 22 rows; every enum member is in the table and vice versa.
    assert len(ERROR_TABLE) == 22
    assert {int(c) for c in ErrorCode} == set(ERROR_TABLE)
    assert describe_error(0x06020000) == "Object does not exist error"
    assert ERROR_TABLE[0x0F00FFC0].cause == "Device is in wrong NMT state"
    assert describe_error(0x12345678) == "Unknown error 0x12345678"


def test_device_error_text() -> None:
    err = DeviceError(0x06020000)
    assert err.code == 0x06020000
    assert str(err) == "0x06020000 Object does not exist error"
