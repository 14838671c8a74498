"""tcp_bridge.bus.order: slots that hold a stage's place on its bus, units, and stops that
supersede the moves in flight they follow (issue 30, finding 1). The end-to-end cases,
two clients and simulated drives, are in tests/test_bridge_stage_order.py."""
from __future__ import annotations

import asyncio
import threading
from types import SimpleNamespace
from typing import Any, Iterator, List

import pytest

from tcp_bridge.bus.order import UNUSED, InFlight, Slot, Unit
from tcp_bridge.bus.workers import BusWorker
from tcp_bridge.errors import DeviceFailure, Superseded
from tcp_bridge.wire import WriteRequest


def job(*addrs: int, text: str = "1S00=1", urgent: bool = False) -> Any:
    """What a Unit needs of a tcp_bridge.plan.job.Job: its request, the axes it moves."""
    axis, cmd, value = int(text[0]), int(text[2:4]), text.split("=")[1]
    return SimpleNamespace(request=WriteRequest(axis, cmd, value), urgent=urgent,
                           moves=tuple(SimpleNamespace(addr=a) for a in addrs),
                           stops=tuple(SimpleNamespace(addr=a) for a in addrs),
                           companions=(), stop=None)


@pytest.fixture
def loop() -> Iterator[asyncio.AbstractEventLoop]:
    loop = asyncio.new_event_loop()
    yield loop
    loop.close()


def unit_of(loop: asyncio.AbstractEventLoop, *addrs: int, wait: float = 30.0) -> Unit:
    return Unit(job(*addrs), wait, loop.create_future())


def in_thread(fn: Any) -> "tuple[threading.Thread, List[Any]]":
    """Run ``fn`` as a bus thread would; its result (or exception) lands in the list."""
    out: List[Any] = []

    def run() -> None:
        try:
            out.append(fn())
        except Exception as exc:
            out.append(exc)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, out


# -- slots -------------------------------------------------------------------------------


def test_a_slot_waits_for_its_stage_then_runs_it(loop: asyncio.AbstractEventLoop) -> None:
    unit = unit_of(loop, 1)
    slot = unit.slot(job(1), flush=lambda: None)
    t, out = in_thread(slot)
    t.join(0.05)
    assert t.is_alive() and out == []  # holds its bus until the stage before it ended
    slot.give(lambda: "moved")
    t.join(10)
    assert out == ["moved"]


def test_a_slot_not_needed_is_released_when_its_plan_ends(loop: asyncio.AbstractEventLoop
                                                          ) -> None:
    unit = unit_of(loop, 1)
    t, out = in_thread(unit.slot(job(1), flush=lambda: None))
    unit.end()
    t.join(10)
    assert out == [UNUSED]


def test_a_slot_hands_over_its_buses_held_results_before_it_waits(
        loop: asyncio.AbstractEventLoop) -> None:
    flushed = threading.Event()
    unit = unit_of(loop, 1)
    t, out = in_thread(unit.slot(job(1), flush=flushed.set))
    assert flushed.wait(10)
    unit.end()
    t.join(10)


def test_a_slot_waits_at_most_its_bound(loop: asyncio.AbstractEventLoop,
                                        caplog: pytest.LogCaptureFixture) -> None:
    unit = unit_of(loop, 1, wait=0.01)
    t, out = in_thread(unit.slot(job(1), flush=lambda: None))
    t.join(10)
    assert out == [UNUSED] and "dropped" in caplog.text


def test_superseded_a_waiting_stage_frees_its_bus_at_once_and_a_halt_still_runs(
        loop: asyncio.AbstractEventLoop) -> None:
    unit = unit_of(loop, 1)
    move = unit.slot(job(1), flush=lambda: None)
    halt = unit.slot(job(1, urgent=True), flush=lambda: None)
    t_move, out_move = in_thread(move)
    t_halt, out_halt = in_thread(halt)
    assert unit.supersede("1S00=8 arrived after it")
    t_move.join(10)
    assert len(out_move) == 1 and isinstance(out_move[0], Superseded)
    assert isinstance(out_move[0], DeviceFailure)  # answered NAK
    t_halt.join(0.05)
    assert t_halt.is_alive()  # a halt keeps its place
    halt.give(lambda: "halted")
    t_halt.join(10)
    assert out_halt == ["halted"]


# -- guard: not begun never begins -----------------------------------------------------------


def test_a_stage_not_begun_never_begins_once_superseded(loop: asyncio.AbstractEventLoop) -> None:
    unit = unit_of(loop, 1)
    ran: List[str] = []
    move = unit.guard(lambda: ran.append("move"), moves=True, halting=False)
    halt = unit.guard(lambda: ran.append("halt"), moves=False, halting=True)
    unit.supersede("2S16=1 arrived after it")
    with pytest.raises(Superseded, match="2S16=1"):
        move()
    halt()
    assert ran == ["halt"] and not unit.begun


def test_begun_is_only_a_stage_that_moves_and_the_halts_run_only_then(
        loop: asyncio.AbstractEventLoop) -> None:
    halted: List[int] = []
    unit = unit_of(loop, 1)
    unit.guard(lambda: None, moves=False, halting=False)()  # a precheck
    unit.halt_if_begun(lambda: halted.append(1))()
    assert halted == [] and not unit.begun
    unit.guard(lambda: None, moves=True, halting=False)()  # the main job
    unit.halt_if_begun(lambda: halted.append(2))()
    assert unit.begun and halted == [2]


def test_a_slot_given_before_the_stop_but_not_yet_started_never_begins(
        loop: asyncio.AbstractEventLoop) -> None:
    unit = unit_of(loop, 1)
    slot = unit.slot(job(1), flush=lambda: None)
    ran: List[str] = []
    slot.give(unit.guard(lambda: ran.append("move"), moves=True, halting=False))
    unit.supersede("1S00=8 arrived after it")
    with pytest.raises(Superseded):
        slot()  # its turn on the bus comes after the stop arrived
    assert ran == []


# -- in flight ---------------------------------------------------------------------------------


def test_a_stop_supersedes_each_move_in_flight_of_its_axes_once(
        loop: asyncio.AbstractEventLoop, caplog: pytest.LogCaptureFixture) -> None:
    flight = InFlight()
    line, other = unit_of(loop, 1, 2), unit_of(loop, 3)
    flight.admit(line)
    flight.admit(other)
    caplog.set_level("INFO", "tcp_bridge.engine")
    assert flight.superseded_by(job(1, 2, text="1S90=0")) == [line]
    assert line.superseded == "1S90=0 arrived after it" and other.superseded is None
    assert "1S90=0 supersedes 1S00=1" in caplog.text
    flight.leave(line)
    assert line.done.done() and flight.all() == [other]
    assert flight.superseded_by(job(2, text="2S00=8")) == []  # its plan ended: too late


def test_a_stop_arriving_after_the_plan_ended_supersedes_nothing(
        loop: asyncio.AbstractEventLoop) -> None:
    unit = unit_of(loop, 1)
    unit.end()
    assert not unit.supersede("1S00=8 arrived after it") and unit.superseded is None


# -- in a bus's order --------------------------------------------------------------------------


def test_a_request_that_arrives_later_runs_after_every_slot_of_an_earlier_one(
        loop: asyncio.AbstractEventLoop) -> None:
    """Two buses: the later request's job on bus B waits until the earlier request's
    second stage, whose place on B was taken at its arrival, has run."""
    a, b = BusWorker("a"), BusWorker("b")
    order: List[str] = []

    async def scenario() -> None:
        unit = unit_of(asyncio.get_running_loop(), 1)
        first = a.submit(lambda: order.append("stage 1 on a"))
        slot = unit.slot(job(1), flush=b.flush)
        second = b.submit(slot)  # its place on b, reserved when the request arrived
        later = b.submit(lambda: order.append("a later request on b"))
        await first
        slot.give(lambda: order.append("stage 2 on b"))
        await asyncio.gather(second, later)

    try:
        loop.run_until_complete(asyncio.wait_for(scenario(), 30))
    finally:
        a.close()
        b.close()
    assert order == ["stage 1 on a", "stage 2 on b", "a later request on b"]
