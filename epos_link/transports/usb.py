"""EPOS4 native USB through pyusb (``usb://``, ``usb://?serial=XXXX``, ``usb://?index=1``).

The EPOS4 enumerates as USB 24E7:3B01 with a vendor-specific interface and
no tty; MAXON SERIAL V2 frames travel over its bulk endpoints exactly as over
RS232 (guide 2.3.1). The endpoints are found from the descriptors: the first
interface of the active configuration with a bulk IN and a bulk OUT endpoint,
vendor-specific (class 0xFF) interfaces first. Some units enumerate as FTDI
0403:A8B0 instead: those are serial ports (``/dev/ttyUSB0``, ``COM3``) and
open through the serial transport; ``usb://`` says so when it finds one.

The libusb backend comes from the ``libusb-package`` wheel when installed,
else from pyusb's own search (a system libusb-1.0). ``EPOS_LINK_LIBUSB=system``
takes the system library even when the wheel is installed, and
``EPOS_LINK_LIBUSB=/path/to/libusb-1.0.so`` a given one: the wheel's libusb
watches hotplug through its own netlink socket, which sees no emulated events
(``epos-link sim --usb``), while Debian's is built with udev and does. pyusb
loads one libusb per process, so the choice holds for the whole process. On Linux the device node
needs a udev rule for non-root users::

    # /etc/udev/rules.d/70-epos4.rules (before 73-seat-late.rules, which applies uaccess)
    SUBSYSTEM=="usb", ATTR{idVendor}=="24e7", ATTR{idProduct}=="3b01", TAG+="uaccess"
    # units that enumerate as FTDI 0403:A8B0 (serial port /dev/ttyUSBn):
    ACTION=="add", ATTR{idVendor}=="0403", ATTR{idProduct}=="a8b0", RUN+="/sbin/modprobe ftdi_sio", RUN+="/bin/sh -c 'echo 0403 a8b0 > /sys/bus/usb-serial/drivers/ftdi_sio/new_id'"

then ``sudo udevadm control --reload-rules && sudo udevadm trigger`` and replug.

Reads ask for one packet (``wMaxPacketSize``) at a time: a transfer that
ends in a timeout loses the bytes it got (pyusb raises without them), and a
one-packet transfer cannot end that way. Any USB error other than a timeout
is a :class:`TransportError`; the client then calls :meth:`UsbTransport.reopen`,
which finds the same unit again (by serial number when known).
"""
from __future__ import annotations

import errno
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, Optional
from urllib.parse import parse_qs, urlsplit

from ..errors import TransportError
from .base import Transport

EPOS4_USB_ID = (0x24E7, 0x3B01)
EPOS4_FTDI_ID = (0x0403, 0xA8B0)
WRITE_TIMEOUT_MS = 1000
_DRAIN_LIMIT = 64  # packets discarded at most by one reset_input

# TAG+="uaccess": systemd-logind gives the user logged in at the seat access
# (an ACL), no one else; a world-writable mode would give every local account the drive.
# Headless machines use a group instead (docs/hardware.md).
UDEV_RULES_FILE = "/etc/udev/rules.d/70-epos4.rules"  # must sort before 73-seat-late.rules
UDEV_RULE = 'SUBSYSTEM=="usb", ATTR{idVendor}=="24e7", ATTR{idProduct}=="3b01", TAG+="uaccess"'
PERMISSION_HELP = (
    "permission denied on the EPOS4 USB device. On Linux add a udev rule:\n"
    f"  echo '{UDEV_RULE}' | sudo tee {UDEV_RULES_FILE}\n"
    "  sudo udevadm control --reload-rules && sudo udevadm trigger\n"
    "then unplug and replug the EPOS4 (or run as root). On Windows install a WinUSB driver "
    "for it (e.g. with Zadig).")
BACKEND_HELP = (
    "no libusb backend found for pyusb: pip install libusb-package (bundles libusb-1.0), "
    "or install the system library (Debian/Ubuntu: sudo apt install libusb-1.0-0)")


def _usb() -> Any:
    try:
        import usb.core
        import usb.util
    except ImportError as exc:  # only this scheme needs pyusb
        raise TransportError(f"usb:// needs pyusb: pip install pyusb ({exc})") from exc
    return usb


LIBUSB_ENV = "EPOS_LINK_LIBUSB"


def default_backend() -> Any:
    """The libusb that ``EPOS_LINK_LIBUSB`` names (``system`` or a path); by default the
    ``libusb-package`` wheel's if installed, else None (pyusb searches the system)."""
    choice = os.environ.get(LIBUSB_ENV, "").strip()
    if choice in ("", "bundled"):
        try:
            import libusb_package
        except ImportError:
            return None
        return libusb_package.get_libusb1_backend()
    _usb()
    import usb.backend.libusb1 as libusb1

    if choice == "system":
        backend = libusb1.get_backend()  # ctypes' search: the system's libusb-1.0
    else:
        backend = libusb1.get_backend(find_library=lambda _name: choice)
    if backend is None:
        raise TransportError(f"{LIBUSB_ENV}={choice}: no usable libusb-1.0 there "
                             "(use 'system', 'bundled' or the path of libusb-1.0.so)")
    return backend


@dataclass(frozen=True)
class UsbDeviceInfo:
    """One EPOS4 on the USB bus, as ``epos-link ports`` lists it."""

    bus: Optional[int]
    address: Optional[int]
    serial: Optional[str]  # None when unreadable (often a permission problem)

    @property
    def url(self) -> str:
        return f"usb://?serial={self.serial}" if self.serial else "usb://"


def _serial_of(dev: Any) -> Optional[str]:
    try:
        value = dev.serial_number
    except (ValueError, OSError, NotImplementedError):
        return None  # pyusb: "The device has no langid (permission issue, ...)"
    return str(value) if value else None


def _find_all(find: Optional[Callable[..., Any]], backend: Any) -> list[Any]:
    usb = _usb()
    find = find or usb.core.find
    try:
        return list(find(find_all=True, idVendor=EPOS4_USB_ID[0], idProduct=EPOS4_USB_ID[1],
                         backend=backend))
    except usb.core.NoBackendError as exc:
        raise TransportError(BACKEND_HELP) from exc
    except OSError as exc:
        raise TransportError(f"cannot list USB devices: {exc}") from exc


def list_usb_devices(*, backend: Any = None, find: Optional[Callable[..., Any]] = None) -> list[UsbDeviceInfo]:
    """Every EPOS4 24E7:3B01 on the bus."""
    if backend is None:
        backend = default_backend()
    return [UsbDeviceInfo(getattr(d, "bus", None), getattr(d, "address", None), _serial_of(d))
            for d in _find_all(find, backend)]


def list_ftdi_ports() -> list[Any]:
    """Serial ports of EPOS4 units that enumerate as FTDI 0403:A8B0 (``ListPortInfo``)."""
    from serial.tools import list_ports

    return [p for p in list_ports.comports() if (p.vid, p.pid) == EPOS4_FTDI_ID]


def _is_permission(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.EACCES, errno.EPERM)


def find_bulk_endpoints(config: Any) -> tuple[Any, Any, Any]:
    """(interface, bulk IN endpoint, bulk OUT endpoint) of a configuration descriptor."""
    usb = _usb()
    util = usb.util

    def bulk(direction: int) -> Callable[[Any], bool]:
        return lambda e: (util.endpoint_type(e.bmAttributes) == util.ENDPOINT_TYPE_BULK
                          and util.endpoint_direction(e.bEndpointAddress) == direction)

    interfaces = sorted(config, key=lambda i: i.bInterfaceClass != 0xFF)  # vendor-specific first
    for intf in interfaces:
        ep_in = util.find_descriptor(intf, custom_match=bulk(util.ENDPOINT_IN))
        ep_out = util.find_descriptor(intf, custom_match=bulk(util.ENDPOINT_OUT))
        if ep_in is not None and ep_out is not None:
            return intf, ep_in, ep_out
    raise TransportError("the EPOS4 USB device has no interface with bulk IN and OUT endpoints")


class UsbTransport(Transport):
    """One EPOS4 over its vendor-specific USB interface."""

    def __init__(self, *, serial: Optional[str] = None, index: int = 0, backend: Any = None,
                 find: Optional[Callable[..., Any]] = None, url: str = "usb://") -> None:
        self.url = url
        self.serial = serial
        self.index = index
        self._backend = backend if backend is not None else default_backend()
        self._find = find
        self._dev: Any = None
        self._intf = -1
        self._ep_in = self._ep_out = 0
        self._packet = 64
        self._buf = b""
        self._maybe_stale = False  # a read timed out: a late answer may still come
        self.open()

    # --- life cycle -------------------------------------------------------

    def _select(self) -> Any:
        devices = _find_all(self._find, self._backend)
        if self.serial is not None:
            devices = [d for d in devices if _serial_of(d) == self.serial]
        if len(devices) > self.index:
            return devices[self.index]
        wanted = f"EPOS4 USB device {EPOS4_USB_ID[0]:04X}:{EPOS4_USB_ID[1]:04X}"
        if self.serial is not None:
            wanted += f" with serial number {self.serial} (unreadable serial numbers can mean a " \
                      f"permission problem: see the udev rule in `epos-link ports --help`)"
        hint = ""
        try:
            ftdi = list_ftdi_ports()
        except Exception:  # listing is a courtesy; never hide the real error
            ftdi = []
        if ftdi:
            hint = ("; found EPOS4 serial port(s) (FTDI 0403:A8B0): "
                    + ", ".join(p.device for p in ftdi) + ": use that path as the URL")
        raise TransportError(f"no {wanted}{hint}")

    def open(self) -> None:
        if self._dev is not None:
            return
        usb = _usb()
        dev = self._select()
        try:
            try:
                config = dev.get_active_configuration()
            except usb.core.USBError as exc:
                if _is_permission(exc):
                    raise
                dev.set_configuration()  # unconfigured: take the first configuration
                config = dev.get_active_configuration()
            intf, ep_in, ep_out = find_bulk_endpoints(config)
            number = intf.bInterfaceNumber
            try:
                if dev.is_kernel_driver_active(number):
                    dev.detach_kernel_driver(number)
            except (NotImplementedError, usb.core.USBError):
                pass  # not on this platform, or nothing to detach
            usb.util.claim_interface(dev, number)
        except (usb.core.USBError, OSError) as exc:
            if _is_permission(exc):
                raise TransportError(PERMISSION_HELP) from exc
            if getattr(exc, "errno", None) == errno.EBUSY:
                # libusb: LIBUSB_ERROR_BUSY, the interface is claimed by another process.
                raise TransportError(f"cannot open {self.url}: the EPOS4 is busy (another program "
                                     "has it open; stop that program first)") from exc
            raise TransportError(f"cannot open {self.url}: {exc}") from exc
        self._dev = dev
        self._intf = number
        self._ep_in, self._ep_out = ep_in.bEndpointAddress, ep_out.bEndpointAddress
        self._packet = max(int(ep_in.wMaxPacketSize), 1)
        self._buf = b""
        self._maybe_stale = False
        if self.serial is None:
            self.serial = _serial_of(dev)  # so reopen finds this very unit again

    def close(self) -> None:
        dev, self._dev = self._dev, None
        self._buf = b""
        if dev is None:
            return
        usb = _usb()
        try:
            usb.util.release_interface(dev, self._intf)
        except (usb.core.USBError, OSError):
            pass  # unplugged: nothing to release
        try:
            usb.util.dispose_resources(dev)
        except (usb.core.USBError, OSError):
            pass

    def reopen(self) -> None:
        self.close()
        self.open()

    # --- I/O --------------------------------------------------------------

    def _failed(self, what: str, exc: BaseException) -> TransportError:
        # The device is unusable now (unplugged, reset); release it so that
        # reopen() starts from a fresh device object.
        self.close()
        return TransportError(f"USB {what} failed: {exc}")

    def write(self, data: bytes) -> None:
        dev = self._dev
        if dev is None:
            raise TransportError(f"{self.url} is closed")
        usb = _usb()
        try:
            sent = dev.write(self._ep_out, data, WRITE_TIMEOUT_MS)
        except (usb.core.USBError, OSError) as exc:
            raise self._failed("write", exc) from exc
        if sent != len(data):
            raise self._failed("write", OSError(f"{sent} of {len(data)} bytes sent"))

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self._buf:
            out, self._buf = self._buf[:max_bytes], self._buf[max_bytes:]
            return out
        dev = self._dev
        if dev is None:
            raise TransportError(f"{self.url} is closed")
        data = self._read_packet(dev, timeout)
        if len(data) > max_bytes:
            data, self._buf = data[:max_bytes], data[max_bytes:]
        return data

    def _read_packet(self, dev: Any, timeout: float) -> bytes:
        usb = _usb()
        # libusb takes whole milliseconds and reads 0 as "wait forever".
        ms = max(1, math.ceil(timeout * 1000))
        try:
            return bytes(dev.read(self._ep_in, self._packet, ms))
        except usb.core.USBTimeoutError:
            self._maybe_stale = True
            return b""
        except (usb.core.USBError, OSError) as exc:
            if getattr(exc, "errno", None) == errno.ETIMEDOUT:
                self._maybe_stale = True
                return b""
            raise self._failed("read", exc) from exc

    def reset_input(self) -> None:
        """Drop buffered bytes; after a timed-out read, also drain what the device has
        queued since (a late answer), with 1 ms reads. Otherwise nothing can be
        pending, and the hot path stays free of extra USB transfers."""
        self._buf = b""
        if not self._maybe_stale or self._dev is None:
            return
        self._maybe_stale = False
        for _ in range(_DRAIN_LIMIT):
            if not self._read_packet(self._dev, 0.001):
                break
        self._maybe_stale = False


def open_usb(url: str, *, backend: Any = None, find: Optional[Callable[..., Any]] = None,
             **_options: Any) -> UsbTransport:
    """``usb://`` (first EPOS4), ``usb://?serial=XXXX``, ``usb://?index=N``.

    Serial-link options such as ``baudrate`` do not apply to USB and are ignored.
    """
    query = parse_qs(urlsplit(url).query)
    unknown = set(query) - {"serial", "index"}
    if unknown:
        raise TransportError(f"{url}: unknown option(s) {', '.join(sorted(unknown))}; "
                             "use serial=... or index=N")
    serial = query.get("serial", [None])[-1]
    try:
        index = int(query.get("index", ["0"])[-1])
    except ValueError:
        raise TransportError(f"{url}: index must be a number") from None
    if index < 0:
        raise TransportError(f"{url}: index counts EPOS4 units from 0, got {index}")
    return UsbTransport(serial=serial, index=index, backend=backend, find=find, url=url)


__all__ = ["EPOS4_FTDI_ID", "EPOS4_USB_ID", "LIBUSB_ENV", "default_backend", "PERMISSION_HELP", "UDEV_RULE", "UsbDeviceInfo",
           "UsbTransport", "find_bulk_endpoints", "list_ftdi_ports", "list_usb_devices", "open_usb"]
