"""The usbdevfs ioctl dispatcher against fake umockdev objects: every ioctl is
completed exactly once, whatever happens (an open ioctl hangs the client)."""
from __future__ import annotations

import errno
import struct
from typing import Any, Callable, Optional

import pytest

from epos_link.simulator import usb_model as m
from epos_link.simulator.usb_ioctl import Dispatcher
from epos_link.simulator.usb_model import Unit

NODE = "/dev/bus/usb/001/002"


class Data:
    """An IoctlData: local bytes, the client's address, children at offsets."""

    def __init__(self, data: bytes, addr: int = 0, children: Optional[dict[int, "Data"]] = None,
                 fail: bool = False) -> None:
        self.buf = bytearray(data)
        self.client_addr = addr
        self.children = children or {}
        self.fail = fail
        self.pointers: dict[int, "Data"] = {}

    def retrieve(self) -> list[int]:
        return list(self.buf)

    def resolve(self, offset: int, length: int) -> "Data":
        if self.fail:
            raise RuntimeError("client memory unreadable")
        return self.children.setdefault(offset, Data(bytes(length)))

    def update(self, offset: int, data: list[int]) -> None:
        self.buf[offset:offset + len(data)] = bytes(data)

    def set_ptr(self, offset: int, child: "Data") -> None:
        self.pointers[offset] = child


class Client:
    def __init__(self, request: int, arg: Data, devnode: str = NODE) -> None:
        self.request, self.arg, self.devnode = request, arg, devnode
        self.completions: list[tuple[int, int]] = []
        self.connected = True

    def get_request(self) -> int:
        return self.request

    def get_arg(self) -> Data:
        return self.arg

    def get_devnode(self) -> str:
        return self.devnode

    def get_connected(self) -> bool:
        return self.connected

    def connect(self, _signal: str, _handler: Callable[..., Any]) -> None:
        pass

    def complete(self, result: int, code: int) -> None:
        self.completions.append((result, code))


class Timers:
    def __init__(self) -> None:
        self.pending: dict[int, tuple[Callable[[int], bool], int]] = {}
        self.next = 1

    def add(self, _ms: int, fn: Callable[[int], bool], key: int) -> int:
        self.next += 1
        self.pending[self.next] = (fn, key)
        return self.next

    def remove(self, source: int) -> None:
        del self.pending[source]

    def fire_all(self) -> None:
        for source, (fn, key) in list(self.pending.items()):
            del self.pending[source]
            fn(key)


@pytest.fixture
def setup() -> tuple[Dispatcher, Unit, Timers, list[tuple[int, bytes]]]:
    unit = Unit("S1")
    timers = Timers()
    out: list[tuple[int, bytes]] = []
    d = Dispatcher([unit], on_out=lambda i, b: out.append((i, b)), timeout_add=timers.add,
                   source_remove=timers.remove)
    d.plug(0, NODE)
    return d, unit, timers, out


def urb_arg(endpoint: int, payload: bytes, length: int, addr: int = 0x7000) -> tuple[Data, Data]:
    raw = m.URB.pack(m.URB_TYPE_BULK, endpoint, 0, 0, 0x9000, length, 0, 0, 0, 0, 0, 0)
    buffer = Data(payload.ljust(length, b"\0"))
    urb = Data(raw, addr, {m.URB_BUFFER_OFFSET: buffer})
    return Data(b"", children={0: urb}), urb


def submit(d: Dispatcher, endpoint: int, payload: bytes, length: int) -> tuple[Client, Data]:
    """USBDEVFS_SUBMITURB of one bulk URB; (the client, the URB)."""
    arg, urb = urb_arg(endpoint, payload, length)
    client = Client(m.USBDEVFS_SUBMITURB, arg)
    d.handle(client)
    return client, urb


def reap(d: Dispatcher, conn_client: Client) -> Client:
    """The next ioctl on the same open file (umockdev: the same IoctlClient)."""
    conn_client.request, conn_client.arg = m.USBDEVFS_REAPURBNDELAY, Data(bytes(8))
    conn_client.completions.clear()
    d.handle(conn_client)
    return conn_client


def test_write_goes_to_the_simulator_and_the_urb_is_reaped(setup: Any) -> None:
    d, unit, timers, out = setup
    client, urb = submit(d, m.EP_OUT, b"\x90\x02", 2)
    assert client.completions == [(0, 0)] and out == [(0, b"\x90\x02")]
    reap(d, client)
    assert client.completions == [(0, 0)] and client.arg.children[0].pointers[0] is urb


def test_a_read_waits_for_the_answer_then_reaps_it(setup: Any) -> None:
    d, unit, timers, out = setup
    client, urb = submit(d, m.EP_IN, b"", 64)
    reap(d, client)
    assert client.completions == [] and timers.pending   # held, not spinning
    d.answer(0, b"answer")
    assert client.completions == [(0, 0)] and not timers.pending
    assert bytes(urb.children[m.URB_BUFFER_OFFSET].buf[:6]) == b"answer"
    actual = struct.unpack_from("=i", urb.buf, m.URB_ACTUAL_OFFSET)[0]
    assert actual == 6


def reading(d: Dispatcher) -> Client:
    """A client with an IN URB in flight (a read waiting for the device)."""
    client, _ = submit(d, m.EP_IN, b"", 64)
    assert client.completions == [(0, 0)]
    return client


def test_with_nothing_in_flight_a_reap_answers_eagain_at_once(setup: Any) -> None:
    d, unit, timers, out = setup
    client, _ = submit(d, m.EP_OUT, b"x", 1)
    reap(d, client)
    assert client.completions == [(0, 0)]                # the OUT URB
    reap(d, client)
    assert client.completions == [(-1, errno.EAGAIN)] and not timers.pending


def test_a_held_reap_answers_eagain_when_its_timer_fires(setup: Any) -> None:
    d, unit, timers, out = setup
    client = reading(d)
    reap(d, client)
    assert client.completions == []
    timers.fire_all()
    assert client.completions == [(-1, errno.EAGAIN)]


def test_a_held_reap_answers_enodev_when_the_cable_is_pulled(setup: Any) -> None:
    d, unit, timers, out = setup
    client = reading(d)
    reap(d, client)
    d.unplug(0)
    assert client.completions == [(-1, errno.ENODEV)] and not timers.pending


@pytest.mark.parametrize("request_, arg, expected", [
    (0x1234, Data(b""), (-1, errno.ENOTTY)),                          # unknown ioctl
    (m.USBDEVFS_SUBMITURB, Data(b"", fail=True), (-1, errno.EIO)),    # unreadable memory
    (m.USBDEVFS_GET_CAPABILITIES, Data(b"", fail=True), (-1, errno.EIO)),
    (m.USBDEVFS_DISCARDURB, Data(bytes(8)), (-1, errno.EINVAL)),      # no such URB
    (m.USBDEVFS_GETDRIVER, Data(b""), (-1, errno.ENODATA)),           # no kernel driver
])
def test_every_ioctl_completes_exactly_once(setup: Any, request_: int, arg: Data,
                                            expected: tuple[int, int]) -> None:
    d, unit, timers, out = setup
    client = Client(request_, arg)
    assert d.handle(client) is True
    assert client.completions == [expected]


def test_an_exception_in_the_model_completes_with_eio(setup: Any, monkeypatch: Any,
                                                        capsys: Any) -> None:
    d, unit, timers, out = setup

    def boom(*_: Any) -> None:
        raise KeyError("bug")

    monkeypatch.setattr(unit, "submit", boom)
    client, _ = submit(d, m.EP_OUT, b"x", 1)
    assert client.completions == [(-1, errno.EIO)]
    assert "KeyError" in capsys.readouterr().err


def test_a_node_of_an_unplugged_unit_answers_enodev(setup: Any) -> None:
    d, unit, timers, out = setup
    old = Client(m.USBDEVFS_CLAIMINTERFACE, Data(b""))
    d.handle(old)
    d.unplug(0)
    d.plug(0, "/dev/bus/usb/001/003")
    d.handle(old)
    assert old.completions == [(0, 0), (-1, errno.ENODEV)]
    stranger = Client(m.USBDEVFS_CLAIMINTERFACE, Data(b""), devnode="/dev/bus/usb/001/099")
    d.handle(stranger)
    assert stranger.completions == [(-1, errno.ENODEV)]


def test_a_vanished_client_frees_its_connection_and_timer(setup: Any) -> None:
    d, unit, timers, out = setup
    client = reading(d)
    reap(d, client)
    assert timers.pending
    client.connected = False
    d.vanished(client)
    assert not timers.pending and unit.connections == [] and d.conns == {}


def test_a_timer_that_fires_at_once_in_the_main_loop_thread_still_answers_the_hold() -> None:
    """umockdev runs the handler in its own thread; the timer may fire before the
    handler has stored the hold. It must wait for the handler, then answer EAGAIN."""
    import threading

    threads: list[threading.Thread] = []

    def timeout_add(_ms: int, fn: Callable[[int], bool], key: int) -> int:
        t = threading.Thread(target=fn, args=(key,))
        t.start()
        threads.append(t)
        return len(threads)

    d = Dispatcher([Unit("S1")], on_out=lambda i, b: None, timeout_add=timeout_add,
                   source_remove=lambda _s: None)
    d.plug(0, NODE)
    client = reading(d)
    reap(d, client)
    for t in threads:
        t.join(10)
    assert client.completions == [(-1, errno.EAGAIN)] and d.held == {}
