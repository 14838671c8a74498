"""Issue 30, finding 1: arrival order for the whole of a request, and a stop is the last word.

A move with companions runs in stages (precheck, main job, companions, halts;
:mod:`tcp_bridge.plan.job`). Each test here is written the way the finding was
seen: two clients (the bridge's two ports, here two free ports of one server),
a move from one, a stop (S00=8, S90=0, S04=0, S16) from the other right after
it, while a bus is held by an earlier request or a drive is slow to answer. The
bridge runs in this process on simulated drives (``sim`` buses: an EPOS4 on
each bus, or ``link = "can"`` for drives in CSP), and the tests watch the
simulated drives themselves: motion starts (:mod:`epos_link.simulator.safety`)
and positions. Before the fix the stop ran between two stages of the move,
answered ACK, and the line or the gantry then made its full move.
"""
from __future__ import annotations

import asyncio
import socket
import threading
import time
from typing import Any, Callable, Dict, Iterator, List, Union

import pytest

from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.server import BridgeServer, ServerOptions
from tcp_bridge.tables.axes import AxisTable, simulated_increments_per_revolution
from tcp_bridge.wire import REPLY_SIZE, Reply, Status, decode_reply
from tests.bridge_sim import TIMING
from tests.helpers import AskOk, psi_ask, wait_until
from tests.test_bridge_csp import table as csp_table

FACTOR = 1000  # increments per mm
CAN2 = 100_000  # spec 3.3 BusOffset: the second CAN bus


class Served(AskOk):
    """An engine built from ``table`` and served on two ports (1912 and 1913 in the field),
    on an event loop thread of its own, with one client connected to each port."""

    def __init__(self, table: Union[Dict[str, Any], AxisTable]) -> None:
        if not isinstance(table, AxisTable):
            table = AxisTable.from_mapping(table)
        self.engine: Engine = build_engine(table)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server = BridgeServer(self.engine, ServerOptions(ports=(0, 0)))
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result(10)
        self.sock = socket.create_connection(self.server.addresses[0], timeout=30)
        self.other = socket.create_connection(self.server.addresses[1], timeout=30)

    def ask(self, line: str) -> Reply:
        return psi_ask(self.sock, line)

    def defer_replies(self) -> None:
        """As on a real EPOS4's link (the ``epos`` backend, tcp_bridge.bus.workers "Replies
        after the next request"): a job's result waits until the next job sends."""
        for bus, worker in self.engine._workers.items():
            self._backend(bus).epos.attach_wait(worker.defer_results())

    def close(self) -> None:
        self.sock.close()
        self.other.close()
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(60)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()

    # -- the bus ------------------------------------------------------------------------

    def hold(self, bus: str) -> threading.Event:
        """An earlier request holds ``bus``: its worker runs nothing else until released."""
        release, started = threading.Event(), threading.Event()

        def busy() -> None:
            started.set()
            release.wait(20)

        async def submit() -> None:
            self.engine._workers[bus].submit(busy)
        asyncio.run_coroutine_threadsafe(submit(), self.loop).result(10)
        assert started.wait(10)
        return release

    def queued(self, bus: str) -> int:
        return self.engine._workers[bus].queued()

    def wait_queued(self, bus: str, more_than: int) -> None:
        wait_until(lambda: self.queued(bus) > more_than, 10, f"nothing more queued on {bus}")

    # -- the drives ---------------------------------------------------------------------

    def drive(self, bus: str, node: int) -> Any:
        """The simulated drive model of ``node`` on ``bus``, brought up to now."""
        sim = self._backend(bus).simulator.drives[node]
        with sim.lock:
            sim.drive.sync()
        return sim.drive

    def _backend(self, bus: str) -> Any:
        """The backend of ``bus`` (build_engine opens them in the table's order)."""
        names = [name for name in self.engine.table.buses
                 if any(a.bus == name for a in self.engine.table.axes.values())]
        return self.engine.backends[names.index(bus)]

    def starts(self, bus: str, node: int) -> int:
        return int(self.drive(bus, node).motion_starts)

    def position(self, bus: str, node: int) -> int:
        return int(self.drive(bus, node).position)


def send(sock: socket.socket, line: str) -> None:
    sock.sendall(line.encode("ascii") + b"\r")


def reply(sock: socket.socket) -> Reply:
    data = b""
    while len(data) < REPLY_SIZE:
        chunk = sock.recv(REPLY_SIZE - len(data))
        assert chunk, "connection closed"
        data += chunk
    return decode_reply(data)


def epos4(addr: int, bus_offset: int, **extra: Any) -> Dict[str, Any]:
    """An EPOS4 axis: node 1 of its bus, the simulated EPOS4 itself."""
    return {"addr": addr, "device": 5, "node_id": 1, "bus_offset": bus_offset,
            "position_factor": FACTOR,
            "increments_per_revolution": simulated_increments_per_revolution(), **extra}


def two_buses(**extra: Any) -> Dict[str, Any]:
    """Axis 1 on can1, axis 2 on can2: each the EPOS4 of its own simulated bus."""
    return {"bridge": TIMING,
            "bus": {"can1": {"backend": "sim"}, "can2": {"backend": "sim"}},
            "axis": [epos4(1, 0, **extra), epos4(2, CAN2, **extra)]}


@pytest.fixture
def line() -> Iterator[Served]:
    """Two internal axes in profile position mode, one on each bus: command 90 moves both."""
    b = Served(two_buses(internal=True, profile="drive"))  # the drives' own profile mode
    try:
        b.ok("1S04=1", "2S04=1", "1S05=10", "1S06=100", "2S05=10", "2S06=100",
             "1S02=5", "2S02=5")  # LINR: each by its own 02
        yield b
    finally:
        b.close()


@pytest.fixture(params=["replies at once", "replies deferred"])
def gantry(request: pytest.FixtureRequest) -> Iterator[Served]:
    """Axis 1 (can1) is the master, axis 2 (can2) its slave (29/30): a gantry on two buses,
    with the results of a bus's jobs handed over at once or after the next job's request."""
    b = Served(two_buses())
    if request.param == "replies deferred":
        b.defer_replies()
    try:
        b.ok("1S04=1", "2S04=1", "1S05=10", "1S06=100", "1S29=2", "1S30=1", "1S02=5")
        yield b
    finally:
        b.close()


# -- a line of internal axes (90), a stop from the other port ----------------------------------


@pytest.mark.parametrize("stop", ["2S00=8", "1S90=0", "2S04=0", "2S17=1"])
def test_a_stop_sent_after_a_line_on_the_other_port_is_never_overtaken_by_it(
        line: Served, stop: str) -> None:
    b = line
    before = [b.starts("can1", 1), b.starts("can2", 1)]
    release = b.hold("can2")
    send(b.sock, "1S90=1")  # port 1912
    b.wait_queued("can2", 0)  # the line waits for the held bus
    queued = b.queued("can2")
    send(b.other, stop)  # port 1913, a few ms after
    b.wait_queued("can2", queued)
    release.set()
    moved, stopped = reply(b.sock), reply(b.other)
    assert stopped.status is Status.ACK, stopped
    # The stop is the last word: the line it followed never started, on either bus.
    assert [b.starts("can1", 1), b.starts("can2", 1)] == before
    assert moved.status is Status.NAK  # not executed, and it says so
    b.poll("1R82", "1")
    assert b.ok("1R12") == "0" and b.ok("2R12") == "0"


def test_a_reset_node_sent_after_a_line_does_not_let_the_other_axis_start(line: Served) -> None:
    """``2S16=1`` after ``1S90=1``: node 2 was reset while axis 1 started."""
    b = line
    before = b.starts("can1", 1)
    release = b.hold("can2")
    send(b.sock, "1S90=1")
    b.wait_queued("can2", 0)
    queued = b.queued("can2")
    send(b.other, "2S16=1")
    b.wait_queued("can2", queued)
    release.set()
    moved, reset = reply(b.sock), reply(b.other)
    assert reset.status is Status.ACK, reset
    assert moved.status is Status.NAK
    assert b.starts("can1", 1) == before  # axis 1 never started
    assert b.ok("1R12") == "0"


def test_a_stop_after_a_csp_line_on_can_whose_bus_is_held_is_never_overtaken_by_it() -> None:
    """Two internal axes in CSP (nodes 2 and 3 of one simulated CAN bus): command 90 is one
    line on the bus's set-point thread; ``2S00=8`` follows it from the other port."""
    b = Served(csp_table())
    try:
        b.ok("1S04=1", "2S04=1", "1S02=40", "2S02=-16")
        start = [b.position("can1", 2), b.position("can1", 3)]
        release = b.hold("can1")
        send(b.sock, "1S90=1")
        b.wait_queued("can1", 0)
        queued = b.queued("can1")
        send(b.other, "2S00=8")
        b.wait_queued("can1", queued)
        release.set()
        moved, stopped = reply(b.sock), reply(b.other)
        assert stopped.status is Status.ACK, stopped
        # Half a second at rest; the line, had it started, would be 2.5 mm on its way
        # (40 mm/s^2 from rest) of its 40 mm.
        time.sleep(0.5)
        assert [b.position("can1", 2), b.position("can1", 3)] == start
        assert moved.status is Status.NAK
    finally:
        b.close()


def test_a_gantry_on_two_buses_moves_whole(gantry: Served) -> None:
    """The stages of one move, each in its place on its bus, with nothing in between."""
    b = gantry
    before = [b.starts("can1", 1), b.starts("can2", 1)]
    b.ok("1S00=1")
    b.poll("1R82", "1")
    b.poll("2R82", "1")
    assert [b.starts("can1", 1), b.starts("can2", 1)] == [before[0] + 1, before[1] + 1]
    assert b.ok("1R12") == "5" and b.ok("2R12") == "5"


# -- a gantry on two buses ------------------------------------------------------------------


def test_a_stop_after_a_gantry_move_whose_slave_waits_for_its_bus_stops_both(
        gantry: Served) -> None:
    """The slave's bus is held: the move's precheck waits there; the stop arrives."""
    b = gantry
    before = [b.starts("can1", 1), b.starts("can2", 1)]
    release = b.hold("can2")
    send(b.sock, "1S00=1")
    b.wait_queued("can2", 0)
    queued = b.queued("can2")
    send(b.other, "1S00=8")
    b.wait_queued("can2", queued)
    release.set()
    moved, stopped = reply(b.sock), reply(b.other)
    assert [b.starts("can1", 1), b.starts("can2", 1)] == before  # the gantry never ran
    assert stopped.status is Status.ACK and moved.status is Status.NAK, (moved, stopped)


class SlowStart:
    """The master's drive takes its start (controlword with bit 4, new set-point) and
    answers only when released: the master's stage has begun and still runs."""

    def __init__(self, backend: Any) -> None:
        self.simulator = backend.simulator
        self.original: Callable[[bytes], Any] = self.simulator.receive
        self.started = threading.Event()
        self.release = threading.Event()
        self.simulator.receive = self.receive

    def receive(self, data: bytes) -> Any:
        from epos_link.framing import decode_frames
        from epos_link.messages import WriteObject, decode_request

        answer = self.original(data)
        for frame in decode_frames(bytes(data)):
            m = decode_request(frame)
            if isinstance(m, WriteObject) and m.index == 0x6040 \
                    and int.from_bytes(m.data[:2], "little") & 0x10 and not self.started.is_set():
                self.started.set()
                self.release.wait(20)
        return answer


def test_a_stop_while_the_master_starts_halts_it_and_the_slave_never_starts(
        gantry: Served) -> None:
    b = gantry
    slave_before = b.starts("can2", 1)
    slow = SlowStart(b._backend("can1"))
    send(b.sock, "1S00=1")
    assert slow.started.wait(10)  # the master's drive has taken the start ...
    queued = b.queued("can1")
    send(b.other, "1S00=8")  # ... when the stop arrives
    b.wait_queued("can1", queued)
    slow.release.set()
    moved, stopped = reply(b.sock), reply(b.other)
    assert stopped.status is Status.ACK, stopped
    assert b.starts("can2", 1) == slave_before  # the slave never started ...
    assert moved.status is Status.NAK  # ... so the move was not executed whole
    # The master's begun stage was brought to rest, short of its 5 mm.
    wait_until(lambda: b.drive("can1", 1).velocity == 0, 10, "the master runs on")
    assert b.position("can1", 1) < 5 * FACTOR
    assert b.starts("can2", 1) == slave_before
