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
  :data:`HEAD_TIMEOUT` seconds: closed unanswered. A request body is never read:
  every answer closes the connection (``Connection: close``, RFC 9112 9.6), so
  nothing is pipelined and nothing waits.
* **Who may connect**: the bridge's own allow-list (``--allow``, ``[bridge] allow``;
  :func:`tcp_bridge.access.is_allowed`), checked as the PSI ports check it: a client
  outside it is closed at once, unanswered, and logged with its address.
* **Bounded**: at most :data:`MAX_CONNECTIONS` connections at once (the others are
  closed unanswered, logged) and :data:`MAX_STREAMS` of them streams (the others
  get 503).

Nothing here writes to a drive: the only data are the sampler's (:mod:`.sampler`).
"""
from __future__ import annotations

import asyncio
import json
import logging
from typing import Any, Dict, Final, List, Optional, Sequence, Set, Tuple

from ..access import LOOPBACK, Network, describe, is_allowed
from ..tasks import cancel_and_wait
from .history_csv import CONTENT_TYPE as CSV_TYPE
from .history_csv import FILENAME as CSV_NAME
from .history_csv import history_csv
from .page import PAGE
from .sampler import DEFAULT_PERIOD, Sampler

log = logging.getLogger(__name__)

MAX_HEAD: Final = 8192  # bytes of request line and header fields
HEAD_TIMEOUT: Final = 10.0  # seconds to send them
MAX_CONNECTIONS: Final = 16
MAX_STREAMS: Final = 8
WRITE_TIMEOUT: Final = 10.0  # a client that does not read its answer is dropped

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
        self._server: Optional[asyncio.Server] = None
        self._tasks: Set["asyncio.Task[None]"] = set()
        self.streams = 0
        self._closing = False

    @property
    def addresses(self) -> List[Tuple[str, int]]:
        sockets = self._server.sockets if self._server is not None else ()
        return [s.getsockname()[:2] for s in sockets or ()]

    async def start(self) -> "StatusServer":
        self._server = await asyncio.start_server(self._serve, self.host, self.port,
                                                  limit=MAX_HEAD)
        return self

    @property
    def url(self) -> str:
        host, port = self.addresses[0]
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}/"

    async def close(self) -> None:
        """Stop listening, end every connection (streams too), stop the sampler."""
        self._closing = True
        if self._server is not None:
            self._server.close()
        if await cancel_and_wait(list(self._tasks), 2.0):
            log.warning("status page: %d connections still open after 2 s", len(self._tasks))
        await self.sampler.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if not is_allowed(peer, self.allow):
            log.warning("status page: refused %s: not in the allow-list (%s)", peer,
                        describe(self.allow))
            writer.close()
            return
        if len(self._tasks) >= MAX_CONNECTIONS:
            log.warning("status page: refused %s: %d connections already", peer,
                        MAX_CONNECTIONS)
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            await self._answer(reader, writer)
        except (ConnectionError, OSError, asyncio.TimeoutError, asyncio.CancelledError):
            pass
        finally:
            self._tasks.discard(task)
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

    async def _answer(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(self._head(reader), HEAD_TIMEOUT)
        except asyncio.IncompleteReadError:
            return  # closed before the end of its head
        except NotHttp:
            # A PSI request sent here by mistake (`tcp-bridge send` to this port): a PSI
            # line ends in CR alone, so its head would never end; say so at once.
            await self._simple(writer, 400, b"not HTTP: this is the bridge's status page; "
                                            b"PSI requests go to its PSI ports (1912, 1913)\n")
            return
        except asyncio.LimitOverrunError:
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
            await self._json(writer, self.sampler.latest or {"seq": 0, "axes": []})
        elif path == "/api/history":
            await self._json(writer, self.sampler.history_body())
        elif path == "/api/history.csv":
            text = history_csv(self.sampler.history_body()).encode("utf-8")
            await self._simple(writer, 200, text, CSV_TYPE, extra=[
                ("Content-Disposition", f'attachment; filename="{CSV_NAME}"')])
        elif path == "/api/stream":
            await self._stream(writer)
        else:
            await self._simple(writer, 404, b"not found\n")

    @staticmethod
    async def _head(reader: asyncio.StreamReader) -> bytes:
        """The request head; :class:`NotHttp` at once if it cannot start an HTTP request
        line (a method is letters, RFC 9110 9.1; a PSI request starts with its axis)."""
        first = await reader.readexactly(1)
        if not first.isalpha():
            raise NotHttp()
        return first + await reader.readuntil(b"\r\n\r\n")

    async def _json(self, writer: asyncio.StreamWriter, body: Dict[str, Any]) -> None:
        await self._simple(writer, 200, json.dumps(body).encode("utf-8"), "application/json")

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        if self.streams >= MAX_STREAMS:
            await self._simple(writer, 503, b"too many streams\n", extra=[("Retry-After", "10")])
            return
        self.streams += 1
        queue = self.sampler.subscribe()
        try:
            await self._send(writer, response_head(200, "text/event-stream"))
            if self.sampler.latest is not None and queue.empty():
                queue.put_nowait(self.sampler.latest)  # the page shows something at once
            while not self._closing:  # a cancellation may be swallowed (tcp_bridge.tasks)
                body = await queue.get()
                await self._send(writer, b"data: " + json.dumps(body).encode("utf-8") + b"\n\n")
        finally:
            self.sampler.unsubscribe(queue)
            self.streams -= 1


async def open_status_page(engine: Any, host: str, port: int, *,
                           allow: Sequence[Network] = LOOPBACK,
                           period: float = DEFAULT_PERIOD) -> StatusServer:
    """``serve --http``: listen (OSError if it cannot), then start sampling ``engine``."""
    server = await StatusServer(Sampler(engine, period=period), host, port, allow=allow).start()
    server.sampler.start()
    return server
