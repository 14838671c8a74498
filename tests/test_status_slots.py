"""tcp_bridge.status.slots: who may hold a status page slot, and the page's rate (issue 35)."""
from __future__ import annotations

import pytest

from tcp_bridge.status.slots import HEAD_GRACE, Phase, RateLimit, Slot, Slots


def test_a_newcomer_takes_the_slot_of_the_oldest_unfinished_head() -> None:
    slots = Slots()
    a, b, c = Slot("a", 0.0), Slot("b", 1.0), Slot("c", 2.0)
    for s in (a, b, c):
        assert slots.admit(s, 3) == (True, None)
    a.enter(Phase.ANSWER, 3.0)  # a's head is complete: it is never taken
    d = Slot("d", 4.0)
    assert slots.admit(d, 3) == (True, b)  # b has been in HEAD the longest
    assert b.evicted and len(slots) == 3


def test_with_no_unfinished_head_a_newcomer_is_refused() -> None:
    slots = Slots()
    held = [Slot(i, float(i)) for i in range(2)]
    for s in held:
        slots.admit(s, 2)
        s.enter(Phase.QUEUED, 5.0)
    assert slots.admit(Slot("new", 6.0), 2) == (False, None)
    assert not any(s.evicted for s in held)


def test_a_new_stream_takes_a_stalled_streams_slot_first_then_the_oldest() -> None:
    slots = Slots()
    streams = [Slot(i, 0.0) for i in range(3)]
    for i, s in enumerate(streams):
        slots.admit(s, 10)
        assert slots.stream(s, float(i), 3, lambda other: False) is None
    stalled = {streams[2]}
    new = Slot("new", 9.0)
    slots.admit(new, 10)
    assert slots.stream(new, 9.0, 3, lambda other: other in stalled) is streams[2]
    newer = Slot("newer", 10.0)
    slots.admit(newer, 10)
    assert slots.stream(newer, 10.0, 3, lambda other: False) is streams[0]  # the oldest
    assert [s.handle for s in slots.in_phase(Phase.STREAM)] == [1, "new", "newer"]


def test_the_rate_limit_lets_a_burst_through_then_spaces_requests() -> None:
    limit = RateLimit(rate=10.0, burst=3)
    assert [limit.take(0.0) for _ in range(3)] == [0.0, 0.0, 0.0]
    assert limit.take(0.0) == pytest.approx(0.1)  # the 4th waits for one token
    assert limit.take(0.0) == pytest.approx(0.2)  # the 5th behind it
    assert limit.take(10.0) == 0.0  # a quiet spell refills the bucket (up to the burst)
    assert [limit.take(10.0) for _ in range(2)] == [0.0, 0.0]
    assert limit.take(10.0) > 0


@pytest.mark.parametrize("rate,burst", [(0.0, 1), (-1.0, 1), (1.0, 0)])
def test_a_rate_limit_needs_a_rate_and_a_burst(rate: float, burst: int) -> None:
    with pytest.raises(ValueError):
        RateLimit(rate, burst)


def test_a_head_younger_than_the_grace_is_not_taken() -> None:
    """A head that has arrived but not been read yet (a loaded page, bench/status_page.py)
    keeps its slot; once it has been coming for HEAD_GRACE it may be taken."""
    slots = Slots()
    young = Slot("young", 10.0)
    assert slots.admit(young, 1) == (True, None)
    assert slots.stale_heads(10.1) == [] and slots.next_stale(10.1) == pytest.approx(HEAD_GRACE - 0.1)
    assert slots.admit(Slot("new", 10.0 + HEAD_GRACE / 2), 1) == (False, None)
    assert not young.evicted
    assert slots.next_stale(10.0 + HEAD_GRACE) is None  # stale now: nothing to wait for
    assert slots.admit(Slot("later", 10.0 + HEAD_GRACE), 1) == (True, young)
    assert young.evicted
    young.enter(Phase.ANSWER, 11.0)
    assert Slots().next_stale(0.0) is None
