"""What each command of spec section 4 does to one axis: the one command implementation.

:class:`AxisOps` turns a validated command into a *plan*: every value is parsed,
converted and range-checked first (pure, on the event loop; a failure raises
:class:`~tcp_bridge.errors.InvalidCommand`, answered CAN, and nothing reaches a
drive), and the result is a closure that performs the SDO transfers (in the
axis's bus worker thread). Parameters are stored only after the drive took
them, so a NAK means "nothing changed". Everything that changes the power
state or moves the axis (00, 04, 07, 16, 17) goes through
:mod:`tcp_bridge.motion`, which holds the safety rule; moves are planned in
:mod:`tcp_bridge.plan.moves`.

Rules not spelled out by the spec, chosen here:

* Parameter reads (02, 05, 06, 23, 24, 26-28, 40-43, 53, 62, 63) with an SDO
  object read the drive, so an absent node answers NAK; the value returned is
  the stored one (the controller's array, spec 3) when there is one, else the
  drive's value converted.
* 05 Velocity is signed: the sign is the direction of a velocity move (S00=3);
  0x6081 (UNSIGNED32) gets the magnitude.
* Velocities and accelerations convert by the drive's units
  (:mod:`tcp_bridge.tables.units`): rpm and rpm/s on an EPOS4 (device 5), whose
  velocity unit 60A9h is read from the drive the first time it is needed.
  A unit the bridge does not know is logged once, and that axis's velocity
  commands answer NAK. 14 Actual Velocity is in user units/s, like 05.
* 26 is "only internal for Technosoft and Copley" and 63 "only Nanotec": for
  other devices they are stored without SDO.
* 11 Detailed Error (spec 4.b): Technosoft devices map their motion error
  register 2000h; every other device composes it from the error code 603Fh
  (CiA 301 classes; maxon EPOS4 codes 8A80h-8A88h) and 60FDh limit inputs.
* 18 General Error is the CiA 301 error register 1001h (spec 4.c has its bits).
* 82 is statusword bit 10; in profile velocity mode, where bit 10 means
  "velocity reached", it is bit 10 and bit 12 ("speed is zero"), so a running
  velocity move reads 0. The mode is the drive's (6061h), read in the same
  job, and only when it matters (bit 10 set, bit 12 clear).
* 83 End switch hit is the limit switch inputs of 60FDh (CiA 402-2: bit 0
  negative, bit 1 positive limit switch), not statusword bit 11, which an
  EPOS4 also sets while it limits current or velocity.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, Final, List, Optional, Tuple, Union

from ..tables.axes import AxisConfig, DeviceCode, parameter_spec, to_stored
from ..tables.commands import CommandKind, CommandSpec, ObjectRef, Quantity, SdoSelector
from ..errors import DeviceFailure, InvalidCommand
from ..motion import MODES_DISPLAY, STATUSWORD, Cia402, Mode, State, Sw, Timing, Why
from ..tables.parameters import ParameterStore
from ..bus.sdo import NodeSilent, SdoPort, object_type
from ..tables.units import DriveUnits, Number, Scaling, velocity_exponent

log = logging.getLogger(__name__)

Value = Union[int, float, str]
ReadPlan = Callable[[], Value]
WritePlan = Callable[[], None]

VELOCITY_UNIT: Final = ObjectRef(0x60A9)  # EPOS4: SI unit velocity
_NOT_INTERNAL_26: Final = {DeviceCode.C_DC_TECHNOSOFT_CAN, DeviceCode.C_DC_TECHNOSOFT_EC,
                           DeviceCode.C_DC_COBLEY_CAN}
# Technosoft motion error register 2000h bit -> spec 4.b bit.
_TECHNOSOFT_MER: Final = {1: 1, 3: 3, 4: 4, 5: 5, 6: 6, 7: 7, 8: 10, 11: 11, 12: 12, 13: 13, 15: 15}
# Parameters written by 85 "write parameters" and after a power cycle, in this order.
DRIVE_PARAMETERS: Final = (26, 27, 5, 6, 28, 23, 24, 40, 41, 42, 43, 53, 62, 63)
# maxon EPOS4 error codes (603Fh) -> spec 4.b bit (EPOS4 Firmware Specification,
# error code table: 8A80h negative limit switch, 8A81h positive limit switch,
# 8A82h software position limit, 8A88h STO).
_MAXON_BITS: Final = {0x8A80: 7, 0x8A81: 6, 0x8A88: 15}
SOFTWARE_LIMIT_ERROR: Final = 0x8A82
LIMIT_INPUTS: Final = 0x3  # 60FDh bit 0 negative, bit 1 positive limit switch


# The drive objects of the parameters (spec 4): what a power cycle takes back to
# the saved values, unlike commands and targets (6040h, 607Ah, 60FFh, ...).
PARAMETER_OBJECTS: Final = frozenset(
    o for n in DRIVE_PARAMETERS for o in (parameter_spec(n).obj, parameter_spec(n).also_obj)
    if o is not None) | {VELOCITY_UNIT}


def detailed_error_from_code(code: int, inputs: int, software_limit_bit: int = 0) -> int:
    """Spec 4.b register from a CiA 301 / maxon error code (603Fh) and 60FDh inputs.

    ``software_limit_bit`` (8 positive, 9 negative) says which side a software
    position limit error (8A82h) is on; the code alone does not say.
    """
    bits = 0
    group, sub = code >> 12, (code >> 4) & 0xF
    if code in _MAXON_BITS:
        bits |= 1 << _MAXON_BITS[code]
    elif code == SOFTWARE_LIMIT_ERROR:
        bits |= 1 << software_limit_bit if software_limit_bit else 0
    elif code == 0x2320:
        bits |= 1 << 1  # short circuit
    elif group == 0x2:
        bits |= 1 << 10  # current
    elif group == 0x3:
        bits |= 1 << (13 if sub == 2 else 12)  # under / over voltage
    elif group == 0x4:
        bits |= 1 << 11  # temperature
    elif code >> 8 == 0x73:
        bits |= 1 << (2 if code in (0x7305, 0x7306) else 5)  # encoder / feedback
    elif code >> 8 in (0x75, 0x81, 0x82):
        bits |= 1 << 4  # communication
    elif code == 0x8611:
        bits |= 1 << 3  # following error
    if inputs & 0x1:  # CiA 402-2 60FDh bit 0: negative limit switch
        bits |= 1 << 7
    if inputs & 0x2:  # bit 1: positive limit switch
        bits |= 1 << 6
    return bits


def check_resolution(addr: int, spec: CommandSpec, user: Number, raw: int,
                     scaling: Scaling) -> None:
    """A velocity or acceleration the drive's unit cannot carry: CAN if it would become
    0, a warning if rounding changes it by more than 1% (rpm are coarse)."""
    if user and not raw:
        raise InvalidCommand(f"axis {addr}: {user} {spec.unit} is below the drive's "
                             "resolution (it would be written as 0)", cmd=spec.number)
    back = AxisOps.from_drive(spec, scaling, raw)
    if user and abs(back - float(user)) > 0.01 * abs(float(user)):
        log.warning("axis %d: %s = %s %s is written as %d in the drive's unit, which is %g %s",
                    addr, spec.name, user, spec.unit, raw, back, spec.unit)


class AxisOps:
    """The runtime of one axis: its drive (if any), its flags, and the command plans."""

    def __init__(self, config: AxisConfig, params: ParameterStore, port: Optional[SdoPort],
                 timing: Timing, **cia402_options: object) -> None:
        self.config = config
        self.addr = config.addr
        self.params = params
        self.port = port
        self.drive = Cia402(port, timing, **cia402_options) if port is not None else None  # type: ignore[arg-type]
        self.moving_ack = 0  # command 86: 1 once the drive accepted a move
        self.velocity_exponent: Optional[int] = None  # EPOS4 60A9h prefix, once read
        self._scaling_memo: Optional[Tuple[Tuple[Any, ...], Scaling]] = None
        self.unit_error: Optional[str] = None
        # Profile objects of a slave that followed its master's profile, with the
        # values to put back before it moves on its own (tcp_bridge.plan.moves).
        self.borrowed_profile: Dict[ObjectRef, int] = {}
        self._compare_parameters = True  # motion.Restore.ignore_differences
        # The last value the bridge wrote to each object of this drive (any command,
        # 81 included): what a drive that kept its RAM values still holds (rule 3).
        self.written: Dict[ObjectRef, int] = {}
        if port is not None and self.drive is not None:
            port.on_write = lambda i, sub, value: self.written.__setitem__(ObjectRef(i, sub), value)
            self.drive.listeners.append(self._on_drive_event)
            self.drive.coasting = self._coasting
        nmt = getattr(getattr(port, "node", None), "nmt", None)
        if self.drive is not None and hasattr(nmt, "add_heartbeat_callback"):
            drive = self.drive
            # CiA 301 7.2.8.3.2.4: a boot-up message is a heartbeat with state 0.
            nmt.add_heartbeat_callback(lambda state: drive.note_bootup() if state == 0 else None)

    def _on_drive_event(self, event: str) -> None:
        """motion.Cia402 listener: what a power cycle or reset makes stale."""
        self.velocity_exponent, self.unit_error = None, None  # 60A9h: read it again
        if event == "reset":  # the drive's RAM values are gone: nothing of ours is left
            self.written.clear()
            self.borrowed_profile.clear()

    def _coasting(self) -> bool:
        """Whether the axis still turns (606Ch above 1 rpm on an EPOS4, not 0 elsewhere)."""
        raw = self._port().read(0x606C, 0)
        if self.device is DeviceCode.C_DC_MAXON_EPOS4 and self.velocity_exponent is not None:
            return abs(raw) > 10 ** -self.velocity_exponent
        return raw != 0

    # -- helpers ---------------------------------------------------------------------

    @property
    def device(self) -> DeviceCode:
        return self.params.device(self.addr)

    def scaling(self) -> Scaling:
        """The axis's conversions now; for an EPOS4 with the velocity prefix last read."""
        # Built for every position poll: kept while 22, 25, 19 and the prefix stay.
        key = (*self.params.values(self.addr, (22, 25, 19)), self.velocity_exponent)
        memo = self._scaling_memo  # one tuple: the bus worker may replace it meanwhile
        if memo is not None and memo[0] == key:
            return memo[1]
        scaling = self._build_scaling()
        self._scaling_memo = (key, scaling)
        return scaling

    def _build_scaling(self) -> Scaling:
        base = self.params.scaling(self.addr)
        if self.device is not DeviceCode.C_DC_MAXON_EPOS4:
            return base
        ipr = self.config.increments_per_revolution
        if ipr is None:
            raise InvalidCommand(f"axis {self.addr}: device 5 needs increments_per_revolution "
                                 "in the axis table")
        units = DriveUnits(ipr, self.velocity_exponent or 0)
        return Scaling(base.factor, base.inversion, base.offset, units)

    def drive_scaling(self, quantity: Quantity = Quantity.VELOCITY) -> Scaling:
        """:meth:`scaling` on the bus worker: reads 60A9h first when a velocity needs it."""
        if self.device is DeviceCode.C_DC_MAXON_EPOS4 and quantity is Quantity.VELOCITY:
            self._read_velocity_unit()
        return self.scaling()

    def _read_velocity_unit(self) -> None:
        if self.velocity_exponent is not None:
            return
        if self.unit_error is None:
            raw = self._port().read(VELOCITY_UNIT.index, VELOCITY_UNIT.subindex)
            try:
                self.velocity_exponent = velocity_exponent(raw)
                log.info("axis %d: velocity unit 0x%08X (rpm x 10^%d)", self.addr, raw,
                         self.velocity_exponent)
                return
            except ValueError as exc:
                self.unit_error = f"axis {self.addr}: {exc}; velocity commands are refused"
                log.error("%s", self.unit_error)
        raise DeviceFailure(self.unit_error)

    def probe_units(self) -> None:
        """Read 60A9h (logged by :meth:`_read_velocity_unit`) and compare the main
        sensor resolution 3000h/05h with the axis table; read-only."""
        port = self._port()
        try:
            self._read_velocity_unit()
        except NodeSilent:
            raise
        except DeviceFailure:
            pass  # an unknown unit is logged; the axis's velocity commands answer NAK
        ipr = self.config.increments_per_revolution
        try:
            resolution = port.read(0x3000, 5)
        except NodeSilent:
            raise
        except DeviceFailure:
            return  # no such object: nothing to compare
        if ipr is not None and resolution != ipr:
            log.warning("axis %d: the drive's main sensor resolution (3000h/05h) is %d "
                        "increments per revolution, the axis table says %d "
                        "(increments_per_revolution): velocities would be wrong by %.3gx",
                        self.addr, resolution, ipr, resolution / ipr)

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

    # -- conversions by quantity ------------------------------------------------------

    @staticmethod
    def to_drive(spec: CommandSpec, scaling: Scaling, user: Number) -> int:
        if spec.quantity is Quantity.VELOCITY:
            return scaling.velocity_to_drive(user)
        if spec.quantity is Quantity.ACCELERATION:
            return scaling.acceleration_to_drive(user)
        return scaling.to_drive(user)

    @staticmethod
    def from_drive(spec: CommandSpec, scaling: Scaling, raw: int) -> float:
        if spec.quantity is Quantity.VELOCITY:
            return scaling.velocity_from_drive(raw)
        if spec.quantity is Quantity.ACCELERATION:
            return scaling.acceleration_from_drive(raw)
        return scaling.from_drive(raw)

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
        if n == 4:
            return lambda: int(self._drive().state() is State.OPERATION_ENABLED)
        if n == 7:
            return lambda: port.read(0x6060, 0)
        if n == 11:
            return self._read_detailed_error
        # Only the reads that convert a position build the axis's scaling: a status
        # poll (R10, R82...) does not pay for it (issue 14: many clients polling).
        if n == 12:
            scaling = self.scaling()
            index = 0x6062 if self.device is DeviceCode.C_DC_NANOTEC else 0x6064
            return lambda: scaling.position_from_drive(port.read_status(index, 0))
        if n == 13:
            scaling = self.scaling()
            return lambda: scaling.from_drive(port.read(0x6067, 0))
        if n == 14:
            return lambda: self.drive_scaling().velocity_from_drive(port.read_status(0x606C, 0))
        if n == 18:
            return lambda: port.read(0x1001, 0)
        if n in (33, 34):
            scaling = self.scaling()
            obj = spec.object_for(scaling.inversion)
            assert obj is not None
            return lambda: scaling.position_from_drive(port.read(obj.index, obj.subindex))
        if n == 81:
            selector = SdoSelector.from_value(self._stored(80) or 0)
            size, signed = object_type(selector.index, selector.subindex)
            signed = signed and size == selector.length
            return lambda: port.read(selector.index, selector.subindex,
                                     size=selector.length, signed=signed)
        if n == 83:
            return lambda: int(bool(port.read_status(0x60FD, 0) & LIMIT_INPUTS))
        if spec.kind is CommandKind.STATUS_BIT:
            assert spec.bit is not None
            bit = spec.bit

            def status_bit() -> int:
                sw = port.read_status(STATUSWORD, 0)
                if n == 82 and sw & Sw.TARGET_REACHED and not sw & Sw.OP_MODE_12:
                    # Reached in any mode but profile velocity, where bit 10 is
                    # "velocity reached" and bit 12 "speed is zero": still moving.
                    return int(port.read_status(MODES_DISPLAY, 0) != Mode.PROFILE_VELOCITY)
                return (sw >> bit) & 1
            return status_bit
        obj = spec.obj
        if obj is None:
            raise AssertionError(f"no read for command {n}")
        if n == 10:  # from a PDO when the bus has them (tcp_bridge.backends.pdo_status)
            return lambda: port.read_status(obj.index, obj.subindex)
        return lambda: port.read(obj.index, obj.subindex)  # raw: 09 15 50 52 61

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
        port = self._port()

        def read() -> Value:
            raw = port.read(obj.index, obj.subindex)
            if user is not None:
                return user  # the stored value (for 05 with its sign: the direction)
            if n == 2:
                return self.scaling().position_from_drive(raw)
            if not spec.scaled:
                return raw
            return self.from_drive(spec, self.drive_scaling(spec.quantity), raw)
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
        side = self._software_limit_side() if code == SOFTWARE_LIMIT_ERROR else 0
        return detailed_error_from_code(code, inputs, side)

    def _software_limit_side(self) -> int:
        """Spec 4.b bit 8 (positive) or 9 (negative) for an EPOS4 software limit error:
        the side whose limit (607Dh) the position (6064h) is nearer to."""
        port = self._port()
        position = port.read(0x6064, 0)
        low, high = port.read(0x607D, 1), port.read(0x607D, 2)
        return 9 if abs(position - low) < abs(position - high) else 8

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
            from .moves import plan_move

            return plan_move(self, int(value))
        port = self._port()
        drive = self._drive()
        if n == 4:  # motion rules 1 and 3 (tcp_bridge.motion)
            return (lambda: drive.enable(self)) if value == 1 else drive.disable
        if n == 7:  # motion rule 2: a mode change halts first
            mode = int(value)
            return lambda: drive.set_mode(mode)
        if n == 16:  # motion rule 1: the client asked for exactly this
            return lambda: drive.reset_node(Why.CLIENT_RESET_NODE)
        if n == 17:
            return drive.fault_reset
        if n == 85:
            return self.write
        if n == 81:
            selector = SdoSelector.from_value(self._stored(80) or 0)
            bits = 8 * selector.length
            if not -(1 << (bits - 1)) <= value < (1 << bits):
                raise InvalidCommand(f"{value} does not fit {selector.length} bytes", cmd=81)
            raw = int(value) & ((1 << bits) - 1)

            def write_raw() -> None:
                port.write(selector.index, selector.subindex, raw, size=selector.length,
                           signed=False)
                if selector.index == VELOCITY_UNIT.index:  # read the new unit when next needed
                    self.velocity_exponent, self.unit_error = None, None
            return write_raw
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
        if n == 19 and stored == DeviceCode.C_DC_MAXON_EPOS4 \
                and self.config.increments_per_revolution is None:
            raise InvalidCommand(f"axis {self.addr} has no increments_per_revolution in the "
                                 "axis table, which device 5 needs", cmd=19)
        if n == 80:
            SdoSelector.from_value(stored)  # length 1..4
        obj = self.parameter_object(spec)
        if obj is not None:
            self._drive_writes(n, value, self.scaling())  # range check, before any transfer
        port = self.port

        def write() -> None:
            if obj is not None:
                assert port is not None
                for o, raw in self._drive_writes(n, value, self.drive_scaling(spec.quantity)):
                    port.write(o.index, o.subindex, raw)
                    self.borrowed_profile.pop(o, None)  # the drive holds our own value now
            self.params.set(self.addr, n, stored)
        return write

    def _drive_writes(self, n: int, user: Number, scaling: Scaling) -> List[Tuple[ObjectRef, int]]:
        """(object, drive value) pairs for parameter ``n`` at user value ``user``."""
        spec = parameter_spec(n)
        obj = self.parameter_object(spec)
        if obj is None:
            return []
        if n == 2:
            raw = scaling.position_to_drive(user)
        elif n == 5:
            raw = scaling.velocity_to_drive(abs(user))
        elif spec.scaled:
            raw = self.to_drive(spec, scaling, user)
        else:
            raw = int(user)
        if spec.quantity is not Quantity.OTHER:
            check_resolution(self.addr, spec, abs(user) if n == 5 else user, raw, scaling)
        size, signed = object_type(obj.index, obj.subindex)
        if not signed and raw < 0:
            raise InvalidCommand(f"{user} must not be negative for 0x{obj.index:04X}", cmd=n)
        if raw >= 1 << (8 * size - (1 if signed else 0)):
            raise InvalidCommand(f"{user} is too large for 0x{obj.index:04X}", cmd=n)
        writes = [(obj, raw)]
        if n == 6 and spec.also_obj is not None:
            writes.append((spec.also_obj, raw))  # acceleration is deceleration too
        return writes

    # -- the parameters as kept by the bridge (motion.Restore) ------------------------

    def _stored_writes(self) -> List[Tuple[ObjectRef, int]]:
        """The stored drive parameters in drive units. With a velocity unit the bridge
        does not know, the velocities are left out (they answer NAK on their own)."""
        stored = {n: self.params.user(self.addr, n) for n in DRIVE_PARAMETERS}
        scaling = self.scaling()
        if any(v is not None and parameter_spec(n).quantity is Quantity.VELOCITY
               for n, v in stored.items()):
            try:
                scaling = self.drive_scaling()
            except NodeSilent:
                raise
            except DeviceFailure:  # unknown unit, already logged
                stored = {n: v for n, v in stored.items()
                          if parameter_spec(n).quantity is not Quantity.VELOCITY}
        writes: List[Tuple[ObjectRef, int]] = []
        for n, user in stored.items():
            if user is not None:
                writes.extend(self._drive_writes(n, user, scaling))
        return writes

    def write(self) -> None:
        """Command 85 and the power-cycle path of 04: every stored drive parameter."""
        port = self._port()
        port.read(STATUSWORD, 0)  # the drive is there, even with nothing to write
        for obj, raw in self._stored_writes():
            port.write(obj.index, obj.subindex, raw)
            self.borrowed_profile.pop(obj, None)

    def differs(self) -> Optional[str]:
        """Why the drive no longer holds the parameter values the bridge wrote to it
        in this session, None if it still does (motion rule 3). Only parameter
        objects count (not the controlword or targets); one the drive does not
        have (an abort) is skipped."""
        if not self._compare_parameters:
            return None
        port = self._port()
        for obj, raw in list(self.written.items()):
            if obj not in PARAMETER_OBJECTS:
                continue
            try:
                held = port.read(obj.index, obj.subindex)
            except NodeSilent:
                raise
            except DeviceFailure:
                continue
            if held != raw:
                return f"0x{obj.index:04X}/{obj.subindex} holds {held}, the bridge wrote {raw}"
        return None

    def ignore_differences(self) -> None:
        self._compare_parameters = False


__all__ = ["AxisOps", "DRIVE_PARAMETERS", "Value", "detailed_error_from_code"]
