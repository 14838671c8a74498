"""The simulator's CAN bus served over socketcand, on real loopback sockets.

python-can's own socketcand client is the compatibility test; a raw socket
plays the badly behaved clients.
"""
from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from typing import Iterator, List, Optional, Tuple

import can
import canopen
import pytest

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.socketcand import SocketcandServer, parse_address
from tests.helpers import wait_until

SDO_READ_1000 = bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])  # CiA 301 initiate upload 1000h:00


@pytest.fixture
def served() -> Iterator[Tuple[Epos4Simulator, SocketcandServer]]:
    sim = Epos4Simulator(1, [2])
    server = SocketcandServer(sim.channel).start()
    try:
        yield sim, server
    finally:
        server.close()
        sim.close()


def bus(server: SocketcandServer) -> can.BusABC:
    host, port = server.address
    return can.Bus(interface="socketcand", host=host, port=port, channel="can0")


def collect(client: can.BusABC, count: int, timeout: float = 10.0) -> List[can.Message]:
    got: List[can.Message] = []
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        msg = client.recv(0.1)
        if msg is not None:
            got.append(msg)
    return got


def frames(msgs: List[can.Message]) -> List[Tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in msgs]


class RawClient:
    """A hand-made client: sends text, reads ``< .. >`` messages."""

    def __init__(self, server: SocketcandServer, rawmode: bool = True,
                 rcvbuf: Optional[int] = None) -> None:
        self.sock = socket.socket()
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(10)
        self.sock.connect(server.address)
        self.buffer = b""
        assert self.read() == "< hi >"
        if rawmode:
            assert self.ask("< open can0 >") == "< ok >"
            assert self.ask("< rawmode >") == "< ok >"
            # Speaking after < rawmode > ends the server's wait for the < ok > to be read.
            self.sock.sendall(b"< echo >")
            while self.read() != "< echo >":
                pass

    def ask(self, text: str) -> str:
        self.sock.sendall(text.encode())
        return self.read()

    def read(self) -> str:
        while b">" not in self.buffer:
            chunk = self.sock.recv(4096)
            assert chunk, "the server closed the connection"
            self.buffer += chunk
        end = self.buffer.index(b">") + 1
        message, self.buffer = self.buffer[:end], self.buffer[end:]
        return message.decode().strip()

    def closed_by_server(self, timeout: float = 10.0) -> bool:
        self.sock.settimeout(timeout)
        try:
            while self.sock.recv(65536):
                pass
        except ConnectionResetError:
            pass
        return True

    def close(self) -> None:
        self.sock.close()


def test_two_clients_see_each_other_and_the_drives_in_one_order(served) -> None:
    _, server = served
    a, b = bus(server), bus(server)
    try:
        # a asks drive 2, b asks the EPOS4 (node 1) itself: raw SDO frames.
        a.send(can.Message(arbitration_id=0x602, data=SDO_READ_1000, is_extended_id=False))
        b.send(can.Message(arbitration_id=0x601, data=SDO_READ_1000, is_extended_id=False))
        a.send(can.Message(arbitration_id=0x1ABCDEF0, data=b"\x01", is_extended_id=True))
        seen_by_a = frames(collect(a, 3))  # b's request, both answers
        seen_by_b = frames(collect(b, 4))  # a's request and frame, both answers
        assert a.recv(0.3) is None and b.recv(0.3) is None  # nothing more: no own frames back
    finally:
        a.shutdown()
        b.shutdown()
    assert sorted(i for i, _ in seen_by_a) == [0x581, 0x582, 0x601]
    assert sorted(i for i, _ in seen_by_b) == [0x581, 0x582, 0x602, 0x1ABCDEF0]
    answer = dict(seen_by_b)[0x582]
    assert answer[0] == 0x43 and struct.unpack("<I", answer[4:])[0] == 0x00020192  # 1000h
    # The frames both saw (neither sent) come in the same order to both.
    assert [f for f in seen_by_a if f[0] in (0x581, 0x582)] == \
        [f for f in seen_by_b if f[0] in (0x581, 0x582)]


def test_the_simulated_nodes_see_a_clients_frames(served) -> None:
    sim, server = served
    listener = can.Bus(interface="virtual", channel=sim.channel)
    a = bus(server)
    try:
        a.send(can.Message(arbitration_id=0x18FF00AA, data=b"\x12\x34", is_extended_id=True))
        msg = listener.recv(10)
        while msg is not None and msg.arbitration_id != 0x18FF00AA:
            msg = listener.recv(10)
    finally:
        a.shutdown()
        listener.shutdown()
    assert msg is not None and msg.is_extended_id and bytes(msg.data) == b"\x12\x34"


def test_canopen_reads_a_drive_through_socketcand(served) -> None:
    _, server = served
    host, port = server.address
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0")
    try:
        node = network.add_node(2, canopen.ObjectDictionary())
        node.sdo.RESPONSE_TIMEOUT = 3.0
        assert struct.unpack("<I", node.sdo.upload(0x1000, 0))[0] == 0x00020192
        statusword = struct.unpack("<H", node.sdo.upload(0x6041, 0))[0]
        assert statusword & 0x4F in (0x40, 0x00, 0x21)  # a CiA 402 state after power-up
    finally:
        network.disconnect()


def test_rtr_echo_and_unsupported_commands(served) -> None:
    _, server = served
    watcher, sender = RawClient(server), RawClient(server)
    try:
        assert sender.ask("< echo >") == "< echo >"
        assert sender.ask("< subscribe 0 0 123 >").startswith("< error ")
        sender.sock.sendall(b"< sendrtr 123 4 >")
        assert watcher.read().split()[:2] == ["<", "rtr"]
        sender.sock.sendall(b"< send 00000123 1 ab >")
        assert watcher.read().split()[2] == "00000123"
    finally:
        watcher.close()
        sender.close()


def test_garbage_and_abrupt_clients_do_not_disturb_another(served) -> None:
    _, server = served
    good = bus(server)
    junk = RawClient(server, rawmode=False)
    rude = RawClient(server)
    try:
        assert junk.ask("< open can0 >") == "< ok >"  # BCM mode: its replies only
        for text in ["hello\r\n", "< bogus >", "< send xyz 1 00 >", "< send 123 2 11 >",
                     "\xff\xfe< \x00 >"]:
            junk.sock.sendall(text.encode("latin-1"))
        replies = [junk.read() for _ in range(4)]
        assert all(r.startswith("< error ") for r in replies), replies
        # An abrupt end: RST instead of FIN, in the middle of a command.
        rude.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        rude.sock.sendall(b"< send 12")
        rude.close()
        good.send(can.Message(arbitration_id=0x602, data=SDO_READ_1000, is_extended_id=False))
        (answer,) = frames(collect(good, 1))
        assert answer[0] == 0x582
        junk.sock.sendall(b"< echo >")
        assert junk.read() == "< echo >"
    finally:
        good.shutdown()
        junk.close()


def test_an_overlong_command_ends_only_that_connection(served, caplog) -> None:
    _, server = served
    other = RawClient(server)
    long = RawClient(server)
    with caplog.at_level(logging.WARNING, logger="epos_link.simulator.socketcand"):
        long.sock.sendall(b"< send " + b"1" * 5000)
        assert long.closed_by_server()
    assert "disconnected" in caplog.text
    other.sock.sendall(b"< echo >")
    assert other.read() == "< echo >"
    other.close()


def test_a_client_that_does_not_read_is_disconnected_alone(caplog) -> None:
    with Epos4Simulator(1, []) as sim, SocketcandServer(sim.channel, output_limit=1 << 16) as server:
        stuck = RawClient(server, rcvbuf=4096)  # after its handshake it reads nothing
        reader = RawClient(server)  # reads as fast as the server sends
        # The server's end of the stuck connection gets a small send buffer too: Linux
        # grows it up to 4 MB on loopback (tcp_wmem), 117,000 frames and 9-17 s of CPU
        # to fill before the server's own queue counts (issue 32); now about 2,000. The
        # reader's keeps the kernel's, so a loaded machine cannot make it lag.
        (end,) = [c for c in server._clients if c.peer == "%s:%d" % stuck.sock.getsockname()[:2]]
        end.transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        received: List[int] = []
        done = threading.Event()

        def read() -> None:
            reader.sock.settimeout(0.1)
            rest = b""
            while not done.is_set():
                try:
                    chunk = reader.sock.recv(1 << 20)
                except socket.timeout:
                    continue
                assert chunk, "the server closed the reader's connection"
                *messages, rest = (rest + chunk).split(b">")
                # < frame 181 TS DATA
                received.extend(int(m.split()[4], 16) for m in messages)

        thread = threading.Thread(target=read)
        thread.start()
        feeder = can.Bus(interface="virtual", channel=sim.channel)
        try:
            with caplog.at_level(logging.WARNING, logger="epos_link.simulator.socketcand"):
                # The stuck client's kernel buffers fill, then its queue: bounded work.
                for n in range(200_000):
                    feeder.send(can.Message(arbitration_id=0x181, data=struct.pack(">Q", n),
                                            is_extended_id=False))
                    if n % 100 == 99:
                        time.sleep(0.002)  # the reader keeps up; the stuck client does not read
                        if "did not read" in caplog.text:
                            break
                wait_until(lambda: "did not read" in caplog.text, why="the stuck client stays")
                wait_until(lambda: received[-1:] == [n], why="the reader misses frames")
            assert caplog.text.count("did not read") == 1
            assert received == list(range(n + 1))  # all of them, in order
        finally:
            done.set()
            thread.join(10)
            stuck.close()
            reader.close()
            feeder.shutdown()


def test_close_ends_clients_and_threads(served) -> None:
    _, server = served
    raw = RawClient(server)
    server.close()
    assert raw.closed_by_server()
    assert not any(t.is_alive() for t in server._threads)
    server.close()  # twice: nothing more to do


@pytest.mark.parametrize("text, expected", [
    ("127.0.0.1:0", ("127.0.0.1", 0)), (":29536", ("127.0.0.1", 29536)),
    ("[::1]:5", ("::1", 5)), ("localhost:65535", ("localhost", 65535)),
])
def test_addresses(text: str, expected: Tuple[str, int]) -> None:
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["", "nowhere", "host:", "host:-1", "host:65536", "h:1x"])
def test_bad_addresses(text: str) -> None:
    with pytest.raises(ValueError):
        parse_address(text)


def test_loopback_by_default() -> None:
    with Epos4Simulator(1, []) as sim, SocketcandServer(sim.channel) as server:
        host: Optional[str] = server.address[0]
    assert host == "127.0.0.1"
