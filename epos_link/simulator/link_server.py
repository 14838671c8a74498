"""The simulated EPOS4's request/answer loop over one byte stream, as a real link runs it.

The device logic is pure (:mod:`.device`); :class:`LinkServer` adds what a
real link has: timing (a baud rate, the device's frame timeout of guide
2.2.7) and faults (dropped, corrupted or delayed reply bytes, silence,
disconnects). The endpoints that a host opens, a pseudo-terminal or a TCP
listener (:mod:`.link`) or a USB device (:mod:`.usb_link`), each run this
loop over their own read and write.

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

import math
import random
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

from ..capture import CaptureWriter

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

