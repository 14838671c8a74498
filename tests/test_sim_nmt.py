"""NMT states, boot-up messages and power cycles of the simulated EPOS4 (issue 10, items 2, 5).

Guide 3.3.3, Table 3-13: after initialisation a node is Pre-Operational and
sends a boot-up message; in Stopped only NMT, LSS and heartbeat work, so an
SDO request gets no answer and the gateway reports 0x05040000 (SDO protocol
timed out) after its timeout; statusword bit 9 (remote) is 1 in Operational
(footnote 3). Boot-up: COB-ID 0x700 + node id, one data byte 0x00 (CiA 301
7.2.8.3.2.1). The serial link to node 0 keeps working in Stopped (chosen,
see epos_link/simulator/core.py).

NMT frames to other nodes travel on the virtual CAN bus and are handled on
its notifier thread, so the tests wait for their effect with a deadline.
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Iterator

import can
import canopen
import pytest
from canopen.sdo import SdoCommunicationError

from epos_link.cia402 import State
from epos_link.client import EposClient
from epos_link.errors import DeviceError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.drive import VirtualClock
from epos_link.simulator.nmt import NmtState
from epos_link.simulator.od import EDS_PATH
from epos_link.simulator.safety import EventKind
from epos_link.transports import open_transport
from tests.helpers import wait_until

REMOTE = 0x0200
WAIT = 5.0  # seconds: a bound for the bus thread, 100x what it needs


def eventually(check: Callable[[], bool], what: str) -> None:
    wait_until(check, WAIT, f"timed out waiting for {what}")


@pytest.fixture
def sim() -> Iterator[Epos4Simulator]:
    with Epos4Simulator(1, [2], clock=VirtualClock(), gateway_timeout=0.1) as s:
        yield s


@pytest.fixture
def client(sim: Epos4Simulator) -> Iterator[EposClient]:
    with EposClient(open_transport("sim://", simulator=sim), timeout=1.0, retries=0) as c:
        yield c


@pytest.fixture
def bus(sim: Epos4Simulator) -> Iterator[can.BusABC]:
    """A listener on the simulator's CAN bus (python-can virtual channel)."""
    b = can.Bus(interface="virtual", channel=sim.channel, receive_own_messages=False)
    yield b
    b.shutdown()


def statusword(c: EposClient, node: int) -> int:
    return struct.unpack("<H", c.read_object(node, 0x6041, 0)[:2])[0]


def boot_ups(bus: can.BusABC, quiet: float = 0.2) -> list[tuple[int, bytes]]:
    """The boot-up messages received until the bus is quiet for ``quiet`` seconds."""
    out = []
    while (msg := bus.recv(timeout=quiet)) is not None:
        if 0x701 <= msg.arbitration_id <= 0x77F:
            out.append((msg.arbitration_id, bytes(msg.data)))
    return out


def test_pre_operational_after_boot_and_bit_9(sim: Epos4Simulator, client: EposClient) -> None:
    assert sim.nmt_state(1) is NmtState.PRE_OPERATIONAL is sim.nmt_state(2)
    assert statusword(client, 0) & REMOTE == 0
    assert statusword(client, 2) & REMOTE == 0
    client.nmt(0, "start")  # all nodes
    eventually(lambda: sim.nmt_state(2) is NmtState.OPERATIONAL, "node 2 operational")
    eventually(lambda: sim.nmt_state(1) is NmtState.OPERATIONAL, "node 1 operational")
    assert statusword(client, 0) & REMOTE and statusword(client, 2) & REMOTE
    client.nmt(2, "preop")
    eventually(lambda: statusword(client, 2) & REMOTE == 0, "bit 9 cleared")


def test_stopped_node_does_not_answer_sdo(sim: Epos4Simulator, client: EposClient) -> None:
    client.nmt(2, "stop")
    eventually(lambda: sim.nmt_state(2) is NmtState.STOPPED, "node 2 stopped")
    with pytest.raises(DeviceError) as info:
        client.read_object(2, 0x6041, 0)
    assert info.value.code == 0x05040000  # the gateway's SDO timeout
    with pytest.raises(DeviceError):
        client.write_object(2, 0x607A, 0, struct.pack("<i", 5))
    assert sim.drive(2).store.get_int(0x607A) == 0  # the write did not happen
    client.nmt(2, "start")
    eventually(lambda: sim.nmt_state(2) is NmtState.OPERATIONAL, "node 2 operational")
    assert statusword(client, 2) & REMOTE


def test_stopped_node_is_silent_on_can_too(sim: Epos4Simulator) -> None:
    net = canopen.Network()
    net.connect(interface="virtual", channel=sim.channel, receive_own_messages=False)
    try:
        node = net.add_node(2, str(EDS_PATH))
        node.sdo.RESPONSE_TIMEOUT = 5.0  # an answer: as long as a loaded machine needs
        node.sdo.MAX_RETRIES = 1  # canopen counts the first try
        assert node.sdo[0x1000].raw == 0x00020192
        node.nmt.send_command(0x02)
        eventually(lambda: sim.nmt_state(2) is NmtState.STOPPED, "node 2 stopped")
        node.sdo.RESPONSE_TIMEOUT = 0.1  # silence: no answer ever comes, so no race
        with pytest.raises(SdoCommunicationError):
            node.sdo.upload(0x1000, 0)
    finally:
        net.disconnect()


def test_serial_link_to_the_gateway_keeps_working_when_stopped(sim: Epos4Simulator,
                                                                client: EposClient) -> None:
    client.nmt(1, "stop")  # the device's own id: executed at once, not via the bus
    assert sim.nmt_state(1) is NmtState.STOPPED
    assert statusword(client, 0) & REMOTE == 0  # answered over RS232/USB (chosen)


def test_power_cycle_restores_saved_parameters_and_boots(sim: Epos4Simulator, client: EposClient,
                                                         bus: can.BusABC) -> None:
    drive = sim.drive(2)
    client.write_object(2, 0x6081, 0, struct.pack("<I", 2000))
    client.write_object(2, 0x1010, 1, b"save")
    client.write_object(2, 0x6081, 0, struct.pack("<I", 3000))  # written, not saved
    client.nmt(0, "start")
    eventually(lambda: sim.nmt_state(2) is NmtState.OPERATIONAL, "node 2 operational")
    for cw in (0x06, 0x0F):
        client.write_object(2, 0x6040, 0, struct.pack("<H", cw))
    client.write_object(2, 0x607A, 0, struct.pack("<i", 5000))
    client.write_object(2, 0x6040, 0, struct.pack("<H", 0x1F))
    assert isinstance(sim.clock, VirtualClock)
    sim.clock.advance(2.0)
    drive.sync()
    assert drive.position == 5000
    boot_ups(bus, quiet=0.05)  # drain
    sim.power_cycle(2)
    assert boot_ups(bus) == [(0x702, b"\x00")]
    assert sim.nmt_state(2) is NmtState.PRE_OPERATIONAL
    assert drive.state is State.SWITCH_ON_DISABLED and drive.position == 0
    assert struct.unpack("<I", client.read_object(2, 0x6081, 0))[0] == 2000
    assert statusword(client, 2) & REMOTE == 0
    assert drive.events[-1].kind is EventKind.POWER_CYCLE


def test_power_cycle_by_simulator_command(sim: Epos4Simulator, client: EposClient,
                                          bus: can.BusABC) -> None:
    client.write_object(2, 0x30B0, 0, struct.pack("<i", 77))  # not saved
    client.write_object(2, 0x2100, 0, struct.pack("<I", 6))
    assert boot_ups(bus) == [(0x702, b"\x00")]
    assert struct.unpack("<i", client.read_object(2, 0x30B0, 0))[0] == 0


def test_nmt_reset_node_boots_and_counts_a_moving_axis(sim: Epos4Simulator, client: EposClient,
                                                      bus: can.BusABC) -> None:
    drive = sim.drive(2)
    client.write_object(2, 0x6060, 0, b"\x03\x00\x00\x00")
    for cw in (0x06, 0x0F):
        client.write_object(2, 0x6040, 0, struct.pack("<H", cw))
    client.write_object(2, 0x60FF, 0, struct.pack("<i", 100))
    assert isinstance(sim.clock, VirtualClock)
    sim.clock.advance(1.0)
    drive.sync()
    assert drive.velocity == 100
    client.nmt(2, "reset")
    eventually(lambda: drive.resets_while_moving == 1, "the reset")
    assert boot_ups(bus) == [(0x702, b"\x00")]
    assert drive.position == 0 and drive.state is State.SWITCH_ON_DISABLED
    assert sim.nmt_state(2) is NmtState.PRE_OPERATIONAL


def test_reset_communication_boots_without_touching_the_drive(sim: Epos4Simulator, client: EposClient,
                                                              bus: can.BusABC) -> None:
    for cw in (0x06, 0x0F):
        client.write_object(2, 0x6040, 0, struct.pack("<H", cw))
    client.nmt(0, "start")
    eventually(lambda: sim.nmt_state(2) is NmtState.OPERATIONAL, "node 2 operational")
    boot_ups(bus, quiet=0.05)
    client.nmt(2, "reset-comm")
    assert boot_ups(bus) == [(0x702, b"\x00")]
    assert sim.nmt_state(2) is NmtState.PRE_OPERATIONAL
    assert sim.drive(2).state is State.OPERATION_ENABLED


def test_boot_up_of_every_drive_at_start() -> None:
    channel = "epos-sim-boot-test"
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as b:
        with Epos4Simulator(1, [2, 3], channel=channel):
            assert sorted(boot_ups(b)) == [(0x701, b"\x00"), (0x702, b"\x00"), (0x703, b"\x00")]
