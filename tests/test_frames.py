"""epos_link.tools.frames: frames with names, typed values and answer times.

Golden bytes: guide 2.2.9 Tables 2-5/2-6 (fixtures/guide_read_home_position.txt)
and the hand-built segmented read of fixtures/client_segmented_read_inline.txt.
"""
from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.capture import read_capture
from epos_link.tools.frames import LinkDecoder
from epos_link.tools.objects import load_directory
from tests.helpers import three_ways

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
REQUEST = bytes.fromhex("90 02 60 02 01 B0 30 00 2E 62")                   # Table 2-5
ANSWER = bytes.fromhex("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")    # Table 2-6


def decoder() -> LinkDecoder:
    return LinkDecoder(load_directory())


@pytest.mark.parametrize("label,chunks,junk", list(three_ways(ANSWER)))
def test_request_and_answer_fed_three_ways(label: str, chunks: list[bytes], junk: bytes) -> None:
    d = decoder()
    events = d.feed(1.0, "TX", REQUEST)
    for i, chunk in enumerate(chunks):
        events += d.feed(1.0 + 0.001 * (i + 1), "RX", chunk)
    events += d.close(2.0)
    frames = [e for e in events if e.is_frame]
    assert [e.decoded.name for e in frames] == ["ReadObject", "ReadObjectAnswer"]
    req, ans = frames
    assert req.obj is not None and req.obj.name == "Home position"
    assert (ans.node, ans.index, ans.subindex, ans.answers) == (1, 0x30B0, 0, "ReadObject")
    assert ans.value == 0x9001 and ans.value_text == "36865 (0x00009001)"
    assert ans.latency is not None and ans.latency > 0
    assert ans.raw == ANSWER and req.raw == REQUEST
    # Junk is shown with its bytes, never hidden; all bytes are accounted for.
    shown = b"".join(e.raw for e in events if e.direction == "RX")
    assert shown == b"".join(chunks)
    if junk:
        assert [e.decoded.problem is not None for e in events if not e.is_frame] == [True, True]


def test_segmented_read_value_comes_with_the_last_segment() -> None:
    capture = read_capture((FIXTURES / "client_segmented_read_inline.txt").read_text())
    d = decoder()
    events = [e for r in capture.records for e in d.feed(r.time, r.direction, r.data)]
    values = [(e.direction, e.value) for e in events]
    assert values[-1] == ("RX", "EPOS4 Compact 50/8 CAN")
    assert all(v is None for _, v in values[:-1])
    assert all(e.obj is not None and e.obj.name == "Manufacturer device name" for e in events)


DAMAGED = [
    ("junk in front", b"\xFF\xEE" + ANSWER, ["not a frame", "ReadObjectAnswer"]),
    # The damaged answer used up the pairing: the next one answers no request (shown as "Answer").
    ("bad CRC then a good frame", ANSWER[:-1] + b"\x00" + ANSWER, ["ReadObjectAnswer", "Answer"]),
    # The stuffing fault drops "90 02 00 04 90", then 0x41 is junk; the good frame still pairs.
    ("stuffing fault then a good frame", bytes.fromhex("90 02 00 04 90 41") + ANSWER,
     ["not a frame", "not a frame", "ReadObjectAnswer"]),
    ("junk after", ANSWER + b"\x11", ["ReadObjectAnswer", "not a frame"]),
]


@pytest.mark.parametrize("label,stream,names", DAMAGED, ids=[d[0] for d in DAMAGED])
def test_damaged_streams_resync(label: str, stream: bytes, names: list[str]) -> None:
    d = decoder()
    d.feed(0.0, "TX", REQUEST)
    events = d.feed(0.1, "RX", stream) + d.close(0.2)
    assert [e.decoded.name for e in events] == names
    assert events[-1].faulty == (label == "junk after")
    assert b"".join(e.raw for e in events) == stream
    if label.startswith("bad CRC"):
        assert events[0].decoded.crc_ok is False and events[0].faulty


@settings(max_examples=50, deadline=None)
@given(st.binary(max_size=200), st.lists(st.integers(1, 40), max_size=10))
def test_random_input_only_gives_events(data: bytes, cuts: list[int]) -> None:
    d = decoder()
    pos = 0
    events = []
    for cut in cuts:
        events += d.feed(0.0, "RX", data[pos:pos + cut])
        pos += cut
    events += d.feed(0.0, "RX", data[pos:]) + d.close(0.0)
    assert all(e.raw for e in events)


def test_segmented_write_value_comes_with_the_last_segment() -> None:
    """fixtures/client_segmented_write.txt: 9 bytes to node 0 0x2100/0x01 in three segments."""
    capture = read_capture((FIXTURES / "client_segmented_write.txt").read_text())
    d = decoder()
    events = [e for r in capture.records for e in d.feed(r.time, r.direction, r.data)]
    tx = [e for e in events if e.direction == "TX"]
    assert [e.decoded.name for e in tx] == ["InitiateSegmentedWrite", "SegmentWrite", "SegmentWrite", "SegmentWrite"]
    assert all((e.node, e.index, e.subindex) == (0, 0x2100, 1) for e in events)
    # 9 bytes fit no fixed-size type: whatever the EDS says of 0x2100/1, no value is made up.
    assert all(e.value is None for e in events)
    assert [e.answers for e in events if e.direction == "RX"] == [
        "InitiateSegmentedWrite", "SegmentWrite", "SegmentWrite", "SegmentWrite"]


def test_statusword_value_names_its_cia402_state() -> None:
    # ReadObject node 2 0x6041/0 and its answer 0x0040, built by tests/reference.py
    # (guide 2.1.1.1 layout): "switch on disabled" by the CiA 402-2 6.4.1.4 state coding.
    from tests.reference import reference_frame

    request = reference_frame(0x60, bytes((2,)) + (0x6041).to_bytes(2, "little") + b"\x00")
    answer = reference_frame(0x00, (0).to_bytes(4, "little") + b"\x40\x00\x00\x00")
    d = decoder()
    events = d.feed(0.0, "TX", request) + d.feed(0.001, "RX", answer)
    ans = events[-1]
    assert ans.value == 0x40 and ans.value_text == "64 (0x0040) [switch on disabled]"
    assert ans.as_json()["meaning"] == "switch on disabled"
