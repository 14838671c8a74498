"""Serve simulated EPOS4 drives as EtherCAT slaves on a network interface (I/O).

A raw ``AF_PACKET`` socket bound to the interface for EtherType 0x88A4; one
thread receives each frame, runs it through the :class:`~.segment.Segment`
(the pure core) and sends the processed frame back out of the same interface,
as the last slave of a line returns it to the master. On a veth pair the
master opens the other end. Between frames the thread wakes every
``TICK`` seconds so the process-data watchdog expires without traffic.

Needs root or CAP_NET_RAW; :func:`open_socket` raises ``PermissionError`` or
``OSError`` (no such interface) for the CLI to report.

``quirks`` make single slaves differ (:mod:`.quirks`); ``events`` (a path)
receives one JSON object per line for what each drive did in every cycle
(:class:`~.drive_app.EthercatDrive`, ``on_event``), flushed at once, so that a
test in another process sees every cycle of a drive, not only what a master
polls; each with ``t`` (the drives' clock) and ``wall`` (``time.time()``), and an
event that a frame caused with ``rx``: the system clock when the frame arrived, as the
kernel stamped it (``SO_TIMESTAMP``), where this thread may have taken it much later on
a loaded machine. A real ESC takes a frame's outputs as the frame passes, so ``rx`` is
when the drive got them; set-points against ``rx`` show the stream as the master sent it.
"""
from __future__ import annotations

import json
import logging
import select
import socket
import struct
import threading
import time
from typing import IO, Any, Callable, Dict, List, Mapping, Optional, Tuple

from .drive_app import EthercatDrive
from .frame import ETHERTYPE
from .quirks import Quirks
from .segment import Segment

__all__ = ["EthercatServer", "open_socket", "TICK"]

TICK = 0.005
_log = logging.getLogger(__name__)
# Linux's SO_TIMESTAMP (= SCM_TIMESTAMP; asm-generic/socket.h, x86 and arm alike; the
# socket module does not name it): each frame comes with a struct timeval of its arrival.
SO_TIMESTAMP = 29
_TIMEVAL = struct.Struct("@ll")


def open_socket(interface: str) -> socket.socket:
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
    try:
        sock.bind((interface, ETHERTYPE))
    except OSError:
        sock.close()
        raise
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMP, 1)
    except OSError:  # not Linux: events carry no "rx"
        pass
    return sock


def arrival(ancdata: List[Tuple[int, int, bytes]]) -> Optional[float]:
    """The kernel's arrival stamp of a frame (system clock, s), or None without one."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMP and len(data) >= _TIMEVAL.size:
            sec, usec = _TIMEVAL.unpack_from(data)
            return sec + usec / 1e6
    return None


class EthercatServer:
    """``slaves`` simulated drives in a line on ``interface``; :meth:`close` stops it."""

    def __init__(self, interface: str, slaves: int = 1,
                 clock: Callable[[], float] = time.monotonic, *,
                 quirks: Optional[Mapping[int, Quirks]] = None,
                 events: Optional[str] = None) -> None:
        if not 1 <= slaves <= 64:
            raise ValueError("1..64 slaves")
        self.interface = interface
        self.clock = clock
        self._events: Optional[IO[str]] = open(events, "a", encoding="utf-8") if events else None
        record = self._record if self._events is not None else None
        self.drives = [EthercatDrive(n, clock, (quirks or {}).get(n, Quirks()), record)
                       for n in range(1, slaves + 1)]
        self.segment = Segment([d.slave for d in self.drives])
        self.lock = threading.Lock()  # the segment: this thread against tests looking in
        self._sock: Optional[socket.socket] = open_socket(interface)
        self._stop = threading.Event()
        self._rx: Optional[float] = None  # the arrival of the frame being handled
        self._thread = threading.Thread(target=self._run, name=f"ethercat-{interface}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([sock], [], [], TICK)
                if not readable:
                    with self.lock:
                        self.segment.tick(self.clock())
                    continue
                frame, ancdata, _, _ = sock.recvmsg(4096, socket.CMSG_SPACE(_TIMEVAL.size))
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(TICK)  # the interface went down: wait for it or for close()
                continue
            try:
                with self.lock:
                    self._rx = arrival(ancdata)
                    try:
                        reply = self.segment.handle(frame, self.clock())
                    finally:
                        self._rx = None
            except Exception:  # a bug must not end the line: drop the frame, as a CRC error would
                _log.exception("EtherCAT frame dropped")
                continue
            if reply is not None:
                try:
                    sock.send(reply)
                except OSError:
                    pass  # the link is gone; the master will time out, as on a cut cable

    def _record(self, event: Dict[str, Any]) -> None:
        events = self._events
        if events is not None:
            # "wall": the system clock as well, the one a master's log lines carry, so that
            # a test can tell the frames a master sent before a line of its log from those
            # it sent after (issue 31: what a bridge did once it had an input).
            event = {**event, "wall": round(time.time(), 6)}
            rx = self._rx
            if rx is not None and threading.current_thread() is self._thread:
                event["rx"] = round(rx, 6)
            events.write(json.dumps(event, separators=(",", ":")) + "\n")
            events.flush()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._events is not None:
            self._events.close()
            self._events = None

    def __enter__(self) -> "EthercatServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
