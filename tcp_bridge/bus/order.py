"""Arrival order for the whole of a request, and a stop as the last word (issue 30, finding 1).

A move with companions runs in stages (:func:`tcp_bridge.plan.job.steps`): the
companions' precheck, the main job, the companions, and the halts if a companion
failed. Each stage may need the outcome of the one before, so they cannot all be
queued as jobs at once; queued one by one as each ended, a request that arrived
in between (from either port) ran between two stages of the move: a stop that
answered ACK before the move it followed had started.

The rules:

1. **One request, one unit in the bus order.** When a request arrives (on the
   event loop, in the order requests arrive from every connection), its first
   stage is queued and every later stage gets a :class:`Slot`, a job queued on
   the stage's bus at once. A slot waits on its bus thread until the scheduler
   gives it the stage's job (the stage before it ended), runs it, or returns
   :data:`UNUSED` when released (the plan does not need it: the companions of a
   refused move, the halts of a move that started whole). Everything that
   arrives later queues behind every slot of the request on every bus they
   share, so nothing runs between two stages of it. Before it waits, a slot hands
   over the results its bus still holds (:meth:`tcp_bridge.bus.workers.BusWorker.flush`,
   "Replies after the next request"): the stage it waits for may need one of them.
2. **No deadlock, no stall.** A slot waits only for an earlier stage of its own
   request. That stage's job stands in its own bus's queue behind jobs of earlier
   requests only, which by the same rule wait for nothing later. A slot waits at
   most the request's safety net (``job_timeout``), and the scheduler releases
   every slot of a request when its plan ends, whatever the outcome, so a bus
   thread is never held past the request it serves.
3. **A stop is the last word.** A :class:`Unit` is a request that sets axes
   moving (``Job.moves``), from its arrival until its plan ended. A stop
   (S00=8, S90=0, S04=0, S16, S17: ``Job.stops``) that arrives while such a unit
   is in flight for one of its axes *supersedes* it, at its arrival and before
   the stop's own jobs are queued:

   * stages not yet begun never begin: their job raises :class:`Superseded`
     (answered NAK) instead of running;
   * begun ones are brought to rest: a halt of every axis of the move is queued
     at once, ahead of the stop's own jobs, and runs (when its turn comes on its
     bus, after the move's own stages there) only if a stage of the move began;
   * the stop's reply waits until the move's plan and those halts ended, so its
     ACK never precedes a start of the move it followed.

   Only moves in flight are superseded: a move whose plan already ended (its
   reply went out) is stopped by the stop's own jobs, as before.

Threads: units and the table of moves in flight are made and read on the event
loop; a slot runs on its bus thread. A unit's condition guards what both touch
(the jobs given, the slots released, superseded, begun).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable, Dict, Final, List, Optional

from ..errors import Superseded

if TYPE_CHECKING:
    import asyncio

    from ..plan.job import Job

log = logging.getLogger("tcp_bridge.engine")

UNUSED: Final = object()  # what a released slot returns: its stage was not needed


class Unit:
    """A request that sets axes moving, from its arrival until its plan ended (rule 3)."""

    def __init__(self, job: "Job", wait: float, done: "asyncio.Future[Any]") -> None:
        self.job = job
        self.done = done  # set when the plan ended (event loop): a stop's reply waits for it
        self.addrs = frozenset(axis.addr for axis in job.moves)
        self.wait = wait  # seconds a slot waits for its stage at most (rule 2)
        self.cond = threading.Condition(threading.Lock())
        self.superseded: Optional[str] = None  # why, once a stop arrived
        self.begun = False  # a stage that sets an axis moving has started
        self.ended = False
        self._slots: Dict[int, "Slot"] = {}  # by id() of the stage's job
        self.halts: List["asyncio.Future[Any]"] = []  # queued when superseded

    # -- the event loop ------------------------------------------------------------------

    def slot(self, job: "Job", flush: Callable[[], None]) -> "Slot":
        """A new slot for ``job``'s stage; the caller queues it on ``job.bus``, whose
        worker's ``flush`` hands over the results it holds."""
        slot = self._slots[id(job)] = Slot(self, flush, halting=job.urgent)
        return slot

    def slot_of(self, job: "Job") -> Optional["Slot"]:
        return self._slots.get(id(job))

    def supersede(self, why: str) -> bool:
        """A stop arrived (rule 3); False if it came too late to matter (plan ended)."""
        with self.cond:
            if self.ended:
                return False
            if self.superseded is None:
                self.superseded = why
            self.cond.notify_all()
        return True

    def end(self) -> None:
        """The plan ended: release every slot not given a job (rule 2)."""
        with self.cond:
            self.ended = True
            self.cond.notify_all()

    # -- any thread ----------------------------------------------------------------------

    def guard(self, job: Callable[[], Any], *, moves: bool, halting: bool) -> Callable[[], Any]:
        """``job`` as its bus runs it: not begun if the unit was superseded (unless it is a
        halt), and counted as begun if it sets an axis moving."""
        def run() -> Any:
            with self.cond:
                if not halting:
                    if self.superseded is not None:
                        raise Superseded(f"not begun: {self.superseded}")
                    if moves:
                        self.begun = True
            return job()
        return run

    def halt_if_begun(self, halt: Callable[[], Any]) -> Callable[[], Any]:
        """``halt``, run only if a stage of this unit began (rule 3: begun ones are halted)."""
        def run() -> Any:
            with self.cond:
                begun = self.begun
            return halt() if begun else None
        return run


class Slot:
    """A stage's place in its bus's queue, reserved when its request arrived (rule 1)."""

    def __init__(self, unit: Unit, flush: Callable[[], None], *, halting: bool) -> None:
        self.unit = unit
        self._flush = flush
        self.halting = halting  # a halt: runs even after the unit was superseded
        self._job: Optional[Callable[[], Any]] = None
        self.future: Optional["asyncio.Future[Any]"] = None  # its job's, on the bus worker

    def give(self, job: Callable[[], Any]) -> None:
        """The stage before ended: run ``job`` when the slot's turn comes (event loop)."""
        with self.unit.cond:
            self._job = job
            self.unit.cond.notify_all()

    def __call__(self) -> Any:
        """The bus thread, at the slot's turn: wait for the stage's job, then run it."""
        unit = self.unit
        with unit.cond:
            given = self._job is not None
        if not given:
            self._flush()  # the stage this slot waits for may wait for a result held here
        with unit.cond:
            deadline = time.monotonic() + unit.wait
            while self._job is None and not unit.ended:
                if unit.superseded is not None and not self.halting:
                    break  # rule 3: it would not begin; free the bus now
                left = deadline - time.monotonic()
                if left <= 0:
                    log.error("a stage waited %.0f s for its turn and was dropped", unit.wait)
                    break
                unit.cond.wait(left)
            job = self._job
            if job is None:
                if unit.superseded is not None and not self.halting and not unit.ended:
                    raise Superseded(f"not begun: {unit.superseded}")
                return UNUSED
        return job()


class InFlight:
    """The moves in flight by axis (event loop only; bounded by the requests in flight)."""

    def __init__(self) -> None:
        self._by_axis: Dict[int, List[Unit]] = {}

    def admit(self, unit: Unit) -> None:
        for addr in unit.addrs:
            self._by_axis.setdefault(addr, []).append(unit)

    def leave(self, unit: Unit) -> None:
        """``unit``'s plan ended: its slots are released, the stops it waits for told."""
        unit.end()
        if not unit.done.done():
            unit.done.set_result(None)
        for addr in unit.addrs:
            units = self._by_axis.get(addr, [])
            if unit in units:
                units.remove(unit)
            if not units:
                self._by_axis.pop(addr, None)

    def superseded_by(self, job: "Job") -> List[Unit]:
        """Every move in flight of an axis that ``job`` (a stop) brings to rest, each once,
        marked superseded (rule 3)."""
        what = _text(job)
        found: List[Unit] = []
        for axis in job.stops:
            for unit in self._by_axis.get(axis.addr, ()):
                if unit not in found and unit.supersede(f"{what} arrived after it"):
                    found.append(unit)
        for unit in found:
            log.info("%s supersedes %s, still in flight: its stages not begun never begin, "
                     "begun ones are halted", what, _text(unit.job))
        return found

    def all(self) -> List[Unit]:
        return list({id(u): u for units in self._by_axis.values() for u in units}.values())


def _text(job: "Job") -> str:
    """``1S90=1``: the request as the client wrote it (for the log)."""
    r = job.request
    value = getattr(r, "value", None)
    return f"{r.axis}{r.kind}{r.cmd:02d}" + (f"={value}" if value is not None else "")


__all__ = ["InFlight", "Slot", "UNUSED", "Unit"]
