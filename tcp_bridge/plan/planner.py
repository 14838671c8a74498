"""From a resolved request to a :class:`~tcp_bridge.plan.job.Job`: the handler of its rule
(taken from the command table), the bus it runs on, its companions, its urgency and
the earlier writes it depends on. No I/O: the job's closures do the transfers.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator, Mapping, Optional, Sequence, Tuple

from ..tables.commands import CommandKind
from .axis import AxisRuntime
from .job import Job
from .tickets import Ticket
from .moves import MovePlan, Part, line_of, plan_combined, plan_move, plan_stop
from .reads import READS
from .resolve import Resolved
from .writes import WRITES

# Rows that need the drive although the table gives no SDO object (16: NMT).
_DRIVE_RULES = frozenset({"reset_node"})
# Issue 30: a stop is the last word for every move that arrived before it. These rows
# (with these values; None: any) bring their axis to rest and supersede its earlier moves.
_STOPS: Mapping[str, Optional[int]] = {"move": 8, "combined_move": 0, "inhibit": 0,
                                       "reset_node": None, "fault_reset": None}


def needs_bus(axis: AxisRuntime, r: Resolved) -> bool:
    """Whether the command touches the drive, so it runs on the bus worker."""
    if axis.port is None:
        return False
    if r.spec.kind is CommandKind.PARAMETER:
        return axis.parameter_object(r.spec.number) is not None
    return r.spec.needs_sdo or r.rule in _DRIVE_RULES


def plan(r: Resolved, axes: Mapping[int, AxisRuntime],
         internal: Sequence[AxisRuntime]) -> Job:
    """The job of ``r`` (an axis command; 91 and 99 are the engine's)."""
    axis = r.axis
    assert axis is not None
    bus = axis.config.bus if needs_bus(axis, r) else None
    if r.reading:
        run = READS[r.rule](r)
        share = (axis.addr, r.spec.number) if bus is not None else None
        return Job(r.request, run, bus=bus, axis=axis, share=share,
                   after=_read_after(axis, r))
    after = axis.tickets()  # before this request's own promise
    stops = _stopped(r, axis, internal)
    move = _move_plan(r, axes, internal)
    if move is None:
        write: Callable[[], object] = WRITES[r.rule](r)
        own = tuple(t for t in axis.tickets() if t not in after)  # promised by this request
        return Job(r.request, write, bus=bus, axis=axis, after=after, own=own,
                   urgent=r.rule == "reset_node",  # a client's S16 is never refused unsent
                   stops=stops)
    companions = tuple(_part_job(r, p, move.stopping) for p in move.companions)
    for p in move.companions:
        after += p.axis.tickets()
    gated = bool(companions) and not move.stopping
    precheck = tuple(Job(r.request, p.axis.need_drive().require_enabled, bus=p.axis.config.bus,
                         axis=p.axis) for p in move.companions) if gated else ()
    stop = Job(r.request, move.halt, bus=axis.config.bus, axis=axis, urgent=True) \
        if move.halt is not None else None
    moves: Tuple[AxisRuntime, ...] = ()
    if not move.stopping:
        moved = (*internal, *(p.axis for p in move.companions)) \
            if r.rule == "combined_move" else \
            (axis, *(f.axis for f in axis.followers), *(p.axis for p in move.companions))
        moves = tuple(dict.fromkeys(moved))  # each once, in order
    return Job(r.request, move.run, bus=bus, axis=axis, companions=companions, gated=gated,
               precheck=precheck, stop=stop, urgent=move.stopping, after=after,
               moves=moves, stops=stops)


def _stopped(r: Resolved, axis: AxisRuntime,
             internal: Sequence[AxisRuntime]) -> Tuple[AxisRuntime, ...]:
    """The axes a stop brings to rest (taken before planning it forgets the followers):
    its axis and the followers its last move started; S90=0 every internal axis."""
    if r.rule not in _STOPS or _STOPS[r.rule] not in (None, r.value):
        return ()
    if r.rule == "combined_move":
        return tuple(internal)
    return (axis, *line_of(axis))  # followers, leader, its profile line (issue 30)


def _move_plan(r: Resolved, axes: Mapping[int, AxisRuntime],
               internal: Sequence[AxisRuntime]) -> Optional[MovePlan]:
    axis = r.axis
    assert axis is not None and r.value is not None
    how = int(r.value)
    if r.rule == "move":
        return plan_move(axis, how, axes)
    if r.rule == "combined_move":
        if not internal:
            raise r.invalid("no internal axes with a drive are configured (spec 3.2)")
        return plan_combined(internal, how)
    if r.rule == "inhibit" and how == 0 and line_of(axis):
        return plan_stop(axis, then=WRITES["inhibit"](r), why="S04=0")
    return None


def _part_job(r: Resolved, part: Part, stopping: bool) -> Job:
    stop = Job(r.request, part.halt, bus=part.axis.config.bus, axis=part.axis, urgent=True) \
        if part.halt is not None else None
    return Job(r.request, part.run, bus=part.axis.config.bus, axis=part.axis, stop=stop,
               urgent=stopping)


def _read_after(axis: AxisRuntime, r: Resolved) -> Tuple[Ticket, ...]:
    # A parameter read answers the value the pending write will store: it stands or
    # falls with that write. Status reads use no pending value.
    if r.spec.kind is not CommandKind.PARAMETER:
        return ()
    return axis.tickets()


@contextmanager
def releasing(job: Job) -> Iterator[None]:
    """Around a job's run: :func:`release` its promises with the outcome, whatever it is."""
    try:
        yield
    except BaseException as exc:
        release(job, exc)
        raise
    release(job, None)


def release(job: Job, failure: Optional[BaseException]) -> None:
    """After a job's outcome is known, or when it never ran (refused, cancelled, timed
    out): end every promise of its request that its run did not end, as failed."""
    if job.axis is None:
        return
    for ticket in job.own:
        if not ticket.settled:
            job.axis.abandon(ticket, failure or RuntimeError("not run"))


__all__ = ["needs_bus", "plan", "release", "releasing"]
