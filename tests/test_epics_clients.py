"""EPICS clients from PyPI against ``tcp-bridge serve --simulate --epics`` (issue 33).

Each client runs in its own process, as at a beamline: pyepics ``epics.Motor``,
ophyd ``EpicsMotor``, ophyd-async ``Motor``, a pyepics monitor on DMOV, and a pyepics
console next to a PSI client on the same axis. One bridge serves the module; each test
moves an axis of its own. Travel times are checked from below (a move of d at v takes
at least d / v), never with a tight upper bound.
"""
from __future__ import annotations

import time
from typing import Iterator

import pytest

from tcp_bridge.cli import send
from tcp_bridge.wire import Status
from tests.epics_harness import NO_SERVER, Console, Served, no_client, run_client

pytestmark = pytest.mark.skipif(NO_SERVER is not None, reason=NO_SERVER or "")

VELO = 4.0  # mm/s: a 4 mm move takes at least 1 s


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    bridge = Served(["--simulate", "--axes", "6"])
    try:
        yield bridge
    finally:
        out = bridge.close()
        assert "Traceback" not in out, out


def psi(bridge: Served, *lines: str) -> list:
    replies = send(bridge.psi, list(lines), timeout=30)
    assert all(r.status is Status.ACK for r in replies), replies
    return [r.value for r in replies]


@pytest.mark.skipif(no_client("epics") is not None, reason=no_client("epics") or "")
def test_pyepics_motor_moves_waits_refuses_beyond_hlm_and_stops(served: Served) -> None:
    out = run_client(f"""
        import json, time, epics
        m = epics.Motor("TST:m2")
        assert epics.caput("TST:m2.CNEN", 1, wait=True, timeout=30) == 1
        m.put("VELO", {VELO}, wait=True); m.put("ACCL", 0.1, wait=True)
        m.put("HLM", 8.0, wait=True)
        t = time.monotonic()
        rc = m.move(4.0, wait=True, timeout=60)
        took = time.monotonic() - t
        rbv = epics.caget("TST:m2.RBV", use_monitor=False)
        hlm = epics.caget("TST:m2.HLM", use_monitor=False)
        # Beyond HLM: the put is accepted, nothing moves, LVIO = 1.
        rc_beyond = m.move(hlm + 5, ignore_limits=True, wait=True, timeout=60)
        lvio = epics.caget("TST:m2.LVIO", use_monitor=False)
        rbv_beyond = epics.caget("TST:m2.RBV", use_monitor=False)
        val_beyond = epics.caget("TST:m2.VAL", use_monitor=False)
        # stop() mid-move: VAL = RBV, DMOV = 1.
        m.move(0.0, wait=False)
        time.sleep(0.5)
        m.stop()
        deadline = time.monotonic() + 30
        while epics.caget("TST:m2.DMOV", use_monitor=False) != 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        stopped = dict(val=epics.caget("TST:m2.VAL", use_monitor=False),
                       rbv=epics.caget("TST:m2.RBV", use_monitor=False),
                       dmov=epics.caget("TST:m2.DMOV", use_monitor=False))
        print(json.dumps(dict(rc=rc, took=took, rbv=rbv, hlm=hlm, rc_beyond=rc_beyond,
                              lvio=lvio, rbv_beyond=rbv_beyond, val_beyond=val_beyond,
                              stopped=stopped)))
        """, served.env)
    assert out["rc"] == 0 and out["rbv"] == pytest.approx(4.0, abs=1e-3)
    assert out["took"] >= 4.0 / VELO * 0.95, out  # returned after the travel time
    assert out["hlm"] == pytest.approx(8.0)
    assert out["rc_beyond"] == -4 and out["lvio"] == 1  # move-with-wait, soft limit seen
    assert out["rbv_beyond"] == pytest.approx(4.0, abs=1e-3)  # nothing moved
    assert out["val_beyond"] == pytest.approx(4.0, abs=1e-3)  # VAL back to the last target
    stopped = out["stopped"]
    assert stopped["dmov"] == 1 and stopped["val"] == pytest.approx(stopped["rbv"], abs=1e-3)
    assert 0.0 < stopped["rbv"] < 4.0, stopped  # stopped on the way, not at 0
    assert float(psi(served, "2R12")[0]) == pytest.approx(stopped["rbv"], abs=1e-3)


@pytest.mark.skipif(no_client("ophyd") is not None, reason=no_client("ophyd") or "")
def test_ophyd_epics_motor_limits_set_wait_and_home_forward(served: Served) -> None:
    psi(served, "3S40=37")  # homing method 37: the actual position is home (CiA 402-2)
    out = run_client(f"""
        import json, time
        from ophyd import EpicsMotor, EpicsSignal
        m = EpicsMotor("TST:m3", name="m3")
        m.wait_for_connection(timeout=60)
        EpicsSignal("TST:m3.CNEN").put(1, wait=True)
        m.velocity.put({VELO}, wait=True)
        m.high_limit_travel.put(6.0, wait=True)
        m.low_limit_travel.put(-6.0, wait=True)
        deadline = time.monotonic() + 30  # the control limits arrive by monitor
        while list(m.limits) != [-6.0, 6.0] and time.monotonic() < deadline:
            time.sleep(0.05)
        limits = list(m.limits)
        t = time.monotonic()
        m.set(4.0).wait(timeout=60)
        took = time.monotonic() - t
        position = m.position
        status = m.home("forward")
        status.wait(timeout=60)
        msta = int(EpicsSignal("TST:m3.MSTA").get(use_monitor=False))
        print(json.dumps(dict(limits=limits, took=took, position=position,
                              homed=status.success, msta=msta)))
        """, served.env)
    assert out["limits"] == pytest.approx([-6.0, 6.0])
    assert out["position"] == pytest.approx(4.0, abs=1e-3)
    assert out["took"] >= 4.0 / VELO * 0.95, out
    assert out["homed"] and out["msta"] & (1 << 14), out  # motor.h RA_HOMED
    assert out["msta"] & (1 << 1)  # RA_DONE


@pytest.mark.skipif(no_client("ophyd_async") is not None, reason=no_client("ophyd_async") or "")
def test_ophyd_async_motor_set_returns_after_the_travel_time(served: Served) -> None:
    out = run_client(f"""
        import asyncio, json, time
        from aioca import caput  # ophyd-async's own CA library (libca from epicscorelibs)
        from ophyd_async.epics.motor import Motor

        async def main():
            m = Motor("TST:m4", name="m4")
            await m.connect(timeout=60)
            await caput("TST:m4.CNEN", 1, wait=True)
            await m.velocity.set({VELO})
            t = time.monotonic()
            await m.set(4.0)
            took = time.monotonic() - t
            return dict(took=took, rbv=await m.user_readback.get_value(),
                        dmov=await m.motor_done_move.get_value())
        print(json.dumps(asyncio.run(main())))
        """, served.env)
    assert out["took"] >= 4.0 / VELO * 0.95, out
    assert out["rbv"] == pytest.approx(4.0, abs=1e-3) and out["dmov"] == 1


@pytest.mark.skipif(no_client("epics") is not None, reason=no_client("epics") or "")
def test_a_dmov_monitor_counts_one_cycle_per_move_zero_length_included(served: Served) -> None:
    console = Console(served.env)
    try:
        assert console("put", "TST:m5.CNEN", value=1, wait=True) == 1
        assert console("put", "TST:m5.VELO", value=20, wait=True) == 1
        assert console("monitor", "TST:m5.DMOV") is True
        for target in (1.0, 1.0, 0.0, 0.0):  # a move, zero-length, a move back, zero-length
            assert console("put", "TST:m5.VAL", value=target, wait=True) == 1
        time.sleep(1.0)  # the last monitor events reach the client
        events = console("events", "TST:m5.DMOV")
    finally:
        console.close()
    assert events == [1] + [0, 1] * 4, events


@pytest.mark.skipif(no_client("epics") is not None, reason=no_client("epics") or "")
def test_epics_and_psi_clients_see_one_axis_and_either_stop_stops_it(served: Served) -> None:
    ca = Console(served.env)
    try:
        assert ca("monitor", "TST:m6.DMOV") is True  # someone watches: moves by others show
        assert ca("put", "TST:m6.CNEN", value=1, wait=True) == 1
        psi(served, "6S05=2", "6S06=50")
        # A PSI move: the CA client's RBV follows; VAL follows when it ends.
        psi(served, "6S02=2", "6S00=1")
        deadline = time.monotonic() + 30
        while psi(served, "6R82")[0] != "1":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        deadline = time.monotonic() + 10
        while ca("get", "TST:m6.DMOV") != 1 or ca("get", "TST:m6.RBV") != pytest.approx(2.0):
            assert time.monotonic() < deadline, "the CA client never saw the PSI move end"
            time.sleep(0.05)
        assert ca("get", "TST:m6.VAL") == pytest.approx(2.0)
        assert float(psi(served, "6R12")[0]) == pytest.approx(ca("get", "TST:m6.RBV"))
        # A CA move: R12 agrees with RBV.
        assert ca("put", "TST:m6.VAL", value=0.5, wait=True) == 1
        assert float(psi(served, "6R12")[0]) == pytest.approx(0.5)
        assert ca("get", "TST:m6.RBV") == pytest.approx(0.5)
        # A PSI stop ends a CA move: its put completes, VAL = RBV = R12.
        assert ca("put", "TST:m6.VAL", value=4.0) == 1  # no wait
        time.sleep(0.6)
        psi(served, "6S00=8")
        deadline = time.monotonic() + 30
        while ca("get", "TST:m6.DMOV") != 1:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        r12 = float(psi(served, "6R12")[0])
        assert 0.5 < r12 < 4.0
        assert ca("get", "TST:m6.RBV") == pytest.approx(r12)
        assert ca("get", "TST:m6.VAL") == pytest.approx(r12)
        # A CA stop ends a PSI move.
        psi(served, "6S02=0", "6S00=1")
        time.sleep(0.4)
        assert ca("put", "TST:m6.STOP", value=1, wait=True) == 1
        deadline = time.monotonic() + 30
        while psi(served, "6R82")[0] != "1":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        stopped_at = float(psi(served, "6R12")[0])
        assert 0.0 < stopped_at < r12
        time.sleep(0.5)
        assert float(psi(served, "6R12")[0]) == stopped_at  # it stays stopped
    finally:
        ca.close()
