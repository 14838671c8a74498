"""The simulated EPOS4's USB device side: descriptors and the URB life cycle of usbdevfs.

Policy of this module (pure: no gi, no I/O, no clock; stdlib only, because
:mod:`.usb_testbed` also runs it under the system Python, see there why):

* **Descriptors.** USB 24E7:3B01 (the id :mod:`epos_link.transports.usb` looks
  for), one configuration, one vendor-specific interface (class 0xFF) with bulk
  OUT 0x01 and bulk IN 0x81 of 64 bytes, full speed, USB 2.0 (guide 2.3.1:
  "follows the Universal Serial Bus Specification Revision 2.0"). The guide
  gives no descriptor dump: the string texts are ours (``maxon motor ag``,
  ``EPOS4``) and the serial number is the simulator's ``--serial``.
* **Bulk OUT.** A bulk OUT URB completes at once with all its bytes, which
  go to the simulator's device side as one chunk (:attr:`Unit.received`).
* **Bulk IN.** Each answer of the device is one USB transfer: it is cut
  into 64-byte packets and a transfer ends at a short packet (a zero-length one
  when the answer is a multiple of 64 bytes), as USB 2.0 section 5.8.3 defines
  the end of a bulk transfer. A pending IN URB completes when it has taken a
  short packet or its buffer is full; the rest of a long answer waits for the
  next URB. An answer that arrives while no URB waits is kept (bounded) for the
  next one, so a late answer is seen by the host's next read, as on the wire.
* **Control.** GET_DESCRIPTOR for strings (USB 2.0 section 9.6.7) is answered;
  other standard requests the host may send (SET_CONFIGURATION,
  SET_INTERFACE, CLEAR_FEATURE) succeed; anything else stalls (``-EPIPE``).
* **Discard and unplug.** DISCARDURB completes the URB with ``-ENOENT`` (what
  the kernel reports for an unlinked URB); after :meth:`Unit.unplug` every
  call answers ``ENODEV``, as the kernel does for a vanished device.

:class:`Unit` is driven by the ioctl glue with plain values (URB fields and
buffer bytes) and returns plain values; the glue owns the client memory.
"""
from __future__ import annotations

import errno
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Optional

VENDOR_ID, PRODUCT_ID = 0x24E7, 0x3B01
EP_OUT, EP_IN = 0x01, 0x81
PACKET = 64
MANUFACTURER = "maxon motor ag"
PRODUCT = "EPOS4"
LANGID_EN_US = 0x0409
MAX_QUEUED_IN = 64 * 1024  # bytes of answers kept while the host reads nothing
MAX_URBS = 256             # URBs in flight per connection (libusb submits a few)

# struct usbdevfs_urb (linux/usbdevice_fs.h), native layout (x86_64: 56 bytes):
# type, endpoint, status, flags, buffer, buffer_length, actual_length,
# start_frame, number_of_packets, error_count, signr, usercontext
URB = struct.Struct("@BBiIPiiiiiIP")
# Offsets of a field = size of the prefix that ends with it, less its own size
# (calcsize pads before a member, never after the last one).
URB_STATUS_OFFSET = struct.calcsize("@BBi") - 4          # 4
URB_BUFFER_OFFSET = struct.calcsize("@BBiIP") - struct.calcsize("P")  # 16 on x86_64
URB_ACTUAL_OFFSET = struct.calcsize("@BBiIPii") - 4      # 28 on x86_64
URB_TYPE_CONTROL, URB_TYPE_BULK = 2, 3


def _ioc(direction: int, number: int, size: int) -> int:
    # asm-generic/ioctl.h: dir << 30 | size << 16 | type << 8 | nr, type 'U' for usbdevfs
    return (direction << 30) | (size << 16) | (ord("U") << 8) | number


_P = struct.calcsize("P")
IOC_NONE, IOC_WRITE, IOC_READ = 0, 1, 2
USBDEVFS_CONTROL = _ioc(IOC_READ | IOC_WRITE, 0, struct.calcsize("@BBHHHIP"))
USBDEVFS_BULK = _ioc(IOC_READ | IOC_WRITE, 2, struct.calcsize("@IIIP"))
USBDEVFS_SETINTERFACE = _ioc(IOC_READ, 4, 8)
USBDEVFS_SETCONFIGURATION = _ioc(IOC_READ, 5, 4)
USBDEVFS_GETDRIVER = _ioc(IOC_WRITE, 8, 4 + 256)
USBDEVFS_SUBMITURB = _ioc(IOC_READ, 10, URB.size)
USBDEVFS_DISCARDURB = _ioc(IOC_NONE, 11, 0)
USBDEVFS_REAPURB = _ioc(IOC_WRITE, 12, _P)
USBDEVFS_REAPURBNDELAY = _ioc(IOC_WRITE, 13, _P)
USBDEVFS_CLAIMINTERFACE = _ioc(IOC_READ, 15, 4)
USBDEVFS_RELEASEINTERFACE = _ioc(IOC_READ, 16, 4)
USBDEVFS_IOCTL = _ioc(IOC_READ | IOC_WRITE, 18, struct.calcsize("@iiP"))
USBDEVFS_RESET = _ioc(IOC_NONE, 20, 0)
USBDEVFS_CLEAR_HALT = _ioc(IOC_READ, 21, 4)
USBDEVFS_GET_CAPABILITIES = _ioc(IOC_READ, 26, 4)
USBDEVFS_DISCONNECT_CLAIM = _ioc(IOC_READ, 27, 4 + 4 + 256)
# linux/usbdevice_fs.h: no packet size limit on bulk URBs; reap after disconnect
USBDEVFS_CAP_NO_PACKET_SIZE_LIM = 0x04
CAPABILITIES = USBDEVFS_CAP_NO_PACKET_SIZE_LIM


def device_descriptor() -> bytes:
    """USB 2.0 table 9-8: bcdUSB 2.00, class per interface, EP0 64 bytes, one configuration."""
    return struct.pack("<BBHBBBBHHHBBBB", 18, 1, 0x0200, 0, 0, 0, 64, VENDOR_ID, PRODUCT_ID,
                       0x0100, 1, 2, 3, 1)


def configuration_descriptor() -> bytes:
    """USB 2.0 tables 9-10, 9-12, 9-13: one vendor interface, bulk OUT 0x01 and IN 0x81."""
    interface = struct.pack("<BBBBBBBBB", 9, 4, 0, 0, 2, 0xFF, 0, 0, 0)
    ep_out = struct.pack("<BBBBHB", 7, 5, EP_OUT, 0x02, PACKET, 0)
    ep_in = struct.pack("<BBBBHB", 7, 5, EP_IN, 0x02, PACKET, 0)
    body = interface + ep_out + ep_in
    # bmAttributes 0xC0: self-powered (the EPOS4 has its own logic supply); 100 mA
    return struct.pack("<BBHBBBBB", 9, 2, 9 + len(body), 1, 1, 0, 0xC0, 50) + body


def sysfs_descriptors() -> bytes:
    """What Linux shows in ``/sys/bus/usb/devices/N-M/descriptors`` and libusb reads."""
    return device_descriptor() + configuration_descriptor()


def string_descriptor(text: str) -> bytes:
    data = text.encode("utf-16-le")
    return bytes([2 + len(data), 3]) + data


def packets(answer: bytes) -> list[bytes]:
    """One bulk IN transfer: 64-byte packets ending in a short one (USB 2.0 5.8.3)."""
    out = [answer[i:i + PACKET] for i in range(0, len(answer), PACKET)]
    if not out or len(out[-1]) == PACKET:
        out.append(b"")  # zero-length packet ends a transfer that fills its last packet
    return out


@dataclass
class Urb:
    """One URB in flight; ``key`` is the client's own address of it."""

    key: int
    type: int
    endpoint: int
    buffer_length: int
    handle: Any = None             # the glue's handle on the client memory
    status: int = 0
    data: bytes = b""              # IN: bytes delivered; OUT: bytes sent


@dataclass
class Connection:
    """One open file of the device node: its URBs in flight and completed."""

    unit: "Unit"
    generation: int
    in_flight: dict[int, Urb] = field(default_factory=dict)
    done: deque[Urb] = field(default_factory=deque)

    @property
    def gone(self) -> bool:
        return not self.unit.plugged or self.generation != self.unit.generation


class UsbError(Exception):
    """An ioctl fails with this errno."""

    def __init__(self, code: int) -> None:
        super().__init__(errno.errorcode.get(code, str(code)))
        self.errno = code


class Unit:
    """One emulated EPOS4 on the bus."""

    def __init__(self, serial: str) -> None:
        self.serial = serial
        self.plugged = True
        self.generation = 0
        self.received: deque[bytes] = deque()     # bulk OUT chunks for the simulator
        self._packets: deque[bytes] = deque()     # bulk IN packets not yet taken
        self._queued = 0
        self._waiting: deque[tuple[Connection, Urb]] = deque()  # IN URBs, oldest first
        self.connections: list[Connection] = []
        self.dropped_in = 0

    # --- plug state ---------------------------------------------------------

    def connect(self) -> Connection:
        if not self.plugged:
            raise UsbError(errno.ENODEV)
        conn = Connection(self, self.generation)
        self.connections.append(conn)
        return conn

    def disconnect(self, conn: Connection) -> None:
        if conn in self.connections:
            self.connections.remove(conn)
        self._waiting = deque(w for w in self._waiting if w[0] is not conn)

    def unplug(self) -> None:
        """The cable is pulled: every open file is dead, queued bytes are lost."""
        self.plugged = False
        self._packets.clear()
        self._queued = 0
        self._waiting.clear()
        self.received.clear()
        for conn in self.connections:
            conn.in_flight.clear()
            conn.done.clear()

    def replug(self) -> None:
        self.plugged = True
        self.generation += 1

    # --- data from the simulator --------------------------------------------

    def answer(self, data: bytes) -> list[Connection]:
        """The device sends one transfer; returns connections with newly reapable URBs."""
        if not self.plugged:
            return []
        new = packets(data)
        size = sum(len(p) for p in new)
        if self._queued + size > MAX_QUEUED_IN:
            self.dropped_in += size  # bounded: a host that never reads loses answers
            return []
        self._packets.extend(new)
        self._queued += size
        return self._fill()

    def _fill(self) -> list[Connection]:
        woken: list[Connection] = []
        while self._waiting and self._packets:
            conn, urb = self._waiting[0]
            if self._packets[0] and len(self._packets[0]) > urb.buffer_length - len(urb.data):
                if not urb.data:
                    # A packet larger than the buffer: the host controller reports babble.
                    urb.status = -errno.EOVERFLOW
                    self._complete(conn, urb)
                    woken.append(conn)
                    self._waiting.popleft()
                    continue
                self._waiting.popleft()
                self._complete(conn, urb)
                woken.append(conn)
                continue
            packet = self._packets.popleft()
            self._queued -= len(packet)
            urb.data += packet
            if len(packet) < PACKET or len(urb.data) >= urb.buffer_length:
                self._waiting.popleft()
                self._complete(conn, urb)
                woken.append(conn)
        return woken

    @staticmethod
    def _complete(conn: Connection, urb: Urb) -> None:
        conn.in_flight.pop(urb.key, None)
        conn.done.append(urb)

    # --- ioctls ---------------------------------------------------------------

    def check(self, conn: Connection) -> None:
        if conn.gone:
            raise UsbError(errno.ENODEV)

    def submit(self, conn: Connection, urb: Urb, buffer: bytes) -> None:
        """USBDEVFS_SUBMITURB; ``buffer`` is the URB's data (OUT and control)."""
        self.check(conn)
        if len(conn.in_flight) >= MAX_URBS or urb.key in conn.in_flight:
            raise UsbError(errno.EINVAL)
        if urb.buffer_length < 0:
            raise UsbError(errno.EINVAL)
        if urb.type == URB_TYPE_CONTROL:
            self._control(urb, buffer)
            conn.done.append(urb)
        elif urb.type == URB_TYPE_BULK and urb.endpoint == EP_OUT:
            urb.data = bytes(buffer[:urb.buffer_length])
            if urb.data:
                self.received.append(urb.data)
            conn.done.append(urb)
        elif urb.type == URB_TYPE_BULK and urb.endpoint == EP_IN:
            conn.in_flight[urb.key] = urb
            self._waiting.append((conn, urb))
            self._fill()
        else:
            raise UsbError(errno.ENOENT)  # usbdevfs: no such endpoint

    def discard(self, conn: Connection, key: int) -> None:
        """USBDEVFS_DISCARDURB: the URB completes with -ENOENT (unlinked)."""
        self.check(conn)
        urb = conn.in_flight.pop(key, None)
        if urb is None:
            raise UsbError(errno.EINVAL)
        self._waiting = deque(w for w in self._waiting if w[1] is not urb)
        urb.status = -errno.ENOENT
        conn.done.append(urb)

    def reap(self, conn: Connection) -> Optional[Urb]:
        """USBDEVFS_REAPURBNDELAY: the oldest completed URB, or None (EAGAIN)."""
        self.check(conn)
        return conn.done.popleft() if conn.done else None

    def _control(self, urb: Urb, setup_and_data: bytes) -> None:
        if len(setup_and_data) < 8:
            raise UsbError(errno.EINVAL)
        request_type, request, value, index, length = struct.unpack_from("<BBHHH", setup_and_data)
        reply: Optional[bytes] = None
        if request_type == 0x80 and request == 6:  # GET_DESCRIPTOR, device to host
            kind, number = value >> 8, value & 0xFF
            reply = self._descriptor(kind, number, index)
        elif request_type == 0x80 and request == 8:  # GET_CONFIGURATION
            reply = b"\x01"
        elif (request_type, request) in ((0x00, 9), (0x01, 11), (0x02, 1), (0x00, 1)):
            reply = b""  # SET_CONFIGURATION, SET_INTERFACE, CLEAR_FEATURE(endpoint/device)
        if reply is None:
            urb.status = -errno.EPIPE  # stall
            return
        urb.data = reply[:min(length, max(urb.buffer_length - 8, 0))]

    def _descriptor(self, kind: int, number: int, langid: int) -> Optional[bytes]:
        if kind == 1:
            return device_descriptor()
        if kind == 2 and number == 0:
            return configuration_descriptor()
        if kind != 3:
            return None
        if number == 0:
            return struct.pack("<BBH", 4, 3, LANGID_EN_US)
        texts = {1: MANUFACTURER, 2: PRODUCT, 3: self.serial}
        return string_descriptor(texts[number]) if number in texts else None


def sysfs_root_hub(bus: int) -> str:
    """The bus's root hub (Linux Foundation 1d6b:0002), which stays when units go.

    libusb's Linux backend refuses to start on a machine with no USB device at
    all, which is what an emulated bus with its only unit unplugged would be.
    """
    hub = struct.pack("<BBHBBBBHHHBBBB", 18, 1, 0x0200, 9, 0, 1, 64, 0x1D6B, 0x0002,
                      0x0601, 3, 2, 1, 1)
    hub_config = (struct.pack("<BBHBBBBB", 9, 2, 25, 1, 1, 0, 0xE0, 0)
                  + struct.pack("<BBBBBBBBB", 9, 4, 0, 0, 1, 9, 0, 0, 0)
                  + struct.pack("<BBBBHB", 7, 5, 0x81, 0x03, 4, 12))
    lines = [
        f"P: /devices/pci0000:00/0000:00:14.0/usb{bus}",
        "E: SUBSYSTEM=usb",
        "E: DEVTYPE=usb_device",
        "E: DRIVER=usb",
        f"E: BUSNUM={bus:03d}",
        "E: DEVNUM=001",
        f"A: busnum={bus}\\n",
        "A: devnum=1\\n",
        "A: idVendor=1d6b\\n",
        "A: idProduct=0002\\n",
        "A: bConfigurationValue=1\\n",
        "A: speed=480\\n",
        "H: descriptors=" + (hub + hub_config).hex(),
    ]
    return "\n".join(lines) + "\n"


def sysfs_device(unit: Unit, bus: int, address: int, sysname: str) -> str:
    """The ``umockdev`` description of one plugged unit (``add_from_string``).

    Sysfs values end with a newline, as the kernel prints them; the ``N:`` line
    makes umockdev create the device node that libusb opens.
    """
    node = f"bus/usb/{bus:03d}/{address:03d}"
    lines = [
        f"P: /devices/pci0000:00/0000:00:14.0/usb{bus}/{sysname}",
        f"N: {node}",
        "E: SUBSYSTEM=usb",
        "E: DEVTYPE=usb_device",
        "E: DRIVER=usb",
        f"E: BUSNUM={bus:03d}",
        f"E: DEVNUM={address:03d}",
        f"E: DEVNAME=/dev/{node}",
        f"E: PRODUCT={VENDOR_ID:x}/{PRODUCT_ID:x}/100",
        f"A: busnum={bus}\\n",
        f"A: devnum={address}\\n",
        f"A: idVendor={VENDOR_ID:04x}\\n",
        f"A: idProduct={PRODUCT_ID:04x}\\n",
        "A: bConfigurationValue=1\\n",
        "A: bNumConfigurations=1\\n",
        "A: speed=12\\n",
        f"A: manufacturer={MANUFACTURER}\\n",
        f"A: product={PRODUCT}\\n",
        f"A: serial={unit.serial}\\n",
        "H: descriptors=" + sysfs_descriptors().hex(),
    ]
    return "\n".join(lines) + "\n"
