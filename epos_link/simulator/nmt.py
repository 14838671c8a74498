"""NMT slave states of a simulated EPOS4 (guide 3.3.3, Table 3-13), pure.

Reset node and reset communication are not state changes here: the owner
runs the reset and then enters Pre-Operational with a boot-up message.
"""
from __future__ import annotations

from enum import Enum

from ..codes import NmtCommand

__all__ = ["NmtState", "next_state"]


class NmtState(Enum):
    """The states of Table 3-13, with CiA 301's heartbeat values."""

    INITIALISING = 0x00  # after a reset, until the boot-up message
    PRE_OPERATIONAL = 0x7F
    OPERATIONAL = 0x05
    STOPPED = 0x04


_AFTER = {
    NmtCommand.START_REMOTE_NODE: NmtState.OPERATIONAL,
    NmtCommand.STOP_REMOTE_NODE: NmtState.STOPPED,
    NmtCommand.ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
}


def next_state(state: NmtState, command: int) -> NmtState:
    """The state after Start, Stop or Enter Pre-Operational; other commands keep it."""
    try:
        return _AFTER[NmtCommand(command)]
    except (ValueError, KeyError):
        return state
