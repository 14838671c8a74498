"""The S handlers for parameters, objects and sequences, by rule (:data:`WRITES`).

Every value is parsed, converted and range-checked when the request is
resolved (CAN, and nothing reaches a drive); the closure returned does the
transfers on the bus thread. A parameter is stored only after the drive took
it, so a NAK means "nothing changed"; meanwhile later requests are resolved
against its value (:meth:`~tcp_bridge.plan.axis.AxisRuntime.promise`), and
fail with it if it fails (:class:`~tcp_bridge.plan.job.Ticket`). Everything
that changes the power state or moves the axis (04, 07, 16, 17) goes through
:mod:`tcp_bridge.motion`, which holds the safety rule; moves are in
:mod:`.moves`.

Rules chosen here: 05 Velocity is signed (the sign is the direction of a
velocity move, S00=3; 6081h gets the magnitude). 02 is written to 607Ah only
when the drive is in a mode where 607Ah waits for a start (a cyclic mode
follows it at once: S02 alone must never move an axis). 81 Perform SDO Access
writes with the object's own sign, and never writes the objects that power or
move a drive while it is enabled (:data:`MOTION_OBJECTS`; the controlword
never: S04, S00 and S17 are its commands). 19 Device Code must agree with the
drive's identity (1018h/1) when the bridge has read it.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, FrozenSet, Final, List, Mapping, Optional, Tuple

from ..bus.sdo import NodeSilent, object_type
from ..cia402_words import MODES_DISPLAY, Mode
from ..errors import DeviceFailure, InvalidCommand
from ..motion import State, Why
from ..motion.cyclic import CSP_MODE, CSV_MODE
from ..motion.supervision import HEARTBEAT_OBJECTS, WATCHDOG_OBJECTS
from ..tables.axes import DeviceCode, parameter_spec, to_stored
from ..tables.commands import CommandSpec, ObjectRef, Quantity, SdoSelector
from ..tables.units import Number, Scaling
from .axis import VELOCITY_UNIT, AxisRuntime
from .cyclic_moves import stop_cyclic, wait_stopped
from .tickets import Ticket
from .resolve import Resolved

log = logging.getLogger("tcp_bridge.plan")

WritePlan = Callable[[], None]

# Parameters written by 85 "write parameters" and after a power cycle, in this order.
DRIVE_PARAMETERS: Final = (26, 27, 5, 6, 28, 23, 24, 40, 41, 42, 43, 53, 62, 63)
# The drive objects of the parameters (spec 4): what a power cycle takes back to
# the saved values, unlike commands and targets (6040h, 607Ah, 60FFh, ...).
PARAMETER_OBJECTS: Final = frozenset(
    o for n in DRIVE_PARAMETERS for o in (parameter_spec(n).obj, parameter_spec(n).also_obj)
    if o is not None) | {VELOCITY_UNIT}
CONTROLWORD_INDEX: Final = 0x6040
# Objects whose write powers or moves a drive (CiA 402-2: 6040h controlword, 6060h
# modes of operation, 607Ah target position, 60FFh target velocity, 6071h target
# torque, 6042h vl target velocity, 60C1h interpolation data, 60B0h-60B2h the
# cyclic modes' offsets): S81 leaves them alone while the axis is enabled.
MOTION_OBJECTS: Final = frozenset({0x6040, 0x6042, 0x6060, 0x6071, 0x607A, 0x60B0, 0x60B1,
                                   0x60B2, 0x60C1, 0x60FF})
# Modes in which 607Ah is the live set-point (CiA 402-2: 7 interpolated position,
# 8 cyclic synchronous position): S02 does not write it there.
_LIVE_TARGET_MODES: Final = frozenset({7, 8})
MAXON_DEVICE: Final = DeviceCode.C_DC_MAXON_EPOS4


def check_resolution(addr: int, spec: CommandSpec, user: Number, raw: int,
                     scaling: Scaling) -> None:
    """A velocity or acceleration the drive's unit cannot carry: CAN if it would become
    0, a warning if rounding changes it by more than 1% (rpm are coarse)."""
    if user and not raw:
        raise InvalidCommand(f"axis {addr}: {user} {spec.unit} is below the drive's "
                             "resolution (it would be written as 0)", cmd=spec.number)
    back = scaling.quantity_from_drive(spec.quantity, raw)
    if user and abs(back - float(user)) > 0.01 * abs(float(user)):
        log.warning("axis %d: %s = %s %s is written as %d in the drive's unit, which is %g %s",
                    addr, spec.name, user, spec.unit, raw, back, spec.unit)


def drive_writes(axis: AxisRuntime, n: int, user: Number,
                 scaling: Scaling) -> List[Tuple[ObjectRef, int]]:
    """(object, drive value) pairs for parameter ``n`` at user value ``user``."""
    spec = parameter_spec(n)
    obj = axis.parameter_object(n)
    if obj is None:
        return []
    if n == 2:
        raw = scaling.position_to_drive(user)
    elif n == 5:
        raw = scaling.velocity_to_drive(abs(user))
    elif spec.scaled:
        raw = scaling.quantity_to_drive(spec.quantity, user)
    else:
        raw = int(user)
    if spec.quantity is not Quantity.OTHER:
        check_resolution(axis.addr, spec, abs(user) if n == 5 else user, raw, scaling)
    size, signed = object_type(obj.index, obj.subindex)
    if not signed and raw < 0:
        raise InvalidCommand(f"{user} must not be negative for 0x{obj.index:04X}", cmd=n)
    if raw >= 1 << (8 * size - (1 if signed else 0)):
        raise InvalidCommand(f"{user} is too large for 0x{obj.index:04X}", cmd=n)
    writes = [(obj, raw)]
    if n == 6 and spec.also_obj is not None:
        writes.append((spec.also_obj, raw))  # acceleration is deceleration too
    return writes


def refuse_cyclic_coupling(master: int, slave: int, axes: Mapping[int, Any]) -> None:
    """29 between axes where either is cyclic is CAN (issue 30 finding 3, **chosen**):
    a cyclic axis moves on its bus's set-point lines only (:mod:`.cyclic_moves`), where
    a slave would not follow; accepted, the master moved and the slave stayed at 0
    (a gantry racks). docs/bridge.md says so."""
    for addr, role in ((master, "master"), (slave, "slave")):
        config = axes.get(addr)
        if config is not None and config.cyclic is not None:
            raise InvalidCommand(f"axis {addr} is cyclic ({config.cyclic!r}): it cannot be a "
                                 f"{role} of 29 (a cyclic axis moves on its line alone; "
                                 "use S90 for axes that move together)", cmd=29)


def _parameter(r: Resolved) -> WritePlan:
    axis, n = r.axis, r.spec.number
    assert axis is not None and r.value is not None
    value = r.value
    stored = to_stored(parameter_spec(n), value, axis.config.position_factor)
    if n == 29 and stored and (stored == axis.addr or stored not in axis.params.table.axes):
        raise InvalidCommand(f"slave axis {stored} is not another configured axis", cmd=29)
    if n == 29 and stored:
        refuse_cyclic_coupling(axis.addr, stored, axis.params.table.axes)
    if n == 80:
        SdoSelector.from_value(stored)  # length 1..4
    obj = axis.parameter_object(n)
    if obj is None:  # no drive involved: stored now, in arrival order, on the event loop
        return lambda: axis.params.set(axis.addr, n, stored)
    scaling = axis.scaling()
    drive_writes(axis, n, value, scaling)  # range check, before any transfer
    port = axis.need_port()
    ticket = Ticket(f"{r.request.axis}S{n:02d}={getattr(r.request, 'value', '')}")
    axis.promise(n, stored, ticket)

    def write() -> None:
        try:
            if n == 2:  # 607Ah is the live set-point in a cyclic mode: S02 never moves
                mode = port.read(MODES_DISPLAY, 0)
                if mode in _LIVE_TARGET_MODES:
                    raise DeviceFailure(f"{port.name}: 607Ah not written: the drive is in "
                                        f"mode {mode}, where it follows 607Ah at once")
            for o, raw in drive_writes(axis, n, value, axis.with_units(scaling, r.spec.quantity)):
                port.write(o.index, o.subindex, raw)
                axis.borrowed_profile.pop(o, None)  # the drive holds our own value now
        except BaseException as exc:
            axis.keep(n, ticket, None)
            ticket.settle(exc)
            raise
        axis.keep(n, ticket, stored)
        ticket.settle(None)
    return write


def _device_code(r: Resolved) -> WritePlan:
    axis = r.axis
    assert axis is not None and r.value is not None
    code = int(r.value)
    if code == MAXON_DEVICE and axis.config.increments_per_revolution is None:
        raise InvalidCommand(f"axis {axis.addr} has no increments_per_revolution in the "
                             "axis table, which device 5 needs", cmd=19)
    if axis.vendor_id is not None and (code == MAXON_DEVICE) != axis.is_maxon():
        # Issue 22 item 6: the unit rule follows what the drive is.
        raise InvalidCommand(f"axis {axis.addr}: device code {code} contradicts the drive's "
                             f"identity (1018h/1 vendor-ID 0x{axis.vendor_id:08X})", cmd=19)
    return _parameter(r)


def supervision_objects(axis: AxisRuntime) -> FrozenSet[int]:
    """The objects that make ``axis``'s drive stop when the bridge dies, which S81 never
    writes (issue 30 finding 5): its heartbeat consumer's on a bus with ``heartbeat_ms``,
    the watchdog reaction on EtherCAT (:mod:`tcp_bridge.motion.supervision`)."""
    if axis.drive is not None and axis.drive.supervision is not None:
        return HEARTBEAT_OBJECTS
    bus = axis.params.table.buses.get(axis.config.bus)
    if bus is not None and bus.backend == "ethercat":
        return WATCHDOG_OBJECTS
    return frozenset()


def _sdo_access(r: Resolved) -> WritePlan:
    axis = r.axis
    assert axis is not None and r.value is not None
    port, value = axis.need_port(), int(r.value)
    selector = SdoSelector.from_value(axis.value(80) or 0)
    if selector.index == CONTROLWORD_INDEX:
        raise InvalidCommand("the controlword is written by S04, S00 and S17 only (motion "
                             "rules), not by S81", cmd=81)
    bits = 8 * selector.length
    if not -(1 << (bits - 1)) <= value < (1 << bits):
        raise InvalidCommand(f"{value} does not fit {selector.length} bytes", cmd=81)
    size, signed = object_type(selector.index, selector.subindex)
    signed = signed and size == selector.length
    # With the object's own sign, so the value kept as written is the one read back.
    raw = value - (1 << bits) if signed and value >= 1 << (bits - 1) else \
        value & ((1 << bits) - 1) if not signed else value
    guarded = selector.index in MOTION_OBJECTS
    supervising = selector.index in supervision_objects(axis)
    drive = axis.drive

    def write_raw() -> None:
        if supervising:
            # Refused whatever the state: the bridge sets these up once per power-up
            # (motion.supervision), so a value written now would still hold when the
            # axis next moves, and a move would run that nothing stops if the bridge
            # dies (issue 30: a velocity move outlived a SIGKILL after S81 to 1016h).
            log.error("%s: S81 to 0x%04X/%d refused: it is the drive's supervision (what "
                      "stops it when the bridge dies), which the bridge keeps as the bus "
                      "table says", port.name, selector.index, selector.subindex)
            raise DeviceFailure(f"{port.name}: 0x{selector.index:04X} is the drive's "
                                "supervision: not written by S81")
        if guarded and drive is not None and drive.state() is State.OPERATION_ENABLED:
            log.error("%s: S81 to 0x%04X refused: the axis is enabled (it would power or "
                      "move it outside the motion rules)", port.name, selector.index)
            raise DeviceFailure(f"{port.name}: 0x{selector.index:04X} is not written while "
                                "the axis is enabled")
        port.write(selector.index, selector.subindex, raw, size=selector.length, signed=signed)
        if selector.index == VELOCITY_UNIT.index:  # read the new unit when next needed
            axis.velocity_exponent, axis.unit_error = None, None
    return write_raw


def _object(r: Resolved) -> WritePlan:
    """A raw object write (09 52)."""
    axis, obj, n = r.axis, r.spec.obj, r.spec.number
    assert axis is not None and obj is not None and r.value is not None
    port, value = axis.need_port(), r.value
    size, signed = object_type(obj.index, obj.subindex)
    low = -(1 << (8 * size - 1)) if signed else 0
    high = (1 << (8 * size - (1 if signed else 0))) - 1
    if not low <= value <= high:
        raise InvalidCommand(f"{value} is outside {low}..{high}", cmd=n)
    return lambda: port.write(obj.index, obj.subindex, int(value))


def _moving_ack(r: Resolved) -> WritePlan:
    axis, value = r.axis, int(r.value or 0)
    assert axis is not None

    def set_ack() -> None:
        axis.moving_ack = value
    return set_ack


class DriveParameters:
    """The parameters as kept by the bridge (motion.Restore), fixed at resolution."""

    def __init__(self, axis: AxisRuntime) -> None:
        self.axis = axis
        self.values = {n: axis.user(n) for n in DRIVE_PARAMETERS}
        self.scaling = axis.scaling()

    def _stored_writes(self) -> List[Tuple[ObjectRef, int]]:
        """The stored drive parameters in drive units. With a velocity unit the bridge
        does not know, the velocities are left out (they answer NAK on their own)."""
        stored = dict(self.values)
        scaling = self.scaling
        if any(v is not None and parameter_spec(n).quantity is Quantity.VELOCITY
               for n, v in stored.items()):
            try:
                scaling = self.axis.with_units(scaling)
            except NodeSilent:
                raise
            except DeviceFailure:  # unknown unit, already logged
                stored = {n: v for n, v in stored.items()
                          if parameter_spec(n).quantity is not Quantity.VELOCITY}
        writes: List[Tuple[ObjectRef, int]] = []
        for n, user in stored.items():
            if user is not None:
                writes.extend(drive_writes(self.axis, n, user, scaling))
        return writes

    def write(self) -> None:
        """Command 85 and the power-cycle path of 04: every stored drive parameter."""
        port = self.axis.need_port()
        self.axis.need_drive().statusword()  # the drive is there, even with nothing to write
        for obj, raw in self._stored_writes():
            port.write(obj.index, obj.subindex, raw)
            self.axis.borrowed_profile.pop(obj, None)

    def differs(self) -> Optional[str]:
        """Why the drive no longer holds the parameter values the bridge wrote to it
        in this session, None if it still does (motion rule 3). Only parameter
        objects count (not the controlword or targets); one the drive does not
        have (an abort) is skipped."""
        if not self.axis.compare_parameters:
            return None
        port = self.axis.need_port()
        for obj, raw in list(self.axis.written.items()):
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
        self.axis.compare_parameters = False


def allowed_modes(axis: AxisRuntime) -> FrozenSet[int]:
    """Spec 31 Possible Modes: the profile modes the axis may be enabled in (homing too)."""
    possible = axis.value(31) or 3
    modes = {Mode.HOMING}
    if possible in (1, 3):
        modes.add(Mode.PROFILE_POSITION)
    if possible in (2, 3):
        modes.add(Mode.PROFILE_VELOCITY)
    return frozenset(int(m) for m in modes)


def _inhibit(r: Resolved) -> WritePlan:
    axis = r.axis
    assert axis is not None
    drive = axis.need_drive()
    if r.value == 1:  # motion rules 1 and 3 (tcp_bridge.motion)
        restore, modes = DriveParameters(axis), allowed_modes(axis)
        if axis.cyclic is None:
            return lambda: drive.enable(restore, modes)
        port = axis.need_port()

        def enable_cyclic() -> None:
            if drive.state() is not State.OPERATION_ENABLED:
                # The drive left OPERATION ENABLED under a run (a quick stop, another
                # master): that run's set-points must not reach it once enabled again,
                # so its line ramps down and ends first (the others on it stop too).
                if stop_cyclic(axis):
                    wait_stopped(axis, drive.timing.ack_timeout)
                # A drive in CSP follows 607Ah at once when enabled: hold where it
                # stands; one in CSV follows 60FFh: hold still.
                mode = port.read(MODES_DISPLAY, 0)
                if mode == CSP_MODE:
                    port.write(0x607A, 0, port.read(0x6064, 0))
                elif mode == CSV_MODE:
                    port.write(0x60FF, 0, 0)
            drive.enable(restore, modes | {CSP_MODE, CSV_MODE})
        return enable_cyclic
    return drive.disable  # a cyclic axis ramps down on its profile first (cyclic_moves.rest)


def _mode(r: Resolved) -> WritePlan:
    assert r.axis is not None
    drive, mode = r.axis.need_drive(), int(r.value or 0)
    return lambda: drive.set_mode(mode)  # motion rule 2: a mode change halts first


def _reset_node(r: Resolved) -> WritePlan:
    assert r.axis is not None
    drive = r.axis.need_drive()
    return lambda: drive.reset_node(Why.CLIENT_RESET_NODE)  # rule 1: the client asked


def _fault_reset(r: Resolved) -> WritePlan:
    assert r.axis is not None
    return r.axis.need_drive().fault_reset


def _write_parameters(r: Resolved) -> WritePlan:
    assert r.axis is not None
    r.axis.need_port()
    return DriveParameters(r.axis).write


WRITES: Final[Mapping[str, Callable[[Resolved], WritePlan]]] = {
    "parameter": _parameter, "sdo_selector": _parameter, "device_code": _device_code,
    "sdo_access": _sdo_access, "sdo": _object, "moving_ack": _moving_ack,
    "inhibit": _inhibit, "mode": _mode, "reset_node": _reset_node,
    "fault_reset": _fault_reset, "write_parameters": _write_parameters,
}
"""S handlers by rule; 00 and 90 are in :mod:`.moves`, 91 in the engine."""

__all__: Final = ["DRIVE_PARAMETERS", "DriveParameters", "MOTION_OBJECTS", "WRITES",
                  "WritePlan", "check_resolution", "drive_writes"]
