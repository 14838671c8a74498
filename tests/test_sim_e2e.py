"""The client against the simulated EPOS4 over a real pty and real TCP (issue 4).

The same steps run on the EPOS4 itself (node 0) and on a drive behind its CAN
gateway (node 2). With EPOS_URL set, the link tests run against that device
instead (real hardware: node EPOS_NODE, default 0; no fault injection there).
"""
from __future__ import annotations

import os
import struct
import time
from typing import Iterator

import pytest

from epos_link.client import EposClient
from epos_link.errors import DeviceError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import PtyLink, TcpLink
from tests.reference import GUIDE_ANSWER, GUIDE_REQUEST

STATE_MASK = 0x006F  # CiA 402 statusword bits 0-3, 5, 6


@pytest.fixture(scope="module")
def simulator() -> Iterator[Epos4Simulator]:
    with Epos4Simulator(1, [2]) as sim:
        yield sim


@pytest.fixture(scope="module", params=["pty", "tcp"])
def url(request: pytest.FixtureRequest, simulator: Epos4Simulator) -> Iterator[str]:
    if os.environ.get("EPOS_URL"):
        yield os.environ["EPOS_URL"]
        return
    link = PtyLink(simulator) if request.param == "pty" else TcpLink(simulator)
    link.start()
    yield link.path if isinstance(link, PtyLink) else link.url
    link.close()


@pytest.fixture
def client(url: str) -> Iterator[EposClient]:
    with EposClient.open(url, timeout=1.0) as c:
        yield c


def u16(data: bytes) -> int:
    return struct.unpack_from("<H", data)[0]


def i32(data: bytes) -> int:
    return struct.unpack_from("<i", data)[0]


def w32(value: int) -> bytes:
    return struct.pack("<i", value)


def write(c: EposClient, node: int, index: int, sub: int, value: int) -> None:
    c.write_object(node, index, sub, w32(value))


def statusword(c: EposClient, node: int) -> int:
    return u16(c.read_object(node, 0x6041, 0))


def wait_status(c: EposClient, node: int, mask: int, value: int, timeout: float = 5.0) -> int:
    deadline = time.monotonic() + timeout
    while True:
        sw = statusword(c, node)
        if sw & mask == value:
            return sw
        assert time.monotonic() < deadline, f"statusword 0x{sw:04X} never matched 0x{value:04X}/0x{mask:04X}"
        time.sleep(0.01)


def test_guide_example_byte_for_byte(url: str, simulator: Epos4Simulator) -> None:
    """Must show 1: 0x30B0 = 0x9001 is read back exactly as Table 2-6 prints it."""
    if os.environ.get("EPOS_URL"):
        pytest.skip("writes the home position of the device")
    simulator.own.store.set(0x30B0, 0, 0x9001)
    from epos_link.transports import open_transport

    with open_transport(url) as link:
        link.write(GUIDE_REQUEST)
        got = b""
        deadline = time.monotonic() + 2
        while len(got) < len(GUIDE_ANSWER) and time.monotonic() < deadline:
            got += link.read(64, 0.2)
    assert got == GUIDE_ANSWER


@pytest.mark.parametrize("node", [0, 2])
def test_name_by_segmented_read(client: EposClient, node: int) -> None:
    assert client.upload(node, 0x1008, 0) == b"EPOS4"


@pytest.mark.parametrize("node", [0, 2])
def test_enable_move_home(client: EposClient, node: int) -> None:
    c = client
    write(c, node, 0x6040, 0, 0x0080)  # fault reset (harmless when there is no fault)
    write(c, node, 0x6040, 0, 0x0006)  # Shutdown
    assert statusword(c, node) & STATE_MASK == 0x21  # READY TO SWITCH ON
    write(c, node, 0x6040, 0, 0x0007)  # Switch on
    assert statusword(c, node) & STATE_MASK == 0x23  # SWITCHED ON
    write(c, node, 0x6040, 0, 0x000F)  # Enable operation
    assert statusword(c, node) & STATE_MASK == 0x27  # OPERATION ENABLED

    write(c, node, 0x6060, 0, 1)  # profile position
    write(c, node, 0x6081, 0, 20000)  # profile velocity, inc/s
    write(c, node, 0x6083, 0, 200000)  # acceleration
    write(c, node, 0x6084, 0, 200000)  # deceleration
    start = i32(c.read_object(node, 0x6064, 0))
    target = start + 1500
    write(c, node, 0x607A, 0, target)
    write(c, node, 0x6040, 0, 0x001F)  # new set-point, absolute
    wait_status(c, node, 1 << 12, 1 << 12)  # set-point acknowledge
    write(c, node, 0x6040, 0, 0x000F)
    wait_status(c, node, 1 << 10, 1 << 10)  # target reached
    assert i32(c.read_object(node, 0x6064, 0)) == target

    write(c, node, 0x607A, 0, -500)
    write(c, node, 0x6040, 0, 0x005F)  # new set-point, relative (bit 6)
    wait_status(c, node, 1 << 12, 1 << 12)
    write(c, node, 0x6040, 0, 0x004F)
    wait_status(c, node, 1 << 10, 1 << 10)
    assert i32(c.read_object(node, 0x6064, 0)) == target - 500

    write(c, node, 0x30B0, 0, 1234)  # home position
    write(c, node, 0x6060, 0, 6)  # homing mode
    write(c, node, 0x6040, 0, 0x001F)  # start homing
    wait_status(c, node, 1 << 12, 1 << 12)  # homing attained
    assert i32(c.read_object(node, 0x6064, 0)) == 1234
    write(c, node, 0x6040, 0, 0x0006)  # back to READY TO SWITCH ON
    assert statusword(c, node) & STATE_MASK == 0x21


ABORTS = [
    ("object missing", lambda c, n: c.read_object(n, 0x1234, 0), 0x06020000),
    ("subindex missing", lambda c, n: c.read_object(n, 0x6041, 5), 0x06090011),
    ("write read-only", lambda c, n: c.write_object(n, 0x6041, 0, w32(1)), 0x06010002),
    ("read write-only", lambda c, n: c.read_object(n, 0x2100, 0), 0x06010001),
    # WriteObject always carries 4 bytes: non-zero surplus bytes for a U16 are a wrong length.
    ("wrong length", lambda c, n: c.write_object(n, 0x6040, 0, bytes.fromhex("06000100")), 0x06070010),
    ("out of range", lambda c, n: c.write_object(n, 0x6060, 0, w32(7)), 0x06090030),
]


@pytest.mark.parametrize("node", [0, 2])
@pytest.mark.parametrize("name,misuse,code", ABORTS, ids=[a[0] for a in ABORTS])
def test_abort_codes(client: EposClient, node: int, name: str, misuse, code: int) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(DeviceError) as info:
        misuse(client, node)
    assert info.value.code == code, str(info.value)


def test_absent_node_is_an_sdo_timeout(client: EposClient) -> None:
    with pytest.raises(DeviceError) as info:
        client.read_object(9, 0x1000, 0)
    assert info.value.code == 0x05040000
