"""Late answers never slide onto the next request (answers carry no request id).

The simulated gateway waits 0.3 s for an absent node's SDO; a client giving up
after 0.1 s must not take that late "SDO timed out" answer for its next request.
"""
from __future__ import annotations

import struct
from typing import Iterator

import pytest

from epos_link.client import EposClient
from epos_link.errors import EposTimeoutError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink


@pytest.fixture
def url() -> Iterator[str]:
    with Epos4Simulator(1, [2, 5]) as sim:
        sim.drives[5].store.set(0x1018, 4, 0x5555)
        link = TcpLink(sim).start()
        yield link.url
        link.close()


def test_scan_with_short_timeout_finds_the_right_nodes(url: str) -> None:
    with EposClient.open(url) as client:
        found = client.scan(range(1, 7), timeout=0.1)
    assert [n.node for n in found] == [1, 2, 5]
    for info in found:
        assert info.device_type == 0x00020192 and info.name == "EPOS4"
        assert info.vendor_id == 0x000000FB
    assert found[2].serial_number == 0x5555


def test_read_after_a_silent_timeout_gets_its_own_answer(url: str) -> None:
    with EposClient.open(url, retries=0) as client:
        with pytest.raises(EposTimeoutError):
            client.read_object(9, 0x1000, 0, timeout=0.1)
        assert struct.unpack("<I", client.read_object(0, 0x1000, 0))[0] == 0x00020192
