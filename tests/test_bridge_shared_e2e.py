"""Shared reads end to end (issue 14, must show 1): no reply is older than its request.

Eight TCP clients poll R12 of one moving axis through the bridge, on the
simulated EPOS4 over a pty paced at 115200 baud (the ``sim`` backend, as a
user runs ``tcp-bridge serve --simulate``), so their reads queue on the one
serial link and share transfers. The drive moves at a constant velocity, so
its position only grows: each client notes the drive's true position just
before it sends the request, and the reply must not be smaller. A reply
from a transfer that started before the request arrived would show the axis
where it was before, and fail.
"""
from __future__ import annotations

import asyncio
import random
import socket
import threading
import time
from typing import Iterator, List, Tuple

import pytest

from tcp_bridge.tables.axes import AxisTable, simulated_increments_per_revolution
from tcp_bridge.engine import build_engine
from tcp_bridge.wire import Status
from tcp_bridge.server import BridgeServer, ServerOptions
from tcp_bridge.bus.shared_reads import SHARE_WINDOW
from tests.helpers import psi_ask

TIMING = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.02,
          "poll_interval": 0.002}
CLIENTS = 8
POLLS = 25


class Served:
    def __init__(self, share_window: float = SHARE_WINDOW) -> None:
        ipr = simulated_increments_per_revolution()
        table = AxisTable.from_mapping({
            "bridge": TIMING,
            "bus": {"can1": {"backend": "sim", "link": "pty", "baud": 115200}},
            "axis": [{"device": 5, "node_id": n, "position_factor": 1000,
                      "increments_per_revolution": ipr} for n in (1, 2)]})
        self.engine = build_engine(table, share_window=share_window)
        self.sim = self.engine.backends[0].simulator
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server = BridgeServer(self.engine, ServerOptions(ports=(0,)))
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result(10)
        self.address = self.server.addresses[0]

    def connect(self) -> socket.socket:
        return socket.create_connection(self.address, timeout=10)

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


def ask(sock: socket.socket, line: str) -> Tuple[Status, str]:
    reply = psi_ask(sock, line)
    return reply.status, reply.value or ""


# Without the gathering window, clients also arrive while a transfer runs: the case
# where joining a transfer that already started would return an older position.
@pytest.fixture(params=[0.0, SHARE_WINDOW], ids=["no-gathering", "gathering"])
def served(request: pytest.FixtureRequest) -> Iterator[Served]:
    s = Served(request.param)
    yield s
    s.close()


def true_position(served: Served, node: int) -> int:
    """6064h of the simulated drive now, in increments (under the drive's lock)."""
    sim = served.sim.drives[node]
    with sim.lock:
        sim.drive.sync()
        return sim.drive.position


def test_eight_clients_polling_a_moving_axis_never_get_an_older_position(served: Served) -> None:
    control = served.connect()
    for line in ("2S05=20", "2S04=1", "2S00=3"):  # 20 mm/s = 20,000 increments/s
        assert ask(control, line)[0] is Status.ACK, line
    shared = served.engine.shared["can1"]
    before_transfers, before_requests = shared.transfers, shared.requests
    failures: List[str] = []
    results: List[Tuple[int, int]] = []  # (position before the request, position replied)
    lock = threading.Lock()
    start = threading.Barrier(CLIENTS)

    def client(seed: int) -> None:
        pause = random.Random(seed)
        try:
            with served.connect() as sock:
                start.wait(10)
                for _ in range(POLLS):
                    # Arrive anywhere in a transfer, not only in step with the others.
                    time.sleep(pause.uniform(0, 0.005))
                    before = true_position(served, 2)
                    status, value = ask(sock, "2R12")
                    assert status is Status.ACK, value
                    with lock:
                        results.append((before, round(float(value) * 1000)))
        except Exception as exc:  # reported below, with the thread's own message
            failures.append(repr(exc))

    threads = [threading.Thread(target=client, args=(seed,)) for seed in range(CLIENTS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert ask(control, "2S00=8")[0] is Status.ACK
    control.close()
    assert not failures, failures
    assert len(results) == CLIENTS * POLLS
    older = [(b, r) for b, r in results if r < b]
    assert not older, f"{len(older)} replies older than their request, e.g. {older[:3]}"
    # Not vacuous: the axis moved, and the clients' reads did share transfers.
    assert results[-1][1] - results[0][0] > 1000
    transfers = shared.transfers - before_transfers
    requests = shared.requests - before_requests
    assert transfers < 0.8 * requests, (transfers, requests)


def test_a_read_after_a_write_shows_the_write(served: Served) -> None:
    """Several clients poll R05 (velocity parameter) while another writes it: once the
    write is answered, no later request of any client reads the old value."""
    writer = served.connect()
    assert ask(writer, "2S05=10")[0] is Status.ACK
    stop = threading.Event()
    seen: List[Tuple[bool, str]] = []  # (sent after the write was answered, value)
    written = threading.Event()

    def poller() -> None:
        with served.connect() as sock:
            while not stop.is_set():
                after = written.is_set()
                seen.append((after, ask(sock, "2R05")[1]))

    threads = [threading.Thread(target=poller) for _ in range(4)]
    for t in threads:
        t.start()
    try:
        assert ask(writer, "2S05=30")[0] is Status.ACK
        written.set()
        while sum(1 for after, _ in seen if after) < 40:
            threading.Event().wait(0.01)
    finally:
        stop.set()
        for t in threads:
            t.join(30)
        writer.close()
    assert all(value == "30" for after, value in seen if after)

