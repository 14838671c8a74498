"""CiA 402 sequences driven by SDO alone: enable, disable, fault reset, moves, homing.

Synchronous code for a bus worker thread. Every wait polls the statusword
(6041h) and is bounded; running out of time raises
:class:`~tcp_bridge.errors.DeviceFailure`, answered NAK. References: CiA 402-2
V4.0 section 6.4 (device control: 6.4.1.3 controlword, 6.4.1.4 statusword
and the state table), 6.6 homing, 6.7 profile position, 6.9 profile velocity.

Choices a client may notice:

* Enable walks the state machine one documented step at a time: Shutdown
  (06h) to READY TO SWITCH ON, Switch on (07h) to SWITCHED ON, Enable
  operation (0Fh) to OPERATION ENABLED, checking the statusword after each.
  QUICK STOP ACTIVE is left with Disable voltage (00h) first. A drive in
  FAULT is not enabled: that needs S17 first (NAK).
* Disable is Shutdown (06h): the power stage is off, the drive stays in
  READY TO SWITCH ON. A drive that is already off is left alone.
* Moves use the profile position set-point handshake of 6.7.1 with "change
  set immediately" (cw bit 5): a new S00=1 while moving goes to the new target
  at once. Bit 4 rises, the drive acknowledges with sw bit 12, bit 4 falls.
* Stop is **halt** (cw bit 8), not quick stop: the drive decelerates with its
  profile deceleration and stays in OPERATION ENABLED, so the next move needs
  no re-enable. The halt bit is released by the next move only after its new
  set-point is acknowledged, so an old target is never resumed.
* Fault reset is a rising edge of cw bit 7 (transition 15) followed by cw 00h;
  a drive that shows no fault is left alone (a reset must never disable a
  running axis).
* Enable, moves and homing each have **one** bound, ``ack_timeout``, for all
  their waits together (a :class:`Deadline`), so the ACK or NAK of 04 and 00
  comes within it; ``state_timeout`` caps each single state or mode change
  inside it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from enum import IntEnum
from typing import Callable, Final, Optional

from epos_link.cia402 import State, state_from_statusword

from .errors import DeviceFailure
from .sdo import SdoPort

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
    SWITCH_ON = 0x07
    ENABLE_OPERATION = 0x0F
    NEW_SET_POINT = 1 << 4  # pp: new set-point; hm: homing operation start
    CHANGE_SET_IMMEDIATELY = 1 << 5
    RELATIVE = 1 << 6
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


class Sw(IntEnum):
    """Statusword bits (CiA 402-2 6.4.1.4; spec 4.a)."""

    FAULT = 1 << 3
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT = 1 << 11
    OP_MODE_12 = 1 << 12  # pp: set-point acknowledge; pv: speed is zero; hm: homing attained
    OP_MODE_13 = 1 << 13  # pp: following error; hm: homing error


def decode_state(statusword: int) -> State:
    """The power state shown by a statusword; DeviceFailure if it shows none."""
    state = state_from_statusword(statusword)
    if state is None:
        raise DeviceFailure(f"statusword 0x{statusword:04X} shows no CiA 402 state")
    return state


class Mode(IntEnum):
    """Modes of operation, 6060h (spec command 07)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6


class Deadline:
    """One bound shared by the waits of a sequence (pyserial's ``Timeout``, in small)."""

    def __init__(self, clock: Callable[[], float], timeout: float) -> None:
        self._clock = clock
        self._end = clock() + timeout

    def time_left(self, cap: Optional[float] = None) -> float:
        left = max(self._end - self._clock(), 0.0)
        return left if cap is None else min(left, cap)


@dataclass(frozen=True)
class Timing:
    ack_timeout: float = 2.0
    state_timeout: float = 1.0
    reset_timeout: float = 5.0
    reset_delay: float = 0.3
    poll_interval: float = 0.002


class Cia402:
    """The sequences of one drive, through its :class:`~tcp_bridge.sdo.SdoPort`."""

    def __init__(self, port: SdoPort, timing: Timing = Timing(), *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.port = port
        self.timing = timing
        self._clock = clock
        self._sleep = sleep

    # -- observation -------------------------------------------------------------

    def statusword(self) -> int:
        return self.port.read(STATUSWORD, 0)

    def state(self) -> State:
        return decode_state(self.statusword())

    def wait_status(self, done: Callable[[int], bool], timeout: float, what: str) -> int:
        """Poll 6041h until ``done(statusword)``; DeviceFailure after ``timeout`` seconds."""
        deadline = self._clock() + timeout
        while True:
            sw = self.statusword()
            if done(sw):
                return sw
            if self._clock() >= deadline:
                raise DeviceFailure(f"{self.port.name}: {what} not seen within {timeout:g} s "
                                    f"(statusword 0x{sw:04X})")
            self._sleep(self.timing.poll_interval)

    def require_enabled(self) -> int:
        sw = self.statusword()
        state = decode_state(sw)
        if state is not State.OPERATION_ENABLED:
            raise DeviceFailure(f"{self.port.name}: not enabled ({state.name})")
        return sw

    # -- power -------------------------------------------------------------------

    def enable(self) -> None:
        """To OPERATION ENABLED, one checked step at a time, within ``ack_timeout``."""
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        steps = {
            State.SWITCH_ON_DISABLED: (Cw.SHUTDOWN, State.READY_TO_SWITCH_ON),
            State.READY_TO_SWITCH_ON: (Cw.SWITCH_ON, State.SWITCHED_ON),
            State.SWITCHED_ON: (Cw.ENABLE_OPERATION, State.OPERATION_ENABLED),
            State.QUICK_STOP_ACTIVE: (Cw.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        }
        state = self.state()
        for _ in range(8):  # at most 4 steps are ever needed; the rest is slack
            if state is State.OPERATION_ENABLED:
                return
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise DeviceFailure(f"{self.port.name}: in {state.name}; reset it (S17) first")
            step_timeout = deadline.time_left(self.timing.state_timeout)
            if state is State.NOT_READY_TO_SWITCH_ON:  # self test: wait, it moves by itself
                state = decode_state(self.wait_status(
                    lambda sw: decode_state(sw) is not State.NOT_READY_TO_SWITCH_ON,
                    step_timeout, "end of self test"))
                continue
            command, target = steps[state]
            self.port.write(CONTROLWORD, 0, command)
            state = decode_state(self.wait_status(
                lambda sw, t=target: decode_state(sw) is t, step_timeout, target.name))
        raise DeviceFailure(f"{self.port.name}: enable did not reach OPERATION_ENABLED")

    def disable(self) -> None:
        """Shutdown (06h) to READY TO SWITCH ON; an axis already off stays as it is."""
        state = self.state()
        if state in (State.OPERATION_ENABLED, State.SWITCHED_ON):
            command = Cw.SHUTDOWN
        elif state is State.QUICK_STOP_ACTIVE:
            command = Cw.DISABLE_VOLTAGE
        else:
            return  # not ready, switch on disabled, ready, fault: the power stage is off
        self.port.write(CONTROLWORD, 0, command)
        off = (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED)
        self.wait_status(lambda sw: decode_state(sw) in off, self.timing.ack_timeout,
                         "power stage off")

    def fault_reset(self) -> None:
        """Rising edge of cw bit 7 (transition 15), then cw 00h; no-op without a fault."""
        sw = self.statusword()
        if decode_state(sw) is State.FAULT_REACTION_ACTIVE:
            sw = self.wait_status(lambda s: decode_state(s) is State.FAULT,
                                  self.timing.state_timeout, "FAULT after fault reaction")
        if not sw & Sw.FAULT:
            return
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)  # bit 7 low: the edge is ours
        self.port.write(CONTROLWORD, 0, Cw.FAULT_RESET)
        self.wait_status(lambda s: not s & Sw.FAULT, self.timing.state_timeout,
                         "fault cleared")
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)

    def wait_for_node(self) -> None:
        """After an NMT reset: wait ``reset_delay``, then poll until the node shows the
        state a drive boots into (SWITCH ON DISABLED, or FAULT if it boots faulty).

        Powered states would be the node before the reset took effect, and a
        silent node is still booting; both are waited out within ``reset_timeout``.
        """
        self._sleep(self.timing.reset_delay)
        deadline = self._clock() + self.timing.reset_timeout
        booted = (State.SWITCH_ON_DISABLED, State.FAULT)
        while True:
            try:
                state = self.state()
                if state in booted:
                    return
                why = f"still {state.name}"
            except DeviceFailure as exc:
                why = str(exc)
            if self._clock() >= deadline:
                raise DeviceFailure(f"{self.port.name}: not back {self.timing.reset_timeout:g} s "
                                    f"after NMT reset ({why})")
            self._sleep(max(self.timing.poll_interval, 0.01))

    # -- modes and motion --------------------------------------------------------

    def set_mode(self, mode: int, timeout: Optional[float] = None) -> None:
        """Write 6060h and wait until 6061h shows it (CiA 402-2 6.3).

        Within ``timeout`` seconds, by default ``state_timeout``.
        """
        if self.port.read(MODES_DISPLAY, 0) == mode:
            return
        self.port.write(MODES_OF_OPERATION, 0, mode)
        timeout = self.timing.state_timeout if timeout is None else timeout
        deadline = Deadline(self._clock, timeout)
        while self.port.read(MODES_DISPLAY, 0) != mode:
            if deadline.time_left() <= 0:
                raise DeviceFailure(f"{self.port.name}: mode {mode} not displayed in 6061h "
                                    f"within {timeout:g} s")
            self._sleep(self.timing.poll_interval)

    def _move_deadline(self) -> Deadline:
        return Deadline(self._clock, self.timing.ack_timeout)

    def move_position(self, target: int, relative: bool) -> None:
        """Profile position set-point (CiA 402-2 6.7.1): returns once acknowledged."""
        deadline = self._move_deadline()
        self.require_enabled()
        self.set_mode(Mode.PROFILE_POSITION, deadline.time_left(self.timing.state_timeout))
        halt = self.port.read(CONTROLWORD, 0) & Cw.HALT
        self.port.write(TARGET_POSITION, 0, target)
        base = Cw.ENABLE_OPERATION | Cw.CHANGE_SET_IMMEDIATELY | (Cw.RELATIVE if relative else 0)
        self.port.write(CONTROLWORD, 0, base | halt)  # bit 4 low, so the next write is an edge
        self.wait_status(lambda sw: not sw & Sw.OP_MODE_12, deadline.time_left(),
                         "set-point acknowledge low")
        self.port.write(CONTROLWORD, 0, base | halt | Cw.NEW_SET_POINT)
        self.wait_status(lambda sw: bool(sw & Sw.OP_MODE_12), deadline.time_left(),
                         "set-point acknowledge")
        self.port.write(CONTROLWORD, 0, base)  # bit 4 and halt released

    def move_velocity(self, velocity: int) -> None:
        """Profile velocity (CiA 402-2 6.9): target velocity, mode 3, halt released."""
        deadline = self._move_deadline()
        self.require_enabled()
        self.port.write(TARGET_VELOCITY, 0, velocity)
        self.set_mode(Mode.PROFILE_VELOCITY, deadline.time_left(self.timing.state_timeout))
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION)
        self.require_enabled()

    def halt(self) -> None:
        """Halt (cw bit 8) in any mode; an axis that is not enabled is not moving."""
        if self.state() is not State.OPERATION_ENABLED:
            return
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.HALT)

    def home(self) -> None:
        """Homing (CiA 402-2 6.6): mode 6, rising edge of bit 4, wait until it runs."""
        deadline = self._move_deadline()
        self.require_enabled()
        self.set_mode(Mode.HOMING, deadline.time_left(self.timing.state_timeout))
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION)
        self.port.write(CONTROLWORD, 0, Cw.ENABLE_OPERATION | Cw.NEW_SET_POINT)
        # In progress: bit 10 low; attained: bit 12; error: bit 13.
        sw = self.wait_status(
            lambda s: bool(s & Sw.OP_MODE_13) or bool(s & Sw.OP_MODE_12)
            or not s & Sw.TARGET_REACHED, deadline.time_left(), "homing started")
        if sw & Sw.OP_MODE_13:
            raise DeviceFailure(f"{self.port.name}: homing error (statusword 0x{sw:04X})")
