"""Issue 22, items 1 and 3: one request, one meaning, with clients on both ports.

The bridge behaves as one serial MasterMACS: each request is resolved in the order
it arrived, from any connection, against the state every earlier request left, and
its values are fixed then. A move queued behind a busy bus keeps the master's and
the slave's targets of that moment; a stop or disable of a master acts on the
slaves its move started. Each test drives two TCP clients (ports 1912 and 1913 of
the real server: here two free ports) and watches the simulated drives.
"""
from __future__ import annotations

import asyncio
import socket
import threading
from typing import Iterator, List, Tuple

import pytest

from tcp_bridge.wire import REPLY_SIZE, Status, decode_reply
from tests.bridge_sim import SimBridge
from tests.helpers import psi_ask, wait_until

FACTOR = 1000  # user units are mm; the drives count increments


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge()
    yield b
    b.close()


def second_port(b: SimBridge) -> socket.socket:
    return socket.create_connection(b.server.addresses[1], timeout=30)


def hold_bus(b: SimBridge) -> threading.Event:
    """Another request holds the bus: its worker runs nothing else until released."""
    release = threading.Event()
    started = threading.Event()

    def busy() -> None:
        started.set()
        release.wait(20)

    async def submit() -> None:
        b.engine._workers["can1"].submit(busy)
    asyncio.run_coroutine_threadsafe(submit(), b.loop).result(10)
    assert started.wait(10)
    return release


def send(sock: socket.socket, line: str) -> None:
    sock.sendall(line.encode("ascii") + b"\r")


def reply(sock: socket.socket) -> Status:
    data = b""
    while len(data) < REPLY_SIZE:
        chunk = sock.recv(REPLY_SIZE - len(data))
        assert chunk, "connection closed"
        data += chunk
    return decode_reply(data).status


def targets(b: SimBridge, *nodes: int) -> List[int]:
    return [int.from_bytes(b.sim.read(n, 0x607A, 0), "little", signed=True) for n in nodes]


def queued(b: SimBridge, count: int = 1) -> None:
    """Wait until ``count`` requests wait behind the hold on the bus's worker."""
    wait_until(lambda: b.engine._workers["can1"].queued() >= count, 10, "nothing was queued")


def gantry(b: SimBridge) -> None:
    # Axis 2 (node 2) is the master, axis 1 (node 1, the EPOS4 itself) its slave.
    b.ok("1S04=1", "2S04=1", "2S05=10", "2S06=100", "2S29=1", "2S30=1", "2S02=4")


def test_a_target_sent_before_a_move_on_the_other_port_moves_master_and_slave_alike(
        bridge: SimBridge) -> None:
    b = bridge
    gantry(b)
    other = second_port(b)
    release = hold_bus(b)
    send(b.sock, "2S02=10")  # port 1912
    queued(b)
    send(other, "2S00=1")  # port 1913, after it
    release.set()
    assert reply(b.sock) is Status.ACK and reply(other) is Status.ACK
    b.poll("2R82", "1")
    b.poll("1R82", "1")
    assert targets(b, 2, 1) == [10 * FACTOR, 10 * FACTOR]  # never racked
    other.close()


@pytest.mark.parametrize("later,expected", [("2S22=-1", 5 * FACTOR), ("2S25=3", 5 * FACTOR)])
def test_a_queued_move_keeps_the_frame_of_its_arrival(bridge: SimBridge, later: str,
                                                      expected: int) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=10", "2S06=100", "2S02=5")
    other = second_port(b)
    release = hold_bus(b)
    send(b.sock, "2S00=1")  # queued behind the busy bus
    queued(b)
    assert psi_ask(other, later).status is Status.ACK  # answered at once, from the other port
    release.set()
    assert reply(b.sock) is Status.ACK
    b.poll("2R82", "1")
    assert targets(b, 2) == [expected]
    other.close()


def test_a_move_resolved_against_a_failed_write_is_not_executed(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=10", "2S06=100", "2S02=1")
    other = second_port(b)
    release = hold_bus(b)
    b.transport.go_silent_after(lambda m: getattr(m, "index", None) == 0x607A, 2)
    send(b.sock, "2S02=10")  # its write will not be answered
    queued(b)
    send(other, "2S00=1")  # resolved against 10 mm
    release.set()
    assert reply(b.sock) is Status.NAK
    b.transport.speak()
    assert reply(other) is Status.NAK  # not a move to a target the drive never took
    assert b.ok("2R02") == "1"


def velocity_gantry(b: SimBridge) -> Tuple[int, int]:
    b.ok("1S04=1", "2S04=1", "2S05=5", "2S06=50", "2S29=1", "2S30=1", "2S00=3")
    b.wait_until(lambda: b.velocity(1) > 0 and b.velocity(2) > 0, why="the gantry never ran")
    return 2, 1


def test_a_stop_of_a_master_stops_the_slave_its_move_started(bridge: SimBridge) -> None:
    b = bridge
    velocity_gantry(b)
    b.ok("2S29=0")  # the slave link is cut while they run ...
    b.ok("2S00=8")  # ... the stop still reaches the slave the move started
    b.wait_until(lambda: b.velocity(1) == 0 and b.velocity(2) == 0, why="an axis runs on")
    assert b.ok("1R04") == "1"  # the slave is halted, still enabled


def test_a_disable_of_a_master_halts_the_slave_its_move_started(bridge: SimBridge) -> None:
    b = bridge
    velocity_gantry(b)
    b.ok("2S04=0")
    b.wait_until(lambda: b.velocity(1) == 0 and b.velocity(2) == 0, why="the slave runs on")
    assert b.ok("2R04") == "0" and b.ok("1R04") == "1"
