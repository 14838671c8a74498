"""CiA 402 power state machine as data: states, controlword commands, transitions.

References: CiA 402-2 V4.0 (= IEC 61800-7-201) section 6.4 "Device control":
Figure "Finite state automaton", table "State transitions" (0..16),
6.4.1.3 controlword (6040h) command coding and 6.4.1.4 statusword (6041h).

The automaton, with the transition numbers used everywhere in this package::

           Start
             | 0
    NOT_READY_TO_SWITCH_ON
             | 1                         13 (fault, from any state)
    SWITCH_ON_DISABLED <------15------ FAULT <--14-- FAULT_REACTION_ACTIVE
        2 |  ^ 7 ^ 10 ^ 9 ^ 12
    READY_TO_SWITCH_ON
        3 |  ^ 6    ^ 8
    SWITCHED_ON     |
        4 |  ^ 5    |
    OPERATION_ENABLED --11--> QUICK_STOP_ACTIVE
            ^-----------16-----------'

Nothing here knows about time or motion; :mod:`epos_link.simulator.drive`
applies the steps and runs the automatic ones (0, 1, 12, 13, 14).
"""
from __future__ import annotations

from enum import Enum, IntEnum

__all__ = [
    "Command",
    "CW",
    "SW",
    "STATE_BITS",
    "State",
    "TRANSITIONS",
    "decode_command",
    "describe_statusword",
    "state_from_statusword",
    "state_text",
]


class State(IntEnum):
    """The eight states of CiA 402-2 6.4.1.1 (values are ours, in power-up order)."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class CW(IntEnum):
    """Controlword (6040h) bits, CiA 402-2 6.4.1.3 and the mode sections."""

    SWITCH_ON = 1 << 0
    ENABLE_VOLTAGE = 1 << 1
    QUICK_STOP = 1 << 2  # active low: 0 requests a quick stop
    ENABLE_OPERATION = 1 << 3
    NEW_SET_POINT = 1 << 4  # pp: new set-point; hm: homing operation start
    CHANGE_SET_IMMEDIATELY = 1 << 5  # pp
    ABS_REL = 1 << 6  # pp: 1 = relative target
    FAULT_RESET = 1 << 7  # rising edge
    HALT = 1 << 8


class SW(IntEnum):
    """Statusword (6041h) bits, CiA 402-2 6.4.1.4 and the mode sections."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5  # active low: 0 = quick stop active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT_ACTIVE = 1 << 11
    OP_MODE_12 = 1 << 12  # pp: set-point acknowledge; pv: speed = 0; hm: homing attained
    OP_MODE_13 = 1 << 13  # pp: following error; hm: homing error
    POSITION_REFERENCED = 1 << 15  # maxon: position referenced to home position


# State-coding bits 0..3, 5, 6 of the statusword (CiA 402-2 6.4.1.4, table
# "State coding"). The "x" of the standard are written as 0 here, except
# bit 5 (quick stop, active low) which is 1 where the table allows it.
STATE_BITS: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,  # xxxx xxxx x0xx 0000
    State.SWITCH_ON_DISABLED: 0x0040,  # xxxx xxxx x1xx 0000
    State.READY_TO_SWITCH_ON: 0x0021,  # xxxx xxxx x01x 0001
    State.SWITCHED_ON: 0x0023,  # xxxx xxxx x01x 0011
    State.OPERATION_ENABLED: 0x0027,  # xxxx xxxx x01x 0111
    State.QUICK_STOP_ACTIVE: 0x0007,  # xxxx xxxx x00x 0111
    State.FAULT_REACTION_ACTIVE: 0x000F,  # xxxx xxxx x0xx 1111
    State.FAULT: 0x0008,  # xxxx xxxx x0xx 1000
}

# (mask, value) pairs that identify a state from a statusword, same table.
_STATE_MASKS: tuple[tuple[int, int, State], ...] = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)


def state_from_statusword(statusword: int) -> State | None:
    """The state a statusword reports, or None if it matches no state coding."""
    for mask, value, state in _STATE_MASKS:
        if statusword & mask == value:
            return state
    return None


# Statusword bits worth naming next to the state when set (CiA 402-2 6.4.1.4;
# bit 15 is maxon's, EPOS4 Firmware Specification "Statusword"). The
# operation-mode-specific bits 12 and 13 are left out: their meaning depends
# on 6061h, which a single reading does not carry.
_FLAG_NAMES: tuple[tuple[SW, str], ...] = (
    (SW.VOLTAGE_ENABLED, "voltage enabled"),
    (SW.WARNING, "warning"),
    (SW.REMOTE, "remote"),
    (SW.TARGET_REACHED, "target reached"),
    (SW.INTERNAL_LIMIT_ACTIVE, "internal limit active"),
    (SW.POSITION_REFERENCED, "position referenced"),
)


def state_text(state: State | None) -> str:
    """A state as the tools print it: ``switch on disabled``; ``no CiA 402 state``."""
    return "no CiA 402 state" if state is None else state.name.replace("_", " ").lower()


def describe_statusword(statusword: int) -> str:
    """The state and the set flags of a statusword, for people:
    ``switch on disabled``, ``operation enabled, remote, target reached``."""
    parts = [state_text(state_from_statusword(statusword))]
    parts += [name for bit, name in _FLAG_NAMES if statusword & bit]
    return ", ".join(parts)


class Command(Enum):
    """Device control commands (CiA 402-2 6.4.1.3, table "Command coding").

    "Switch on" and "disable operation" share the coding 0xxx 0111, as do
    "enable operation" and "switch on + enable operation" (0xxx 1111): the
    current state decides which one is meant.
    """

    SHUTDOWN = "shutdown"  # 0xxx x110 -> 2, 6, 8
    SWITCH_ON = "switch on / disable operation"  # 0xxx 0111 -> 3, 5
    ENABLE_OPERATION = "enable operation / switch on + enable operation"  # 0xxx 1111 -> 3+4, 4, 16
    DISABLE_VOLTAGE = "disable voltage"  # 0xxx xx0x -> 7, 9, 10, 12
    QUICK_STOP = "quick stop"  # 0xxx x01x -> 7, 10, 11
    FAULT_RESET = "fault reset"  # bit 7 rising edge -> 15


def decode_command(controlword: int, previous: int) -> Command | None:
    """The command a controlword write carries, given the previous controlword.

    Bit 7 is "0" in every command except fault reset, so while bit 7 stays
    set the word carries no command; its rising edge is the fault reset and
    the low bits of that write are not evaluated.
    """
    if controlword & CW.FAULT_RESET:
        return None if previous & CW.FAULT_RESET else Command.FAULT_RESET
    low = controlword & 0x0F
    if not low & CW.ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not low & CW.QUICK_STOP:
        return Command.QUICK_STOP
    if not low & CW.SWITCH_ON:
        return Command.SHUTDOWN
    if low & CW.ENABLE_OPERATION:
        return Command.ENABLE_OPERATION
    return Command.SWITCH_ON


Step = tuple[int, State]

# The commanded transitions: (state, command) -> steps (transition number,
# next state). A pair not listed means the command is ignored in that state.
# Transition 16 is only allowed for quick stop option codes 5..8; the drive
# checks that, since it depends on 605Ah.
TRANSITIONS: dict[tuple[State, Command], tuple[Step, ...]] = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): ((2, State.READY_TO_SWITCH_ON),),
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): ((3, State.SWITCHED_ON),),
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): (
        (3, State.SWITCHED_ON), (4, State.OPERATION_ENABLED)),
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): ((7, State.SWITCH_ON_DISABLED),),
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): ((7, State.SWITCH_ON_DISABLED),),
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): ((4, State.OPERATION_ENABLED),),
    (State.SWITCHED_ON, Command.SHUTDOWN): ((6, State.READY_TO_SWITCH_ON),),
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): ((10, State.SWITCH_ON_DISABLED),),
    (State.SWITCHED_ON, Command.QUICK_STOP): ((10, State.SWITCH_ON_DISABLED),),
    (State.OPERATION_ENABLED, Command.SWITCH_ON): ((5, State.SWITCHED_ON),),
    (State.OPERATION_ENABLED, Command.SHUTDOWN): ((8, State.READY_TO_SWITCH_ON),),
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): ((9, State.SWITCH_ON_DISABLED),),
    (State.OPERATION_ENABLED, Command.QUICK_STOP): ((11, State.QUICK_STOP_ACTIVE),),
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): ((12, State.SWITCH_ON_DISABLED),),
    (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): ((16, State.OPERATION_ENABLED),),
    (State.FAULT, Command.FAULT_RESET): ((15, State.SWITCH_ON_DISABLED),),
}

# Automatic transitions, run by the drive model.
T_INITIALISED = (0, State.NOT_READY_TO_SWITCH_ON)
T_SELF_TEST_DONE = (1, State.SWITCH_ON_DISABLED)
T_QUICK_STOP_DONE = (12, State.SWITCH_ON_DISABLED)
T_FAULT = (13, State.FAULT_REACTION_ACTIVE)
T_FAULT_REACTION_DONE = (14, State.FAULT)

# States in which the power stage drives the motor (statusword bit 4 here).
POWERED_STATES = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})
