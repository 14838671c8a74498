"""The status page's sampler: every axis read through the engine, as a client would.

"One request, one meaning": the page has no path of its own to the drives. Its
sampler builds ordinary read requests (:class:`~tcp_bridge.wire.ReadRequest`, never
an S command: it cannot move anything) and hands them to
:meth:`tcp_bridge.engine.Engine.execute`, the same call the TCP server makes. So
they take their place in arrival order, share transfers with identical client
polls (:mod:`tcp_bridge.bus.shared_reads`), are answered from PDOs where the bus
has them (:mod:`tcp_bridge.backends.pdo_status`), are refused at once on a silent
bus (:mod:`tcp_bridge.bus.failfast`), and read the values a client would read (the
reply's text, decoded as ``tcp-bridge send`` decodes it).

**Bounded bus load.** One sampler per bridge; one sample of all axes at a time,
axis after axis, request after request (never two of its requests in flight),
then a pause of ``period`` seconds (:data:`DEFAULT_PERIOD`, 0.5 s) *after* the
sample ends: a slow bus slows the sampler down, never the other way round. Per
axis with a drive, each sample reads:

=================  ==========================================  ===================
commands           SDO transfers at most (objects)              when
=================  ==========================================  ===================
R10, R12, R14      1 + 1 + 1 (6041h, 6064h, 606Ch)              every sample
R82                2 (6041h, and 6061h when bit 10 alone says   every sample
                   "target reached", tcp_bridge.plan.reads)
R86                0 (the bridge's own flag)                    every sample
R15, R11           1 + 5 (6061h; 603Fh, 60FDh, and 6064h,       every
                   607Dh/1, 607Dh/2 for a software limit        :data:`SLOW_EVERY`
                   error)                                       th sample (4th)
=================  ==========================================  ===================

So at most :data:`FAST_TRANSFERS` (5) transfers per axis per sample, plus
:data:`SLOW_TRANSFERS` (6) every 4th: at the default period at most
``(4 * 5 + 6) / (4 * 0.5 s)`` = **13 SDO transfers per second per axis**
(:func:`max_transfers_per_second`), usually 9.5 to 11.5 (R82 reads one object or
two, R11 two when no software limit is hit). Add one read of 60A9h (an EPOS4's
velocity unit) after a power cycle, which any client's R14 would cost too. With
PDO-fed status (``pdo = true``) R10, R12, R14 and R82 cost nothing while the PDOs
are fresh: R15 and R11 remain, usually 1.5 transfers per second, at most 3. A bus whose device is silent costs nothing (answered NAK at once). An
axis without a drive (an internal axis with node 0) reads only R86.

**Chosen** (no source speaks of a status page): the period, the slow set and the
one-minute history (:data:`HISTORY_SECONDS`); the sampler runs from the start of
``serve --http`` to its end, watched or not, so a page opened later has its minute.

A failed read is shown, not raised: its command's cell is empty for that sample,
the axis's state cell says what failed and why (:func:`tcp_bridge.status.rows.condition`),
and its ``last_error`` keeps the newest failure (time, command, reason) until that
command answers again (then it is cleared: a recovered axis shows no stale error).
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from typing import Any, Callable, Deque, Dict, Final, List, Optional, Set, Tuple

from ..errors import BridgeError
from ..tasks import cancel_and_wait
from ..wire import ReadRequest, decode_reply
from .rows import failure_kind, row

log = logging.getLogger(__name__)

FAST: Final[Tuple[int, ...]] = (10, 12, 14, 82, 86)
SLOW: Final[Tuple[int, ...]] = (15, 11)
FAST_TRANSFERS: Final = 5  # per axis and sample, at most (module docstring)
SLOW_TRANSFERS: Final = 6
DEFAULT_PERIOD: Final = 0.5  # seconds between the end of a sample and the next
SLOW_EVERY: Final = 4
HISTORY_SECONDS: Final = 60.0
CLOSE_TIMEOUT: Final = 5.0  # seconds close() waits for the sampling task to end
QUEUE_SIZE: Final = 4  # samples a slow stream client may be behind before it skips some


def max_transfers_per_second(period: float = DEFAULT_PERIOD, slow_every: int = SLOW_EVERY
                             ) -> float:
    """The bound of the module docstring, per axis (samples taking no time at all)."""
    return (slow_every * FAST_TRANSFERS + SLOW_TRANSFERS) / (slow_every * period)


class Sampler:
    """Samples every axis of ``engine`` each ``period`` seconds; keeps the last minute."""

    def __init__(self, engine: Any, *, period: float = DEFAULT_PERIOD,
                 slow_every: int = SLOW_EVERY, history_seconds: float = HISTORY_SECONDS,
                 clock: Callable[[], float] = time.time) -> None:
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be a positive number of seconds, not {period!r}")
        self.engine = engine
        self.period = period
        self.slow_every = max(1, int(slow_every))
        self.clock = clock
        self.seq = 0  # samples taken
        self.latest: Optional[Dict[str, Any]] = None
        self.history: Deque[Dict[str, Any]] = deque(
            maxlen=max(1, math.ceil(history_seconds / period)) + 1)
        self.addrs: List[int] = sorted(engine.axes)
        self._values: Dict[int, Dict[int, Optional[str]]] = {a: {} for a in self.addrs}
        self._last_error: Dict[int, Dict[str, Any]] = {}
        self._listeners: Set["asyncio.Queue[Dict[str, Any]]"] = set()
        self._task: Optional["asyncio.Task[None]"] = None
        self._closing = False

    # -- life ------------------------------------------------------------------------

    def start(self) -> "Sampler":
        self._task = asyncio.ensure_future(self._run())
        return self

    async def close(self) -> None:
        """Stop sampling (a read in flight is abandoned by this task, not by the bus)."""
        self._closing = True
        if self._task is not None:
            if await cancel_and_wait([self._task], CLOSE_TIMEOUT):
                log.warning("status sampler: still running %g s after it was cancelled",
                            CLOSE_TIMEOUT)
            self._task = None

    async def _run(self) -> None:
        while not self._closing:  # a cancellation may be swallowed (tcp_bridge.tasks)
            try:
                await self.sample()
            except asyncio.CancelledError:
                raise
            except Exception:  # a bug here must not end the page's sampling for good
                log.exception("status sampler: sample failed")
            await asyncio.sleep(self.period)

    # -- one sample ------------------------------------------------------------------

    async def sample(self) -> Dict[str, Any]:
        """Read every axis once; publish and return the sample (``/api/axes``'s body)."""
        slow = self.seq % self.slow_every == 0
        started = self.clock()
        rows = [await self._axis(addr, slow) for addr in self.addrs]
        self.seq += 1
        body = {"seq": self.seq, "t": started, "period": self.period, "axes": rows}
        self.latest = body
        self.history.append({"t": started, "position": [r["position"] for r in rows],
                             "velocity": [r["velocity"] for r in rows]})
        for queue in list(self._listeners):
            if queue.full():  # a slow reader skips the oldest sample, never blocks us
                queue.get_nowait()
            queue.put_nowait(body)
        return body

    async def _axis(self, addr: int, slow: bool) -> Dict[str, Any]:
        axis = self.engine.axes[addr]
        has_drive = axis.port is not None
        cmds = (FAST + SLOW if slow else FAST) if has_drive else (86,)
        values = self._values[addr]
        errors: Dict[int, BaseException] = {}
        for cmd in cmds:
            try:
                reply = decode_reply(await self.engine.execute(ReadRequest(addr, cmd)))
                values[cmd] = reply.value
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                if not isinstance(exc, (BridgeError, asyncio.TimeoutError)):
                    log.exception("status sampler: R%02d of axis %d", cmd, addr)
                values[cmd] = None
                errors[cmd] = exc
                self._last_error[addr] = {"t": self.clock(), "cmd": cmd,
                                          "error": failure_kind(exc)[1]}
            else:
                last = self._last_error.get(addr)
                if last is not None and last["cmd"] == cmd:
                    del self._last_error[addr]  # the command that failed answers again
        return row(axis.config, values, t=self.clock(), errors=errors,
                   last_error=self._last_error.get(addr), has_drive=has_drive)

    # -- readers ---------------------------------------------------------------------

    def history_body(self) -> Dict[str, Any]:
        """``/api/history``: the last minute of positions and velocities, oldest first."""
        return {"axes": self.addrs, "period": self.period, "samples": list(self.history)}

    def subscribe(self) -> "asyncio.Queue[Dict[str, Any]]":
        queue: "asyncio.Queue[Dict[str, Any]]" = asyncio.Queue(QUEUE_SIZE)
        self._listeners.add(queue)
        return queue

    def unsubscribe(self, queue: "asyncio.Queue[Dict[str, Any]]") -> None:
        self._listeners.discard(queue)
