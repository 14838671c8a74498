"""The motor record's motion rules the way a user meets them (issue 33), pyepics in its
own process against ``tcp-bridge serve --simulate --epics``:

* a new target while the axis moves (``motorRecord.cc`` ``process()``, NTM = YES):
  behind the running move, the axis stops and goes to it, DMOV stays 0 and the first
  put (with callback) completes only when the final move ended; ahead of it, the
  running move ends and the axis goes on;
* SPMG: Pause stops and keeps VAL (the put waits, DMOV 0), Go moves to VAL; Stop
  stops with VAL = RBV and ends the waiting put; a target put while stopped waits for
  Go; Move moves once and then pauses;
* MSTA's homed bit comes from the drive: a homing by a PSI client on port 1912 sets
  it, a node reset clears it.

Travel checks go from below (a move of d at v takes at least d / v) or by position,
never by a tight upper time bound; waits are 30 s deadlines on observed states.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Iterator

import pytest

from tcp_bridge.cli import send
from tcp_bridge.wire import Status
from tests.epics_harness import Console, Served, no_client

REASON = no_client("epics")
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")

VELO = 2.0  # mm/s: slow enough that a put lands mid-move on a loaded machine
HOMED = 1 << 14  # motor.h RA_HOMED


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    bridge = Served(["--simulate", "--axes", "6"])
    try:
        yield bridge
    finally:
        out = bridge.close()
        assert "Traceback" not in out, out


@pytest.fixture
def ca(served: Served) -> Iterator[Console]:
    console = Console(served.env)
    try:
        yield console
    finally:
        console.close()


def psi(bridge: Served, *lines: str) -> list:
    replies = send(bridge.psi, list(lines), timeout=30)
    assert all(r.status is Status.ACK for r in replies), replies
    return [r.value for r in replies]


def until(what: Callable[[], Any], why: str, timeout: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if value:
            return value
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.05)


def ready(ca: Console, pv: str) -> None:
    assert ca("put", f"{pv}.CNEN", value=1, wait=True) == 1
    assert ca("put", f"{pv}.VELO", value=VELO, wait=True) == 1
    assert ca("put", f"{pv}.ACCL", value=0.05, wait=True) == 1
    assert ca("monitor", f"{pv}.DMOV") is True
    assert ca("monitor", f"{pv}.RBV") is True


def test_a_target_behind_the_running_move_stops_it_and_goes_there_dmov_stays_0(
        served: Served, ca: Console) -> None:
    pv = "TST:m2"
    ready(ca, pv)
    assert ca("put_async", f"{pv}.VAL", value=4.0) is True  # with callback, like ophyd
    until(lambda: 0.8 < ca("get", f"{pv}.RBV") < 2.5, "the axis never got under way")
    assert ca("complete", f"{pv}.VAL") is False
    assert ca("put", f"{pv}.VAL", value=0.5) == 1  # behind it: NTM stops, then goes
    until(lambda: ca("complete", f"{pv}.VAL"), "the first put never completed")
    rbv, dmov = ca("get", f"{pv}.RBV"), ca("get", f"{pv}.DMOV")
    assert rbv == pytest.approx(0.5, abs=1e-3) and dmov == 1  # completed at the very end
    assert ca("get", f"{pv}.VAL") == pytest.approx(0.5)
    assert float(psi(served, "2R12")[0]) == pytest.approx(0.5, abs=1e-3)
    time.sleep(0.5)  # the last monitor events reach the client
    furthest = max(ca("events", f"{pv}.RBV"))
    assert furthest < 3.5, f"it ran on towards 4 (RBV {furthest}) instead of stopping"
    assert ca("events", f"{pv}.DMOV") == [1, 0, 1]


def test_a_target_ahead_of_the_running_move_is_taken_when_it_ends(
        served: Served, ca: Console) -> None:
    pv = "TST:m3"
    ready(ca, pv)
    assert ca("put_async", f"{pv}.VAL", value=1.5) is True
    until(lambda: ca("get", f"{pv}.RBV") > 0.3, "the axis never got under way")
    assert ca("put", f"{pv}.VAL", value=2.5) == 1  # ahead, same direction: no stop
    until(lambda: ca("complete", f"{pv}.VAL"), "the first put never completed")
    assert ca("get", f"{pv}.RBV") == pytest.approx(2.5, abs=1e-3)
    time.sleep(0.5)
    assert ca("events", f"{pv}.DMOV") == [1, 0, 1]


def test_spmg_pause_keeps_val_and_go_moves_to_it(served: Served, ca: Console) -> None:
    pv = "TST:m4"
    ready(ca, pv)
    t = time.monotonic()
    assert ca("put_async", f"{pv}.VAL", value=3.0) is True
    until(lambda: ca("get", f"{pv}.RBV") > 0.5, "the axis never got under way")
    assert ca("put", f"{pv}.SPMG", value="Pause", wait=True) == 1
    until(lambda: psi(served, "4R82")[0] == "1", "Pause never stopped the axis")
    paused_at = float(psi(served, "4R12")[0])  # the drive's word: RBV may be a poll behind
    time.sleep(1.0)  # it stays paused
    assert 0.5 < paused_at < 2.9, paused_at
    assert float(psi(served, "4R12")[0]) == pytest.approx(paused_at, abs=1e-3)
    assert ca("get", f"{pv}.RBV") == pytest.approx(paused_at, abs=1e-3)
    assert ca("get", f"{pv}.VAL") == pytest.approx(3.0)  # Pause keeps VAL
    assert ca("get", f"{pv}.DMOV") == 0 and ca("get", f"{pv}.MOVN") == 0
    assert ca("complete", f"{pv}.VAL") is False  # the motion is not over
    assert ca("put", f"{pv}.SPMG", value="Go", wait=True) == 1
    until(lambda: ca("complete", f"{pv}.VAL"), "Go never finished the move")
    assert time.monotonic() - t >= 3.0 / VELO * 0.95
    assert ca("get", f"{pv}.RBV") == pytest.approx(3.0, abs=1e-3)
    assert ca("get", f"{pv}.DMOV") == 1
    time.sleep(0.5)
    assert ca("events", f"{pv}.DMOV") == [1, 0, 1]


def test_spmg_stop_sets_val_to_rbv_a_target_waits_for_go_and_move_pauses_after(
        served: Served, ca: Console) -> None:
    pv = "TST:m5"
    ready(ca, pv)
    assert ca("put_async", f"{pv}.VAL", value=3.0) is True
    until(lambda: ca("get", f"{pv}.RBV") > 0.5, "the axis never got under way")
    assert ca("put", f"{pv}.SPMG", value="Stop", wait=True) == 1
    until(lambda: ca("complete", f"{pv}.VAL"), "Stop never ended the put")
    until(lambda: psi(served, "5R82")[0] == "1", "Stop never stopped the axis")
    rbv = float(psi(served, "5R12")[0])
    assert 0.5 < rbv < 2.9 and ca("get", f"{pv}.VAL") == pytest.approx(rbv, abs=1e-3)
    assert ca("get", f"{pv}.RBV") == pytest.approx(rbv, abs=1e-3)
    assert ca("get", f"{pv}.DMOV") == 1
    # While SPMG is Stop a new target is kept, and nothing moves.
    assert ca("put_async", f"{pv}.VAL", value=0.2) is True
    time.sleep(1.0)
    assert ca("get", f"{pv}.RBV") == pytest.approx(rbv, abs=1e-3)
    assert ca("get", f"{pv}.DMOV") == 0 and ca("complete", f"{pv}.VAL") is False
    # Move: goes to VAL once, then SPMG is Pause (maybeRetry()).
    assert ca("put", f"{pv}.SPMG", value="Move", wait=True) == 1
    until(lambda: ca("complete", f"{pv}.VAL"), "Move never finished the move")
    assert ca("get", f"{pv}.RBV") == pytest.approx(0.2, abs=1e-3)
    assert ca("get", f"{pv}.SPMG", as_string=True) == "Pause"
    assert ca("put", f"{pv}.SPMG", value="Go", wait=True) == 1


def test_msta_homed_is_the_drives_a_psi_homing_sets_it_a_node_reset_clears_it(
        served: Served, ca: Console) -> None:
    pv = "TST:m6"
    assert ca("monitor", f"{pv}.MSTA") is True  # someone watches: the record polls
    assert not ca("get", f"{pv}.MSTA") & HOMED
    psi(served, "6S04=1", "6S40=37", "6S00=9")  # method 37: here is home (CiA 402-2)
    until(lambda: ca("get", f"{pv}.MSTA") & HOMED, "a PSI client's homing never showed")
    psi(served, "6S16=1")  # NMT reset node: the drive forgets its reference
    until(lambda: not ca("get", f"{pv}.MSTA") & HOMED, "the drive's reset never showed")
