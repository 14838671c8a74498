"""A socketcand client's frames reach the simulated bus however its connection ends.

On a CAN bus a frame that was sent is on the bus, whatever its sender does next.
A python-can client that closes its socket with frames still unread ends the
connection with a TCP reset; the frames it sent just before must still reach the
bus (issue 34: ``examples/pp_move.py``'s last frame, the new set-point, was lost).
:mod:`epos_link.simulator.socketcand`, "A client's frames reach the bus".
"""
from __future__ import annotations

import socket
import struct
import threading
import time
from typing import Iterator

import can
import pytest

from epos_link.simulator.socketcand import DRAIN_LIMIT, SocketcandServer, _drain
from tests.test_sim_socketcand import RawClient

CHANNEL = "i34-socketcand-close"


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    channel = f"{CHANNEL}-{time.monotonic_ns()}"
    with SocketcandServer(channel) as served:
        yield served


def _wait_for(peer: can.BusABC, can_id: int, timeout: float = 10.0) -> can.Message | None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = peer.recv(0.1)
        if msg is not None and msg.arbitration_id == can_id:
            return msg
    return None


def _reset_close(sock: socket.socket) -> None:
    """Close as python-can's shutdown() does with frames unread: a TCP reset (forced
    with SO_LINGER 0 so the test does not depend on what is unread)."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_a_frame_sent_just_before_a_reset_reaches_the_bus(server: SocketcandServer) -> None:
    """The server's loop is busy while the client sends its last frame and resets; when
    the loop runs again, its first act on that connection is a write (a frame of the
    bus for the client), which fails with the reset. The frame must still go out."""
    peer = can.Bus(interface="virtual", channel=server.channel, receive_own_messages=False)
    try:
        client = RawClient(server)
        blocked = threading.Event()

        def busy() -> None:
            blocked.set()
            time.sleep(0.5)

        server._loop.call_soon_threadsafe(busy)
        assert blocked.wait(10)
        # Queued behind busy(): a frame for the client (its write meets the reset) ...
        peer.send(can.Message(arbitration_id=0x181, data=b"\x37\x06", is_extended_id=False))
        time.sleep(0.05)  # the server's bus reader has queued its delivery
        # ... and the client's last frame, then the reset.
        client.sock.sendall(b"< send 402 6 1f 00 20 4e 00 00 >")
        _reset_close(client.sock)
        got = _wait_for(peer, 0x402)
        assert got is not None, "the frame sent before the reset never reached the bus"
        assert bytes(got.data) == bytes.fromhex("1f00204e0000")
    finally:
        peer.shutdown()


def test_every_frame_of_a_burst_before_a_reset_reaches_the_bus(server: SocketcandServer) -> None:
    peer = can.Bus(interface="virtual", channel=server.channel, receive_own_messages=False)
    try:
        client = RawClient(server)
        server._loop.call_soon_threadsafe(time.sleep, 0.3)
        peer.send(can.Message(arbitration_id=0x181, data=b"\x37\x06", is_extended_id=False))
        time.sleep(0.05)
        client.sock.sendall(b"".join(f"< send 300 1 {k:02x} >".encode() for k in range(50)))
        _reset_close(client.sock)
        seen = []
        deadline = time.monotonic() + 10
        while len(seen) < 50 and time.monotonic() < deadline:
            msg = peer.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x300:
                seen.append(msg.data[0])
        assert seen == list(range(50)), "frames lost or reordered at the reset"
    finally:
        peer.shutdown()


def test_the_server_serves_others_after_a_reset(server: SocketcandServer) -> None:
    first = RawClient(server)
    _reset_close(first.sock)
    second = RawClient(server)
    assert second.ask("< echo >") == "< echo >"
    second.sock.close()


def test_drain_reads_what_a_reset_socket_holds_then_stops() -> None:
    a, b = socket.socketpair()
    try:
        a.sendall(b"< send 123 0 >")
        a.close()
        b.setblocking(False)
        assert _drain(b.fileno()) == b"< send 123 0 >"
        assert _drain(b.fileno()) == b""
    finally:
        b.close()


def test_drain_is_bounded() -> None:
    a, b = socket.socketpair()
    try:
        b.setblocking(False)
        a.sendall(b"x" * 5000)
        assert len(_drain(b.fileno(), limit=1000)) == 1000
        assert DRAIN_LIMIT >= 1 << 16
    finally:
        a.close()
        b.close()
