from __future__ import annotations

import io
from pathlib import Path

import pytest

from epos_link.capture import (Capture, CaptureFormatError, CaptureWriter, Direction, Record,
                               read_capture)
from epos_link.framing import decode_frames
from epos_link.messages import ReadObject, ReadObjectAnswer, decode_answer, decode_request
from tests.reference import GUIDE_ANSWER, GUIDE_REQUEST

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


def test_guide_fixture_replays() -> None:
    cap = read_capture((FIXTURES / "guide_read_home_position.txt").read_text())
    assert any("Table 2-5" in c for c in cap.comments)
    assert cap.stream(Direction.TX) == GUIDE_REQUEST
    assert cap.stream(Direction.RX) == GUIDE_ANSWER
    (req,) = decode_frames(cap.stream(Direction.TX))
    (ans,) = decode_frames(cap.stream(Direction.RX))
    assert decode_request(req) == ReadObject(1, 0x30B0, 0)
    assert decode_answer(ans, ReadObject) == ReadObjectAnswer(0, bytes.fromhex("01 90 00 00"))


def test_write_then_read_back() -> None:
    out = io.StringIO()
    w = CaptureWriter(out, comments=["source: unit test"])
    w.write(0.0, "TX", GUIDE_REQUEST)
    w.write(0.001234, Direction.RX, GUIDE_ANSWER)
    cap = read_capture(out.getvalue())
    assert cap.comments == ["epos-link capture v1", "source: unit test"]
    assert cap.records == [Record(0.0, Direction.TX, GUIDE_REQUEST),
                           Record(0.001234, Direction.RX, GUIDE_ANSWER)]


def test_lenient_hex_and_trailing_comment() -> None:
    cap = read_capture("1.5 rx 9002,0x60:02  # note\n\n")
    assert cap.records == [Record(1.5, Direction.RX, bytes.fromhex("90026002"))]


@pytest.mark.parametrize("line", ["0.0", "x TX 00", "0 XX 00", "0 TX 0G", "0 TX 123"])
def test_bad_lines_name_their_number(line: str) -> None:
    with pytest.raises(CaptureFormatError, match="line 2"):
        read_capture("# ok\n" + line)


def test_empty_capture() -> None:
    assert read_capture("") == Capture()


def test_an_error_quotes_at_most_40_characters_of_the_input() -> None:
    from epos_link.capture import CaptureFormatError, excerpt, parse_hex, parse_line

    assert excerpt("short") == "'short'"
    assert excerpt("x" * 41) == f"{'x' * 40!r}... (41 characters)"
    for bad in (lambda: parse_hex("Z" * 10**6), lambda: parse_line("0 TX " + "Z" * 10**6, 3),
                lambda: parse_line("Z" * 10**6, 3), lambda: parse_line("1 " + "Q" * 10**6, 3),
                lambda: parse_line("N" * 10**6 + " TX 90", 3)):
        with pytest.raises(CaptureFormatError) as info:
            bad()
        assert len(str(info.value)) < 120 and "(1000000 characters)" in str(info.value)
