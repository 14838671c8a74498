"""Issue 22, item 5: a node that another master put in NMT Stopped can still be stopped
and reset through the bridge.

In NMT Stopped a node answers only NMT (EPOS4 Communication Guide 3.3.3.5,
Table 3-13: no SDO), so behind the EPOS4 gateway every SDO to it ends in abort
0x05040000 "SDO protocol timed out" (the simulator models this:
``epos_link/simulator/core.py``), while its drive keeps doing what it did: a
velocity move goes on. A user met it this way: ``2S00=8`` and ``2S16=1``
answered NAK, no NMT frame was ever sent, the axis kept moving.

Each test drives the bridge over TCP (``tests/bridge_sim.py``: PSI requests, the
``epos`` backend, MAXON SERIAL V2 to the simulated EPOS4), stops node 2 from
*another master* on the simulated CAN bus (a canopen ``Network`` of its own, so
the bridge's own view of the node's NMT state knows nothing of it), then looks
at the simulated drive itself. The rule under test is in
``tcp_bridge/motion/__init__.py`` (rule 1) and :meth:`tcp_bridge.motion.Cia402.halt`.
"""
from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Iterator

import canopen
import pytest

from epos_link.cia402 import State
from epos_link.codes import NmtCommand
from epos_link.messages import SendNMTService
from epos_link.simulator.nmt import NmtState
from tcp_bridge.tables.axes import AxisTable, simulated_increments_per_revolution
from tcp_bridge.engine import build_engine
from tcp_bridge.wire import Status, decode_reply, parse_request
from tests.bridge_sim import TIMING, SimBridge, power_ups, run_velocity_move
from tests.helpers import wait_until


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge(timing={"probe_interval": 1000.0})  # no periodic probe: exact traffic
    yield b
    b.close()


@contextmanager
def another_master(b: SimBridge) -> Iterator[canopen.Network]:
    """A second CANopen master on the drives' CAN bus, beside the EPOS4's gateway."""
    net = canopen.Network()
    net.connect(interface="virtual", channel=b.sim.channel, receive_own_messages=False)
    try:
        yield net
    finally:
        net.disconnect()


def stop_by_nmt(b: SimBridge, node: int) -> None:
    """Another master sends NMT Stop Remote Node (CiA 301 7.2.8.3.2.1) to ``node``."""
    with another_master(b) as net:
        net.send_message(0x000, bytes([NmtCommand.STOP_REMOTE_NODE, node]))
        b.wait_until(lambda: b.sim.nmt_state(node) is NmtState.STOPPED,
                     why=f"node {node} never entered NMT Stopped")


def nmt_sent(b: SimBridge, start: int, node: int) -> list[int]:
    """The NMT command specifiers the bridge sent to ``node`` since request ``start``."""
    return [int(m.command) for m in b.transport.requests[start:]
            if isinstance(m, SendNMTService) and m.node == node]


def test_a_stop_reaches_a_moving_axis_that_another_master_stopped_by_nmt(
        bridge: SimBridge, caplog: pytest.LogCaptureFixture) -> None:
    b = bridge
    run_velocity_move(b, 2)
    stop_by_nmt(b, 2)
    assert b.velocity(2) > 0  # NMT Stopped does not stop the drive
    resets, sent = power_ups(b, 2), len(b.transport.requests)
    with caplog.at_level(logging.WARNING, logger="tcp_bridge"):
        assert b.ask("2S00=8").status is Status.ACK
    # Start Remote Node made it answer SDO; then the halt went through.
    assert nmt_sent(b, sent, 2) == [NmtCommand.START_REMOTE_NODE]
    b.wait_until(lambda: b.velocity(2) == 0, why="the stopped node's axis never came to rest")
    assert b.now(2).state is State.OPERATION_ENABLED  # a stop is not a disable
    assert power_ups(b, 2) == resets  # nor a reset
    assert b.sim.nmt_state(2) is NmtState.OPERATIONAL
    assert any("node 2" in r.getMessage() and "NMT Stopped" in r.getMessage()
               and r.levelno == logging.WARNING for r in caplog.records), caplog.text
    b.ok("2R10")  # and it answers the polls again


def test_a_reset_node_reaches_a_moving_axis_that_another_master_stopped_by_nmt(
        bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2)
    stop_by_nmt(b, 2)
    resets, sent = power_ups(b, 2), len(b.transport.requests)
    assert b.ask("2S16=1").status is Status.ACK
    # Start (to make it answer), halt and standstill, only then the reset (rule 1).
    assert nmt_sent(b, sent, 2) == [NmtCommand.START_REMOTE_NODE, NmtCommand.RESET_NODE]
    b.wait_until(lambda: power_ups(b, 2) == resets + 1, why="node 2 was never reset")
    assert b.now(2).resets_while_moving == 0 and b.velocity(2) == 0
    b.wait_until(lambda: b.sim.nmt_state(2) is NmtState.PRE_OPERATIONAL,
                 why="node 2 never booted after the reset")
    b.ok("2R10")


def test_reset_node_is_not_refused_after_the_stopped_node_was_declared_silent() -> None:
    # A long probe interval: no periodic probe of the silent node may fall between
    # counting the requests sent and the refused read (a loaded machine found one).
    b = SimBridge(timing={"probe_interval": 1000.0})
    try:
        _reset_node_after_silence(b)
    finally:
        b.close()


def _reset_node_after_silence(b: SimBridge) -> None:
    run_velocity_move(b, 2)
    stop_by_nmt(b, 2)
    health = b.engine.guards["can1"].health
    assert b.ask("2R10").status is Status.NAK  # the gateway's timeout, then one probe ...
    assert health.node_silent(2)  # ... declares the node silent (fail-fast)
    sent = len(b.transport.requests)
    assert b.ask("2R10").status is Status.NAK  # refused at once, nothing sent
    assert len(b.transport.requests) == sent
    resets = power_ups(b, 2)
    assert b.ask("2S16=1").status is Status.ACK  # the client's explicit reset is tried
    b.wait_until(lambda: power_ups(b, 2) == resets + 1, why="node 2 was never reset")
    assert b.now(2).resets_while_moving == 0
    b.wait_until(lambda: not health.node_silent(2), why="its answers never reopened it")
    b.wait_until(lambda: b.sim.nmt_state(2) is NmtState.PRE_OPERATIONAL)
    b.ok("2R10")


def test_a_stop_to_an_absent_node_is_nak_and_its_start_remote_node_reaches_nobody() -> None:
    # Node 4 is configured but not on the CAN bus: no answer, before or after the
    # Start Remote Node the stop tries, so the stop stays NAK (never a false ACK).
    ipr = simulated_increments_per_revolution()
    b = SimBridge(axes=[{"device": 5, "node_id": n, "position_factor": 1000,
                         "increments_per_revolution": ipr} for n in (1, 2, 3, 4)],
                  timing={"probe_interval": 1000.0})
    try:
        sent = len(b.transport.requests)
        assert b.ask("4S00=8").status is Status.NAK
        assert nmt_sent(b, sent, 4) == [NmtCommand.START_REMOTE_NODE]
        assert b.sim.nmt_state(2) is NmtState.PRE_OPERATIONAL  # nobody else was started
        b.ok("2R10")
    finally:
        b.close()


def test_on_a_can_bus_a_stop_reaches_an_axis_another_master_stopped_by_nmt() -> None:
    # The canopen backend on the simulator's virtual CAN bus: a stopped node's SDO
    # gets no response at all (canopen's SdoCommunicationError, no abort code).
    ipr = simulated_increments_per_revolution()
    engine = build_engine(AxisTable.from_mapping({
        "bridge": {**TIMING, "probe_interval": 1000.0},
        "bus": {"can1": {"backend": "sim", "link": "can", "sdo_timeout": 0.1}},
        "axis": [{"device": 5, "node_id": n, "position_factor": 1000,
                  "increments_per_revolution": ipr} for n in (1, 2)]}))

    def ask(line: str) -> Status:
        return decode_reply(engine.execute_sync(parse_request(line.encode()))).status

    def velocity() -> int:
        with sim.drives[2].lock:  # brought up to the present, as SimBridge.now does
            sim.drive(2).sync()
            return int(sim.drive(2).velocity)
    try:
        sim = engine.backends[0].simulator
        for line in ("2S04=1", "2S05=5", "2S06=50", "2S00=3"):
            assert ask(line) is Status.ACK, line
        wait_until(lambda: velocity() != 0, why="the velocity move never started")
        sim.nmt(2, NmtCommand.STOP_REMOTE_NODE)  # as another master on that bus would
        wait_until(lambda: sim.nmt_state(2) is NmtState.STOPPED, why="node 2 never stopped")
        assert ask("2S00=8") is Status.ACK
        wait_until(lambda: velocity() == 0, why="node 2 never came to rest")
        assert sim.drive(2).state is State.OPERATION_ENABLED
    finally:
        engine.close()
