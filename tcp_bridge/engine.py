"""The command layer: a parsed request in, a 30-byte reply (or an exception) out.

::

    Request --prepare()--> Job --execute()--> reply bytes
              (event loop:          (bus worker thread: SDO transfers,
               validate, convert;    one BusWorker per bus,
               InvalidCommand=CAN)   tcp_bridge.workers; DeviceFailure = NAK)

:meth:`Engine.prepare` checks everything a request says (axis, command, R/W
rights, value, conversions, ranges) before any transfer is planned, so a
malformed request never reaches a drive. :meth:`Engine.execute` runs the job on
its bus's worker, so SDO traffic of one bus is serialised, buses run in
parallel, and the event loop never blocks. Exceptions propagate: the server
has the one place that turns them into replies
(:func:`tcp_bridge.protocol.format_error_reply`).

A move of an axis with a slave (commands 29/30) also moves the slave with its
direction (:mod:`tcp_bridge.moves`): a slave on the master's bus moves in the
master's own bus job, so both start together. Command 90 moves the configured
internal axes, and a slave on another bus moves too: these *companion* jobs
run on their own buses; the reply is ACK only if all of them succeed. A
move that starts motion is *gated* (:func:`steps`) so that no axis moves
unless every one can:

1. every companion's drive must be enabled (read in parallel), else NAK and
   nothing moved;
2. the main move, and only if the drive accepted it,
3. the companions' moves, in parallel;
4. if one of them failed: halt every axis of the request, then NAK.

A stop (S00=8, S90=0) is not gated: every axis is told to stop, whatever
the others answer.

Identical reads waiting in a bus's queue at the same time share one transfer
(:mod:`tcp_bridge.shared_reads`, issue 14); every other request closes the
open groups of the buses it touches, so a read after a write stays after it.
"""
from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field, replace
from importlib import metadata
from typing import (Any, Callable, Dict, Generator, List, Mapping, Optional, Sequence, Tuple,
                    Union)

from .axes import AxisConfig, AxisTable, ConfigError, DeviceCode, parameter_spec
from .parameters import ParameterStore
from .commands import CommandSpec, resolve
from .errors import InvalidCommand
from .failfast import BusGuard, log_change
from .health import BusHealth
from .moves import Follower, plan_move, stored_profile
from .operations import AxisOps
from .protocol import ReadRequest, Request, Status, format_read_reply, format_write_reply
from .sdo import SdoPort
from .shared_reads import BUSY, SHARE_WINDOW, SharedReads
from .motion import Timing
from .units import parse_value
from .workers import BusWorker

log = logging.getLogger(__name__)

SPEC_REVISION = "2.3"
GLOBAL_COMMANDS = frozenset({91, 99})  # answered for any axis number


def software_version() -> str:
    """Command 99: the spec revision served and the package version, e.g. "2.3-py0.1.0"."""
    try:
        version = metadata.version("epos-link")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        version = "0+unknown"
    return f"{SPEC_REVISION}-py{version}"


@dataclass
class Job:
    """One planned request: where it runs and what it does."""

    request: Request
    run: Callable[[], bytes]
    bus: Optional[str] = None  # worker to run on; None: no drive involved, run on the loop
    ops: Optional[AxisOps] = None
    companions: Tuple["Job", ...] = field(default_factory=tuple)
    gated: bool = False  # companions start only after this job succeeded (see steps())
    precheck: Tuple["Job", ...] = field(default_factory=tuple)  # before anything moves
    stop: Optional["Job"] = None  # halts what ``run`` started, if a companion fails
    share: Optional[Tuple[int, int]] = None  # (axis, command) of a read that may be shared
    # A stop or halt, or a client's reset node (S16): tried even on a bus declared
    # silent (tcp_bridge.health), because a NAK without trying could leave an axis
    # moving, and these are how a client gets a node back (one in NMT Stopped:
    # tcp_bridge.motion.nmt_stopped); it costs one timeout at most.
    urgent: bool = False

    def __call__(self) -> bytes:
        if self.bus is not None and self.ops is not None and self.ops.drive is not None:
            self.ops.drive.settle()  # a halt owed since a move's outcome was unknown
        return self.run()


Outcome = Union[bytes, BaseException]
Steps = Generator[Tuple[Job, ...], List[Outcome], bytes]


def _first_failure(outcomes: Sequence[Outcome]) -> Optional[BaseException]:
    return next((o for o in outcomes if isinstance(o, BaseException)), None)


def steps(job: Job) -> Steps:
    """The order in which a job and its companions run, without any I/O.

    Yields batches of jobs to run in parallel and receives their outcomes (the
    reply bytes or the exception, in batch order); returns the reply or raises
    the first failure. :meth:`Engine.execute` (bus workers) and
    :meth:`Engine.execute_sync` (caller's thread) are thin drivers over it.
    """
    if not job.gated:
        outcomes = yield (job, *job.companions)
        failure = _first_failure(outcomes)
        if failure is not None:
            raise failure
        return outcomes[0]  # type: ignore[return-value]
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
                          halt.ops.addr if halt.ops else "?", result)
        raise failure
    return outcome


def _log_halt(future: "asyncio.Future[bytes]") -> None:
    if not future.cancelled() and future.exception() is not None:
        log.error("halt after a timed-out move failed: %s", future.exception())


class Engine:
    """All axes, their parameters and their bus workers; the one command implementation."""

    def __init__(self, table: AxisTable, nodes: Mapping[int, Any], *,
                 params: Optional[ParameterStore] = None, backends: Sequence[Any] = (),
                 job_timeout: float = 60.0, share_window: float = SHARE_WINDOW,
                 link_probes: Optional[Mapping[str, Callable[[], Any]]] = None,
                 health_clock: Callable[[], float] = time.monotonic,
                 **cia402_options: Any) -> None:
        self.table = table
        self.params = params if params is not None else ParameterStore(table)
        self.debug = table.settings.debug
        self.job_timeout = job_timeout
        self.version = software_version()
        self.backends = list(backends)
        s = table.settings
        timing = Timing(s.ack_timeout, s.state_timeout, s.reset_timeout, s.reset_delay,
                        s.poll_interval)
        # Fail-fast buses (tcp_bridge.health, tcp_bridge.failfast): one guard per bus.
        self.guards: Dict[str, BusGuard] = {
            bus: BusGuard(BusHealth(bus, health_clock, probe_interval=s.probe_interval,
                                    on_change=log_change),
                          {a.node_id: nodes[a.addr] for a in table.axes.values()
                           if a.bus == bus and a.addr in nodes},
                          (link_probes or {}).get(bus))
            for bus in sorted({a.bus for a in table.axes.values() if a.addr in nodes})
        }
        self.axes: Dict[int, AxisOps] = {}
        for addr, axis in table.axes.items():
            node = nodes.get(addr)
            port = None
            if node is not None:
                port = SdoPort(node, name=f"axis {addr} ({axis.bus} node {axis.node_id})",
                               debug=lambda: self.debug,
                               observer=self.guards[axis.bus].observer(axis.node_id))
            self.axes[addr] = AxisOps(axis, self.params, port, timing, **cia402_options)
        self._workers: Dict[str, BusWorker] = {
            bus: BusWorker(bus, guard.maintain) for bus, guard in self.guards.items()}
        self.shared: Dict[str, SharedReads] = {
            bus: SharedReads(worker, window=share_window) for bus, worker in self._workers.items()}
        for backend in self.backends:  # e.g. PDO mappings restored after a boot-up
            attach = getattr(backend, "attach_worker", None)
            worker = self._workers.get(getattr(backend, "name", None))  # type: ignore[arg-type]
            if attach is not None and worker is not None:
                attach(worker.post)
            sent = getattr(backend, "attach_wait", None)
            if sent is not None and worker is not None:
                sent(worker.defer_results())

    # -- planning (event loop, no I/O) -------------------------------------------------

    def prepare(self, request: Request) -> Job:
        """Validate ``request`` completely and plan it; InvalidCommand (CAN) if it is not valid."""
        spec = resolve(request)
        if request.cmd in GLOBAL_COMMANDS:
            return self._prepare_global(request)
        ops = self.axes.get(request.axis)
        if ops is None:
            raise InvalidCommand(f"axis {request.axis} is not configured",
                                 axis=request.axis, kind=request.kind, cmd=request.cmd)
        try:
            if isinstance(request, ReadRequest):
                return self._prepare_read(request, spec, ops)
            return self._prepare_write(request, spec, ops)
        except InvalidCommand as exc:
            # Conversions know only the command: give the reply its full header.
            raise InvalidCommand(str(exc), axis=request.axis, kind=request.kind,
                                 cmd=request.cmd) from exc

    def _prepare_global(self, request: Request) -> Job:
        if isinstance(request, ReadRequest):
            value: Any = self.version if request.cmd == 99 else int(self.debug)
            reply = format_read_reply(request.axis, request.cmd, value)
            return Job(request, lambda: reply)
        self.debug = bool(parse_value(resolve(request), request.value))  # 91
        reply = format_write_reply(request.axis, request.cmd, Status.ACK)
        return Job(request, lambda: reply)

    def _bus(self, ops: AxisOps, spec: CommandSpec) -> Optional[str]:
        return ops.config.bus if ops.port is not None and ops.needs_bus(spec) else None

    def _prepare_read(self, request: ReadRequest, spec: CommandSpec, ops: AxisOps) -> Job:
        plan = ops.plan_read(spec)
        axis, cmd = request.axis, request.cmd
        bus = self._bus(ops, spec)
        return Job(request, lambda: format_read_reply(axis, cmd, plan()),
                   bus=bus, ops=ops, share=(axis, cmd) if bus is not None else None)

    def _prepare_write(self, request: Request, spec: CommandSpec, ops: AxisOps) -> Job:
        assert not isinstance(request, ReadRequest)
        value = parse_value(parameter_spec(spec.number) if spec.number == 19 else spec,
                            request.value)
        ack = format_write_reply(request.axis, request.cmd, Status.ACK)
        companions: Tuple[Job, ...] = ()
        stop: Optional[Job] = None
        how = int(value) if spec.number in (0, 90) else None
        if spec.number == 90:
            plan, companions = self._plan_combined_move(request, int(value))
        elif spec.number == 0:
            followers, companions = self._plan_slave_move(request, ops, int(value))
            plan = plan_move(ops, int(value), followers)
            stop = self._halt_job(request, ops, followers)
        else:
            plan = ops.plan_write(spec, value)

        def run() -> bytes:
            plan()
            return ack
        bus = self._bus(ops, spec)
        # A stop (00=8, 90=0) is never gated: every axis must be told.
        stopping = (spec.number, how) in ((0, 8), (90, 0))
        gated = bool(companions) and not stopping
        precheck = tuple(self._axis_job(request, c.ops, self._require_enabled(c.ops))
                         for c in companions if c.ops is not None) if gated else ()
        if stopping:
            companions = tuple(replace(c, urgent=True) for c in companions)
        return Job(request, run, bus=bus, ops=ops, companions=companions,
                   gated=gated, precheck=precheck, stop=stop,
                   urgent=stopping or spec.number == 16)

    def _plan_slave_move(self, request: Request, master: AxisOps,
                         how: int) -> Tuple[Tuple[Follower, ...], Tuple[Job, ...]]:
        """Spec 29/30: the slave follows the master's move, with its direction.

        Returns (followers moved in the master's own job, companion jobs): a slave
        on the master's bus is a follower, one on another bus a companion.
        """
        slave_addr = self.params.get(master.addr, 29) or 0
        slave = self.axes.get(slave_addr)
        if slave is None or slave is master or slave.port is None:
            return (), ()
        direction = -1 if self.params.get(master.addr, 30) == -1 else 1
        if slave.config.bus == master.config.bus:
            return (Follower(slave, direction),), ()
        target = None
        if how in (1, 2):
            target = self.params.user(master.addr, 2)
        elif how == 3:
            target = self.params.user(master.addr, 5)
        plan = plan_move(slave, how, target=target, direction=direction,
                         profile=stored_profile(master))
        return (), (self._companion(request, slave, plan),)

    def _plan_combined_move(self, request: Request, how: int) -> Tuple[Callable[[], None], Tuple[Job, ...]]:
        """Spec 90 with 3.2: 0 stop, 1 LINR (relative by each 02), 2 LINA to zero."""
        internal = [self.axes[a.addr] for a in self.table.internal_axes
                    if self.axes[a.addr].port is not None]
        if not internal:
            raise InvalidCommand("no internal axes with a drive are configured (spec 3.2)",
                                 axis=request.axis, kind=request.kind, cmd=request.cmd)
        jobs = []
        for ops in internal:
            if how == 0:
                plan = plan_move(ops, 8)
            elif how == 1:
                plan = plan_move(ops, 2)
            else:
                plan = plan_move(ops, 1, target=0.0)
            jobs.append(self._companion(request, ops, plan))
        return (lambda: None), tuple(jobs)

    def _axis_job(self, request: Request, ops: AxisOps, plan: Callable[[], Any]) -> Job:
        def run() -> bytes:
            plan()
            return b""
        return Job(request, run, bus=ops.config.bus, ops=ops)

    def _companion(self, request: Request, ops: AxisOps, plan: Callable[[], None]) -> Job:
        return replace(self._axis_job(request, ops, plan), stop=self._halt_job(request, ops))

    def _halt_job(self, request: Request, ops: AxisOps,
                  followers: Sequence[Follower] = ()) -> Optional[Job]:
        if ops.drive is None:
            return None
        return replace(self._axis_job(request, ops, plan_move(ops, 8, followers)), urgent=True)

    @staticmethod
    def _require_enabled(ops: AxisOps) -> Callable[[], Any]:
        assert ops.drive is not None
        return ops.drive.require_enabled

    # -- execution -----------------------------------------------------------------------

    async def probe(self) -> None:
        """At start-up: read each EPOS4 axis's units (60A9h, 3000h/05h) and log them.

        A velocity unit the bridge does not know, or a main sensor resolution other
        than the axis's ``increments_per_revolution``, is logged at once rather
        than found by the first velocity command; an absent drive is read later,
        when a command needs it. Nothing is written.
        """
        jobs = [self._workers[ops.config.bus].submit(
                    self.guards[ops.config.bus].guarded(ops.probe_units, ops.config.node_id))
                for ops in self.axes.values()
                if ops.port is not None and ops.config.bus in self._workers
                and ops.device is DeviceCode.C_DC_MAXON_EPOS4]
        for outcome in await asyncio.gather(*jobs, return_exceptions=True):
            if isinstance(outcome, BaseException):
                log.info("start-up probe: %s", outcome)

    async def execute(self, request: Request) -> bytes:
        """Prepare and run ``request``; returns the reply, raises on failure."""
        job = self.prepare(request)
        answer = self._at_once(job)  # no coroutine, no future: the status poll's path
        if answer is not BUSY:
            return answer  # type: ignore[no-any-return]
        return await self._queued(job, job if job.share is not None else None)

    def _at_once(self, job: Job) -> Any:
        """The reply of a job that waits for nothing, else BUSY: one without a drive, or
        a status poll answered from PDOs (shared_reads rule 5), the common case of many
        polling clients."""
        if job.share is None:
            self._close_shared(job)
        if job.bus is None and not job.companions:
            return job()
        fast = self._from_pdo(job)
        if fast is None or self._refusal(job) is not None:
            return BUSY
        return self.shared[job.bus].answer_now(fast)

    async def _queued(self, job: Job, tried: Optional[Job]) -> bytes:
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
            return done.value  # type: ignore[no-any-return]
        except asyncio.TimeoutError:
            # The safety net ran out before the move's own bounds did: the job
            # may still start its axes after the NAK. Halt every axis of the
            # request (queued behind it on each bus, not awaited: the request
            # already failed), so that a NAK never leaves an axis moving.
            for axis_job in (job, *job.companions):
                if axis_job.stop is not None:
                    self._submit(axis_job.stop).add_done_callback(_log_halt)
            raise

    @staticmethod
    def _from_pdo(job: Job) -> Optional[Callable[[], bytes]]:
        """A read of an axis fed by PDOs may be answered on the loop (shared_reads rule 5)."""
        port = job.ops.port if job.ops is not None and job.share is not None else None
        if port is None or getattr(port, "feed", None) is None:
            return None
        if job.ops is not None and getattr(job.ops.drive, "halt_owed", False):
            return None  # the job sends that halt first (Job.__call__), on the bus worker
        return lambda: port.pdo_only(job)  # type: ignore[union-attr]

    def _close_shared(self, job: Job) -> None:
        """Shared reads, rule 3: a read after this request does not join one before it."""
        for j in (job, *job.companions, *job.precheck):
            for bus in (j.bus, j.ops.config.bus if j.ops is not None else None):
                if bus in self.shared:
                    self.shared[bus].close_groups()

    def _submit(self, job: Job, *, fast: bool = True) -> "asyncio.Future[bytes]":
        future: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
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

    # Fail-fast buses (tcp_bridge.health): a job for a silent bus or node is refused
    # before it is queued, and again when its turn comes; stops and halts are tried.

    def _refusal(self, job: Job) -> Optional[Exception]:
        if job.bus is None or job.urgent:
            return None
        return self.guards[job.bus].refusal(_node_of(job))

    def _guarded(self, job: Job) -> Callable[[], bytes]:
        if job.bus is None:
            return job
        return self.guards[job.bus].guarded(job, _node_of(job), check=not job.urgent)

    def execute_sync(self, request: Request) -> bytes:
        """Run a request in the caller's thread (tests, tools); raises on failure."""
        plan = steps(self.prepare(request))
        try:
            batch = next(plan)
            while True:
                batch = plan.send([_outcome(self._guarded(j)) for j in batch])
        except StopIteration as done:
            return done.value  # type: ignore[no-any-return]

    def close(self, wait: bool = True) -> None:
        """Finish the transfers in flight (``wait``), write the state file, close the backends."""
        for worker in self._workers.values():
            worker.close(wait=wait)
        self.params.close()
        for backend in self.backends:
            try:
                backend.close()
            except Exception:  # closing one backend must not keep the others open
                log.exception("closing backend %r failed", backend)


def _result(future: "asyncio.Future[bytes]") -> Outcome:
    error = future.exception()
    return error if error is not None else future.result()


def _node_of(job: Job) -> Optional[int]:
    return job.ops.config.node_id if job.ops is not None else None


def _outcome(job: Callable[[], bytes]) -> Outcome:
    try:
        return job()
    except Exception as exc:
        return exc


def build_engine(table: AxisTable, *, params: Optional[ParameterStore] = None,
                 **options: Any) -> Engine:
    """Open every bus's backend (registry in :mod:`tcp_bridge.backends`) and an Engine."""
    from .backends import open_backend

    nodes: Dict[int, Any] = {}
    backends: List[Any] = []
    probes: Dict[str, Callable[[], Any]] = {}
    try:
        for name, bus in table.buses.items():
            axes: List[AxisConfig] = [a for a in table.axes.values() if a.bus == name and a.has_node]
            if not axes:
                continue
            try:
                backend = open_backend(bus, axes)
            except ConfigError:
                raise
            except (TypeError, ValueError) as exc:  # a bus option of the wrong type or value
                raise ConfigError(f"{table.source}: [bus.{name}]: {exc}") from None
            backends.append(backend)
            if callable(getattr(backend, "probe", None)):
                probes[name] = backend.probe
            for axis in axes:
                nodes[axis.addr] = backend.node(axis.node_id)
    except BaseException:
        for backend in backends:
            backend.close()
        raise
    return Engine(table, nodes, params=params, backends=backends, link_probes=probes, **options)
