"""The pipeline of a request: parse (wire), resolve and plan (plan), run (bus), format.

::

    bytes --wire--> Request --plan.resolve--> Resolved --plan.planner--> Job
          --bus.scheduler--> value or exception --wire.replies--> 30 bytes

**Arrival order, as one MasterMACS.** :meth:`Engine.prepare` runs on the event
loop, one request at a time, in the order the server received them from every
connection. Each request is resolved completely against the state that all
earlier requests left (:class:`~tcp_bridge.plan.axis.AxisRuntime`, including
the values of writes not yet executed) and its values are fixed then: a later
S02, S22 or S29 from another port cannot change a move already accepted.
Writes and moves of one axis (and of the axes a move involves) run on their
bus's worker in that same order, every stage of a move included: its later
stages take their places on their buses when it arrives, and a stop supersedes
the moves in flight it follows (:mod:`tcp_bridge.bus.order`). A request resolved
against a write that then fails is not executed either (NAK;
:class:`~tcp_bridge.plan.tickets.Ticket`).
Reads may be shared or answered from PDOs, but never see a state older than
an earlier request's ACK.

**Durable before ACK** (issue 35). The ACK of a write that changed stored
state (the S-command values of :mod:`tcp_bridge.tables.parameters`) leaves
only once the state file holds the change (:meth:`Engine.execute` awaits
:meth:`~tcp_bridge.tables.parameters.ParameterStore.written`). The bus worker
stored the value and went on; only the reply waits, on the event loop, and
writes that arrive together share one fsync.

The reply is formatted after the outcome (:func:`format_outcome`); the server
turns an exception into CAN or NAK in its one place
(:func:`tcp_bridge.wire.format_error_reply`).
"""
from __future__ import annotations

import asyncio
import logging
import time
from functools import partial
from importlib import metadata
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence

from .bus.failfast import BusGuard, log_change
from .bus.health import BusHealth, Silence
from .bus.scheduler import Scheduler
from .bus.sdo import SdoPort, Switch
from .bus.shared_reads import BUSY, SHARE_WINDOW, SharedReads
from .bus.workers import BusWorker, maintaining
from .errors import BusUnavailable, InvalidCommand
from .motion import Timing
from .motion.together import Watch
from .plan.axis import AxisRuntime
from .plan.cyclic_moves import install_rest
from .plan.job import Job
from .plan.planner import plan, release, releasing
from .plan.resolve import Resolved, resolve
from .tables.axes import AxisConfig, AxisTable, ConfigError, DeviceCode
from .tables.parameters import ParameterStore
from .wire import (ReadRequest, Request, Status, WriteRequest, format_read_reply,
                   format_request, format_write_reply)

log = logging.getLogger(__name__)

SPEC_REVISION = "2.3"


# The backends whose buses stream set-points to internal axes in CSP (their nodes' cyclic).
STREAMING_BACKENDS = frozenset({"canopen", "ethercat"})


def _streams_once_open(table: AxisTable, bus: str, unopened: Optional[Mapping[str, str]]) -> bool:
    """A bus that could not be opened at start-up has no set-point thread yet; its CSP
    axes get it when the probes open it (backends.reopen). Only a backend that streams
    may wait for that: any other is still a table mistake at start-up. (A bridge started
    while the EtherCAT slaves did not answer yet exited 2 with 'cannot stream'.)"""
    config = table.buses.get(bus)
    return (bus in (unopened or {}) and config is not None
            and config.backend in STREAMING_BACKENDS)


def software_version() -> str:
    """Command 99: the spec revision served and the package version, e.g. "2.3-py0.1.0"."""
    try:
        version = metadata.version("epos-link")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        version = "0+unknown"
    return f"{SPEC_REVISION}-py{version}"


def format_outcome(request: Request, value: Any) -> bytes:
    """The ACK reply of a request that succeeded: a read's value, or a write's ACK."""
    if isinstance(request, ReadRequest):
        return format_read_reply(request.axis, request.cmd, value)
    return format_write_reply(request.axis, request.cmd, Status.ACK)


class Engine:
    """All axes, their parameters and their bus workers: the pipeline of a request."""

    def __init__(self, table: AxisTable, nodes: Mapping[int, Any], *,
                 params: Optional[ParameterStore] = None, backends: Sequence[Any] = (),
                 job_timeout: float = 60.0, share_window: float = SHARE_WINDOW,
                 link_probes: Optional[Mapping[str, Callable[[], Any]]] = None,
                 unopened: Optional[Mapping[str, str]] = None,
                 health_clock: Callable[[], float] = time.monotonic,
                 **cia402_options: Any) -> None:
        self.table = table
        self.params = params if params is not None else ParameterStore(table)
        self._debug = Switch(table.settings.debug)  # command 91: every port reads it
        self.version = software_version()
        self.backends = list(backends)
        s = table.settings
        timing = Timing(s.ack_timeout, s.state_timeout, s.reset_timeout, s.reset_delay,
                        s.poll_interval)
        # Fail-fast buses (tcp_bridge.bus.health, tcp_bridge.bus.failfast): one guard per bus.
        # A backend's describe_silence words its silent device in the log (URL, what to check).
        describers = {getattr(b, "name", None): getattr(b, "describe_silence", None)
                      for b in self.backends}
        self.guards: Dict[str, BusGuard] = {
            bus: BusGuard(BusHealth(bus, health_clock, probe_interval=s.probe_interval,
                                    on_change=partial(log_change, describe=describers.get(bus))),
                          {a.node_id: nodes[a.addr] for a in table.axes.values()
                           if a.bus == bus and a.addr in nodes},
                          (link_probes or {}).get(bus))
            for bus in sorted({a.bus for a in table.axes.values() if a.addr in nodes})
        }
        for bus, why in (unopened or {}).items():  # silent from the start (logged once), before the
            self.guards[bus].health.probed(None, Silence.LINK, why)  # workers probe it
        self.axes: Dict[int, AxisRuntime] = {}
        for addr, axis in table.axes.items():
            node = nodes.get(addr)
            port = None
            if node is not None:
                port = SdoPort(node, name=f"axis {addr} ({axis.bus} node {axis.node_id})",
                               debug=self._debug, health=self.guards[axis.bus].node(axis.node_id))
            self.axes[addr] = AxisRuntime(axis, self.params, port, timing, **cia402_options)
            if axis.cyclic is not None and port is not None and self.axes[addr].cyclic is None \
                    and not _streams_once_open(table, axis.bus, unopened):
                raise ConfigError(f"{table.source}: [[axis]] AxAddr {addr}: an internal axis "
                                  f"is moved in CSP, but bus {axis.bus} cannot stream set-points "
                                  "(a canopen or ethercat bus, or sim with link = \"can\", can); "
                                  "profile = \"drive\" keeps the drive's own profile modes")
            install_rest(self.axes[addr])  # a cyclic axis rests by its own profile
        # Between jobs each bus worker probes silent links and watches the drives of its
        # profile lines and master/slave moves (tcp_bridge.motion.together, issue 30).
        self._workers: Dict[str, BusWorker] = {
            bus: BusWorker(bus, maintaining(guard.maintain, Watch(
                [a.drive for a in self.axes.values()
                 if a.config.bus == bus and a.drive is not None]).maintain))
            for bus, guard in self.guards.items()}
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

        self.internal = [self.axes[a.addr] for a in table.internal_axes
                         if self.axes[a.addr].port is not None]
        self.scheduler = Scheduler(self.shared, self.guards, job_timeout)

    @property
    def debug(self) -> bool:
        """Command 91 "debug print": each transfer logged by its port."""
        return self._debug.on

    @debug.setter
    def debug(self, on: bool) -> None:
        self._debug.on = on

    @property
    def job_timeout(self) -> float:
        """The safety net of one request's jobs (seconds)."""
        return self.scheduler.job_timeout

    @job_timeout.setter
    def job_timeout(self, seconds: float) -> None:
        self.scheduler.job_timeout = seconds

    # -- the pipeline ------------------------------------------------------------------

    def prepare(self, request: Request) -> Job:
        """Resolve ``request`` against the state every earlier request left, and plan it;
        InvalidCommand (CAN) if it is not valid. Called in arrival order, on the loop."""
        resolved = resolve(request, self.axes)
        if resolved.axis is None:
            return self._global(resolved)
        try:
            return plan(resolved, self.axes, self.internal)
        except InvalidCommand as exc:
            # Conversions know only the command: give the reply its full header.
            raise resolved.invalid(str(exc)) from exc

    def _global(self, r: Resolved) -> Job:
        if r.reading:
            value: Any = self.version if r.spec.number == 99 else int(self.debug)
            return Job(r.request, lambda: value)

        def set_debug() -> None:  # 91
            self.debug = bool(r.value)
        return Job(r.request, set_debug)

    async def execute(self, request: Request) -> bytes:
        """Resolve, plan and run ``request``; returns the reply, raises on failure."""
        job = self.prepare(request)
        with releasing(job):
            value = self.scheduler.at_once(job)  # no coroutine: the status poll's path
            if value is BUSY:
                value = await self.scheduler.queued(job, job if job.share is not None else None)
        if isinstance(request, WriteRequest):
            await self._persisted(request, self.params.version)
        return format_outcome(request, value)

    async def execute_all(self, requests: Sequence[Request]) -> List[bytes]:
        """Several requests of one client action (a CA put, :mod:`tcp_bridge.epics`):
        all resolved back to back, so no other request falls between them in arrival
        order, then run in order. A failure ends the rest unrun (their writes are
        released as failed) and is raised."""
        jobs: List[Job] = []
        try:
            for request in requests:
                jobs.append(self.prepare(request))
        except BaseException as exc:
            for job in jobs:
                release(job, exc)
            raise
        replies: List[bytes] = []
        for n, (request, job) in enumerate(zip(requests, jobs)):
            try:
                with releasing(job):
                    value = self.scheduler.at_once(job)
                    if value is BUSY:
                        value = await self.scheduler.queued(
                            job, job if job.share is not None else None)
            except BaseException as exc:
                for later in jobs[n + 1:]:
                    release(later, exc)
                raise
            if isinstance(request, WriteRequest):
                await self._persisted(request, self.params.version)  # durable before ACK
            replies.append(format_outcome(request, value))
        return replies

    async def _persisted(self, request: Request, version: int) -> None:
        """Hold a write's ACK until the state file holds every change made so far
        (this request's among them); at once when nothing is waiting to be written."""
        if not await self.params.written(version, self.job_timeout):
            # The value is in effect (NAK would say it is not, spec 2.2.2); say plainly
            # that it may not survive a restart.
            log.error("%s: the state file write holding it has not ended after %g s; "
                      "answered ACK, but the value may be lost at a restart",
                      format_request(request).decode("ascii", "replace").strip(),
                      self.job_timeout)

    def execute_sync(self, request: Request) -> bytes:
        """Run a request in the caller's thread (tests, tools); raises on failure."""
        job = self.prepare(request)
        with releasing(job):
            value = self.scheduler.run_sync(job)
        if isinstance(request, WriteRequest):
            self.params.flush(self.job_timeout)  # durable before the ACK, as execute()
        return format_outcome(request, value)

    async def probe(self) -> None:
        """At start-up: read each EPOS4 axis's identity (1018h/1) and units (60A9h,
        3000h/05h), and log them.

        A velocity unit the bridge does not know, or a main sensor resolution other
        than the axis's ``increments_per_revolution``, is logged at once rather
        than found by the first velocity command; an absent drive is read later,
        when a command needs it. Nothing is written, except to a drive found enabled
        on a bus with ``heartbeat_ms``: its heartbeat consumer, queued first, before
        any request (:meth:`~tcp_bridge.motion.Cia402.supervise_if_enabled`, issue 30).
        """
        arms = [self._workers[axis.config.bus].submit(
                    self.guards[axis.config.bus].guarded(axis.drive.supervise_if_enabled,
                                                         axis.config.node_id))
                for axis in self.axes.values()
                if axis.drive is not None and axis.drive.supervision is not None
                and axis.config.bus in self._workers]
        jobs = arms + [self._workers[axis.config.bus].submit(
                    self.guards[axis.config.bus].guarded(axis.probe_units, axis.config.node_id))
                for axis in self.axes.values()
                if axis.port is not None and axis.config.bus in self._workers
                and axis.device is DeviceCode.C_DC_MAXON_EPOS4]
        for outcome in await asyncio.gather(*jobs, return_exceptions=True):
            if isinstance(outcome, BaseException):
                log.info("start-up probe: %s", outcome)

    def close(self, wait: bool = True) -> None:
        """Finish the transfers in flight (``wait``), write the state file, close the backends."""
        self.scheduler.close()
        for worker in self._workers.values():
            worker.close(wait=wait)
        self.params.close()
        for backend in self.backends:
            try:
                backend.close()
            except Exception:  # closing one backend must not keep the others open
                log.exception("closing backend %r failed", backend)



def build_engine(table: AxisTable, *, params: Optional[ParameterStore] = None,
                 **options: Any) -> Engine:
    """Open every bus's backend (registry in :mod:`tcp_bridge.backends`) and an Engine.

    A bus whose device cannot be opened now (BusUnavailable) does not stop the others:
    it starts silent and its probes open it (:mod:`tcp_bridge.backends.reopen`)."""

    from .backends.reopen import UnopenedBackend

    nodes: Dict[int, Any] = {}
    backends: List[Any] = []
    probes: Dict[str, Callable[[], Any]] = {}
    unopened: Dict[str, str] = {}
    try:
        for name, bus in table.buses.items():
            axes: List[AxisConfig] = [a for a in table.axes.values() if a.bus == name and a.has_node]
            if not axes:
                continue
            opener = partial(_open, table, name, bus, axes)
            try:
                backend = opener()
            except BusUnavailable as exc:
                # Not there now: served as a silent bus, opened by its probes (backends/reopen).
                backend = UnopenedBackend(name, opener, str(exc))
                unopened[name] = backend.why
            backends.append(backend)
            if callable(getattr(backend, "probe", None)):
                probes[name] = backend.probe
            for axis in axes:
                nodes[axis.addr] = backend.node(axis.node_id)
    except BaseException:
        for backend in backends:
            backend.close()
        raise
    try:
        return Engine(table, nodes, params=params, backends=backends, link_probes=probes,
                      unopened=unopened, **options)
    except BaseException:  # e.g. a cyclic axis on a bus that cannot stream set-points
        for backend in backends:
            backend.close()
        raise


def _open(table: AxisTable, name: str, bus: Any, axes: List[AxisConfig]) -> Any:
    """Open one bus's backend; a bus option of the wrong type or value is a ConfigError."""
    from .backends import open_backend

    try:
        return open_backend(bus, axes)
    except (ConfigError, BusUnavailable):
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{table.source}: [bus.{name}]: {exc}") from None
