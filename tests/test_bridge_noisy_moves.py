"""Issue 22, item 8: a move's reply says what the drive did, also on a noisy link.

A trial served the ``epos`` backend with 5% of the EPOS4's reply bytes
corrupted (``epos-link sim --corrupt 0.05``). Two findings, each tested the
way a user meets it, over TCP and the bridge against the simulated EPOS4
(``tests/bridge_sim.py``), looking at the simulated drive itself:

* relative moves were answered NAK although the drive made the full step, so
  a client that retries a NAK'd move moved twice;
* a relative move after a move that the bridge had halted (S00=8) went from
  the halted move's old target, not from where the axis stood (CiA 402-2 6.7:
  a relative target counts from the preceding target).

The rules are in :mod:`tcp_bridge.motion` (rule 4) and :mod:`tcp_bridge.motion.start`.
"""
from __future__ import annotations

from typing import Iterator, List, Tuple

import pytest

from epos_link.simulator.link import LinkOptions
from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge

FACTOR = 1000  # increments per mm: every step below is exact in increments
TARGET_REACHED = 0x0400  # CiA 402-2 statusword bit 10
# The link answers at once (sim://); 20 ms is ample for an in-process answer
# and keeps the cost of a reply whose length byte was garbled small.
CLIENT_TIMEOUT = 0.02


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    # The trial's ack_timeout (3 s); drive 3 is a slave in the last test.
    b = SimBridge(drives=(2, 3), timing={"ack_timeout": 3.0}, client_timeout=CLIENT_TIMEOUT)
    yield b
    b.close()


def at_rest(b: SimBridge, node: int) -> None:
    b.wait_until(lambda: bool(b.now(node).statusword & TARGET_REACHED) and b.velocity(node) == 0,
                 why=f"drive {node} never came to rest")


def moved(b: SimBridge, node: int, line: str) -> Tuple[Status, int, int]:
    """Send ``line``; (its answer, how far the drive went, how many motions it started)."""
    position, starts = b.position(node), b.now(node).motion_starts
    status = b.ask(line).status
    at_rest(b, node)
    return status, b.position(node) - position, b.now(node).motion_starts - starts


# --- finding 1: a NAK'd move had moved ----------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2])
def test_on_a_noisy_link_every_move_answer_tells_what_the_drive_did(
        bridge: SimBridge, seed: int) -> None:
    b = bridge
    wanted = 25  # steps of 1 mm; about 5 s on the development VM
    b.ok("2S04=1", "2S05=50", "2S06=1000", "2S02=1")
    start = b.position(2)
    b.transport.add_noise(LinkOptions(corrupt=0.05, seed=seed))
    answers: List[Status] = []
    made = 0
    while made < wanted:
        # A careful client: it sends the move again when it was answered NAK.
        status, step, starts = moved(b, 2, "2S00=2")
        answers.append(status)
        if status is Status.ACK:
            assert (step, starts) == (FACTOR, 1), f"move {len(answers)}: ACK, but {step} inc"
            made += 1
        else:
            # NAK: the move did not start (a silent bus is refused at once; see
            # tcp_bridge.bus.health), so the client may safely send it again.
            assert (step, starts) == (0, 0), f"move {len(answers)}: NAK, yet moved {step} inc"
            # Its next try waits for the bus to be served again (a periodic probe).
            b.wait_until(lambda: b.engine.guards["can1"].health.refusal(2) is None,
                         why="the bus was never served again")
        # A garbled answer is retried within the move's bound: it alone never
        # makes a move NAK (the prepare steps are idempotent, the start is read back).
        assert answers.count(Status.NAK) <= wanted // 4, answers
    assert b.position(2) - start == wanted * FACTOR  # the sum of the ACK'd steps, exactly
    assert not b.now(2).unsafe_stops


# --- finding 2: a relative move after a halted move -------------------------------------


def halted_mid_move(b: SimBridge, *axes: int) -> None:
    """An absolute move of ``axes[0]`` (its slaves follow) stopped half-way by S00=8."""
    master = axes[0]
    b.ok(f"{master}S02=20", f"{master}S00=1")
    b.wait_until(lambda: b.position(master) > 5 * FACTOR, why="the move never got going")
    b.ok(f"{master}S00=8")
    for axis in axes:
        at_rest(b, axis)
    assert b.position(master) < 19 * FACTOR  # it really stopped short of its target


def test_a_relative_move_after_a_halted_move_goes_from_where_the_axis_stands(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=20", "2S06=100")
    halted_mid_move(b, 2)
    for distance in ("1", "-1", "2.5"):
        b.ok(f"2S02={distance}")
        status, step, _ = moved(b, 2, "2S00=2")
        assert status is Status.ACK
        assert step == round(float(distance) * FACTOR), f"asked {distance} mm, moved {step} inc"


def test_each_axis_of_a_slave_move_goes_its_distance_from_its_own_position(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("3S04=1", "2S04=1", "2S05=20", "2S06=100", "2S29=3", "2S30=-1")
    b.ok("3S25=7")  # the slave's own offset: never applied to a distance
    halted_mid_move(b, 2, 3)
    before = b.positions(2, 3)
    b.ok("2S02=1")
    assert b.ask("2S00=2").status is Status.ACK
    at_rest(b, 2)
    at_rest(b, 3)
    after = b.positions(2, 3)
    # The slave mirrors its master (S30=-1), each from where it stood.
    assert [a - s for a, s in zip(after, before)] == [FACTOR, -FACTOR]
