"""Issue 23: a profile position target beyond the drive's software limits (607Dh).

No public maxon source says whether an EPOS4 clamps such a target (CiA 402-2
6.5.2 allows it; the simulator does, epos_link/simulator/setpoints.py) or faults
(8A82h). Either way the axis would not do what the client asked, so the bridge
reads 607Dh before the start write and refuses the move (NAK, nothing started),
whoever wrote the limits: here another master, behind the bridge's back.
Axis 2 = node 2, factor 1000 (user units mm; 1 mm = 1000 increments).
"""
from __future__ import annotations

from typing import Iterator

import pytest

from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge, starts

LIMIT = 0x607D


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge()
    yield b
    b.close()


def limit_to_10_mm(b: SimBridge) -> None:
    b.other_master_write(2, LIMIT, 1, -10_000, 4)
    b.other_master_write(2, LIMIT, 2, 10_000, 4)


@pytest.mark.parametrize("how,target", [("1", "12"), ("2", "12"), ("1", "-10.5")])
def test_a_target_beyond_the_limits_is_refused_and_nothing_moves(
        bridge: SimBridge, how: str, target: str) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=100", "2S06=1000")
    limit_to_10_mm(b)
    before = starts(b, 2)
    b.ok(f"2S02={target}")
    assert b.ask(f"2S00={how}").status is Status.NAK
    assert starts(b, 2) == before and b.position(2) == 0 and b.velocity(2) == 0


def test_a_relative_step_that_would_leave_the_limits_is_refused_where_it_stands(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=100", "2S06=1000", "2S02=6", "2S00=1")
    b.poll("2R82", "1")
    limit_to_10_mm(b)
    before = starts(b, 2)
    assert b.ask("2S00=2").status is Status.NAK  # 6 + 6 = 12 mm > 10 mm
    assert starts(b, 2) == before and b.position(2) == 6000


def test_a_target_within_the_limits_and_switched_off_limits_move(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=100", "2S06=1000")
    limit_to_10_mm(b)
    b.ok("2S02=10", "2S00=1")  # on the limit itself: inside
    b.poll("2R82", "1")
    assert b.position(2) == 10_000
    b.other_master_write(2, LIMIT, 1, 0, 4)
    b.other_master_write(2, LIMIT, 2, 0, 4)  # min >= max: switched off (CiA 402-2 607Dh)
    b.ok("2S02=12", "2S00=1")
    b.poll("2R82", "1")
    assert b.position(2) == 12_000
