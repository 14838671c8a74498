"""Who may hold a connection slot of the status page, and how fast it is served (issue 35).

Pure bookkeeping for :mod:`.http` (no sockets, no clock of its own: the caller
passes the loop's time). The rules:

* A connection is in one phase at a time: ``HEAD`` (its request head is still
  coming), ``QUEUED`` (a complete request waiting for its turn, see below),
  ``ANSWER`` (being answered) or ``STREAM`` (an event stream).
* **No slot is held by a client that does not talk.** With every slot taken, a
  newcomer takes the slot of the connection that has been in ``HEAD`` the
  longest, once it has been there for :data:`HEAD_GRACE`: a browser sends its
  head at once, so only a slow or silent client is ever there for long (and each
  is closed by the head and idle timeouts in :mod:`.http` anyway). With nobody in
  ``HEAD`` that long, the newcomer is refused (and :mod:`.http` does not accept
  it until then). Without the grace, a page loaded at 600 requests/s evicted
  1,389 connections in 5 s whose heads had arrived but were not yet read ("after
  0.0 s"), each one a connection set up, logged and closed on the event loop the
  PSI ports share (``bench/status_page.py``).
* **No stream slot is held by a client that does not read.** With every stream
  slot taken, a new stream takes the slot of one that is stalled (bytes waiting
  that it has not taken), else of the oldest stream: EventSource reconnects by
  itself (the ``retry`` the stream announces), a client that stopped reading
  never does, so the dead ones go and the live ones come back.
* **Page traffic has a budget** (:class:`RateLimit`): complete requests are
  answered at most ``rate`` per second (a burst of ``burst``), the others wait
  in ``QUEUED``. The page shares the event loop with the PSI ports, so this is
  what keeps a page hammered with requests from slowing the PSI clients down
  (``bench/status_page.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from itertools import count
from typing import Any, Callable, Dict, Final, List, Optional

PAGE_RATE: Final = 50.0  # requests answered per second, at most
PAGE_BURST: Final = 25  # answered at once after a quiet spell
HEAD_GRACE: Final = 0.25  # s in HEAD before a newcomer may take the slot (a browser: ms)


class Phase(Enum):
    HEAD = "head"
    QUEUED = "queued"
    ANSWER = "answer"
    STREAM = "stream"


_order = count()


@dataclass(eq=False)
class Slot:
    """One connection: what it is doing since when, and its handle for the server."""

    handle: Any  # the server's (a task to cancel)
    now: float
    phase: Phase = Phase.HEAD
    since: float = 0.0
    evicted: bool = False
    order: int = field(default_factory=lambda: next(_order))

    def __post_init__(self) -> None:
        self.since = self.now

    def enter(self, phase: Phase, now: float) -> None:
        self.phase, self.since = phase, now


class Slots:
    """The connection and stream slots of one status page server."""

    def __init__(self) -> None:
        self._slots: Dict[int, Slot] = {}

    def __len__(self) -> int:
        return len(self._slots)

    def in_phase(self, phase: Phase) -> List[Slot]:
        return [s for s in self._slots.values() if s.phase is phase]

    def stale_heads(self, now: float, grace: float = HEAD_GRACE) -> List[Slot]:
        """The connections in ``HEAD`` for ``grace`` seconds or more at ``now``."""
        return [s for s in self.in_phase(Phase.HEAD) if now - s.since >= grace]

    def next_stale(self, now: float, grace: float = HEAD_GRACE) -> Optional[float]:
        """Seconds from ``now`` until one more connection in ``HEAD`` has been there for
        ``grace`` (always > 0); None if every one in ``HEAD`` has been already."""
        young = [s.since for s in self.in_phase(Phase.HEAD) if now - s.since < grace]
        return min(young) + grace - now if young else None

    def admit(self, slot: Slot, connections: int,
              grace: float = HEAD_GRACE) -> "tuple[bool, Optional[Slot]]":
        """Whether ``slot`` gets one of ``connections`` slots, and whose slot it takes
        (to be closed): one in ``HEAD`` for ``grace`` seconds at ``slot``'s arrival."""
        victim = None
        if len(self._slots) >= connections:
            heads = self.stale_heads(slot.now, grace)
            if not heads:
                return False, None
            victim = min(heads, key=lambda s: (s.since, s.order))
            self.remove(victim)
            victim.evicted = True
        self._slots[id(slot)] = slot
        return True, victim

    def stream(self, slot: Slot, now: float, streams_max: int,
               stalled: Callable[[Slot], bool]) -> Optional[Slot]:
        """``slot`` becomes one of ``streams_max`` streams; returns the stream whose slot it
        takes, if all are taken. ``stalled(s)`` tells whether a stream has bytes waiting
        unread."""
        victim = None
        streams = [s for s in self.in_phase(Phase.STREAM) if s is not slot]
        if len(streams) >= streams_max:
            dead = [s for s in streams if stalled(s)]
            victim = min(dead or streams, key=lambda s: (s.since, s.order))
            self.remove(victim)
            victim.evicted = True
        slot.enter(Phase.STREAM, now)
        return victim

    def remove(self, slot: Slot) -> None:
        self._slots.pop(id(slot), None)


class RateLimit:
    """A token bucket: :meth:`take` says how long to wait for the next token."""

    def __init__(self, rate: float = PAGE_RATE, burst: int = PAGE_BURST) -> None:
        if not rate > 0 or burst < 1:
            raise ValueError("rate must be positive and burst at least 1")
        self.rate, self.burst = rate, burst
        self._tokens = float(burst)
        self._at: Optional[float] = None

    def take(self, now: float) -> float:
        """Take one token; 0 if it was there, else the seconds until it is (it is taken
        all the same: a later caller waits behind this one)."""
        if self._at is not None:
            self._tokens = min(float(self.burst), self._tokens + (now - self._at) * self.rate)
        self._at = now
        self._tokens -= 1.0
        return 0.0 if self._tokens >= 0 else -self._tokens / self.rate


__all__ = ["HEAD_GRACE", "PAGE_BURST", "PAGE_RATE", "Phase", "RateLimit", "Slot", "Slots"]
