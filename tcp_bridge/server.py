"""The TCP side of the gateway: asyncio, thin.

Spec 2.1: the gateway is a TCP server on two ports, 1912 (NICOS / EPICS) and
1913 (maintenance); both serve the same commands here. Per connection:

* bytes go through a :class:`~tcp_bridge.wire.LineSplitter` (bounded
  line length; an overlong line is answered CAN once);
* requests are processed strictly in order, each awaited before the next, so
  every client gets its replies in request order; different connections
  interleave freely, request by request, even when one pipelines;
* a client that went away (reset) has the rest of its pipeline dropped;
* each reply is one 30-byte ``write`` (spec 2.2.2);
* :meth:`BridgeServer._answer` is the one place where an exception becomes a
  reply: CAN for an invalid command, NAK for anything else (a failed device
  transfer, a value that does not fit the reply, a bug), and the connection
  keeps serving.

Connection slots cannot be held hostage (issue 12):

* **allow-list**: a client whose address is not in ``options.allow``
  (:mod:`tcp_bridge.access`; default: loopback) is closed at once, unanswered,
  and logged with its address, before it counts against any limit;
* **idle timeout**: a connection is closed when it has sent no *request* for
  ``idle_timeout`` seconds. Only a complete request that parses and is not
  refused with CAN resets the clock (so does answering one): bytes trickled
  without ever completing a request, lines of junk, or requests for an axis or
  command the bridge does not serve (``9R10``, issue 35) do not; nor does a client that sends requests
  but never reads the replies (its writes cannot drain, so nothing is read
  from it any more). The default, 60 s
  (:data:`DEFAULT_IDLE_TIMEOUT`), is far above the polling period of the
  clients this gateway serves: EPICS motor drivers and NICOS poll each axis
  about once a second while it moves and every few seconds at rest, so
  only a client that has stopped talking is closed, and EPICS (asyn) and
  NICOS reconnect by themselves if it ever happens;
* **eviction** (issue 24): with all ``max_connections`` slots taken, a new
  client may take the slot of a connection that is not *active*. Active means a
  request in flight, or a request answered within the last ``active_window``
  seconds (:data:`DEFAULT_ACTIVE_WINDOW`, 10 s: several polls of a client at rest,
  see above). An active client is never evicted by a newcomer. Among the others
  the one that has said nothing for longest goes first: the idle (requests, but
  none lately) and the silent (connected, never a request; a newcomer of a burst
  is one) are ranked together by the time of their last request, or of their
  connection if they never sent one. A newcomer's own clock starts at connect,
  but it is not protected by it: only a request makes a connection active, so a
  burst of connections churns through its own slots and the slots of the idle,
  never through a polling client's. When nobody can be evicted, the newcomer is
  refused (closed unanswered): the newcomers themselves go last in line.
* **per-host cap**: one client host (by IP address) holds at most
  ``max_per_host`` connections (default: half of ``max_connections``, rounded
  up). A newcomer from a host at its cap may only take the slot of that host's
  own idle or silent connection, never another host's; so one host cannot take
  every slot, and a burst from one host leaves the other hosts' slots alone.
  Every eviction and refusal is logged with the addresses concerned.

:meth:`BridgeServer.close` stops accepting, lets each request in flight
finish and answer, closes the connections, then the engine (its bus workers
finish their transfers).
"""
from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import List, Optional, Sequence, Set, Tuple

from .access import LOOPBACK, Address, Network, client_address, describe, is_allowed
from .engine import Engine
from .errors import BridgeError
from .reasons import ReasonLog
from .tasks import cancel_and_wait
from .wire import (DEFAULT_MAX_LINE, Line, LineSplitter, Request, Status, format_error_reply,
                   parse_item, status_for)

log = logging.getLogger(__name__)
debug_log = logging.getLogger("tcp_bridge.debug")

DEFAULT_PORTS: Tuple[int, int] = (1912, 1913)  # spec 2.1: TCP_PORT_NUM_1 / TCP_PORT_NUM_2
DEFAULT_IDLE_TIMEOUT = 60.0  # seconds without a request; why 60: see the module docstring
DEFAULT_ACTIVE_WINDOW = 10.0  # a request this recent protects a connection from eviction
READ_SIZE = 4096


@dataclass
class ServerOptions:
    host: str = "127.0.0.1"
    ports: Sequence[int] = DEFAULT_PORTS
    max_line: int = DEFAULT_MAX_LINE
    max_connections: int = 64
    idle_timeout: Optional[float] = DEFAULT_IDLE_TIMEOUT  # None: never (tests, tools)
    close_grace: float = 10.0  # how long close() waits for requests in flight
    allow: Sequence[Network] = LOOPBACK  # client networks served (tcp_bridge.access)
    max_per_host: Optional[int] = None  # None: half of max_connections, rounded up
    active_window: float = DEFAULT_ACTIVE_WINDOW  # see the module docstring

    def __post_init__(self) -> None:
        if isinstance(self.max_connections, bool) or not isinstance(self.max_connections, int) \
                or self.max_connections < 1:
            raise ValueError(f"max_connections: must be a positive integer, not "
                             f"{self.max_connections!r}")
        if self.max_per_host is None:
            self.max_per_host = default_max_per_host(self.max_connections)
        cap = self.max_per_host
        if isinstance(cap, bool) or not isinstance(cap, int) \
                or not 1 <= cap <= self.max_connections:
            raise ValueError(f"max_per_host: must be an integer 1..{self.max_connections} "
                             f"(max_connections), not {cap!r}")
        if not self.active_window > 0:  # also refuses nan
            raise ValueError(f"active_window: must be a positive number of seconds, not "
                             f"{self.active_window!r}")


def default_max_per_host(max_connections: int) -> int:
    """Half the slots, rounded up: one host cannot take them all (unless there is one)."""
    return (max_connections + 1) // 2


class _Connection:
    def __init__(self, task: "asyncio.Task[None]", writer: asyncio.StreamWriter, now: float
                 ) -> None:
        self.task = task
        self.writer = writer
        self.peer = writer.get_extra_info("peername")
        self.host: Optional[Address] = client_address(self.peer)  # for the per-host cap
        self.busy = False  # a request in flight: never evicted, never idle
        self.waiting = False  # waiting for bytes between requests
        self.spoke = False  # has sent a request that parsed (see _evictable)
        self.last_request = now  # loop time of the last complete request (or connect)
        self.watchdog: Optional[asyncio.TimerHandle] = None  # the idle timeout


class BridgeServer:
    """Serves an :class:`~tcp_bridge.engine.Engine` on TCP."""

    def __init__(self, engine: Engine, options: Optional[ServerOptions] = None) -> None:
        self.engine = engine
        self.options = options or ServerOptions()
        self._servers: List[asyncio.Server] = []
        self._connections: Set[_Connection] = set()
        self._closing = False
        self._closed = asyncio.Event()
        self.reasons = ReasonLog()  # each CAN/NAK's reason at -v (tcp_bridge.reasons)

    @property
    def addresses(self) -> List[Tuple[str, int]]:
        """(host, port) of every listening socket, in the order of ``options.ports``."""
        return [s.getsockname()[:2] for srv in self._servers for s in (srv.sockets or ())]

    async def start(self) -> "BridgeServer":
        try:
            for port in self.options.ports:
                self._servers.append(await asyncio.start_server(
                    self._serve, self.options.host, port, limit=READ_SIZE))
        except BaseException:
            for srv in self._servers:
                srv.close()
            raise
        # Reads (never writes) each drive's units and logs them; awaitable by tests.
        self.probing: "asyncio.Future[None]" = asyncio.ensure_future(self.engine.probe())
        return self

    async def wait_closed(self) -> None:
        await self._closed.wait()

    # -- admission ---------------------------------------------------------------------

    def _admit(self, peer: object) -> bool:
        """Allow-list, the per-host cap, then a free slot (evicting if need be, see the
        module docstring); False: close unanswered."""
        if not is_allowed(peer, self.options.allow):
            log.warning("refused connection from %s: not in the allow-list (%s)", peer,
                        describe(self.options.allow))
            return False
        if self._closing:
            log.info("refused connection from %s: shutting down", peer)
            return False
        host = client_address(peer)
        same_host = [c for c in self._connections if c.host == host]
        cap = self.options.max_per_host
        assert cap is not None  # set by ServerOptions.__post_init__
        if len(same_host) >= cap:
            # Evicting its own host's connection keeps the total unchanged too.
            return self._make_room(peer, same_host, f"its host already holds {cap} connections "
                                   f"(the per-host cap)")
        if len(self._connections) < self.options.max_connections:
            return True
        return self._make_room(peer, list(self._connections),
                               f"all {self.options.max_connections} connections are taken")

    def _evictable(self, conn: _Connection, now: float) -> bool:
        """Not active: no request in flight, and none answered within ``active_window``."""
        if conn.busy:
            return False
        return not conn.spoke or now - conn.last_request >= self.options.active_window

    def _make_room(self, peer: object, among: List[_Connection], why: str) -> bool:
        """Evict the connection of ``among`` that has said nothing for longest, unless
        every one is active; False: ``peer`` is refused."""
        now = asyncio.get_running_loop().time()
        candidates = [c for c in among if self._evictable(c, now)]
        if not candidates:
            log.warning("refused connection from %s: %s, and each is active (a request in "
                        "flight or answered within %g s)", peer, why, self.options.active_window)
            return False
        victim = min(candidates, key=lambda c: c.last_request)
        log.warning("%s: closing %s, %s for %.1f s, to serve %s", why, victim.peer,
                    "idle" if victim.spoke else "silent since it connected",
                    now - victim.last_request, peer)
        self._connections.discard(victim)  # the slot is free now; the task closes it
        victim.task.cancel()
        return True

    # -- one connection ------------------------------------------------------------------

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if not self._admit(peer):
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        conn = _Connection(task, writer, asyncio.get_running_loop().time())
        self._connections.add(conn)
        log.info("client %s connected", peer)
        self._watch(conn)
        try:
            await self._converse(conn, reader, writer)
        except (ConnectionError, OSError) as exc:
            log.info("client %s: %s", peer, exc)
        except asyncio.CancelledError:
            pass  # shutdown, eviction or idle timeout
        finally:
            if conn.watchdog is not None:
                conn.watchdog.cancel()
            self._connections.discard(conn)  # the slot is free before the close handshake
            writer.close()
            try:
                await asyncio.wait_for(writer.wait_closed(), 1.0)
            except (ConnectionError, OSError, asyncio.TimeoutError, asyncio.CancelledError):
                # close() waits for the replies still buffered to go out; a client
                # that does not read them would hold the socket and its buffers
                # for ever: reset it instead.
                writer.transport.abort()
            log.info("client %s disconnected", peer)

    def _watch(self, conn: _Connection) -> None:
        """The idle timeout: one timer per connection, not one per read (a timer costs
        more than the rest of a status poll's bookkeeping), checked when it fires.

        It closes a connection that sent no request for ``idle_timeout`` seconds and
        has none in flight, whether it waits for bytes or for a client that does not
        read its replies (a write that cannot drain).
        """
        limit = self.options.idle_timeout
        if limit is None:
            return
        loop = asyncio.get_running_loop()
        due = conn.last_request + limit
        now = loop.time()
        if conn.busy or now < due:
            # A request came since the timer was set, or one is in flight (its
            # answer moves last_request on): look again then.
            conn.watchdog = loop.call_at(now + limit if conn.busy else due, self._watch, conn)
            return
        log.info("client %s sent no request for %g s; closing", conn.peer, limit)
        conn.watchdog = None
        conn.task.cancel()

    async def _converse(self, conn: _Connection, reader: asyncio.StreamReader,
                        writer: asyncio.StreamWriter) -> None:
        """Read requests and answer them in order until EOF, idle timeout, or shutdown."""
        loop = asyncio.get_running_loop()
        splitter = LineSplitter(self.options.max_line)
        while not self._closing:
            conn.waiting = True
            try:
                data = await reader.read(READ_SIZE)
            finally:
                conn.waiting = False
            if not data:
                return  # EOF; a half-received request is dropped unanswered
            items = splitter.feed(data)
            for done, item in enumerate(items):
                if done:
                    # Requests answered without the bus never suspend: yield to
                    # the loop between pipelined requests, so that one client's
                    # pipeline cannot hold up every other connection.
                    await asyncio.sleep(0)
                if writer.is_closing():
                    # The client went away (reset, or a failed write): the rest of
                    # its pipeline would only be executed for nobody.
                    log.info("client %s gone; %d pipelined requests dropped",
                             conn.peer, len(items) - done)
                    return
                conn.busy = True
                try:
                    reply, valid = await self._answer(item)
                finally:
                    conn.busy = False
                if valid:
                    # Only a request resets the idle clock (issue 12) and makes the
                    # connection active (issue 24): bytes or junk lines trickled to
                    # hold the slot do not.
                    conn.last_request = loop.time()
                    conn.spoke = True
                if not writer.is_closing():
                    writer.write(reply)
                if self._closing:
                    break
            if writer.transport.get_write_buffer_size():
                await writer.drain()  # the client reads slower than it asks

    async def _answer(self, item: Line) -> Tuple[bytes, bool]:
        """The one place where an exception becomes a reply (CAN or NAK).

        Returns the reply and whether ``item`` was a request that counts: it parsed,
        and was not refused with CAN.
        """
        request: Optional[Request] = None
        counts = False
        try:
            request = parse_item(item)
            reply = await self.engine.execute(request)
            counts = True
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            if not isinstance(exc, (BridgeError, asyncio.TimeoutError)):
                log.exception("unexpected error for %r; answered NAK", item)
            else:
                self.reasons.refused(item, request, exc, status_for(exc))
                if self.engine.debug:
                    debug_log.info("error: %s", exc)
            reply = format_error_reply(exc, request)
            counts = request is not None and status_for(exc) is not Status.CAN
        if self.engine.debug:
            debug_log.info("request %r -> reply %r", item, reply.rstrip(b"\0"))
        return reply, counts

    # -- shutdown ----------------------------------------------------------------------------

    async def close(self) -> None:
        """Stop accepting, finish requests in flight, close connections and the engine."""
        if self._closing:
            await self._closed.wait()
            return
        self._closing = True
        for srv in self._servers:
            srv.close()
        for conn in list(self._connections):
            if not conn.busy:
                conn.task.cancel()
        tasks = [c.task for c in self._connections]
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=self.options.close_grace)
            # 1.5 s after each cancellation: a connection closes its socket within 1 s
            # (_serve); a second one only for a cancellation that was lost (tasks.py).
            left = await cancel_and_wait(pending, 2.5, retry=1.5)
            if left:
                log.warning("%d client connections still open after the close", len(left))
        probing = getattr(self, "probing", None)  # set by start()
        if probing is not None and not probing.done():
            # A close right after start (serve's --epics or --http failing): the probe
            # must not submit to workers the engine is closing ("worker is closed").
            await cancel_and_wait([probing], 2.5)
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, self.engine.close)
        self._closed.set()

    async def __aenter__(self) -> "BridgeServer":
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

