"""Serve the simulator's CAN bus to other processes over the socketcand protocol.

The simulated drives live on a python-can ``virtual`` channel, which only the
simulator's own process can join. :class:`SocketcandServer` joins that channel
and serves it over TCP, so that any python-can program joins the same bus with
``can.Bus(interface="socketcand", host=HOST, port=PORT, channel="can0")``:
``python -m can.logger``, ``can.viewer``, a ``canopen.Network``, the bridge.
The protocol (modes, commands, formats) is :mod:`epos_link.simulator.socketcand_wire`.

The rules:

* **One bus order.** Every frame reaches the clients through one dispatcher, the
  server's event loop: a frame from a simulated node (read from the virtual
  channel by one reader thread) and a frame a client sends (put onto the
  virtual channel, then passed on) are queued to the clients in the order the
  loop handles them, so all clients see the same sequence. The simulated nodes
  see a client's frame when the loop sends it. (The virtual channel itself has
  no global order: two threads sending at once may reach two listeners in
  opposite orders; the clients' order is the server's view of the bus.)
* **Own frames.** A client does not receive the frames it sent itself: the
  reference server reads the bus with a CAN_RAW socket, which does not receive
  its own frames unless CAN_RAW_RECV_OWN_MSGS is set (Linux
  ``Documentation/networking/can.rst``, "RAW socket option
  CAN_RAW_RECV_OWN_MSGS": off by default). Every other client does.
* **One client cannot disturb the others.** Each message is written to the
  client's transport at once (it goes to the kernel while the client reads);
  what waits for a client is bounded (:data:`OUTPUT_LIMIT` bytes). A client
  over the bound (it stopped reading) is disconnected with a log line. Input is
  bounded too (:data:`~epos_link.simulator.socketcand_wire.MAX_COMMAND`);
  garbage is answered ``< error .. >`` or skipped, a client that goes away is
  forgotten.
* **Bounded by connections and by turns** (issue 35). At most ``max_clients``
  (:data:`MAX_CLIENTS`) connections are served; one more is told
  ``< error too many clients ... >`` at once, instead of ``< hi >``, and closed
  (python-can's client raises ``CanError`` with that text). The loop is asyncio's
  selector loop (epoll on Linux), so descriptors above 1024 are no problem
  here, and the cap keeps the process's descriptors, and so those of the
  simulator's own links, few. Each client is served one read (at most
  :data:`READ_SIZE` bytes, about 130 frames) per turn, then the loop moves on
  to the others, so a client that floods the bus delays another client's frame
  by at most one read's worth per connection, not by its whole backlog.
* **Loopback by default** (127.0.0.1): the protocol has no authentication, and
  a client can put any frame on the bus.
* **Chosen:** after ``< ok >`` to ``< rawmode >`` the server sends that client
  no frame until it sends something itself (it has read the ``< ok >`` then) or
  :data:`RAW_SETTLE` seconds have passed; the frames are held for it, none is
  lost. python-can's client checks the ``< ok >`` with one ``recv()`` compared to
  the exact text, so a frame sent right behind it could arrive in the same read
  and fail the handshake (the reference server has the same race).
* **A client's frames reach the bus, even when its connection ends in a reset**,
  as on a CAN bus, where a frame sent is on the bus whatever its sender does
  next. A client that closes its socket with frames still unread (python-can's
  ``shutdown()`` does) makes its kernel answer with a TCP reset, and the
  server's next write or read then fails with ``ECONNRESET``; asyncio would
  forget the bytes that client sent before the reset (still in the kernel, or
  read but not yet taken from the :class:`asyncio.StreamReader`).
  :class:`_TakeAllProtocol` reads what the socket still holds when the
  connection is lost and hands it to the reader, followed by an ordinary end
  of stream, so every command the client sent before the reset is carried
  out (Linux delivers the data queued before a reset before it reports the
  reset: ``tcp_recvmsg`` copies the receive queue before it looks at
  ``sk_err``). Bounded by :data:`DRAIN_LIMIT` bytes.
* Close: the reader thread and the loop thread are joined with timeouts, the
  clients' connections are closed, the virtual bus connection is shut down.
"""
from __future__ import annotations

import asyncio
import logging
import os
import socket
import threading
import time
from typing import Any, List, Optional, Set, Tuple

import can

from .socketcand_wire import (HI, CommandReader, CommandTooLong, Frame, Session,
                              SocketcandError, error_reply, format_frame)

log = logging.getLogger(__name__)
MAX_CLIENTS = 64  # connections served at once (see the module docstring)
LISTEN_BACKLOG = 4096  # connections the kernel queues before they are accepted
READ_SIZE = 4096  # bytes of one client handled per turn
OUTPUT_LIMIT = 1 << 20  # bytes waiting for one client: ~20000 frames, 2 s of a full 1 Mbit/s bus
RAW_SETTLE = 0.1  # seconds at most between < ok > to < rawmode > and the first frame (see above)
DRAIN_LIMIT = 1 << 20  # bytes read from a reset connection's socket (a kernel holds ~200 kB)
DEFAULT_HOST = "127.0.0.1"
BUS_NAME = "can0"


def parse_address(text: str) -> Tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6; empty host: 127.0.0.1; port 0: any free one)."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"expected HOST:PORT (port 0..65535), got {text!r}")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    return host or DEFAULT_HOST, int(port)


def listen_error(exc: OSError) -> str:
    """Why a server could not listen, in one short phrase (create_server() appends the
    address to strerror; a resolver error has a negative errno)."""
    if exc.errno and exc.errno > 0:
        return os.strerror(exc.errno)
    return (exc.strerror or str(exc)).split(" (while attempting")[0]


def _to_frame(msg: can.Message) -> Optional[Frame]:
    if msg.is_fd:
        return None  # socketcand's fdframe is not in protocol.md; the simulator sends none
    try:
        return Frame(msg.arbitration_id, b"" if msg.is_remote_frame else bytes(msg.data),
                     extended=msg.is_extended_id, remote=msg.is_remote_frame,
                     error=msg.is_error_frame, dlc=msg.dlc if msg.is_remote_frame else -1)
    except SocketcandError:
        return None


def _drain(fd: int, limit: int = DRAIN_LIMIT) -> bytes:
    """What a lost connection's socket still holds, up to ``limit`` bytes (the fd is
    non-blocking: asyncio's). Stops at the end of the data, the reset or any error."""
    chunks: list[bytes] = []
    taken = 0
    while taken < limit:
        try:
            chunk = os.read(fd, min(65536, limit - taken))
        except OSError:  # BlockingIOError: nothing more; ConnectionResetError: the reset
            break
        if not chunk:
            break
        chunks.append(chunk)
        taken += len(chunk)
    return b"".join(chunks)


class _TakeAllProtocol(asyncio.StreamReaderProtocol):
    """asyncio's stream protocol, except that a connection lost with an error (a reset)
    first delivers what its socket still holds, then an end of stream (module docstring).

    asyncio closes the socket only after ``connection_lost`` returns
    (``_SelectorTransport._call_connection_lost``), so it can still be read here."""

    def __init__(self, reader: asyncio.StreamReader, connected: Any) -> None:
        super().__init__(reader, connected)
        self._reader = reader
        self._fd = -1

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        sock = transport.get_extra_info("socket")
        self._fd = sock.fileno() if sock is not None else -1
        super().connection_made(transport)

    def connection_lost(self, exc: Optional[Exception]) -> None:
        if exc is not None and self._fd >= 0:
            rest = _drain(self._fd)
            if rest:
                self._reader.feed_data(rest)
            exc = None  # the commands before the reset are read first, then the end
        super().connection_lost(exc)


class _Client:
    def __init__(self, writer: asyncio.StreamWriter, bus_name: str) -> None:
        self.transport = writer.transport
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.session = Session(bus_name)
        self.held: Optional[List[bytes]] = None  # frames held until its < ok > is read
        self.held_bytes = 0
        self.gone = False


class SocketcandServer:
    """A socketcand server for one python-can virtual ``channel`` (the simulator's)."""

    def __init__(self, channel: str, host: str = DEFAULT_HOST, port: int = 0, *,
                 bus_name: str = BUS_NAME, output_limit: int = OUTPUT_LIMIT,
                 settle: float = RAW_SETTLE, max_clients: int = MAX_CLIENTS) -> None:
        if isinstance(max_clients, bool) or not isinstance(max_clients, int) or max_clients < 1:
            raise ValueError(f"max_clients: must be a positive integer, not {max_clients!r}")
        self.max_clients = max_clients
        self.refused = 0  # connections refused by the cap
        self._refusals_logged = 0.0  # loop time of the last refusal log line
        self.channel = channel
        self.bus_name = bus_name
        self.output_limit = output_limit
        self.settle = settle
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        # Bound now, so that a port in use or a bad host is the caller's OSError.
        self._sock = socket.create_server((host, port), family=family)
        self.address: Tuple[str, int] = self._sock.getsockname()[:2]
        self._bus: Optional[can.BusABC] = None
        self._loop = asyncio.new_event_loop()
        self._clients: Set[_Client] = set()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._server: Optional[asyncio.AbstractServer] = None

    def start(self) -> "SocketcandServer":
        try:
            # preserve_timestamps: the simulated nodes see a client's frame with the
            # timestamp the other clients are sent.
            self._bus = can.Bus(interface="virtual", channel=self.channel,
                                receive_own_messages=False, preserve_timestamps=True)
            loop_thread = threading.Thread(target=self._loop.run_forever,
                                           name="socketcand-loop", daemon=True)
            loop_thread.start()
            self._threads.append(loop_thread)
            self._server = asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(10)
            reader = threading.Thread(target=self._read_bus, name="socketcand-bus", daemon=True)
            reader.start()
            self._threads.append(reader)
        except BaseException:
            self.close()
            raise
        log.info("CAN channel %s served over socketcand at %s:%d", self.channel, *self.address)
        return self

    async def _listen(self) -> asyncio.AbstractServer:
        """asyncio.start_server, with :class:`_TakeAllProtocol` for each connection."""
        loop = asyncio.get_running_loop()

        def protocol() -> _TakeAllProtocol:
            return _TakeAllProtocol(asyncio.StreamReader(loop=loop), self._serve)
        # asyncio's backlog of 100 would make a burst of connections (tests/
        # test_sim_bounded_servers.py opens 2,000) wait for the kernel's SYN retry, 1 s
        # and more each, once the queue is full: the kernel caps this at somaxconn.
        return await loop.create_server(protocol, sock=self._sock, backlog=LISTEN_BACKLOG)

    @property
    def url(self) -> str:
        host, port = self.address
        return f"{'[' + host + ']' if ':' in host else host}:{port}"

    # -- the simulated nodes' side ---------------------------------------------------------

    def _read_bus(self) -> None:
        """Every frame of the virtual channel goes to the dispatcher (clients or not: the
        channel's queue for this connection must not grow)."""
        bus = self._bus
        assert bus is not None
        while not self._stop.is_set():
            try:
                msg = bus.recv(0.1)
            except can.CanError:
                return  # shut down
            if msg is None:
                continue
            frame = _to_frame(msg)
            if frame is None:
                continue
            try:
                self._loop.call_soon_threadsafe(self._deliver, frame, msg.timestamp, None)
            except RuntimeError:  # the loop is closed: the server is closing
                return

    # -- the dispatcher (all on the loop thread) ----------------------------------------------

    def _deliver(self, frame: Frame, timestamp: float, source: Optional[_Client]) -> None:
        line = format_frame(frame, timestamp).encode("ascii")
        for client in list(self._clients):
            if client is not source and client.session.receives_frames:
                self._write(client, line, frame=True)

    def _from_client(self, client: _Client, frame: Frame) -> None:
        timestamp = time.time()
        msg = can.Message(timestamp=timestamp, arbitration_id=frame.can_id,
                          is_extended_id=frame.extended, is_remote_frame=frame.remote,
                          dlc=frame.dlc, data=frame.data)
        try:
            assert self._bus is not None
            self._bus.send(msg)
        except (can.CanError, AssertionError) as exc:
            self._write(client, error_reply(f"bus: {exc}").encode("ascii", "replace"))
            return
        self._deliver(frame, timestamp, client)

    def _write(self, client: _Client, data: bytes, frame: bool = False) -> None:
        if client.gone or client.transport.is_closing():
            return  # a client whose connection is lost may still have commands to run
        if frame and client.held is not None:
            client.held.append(data)
            client.held_bytes += len(data)
            waiting = client.held_bytes
        else:
            client.transport.write(data)
            waiting = client.transport.get_write_buffer_size()
        if waiting > self.output_limit:
            log.warning("socketcand client %s disconnected: it did not read (%d bytes waiting "
                        "for it)", client.peer, waiting)
            self._drop(client)

    def _release(self, client: _Client) -> None:
        """The client has read its < ok > (or RAW_SETTLE has passed): send what was held."""
        held, client.held, client.held_bytes = client.held, None, 0
        if held:
            self._write(client, b"".join(held))

    def _release_held(self, client: _Client) -> None:
        if client.held is not None:  # not released yet by the client's next command
            self._release(client)

    def _drop(self, client: _Client) -> None:
        client.gone = True
        self._clients.discard(client)
        client.transport.abort()

    # -- one client --------------------------------------------------------------------------

    def _refuse(self, writer: asyncio.StreamWriter) -> None:
        """One connection over the cap: told why in the place of ``< hi >``, then closed."""
        self.refused += 1
        text = error_reply(f"too many clients: {self.max_clients} connected, the server's cap")
        writer.write(text.encode("ascii"))
        writer.close()  # FIN after the line, not RST
        now = self._loop.time()
        if now - self._refusals_logged >= 1.0:  # a burst of refusals is one line a second
            self._refusals_logged = now
            log.warning("socketcand: refused %s: %d clients connected (the cap); %d refused "
                        "so far", writer.get_extra_info("peername"), self.max_clients,
                        self.refused)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._clients) >= self.max_clients:
            self._refuse(writer)
            return
        client = _Client(writer, self.bus_name)
        self._clients.add(client)
        log.info("socketcand client %s connected", client.peer)
        commands = CommandReader()
        self._write(client, HI.encode())
        try:
            while not client.gone:
                data = await reader.read(READ_SIZE)
                if not data:
                    break
                if client.held is not None and client.session.receives_frames:
                    self._release(client)  # it speaks after < rawmode >: it has read the < ok >
                for text in commands.feed(data):
                    if not self._handle(client, text):
                        # Its last replies go out, then the connection closes (FIN, not RST).
                        client.gone = True
                        self._clients.discard(client)
                        client.transport.close()
                        break
                # Its turn is over: a read returns at once while bytes are buffered, so
                # without this a flooding client would hold the loop (module docstring).
                await asyncio.sleep(0)
        except CommandTooLong as exc:
            log.warning("socketcand client %s disconnected: %s", client.peer, exc)
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # The server is closing. Ending normally: asyncio's stream callback asks a
            # finished connection task for its exception, which re-raises a cancellation.
            pass
        finally:
            if not client.gone:
                self._drop(client)
            log.info("socketcand client %s gone", client.peer)

    def _handle(self, client: _Client, text: str) -> bool:
        """Carry out one command; False when the connection ends with it."""
        outcome = client.session.handle(text)
        for reply in outcome.replies:
            self._write(client, reply.encode("ascii", "replace"))
        if outcome.entered_raw:
            client.held = []
            self._loop.call_later(self.settle, self._release_held, client)
        if outcome.frame is not None:
            self._from_client(client, outcome.frame)
        return not outcome.close

    # -- closing -------------------------------------------------------------------------------

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
        for client in list(self._clients):
            self._drop(client)  # its connection task sees the end of its stream and returns
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=1.0)
            for task in pending:
                task.cancel()

    def close(self, timeout: float = 2.0) -> None:
        """Stop serving: clients disconnected, threads joined (each within ``timeout``)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._loop.is_running():
            try:
                asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(timeout)
            except Exception as exc:  # a timeout: the loop is stopped below all the same
                log.warning("socketcand server: clients not closed within %.1f s (%s)",
                            timeout, exc)
            self._loop.call_soon_threadsafe(self._loop.stop)
        for thread in self._threads:
            thread.join(timeout)
            if thread.is_alive():
                log.warning("socketcand server: thread %s did not stop", thread.name)
        if not self._loop.is_running():
            self._loop.close()
        self._sock.close()
        if self._bus is not None:
            self._bus.shutdown()

    def __enter__(self) -> "SocketcandServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["BUS_NAME", "DEFAULT_HOST", "DRAIN_LIMIT", "MAX_CLIENTS", "OUTPUT_LIMIT", "READ_SIZE",
           "RAW_SETTLE", "SocketcandServer",
           "listen_error", "parse_address"]
