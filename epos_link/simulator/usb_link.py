"""Serving simulated EPOS4 units as USB devices 24E7:3B01 (``epos-link sim --usb``).

The USB bus is emulated by umockdev in a helper process (:mod:`.usb_testbed`,
run under the system Python and the umockdev preload; its docstring says why). This module starts that
helper, relays bytes with it and serves each unit with the same
:class:`~.link_server.LinkServer` as the pty and TCP links, so the fault options
(drop, corrupt, delay, silent) and the trace behave alike on every link. One
request/answer loop per unit; each answer of the device is one USB transfer.

A program reaches the units through real libusb when it runs under umockdev's
preload with the testbed's directory in its environment::

    UMOCKDEV_DIR=/tmp/umockdev.XXXXXX umockdev-wrapper PROGRAM ...

(:attr:`UsbLink.environment` and :meth:`UsbLink.command`). Unplugging a unit
(:meth:`UsbLink.unplug`) removes its device: open files answer ENODEV, the
hotplug ``remove`` uevent is sent, queued bytes are lost and the device side
is reset; :meth:`UsbLink.replug` adds it back at a new address, as a kernel
does. Every wait on the helper is bounded.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import selectors
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Optional, Sequence

from ..capture import CaptureWriter
from ..errors import TransportError
from .link_server import USB_FRAME_TIMEOUT, Device, LinkOptions, LinkServer

log = logging.getLogger(__name__)
HELPER = Path(__file__).with_name("usb_testbed.py")
WRAPPER = "umockdev-wrapper"
SYSTEM_PYTHON = "/usr/bin/python3"
START_TIMEOUT = 30.0    # the helper imports gi and builds the testbed
COMMAND_TIMEOUT = 10.0  # plug/unplug acknowledgement
MAX_QUEUED_CHUNKS = 1024
MAX_EVENTS = 256
_GI_CHECK = ("import gi; gi.require_version('UMockdev', '1.0'); "
             "from gi.repository import UMockdev; UMockdev.IoctlBase")
INSTALL_HINT = "Debian/Ubuntu: sudo apt install umockdev gir1.2-umockdev-1.0 python3-gi"


def gi_python() -> str:
    """The Python that runs the helper: ``EPOS_LINK_GI_PYTHON``, else the system's."""
    return os.environ.get("EPOS_LINK_GI_PYTHON") or SYSTEM_PYTHON


def unavailable_reason() -> Optional[str]:
    """Why ``sim --usb`` cannot run here, or None when it can."""
    if shutil.which(WRAPPER) is None:
        return f"{WRAPPER} not found ({INSTALL_HINT})"
    python = gi_python()
    if not os.access(python, os.X_OK):
        return f"{python} not found: the USB testbed needs a Python with gi ({INSTALL_HINT})"
    try:
        out = subprocess.run([python, "-c", _GI_CHECK], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot run {python}: {exc}"
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["failed"])[-1]
        return f"{python} cannot load umockdev through gi (0.16 or later): {last} ({INSTALL_HINT})"
    return None


@dataclass
class UsbUnit:
    """One unit as the helper reports it."""

    index: int
    serial: str
    plugged: bool = True
    bus: int = 1
    address: int = 0
    devnode: str = ""
    generation: int = 0  # counts plug events: a server loop belongs to one generation
    chunks: "queue.Queue[Optional[bytes]]" = field(default_factory=lambda: queue.Queue(MAX_QUEUED_CHUNKS))

    @property
    def url(self) -> str:
        return f"usb://?serial={self.serial}"


class _LockedTrace:
    """Several units' servers write one capture file."""

    def __init__(self, writer: CaptureWriter) -> None:
        self._writer = writer
        self._lock = threading.Lock()

    def write(self, time: float, direction: str, data: bytes) -> None:
        with self._lock:
            self._writer.write(time, direction, data)


class UsbLink:
    """EPOS4 units on an emulated USB bus, each served by its own device object."""

    def __init__(self, devices: Sequence[Device], serials: Sequence[str],
                 options: Optional[LinkOptions] = None, trace: Optional[CaptureWriter] = None,
                 *, stderr: Optional[IO[str]] = None) -> None:
        if len(devices) != len(serials) or not serials:
            raise ValueError("one serial number per device, at least one")
        if len(set(serials)) != len(serials):
            raise ValueError("serial numbers must differ")
        locked: Any = _LockedTrace(trace) if trace is not None else None
        self.servers = [LinkServer(d, options, locked, frame_timeout_object=USB_FRAME_TIMEOUT)
                        for d in devices]
        self._events: "queue.Queue[dict[str, Any]]" = queue.Queue(MAX_EVENTS)
        self._send_lock = threading.Lock()
        self._command_lock = threading.Lock()  # one plug/unplug/stats exchange at a time
        self._threads: list[threading.Thread] = []
        self._closed = threading.Event()
        config = json.dumps({"serials": list(serials)})
        try:
            self.proc = subprocess.Popen([WRAPPER, gi_python(), str(HELPER), config], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=stderr)
        except OSError as exc:
            raise TransportError(f"cannot start the USB testbed helper: {exc} ({INSTALL_HINT})") from exc
        try:
            ready = self._first_message()
        except BaseException:
            self._stop_helper()
            raise
        self.root: str = ready["root"]
        self.units = [UsbUnit(u["unit"], u["serial"], u["plugged"], u["bus"], u["address"],
                              u["devnode"]) for u in ready["units"]]

    def _first_message(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        # selectors, not select(): no limit of 1024 on the descriptor (see link.py).
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            ready = selector.select(START_TIMEOUT)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            code = self.proc.poll()
            raise TransportError(f"the USB testbed helper did not start (exit status {code}; "
                                 f"{INSTALL_HINT})")
        message = json.loads(line)
        if message.get("event") != "ready":
            raise TransportError(f"the USB testbed helper failed: {message.get('message', message)}")
        return dict(message)

    # --- what a client needs ------------------------------------------------------

    @property
    def environment(self) -> dict[str, str]:
        """Variables a client process needs (besides the preload of :data:`WRAPPER`)."""
        return {"UMOCKDEV_DIR": self.root}

    def command(self, argv: Sequence[str]) -> list[str]:
        """``argv`` run under the umockdev preload (add :attr:`environment` to its env)."""
        return [WRAPPER, *argv]

    @property
    def how_to_run(self) -> str:
        return f"UMOCKDEV_DIR={self.root} {WRAPPER} PROGRAM"

    # --- life cycle -----------------------------------------------------------------

    def start(self) -> "UsbLink":
        reader = threading.Thread(target=self._read_helper, name="epos-sim-usb-relay", daemon=True)
        self._threads.append(reader)
        for unit, server in zip(self.units, self.servers):
            t = threading.Thread(target=self._serve, args=(unit, server),
                                 name=f"epos-sim-usb-{unit.index}", daemon=True)
            self._threads.append(t)
        for t in self._threads:
            t.start()
        return self

    def _send(self, **message: Any) -> None:
        assert self.proc.stdin is not None
        data = (json.dumps(message) + "\n").encode()
        with self._send_lock:
            try:
                self.proc.stdin.write(data)
                self.proc.stdin.flush()
            except (OSError, ValueError) as exc:  # helper gone, or closed by close()
                if not self._closed.is_set():
                    raise TransportError(f"the USB testbed helper is gone: {exc}") from exc

    def _read_helper(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                self._dispatch(json.loads(line))
            except (ValueError, KeyError, IndexError, TypeError, AttributeError) as exc:
                log.warning("bad line from the USB testbed helper: %s (%r)", exc, line[:200])
        for unit in self.units:  # helper ended: stop every unit's loop
            _put_latest(unit.chunks, None)
        self._closed.set()

    def _dispatch(self, message: dict[str, Any]) -> None:
        event = message.get("event")
        if event == "out":
            unit = self.units[message["unit"]]
            try:
                unit.chunks.put_nowait(bytes.fromhex(message["data"]))
            except queue.Full:
                pass  # bounded: a device side that stopped reading loses requests
        elif event in ("plugged", "unplugged"):
            unit = self.units[message["unit"]]
            unit.plugged = message["plugged"]
            unit.address, unit.devnode = message["address"], message["devnode"]
            unit.generation += 1
            _put_latest(unit.chunks, None)  # wakes the unit's loop: it ends and resets
            _put_latest(self._events, message)
        else:
            _put_latest(self._events, message)

    def _serve(self, unit: UsbUnit, server: LinkServer) -> None:
        generation = unit.generation

        def read(timeout: float) -> Optional[bytes]:
            try:
                item = unit.chunks.get(timeout=timeout)
            except queue.Empty:
                item = b""
            if unit.generation != generation or self._closed.is_set():
                return None  # unplugged (and maybe replugged) since: end this session
            return item or b""  # None alone is a wake-up

        def write(data: bytes) -> None:
            if unit.plugged:
                self._send(op="in", unit=unit.index, data=data.hex())

        while not server.stopped and not self._closed.is_set():
            if not unit.plugged:
                self._closed.wait(0.05)
                continue
            generation = unit.generation
            try:
                server.serve_stream(read, write)  # returns at unplug; the device resets
            except TransportError:
                return

    def _exchange(self, want: str, **command: Any) -> dict[str, Any]:
        """Send one command to the helper and wait (bounded) for its ``want`` event."""
        with self._command_lock:
            while True:  # events nobody waited for are stale now
                try:
                    self._events.get_nowait()
                except queue.Empty:
                    break
            self._send(**command)
            deadline = time.monotonic() + COMMAND_TIMEOUT
            while True:
                left = deadline - time.monotonic()
                try:
                    message = self._events.get(timeout=max(left, 0.0))
                except queue.Empty:
                    raise TransportError(f"the USB testbed did not answer {command}") from None
                if message.get("event") == want and message.get("unit", command.get("unit")) == \
                        command.get("unit"):
                    return message
                if message.get("event") == "error":
                    raise TransportError(f"USB testbed: {message.get('message')}")

    def _change(self, index: int, op: str, want: str) -> UsbUnit:
        if not 0 <= index < len(self.units):
            raise ValueError(f"no USB unit {index} (there are {len(self.units)})")
        self._exchange(want, op=op, unit=index)
        return self.units[index]

    def unplug(self, index: int = 0) -> UsbUnit:
        """Pull the cable of unit ``index``; returns once the device is gone."""
        return self._change(index, "unplug", "unplugged")

    def replug(self, index: int = 0) -> UsbUnit:
        """Plug unit ``index`` back in (a new address, a fresh device side)."""
        return self._change(index, "plug", "plugged")

    def stats(self) -> dict[str, Any]:
        """Counts of the ioctls the testbed answered, by name (``DISCARDURB``, ...)."""
        return self._exchange("stats", op="stats")

    def _stop_helper(self) -> None:
        self._closed.set()
        try:
            if self.proc.stdin:
                self.proc.stdin.close()  # the helper ends when its stdin closes
        except OSError:
            pass
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        if self.proc.stdout:
            self.proc.stdout.close()

    def close(self) -> None:
        for server in self.servers:
            server.stop()
        for unit in self.units:
            _put_latest(unit.chunks, None)
        self._stop_helper()
        for t in self._threads:
            t.join(2)


def _put_latest(q: "queue.Queue[Any]", item: Any) -> None:
    """Put ``item`` even into a full queue (dropping the oldest entry)."""
    while True:
        try:
            q.put_nowait(item)
            return
        except queue.Full:
            try:
                q.get_nowait()
            except queue.Empty:
                pass
