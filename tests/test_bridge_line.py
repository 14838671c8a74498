"""Issue 30 finding 2: a line is one motion. When one drive of a line (S90 of cyclic
internal axes) leaves OPERATION ENABLED by itself (its quick stop, a fault such as
8611h following error) or is lost, the other axis of the line ramps down on the line
at 28 at once, instead of running on to its target while the first one stands (the
tool left its straight line). R86 of the axis that ended the line is 0, and the log
names it and why.

The bridge runs the ``canopen`` backend on the embedded simulator's virtual CAN bus
(``sim`` with ``link = "can"``, tests/test_bridge_csp.py's table): nodes 2 and 3 are
AxAddr 1 and 2. The drive's own event is made on the simulator's model (a quick
stop command as from its input or another master, a fault injected, a power cycle
that takes the node off the bus) while the line runs. No tight wall-clock bound:
the other axis must stop far short of its target (150 mm) within the stop ramp (2.5
mm at 28) plus a generous allowance for the bridge noticing (:data:`ALLOWED`).
"""
from __future__ import annotations

import logging
import time
from typing import Callable, Dict, Iterator

import pytest

from epos_link.cia402 import State
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.errors import InvalidCommand
from tcp_bridge.wire import Status
from tests.helpers import wait_until
from tests.test_bridge_csp import FACTOR, NODES, Sampler, ask, enable_both, table

DISTANCE = 150  # mm: 7.5 s of travel at 20 mm/s, so a line that runs on is plain to see
# How far the other axis may go after the event: the stop ramp (2.5 mm at 28) and the
# bridge noticing: a statusword on change (a few ms; 0.6 s allowed), or a lost drive
# after twice the heartbeat consumer time (1.6 s; 3.3 s allowed): at 20 mm/s.
ALLOWED = {"quick_stop": 15, "fault_8611": 15, "lost": 70}


@pytest.fixture
def engine() -> Iterator[Engine]:
    # A drive trips after 800 ms without the bridge's heartbeat (a loaded machine's
    # pause must not), and is lost to the bridge after 1.6 s without its statusword.
    engine = build_engine(table(heartbeat_ms=200, heartbeat_consumer_ms=800,
                                sdo_timeout=1.0))
    try:
        yield engine
    finally:
        engine.close()


def quick_stop(engine: Engine, node: int) -> None:
    """The drive quick-stops (its input, or another master: CiA 402-2 command 0x0002)."""
    drive = engine.backends[0].simulator.drives[node]
    with drive.lock:
        drive.store.write_value(0x6040, 0, 0x0002)


def following_error(engine: Engine, node: int) -> None:
    drive = engine.backends[0].simulator.drives[node]
    with drive.lock:
        drive.drive.inject_fault("following_error")  # 8611h, its fault reaction


def power_cycle(engine: Engine, node: int) -> None:
    """The drive is lost: off the bus a moment, then in pre-operational (no PDO)."""
    engine.backends[0].simulator.power_cycle(node)


EVENTS: Dict[str, Callable[[Engine, int], None]] = {
    "quick_stop": quick_stop, "fault_8611": following_error, "lost": power_cycle}
WHY = {"quick_stop": "QUICK_STOP_ACTIVE", "fault_8611": "FAULT", "lost": "lost"}


@pytest.mark.parametrize("event", sorted(EVENTS))
def test_when_one_drive_leaves_the_line_the_other_ramps_down_on_it(
        engine: Engine, event: str, caplog: pytest.LogCaptureFixture) -> None:
    enable_both(engine)
    assert ask(engine, f"1S02={DISTANCE}")[0] is Status.ACK
    assert ask(engine, f"2S02={DISTANCE}")[0] is Status.ACK
    sampler = Sampler(engine)
    start = sampler.now()
    with caplog.at_level(logging.ERROR):
        assert ask(engine, "1S90=1")[0] is Status.ACK
        wait_until(lambda: sampler.now()[1] - start[1] > 10 * FACTOR, 30, "never got going")
        at_event = sampler.now()
        EVENTS[event](engine, NODES[1])  # node 3, AxAddr 2
        sender = engine.backends[0].cyclic
        wait_until(lambda: sender.active(NODES[0]) is None, 30, "the line never ended")
        time.sleep(0.2)
    seen = sampler.close()
    rest = seen[-1]
    assert rest[3] is State.OPERATION_ENABLED  # the other drive: stopped by its line, enabled
    travelled = rest[1] - at_event[1]
    assert rest[1] - start[1] < (DISTANCE - 60) * FACTOR, "the other axis ran on to its target"
    assert travelled < ALLOWED[event] * FACTOR, travelled  # the stop ramp and the notice
    # on the line at 28 (80 mm/s^2 from 20 mm/s: 2.5 mm), not a step where it stood
    assert travelled > 1.5 * FACTOR, travelled
    assert ask(engine, "1R86")[1] == "1"  # its move was accepted, then ramped down
    assert ask(engine, "2R86")[1] == "0"  # the axis that ended the line
    text = caplog.text
    assert "axis 2 left its cyclic move" in text and WHY[event] in text, text
    assert "axes [1] on its line ramp down" in text


def test_the_line_of_a_drive_that_stays_enabled_runs_to_its_end(engine: Engine) -> None:
    """The watch ends nothing by itself: a line whose drives stay enabled reaches its
    targets (the statusword TPDO comes, and is fresh, all along)."""
    enable_both(engine)
    assert ask(engine, "1S02=10")[0] is Status.ACK
    assert ask(engine, "2S02=-10")[0] is Status.ACK
    assert ask(engine, "1S90=1")[0] is Status.ACK
    wait_until(lambda: ask(engine, "1R82")[1] == "1" and ask(engine, "2R82")[1] == "1", 30,
               "the line did not end in target")
    assert ask(engine, "1R12")[1] == "10" and ask(engine, "2R12")[1] == "-10"
    assert ask(engine, "1R86")[1] == "1" and ask(engine, "2R86")[1] == "1"


# -- finding 3: 29/30 on cyclic axes ---------------------------------------------------------


def test_s29_on_a_cyclic_axis_is_refused_not_acked_and_ignored(engine: Engine) -> None:
    """Issue 30 finding 3, as it was seen: ``1S29=2 1S30=1 1S02=5 1S00=1`` on cyclic axis
    1 was ACK all along, moved the master 5 mm and left the slave at 0 (a gantry coupled
    so racks). Now 29 between cyclic axes is CAN (docs/bridge.md), so nothing is ACK and
    then ignored; S90 is how cyclic axes move together."""
    enable_both(engine)
    sim = engine.backends[0].simulator
    with pytest.raises(InvalidCommand, match="cannot be a master of 29"):
        ask(engine, "1S29=2")
    assert ask(engine, "1R29")[1] == "0"
    assert ask(engine, "1S30=1")[0] is Status.ACK
    assert ask(engine, "1S02=5")[0] is Status.ACK
    assert ask(engine, "1S00=1")[0] is Status.ACK  # the master alone, as asked now
    wait_until(lambda: ask(engine, "1R82")[1] == "1", 30, "S00=1 did not end in target")
    assert ask(engine, "1R12")[1] == "5" and ask(engine, "2R12")[1] == "0"
    # A 29 kept from before the axis was cyclic (the state file) does not move it either.
    engine.params.set(1, 29, 2)
    with pytest.raises(InvalidCommand, match="cannot be a master of 29"):
        ask(engine, "1S00=1")
    assert sim.drives[3].drive.motion_starts == 0


def test_a_cyclic_axis_cannot_be_the_slave_of_29_either() -> None:
    mapping = {"bridge": {"ack_timeout": 2.0}, "bus": {"can1": {"backend": "instant"}},
               "axis": [{"device": 5, "node_id": 2, "cyclic": "csp", "internal": True,
                         "increments_per_revolution": 2000},
                        {"device": 5, "node_id": 3, "increments_per_revolution": 2000}]}
    from tcp_bridge.tables.axes import AxisTable
    from tcp_bridge.plan.writes import refuse_cyclic_coupling

    axes = AxisTable.from_mapping(mapping).axes
    with pytest.raises(InvalidCommand, match="axis 1 is cyclic .* slave of 29"):
        refuse_cyclic_coupling(2, 1, axes)
    refuse_cyclic_coupling(2, 2, {2: axes[2]})  # two profile axes: allowed
