"""Issue 30, "a line is one motion", for axes in the drives' own profile modes.

A line of command 90 on internal axes with ``profile = "drive"`` (each drive in
profile position mode) and a master with its slave (29/30) start together, then
each drive runs its own trajectory. As the finding was seen: while the motion
runs, one drive leaves OPERATION ENABLED by itself (its quick stop, as from its
input or another master; a fault 8611h following error), or a client stops ONE
of its axes (S00=8, S04=0) from the other port; the other axis must come to rest
far short of its target instead of running on alone (the tool leaves its line, a
gantry racks). R86 of an axis that left by itself is 0 and the log names it and
why (:mod:`tcp_bridge.motion.together`).

The bridge runs in this process on two simulated EPOS4 buses (``sim``), axis 1 on
can1 and axis 2 on can2 (tests/test_bridge_stage_order.py's two ports); the drives'
events are made on the simulator's model. No tight wall-clock bound: the other axis
must stop within a quarter of its 100 mm (10 s of travel at 10 mm/s), where its
halt ramp is 0.5 mm and the watch reads each statusword every 20 ms.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, Iterator

import pytest

from tcp_bridge.wire import Status
from tests.helpers import wait_until
from tests.test_bridge_stage_order import FACTOR, Served, reply, send, two_buses

DISTANCE = 100  # mm
STOPPED_WITHIN = 25 * FACTOR  # of the other axis's travel, in increments
BUS = {1: "can1", 2: "can2"}


def quick_stop(b: Served, addr: int) -> None:
    """The drive quick-stops (its input, or another master: CiA 402-2 command 0x0002)."""
    sim = b._backend(BUS[addr]).simulator.drives[1]
    with sim.lock:
        sim.store.write_value(0x6040, 0, 0x0002)


def following_error(b: Served, addr: int) -> None:
    sim = b._backend(BUS[addr]).simulator.drives[1]
    with sim.lock:
        sim.drive.inject_fault("following_error")  # 8611h, its fault reaction


EVENTS: Dict[str, Callable[[Served, int], None]] = {
    "quick_stop": quick_stop, "fault_8611": following_error}
WHY = {"quick_stop": "QUICK_STOP_ACTIVE", "fault_8611": "FAULT"}


@pytest.fixture
def line() -> Iterator[Served]:
    """Two internal axes in profile position mode, one on each bus: 90=1 moves both."""
    b = Served(two_buses(internal=True, profile="drive"))
    try:
        b.ok("1S04=1", "2S04=1", "1S05=10", "1S06=100", "2S05=10", "2S06=100",
             f"1S02={DISTANCE}", f"2S02={DISTANCE}")
        yield b
    finally:
        b.close()


@pytest.fixture
def gantry() -> Iterator[Served]:
    """Axis 1 (can1) is the master, axis 2 (can2) its slave: profile axes on two buses."""
    b = Served(two_buses())
    try:
        b.ok("1S04=1", "2S04=1", "1S05=10", "1S06=100", "1S29=2", "1S30=1",
             f"1S02={DISTANCE}")
        yield b
    finally:
        b.close()


def _under_way(b: Served) -> None:
    wait_until(lambda: b.position("can1", 1) > 2 * FACTOR
               and b.position("can2", 1) > 2 * FACTOR, 30, "the motion never got going")


def _at_rest(b: Served, bus: str) -> int:
    wait_until(lambda: b.drive(bus, 1).velocity == 0, 30, f"the axis on {bus} runs on")
    return b.position(bus, 1)


@pytest.mark.parametrize("event", sorted(EVENTS))
@pytest.mark.parametrize("leaves", [1, 2])
def test_when_one_drive_of_a_profile_line_leaves_it_the_other_is_halted(
        line: Served, event: str, leaves: int, caplog: pytest.LogCaptureFixture) -> None:
    b = line
    other = 3 - leaves
    with caplog.at_level(logging.WARNING):
        b.ok("1S90=1")
        _under_way(b)
        at_event = b.position(BUS[other], 1)
        EVENTS[event](b, leaves)
        rest = _at_rest(b, BUS[other])
    assert rest - at_event < STOPPED_WITHIN, "the other axis ran on along the line alone"
    assert b.ok(f"{other}R04") == "1"  # halted, still enabled (rule 1)
    assert b.ok(f"{leaves}R86") == "0" and b.ok(f"{other}R86") == "1"
    text = caplog.text
    assert f"axis {leaves} ({BUS[leaves]} node 1) left its line" in text, text
    assert WHY[event] in text and f"halting axis {other}" in text, text


@pytest.mark.parametrize("stop", ["2S00=8", "2S04=0", "1S00=8"])
def test_a_client_s_stop_of_one_axis_of_a_profile_line_halts_the_line(
        line: Served, stop: str, caplog: pytest.LogCaptureFixture) -> None:
    """The stop comes from the other port, for one axis of the running line."""
    b = line
    stopped = int(stop[0])
    other = 3 - stopped
    with caplog.at_level(logging.WARNING):
        send(b.sock, "1S90=1")
        assert reply(b.sock).status is Status.ACK
        _under_way(b)
        at_stop = b.position(BUS[other], 1)
        send(b.other, stop)
        assert reply(b.other).status is Status.ACK
        rest = _at_rest(b, BUS[other])
    assert rest - at_stop < STOPPED_WITHIN, "the other axis ran on along the line alone"
    assert f"axis {stopped} ({BUS[stopped]} node 1) left its line (stopped by a client" \
        in caplog.text, caplog.text


@pytest.mark.parametrize("event", sorted(EVENTS))
@pytest.mark.parametrize("leaves", [1, 2], ids=["master", "slave"])
def test_when_one_drive_of_a_gantry_leaves_the_move_the_other_is_halted(
        gantry: Served, event: str, leaves: int, caplog: pytest.LogCaptureFixture) -> None:
    b = gantry
    other = 3 - leaves
    with caplog.at_level(logging.WARNING):
        b.ok("1S00=1")
        _under_way(b)
        at_event = b.position(BUS[other], 1)
        EVENTS[event](b, leaves)
        rest = _at_rest(b, BUS[other])
    assert rest - at_event < STOPPED_WITHIN, "the gantry racked: one side ran on alone"
    assert b.ok(f"{leaves}R86") == "0" and b.ok(f"{other}R86") == "1"
    assert f"axis {leaves} ({BUS[leaves]} node 1) left its line" in caplog.text, caplog.text


@pytest.mark.parametrize("stop", ["2S00=8", "2S04=0"])
def test_a_client_s_stop_of_the_slave_halts_its_master(gantry: Served, stop: str) -> None:
    b = gantry
    send(b.sock, "1S00=1")
    assert reply(b.sock).status is Status.ACK
    _under_way(b)
    at_stop = b.position("can1", 1)
    send(b.other, stop)
    assert reply(b.other).status is Status.ACK
    rest = _at_rest(b, "can1")
    assert rest - at_stop < STOPPED_WITHIN, "the master ran on without its slave"


def test_a_profile_line_whose_drives_stay_enabled_runs_to_its_end(line: Served) -> None:
    """The watch ends nothing by itself; and once the line arrived, a stop of one axis
    (a later, separate request) is a plain stop of that axis."""
    b = line
    b.ok("1S02=3", "2S02=-3", "1S90=1")
    b.poll("1R82", "1", 30)
    b.poll("2R82", "1", 30)
    assert b.ok("1R12") == "3" and b.ok("2R12") == "-3"
    assert b.ok("1R86") == "1" and b.ok("2R86") == "1"


class Unplugged:
    """The link to ``bus``'s gateway falls silent (an unplugged cable): requests arrive
    and the drives run on, but no answer comes back."""

    def __init__(self, b: Served, bus: str) -> None:
        self.simulator = b._backend(bus).simulator
        self.original: Callable[[bytes], Any] = self.simulator.receive
        self.silent = False
        self.simulator.receive = self.receive

    def receive(self, data: bytes) -> Any:
        answer = self.original(data)
        return [] if self.silent else answer


def test_when_one_drive_of_a_profile_line_is_lost_the_other_is_halted(
        line: Served, caplog: pytest.LogCaptureFixture) -> None:
    """Lost: the watch's statusword read finds the node silent (no answer within the
    link's timeouts: 1.5 s seen here). At 4 mm/s the line takes 25 s; axis 1 must stop
    within 15 s of travel."""
    b = line
    b.ok("1S05=4", "2S05=4")
    link = Unplugged(b, "can2")
    with caplog.at_level(logging.WARNING):
        b.ok("1S90=1")
        _under_way(b)
        at_event = b.position("can1", 1)
        link.silent = True
        rest = _at_rest(b, "can1")
    link.silent = False
    assert rest - at_event < 60 * FACTOR, "axis 1 ran on along the line alone"
    assert "axis 2 (can2 node 1) left its line (lost" in caplog.text, caplog.text


@pytest.mark.parametrize("leaves", [1, 2], ids=["slave", "master"])
def test_a_gantry_on_one_bus_is_one_motion_too(
        leaves: int, caplog: pytest.LogCaptureFixture) -> None:
    """Master (axis 2, node 2) and slave (axis 1, node 1, the EPOS4 itself) on one epos
    bus start in one job; the drive of one quick-stops mid-move, the other is halted."""
    from tests.bridge_sim import SimBridge

    b = SimBridge(drives=(2,))
    try:
        b.ok("1S04=1", "2S04=1", "2S05=10", "2S06=100", "2S29=1", "2S30=1",
             f"2S02={DISTANCE}", "2S00=1")
        wait_until(lambda: b.position(1) > 2 * FACTOR and b.position(2) > 2 * FACTOR, 30,
                   "the gantry never got going")
        other = 3 - leaves
        at_event = b.position(other)
        with caplog.at_level(logging.WARNING):
            sim = b.sim.drives[leaves]
            with sim.lock:
                sim.store.write_value(0x6040, 0, 0x0002)  # its quick stop
            wait_until(lambda: b.now(other).velocity == 0, 30, "the other side runs on")
        assert b.position(other) - at_event < STOPPED_WITHIN, "the gantry racked"
        assert b.ok(f"{leaves}R86") == "0" and b.ok(f"{other}R86") == "1"
        assert f"axis {leaves} (can1 node {leaves}) left its line" in caplog.text, caplog.text
    finally:
        b.close()
