"""Issue 22: hazards of the bridge on a real EPOS4, each the way a user meets it.

Every test drives the bridge over TCP (``tests/bridge_sim.py``: PSI requests,
the ``epos`` backend, MAXON SERIAL V2 to the simulated EPOS4 and the drives
behind its gateway) and then looks at the simulated drive itself. Axes 1, 2
and 3 are nodes 1 (the gateway), 2 and 3, device 5, factor 1000 (mm).

The tests of items 2, 4, 6 and 7 failed on the bridge before issue 22 (each on
the hazard it describes); the others check the simulator's own strictness
(homing errors and interruptions, cyclic synchronous position mode, another
master on the bus) and that a real power cycle is still detected.
"""
from __future__ import annotations

import time
from typing import Iterator

import pytest

from epos_link.cia402 import State
from epos_link.simulator.homing import HomingStatus
from epos_link.simulator.objects import Mode
from tcp_bridge.wire import Status
from tests.bridge_sim import SimBridge, power_ups, run_velocity_move, starts

FACTOR = 1000  # user units are mm; the drives count increments
MAXON_VENDOR_ID = 0x000000FB  # 1018h/1 of the simulated EPOS4 (CiA 301 identity object)
CSP = 8  # 6060h: cyclic synchronous position mode (CiA 402-2 6060h value table)
# Statusword bits 13/12/10 in homing mode (CiA 402-2 6.6, table of bits).
HOMING_BITS, HOMING_ERROR_AT_REST, INTERRUPTED = 0x2000 | 0x1000 | 0x0400, 0x2400, 0x0400
NEGATIVE_LIMIT_BIT, POSITIVE_LIMIT_BIT = 1 << 7, 1 << 6  # R11, PSI spec 4.b


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge()
    yield b
    b.close()


def start_homing(b: SimBridge, axis: int) -> None:
    """Method 18 (positive limit switch, CiA 402-2 6.6): at the default switch speed the
    search takes about 3 s to the simulator's switch at +10000 increments."""
    b.ok(f"{axis}S04=1", f"{axis}S40=18", f"{axis}S00=9")
    b.wait_until(lambda: b.velocity(axis) != 0, why="the homing never started")


# --- item 2: a changed parameter is taken for a power cycle ------------------------------


def test_a_software_limit_written_with_81_is_not_taken_for_a_power_cycle(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S02=5", "2S00=1")
    b.poll("2R82", "1")
    resets = power_ups(b, 2)
    b.ok("2S80=0x607D0104", "2S81=-1000")  # 607Dh/1 min position limit, 4 bytes: -1 mm
    b.ok("2S04=0", "2S04=1")
    assert power_ups(b, 2) == resets, "an NMT reset was sent"
    assert float(b.ok("2R12")) == 5  # an NMT reset would have set the counter to 0
    assert b.other_master_read(2, 0x607D, 1, signed=True) == -1000


def test_another_masters_write_is_not_taken_for_a_power_cycle(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=5")  # the bridge wrote 6081h
    resets = power_ups(b, 2)
    b.other_master_write(2, 0x6081, 0, 123, 4)  # e.g. maxon's studio tunes the profile
    b.ok("2S04=0", "2S04=1")
    assert power_ups(b, 2) == resets, "an NMT reset was sent"


def test_a_power_cycle_between_disable_and_enable_is_still_detected(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=7", "2S06=70")
    held = b.sim.drives[2].store.get_int(0x6081)
    b.ok("2S04=0")
    b.sim.power_cycle(2)  # power lost and back: saved parameters, SWITCH ON DISABLED
    assert b.sim.drives[2].store.get_int(0x6081) != held
    b.ok("2S04=1")
    assert b.sim.drives[2].store.get_int(0x6081) == held  # written back
    assert b.ok("2R04") == "1"


# --- item 4: modes and controlwords the bridge does not own ----------------------------------


def test_another_master_can_leave_a_drive_in_csp(bridge: SimBridge) -> None:
    # Simulator strictness (s2, s3): 6060h accepts 8, 6061h and R07 show it.
    b = bridge
    b.other_master_write(2, 0x6060, 0, CSP, 1)
    assert b.other_master_read(2, 0x6061, 0) == CSP
    assert b.ok("2R07") == str(CSP)


def test_a_drive_left_in_csp_never_moves_on_a_target_alone(bridge: SimBridge) -> None:
    b = bridge
    b.other_master_write(2, 0x6060, 0, CSP, 1)
    reply = b.ask("2S04=1")
    if reply.status is Status.ACK:  # enabled, but only after setting a profile mode
        assert b.now(2).mode is not Mode.CYCLIC_SYNC_POSITION, "enabled in csp"
    else:  # or refused, with nothing enabled
        assert reply.status is Status.NAK and b.now(2).state is not State.OPERATION_ENABLED
    before = b.now(2).axis_position  # the physical axis: not moved by a reset either
    b.ask("2S02=50")  # a target, no move command: in csp the drive follows 607Ah at once
    time.sleep(0.3)
    assert b.now(2).axis_position == before and starts(b, 2) == 0, "the axis moved"


def test_a_shutdown_written_with_81_never_switches_off_a_moving_axis(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2)
    b.ask("2S80=0x60400002")  # 6040h controlword, 2 bytes
    reply = b.ask("2S81=6")  # Shutdown (CiA 402-2 6.4.1.3): transition 8, drive function off
    assert reply.status in (Status.NAK, Status.CAN)
    assert b.now(2).state is State.OPERATION_ENABLED
    assert not b.now(2).unsafe_stops  # the power stage never went off while it moved


def test_a_mode_written_with_81_is_refused_while_enabled(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1")
    b.ask("2S80=0x60600001")  # 6060h modes of operation, 1 byte
    reply = b.ask("2S81=8")  # csp: the drive would follow 607Ah from now on
    assert reply.status in (Status.NAK, Status.CAN)
    assert b.now(2).mode is not Mode.CYCLIC_SYNC_POSITION
    assert b.now(2).state is State.OPERATION_ENABLED


# --- item 6: an EPOS4 axis loses its units through 19 ------------------------------------


@pytest.mark.parametrize("code", ["0", "1"])
def test_an_epos4_keeps_its_device_code(bridge: SimBridge, code: str) -> None:
    b = bridge
    b.ok("2S80=0x10180104")  # 1018h/1 vendor id, 4 bytes
    assert int(b.ok("2R81")) == MAXON_VENDOR_ID  # the drive identifies as maxon's
    assert b.ask(f"2S19={code}").status is Status.CAN
    ipr = b.sim.increments_per_revolution(2)
    b.ok("2S04=1", "2S05=10")
    # 10 mm/s = 10000 inc/s = 10000 * 60 / ipr rpm (60A9h, EPOS4 default unit)
    assert b.sim.drives[2].store.get_int(0x6081) == round(10 * FACTOR * 60 / ipr)


# --- item 7: what the bridge reports ---------------------------------------------------------


def test_r14_has_the_sign_of_the_motion_r12_shows_on_an_inverted_axis(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S22=-1")
    run_velocity_move(b, 2, speed="5", direction=-1)
    b.wait_until(lambda: abs(b.velocity(2)) > 4 * FACTOR, why="not at speed")
    first = float(b.ok("2R12"))
    b.wait_until(lambda: float(b.ok("2R12")) != first, why="R12 does not change")
    increasing = float(b.ok("2R12")) > first
    assert (float(b.ok("2R14")) > 0) == increasing


def test_a_positive_limit_switch_is_the_negative_end_of_an_inverted_axis(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S22=-1", "2S04=1")
    with b.sim.drives[2].lock:
        b.drive(2).inject_fault("limit_positive")  # 8A81h, 60FDh bit 1 (drive's positive)
    r11 = int(b.ok("2R11"))
    assert r11 & NEGATIVE_LIMIT_BIT and not r11 & POSITIVE_LIMIT_BIT


def test_a_homing_interrupted_by_another_master_reads_interrupted_in_r10(
        bridge: SimBridge) -> None:
    # Simulator strictness (s1, s3): controlword bit 4 "homing operation start"
    # 1 -> 0 interrupts the homing (CiA 402-2 6.6.1.1): the axis stops, 0/0/1.
    b = bridge
    start_homing(b, 2)
    b.other_master_write(2, 0x6040, 0, 0x000F, 2)  # enable operation, bit 4 cleared
    b.wait_until(lambda: b.velocity(2) == 0, why="the homing was not stopped")
    assert int(b.ok("2R10")) & HOMING_BITS == INTERRUPTED
    assert b.now(2).homing_status is HomingStatus.IDLE


def test_r82_is_0_after_an_interrupted_homing(bridge: SimBridge) -> None:
    b = bridge
    start_homing(b, 2)
    b.ok("2S00=8")
    b.wait_until(lambda: b.velocity(2) == 0, why="the homing was not stopped")
    assert b.ok("2R82") == "0"  # not homed: the client must not take it for done


def no_limit_switch(b: SimBridge) -> None:
    """Drive 2's positive limit switch is not fitted: a method 18 search ends on the
    end stop, here 1.5 revolutions out (epos_link/simulator/homing.py)."""
    with b.sim.drives[2].lock:
        switches = b.drive(2).switches
        switches.positive_limit = None
        switches.positive_stop = 3000.0


def test_a_homing_that_finds_no_switch_reads_homing_error_in_r10(bridge: SimBridge) -> None:
    # Simulator strictness (s1): 1/0/1 "homing error occurred, velocity is 0".
    b = bridge
    no_limit_switch(b)
    start_homing(b, 2)
    b.wait_until(lambda: b.now(2).homing_status is HomingStatus.ERROR, why="no homing error")
    b.wait_until(lambda: int(b.ok("2R10")) & HOMING_BITS == HOMING_ERROR_AT_REST,
                 why="R10 does not show the homing error at rest")


def test_r82_is_0_after_a_failed_homing(bridge: SimBridge) -> None:
    b = bridge
    no_limit_switch(b)
    start_homing(b, 2)
    b.wait_until(lambda: b.now(2).homing_status is HomingStatus.ERROR, why="no homing error")
    b.wait_until(lambda: b.velocity(2) == 0)
    assert b.ok("2R82") == "0"  # failed: the client must not take it for done
