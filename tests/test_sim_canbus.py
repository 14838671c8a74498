"""Frame times of the simulated CAN bus (epos_link.simulator.canbus): an SDO answer comes
no sooner than a real bus carries the request and the answer."""
from __future__ import annotations

import time

import canopen
import pytest

from epos_link.simulator.canbus import DEFAULT_BITRATE, frame_time, sdo_answer_due
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.od import EDS_PATH


def test_frame_times_follow_iso_11898_1() -> None:
    # 2.0A data frame: 44 + 8n bits, then 3 bits of intermission (stuff bits not counted).
    assert frame_time(8, 1_000_000) == pytest.approx(111e-6)
    assert frame_time(0, 125_000) == pytest.approx(47 / 125_000)
    assert sdo_answer_due(100.0, 8, 500_000) == pytest.approx(100.0 + 2 * 222e-6)
    assert sdo_answer_due(100.0, 8, None) == 100.0
    with pytest.raises(ValueError):
        frame_time(9, DEFAULT_BITRATE)


def test_a_bad_bit_rate_is_refused() -> None:
    with pytest.raises(ValueError, match="bit rate"):
        Epos4Simulator(1, [2], can_bitrate=0)


@pytest.mark.parametrize("bitrate", [125_000, None])
def test_sdo_answers_take_the_bus_time_of_two_frames(bitrate: "int | None") -> None:
    sim = Epos4Simulator(1, [2], can_bitrate=bitrate)
    net = canopen.Network()
    net.connect(interface="virtual", channel=sim.channel, receive_own_messages=False)
    node = canopen.RemoteNode(2, str(EDS_PATH))
    net.add_node(node)
    try:
        rounds = 20
        start = time.perf_counter()
        for _ in range(rounds):
            assert node.sdo.upload(0x1000, 0)  # device type
        per_transfer = (time.perf_counter() - start) / rounds
        if bitrate is not None:  # a lower bound only: a busy machine is slower, never faster
            assert per_transfer >= 2 * frame_time(8, bitrate)
    finally:
        net.disconnect()
        sim.close()
