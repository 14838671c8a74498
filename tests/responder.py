"""A scripted device for integration tests over real sockets and pseudo-terminals.

It answers whole request frames it knows with fixed answer frames, byte for
byte. Both are built by :func:`tests.reference.reference_frame` (the guide's
CRC and stuffing written independently of our codec), never by our encoder.
A request mapped to None gets no answer (a silent device).
"""
from __future__ import annotations

import os
import select
import socket
import struct
import threading
import tty
from typing import Callable, Optional

from tests.reference import reference_frame

Script = dict[bytes, Optional[bytes]]


def _addr(node: int, index: int, subindex: int) -> bytes:
    return struct.pack("<BHB", node, index, subindex)


def answer(code: int, rest: bytes = b"") -> bytes:
    data = struct.pack("<I", code) + rest
    return reference_frame(0x00, data + b"\x00" * (len(data) % 2))


def read_request(node: int, index: int, subindex: int) -> bytes:
    return reference_frame(0x60, _addr(node, index, subindex))


def write_request(node: int, index: int, subindex: int, data: bytes) -> bytes:
    return reference_frame(0x68, _addr(node, index, subindex) + data.ljust(4, b"\x00"))


def read_pair(node: int, index: int, subindex: int, value: bytes, code: int = 0) -> tuple[bytes, bytes]:
    """ReadObject (2.1.1.1) and its answer: error code and 4 data bytes."""
    return read_request(node, index, subindex), answer(code, value.ljust(4, b"\x00"))


def write_pair(node: int, index: int, subindex: int, data: bytes, code: int = 0) -> tuple[bytes, bytes]:
    """WriteObject (2.1.2.1) and its answer: the error code alone."""
    return write_request(node, index, subindex, data), answer(code)


def segmented_read_pairs(node: int, index: int, subindex: int, data: bytes) -> list[tuple[bytes, bytes]]:
    """InitiateSegmentedRead with an empty first answer, then one SegmentRead (2.1.1.2-3)."""
    return [
        (reference_frame(0x81, _addr(node, index, subindex)),
         answer(0, struct.pack("<IB", len(data), 0))),
        (reference_frame(0x62, b"\x00\x00"), answer(0, bytes((len(data), 0x02)) + data)),
    ]


class Responder:
    """Serves a :data:`Script` on one byte stream. ``delay`` holds each answer back;
    bytes arriving meanwhile count as ``interleaved`` (a second request in flight)."""

    def __init__(self, script: Script, *, delay: float = 0.0) -> None:
        self.script = dict(script)
        self.delay = delay
        self.requests = 0
        self.interleaved = 0
        self.unexpected = bytearray()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def _process(self, buf: bytearray, readable: Callable[[float], bool],
                 send: Callable[[bytes], None]) -> None:
        script = self.script
        while buf:
            whole = bytes(buf)
            request = whole if whole in script else next(
                (r for r in script if whole.startswith(r)), None)
            if request is None:
                if any(r.startswith(whole) for r in script):
                    return  # a request still arriving
                self.unexpected.append(buf.pop(0))
                continue
            del buf[:len(request)]
            self.requests += 1
            if self.delay and readable(self.delay):
                self.interleaved += 1
            reply = script[request]
            if reply is not None:
                send(reply)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)

    def __enter__(self) -> "Responder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class SocketResponder(Responder):
    """Listens on 127.0.0.1 (``url`` is ``socket://127.0.0.1:PORT``) and serves one
    connection at a time, for as many connections as come."""

    def __init__(self, script: Script, **kw: float) -> None:
        super().__init__(script, **kw)
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self.connections = 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with self._server:
            while not self._stop.is_set():
                if not select.select([self._server], [], [], 0.05)[0]:
                    continue
                conn, _ = self._server.accept()
                self.connections += 1
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with conn:
                    self._serve(conn)

    def _serve(self, conn: socket.socket) -> None:
        buf = bytearray()
        readable = lambda t: bool(select.select([conn], [], [], t)[0])  # noqa: E731
        while not self._stop.is_set():
            if not readable(0.05):
                continue
            try:
                data = conn.recv(4096)
            except OSError:
                return
            if not data:
                return
            buf += data
            self._process(buf, readable, conn.sendall)


class PtyResponder(Responder):
    """Serves the master side of a pseudo-terminal; ``path`` is the slave (``/dev/pts/N``),
    which the code under test opens like a real serial port."""

    def __init__(self, script: Script, **kw: float) -> None:
        super().__init__(script, **kw)
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing, before anyone opens it
        self.path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = bytearray()
        fd = self.master
        readable = lambda t: bool(select.select([fd], [], [], t)[0])  # noqa: E731
        send = lambda b: os.write(fd, b)  # noqa: E731
        while not self._stop.is_set():
            if not readable(0.05):
                continue
            try:
                data = os.read(fd, 4096)
            except OSError:
                return
            buf += data
            self._process(buf, readable, send)

    def stop(self) -> None:
        super().stop()
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def hang_up(self) -> None:
        """Close the master side, as when a USB-serial adapter is pulled out."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        os.close(self.master)
        os.close(self._slave)
        self.master = self._slave = -1
