"""The transparent proxy under ``epos-link monitor``: an application on one side,
the device on the other, every byte copied unchanged.

::

    application --(pty or TCP)--> [up thread]   --> device transport
    application <-(pty or TCP)--- [down thread] <-- device transport
                                       |
                         (time, direction, bytes) into a bounded queue,
                         never waiting: the display never delays traffic

Policy:

* Each direction has its own thread that reads with a short timeout, appends
  the chunk to the queue (non-blocking, so an answer is always queued before
  the application can react to it) and writes it to the other side. No
  request is ever made up, held back, reordered or dropped by the proxy, and
  the device's input is never flushed (no ``reset_input``).
* The queue is bounded (:data:`QUEUE_LIMIT` chunks). If the display falls that
  far behind, chunks are left out of the display (never out of the traffic)
  and counted, and the display says how many bytes it missed.
* The application side is a pseudo-terminal (the application opens its path
  as a serial port) or a TCP listener that serves one client at a time; bytes
  from the device while no client is connected are shown and dropped.
* A link failure on the device side ends the proxy; the error is kept for the
  caller to report. Every wait has a timeout, so :meth:`Proxy.stop` takes
  effect within :data:`POLL` seconds.
"""
from __future__ import annotations

import os
import queue
import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, Protocol, Union

from ..transports.base import Transport

POLL = 0.05
QUEUE_LIMIT = 65536
READ_SIZE = 4096


@dataclass(frozen=True)
class Chunk:
    time: float          # clock() when the read returned
    direction: str       # "TX" application to device, "RX" device to application
    data: bytes


@dataclass(frozen=True)
class Note:
    time: float
    text: str


Item = Union[Chunk, Note]


class Front(Protocol):
    where: str

    def read(self, timeout: float) -> bytes: ...

    def write(self, data: bytes) -> bool: ...

    def close(self) -> None: ...


class PtyFront:
    """A pseudo-terminal in raw mode; the application opens :attr:`where`."""

    def __init__(self) -> None:
        import termios
        import tty

        self.master, self.slave = os.openpty()
        for fd in (self.master, self.slave):
            tty.setraw(fd, termios.TCSANOW)
        self.where = os.ttyname(self.slave)

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout)
        if not ready:
            return b""
        try:
            return os.read(self.master, READ_SIZE)
        except OSError:  # EIO while no process has the slave open
            time.sleep(timeout)
            return b""

    def write(self, data: bytes) -> bool:
        view = memoryview(data)
        try:
            while view:
                n = os.write(self.master, view)
                view = view[n:]
        except OSError:
            return False
        return True

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpFront:
    """A TCP listener serving one application at a time (``socket://HOST:PORT``)."""

    def __init__(self, host: str, port: int) -> None:
        self.sock = socket.create_server((host, port))
        self.sock.settimeout(POLL)
        self.host, self.port = self.sock.getsockname()[:2]
        self.where = f"socket://{self.host}:{self.port}"
        self._conn: Optional[socket.socket] = None
        self._lock = threading.Lock()
        self.notes: "queue.Queue[str]" = queue.Queue(maxsize=64)

    def _note(self, text: str) -> None:
        try:
            self.notes.put_nowait(text)
        except queue.Full:
            pass

    def _drop(self, why: str) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()
            self._note(f"application disconnected ({why})")

    def read(self, timeout: float) -> bytes:
        conn = self._conn
        if conn is None:
            try:
                conn, peer = self.sock.accept()
            except (socket.timeout, BlockingIOError):
                return b""
            except OSError:
                time.sleep(timeout)
                return b""
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conn = conn
            self._note(f"application connected from {peer[0]}:{peer[1]}")
            return b""
        try:
            ready, _, _ = select.select([conn], [], [], timeout)
            if not ready:
                return b""
            data = conn.recv(READ_SIZE)
        except (OSError, ValueError) as exc:
            self._drop(str(exc))
            return b""
        if not data:
            self._drop("closed")
        return data

    def write(self, data: bytes) -> bool:
        with self._lock:
            conn = self._conn
            if conn is None:
                return False
            try:
                conn.sendall(data)
            except OSError:
                pass
            else:
                return True
        self._drop("send failed")
        return False

    def close(self) -> None:
        self._drop("monitor stopped")
        try:
            self.sock.close()
        except OSError:
            pass


class Proxy:
    """Copies bytes both ways between ``front`` and ``device``; :attr:`items` gets copies."""

    def __init__(self, front: Front, device: Transport, *, clock: Callable[[], float] = time.monotonic,
                 queue_limit: int = QUEUE_LIMIT) -> None:
        self.front = front
        self.device = device
        self.clock = clock
        self.items: "queue.Queue[Item]" = queue.Queue(maxsize=queue_limit)
        self.missed_bytes = 0          # left out of the display (never out of the traffic)
        self.unsent_bytes = 0          # from the device while no application was connected
        self.error: Optional[BaseException] = None
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._up, name="monitor-up", daemon=True),
                         threading.Thread(target=self._down, name="monitor-down", daemon=True)]

    def start(self) -> "Proxy":
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            if t.is_alive() and t is not threading.current_thread():
                t.join(2)

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def _offer(self, item: Item) -> None:
        try:
            self.items.put_nowait(item)
        except queue.Full:
            if isinstance(item, Chunk):
                self.missed_bytes += len(item.data)

    def _notes(self) -> None:
        notes = getattr(self.front, "notes", None)
        while notes is not None and not notes.empty():
            self._offer(Note(self.clock(), notes.get_nowait()))

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc
        self._stop.set()

    def _up(self) -> None:
        read, write = self.front.read, self.device.write
        try:
            while not self._stop.is_set():
                data = read(POLL)
                self._notes()
                if not data:
                    continue
                # Queued before the copy so the display keeps causal order (an
                # answer is never shown before its request); queuing is a
                # non-blocking append, a few microseconds, and never waits.
                self._offer(Chunk(self.clock(), "TX", data))
                write(data)
        except Exception as exc:  # a device link failure ends the proxy
            self._fail(exc)

    def _down(self) -> None:
        read, write = self.device.read, self.front.write
        try:
            while not self._stop.is_set():
                data = read(READ_SIZE, POLL)
                if not data:
                    continue
                self._offer(Chunk(self.clock(), "RX", data))
                if not write(data):
                    self.unsent_bytes += len(data)
        except Exception as exc:
            self._fail(exc)


__all__ = ["Chunk", "Note", "Proxy", "PtyFront", "TcpFront", "POLL", "QUEUE_LIMIT"]
