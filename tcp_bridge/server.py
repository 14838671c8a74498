"""The TCP side of the gateway: asyncio, thin.

Spec 2.1: the gateway is a TCP server on two ports, 1912 (NICOS / EPICS) and
1913 (maintenance); both serve the same commands here. Per connection:

* bytes go through a :class:`~tcp_bridge.protocol.LineSplitter` (bounded
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

Limits: a maximum number of simultaneous connections (a connection above it is
closed at once, unanswered), an optional idle timeout. :meth:`BridgeServer.close`
stops accepting, lets each request in flight finish and answer, closes the
connections, then the engine (its bus workers finish their transfers).
"""
from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from typing import List, Optional, Sequence, Set, Tuple

from .engine import Engine
from .errors import BridgeError
from .protocol import DEFAULT_MAX_LINE, Line, LineSplitter, Request, format_error_reply, parse_item

log = logging.getLogger(__name__)
debug_log = logging.getLogger("tcp_bridge.debug")

DEFAULT_PORTS: Tuple[int, int] = (1912, 1913)  # spec 2.1: TCP_PORT_NUM_1 / TCP_PORT_NUM_2
READ_SIZE = 4096


@dataclass
class ServerOptions:
    host: str = "127.0.0.1"
    ports: Sequence[int] = DEFAULT_PORTS
    max_line: int = DEFAULT_MAX_LINE
    max_connections: int = 64
    idle_timeout: Optional[float] = None  # seconds without a request; None: no limit
    close_grace: float = 10.0  # how long close() waits for requests in flight


class _Connection:
    def __init__(self, task: "asyncio.Task[None]", peer: object) -> None:
        self.task = task
        self.peer = peer
        self.busy = False


class BridgeServer:
    """Serves an :class:`~tcp_bridge.engine.Engine` on TCP."""

    def __init__(self, engine: Engine, options: Optional[ServerOptions] = None) -> None:
        self.engine = engine
        self.options = options or ServerOptions()
        self._servers: List[asyncio.AbstractServer] = []
        self._connections: Set[_Connection] = set()
        self._closing = False
        self._closed = asyncio.Event()

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

    # -- one connection ------------------------------------------------------------------

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if self._closing or len(self._connections) >= self.options.max_connections:
            log.warning("refusing connection from %s: %s", peer,
                        "shutting down" if self._closing else "connection limit reached")
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        conn = _Connection(task, peer)
        self._connections.add(conn)
        log.info("client %s connected", peer)
        try:
            await self._converse(conn, reader, writer)
        except (ConnectionError, OSError) as exc:
            log.info("client %s: %s", peer, exc)
        except asyncio.CancelledError:
            pass  # shutdown of an idle connection
        finally:
            self._connections.discard(conn)  # the slot is free before the close handshake
            writer.close()
            try:
                await asyncio.wait_for(writer.wait_closed(), 1.0)
            except (ConnectionError, OSError, asyncio.TimeoutError, asyncio.CancelledError):
                pass
            log.info("client %s disconnected", peer)

    async def _converse(self, conn: _Connection, reader: asyncio.StreamReader,
                        writer: asyncio.StreamWriter) -> None:
        """Read requests and answer them in order until EOF, idle timeout, or shutdown."""
        splitter = LineSplitter(self.options.max_line)
        while not self._closing:
            try:
                data = await asyncio.wait_for(reader.read(READ_SIZE), self.options.idle_timeout)
            except asyncio.TimeoutError:
                log.info("client %s idle for %g s; closing", conn.peer, self.options.idle_timeout)
                return
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
                    reply = await self._answer(item)
                finally:
                    conn.busy = False
                if not writer.is_closing():
                    writer.write(reply)
                if self._closing:
                    break
            await writer.drain()

    async def _answer(self, item: Line) -> bytes:
        """The one place where an exception becomes a reply (CAN or NAK)."""
        request: Optional[Request] = None
        try:
            request = parse_item(item)
            reply = await self.engine.execute(request)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            if not isinstance(exc, (BridgeError, asyncio.TimeoutError)):
                log.exception("unexpected error for %r; answered NAK", item)
            elif self.engine.debug:
                debug_log.info("error: %s", exc)
            reply = format_error_reply(exc, request)
        if self.engine.debug:
            debug_log.info("request %r -> reply %r", item, reply.rstrip(b"\0"))
        return reply

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
            for task in pending:
                task.cancel()
            if pending:
                await asyncio.wait(pending, timeout=1.0)
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, self.engine.close)
        self._closed.set()

    async def __aenter__(self) -> "BridgeServer":
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
