"""The cyclic sender: one thread per bus that streams CSP set-points (PSI spec 3.2).

An internal axis declared ``cyclic = "csp"`` (docs/bridge.md) runs in cyclic
synchronous position mode (CiA 402-2 mode 8): the drive follows its target
position 607Ah as it comes, so the bridge computes the profile
(:mod:`.profile`) and this thread sends a sample of it every ``cycle_ms``
through the bus's process data. The transport is an interface,
:class:`Setpoints`: the ``canopen`` backend implements it with RPDO3
remapped to 607Ah alone (:class:`CanopenSetpoints` says why no controlword);
the ``ethercat`` backend with its process data, its controlword likewise left
as the bridge's SDO writes set it, and with the cycle itself as this loop
(:mod:`tcp_bridge.backends.ethercat_csp`).

The rules (the safety rules of :mod:`tcp_bridge.motion` hold):

* **Motion only on a move command**: the thread sends only while a run is
  active, and a run starts only from a move (S90, S00=1/2, S00=3). Before it, on
  the bus worker (:func:`tcp_bridge.plan.cyclic_moves`), the drive gets mode
  8 with 607Ah equal to its actual position, so entering CSP moves nothing,
  and the run's first sample is that same position: no jump.
* **ACK only when the profile started**: :meth:`CyclicSender.start` returns
  once the thread has sent the run's first set-points and the transport took
  them; a run that could not be sent is a :class:`DeviceFailure` (NAK).
* **Stop and disable ramp down**: :meth:`CyclicSender.stop` replaces the
  run's profile by its stop ramp (:meth:`.profile.Line.stop_at`) at the
  next cycle, never a step. A transport error ends the run (logged); the
  drive then holds its last set-point.
* **A line is one motion** (issue 30 finding 2): every cycle, before the
  set-points go out, the sender looks at each drive of each run as its process
  data shows it now (:meth:`Setpoints.statuswords`: on CAN the statusword in
  TPDO3, which :class:`CanopenSetpoints` maps; on EtherCAT the statusword in
  the inputs of that cycle). When one drive of a run shows any state other
  than OPERATION ENABLED (its quick stop input, a fault such as 8611h
  following error, its 6007h reaction), or is lost (no fresh statusword, the
  slave out of OP), every other drive of the run ramps down on the line at 28
  from that cycle (:meth:`.profile.Line.stop_at`), exactly as S90=0 would; the
  drive that ended it gets no more set-points (it follows its own reaction,
  CiA 402-2 6.4.1: in QUICK STOP ACTIVE or FAULT the drive does not follow
  607Ah). The run records which node ended it and why (:attr:`Run.ended_by`,
  logged once, and its ``on_end`` callback: R86 of that axis becomes 0). The
  drive itself decides that it left the motion; the bridge only stops the rest
  of the line with it, so the tool stays on its straight line.
* **A lost cycle thread ends in the drive's own reaction**: on CAN that is
  the heartbeat consumer (issue 23): a bus with cyclic axes must have
  ``heartbeat_ms`` (ConfigError otherwise), so a bridge that dies stops
  sending set-points *and* heartbeats, and each drive quick-stops (6007h)
  from the last set-point it holds. On such a bus this thread sends the
  heartbeat itself (:meth:`CyclicSender.add_beat`), not python-can's periodic
  task: a set-point thread that stalls (blocked in a bus call) or ends stops
  the heartbeat too, so the drives react even while the process lives. A
  drive's own CSP watchdog (e.g. a sync or PDO timeout) is drive specific and
  not set up by the bridge. On EtherCAT it is each slave's SM watchdog instead
  (:mod:`tcp_bridge.backends.ethercat_csp`): no heartbeat there.

Velocity moves (S00=3) of such an axis run in cyclic synchronous velocity mode
(CSV, mode 9) by the same rules: the run is a :class:`.profile.VelocityRamp`
and each cycle sends its target velocity 60FFh (:meth:`Setpoints.write_velocities`;
on CAN RPDO4 remapped to 60FFh alone), again never the controlword. Before it
the drive gets 60FFh = its actual velocity, then mode 9, so entering CSV moves
nothing; the ramp starts from that velocity.

Timing: the thread keeps an absolute schedule (``next += cycle``); a cycle that
comes late samples the profile at the real time, so a late set-point is the
right one for its moment, and cycles missed are skipped, not sent in a burst.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import (Any, Callable, Dict, Iterable, List, Mapping, Optional, Protocol, Set, Tuple,
                    Union)

from epos_link.cia402 import State, state_from_statusword

from ..errors import DeviceFailure
from .profile import Line, VelocityRamp

log = logging.getLogger("tcp_bridge.motion")

CSP_MODE = 8  # CiA 402-2 6060h: cyclic synchronous position mode
CSV_MODE = 9  # cyclic synchronous velocity mode


class Setpoints(Protocol):
    """What the sender needs of a bus's process data (canopen RPDOs, EtherCAT PDOs)."""

    def prepare(self, node: int) -> None:
        """Before a node's first run (bus worker, SDO allowed): map its process data."""

    def write_targets(self, targets: Mapping[int, int]) -> None:
        """Send a target position (607Ah, increments) to each node; the cycle thread."""

    def read_actual(self, nodes: Iterable[int]) -> Dict[int, int]:
        """The actual position (6064h) of each node; bus worker only."""

    def prepare_velocity(self, node: int) -> None:
        """Before a node's first velocity run (CSV): map its target velocity 60FFh."""

    def write_velocities(self, velocities: Mapping[int, int]) -> None:
        """Send a target velocity (60FFh, the drive's velocity unit) to each node."""

    def statuswords(self, nodes: Iterable[int]) -> Mapping[int, Seen]:
        """Each node's statusword as its process data shows it now (the cycle thread):
        the statusword, None while none has come yet since :meth:`prepare` (no verdict),
        or a text saying why the node is lost (no statusword for too long, out of OP)."""


Seen = Union[int, str, None]  # Setpoints.statuswords: statusword, why lost, or not yet


@dataclass
class Run:
    """One profile being streamed to some nodes of the bus."""

    nodes: Tuple[int, ...]
    line: Union[Line, VelocityRamp]  # a position line (CSP) or a velocity ramp (CSV)
    started: threading.Event = field(default_factory=threading.Event)
    ended: threading.Event = field(default_factory=threading.Event)
    failure: Optional[str] = None
    # The node whose drive left the motion, and why (module doc, "a line is one motion").
    ended_by: Optional[Tuple[int, str]] = None
    # called once for each node that leaves the run (ended_by is the first of them)
    on_end: Optional[Callable[[int, str], None]] = None
    out: Set[int] = field(default_factory=set)  # nodes sent nothing more (they left)


class CyclicSender:
    """The set-point thread of one bus (module docstring)."""

    def __init__(self, bus: str, transport: Setpoints, cycle_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not 0.001 <= cycle_s <= 1.0:
            raise ValueError(f"cycle must be 1..1000 ms, not {cycle_s * 1e3:g} ms")
        self.bus = bus
        self.transport = transport
        self.cycle = cycle_s
        self.clock = clock
        self._lock = threading.Lock()
        self._runs: List[Run] = []
        self._last: Dict[int, Run] = {}  # each node's latest run (R82)
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._beats: List[List[Any]] = []  # [period, send, next due]: the bus's heartbeat

    def add_beat(self, period_s: float, send: Callable[[], None]) -> None:
        """Send ``send()`` every ``period_s`` from this thread (the bridge's heartbeat on a
        bus with cyclic axes): a stalled or dead set-point thread then stops the
        heartbeat too, and every drive reacts (6007h), not only when the process dies."""
        with self._lock:
            self._beats.append([period_s, send, self.clock()])
        self.begin()
        self._wake.set()

    def _beat(self) -> float:
        """Send the heartbeats that are due; seconds until the next one (inf: none)."""
        now = self.clock()
        with self._lock:
            beats = list(self._beats)
        soonest = float("inf")
        for beat in beats:
            period, send, due = beat
            if now >= due:
                try:
                    send()
                except Exception as exc:  # a bus error: the next cycle tries again
                    log.warning("bus %s: heartbeat not sent (%s)", self.bus, exc)
                beat[2] = due + period if due + period > now else now + period
            soonest = min(soonest, beat[2] - now)
        return soonest

    # -- the thread -------------------------------------------------------------------

    def begin(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name=f"cyclic-{self.bus}",
                                            daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Clean shutdown: the runs are stopped on their ramps first (bounded wait)."""
        self.finish_runs()
        self.kill()

    def finish_runs(self) -> None:
        """Every run ramps down on its line and ends (bounded wait); the thread, and
        the heartbeat it sends, go on until :meth:`kill`."""
        with self._lock:
            runs = list(self._runs)
        for run in runs:
            self.stop(run.nodes)
        for run in runs:
            run.ended.wait(min(10.0, max(0.0, run.line.end_time - self.clock()) + 1.0))

    def kill(self) -> None:
        """End the thread at once, nothing more sent (tests: a dead bridge)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5)

    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive() and not self._stop.is_set()

    def _loop(self) -> None:
        next_at = self.clock()
        while not self._stop.is_set():
            beat_in = self._beat()
            if not self._cycle():
                # Idle: nothing to send until a run starts, or the next heartbeat.
                self._wake.wait(min(1.0, max(0.0, beat_in)))
                self._wake.clear()
                next_at = self.clock()
                continue
            next_at += self.cycle
            now = self.clock()
            if next_at < now:  # late: skip the missed cycles, no burst
                next_at = now
            self._stop.wait(next_at - now)

    def _cycle(self) -> bool:
        """Send one sample of every active run; False when there is none."""
        now = self.clock()
        with self._lock:
            runs = list(self._runs)
        if not runs:
            return False
        self._watch(runs, now)
        targets: Dict[int, int] = {}
        velocities: Dict[int, int] = {}
        for run in runs:
            line = run.line
            if isinstance(line, VelocityRamp):
                for node, velocity in zip(run.nodes, line.velocities(now)):
                    if node not in run.out:
                        velocities[node] = round(velocity)
            else:
                for node, position in zip(run.nodes, line.positions(now)):
                    if node not in run.out:
                        targets[node] = round(position)
        try:
            if targets:
                self.transport.write_targets(targets)
            if velocities:
                self.transport.write_velocities(velocities)
        except Exception as exc:  # a bus error: the drives hold their last set-points
            log.error("bus %s: set-points not sent (%s); the cyclic moves of nodes %s end "
                      "here", self.bus, exc, sorted({**targets, **velocities}))
            with self._lock:
                for run in runs:
                    run.failure = str(exc) or type(exc).__name__
                    self._end(run)
            return True
        with self._lock:
            for run in runs:
                run.started.set()
                if run.line.finished(now) and run in self._runs:
                    self._end(run)  # its last sample was the target itself
        return True

    def _watch(self, runs: List[Run], now: float) -> None:
        """A line is one motion (module docstring): the drives of each run as their
        process data shows them now; a run whose drive left ramps down from ``now``."""
        nodes = {n for run in runs for n in run.nodes if n not in run.out}
        if not nodes:
            return
        seen = self.transport.statuswords(nodes)
        for run in runs:
            for node in run.nodes:
                if node in run.out:
                    continue
                why = _left(seen.get(node))
                if why is None:
                    continue
                with self._lock:
                    run.out.add(node)
                    first = run.ended_by is None
                    if first:
                        run.ended_by = (node, why)
                        if run in self._runs:
                            run.line = run.line.stop_at(now)
                # Every drive that leaves is named and recorded, not only the first: after a
                # stall or a cable pull all slaves of a line drop out together, and each
                # axis's R86 must say its move was not made (issue 31, build bullet 1).
                others = [n for n in run.nodes if n != node and n not in run.out]
                if first:
                    log.error("bus %s: node %d left the cyclic move (%s); %s", self.bus, node,
                              why, f"nodes {others} ramp down on its line" if others
                              else "its set-point ramps down")
                else:
                    log.error("bus %s: node %d left the cyclic move too (%s)", self.bus, node,
                              why)
                if run.on_end is not None:
                    try:
                        run.on_end(node, why)
                    except Exception:  # a bug in the callback must not stop the cycle
                        log.exception("bus %s: the end of a cyclic move was not recorded",
                                      self.bus)

    def _end(self, run: Run) -> None:
        if run in self._runs:
            self._runs.remove(run)
        run.started.set()
        run.ended.set()

    # -- the bus worker's side ----------------------------------------------------------

    def active(self, node: int) -> Optional[Run]:
        with self._lock:
            return next((r for r in self._runs if node in r.nodes), None)

    def last(self, node: int) -> Optional[Run]:
        """The node's latest run, active or ended (target reached, R82)."""
        with self._lock:
            return self._last.get(node)

    def start(self, nodes: Tuple[int, ...], line: Union[Line, VelocityRamp],
              timeout: float, on_end: Optional[Callable[[int, str], None]] = None) -> Run:
        """Stream ``line`` to ``nodes``; returns once its first set-points went out.
        ``on_end(node, why)``: called (on the cycle thread) if a drive leaves the run."""
        if not self.alive() and self._thread is not None:
            raise DeviceFailure(f"bus {self.bus}: the cyclic thread has ended")
        with self._lock:
            busy = sorted(n for r in self._runs for n in r.nodes if n in nodes)
            if busy:
                raise DeviceFailure(f"bus {self.bus}: nodes {busy} are still on a cyclic move; "
                                    "stop them first (S90=0 or S00=8)")
            run = Run(tuple(nodes), line, on_end=on_end)
            self._runs.append(run)
            for n in nodes:
                self._last[n] = run
        self.begin()
        self._wake.set()
        if not run.started.wait(timeout):
            self.stop(nodes)
            raise DeviceFailure(f"bus {self.bus}: the first set-points were not sent within "
                                f"{timeout:g} s; the move was stopped")
        if run.failure is not None:
            raise DeviceFailure(f"bus {self.bus}: the set-points were not sent: {run.failure}")
        if run.ended_by is not None:
            node, why = run.ended_by
            raise DeviceFailure(f"bus {self.bus}: node {node} left the move as it started "
                                f"({why}); the others ramp down")
        return run

    def stop(self, nodes: Iterable[int]) -> List[Run]:
        """Every active run of ``nodes`` ramps down on its line from now (never a step)."""
        wanted = set(nodes)
        now = self.clock()
        with self._lock:
            stopped = [r for r in self._runs if wanted & set(r.nodes)]
            for run in stopped:
                run.line = run.line.stop_at(now)
        return stopped


def _left(seen: Seen) -> Optional[str]:
    """Why a drive has left the motion (None: it has not, or nothing is known yet)."""
    if seen is None:
        return None
    if isinstance(seen, str):
        return f"lost: {seen}"
    state = state_from_statusword(seen)
    if state is State.OPERATION_ENABLED:
        return None
    name = state.name if state is not None else "no CiA 402 state"
    return f"{name}, statusword 0x{seen:04X}"


class CanopenSetpoints:
    """:class:`Setpoints` through canopen's PDO API: RPDO3 remapped to 607Ah alone.

    RPDO3 (COB-ID 400h + node-ID) maps controlword + 607Ah by default on an
    EPOS4. The bridge remaps it to the target position only, before a node's
    run (CiA 301 7.5.2.36 procedure, through canopen's ``save``), and puts the
    node in NMT Operational, where RPDOs count (CiA 301 7.3.2.2). No
    controlword in the stream, on purpose: "enable operation" repeated every
    cycle would undo a quick stop that another master, a limit or the drive
    itself started while the run went on (CiA 402-2 transition 16, QUICK STOP
    ACTIVE -> OPERATION ENABLED, with 605Ah = 5..8; maxon's EDS default is
    6), and CSP would then jump to the latest set-point. The drive was enabled
    by SDO before the run (S04=1); the stream only moves its target.
    Event-driven (type 255): each frame is acted upon at once; a SYNC-driven
    mapping is left to an EtherCAT-like transport with distributed clocks.

    The drives' states (:meth:`statuswords`, "a line is one motion"): TPDO3
    (COB-ID 380h + node-ID, CiA 301 Table 3-15 of the EPOS4 guide: 1802h) is
    mapped to the statusword 6041h alone, event-driven (type 255: sent when it
    changes, CiA 301 7.2.2.2.1) with an event timer of ``status_period`` (the
    bus's heartbeat period), so a live drive sends it at least that often. A
    drive whose statusword has not come for ``lost_after`` (twice the bus's
    heartbeat consumer time, :mod:`tcp_bridge.backends.canopen_bus`) is lost. TPDO1 and TPDO2 stay free for ``pdo = true``
    (:mod:`tcp_bridge.backends.pdo_status`).
    """

    RPDO = 3
    VELOCITY_RPDO = 4  # CSV: RPDO4 (controlword + 60FFh by default) remapped to 60FFh alone
    STATUS_TPDO = 3

    def __init__(self, network: Any, status_period: float = 0.05,
                 lost_after: float = 0.3, clock: Callable[[], float] = time.monotonic) -> None:
        self.network = network
        self.status_period = status_period
        self.lost_after = lost_after
        self.clock = clock
        self._vars: Dict[int, Tuple[Any, Any]] = {}  # node -> (pdo, target)
        self._velocity_vars: Dict[int, Tuple[Any, Any]] = {}  # node -> (pdo, 60FFh)
        # node -> (statusword, received at); node -> when its TPDO3 was (re)mapped.
        self._status: Dict[int, Tuple[int, float]] = {}
        self._watched: Dict[int, float] = {}

    def _remap(self, node: int, number: int, index: int) -> Tuple[Any, Any]:
        remote = self.network[node]
        pdo = remote.rpdo[number]
        pdo.read()
        pdo.clear()
        variable = pdo.add_variable(index)
        if variable is None:  # canopen logs and returns None
            raise DeviceFailure(f"node {node}: {index:04X}h is not in the object dictionary "
                                "(an EDS is needed for CSP/CSV)")
        pdo.trans_type = 255
        pdo.enabled = True
        pdo.save()
        remote.nmt.state = "OPERATIONAL"
        return pdo, variable

    def prepare(self, node: int) -> None:
        self._vars[node] = self._remap(node, self.RPDO, 0x607A)
        self._watch_status(node)

    def prepare_velocity(self, node: int) -> None:
        """RPDO4 to 60FFh alone: no controlword in the stream, for the reason above."""
        self._velocity_vars[node] = self._remap(node, self.VELOCITY_RPDO, 0x60FF)
        self._watch_status(node)

    def _watch_status(self, node: int) -> None:
        """TPDO3 = 6041h (class docstring); bus worker. Values from before count not."""
        remote = self.network[node]
        tpdo = remote.tpdo[self.STATUS_TPDO]
        tpdo.read()
        tpdo.clear()
        if tpdo.add_variable(0x6041) is None:  # canopen logs and returns None
            raise DeviceFailure(f"node {node}: 6041h is not in the object dictionary (an EDS "
                                "is needed for CSP/CSV)")
        tpdo.trans_type = 255
        tpdo.event_timer = max(1, round(self.status_period * 1e3))  # ms
        tpdo.inhibit_time = 0  # a change of state is wanted at once
        tpdo.enabled = True
        first = node not in self._watched
        self._watched[node] = self.clock()
        if first:
            def received(pdo: Any, node: int = node) -> None:  # the CAN notifier thread
                self._status[node] = (int(pdo[0x6041].raw), self.clock())
            tpdo.add_callback(received)
        tpdo.save()
        remote.nmt.state = "OPERATIONAL"

    def statuswords(self, nodes: Iterable[int]) -> Dict[int, Seen]:
        now = self.clock()
        out: Dict[int, Seen] = {}
        for node in nodes:
            since = self._watched.get(node)
            if since is None:
                out[node] = None  # not watched (never prepared): no verdict
                continue
            entry = self._status.get(node)
            last = entry[1] if entry is not None and entry[1] >= since else None
            if last is None:
                out[node] = (f"no statusword (TPDO3) for {now - since:.3f} s" if
                             now - since > self.lost_after else None)
            elif now - last > self.lost_after:
                out[node] = f"no statusword (TPDO3) for {now - last:.3f} s"
            else:
                assert entry is not None
                out[node] = entry[0]
        return out

    def write_targets(self, targets: Mapping[int, int]) -> None:
        for node, position in targets.items():
            pdo, target = self._vars[node]
            target.raw = position
            pdo.transmit()

    def write_velocities(self, velocities: Mapping[int, int]) -> None:
        for node, velocity in velocities.items():
            pdo, target = self._velocity_vars[node]
            target.raw = velocity
            pdo.transmit()

    def read_actual(self, nodes: Iterable[int]) -> Dict[int, int]:
        out: Dict[int, int] = {}
        for n in nodes:
            data = self.network[n].sdo.upload(0x6064, 0)  # INTEGER32, CiA 402-2 6.5
            out[n] = int.from_bytes(data[:4], "little", signed=True)
        return out

__all__ = ["CSP_MODE", "CSV_MODE", "CanopenSetpoints", "CyclicSender", "Run",
           "Setpoints"]
