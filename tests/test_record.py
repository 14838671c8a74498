"""``epos-link record`` against the simulator: sampling against the simulator's own
clock, the position against its motion profile, the SDO traffic, Ctrl-C, and the
whole command through ``epos-link sim --tcp`` at a 5 ms period (issue 25, must show 1).

The plots' contents are tests/test_record_plot.py's.
"""
from __future__ import annotations

import csv
import re
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest

from epos_link.cli import main
from epos_link.client import EposClient
from epos_link.errors import LocalProtocolError
from epos_link.simulator.clock import VirtualClock
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.motion import plan_position
from epos_link.simulator.transport import SimTransport
from epos_link.simulator.units import units_of
from epos_link.tools.access import read_value
from epos_link.tools.objects import load_directory
from epos_link.tools.record import parse_trigger, resolve, sample_loop
from epos_link.tools.recording import Crossing, MoveStart, Phase, Recorder, Schedule, median_interval
from tests.test_record_plot import plot_panels

ROOT = Path(__file__).resolve().parent.parent
OBJECTS = ["position_actual_value", "velocity_actual_value", "statusword"]
TARGET = 20000


def _u(value: int, size: int) -> bytes:
    return value.to_bytes(size, "little", signed=True)


def _start_move(client: EposClient, node: int) -> None:
    """Profile position mode, enable, and a new set-point (CiA 402-2 6.6)."""
    client.download(node, 0x6060, 0, _u(1, 1))
    for cw in (0x06, 0x07, 0x0F):
        client.download(node, 0x6040, 0, _u(cw, 2))
    client.download(node, 0x607A, 0, _u(TARGET, 4))
    client.download(node, 0x6040, 0, _u(0x1F, 2))


def test_sampling_on_the_simulators_own_clock() -> None:
    """A virtual clock shared by the simulator and the sampler: the rows fall exactly on the
    5 ms grid, the pre-trigger and post-trigger counts are exact, the trigger row is the
    first after the move's start, and position and velocity are the profile's."""
    clock = VirtualClock(100.0)
    sim = Epos4Simulator(1, [], clock=clock)
    directory = load_directory(None, 1)
    with EposClient(SimTransport(sim)) as client:
        targets = [resolve(directory, 1, text) for text in OBJECTS]
        trigger = parse_trigger("move", targets, directory, 1)
        assert isinstance(trigger, MoveStart) and trigger.column == 2  # the statusword, named
        move_at: list[float] = []
        calls = 0

        def read_row() -> tuple:
            nonlocal calls
            calls += 1
            if calls == 31:  # the move starts just before the 31st row's reads
                _start_move(client, 1)
                move_at.append(clock())
            return tuple(t.type.decode(read_value(client, t)) for t in targets)

        recorder = Recorder(trigger, duration=0.8, pre=0.05)
        schedule = Schedule(0.005)
        outcome = sample_loop(read_row, recorder, schedule, clock=clock, sleep=clock.advance)
        store = sim.drive(1).store
        units = units_of(store)
        v, a, d = (store.get_int(i) for i in (0x6081, 0x6083, 0x6084))
    sim.close()
    assert recorder.phase is Phase.DONE and not outcome.interrupted and schedule.missed == 0
    assert recorder.trigger_time == move_at[0] == pytest.approx(100.0 + 30 * 0.005)
    rows = recorder.rows()
    times = [t for t, _ in rows]
    assert len(recorder.before) == 10 and len(recorder.after) == 161      # 50 ms before, 0..800 ms
    assert times == pytest.approx([k * 0.005 for k in range(-10, 161)], abs=1e-9)
    assert median_interval(times) == pytest.approx(0.005, abs=1e-12)
    profile = plan_position(move_at[0], 0.0, 0.0, TARGET, units.velocity_to_inc_s(v),
                            units.acceleration_to_inc_s2(a), units.acceleration_to_inc_s2(d))
    for t, (position, velocity, _) in rows:
        p, speed = profile.state_at(max(move_at[0], move_at[0] + t))
        assert abs(position - p) <= 1, t
        assert abs(velocity - units.velocity_from_inc_s(speed)) <= 1, t
    assert rows[-1][1][0] == TARGET


def test_the_traffic_is_one_read_object_per_object_per_sample(tmp_path: Path) -> None:
    """Must show 4 (part): 60A9h once (a velocity is recorded), then N ReadObjects a row."""
    trace, table = tmp_path / "trace.txt", tmp_path / "rec.csv"
    code = main(["record", "sim://?drives=2", "--node", "2", *OBJECTS, "--duration", "0.05",
                 "--trace", str(trace), "--csv", str(table)])
    assert code == 0
    sent = [bytes.fromhex(line.split(" ", 2)[2]) for line in trace.read_text().splitlines()
            if " TX " in line]
    assert all(frame[2] == 0x60 for frame in sent)  # ReadObject op code (guide 2.1.1.1), nothing else
    asked = [(frame[4], int.from_bytes(frame[5:7], "little"), frame[7]) for frame in sent]
    rows = list(csv.reader(table.open()))[1:]
    assert asked[0] == (2, 0x60A9, 0)
    assert asked[1:] == [(2, 0x6064, 0), (2, 0x606C, 0), (2, 0x6041, 0)] * len(rows)


def test_a_position_only_recording_reads_no_unit(tmp_path: Path) -> None:
    trace = tmp_path / "trace.txt"
    assert main(["record", "sim://?drives=2", "--node", "2", "0x6064", "--duration", "0.02",
                 "--trace", str(trace), "--csv", str(tmp_path / "r.csv")]) == 0
    tx = [line for line in trace.read_text().splitlines() if " TX " in line]
    assert all("64 60 00" in line for line in tx)


def test_ctrl_c_keeps_what_was_recorded() -> None:
    calls = 0

    def read_row() -> tuple:
        nonlocal calls
        calls += 1
        if calls == 5:
            raise KeyboardInterrupt
        return (calls,)

    clock = VirtualClock()
    recorder = Recorder(Crossing(0, 10, True), duration=1, pre=1)
    outcome = sample_loop(read_row, recorder, Schedule(0.01), clock=clock, sleep=clock.advance)
    assert outcome.interrupted and [v for _, v in recorder.rows()] == [(1,), (2,), (3,), (4,)]


def test_bad_objects_and_triggers_are_usage_errors(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    directory = load_directory(None, 2)
    targets = [resolve(directory, 2, "0x6064")]
    with pytest.raises(LocalProtocolError):
        parse_trigger("sometimes", targets, directory, 2)
    trigger = parse_trigger("velocity_actual_value > 100", targets, directory, 2)
    assert trigger == Crossing(1, 100.0, True) and len(targets) == 2  # added as a column
    with pytest.raises(LocalProtocolError):
        resolve(directory, 2, "Manufacturer device name")  # a string: not sampled
    assert main(["record", "sim://", "--node", "0", "no_such_object", "--csv", str(tmp_path / "r.csv")]) == 2
    assert "no object named" in capsys.readouterr().err


def test_a_png_without_matplotlib_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    assert main(["record", "sim://", "--node", "0", "0x6064", "--plot", "x.png"]) == 2
    assert "pip install 'epos-link[plot]'" in capsys.readouterr().err


# --- the whole command through epos-link sim --tcp (issue 25, must show 1) ------------------


def _first_line(proc: subprocess.Popen, pattern: str) -> re.Match:
    assert proc.stdout is not None
    for _ in range(10):
        found = re.search(pattern, proc.stdout.readline())
        if found:
            return found
    raise AssertionError(f"no line matching {pattern!r}")


def test_record_a_move_at_5_ms_through_sim_tcp(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="the PNG needs matplotlib (pip install 'epos-link[plot]')")
    sys.path.insert(0, str(ROOT))
    from examples.pp_move import move

    cli = [sys.executable, "-m", "epos_link"]
    sim = subprocess.Popen([*cli, "sim", "--tcp", "127.0.0.1:0", "--drives", "2",
                            "--can-server", "127.0.0.1:0"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        url = _first_line(sim, r"socket://\S+").group(0)
        can = _first_line(sim, r"socketcand at (\S+)").group(1)
        table, png, page = tmp_path / "move.csv", tmp_path / "move.png", tmp_path / "move.html"
        record = subprocess.Popen([*cli, "record", url, "--node", "2", *OBJECTS, "--period", "0.005",
                                   "--duration", "1", "--pre", "0.5", "--trigger", "move",
                                   "--csv", str(table), "--plot", str(png), "--plot", str(page)],
                                  cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        _first_line(record, r"waiting for the trigger")
        move(can, 2, TARGET)
        out, _ = record.communicate(timeout=120)
        assert record.returncode == 0, out
    finally:
        sim.terminate()
        sim.wait(timeout=30)
    rows = list(csv.reader(table.open()))
    assert rows[0] == ["time [s]", "position actual value [inc]", "velocity actual value [rpm]",
                       "statusword", "statusword state"]
    times = [float(r[0]) for r in rows[1:]]
    positions = [int(r[1]) for r in rows[1:]]
    gap = median_interval(times)
    # Never faster than the 5 ms period (recording.py: Schedule). Whether the link keeps
    # every slot is a speed, which a loaded 2-core machine does not always give (issue 32:
    # medians of 9.8 and 10.7 ms with the suite on 3-4 workers, slots skipped and counted;
    # the row's time is the middle of its reads, so not on the grid either): speed is a
    # benchmark's business (GUIDE.md).
    assert gap is not None and gap >= 0.005 - 0.0005, gap
    # Samples before the trigger are kept for --pre: 0.5 s, ten times the longest gap a
    # loaded suite run showed there (with --pre 0.05 one run kept none: the last sample
    # before the trigger came more than 50 ms before it, and recording.py keeps only
    # what lies within --pre).
    assert times[0] < 0 and 0.0 in times and times[-1] >= 1.0 - 1e-6
    _assert_matches_profile(times, positions, gap)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(plot_panels(page.read_text())) == 3


def _assert_matches_profile(times: list[float], positions: list[int], gap: float) -> None:
    """The recorded positions are the simulator's trapezoid (its EDS defaults: 1000 rpm,
    10000 rpm/s, 2000 inc/rev), started at a time fitted within 15 ms of the trigger."""
    od = load_directory(None, 2).od
    per_rev = 4 * int(od[0x3010][1].default)
    v, a, d = (int(od[i].default) * per_rev / 60 for i in (0x6081, 0x6083, 0x6084))
    profile = plan_position(0.0, 0.0, 0.0, TARGET, v, a, d)
    at: Callable[[float], float] = lambda t: profile.state_at(max(t, 0.0))[0]

    def errors(start: float) -> list[float]:
        return sorted(abs(p - at(t - start)) for t, p in zip(times, positions))

    start = min((k * 0.0002 for k in range(-75, 26)), key=lambda s: statistics.median(errors(s)))
    worst = errors(start)
    # A row's time is the middle of its three reads; the position is the first of them:
    # off by up to half the time its reads took, which fill its gap. 2 ms when reads
    # are quick; half the median gap on a loaded machine (at load 10-15 a median error
    # of 5 ms of travel with the 2 ms bound alone: a wall-clock bound, not the recorder's).
    assert statistics.median(worst) <= max(0.002, gap / 2) * v, (start, gap,
                                                                  statistics.median(worst))
    # Nine rows in ten within two gaps of travel: with two CPU hogs the 90th percentile
    # was 18 ms of travel at a 16.4 ms median gap (a row whose reads the machine
    # stretched); the median above is the check of the recorder's timing.
    assert worst[int(0.9 * len(worst))] <= max(0.01, 2 * gap) * v, (start, gap, worst[-5:])
    assert positions[-1] == TARGET
