"""The USB transport against fake pyusb device objects: descriptors, bulk reads and
writes, timeouts, permissions and unplugging, without hardware.

The fakes mimic what pyusb's ``Device`` offers: descriptor fields, iteration
over configurations/interfaces/endpoints (what ``usb.util.find_descriptor``
walks), ``read``/``write`` on endpoint addresses with millisecond timeouts,
and the ``_ctx`` that ``usb.util.claim_interface`` and friends call.
"""
from __future__ import annotations

import array
import errno
import time
from typing import Any, Optional

import pytest
import usb.core

from epos_link.client import EposClient
from epos_link.errors import EposTimeoutError, TransportError
from epos_link.transports import open_transport
from epos_link.transports import usb as usb_transport
from epos_link.transports.usb import UDEV_RULE, UsbTransport, find_bulk_endpoints, list_usb_devices, open_usb
from tests.responder import read_pair, segmented_read_pairs

BULK, INTERRUPT = 0x02, 0x03
VALUE = (1000).to_bytes(4, "little")
NAME = b"EPOS4 Compact 50/8 CAN"


class Endpoint:
    def __init__(self, address: int, attributes: int = BULK, packet: int = 64) -> None:
        self.bEndpointAddress = address
        self.bmAttributes = attributes
        self.wMaxPacketSize = packet


class Interface:
    def __init__(self, number: int, cls: int, endpoints: list[Endpoint]) -> None:
        self.bInterfaceNumber = number
        self.bAlternateSetting = 0
        self.bInterfaceClass = cls
        self.endpoints = endpoints

    def __iter__(self) -> Any:
        return iter(self.endpoints)


class Configuration:
    bConfigurationValue = 1

    def __init__(self, interfaces: list[Interface]) -> None:
        self.interfaces = interfaces

    def __iter__(self) -> Any:
        return iter(self.interfaces)


def epos4_configuration(packet: int = 64) -> Configuration:
    """A CDC-like control interface, then the vendor interface with bulk 0x81 IN / 0x01 OUT."""
    return Configuration([
        Interface(0, 0x02, [Endpoint(0x82, INTERRUPT, 16)]),
        Interface(1, 0xFF, [Endpoint(0x01, BULK, packet), Endpoint(0x81, BULK, packet)]),
    ])


class Context:
    def __init__(self) -> None:
        self.claimed: list[int] = []
        self.released: list[int] = []
        self.disposed = 0

    def managed_claim_interface(self, device: Any, interface: int) -> None:
        self.claimed.append(interface)

    def managed_release_interface(self, device: Any, interface: int) -> None:
        self.released.append(interface)

    def dispose(self, device: Any) -> None:
        self.disposed += 1


class FakeDevice:
    """An EPOS4 24E7:3B01 that answers a script of whole request frames."""

    idVendor, idProduct = 0x24E7, 0x3B01

    def __init__(self, script: dict[bytes, Optional[bytes]], *, serial: Optional[str] = "0123456789AB",
                 config: Optional[Configuration] = None, configured: bool = True,
                 kernel_driver: bool = False, permission_denied: bool = False) -> None:
        self.script = script
        self._serial = serial
        self.config = config or epos4_configuration()
        self.configured = configured
        self.kernel_driver = kernel_driver
        self.permission_denied = permission_denied
        self.bus, self.address = 1, 7
        self._ctx = Context()
        self.inbox = bytearray()
        self.outbox: list[bytes] = []
        self.requests: list[bytes] = []
        self.read_timeouts: list[int] = []
        self.endpoints_used: set[tuple[str, int]] = set()
        self.unplug_after_reads: Optional[int] = None
        self.unplugged = False
        self.late: list[bytes] = []  # answers that arrive only after a timed-out read

    @property
    def serial_number(self) -> str:
        if self._serial is None:
            raise ValueError("The device has no langid (permission issue, no string descriptors "
                             "supported or device error)")
        return self._serial

    def _check(self) -> None:
        if self.permission_denied:
            raise usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES)
        if self.unplugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)

    def get_active_configuration(self) -> Configuration:
        self._check()
        if not self.configured:
            raise usb.core.USBError("Configuration not set")
        return self.config

    def set_configuration(self) -> None:
        self._check()
        self.configured = True

    def is_kernel_driver_active(self, number: int) -> bool:
        return self.kernel_driver

    def detach_kernel_driver(self, number: int) -> None:
        self.kernel_driver = False

    def write(self, endpoint: int, data: bytes, timeout: int) -> int:
        self._check()
        self.endpoints_used.add(("write", endpoint))
        self.inbox += bytes(data)
        for request, reply in self.script.items():
            if bytes(self.inbox).startswith(request):
                del self.inbox[:len(request)]
                self.requests.append(request)
                if reply is not None:
                    self.outbox.append(reply)
        return len(data)

    def read(self, endpoint: int, size: int, timeout: int) -> array.array:
        self._check()
        self.endpoints_used.add(("read", endpoint))
        assert timeout >= 1, "libusb reads 0 ms as 'wait forever'"
        if self.unplug_after_reads is not None:
            if self.unplug_after_reads == 0:
                self.unplugged = True
                self._check()
            self.unplug_after_reads -= 1
        if not self.outbox:
            self.read_timeouts.append(timeout)
            if self.late:
                self.outbox.append(self.late.pop(0))  # arrives after this read gave up
            time.sleep(timeout / 1000)
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        head = self.outbox[0]
        chunk, rest = head[:size], head[size:]
        if rest:
            self.outbox[0] = rest
        else:
            self.outbox.pop(0)
        return array.array("B", chunk)


class Finder:
    """Stands in for ``usb.core.find``; ``devices`` can change between calls (replug)."""

    def __init__(self, *devices: FakeDevice) -> None:
        self.devices = list(devices)
        self.calls = 0
        self.no_backend = False

    def __call__(self, *, find_all: bool, idVendor: int, idProduct: int, backend: Any) -> Any:
        assert find_all and (idVendor, idProduct) == (0x24E7, 0x3B01)
        self.calls += 1
        if self.no_backend:
            raise usb.core.NoBackendError("No backend available")
        return iter(list(self.devices))


SCRIPT = dict([read_pair(1, 0x6064, 0, VALUE), *segmented_read_pairs(1, 0x1008, 0, NAME)])


@pytest.fixture(autouse=True)
def no_ftdi_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(usb_transport, "list_ftdi_ports", lambda: [])


def client_for(*devices: FakeDevice, url: str = "usb://", **options: Any) -> tuple[EposClient, Finder]:
    finder = Finder(*devices)
    options.setdefault("timeout", 0.05)
    return EposClient(open_usb(url, find=finder, backend=object()), **options), finder


def test_endpoints_come_from_the_descriptors() -> None:
    dev = FakeDevice(SCRIPT, config=Configuration([
        Interface(0, 0x0A, [Endpoint(0x83), Endpoint(0x04)]),   # bulk pair, but not vendor class
        Interface(3, 0xFF, [Endpoint(0x85, INTERRUPT), Endpoint(0x86), Endpoint(0x07)]),
    ]))
    client, _ = client_for(dev)
    assert client.read_object(1, 0x6064, 0) == VALUE
    assert dev.endpoints_used == {("write", 0x07), ("read", 0x86)}
    assert dev._ctx.claimed == [3]


def test_non_vendor_interface_with_bulk_pair_is_used_when_it_is_the_only_one() -> None:
    intf, ep_in, ep_out = find_bulk_endpoints(Configuration([
        Interface(0, 0x02, [Endpoint(0x81, INTERRUPT)]),
        Interface(1, 0x0A, [Endpoint(0x02), Endpoint(0x83)]),
    ]))
    assert (intf.bInterfaceNumber, ep_in.bEndpointAddress, ep_out.bEndpointAddress) == (1, 0x83, 0x02)


def test_no_bulk_endpoints_is_a_transport_error() -> None:
    dev = FakeDevice(SCRIPT, config=Configuration([Interface(0, 0xFF, [Endpoint(0x81, INTERRUPT)])]))
    with pytest.raises(TransportError, match="bulk IN and OUT"):
        client_for(dev)


def test_answers_in_small_packets_are_reassembled() -> None:
    dev = FakeDevice(SCRIPT, config=epos4_configuration(packet=8))
    client, _ = client_for(dev)
    assert client.read_object(1, 0x6064, 0) == VALUE
    assert client.upload(1, 0x1008, 0) == NAME


def test_unconfigured_device_and_kernel_driver() -> None:
    dev = FakeDevice(SCRIPT, configured=False, kernel_driver=True)
    client, _ = client_for(dev)
    assert dev.configured and not dev.kernel_driver
    assert client.read_object(1, 0x6064, 0) == VALUE
    client.close()
    assert dev._ctx.released == [1] and dev._ctx.disposed == 1


def test_silent_device_times_out_with_whole_millisecond_reads() -> None:
    dev = FakeDevice({})
    client, _ = client_for(dev, retries=0)
    with pytest.raises(EposTimeoutError):
        client.read_object(1, 0x6064, 0)
    assert dev.read_timeouts and min(dev.read_timeouts) >= 1


def test_unplug_mid_transfer_reopens_and_restarts_the_transfer() -> None:
    first = FakeDevice(SCRIPT)
    client, finder = client_for(first)
    first.unplug_after_reads = 1  # the Initiate answer is read, the SegmentRead answer is not
    second = FakeDevice(SCRIPT)   # the same unit, replugged
    finder.devices = [second]
    assert client.upload(1, 0x1008, 0) == NAME
    assert [r[2] for r in first.requests] == [0x81, 0x62]
    assert [r[2] for r in second.requests] == [0x81, 0x62]  # from the beginning, not the middle
    assert finder.calls == 2


def test_unplug_without_retry_raises_and_the_next_request_reopens() -> None:
    first = FakeDevice(SCRIPT)
    client, finder = client_for(first, retries=0)
    first.unplugged = True
    with pytest.raises(TransportError, match="No such device"):
        client.read_object(1, 0x6064, 0)
    second = FakeDevice(SCRIPT)
    finder.devices = [second]
    assert client.read_object(1, 0x6064, 0) == VALUE
    assert finder.calls == 2


def test_reopen_finds_the_same_unit_by_serial_number() -> None:
    mine, other = FakeDevice(SCRIPT, serial="B"), FakeDevice(SCRIPT, serial="A")
    client, finder = client_for(mine)
    assert client.transport.serial == "B"  # type: ignore[attr-defined]
    mine.unplugged = True
    finder.devices = [other, FakeDevice(SCRIPT, serial="B")]
    assert client.read_object(1, 0x6064, 0) == VALUE
    assert other.requests == []


def test_late_answer_is_drained_after_a_timeout() -> None:
    request, _ = read_pair(1, 0x6064, 0, VALUE)
    stale = read_pair(1, 0x6064, 0, b"\x11" * 4)[1]
    dev = FakeDevice({request: None})
    dev.late = [stale]
    client, _ = client_for(dev, retries=0)
    with pytest.raises(EposTimeoutError):
        client.read_object(1, 0x6064, 0)
    dev.script = SCRIPT
    assert client.read_object(1, 0x6064, 0) == VALUE  # not the stale 0x11111111


def test_permission_problem_names_the_udev_rule() -> None:
    with pytest.raises(TransportError) as info:
        client_for(FakeDevice(SCRIPT, permission_denied=True))
    assert "permission denied" in str(info.value) and UDEV_RULE in str(info.value)


def test_missing_backend_says_what_to_install() -> None:
    finder = Finder()
    finder.no_backend = True
    with pytest.raises(TransportError, match="libusb-package"):
        open_usb("usb://", find=finder, backend=None)


def test_selection_by_serial_and_index() -> None:
    a, b = FakeDevice(SCRIPT, serial="A"), FakeDevice(SCRIPT, serial="B")
    finder = Finder(a, b)
    assert open_usb("usb://?serial=B", find=finder, backend=object())._dev is b
    assert open_usb("usb://?index=1", find=finder, backend=object())._dev is b
    assert open_transport("usb://", find=finder, backend=object())._dev is a  # type: ignore[attr-defined]
    with pytest.raises(TransportError, match="serial number C"):
        open_usb("usb://?serial=C", find=finder, backend=object())
    with pytest.raises(TransportError, match="unknown option"):
        open_usb("usb://?baud=3", find=finder, backend=object())


def test_no_device_mentions_the_ids_and_an_ftdi_port(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(TransportError, match="24E7:3B01"):
        open_usb("usb://", find=Finder(), backend=object())

    class Port:
        device = "/dev/ttyUSB7"

    monkeypatch.setattr(usb_transport, "list_ftdi_ports", lambda: [Port()])
    with pytest.raises(TransportError, match="/dev/ttyUSB7"):
        open_usb("usb://", find=Finder(), backend=object())


def test_list_usb_devices() -> None:
    found = list_usb_devices(find=Finder(FakeDevice(SCRIPT, serial="A"), FakeDevice(SCRIPT, serial=None)),
                             backend=object())
    assert [(d.serial, d.url) for d in found] == [("A", "usb://?serial=A"), (None, "usb://")]


def test_closed_transport_refuses_io() -> None:
    link = open_usb("usb://", find=Finder(FakeDevice(SCRIPT)), backend=object())
    link.close()
    link.close()
    with pytest.raises(TransportError, match="closed"):
        link.write(b"x")
    with pytest.raises(TransportError, match="closed"):
        link.read(1, 0.01)
    assert isinstance(link, UsbTransport)
