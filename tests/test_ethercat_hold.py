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


def test_nothing_is_changed_before_the_drive_was_enabled_under_it() -> None:
    """At start-up the image holds the drive's own controlword (seeded); a drive not
    yet in OPERATION ENABLED is left to the bridge's enable sequence."""
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: LAYOUT})
    cycle.write(0x000F)
    cycle.shows(State.SWITCHED_ON)
    hold.check(0)
    assert cycle.cw == 0x000F


def test_slaves_without_6040h_out_or_6041h_in_are_left_alone() -> None:
    cycle = Cycle()
    hold = ControlwordHold(cycle, {1: Layout({(0x6040, 0): CW}, {}, 2, 0), 2: None})
    assert hold.entries == {}
    hold.check(0)
