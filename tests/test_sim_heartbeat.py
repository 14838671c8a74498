"""Heartbeat producer (1017h) and consumer (1016h, 6007h) of the simulated drives
(epos_link.simulator.heartbeat, .comm), on the virtual bus.

The master's heartbeat is played by a python-can bus in the test sending 77Fh
(node 127) every 100 ms. Time bounds are generous: a loaded machine may be late
by far more than a CAN bus, so only orders of magnitude are checked.
"""
from __future__ import annotations

import threading
import time
from typing import Iterator, List, Tuple

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from epos_link.cia402 import State
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.heartbeat import ABORT_PARAMETER_INCOMPATIBLE
from tests.helpers import canopen_node_on_simulator, wait_until

NODE = 2
MASTER = 127
CONSUMER_MS = 300


@pytest.fixture
def bus() -> Iterator[Tuple[Epos4Simulator, canopen.RemoteNode]]:
    with canopen_node_on_simulator(NODE) as pair:
        yield pair


class FakeMaster:
    """Sends the heartbeat of node 127 (state 05h) every 100 ms until stopped."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.last = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.bus.send(can.Message(arbitration_id=0x700 + MASTER, data=b"\x05", is_extended_id=False))
            self.last = time.monotonic()
            self._stop.wait(0.1)

    def stop(self) -> float:
        """Stop; returns when the last heartbeat was sent."""
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()
        return self.last


def seen(sim: Epos4Simulator) -> Tuple[State, int]:
    """The drive's state and velocity now (outside Operational no PDO ticker brings the
    model up to date, so catch up with the clock first)."""
    sim_drive = sim.drives[NODE]
    with sim_drive.lock:
        sim_drive.drive.sync()
        return sim_drive.drive.state, sim_drive.drive.velocity


def run_velocity(node: canopen.RemoteNode, rpm: int = 500) -> None:
    node.sdo[0x6060].raw = 3
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    node.sdo[0x60FF].raw = rpm


def watch(node: canopen.RemoteNode, option: int) -> None:
    node.sdo[0x6007].raw = option
    node.sdo[0x1016][1].raw = (MASTER << 16) | CONSUMER_MS


def test_producer_sends_the_nmt_state_at_its_period(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    sim, node = bus
    assert node.sdo[0x1017].raw == 0  # off by default (maxon's EDS)
    frames: List[Tuple[float, bytes]] = []
    with can.Bus(interface="virtual", channel=sim.channel) as raw:
        time.sleep(0.3)
        assert raw.recv(0) is None  # no heartbeat while 1017h is 0
        node.sdo[0x1017].raw = 50
        start = time.monotonic()
        while time.monotonic() - start < 1.0:
            msg = raw.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x700 + NODE:
                frames.append((time.monotonic(), bytes(msg.data)))
        assert 5 <= len(frames) <= 25  # 20 expected; a loaded machine skips beats, never bursts
        assert {data for _, data in frames} == {b"\x7f"}  # pre-operational
        for state, byte in (("OPERATIONAL", b"\x05"), ("STOPPED", b"\x04")):
            node.nmt.state = state
            wait_until(lambda: (m := raw.recv(0.05)) is not None and m.arbitration_id == 0x700 + NODE
                  and bytes(m.data) == byte, 5.0, f"a heartbeat in {state}")


def test_a_lost_master_heartbeat_quick_stops_the_drive(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    sim, node = bus
    drive = sim.drive(NODE)
    assert node.sdo[0x6007].raw == 3  # quick stop: the EPOS4 default (maxon's EDS)
    watch(node, 3)
    master = FakeMaster(sim.channel)
    try:
        run_velocity(node)
        wait_until(lambda: seen(sim) == (State.OPERATION_ENABLED, 500), 5.0, "the velocity")
        time.sleep(1.0)  # three consumer times: the heartbeats keep it running
        assert seen(sim) == (State.OPERATION_ENABLED, 500)
        assert node.emcy.log == []
    finally:
        last = master.stop()
    wait_until(lambda: [e.code for e in node.emcy.log] == [0x8130], 5.0, "EMCY 8130h")
    lost_after = time.monotonic() - last
    assert lost_after >= CONSUMER_MS / 1000 - 0.05  # not before the consumer time
    assert node.emcy.log[0].register & 0x11 == 0x11  # generic, communication
    # 605Ah = 6 (maxon's EDS): the quick stop ramp, then it stays in QUICK STOP ACTIVE
    wait_until(lambda: seen(sim) == (State.QUICK_STOP_ACTIVE, 0), 5.0, "605Ah = 6: at rest")
    assert time.monotonic() - last < CONSUMER_MS / 1000 + 3.0  # ramp 500 rpm at 10000 rpm/s: 50 ms
    assert not drive.unsafe_stops  # it ramped down with the power stage on


def test_option_0_only_emcy_and_option_1_fault(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    sim, node = bus
    watch(node, 0)
    run_velocity(node)
    FakeMaster(sim.channel).stop()  # one heartbeat: active, then lost
    wait_until(lambda: [e.code for e in node.emcy.log] == [0x8130], 5.0, "EMCY 8130h")
    time.sleep(0.2)
    assert seen(sim) == (State.OPERATION_ENABLED, 500)
    node.sdo[0x6007].raw = 1
    FakeMaster(sim.channel).stop()  # active again, lost again: now a fault
    wait_until(lambda: [e.code for e in node.emcy.log] == [0x8130, 0x8130], 5.0, "the second EMCY 8130h")
    wait_until(lambda: seen(sim)[0] is State.FAULT, 5.0, "FAULT")
    assert node.sdo[0x603F].raw == 0x8130 and node.sdo[0x1001].raw == 0x11


def test_a_consumer_never_activated_does_not_trip(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    sim, node = bus
    drive = sim.drive(NODE)
    watch(node, 3)
    run_velocity(node)
    time.sleep(3 * CONSUMER_MS / 1000)
    assert node.emcy.log == [] and seen(sim) == (State.OPERATION_ENABLED, 500)
    drive.store.write_value(0x6040, 0, 0x0002)  # the test ends at rest


def test_consumer_entries_for_the_same_node_abort(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    _, node = bus
    node.sdo[0x1016][1].raw = (MASTER << 16) | 300
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x1016][2].raw = (MASTER << 16) | 500
    assert exc.value.code == ABORT_PARAMETER_INCOMPATIBLE
    node.sdo[0x1016][2].raw = MASTER << 16  # time 0: unused, allowed
    node.sdo[0x1016][2].raw = (5 << 16) | 500  # another node
    node.sdo[0x1016][1].raw = (5 << 16) | 0  # the same node with time 0: allowed


def test_reset_node_stops_the_supervision(bus: Tuple[Epos4Simulator, canopen.RemoteNode]) -> None:
    sim, node = bus
    watch(node, 3)
    node.sdo[0x1010][1].raw = 0x65766173  # save: the consumer survives the reset
    FakeMaster(sim.channel).stop()  # active...
    node.nmt.send_command(0x81)  # ...but a reset node starts supervision again
    wait_until(lambda: sim.nmt_state(NODE).name == "PRE_OPERATIONAL", 5.0, "boot-up")
    time.sleep(3 * CONSUMER_MS / 1000)
    assert node.sdo[0x1016][1].raw == (MASTER << 16) | CONSUMER_MS
    assert node.emcy.log == []
