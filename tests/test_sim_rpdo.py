"""The simulated drives' receive PDOs and EMCY (epos_link.simulator.rpdo, .emcy, .comm).

A canopen client on the simulator's virtual bus drives a node the usual way:
``BaseNode402`` with the PDO configuration read from the drive, NMT
Operational, the state machine through RPDO1, a profile position move through
RPDO3. Time bounds are generous (seconds), never tight.
"""
from __future__ import annotations

import time
from typing import Iterator, Tuple

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from epos_link.cia402 import State
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.pdo import ABORT_NOT_MAPPABLE, ABORT_UNSUPPORTED
from tests.helpers import canopen_node_on_simulator, wait_until

NODE = 2


@pytest.fixture
def bus() -> Iterator[Tuple[Epos4Simulator, canopen.BaseNode402]]:
    with canopen_node_on_simulator(NODE, canopen.BaseNode402) as pair:
        yield pair


def emcy_codes(node: canopen.BaseNode402) -> list:
    return [e.code for e in node.emcy.log]


def nmt(sim: Epos4Simulator, node: canopen.BaseNode402, state: str) -> None:
    """Send an NMT command and wait until the drive has it (it runs on another thread)."""
    node.nmt.state = state
    wait_until(lambda: sim.nmt_state(NODE).name == state.replace("-", "_"), 5.0, f"NMT {state}")


def test_the_default_mapping_is_maxons(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    """maxon's EPOS4 EDS: RPDO1..4 valid on 200h..500h + id, controlword first; TPDO1 statusword."""
    _, node = bus
    node.tpdo.read()
    node.rpdo.read()
    rpdos = {n: (m.enabled, m.cob_id, m.trans_type, [v.index for v in m.map]) for n, m in node.rpdo.map.items()}
    assert rpdos == {1: (True, 0x202, 255, [0x6040]),
                     2: (True, 0x302, 255, [0x6040, 0x6060]),
                     3: (True, 0x402, 255, [0x6040, 0x607A]),
                     4: (True, 0x502, 255, [0x6040, 0x60FF])}
    assert [v.index for v in node.tpdo[1].map] == [0x6041] and node.tpdo[1].enabled


def test_basenode402_enables_and_moves_through_pdos(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    sim, node = bus
    drive = sim.drive(NODE)
    node.tpdo.read()
    node.rpdo.read()
    node.setup_402_state_machine(read_pdos=False)
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: node.tpdo_values.get(0x6041, 0) & 0x0200 != 0, 5.0, "the statusword TPDO (remote bit)")
    for state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"):
        node.state = state
    assert drive.state is State.OPERATION_ENABLED and node.state == "OPERATION ENABLED"
    # RPDO3: controlword + target position, in one frame; bit 4 sees this frame's target.
    rpdo = node.rpdo[3]
    rpdo["Controlword"].raw = 0x000F
    rpdo["Target position"].raw = 4000
    rpdo.transmit()
    rpdo["Controlword"].raw = 0x001F  # new set-point, absolute
    rpdo.transmit()
    wait_until(lambda: node.tpdo_values[0x6041] & 0x0400 != 0 and drive.position == 4000, 5.0, "target reached")
    assert node.sdo[0x6064].raw == 4000
    rpdo["Controlword"].raw = 0x000F
    rpdo.transmit()
    node.state = "SWITCH ON DISABLED"
    assert drive.state is State.SWITCH_ON_DISABLED


def test_rpdos_count_only_in_operational(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    sim, node = bus
    node.rpdo.read()
    rpdo = node.rpdo[1]
    rpdo["Controlword"].raw = 0x0006
    rpdo.transmit()  # pre-operational: ignored
    time.sleep(0.1)
    assert sim.drive(NODE).controlword == 0
    nmt(sim, node, "OPERATIONAL")
    rpdo.transmit()
    wait_until(lambda: sim.drive(NODE).state is State.READY_TO_SWITCH_ON, 5.0, "shutdown through RPDO1")
    nmt(sim, node, "STOPPED")
    rpdo["Controlword"].raw = 0x0007
    rpdo.transmit()
    time.sleep(0.1)
    assert sim.drive(NODE).state is State.READY_TO_SWITCH_ON


def test_remapping_follows_the_cia301_procedure(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    sim, node = bus
    node.rpdo.read()
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x1601][0].raw = 0  # valid PDO: destroy it first
    assert exc.value.code == ABORT_UNSUPPORTED
    node.sdo[0x1401][1].raw = 0x80000302
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x1601][1].raw = 0x60FF0020  # sub 0 is still 2
    assert exc.value.code == ABORT_UNSUPPORTED
    node.sdo[0x1601][0].raw = 0
    with pytest.raises(SdoAbortedError) as exc:
        node.sdo[0x1601][1].raw = 0x60410010  # the statusword cannot be written
    assert exc.value.code == ABORT_NOT_MAPPABLE
    node.sdo[0x1401][1].raw = 0x00000302  # (mapping with 0 entries: valid again, as before)
    # canopen's own save(): invalid, sub 0 = 0, entries, sub 0, valid.
    rpdo = node.rpdo[2]
    rpdo.clear()
    rpdo.add_variable(0x60FF)
    rpdo.add_variable(0x6040)
    rpdo.cob_id = 0x310
    rpdo.trans_type = 255
    rpdo.enabled = True
    rpdo.save()
    assert node.sdo[0x1601][1].raw == 0x60FF0020 and node.sdo[0x1401][1].raw == 0x310
    node.sdo[0x6060].raw = 3  # profile velocity
    nmt(sim, node, "OPERATIONAL")
    drive = sim.drive(NODE)
    for cw in (0x06, 0x07, 0x0F):
        rpdo["Controlword"].raw = cw
        rpdo["Target velocity"].raw = 500
        rpdo.transmit()
    wait_until(lambda: drive.velocity == 500, 5.0, "the velocity from the remapped RPDO2")
    drive.store.write_value(0x6040, 0, 0x0002)  # quick stop: the test ends at rest
    wait_until(lambda: drive.velocity == 0, 5.0, "standstill")


def test_wrong_lengths(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    """Short: not processed, EMCY 8210h; long: first bytes used, EMCY 8220h; once per event."""
    sim, node = bus
    nmt(sim, node, "OPERATIONAL")
    with can.Bus(interface="virtual", channel=sim.channel) as raw:
        raw.send(can.Message(arbitration_id=0x202, data=b"\x06", is_extended_id=False))
        wait_until(lambda: emcy_codes(node) == [0x8210], 5.0, "EMCY 8210h")
        raw.send(can.Message(arbitration_id=0x202, data=b"\x06", is_extended_id=False))
        time.sleep(0.1)
        assert sim.drive(NODE).controlword == 0
        assert [e.code for e in node.emcy.log] == [0x8210]  # not repeated
        assert node.emcy.log[0].register & 0x10  # communication error
        raw.send(can.Message(arbitration_id=0x202, data=b"\x06\x00\xAA", is_extended_id=False))
        wait_until(lambda: emcy_codes(node) == [0x8210, 0x8220], 5.0, "EMCY 8220h")
        wait_until(lambda: sim.drive(NODE).controlword == 6, 5.0, "the long frame's first bytes")


def test_emcy_on_fault_and_reset(bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    sim, node = bus
    received = []
    node.emcy.add_callback(received.append)
    sim.drive(NODE).inject_fault("sto")
    wait_until(lambda: emcy_codes(node) == [0x8A88], 5.0, "EMCY 8A88h")
    emcy = node.emcy.log[0]
    assert emcy.register == node.sdo[0x1001].raw == 0x01
    assert emcy.data == bytes(5)
    assert [e.code for e in node.emcy.active] == [0x8A88]
    node.sdo[0x6040].raw = 0x0080  # fault reset: EMCY 0000h
    wait_until(lambda: len(received) == 2, 5.0, "the error reset EMCY")
    assert (received[1].code, received[1].register) == (0x0000, 0) and node.emcy.active == []
    nmt(sim, node, "STOPPED")  # no EMCY in Stopped (guide Table 3-13)
    sim.drive(NODE).inject_fault("following_error")
    time.sleep(0.2)
    assert len(received) == 2


def test_emcy_cob_id_from_1014h_and_reset_restores_the_mapping(
        bus: Tuple[Epos4Simulator, canopen.BaseNode402]) -> None:
    sim, node = bus
    assert node.sdo[0x1014].raw == 0x80 + NODE
    node.sdo[0x1402][1].raw = 0x80000402
    node.sdo[0x1602][0].raw = 0
    node.sdo[0x1017].raw = 250
    node.sdo[0x1016][1].raw = (5 << 16) | 300
    node.sdo[0x6007].raw = 0
    node.nmt.send_command(0x81)  # reset node: nothing saved, so the EDS defaults again
    wait_until(lambda: sim.nmt_state(NODE).name == "PRE_OPERATIONAL", 5.0, "boot-up")
    assert node.sdo[0x1402][1].raw == 0x402 and node.sdo[0x1602][0].raw == 2
    assert (node.sdo[0x1017].raw, node.sdo[0x1016][1].raw, node.sdo[0x6007].raw) == (0, 0, 3)
