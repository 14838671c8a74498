"""What each command of spec section 4 does to one axis: the one command implementation.

:class:`AxisOps` turns a validated command into a *plan*: every value is parsed,
converted and range-checked first (pure, on the event loop; a failure raises
:class:`~tcp_bridge.errors.InvalidCommand`, answered CAN, and nothing reaches a
drive), and the result is a closure that performs the SDO transfers (in the
axis's bus worker thread). Parameters are stored only after the drive took
them, so a NAK means "nothing changed".

Rules not spelled out by the spec, chosen here:

* Parameter reads (02, 05, 06, 23, 24, 26-28, 40-43, 53, 62, 63) with an SDO
  object read the drive, so an absent node answers NAK; the value returned is
  the stored one (the controller's array, spec 3) when there is one, else the
  drive's value converted.
* 05 Velocity is signed: the sign is the direction of a velocity move (S00=3);
  0x6081 (UNSIGNED32) gets the magnitude.
* 26 is "only internal for Technosoft and Copley" and 63 "only Nanotec": for
  other devices they are stored without SDO.
* 11 Detailed Error (spec 4.b): Technosoft devices map their motion error
  register 2000h; every other device composes it from the error code 603Fh
  (CiA 301 Table 21 classes, maxon limit switch codes) and 60FDh limit inputs.
* 18 General Error is the CiA 301 error register 1001h (spec 4.c has its bits).
* 82 is statusword bit 10; in profile velocity mode, where bit 10 means
  "velocity reached", it is bit 10 and bit 12 ("speed is zero"), so a running
  velocity move reads 0. The mode is the drive's (6061h), read in the same
  job, and only when it matters (bit 10 set, bit 12 clear): a mode changed by
  raw SDO, another master or a reset is never mistaken.
"""
from __future__ import annotations

import logging
from typing import Callable, Final, List, Optional, Tuple, Union

from .axes import AxisConfig, DeviceCode, parameter_spec, to_stored
from .parameters import ParameterStore
from .commands import CommandKind, CommandSpec, ObjectRef, SdoSelector
from .errors import DeviceFailure, InvalidCommand
from .sdo import NodeSilent, SdoPort, object_type
from .sequences import MODES_DISPLAY, STATUSWORD, Cia402, Mode, Sw, State, Timing
from .units import Number, Scaling

log = logging.getLogger(__name__)

Value = Union[int, float, str]
ReadPlan = Callable[[], Value]
WritePlan = Callable[[], None]

_NOT_INTERNAL_26: Final = {DeviceCode.C_DC_TECHNOSOFT_CAN, DeviceCode.C_DC_TECHNOSOFT_EC,
                           DeviceCode.C_DC_COBLEY_CAN}
# Technosoft motion error register 2000h bit -> spec 4.b bit.
_TECHNOSOFT_MER: Final = {1: 1, 3: 3, 4: 4, 5: 5, 6: 6, 7: 7, 8: 10, 11: 11, 12: 12, 13: 13, 15: 15}
# Parameters written by 85 "write parameters" and after a power cycle, in this order.
_DRIVE_PARAMETERS: Final = (26, 27, 5, 6, 28, 23, 24, 40, 41, 42, 43, 53, 62, 63)


def detailed_error_from_code(code: int, inputs: int) -> int:
    """Spec 4.b register from a CiA 301 / maxon error code (603Fh) and 60FDh inputs."""
    bits = 0
    group, sub = code >> 12, (code >> 4) & 0xF
    if code == 0x2320:
        bits |= 1 << 1  # short circuit
    elif group == 0x2:
        bits |= 1 << 10  # current
    elif group == 0x3:
        bits |= 1 << (12 if sub == 1 else 13 if sub == 2 else 12)  # over/under voltage
    elif group == 0x4:
        bits |= 1 << 11  # temperature
    elif code >> 8 == 0x73:
        bits |= 1 << (2 if code in (0x7305, 0x7306) else 5)  # encoder / feedback
    elif code >> 8 in (0x75, 0x81, 0x82):
        bits |= 1 << 4  # communication
    elif code == 0x8611:
        bits |= 1 << 3  # following error
    elif code == 0x8A88:
        bits |= 1 << 7  # maxon: negative limit switch
    elif code == 0x8A89:
        bits |= 1 << 6  # maxon: positive limit switch
    if inputs & 0x1:  # CiA 402-2 60FDh bit 0: negative limit switch
        bits |= 1 << 7
    if inputs & 0x2:  # bit 1: positive limit switch
        bits |= 1 << 6
    return bits


class AxisOps:
    """The runtime of one axis: its drive (if any), its flags, and the command plans."""

    def __init__(self, config: AxisConfig, params: ParameterStore, port: Optional[SdoPort],
                 timing: Timing, **cia402_options: object) -> None:
        self.config = config
        self.addr = config.addr
        self.params = params
        self.port = port
        self.drive = Cia402(port, timing, **cia402_options) if port is not None else None  # type: ignore[arg-type]
        self.power_cycled = True  # spec 2.1: first enable after power-up resets and writes
        self.moving_ack = 0  # command 86

    # -- helpers ---------------------------------------------------------------------

    @property
    def device(self) -> DeviceCode:
        return self.params.device(self.addr)

    def scaling(self) -> Scaling:
        return self.params.scaling(self.addr)

    def _port(self) -> SdoPort:
        if self.port is None:
            raise InvalidCommand(f"axis {self.addr} has no drive (internal axis, node 0)")
        return self.port

    def _drive(self) -> Cia402:
        self._port()
        assert self.drive is not None
        return self.drive

    def parameter_object(self, spec: CommandSpec) -> Optional[ObjectRef]:
        """The SDO object behind a parameter on this device, None if internal only."""
        if spec.number == 26 and self.device in _NOT_INTERNAL_26:
            return None
        if spec.number == 63 and self.device is not DeviceCode.C_DC_NANOTEC:
            return None
        return spec.obj if self.port is not None else None

    def needs_bus(self, spec: CommandSpec) -> bool:
        """Whether the command touches the drive, so it runs on the bus worker."""
        if spec.kind is CommandKind.PARAMETER:
            return self.parameter_object(spec) is not None
        return spec.needs_sdo or spec.number == 16

    # -- reads -------------------------------------------------------------------------

    def plan_read(self, spec: CommandSpec) -> ReadPlan:
        n = spec.number
        if spec.kind is CommandKind.PARAMETER:
            return self._plan_read_parameter(spec)
        if n == 86:
            return lambda: self.moving_ack
        if n == 99 or n == 91:
            raise AssertionError("global commands are answered by the engine")
        port = self._port()
        scaling = self.scaling()
        if n == 4:
            return lambda: int(self._drive().state() is State.OPERATION_ENABLED)
        if n == 7:
            return lambda: port.read(0x6060, 0)
        if n == 11:
            return self._read_detailed_error
        if n == 12:
            index = 0x6062 if self.device is DeviceCode.C_DC_NANOTEC else 0x6064
            return lambda: scaling.position_from_drive(port.read(index, 0))
        if n == 13:
            return lambda: scaling.from_drive(port.read(0x6067, 0))
        if n == 18:
            return lambda: port.read(0x1001, 0)
        if n in (33, 34):
            obj = spec.object_for(scaling.inversion)
            assert obj is not None
            return lambda: scaling.position_from_drive(port.read(obj.index, obj.subindex))
        if n == 81:
            selector = SdoSelector.from_value(self._stored(80) or 0)
            size, signed = object_type(selector.index, selector.subindex)
            signed = signed and size == selector.length
            return lambda: port.read(selector.index, selector.subindex,
                                     size=selector.length, signed=signed)
        if spec.kind is CommandKind.STATUS_BIT:
            assert spec.bit is not None
            bit = spec.bit

            def status_bit() -> int:
                sw = port.read(STATUSWORD, 0)
                if n == 82 and sw & Sw.TARGET_REACHED and not sw & Sw.OP_MODE_12:
                    # Reached in any mode but profile velocity, where bit 10 is
                    # "velocity reached" and bit 12 "speed is zero": still moving.
                    return int(port.read(MODES_DISPLAY, 0) != Mode.PROFILE_VELOCITY)
                return (sw >> bit) & 1
            return status_bit
        obj = spec.obj
        if obj is None:
            raise AssertionError(f"no read for command {n}")
        return lambda: port.read(obj.index, obj.subindex)  # raw: 09 10 14 15 50 52 61

    def _stored(self, cmd: int) -> Optional[int]:
        return self.params.get(self.addr, cmd)

    def _plan_read_parameter(self, spec: CommandSpec) -> ReadPlan:
        n = spec.number
        stored = self._stored(n)
        user = self.params.user(self.addr, n)
        obj = self.parameter_object(spec)
        if n == 80:
            return lambda: f"0x{stored or 0:08X}"
        if obj is None:
            value: Value = 0 if user is None else user  # the controller's arrays start at 0
            return lambda: value
        port, scaling = self._port(), self.scaling()

        def read() -> Value:
            raw = port.read(obj.index, obj.subindex)
            if n == 5 and user is not None and scaling.to_drive(abs(user)) == raw:
                return user  # the sign is ours (direction of a velocity move)
            if user is not None:
                return user
            if n == 2:
                return scaling.position_from_drive(raw)
            return scaling.from_drive(raw) if spec.scaled else raw
        return read

    def _read_detailed_error(self) -> int:
        port = self._port()
        if self.device in (DeviceCode.C_DC_TECHNOSOFT_CAN, DeviceCode.C_DC_TECHNOSOFT_EC):
            mer = port.read(0x2000, 0)
            return sum(1 << out for bit, out in _TECHNOSOFT_MER.items() if mer >> bit & 1)
        code = port.read(0x603F, 0)
        try:
            inputs = port.read(0x60FD, 0)
        except NodeSilent:
            raise
        except DeviceFailure:
            inputs = 0  # no digital inputs object (an abort): only the error code counts
        return detailed_error_from_code(code, inputs)

    # -- writes ------------------------------------------------------------------------

    def plan_write(self, spec: CommandSpec, value: Number) -> WritePlan:
        n = spec.number
        if spec.kind is CommandKind.PARAMETER:
            return self._plan_write_parameter(spec, value)
        if n == 86:
            def set_ack() -> None:
                self.moving_ack = int(value)
            return set_ack
        if n == 0:
            return self.plan_move(int(value), self.scaling())
        port = self._port()
        drive = self._drive()
        if n == 4:
            return self._enable if value == 1 else drive.disable
        if n == 7:
            mode = int(value)

            return lambda: drive.set_mode(mode)
        if n == 16:
            def reset_node() -> None:
                port.nmt_reset()
                self.power_cycled = True
            return reset_node
        if n == 17:
            return drive.fault_reset
        if n == 85:
            return self._plan_write_parameters()
        if n == 81:
            selector = SdoSelector.from_value(self._stored(80) or 0)
            bits = 8 * selector.length
            if not -(1 << (bits - 1)) <= value < (1 << bits):
                raise InvalidCommand(f"{value} does not fit {selector.length} bytes", cmd=81)
            raw = int(value) & ((1 << bits) - 1)
            return lambda: port.write(selector.index, selector.subindex, raw,
                                      size=selector.length, signed=False)
        obj = spec.obj
        if spec.kind is not CommandKind.SDO or obj is None:
            raise AssertionError(f"no write for command {n}")
        size, signed = object_type(obj.index, obj.subindex)
        low = -(1 << (8 * size - 1)) if signed else 0
        high = (1 << (8 * size - (1 if signed else 0))) - 1
        if not low <= value <= high:
            raise InvalidCommand(f"{value} is outside {low}..{high}", cmd=n)
        return lambda: port.write(obj.index, obj.subindex, int(value))  # 09 52

    def _plan_write_parameter(self, spec: CommandSpec, value: Number) -> WritePlan:
        n = spec.number
        factor = self.config.position_factor
        stored = to_stored(parameter_spec(n), value, factor)  # range-checks scaled values
        if n == 29 and stored and (stored == self.addr or stored not in self.params.table.axes):
            raise InvalidCommand(f"slave axis {stored} is not another configured axis", cmd=29)
        if n == 80:
            SdoSelector.from_value(stored)  # length 1..4
        obj = self.parameter_object(spec)
        writes = self._drive_writes(n, value) if obj is not None else []
        port = self.port

        def write() -> None:
            for o, raw in writes:
                assert port is not None
                port.write(o.index, o.subindex, raw)
            self.params.set(self.addr, n, stored)
        return write

    def _drive_writes(self, n: int, user: Number) -> List[Tuple[ObjectRef, int]]:
        """(object, drive value) pairs for parameter ``n`` at user value ``user``."""
        spec = parameter_spec(n)
        obj = self.parameter_object(spec)
        if obj is None:
            return []
        scaling = self.scaling()
        if n == 2:
            raw = scaling.position_to_drive(user)
        elif n == 5:
            raw = scaling.to_drive(abs(user))
        elif spec.scaled:
            raw = scaling.to_drive(user)
        else:
            raw = int(user)
        size, signed = object_type(obj.index, obj.subindex)
        if not signed and raw < 0:
            raise InvalidCommand(f"{user} must not be negative for 0x{obj.index:04X}", cmd=n)
        if raw >= 1 << (8 * size - (1 if signed else 0)):
            raise InvalidCommand(f"{user} is too large for 0x{obj.index:04X}", cmd=n)
        writes = [(obj, raw)]
        if n == 6 and spec.also_obj is not None:
            writes.append((spec.also_obj, raw))  # acceleration is deceleration too
        return writes

    def _plan_write_parameters(self) -> WritePlan:
        """Command 85 and the power-cycle path of 04: every stored drive parameter."""
        writes = []
        for n in _DRIVE_PARAMETERS:
            user = self.params.user(self.addr, n)
            if user is not None:
                writes.extend(self._drive_writes(n, user))
        port = self._port()

        def write_all() -> None:
            port.read(STATUSWORD, 0)  # the drive is there, even with nothing to write
            for obj, raw in writes:
                port.write(obj.index, obj.subindex, raw)
        return write_all

    def _enable(self) -> None:
        """04 = 1: after a power cycle NMT reset and write the parameters first (spec 2.1)."""
        drive, port = self._drive(), self._port()
        if self.power_cycled:
            drive.statusword()  # an absent node answers NAK now, not after reset_timeout
            port.nmt_reset()
            drive.wait_for_node()
            self._plan_write_parameters()()
            self.power_cycled = False
        drive.enable()

    # -- moves (00) ----------------------------------------------------------------------

    def plan_move(self, how: int, scaling: Scaling, direction: int = 1,
                  target: Optional[Number] = None) -> WritePlan:
        """00 Move: 1 absolute, 2 relative, 3 velocity, 8 stop, 9 home.

        ``direction`` (-1 or 1) and ``target`` (user units) are given for a
        slave axis, which follows its master's value with its own direction.
        """
        drive = self._drive()
        if how in (1, 2):
            user = self.params.user(self.addr, 2) if target is None else target
            if user is None:
                raise InvalidCommand(f"axis {self.addr}: no target position (S02) set", cmd=0)
            user = user * direction
            if how == 1:
                raw = scaling.position_to_drive(user)
            else:  # a distance: inverted and scaled, never offset
                raw = scaling.to_drive(user) * scaling.inversion

            def start() -> None:
                drive.move_position(raw, relative=how == 2)
        elif how == 3:
            velocity = self.params.user(self.addr, 5) if target is None else target
            if velocity is None:
                raise InvalidCommand(f"axis {self.addr}: no velocity (S05) set", cmd=0)
            raw = scaling.to_drive(velocity * direction) * scaling.inversion

            def start() -> None:
                drive.move_velocity(raw)
        elif how == 9:
            def start() -> None:
                drive.home()
        else:  # 8: stop
            return drive.halt

        def move() -> None:
            self.moving_ack = 0  # spec: 86 is 0 before the move ...
            start()
            self.moving_ack = 1  # ... and 1 once the drive accepted it
        return move


def note_failure(ops: AxisOps, exc: BaseException) -> None:
    """A node that stopped answering may have been power cycled: re-init on next enable."""
    if isinstance(exc, NodeSilent):
        ops.power_cycled = True


__all__ = ["AxisOps", "Value", "detailed_error_from_code", "note_failure"]

