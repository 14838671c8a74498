"""The EtherCAT CSP pieces without a network (:mod:`tcp_bridge.backends.ethercat_csp`):
the transport writes 607Ah alone, refuses a slave without it or out of OP, and the
sender runs on a cycle hook (one set-point per cycle, on that cycle)."""
from __future__ import annotations

from typing import Callable, Dict, List, Optional

import pytest

from tcp_bridge.backends import ethercat_pdo as pdo
from tcp_bridge.backends.ethercat_csp import CycleSender, EthercatSetpoints
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.motion.profile import AxisLimits, plan_line

CW, TARGET = pdo.Entry(0x6040, 0, 0, 2), pdo.Entry(0x607A, 0, 2, 4)
VELOCITY = pdo.Entry(0x60FF, 0, 6, 4)
ACTUAL = pdo.Entry(0x6064, 0, 0, 4)


class FakeCycle:
    def __init__(self) -> None:
        self.lost: Dict[int, str] = {}
        self.link_down = False
        self.hooks: List[Callable[[int], None]] = []

    def add_hook(self, hook: Callable[[int], None]) -> None:
        self.hooks.append(hook)

    def remove_hook(self, hook: Callable[[int], None]) -> None:
        self.hooks.remove(hook)

    def step(self, count: int = 0) -> None:
        for hook in list(self.hooks):
            hook(count)


class FakeNode:
    def __init__(self) -> None:
        self.outputs = bytearray(10)
        self.inputs = (1234).to_bytes(4, "little", signed=True)

    def cyclic_target(self, position: int) -> None:
        pdo.put(self.outputs, TARGET, position.to_bytes(4, "little", signed=True))

    def pdo_write(self, index: int, subindex: int, value: int) -> None:
        entry = {(0x607A, 0): TARGET, (0x60FF, 0): VELOCITY}[(index, subindex)]
        pdo.put(self.outputs, entry, value.to_bytes(4, "little", signed=True))

    def pdo_read(self, index: int, subindex: int = 0) -> int:
        return pdo.get(self.inputs, ACTUAL, True)


class FakeBackend:
    interface = "veth0"

    def __init__(self, with_target: bool = True) -> None:
        outputs = {(0x6040, 0): CW,
                   **({(0x607A, 0): TARGET, (0x60FF, 0): VELOCITY} if with_target else {})}
        self.layouts: Dict[int, Optional[pdo.Layout]] = {
            1: pdo.Layout(outputs, {(0x6064, 0): ACTUAL}, 10, 4), 2: None}
        self.cycle = FakeCycle()
        self.nodes = {1: FakeNode()}

    def node(self, n: int) -> FakeNode:
        return self.nodes[n]


def test_prepare_names_607a_when_it_is_not_in_the_outputs() -> None:
    EthercatSetpoints(FakeBackend()).prepare(1)
    with pytest.raises(DeviceFailure, match="607Ah is not mapped"):
        EthercatSetpoints(FakeBackend(with_target=False)).prepare(1)
    with pytest.raises(DeviceFailure, match="607Ah"):
        EthercatSetpoints(FakeBackend()).prepare(2)  # mapping unknown


def test_write_targets_leaves_the_controlword_alone() -> None:
    backend = FakeBackend()
    node = backend.nodes[1]
    node.outputs[0:2] = (0x000F).to_bytes(2, "little")  # what the enable wrote
    EthercatSetpoints(backend).write_targets({1: -5000})
    assert node.outputs[0:2] == (0x000F).to_bytes(2, "little")
    assert int.from_bytes(node.outputs[2:6], "little", signed=True) == -5000
    assert EthercatSetpoints(backend).read_actual([1]) == {1: 1234}


def test_velocity_set_points_are_60ffh_alone() -> None:
    """CSV (S00=3): prepare_velocity wants 60FFh in the outputs; write_velocities puts
    60FFh there and leaves the controlword and 607Ah alone."""
    EthercatSetpoints(FakeBackend()).prepare_velocity(1)
    with pytest.raises(DeviceFailure, match="60FFh is not mapped"):
        EthercatSetpoints(FakeBackend(with_target=False)).prepare_velocity(1)
    backend = FakeBackend()
    node = backend.nodes[1]
    node.outputs[0:6] = (0x000F).to_bytes(2, "little") + (777).to_bytes(4, "little")
    EthercatSetpoints(backend).write_velocities({1: -321})
    assert node.outputs[0:6] == (0x000F).to_bytes(2, "little") + (777).to_bytes(4, "little")
    assert int.from_bytes(node.outputs[6:10], "little", signed=True) == -321
    backend.cycle.link_down = True
    with pytest.raises(DeviceFailure, match="no EtherCAT frame"):
        EthercatSetpoints(backend).write_velocities({1: 1})


def test_a_lost_slave_or_a_dark_link_refuses_the_set_points() -> None:
    backend = FakeBackend()
    backend.cycle.lost[1] = "slave 1 is in SAFEOP+ERROR, AL status 0x001B"
    with pytest.raises(DeviceFailure, match="0x001B"):
        EthercatSetpoints(backend).write_targets({1: 1})
    backend.cycle.lost.clear()
    backend.cycle.link_down = True
    with pytest.raises(DeviceFailure, match="no EtherCAT frame"):
        EthercatSetpoints(backend).write_targets({1: 1})


def sender(backend: FakeBackend, now: List[float]) -> CycleSender:
    s = CycleSender("ethercat", EthercatSetpoints(backend), 0.004, backend.cycle.add_hook,
                    backend.cycle.remove_hook)
    s.clock = lambda: now[0]
    s.begin()
    return s


def test_the_sender_samples_the_profile_on_each_cycle() -> None:
    backend, now = FakeBackend(), [10.0]
    s = sender(backend, now)
    assert s.alive() and len(backend.cycle.hooks) == 1
    line = plan_line([0], [1000], [AxisLimits(10_000.0, 100_000.0, 100_000.0)], 10.0)
    node = backend.nodes[1]
    positions = []
    import threading
    started = threading.Thread(target=lambda: s.start((1,), line, 30.0))
    started.start()
    while started.is_alive():  # the first set-point goes out on the next cycle
        backend.cycle.step()
        started.join(0.01)
    while s.active(1) is not None:
        now[0] += 0.004
        backend.cycle.step()
        positions.append(int.from_bytes(node.outputs[2:6], "little", signed=True))
    assert positions[-1] == 1000 and positions == sorted(positions)
    s.kill()
    assert not s.alive() and backend.cycle.hooks == []
    with pytest.raises(DeviceFailure, match="ended"):
        s.start((1,), line, 1.0)


def test_the_sender_sends_no_heartbeat() -> None:
    with pytest.raises(NotImplementedError):
        sender(FakeBackend(), [0.0]).add_beat(0.1, lambda: None)


def test_an_ethercat_bus_takes_no_heartbeat_ms() -> None:
    """The SM watchdog (watchdog_ms) is what stops CSP drives of a dead bridge here."""
    from tcp_bridge.backends.ethercat import parse_options
    from tcp_bridge.tables.axes import BusConfig, ConfigError

    with pytest.raises(ConfigError, match="heartbeat_ms"):
        parse_options(BusConfig("ethercat", "ethercat", {"interface": "eth1",
                                                         "heartbeat_ms": 100}))
