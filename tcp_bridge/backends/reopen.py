"""A bus whose device could not be opened at start-up, opened again by the probes.

Why: a missing adapter, an EPOS4 that is powered off or a serial-to-TCP
converter that refuses the connection used to stop ``tcp-bridge serve`` (exit
2), so one unplugged bus kept the axes of every other bus offline too, although
the same outage *while running* is handled by the fail-fast probes
(:mod:`tcp_bridge.bus.health`). Now the bridge starts with the buses it can
open, and a bus that cannot be opened is an :class:`UnopenedBackend`:

* it is declared silent from the start (:class:`tcp_bridge.engine.Engine`'s
  ``unopened``), which logs it once with the reason; every command to its axes
  answers NAK at once, a stop is tried and answered NAK;
* each periodic probe of the bus's device (every ``probe_interval``, on the
  bus's worker thread) is :meth:`UnopenedBackend.probe`: it tries to open the
  backend; once that works, the backend's own probe (if any) must answer too,
  and the fail-fast machinery reopens the bus as for any outage ("answers
  again after N s silent");
* its nodes are :class:`LateNode` stand-ins, created at start-up for the
  engine: while the bus is not open, their SDO and NMT calls raise
  :class:`~tcp_bridge.errors.BusUnavailable` (a link failure: the device is
  silent, not the node); afterwards they are the real backend's nodes.

What only a misconfiguration causes (a bad key, an unknown backend, an EDS
that cannot be read) is a :class:`~tcp_bridge.tables.axes.ConfigError` and
still refuses to start; a backend raises :class:`BusUnavailable` only for the
device or adapter not being there now.

**Chosen:** a bus opened late has no PDO-fed status until the bridge restarts
(``pdo = true`` on a canopen bus: :class:`~tcp_bridge.bus.sdo.SdoPort` takes a
node's status feed when the engine is built); its status is read by SDO.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, List, Optional

from ..errors import BusUnavailable

log = logging.getLogger(__name__)


class UnopenedBackend:
    """Stands in for the backend of bus ``name`` until ``opener()`` succeeds."""

    def __init__(self, name: str, opener: Callable[[], Any], why: str) -> None:
        self.name = name
        self.why = self._own(why)  # the last reason the backend could not be opened
        self._opener = opener
        self.backend: Optional[Any] = None  # the real one, once open
        self._nodes: Dict[int, LateNode] = {}
        self._hooks: List[Callable[[Any], None]] = []  # attach_* calls, replayed on opening

    # -- the Backend interface ---------------------------------------------------------

    def node(self, node_id: int) -> "LateNode":
        node = self._nodes.get(node_id)
        if node is None:
            node = self._nodes[node_id] = LateNode(self, node_id)
        return node

    def attach_worker(self, post: Callable[[Callable[[], Any]], None]) -> None:
        self._attach("attach_worker", post)

    def attach_wait(self, hook: Callable[[], None]) -> None:
        self._attach("attach_wait", hook)

    def probe(self) -> None:
        """Open the backend if it is not open yet, then its own probe; raises while the
        device is not there (BusUnavailable, or the backend's probe's error)."""
        backend = self.backend
        if backend is None:
            backend = self._open()
        probe = getattr(backend, "probe", None)
        if callable(probe):
            probe()

    def describe_silence(self, why: str) -> str:
        """The log line's words (tcp_bridge.bus.failfast.log_change)."""
        describe = getattr(self.backend, "describe_silence", None)
        if callable(describe):
            return str(describe(why))
        return f"{why}; opened again in the background"

    def close(self) -> None:
        backend, self.backend = self.backend, None
        if backend is not None:
            backend.close()

    # -- opening -------------------------------------------------------------------------

    def _open(self) -> Any:
        try:
            backend = self._opener()
        except BusUnavailable as exc:
            self.why = self._own(str(exc))
            raise BusUnavailable(self.why) from None
        for hook in self._hooks:
            hook(backend)
        self.backend = backend  # a node that sees it sees a backend ready to use
        for node in self._nodes.values():
            node.nmt._real()  # heartbeat callbacks reach the real nodes before any traffic
        log.warning("bus %s: opened", self.name)
        return backend

    def _own(self, why: str) -> str:
        """``why`` without the "bus NAME: " a backend puts first (the log line says it)."""
        return why.removeprefix(f"bus {self.name}: ")

    def _attach(self, name: str, argument: Any) -> None:
        def hook(backend: Any) -> None:
            method = getattr(backend, name, None)
            if callable(method):
                method(argument)
        self._hooks.append(hook)

    def real_node(self, node_id: int) -> Any:
        """The real backend's node ``node_id``; BusUnavailable while it is not open."""
        backend = self.backend
        if backend is None:
            raise BusUnavailable(self.why)
        return backend.node(node_id)


class LateNode:
    """A node of an :class:`UnopenedBackend`: ``sdo`` reaches the real node once the bus
    is open, and raises :class:`BusUnavailable` before; ``nmt`` is a :class:`LateNmt`."""

    def __init__(self, owner: UnopenedBackend, node_id: int) -> None:
        self.id = node_id
        self._owner = owner
        self.nmt = LateNmt(self)

    @property
    def sdo(self) -> Any:
        return self.real().sdo

    @property
    def cyclic(self) -> Any:
        """The real node's set-point thread (internal axes in CSP), None until open."""
        backend = self._owner.backend
        return None if backend is None else getattr(backend.node(self.id), "cyclic", None)

    def real(self) -> Any:
        return self._owner.real_node(self.id)


class LateNmt:
    """canopen's ``NmtMaster`` of a :class:`LateNode`: ``state`` reaches the real node's;
    heartbeat callbacks (a boot-up seen by :mod:`tcp_bridge.plan.axis`) given before the
    bus opened are handed to the real node's NMT when it is first reached."""

    def __init__(self, node: LateNode) -> None:
        self._node = node
        self._callbacks: List[Callable[[int], None]] = []
        self._handed: Optional[Any] = None  # the real NMT that has the callbacks

    def add_heartbeat_callback(self, callback: Callable[[int], None]) -> None:
        self._callbacks.append(callback)
        if self._handed is not None:
            self._handed.add_heartbeat_callback(callback)

    def _real(self) -> Any:
        nmt = self._node.real().nmt
        if self._handed is not nmt:
            self._handed = nmt
            if hasattr(nmt, "add_heartbeat_callback"):
                for callback in self._callbacks:
                    nmt.add_heartbeat_callback(callback)
        return nmt

    @property
    def state(self) -> Any:
        return self._real().state

    @state.setter
    def state(self, value: Any) -> None:
        self._real().state = value


__all__ = ["LateNmt", "LateNode", "UnopenedBackend"]
