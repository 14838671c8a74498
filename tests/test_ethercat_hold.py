"""tcp_bridge.backends.ethercat_hold: a stale "enable operation" in the output image
never takes a drive that left OPERATION ENABLED by itself back up (transition 16)."""
from __future__ import annotations

from typing import Dict

import pytest

from epos_link.cia402 import State
from tcp_bridge.backends.ethercat_hold import ControlwordHold, hold_command
from tcp_bridge.backends.ethercat_pdo import Entry, Layout

CW = Entry(0x6040, 0, 0, 2)
SW = Entry(0x6041, 0, 0, 2)
LAYOUT = Layout({(0x6040, 0): CW}, {(0x6041, 0): SW}, 2, 2)
# CiA 402-2 6.4.1.1 statusword patterns (bits 0-3, 5, 6), voltage enabled (bit 4)
STATUS = {State.SWITCH_ON_DISABLED: 0x0050, State.READY_TO_SWITCH_ON: 0x0031,
          State.SWITCHED_ON: 0x0033, State.OPERATION_ENABLED: 0x0037,
          State.QUICK_STOP_ACTIVE: 0x0017, State.FAULT: 0x0018}


class Cycle:
    def __init__(self) -> None:
        self.outputs: Dict[int, bytearray] = {1: bytearray(2)}
        self.inputs: Dict[int, bytes] = {1: bytes(2)}

    def write(self, cw: int) -> None:
        self.outputs[1][:] = cw.to_bytes(2, "little")

    def shows(self, state: State) -> None:
        self.inputs[1] = STATUS[state].to_bytes(2, "little")

    @property
    def cw(self) -> int:
        return int.from_bytes(self.outputs[1], "little")


@pytest.fixture
def enabled() -> "tuple[Cycle, ControlwordHold]":
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: LAYOUT})
    cycle.write(0x010F)  # the bridge's enable: enable operation, halted
    hold.commanded(1)
    cycle.shows(State.SWITCHED_ON)
    hold.check(0)
    assert cycle.cw == 0x010F  # on its way up: sent as written
    cycle.shows(State.OPERATION_ENABLED)
    hold.check(1)
    cycle.write(0x001F)  # a move's start write (enable operation, new set-point)
    hold.commanded(1)
    hold.check(2)
    return cycle, hold


@pytest.mark.parametrize(("state", "held"), [
    (State.QUICK_STOP_ACTIVE, 0x0102), (State.SWITCHED_ON, 0x0107),
    (State.READY_TO_SWITCH_ON, 0x0106), (State.SWITCH_ON_DISABLED, 0x0100),
    (State.FAULT, 0x0100)])
def test_a_drive_that_left_by_itself_is_held_where_it_is(
        enabled: "tuple[Cycle, ControlwordHold]", state: State, held: int) -> None:
    cycle, hold = enabled
    cycle.shows(state)
    hold.check(3)
    assert cycle.cw == held == hold_command(state)
    hold.check(4)  # and it stays so
    assert cycle.cw == held


def test_the_bridge_s_next_controlword_goes_out_as_written(
        enabled: "tuple[Cycle, ControlwordHold]") -> None:
    cycle, hold = enabled
    cycle.shows(State.QUICK_STOP_ACTIVE)
    hold.check(3)
    cycle.write(0x0100)  # a client's S04=1: disable voltage first, then up again
    hold.commanded(1)
    cycle.shows(State.SWITCH_ON_DISABLED)
    hold.check(4)
    cycle.write(0x010F)
    hold.commanded(1)
    cycle.shows(State.SWITCHED_ON)
    hold.check(5)
    assert cycle.cw == 0x010F


@pytest.mark.parametrize(("state", "held"), [
    (State.QUICK_STOP_ACTIVE, 0x0102), (State.SWITCHED_ON, 0x0107),
    (State.OPERATION_ENABLED, 0x010F), (State.FAULT, 0x0100)])
def test_at_start_up_the_image_keeps_each_drive_where_it_is(state: State, held: int) -> None:
    """Issue 31: a new bridge's image is not the dead one's "enable operation" (what an
    SDO read of 6040h gives back): from the first inputs on, it keeps the state shown."""
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: LAYOUT})
    cycle.write(0x000F)  # what the image might hold before the first inputs came
    cycle.shows(state)
    hold.check(0)
    assert cycle.cw == held and hold.holding(1)
    cycle.shows(State.FAULT)  # and it follows the drive down, never up
    hold.check(1)
    assert cycle.cw == 0x0100


def test_a_client_s_controlword_ends_the_following() -> None:
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: LAYOUT})
    cycle.shows(State.SWITCHED_ON)
    hold.check(0)
    cycle.write(0x000F)  # a client's S04=1
    hold.commanded(1)
    hold.check(1)
    assert cycle.cw == 0x000F and not hold.holding(1)


def test_set_point_mode_and_velocity_follow_the_drive_until_written() -> None:
    rx = {(0x6040, 0): Entry(0x6040, 0, 0, 2), (0x607A, 0): Entry(0x607A, 0, 2, 4),
          (0x60FF, 0): Entry(0x60FF, 0, 6, 4), (0x6060, 0): Entry(0x6060, 0, 10, 1)}
    tx = {(0x6041, 0): Entry(0x6041, 0, 0, 2), (0x6064, 0): Entry(0x6064, 0, 2, 4),
          (0x6061, 0): Entry(0x6061, 0, 6, 1)}
    cycle = Cycle()
    cycle.outputs[1] = bytearray((0x000F).to_bytes(2, "little") + (4500).to_bytes(4, "little")
                                 + (1000).to_bytes(4, "little") + b"\x09")
    cycle.inputs[1] = (0x0017).to_bytes(2, "little") + (-250).to_bytes(4, "little", signed=True) \
        + b"\x08"
    hold = ControlwordHold(cycle, {1: Layout(rx, tx, 11, 7)})
    hold.check(0)
    image = bytes(cycle.outputs[1])
    assert int.from_bytes(image[0:2], "little") == 0x0102  # QUICK STOP ACTIVE held
    assert int.from_bytes(image[2:6], "little", signed=True) == -250  # 607Ah = 6064h
    assert int.from_bytes(image[6:10], "little") == 0 and image[10] == 8  # 60FFh 0, 6060h = 6061h
    cycle.outputs[1][2:6] = (7).to_bytes(4, "little")  # the bridge writes 607Ah for a move
    hold.commanded(1, (0x607A, 0))
    hold.check(1)
    assert int.from_bytes(cycle.outputs[1][2:6], "little") == 7


def test_slaves_without_6040h_out_or_6041h_in_are_left_alone() -> None:
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: Layout({(0x6040, 0): CW}, {}, 2, 0), 2: None})
    assert hold.entries == {}
    hold.check(0)
