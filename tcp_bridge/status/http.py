"""A small read-only HTTP/1.1 server for the status page, on the bridge's event loop.

No framework (no new dependency): the page needs four GET routes and nothing
else. RFC 9112 (HTTP/1.1 message syntax) and RFC 9110 (semantics) as far as
they matter here:

* ``GET /`` the page (:mod:`.page`); ``GET /api/axes`` the latest sample (JSON);
  ``GET /api/history`` the last minute of positions and velocities (JSON);
  ``GET /api/history.csv`` the same as CSV, to download (:mod:`.history_csv`);
  ``GET /api/stream`` Server-Sent Events (WHATWG HTML, "Server-sent events"):
  one ``data:`` event per sample, the body of ``/api/axes``. ``HEAD`` is not served.
* Any other method: 405 with ``Allow: GET`` (RFC 9110 15.5.6); any other path:
  404; a request line or head that is not HTTP: 400; a head longer than
  :data:`MAX_HEAD` bytes: 431 (RFC 6585 5); a head not complete within
  :data:`HEAD_TIMEOUT` seconds, or silent for :data:`IDLE_TIMEOUT` seconds before it
  is: closed unanswered. A request body is never read:
  every answer closes the connection (``Connection: close``, RFC 9112 9.6), so
  nothing is pipelined and nothing waits.
* **Who may connect**: the bridge's own allow-list (``--allow``, ``[bridge] allow``;
  :func:`tcp_bridge.access.is_allowed`), checked as the PSI ports check it: a client
  outside it is closed at once, unanswered, and logged with its address.
* **Bounded, and no client holds a slot by saying or reading nothing** (issue 35):
  at most :data:`MAX_CONNECTIONS` connections at once and :data:`MAX_STREAMS` of
  them streams; a newcomer takes the slot of the slowest request head, a new
  stream that of a stalled or else the oldest stream (which reconnects after the
  ``retry`` it was told), and complete requests are answered at most
  :data:`~.slots.PAGE_RATE` a second, so that the page cannot slow the PSI ports
  that share its event loop. The rules are in :mod:`.slots`. Bodies are encoded
  once per sample, not once per request or per stream.

Nothing here writes to a drive: the only data are the sampler's (:mod:`.sampler`).
"""
from __future__ import annotations

import asyncio
import json
import logging
import socket
from typing import Any, Dict, Final, List, Optional, Sequence, Set, Tuple

from ..access import LOOPBACK, Network, describe, is_allowed
from ..tasks import cancel_and_wait
from .history_csv import CONTENT_TYPE as CSV_TYPE
from .history_csv import FILENAME as CSV_NAME
from .history_csv import history_csv
from .page import PAGE
from .sampler import DEFAULT_PERIOD, Sampler
from .slots import Phase, RateLimit, Slot, Slots

log = logging.getLogger(__name__)

MAX_HEAD: Final = 8192  # bytes of request line and header fields
HEAD_TIMEOUT: Final = 5.0  # seconds to send them (a browser sends them at once)
IDLE_TIMEOUT: Final = 2.0  # seconds without a byte while the head is still coming
MAX_CONNECTIONS: Final = 16
MAX_STREAMS: Final = 8
ACCEPT_BACKLOG: Final = 64  # connections the kernel holds while every slot is busy
WRITE_TIMEOUT: Final = 10.0  # a client that does not read its answer is dropped
STREAM_RETRY_MS: Final = 3000  # EventSource's reconnection time, sent with each stream

_REASONS: Final = {200: "OK", 400: "Bad Request", 404: "Not Found",
                   405: "Method Not Allowed", 431: "Request Header Fields Too Large",
                   503: "Service Unavailable"}


class NotHttp(ValueError):
    """The first byte of a request cannot begin an HTTP method."""


def parse_address(text: str) -> Tuple[str, int]:
    """``--http``'s value: ``HOST:PORT``, ``[v6]:PORT`` or ``PORT`` (host 127.0.0.1)."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", text
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r} is not HOST:PORT (port 0..65535; 0 picks one)")
    return host, int(port)


def response_head(status: int, content_type: str, length: Optional[int] = None,
                  extra: Sequence[Tuple[str, str]] = ()) -> bytes:
    lines = [f"HTTP/1.1 {status} {_REASONS[status]}", f"Content-Type: {content_type}",
             "Cache-Control: no-store", "Connection: close", "X-Content-Type-Options: nosniff"]
    if length is not None:
        lines.append(f"Content-Length: {length}")
    lines.extend(f"{k}: {v}" for k, v in extra)
    return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii")


def parse_request_line(head: bytes) -> Tuple[str, str]:
    """(method, path without query) of a request head; ValueError if it is not HTTP/1.x."""
    line = head.split(b"\r\n", 1)[0].split(b"\n", 1)[0]
    parts = line.split(b" ")
    if len(parts) != 3 or not parts[2].startswith(b"HTTP/1."):
        raise ValueError("not an HTTP/1.x request line")
    method, target = parts[0].decode("ascii"), parts[1].decode("ascii")
    if not method.isalpha() or not target.startswith("/"):
        raise ValueError("not an HTTP/1.x request line")
    return method, target.split("?", 1)[0]


class StatusServer:
    """Serves a :class:`Sampler`'s data on ``host:port``."""

    def __init__(self, sampler: Sampler, host: str = "127.0.0.1", port: int = 0, *,
                 allow: Sequence[Network] = LOOPBACK) -> None:
        self.sampler = sampler
        self.host, self.port = host, port
        self.allow = allow
        self._listener: Optional[socket.socket] = None
        self._acceptor: Optional["asyncio.Task[None]"] = None
        self._room = asyncio.Event()  # set when a connection ends (a slot may be free)
        self._tasks: Set["asyncio.Task[None]"] = set()
        self._slots = Slots()
        self.limit = RateLimit()
        self._encoded: Dict[str, Tuple[Any, bytes]] = {}  # route -> (body, its JSON)
        self.refused = 0  # connections refused for want of a slot
        self._pending = 0  # accepted, not yet in a slot (see _accept)
        self._refusal_logged = float("-inf")
        self._closing = False

    @property
    def streams(self) -> int:
        return len(self._slots.in_phase(Phase.STREAM))

    @property
    def addresses(self) -> List[Tuple[str, int]]:
        return [self._listener.getsockname()[:2]] if self._listener is not None else []

    async def start(self) -> "StatusServer":
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        self._listener = socket.create_server((self.host, self.port), family=family,
                                              backlog=ACCEPT_BACKLOG)
        self._listener.setblocking(False)
        self._acceptor = asyncio.ensure_future(self._accept(self._listener))
        return self

    async def _accept(self, listener: socket.socket) -> None:
        """Accept a connection only when it can have a slot (a free one, or one whose
        head has been coming for HEAD_GRACE): with every slot busy answering, the
        next ones wait in the kernel's listen backlog and cost the event loop, which
        the PSI ports share, nothing at all."""
        loop = asyncio.get_running_loop()
        while not self._closing:
            # Accepted and not yet given a slot: each will take a stale head's (or a free)
            # slot, so no more are accepted than there are (a newcomer refused for a head
            # that was stale when it was accepted but taken since would be reset).
            room = MAX_CONNECTIONS - len(self._slots)
            if self._pending >= max(room, len(self._slots.stale_heads(loop.time()))):
                self._room.clear()
                # A slot frees (a connection ends or an accepted one takes its slot),
                # or one more head has taken HEAD_GRACE and may be given to the next
                # one (.slots).
                stale = self._slots.next_stale(loop.time())
                try:
                    await asyncio.wait_for(self._room.wait(), stale)
                except asyncio.TimeoutError:
                    pass
                continue
            try:
                conn, _ = await loop.sock_accept(listener)
            except OSError as exc:  # e.g. out of descriptors: try again shortly
                log.warning("status page: accept failed: %s", exc)
                await asyncio.sleep(0.1)
                continue
            self._pending += 1
            task = asyncio.ensure_future(self._connection(conn))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _connection(self, conn: socket.socket) -> None:
        try:
            reader, writer = await asyncio.open_connection(sock=conn, limit=MAX_HEAD)
        except OSError:
            conn.close()
            return
        finally:
            self._pending -= 1  # from here on it has a slot, or is refused or gone
            self._room.set()
        await self._serve(reader, writer)

    @property
    def url(self) -> str:
        host, port = self.addresses[0]
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}/"

    async def close(self, *, sampler: bool = True) -> None:
        """Stop listening, end every connection (streams too), stop the sampler (unless
        ``sampler`` is False: another server shares it)."""
        self._closing = True
        self._room.set()
        if self._acceptor is not None:
            await cancel_and_wait([self._acceptor], 2.0)
        if self._listener is not None:
            self._listener.close()
        if await cancel_and_wait(list(self._tasks), 2.0):
            log.warning("status page: %d connections still open after 2 s", len(self._tasks))
        if sampler:
            await self.sampler.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if not is_allowed(peer, self.allow):
            log.warning("status page: refused %s: not in the allow-list (%s)", peer,
                        describe(self.allow))
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        slot = Slot((task, writer), loop.time())
        admitted, victim = self._slots.admit(slot, MAX_CONNECTIONS)
        if not admitted:  # a head finished since the acceptor looked, or is too young
            self.refused += 1
            if loop.time() - self._refusal_logged >= 1.0:  # a flood is one line a second
                self._refusal_logged = loop.time()
                log.warning("status page: refused %s: %d connections already, each with a "
                            "complete request (%d refused so far)", peer, MAX_CONNECTIONS,
                            self.refused)
            writer.transport.abort()  # nothing to say, nothing to wait for
            return
        if victim is not None:
            log.info("status page: %d connections; closed %s, whose request head was still "
                     "coming after %.1f s, for %s", MAX_CONNECTIONS,
                     victim.handle[1].get_extra_info("peername"), loop.time() - victim.since,
                     peer)
            _end(victim)
        try:
            await self._answer(slot, reader, writer)
        except (ConnectionError, OSError, asyncio.TimeoutError, asyncio.CancelledError):
            pass
        finally:
            self._slots.remove(slot)
            self._room.set()
            if writer.transport.get_write_buffer_size():
                writer.transport.abort()  # a client that does not read: no close handshake
            else:
                writer.close()

    async def _send(self, writer: asyncio.StreamWriter, data: bytes) -> None:
        writer.write(data)
        await asyncio.wait_for(writer.drain(), WRITE_TIMEOUT)

    async def _simple(self, writer: asyncio.StreamWriter, status: int, body: bytes,
                      content_type: str = "text/plain; charset=utf-8",
                      extra: Sequence[Tuple[str, str]] = ()) -> None:
        await self._send(writer, response_head(status, content_type, len(body), extra) + body)

    async def _read_head(self, reader: asyncio.StreamReader) -> Optional[bytes]:
        """The request head; None if the client closed, or fell silent for IDLE_TIMEOUT,
        or took HEAD_TIMEOUT in all; ``b""`` if it is longer than MAX_HEAD;
        :class:`NotHttp` at once if it cannot start an HTTP request line."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + HEAD_TIMEOUT
        head = b""
        while b"\r\n\r\n" not in head:
            if len(head) >= MAX_HEAD:
                return b""
            left = deadline - loop.time()
            if left <= 0:
                return None
            try:
                data = await asyncio.wait_for(reader.read(MAX_HEAD), min(IDLE_TIMEOUT, left))
            except asyncio.TimeoutError:
                return None
            if not data:
                return None
            if not head and not data[:1].isalpha():
                # A method is letters (RFC 9110 9.1); a PSI request starts with its axis.
                raise NotHttp()
            head += data
        return head

    async def _answer(self, slot: Slot, reader: asyncio.StreamReader,
                      writer: asyncio.StreamWriter) -> None:
        try:
            head = await self._read_head(reader)
        except NotHttp:
            # A PSI request sent here by mistake (`tcp-bridge send` to this port): a PSI
            # line ends in CR alone, so its head would never end; say so at once.
            await self._simple(writer, 400, b"not HTTP: this is the bridge's status page; "
                                            b"PSI requests go to its PSI ports (1912, 1913)\n")
            return
        if head is None:
            return  # closed, silent or too slow: unanswered
        loop = asyncio.get_running_loop()
        slot.enter(Phase.QUEUED, loop.time())
        wait = self.limit.take(loop.time())
        if wait:
            await asyncio.sleep(wait)  # the page's budget (see .slots)
        slot.enter(Phase.ANSWER, loop.time())
        if not head:
            await self._simple(writer, 431, b"request head too large\n")
            return
        try:
            method, path = parse_request_line(head)
        except (ValueError, UnicodeError):
            await self._simple(writer, 400, b"bad request\n")
            return
        if method != "GET":
            await self._simple(writer, 405, b"read-only: GET only\n", extra=[("Allow", "GET")])
            return
        if path == "/":
            await self._simple(writer, 200, PAGE.encode("utf-8"), "text/html; charset=utf-8")
        elif path == "/api/axes":
            await self._json(writer, path, self.sampler.latest or {"seq": 0, "axes": []})
        elif path == "/api/history":
            await self._json(writer, path, self.sampler.history_body)
        elif path == "/api/history.csv":
            text = history_csv(self.sampler.history_body()).encode("utf-8")
            await self._simple(writer, 200, text, CSV_TYPE, extra=[
                ("Content-Disposition", f'attachment; filename="{CSV_NAME}"')])
        elif path == "/api/stream":
            await self._stream(slot, writer)
        else:
            await self._simple(writer, 404, b"not found\n")

    def _encode(self, route: str, body: Any) -> bytes:
        """JSON of ``body``, encoded once per sample: the sampler makes a new body for
        each sample (the same object is the same text), and ``history_body`` (a
        callable here) changes only with the sample count."""
        cached = self._encoded.get(route)
        if callable(body):
            key: Any = self.sampler.seq
            if cached is not None and cached[0] == key:
                return cached[1]
            body = body()
        else:
            key = body
            if cached is not None and cached[0] is key:
                return cached[1]
        text = json.dumps(body).encode("utf-8")
        self._encoded[route] = (key, text)
        return text

    async def _json(self, writer: asyncio.StreamWriter, route: str, body: Any) -> None:
        await self._simple(writer, 200, self._encode(route, body), "application/json")

    async def _stream(self, slot: Slot, writer: asyncio.StreamWriter) -> None:
        def stalled(other: Slot) -> bool:
            return bool(other.handle[1].transport.get_write_buffer_size())
        victim = self._slots.stream(slot, asyncio.get_running_loop().time(), MAX_STREAMS,
                                    stalled)
        if victim is not None:
            log.info("status page: %d streams; closed the %s stream of %s for %s",
                     MAX_STREAMS, "stalled" if stalled(victim) else "oldest",
                     victim.handle[1].get_extra_info("peername"),
                     writer.get_extra_info("peername"))
            _end(victim)
        queue = self.sampler.subscribe()
        try:
            await self._send(writer, response_head(200, "text/event-stream")
                             + f"retry: {STREAM_RETRY_MS}\n\n".encode("ascii"))
            if self.sampler.latest is not None and queue.empty():
                queue.put_nowait(self.sampler.latest)  # the page shows something at once
            # A cancellation may be swallowed (tcp_bridge.tasks): the flags end it too.
            while not self._closing and not slot.evicted:
                body = await queue.get()
                await self._send(writer, b"data: " + self._encode("event", body) + b"\n\n")
        finally:
            self.sampler.unsubscribe(queue)


def _end(victim: Slot) -> None:
    """Close the connection of a slot given to another: its socket at once (a client
    that does not read gets no close handshake), and its task."""
    task, writer = victim.handle
    if writer.transport.get_write_buffer_size():
        writer.transport.abort()
    else:
        writer.close()
    task.cancel()


async def open_status_page(engine: Any, host: str, port: int, *,
                           allow: Sequence[Network] = LOOPBACK,
                           period: float = DEFAULT_PERIOD) -> StatusServer:
    """``serve --http``: listen (OSError if it cannot), then start sampling ``engine``."""
    server = await StatusServer(Sampler(engine, period=period), host, port, allow=allow).start()
    server.sampler.start()
    return server
