"""Rule 3 of tcp_bridge.backends.ethercat_cycle: a slave whose state reads go unanswered
is lost only after SILENT_CHECKS checks in a row *and* ``silent_after`` seconds.

Seen under load (issue 32): the suite at load 4 lost a simulated slave after three
state reads of about 16 ms each got no answer, the axis answered NAK ("slave 1 is in
NONE") and a test failed; the slave had never left OP (its watchdog is 100 ms). The
clock is injected: no wall-clock bound.
"""
from __future__ import annotations

from typing import Any, Dict, List

from tcp_bridge.backends.ethercat_cycle import NONE, OP, SILENT_CHECKS, CycleLoop


class Slave:
    def __init__(self) -> None:
        self.state = OP
        self.input = b"\0" * 4
        self.output = b"\0" * 4
        self.al_status = 0
        self.recovered = 0

    def recover(self, timeout: int) -> int:
        self.recovered += 1
        return 0  # still gone

    def write_state(self) -> None:
        pass


class Master:
    expected_wkc = 3

    def __init__(self, slaves: List[Slave]) -> None:
        self.slaves = slaves
        self.answers = True

    def read_state(self) -> None:
        if not self.answers:  # no frame back: SOEM leaves the states it could not read 0
            for slave in self.slaves:
                slave.state = NONE


def loop(now: List[float]) -> "tuple[CycleLoop, Master, Dict[int, str]]":
    slave = Slave()
    master = Master([slave])
    cycle = CycleLoop(master, {1: slave}, 0.004, al_text=lambda code: "", silent_after=0.1,
                      clock=lambda: now[0])
    lost: Dict[int, str] = {}
    cycle.on_lost = lambda position, why: lost.__setitem__(position, why)
    return cycle, master, lost


def check(cycle: Any, now: List[float], dt: float) -> None:
    now[0] += dt
    cycle._check_states()


def test_three_unanswered_checks_within_the_watchdog_time_are_not_a_drop_out() -> None:
    now = [100.0]
    cycle, master, lost = loop(now)
    master.answers = False
    for _ in range(SILENT_CHECKS + 3):  # 6 checks 16 ms apart: 96 ms, under 100 ms
        check(cycle, now, 0.016)
    assert lost == {} and cycle.lost == {}
    master.answers = True  # the host caught up: the slave answers, in OP all along
    master.slaves[0].state = OP
    check(cycle, now, 0.016)
    check(cycle, now, 0.5)
    master.answers = False  # a new silence counts from its own start
    for _ in range(SILENT_CHECKS):
        check(cycle, now, 0.03)
    assert lost == {}


def test_a_slave_silent_past_its_watchdog_time_is_lost() -> None:
    now = [100.0]
    cycle, master, lost = loop(now)
    master.answers = False
    check(cycle, now, 0.0)
    check(cycle, now, 0.05)
    check(cycle, now, 0.04)  # three checks, 90 ms: not yet
    assert lost == {}
    check(cycle, now, 0.02)  # 110 ms
    assert list(lost) == [1] and "slave 1 is in NONE" in lost[1]


def test_many_seconds_but_fewer_checks_than_silent_checks_are_not_a_drop_out() -> None:
    now = [100.0]
    cycle, master, lost = loop(now)
    master.answers = False
    for _ in range(SILENT_CHECKS - 1):
        check(cycle, now, 1.0)  # a stalled bridge: two checks, seconds apart
    assert lost == {}
    check(cycle, now, 1.0)
    assert list(lost) == [1]
