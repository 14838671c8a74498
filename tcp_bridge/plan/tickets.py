"""The :class:`Ticket` of a write that later requests were resolved against (issue 22).

A write resolved but not yet executed promises its value
(:meth:`tcp_bridge.plan.axis.AxisRuntime.promise`); requests resolved after it use
that value and hold its ticket. A job waits for the tickets it holds before it
touches a drive (:class:`tcp_bridge.plan.job.Job`): a write that failed makes
every request resolved against it fail too (:class:`DependencyFailed`, answered
NAK), so "NAK: not executed" holds for them as well. Its own module, so that the
per-axis state (:mod:`.axis`) and the handlers (:mod:`.writes`) need not import
the jobs that run them.
"""
from __future__ import annotations

import threading
from typing import Optional

from ..errors import DependencyFailed

TICKET_WAIT = 60.0  # seconds: a job waits this long at most for an earlier write on another bus


class Ticket:
    """One write not yet executed: later requests were resolved against its value."""

    __slots__ = ("what", "_done", "failure")

    def __init__(self, what: str) -> None:
        self.what = what
        self._done = threading.Event()
        self.failure: Optional[str] = None

    def settle(self, failure: Optional[BaseException]) -> None:
        if self._done.is_set():
            return  # the first outcome stands
        self.failure = None if failure is None else str(failure) or type(failure).__name__
        self._done.set()

    @property
    def settled(self) -> bool:
        return self._done.is_set()

    def check(self, timeout: float = TICKET_WAIT) -> None:
        """Wait until the write ended; :class:`DependencyFailed` if it did not happen."""
        if not self._done.wait(timeout):
            raise DependencyFailed(f"{self.what} has not ended after {timeout:g} s")
        if self.failure is not None:
            raise DependencyFailed(f"not executed: it was resolved against {self.what}, "
                                   f"which failed ({self.failure})")


__all__ = ["TICKET_WAIT", "Ticket"]
