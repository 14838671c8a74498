"""Serving the simulated EPOS4 over a pseudo-terminal or TCP, with link faults.

The device logic is pure (:mod:`.device`); this module adds what a real link
has: timing (a baud rate, the device's frame timeout of guide 2.2.7) and
faults (dropped, corrupted or delayed reply bytes, silence, disconnects).
One host at a time, like the real device.

Pacing (``--baud``): a UART sends one byte every 10 bit times (8N1, guide
2.2.6). A request is answered once its own bytes would have arrived
(``start`` = when it was read + its length in byte times), and each answer
byte is written when its stop bit would have left the wire: byte ``i`` at
``start + (i + 1) * 10 / baud``, on an absolute schedule, so a late wake-up is
caught up (every byte already due goes out at once) and does not accumulate.
The last byte of an answer is timed by waiting on the clock for its final
stretch, so the answer ends on time and the link runs at the wire's rate.
On Linux a sleeping thread wakes up to 50 us late by default (its timer
slack, prctl(2) PR_SET_TIMERSLACK), more on a loaded machine: the link thread
asks for 1 us (:func:`precise_timers`), and then waits on the clock for the
last 100 us only (``PRECISE_SPIN``), instead of 300 us (``SPIN``). Measured on
the 2-core development VM: 200 us sleeps overshot by 65 us median, 121 us p99
with the default slack; 8 us and 20 us with 1 us. That spin was most of the
simulator's CPU time per request, taken from the host it serves.
The clock, the sleep and that spin are injectable for tests.

Frame timeout (guide 2.2.7, Table 2-4): a partial frame is dropped once no
byte has come for the frame timeout, "RS232 Frame Timeout" 2005h or "USB
Frame Timeout" 2006h, UNSIGNED16 in ms, default 500, and "may be changed by
writing to the Object Dictionary". The link asks the device for the value
of its interface's object at each check (:meth:`Device.frame_timeout`), so
a write takes effect at once; a device without that method, or
``LinkOptions.frame_timeout`` set, gets the fixed value. **Chosen**: 0 ms
is taken literally (any pause drops a partial frame).
"""
from __future__ import annotations

import logging
import math
import os
import random
import select
import socket
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

from ..capture import CaptureWriter

log = logging.getLogger(__name__)

BITS_PER_BYTE = 10  # 8N1: start, 8 data, stop (guide 2.2.6)
SPIN = 0.0003  # see LinkServer._wait_until: longer than a typical late wake-up
PRECISE_SPIN = 0.0001  # the same with a 1 us timer slack (precise_timers)
_PR_SET_TIMERSLACK = 29  # linux/prctl.h


def precise_timers() -> bool:
    """Ask Linux for a 1 us timer slack for the calling thread (prctl(2)); False
    where that cannot be done (another system, no libc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


RS232_FRAME_TIMEOUT = 0x2005  # guide 2.2.7, Table 2-4: ms, default 500
USB_FRAME_TIMEOUT = 0x2006
DEFAULT_FRAME_TIMEOUT = 0.5  # s, the guide's default for both
POLL = 0.05  # s, longest wait for host bytes before the frame timeout is checked


class Device(Protocol):
    def receive(self, data: bytes) -> list[bytes]: ...

    def reset(self) -> None: ...


def device_frame_timeout(device: object, index: int) -> float:
    """The device's frame timeout in seconds from ``index`` (2005h/2006h), if it has one."""
    ask = getattr(device, "frame_timeout", None)
    if ask is None:
        return DEFAULT_FRAME_TIMEOUT
    return float(ask(index))


@dataclass
class LinkOptions:
    """Link speed and faults. Rates are probabilities per reply byte (0..1)."""

    baud: Optional[int] = None      # None: instant; else replies take wire time
    drop: float = 0.0               # drop a reply byte
    corrupt: float = 0.0            # flip bits of a reply byte
    delay: float = 0.0              # seconds before each reply
    silent: bool = False            # read requests, never answer
    disconnect_after: Optional[int] = None  # close the link after N replies
    frame_timeout: Optional[float] = None  # s; None: the device's 2005h/2006h (guide 2.2.7)
    seed: Optional[int] = None

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a probability between 0 and 1, got {value}")
        if self.baud is not None and self.baud <= 0:
            raise ValueError("baud must be positive")
        if not math.isfinite(self.delay) or self.delay < 0:
            raise ValueError("delay must be a finite, non-negative number of seconds")
        ft = self.frame_timeout
        if ft is not None and (not math.isfinite(ft) or ft < 0):
            raise ValueError("frame_timeout must be a finite, non-negative number of seconds")


class FaultInjector:
    """Applies drop/corrupt faults to reply bytes; counts what it did."""

    def __init__(self, options: LinkOptions) -> None:
        self.options = options
        self.rng = random.Random(options.seed)
        self.dropped = 0
        self.corrupted = 0

    def apply(self, reply: bytes) -> bytes:
        drop, corrupt = self.options.drop, self.options.corrupt
        if not drop and not corrupt:
            return reply
        out = bytearray()
        rnd = self.rng.random
        for b in reply:
            if drop and rnd() < drop:
                self.dropped += 1
                continue
            if corrupt and rnd() < corrupt:
                b ^= self.rng.randrange(1, 256)
                self.corrupted += 1
            out.append(b)
        return bytes(out)


class LinkServer:
    """Runs the request/answer loop over one byte stream (fd or socket)."""

    def __init__(self, device: Device, options: Optional[LinkOptions] = None,
                 trace: Optional[CaptureWriter] = None, *,
                 clock: Callable[[], float] = time.perf_counter,
                 sleep: Callable[[float], None] = time.sleep, spin: float = SPIN,
                 frame_timeout_object: int = RS232_FRAME_TIMEOUT) -> None:
        self.device = device
        self.options = options or LinkOptions()
        self.frame_timeout_object = frame_timeout_object  # 2005h (serial) or 2006h (USB)
        self._clock = clock
        self._sleep = sleep
        self.spin = spin  # seconds waited on the clock before an answer's last byte
        self._wire_free = float("-inf")  # when the device's transmitter is idle again
        self.faults = FaultInjector(self.options)
        self.replies = 0
        # Records the link as the host sees it: TX host to device, RX as sent (faults included).
        self.trace = trace
        self._t0 = time.monotonic()
        self._stop = threading.Event()

    def _record(self, direction: str, data: bytes) -> None:
        if self.trace is not None and data:
            self.trace.write(time.monotonic() - self._t0, direction, data)

    def use_precise_timers(self) -> None:
        """Called on the thread that serves: a short spin if its timers are precise."""
        if self.options.baud and self.spin == SPIN and precise_timers():
            self.spin = PRECISE_SPIN

    def stop(self) -> None:
        self._stop.set()

    def frame_timeout(self) -> float:
        """Seconds of silence after which a partial frame is dropped (guide 2.2.7)."""
        fixed = self.options.frame_timeout
        if fixed is not None:
            return fixed
        return device_frame_timeout(self.device, self.frame_timeout_object)

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def _send(self, write: Callable[[bytes], None], reply: bytes, not_before: float) -> None:
        """Write ``reply``; with a baud rate, byte i once its stop bit is past ``not_before``."""
        opts = self.options
        if opts.delay:
            self._sleep(opts.delay)
        reply = self.faults.apply(reply)
        self._record("RX", reply)
        if not reply:
            return
        if not opts.baud:
            write(reply)
            return
        per_byte = BITS_PER_BYTE / opts.baud
        start = max(not_before, self._clock()) if opts.delay else not_before
        sent = 0
        while sent < len(reply):
            last = len(reply) - sent == 1
            self._wait_until(start + (sent + 1) * per_byte, precise=last)
            # Every byte whose stop bit is past by now: one, or more after a late wake-up.
            done = int((self._clock() - start) / per_byte)
            upto = min(len(reply), max(sent + 1, done))
            write(reply[sent:upto])
            sent = upto
        self._wire_free = start + len(reply) * per_byte

    def _wait_until(self, due: float, *, precise: bool) -> None:
        """Sleep until ``due``; the last byte of an answer is timed to the microsecond.

        A sleep wakes up late by a scheduler tick; that lateness would add to
        every answer. So the last stretch before an answer's last byte (at most
        ``spin`` seconds) is waited in a loop on the clock instead.
        """
        while True:
            left = due - self._clock()
            if left <= 0:
                return
            if precise and left <= self.spin:
                while self._clock() < due:
                    pass
                return
            self._sleep(left - self.spin if precise else left)

    def serve_stream(self, read: Callable[[float], Optional[bytes]],
                     write: Callable[[bytes], None]) -> None:
        """Serve until stopped, the peer closes (read returns None) or a disconnect fault."""
        opts = self.options
        last_rx = self._clock()
        self.device.reset()
        while not self._stop.is_set():
            timeout = self.frame_timeout()
            data = read(min(POLL, max(timeout, 0.001)))
            now = self._clock()
            if data is None:
                return
            if not data:
                if now - last_rx > timeout:
                    self.device.reset()  # a partial frame older than the frame timeout
                    last_rx = now
                continue
            # The request itself took wire time to arrive: its last byte is in at
            # ``arrived``, and the answer starts then, or when the wire is free.
            arrived = self._clock()
            if opts.baud:
                arrived += len(data) * BITS_PER_BYTE / opts.baud
            not_before = max(arrived, self._wire_free)
            last_rx = now
            self._record("TX", data)
            for reply in self.device.receive(data):
                if opts.silent:
                    continue
                self._send(write, reply, not_before)
                not_before = max(not_before, self._wire_free)
                self.replies += 1
                if opts.disconnect_after is not None and self.replies >= opts.disconnect_after:
                    return


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
        self._thread = threading.Thread(target=self._run, name="epos-sim-pty", daemon=True)

    def start(self) -> "PtyLink":
        self._thread.start()
        return self

    def _read(self, timeout: float) -> Optional[bytes]:
        ready, _, _ = select.select([self.master], [], [], timeout)
        if not ready:
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
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(None)

                def read(timeout: float, conn: socket.socket = conn) -> Optional[bytes]:
                    ready, _, _ = select.select([conn, self.sock], [], [], timeout)
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
