"""``epos-link record --on-drive``: the EPOS4's own recorder configured, armed, read back.

Issue 34, must show 2: on the simulator, samples at 1 ms whose positions match the
simulator's profile. In process with a virtual clock (exact: the drive's recorder
samples in the drive's time, so the positions are the profile's at each millisecond,
to the increment), and through ``epos-link sim --tcp`` as a user runs it, moved by
``examples/pp_move.py`` over socketcand.
"""
from __future__ import annotations

import csv
import math
import re
import struct
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest

from epos_link import data_recorder as f
from epos_link.cli import main
from epos_link.client import EposClient
from epos_link.data_recorder import Control, TriggerMode
from epos_link.errors import LocalProtocolError
from epos_link.simulator.clock import VirtualClock
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.motion import plan_position
from epos_link.simulator.transport import SimTransport
from epos_link.simulator.units import units_of
from epos_link.tools.objects import load_directory
from epos_link.tools.record import parse_trigger, resolve
from epos_link.tools.record_on_drive import Plan, plan, record_on_drive
from epos_link.tools.recording import Crossing, Immediate
from tests.test_record_plot import plot_panels

ROOT = Path(__file__).resolve().parent.parent
OBJECTS = ["position_actual_value", "velocity_actual_value", "statusword"]
TARGET = 20000


def _targets(texts: list[str], trigger: str = "move", node: int = 2) -> tuple:
    directory = load_directory(None, node)
    targets = [resolve(directory, node, t) for t in texts]
    named = list(targets)
    parsed = parse_trigger(trigger, targets, directory, node)
    return named, parsed, targets


# --- the plan: what is written to the recorder ---------------------------------------------


def test_a_move_at_1_ms_for_0_4_s_with_20_ms_before() -> None:
    named, trigger, all_targets = _targets(OBJECTS)
    config = plan(named, trigger, all_targets, 0.001, 0.4, 0.02)
    assert config == Plan(variables=(0x60640000, 0x606C0000, 0x60410000, 0), period=100,
                          samples=421, preceding=20, trigger_variable=0x60410000,
                          mode=TriggerMode.RISING_EDGE, high=0x1000, low=0, mask=0x1000,
                          control=Control.START)
    writes = config.writes()
    assert writes[0] == (0x31E4, 1, 0, 2)  # stop first: the configuration may change then
    assert (0x31E1, 1, 100, 2) in writes and (0x31E2, 6, 20, 2) in writes


def test_thresholds_map_to_the_drives_crossing_modes() -> None:
    named, trigger, all_targets = _targets(["position_actual_value"], "position_actual_value>1000")
    assert isinstance(trigger, Crossing)
    up = plan(named, trigger, all_targets, 0.001, 0.1, 0)
    # record's crossing "first sample at or above 1000": rising over 999 (v > 999, prev <= 999)
    assert (up.mode, up.high, up.trigger_variable) == (TriggerMode.RISING_OVER_VALUE, 999,
                                                       0x60640000)
    named, trigger, all_targets = _targets(["position_actual_value"], "position_actual_value<-2.5")
    down = plan(named, trigger, all_targets, 0.001, 0.1, 0)
    # "at or below -2.5" on integers is v <= -3: falling under -2 (v < -2, prev >= -2)
    assert (down.mode, down.high) == (TriggerMode.FALLING_UNDER_VALUE, f.unsigned32(-2))
    # a trigger on an object not recorded: the drive watches it, no column is added
    named, trigger, all_targets = _targets(["velocity_actual_value"], "statusword>0")
    assert plan(named, trigger, all_targets, 0.001, 0.1, 0).trigger_variable == 0x60410000


def test_now_starts_with_the_trigger_forced() -> None:
    named, trigger, all_targets = _targets(["statusword"], "now")
    assert isinstance(trigger, Immediate)
    assert plan(named, trigger, all_targets, 0.0004, 0.1, 0).control is Control.START_FORCED


def test_without_period_the_shortest_that_holds_the_recording() -> None:
    named, trigger, all_targets = _targets(["statusword"], "now")
    assert plan(named, trigger, all_targets, 0.0, 0.1, 0).period == 40  # 0.4 ms: 251 samples
    config = plan(named, trigger, all_targets, 0.0, 2.0, 0.5)
    assert config.samples <= 500 and config.period * 10e-6 * 499 >= 2.5 - 1e-9


@pytest.mark.parametrize("texts, period, duration, pre, why", [
    (OBJECTS + ["0x6062", "0x607A"], 0.001, 0.1, 0, "at most 4 objects"),
    (["position_actual_value"], 0.001, 1.0, 0, "needs 1001"),
    (["position_actual_value"], 0.0003, 0.1, 0, "outside the recorder's 0.4 ms"),
    (["position_actual_value"], 0.001005, 0.1, 0, "whole number of 10 us"),
])
def test_what_the_recorder_cannot_hold_is_one_line(texts: list[str], period: float,
                                                   duration: float, pre: float, why: str) -> None:
    named, trigger, all_targets = _targets(texts, "now")
    with pytest.raises(LocalProtocolError, match=re.escape(why)):
        plan(named, trigger, all_targets, period, duration, pre)


# --- recorded in the simulated drive ---------------------------------------------------------


def _start_move(client: EposClient, node: int) -> None:
    def put(index: int, value: int, size: int) -> None:
        client.download(node, index, 0, value.to_bytes(size, "little", signed=True))
    put(0x6060, 1, 1)
    for cw in (0x06, 0x07, 0x0F):
        put(0x6040, cw, 2)
    put(0x607A, TARGET, 4)
    put(0x6040, 0x1F, 2)


def _int(value: object) -> int:
    assert isinstance(value, int) and not isinstance(value, bool)
    return value


def test_samples_at_1_ms_are_the_simulators_profile_to_the_increment() -> None:
    clock = VirtualClock(50.0)
    sim = Epos4Simulator(1, [], clock=clock)
    named, trigger, all_targets = _targets(OBJECTS, node=1)
    config = plan(named, trigger, all_targets, 0.001, 0.45, 0.01)
    moved: list[float] = []
    polls = 0

    def sleep(dt: float) -> None:  # the host's polling: the move starts during the 3rd wait
        nonlocal polls
        polls += 1
        clock.advance(dt / 2)
        if polls == 3:
            _start_move(client, 1)
            moved.append(clock())
        clock.advance(dt / 2)

    with EposClient(SimTransport(sim)) as client:
        recording = record_on_drive(client, 1, named, config, clock=clock, sleep=sleep)
        store = sim.drive(1).store
        units = units_of(store)
        v, a, d = (store.get_int(i) for i in (0x6081, 0x6083, 0x6084))
    sim.close()
    assert recording.triggered and not recording.interrupted
    rows = [(t, tuple(_int(v) for v in row)) for t, row in recording.rows()]
    assert len(rows) == 461 and rows[10][0] == 0.0 and rows[0][0] == pytest.approx(-0.010)
    assert all(b[0] - a[0] == pytest.approx(0.001) for a, b in zip(rows, rows[1:]))
    profile = plan_position(0.0, 0.0, 0.0, TARGET, units.velocity_to_inc_s(v),
                            units.acceleration_to_inc_s2(a), units.acceleration_to_inc_s2(d))
    at: Callable[[float], float] = lambda t: profile.state_at(max(t, 0.0))[0]
    # The trigger sample is the first sampling instant at or after the move's start:
    # within one period after it. The whole curve fixes where.
    offsets = [k * 1e-5 for k in range(0, 101)]

    def worst(offset: float) -> float:
        return max(abs(row[0] - at(t + offset)) for t, row in rows)

    best = min(offsets, key=worst)
    assert worst(best) <= 1.0, (best, worst(best))  # the counter is whole increments
    assert 0.0 <= best <= 0.001  # a move starting on a sampling instant shows at the next
    for t, (_, velocity, _) in rows:  # and the velocity column is the profile's too
        speed = profile.state_at(max(t + best, 0.0))[1]
        assert abs(velocity - units.velocity_from_inc_s(speed)) <= 1, t
    positions = [row[0] for _, row in rows]
    assert positions[:10] == [0] * 10
    assert all(b >= a for a, b in zip(positions, positions[1:])) and positions[-1] > 10000
    statuswords = [row[2] for _, row in rows]
    assert all(not w & 0x1000 for w in statuswords[:10]) and statuswords[10] & 0x1000
    assert isinstance(statuswords[0], int) and 0 <= statuswords[0] <= 0xFFFF
    assert moved and math.isfinite(moved[0])


def test_the_command_through_sim_tcp_at_1_ms(tmp_path: Path) -> None:
    """As a user runs it: epos-link sim, record --on-drive, examples/pp_move.py."""
    sys.path.insert(0, str(ROOT))
    from examples.pp_move import move

    cli = [sys.executable, "-m", "epos_link"]
    sim = subprocess.Popen([*cli, "sim", "--tcp", "127.0.0.1:0", "--drives", "2",
                            "--can-server", "127.0.0.1:0"], cwd=ROOT, stdout=subprocess.PIPE,
                           text=True)
    try:
        assert sim.stdout is not None
        url = re.search(r"socket://\S+", sim.stdout.readline())
        assert url is not None
        can = None
        while can is None:
            can = re.search(r"socketcand at (\S+)", sim.stdout.readline())
        table, page = tmp_path / "move.csv", tmp_path / "move.html"
        record = subprocess.Popen([*cli, "record", url.group(0), "--node", "2", *OBJECTS,
                                   "--on-drive", "--period", "0.001", "--duration", "0.4",
                                   "--pre", "0.02", "--trigger", "move", "--csv", str(table),
                                   "--plot", str(page),
                                   # The simulated gateway uploads the whole buffer (241 CAN
                                   # segments through threads) before it answers the initiate;
                                   # a loaded machine took more than the 0.5 s default (CI).
                                   "--timeout", "5"],
                                  cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True)
        assert record.stderr is not None
        assert "waiting for the trigger" in record.stderr.readline()
        move(can.group(1), 2, TARGET)
        out, err = record.communicate(timeout=120)
        assert record.returncode == 0, err
    finally:
        sim.terminate()
        sim.wait(timeout=30)
    assert out.startswith("recorded 421 samples (20 before the trigger) of 3 objects in the "
                          "drive, every 1 ms; wrote ")
    rows = list(csv.reader(table.open()))
    assert rows[0] == ["time [s]", "position actual value [inc]", "velocity actual value [rpm]",
                       "statusword", "statusword state"]
    times = [float(r[0]) for r in rows[1:]]
    assert times[0] == pytest.approx(-0.02) and times[20] == 0.0 and times[-1] == pytest.approx(0.4)
    assert all(b - a == pytest.approx(0.001) for a, b in zip(times, times[1:]))
    positions = [int(r[1]) for r in rows[1:]]
    assert positions[20] <= 1 and positions[-1] > 10000
    assert plot_panels(page.read_text())  # the plot's charts (epos_link/tools/plot_html.py)


def test_one_line_and_exit_2_for_what_the_drive_cannot_record(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["record", "sim://?drives=2", "--node", "2", "position_actual_value",
                 "--on-drive", "--period", "0.001", "--duration", "1",
                 "--csv", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "at most 500 samples per object" in err
    assert not (tmp_path / "x.csv").exists()


def test_buffers_hold_int32_little_endian() -> None:
    assert struct.pack("<i", -2) == b"\xfe\xff\xff\xff"
    assert f.decode_buffer(b"\xfe\xff\xff\xff") == [-2]
