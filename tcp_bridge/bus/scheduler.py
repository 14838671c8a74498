"""When and where a planned job runs: on the event loop at once, from PDOs, or on its
bus's worker (shared reads, fail-fast refusals, companions in parallel).

A job arrives fully planned (:mod:`tcp_bridge.plan`); the scheduler never changes what
it means. Writes and moves of one axis run on its bus's worker in the order their
requests arrived (one FIFO per bus); identical reads waiting in a queue share one
transfer (:mod:`.shared_reads`), and every other request closes the open groups of
the buses it touches, so a read after a write stays after it. Fail-fast buses
(:mod:`.health`): a job for a silent bus or node is refused before it is queued, and
again when its turn comes; stops, halts and a client's S16 are tried.
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any, Callable, Mapping, Optional, Sequence

from ..plan.job import Job, Outcome, steps
from .failfast import BusGuard
from .shared_reads import BUSY, SharedReads

log = logging.getLogger("tcp_bridge.engine")


class Scheduler:
    """Runs jobs on the buses' workers (see the module docstring)."""

    def __init__(self, shared: Mapping[str, SharedReads], guards: Mapping[str, BusGuard],
                 job_timeout: float) -> None:
        self.shared = shared
        self.guards = guards
        self.job_timeout = job_timeout

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
        (queued without trying them a second time)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.job_timeout
        plan = steps(job)
        try:
            batch = next(plan)
            while True:
                futures = [self._submit(j, fast=j is not tried) for j in batch]
                if all(f.done() for f in futures):  # answered at once (a read from PDOs)
                    outcomes: Sequence[Outcome] = [_result(f) for f in futures]
                else:
                    outcomes = await asyncio.wait_for(
                        asyncio.gather(*futures, return_exceptions=True),
                        max(deadline - loop.time(), 0.0))
                batch = plan.send(list(outcomes))
        except StopIteration as done:
            return done.value
        except asyncio.TimeoutError:
            # The safety net ran out before the move's own bounds did: the job
            # may still start its axes after the NAK. Halt every axis of the
            # request (queued behind it on each bus, not awaited: the request
            # already failed), so that a NAK never leaves an axis moving.
            for axis_job in (job, *job.companions):
                if axis_job.stop is not None:
                    self._submit(axis_job.stop).add_done_callback(_log_halt)
            raise

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

    def _submit(self, job: Job, *, fast: bool = True) -> "asyncio.Future[Any]":
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        if job.bus is not None:
            refusal = self._refusal(job)
            if refusal is None:
                return self.shared[job.bus].submit(self._guarded(job), job.share,
                                                   fast=self._from_pdo(job) if fast else None)
            future.set_exception(refusal)  # NAK at once: nothing queued, nothing sent
            return future
        try:
            future.set_result(job())
        except Exception as exc:
            future.set_exception(exc)
        return future

    def _refusal(self, job: Job) -> Optional[Exception]:
        if job.bus is None or job.urgent:
            return None
        return self.guards[job.bus].refusal(_node_of(job))

    def _guarded(self, job: Job) -> Callable[[], Any]:
        if job.bus is None:
            return job
        return self.guards[job.bus].guarded(job, _node_of(job), check=not job.urgent)


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
