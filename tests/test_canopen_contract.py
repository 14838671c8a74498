"""One contract, two SDO paths (issue 5).

Every test body runs unchanged against:

* ``can``: canopen's own RemoteNode/BaseNode402 on the simulator's python-can
  virtual bus (set CAN_CHANNEL/CAN_INTERFACE to run it on a real bus);
* ``epos``: ``epos_link.connect_node`` through the simulated EPOS4 over a
  pseudo-terminal (set EPOS_URL to run it on a real EPOS4).

Each path is exercised on the gateway device itself and on a drive behind it.
"""
from __future__ import annotations

import os
import time
from typing import Callable, Iterator

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from epos_link import canopen_adapter
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import PtyLink
from epos_link.simulator.od import EDS_PATH, add_value_descriptions

GATEWAY_ID, DRIVE_ID = 1, 2
NodeFactory = Callable[..., canopen.RemoteNode]


@pytest.fixture(scope="module")
def simulator() -> Iterator[Epos4Simulator]:
    with Epos4Simulator(GATEWAY_ID, [DRIVE_ID]) as sim:
        yield sim


def _od(node_id: int) -> canopen.ObjectDictionary:
    od = canopen.import_od(str(EDS_PATH), node_id)
    add_value_descriptions(od)
    return od


@pytest.fixture(scope="module", params=["can", "epos"])
def path(request: pytest.FixtureRequest, simulator: Epos4Simulator) -> Iterator[Callable[[int, bool], canopen.RemoteNode]]:
    if request.param == "can":
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface=os.environ.get("CAN_INTERFACE", "virtual"),
                    channel=os.environ.get("CAN_CHANNEL", simulator.channel),
                    receive_own_messages=False)

        def make(node_id: int, p402: bool) -> canopen.RemoteNode:
            cls = BaseNode402 if p402 else canopen.RemoteNode
            node = cls(node_id or GATEWAY_ID, _od(node_id or GATEWAY_ID))
            net.add_node(node)
            return node

        yield make
        net.disconnect()
    else:
        link = None
        url = os.environ.get("EPOS_URL")
        if not url:
            link = PtyLink(simulator).start()
            url = link.path
        client = canopen_adapter.EposClient.open(url, timeout=1.0)

        def make(node_id: int, p402: bool) -> canopen.RemoteNode:
            return canopen_adapter.connect_node(client, node_id, profile="402" if p402 else None)

        yield make
        client.close()
        if link:
            link.close()


@pytest.fixture(params=["gateway", "drive"])
def node_id(request: pytest.FixtureRequest, path: Callable[[int, bool], canopen.RemoteNode]) -> int:
    # The gateway itself is node 0 on the serial link and its own id on CAN.
    return 0 if request.param == "gateway" else DRIVE_ID


@pytest.fixture
def node(path: Callable[[int, bool], canopen.RemoteNode], node_id: int) -> canopen.RemoteNode:
    return path(node_id, False)


@pytest.fixture
def node402(path: Callable[[int, bool], canopen.RemoteNode], node_id: int) -> BaseNode402:
    n = path(node_id, True)
    assert isinstance(n, BaseNode402)
    return n


def test_by_name_and_by_index(node: canopen.RemoteNode) -> None:
    assert node.sdo["Device type"].raw == 0x00020192
    assert node.sdo[0x1000].raw == 0x00020192
    node.sdo[0x607A].raw = 1000
    assert node.sdo["Target position"].raw == 1000
    node.sdo["Target position"].raw = -7
    assert node.sdo[0x607A].raw == -7
    node.sdo.download(0x607A, 0, (123456).to_bytes(4, "little", signed=True))
    assert node.sdo.upload(0x607A, 0) == (123456).to_bytes(4, "little")


def test_small_objects_are_truncated_to_their_size(node: canopen.RemoteNode) -> None:
    assert len(node.sdo.upload(0x6041, 0)) == 2  # UNSIGNED16, though ReadObject returns 4 bytes
    assert len(node.sdo.upload(0x6060, 0)) == 1


def test_phys_bits_desc(node: canopen.RemoteNode) -> None:
    node.sdo["Modes of operation"].raw = 1
    assert node.sdo["Modes of operation"].desc == "Profile Position Mode"
    node.sdo[0x6060].desc = "Homing Mode"
    assert node.sdo[0x6060].raw == 6
    # Statusword bit 9 (remote) = NMT Operational (guide Table 3-13, footnote 3).
    node.nmt.state = "OPERATIONAL"
    deadline = time.monotonic() + 5.0  # the NMT frame reaches the drive on the bus thread
    while node.sdo["Statusword"].bits[9] != 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert node.sdo["Statusword"].bits[9] == 1
    assert node.sdo[0x6081].phys == node.sdo[0x6081].raw  # factor 1 in our EDS


def test_records_and_arrays(node: canopen.RemoteNode) -> None:
    identity = node.sdo[0x1018]
    assert identity[1].raw == 0x000000FB  # maxon's vendor id
    limits = node.sdo["Software position limit"]
    limits[1].raw, limits[2].raw = -100000, 100000
    assert (limits[1].raw, limits[2].raw) == (-100000, 100000)
    limits[1].raw, limits[2].raw = 0, 0  # limits off again (min >= max)
    assert len(node.sdo[0x1018]) == 4


def test_strings_and_streams(node: canopen.RemoteNode) -> None:
    assert node.sdo["Manufacturer device name"].raw == "EPOS4"
    with node.sdo[0x1008].open("rt") as fp:
        assert fp.read() == "EPOS4"
    with node.sdo[0x1008].open("rb") as fp:
        assert fp.read() == b"EPOS4"


def test_store(node: canopen.RemoteNode) -> None:
    node.store()  # 0x1010:1 = "save"


ABORTS = [
    (lambda n: n.sdo.upload(0x1234, 0), 0x06020000),
    (lambda n: n.sdo.upload(0x6041, 7), 0x06090011),
    (lambda n: n.sdo.download(0x6041, 0, b"\x01\x00"), 0x06010002),
    (lambda n: n.sdo.upload(0x2100, 0), 0x06010001),
    (lambda n: n.sdo.download(0x6060, 0, b"\x07"), 0x06090030),
]


@pytest.mark.parametrize("misuse,code", ABORTS, ids=[hex(c) for _, c in ABORTS])
def test_abort_codes(node: canopen.RemoteNode, misuse, code: int) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(canopen.SdoAbortedError) as info:
        misuse(node)
    assert info.value.code == code


def test_state_machine_and_absolute_move(node402: BaseNode402) -> None:
    n = node402
    n.setup_402_state_machine(read_pdos=False)
    n.state = "SWITCH ON DISABLED"
    assert n.state == "SWITCH ON DISABLED"
    n.state = "OPERATION ENABLED"
    assert n.state == "OPERATION ENABLED"
    n.op_mode = "PROFILED POSITION"
    n.sdo["Profile velocity"].raw = 50000
    n.sdo["Profile acceleration"].raw = 500000
    n.sdo["Profile deceleration"].raw = 500000
    target = n.sdo["Position actual value"].raw + 2000
    n.sdo["Target position"].raw = target
    n.controlword = 0x1F  # new set-point, absolute
    deadline = time.monotonic() + 5
    while not n.statusword & (1 << 12):
        assert time.monotonic() < deadline
    n.controlword = 0x0F
    while not n.statusword & (1 << 10):
        assert time.monotonic() < deadline, "target not reached"
        time.sleep(0.005)
    assert n.sdo["Position actual value"].raw == target
    n.state = "SWITCH ON DISABLED"
    assert n.state == "SWITCH ON DISABLED"


def test_domain_write_of_4_bytes_or_less(node: canopen.RemoteNode) -> None:
    """canopen forces segmented transfers for DOMAIN; small ones still go through."""
    node.sdo.download(0x607A, 0, (77).to_bytes(4, "little"), force_segment=True)
    assert node.sdo[0x607A].raw == 77
