"""PSI requests through the bridge to CiA 402 drives on the ``ethercat`` backend, on a fake
pysoem whose slaves have the instant backend's drive behind them (tests/fake_soem.py
``DriveSlave``): the controlword and targets go out in the process data, as on an
EPOS4 EtherCAT, and the command layer and its motion rules are the CAN ones."""
from __future__ import annotations

import time
from types import MappingProxyType
from typing import Iterator, List

import pytest

from tcp_bridge.backends.ethercat import EthercatBackend
from tcp_bridge.engine import Engine
from tcp_bridge.tables.axes import AxisTable, BusConfig
from tcp_bridge.wire import Reply, Status, decode_reply, parse_request
from tests.bridge_sim import TIMING
from tests.fake_soem import DriveSlave, FakeSoem
from tests.helpers import AskOk, wait_until


class EcatBridge(AskOk):
    def __init__(self) -> None:
        self.soem = FakeSoem(count=2, drives=True)
        options = {"backend": "ethercat", "interface": "ecat0", "cycle_ms": 1}
        self.table = AxisTable.from_mapping({
            "bridge": TIMING, "bus": {"ethercat": options},
            "axis": [{"addr": n, "device": 5, "bus_offset": 1000000, "node_id": n,
                      "position_factor": 1000, "increments_per_revolution": 2000}
                     for n in (1, 2)]})
        bus = BusConfig("ethercat", "ethercat", MappingProxyType(
            {k: v for k, v in options.items() if k != "backend"}))
        self.backend = EthercatBackend(bus, list(self.table.axes.values()), soem=self.soem)
        nodes = {a.addr: self.backend.node(a.node_id) for a in self.table.axes.values()}
        self.engine = Engine(self.table, nodes, backends=[self.backend],
                             link_probes={"ethercat": self.backend.probe})

    def slave(self, position: int) -> DriveSlave:
        slave = self.soem.masters[0].slaves[position - 1]
        assert isinstance(slave, DriveSlave)
        return slave

    def ask(self, line: str) -> Reply:
        try:
            return decode_reply(self.engine.execute_sync(parse_request(line.encode())))
        except Exception as exc:  # the engine raises on failure; the server answers NAK
            self.why = str(exc)
            return Reply(int(line[0]), line[1], int(line[2:4]), Status.NAK)

    def close(self) -> None:
        self.engine.close()


@pytest.fixture
def bridge() -> Iterator[EcatBridge]:
    b = EcatBridge()
    yield b
    b.close()


def mailbox_writes(slave: DriveSlave) -> List[int]:
    return [index for op, index, _, _ in slave.drive.log if op == "download"]


def test_enable_a_profile_position_move_and_a_velocity_move(bridge: EcatBridge) -> None:
    ok = bridge.ok
    ok("1S04=1")
    assert int(ok("1R10")) & 0x6F == 0x27  # operation enabled
    assert bridge.backend.node(1).pdo_read(0x6040) & 0x0F == 0x0F  # through the outputs
    ok("1S05=20", "1S06=200", "1S02=5.25", "1S00=1")
    bridge.poll("1R82", "1")
    assert ok("1R12") == "5.25" and ok("1R15") == "1"
    ok("1S05=10", "1S00=3")
    assert ok("1R82") == "0" and bridge.slave(1).drive.velocity_moving
    ok("1S00=8")
    bridge.poll("1R82", "1")
    assert not bridge.slave(1).drive.velocity_moving and ok("1R04") == "1"
    time.sleep(0.05)
    assert not bridge.slave(1).drive.velocity_moving  # a stopped move stays stopped
    ok("1S04=0")
    assert int(ok("1R10")) & 0x6F == 0x21
    # Axis 2 was never touched: still switch on disabled.
    assert int(ok("2R10")) & 0x4F == 0x40


def test_a_slave_that_drops_out_is_nak_at_once_and_served_when_back(bridge: EcatBridge) -> None:
    ok = bridge.ok
    ok("2S04=1", "2S05=10", "2S00=3")
    slave = bridge.slave(2)
    slave.present = False
    wait_until(lambda: 2 in bridge.backend.cycle.lost)
    assert bridge.ask("2R10").status is Status.NAK
    assert bridge.ask("2S00=3").status is Status.NAK  # no move started on a silent node
    assert ok("1R04") == "0"  # the other slave is served meanwhile
    slave.present = True
    wait_until(lambda: 2 not in bridge.backend.cycle.lost)
    wait_until(lambda: bridge.ask("2R10").status is Status.ACK, why="axis 2 never served again")
    ok("2S00=8")
    bridge.poll("2R82", "1")
    assert not slave.drive.velocity_moving


def test_a_power_cycled_drive_is_reset_through_init_and_enabled_again(bridge: EcatBridge) -> None:
    ok = bridge.ok
    ok("1S04=1")
    slave = bridge.slave(1)
    slave.drive.power_cycle()  # RAM values lost, back in switch on disabled
    ok("1S16=1")  # the client's reset: INIT, then OP again
    assert slave.resets == 1
    wait_until(lambda: bridge.ask("1R10").status is Status.ACK)
    ok("1S04=1")
    assert int(ok("1R10")) & 0x6F == 0x27
