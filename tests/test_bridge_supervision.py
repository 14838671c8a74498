"""Issue 30 findings 4 and 5 in this process (the SIGTERM/SIGKILL scenarios are
tests/test_bridge_supervision_e2e.py): the ``canopen`` backend on the embedded
simulator's CAN bus with ``heartbeat_ms`` (tests/test_bridge_heartbeat.py's table and
write log).

* A clean shutdown halts a running profile velocity move, waits for standstill, and
  only then switches the drive's consumer off.
* S81 never writes 1016h, 1017h or 6007h of a supervised axis (NAK, logged); on a bus
  without supervision they stay writable.
* ``tcp-bridge check`` reads each drive's supervision and says so, UNSUPERVISED for
  an enabled drive without a consumer.
"""
from __future__ import annotations

import logging
from typing import Any

import pytest

from tcp_bridge.check import check
from tcp_bridge.engine import build_engine
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.wire import Status
from tests.helpers import wait_until
from tests.test_bridge_heartbeat import ask, record_writes, table

ENTRY = (127 << 16) | 150  # 1016h:01 as the bridge sets it: node 127, 3 x 50 ms
HALT = 0x010F  # enable operation with halt (CiA 402-2 6.4.1.3)


def test_a_clean_shutdown_halts_a_velocity_move_before_releasing_the_consumer() -> None:
    engine = build_engine(table(heartbeat_ms=50))
    backend = engine.backends[0]
    writes = record_writes(engine, 2)
    for line in ("2S04=1", "2S05=5", "2S06=50", "2S00=3"):
        assert ask(engine, line) is Status.ACK, line
    sim = backend.simulator

    def velocity() -> float:
        with sim.drives[2].lock:
            sim.drives[2].drive.sync()
            return float(sim.drives[2].drive.velocity)
    wait_until(lambda: velocity() != 0, 10, "the move never started")
    engine.close()
    order = [(i, v) for i, _, v, _ in writes]
    halt = len(order) - 1 - order[::-1].index((0x6040, HALT))  # the last halt written
    release = order.index((0x1016, 0))
    assert halt < release, order[-8:]  # halted first, then released
    assert velocity() == 0  # at rest, not turning unwatched
    assert sim.drives[2].store.get_int(0x1016, 1) == 0


@pytest.mark.parametrize("selector, what", [
    (0x1016 << 16 | 1 << 8 | 4, "consumer"), (0x1017 << 16 | 0 << 8 | 2, "producer"),
    (0x6007 << 16 | 0 << 8 | 2, "abort connection option")])
def test_s81_leaves_a_supervised_axis_s_supervision_alone(
        selector: int, what: str, caplog: pytest.LogCaptureFixture) -> None:
    engine = build_engine(table(heartbeat_ms=50))
    try:
        store = engine.backends[0].simulator.drives[2].store
        assert ask(engine, "2S04=1") is Status.ACK
        before = store.get_int(selector >> 16, (selector >> 8) & 0xFF)
        assert ask(engine, f"2S80={selector}") is Status.ACK
        with caplog.at_level(logging.ERROR), pytest.raises(DeviceFailure, match="supervision"):
            ask(engine, "2S81=0")  # NAK
        assert store.get_int(selector >> 16, (selector >> 8) & 0xFF) == before
        assert f"S81 to 0x{selector >> 16:04X}" in caplog.text and "refused" in caplog.text
    finally:
        engine.close()


def test_without_supervision_s81_writes_6007h_as_before() -> None:
    engine = build_engine(table())
    try:
        assert ask(engine, f"2S80={0x6007 << 16 | 2}") is Status.ACK
        assert ask(engine, "2S81=1") is Status.ACK
        assert engine.backends[0].simulator.drives[2].store.get_int(0x6007, 0) == 1
    finally:
        engine.close()


class Borrowed:
    """The engine's own backend for ``check`` (so it sees the same drives); not closed."""

    def __init__(self, backend: Any) -> None:
        self.backend = backend

    def node(self, node_id: int) -> Any:
        return self.backend.node(node_id)

    def close(self) -> None:
        pass


def test_check_prints_each_axis_s_supervision_as_read_from_the_drive() -> None:
    t = table(heartbeat_ms=50)
    engine = build_engine(t)
    try:
        sim = engine.backends[0].simulator
        assert ask(engine, "2S04=1") is Status.ACK  # the bridge sets node 2's consumer up
        for word in (0x06, 0x07, 0x10F):  # another tool enables node 3, unwatched
            sim.drives[3].store.write(0x6040, 0, word.to_bytes(2, "little"))
        wait_until(lambda: sim.drive(3).statusword & 0x6F == 0x27, 10, "not enabled")
        reports = {r.axis.addr: r.reading.supervision
                   for r in check(t, opener=lambda bus, axes: Borrowed(engine.backends[0]))}
        assert reports[2] == ("heartbeat consumer of node 127, 150 ms (1016h:01); "
                              "6007h = 3 (quick stop)")
        assert reports[3] is not None and reports[3].startswith(
            "UNSUPERVISED: no heartbeat consumer (1016h:01 = 0) while OPERATION_ENABLED")
        assert reports[1] == "no heartbeat consumer (1016h:01 = 0)"
        assert sim.drives[2].store.get_int(0x1016, 1) == ENTRY
    finally:
        engine.close()
