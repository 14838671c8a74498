"""epos_link.tools.follow: lines as they arrive, with bounded waits and injected time."""
from __future__ import annotations

import os
from pathlib import Path

from epos_link.tools.follow import RESTART, follow_file, stream_lines


class FakeTime:
    """A clock that advances only when the code under test sleeps; each sleep
    may run an action (append to the file) first."""

    def __init__(self, actions: list) -> None:  # type: ignore[type-arg]
        self.now = 0.0
        self.actions = list(actions)
        self.sleeps = 0

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        if self.actions:
            self.actions.pop(0)()
        self.now += seconds


def test_follow_sees_appends_partial_lines_and_truncation(tmp_path: Path) -> None:
    path = tmp_path / "cap.txt"
    path.write_text("a\nb")

    def append(text: str):  # type: ignore[no-untyped-def]
        return lambda: path.open("a").write(text)

    def truncate() -> None:
        path.write_text("x\n")

    t = FakeTime([append("c\n"), lambda: None, append("d\n"), truncate])
    lines = list(follow_file(str(path), poll=0.2, idle_exit=1.0, clock=t.clock, sleep=t.sleep))
    assert lines == ["a", "bc", "d", RESTART, "x"]
    assert t.now < 2.0  # stopped by idle_exit, on the fake clock


def test_follow_bounds_a_line_without_newline(tmp_path: Path) -> None:
    path = tmp_path / "cap.txt"
    path.write_bytes(b"z" * 25)
    t = FakeTime([])
    lines = list(follow_file(str(path), idle_exit=0.0, clock=t.clock, sleep=t.sleep, max_line=10))
    assert lines == ["z" * 10, "z" * 10, "z" * 5]


def test_stream_lines_gives_each_line_before_the_end() -> None:
    r, w = os.pipe()
    try:
        os.write(w, b"one\ntw")
        gen = stream_lines(r, poll=0.01)
        assert next(gen) == "one"  # the writer is still open: the line came as it arrived
        os.write(w, b"o\n")
        assert next(gen) == "two"
        os.write(w, b"tail")
        os.close(w)
        w = -1
        assert list(gen) == ["tail"]
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)


def test_stream_lines_idle_exit() -> None:
    r, w = os.pipe()
    try:
        now = [0.0]

        def clock() -> float:
            now[0] += 1.0
            return now[0]

        assert list(stream_lines(r, poll=0.001, idle_exit=3.0, clock=clock)) == []
    finally:
        os.close(r)
        os.close(w)
