"""A line is one motion, when more than one drive leaves it at once (issue 31, build bullet 1).

After a stall of the bridge or a cable pull every slave of a line drops out in the
same cycle. Each drive that leaves a run must be recorded (its ``on_end``: R86 of
its axis becomes 0, :func:`tcp_bridge.plan.cyclic_moves.left_the_line`) and named
in the log, not only the first: before, the second axis kept R86 = 1 for a move it
never made. The sender's cycle is driven by hand with an injected clock.
"""
from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any, Dict, Iterable, List, Mapping, Tuple, Union, cast

import pytest

from tcp_bridge.motion.cyclic import CyclicSender, Run
from tcp_bridge.motion.profile import AxisLimits, plan_line
from tcp_bridge.plan.cyclic_moves import left_the_line

OPERATION_ENABLED = 0x0237  # statusword, CiA 402-2 6.4.1.2 (remote, voltage enabled)
Seen = Union[int, str, None]


class Transport:
    """What the sender reads and writes; ``seen`` is each node's statusword or why lost."""

    def __init__(self) -> None:
        self.seen: Dict[int, Seen] = {1: OPERATION_ENABLED, 2: OPERATION_ENABLED}
        self.targets: List[Dict[int, int]] = []

    def statuswords(self, nodes: Iterable[int]) -> Dict[int, Seen]:
        return {n: self.seen[n] for n in nodes}

    def write_targets(self, targets: Mapping[int, int]) -> None:
        self.targets.append(dict(targets))

    def write_velocities(self, velocities: Mapping[int, int]) -> None:
        raise AssertionError("a position line sends no velocities")


def a_line(transport: Transport, on_end: Any) -> Tuple[CyclicSender, Run, List[float]]:
    now = [0.0]
    sender = CyclicSender("ecat", cast(Any, transport), 0.004, clock=lambda: now[0])
    limits = AxisLimits(10000.0, 40000.0, 80000.0)
    run = Run((1, 2), plan_line([0.0, 0.0], [20000.0, 10000.0], [limits, limits], 0.0),
              on_end=on_end)
    sender._runs.append(run)  # as start() does, without the thread: cycles by hand
    return sender, run, now


def test_every_drive_that_leaves_a_line_in_the_same_cycle_is_recorded() -> None:
    transport = Transport()
    ended: List[Tuple[int, str]] = []
    sender, run, now = a_line(transport, lambda node, why: ended.append((node, why)))
    for _ in range(10):
        now[0] += 0.004
        assert sender._cycle()
    transport.seen = {1: "slave 1 is in SAFEOP+ERROR", 2: "slave 2 is in SAFEOP+ERROR"}
    now[0] += 0.004
    sent = len(transport.targets)
    sender._cycle()
    assert ended == [(1, "lost: slave 1 is in SAFEOP+ERROR"),
                     (2, "lost: slave 2 is in SAFEOP+ERROR")]
    assert run.ended_by == (1, "lost: slave 1 is in SAFEOP+ERROR")  # the first ended it
    assert run.out == {1, 2}
    assert all(not t for t in transport.targets[sent:]), "set-points for drives that left"


def test_each_axis_that_left_reads_r86_0_and_the_log_names_it(
        caplog: pytest.LogCaptureFixture) -> None:
    axes = [SimpleNamespace(addr=a, config=SimpleNamespace(node_id=a), moving_ack=1)
            for a in (1, 2)]
    transport = Transport()
    sender, _run, now = a_line(transport, left_the_line(cast(Any, axes)))
    now[0] += 0.004
    sender._cycle()
    transport.seen = {1: "slave 1 is in SAFEOP+ERROR", 2: "slave 2 is in SAFEOP+ERROR"}
    now[0] += 0.004
    with caplog.at_level(logging.ERROR):
        sender._cycle()
    assert [a.moving_ack for a in axes] == [0, 0]
    text = caplog.text
    assert "axis 1 left its cyclic move (lost: slave 1 is in SAFEOP+ERROR); axes [2]" in text
    assert "axis 2 left its cyclic move too (lost: slave 2 is in SAFEOP+ERROR)" in text
    assert "node 2 left the cyclic move too" in text


def test_one_drive_leaving_still_ramps_the_other_down_and_keeps_its_r86() -> None:
    axes = [SimpleNamespace(addr=a, config=SimpleNamespace(node_id=a), moving_ack=1)
            for a in (1, 2)]
    transport = Transport()
    sender, run, now = a_line(transport, left_the_line(cast(Any, axes)))
    now[0] += 0.004
    sender._cycle()
    transport.seen[2] = 0x0217  # QUICK STOP ACTIVE (CiA 402-2 6.4.1.2)
    now[0] += 0.004
    sender._cycle()
    assert [a.moving_ack for a in axes] == [1, 0]  # axis 1's move was accepted, then ramped
    assert run.out == {2} and run.ended_by is not None and run.ended_by[0] == 2
    assert set(transport.targets[-1]) == {1}
