"""The USB half of ``epos-link sim --usb``: EPOS4 units on an emulated bus (umockdev).

Run by :mod:`.usb_link` as ``umockdev-wrapper /usr/bin/python3 usb_testbed.py
CONFIG_JSON``; it imports only the standard library, gi and its two sibling
modules (:mod:`.usb_model`, :mod:`.usb_ioctl`), never the rest of the project.

Why a separate process under the system Python: umockdev's Python API is
GObject introspection (``gi``), which Debian ships only for its own Python
(``python3-gi``, in /usr/lib/python3/dist-packages). The project's venv may
run another Python (pyenv, another minor version), and PyGObject from PyPI is
an sdist that needs a compiler and the introspection development files (its
newer releases need a newer GLib than Debian 12 has). A helper that relays
bytes works whatever Python the venv has, and keeps the device side (faults,
trace, drives) in the simulator process, with the pty and TCP links.

Why it runs under the umockdev preload itself: hotplug uevents that the
testbed sends reach the clients' (emulated) netlink sockets only from a
preloaded process; without the preload a client's libusb never hears that a
unit came back (found while trying, issue 16).

What it does:

* creates a umockdev ``Testbed`` (the clients find it through ``UMOCKDEV_DIR``)
  with a root hub and one USB device per unit: sysfs attributes, the raw
  ``descriptors`` libusb reads, and a device node whose ioctls
  :class:`~.usb_ioctl.Dispatcher` answers;
* relays bytes with the simulator over stdin/stdout, one JSON object per line:
  in ``{"op": "in"|"unplug"|"plug"|"stats", "unit": N, "data": HEX}``, out
  ``{"event": "ready"|"out"|"plugged"|"unplugged"|"stats"|"error", ...}``;
* ends when its stdin closes (the simulator is gone), removing the testbed.

umockdev calls the ioctl handler in a thread of its own, while stdin and the
timers run in the main loop: the dispatcher serialises them with one lock.
"""
from __future__ import annotations

import gc
import json
import os
import shutil
import sys
import threading
from typing import Any

try:
    from .usb_ioctl import Dispatcher
    from .usb_model import Unit, sysfs_device, sysfs_root_hub
except ImportError:  # run as a script under the system Python (see the docstring)
    from usb_ioctl import Dispatcher  # type: ignore[no-redef]
    from usb_model import Unit, sysfs_device, sysfs_root_hub  # type: ignore[no-redef]

BUS = 1
MAX_LINE = 1 << 20  # a relay line longer than this is a broken simulator, not data
DEBUG = bool(os.environ.get("EPOS_LINK_USB_DEBUG"))


def _load_gi() -> tuple[Any, Any]:
    import gi

    gi.require_version("UMockdev", "1.0")
    from gi.repository import GLib, UMockdev

    return GLib, UMockdev


class Relay:
    """JSON lines to the simulator on stdout; a dead simulator ends this process.

    Both threads send (bulk OUT data from the ioctl thread, events from the main
    loop); a line longer than the pipe's atomic size would interleave unlocked."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self._lock = threading.Lock()

    def send(self, **message: Any) -> None:
        data = (json.dumps(message) + "\n").encode()
        with self._lock:
            try:
                while data:
                    data = data[os.write(self.fd, data):]
            except OSError:
                os._exit(0)  # nobody to serve


class Bus:
    """The testbed, its units and their device nodes."""

    def __init__(self, serials: list[str], relay: Relay) -> None:
        self.GLib, UMockdev = _load_gi()
        self.relay = relay
        self.testbed = UMockdev.Testbed.new()
        self.root = self.testbed.get_root_dir()
        self.units = [Unit(s) for s in serials]
        self.addresses = [0] * len(self.units)
        self._next_address = 2  # address 1 is the root hub's
        self.dispatcher = Dispatcher(
            self.units, on_out=lambda i, data: relay.send(event="out", unit=i, data=data.hex()),
            timeout_add=self.GLib.timeout_add, source_remove=self.GLib.source_remove, debug=DEBUG)
        dispatcher = self.dispatcher

        class Handler(UMockdev.IoctlBase):  # type: ignore[misc, name-defined]
            def do_handle_ioctl(self, client: Any) -> bool:
                return dispatcher.handle(client)

        self.handler = Handler()
        self.testbed.add_from_string(sysfs_root_hub(BUS))
        for i in range(len(self.units)):
            self._add(i)

    def syspath(self, i: int) -> str:
        return f"/sys/devices/pci0000:00/0000:00:14.0/usb{BUS}/{BUS}-{i + 1}"

    def devnode(self, i: int) -> str:
        return f"/dev/bus/usb/{BUS:03d}/{self.addresses[i]:03d}"

    def _add(self, i: int) -> None:
        # A replugged device gets a new address, as the kernel gives it (2..127).
        self.addresses[i] = self._next_address
        self._next_address = 2 if self._next_address >= 127 else self._next_address + 1
        node = self.devnode(i)
        self.dispatcher.plug(i, node)
        # Attach the handler before the node exists, so no open() can miss it
        # (libusb's own umockdev test does the same). add_from_string sends "add".
        self.testbed.attach_ioctl(node, self.handler)
        self.testbed.add_from_string(sysfs_device(self.units[i], BUS, self.addresses[i],
                                                  f"{BUS}-{i + 1}"))

    def info(self, i: int) -> dict[str, Any]:
        return {"unit": i, "serial": self.units[i].serial, "plugged": self.units[i].plugged,
                "bus": BUS, "address": self.addresses[i], "devnode": self.devnode(i)}

    def unplug(self, i: int) -> None:
        if not self.units[i].plugged:
            return
        self.dispatcher.unplug(i)  # from now on its open files answer ENODEV
        node = self.devnode(i)
        self.testbed.remove_device(self.syspath(i))  # sends the "remove" uevent
        try:
            self.testbed.detach_ioctl(node)
        except Exception:  # gi raises GLib.Error subclasses; nothing to detach then
            pass
        try:  # the kernel removes the node; umockdev leaves the file
            os.remove(self.root + node)
        except OSError:
            pass

    def replug(self, i: int) -> None:
        if self.units[i].plugged:
            return
        self._add(i)

    def command(self, message: dict[str, Any]) -> None:
        op = message.get("op")
        i = int(message.get("unit", 0))
        if not 0 <= i < len(self.units):
            raise ValueError(f"no unit {i}")
        if op == "in":
            self.dispatcher.answer(i, bytes.fromhex(message["data"]))
        elif op == "unplug":
            self.unplug(i)
            self.relay.send(event="unplugged", **self.info(i))
        elif op == "plug":
            self.replug(i)
            self.relay.send(event="plugged", **self.info(i))
        elif op == "stats":
            self.relay.send(event="stats", counts=self.dispatcher.stats(),
                            dropped_in=[u.dropped_in for u in self.units])
        else:
            raise ValueError(f"unknown op {op!r}")

    def close(self) -> None:
        # Dropping the testbed removes its directory (umockdev does; removing it
        # first makes umockdev abort). The rmtree is for a testbed that lingers.
        self.testbed = None
        gc.collect()
        shutil.rmtree(self.root, ignore_errors=True)


def main(argv: list[str]) -> int:
    config = json.loads(argv[1]) if len(argv) > 1 else {}
    serials = [str(s) for s in config.get("serials", ["SIM00001"])]
    relay = Relay(sys.stdout.fileno())
    try:
        bus = Bus(serials, relay)
    except (ImportError, ValueError) as exc:
        relay.send(event="error", message=f"umockdev is not usable: {exc}")
        return 3
    GLib = bus.GLib
    loop = GLib.MainLoop()
    pending = bytearray()
    stdin = sys.stdin.fileno()

    def on_stdin(_fd: int, _cond: Any) -> bool:
        try:
            chunk = os.read(stdin, 65536)
        except OSError:
            chunk = b""
        if not chunk or (len(pending) > MAX_LINE and b"\n" not in pending):
            loop.quit()  # the simulator closed the relay (or broke it): stop
            return False
        pending.extend(chunk)
        while b"\n" in pending:
            line, _, rest = bytes(pending).partition(b"\n")
            pending[:] = rest
            try:
                bus.command(json.loads(line))
            except Exception as exc:  # a bad command is reported, never fatal
                relay.send(event="error", message=f"bad relay command: {exc}")
        return True

    GLib.io_add_watch(stdin, GLib.PRIORITY_DEFAULT, GLib.IO_IN | GLib.IO_HUP | GLib.IO_ERR, on_stdin)
    relay.send(event="ready", root=bus.root, units=[bus.info(i) for i in range(len(bus.units))])
    try:
        loop.run()
    except KeyboardInterrupt:
        pass
    finally:
        bus.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
