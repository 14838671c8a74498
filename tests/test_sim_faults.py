"""Fault injection (issue 4, must show 4): the client completes every read by retrying."""
from __future__ import annotations

import struct

import pytest

from epos_link.client import EposClient
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import LinkOptions, TcpLink
from epos_link.transports import open_transport

VALUE = 0x12345678


def run_reads(client: EposClient, count: int) -> None:
    for i in range(count):
        data = client.read_object(0, 0x30B0, 0)
        assert struct.unpack("<i", data)[0] == VALUE, f"read {i} returned {data.hex()}"


def test_in_process_5_percent_corrupted_bytes() -> None:
    """1,000 reads with 5% of reply bytes corrupted (seeded, so the run is reproducible)."""
    with Epos4Simulator(1) as sim:
        sim.own.store.set(0x30B0, 0, VALUE)
        transport = open_transport("sim://?corrupt=0.05&seed=7", simulator=sim)
        with EposClient(transport, timeout=0.02, retries=25) as client:
            run_reads(client, 1000)
            stats = client.stats
        faults = transport.faults  # type: ignore[attr-defined]
    print(f"1000 reads: {stats.retries} retries, {faults.corrupted} bytes corrupted, "
          f"causes {stats.failures}")
    assert stats.calls == 1000
    assert faults.corrupted > 400  # the faults really happened
    assert stats.retries >= 300  # about half the 15-byte answers are hit


@pytest.mark.parametrize("drop,corrupt", [(0.0, 0.05), (0.02, 0.0)])
def test_over_tcp_with_faults(drop: float, corrupt: float) -> None:
    with Epos4Simulator(1) as sim:
        sim.own.store.set(0x30B0, 0, VALUE)
        link = TcpLink(sim, LinkOptions(drop=drop, corrupt=corrupt, seed=3)).start()
        try:
            with EposClient.open(link.url, timeout=0.1, retries=25) as client:
                run_reads(client, 100)
                assert client.stats.retries > 0
        finally:
            link.close()
