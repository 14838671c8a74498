"""The pure core of ``epos-link record`` (epos_link/tools/recording.py): the schedule's
grid, the triggers, the bounded pre-trigger buffer, the CSV, and its purity."""
from __future__ import annotations

import csv
import io
import subprocess
import sys

import pytest

from epos_link.tools.recording import (Channel, Crossing, Immediate, MoveStart, Phase, Recorder,
                                       Sample, Schedule, headers, median_interval, unit_of,
                                       velocity_unit, write_csv)

OP_ENABLED = 0x0037      # operation enabled, quick stop off, voltage enabled
ACK = 0x1000             # pp: set-point acknowledge
TARGET_REACHED = 0x0400


def test_the_module_is_pure() -> None:
    code = ("import sys; before = set(sys.modules)\nimport epos_link.tools.recording\n"
            "bad = {'serial','usb','socket','asyncio','threading','time','select','can','canopen'}"
            " & (set(sys.modules) - before)\nprint(','.join(sorted(bad)))")
    out = subprocess.run([sys.executable, "-S", "-c", f"import sys; sys.path[:0] = {sys.path!r}\n" + code],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_schedule_keeps_a_grid_and_skips_slots_the_link_missed() -> None:
    s = Schedule(0.005)
    assert s.due(10.0) == 10.0               # the first sample: at once
    s.taken(10.0, 10.001)
    assert s.due(10.001) == pytest.approx(10.005)
    s.taken(10.005, 10.0175)                 # this one took 12.5 ms: slots 10.010 and 10.015 are past
    assert s.due(10.0175) == pytest.approx(10.020)
    assert s.missed == 2
    s.taken(10.020, 10.025)                  # ends exactly on the next slot: that slot is kept
    assert s.due(10.025) == pytest.approx(10.025) and s.missed == 2


def test_period_zero_is_as_fast_as_the_link() -> None:
    s = Schedule(0)
    s.taken(1.0, 1.002)
    assert s.due(1.002) == 1.002 and s.missed == 0
    with pytest.raises(ValueError):
        Schedule(-1)


@pytest.mark.parametrize("trigger, previous, row, fires", [
    (Immediate(), None, (0,), True),
    (Crossing(0, 100, True), None, (150,), False),       # no predecessor: no crossing
    (Crossing(0, 100, True), (99,), (100,), True),
    (Crossing(0, 100, True), (101,), (150,), False),     # already above: waits
    (Crossing(0, 100, False), (101,), (100,), True),
    (Crossing(0, 100, False), (99,), (50,), False),
    (MoveStart(0), (OP_ENABLED,), (OP_ENABLED | ACK,), True),
    (MoveStart(0), (OP_ENABLED | TARGET_REACHED,), (OP_ENABLED,), True),
    (MoveStart(0), (OP_ENABLED | ACK,), (OP_ENABLED | ACK,), False),
    (MoveStart(0), (0x0040,), (0x0040 | ACK,), False),   # switch on disabled: no move
    (MoveStart(0), (OP_ENABLED,), (OP_ENABLED,), False),
])
def test_triggers(trigger: object, previous: tuple | None, row: tuple, fires: bool) -> None:
    assert trigger.fires(previous, row) is fires  # type: ignore[attr-defined]


def _feed(rec: Recorder, values: list[int], period: float = 0.01) -> None:
    for k, v in enumerate(values):
        if rec.add(Sample(k * period, (v,))) is Phase.DONE:
            break


def test_recorder_keeps_pre_seconds_before_the_trigger_and_duration_after() -> None:
    rec = Recorder(Crossing(0, 50, True), duration=0.05, pre=0.03)
    _feed(rec, list(range(0, 200, 5)))                    # crosses 50 at sample 10 (t = 0.10)
    assert rec.trigger_time == pytest.approx(0.10)
    times = [round(t, 6) for t, _ in rec.rows()]
    assert times == [-0.03, -0.02, -0.01, 0.0, 0.01, 0.02, 0.03, 0.04, 0.05]
    assert rec.phase is Phase.DONE and len(rec.before) == 3


def test_the_ring_buffer_is_bounded_whatever_pre_says() -> None:
    rec = Recorder(Crossing(0, 10**9, True), duration=1, pre=1e9, max_pre=50)
    _feed(rec, [0] * 10_000)
    assert rec.phase is Phase.WAITING and len(rec.before) == 50
    rows = rec.rows()                                      # never triggered: times from the last
    assert rows[-1][0] == 0 and rows[0][0] == pytest.approx(-0.49)


def test_max_samples_stops_the_recording() -> None:
    rec = Recorder(Immediate(), duration=100, max_samples=7)
    _feed(rec, [1] * 100)
    assert rec.phase is Phase.DONE and rec.truncated and len(rec.after) == 7


def test_csv_header_units_state_column_and_values() -> None:
    chans = [Channel(0x6064, 0, "position actual value", "inc"),
             Channel(0x606C, 0, "velocity actual value", "rpm"), Channel(0x6041, 0, "statusword")]
    out = io.StringIO()
    assert write_csv(out, chans, [(-0.005, (0, 0, 0x40)), (0.0, (12, 3, 0x1037))]) == 2
    rows = list(csv.reader(io.StringIO(out.getvalue())))
    assert rows[0] == headers(chans) == ["time [s]", "position actual value [inc]",
                                         "velocity actual value [rpm]", "statusword", "statusword state"]
    assert rows[1] == ["-0.005000", "0", "0", "64", "switch on disabled"]
    assert rows[2] == ["0.000000", "12", "3", "4151", "operation enabled"]


def test_units() -> None:
    assert unit_of(0x6064) == "inc" and unit_of(0x6083) == "rpm/s" and unit_of(0x6041) == ""
    assert unit_of(0x606C, velocity_unit(0x00B44700)) == "rpm"
    assert velocity_unit(0xFDB44700) == "0.001 rpm"
    assert velocity_unit(0x12345678) == ""   # not rpm: no unit rather than a guess


def test_median_interval() -> None:
    assert median_interval([0, 1, 3, 4]) == 1
    assert median_interval([0, 1, 3]) == 1.5
    assert median_interval([5]) is None
