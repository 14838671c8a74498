"""Fail-fast buses end to end (issue 12, must show 3): a TCP client, the bridge, the real
``epos`` path (EposClient over MAXON SERIAL V2, epos_link.connect_node) and a simulated
EPOS4 whose link can fall silent, as an unplugged USB cable or a powered-off EPOS4 does.

The client's timeouts are the defaults (0.5 s, one retry, 0.5 s late-answer wait), so
the first request that meets the silence costs what it costs on hardware.
Deterministic checks count the requests that reached the link; the two durations of
must show 3 are asserted with bounds far above what is expected (a refusal takes ~1 ms,
so 0.3 s is 100x that; recovery takes ~1 s, asserted within 20 s) and printed.
"""
from __future__ import annotations

import time
from typing import Any, Dict, Iterator, List, Optional

import pytest

from epos_link.client import EposClient
from epos_link.framing import decode_frames
from epos_link.messages import Message, ReadObject, decode_request
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.transport import SimTransport
from tcp_bridge.tables.axes import AxisTable, BusConfig, simulated_increments_per_revolution
from tcp_bridge.backends.epos import EposBackend
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.wire import Status, decode_reply
from tests.test_bridge_server import Running, exchange, recv_replies

FAST = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.05,
        "poll_interval": 0.002}


class SwitchableTransport(SimTransport):
    """``sim://`` whose device can fall silent: requests are recorded, then dropped."""

    def __init__(self, simulator: Epos4Simulator) -> None:
        super().__init__(simulator)
        self.silent = False
        self.requests: List[Message] = []

    def write(self, data: bytes) -> None:
        self.requests.extend(decode_request(f) for f in decode_frames(bytes(data)))
        if not self.silent:
            super().write(data)


def is_probe(message: Message) -> bool:
    """The backend's probe: ReadObject 1000h/00h of node 0, the EPOS4 itself."""
    return isinstance(message, ReadObject) and message.node == 0 and message.index == 0x1000


class Bridge:
    def __init__(self, drives: List[int], axes: List[int], **bridge: Any) -> None:
        self.sim = Epos4Simulator(1, drives, gateway_timeout=0.3)
        self.transport = SwitchableTransport(self.sim)
        self.client = EposClient(self.transport, gateway_node_id=1)  # default timeouts
        ipr = simulated_increments_per_revolution()
        table = AxisTable.from_mapping({
            "bridge": {**FAST, **bridge}, "bus": {"can1": {"backend": "epos"}},
            "axis": [{"device": 5, "node_id": n, "position_factor": 1000,
                      "increments_per_revolution": ipr} for n in axes]})
        self.backend = EposBackend(BusConfig("can1", "epos", {}), list(table.axes.values()),
                                   client=self.client)
        nodes = {a.addr: self.backend.node(a.node_id) for a in table.axes.values()}
        # The backend is closed by close() below (Running clears instant nodes' logs
        # of engine.backends[0], which these nodes do not have).
        self.engine = Engine(table, nodes, link_probes={"can1": self.backend.probe})
        self.running = Running(self.engine)
        self.sock = self.running.connect()
        self.sock.settimeout(30)

    def ask(self, line: str) -> Status:
        return decode_reply(exchange(self.sock, line.encode())[0]).status

    def timed(self, line: str) -> "tuple[Status, float]":
        start = time.monotonic()
        status = self.ask(line)
        return status, time.monotonic() - start

    def close(self) -> None:
        self.sock.close()
        self.running.stop()
        self.backend.close()
        self.sim.close()


@pytest.fixture
def bridge() -> Iterator[Bridge]:
    b = Bridge([2, 3], [1, 2, 3])
    yield b
    b.close()


def test_a_silent_device_answers_nak_at_once_and_comes_back(bridge: Bridge) -> None:
    b = bridge
    assert [b.ask(f"{a}R10") for a in (1, 2, 3)] == [Status.ACK] * 3
    b.transport.silent = True
    first, took_first = b.timed("2R10")  # pays the client's timeouts and one probe
    assert first is Status.NAK
    sent = len(b.transport.requests)
    later = [b.timed(f"{a}R10") for a in (1, 2, 3, 1, 2, 3)]
    commands = [m for m in b.transport.requests[sent:] if not is_probe(m)]
    print(f"\nsilent device: first request {took_first:.2f} s, then "
          + ", ".join(f"{t * 1000:.1f} ms" for _, t in later))
    assert [s for s, _ in later] == [Status.NAK] * 6
    assert commands == []  # not one of them reached the link: answered without a wait
    assert all(t < 0.3 for _, t in later), later  # must show 3; expected ~1 ms each
    assert b.engine.guards["can1"].health.silent
    assert b.ask("2R22") is Status.ACK  # a parameter kept by the bridge needs no bus

    b.transport.silent = False  # the device comes back
    start = time.monotonic()
    deadline = start + 20
    while b.ask("1R10") is not Status.ACK:
        assert time.monotonic() < deadline, "the bus was never reopened"
        time.sleep(0.005)
    back = time.monotonic() - start
    print(f"device back: commands succeed again after {back:.2f} s")
    assert [b.ask(f"{a}R10") for a in (1, 2, 3)] == [Status.ACK] * 3
    assert not b.engine.guards["can1"].health.silent


def test_nothing_queued_during_the_outage_is_replayed(bridge: Bridge) -> None:
    b = bridge
    assert b.ask("1R10") is Status.ACK
    health = b.engine.guards["can1"].health
    b.transport.silent = True
    sent = len(b.transport.requests)
    # One pipeline: the first request meets the silence, the others wait in the bus
    # queue meanwhile and are refused when their turn comes.
    b.sock.sendall(b"2S05=3\r3S05=4\r1S05=5\r3S04=1\r1S07=3\r")
    assert [decode_reply(r).status for r in recv_replies(b.sock, 5)] == [Status.NAK] * 5
    b.transport.silent = False
    deadline = time.monotonic() + 20
    while health.silent:
        assert time.monotonic() < deadline, "the bus was never reopened"
        time.sleep(0.005)
    time.sleep(0.5)  # a replay, if there were one, would come now
    tried = [m for m in b.transport.requests[sent:] if not is_probe(m)]
    assert tried and {m.node for m in tried} == {2}  # only the first request was ever tried
    assert b.ask("3R10") is Status.ACK


def test_a_stop_is_tried_on_a_silent_bus_and_its_answer_reopens_it() -> None:
    b = Bridge([2, 3], [1, 2, 3], probe_interval=1000.0)  # no periodic probe in this test
    try:
        b.transport.silent = True
        assert b.ask("2R10") is Status.NAK  # declared silent
        sent = len(b.transport.requests)
        assert b.ask("2S00=8") is Status.NAK  # tried: a NAK without trying could leave it moving
        assert any(not is_probe(m) and m.node == 2 for m in b.transport.requests[sent:])
        b.transport.silent = False
        assert b.ask("1R10") is Status.NAK  # still declared: no probe has run
        assert b.ask("2S00=8") is Status.ACK  # the stop went through ...
        assert b.ask("1R10") is Status.ACK  # ... and its answer reopened the bus
    finally:
        b.close()


def test_an_absent_node_behind_a_healthy_gateway_does_not_slow_the_others() -> None:
    # Node 4 is not on the simulated CAN: the gateway answers SDO abort 0x05040000
    # after its own timeout (0.3 s). Periodic probes are off, so the count is exact.
    b = Bridge([2, 3], [1, 2, 3, 4], probe_interval=1000.0)
    try:
        assert b.ask("4R10") is Status.NAK  # the gateway's timeout, and one probe of node 4
        sent = len(b.transport.requests)
        statuses: Dict[int, List[Status]] = {a: [] for a in (1, 2, 3, 4)}
        start = time.monotonic()
        for _ in range(20):
            for a in (4, 1, 2, 3):
                statuses[a].append(b.ask(f"{a}R10"))
        took = time.monotonic() - start
        print(f"\n20 polls of 4 axes, one of them absent: {took:.2f} s")
        assert statuses[4] == [Status.NAK] * 20
        assert statuses[1] == statuses[2] == statuses[3] == [Status.ACK] * 20
        assert not any(m.node == 4 for m in b.transport.requests[sent:])  # no gateway waits
        health = b.engine.guards["can1"].health
        assert health.node_silent(4) and not health.silent  # not a silent bus
    finally:
        b.close()


def test_build_engine_gives_the_backends_probe_to_its_bus(tmp_path: Any) -> None:
    table = AxisTable.from_mapping({"bus": {"can1": {"backend": "sim"}}, "axis": [
        {"device": 5, "node_id": 1, "position_factor": 1000,
         "increments_per_revolution": simulated_increments_per_revolution()}]})
    engine = build_engine(table)
    try:
        guard = engine.guards["can1"]
        assert guard._link_probe is not None
        guard._link_probe()  # the simulated EPOS4 answers its device type
    finally:
        engine.close()


def test_a_silent_node_on_the_instant_backend_is_probed_back() -> None:
    # Periodic probes on the real clock: the node comes back within a bounded time.
    table = AxisTable.from_mapping({"bridge": {**FAST, "probe_interval": 0.05},
                                    "bus": {"can1": {"backend": "instant"}},
                                    "axis": [{"node_id": 1}, {"node_id": 2}]})
    engine = build_engine(table)
    node = engine.backends[0].nodes[1]
    try:
        from tests.test_bridge_engine import ask

        node.absent = True
        assert ask(engine, "1R10").status is Status.NAK
        assert engine.guards["can1"].health.node_silent(1)
        logged = len(node.log)
        assert ask(engine, "1R10").status is Status.NAK and len(node.log) == logged
        assert ask(engine, "2R10").status is Status.ACK
        node.absent = False
        deadline = time.monotonic() + 20
        status: Optional[Status] = None
        while status is not Status.ACK:
            assert time.monotonic() < deadline, "the node was never probed back"
            time.sleep(0.01)
            status = ask(engine, "1R10").status
    finally:
        engine.close()
