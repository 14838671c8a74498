"""``tcp-bridge record``: an axis recorded through the bridge itself (issue 34, must show 2).

The recording is a PSI client of a bridge on the simulator (tests/bridge_sim.py: the
real epos path, EPOS4 gateway, drives behind it). While the bridge moves axis 2,
another client reads R12 and notes when; every R12 value it got must lie on the
recorded position curve at that time (within one sample interval either side: both
are reads of a moving axis, each at some instant of its request). Plus the pure
parts: commands by number and name, columns, triggers, values, and the command line.
"""
from __future__ import annotations

import csv
import threading
import time
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

from epos_link.tools.recording import STATUSWORD, Crossing, Immediate, MoveStart, Recorder, Schedule
from tcp_bridge import cli
from tcp_bridge.errors import MalformedReply
from tcp_bridge.record import (RefusedRead, Session, channel_of, command_of, parse_trigger, record,
                               value_of)
from tcp_bridge.tables.commands import COMMANDS
from tests.bridge_sim import SimBridge
from tests.test_record_plot import plot_panels


# --- pure parts ------------------------------------------------------------------------


@pytest.mark.parametrize("text, number", [("12", 12), ("R12", 12), ("r14", 14), ("position", 12),
                                          ("Actual Velocity", 14), ("actual_velocity", 14),
                                          ("status", 10), ("R82", 82)])
def test_commands_by_number_or_name(text: str, number: int) -> None:
    assert command_of(text).number == number


@pytest.mark.parametrize("text, why", [("77", "no command 77"), ("R00", "not readable"),
                                       ("speed", "no command of that name"),
                                       ("R16", "not readable"), ("R99", "is text")])
def test_commands_that_cannot_be_recorded(text: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        command_of(text)


def test_columns_name_the_command_and_its_units() -> None:
    position, velocity, status, bit = (channel_of(COMMANDS[n]) for n in (12, 14, 10, 82))
    assert position.header == "position (R12) [user units]"
    assert velocity.header == "actual velocity (R14) [user units/s]"
    assert status.is_statusword and status.header == "status (R10)"
    assert not bit.is_statusword and bit.unit == ""  # a bit of the statusword, not the word


def test_triggers() -> None:
    specs = [COMMANDS[12]]
    assert isinstance(parse_trigger("now", specs), Immediate)
    move = parse_trigger("move", specs)
    assert isinstance(move, MoveStart) and [s.number for s in specs] == [12, 10]
    assert move.column == 1
    crossing = parse_trigger("R12>2.5", specs)
    assert crossing == Crossing(0, 2.5, True)
    below = parse_trigger("actual_velocity<-1", specs)
    assert below == Crossing(2, -1.0, False) and specs[2].number == 14
    for bad in ("soon", "R12>x", "R99>1"):
        with pytest.raises(ValueError):
            parse_trigger(bad, [COMMANDS[12]])


def test_values_are_numbers() -> None:
    assert value_of("567") == 567 and isinstance(value_of("567"), int)
    assert value_of("-1.25") == -1.25
    for bad in (None, "abc", ""):
        with pytest.raises(MalformedReply):
            value_of(bad)


# --- through a bridge on the simulator ---------------------------------------------------


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge(drives=(2,))
    yield b
    b.close()


def _interpolate(curve: List[Tuple[float, float]], t: float) -> float:
    if t <= curve[0][0]:
        return curve[0][1]
    for (t0, p0), (t1, p1) in zip(curve, curve[1:]):
        if t0 <= t <= t1:
            return p0 if t1 == t0 else p0 + (p1 - p0) * (t - t0) / (t1 - t0)
    return curve[-1][1]


def test_a_bridge_move_recorded_matches_r12_reads_taken_during_it(bridge: SimBridge) -> None:
    target = 20.0  # user units (position_factor 1000: 20000 inc)
    bridge.ok("2S04=1", "2S05=10", "2S06=40", f"2S02={target:g}")
    session = Session.open("%s:%d" % bridge.server.addresses[0], 2,
                           [COMMANDS[12], COMMANDS[14]], timeout=10)
    specs = list(session.specs)
    trigger = parse_trigger("move", specs)
    session.specs = specs
    recorder = Recorder(trigger, duration=3.0, pre=0.1)
    done = threading.Event()
    outcome = []

    def run() -> None:
        outcome.append(record(session, recorder, Schedule(0.0)))
        done.set()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    time.sleep(0.3)  # the recorder samples the axis at rest, waiting for the move
    bridge.ok("2S00=1")
    reads: List[Tuple[float, float, float]] = []  # (sent, answered, R12)
    while not done.is_set():
        sent = time.monotonic()
        value = float(bridge.ok("2R12"))
        reads.append((sent, time.monotonic(), value))
    thread.join(10)
    session.close()
    result = outcome[0]
    assert result.error is None, result.error
    assert recorder.trigger_time is not None, "the move did not trigger the recording"
    samples = recorder.samples
    curve = [(s.time, float(s.values[0])) for s in samples]
    times = [t for t, _ in curve]
    gaps = [b - a for a, b in zip(times, times[1:])]
    # A row is stamped at the middle of its reads and its R12 is from somewhere within
    # them: off by up to half their span. A gap between two stamps holds half of each
    # row's span, so half a span is at most one gap, not half of one (a long row between
    # two quick ones: seen at load 10-15, 1 ms of travel beyond the half-gap bound).
    slack = max(gaps)
    during = [r for r in reads if curve[0][0] <= r[0] and r[1] <= curve[-1][0]]
    moving = [r for r in during if 0.0 < r[2] < target]
    assert len(moving) >= 5, f"too few R12 reads during the move: {len(moving)}"
    for sent, answered, value in during:
        low = _interpolate(curve, sent - slack)
        high = _interpolate(curve, answered + slack)
        # 0.002: two increments, the chord of the accelerating curve between two samples
        assert low - 0.002 <= value <= high + 0.002, (sent, answered, value, low, high)
    assert curve[-1][1] == target
    assert any(0.0 < p < target for _, p in curve)


def test_a_refused_read_ends_the_recording_with_what_came_before(bridge: SimBridge) -> None:
    session = Session.open("%s:%d" % bridge.server.addresses[0], 9, [COMMANDS[12]], timeout=10)
    try:
        result = record(session, Recorder(Immediate(), 1.0), Schedule(0.0))
    finally:
        session.close()
    assert isinstance(result.error, RefusedRead) and "9R12: CAN" in str(result.error)


def test_the_command_line_writes_csv_and_plot(bridge: SimBridge, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    where = "%s:%d" % bridge.server.addresses[0]
    table, page = tmp_path / "axis2.csv", tmp_path / "axis2.html"
    rc = cli.main(["record", where, "2", "--duration", "0.2", "--csv", str(table),
                   "--plot", str(page)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert out.out.startswith("recorded ") and f"wrote {table}, {page}" in out.out
    rows = list(csv.reader(table.open()))
    assert rows[0] == ["time [s]", "position (R12) [user units]",
                       "actual velocity (R14) [user units/s]", "status (R10)", "status (R10) state"]
    assert len(rows) >= 3 and rows[1][0] == "0.000000"
    assert plot_panels(page.read_text())  # the plot's charts (epos_link/tools/plot_html.py)


def test_the_command_line_says_what_is_wrong_in_one_line(bridge: SimBridge, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    where = "%s:%d" % bridge.server.addresses[0]
    assert cli.main(["record", where, "2", "R16", "--csv", str(tmp_path / "x.csv")]) == 2
    assert capsys.readouterr().err.strip() == (
        "tcp-bridge record: 'R16': command 16 (Reset Node) is not readable")
    assert cli.main(["record", where, "2"]) == 2  # no output asked for
    assert "nothing would keep the samples" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()
    assert cli.main(["record", where, "9", "--csv", str(tmp_path / "y.csv")]) == 2
    err = capsys.readouterr().err
    assert "9R12: CAN (not a valid request" in err
    with pytest.raises(SystemExit) as exit_:
        cli.main(["record", where, "0", "--csv", "-"])
    assert exit_.value.code == 2


def test_the_statusword_column_is_the_recordings_statusword() -> None:
    assert (channel_of(COMMANDS[10]).index, channel_of(COMMANDS[10]).subindex) == STATUSWORD
