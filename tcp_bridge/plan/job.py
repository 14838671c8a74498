"""A planned request (:class:`Job`) and the order its parts run in (:func:`steps`).

A job carries everything decided when its request was resolved: the bus, the
closure that does the transfers (it returns the value a read answers, or None),
the companion jobs of a move on other buses, the halts that undo a move, and
the tickets of earlier writes whose values it used. Running a job first sends
a halt its axis owes (motion rule 4), then waits for those tickets: a write it
was resolved against that failed makes it fail too, before it touches a drive
(:class:`DependencyFailed`, answered NAK), so "NAK: not executed" holds for
every request resolved after it as well.

:func:`steps` is the order of a move with companions, without any I/O:

1. every companion's drive must be enabled (read in parallel), else NAK and
   nothing moved;
2. the main move, and only if the drive accepted it,
3. the companions' moves, in parallel;
4. if one of them failed: halt every axis of the request, then NAK.

A stop (S00=8, S90=0) is not gated: every axis is told to stop, whatever the
others answer.

The stages are one unit in the bus order: :class:`tcp_bridge.bus.scheduler.Scheduler`
gives each of them its place on its bus when the request arrives
(:mod:`tcp_bridge.bus.order`), so nothing that arrives later runs between them. A
job names the axes its request sets moving (``moves``) and, for a stop, the axes
it brings to rest (``stops``): a stop supersedes every earlier move of those axes
still in flight.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import (TYPE_CHECKING, Any, Callable, Generator, List, Optional, Sequence, Tuple,
                    Union)

from ..errors import DependencyFailed
from .tickets import Ticket

if TYPE_CHECKING:
    from ..wire import Request
    from .axis import AxisRuntime

log = logging.getLogger("tcp_bridge.plan")

@dataclass
class Job:
    """One planned request: where it runs and what it does."""

    request: "Request"
    run: Callable[[], Any]
    bus: Optional[str] = None  # worker to run on; None: no drive involved, run on the loop
    axis: Optional["AxisRuntime"] = None
    companions: Tuple["Job", ...] = field(default_factory=tuple)
    gated: bool = False  # companions start only after this job succeeded (see steps())
    precheck: Tuple["Job", ...] = field(default_factory=tuple)  # before anything moves
    stop: Optional["Job"] = None  # halts what ``run`` started, if a companion fails
    share: Optional[Tuple[int, int]] = None  # (axis, command) of a read that may be shared
    # A stop or halt: tried even on a bus declared silent (tcp_bridge.bus.health),
    # because a NAK without trying could leave an axis moving; it costs one timeout at most.
    urgent: bool = False
    after: Tuple[Ticket, ...] = ()  # earlier writes whose values this job uses
    own: Tuple[Ticket, ...] = ()  # the writes of this request that later ones may use
    # Issue 30, finding 1 (tcp_bridge.bus.order): the axes this request sets moving, and
    # the axes a stop (S00=8, S90=0, S04=0, S16, S17) brings to rest.
    moves: Tuple["AxisRuntime", ...] = ()
    stops: Tuple["AxisRuntime", ...] = ()

    def __call__(self) -> Any:
        if self.bus is not None and self.axis is not None and self.axis.drive is not None:
            self.axis.drive.settle()  # a halt owed since a move's outcome was unknown
        for ticket in self.after:
            ticket.check()
        return self.run()


Outcome = Union[Any, BaseException]
Steps = Generator[Tuple[Job, ...], List[Outcome], Any]


def _first_failure(outcomes: Sequence[Outcome]) -> Optional[BaseException]:
    return next((o for o in outcomes if isinstance(o, BaseException)), None)


def steps(job: Job) -> Steps:
    """The order in which a job and its companions run (module docstring).

    Yields batches of jobs to run in parallel and receives their outcomes (the
    value or the exception, in batch order); returns the main job's value or
    raises the first failure. :class:`tcp_bridge.bus.scheduler.Scheduler` drives it.
    """
    if not job.gated:
        outcomes = yield (job, *job.companions)
        failure = _first_failure(outcomes)
        if failure is not None:
            raise failure
        return outcomes[0]
    if job.precheck:
        failure = _first_failure((yield job.precheck))
        if failure is not None:
            raise failure  # a companion cannot move: nothing has moved
    [outcome] = yield (job,)
    if isinstance(outcome, BaseException):
        raise outcome  # the main axis refused: its companions stay where they are
    failure = _first_failure((yield job.companions))
    if failure is not None:
        # Some axes of the request started: halt them all (a halt of an axis
        # that is not enabled is a no-op), then report the first failure.
        halts = tuple(j.stop for j in (job, *job.companions) if j.stop is not None)
        for halt, result in zip(halts, (yield halts)):
            if isinstance(result, BaseException):
                log.error("axis %s: halt after a failed companion move failed: %s",
                          halt.axis.addr if halt.axis else "?", result)
        raise failure
    return outcome


__all__ = ["DependencyFailed", "Job", "Outcome", "Steps", "Ticket", "steps"]
