"""Issue 10: the bridge is safe on a real axis. Each finding, the way a user meets it.

Every test drives the bridge over TCP (``tests/bridge_sim.py``: PSI requests,
the ``epos`` backend, MAXON SERIAL V2 to the simulated EPOS4 and the drives
behind its gateway) and then looks at the simulated drive itself: its
position, velocity and state history. So each proves that the drive never
moved when it should not have, and moved exactly once when it should. The
motion rules under test are in ``tcp_bridge/motion.py``.
"""
from __future__ import annotations

import time
from typing import Iterator, List

import pytest

from epos_link.cia402 import State
from epos_link.messages import ReadObject, WriteObject
from tcp_bridge.wire import Status
from tests.bridge_sim import (SimBridge, controlword_write, opcodes, power_ups,
                              run_velocity_move, starts)

FACTOR = 1000  # user units are mm; the drives count increments


@pytest.fixture
def bridge() -> Iterator[SimBridge]:
    b = SimBridge()
    yield b
    b.close()


def transitions_since(b: SimBridge, node: int, t: float) -> List[int]:
    return [number for when, number, _ in b.drive(node).history if when >= t]


# --- finding 1: enable resets a moving drive ---------------------------------------------


def test_a_lost_answer_never_makes_enable_reset_a_moving_drive(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2)
    resets = power_ups(b, 2)
    # One poll's answer is lost twice (the client's retry too): the poll is NAK ...
    b.transport.lose_answers(lambda m: isinstance(m, ReadObject) and m.node == 2, 2)
    assert b.ask("2R10").status is Status.NAK
    # ... and the routine enable that follows leaves the moving drive alone.
    b.ok("2S04=1")
    time.sleep(0.1)
    assert power_ups(b, 2) == resets and b.now(2).resets_while_moving == 0
    assert b.now(2).state is State.OPERATION_ENABLED and b.velocity(2) > 0
    assert starts(b, 2) == 1 and not b.now(2).unsafe_stops


def test_a_bridge_restart_never_resets_a_moving_drive(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2)
    resets = power_ups(b, 2)
    b.restart()
    b.ok("2S04=1")  # what a client sends after it reconnects
    time.sleep(0.1)
    assert power_ups(b, 2) == resets and b.now(2).resets_while_moving == 0
    assert b.velocity(2) > 0 and starts(b, 2) == 1


# --- finding 2: a stopped velocity move restarts by itself ----------------------------------


@pytest.mark.parametrize("then", [["2S04=0", "2S04=1"], ["2S07=3"], ["2S07=1", "2S07=3"],
                                  ["2S04=0", "2S04=1", "2S07=3"]])
def test_a_stopped_velocity_move_stays_stopped(bridge: SimBridge, then: List[str]) -> None:
    b = bridge
    run_velocity_move(b, 2)
    b.ok("2S00=8")
    b.poll("2R82", "1")
    b.wait_until(lambda: b.velocity(2) == 0)
    b.ok(*then)
    stopped = b.position(2)
    time.sleep(0.3)
    assert b.velocity(2) == 0 and b.position(2) == stopped, "the axis moved without a move command"
    assert starts(b, 2) == 1
    b.ok("2S00=3")  # the next move command does move it, once
    b.wait_until(lambda: b.velocity(2) > 0)
    assert starts(b, 2) == 2


# --- finding 3: disable cuts the power of a moving axis ----------------------------------------


def test_disable_during_a_move_brings_the_axis_to_rest_first(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2, speed="20")
    t0 = b.now(2).now
    b.ok("2S04=0")
    assert b.now(2).state is State.READY_TO_SWITCH_ON
    steps = transitions_since(b, 2, t0)
    # CiA 402: 5 = disable operation (OE -> SO), 6 = shutdown (SO -> RTSO). Never 8,
    # shutdown straight from OPERATION ENABLED, which cuts an EPOS4's drive function.
    assert 8 not in steps and steps[:2] == [5, 6], steps
    assert b.velocity(2) == 0
    assert not b.now(2).unsafe_stops  # the power stage never went off while it moved


# --- finding 5: a move that started is answered NAK ---------------------------------------------


@pytest.mark.parametrize("how,target,expected", [("1", "5", 5.0), ("2", "2", 2.0)])
def test_a_move_whose_start_answer_is_lost_is_ack_and_moves_once(
        bridge: SimBridge, how: str, target: str, expected: float) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=20", "2S06=200", "2S86=0", f"2S02={target}")
    start = b.position(2) / FACTOR
    before = starts(b, 2)
    # The write that starts the move (controlword bit 4) and the client's retry
    # of it are executed by the drive, but both answers are lost.
    b.transport.lose_answers(controlword_write(2, bits=0x10), 2)
    assert b.ask(f"2S00={how}").status is Status.ACK
    assert len(b.transport.dropped) == 2
    assert b.ok("2R86") == "1"
    b.poll("2R82", "1")
    time.sleep(0.1)
    assert b.position(2) / FACTOR == pytest.approx(start + expected if how == "2" else expected)
    assert starts(b, 2) == before + 1  # moved exactly once


def test_a_move_that_could_not_start_is_nak_and_nothing_moves(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=20", "2S06=200", "2S02=5")
    # The target write is lost for good (the drive never answers it): nothing started.
    b.transport.lose_answers(lambda m: isinstance(m, WriteObject) and m.index == 0x607A, 100)
    assert b.ask("2S00=1").status is Status.NAK
    assert b.ok("2R86") == "0"
    time.sleep(0.2)
    assert b.position(2) == 0 and starts(b, 2) == 0


# --- finding 6: a real power loss between polls goes unnoticed -----------------------------------


def test_a_power_cycle_between_polls_makes_enable_write_the_parameters_back(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=7", "2S06=70")
    held = b.sim.drives[2].store.get_int(0x6081)
    b.sim.power_cycle(2)  # power lost and back: saved parameters, SWITCH ON DISABLED
    assert b.sim.drives[2].store.get_int(0x6081) != held
    b.ok("2S04=1")  # no poll in between
    assert b.sim.drives[2].store.get_int(0x6081) == held
    assert b.ok("2R04") == "1"


def test_a_power_cycle_seen_by_a_poll_is_restored_too(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=7")
    held = b.sim.drives[2].store.get_int(0x6081)
    b.sim.power_cycle(2)
    assert int(b.ok("2R10")) & 0x4F == 0x40  # a poll sees SWITCH ON DISABLED
    b.ok("2S04=1")
    assert b.sim.drives[2].store.get_int(0x6081) == held


# --- finding 7: every read is a segmented read ------------------------------------------------


@pytest.mark.parametrize("axis", [1, 2])
def test_a_status_poll_is_one_read_object(bridge: SimBridge, axis: int) -> None:
    b = bridge
    b.ok(f"{axis}R10")  # the first poll may read more (e.g. the node id)
    b.transport.requests.clear()
    b.ok(f"{axis}R10", f"{axis}R12", f"{axis}R82")
    assert set(opcodes(b.transport.requests)) == {"ReadObject"}


# --- finding 8: wrong error codes and bits --------------------------------------------------------


@pytest.mark.parametrize("fault,r83,r11", [
    ("limit_positive", "1", 1 << 6),  # 8A81h; spec 4.b bit 6: positive limit switch
    ("limit_negative", "1", 1 << 7),  # 8A80h; bit 7: negative limit switch
    ("sto", "0", 1 << 15),  # 8A88h; bit 15: STO, not a limit switch
    ("following_error", "0", 1 << 3),  # 8611h
])
def test_faults_are_named_by_their_epos4_codes(bridge: SimBridge, fault: str, r83: str,
                                               r11: int) -> None:
    b = bridge
    b.ok("2S04=1")
    with b.sim.drives[2].lock:
        b.drive(2).inject_fault(fault)
    assert b.ok("2R84") == "1"
    assert b.ok("2R83") == r83
    assert int(b.ok("2R11")) == r11


def test_a_software_limit_error_names_its_side(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S23=1", "2S24=-1")  # 607Dh: -1 .. 1 mm
    with b.sim.drives[2].lock:
        b.drive(2).inject_fault("software_limit")
    assert int(b.ok("2R11")) in (1 << 8, 1 << 9)


def test_velocity_limiting_is_not_an_end_switch_hit(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S26=2")  # max velocity below the move's: the drive limits it (sw bit 11)
    run_velocity_move(b, 2, speed="5")
    b.wait_until(lambda: int(b.ok("2R10")) & (1 << 11) != 0, why="no internal limit shown")
    assert b.ok("2R83") == "0"


def test_an_epos4_axis_is_driven_in_rpm(bridge: SimBridge) -> None:
    b = bridge
    ipr = b.sim.increments_per_revolution(2)
    b.ok("2S04=1", "2S05=10", "2S06=100")
    # 10 mm/s = 10000 inc/s = 10000 * 60 / ipr rpm; before: 10000 "rpm"
    assert b.sim.drives[2].store.get_int(0x6081) == round(10 * FACTOR * 60 / ipr)
    assert b.sim.drives[2].store.get_int(0x6083) == round(100 * FACTOR * 60 / ipr)
    b.ok("2S00=3")
    b.poll("2R82", "0")
    b.wait_until(lambda: abs(b.velocity(2) - 10 * FACTOR) < 0.02 * 10 * FACTOR,
                 why="not running at 10000 inc/s")
    assert float(b.ok("2R05")) == 10


def test_r14_is_in_user_units(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2, speed="5")
    b.poll("2R82", "0")
    b.wait_until(lambda: abs(float(b.ok("2R14")) - 5.0) < 0.1, why="R14 is not 5 mm/s")


# --- finding 9: slave axes are not synchronised ----------------------------------------------------


def test_a_slave_moves_in_step_with_its_master(bridge: SimBridge) -> None:
    b = bridge
    # 20 mm at 5 mm/s: the two start writes go out back to back (well under a
    # millisecond apart, 0.005 mm at this speed); 1% of the travel is 0.2 mm.
    travel = 20.0
    b.ok("3S04=1", "3S05=1", "3S06=5")  # the slave's own, much slower profile
    b.ok("2S04=1", "2S05=5", "2S06=50", "2S29=3", "2S30=-1", f"2S02={travel}", "2S00=1")
    worst = 0.0
    deadline = time.monotonic() + 20
    while True:
        master, slave = (p / FACTOR for p in b.positions(2, 3))
        worst = max(worst, abs(master + slave))  # mirrored by S30=-1
        if master == travel and b.velocity(2) == 0:
            break
        assert time.monotonic() < deadline, "the master never arrived"
        time.sleep(0.005)
    b.wait_until(lambda: b.velocity(3) == 0)
    assert b.position(3) / FACTOR == -travel
    assert worst <= 0.01 * travel, f"slave and master apart by {worst} mm"


# --- the CAN backend: a boot-up message is evidence of a power cycle -----------------------


def test_a_boot_up_message_on_can_makes_enable_reset_and_restore() -> None:
    from epos_link.simulator.core import Epos4Simulator
    from tcp_bridge.tables.axes import AxisTable, simulated_increments_per_revolution
    from tcp_bridge.engine import build_engine
    from tcp_bridge.wire import decode_reply, parse_request

    sim = Epos4Simulator(1, [2])
    table = AxisTable.from_mapping({
        "bridge": {"reset_delay": 0.05, "reset_timeout": 3.0},
        "bus": {"can1": {"backend": "canopen", "interface": "virtual", "channel": sim.channel,
                         "receive_own_messages": False, "sdo_timeout": 0.2}},
        "axis": [{"device": 5, "node_id": 2, "position_factor": FACTOR,
                  "increments_per_revolution": simulated_increments_per_revolution()}]})
    engine = build_engine(table)

    def ok(line: str) -> None:
        reply = decode_reply(engine.execute_sync(parse_request(line.encode())))
        assert reply.status is Status.ACK, (line, reply)
    try:
        ok("1S04=1")
        ok("1S05=7")
        held = sim.drives[2].store.get_int(0x6081)
        ok("1S04=0")  # not enabled: the drive's own state tells nothing more than SWITCHED ON
        sim.power_cycle(2)  # sends the boot-up message 0x702 on the bus
        deadline = time.monotonic() + 10
        while engine.axes[1].drive.power_cycle_evidence is None:  # type: ignore[union-attr]
            assert time.monotonic() < deadline, "the boot-up message was not noticed"
            time.sleep(0.01)
        resets = power_ups_of(sim.drive(2))
        ok("1S04=1")
        assert power_ups_of(sim.drive(2)) == resets + 1  # spec 04: NodeReset ...
        assert sim.drives[2].store.get_int(0x6081) == held  # ... and WriteParameter
    finally:
        engine.close()
        sim.close()


def power_ups_of(drive: object) -> int:
    return sum(1 for _, number, _ in drive.history if number == 0)  # type: ignore[attr-defined]


# --- review findings: quick stop ramps, velocity changes, unknown outcomes, coasting ---------


def test_enable_during_a_quick_stop_ramp_lets_the_ramp_finish(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S28=5")  # a slow quick stop ramp: 5 mm/s^2
    run_velocity_move(b, 2, speed="20")
    b.sim.write(2, 0x6040, 0, (0x000B).to_bytes(2, "little"))  # quick stop: an input or another master
    assert b.velocity(2) > 0
    b.ok("2S04=1")
    assert not b.now(2).unsafe_stops  # the power stage never went off while it moved


def test_a_new_velocity_whose_answer_is_lost_is_ack_and_runs(bridge: SimBridge) -> None:
    b = bridge
    run_velocity_move(b, 2, speed="5")
    b.ok("2S05=10")
    b.transport.lose_answers(lambda m: isinstance(m, WriteObject) and m.index == 0x60FF, 2)
    assert b.ask("2S00=3").status is Status.ACK  # the running drive took the new 60FFh
    b.wait_until(lambda: abs(b.velocity(2) - 10 * FACTOR) < 200, why="not at the new speed")
    assert b.ok("2R86") == "1"


def test_a_move_whose_node_goes_silent_is_nak_and_halted_when_it_answers(
        bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S05=5", "2S06=50", "2S02=50")
    b.transport.go_silent_after(controlword_write(2, bits=0x10), node=2)
    assert b.ask("2S00=1").status is Status.NAK  # outcome unknown for the whole ack_timeout
    assert b.velocity(2) > 0  # the start write had arrived: it moves
    b.transport.speak()
    b.ok("2R10")  # the next command to the axis first sends the halt it owes
    assert b.now(2).controlword & 0x100  # halt (cw bit 8), before the 10 s move ends
    b.wait_until(lambda: b.velocity(2) == 0, why="the owed halt was not sent")
    assert b.position(2) < 25 * FACTOR


def test_units_are_read_again_after_a_power_cycle(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S80=0x60A90004", "2S81=0xFDB44700")  # milli-rpm, not saved
    b.ok("2S05=10")
    ipr = b.sim.increments_per_revolution(2)
    assert b.sim.drives[2].store.get_int(0x6081) == round(10 * FACTOR * 60 / ipr * 1000)
    b.sim.power_cycle(2)  # 60A9h is back to rpm
    b.ok("2S04=1")
    assert b.sim.drives[2].store.get_int(0x6081) == round(10 * FACTOR * 60 / ipr)


def test_no_nmt_reset_while_a_powerless_axis_coasts(bridge: SimBridge) -> None:
    b = bridge
    b.ok("2S04=1", "2S26=200", "2S27=2000")
    run_velocity_move(b, 2, speed="150")  # 4500 rpm: it coasts for about 2 s
    b.wait_until(lambda: b.velocity(2) > 140 * FACTOR)
    b.ok("2S80=0x21000004", "2S81=6")  # the simulator's power cycle: it coasts
    b.ask("2S04=1")  # ACK once it stood still, or NAK within ack_timeout
    assert b.now(2).resets_while_moving == 0
