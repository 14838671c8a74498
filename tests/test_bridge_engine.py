"""Tests of the command layer (tcp_bridge.engine, operations, sequences, sdo).

The drives are the ``instant`` backend's fake CiA 402 nodes, whose SDO log shows
exactly which transfers each request caused. Controlword values are from CiA
402-2 6.4.1.3 (06h shutdown, 07h switch on, 0Fh enable operation, bit 4 new
set-point, bit 5 change set immediately, bit 6 relative, bit 7 fault reset,
bit 8 halt); expected drive values are worked out by hand from spec 3.6.
"""
from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any, Dict, List, Optional, Tuple

import pytest

from tcp_bridge.tables.axes import AxisTable
from tcp_bridge.backends.instant import FakeNode
from tcp_bridge.tables.commands import COMMANDS
from tcp_bridge.engine import Engine, build_engine, software_version
from tcp_bridge.errors import DeviceFailure
from tcp_bridge.plan.reads import detailed_error_from_code
from tcp_bridge.wire import Reply, Status, decode_reply, format_error_reply, parse_request
from tcp_bridge.motion import Cia402, State, Timing, decode_state

# An EPOS4 (device 5) takes rpm: rpm = user/s * factor * 60 / IPR. With IPR 60 and
# factor 1000 a drive value is user * 1000, the hand-worked values of spec 3.6.
IPR = 60

FAST = {"ack_timeout": 0.2, "state_timeout": 0.2, "reset_timeout": 0.2, "reset_delay": 0.0,
        "poll_interval": 0.0}


def make(axes: Optional[List[Dict[str, Any]]] = None, **bus: Any) -> Tuple[Engine, Dict[int, FakeNode]]:
    axes = axes if axes is not None else [
        {"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR},
        {"device": 5, "node_id": 2, "position_factor": 1000, "increments_per_revolution": IPR},
    ]
    t = AxisTable.from_mapping({"bridge": FAST, "bus": {"can1": {"backend": "instant", **bus}},
                                "axis": axes})
    engine = build_engine(t)
    return engine, engine.backends[0].nodes


def ask(engine: Engine, line: str) -> Reply:
    """One request through the engine, with the server's exception-to-reply rule."""
    request = None
    try:
        request = parse_request(line.encode())
        raw = engine.execute_sync(request)
    except Exception as exc:
        raw = format_error_reply(exc, request)
    return decode_reply(raw)


def ok(engine: Engine, line: str) -> Optional[str]:
    reply = ask(engine, line)
    assert reply.status is Status.ACK, (line, reply)
    return reply.value


def wait_answering(engine: Engine, timeout: float = 10.0) -> None:
    """Until no link of any bus is declared silent (the probes run every 0.25 s)."""
    deadline = time.monotonic() + timeout
    while any(g.health.refusal(n) for g in engine.guards.values() for n in g.nodes):
        assert time.monotonic() < deadline, "a silent link was never reopened by its probe"
        time.sleep(0.01)


def downloads(node: FakeNode, index: Optional[int] = None) -> List[Tuple[int, int, int]]:
    """(index, subindex, value) of every download, optionally of one object."""
    out = []
    for what, i, s, data in node.log:
        if what == "download" and (index is None or i == index):
            out.append((i, s, int.from_bytes(data, "little", signed=True)))
    return out


def controlwords(node: FakeNode) -> List[int]:
    return [v & 0xFFFF for _, _, v in downloads(node, 0x6040)]


def enabled(engine: Engine, nodes: Dict[int, FakeNode], axis: int = 1) -> FakeNode:
    ok(engine, f"{axis}S04=1")
    node = nodes[axis]
    node.log.clear()
    return node


# --- rights and validation: nothing reaches a drive --------------------------------


@pytest.mark.parametrize("number", sorted(n for n, c in COMMANDS.items() if not c.writable))
def test_read_only_commands_refuse_a_write_without_sdo(number: int) -> None:
    engine, nodes = make()
    assert ask(engine, f"1S{number:02d}=1").status is Status.CAN
    assert nodes[1].log == []


@pytest.mark.parametrize("number", sorted(n for n, c in COMMANDS.items() if not c.readable))
def test_write_only_commands_refuse_a_read_without_sdo(number: int) -> None:
    engine, nodes = make()
    assert ask(engine, f"1R{number:02d}").status is Status.CAN
    assert nodes[1].log == []


@pytest.mark.parametrize("line", [
    "1S02=1x", "1S02=", "1S00=7", "1S00=1.5", "1S04=2", "1S07=2", "1S22=0", "1S05=0x10",
    "1S02=9999999", "1S09=40000", "1S52=-1", "1S29=1", "1S29=7", "1S80=0x60410005",
    "1S81=70000", "1S19=6", "1S86=2", "1S91=3", "7R10", "1R55", "1S90=1", "1R02=1",
])
def test_invalid_requests_answer_can_and_send_nothing(line: str) -> None:
    engine, nodes = make()
    reply = ask(engine, line)
    assert reply.status is Status.CAN, reply
    assert reply.axis == int(line[0])
    assert all(n.log == [] for n in nodes.values())


def test_s81_checks_the_selected_length() -> None:
    engine, nodes = make()
    ok(engine, "1S80=0x60FE0101")  # 60FEh/1, one byte
    assert ask(engine, "1S81=256").status is Status.CAN
    assert nodes[1].log == []


# --- enable, disable, reset ----------------------------------------------------------


def test_enable_after_a_power_cycle_resets_the_node_writes_parameters_then_enables() -> None:
    engine, nodes = make([{"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR,
                           "parameters": {"velocity": 2.0, "acceleration": 30.0}}])
    node = nodes[1]
    ok(engine, "1S05=2.5")  # stored and written at once: 2500 inc/s
    ok(engine, "1S04=1")  # the bridge saw the drive powered
    ok(engine, "1S04=0")
    node.power_cycle()  # it forgot 6081h and fell back to SWITCH ON DISABLED: evidence
    node.resets = 0
    assert ok(engine, "1R04") == "0"
    node.log.clear()
    ok(engine, "1S04=1")
    assert node.resets == 1  # NMT reset node (spec 04: "If PowerCycle then NodeReset")
    assert downloads(node, 0x6081) == [(0x6081, 0, 2500)]
    assert downloads(node, 0x6083) == [(0x6083, 0, 30000)]
    assert downloads(node, 0x6084) == [(0x6084, 0, 30000)]  # 06 also sets deceleration
    # CiA 402: shutdown, switch on, enable operation, each with halt (bit 8) set,
    # so the drive arrives halted (motion rule 2)
    assert controlwords(node) == [0x106, 0x107, 0x10F]
    assert decode_state(node.statusword) is State.OPERATION_ENABLED
    assert ok(engine, "1R04") == "1"
    node.log.clear()
    ok(engine, "1S04=1")  # no power cycle since: no reset, nothing to do
    assert node.resets == 1 and controlwords(node) == []


def test_one_changed_value_is_not_a_power_cycle() -> None:
    # Issue 22 item 2: another master (a studio) writes 6081h; the drive never fell
    # back to SWITCH ON DISABLED. Enable writes the bridge's value back, no NMT reset.
    engine, nodes = make([{"device": 5, "node_id": 1, "position_factor": 1000,
                           "increments_per_revolution": IPR}])
    node = nodes[1]
    for line in ("1S05=2.5", "1S04=1", "1S04=0"):
        ok(engine, line)
    node.values[(0x6081, 0)] = 1
    node.log.clear()
    ok(engine, "1S04=1")
    assert node.resets == 0
    assert downloads(node, 0x6081) == [(0x6081, 0, 2500)]
    assert decode_state(node.statusword) is State.OPERATION_ENABLED


def test_disable_halts_then_disables_operation_then_shuts_down() -> None:
    # Motion rule 1: at rest first (halt, sw bit 10), then Disable Operation (07h,
    # which ramps on an EPOS4: 605Ch = 1), then Shutdown (06h, no ramp: 605Bh = 0).
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S04=0")
    assert controlwords(node) == [0x10F, 0x07, 0x06]
    assert ok(engine, "1R04") == "0"
    node.log.clear()
    ok(engine, "1S04=0")
    assert controlwords(node) == []


def test_enable_leaves_quick_stop_first_and_refuses_a_fault() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.state = "QS"
    ok(engine, "1S04=1")
    assert controlwords(node) == [0x100, 0x106, 0x107, 0x10F]
    node.inject_fault()
    assert ask(engine, "1S04=1").status is Status.NAK


def test_fault_reset_17_is_a_rising_edge_and_never_an_nmt_reset() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.inject_fault(0x8611)
    assert ok(engine, "1R84") == "1"
    assert ok(engine, "1R18") == str(0x81)  # 1001h: generic + manufacturer
    assert ok(engine, "1R11") == str(1 << 3)  # following error (spec 4.b bit 3)
    node.log.clear()
    resets = node.resets  # 1: the first enable
    ok(engine, "1S17=1")
    assert controlwords(node) == [0x00, 0x80, 0x00]
    assert node.resets == resets
    assert ok(engine, "1R84") == "0" and ok(engine, "1R18") == "0"
    ok(engine, "1S04=1")  # enable again without a node reset
    assert node.resets == resets


def test_fault_reset_leaves_a_healthy_drive_alone() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S17=1")
    assert controlwords(node) == []
    assert ok(engine, "1R04") == "1"


def test_reset_node_16_brings_the_axis_to_rest_first_and_the_next_enable_restores() -> None:
    engine, nodes = make([{"device": 5, "node_id": 1, "position_factor": 1000,
                           "increments_per_revolution": IPR, "parameters": {"velocity": 2.0}}])
    node = nodes[1]
    node.values[(0x6081, 0)] = 2000  # the drive holds the table's value: no reset
    ok(engine, "1S04=1")
    assert node.resets == 0  # a bridge start is not a power cycle
    node.log.clear()
    ok(engine, "1S16=1")  # the client asked for exactly this (motion rule 1)
    assert node.resets == 1
    assert controlwords(node) == [0x10F]  # halt, at rest, then the NMT reset
    node.log.clear()
    ok(engine, "1S04=1")
    assert node.resets == 1  # the node was just reset: the parameters go back, no reset
    assert downloads(node, 0x6081) == [(0x6081, 0, 2000)]


# --- moves --------------------------------------------------------------------------


def test_absolute_move_with_set_point_handshake() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S02=12.5")
    assert downloads(node, 0x607A) == [(0x607A, 0, 12500)]
    ok(engine, "1S00=1")
    # bit 4 low with halt as the enable left it (12Fh = enable + change set
    # immediately + halt), rising with halt released in the same write (3Fh),
    # bit 4 low again (2Fh)
    assert controlwords(node) == [0x12F, 0x3F, 0x2F]
    assert ok(engine, "1R82") == "1"
    assert ok(engine, "1R12") == "12.5"
    assert ok(engine, "1R86") == "1"


def test_relative_move_goes_from_the_position_demand_value_with_no_offset() -> None:
    # tcp_bridge.motion rule 4: the distance is added to 6062h and the move is
    # absolute (cw bit 6 low), since bit 6 would count from the preceding target.
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.values[(0x6062, 0)] = 4321
    ok(engine, "1S25=100")  # an offset never applies to a distance
    ok(engine, "1S02=-1.5")
    node.log.clear()
    ok(engine, "1S00=2")
    assert downloads(node, 0x607A) == [(0x607A, 0, 4321 - 1500)]
    assert controlwords(node) == [0x12F, 0x3F, 0x2F]


def test_offset_and_inversion_on_target_and_position() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S22=-1")
    ok(engine, "1S25=1.25")
    node.log.clear()
    ok(engine, "1S02=10")
    # round((10 - 1.25) * 1000) * -1 = -8750 (spec 3.6 with offset and inversion)
    assert downloads(node, 0x607A) == [(0x607A, 0, -8750)]
    ok(engine, "1S00=1")
    assert node.values[(0x6064, 0)] == -8750
    assert ok(engine, "1R12") == "10"
    assert ok(engine, "1R61") == "-8750"  # encoder position in system units
    assert ok(engine, "1R02") == "10"


def test_a_position_poll_follows_every_change_of_inversion_and_offset() -> None:
    # The scalings and the formatted replies are kept between polls (issue 14):
    # each change of 22 or 25, and each raw value, must still show at once.
    engine, nodes = make()
    nodes[1].values[(0x6064, 0)] = 2500
    seen = [ok(engine, "1R12")]
    for line in ("1S25=0.5", "1S22=-1", "1S25=0", "1S22=1"):
        ok(engine, line)
        seen.append(ok(engine, "1R12"))
    nodes[1].values[(0x6064, 0)] = 2501
    seen.append(ok(engine, "1R12"))
    assert seen == ["2.5", "3", "-2", "-2.5", "2.5", "2.501"]
    assert ok(engine, "2R12") == "0"  # the same raw value, another axis: its own scaling


def test_an_axis_scaling_follows_its_device_code_and_velocity_prefix() -> None:
    engine, _ = make()
    ops = engine.axes[1]
    first = ops.scaling()
    assert ops.scaling() is first  # kept while nothing it depends on changes
    ops.velocity_exponent = -3
    assert ops.scaling().units.velocity_exponent == -3
    engine.params.set(1, 19, 1)  # another device: no EPOS4 velocity units
    assert ops.scaling().units.increments_per_revolution is None
    engine.params.set(1, 19, 5)
    engine.params.set(1, 25, 2000)  # offset 2 (stored x factor)
    assert ops.scaling().offset == 2.0 and ops.scaling().units.velocity_exponent == -3
    assert engine.params.values(1, (19, 25, 22)) == (5, 2000, engine.params.get(1, 22))


def test_display_limits_swap_on_an_inverted_axis() -> None:
    engine, nodes = make()
    node = nodes[1]
    node.values[(0x607D, 1)] = -5000
    node.values[(0x607D, 2)] = 20000
    assert (ok(engine, "1R33"), ok(engine, "1R34")) == ("20", "-5")
    assert (ok(engine, "1R23"), ok(engine, "1R24")) == ("20", "-5")
    ok(engine, "1S22=-1")
    ok(engine, "1S25=1")
    # positive display limit from 607Dh/1: -5000 * -1 / 1000 + 1 = 6
    assert (ok(engine, "1R33"), ok(engine, "1R34")) == ("6", "-19")


def test_velocity_move_stop_and_82_in_velocity_mode() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S05=-2")  # signed: the direction of a velocity move
    assert downloads(node, 0x6081) == [(0x6081, 0, 2000)]  # 6081h is UNSIGNED32
    assert ok(engine, "1R05") == "-2"
    node.log.clear()
    ok(engine, "1S00=3")
    assert downloads(node, 0x60FF) == [(0x60FF, 0, -2000)]
    assert downloads(node, 0x6060) == [(0x6060, 0, 3)]
    assert ok(engine, "1R82") == "0"  # moving at constant speed: bit 10 alone would say 1
    node.log.clear()
    ok(engine, "1S00=8")
    assert controlwords(node) == [0x10F]  # halt
    assert downloads(node, 0x60FF) == [(0x60FF, 0, 0)]  # and no velocity left to resume
    assert ok(engine, "1R82") == "1"
    assert ok(engine, "1R04") == "1"  # halt keeps the drive enabled


def test_next_move_after_stop_releases_halt_with_its_own_set_point() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S02=1")
    ok(engine, "1S00=8")
    node.log.clear()
    ok(engine, "1S00=1")
    # halt stays set while the target is written; the edge of bit 4 releases it
    assert controlwords(node) == [0x12F, 0x3F, 0x2F]


def test_homing_mode_6_and_bit_4() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.values[(0x6064, 0)] = 777
    ok(engine, "1S00=9")
    assert downloads(node, 0x6060) == [(0x6060, 0, 6)]
    # a mode change halts first (rule 2); bit 4 low with halt, then the start edge
    # with halt released; bit 4 stays high (falling would interrupt the homing)
    assert controlwords(node) == [0x10F, 0x10F, 0x1F]
    assert ok(engine, "1R12") == "0" and ok(engine, "1R82") == "1"
    assert ok(engine, "1R15") == "6"


def test_mode_of_operation_07_and_its_display_15() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    for mode in (3, 6, 1):  # profile velocity, homing, profile position (CiA 402-2 6.3)
        node.log.clear()
        ok(engine, f"1S07={mode}")
        assert downloads(node, 0x6060) == [(0x6060, 0, mode)]
        assert ok(engine, "1R07") == str(mode)  # 6060h
        assert ok(engine, "1R15") == str(mode)  # 6061h, the drive's display
    node.log.clear()
    ok(engine, "1S07=1")  # already displayed: nothing to write
    assert downloads(node, 0x6060) == []


def test_move_needs_an_enabled_drive_and_a_target() -> None:
    engine, nodes = make()
    assert ask(engine, "1S00=1").status is Status.CAN  # no S02 yet: nothing to move to
    ok(engine, "1S02=1")
    assert ask(engine, "1S00=1").status is Status.NAK  # not enabled
    assert ok(engine, "1R86") == "0"


def test_moving_acknowledgement_86() -> None:
    engine, nodes = make()
    enabled(engine, nodes)
    ok(engine, "1S86=0")
    assert ok(engine, "1R86") == "0"
    ok(engine, "1S02=3")
    ok(engine, "1S00=1")
    assert ok(engine, "1R86") == "1"


class NoAckNode(FakeNode):
    """A drive that never acknowledges a set-point."""

    @property
    def statusword(self) -> int:
        return FakeNode.statusword.fget(self) & ~0x1000  # type: ignore[attr-defined]


def test_unacknowledged_set_point_is_nak_within_the_bound() -> None:
    now = [0.0]  # the engine's clock: each pause advances it (no wall clock, issue 12)

    def sleep(dt: float) -> None:
        now[0] += max(dt, 0.001)
    t = AxisTable.from_mapping({"bridge": FAST, "bus": {"can1": {"backend": "instant"}},
                                "axis": [{"device": 5, "node_id": 1, "position_factor": 1000,
                                          "increments_per_revolution": IPR}]})
    engine = build_engine(t, clock=lambda: now[0], sleep=sleep)
    node = NoAckNode(1)
    engine.axes[1].port.node = node  # type: ignore[union-attr]
    ok(engine, "1S04=1")
    ok(engine, "1S02=1")
    start = now[0]
    assert ask(engine, "1S00=1").status is Status.NAK
    assert now[0] - start <= 0.2 + 0.002  # ack_timeout is 0.2 s here
    # Never acknowledged, but this fake moves at the edge of bit 4 all the same: its
    # position demand 6062h left where it stood, so R86 says the move started (issue 35).
    assert ok(engine, "1R86") == "1"
    assert engine.axes[1].drive.power_cycle_evidence is None  # type: ignore[union-attr]


def test_slave_axis_follows_with_its_direction() -> None:
    engine, nodes = make()
    enabled(engine, nodes, 1)
    slave = enabled(engine, nodes, 2)
    ok(engine, "1S29=2")
    ok(engine, "1S30=-1")
    ok(engine, "1S02=4")
    ok(engine, "1S00=1")
    assert downloads(slave, 0x607A) == [(0x607A, 0, -4000)]
    assert ok(engine, "2R12") == "-4" and ok(engine, "1R12") == "4"
    ok(engine, "1S05=1")
    ok(engine, "1S00=3")
    assert slave.values[(0x60FF, 0)] == -1000
    ok(engine, "1S00=8")
    assert slave.values[(0x6040, 0)] & 0x100


def test_combined_move_90_moves_internal_axes() -> None:
    engine, nodes = make([
        {"internal": True, "profile": "drive", "node_id": 1, "position_factor": 10},
        {"internal": True, "profile": "drive", "node_id": 2, "position_factor": 10},
        {"node_id": 3},
    ])
    for axis in (1, 2):
        enabled(engine, nodes, axis)
        ok(engine, f"{axis}S02={axis}")
    ok(engine, "3S90=1")  # LINR: each internal axis moves by its own 02
    assert (ok(engine, "1R12"), ok(engine, "2R12")) == ("1", "2")
    ok(engine, "1S90=1")
    assert (ok(engine, "1R12"), ok(engine, "2R12")) == ("2", "4")
    ok(engine, "1S90=2")  # LINA to zero
    assert (ok(engine, "1R12"), ok(engine, "2R12")) == ("0", "0")
    ok(engine, "1S90=0")
    assert nodes[3].log == []


# --- reads, parameters, raw access ------------------------------------------------------


def test_statusword_bits_82_83_84() -> None:
    engine, nodes = make()
    nodes[1].values[(0x6040, 0)] = 0  # statusword 0x0640: bits 6, 9, 10
    assert ok(engine, "1R10") == str(0x0640)
    assert [ok(engine, f"1R{c}") for c in (82, 83, 84)] == ["1", "0", "0"]


def test_nanotec_position_reads_6062() -> None:
    engine, nodes = make([{"device": 1, "node_id": 1}])
    nodes[1].values[(0x6062, 0)] = 42
    nodes[1].values[(0x6064, 0)] = 7
    assert ok(engine, "1R12") == "42"
    assert ok(engine, "1R61") == "7"


def test_max_velocity_26_is_internal_for_technosoft() -> None:
    engine, nodes = make([{"device": 2, "node_id": 1, "position_factor": 10},
                          {"device": 5, "node_id": 2, "position_factor": 10,
                           "increments_per_revolution": IPR}])
    ok(engine, "1S26=5")
    ok(engine, "2S26=5")
    assert downloads(nodes[1]) == [] and downloads(nodes[2]) == [(0x607F, 0, 50)]
    assert ok(engine, "1R26") == "5"


def test_parameters_85_write_all() -> None:
    engine, nodes = make([{"device": 5, "node_id": 1, "position_factor": 10,
                           "increments_per_revolution": IPR, "parameters": {"max_velocity": 3, "homing_mode": 35,
                                          "quickstop_accel": 7}}])
    ok(engine, "1S85=1")
    assert sorted(downloads(nodes[1])) == [(0x607F, 0, 30), (0x6085, 0, 70), (0x6098, 0, 35)]


def test_raw_sdo_80_81() -> None:
    engine, nodes = make()
    assert ok(engine, "1R80") == "0x60410002"
    ok(engine, "1S80=0x60810004")
    assert ok(engine, "1R80") == "0x60810004"
    ok(engine, "1S81=1234")
    assert nodes[1].values[(0x6081, 0)] == 1234
    assert ok(engine, "1R81") == "1234"
    ok(engine, "1S80=0x607A0004")
    ok(engine, "1S81=-5")
    assert ok(engine, "1R81") == "-5"  # 607Ah is INTEGER32
    ok(engine, "1S80=0x12340001")
    assert ask(engine, "1R81").status is Status.NAK  # abort 06020000h: no such object


def test_parameter_kept_only_when_the_drive_took_it() -> None:
    engine, nodes = make()
    nodes[1].values.pop((0x6083, 0))  # the object is gone: abort
    assert ask(engine, "1S06=5").status is Status.NAK
    assert engine.params.get(1, 6) is None


def test_internal_parameters_and_globals() -> None:
    engine, nodes = make()
    assert ok(engine, "1R31") == "3" and ok(engine, "1R32") == "0"
    ok(engine, "1S54=20")
    ok(engine, "1S19=5")
    assert ok(engine, "1R54") == "20" and ok(engine, "1R19") == "5"
    assert ok(engine, "1R99") == software_version() == ok(engine, "59R99")
    assert ok(engine, "1R91") == "0"
    ok(engine, "1S91=1")
    assert ok(engine, "2R91") == "1" and engine.debug
    assert all(n.log == [] for n in nodes.values())


def test_detailed_error_register() -> None:
    # EPOS4 codes (EPOS4 Firmware Specification error table) -> spec 4.b bits
    assert detailed_error_from_code(0x8A81, 0x2) == 1 << 6  # positive limit switch
    assert detailed_error_from_code(0x8A80, 0x1) == 1 << 7  # negative limit switch
    assert detailed_error_from_code(0x8A88, 0) == 1 << 15  # STO, not a limit switch
    assert detailed_error_from_code(0x8A82, 0, 8) == 1 << 8  # software limit, positive side
    assert detailed_error_from_code(0x8A82, 0, 9) == 1 << 9
    assert detailed_error_from_code(0x2320, 0) == 1 << 1  # short circuit
    assert detailed_error_from_code(0x3210, 0) == 1 << 12  # over-voltage
    assert detailed_error_from_code(0x3220, 0) == 1 << 13  # under-voltage
    assert detailed_error_from_code(0x4310, 0) == 1 << 11
    assert detailed_error_from_code(0x8130, 0) == 1 << 4
    assert detailed_error_from_code(0, 0) == 0
    engine, nodes = make([{"device": 2, "node_id": 1}])
    nodes[1].values[(0x2000, 0)] = (1 << 8) | (1 << 13)  # Technosoft MER: over-current, UV
    assert ok(engine, "1R11") == str((1 << 10) | (1 << 13))


# --- absent nodes ----------------------------------------------------------------------


@pytest.mark.parametrize("line", ["1R10", "1R12", "1S04=1", "1S02=1", "1R02", "1S17=1",
                                  "1S00=8", "1R11", "1S85=1", "1R81"])
def test_absent_node_answers_nak(line: str) -> None:
    engine, nodes = make(absent=[1])
    start = time.monotonic()
    assert ask(engine, line).status is Status.NAK
    assert time.monotonic() - start < 1.0


def test_a_node_that_was_silent_once_is_not_reset_by_the_next_enable() -> None:
    # Finding 1 of issue 10: a timeout is not evidence of a power cycle.
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.absent = True
    assert ask(engine, "1R10").status is Status.NAK
    node.absent = False
    wait_answering(engine)  # fail-fast (issue 12): the node's probe reopens it
    ok(engine, "1S04=0")
    ok(engine, "1S04=1")
    assert node.resets == 0


def test_a_fall_back_with_the_values_kept_writes_them_again_without_a_reset() -> None:
    # An external quick stop input also ends in SWITCH ON DISABLED: not a power cycle.
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S05=2")
    node.state = "SOD"
    assert ok(engine, "1R04") == "0"  # a poll sees the fall back (rule 3: look)
    node.log.clear()
    ok(engine, "1S04=1")
    assert node.resets == 0
    assert downloads(node, 0x6081) == [(0x6081, 0, 2000)]  # written again, no reset


def test_a_fall_back_with_the_values_lost_is_a_power_cycle() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S05=2")
    node.power_cycle()  # behind the bridge's back: SWITCH ON DISABLED, defaults
    node.resets = 0
    ok(engine, "1S04=1")
    assert node.resets == 1  # spec 04: NodeReset and WriteParameter
    assert node.values[(0x6081, 0)] == 2000


def test_values_written_through_81_are_not_taken_for_a_power_cycle() -> None:
    engine, nodes = make()
    node = enabled(engine, nodes)
    ok(engine, "1S05=2")
    ok(engine, "1S80=0x60810004")
    ok(engine, "1S81=5000")  # the client's own value for 6081h
    ok(engine, "1S04=0")
    ok(engine, "1S04=1")
    assert node.resets == 0


def test_table_parameters_are_written_by_the_first_enable_without_a_reset() -> None:
    engine, nodes = epos4(IPR, parameters={"velocity": 3.0})
    node = nodes[1]
    ok(engine, "1S04=1")
    assert node.resets == 0  # a bridge start is not a power cycle
    assert downloads(node, 0x6081) == [(0x6081, 0, 3000)]


# --- state machine helpers -----------------------------------------------------------------


@pytest.mark.parametrize("statusword,state", [
    (0x0000, State.NOT_READY_TO_SWITCH_ON), (0x0250, State.SWITCH_ON_DISABLED),
    (0x0231, State.READY_TO_SWITCH_ON), (0x0233, State.SWITCHED_ON),
    (0x1637, State.OPERATION_ENABLED), (0x0217, State.QUICK_STOP_ACTIVE),
    (0x021F, State.FAULT_REACTION_ACTIVE), (0x0218, State.FAULT),
])
def test_decode_state(statusword: int, state: State) -> None:
    # CiA 402-2 6.4.1.4 state coding; bit 4 voltage enabled and bit 9 remote are ignored.
    assert decode_state(statusword) is state


def test_wait_status_is_bounded_by_the_clock() -> None:
    now = [0.0]

    def sleep(dt: float) -> None:
        now[0] += 0.01

    class Port:
        name = "p"

        def read(self, index: int, sub: int) -> int:
            return 0x0250

    drive = Cia402(Port(), Timing(), clock=lambda: now[0], sleep=sleep)  # type: ignore[arg-type]
    with pytest.raises(DeviceFailure, match="within 0.5 s"):
        drive.wait_status(lambda sw: False, 0.5, "never")
    assert 0.5 <= now[0] < 0.6


def test_wait_for_node_waits_out_the_old_state_and_silence() -> None:
    # After NMT reset a drive boots into SWITCH ON DISABLED (CiA 402-2 6.4.1.1);
    # reads before the reset took effect, or while the node boots, are waited out.
    answers: List[Any] = [0x0237, DeviceFailure("silent"), DeviceFailure("silent"), 0x0250]
    now = [0.0]

    class Port:
        name = "p"

        def read(self, index: int, sub: int) -> int:
            answer = answers.pop(0)
            if isinstance(answer, Exception):
                raise answer
            return answer

    def sleep(dt: float) -> None:
        now[0] += dt

    drive = Cia402(Port(), Timing(reset_delay=0.3, reset_timeout=1.0),  # type: ignore[arg-type]
                   clock=lambda: now[0], sleep=sleep)
    drive.wait_for_node()
    assert answers == [] and now[0] >= 0.3
    answers[:] = [0x0237] * 200
    with pytest.raises(DeviceFailure, match="still OPERATION_ENABLED"):
        drive.wait_for_node()


# --- execution: buses serialised, parallel, loop never blocked -------------------------------


class HeldNode(FakeNode):
    """Each upload is held until the test releases it; ``active`` counts the uploads in
    flight on each bus, ``peak`` the most at once (no wall clock, issue 12)."""

    lock = threading.Lock()

    def __init__(self, node_id: int, bus: str, active: Dict[str, int], peak: Dict[str, int]) -> None:
        super().__init__(node_id)
        self.bus, self.active, self.peak = bus, active, peak
        self.entered = threading.Event()
        self.release = threading.Event()

    def upload(self, index: int, subindex: int) -> bytes:
        with self.lock:
            self.active[self.bus] += 1
            self.peak[self.bus] = max(self.peak[self.bus], self.active[self.bus])
        self.entered.set()
        try:
            assert self.release.wait(30), "never released"
        finally:
            with self.lock:
                self.active[self.bus] -= 1
        return super().upload(index, subindex)


def test_one_bus_is_serialised_buses_run_in_parallel() -> None:
    t = AxisTable.from_mapping({
        "bridge": FAST,
        "bus": {"can1": {"backend": "instant"}, "can2": {"backend": "instant"}},
        "axis": [{"node_id": 1}, {"node_id": 2}, {"node_id": 1, "bus_offset": 100000}],
    })
    active = {"can1": 0, "can2": 0}
    peak = dict(active)
    nodes = {1: HeldNode(1, "can1", active, peak), 2: HeldNode(2, "can1", active, peak),
             3: HeldNode(1, "can2", active, peak)}
    engine = Engine(t, nodes)

    async def entered(node: HeldNode) -> None:
        assert await asyncio.get_running_loop().run_in_executor(None, node.entered.wait, 30)

    def request(line: str) -> "asyncio.Future[bytes]":
        return asyncio.ensure_future(engine.execute(parse_request(line.encode())))

    async def scenario() -> None:
        # One bus: while axis 1's transfer is held, axis 2's does not start.
        first, second = request("1R10"), request("2R10")
        await entered(nodes[1])
        await asyncio.sleep(0.05)  # room for a wrong implementation to start axis 2
        assert not nodes[2].entered.is_set() and active["can1"] == 1
        # Two buses: axis 3 (can2) starts while axis 1 (can1) is still held.
        third = request("3R10")
        await entered(nodes[3])
        # The event loop is not blocked by either: a request without a drive is answered.
        assert (await asyncio.wait_for(engine.execute(parse_request(b"1R99")), 30)).startswith(b"1 R 99=")
        for node in nodes.values():
            node.release.set()
        await asyncio.gather(first, second, third)

    asyncio.run(scenario())
    engine.close()
    assert peak == {"can1": 1, "can2": 1}
    assert nodes[2].entered.is_set()


# --- companions (29/30 slave, 90 combined): nothing moves unless every axis can ----------


def run_async(engine: Engine, line: str) -> Reply:
    """One request through the real async path (Engine.execute, bus worker threads)."""
    request = parse_request(line.encode())

    async def go() -> bytes:
        try:
            return await engine.execute(request)
        except Exception as exc:
            return format_error_reply(exc, request)
    return decode_reply(asyncio.run(go()))


def test_slave_does_not_move_when_its_master_refuses() -> None:
    engine, nodes = make()
    slave = enabled(engine, nodes, 2)  # the master (axis 1) is NOT enabled
    ok(engine, "1S29=2")
    ok(engine, "1S02=4")
    slave.log.clear()
    assert run_async(engine, "1S00=1").status is Status.NAK
    assert downloads(slave, 0x607A) == [] and controlwords(slave) == []
    assert ok(engine, "2R12") == "0"
    engine.close()


def test_master_does_not_move_when_its_slave_is_not_enabled() -> None:
    engine, nodes = make()
    master = enabled(engine, nodes, 1)  # the slave (axis 2) is NOT enabled
    ok(engine, "1S29=2")
    ok(engine, "1S02=4")
    master.log.clear()
    assert run_async(engine, "1S00=1").status is Status.NAK
    assert downloads(master, 0x607A) == [] and controlwords(master) == []
    assert ok(engine, "1R12") == "0"
    engine.close()


def test_master_is_halted_when_its_slave_fails_during_the_move() -> None:
    engine, nodes = make()
    master = enabled(engine, nodes, 1)
    enabled(engine, nodes, 2)
    stuck = NoAckNode(2)  # enabled, but never acknowledges the set-point
    ok(engine, "1S29=2")
    ok(engine, "1S02=4")
    stuck.state = "OE"
    engine.axes[2].port.node = stuck  # type: ignore[union-attr]
    master.log.clear()
    assert run_async(engine, "1S00=1").status is Status.NAK
    assert master.values[(0x6040, 0)] & 0x100  # halt (cw bit 8)
    assert stuck.values[(0x6040, 0)] & 0x100  # and the slave too
    engine.close()


def test_stop_halts_the_slave_even_when_the_master_is_absent() -> None:
    engine, nodes = make()
    slave = enabled(engine, nodes, 2)
    ok(engine, "1S29=2")
    nodes[1].absent = True
    assert run_async(engine, "1S00=8").status is Status.NAK
    assert slave.values[(0x6040, 0)] & 0x100
    engine.close()


def test_combined_move_90_moves_nothing_when_one_axis_is_not_enabled() -> None:
    engine, nodes = make([
        {"internal": True, "profile": "drive", "node_id": 1, "position_factor": 10},
        {"internal": True, "profile": "drive", "node_id": 2, "position_factor": 10},
    ])
    first = enabled(engine, nodes, 1)  # axis 2 is NOT enabled
    ok(engine, "1S02=1")
    ok(engine, "2S02=1")
    first.log.clear()
    assert run_async(engine, "1S90=1").status is Status.NAK
    assert downloads(first, 0x607A) == [] and ok(engine, "1R12") == "0"
    engine.close()


def test_failed_state_file_write_is_still_ack(tmp_path: Any) -> None:
    # The drive and the arrays hold the new value; only its persistence failed
    # (logged), so NAK ("nothing changed", spec 2.2.2) would be a lie.
    blocker = tmp_path / "gone"
    t = AxisTable.from_mapping({"bridge": {**FAST, "state_file": str(blocker / "s.json")},
                                "bus": {"can1": {"backend": "instant"}},
                                "axis": [{"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR}]})
    engine = build_engine(t)
    blocker.rmdir()  # made by the start-up check (issue 12) ...
    blocker.write_text("x")  # ... replaced after start: the directory cannot be created
    assert run_async(engine, "1S05=3").status is Status.ACK  # drive parameter (6081h)
    assert engine.backends[0].nodes[1].values[(0x6081, 0)] == 3000
    assert run_async(engine, "1S22=-1").status is Status.ACK  # internal parameter
    assert run_async(engine, "1R22").value == "-1"
    engine.close()


def test_a_stuck_state_file_never_stalls_the_bus(tmp_path: Any, monkeypatch: Any) -> None:
    """Issue 35: the ACK of an S command waits for the state file, the bus does not."""
    import tcp_bridge.tables.parameters as parameters

    disk = threading.Event()
    written = threading.Event()
    real = parameters.write_atomically

    def stuck(path: Any, text: str) -> None:
        disk.wait(30)
        real(path, text)
        written.set()
    monkeypatch.setattr(parameters, "write_atomically", stuck)
    path = tmp_path / "s.json"
    t = AxisTable.from_mapping({"bridge": {**FAST, "state_file": str(path)},
                                "bus": {"can1": {"backend": "instant"}},
                                "axis": [{"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR}]})
    engine = build_engine(t)

    async def go() -> List[Reply]:
        writes = [asyncio.ensure_future(engine.execute(parse_request(line)))
                  for line in (b"1S05=3", b"1S22=-1")]
        read = decode_reply(await engine.execute(parse_request(b"1R10")))  # the bus is free ...
        assert read.status is Status.ACK
        assert engine.backends[0].nodes[1].values[(0x6081, 0)] == 3000  # ... 6081h written
        assert not any(w.done() for w in writes)  # ... but no ACK while the disk is stuck
        assert not written.is_set()
        disk.set()
        return [decode_reply(r) for r in await asyncio.gather(*writes)]
    assert [r.status for r in asyncio.run(go())] == [Status.ACK, Status.ACK]
    assert written.is_set()  # both ACKs came after the write ended
    assert json.loads(path.read_text())["axes"]["1"]["parameters"] == {"22": -1, "5": 3000}
    engine.close()


def test_an_ack_leaves_only_once_its_value_is_on_disk(tmp_path: Any, monkeypatch: Any) -> None:
    """Issue 35: at the moment each ACK leaves, the state file already holds its value;
    writes that arrive together share a write (batched), and each gets its ACK."""
    import tcp_bridge.tables.parameters as parameters

    path = tmp_path / "s.json"
    real = parameters.write_atomically
    writes: List[int] = []

    def counted(p: Any, text: str) -> None:
        writes.append(1)
        real(p, text)
    monkeypatch.setattr(parameters, "write_atomically", counted)
    t = AxisTable.from_mapping({"bridge": {**FAST, "state_file": str(path)},
                                "bus": {"can1": {"backend": "instant"}},
                                "axis": [{"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR}]})
    engine = build_engine(t)
    on_disk_at_ack: List[Tuple[int, int]] = []

    async def one(n: int) -> None:
        reply = decode_reply(await engine.execute(parse_request(f"1S54={n}".encode())))
        assert reply.status is Status.ACK
        on_disk = json.loads(path.read_text())["axes"]["1"]["parameters"]["54"]
        on_disk_at_ack.append((n, on_disk))

    async def go() -> None:
        for n in range(5):  # one after the other: each its own write
            await one(n)
        await asyncio.gather(*(one(n) for n in range(10, 40)))  # together: batched
    asyncio.run(go())
    engine.close()
    assert on_disk_at_ack[:5] == [(n, n) for n in range(5)]
    # a batch holds the newest value resolved so far: never one older than the ACK's
    assert all(disk >= n for n, disk in on_disk_at_ack[5:]), on_disk_at_ack
    assert len(writes) < 5 + 30  # the 30 concurrent writes shared fsyncs


def test_move_nak_comes_within_one_ack_timeout() -> None:
    # The set-point acknowledge (sw bit 12) of a previous set-point stays high
    # for 0.15 s, then the drive never acknowledges the new one. The documented
    # bound is ack_timeout (0.2 s here) for the whole move, not per wait.
    now = [0.0]

    def sleep(dt: float) -> None:
        now[0] += max(dt, 0.01)

    class LateNode(FakeNode):
        ack_high_until = float("inf")

        @property
        def statusword(self) -> int:
            sw = FakeNode.statusword.fget(self) & ~0x1000  # type: ignore[attr-defined]
            return sw | 0x1000 if now[0] < self.ack_high_until else sw

    t = AxisTable.from_mapping({"bridge": FAST, "bus": {"can1": {"backend": "instant"}},
                                "axis": [{"device": 5, "node_id": 1, "position_factor": 1000, "increments_per_revolution": IPR}]})
    engine = build_engine(t, clock=lambda: now[0], sleep=sleep)
    node = LateNode(1)
    engine.axes[1].port.node = node  # type: ignore[union-attr]
    ok(engine, "1S04=1")
    ok(engine, "1S02=1")
    start = now[0]
    node.ack_high_until = start + 0.15
    assert ask(engine, "1S00=1").status is Status.NAK
    assert now[0] - start <= 0.2 + 0.011
    engine.close()


def test_82_reads_the_drive_mode_not_a_remembered_one() -> None:
    # Mode changes the bridge did not make (another master, a drive reset) must
    # not change the meaning of 82: the drive's 6061h decides. (S81 refuses to
    # write these objects of an enabled axis: another master writes them here.)
    engine, nodes = make()
    node = enabled(engine, nodes)
    node.download(0x6060, 0, (3).to_bytes(1, "little"))  # profile velocity, behind its back
    node.download(0x60FF, 0, (2000).to_bytes(4, "little"))
    node.download(0x6040, 0, (15).to_bytes(2, "little"))  # halt released: sw 10 set, 12 clear
    assert ok(engine, "1R82") == "0"
    ok(engine, "1S05=1")
    ok(engine, "1S00=3")  # a velocity move the bridge made ...
    node.download(0x6060, 0, (1).to_bytes(1, "little"))  # ... then profile position
    assert node.statusword & 0x1400 == 0x0400  # target reached, no set-point acknowledge
    assert ok(engine, "1R82") == "1"


def test_a_multi_axis_move_that_times_out_is_halted() -> None:
    """The engine's safety-net timeout cancels a slave/master move part-way: every
    axis of the request is then halted, not left moving."""

    class StallingNode(FakeNode):
        stall = 0.0

        def download(self, index: int, subindex: int, data: bytes, force_segment: bool = False) -> None:
            if index == 0x607A and self.stall:
                time.sleep(self.stall)
                self.stall = 0.0
            super().download(index, subindex, data, force_segment)

    engine, nodes = make()
    master = enabled(engine, nodes, 1)
    enabled(engine, nodes, 2)
    slave = StallingNode(2)
    slave.state = "OE"
    engine.axes[2].port.node = slave  # type: ignore[union-attr]
    ok(engine, "1S29=2")
    ok(engine, "1S02=4")
    engine.job_timeout = 0.3
    slave.stall = 0.6  # the slave's target write outlasts the request's time
    assert run_async(engine, "1S00=1").status is Status.NAK
    deadline = time.monotonic() + 5
    while not (master.values.get((0x6040, 0), 0) & 0x100 and slave.values.get((0x6040, 0), 0) & 0x100):
        assert time.monotonic() < deadline, "the axes were not halted"
        time.sleep(0.01)
    engine.close()


# --- EPOS4 units (issue 10, finding 4) ------------------------------------------------------


def epos4(ipr: int = 2048, **extra: Any) -> Tuple[Engine, Dict[int, FakeNode]]:
    return make([{"device": 5, "node_id": 1, "position_factor": 1000,
                  "increments_per_revolution": ipr, **extra}])


def test_epos4_velocities_are_rpm_and_accelerations_rpm_per_second() -> None:
    engine, nodes = epos4(2048)  # 512-pulse encoder x 4
    ok(engine, "1S05=10")  # 10 mm/s = 10000 inc/s = 10000 * 60 / 2048 rpm = 292.97 -> 293
    assert downloads(nodes[1], 0x6081) == [(0x6081, 0, 293)]
    ok(engine, "1S06=100")  # 100 mm/s^2 = 2929.7 rpm/s -> 2930, deceleration too
    assert downloads(nodes[1], 0x6083) == [(0x6083, 0, 2930)]
    assert downloads(nodes[1], 0x6084) == [(0x6084, 0, 2930)]
    for cmd, index, sub in ((26, 0x607F, 0), (41, 0x6099, 1), (42, 0x6099, 2)):
        ok(engine, f"1S{cmd}=10")
        assert downloads(nodes[1], index)[-1] == (index, sub, 293)
    for cmd, index in ((27, 0x60C5), (28, 0x6085), (43, 0x609A)):
        ok(engine, f"1S{cmd}=100")
        assert downloads(nodes[1], index)[-1] == (index, 0, 2930)
    assert ok(engine, "1R05") == "10"  # the stored value, as written
    nodes[1].values[(0x606C, 0)] = 293  # 293 rpm actual = 10.0012 mm/s
    assert float(ok(engine, "1R14")) == pytest.approx(10.0, abs=0.01)
    ok(engine, "1S04=1")
    ok(engine, "1S05=-10")
    ok(engine, "1S00=3")
    assert nodes[1].values[(0x60FF, 0)] == -293


def test_epos4_velocity_prefix_from_60a9_is_honoured() -> None:
    engine, nodes = epos4(2048)
    nodes[1].values[(0x60A9, 0)] = 0xFDB44700  # milli-rpm
    ok(engine, "1S05=10")
    assert downloads(nodes[1], 0x6081) == [(0x6081, 0, 292969)]  # 292.96875 rpm in milli-rpm
    ok(engine, "1S06=100")  # 60AAh is fixed: accelerations stay rpm/s
    assert downloads(nodes[1], 0x6083) == [(0x6083, 0, 2930)]


def test_a_prefix_below_milli_rpm_is_an_unknown_unit() -> None:
    # maxon's velocity notation stops at milli-rpm (Definitions.h VN_MILLI = -3):
    # 10^-4..10^-6 rpm are not scaled by a guess; velocity commands are refused.
    engine, nodes = epos4(2048)
    nodes[1].values[(0x60A9, 0)] = 0xFAB44700
    assert ask(engine, "1S05=10").status is Status.NAK
    assert downloads(nodes[1], 0x6081) == []


def test_an_unknown_velocity_unit_refuses_velocity_commands_only(caplog: Any) -> None:
    engine, nodes = epos4(2048)
    nodes[1].values[(0x60A9, 0)] = 0x00B44800  # revolutions per hour: not rpm
    assert ask(engine, "1S05=10").status is Status.NAK
    assert downloads(nodes[1], 0x6081) == []
    assert "0x00B44800 is not rpm" in caplog.text
    assert ask(engine, "1R14").status is Status.NAK
    ok(engine, "1S06=100")  # accelerations do not depend on 60A9h
    ok(engine, "1S02=1")
    ok(engine, "1S04=1")
    ok(engine, "1S00=1")  # a position move needs no velocity unit


def test_devices_1_to_4_keep_increments_per_second() -> None:
    engine, nodes = make([{"device": 2, "node_id": 1, "position_factor": 1000}])
    ok(engine, "1S05=10")
    assert downloads(nodes[1], 0x6081) == [(0x6081, 0, 10000)]


def test_device_code_5_needs_increments_per_revolution() -> None:
    engine, nodes = make([{"device": 2, "node_id": 1, "position_factor": 1000}])
    assert ask(engine, "1S19=5").status is Status.CAN
    engine, nodes = make([{"device": 2, "node_id": 1, "position_factor": 1000,
                           "increments_per_revolution": 2048}])
    ok(engine, "1S19=5")
    ok(engine, "1S05=10")
    assert downloads(nodes[1], 0x6081) == [(0x6081, 0, 293)]


def test_a_velocity_unit_written_through_81_is_read_again() -> None:
    engine, nodes = epos4(2048)
    ok(engine, "1S05=10")
    ok(engine, "1S80=0x60A90004")
    ok(engine, "1S81=0xFDB44700")
    ok(engine, "1S05=10")
    assert downloads(nodes[1], 0x6081)[-1] == (0x6081, 0, 292969)


class RoundingNode(FakeNode):
    """A drive that keeps 6081h to a multiple of 10, whatever was written."""

    def download(self, index: int, subindex: int, data: bytes, force_segment: bool = False) -> None:
        super().download(index, subindex, data, force_segment)
        if index == 0x6081:
            self.values[(0x6081, 0)] -= self.values[(0x6081, 0)] % 10


def test_a_drive_that_rounds_a_parameter_is_not_reset_at_every_enable() -> None:
    engine, nodes = epos4(IPR, parameters={"velocity": 2.005})  # 2005 rpm, kept as 2000
    node = RoundingNode(1)
    engine.axes[1].port.node = node  # type: ignore[union-attr]
    ok(engine, "1S04=1")  # writes 2005, reads 2000 back: not taken as evidence again
    assert node.resets == 0
    for _ in range(3):
        ok(engine, "1S04=0")
        ok(engine, "1S04=1")
    assert node.resets == 0


def test_a_velocity_below_the_drives_resolution_is_refused_and_coarse_ones_warned(
        caplog: Any) -> None:
    engine, nodes = epos4(2048)
    assert ask(engine, "1S05=0.01").status is Status.CAN  # 0.29 rpm would be 0 rpm
    assert ask(engine, "1S06=0.001").status is Status.CAN
    assert downloads(nodes[1]) == []
    ok(engine, "1S05=0.05")  # 1.46 rpm, written as 1 rpm: 0.034 mm/s
    assert downloads(nodes[1], 0x6081) == [(0x6081, 0, 1)]
    assert "is written as 1 in the drive's unit" in caplog.text


def test_16_and_17_take_1_only() -> None:
    engine, nodes = make()
    for line in ("1S16=0", "1S16=2", "1S17=0"):
        assert ask(engine, line).status is Status.CAN
    assert nodes[1].resets == 0 and nodes[1].log == []


def test_the_start_up_probe_logs_units_and_a_resolution_mismatch(caplog: Any) -> None:
    engine, nodes = epos4(4096)  # the fake drive's 3000h/05h is 2000
    caplog.set_level("INFO")
    asyncio.run(engine.probe())
    assert "velocity unit 0x00B44700" in caplog.text
    assert "main sensor resolution (3000h/05h) is 2000" in caplog.text
    assert downloads(nodes[1]) == []  # read-only
    engine.close()
