"""PDO-fed status on the ``canopen`` backend: which TPDOs, how they are set, when a value counts.

With ``pdo = true`` on a canopen bus (issue 14) the bridge maps two transmit
PDOs on each drive, by SDO, through canopen's own PDO API
(``node.tpdo[n].read()``, ``add_variable``, ``save()``), then starts the node
(NMT Start Remote Node: a drive sends PDOs only in Operational, guide 3.3.3.5
Table 3-13; so statusword bit 9 "remote" reads 1 from then on):

=====  =================================================  ====
TPDO   objects                                            bits
=====  =================================================  ====
1      6041h statusword, 6061h modes of operation          56
       display, 6064h position actual value
2      606Ch velocity actual value, 60FDh digital inputs   64
=====  =================================================  ====

One CAN frame carries 64 bits, so the three values of the issue (statusword,
position, velocity: 80 bits) need two PDOs; 6061h (R82 in profile velocity
mode) and 60FDh (R83) ride along. The statusword and the position share a
frame on purpose: a client that polls R82 until the move is done and then
reads R12 gets the position of the same sample (or a later one), never one
from before the end of the move. Both PDOs are event-driven (transmission type
255: sent when a mapped value changes, CiA 301 7.2.2.2.1) with an event timer
of ``pdo_event_timer`` (default 50 ms), so a live drive sends at least that
often, and an inhibit time of ``pdo_inhibit_time`` (default 10 ms): the
position changes all the time while an axis moves (and by an increment of
encoder noise at rest), and the inhibit time bounds the bus load to two frames
per axis per 10 ms (20 moving axes: 4,000 frames/s, about 500 kbit/s with
stuffing; raise it on a slow or crowded bus). A change is reported at most
one inhibit time late.

When a value counts (:meth:`StatusFeed.value`): R10, R12, R14, R82, R83, R84
are answered from the newest PDO if

1. it is younger than ``pdo_max_age`` (default 100 ms, more than the event
   timer: a drive that stopped sending, was power cycled or left Operational
   falls back to SDO within that bound), and
2. it was received after the end of the node's last SDO write, and of its
   last SDO read of the same object. A drive answers an SDO only after it
   executed it, and a PDO it sends later shows that; so a PDO value never
   shows the drive from before a write of the bridge (an enable, a move), and a
   poll never returns a value older than one already read by SDO.

Why not "received after the request arrived" as for shared reads: that means
waiting for the next PDO, up to the event timer, for every poll. A PDO is sent
on every change, so the newest one *is* the drive's value at the request,
except for a change in flight (one CAN frame, plus at most one inhibit time:
10 ms by default): the staleness is bounded and documented, and the bus is
not touched. Everything that changes state (moves, enables, S04, S16, S17) still
reads the statusword by SDO (:mod:`tcp_bridge.motion`) and waits for the
drive's own acknowledgement, exactly as without PDOs.

A statusword taken from a PDO goes to the same watcher as one read by SDO
(:meth:`tcp_bridge.bus.sdo.SdoPort.read_status`: :class:`tcp_bridge.motion.Cia402`
sees every statusword a poll returns). That happens on the bus worker's thread,
or on the event loop while the worker has nothing queued or running
(:mod:`tcp_bridge.bus.shared_reads` rule 5), so never on two threads at once.

A drive that refuses the mapping (an SDO abort) stays on SDO, with one log
line. After a boot-up message (power cycle, NMT reset) the drive's mapping is
back at its saved values: the cache is dropped at once and the mapping is set
again on the bus worker (:meth:`PdoStatus.attach_worker`), never from the CAN
notifier's thread, whose SDO answers it would itself have to deliver.
"""
from __future__ import annotations

import logging
import time
from functools import partial
from dataclasses import dataclass
from typing import Any, Callable, Dict, Final, Optional, Tuple

from canopen.sdo import SdoAbortedError

log = logging.getLogger(__name__)

Key = Tuple[int, int]
# TPDO number -> the objects it carries, in order (the table in the module docstring).
TPDO_MAP: Final[Dict[int, Tuple[int, ...]]] = {1: (0x6041, 0x6061, 0x6064), 2: (0x606C, 0x60FD)}
FED: Final = frozenset((index, 0) for objects in TPDO_MAP.values() for index in objects)


@dataclass(frozen=True)
class PdoSettings:
    """The bus options of PDO-fed status (seconds); see the canopen backend's docstring."""

    max_age: float = 0.1
    event_timer: float = 0.05
    inhibit_time: float = 0.01

    def __post_init__(self) -> None:
        if not 0 < self.event_timer <= 0.05:
            raise ValueError("pdo_event_timer must be more than 0 and at most 0.05 s")
        if not self.max_age > self.event_timer:
            raise ValueError("pdo_max_age must be longer than pdo_event_timer")
        if not 0 <= self.inhibit_time < self.max_age:
            raise ValueError("pdo_inhibit_time must be 0 or more and shorter than pdo_max_age")


class StatusFeed:
    """The newest PDO values of one node, and whether they count (module docstring).

    Written by the CAN notifier thread (:meth:`on_pdo`) and the bus worker
    (:meth:`note_transfer`), read by the bus worker (:meth:`value`). Each entry
    is one tuple, replaced whole, so a reader never sees half an update.
    """

    def __init__(self, max_age: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_age = max_age
        self._clock = clock
        self.active = False  # the mapping is in place (set on the bus worker)
        self._values: Dict[Key, Tuple[int, float]] = {}
        self._written_at = float("-inf")  # end of the last SDO download
        self._read_at: Dict[Key, float] = {}  # end of the last SDO upload, by object
        self.used = 0  # values answered from PDOs (tests, bench)

    def on_pdo(self, values: Dict[Key, int]) -> None:
        now = self._clock()
        for key, value in values.items():
            self._values[key] = (value, now)

    def note_transfer(self, key: Optional[Key]) -> None:
        """An SDO transfer ended: an upload of ``key``, or a download (``key`` None)."""
        now = self._clock()
        if key is None:
            self._written_at = now
        elif key in FED:
            self._read_at[key] = now

    def value(self, index: int, subindex: int = 0) -> Optional[int]:
        """The PDO value of an object if it counts now, else None (read it by SDO)."""
        if not self.active:
            return None
        key = (index, subindex)
        entry = self._values.get(key)
        if entry is None:
            return None
        value, at = entry
        if self._clock() - at > self.max_age:
            return None  # rule 1: too old, the drive may have stopped sending
        if at <= self._written_at or at <= self._read_at.get(key, float("-inf")):
            return None  # rule 2: not after the last SDO of the bridge
        self.used += 1
        return value

    def invalidate(self) -> None:
        """The drive booted: its mapping is gone, and so is every value."""
        self.active = False
        self._values = {}


class PdoStatus:
    """PDO-fed status of every node of one canopen bus."""

    def __init__(self, bus: str, settings: PdoSettings) -> None:
        self.bus = bus
        self.settings = settings
        self.feeds: Dict[int, StatusFeed] = {}
        self._nodes: Dict[int, Any] = {}
        self._post: Optional[Callable[[Callable[[], Any]], None]] = None

    def add(self, node: Any) -> StatusFeed:
        """Feed ``node`` (a canopen RemoteNode) from its TPDOs once they are mapped."""
        feed = StatusFeed(self.settings.max_age)
        self.feeds[node.id] = feed
        self._nodes[node.id] = node
        for n, objects in TPDO_MAP.items():
            node.tpdo[n].add_callback(
                lambda pdo, objects=objects: feed.on_pdo(
                    {(index, 0): int(pdo[index].raw) for index in objects}))
        # CiA 301 7.2.8.3.2.4: a boot-up message is a heartbeat with state 0.
        node.nmt.add_heartbeat_callback(lambda state, nid=node.id: self._booted(nid)
                                        if state == 0 else None)
        return feed

    def attach_worker(self, post: Callable[[Callable[[], Any]], None]) -> None:
        """The bus worker is ready: map every node there, one job each."""
        self._post = post
        for node_id in self._nodes:
            post(partial(self.map, node_id))

    def _booted(self, node_id: int) -> None:
        # CAN notifier thread: drop the values now, map on the bus worker later.
        self.feeds[node_id].invalidate()
        if self._post is not None:
            self._post(lambda: self.map(node_id))

    def map(self, node_id: int) -> bool:
        """Map the TPDOs of one node and start it (bus worker); False if it stays on SDO."""
        node, feed = self._nodes[node_id], self.feeds[node_id]
        feed.invalidate()
        where = f"bus {self.bus} node {node_id}"
        try:
            for n, objects in TPDO_MAP.items():
                self._map_one(node.tpdo[n], n, objects)
            node.nmt.state = "OPERATIONAL"  # PDOs only in Operational (guide Table 3-13)
        except SdoAbortedError as exc:
            log.warning("%s: the drive refused the PDO mapping (%s); its status is read "
                        "by SDO", where, exc)
            return False
        except Exception as exc:  # silent node, CAN error: try again at its boot-up
            log.warning("%s: PDO mapping failed (%s); its status is read by SDO until its "
                        "next boot-up", where, exc)
            return False
        feed.active = True
        log.info("%s: status from TPDO1/TPDO2 (event timer %g ms)", where,
                 self.settings.event_timer * 1e3)
        return True

    def _map_one(self, tpdo: Any, n: int, objects: Tuple[int, ...]) -> None:
        tpdo.read()  # the drive's COB-ID and current settings, by SDO
        tpdo.clear()
        for index in objects:
            if tpdo.add_variable(index) is None:  # canopen logs and returns None
                raise LookupError(f"0x{index:04X} is not in the object dictionary")
        tpdo.trans_type = 255  # event-driven (CiA 301 7.5.2.37)
        tpdo.event_timer = round(self.settings.event_timer * 1e3)  # ms
        tpdo.inhibit_time = round(self.settings.inhibit_time * 1e4)  # 100 us units
        tpdo.enabled = True
        tpdo.save()


__all__ = ["FED", "PdoSettings", "PdoStatus", "StatusFeed", "TPDO_MAP"]
