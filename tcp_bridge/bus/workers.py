"""One thread per bus: runs its jobs one at a time, in order, off the event loop.

::

    event loop                          bus thread
    ----------                          ----------
    submit(job) -> future  --queue-->   job()             (blocking SDO transfers)
    await future           <--------    loop.call_soon_threadsafe(resolve future)

Why not ``loop.run_in_executor(ThreadPoolExecutor(max_workers=1), job)``: the
hand-off is most of the bridge's own cost per request (two thread wake-ups;
parsing, planning and formatting a reply take ~30 us), and the executor
adds a concurrent future chained to the asyncio one. Resolving the asyncio
future directly measured 10-25% more commands/s for one client in
``bench/bridge.py`` (instant backend, 2 CPUs). The semantics are the
executor's: a job whose future was cancelled before it started never runs;
:meth:`BusWorker.close` lets the job in flight finish and cancels the queued
ones.

Replies after the next request (:meth:`BusWorker.defer_results`): handing a
result to the event loop wakes the loop thread, which then holds Python's
interpreter lock while it writes the reply and reads the client's next request;
the bus thread, which needs the lock to send the next queued request, waits.
On a serial link that wait is dead time on the wire: R10 on the simulated
EPOS4 at 115200 baud, 8 clients, spent ~0.1 ms of every 2.5 ms transaction
there (``bench/bridge.py``). So when a bus's link can say "I am waiting now"
(:attr:`epos_link.client.EposClient.on_wait`: a request is on the wire, or a late
answer is awaited before the next request), a job's result waits while another
job is queued, and is handed over as soon as that job first waits on the link,
i.e. while the wire carries its request. At most one job's result waits, and
never beyond the end of the next job: a job that sends nothing, a skipped job
and an empty queue hand everything over at once.

Maintenance: a worker may be given ``maintenance``, a callable run on the
worker thread before each job and whenever the queue has been empty for as
long as it asked (it returns the seconds until it wants to run again, or None
for "nothing to do"; it runs at least every second anyway). The fail-fast
probes of a silent bus run there (:mod:`tcp_bridge.bus.failfast`): on the one
thread that talks to the bus, between jobs, never concurrently with one.
"""
from __future__ import annotations

import asyncio
import logging
import queue
import threading
from typing import Any, Callable, List, Optional, Tuple

log = logging.getLogger(__name__)

MAINTENANCE_RETRY = 1.0  # seconds: after a maintenance call that raised, run it again this late
MAX_IDLE_WAIT = 1.0  # seconds: maintenance runs at least this often

# (loop, future, job); a posted job (post()) has neither loop nor future.
_Item = Optional[Tuple[Optional[asyncio.AbstractEventLoop], Optional["asyncio.Future[Any]"],
                       Callable[[], Any]]]


def maintaining(*parts: Callable[[], Optional[float]]) -> Callable[[], Optional[float]]:
    """One ``maintenance`` of several (the fail-fast probes, the watch of the drives
    of a line): each runs; the soonest wait of theirs is the worker's."""
    def maintain() -> Optional[float]:
        waits = [w for w in (part() for part in parts) if w is not None]
        return min(waits) if waits else None
    return maintain


def _resolve(future: "asyncio.Future[Any]", result: Any, error: Optional[BaseException]) -> None:
    if future.done():
        return  # cancelled while the job ran (a timeout): nobody waits for it
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)


def _cancel(loop: asyncio.AbstractEventLoop, future: "asyncio.Future[Any]") -> None:
    try:
        loop.call_soon_threadsafe(future.cancel)
    except RuntimeError:
        pass  # the loop is closed: nobody waits for it


class BusWorker:
    """A daemon thread that runs submitted jobs in order; see the module docstring."""

    def __init__(self, name: str,
                 maintenance: Optional[Callable[[], Optional[float]]] = None) -> None:
        self.name = name
        self._maintenance = maintenance
        self._queue: "queue.SimpleQueue[_Item]" = queue.SimpleQueue()
        self._closed = False
        # idle(): jobs queued so far (loop thread; posts under a lock) against jobs done
        # (worker thread); each counter has one writer, so reading them needs no lock.
        self._submitted = 0
        self._posted = 0
        self._post_lock = threading.Lock()
        self._finished = 0
        # Results not yet handed to the event loop (see "Replies after the next
        # request"); worker thread only.
        self._defer = False
        self._pending: List[Tuple[asyncio.AbstractEventLoop, "asyncio.Future[Any]", Any,
                                  Optional[BaseException]]] = []
        self._thread = threading.Thread(target=self._run, name=f"bus-{name}", daemon=True)
        self._thread.start()

    def defer_results(self) -> Callable[[], None]:
        """From now on a result may wait for the next job's first request (module
        docstring). Returns the hook the link calls when it starts to wait."""
        self._defer = True
        return self.flush

    def flush(self) -> None:
        """Hand every finished job's result to its event loop. A no-op off the
        worker thread (the link may be used by another thread: execute_sync)."""
        if not self._pending or threading.current_thread() is not self._thread:
            return
        pending, self._pending = self._pending, []
        for loop, future, result, error in pending:
            try:
                loop.call_soon_threadsafe(_resolve, future, result, error)
            except RuntimeError:  # the loop is closed
                log.debug("bus %s: a result dropped, event loop closed", self.name)

    def submit(self, job: Callable[[], Any]) -> "asyncio.Future[Any]":
        """Queue ``job``; its result (or exception) resolves the returned future."""
        if self._closed:
            raise RuntimeError(f"bus {self.name}: worker is closed")
        loop = asyncio.get_running_loop()
        future: "asyncio.Future[Any]" = loop.create_future()
        self._submitted += 1
        self._queue.put((loop, future, job))
        return future

    def post(self, job: Callable[[], Any]) -> None:
        """Queue ``job`` with nobody waiting for it, from any thread (e.g. a CAN
        notifier's callback: work for the bus, such as restoring a PDO mapping
        after a boot-up). An exception is logged; after close() it is dropped."""
        if not self._closed:
            with self._post_lock:
                self._posted += 1
            self._queue.put((None, None, job))

    def idle(self) -> bool:
        """No job queued or running: nothing submitted so far can still touch the bus."""
        return self._submitted + self._posted == self._finished

    def queued(self) -> int:
        """How many jobs wait in the queue (approximate across threads; the job in
        flight is not counted). :mod:`tcp_bridge.bus.shared_reads` stops gathering on it."""
        return self._queue.qsize()

    def close(self, wait: bool = True) -> None:
        """Cancel the queued jobs, let the one in flight finish (joined if ``wait``)."""
        if self._closed:
            return
        self._closed = True
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not None and item[0] is not None and item[1] is not None:
                _cancel(item[0], item[1])
        self._queue.put(None)
        if wait:
            self._thread.join()

    def _maintain(self) -> Optional[float]:
        if self._maintenance is None:
            return None
        try:
            return self._maintenance()
        except Exception:  # a bug: never kill the bus thread
            log.exception("bus %s: maintenance failed", self.name)
            return MAINTENANCE_RETRY

    def _run(self) -> None:
        while True:
            if self._pending and self._queue.empty():
                self.flush()  # nothing comes to send them with
            wait = self._maintain()
            if self._maintenance is not None:
                # Bounded even with nothing to do: a job run outside this thread
                # (Engine.execute_sync) may have declared a link silent meanwhile.
                wait = MAX_IDLE_WAIT if wait is None else min(wait, MAX_IDLE_WAIT)
            try:
                item = self._queue.get(timeout=wait)
            except queue.Empty:
                continue  # time for maintenance
            if item is None:
                self.flush()
                return
            self._run_one(*item)

    def _run_one(self, loop: Optional[asyncio.AbstractEventLoop],
                 future: Optional["asyncio.Future[Any]"], job: Callable[[], Any]) -> None:
        """One job: posted (nobody waits for it) or submitted (its future is resolved).
        It counts as finished before its future is resolved, so the reply's next
        request already finds the worker idle."""
        if loop is None or future is None:
            try:
                job()
            except Exception:
                log.exception("bus %s: posted job %r failed", self.name, job)
            finally:
                self._finished += 1
                self.flush()
            return
        if future.cancelled():  # read across threads: at worst one job runs in vain
            self._finished += 1
            self.flush()
            return
        result: Any = None
        error: Optional[BaseException] = None
        try:
            result = job()
        except Exception as exc:
            error = exc
        self._finished += 1
        self._pending.append((loop, future, result, error))
        # Wait for the next job's first request only if there is a next job, and
        # only one result at a time (this job sent nothing: hand both over now).
        if not self._defer or len(self._pending) > 1 or self._queue.empty():
            self.flush()
