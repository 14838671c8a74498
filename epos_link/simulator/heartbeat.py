"""Heartbeat producer (1017h) and consumer (1016h) of a simulated drive, and their timer.

Producer (CiA 301 V4.2 7.2.8.3.2.2, 7.5.2.20): 1017h is the period in ms,
0 = off (the EPOS4 default, maxon's EDS). Every period the drive sends COB-ID
700h + node id with one byte, its NMT state (7Fh pre-operational, 05h
operational, 04h stopped), in each of those states (guide Table 3-13: Stopped
keeps "Lifeguarding (Heartbeating)"). The first heartbeat goes out one period
after the boot-up message or after the write of 1017h (**chosen**: CiA 301
only says the producer starts "immediately"; a period later keeps the boot-up
message first). A late timer thread skips beats, it never sends a burst.

Consumer (CiA 301 7.2.8.3.2.2, 7.5.2.19): 1016h subs 1..2 (as maxon's EDS),
bits 16..23 node id, bits 0..15 time in ms; node id 0 or time 0: unused.
Two entries with the same node id and a time other than 0 abort the SDO
download with 06040043h. A consumer becomes active at the first heartbeat from
its node after it was configured or the drive was reset; a time without one
after that is a heartbeat event, reported once; the consumer is then inactive
again until the next heartbeat (CiA 301: "activated by the first reception").
A boot-up message (state 0) counts as a heartbeat (**chosen**). Times are those
of the caller's clock at the frame's arrival (``time.monotonic`` in the
simulator); what the drive does about a heartbeat event is
:mod:`epos_link.simulator.comm`'s job.

Pure but for :class:`HeartbeatTicker`, the one thread that drives the timers.
"""
from __future__ import annotations

import math
from functools import partial
import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, Final, Iterable, List, Optional, Tuple

import can
from canopen.sdo import SdoAbortedError

from .od import ObjectStore, Value

__all__ = ["ABORT_PARAMETER_INCOMPATIBLE", "CONSUMER", "HEARTBEAT_BASE", "PRODUCER",
           "HeartbeatTicker", "Heartbeats"]

CONSUMER: Final = 0x1016
PRODUCER: Final = 0x1017
HEARTBEAT_BASE: Final = 0x700
ABORT_PARAMETER_INCOMPATIBLE: Final = 0x06040043  # CiA 301 Table 22
IDLE_WAIT: Final = 0.5  # seconds the ticker sleeps at most (a bound only)


@dataclass
class _Consumer:
    period: float  # seconds
    last: Optional[float] = None  # the last heartbeat; None: not active


def _entry(value: int) -> Tuple[int, int]:
    """(node id, time in ms) of a 1016h entry."""
    return (value >> 16) & 0xFF, value & 0xFFFF


class Heartbeats:
    """One drive's producer and consumers; the caller serialises access (the drive's lock)."""

    def __init__(self, store: ObjectStore, clock: Callable[[], float],
                 on_change: Callable[[], None] = lambda: None) -> None:
        self.store = store
        self.clock = clock
        self.on_change = on_change  # the timer must look again (a new period or consumer)
        self._subs: List[int] = []
        self._consumers: Dict[int, _Consumer] = {}
        self._next_beat = math.inf
        if PRODUCER in store.od:
            store.add_write_hook(PRODUCER, 0, self._producer_written)
        if CONSUMER in store.od:
            self._subs = [s for s in getattr(store.od[CONSUMER], "subindices", {}) if s > 0]
            for sub in self._subs:
                store.add_write_hook(CONSUMER, sub, partial(self._consumer_written, sub))
        self.reset()

    def reset(self) -> None:
        """After a reset (the objects hold their saved values): consumers inactive, the
        producer's period starts again."""
        self._consumers = self._configured({}, forget=True)
        self._restart(self.store.get_int(PRODUCER) if PRODUCER in self.store.od else 0)

    @property
    def active(self) -> Dict[int, bool]:
        """Watched node id -> whether its consumer is active."""
        return {node: c.last is not None for node, c in self._consumers.items()}

    # -- SDO download rules --------------------------------------------------------------

    def _restart(self, ms: int) -> None:
        self._next_beat = self.clock() + ms / 1000 if ms else math.inf

    def _producer_written(self, value: Value) -> None:
        assert isinstance(value, int)
        self._restart(value)
        self.on_change()

    def _consumer_written(self, sub: int, value: Value) -> None:
        assert isinstance(value, int)
        node, ms = _entry(value)
        if node and ms:
            for other in self._subs:
                other_node, other_ms = _entry(self.store.get_int(CONSUMER, other))
                if other != sub and other_node == node and other_ms:
                    raise SdoAbortedError(ABORT_PARAMETER_INCOMPATIBLE)
        self._consumers = self._configured({sub: value}, forget=False)
        self.on_change()

    def _configured(self, written: Dict[int, int], *, forget: bool) -> Dict[int, _Consumer]:
        """The consumers 1016h configures (``written``: values not stored yet). An entry
        that did not change keeps its state unless ``forget``."""
        out: Dict[int, _Consumer] = {}
        for sub in self._subs:
            node, ms = _entry(written.get(sub, self.store.get_int(CONSUMER, sub)))
            if not node or not ms:
                continue
            old = self._consumers.get(node)
            keep = old is not None and not forget and old.period == ms / 1000
            out[node] = old if keep and old is not None else _Consumer(ms / 1000)
        return out

    # -- time ------------------------------------------------------------------------------

    def heard(self, node: int, now: float) -> bool:
        """A heartbeat (or boot-up) from ``node`` arrived at ``now``; True if that activated
        its consumer (the timer must look again)."""
        consumer = self._consumers.get(node)
        if consumer is None:
            return False
        activated = consumer.last is None
        consumer.last = now
        return activated

    def due(self, now: float) -> Tuple[bool, List[int], float]:
        """(send a heartbeat now, node ids whose heartbeat is lost, when to look again)."""
        beat = now >= self._next_beat
        if beat:
            period = self.store.get_int(PRODUCER) / 1000
            self._next_beat += period
            if self._next_beat <= now:  # late: skip ahead, never burst
                self._next_beat = now + period
        lost: List[int] = []
        next_at = self._next_beat
        for node, consumer in self._consumers.items():
            if consumer.last is None:
                continue
            expiry = consumer.last + consumer.period
            if now > expiry:
                consumer.last = None  # one event; active again at the next heartbeat
                lost.append(node)
            else:
                next_at = min(next_at, expiry)
        return beat, lost, next_at


class HeartbeatTicker:
    """One thread per simulator: sends the heartbeats that are due and finds lost ones, for
    every drive (``drive.heartbeat_tick(now) -> when to look again``), on ``clock``.

    It sleeps until the earliest time a drive asked for (at most IDLE_WAIT, so an
    injected clock is followed too), or until :meth:`wake`.
    """

    def __init__(self, drives: Callable[[], Iterable[object]],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._drives = drives
        self._clock = clock
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-heartbeat", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            now, next_at = self._clock(), math.inf
            for drive in self._drives():
                tick = getattr(drive, "heartbeat_tick", None)
                if tick is None:
                    continue
                try:
                    next_at = min(next_at, tick(now))
                except can.CanError:
                    return  # the bus is closed: the simulator is closing
            delay = min(max(next_at - self._clock(), 0.0), IDLE_WAIT)
            if self._wake.wait(delay):
                self._wake.clear()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5)
