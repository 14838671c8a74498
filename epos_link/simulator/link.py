"""Serving the simulated EPOS4 over a pseudo-terminal or TCP, with link faults.

One host at a time, like the real device. Both endpoints run the same
request/answer loop, :class:`~.link_server.LinkServer`, which adds what a real
link has: timing (a baud rate, the device's frame timeout of guide 2.2.7) and
faults (dropped, corrupted or delayed reply bytes, silence, disconnects).
Pacing and the frame timeout are described in :mod:`.link_server`'s
docstring; its names (``LinkServer``, ``LinkOptions``, ``FaultInjector``,
the constants, ...) are re-exported here, where they were defined before.

Waiting for bytes uses :mod:`selectors` (epoll on Linux), never ``select()``:
``select()`` refuses descriptors of 1024 and above (FD_SETSIZE), which a
simulator serving many socketcand clients in the same process reaches, and a
link thread that raised there would stop answering for good (issue 35).
"""
from __future__ import annotations

import logging
import os
import selectors
import socket
import threading
import time
from typing import Optional

from ..capture import CaptureWriter
from .link_server import (
    BITS_PER_BYTE,
    DEFAULT_FRAME_TIMEOUT,
    POLL,
    PRECISE_SPIN,
    RS232_FRAME_TIMEOUT,
    SPIN,
    USB_FRAME_TIMEOUT,
    Device,
    FaultInjector,
    LinkOptions,
    LinkServer,
    device_frame_timeout,
    precise_timers,
)

__all__ = [
    "PtyLink",
    "TcpLink",
    # From link_server, importable here as before the split.
    "BITS_PER_BYTE",
    "DEFAULT_FRAME_TIMEOUT",
    "POLL",
    "PRECISE_SPIN",
    "RS232_FRAME_TIMEOUT",
    "SPIN",
    "USB_FRAME_TIMEOUT",
    "Device",
    "FaultInjector",
    "LinkOptions",
    "LinkServer",
    "device_frame_timeout",
    "precise_timers",
]

log = logging.getLogger(__name__)


def _raw_tty(fd: int) -> None:
    import termios
    import tty

    tty.setraw(fd, termios.TCSANOW)


class PtyLink:
    """A pseudo-terminal: the host opens :attr:`path` like a serial port."""

    def __init__(self, device: Device, options: Optional[LinkOptions] = None,
                 trace: Optional[CaptureWriter] = None) -> None:
        self.server = LinkServer(device, options, trace)
        self.master, self.slave = os.openpty()
        _raw_tty(self.slave)
        _raw_tty(self.master)
        self.path = os.ttyname(self.slave)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self.master, selectors.EVENT_READ)
        self._thread = threading.Thread(target=self._run, name="epos-sim-pty", daemon=True)

    def start(self) -> "PtyLink":
        self._thread.start()
        return self

    def _read(self, timeout: float) -> Optional[bytes]:
        if not self._selector.select(timeout):
            return b""
        try:
            return os.read(self.master, 4096)
        except OSError:  # EIO: no process has the slave open right now
            time.sleep(timeout)
            return b""

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.master, view)
            view = view[n:]

    def _run(self) -> None:
        self.server.use_precise_timers()
        while not self.server.stopped:
            self.server.serve_stream(self._read, self._write)
            if self.server.options.disconnect_after is not None:
                return  # a pty cannot be "unplugged" and replugged: stop serving

    def close(self) -> None:
        self.server.stop()
        if self._thread.is_alive():
            self._thread.join(2)
        self._selector.close()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpLink:
    """A TCP listener, one host at a time: reach it with ``socket://HOST:PORT``.

    A second host while one is served is told so in one line and closed
    (:meth:`_refuse`), instead of waiting in the listen backlog unanswered.
    A host that has gone is noticed before a new one is judged: its end of
    stream is read first, so commands run one after the other (each closing
    its connection as the next connects) are all served, never refused. (On
    one machine a closed connection's end of stream is queued before the next
    command can connect.)
    """

    # What a second host reads before its connection is closed. Not a frame (no
    # DLE STX), so a MAXON SERIAL V2 client discards it as junk and then sees the
    # connection closed; a person with nc or telnet reads it.
    BUSY_MESSAGE = (b"epos-link sim: busy: another host is connected; this simulated EPOS4 "
                    b"serves one host at a time\r\n")

    def __init__(self, device: Device, options: Optional[LinkOptions] = None,
                 host: str = "127.0.0.1", port: int = 0,
                 trace: Optional[CaptureWriter] = None) -> None:
        self.server = LinkServer(device, options, trace)
        self.sock = socket.create_server((host, port))
        self.sock.settimeout(0.1)
        self.host, self.port = self.sock.getsockname()[:2]
        self.url = f"socket://{self.host}:{self.port}"
        self._thread = threading.Thread(target=self._run, name="epos-sim-tcp", daemon=True)

    def start(self) -> "TcpLink":
        self._thread.start()
        return self

    def _run(self) -> None:
        self.server.use_precise_timers()
        while not self.server.stopped:
            try:
                conn, _ = self.sock.accept()
            except (socket.timeout, BlockingIOError):
                continue
            except OSError:
                return
            with conn, selectors.DefaultSelector() as selector:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(None)
                selector.register(conn, selectors.EVENT_READ)
                selector.register(self.sock, selectors.EVENT_READ)

                def read(timeout: float, conn: socket.socket = conn,
                         selector: selectors.BaseSelector = selector) -> Optional[bytes]:
                    ready = {key.fileobj for key, _ in selector.select(timeout)}
                    if conn not in ready:
                        if self.sock in ready:
                            self._refuse()  # this host is still connected
                        return b""
                    # This host first: its end of stream (it has gone, perhaps while a
                    # request kept the device busy) lets a waiting new host in.
                    try:
                        data = conn.recv(4096)
                    except OSError:
                        return None
                    return data or None  # None: the host has gone; the next one is accepted

                try:
                    self.server.serve_stream(read, conn.sendall)
                except OSError as exc:
                    log.info("host connection ended: %s", exc)
                self.server.replies = 0

    def _refuse(self) -> None:
        """A second host while one is served: told so in one line, then closed.

        Like the device, the link serves one host at a time: two hosts' frames
        would interleave in one receive buffer. Without this, the second
        connection would wait in the listen backlog, never answered.
        """
        try:
            other, peer = self.sock.accept()
        except OSError:
            return
        with other:
            log.warning("refused a second host %s:%s while one is connected (one host at a time)",
                        *peer[:2])
            try:
                other.sendall(self.BUSY_MESSAGE)
            except OSError:
                pass

    def close(self) -> None:
        self.server.stop()
        try:
            self.sock.close()
        except OSError:
            pass
        if self._thread.is_alive():
            self._thread.join(2)
