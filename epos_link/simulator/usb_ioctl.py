"""usbdevfs ioctls of the emulated EPOS4 units, answered from :mod:`.usb_model`.

Policy: **every ioctl is completed exactly once**, on every path: a UsbError
completes it with its errno, any other exception with EIO (and a traceback on
stderr). An ioctl left open hangs the client for ever, so nothing here may
return without completing or handing the ioctl to a timer that will.

Threads: umockdev calls :meth:`Dispatcher.handle` in a thread of its own; the
answers from the simulator, plug changes and the reap timers come from the
helper's main loop. One lock serialises every entry point, and a timer checks
that the hold it fires for is still the one it was made for.

The objects are umockdev's (``IoctlClient``, ``IoctlData``) but this module
does not import gi: the timer functions are passed in, so the tests run it
with fakes under any Python. It runs under the system Python in
:mod:`.usb_testbed` (stdlib only, sibling imports; see there why).

A REAPURBNDELAY that finds nothing while the connection has a URB in flight
(a read waiting for the device) is held for up to :data:`REAP_HOLD_MS`, or
until a URB of that connection completes, before it answers EAGAIN. An
emulated node always polls ready, so without the hold libusb would spin on
the ioctl socket while it waits for an answer; with it, a client's timeout
ends at most that much later. With nothing in flight EAGAIN comes at once:
libusb reaps until EAGAIN after every transfer.
"""
from __future__ import annotations

import errno
import struct
import sys
import threading
import traceback
from typing import Any, Callable, Optional

try:
    from . import usb_model as model
    from .usb_model import Connection, Unit, Urb, UsbError
except ImportError:  # run as a script under the system Python (see usb_testbed)
    import usb_model as model  # type: ignore[no-redef]
    from usb_model import Connection, Unit, Urb, UsbError  # type: ignore[no-redef]

REAP_HOLD_MS = 5
POINTER = struct.calcsize("P")
NO_ARG_OK = frozenset({
    model.USBDEVFS_CLAIMINTERFACE, model.USBDEVFS_RELEASEINTERFACE, model.USBDEVFS_SETINTERFACE,
    model.USBDEVFS_SETCONFIGURATION, model.USBDEVFS_CLEAR_HALT, model.USBDEVFS_RESET,
    model.USBDEVFS_DISCONNECT_CLAIM,
})
NAMES = {getattr(model, n): n[len("USBDEVFS_"):] for n in dir(model) if n.startswith("USBDEVFS_")
         and not n.startswith("USBDEVFS_CAP")}


def data_bytes(data: Any) -> bytes:
    # IoctlData.data is a C array field that PyGObject cuts to one byte;
    # retrieve() returns the whole local copy.
    return bytes(data.retrieve())


class Dispatcher:
    """Maps device nodes to units and ioctls to :class:`~.usb_model.Unit` calls."""

    def __init__(self, units: list[Unit], *, on_out: Callable[[int, bytes], None],
                 timeout_add: Callable[[int, Callable[[int], bool], int], int],
                 source_remove: Callable[[int], Any], debug: bool = False) -> None:
        self.units = units
        self.on_out = on_out
        self._timeout_add = timeout_add
        self._source_remove = source_remove
        self.debug = debug
        self.nodes: dict[str, tuple[int, int]] = {}  # devnode -> (unit index, generation)
        # id(client) -> (client, connection). Holding the wrapper keeps id() unique:
        # PyGObject may hand out a new wrapper (and a recycled id) once the old one is freed.
        self.conns: dict[int, tuple[Any, Connection]] = {}
        self.held: dict[int, tuple[Any, Any, int]] = {}  # id(client) -> (client, arg, timer)
        self.counts: dict[str, int] = {}
        # umockdev calls the ioctl handler in its own thread, while the relay and
        # the timers run in the main loop's: every entry point takes this lock.
        self._lock = threading.RLock()

    # --- completion -----------------------------------------------------------------

    @staticmethod
    def finish(client: Any, result: int, code: int = 0) -> None:
        try:
            client.complete(result, code)
        except Exception:  # the client vanished meanwhile: nothing left to answer
            pass

    def handle(self, client: Any) -> bool:
        """The ``handle-ioctl`` handler: completes ``client``'s ioctl now or via a timer."""
        with self._lock:
            return self._handle_locked(client)

    def _handle_locked(self, client: Any) -> bool:
        try:
            done = self._handle(client)
        except UsbError as exc:
            done = (-1, exc.errno)
        except Exception:
            traceback.print_exc(file=sys.stderr)
            done = (-1, errno.EIO)
        if done is not None:
            self.finish(client, *done)
        return True

    # --- connections ------------------------------------------------------------------

    def connection(self, client: Any) -> Connection:
        key = id(client)
        known = self.conns.get(key)
        if known is not None:
            return known[1]
        index, generation = self.nodes.get(client.get_devnode(), (-1, -1))
        if index < 0:
            raise UsbError(errno.ENODEV)
        unit = self.units[index]
        if generation != unit.generation or not unit.plugged:
            raise UsbError(errno.ENODEV)
        conn = unit.connect()
        self.conns[key] = (client, conn)
        client.connect("notify::connected", self.vanished)
        return conn

    def vanished(self, client: Any, _pspec: Any = None) -> None:
        with self._lock:
            self._vanished(client)

    def _vanished(self, client: Any) -> None:
        if client.get_connected():
            return
        key = id(client)
        known = self.conns.pop(key, None)
        held = self.held.pop(key, None)
        if held is not None:
            self._source_remove(held[2])
        if known is not None:
            known[1].unit.disconnect(known[1])

    def unplug(self, index: int) -> None:
        """The cable of unit ``index`` is pulled: its node goes, its held reaps answer ENODEV."""
        with self._lock:
            unit = self.units[index]
            unit.unplug()
            for node, (i, _generation) in list(self.nodes.items()):
                if i == index:
                    del self.nodes[node]
            self._unplugged(unit)

    def plug(self, index: int, node: str) -> None:
        """Unit ``index`` is (back) on the bus at device node ``node``."""
        with self._lock:
            unit = self.units[index]
            if not unit.plugged:
                unit.replug()
            self.nodes[node] = (index, unit.generation)

    def stats(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)

    def _unplugged(self, unit: Unit) -> None:
        for key, (client, _arg, timer) in list(self.held.items()):
            known = self.conns.get(key)
            if known is not None and known[1].unit is unit:
                self._source_remove(timer)
                del self.held[key]
                self.finish(client, -1, errno.ENODEV)

    # --- the ioctls ---------------------------------------------------------------------

    def _handle(self, client: Any) -> Optional[tuple[int, int]]:
        request = client.get_request()
        name = NAMES.get(request, f"{request:#x}")
        self.counts[name] = self.counts.get(name, 0) + 1
        if self.debug:
            print(f"usb_testbed: {name} on {client.get_devnode()}", file=sys.stderr)
        conn = self.connection(client)
        unit = conn.unit
        unit.check(conn)
        arg = client.get_arg()
        if request == model.USBDEVFS_GET_CAPABILITIES:
            arg.resolve(0, 4).update(0, list(struct.pack("=I", model.CAPABILITIES)))
            return 0, 0
        if request in NO_ARG_OK:
            return 0, 0
        if request == model.USBDEVFS_GETDRIVER:
            return -1, errno.ENODATA  # no kernel driver is bound to the interface
        if request == model.USBDEVFS_SUBMITURB:
            self._submit(conn, arg)
            return 0, 0
        if request == model.USBDEVFS_DISCARDURB:
            unit.discard(conn, int.from_bytes(data_bytes(arg)[:POINTER], sys.byteorder))
            self._wake()
            return 0, 0
        if request in (model.USBDEVFS_REAPURB, model.USBDEVFS_REAPURBNDELAY):
            # REAPURB (blocking) is held the same way; libusb uses the NDELAY form.
            return self._reap(client, conn, arg, hold=True)
        return -1, errno.ENOTTY

    def _submit(self, conn: Connection, arg: Any) -> None:
        urb_data = arg.resolve(0, model.URB.size)
        kind, endpoint, _status, _flags, _buffer, length = model.URB.unpack(data_bytes(urb_data))[:6]
        buffer = urb_data.resolve(model.URB_BUFFER_OFFSET, length) if length > 0 else None
        urb = Urb(key=urb_data.client_addr, type=kind, endpoint=endpoint, buffer_length=length,
                  handle=(urb_data, buffer))
        conn.unit.submit(conn, urb, data_bytes(buffer) if buffer is not None else b"")
        while conn.unit.received:
            self.on_out(self.units.index(conn.unit), conn.unit.received.popleft())
        self._wake()

    @staticmethod
    def _write_back(urb: Urb) -> None:
        urb_data, buffer = urb.handle
        urb_data.update(model.URB_STATUS_OFFSET, list(struct.pack("=i", urb.status)))
        urb_data.update(model.URB_ACTUAL_OFFSET, list(struct.pack("=i", len(urb.data))))
        device_to_host = urb.type == model.URB_TYPE_CONTROL or urb.endpoint & 0x80
        if device_to_host and buffer is not None and urb.data:
            # usbdevfs: a control URB's data follows its 8-byte setup packet.
            buffer.update(8 if urb.type == model.URB_TYPE_CONTROL else 0, list(urb.data))

    def _reap(self, client: Any, conn: Connection, arg: Any, hold: bool) -> Optional[tuple[int, int]]:
        urb = conn.unit.reap(conn)
        if urb is None:
            if not hold or not conn.in_flight:
                # Nothing can complete (libusb reaps until EAGAIN after every
                # transfer): holding would only delay it.
                return -1, errno.EAGAIN
            key = id(client)
            # The timer may fire in the other thread at once: it waits for our
            # lock, then finds the hold by its id (the box is filled before).
            box = [0]
            box[0] = self._timeout_add(REAP_HOLD_MS, lambda _k: self._hold_expired(key, box), key)
            self.held[key] = (client, arg, box[0])
            return None  # completed by _wake, _hold_expired or unplugged
        self._write_back(urb)
        arg.resolve(0, POINTER).set_ptr(0, urb.handle[0])  # the kernel writes the URB's address
        return 0, 0

    def _hold_expired(self, key: int, timer: list[int]) -> bool:
        with self._lock:
            held = self.held.get(key)
            if held is not None and held[2] == timer[0]:  # not a newer hold of this client
                del self.held[key]
                self._answer_held(held[0], held[1])
        return False  # one-shot timer

    def _answer_held(self, client: Any, arg: Any) -> None:
        try:
            conn = self.connection(client)
            conn.unit.check(conn)
            done = self._reap(client, conn, arg, hold=False)
        except UsbError as exc:
            done = (-1, exc.errno)
        except Exception:
            traceback.print_exc(file=sys.stderr)
            done = (-1, errno.EIO)
        assert done is not None  # hold=False always answers
        self.finish(client, *done)

    def _wake(self) -> None:
        """URBs completed: answer the held reaps of connections that have one to reap."""
        for key, (client, arg, timer) in list(self.held.items()):
            known = self.conns.get(key)
            if known is not None and known[1].done:
                self._source_remove(timer)
                del self.held[key]
                self._answer_held(client, arg)

    def answer(self, index: int, data: bytes) -> None:
        """The simulator's answer for unit ``index``: one bulk IN transfer."""
        with self._lock:
            self.units[index].answer(data)
            self._wake()
