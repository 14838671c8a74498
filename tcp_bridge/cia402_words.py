"""The CiA 402 words the bridge writes and reads, and the time bounds of its waits.

Controlword commands and bits (CiA 402-2 V4.0 6.4.1.3), statusword bits
(6.4.1.4; PSI spec 4.a), modes of operation (6.3.1), and the
:class:`Deadline` that bounds a whole sequence. The sequences themselves and
the safety rule are :mod:`tcp_bridge.motion`.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Callable, Final, Optional

from epos_link.cia402 import State, state_from_statusword

from .errors import DeviceFailure

CONTROLWORD: Final = 0x6040
STATUSWORD: Final = 0x6041
MODES_OF_OPERATION: Final = 0x6060
MODES_DISPLAY: Final = 0x6061
TARGET_POSITION: Final = 0x607A
TARGET_VELOCITY: Final = 0x60FF


class Cw(IntEnum):
    """Controlword commands (CiA 402-2 6.4.1.3) and bits."""

    DISABLE_VOLTAGE = 0x00
    SHUTDOWN = 0x06
    SWITCH_ON = 0x07  # also "disable operation" from OPERATION ENABLED (transition 5)
    ENABLE_OPERATION = 0x0F
    NEW_SET_POINT = 1 << 4  # pp: new set-point; hm: homing operation start
    CHANGE_SET_IMMEDIATELY = 1 << 5
    RELATIVE = 1 << 6
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


class Sw(IntEnum):
    """Statusword bits (CiA 402-2 6.4.1.4; PSI spec 4.a)."""

    FAULT = 1 << 3
    TARGET_REACHED = 1 << 10  # with halt set, in pp, pv and hm: "velocity of axis is 0"
    INTERNAL_LIMIT = 1 << 11
    OP_MODE_12 = 1 << 12  # pp: set-point acknowledge; pv: speed is zero; hm: homing attained
    OP_MODE_13 = 1 << 13  # pp: following error; hm: homing error


class Mode(IntEnum):
    """Modes of operation, 6060h (spec command 07)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6


def decode_state(statusword: int) -> State:
    """The power state shown by a statusword; DeviceFailure if it shows none."""
    state = state_from_statusword(statusword)
    if state is None:
        raise DeviceFailure(f"statusword 0x{statusword:04X} shows no CiA 402 state")
    return state


class Deadline:
    """One bound shared by the waits of a sequence (pyserial's ``Timeout``, in small)."""

    def __init__(self, clock: Callable[[], float], timeout: float) -> None:
        self._clock = clock
        self._end = clock() + timeout

    def time_left(self, cap: Optional[float] = None) -> float:
        left = max(self._end - self._clock(), 0.0)
        return left if cap is None else min(left, cap)

    def expired(self) -> bool:
        return self._clock() >= self._end


@dataclass(frozen=True)
class Timing:
    ack_timeout: float = 2.0
    state_timeout: float = 1.0
    reset_timeout: float = 5.0
    reset_delay: float = 0.3
    poll_interval: float = 0.002


__all__ = ["CONTROLWORD", "Cw", "Deadline", "MODES_DISPLAY", "MODES_OF_OPERATION", "Mode",
           "STATUSWORD", "Sw", "TARGET_POSITION", "TARGET_VELOCITY", "Timing", "decode_state"]
