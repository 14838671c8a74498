"""PDO-fed status on the canopen backend (issue 14, must show 3).

Unit tests of :class:`~tcp_bridge.backends.pdo_status.StatusFeed` with an
injected clock (when a PDO value counts), then the bridge's canopen backend
with ``pdo = true`` on the simulator's virtual CAN bus, whose drives send the
TPDOs the bridge maps (``epos_link.simulator.pdo``): a stale PDO falls back to
SDO, a drive that refuses the mapping stays on SDO with one log line, a drive
that reboots gets its mapping back, and moves and enables send the drive
exactly what they send without PDOs.
"""
from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Callable, Dict, Iterator, List, Tuple

import pytest

from epos_link.simulator.core import Epos4Simulator
from tcp_bridge.tables.axes import AxisTable, BusConfig, ConfigError, simulated_increments_per_revolution
from tcp_bridge.backends.canopen_bus import CanopenBackend
from tcp_bridge.backends.pdo_status import PdoSettings, StatusFeed
from tcp_bridge.engine import Engine, build_engine
from tcp_bridge.wire import Status, decode_reply, parse_request
from tests.helpers import wait_until

TIMING = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.02,
          "poll_interval": 0.002}
SW = (0x6041, 0)


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


# -- StatusFeed: when a PDO value counts -------------------------------------------------

def test_a_fresh_pdo_counts_an_old_one_falls_back() -> None:
    clock = Clock()
    feed = StatusFeed(0.1, clock)
    feed.active = True
    feed.on_pdo({SW: 0x0237})
    clock.now += 0.05
    assert feed.value(*SW) == 0x0237
    clock.now += 0.06  # 110 ms old: older than the bound
    assert feed.value(*SW) is None
    feed.on_pdo({SW: 0x0637})
    assert feed.value(*SW) == 0x0637


def test_a_pdo_from_before_an_sdo_write_does_not_count() -> None:
    clock = Clock()
    feed = StatusFeed(0.1, clock)
    feed.active = True
    feed.on_pdo({SW: 0x0240, (0x6064, 0): 5})
    clock.now += 0.001
    feed.note_transfer(None)  # e.g. the controlword of an enable
    clock.now += 0.001
    assert feed.value(*SW) is None and feed.value(0x6064) is None
    feed.on_pdo({SW: 0x0237})  # sent after the drive answered the write
    assert feed.value(*SW) == 0x0237


def test_an_sdo_read_outdates_older_pdos_of_that_object_only() -> None:
    clock = Clock()
    feed = StatusFeed(0.1, clock)
    feed.active = True
    feed.on_pdo({SW: 0x0237, (0x6064, 0): 5})
    clock.now += 0.001
    feed.note_transfer(SW)  # a sequence read the statusword by SDO
    assert feed.value(*SW) is None  # never older than what was already read
    assert feed.value(0x6064) == 5


def test_nothing_counts_before_the_mapping_or_after_a_boot_up() -> None:
    clock = Clock()
    feed = StatusFeed(0.1, clock)
    feed.on_pdo({SW: 0x0237})
    assert feed.value(*SW) is None  # not active yet
    feed.active = True
    assert feed.value(*SW) == 0x0237
    feed.invalidate()
    feed.active = True
    assert feed.value(*SW) is None  # the values went with the boot-up


@pytest.mark.parametrize("options, message", [
    ({"pdo": "yes"}, "pdo must be true or false"),
    ({"pdo": True, "pdo_event_timer": 0.2}, "at most 0.05"),
    ({"pdo": True, "pdo_max_age": 0.04}, "longer than pdo_event_timer"),
    ({"pdo": True, "pdo_max_age": "fast"}, "number of seconds"),
    ({"pdo": True, "eds": "none"}, "needs an EDS"),
])
def test_bad_pdo_options_are_one_config_error(options: Dict[str, Any], message: str) -> None:
    bus = BusConfig("can1", "canopen", {"interface": "virtual", "channel": "pdo-options",
                                        **options})
    with pytest.raises(ConfigError, match=message):
        CanopenBackend(bus)


def test_settings_defaults_are_the_issue_s() -> None:
    s = PdoSettings()
    assert (s.max_age, s.event_timer) == (0.1, 0.05)


# -- the bridge on the simulator's CAN bus ---------------------------------------------------

class Rig:
    """Simulator + engine on the canopen backend; requests run as the server runs them."""

    def __init__(self, pdo: bool, *, refuse: Tuple[int, ...] = (), max_age: float = 0.1) -> None:
        self.sim = Epos4Simulator(1, [2, 3])
        for node in refuse:
            self.sim.drives[node].tpdo.refuse_mapping = True
        bus = {"backend": "canopen", "interface": "virtual", "channel": self.sim.channel,
               "receive_own_messages": False, "sdo_timeout": 0.3, "pdo": pdo,
               "pdo_max_age": max_age}
        ipr = simulated_increments_per_revolution()
        table = AxisTable.from_mapping({"bridge": TIMING, "bus": {"can1": bus}, "axis": [
            {"device": 5, "node_id": n, "position_factor": 1000,
             "increments_per_revolution": ipr} for n in (2, 3)]})
        self.engine: Engine = build_engine(table)
        self.backend = self.engine.backends[0]
        self.downloads: List[Tuple[int, int, int, bytes]] = []
        self.uploads = 0
        for addr, ops in self.engine.axes.items():
            assert ops.port is not None
            self._record(addr, ops.port.node.sdo)

    def _record(self, addr: int, sdo: Any) -> None:
        upload, download = sdo.upload, sdo.download

        def counted_upload(index: int, subindex: int) -> bytes:
            self.uploads += 1
            return upload(index, subindex)

        def recorded_download(index: int, subindex: int, data: bytes, *a: Any, **k: Any) -> None:
            self.downloads.append((addr, index, subindex, bytes(data)))
            download(index, subindex, data, *a, **k)
        sdo.upload, sdo.download = counted_upload, recorded_download

    def ask(self, line: str) -> Tuple[Status, str]:
        reply = decode_reply(self.engine.execute_sync(parse_request(line.encode())))
        return reply.status, reply.value or ""

    def ok(self, line: str) -> str:
        status, value = self.ask(line)
        assert status is Status.ACK, (line, status, value)
        return value

    def feed(self, node: int) -> StatusFeed:
        return self.backend.pdo.feeds[node]

    def until(self, condition: Callable[[], bool], what: str, timeout: float = 5.0) -> None:
        wait_until(condition, timeout, f"no {what}")

    def close(self) -> None:
        self.engine.close()
        self.sim.close()


# The bound within which a PDO counts, in the tests that expect polls answered from
# PDOs: 20 event timers, so that a simulated drive's thread that a loaded machine
# delays does not turn a poll into an SDO (issue 12: no tight wall-clock bounds).
MAX_AGE = 1.0


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(pdo=True, max_age=MAX_AGE)
    r.until(lambda: r.feed(2).active and r.feed(3).active, "the PDO mapping")
    yield r
    r.close()


def polls_from_pdos(rig: Rig, line: str, count: int = 20) -> int:
    """Poll ``line`` ``count`` times; the SDO uploads it took."""
    before = rig.uploads
    for _ in range(count):
        rig.ok(line)
    return rig.uploads - before


def test_status_polls_are_answered_from_pdos(rig: Rig) -> None:
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a first PDO")
    sw = int(rig.ok("1R10"))
    assert sw == rig.sim.drive(2).statusword
    rig.ok("1R14")  # the first velocity reads the drive's velocity unit (60A9h) by SDO, once
    assert polls_from_pdos(rig, "1R10") + polls_from_pdos(rig, "1R12") \
        + polls_from_pdos(rig, "1R82") + polls_from_pdos(rig, "1R83") \
        + polls_from_pdos(rig, "1R84") + polls_from_pdos(rig, "1R14") == 0
    assert rig.ok("1R12") == "0"


def test_the_server_path_answers_pdo_reads_without_the_bus_thread(rig: Rig) -> None:
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a first PDO")
    shared = rig.engine.shared["can1"]
    before, uploads = shared.fast, rig.uploads

    async def polls() -> List[bytes]:
        return [await rig.engine.execute(parse_request(line)) for line in (b"1R10", b"1R12")]
    replies = asyncio.run(polls())
    assert [decode_reply(r).status for r in replies] == [Status.ACK, Status.ACK]
    assert shared.fast == before + 2 and rig.uploads == uploads


def test_a_poll_whose_pdo_does_not_count_tries_it_once_then_reads_by_sdo(rig: Rig) -> None:
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a first PDO")
    port = rig.engine.axes[1].port
    assert port is not None
    tries: List[int] = []
    pdo_only = port.pdo_only
    port.pdo_only = lambda plan: (tries.append(1), pdo_only(plan))[1]  # type: ignore[method-assign]
    feed = rig.feed(2)
    max_age, feed.max_age = feed.max_age, 0.0  # no PDO counts, not even one arriving now
    uploads = rig.uploads

    async def poll() -> bytes:
        return await rig.engine.execute(parse_request(b"1R10"))
    try:
        assert decode_reply(asyncio.run(poll())).status is Status.ACK
    finally:
        feed.max_age = max_age
    assert len(tries) == 1 and rig.uploads == uploads + 1


def test_a_pdo_older_than_the_bound_falls_back_to_sdo(rig: Rig) -> None:
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a first PDO")
    assert polls_from_pdos(rig, "1R10", 5) == 0
    # The drive stops sending (NMT Pre-Operational, behind the bridge's back).
    rig.sim.drives[2].nmt(0x80)
    sent = time.monotonic()
    rig.until(lambda: rig.feed(2).value(0x6041) is None, "the last PDO to age", timeout=30)
    assert time.monotonic() - sent >= MAX_AGE * 0.9  # it counted for its bound, no longer
    assert polls_from_pdos(rig, "1R10", 5) == 5  # every poll by SDO now
    assert int(rig.ok("1R10")) == rig.sim.drive(2).statusword  # and right


def test_a_drive_that_refuses_the_mapping_stays_on_sdo(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="tcp_bridge.backends.pdo_status")
    r = Rig(pdo=True, refuse=(2,))
    try:
        r.until(lambda: r.feed(3).active, "node 3's mapping")
        refusals = [rec for rec in caplog.records if "refused the PDO mapping" in rec.getMessage()]
        assert len(refusals) == 1 and "node 2" in refusals[0].getMessage()
        assert not r.feed(2).active
        assert polls_from_pdos(r, "1R10", 5) == 5  # axis 1 = node 2: by SDO
        assert int(r.ok("1R10")) == r.sim.drive(2).statusword
        r.until(lambda: r.feed(3).value(0x6041) is not None, "node 3's first PDO")
        assert polls_from_pdos(r, "2R10", 5) == 0  # node 3 is fed
    finally:
        r.close()


def test_after_a_reboot_the_mapping_is_restored(rig: Rig) -> None:
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a first PDO")
    rig.sim.power_cycle(2)  # mapping back at the EDS defaults, node Pre-Operational
    rig.until(lambda: rig.sim.drives[2].store.get_int(0x1A01, 0) == 2
              and rig.feed(2).active, "the mapping after the boot-up")
    store = rig.sim.drives[2].store
    assert [store.get_int(0x1A00, s) for s in range(1, 4)] == [0x60410010, 0x60610008,
                                                                0x60640020]
    assert [store.get_int(0x1A01, s) for s in (1, 2)] == [0x606C0020, 0x60FD0020]
    rig.until(lambda: rig.feed(2).value(0x6041) is not None, "a PDO after the boot-up")
    assert polls_from_pdos(rig, "1R10", 5) == 0
    # The boot-up was seen as a power cycle (motion rule 3) as without PDOs.
    assert rig.engine.axes[1].drive.power_cycle_evidence == "boot-up message received"  # type: ignore[union-attr]


def scenario(r: Rig) -> List[Tuple[int, int, int, bytes]]:
    """Enable, move absolute and relative, velocity move, stop, disable: what the drive got."""
    r.ok("1S05=20")
    r.ok("1S06=200")
    r.ok("1S04=1")
    assert r.ok("1R04") == "1"
    r.ok("1S02=2.5")
    r.ok("1S00=1")
    r.until(lambda: r.ok("1R82") == "1", "target reached")
    assert r.ok("1R12") == "2.5"
    r.ok("1S02=-1")
    r.ok("1S00=2")
    r.until(lambda: r.ok("1R82") == "1", "target reached")
    assert r.ok("1R12") == "1.5"
    r.ok("1S00=3")
    r.until(lambda: r.ok("1R82") == "0", "moving")
    r.ok("1S00=8")
    r.until(lambda: r.ok("1R14") == "0", "standstill")
    r.ok("1S04=0")
    assert r.ok("1R04") == "0"
    pdo_config = range(0x1400, 0x1C00)
    return [d for d in r.downloads if d[1] not in pdo_config]


def test_moves_and_enables_send_exactly_what_they_send_without_pdos() -> None:
    sent: Dict[bool, List[Tuple[int, int, int, bytes]]] = {}
    history: Dict[bool, List[Any]] = {}
    for pdo in (False, True):
        r = Rig(pdo=pdo, max_age=MAX_AGE)
        try:
            if pdo:
                r.until(lambda: r.feed(2).active, "the mapping")
            sent[pdo] = scenario(r)
            drive = r.sim.drive(2)
            history[pdo] = [state for _, _, state in drive.history]
            assert not drive.unsafe_stops and drive.resets_while_moving == 0
            if pdo:
                assert r.feed(2).used > 0  # the polls were served from PDOs
        finally:
            r.close()
    assert sent[True] == sent[False]
    assert history[True] == history[False]
