"""Fail-fast buses: which links are silent, and when to probe them. Pure; the clock is injected.

Why: a device that does not answer costs every request its full wait (the
EPOS4 client's 0.5 s timeout, a late-answer wait, the retry: about 2 s), and
a bus worker runs one request at a time, so one silent device used to stall
every axis of its bus: a client polling 8 axes waited 16 s per cycle.

Two kinds of silence, told apart by who failed to answer
(:func:`tcp_bridge.bus.sdo.silence_of` classifies the exceptions):

* :attr:`Silence.LINK`, **the bus's device**: the EPOS4 on USB/RS232 (``epos``
  and ``sim`` backends: ``EposTimeoutError``, ``TransportError``) or the CAN
  adapter (``canopen`` backend: python-can ``CanError``, ``OSError``) gives no
  answer at all. Every node of the bus is behind it: the whole bus is silent.
* :attr:`Silence.NODE`, **one node**: the EPOS4's gateway answered for it with
  SDO abort 0x05040000 "SDO protocol timed out" (CiA 301 7.2.4.3.17; EPOS4
  Communication Guide, gateway chapter 5), or no CAN node answered the SDO
  (canopen). The link works; an absent node behind a healthy gateway is this,
  never a silent bus, and it does not close the bus to the other nodes.

A garbled answer is neither: the device answered through noise, and the
transfer is tried again (:func:`tcp_bridge.bus.sdo.retry_garbled`); only a
transfer whose every try was garbled reaches this module, as the device's silence.

Each link (the bus's device, each node) is ANSWERING, SUSPECT or SILENT:

* ANSWERING -> SUSPECT when a transfer ended in its silence (the client
  already retried). Nothing is refused yet: one lost exchange is not an outage.
* SUSPECT -> SILENT or ANSWERING right after the job that saw the silence, on
  the worker thread, before the job's reply goes out: one probe (below)
  decides. So the request that found the silence pays its wait and one probe;
  a loss that has already passed (the probe is answered) closes nothing, and
  there is no window in which the next request races the probe.
* SILENT (a :class:`Change`, logged at WARNING): :meth:`BusHealth.refusal` gives the reason to
  answer NAK at once, without a transfer: for every node of a silent bus, for
  a silent node alone. A request queued on the bus worker before the
  declaration is refused when its turn comes, so nothing queued during the
  outage reaches the device later.
* SILENT -> ANSWERING when anything answers: a periodic probe, or a stop
  (stops are always tried, :mod:`tcp_bridge.engine`). Logged at WARNING with
  the outage's length. Requests refused during the outage are never replayed:
  they were answered NAK, and a client that still wants them sends them again.

Periodic probes (run by the bus worker, :mod:`tcp_bridge.bus.workers`, between
jobs and while idle): a silent bus's device is probed every
``probe_interval`` (default 0.25 s), as nothing else uses its bus meanwhile;
a silent node costs the other nodes of its bus one gateway timeout per probe,
so its probes back off, doubling from ``probe_interval`` up to
``max_node_interval`` (5 s).

A silence is never evidence of a power cycle (:mod:`tcp_bridge.motion` rule
3): this module changes nothing in the axes' CiA 402 state; the first
statusword read after the outage decides.

Threads: every record and probe happens on the bus's worker thread (one
writer); the event loop only calls :meth:`BusHealth.refusal`, which reads
attributes each replaced whole.

One node's view (:class:`NodeHealth`) is what its axis holds
(``AxisRuntime.health``) and what its :class:`~tcp_bridge.bus.sdo.SdoPort` tells
the outcome of each transfer: the health of an axis is reachable from the axis.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable, Dict, List, Optional

DEFAULT_PROBE_INTERVAL = 0.25
MAX_NODE_INTERVAL = 5.0
Target = Optional[int]  # None: the bus's device; an int: a node id


class Silence(Enum):
    """Who did not answer (see the module docstring)."""

    LINK = "the bus's device"
    NODE = "the node"


@dataclass(frozen=True)
class Change:
    """A link was declared silent (``silent``), or answers again after ``duration`` s.

    Given to the ``on_change`` callback of :class:`BusHealth`, which logs it
    (:mod:`tcp_bridge.bus.failfast`): this module does no I/O, logging included.
    """

    link: str
    silent: bool
    why: str = ""
    duration: float = 0.0
    device: bool = False  # the bus's device (not a node): the whole bus


@dataclass
class _Link:
    name: str
    suspect: bool = False  # a transfer got no answer; the next settle() probes it
    silent_since: Optional[float] = None
    why: str = ""
    next_probe: float = 0.0
    failed_probes: int = 0


class BusHealth:
    """The links of one bus: its device and each node on it."""

    def __init__(self, bus: str, clock: Callable[[], float], *,
                 probe_interval: float = DEFAULT_PROBE_INTERVAL,
                 max_node_interval: float = MAX_NODE_INTERVAL,
                 on_change: Callable[[Change], None] = lambda change: None) -> None:
        self.bus = bus
        self.clock = clock
        self.on_change = on_change
        self.probe_interval = probe_interval
        self.max_node_interval = max(max_node_interval, probe_interval)
        self._device = _Link(f"bus {bus}: device")
        self._nodes: Dict[int, _Link] = {}

    def _link(self, target: Target) -> _Link:
        if target is None:
            return self._device
        link = self._nodes.get(target)
        if link is None:
            link = self._nodes[target] = _Link(f"bus {self.bus}: node {target}")
        return link

    # -- queries (any thread) ------------------------------------------------------------

    @property
    def silent(self) -> bool:
        """True while the bus's device is declared silent."""
        return self._device.silent_since is not None

    def node_silent(self, node_id: int) -> bool:
        link = self._nodes.get(node_id)
        return link is not None and link.silent_since is not None

    def refusal(self, node_id: Optional[int]) -> Optional[str]:
        """Why a request for ``node_id`` (None: the bus only) is answered NAK at once, or None."""
        for link in (self._device, self._nodes.get(node_id) if node_id is not None else None):
            if link is None:
                continue
            since, why = link.silent_since, link.why
            if since is not None:
                return (f"{link.name} silent for {max(self.clock() - since, 0.0):.1f} s "
                        f"({why}); answered at once, a probe reopens it")
        return None

    # -- records and probes (the bus worker's thread) ---------------------------------------

    def record(self, node_id: Optional[int], silence: Optional[Silence], why: str = "") -> None:
        """The outcome of a transfer to ``node_id``: None if the node answered."""
        if silence is Silence.LINK:
            self._suspect(self._device, why)
            return
        self._answered(self._device)  # an answer, or the gateway's word for a node
        if node_id is None:
            return
        if silence is Silence.NODE:
            self._suspect(self._link(node_id), why)
        elif node_id in self._nodes:
            self._answered(self._nodes[node_id])

    def suspects(self) -> List[Target]:
        """Links to probe now, before the reply of the job that found them silent."""
        if self._device.suspect:
            return [None]
        if self.silent:
            return []  # behind a silent device every node is silent: nothing to learn
        return [n for n, link in self._nodes.items() if link.suspect]

    def due(self) -> List[Target]:
        """Silent links whose periodic probe is due now, the bus's device first."""
        now = self.clock()
        if self.silent:
            return [None] if now >= self._device.next_probe else []
        return [n for n, link in self._nodes.items()
                if link.silent_since is not None and now >= link.next_probe]

    def next_due(self) -> Optional[float]:
        """Seconds until the next periodic probe (0: one is due), None if nothing is silent."""
        if self.silent:
            links = [self._device]
        else:
            links = [link for link in self._nodes.values() if link.silent_since is not None]
        if not links:
            return None
        return max(min(link.next_probe for link in links) - self.clock(), 0.0)

    def probed(self, target: Target, silence: Optional[Silence], why: str = "") -> None:
        """The outcome of a probe of ``target`` (a suspect's or a periodic one)."""
        if silence is Silence.LINK:
            self._declare(self._device, why)
            if target is None:
                self._failed(self._device, why, self.probe_interval)
            return
        self._answered(self._device)  # the node's silence is the gateway's answer
        if target is None:
            return
        link = self._link(target)
        if silence is None:
            self._answered(link)
            return
        was_silent = link.silent_since is not None
        self._declare(link, why)
        interval = self.probe_interval
        if was_silent:
            interval = min(self.probe_interval * 2 ** (link.failed_probes + 1),
                           self.max_node_interval)
        self._failed(link, why, interval)

    # -- transitions ------------------------------------------------------------------------

    def _suspect(self, link: _Link, why: str) -> None:
        if link.silent_since is None:
            link.suspect = True
            link.why = why

    def _declare(self, link: _Link, why: str) -> None:
        link.suspect = False
        if link.silent_since is not None:
            return
        now = self.clock()
        link.why, link.failed_probes, link.next_probe = why, -1, now
        link.silent_since = now  # last: a reader that sees it sees the rest
        self.on_change(Change(link.name, True, why, device=link is self._device))

    def _failed(self, link: _Link, why: str, interval: float) -> None:
        link.failed_probes += 1
        link.why = why or link.why
        link.next_probe = self.clock() + interval

    def _answered(self, link: _Link) -> None:
        link.suspect = False
        since = link.silent_since
        if since is None:
            return
        link.silent_since = None
        self.on_change(Change(link.name, False, duration=max(self.clock() - since, 0.0),
                              device=link is self._device))


class NodeHealth:
    """One node of a bus: its transfers' outcomes, and whether it is refused now."""

    __slots__ = ("bus", "node_id")

    def __init__(self, bus: BusHealth, node_id: int) -> None:
        self.bus = bus
        self.node_id = node_id

    def record(self, silence: Optional[Silence], why: str = "") -> None:
        """The outcome of a transfer to this node (:meth:`BusHealth.record`)."""
        self.bus.record(self.node_id, silence, why)

    def refusal(self) -> Optional[str]:
        """Why a request for this node is answered NAK at once now, or None."""
        return self.bus.refusal(self.node_id)

    @property
    def silent(self) -> bool:
        """The bus's device or this node is declared silent."""
        return self.bus.silent or self.bus.node_silent(self.node_id)
