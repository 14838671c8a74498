"""Issue 35: a NAK says what it knows. A move whose answers are lost or garbled after its
start write is answered NAK, and the log says "outcome unknown" with what the drive
showed afterwards (position read back); R86 tells whether the drive took the move, so a
client can decide before it sends the move again. Nothing is started twice.

Over TCP, through the bridge and the real ``epos`` path to the simulated EPOS4
(``tests/bridge_sim.py``), looking at the simulated drive itself. The figure for
240 moves under 5% reply corruption is ``python bench/noisy_moves.py``.
"""
from __future__ import annotations

import logging
import re
from typing import Iterator, List

import pytest

from epos_link.messages import Message, ReadObject, WriteObject
from epos_link.simulator.link import LinkOptions
from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge

FACTOR = 1000  # increments per mm
NEW_SET_POINT = 0x0010  # CiA 402-2 6.7.1: cw bit 4
TARGET_REACHED = 0x0400  # sw bit 10


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    # The default bound and client timeout are 2 s and 0.5 s; a quarter of each here.
    b = SimBridge(drives=(2,), timing={"ack_timeout": 0.5}, client_timeout=0.1)
    b.ok("2S04=1", "2S05=50", "2S06=1000", "2S02=1")
    yield b
    b.close()


def at_rest(b: SimBridge, node: int) -> None:
    b.wait_until(lambda: bool(b.now(node).statusword & TARGET_REACHED) and b.velocity(node) == 0,
                 why=f"drive {node} never came to rest")


def unknown_lines(caplog: pytest.LogCaptureFixture) -> List[str]:
    return [r.getMessage() for r in caplog.records if "outcome unknown" in r.getMessage()]


def test_polls_lost_after_the_start_write_give_nak_and_outcome_unknown_with_the_position(
        bridge: SimBridge, caplog: pytest.LogCaptureFixture) -> None:
    """The start write is executed and answered; every statusword poll after it is
    lost until the bound runs out. The drive made its step all the same."""
    b = bridge
    lost = [False]

    def after_start(m: Message) -> bool:
        if isinstance(m, WriteObject) and m.node == 2 and m.index == 0x6040 \
                and int.from_bytes(m.data[:2], "little") & NEW_SET_POINT:
            lost[0] = True  # the start write itself is answered
            return False
        if isinstance(m, ReadObject) and m.node == 2 and m.index == 0x6064:
            lost[0] = False  # the read back after the NAK is answered again
        return lost[0] and isinstance(m, ReadObject) and m.node == 2 and m.index == 0x6041
    b.transport.lose_answers(after_start, 1 << 30)
    position, starts = b.position(2), b.now(2).motion_starts
    with caplog.at_level(logging.WARNING, logger="tcp_bridge.motion"):
        assert b.ask("2S00=2").status is Status.NAK
    at_rest(b, 2)
    b.transport.lose_answers(after_start, 0)
    assert (b.position(2) - position, b.now(2).motion_starts - starts) == (FACTOR, 1)
    (line,) = unknown_lines(caplog)
    assert line.startswith("axis 2 (can1 node 2): outcome unknown: the move is answered NAK")
    shown = int(re.search(r"position (-?\d+) \(6064h\)", line).group(1))  # type: ignore[union-attr]
    assert shown == b.position(2)  # the step had ended when it was read back
    assert f"6062h; {position} before the start write: it started" in line
    assert b.ok("2R86") == "1"  # the drive took the move: a client must not send it again
    assert int(float(b.ok("2R12")) * FACTOR) == b.position(2)


def test_a_start_refused_before_it_is_written_is_a_plain_nak(
        bridge: SimBridge, caplog: pytest.LogCaptureFixture) -> None:
    """Nothing went out: no "outcome unknown", R86 stays 0."""
    b = bridge
    b.ok("2S04=0")  # disabled: the move is refused before anything is written
    with caplog.at_level(logging.WARNING, logger="tcp_bridge.motion"):
        assert b.ask("2S00=2").status is Status.NAK
    assert unknown_lines(caplog) == []
    assert b.ok("2R86") == "0"


@pytest.mark.parametrize("seed", [3, 4])
def test_under_seeded_reply_corruption_every_nak_that_moved_says_outcome_unknown(
        bridge: SimBridge, caplog: pytest.LogCaptureFixture, seed: int) -> None:
    """5% of the EPOS4's reply bytes corrupted (``epos-link sim --corrupt 0.05``): an ACK
    moved exactly one step, a NAK that moved is logged "outcome unknown" with the
    position read back and R86 = 1, and no move started twice."""
    b = bridge
    b.transport.add_noise(LinkOptions(corrupt=0.05, seed=seed))
    for i in range(30):
        position, starts = b.position(2), b.now(2).motion_starts
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="tcp_bridge.motion"):
            status = b.ask("2S00=2").status
        at_rest(b, 2)
        step, started = b.position(2) - position, b.now(2).motion_starts - starts
        assert started <= 1, f"move {i}: started {started} times"
        if status is Status.ACK:
            assert (step, started) == (FACTOR, 1), f"move {i}: ACK, but {step} inc"
            continue
        b.wait_until(lambda: b.engine.guards["can1"].health.refusal(2) is None,
                     why="the bus was never served again")
        if started:
            lines = unknown_lines(caplog)
            assert len(lines) == 1 and "(6064h)" in lines[0], (i, lines)
