"""When and where a planned job runs: on the event loop at once, from PDOs, or on its
bus's worker (shared reads, fail-fast refusals, companions in parallel).

A job arrives fully planned (:mod:`tcp_bridge.plan`); the scheduler never changes what
it means. Writes and moves of one axis run on its bus's worker in the order their
requests arrived (one FIFO per bus); identical reads waiting in a queue share one
transfer (:mod:`.shared_reads`), and every other request closes the open groups of
the buses it touches, so a read after a write stays after it. Fail-fast buses
(:mod:`.health`): a job for a silent bus or node is refused before it is queued, and
again when its turn comes; stops, halts and a client's S16 are tried.

A request whose plan has several stages (a move with companions) is one unit in
the bus order: its later stages get their places on their buses when it arrives,
and a stop supersedes the moves still in flight that it follows
(:mod:`.order`, issue 30).
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any, Callable, List, Mapping, Optional, Sequence

from ..plan.job import Job, Outcome, steps
from .failfast import BusGuard
from .order import UNUSED, InFlight, Unit
from .shared_reads import BUSY, SharedReads

log = logging.getLogger("tcp_bridge.engine")


class Scheduler:
    """Runs jobs on the buses' workers (see the module docstring)."""

    def __init__(self, shared: Mapping[str, SharedReads], guards: Mapping[str, BusGuard],
                 job_timeout: float) -> None:
        self.shared = shared
        self.guards = guards
        self.job_timeout = job_timeout
        self.in_flight = InFlight()  # moves in flight by axis (.order rule 3)

    def at_once(self, job: Job) -> Any:
        """The value of a job that waits for nothing, else BUSY: one without a drive, or
        a status poll answered from PDOs (shared_reads rule 5), the common case of many
        polling clients."""
        if job.share is None:
            self._close_shared(job)
        if job.bus is None and not job.companions:
            return job()
        fast = self._from_pdo(job)
        if fast is None or self._refusal(job) is not None:
            return BUSY
        return self.shared[job.bus].answer_now(fast)  # type: ignore[index]

    async def queued(self, job: Job, tried: Optional[Job]) -> Any:
        """Run ``job`` on the bus workers; ``tried``: a read whose PDOs did not count
        (queued without trying them a second time).

        Everything up to the first wait runs at the request's arrival (:mod:`.order`):
        a stop supersedes the moves in flight it follows, and queues their halts ahead
        of its own jobs; a move becomes a unit, its first stage queued and its later
        stages given their places."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.job_timeout
        superseded = self._supersede(job) if job.stops else []
        unit: Optional[Unit] = None
        if job.moves:
            unit = Unit(job, self.job_timeout, loop.create_future())
            self.in_flight.admit(unit)
        try:
            value = await self._run(job, unit, tried, deadline)
        finally:
            if unit is not None:
                self.in_flight.leave(unit)
        if superseded:
            await self._settled(superseded, deadline)
        return value

    async def _run(self, job: Job, unit: Optional[Unit], tried: Optional[Job],
                   deadline: float) -> Any:
        loop = asyncio.get_running_loop()
        plan = steps(job)
        halts = {id(j.stop) for j in (job, *job.companions) if j.stop is not None}
        try:
            batch = next(plan)
            futures = [self._stage(unit, j, fast=j is not tried) for j in batch]
            if unit is not None and job.gated:
                self._reserve(unit, job, batch)
            while True:
                if all(f.done() for f in futures):  # answered at once (a read from PDOs)
                    outcomes: Sequence[Outcome] = [_result(f) for f in futures]
                else:
                    outcomes = await asyncio.wait_for(
                        asyncio.gather(*futures, return_exceptions=True),
                        max(deadline - loop.time(), 0.0))
                batch = plan.send(list(outcomes))
                if unit is not None and unit.superseded and all(id(j) in halts for j in batch):
                    # The stop that superseded the move queued these halts ahead of itself
                    # (.order rule 3): the reserved ones are released unused.
                    batch = plan.send([None] * len(batch))
                futures = [self._stage(unit, j, fast=j is not tried) for j in batch]
        except StopIteration as done:
            return done.value
        except asyncio.TimeoutError:
            # The safety net ran out before the move's own bounds did: the job
            # may still start its axes after the NAK. Its stages not begun never
            # begin, and every axis of the request is halted (queued behind it on
            # each bus, not awaited: the request already failed), so that a NAK
            # never leaves an axis moving.
            if unit is not None:
                unit.supersede("its safety net (job_timeout) ran out")
            for axis_job in (job, *job.companions):
                if axis_job.stop is not None:
                    self._submit(axis_job.stop).add_done_callback(_log_halt)
            raise

    def _reserve(self, unit: Unit, job: Job, first: Sequence[Job]) -> None:
        """Places on their buses for every stage after ``first`` (.order rule 1)."""
        halts = tuple(j.stop for j in (job, *job.companions) if j.stop is not None)
        for stage in ((job,), job.companions, halts):
            for j in stage:
                if j.bus is not None and not any(j is f for f in first):
                    shared = self.shared[j.bus]
                    slot = unit.slot(j, shared.worker.flush)
                    slot.future = shared.submit(slot)
                    # A slot whose stage never came (its plan ended before: refused,
                    # superseded) may end in Superseded that nobody awaits.
                    slot.future.add_done_callback(_retrieved)

    def _stage(self, unit: Optional[Unit], job: Job, *, fast: bool) -> "asyncio.Future[Any]":
        """Run one stage's job: in its reserved slot if it has one, else queued now."""
        if unit is None:
            return self._submit(job, fast=fast)
        moves = job is unit.job or any(job is c for c in unit.job.companions)
        run = unit.guard(job, moves=moves, halting=job.urgent)
        slot = unit.slot_of(job)
        if slot is None:
            return self._submit(job, fast=fast, run=run)
        refusal = self._refusal(job)
        if refusal is not None:
            slot.give(lambda: UNUSED)  # NAK at once: nothing sent
            future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
            future.set_exception(refusal)
            return future
        slot.give(self._guarded(job, run))
        assert slot.future is not None
        return slot.future

    def _supersede(self, job: Job) -> List[Unit]:
        """.order rule 3: the moves in flight that the stop ``job`` follows never begin what
        they have not begun; the halts of their axes are queued now, ahead of the stop."""
        units = self.in_flight.superseded_by(job)
        for unit in units:
            for axis_job in (unit.job, *unit.job.companions):
                halt = axis_job.stop
                if halt is not None and halt.bus is not None:
                    future = self._submit(halt, run=unit.halt_if_begun(halt))
                    future.add_done_callback(_log_superseded_halt)
                    unit.halts.append(future)
        return units

    async def _settled(self, units: List[Unit], deadline: float) -> None:
        """The stop's reply waits until the moves it superseded ended and were halted."""
        waits: List["asyncio.Future[Any]"] = [u.done for u in units]
        waits += [h for u in units for h in u.halts]
        loop = asyncio.get_running_loop()
        _, pending = await asyncio.wait(waits, timeout=max(deadline - loop.time(), 0.0))
        if pending:
            raise asyncio.TimeoutError("the moves this stop superseded have not ended")

    def close(self) -> None:
        """Release every stage still waiting for its turn (the engine closes)."""
        for unit in self.in_flight.all():
            unit.end()

    def run_sync(self, job: Job) -> Any:
        """Run a job in the caller's thread (tests, tools); raises on failure."""
        plan = steps(job)
        try:
            batch = next(plan)
            while True:
                batch = plan.send([_outcome(self._guarded(j)) for j in batch])
        except StopIteration as done:
            return done.value

    @staticmethod
    def _from_pdo(job: Job) -> Optional[Callable[[], Any]]:
        """A read of an axis fed by PDOs may be answered on the loop (shared_reads rule 5)."""
        port = job.axis.port if job.axis is not None and job.share is not None else None
        if port is None or getattr(port, "feed", None) is None:
            return None
        if job.axis is not None and getattr(job.axis.drive, "halt_owed", False):
            return None  # the job sends that halt first (Job.__call__), on the bus worker
        return lambda: port.pdo_only(job)  # type: ignore[union-attr]

    def _close_shared(self, job: Job) -> None:
        """Shared reads, rule 3: a read after this request does not join one before it."""
        for j in (job, *job.companions, *job.precheck):
            for bus in (j.bus, j.axis.config.bus if j.axis is not None else None):
                if bus in self.shared:
                    self.shared[bus].close_groups()  # type: ignore[index]

    def _submit(self, job: Job, *, fast: bool = True,
                run: Optional[Callable[[], Any]] = None) -> "asyncio.Future[Any]":
        """Queue ``job`` (``run``: the job as a unit wraps it) on its bus, or run it now."""
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        if job.bus is not None:
            refusal = self._refusal(job)
            if refusal is None:
                return self.shared[job.bus].submit(self._guarded(job, run), job.share,
                                                   fast=self._from_pdo(job) if fast else None)
            future.set_exception(refusal)  # NAK at once: nothing queued, nothing sent
            return future
        try:
            future.set_result((run or job)())
        except Exception as exc:
            future.set_exception(exc)
        return future

    def _refusal(self, job: Job) -> Optional[Exception]:
        if job.bus is None or job.urgent:
            return None
        return self.guards[job.bus].refusal(_node_of(job))

    def _guarded(self, job: Job, run: Optional[Callable[[], Any]] = None) -> Callable[[], Any]:
        if job.bus is None:
            return run or job
        return self.guards[job.bus].guarded(run or job, _node_of(job), check=not job.urgent)


def _retrieved(future: "asyncio.Future[Any]") -> None:
    if not future.cancelled():
        future.exception()  # seen: asyncio does not report it as never retrieved


def _log_superseded_halt(future: "asyncio.Future[Any]") -> None:
    if not future.cancelled() and future.exception() is not None:
        log.error("halt of a move superseded by a stop failed: %s", future.exception())


def _log_halt(future: "asyncio.Future[Any]") -> None:
    if not future.cancelled() and future.exception() is not None:
        log.error("halt after a timed-out move failed: %s", future.exception())


def _result(future: "asyncio.Future[Any]") -> Outcome:
    error = future.exception()
    return error if error is not None else future.result()


def _node_of(job: Job) -> Optional[int]:
    return job.axis.config.node_id if job.axis is not None else None


def _outcome(job: Callable[[], Any]) -> Outcome:
    try:
        return job()
    except Exception as exc:
        return exc


__all__ = ["Scheduler"]
