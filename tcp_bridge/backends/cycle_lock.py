"""The lock of an EtherCAT master, with the process-data cycle first in line.

Every call into pysoem holds one lock (:mod:`tcp_bridge.backends.ethercat_cycle`,
rule 1). A plain ``threading.RLock`` is not fair: a thread that releases it and
asks again at once (a client's burst of CoE SDO transfers, each a bounded
exchange) usually gets it back before a thread already waiting. The cycle thread
then waits for the whole burst, not for one transfer: ``bench/ethercat.py``
measured a single 13-25 ms gap in a 2 ms cycle during 100 back-to-back SDO
uploads of 0.2 ms each, and a longer burst would outlast the slaves' SM
watchdog (100 ms by default) and drop them to SAFE-OP.

So the cycle takes the lock with :meth:`CycleLock.priority`, which first raises a
flag; every other holder (``with lock:``) waits while that flag is up, before it
queues for the lock itself. A transfer already holding the lock finishes (rule 1
bounds it); the next one waits until the cycle has run. Re-entry by the thread
that holds the lock never waits (a cycle hook that takes it again, nested calls),
and no one waits on the flag longer than ``wait_limit`` (a cycle thread that died
with its flag up must not stop the SDO path: the watchdogs handle the drives).
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator, Optional


class CycleLock:
    """A re-entrant lock whose :meth:`priority` holder is served before the others."""

    def __init__(self, wait_limit: float) -> None:
        self.wait_limit = wait_limit
        self._lock = threading.RLock()
        self._turn = threading.Condition(threading.Lock())
        self._priority_waiting = False
        self._owner: Optional[int] = None
        self._depth = 0

    @property
    def priority_waiting(self) -> bool:
        """The cycle is due and waits for the lock (for tests and diagnostics)."""
        return self._priority_waiting

    def __enter__(self) -> "CycleLock":
        me = threading.get_ident()
        if self._owner != me:  # only this thread sets _owner to its own ident
            with self._turn:
                self._turn.wait_for(lambda: not self._priority_waiting, self.wait_limit)
        self._acquire(me)
        return self

    def __exit__(self, *exc: object) -> None:
        self._depth -= 1
        if self._depth == 0:
            self._owner = None
        self._lock.release()

    @contextmanager
    def priority(self) -> Iterator["CycleLock"]:
        """Hold the lock as the cycle: ahead of every holder that is not yet inside."""
        me = threading.get_ident()
        nested = self._owner == me
        if not nested:
            with self._turn:
                self._priority_waiting = True
        try:
            self._acquire(me)
        finally:
            if not nested:
                with self._turn:
                    self._priority_waiting = False
                    self._turn.notify_all()
        try:
            yield self
        finally:
            self.__exit__()

    def _acquire(self, me: int) -> None:
        self._lock.acquire()
        self._owner = me
        self._depth += 1
