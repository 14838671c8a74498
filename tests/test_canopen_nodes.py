"""Several nodes of one link in one program (issue 24 point 4): ``connect_node(url, 1)`` then
``connect_node(url, 2)`` share the link; ``node.network.add_node(3, od)`` works as on a bus.
Against the simulated EPOS4 on a pseudo-terminal and on TCP, where a second opening of the
link used to fail ("another program has it open", "connection reset")."""
from __future__ import annotations

from typing import Any, Iterator

import canopen
import pytest

from epos_link import canopen_adapter, connect_node
from epos_link.canopen_gateway import GatewayLimitationError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import PtyLink, TcpLink

DEVICE_TYPE = 0x1000


@pytest.fixture(params=["pty", "tcp"])
def url(request: pytest.FixtureRequest) -> Iterator[str]:
    sim = Epos4Simulator(1, [2, 3])
    link: Any = PtyLink(sim) if request.param == "pty" else TcpLink(sim)
    link.start()
    try:
        yield link.path if request.param == "pty" else link.url
    finally:
        link.close()
        sim.close()


def test_connect_node_twice_on_one_url_shares_the_link(url: str) -> None:
    first = connect_node(url, 1)
    second = connect_node(url, 2)
    try:
        assert first.epos_client is second.epos_client  # one link, opened once
        assert first.sdo[DEVICE_TYPE].raw == second.sdo[DEVICE_TYPE].raw != 0
        assert first.network is second.network and first.network[2] is second
    finally:
        first.close()
    # The link stays open while a node opened by URL holds it, and closes with the last.
    assert second.sdo["Statusword"].raw is not None
    second.close()
    third = connect_node(url, 2)  # opened again
    try:
        assert third.epos_client is not first.epos_client
        assert third.sdo[DEVICE_TYPE].raw != 0
    finally:
        third.close()


def test_network_add_node_reaches_another_node_through_the_gateway(url: str) -> None:
    with connect_node(url, 2) as node:
        added = node.network.add_node(3, canopen_adapter.default_eds())
        assert node.network[3] is added and added.epos_client is node.epos_client
        assert added.sdo["Statusword"].raw is not None and added.sdo[DEVICE_TYPE].raw != 0
        one = node.network.add_node(1)  # the EPOS4 itself, by its own id
        assert one.sdo[DEVICE_TYPE].raw == added.sdo[DEVICE_TYPE].raw
        added.close()  # a node of the network does not own the link
        assert node.sdo["Statusword"].raw is not None


def test_what_add_node_cannot_do_through_the_gateway_is_said() -> None:
    with connect_node("sim://?drives=2", 2) as node:
        with pytest.raises(GatewayLimitationError, match="upload_eds"):
            node.network.add_node(3, upload_eds=True)
        with pytest.raises(TypeError, match=r"add_node\(3, od\)"):
            node.network.add_node(canopen.RemoteNode(3, canopen.ObjectDictionary()))
