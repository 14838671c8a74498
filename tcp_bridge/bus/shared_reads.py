"""Shared reads: identical reads waiting in a bus's queue are served by one transfer.

NICOS, EPICS and maintenance tools poll the same status of the same axis at the
same time (issue 14). On one bus those polls queue; when several identical
reads wait in the queue together, one transfer answers them all. The rules:

1. **No reply is older than its request.** A request joins only a *group* that
   has not started yet: a group is open while its job waits in the worker's
   queue and closes, under the lock, at the instant the worker starts it. A
   request that arrives after that starts a new group queued behind. So every
   reply comes from a transfer that started after its request arrived.
2. **Only reads are shared.** The key is the request's axis and command
   (``Engine`` plans the same read the same way for both). Writes, moves and
   every other job go to the worker as before, one job each, in order: they
   are never merged or reordered.
3. **A read after a write stays after it.** Any other job for a bus closes
   every open group of that bus (:meth:`SharedReads.close_groups`; the engine
   calls it for writes answered on the event loop too, e.g. a scale factor, since
   they change what the next read returns). A read that arrives after the write
   starts a new group, queued behind the write.
4. **Gathering, bounded.** If every client waits for its reply before it sends
   the next poll, a client whose reply just went out is not back before the bus
   starts the next transfer, so it waits for the one after that: with transfers
   back to back, each client is answered every *second* transfer at best. So
   when the previous transfer of the same read was shared by *n* requests, a
   group waits before it starts until *n* requests have joined it, for at most
   ``window`` seconds, and not at all once another job is queued behind it (a
   write never waits for the gathering of reads). A read polled by one client
   never waits. Measured in ``bench/bridge.py`` (8 clients polling R10 on one
   axis of the simulated EPOS4 at 115200 baud).

5. **Answered at once when the bus has nothing to do.** A read may come with a
   ``fast`` plan that answers without the bus (PDO-fed status,
   :mod:`tcp_bridge.backends.pdo_status`). It runs on the event loop only when
   the worker is idle, nothing queued or running, so it overtakes nothing and
   no thread touches the same drive meanwhile; when it raises
   :class:`NeedsBus` (a value is not fresh from a PDO) the read is queued as
   usual.

The tables are bounded: open groups by the keys (configured axes x read
commands), and so is the size of each key's last group.
"""
from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Dict, Final, Hashable, List, Optional, Protocol

from ..errors import NeedsBus

SHARE_WINDOW: Final = 0.002  # seconds a group may wait for the requests it expects (rule 4)


BUSY: Final = object()  # SharedReads.answer_now(): not answered, submit the read


class Worker(Protocol):
    """What :class:`SharedReads` needs of a :class:`tcp_bridge.bus.workers.BusWorker`."""

    def submit(self, job: Callable[[], Any]) -> "asyncio.Future[Any]": ...

    def queued(self) -> int: ...

    def idle(self) -> bool: ...

    def flush(self) -> None: ...


@dataclass
class _Group:
    key: Hashable
    expect: int  # how many requests shared the last transfer of this read
    waiters: List["asyncio.Future[Any]"] = field(default_factory=list)
    started: bool = False
    inner: Optional["asyncio.Future[Any]"] = None


class SharedReads:
    """One bus's worker, with identical queued reads served together (module docstring)."""

    def __init__(self, worker: Worker, *, window: float = SHARE_WINDOW,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not window >= 0:
            raise ValueError("the share window must not be negative")
        self.worker = worker
        self.window = window
        self._clock = clock
        self._cond = threading.Condition(threading.Lock())
        self._open: Dict[Hashable, _Group] = {}
        self._last_size: Dict[Hashable, int] = {}
        self.transfers = 0  # jobs started (shared groups count once): for tests and bench
        self.requests = 0  # jobs and requests submitted
        self.fast = 0  # reads answered on the event loop (rule 5)

    # -- the event loop side -----------------------------------------------------------

    def submit(self, job: Callable[[], Any], key: Optional[Hashable] = None, *,
               fast: Optional[Callable[[], Any]] = None) -> "asyncio.Future[Any]":
        """Queue ``job``; with ``key`` (a read), join an identical queued read if there is
        one; with ``fast`` too, answer at once if the bus is idle (rule 5)."""
        if key is not None and fast is not None:
            done: "asyncio.Future[Any]" = asyncio.get_running_loop().create_future()
            try:
                answer = self.answer_now(fast)
            except Exception as exc:
                done.set_exception(exc)
                return done
            if answer is not BUSY:
                done.set_result(answer)
                return done
        self.requests += 1
        if key is None:
            future = self.worker.submit(self._counted(job))
            self.close_groups()  # after the put: a gathering group sees it queued (rule 4)
            return future
        waiter: "asyncio.Future[Any]" = asyncio.get_running_loop().create_future()
        with self._cond:
            group = self._open.get(key)
            if group is not None:
                group.waiters.append(waiter)
                self._cond.notify_all()
                waiter.add_done_callback(partial(self._abandon, group))
                return waiter
            group = _Group(key, self._last_size.get(key, 1), [waiter])
            self._open[key] = group
        group.inner = self.worker.submit(lambda: self._run(group, job))
        group.inner.add_done_callback(lambda inner: _settle(group, inner))
        waiter.add_done_callback(lambda w: self._abandon(group, w))
        return waiter

    def answer_now(self, fast: Callable[[], Any]) -> Any:
        """Rule 5 alone: what ``fast`` answers if the bus is idle and it needs no
        transfer (or what it raises), else :data:`BUSY`: submit the read then."""
        if not self.worker.idle():
            return BUSY
        try:
            answer = fast()
        except NeedsBus:
            return BUSY
        except Exception:
            self._count_fast()
            raise
        self._count_fast()
        return answer

    def _count_fast(self) -> None:
        self.requests += 1
        self.fast += 1

    def close_groups(self) -> None:
        """Rule 3: reads submitted from now on do not join the groups queued so far."""
        with self._cond:
            self._open.clear()
            self._cond.notify_all()

    def _abandon(self, group: _Group, waiter: "asyncio.Future[Any]") -> None:
        # A waiter cancelled (its request timed out): if nobody waits any more and
        # the transfer has not started, it never runs (the worker's own rule).
        if not waiter.cancelled():
            return
        with self._cond:
            if group.started or not all(w.cancelled() for w in group.waiters):
                return
            if self._open.get(group.key) is group:
                del self._open[group.key]
        if group.inner is not None:
            group.inner.cancel()

    # -- the worker thread side ----------------------------------------------------------

    def _counted(self, job: Callable[[], Any]) -> Callable[[], Any]:
        def run() -> Any:
            self.transfers += 1
            return job()
        return run

    def _run(self, group: _Group, job: Callable[[], Any]) -> Any:
        with self._cond:
            if self.window > 0 and group.expect > 1:
                self.worker.flush()  # a reply held for this job's request goes out now
                deadline = self._clock() + self.window
                while len(group.waiters) < group.expect and not self.worker.queued() \
                        and self._open.get(group.key) is group:
                    left = deadline - self._clock()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            if self._open.get(group.key) is group:
                del self._open[group.key]
            group.started = True  # rule 1: from here on nobody joins
            self._last_size[group.key] = len(group.waiters)
            self.transfers += 1
        return job()


def _settle(group: _Group, inner: "asyncio.Future[Any]") -> None:
    """Hand the one outcome to every request of the group (event loop thread)."""
    for waiter in group.waiters:
        if waiter.done():
            continue
        if inner.cancelled():
            waiter.cancel()
        elif inner.exception() is not None:
            waiter.set_exception(inner.exception())  # type: ignore[arg-type]
        else:
            waiter.set_result(inner.result())


__all__ = ["BUSY", "NeedsBus", "SHARE_WINDOW", "SharedReads"]
