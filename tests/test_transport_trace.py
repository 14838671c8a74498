"""The tracing wrapper records a transport's traffic in the capture format."""
from __future__ import annotations

import io
from pathlib import Path

import pytest

from epos_link.capture import Direction, read_capture
from epos_link.errors import TransportError
from epos_link.transports.replay import ReplayTransport
from epos_link.transports.trace import TracingTransport, trace_to_file

SCRIPT = "0 TX 01 02\n0 RX AA\n0 RX BB CC\n0 TX 03\n"


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += 0.25
        return self.now


def test_records_writes_and_non_empty_reads_with_relative_times() -> None:
    out = io.StringIO()
    link = TracingTransport(ReplayTransport(read_capture(SCRIPT)), out, comments=["source: test"],
                            clock=Clock())
    link.write(b"\x01\x02")
    assert link.read(10, 0) == b"\xAA"
    assert link.read(10, 0) == b"\xBB\xCC"
    assert link.read(10, 0) == b""       # nothing recorded for an empty read
    link.reset_input()
    link.write(b"\x03")
    text = out.getvalue()
    assert text.splitlines()[:2] == ["# epos-link capture v1", "# source: test"]
    capture = read_capture(text)
    assert [(r.time, r.direction, r.data) for r in capture.records] == [
        (0.25, Direction.TX, b"\x01\x02"), (0.5, Direction.RX, b"\xAA"),
        (0.75, Direction.RX, b"\xBB\xCC"), (1.0, Direction.TX, b"\x03")]


def test_failures_and_reopen_leave_comments() -> None:
    out = io.StringIO()
    inner = ReplayTransport(read_capture(SCRIPT))
    link = TracingTransport(inner, out)
    inner.close()
    with pytest.raises(TransportError):
        link.write(b"\x01\x02")
    with pytest.raises(TransportError):
        link.read(1, 0)
    link.reopen()
    comments = read_capture(out.getvalue()).comments
    assert any("TX failed" in c and "01 02" in c for c in comments)
    assert any("RX failed" in c for c in comments)
    assert any("link reopened" in c for c in comments)
    assert read_capture(out.getvalue()).records == []


def test_trace_file_replays(tmp_path: Path) -> None:
    path = tmp_path / "t.txt"
    link = trace_to_file(ReplayTransport(read_capture(SCRIPT), url="replay://x"), str(path))
    link.write(b"\x01\x02")
    link.read(10, 0)
    link.read(10, 0)
    link.write(b"\x03")
    link.close()
    again = ReplayTransport(read_capture(path.read_text()))
    again.write(b"\x01\x02")
    assert again.read(10, 0) + again.read(10, 0) == b"\xAA\xBB\xCC"
    again.write(b"\x03")
    again.check_complete()
    assert "# source: epos-link trace of replay://x" in path.read_text()


def test_unwritable_trace_is_a_transport_error(tmp_path: Path) -> None:
    with pytest.raises(TransportError, match="cannot write trace"):
        trace_to_file(ReplayTransport(read_capture(SCRIPT)), str(tmp_path / "no" / "such" / "dir.txt"))
