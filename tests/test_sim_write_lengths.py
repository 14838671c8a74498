"""A 4-byte WriteObject to a smaller object (issue 10, item 10).

WriteObject always carries 4 data bytes (guide 2.1.2.1). The guide does not
say what an EPOS4 does with the surplus bytes of a 1- or 2-byte object. The
simulator's rule is decided once, in epos_link/simulator/od.py (``fit_length``):
zero padding is accepted, and for a signed object holding a negative value
0xFF sign extension too; any other surplus is refused with 0x06070010. Our
client and the canopen adapter send zero padding, which works either way:
that is what this module checks on the bytes that reach the device.
"""
from __future__ import annotations

from collections.abc import Iterator

import pytest

from epos_link import canopen_adapter
from epos_link.client import EposClient
from epos_link.framing import NEED_DATA, FrameDecoder
from epos_link.messages import WriteObject, decode_request
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.transport import SimTransport


class Recorder:
    """Stands between the transport and the simulator and keeps every WriteObject."""

    def __init__(self, sim: Epos4Simulator) -> None:
        self.sim = sim
        self.decoder = FrameDecoder()
        self.writes: list[WriteObject] = []

    def receive(self, data: bytes) -> list[bytes]:
        self.decoder.feed(data)
        while (frame := self.decoder.next_frame()) is not NEED_DATA:
            request = decode_request(frame)  # type: ignore[arg-type]
            if isinstance(request, WriteObject):
                self.writes.append(request)
        return self.sim.receive(data)

    def close(self) -> None:
        pass


@pytest.fixture
def rig() -> Iterator[tuple[Epos4Simulator, Recorder, EposClient]]:
    with Epos4Simulator(1, [2]) as sim:
        recorder = Recorder(sim)
        with EposClient(SimTransport(recorder), timeout=1.0) as client:  # type: ignore[arg-type]
            yield sim, recorder, client


@pytest.mark.parametrize("node", [0, 2])
def test_canopen_adapter_sends_zero_padding(rig: tuple[Epos4Simulator, Recorder, EposClient],
                                            node: int) -> None:
    sim, recorder, client = rig
    remote = canopen_adapter.connect_node(client, node)
    remote.sdo[0x6098].raw = -3  # INTEGER8 homing method
    remote.sdo[0x6040].raw = 0x0006  # UNSIGNED16
    assert [(w.index, w.data) for w in recorder.writes] == [
        (0x6098, b"\xfd\x00\x00\x00"), (0x6040, b"\x06\x00\x00\x00")]
    assert sim.drive(node or 1).store.get_int(0x6098) == -3


def test_client_pads_with_zeros(rig: tuple[Epos4Simulator, Recorder, EposClient]) -> None:
    sim, recorder, client = rig
    client.write_object(2, 0x6098, 0, b"\xfc")
    assert recorder.writes[-1].data == b"\xfc\x00\x00\x00"
    assert sim.drive(2).store.get_int(0x6098) == -4


@pytest.mark.parametrize("node", [0, 2])
@pytest.mark.parametrize(("data", "value"), [
    (b"\xfd\x00\x00\x00", -3),  # zero padding (what we send)
    (b"\xfd\xff\xff\xff", -3),  # sign extension (what another master may send)
])
def test_the_simulator_takes_either_form(rig: tuple[Epos4Simulator, Recorder, EposClient],
                                         node: int, data: bytes, value: int) -> None:
    sim, _, client = rig
    client.write_object(node, 0x6098, 0, data)
    assert sim.drive(node or 1).store.get_int(0x6098) == value
