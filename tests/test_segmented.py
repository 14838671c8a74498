"""segmented.py: toggle-bit state machines of guide 2.1.1.2-2.1.1.3 and 2.1.2.2-2.1.2.3.

The machines consume decoded answer objects, so these tests drive them with
answers built field by field as the guide lays them out.
"""
from __future__ import annotations

import subprocess
import sys

import pytest
from hypothesis import given, strategies as st

from epos_link.errors import DeviceError, LocalProtocolError, RemoteProtocolError
from epos_link.messages import (
    InitiateSegmentedRead,
    InitiateSegmentedReadAnswer,
    InitiateSegmentedWrite,
    SegmentRead,
    SegmentReadAnswer,
    SegmentWrite,
    SegmentWriteAnswer,
    StatusAnswer,
)
from epos_link.segmented import (
    SegmentedRead,
    SegmentedWrite,
    SegmentLengthError,
    ToggleBitError,
    TransferState,
)

NAME = b"EPOS4 Compact 50/8 CAN"


def ok_initiate(total: int, first: bytes = b"") -> InitiateSegmentedReadAnswer:
    return InitiateSegmentedReadAnswer(0, total, first)


def seg(data: bytes, toggle: bool, last: bool) -> SegmentReadAnswer:
    return SegmentReadAnswer(0, data, toggle, last)


# --- segmented read ---------------------------------------------------------

def test_read_first_chunk_in_initiate_answer() -> None:
    m = SegmentedRead(1, 0x1008, 0)
    assert m.start() == InitiateSegmentedRead(1, 0x1008, 0)
    assert m.receive(ok_initiate(len(NAME), NAME[:4])) == SegmentRead(False)
    assert m.receive(seg(NAME[4:12], False, False)) == SegmentRead(True)
    assert m.receive(seg(NAME[12:], True, True)) is None
    assert m.done and m.data == NAME and m.segments == 2


def test_read_initiate_answer_without_data() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    assert m.receive(ok_initiate(len(NAME))) == SegmentRead(False)
    assert m.receive(seg(NAME[:10], False, False)) == SegmentRead(True)
    assert m.receive(seg(NAME[10:20], True, False)) == SegmentRead(False)
    assert m.receive(seg(NAME[20:], False, True)) is None
    assert m.data == NAME


def test_read_complete_in_initiate_answer_needs_no_segment() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    assert m.receive(ok_initiate(len(NAME), NAME)) is None
    assert m.data == NAME and m.segments == 0


def test_read_empty_object() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    assert m.receive(ok_initiate(0)) is None
    assert m.data == b""


def test_read_empty_last_segment_is_accepted() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    m.receive(ok_initiate(3, b"abc"[:0]))
    m.receive(seg(b"abc", False, False))
    assert m.receive(seg(b"", True, True)) is None
    assert m.data == b"abc"


@pytest.mark.parametrize("where", ["initiate", "segment"])
def test_read_device_error(where: str) -> None:
    m = SegmentedRead(2, 0x1008, 0)
    m.start()
    if where == "segment":
        m.receive(ok_initiate(10))
        answer: object = SegmentReadAnswer(0x05030000)
    else:
        answer = InitiateSegmentedReadAnswer(0x06020000)
    with pytest.raises(DeviceError) as info:
        m.receive(answer)  # type: ignore[arg-type]
    assert info.value.code == (0x05030000 if where == "segment" else 0x06020000)
    assert "node 2 0x1008/0x00" in str(info.value)
    assert m.state is TransferState.FAILED
    with pytest.raises(LocalProtocolError):
        m.receive(seg(b"x", False, True))


def test_read_toggle_mismatch() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    m.receive(ok_initiate(10))
    m.receive(seg(b"12345", False, False))
    with pytest.raises(ToggleBitError):
        m.receive(seg(b"67890", False, True))  # toggle must be 1 now
    assert m.state is TransferState.FAILED
    assert isinstance(ToggleBitError("x"), RemoteProtocolError)


@pytest.mark.parametrize("initiate, segments", [
    (ok_initiate(4, b"12345"), []),                                 # first chunk too long
    (ok_initiate(4), [seg(b"12345", False, True)]),                 # segment overflows
    (ok_initiate(6), [seg(b"123", False, True)]),                   # last bit too early
    (ok_initiate(6), [seg(b"", False, False)]),                     # no progress
])
def test_read_length_errors(initiate: InitiateSegmentedReadAnswer,
                            segments: list[SegmentReadAnswer]) -> None:
    m = SegmentedRead(0, 0x1008, 0)
    m.start()
    with pytest.raises(SegmentLengthError):
        m.receive(initiate)
        for answer in segments:
            m.receive(answer)
    assert m.state is TransferState.FAILED


def test_read_max_length_is_refused_before_segments() -> None:
    m = SegmentedRead(0, 0x1F50, 1, max_length=100)
    m.start()
    with pytest.raises(LocalProtocolError):
        m.receive(ok_initiate(101))


def test_read_misuse() -> None:
    m = SegmentedRead(0, 0x1008, 0)
    with pytest.raises(LocalProtocolError):
        m.receive(ok_initiate(1))  # not started
    m.start()
    with pytest.raises(LocalProtocolError):
        m.start()
    with pytest.raises(LocalProtocolError):
        _ = m.data  # not done
    with pytest.raises(LocalProtocolError):
        m.receive(seg(b"x", False, True))  # wrong answer type in INITIATING
    with pytest.raises(LocalProtocolError):
        SegmentedRead(256, 0x1008, 0)


@given(st.binary(max_size=600), st.integers(0, 255), st.integers(1, 255))
def test_read_any_split(data: bytes, first: int, size: int) -> None:
    """An ideal device splitting the object any way gives the object back."""
    m = SegmentedRead(0, 0x2000, 1)
    m.start()
    first = min(first, len(data))
    request = m.receive(ok_initiate(len(data), data[:first]))
    pos, toggle = first, False
    while request is not None:
        assert request == SegmentRead(toggle)
        chunk = data[pos:pos + size]
        pos += len(chunk)
        request = m.receive(seg(chunk, toggle, pos >= len(data)))
        toggle = not toggle
    assert m.data == data


# --- segmented write --------------------------------------------------------

def test_write_segments_toggle_and_last_bit() -> None:
    data = b"123456789"
    m = SegmentedWrite(0, 0x2100, 1, data, segment_size=4)
    assert m.start() == InitiateSegmentedWrite(0, 0x2100, 1, length=9)
    assert m.receive(StatusAnswer(0)) == SegmentWrite(b"1234", False, False)
    assert m.receive(SegmentWriteAnswer(0, 4, False)) == SegmentWrite(b"5678", True, False)
    assert m.receive(SegmentWriteAnswer(0, 4, True)) == SegmentWrite(b"9", False, True)
    assert m.receive(SegmentWriteAnswer(0, 1, False)) is None
    assert m.done and m.written == 9 and m.segments == 3


def test_write_one_segment_by_default() -> None:
    data = bytes(range(200))
    m = SegmentedWrite(0, 0x2100, 1, data)
    m.start()
    assert m.receive(StatusAnswer(0)) == SegmentWrite(data, False, True)
    assert m.receive(SegmentWriteAnswer(0, 200, False)) is None


def test_write_empty_data_sends_one_empty_last_segment() -> None:
    m = SegmentedWrite(0, 0x2100, 1, b"")
    assert m.start().length == 0
    assert m.receive(StatusAnswer(0)) == SegmentWrite(b"", False, True)
    assert m.receive(SegmentWriteAnswer(0, 0, False)) is None


def test_write_errors() -> None:
    m = SegmentedWrite(0, 0x2100, 1, b"12345678", segment_size=4)
    m.start()
    with pytest.raises(DeviceError) as info:
        m.receive(StatusAnswer(0x06010002))
    assert info.value.code == 0x06010002

    m = SegmentedWrite(0, 0x2100, 1, b"12345678", segment_size=4)
    m.start()
    m.receive(StatusAnswer(0))
    with pytest.raises(ToggleBitError):
        m.receive(SegmentWriteAnswer(0, 4, True))

    m = SegmentedWrite(0, 0x2100, 1, b"12345678", segment_size=4)
    m.start()
    m.receive(StatusAnswer(0))
    with pytest.raises(SegmentLengthError):
        m.receive(SegmentWriteAnswer(0, 3, False))
    assert m.state is TransferState.FAILED

    m = SegmentedWrite(0, 0x2100, 1, b"12345678", segment_size=4)
    m.start()
    m.receive(StatusAnswer(0))
    with pytest.raises(DeviceError):
        m.receive(SegmentWriteAnswer(0x05030000))


@pytest.mark.parametrize("size", [0, 256])
def test_write_segment_size_range(size: int) -> None:
    with pytest.raises(LocalProtocolError):
        SegmentedWrite(0, 0x2100, 1, b"x", segment_size=size)


@given(st.binary(max_size=1000), st.integers(1, 255))
def test_write_any_size(data: bytes, size: int) -> None:
    """An ideal device that stores each segment ends up with the data."""
    m = SegmentedWrite(0, 0x2100, 1, data, segment_size=size)
    assert m.start().length == len(data)
    request = m.receive(StatusAnswer(0))
    stored, toggle = bytearray(), False
    while request is not None:
        assert request.toggle == toggle and len(request.data) <= size
        stored += request.data
        assert request.last == (len(stored) == len(data))
        request = m.receive(SegmentWriteAnswer(0, len(request.data), toggle))
        toggle = not toggle
    assert bytes(stored) == data


def test_segmented_is_pure() -> None:
    code = (
        "import sys\nbefore = set(sys.modules)\nimport epos_link.segmented\n"
        "new = set(sys.modules) - before\n"
        "print(','.join(m for m in ['serial', 'usb', 'socket', 'asyncio', 'threading', 'time',"
        " 'select'] if m in new))\n"
    )
    out = subprocess.run([sys.executable, "-S", "-c", f"import sys; sys.path[:0] = {sys.path!r}\n" + code],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
