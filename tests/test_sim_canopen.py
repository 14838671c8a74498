"""canopen's own RemoteNode on the simulator's virtual CAN bus, no epos_link in between."""
from __future__ import annotations

from typing import Iterator

import canopen
import pytest

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.od import EDS_PATH


@pytest.fixture
def network() -> Iterator[tuple[Epos4Simulator, canopen.Network]]:
    with Epos4Simulator(1, [2, 3]) as sim:
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05  # quick teardown
        net.connect(interface="virtual", channel=sim.channel, receive_own_messages=False)
        try:
            yield sim, net
        finally:
            net.disconnect()


def test_remote_node_reads_and_writes(network: tuple[Epos4Simulator, canopen.Network]) -> None:
    sim, net = network
    node = canopen.RemoteNode(3, str(EDS_PATH))
    net.add_node(node)
    assert node.sdo[0x1000].raw == 0x00020192
    assert node.sdo["Manufacturer device name"].raw == "EPOS4"
    node.sdo[0x30B0].raw = -4321
    assert node.sdo[0x30B0].raw == -4321
    assert sim.drives[3].store.get(0x30B0, 0) == -4321  # it really reached drive 3
    node.sdo["Controlword"].raw = 0x06
    assert node.sdo["Statusword"].raw & 0x6F == 0x21
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo.upload(0x1234, 0)
    assert info.value.code == 0x06020000


def test_two_drives_are_independent(network: tuple[Epos4Simulator, canopen.Network]) -> None:
    sim, net = network
    a, b = canopen.RemoteNode(2, str(EDS_PATH)), canopen.RemoteNode(3, str(EDS_PATH))
    net.add_node(a)
    net.add_node(b)
    a.sdo[0x607A].raw = 111
    b.sdo[0x607A].raw = 222
    assert (a.sdo[0x607A].raw, b.sdo[0x607A].raw) == (111, 222)
