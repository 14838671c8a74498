"""Issue 23: the bridge's heartbeat on a canopen bus, and each drive set up to watch it.

The bridge runs the ``canopen`` backend on the embedded simulator's virtual CAN
bus (``sim`` with ``link = "can"``), in this process. A listener on that bus
counts the bridge's heartbeat frames; the simulated drives' object stores show
what the bridge wrote (every write is logged with what the controlword was
doing, so "before the first enable" is a question of order, not of time).
The drive's reaction to a lost heartbeat is the simulator's part, and the
SIGKILL scenario is ``tests/test_bridge_heartbeat_e2e.py``.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Dict, Iterator, List, Tuple

import can
import pytest
from canopen.sdo import SdoAbortedError

from tcp_bridge.backends import open_backend
from tcp_bridge.check import check, liveness_notes
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.tables.axes import AxisTable, ConfigError, simulated_increments_per_revolution
from tcp_bridge.wire import Status, decode_reply, parse_request
from tests.helpers import wait_until

PRODUCER = 0x700 + 127  # default heartbeat_node_id
TIMING = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.05,
          "poll_interval": 0.002}
Write = Tuple[int, int, int, bool]  # index, subindex, value, heartbeat running at the time


def table(nodes: Tuple[int, ...] = (1, 2, 3), backend: str = "sim", **bus: object) -> AxisTable:
    options: Dict[str, Any] = {"backend": backend, **bus}
    if backend == "sim" and "link" not in bus:
        options["link"] = "can"
    return AxisTable.from_mapping({
        "bridge": TIMING, "bus": {"can1": options},
        "axis": [{"device": 5, "node_id": n, "position_factor": 1000,
                  "increments_per_revolution": simulated_increments_per_revolution()}
                 for n in nodes]})


def ask(engine: Engine, line: str) -> Status:
    return decode_reply(engine.execute_sync(parse_request(line.encode()))).status


def record_writes(engine: Engine, node: int) -> List[Write]:
    """Every write the simulated drive ``node`` accepts, in order, with whether the
    bridge's heartbeat was running at that moment."""
    backend = engine.backends[0]
    store = backend.simulator.drives[node].store
    write = store.write
    log_: List[Write] = []

    def logged(index: int, subindex: int, data: bytes) -> None:
        write(index, subindex, data)
        running = backend.heartbeat is not None and backend.heartbeat.running
        log_.append((index, subindex, int.from_bytes(data[:4], "little"), running))
    store.write = logged
    return log_


class Frames:
    """The frames on a simulator's virtual bus with one COB-ID, with their times."""

    def __init__(self, channel: str, cob_id: int = PRODUCER) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.cob_id = cob_id
        self.seen: List[can.Message] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            message = self.bus.recv(0.05)
            if message is not None and message.arbitration_id == self.cob_id:
                self.seen.append(message)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()


@pytest.fixture
def heartbeat() -> Iterator[Engine]:
    engine = build_engine(table(heartbeat_ms=50))
    try:
        yield engine
    finally:
        engine.close()


# -- the producer ------------------------------------------------------------------------------


def test_the_heartbeat_comes_at_its_period_with_the_operational_state(heartbeat: Engine) -> None:
    frames = Frames(heartbeat.backends[0].simulator.channel)
    try:
        wait_until(lambda: len(frames.seen) >= 21, 30, "fewer than 21 heartbeats")
    finally:
        frames.close()
    seen = frames.seen[:21]
    assert all(bytes(m.data) == b"\x05" for m in seen)  # CiA 301 7.2.8.3.2.2: Operational
    mean = (seen[-1].timestamp - seen[0].timestamp) / 20
    # 50 ms asked; a loaded 2-core machine delays frames, the cyclic task never sends early
    assert 0.025 < mean < 0.5, mean


def test_without_heartbeat_ms_nothing_is_sent_nor_written() -> None:
    engine = build_engine(table())
    try:
        backend = engine.backends[0]
        assert backend.heartbeat is None
        frames = Frames(backend.simulator.channel, PRODUCER)
        writes = record_writes(engine, 2)
        try:
            assert ask(engine, "2S04=1") is Status.ACK
            assert ask(engine, "2S04=0") is Status.ACK
            time.sleep(0.3)
        finally:
            frames.close()
        assert frames.seen == []
        assert not [w for w in writes if w[0] in (0x1016, 0x6007)]
        assert backend.simulator.drives[2].store.get_int(0x1016, 1) == 0
    finally:
        engine.close()


# -- the consumer on each drive ------------------------------------------------------------------


def test_consumer_and_abort_option_are_written_before_the_first_enable(heartbeat: Engine) -> None:
    writes = record_writes(heartbeat, 2)
    store = heartbeat.backends[0].simulator.drives[2].store
    assert store.get_int(0x1016, 1) == 0  # nothing before a client asks for anything
    assert ask(heartbeat, "2S04=1") is Status.ACK
    order = [(i, s) for i, s, _, _ in writes]
    first_controlword = order.index((0x6040, 0))
    assert (0x6007, 0) in order[:first_controlword]
    assert (0x1016, 1) in order[:first_controlword]
    assert order.index((0x6007, 0)) < order.index((0x1016, 1))  # the reaction set first
    assert store.get_int(0x1016, 1) == (127 << 16) | 150  # CiA 301 7.5.2.19; 3 x 50 ms
    assert store.get_int(0x6007, 0) == 3  # quick stop
    assert all(running for i, _, _, running in writes if i == 0x1016)


def test_it_is_written_once_per_power_up(heartbeat: Engine) -> None:
    writes = record_writes(heartbeat, 2)
    assert ask(heartbeat, "2S04=1") is Status.ACK
    assert ask(heartbeat, "2S04=0") is Status.ACK
    assert ask(heartbeat, "2S04=1") is Status.ACK
    assert [w[:3] for w in writes if w[0] == 0x1016] == [(0x1016, 1, (127 << 16) | 150)]
    assert ask(heartbeat, "2S04=0") is Status.ACK
    sim = heartbeat.backends[0].simulator
    sim.power_cycle(2)  # the store is back at its saved values: 1016h:01 = 0
    supervision = heartbeat.axes[2].need_drive().supervision
    assert supervision is not None
    wait_until(lambda: not supervision.configured, 10, "the boot-up was not noticed")
    assert ask(heartbeat, "2S04=1") is Status.ACK
    assert sim.drives[2].store.get_int(0x1016, 1) == (127 << 16) | 150


def test_a_move_on_a_drive_enabled_by_someone_else_sets_it_up_first(heartbeat: Engine) -> None:
    sim = heartbeat.backends[0].simulator
    # Another tool (its own channel, not this CAN bus's SDO server of node 3, which a
    # second SDO client would share): shutdown, switch on, enable operation with halt.
    for word in (0x06, 0x07, 0x10F):
        sim.drives[3].store.write(0x6040, 0, word.to_bytes(2, "little"))
    wait_until(lambda: sim.drive(3).statusword & 0x6F == 0x27, 10, "not enabled")
    assert ask(heartbeat, "3S07=3") is Status.ACK  # profile velocity
    assert ask(heartbeat, "3S05=1") is Status.ACK
    assert ask(heartbeat, "3S00=3") is Status.ACK
    assert sim.drives[3].store.get_int(0x1016, 1) == (127 << 16) | 150
    assert ask(heartbeat, "3S00=8") is Status.ACK


def test_a_drive_that_refuses_the_consumer_is_not_enabled(
        heartbeat: Engine, caplog: pytest.LogCaptureFixture) -> None:
    sim = heartbeat.backends[0].simulator

    def no_consumer(value: int) -> None:
        raise SdoAbortedError(0x06020000)  # "object does not exist", as a drive without 1016h
    sim.drives[2].store.add_write_hook(0x1016, 1, no_consumer)
    with caplog.at_level(logging.ERROR, logger="tcp_bridge.motion"), \
            pytest.raises(DeviceFailure, match="0x1016/1 failed"):  # answered NAK
        ask(heartbeat, "2S04=1")
    assert sim.drive(2).statusword & 0x4F == 0x40  # still switch on disabled
    assert "heartbeat supervision" in caplog.text and "0x06020000" in caplog.text.lower()


def test_a_clean_shutdown_switches_the_consumer_off_before_the_heartbeat_stops() -> None:
    engine = build_engine(table(heartbeat_ms=50))
    backend = engine.backends[0]
    writes = record_writes(engine, 2)
    untouched = record_writes(engine, 3)
    assert ask(engine, "2S04=1") is Status.ACK
    engine.close()
    last = [w for w in writes if w[0] == 0x1016][-1]
    assert last == (0x1016, 1, 0, True)  # off, while the heartbeat still ran
    assert backend.simulator.drives[2].store.get_int(0x1016, 1) == 0
    assert not backend.heartbeat.running
    assert sim_state_enabled(backend, 2)  # left as the client left it
    assert [w for w in untouched if w[0] == 0x1016] == []  # never set up: nothing to undo


def sim_state_enabled(backend: Any, node: int) -> bool:
    return backend.simulator.drive(node).statusword & 0x6F == 0x27


# -- configuration -------------------------------------------------------------------------------


@pytest.mark.parametrize("bus, message", [
    ({"heartbeat_ms": 5}, "heartbeat_ms must be an integer 10..10000 (ms), not 5"),
    ({"heartbeat_ms": True}, "heartbeat_ms must be an integer"),
    ({"heartbeat_ms": 0.1}, "heartbeat_ms must be an integer"),
    ({"heartbeat_ms": 100, "heartbeat_node_id": 2},
     "heartbeat_node_id 2 is the node id of axis 2"),
    ({"heartbeat_ms": 100, "heartbeat_node_id": 128}, "heartbeat_node_id must be an integer 1..127"),
    ({"heartbeat_ms": 100, "heartbeat_consumer_ms": 500},
     "heartbeat_consumer_ms must be an integer 200..400"),
    ({"heartbeat_ms": 100, "heartbeat_consumer_ms": 150}, "200..400"),
    ({"heartbeat_ms": 100, "abort_connection": "stop"}, "abort_connection must be one of"),
    ({"heartbeat_ms": 100, "abort_connection": 3}, "abort_connection must be one of"),
    ({"abort_connection": "fault"}, "abort_connection need heartbeat_ms"),
    ({"link": "inprocess", "heartbeat_ms": 100}, "heartbeat_ms only with link = \"can\""),
    ({"backend": "epos", "url": "sim://", "heartbeat_ms": 100},
     "heartbeat_ms only on a canopen bus, not epos (an EPOS4 gateway forwards SDO only"),
    ({"backend": "instant", "heartbeat_ms": 100}, "heartbeat_ms only on a canopen bus, not instant"),
])
def test_bad_heartbeat_options_are_one_config_error(bus: Dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        build_engine(table(**bus))
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_the_other_reactions_and_a_chosen_node_id() -> None:
    engine = build_engine(table(heartbeat_ms=100, heartbeat_node_id=100,
                                heartbeat_consumer_ms=400, abort_connection="disable_voltage"))
    try:
        assert ask(engine, "2S04=1") is Status.ACK
        store = engine.backends[0].simulator.drives[2].store
        assert store.get_int(0x1016, 1) == (100 << 16) | 400
        assert store.get_int(0x6007, 0) == 2
    finally:
        engine.close()


# -- tcp-bridge check -------------------------------------------------------------------------


def test_check_sends_no_heartbeat() -> None:
    seen: List[Frames] = []

    def opener(bus: Any, axes: Any) -> Any:
        backend = open_backend(bus, axes)
        seen.append(Frames(backend.simulator.channel))
        return backend
    reports = check(table(heartbeat_ms=10), opener=opener)
    time.sleep(0.1)
    for frames in seen:
        frames.close()
    assert all(r.ok for r in reports)
    assert seen and all(f.seen == [] for f in seen)


def test_check_says_what_stops_the_axes_when_the_host_dies() -> None:
    gateway, = liveness_notes(table(link="inprocess"))
    assert "cannot reach the CAN bus" in gateway and "forwards SDO only" in gateway
    assert "What protects the axes then" in gateway and "STO" in gateway
    none, = liveness_notes(table())
    assert "no heartbeat" in none and "keep their last command" in none
    watched, = liveness_notes(table(heartbeat_ms=100))
    assert "quick stop" in watched and "after 300 ms" in watched and "8130h" in watched


def test_the_hardware_guide_says_what_protects_the_axes_on_each_kind_of_bus() -> None:
    from pathlib import Path

    doc = (Path(__file__).resolve().parent.parent / "docs" / "hardware.md").read_text()
    section = doc[doc.index("## When the host dies"):]
    section = section[:section.index("\n## ", 1)]
    for words in ("`canopen` with `heartbeat_ms`", "`canopen` without `heartbeat_ms`", "`epos`",
                  "forwards SDO only", "what protects the axes", "STO", "8130h"):
        assert words in section, words
