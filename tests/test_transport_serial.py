"""The pyserial transport over a real TCP socket, a pseudo-terminal, and pyserial's own URLs."""
from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Iterator, List, Tuple

import pytest

from epos_link.client import EposClient
from epos_link.errors import EposTimeoutError, TransportError
from epos_link.transports import open_transport
from epos_link.transports.serial import SerialTransport, open_serial
from tests.responder import PtyResponder, SocketResponder, read_pair

REQUEST, ANSWER = read_pair(1, 0x6064, 0, (1000).to_bytes(4, "little"))
pytestmark = pytest.mark.skipif(os.name != "posix", reason="pseudo-terminals are POSIX")


def read_all(link: SerialTransport, count: int, timeout: float = 1.0) -> bytes:
    got = b""
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        got += link.read(count - len(got), deadline - time.monotonic())
    return got


def test_socket_url_round_trip_and_reader() -> None:
    with SocketResponder({REQUEST: ANSWER}) as dev:
        link = open_transport(dev.url)
        assert isinstance(link, SerialTransport) and link._read == link._read_socket
        link.write(REQUEST)
        assert read_all(link, len(ANSWER)) == ANSWER
        link.close()
        link.close()  # idempotent


def test_pty_opened_like_a_serial_port() -> None:
    with PtyResponder({REQUEST: ANSWER}) as dev:
        link = open_serial(dev.path, baudrate=115200)
        assert link._read == link._read_fd and link._port.baudrate == 115200
        link.write(REQUEST)
        assert read_all(link, len(ANSWER)) == ANSWER
        link.close()


@pytest.mark.parametrize("kind", ["socket", "pty", "spy"])
def test_read_timeout_returns_nothing_in_time(kind: str) -> None:
    responder = SocketResponder({}) if kind == "socket" else PtyResponder({})
    with responder as dev:
        url = {"socket": getattr(dev, "url", ""), "pty": getattr(dev, "path", ""),
               "spy": f"spy://{getattr(dev, 'path', '')}?file=/dev/null"}[kind]
        link = open_transport(url)
        start = time.monotonic()
        assert link.read(100, 0.05) == b""
        took = time.monotonic() - start
        assert 0.04 <= took < 2.0  # waited, and returned (40x slack)
        assert link.read(100, 0) == b""
        link.close()


def test_generic_reader_over_spy_url_returns_what_is_there() -> None:
    with PtyResponder({REQUEST: ANSWER}) as dev:
        link = open_transport(f"spy://{dev.path}?file=/dev/null")
        assert isinstance(link, SerialTransport) and link._read == link._read_generic
        link.write(REQUEST)
        assert read_all(link, len(ANSWER)) == ANSWER
        link.close()


def test_loop_url() -> None:
    link = open_transport("loop://")
    link.write(b"\x90\x02abc")
    assert read_all(link, 5) == b"\x90\x02abc"
    link.write(b"stale")
    time.sleep(0.01)
    link.reset_input()
    assert link.read(10, 0.01) == b""
    link.close()


def test_reset_input_discards_pending_bytes_on_a_pty() -> None:
    with PtyResponder({}) as dev:
        link = open_serial(dev.path)
        os.write(dev.master, b"stale bytes")
        time.sleep(0.02)
        link.reset_input()
        assert link.read(100, 0.02) == b""
        link.close()


def test_missing_device_is_a_transport_error() -> None:
    with pytest.raises(TransportError, match="cannot open /dev/does-not-exist"):
        open_transport("/dev/does-not-exist")
    with pytest.raises(TransportError, match="cannot open"):
        open_transport("nosuchscheme://x")


def test_refused_socket_is_a_transport_error() -> None:
    with SocketResponder({}) as dev:
        port = dev.port
    time.sleep(0.1)  # the listener is closed now
    with pytest.raises(TransportError):
        open_transport(f"socket://127.0.0.1:{port}")


def test_closed_transport_refuses_io() -> None:
    link = open_transport("loop://")
    link.close()
    for call in (lambda: link.write(b"x"), lambda: link.read(1, 0), link.reset_input):
        with pytest.raises(TransportError, match="closed"):
            call()


def test_pty_hang_up_is_a_transport_error() -> None:
    dev = PtyResponder({})
    link = open_serial(dev.path)
    dev.hang_up()
    with pytest.raises(TransportError):
        link.read(10, 0.2)
    link.close()


def test_broken_socket_is_reopened_by_the_client() -> None:
    with SocketResponder({REQUEST: ANSWER}) as dev:
        client = EposClient(open_transport(dev.url), timeout=5.0)  # answers come in ms
        assert client.read_object(1, 0x6064, 0) == (1000).to_bytes(4, "little")
        # The connection breaks: the next call fails, reopens (a new connection) and retries.
        client.transport._sock.shutdown(2)  # type: ignore[attr-defined]
        assert client.read_object(1, 0x6064, 0) == (1000).to_bytes(4, "little")
        assert dev.connections == 2
        client.close()


def test_client_over_pty_times_out_on_a_silent_device() -> None:
    with PtyResponder({}) as dev:
        client = EposClient(open_serial(dev.path), timeout=0.05, retries=0)
        with pytest.raises(EposTimeoutError):
            client.read_object(1, 0x6064, 0)
        client.close()


@pytest.fixture
def pty_port() -> Iterator[Tuple[int, SerialTransport]]:
    """(master fd, the slave opened as a serial port at 115200 baud)."""
    import pty as pty_module

    master, slave = pty_module.openpty()
    link = open_serial(os.ttyname(slave), baudrate=115200)
    try:
        yield master, link
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_read_some_wakes_once_when_the_wanted_bytes_are_in(
        pty_port: Tuple[int, SerialTransport]) -> None:
    # VMIN = wanted (VTIME 0): the port turns readable only once all of them are
    # in, so an answer sent byte by byte is read in one piece, by one wake-up.
    master, link = pty_port

    def dribble() -> None:
        for b in b"\x90\x02\x00\x04\x00":
            os.write(master, bytes([b]))
            time.sleep(0.02)

    writer = threading.Thread(target=dribble)
    writer.start()
    assert link.read_some(16, 5.0, wanted=5) == b"\x90\x02\x00\x04\x00"
    writer.join()
    # A plain read() takes the first byte that comes, as before.
    os.write(master, b"\x01\x02")
    assert link.read(16, 5.0)[:1] == b"\x01"


def test_read_some_returns_what_came_at_the_deadline(
        pty_port: Tuple[int, SerialTransport]) -> None:
    # Fewer bytes than wanted (a lost byte, a short answer): at the deadline the
    # reader gets what is there, so the client can say what it heard.
    master, link = pty_port
    os.write(master, b"\x90\x02\x00")
    time.sleep(0.05)
    assert link.read_some(16, 0.1, wanted=9) == b"\x90\x02\x00"
    assert link.read_some(16, 0.05, wanted=9) == b""  # nothing more: nothing


def test_read_some_sleeps_while_the_wanted_bytes_are_on_the_wire_without_vmin(
        pty_port: Tuple[int, SerialTransport]) -> None:
    # Where VMIN cannot be set, the reader sleeps instead. At 115200 baud a byte
    # takes 10 / 115200 s (8N1, guide 2.2.6): with 9 bytes wanted and 1 already
    # received, 7 more are certainly still on the wire.
    master, link = pty_port
    link._vmin = 0  # what open() finds on a port that is not a terminal
    pauses: list = []
    link._sleep = pauses.append  # type: ignore[assignment]
    os.write(master, b"\x90\x02")
    deadline = time.monotonic() + 5
    while not link.read_some(1, 0.0, wanted=1) and time.monotonic() < deadline:
        pass  # take one byte, leave one waiting
    assert link.read_some(16, 1.0, wanted=9) == b"\x02"
    assert pauses == [pytest.approx(7 * 10 / 115200)]
    os.write(master, b"\x00\x04")  # bytes already there: no pause
    time.sleep(0.05)
    pauses.clear()
    assert link.read_some(16, 1.0, wanted=3) == b"\x00\x04"
    assert pauses == []


@contextlib.contextmanager
def watched(client: EposClient) -> Iterator[Tuple[List[int], List[int]]]:
    """(VMIN values the serial transport sets, bytes of each read it wakes up for)."""
    import epos_link.transports.serial as serial_module

    transport = client.transport
    assert isinstance(transport, SerialTransport)
    sets: List[int] = []
    reads: List[int] = []
    set_vmin, read_fd = serial_module._set_vmin, transport._read_fd

    def setting(fd: int, vmin: int) -> bool:
        sets.append(vmin)
        return set_vmin(fd, vmin)

    def reading(n: int, t: float) -> bytes:
        data = read_fd(n, t)
        reads.append(len(data))
        return data

    serial_module._set_vmin = setting
    transport._read_fd = reading  # type: ignore[method-assign]
    try:
        yield sets, reads
    finally:
        serial_module._set_vmin = set_vmin
        transport._read_fd = read_fd  # type: ignore[method-assign]


def test_status_reads_wake_once_per_answer_that_comes_in_one_piece() -> None:
    # A USB-RS232 adapter hands an answer over in one USB packet: then a status
    # poll (ReadObject, guide 2.1.1.1: 14 bytes) is read by one wake-up and the
    # terminal's settings stay put from one poll to the next. That matters there:
    # on an FTDI adapter each tcsetattr is a USB control transfer (Linux
    # ftdi_sio.c, ftdi_set_termios sets the flow control every time).
    with PtyResponder({REQUEST: ANSWER}) as dev:
        client = EposClient(open_serial(dev.path, baudrate=115200), timeout=5.0)
        try:
            client.read_object(1, 0x6064, 0)  # warm-up: VMIN settles
            with watched(client) as (sets, reads):
                for _ in range(10):
                    assert client.read_object(1, 0x6064, 0) == (1000).to_bytes(4, "little")
            assert sets == [], f"{len(sets)} termios changes for 10 reads: {sets}"
            assert len(reads) == 10, f"{len(reads)} wake-ups for 10 answers"
        finally:
            client.close()


def test_an_answer_that_trickles_in_wakes_the_reader_just_before_its_last_bytes() -> None:
    # A UART (here the simulator, paced at 115200 Bd) delivers byte by byte: the
    # first wake-up comes WAKE_EARLY bytes before the answer's end, the second
    # with its last byte; never one per byte.
    from epos_link.client import WAKE_EARLY
    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import LinkOptions, PtyLink

    sim = Epos4Simulator(1, [])
    link = PtyLink(sim, LinkOptions(baud=115200)).start()
    client = EposClient.open(link.path, baudrate=115200, gateway_node_id=1)
    try:
        client.read_object(0, 0x6041, 0)  # warm-up
        with watched(client) as (sets, got):
            for _ in range(10):
                client.read_object(0, 0x6041, 0)
        assert len(got) <= 20, f"{len(got)} wake-ups for 10 answers: {got}"
        assert sum(got) == 10 * 14
        # Woken at 12 bytes (or a little later: 13), then VMIN = what is left.
        assert set(sets) <= {14 - WAKE_EARLY, WAKE_EARLY, 1}, sets
    finally:
        client.close()
        link.close()
        sim.close()


def test_an_answer_after_noise_with_a_false_sync_is_read_when_it_arrives() -> None:
    # Line noise that happens to contain DLE STX and a large Len
    # byte opens a frame that "still needs" ~126 bytes; VMIN is set to that, so the
    # real answer that follows (14 bytes, whose own DLE STX would resynchronise the
    # decoder at once) does not wake the reader: it is read only at the deadline.
    # The reader must wake for the real answer (~20 ms after the noise).
    import pty as pty_module
    import tty as tty_module

    master, slave = pty_module.openpty()
    tty_module.setraw(master)
    client = EposClient(open_serial(os.ttyname(slave), baudrate=115200), timeout=5.0, retries=0)

    def device() -> None:
        got = b""
        while len(got) < len(REQUEST):
            got += os.read(master, 100)
        os.write(master, b"\x11\x22\x33\x44\x55\x66\x90\x02\x00\x3f")  # noise, false sync, Len 63
        time.sleep(0.02)
        os.write(master, ANSWER)

    writer = threading.Thread(target=device)
    writer.start()
    try:
        started = time.monotonic()
        with watched(client) as (sets, _):
            assert client.read_object(1, 0x6064, 0) == (1000).to_bytes(4, "little")
        assert max(sets, default=0) <= len(ANSWER)  # never waits for the false frame's bytes
        assert time.monotonic() - started < 2.5  # 100x the expected; the whole timeout is 5 s
    finally:
        writer.join()
        client.close()
        os.close(master)
        os.close(slave)
