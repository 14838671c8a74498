"""The simulated drives' transmit PDOs (epos_link.simulator.pdo), through canopen's own PDO API.

A canopen ``RemoteNode`` on the simulator's virtual bus maps TPDOs the way the
bridge does (``node.tpdo[n].read()``, ``add_variable``, ``save()``), starts the
node and watches what arrives. Time bounds are generous (seconds), never tight.
"""
from __future__ import annotations

import threading
from typing import Iterator, List, Tuple

import canopen
import pytest
from canopen.sdo import SdoAbortedError

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.pdo import ABORT_NOT_MAPPABLE, ABORT_UNSUPPORTED
from tests.helpers import canopen_node_on_simulator

NODE = 2


@pytest.fixture
def bus() -> Iterator[Tuple[Epos4Simulator, canopen.RemoteNode]]:
    with canopen_node_on_simulator(NODE) as pair:
        yield pair


def map_status(node: canopen.RemoteNode, *, event_ms: int = 20) -> None:
    """TPDO1: statusword + position; TPDO2: velocity + digital inputs."""
    for n, objects in ((1, (0x6041, 0x6064)), (2, (0x606C, 0x60FD))):
        tpdo = node.tpdo[n]
        tpdo.read()
        tpdo.clear()
        for index in objects:
            tpdo.add_variable(index)
        tpdo.trans_type = 255
        tpdo.event_timer = event_ms
        tpdo.inhibit_time = 0
        tpdo.enabled = True
        tpdo.save()


def collect(node: canopen.RemoteNode, n: int, count: int, timeout: float = 5.0) -> List[bytes]:
    got: List[bytes] = []
    done = threading.Event()

    def on_pdo(pdo: canopen.pdo.PdoMap) -> None:
        got.append(bytes(pdo.data))
        if len(got) >= count:
            done.set()
    node.tpdo[n].add_callback(on_pdo)
    assert done.wait(timeout), f"only {len(got)} PDOs of TPDO{n} in {timeout} s"
    return got


def test_mapped_tpdos_carry_the_drive_values_in_operational(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    map_status(node)
    node.nmt.state = "OPERATIONAL"
    status = collect(node, 1, 2)  # on entering Operational, then every event timer period
    sw = int.from_bytes(status[-1][:2], "little")
    assert len(status[-1]) == 6
    assert sw & 0x6F == 0x40  # switch on disabled (CiA 402), bit 9 remote set below
    assert sw & 0x200  # Operational: remote (guide Table 3-13)
    drive = sim.drive(NODE)
    assert node.tpdo[1]["Position actual value"].raw == drive.position
    collect(node, 2, 1)
    assert node.tpdo[2]["Velocity actual value"].raw == 0
    # canopen decodes the PDO through the same EDS
    assert node.tpdo[1]["Statusword"].raw == sw


def test_a_change_is_sent_without_waiting_for_the_event_timer(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    map_status(node, event_ms=0)  # no event timer: only changes are sent
    node.nmt.state = "OPERATIONAL"
    collect(node, 1, 1)  # the one sent on entering Operational
    seen: List[int] = []
    changed = threading.Event()

    def on_pdo(pdo: canopen.pdo.PdoMap) -> None:
        seen.append(int.from_bytes(bytes(pdo.data[:2]), "little"))
        if seen[-1] & 0x6F == 0x21:
            changed.set()
    node.tpdo[1].add_callback(on_pdo)
    node.sdo[0x6040].raw = 0x06  # shutdown: ready to switch on
    assert changed.wait(5.0)


def test_no_pdo_outside_operational(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    map_status(node)
    node.nmt.state = "OPERATIONAL"
    collect(node, 1, 1)
    node.nmt.state = "PRE-OPERATIONAL"
    import time
    time.sleep(0.1)  # let a PDO already in flight arrive
    before = node.tpdo[1].timestamp
    assert node.tpdo[1].wait_for_reception(0.3) is None  # 15 event periods: none came
    assert node.tpdo[1].timestamp == before


def test_mapping_rules(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    node.tpdo[1].read()
    # A valid PDO's mapping cannot be changed (CiA 301 7.5.2.38: destroy it first).
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][0].raw = 0
    assert err.value.code == ABORT_UNSUPPORTED
    node.sdo[0x1800][1].raw = 0x80000182
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][2].raw = 0x60640020  # sub 0 is still 1
    assert err.value.code == ABORT_UNSUPPORTED
    node.sdo[0x1A00][0].raw = 0
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][1].raw = 0x60650020  # 6065h is not mappable (EDS PDOMapping=0)
    assert err.value.code == ABORT_NOT_MAPPABLE
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][1].raw = 0x60640010  # 6064h is 32 bits, not 16
    assert err.value.code == ABORT_NOT_MAPPABLE
    for sub, entry in enumerate((0x60640020, 0x606C0020, 0x60410010), start=1):
        node.sdo[0x1A00][sub].raw = entry
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1A00][0].raw = 3  # 80 bits do not fit one CAN frame
    assert err.value.code == 0x06040042
    node.sdo[0x1A00][0].raw = 2
    # a valid PDO keeps its identifier
    node.sdo[0x1800][1].raw = 0x182
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1800][1].raw = 0x183
    assert err.value.code == 0x06090030


def test_a_drive_that_refuses_the_mapping(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    sim.drives[NODE].tpdo.refuse_mapping = True
    with pytest.raises(SdoAbortedError) as err:
        map_status(node)
    assert err.value.code == ABORT_NOT_MAPPABLE


def test_a_reset_node_brings_back_the_default_mapping(bus) -> None:  # type: ignore[no-untyped-def]
    sim, node = bus
    map_status(node)
    sim.power_cycle(NODE)
    node.tpdo[1].read()
    assert [v.index for v in node.tpdo[1].map] == [0x6041]  # the EDS default again
    node.tpdo[2].read()
    assert not node.tpdo[2].enabled


# -- quiet drives are cheap: one wake-up for all, on a common grid ----------------------------


def test_quiet_drives_are_sampled_at_the_same_instants() -> None:
    from epos_link.simulator.core import SimulatedDrive
    from epos_link.simulator.pdo import GRID, QUIET

    samples = []
    for node_id, now in ((2, 10.0011), (3, 10.0037)):  # sampled 2.6 ms apart
        drive = SimulatedDrive(node_id, lambda: now)
        store = drive.store
        store.write_value(0x1800, 1, 0x80000180 + node_id)  # not valid while mapping
        store.write_value(0x1A00, 0, 0)
        store.write_value(0x1A00, 1, 0x60410010)
        store.write_value(0x1A00, 0, 1)
        store.write_value(0x1800, 5, 50)  # event timer 50 ms
        store.write_value(0x1800, 1, 0x180 + node_id)
        assert len(drive.tpdo.due(now)) == 1  # the first sample is sent
        assert drive.tpdo.due(now) == []  # nothing changed: quiet
        samples.append((now, drive.tpdo.next_sample))
    (t1, n1), (t2, n2) = samples
    assert n1 == n2  # one wake-up of the ticker serves both
    assert t2 + QUIET <= n2 <= t1 + QUIET + GRID
    assert round(n1 / GRID, 6).is_integer()


def test_the_ticker_sleeps_while_every_drive_is_quiet(bus) -> None:  # type: ignore[no-untyped-def]
    import time
    sim, node = bus
    map_status(node)  # event timer 20 ms, quiet otherwise
    node.nmt.state = "OPERATIONAL"
    collect(node, 1, 2)
    drive = sim.drives[NODE]
    calls = []
    send = drive.send_pdos
    drive.send_pdos = lambda now: (calls.append(now), send(now))  # type: ignore[method-assign]
    time.sleep(1.0)
    # A ticker waking every 2 ms looks 500 times a second; a quiet drive needs a
    # look every 10 ms (QUIET) and at its event timer. A busy machine looks less.
    assert 0 < len(calls) < 300


def test_an_event_timer_keeps_its_period_on_the_grid() -> None:
    from epos_link.simulator.core import SimulatedDrive
    from epos_link.simulator.pdo import GRID

    for timer_ms, late in ((50, 0.0001), (50, 0.002), (20, 0.0007), (33, 0.0013)):
        now = 10.0013
        drive = SimulatedDrive(2, lambda: now)
        store = drive.store
        store.write_value(0x1800, 1, 0x80000182)
        store.write_value(0x1A00, 0, 0)
        store.write_value(0x1A00, 1, 0x60410010)
        store.write_value(0x1A00, 0, 1)
        store.write_value(0x1800, 5, timer_ms)
        store.write_value(0x1800, 1, 0x182)
        sent = []
        for _ in range(400):  # a quiet drive; the ticker wakes ``late`` after each sample time
            if drive.tpdo.due(now):
                sent.append(now)
            now = max(drive.tpdo.next_sample, now) + late
        periods = [b - a for a, b in zip(sent, sent[1:])]
        timer = timer_ms / 1000
        assert len(periods) > 10
        # The first sample (entering Operational) is off the grid: its period ends at
        # the nearest grid instant. From then on a multiple of the grid keeps its
        # period, any other stays within a grid step of it.
        assert abs(periods[0] - timer) <= GRID / 2 + late + 1e-9
        bound = 1e-9 if timer_ms % 5 == 0 else GRID + 1e-9
        assert all(abs(p - timer) <= bound for p in periods[1:]), periods[:5]
        assert abs((sent[-1] - sent[0]) / (len(sent) - 1) - timer) < 0.05 * GRID  # no drift
