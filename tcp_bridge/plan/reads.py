"""The R handlers: one per rule of the command table (:data:`READS`), each returning
the closure that the bus runs, with every value of the request fixed.

Rules not spelled out by the spec, chosen here:

* Parameter reads (02, 05, 06, 23, 24, 26-28, 40-43, 53, 62, 63) with an SDO
  object read the drive, so an absent node answers NAK; the value returned is
  the stored one (the controller's array, spec 3) when there is one, else the
  drive's value converted.
* Velocities and accelerations convert by the drive's units
  (:mod:`tcp_bridge.tables.units`): rpm and rpm/s on an EPOS4 (device 5), whose
  velocity unit 60A9h is read from the drive the first time it is needed.
* Readings are in the user's frame (22 applied): 12 and 33/34 with offset and
  inversion, 14 Actual Velocity in user units/s with the sign of the motion
  that 12 shows, and the limit bits of 11 swapped on an inverted axis (the
  drive's positive limit switch ends the user's negative travel).
* 11 Detailed Error (spec 4.b): Technosoft devices map their motion error
  register 2000h; every other device composes it from the error code 603Fh
  (CiA 301 classes; maxon EPOS4 codes 8A80h-8A88h) and 60FDh limit inputs.
* 82 is statusword bit 10 read in the drive's mode (6061h, read only when it
  matters): in profile velocity, where bit 10 is "velocity reached", it is bit
  12 "speed is zero"; in homing it is 1 only when homing attained (bit 12)
  without error (bit 13), so an interrupted or failed homing reads 0
  (CiA 402-2 6.6, statusword table).
* 83 End switch hit is the limit switch inputs of 60FDh (CiA 402-2: bit 0
  negative, bit 1 positive limit switch), not statusword bit 11, which an
  EPOS4 also sets while it limits current or velocity.
"""
from __future__ import annotations

from typing import Callable, Final, Mapping, Union

from ..bus.sdo import NodeSilent, object_type
from ..cia402_words import MODES_DISPLAY, STATUSWORD, Mode, Sw
from ..errors import DeviceFailure
from ..motion import State
from ..tables.axes import DeviceCode
from ..tables.commands import SdoSelector
from .axis import AxisRuntime
from .resolve import Resolved

Value = Union[int, float, str]
ReadPlan = Callable[[], Value]

# Technosoft motion error register 2000h bit -> spec 4.b bit.
_TECHNOSOFT_MER: Final = {1: 1, 3: 3, 4: 4, 5: 5, 6: 6, 7: 7, 8: 10, 11: 11, 12: 12, 13: 13, 15: 15}
# maxon EPOS4 error codes (603Fh) -> spec 4.b bit (EPOS4 Firmware Specification,
# error code table: 8A80h negative limit switch, 8A81h positive limit switch,
# 8A82h software position limit, 8A88h STO).
_MAXON_BITS: Final = {0x8A80: 7, 0x8A81: 6, 0x8A88: 15}
SOFTWARE_LIMIT_ERROR: Final = 0x8A82
LIMIT_INPUTS: Final = 0x3  # 60FDh bit 0 negative, bit 1 positive limit switch
_SIDES: Final = ((6, 7), (8, 9))  # spec 4.b: positive/negative limit switch, software limit


def detailed_error_from_code(code: int, inputs: int, software_limit_bit: int = 0) -> int:
    """Spec 4.b register from a CiA 301 / maxon error code (603Fh) and 60FDh inputs, in
    the drive's frame. ``software_limit_bit`` (8 positive, 9 negative) says which side
    a software position limit error (8A82h) is on; the code alone does not say."""
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


def in_user_frame(bits: int, inversion: int) -> int:
    """Spec 4.b bits with the sides swapped on an inverted axis (22 = -1)."""
    if inversion != -1:
        return bits
    for positive, negative in _SIDES:
        p, n = bits >> positive & 1, bits >> negative & 1
        bits &= ~(1 << positive | 1 << negative)
        bits |= n << positive | p << negative
    return bits


def _parameter(r: Resolved) -> ReadPlan:
    axis, spec = r.axis, r.spec
    assert axis is not None
    n = spec.number
    user = axis.user(n)
    obj = axis.parameter_object(n)
    if obj is None:
        value: Value = 0 if user is None else user  # the controller's arrays start at 0
        return lambda: value
    port = axis.need_port()
    scaling = axis.scaling() if spec.scaled or n == 2 else None

    def read() -> Value:
        raw = port.read(obj.index, obj.subindex)
        if user is not None:
            return user  # the stored value (for 05 with its sign: the direction)
        if scaling is None:
            return raw
        if n == 2:
            return scaling.position_from_drive(raw)
        return axis.with_units(scaling, spec.quantity).quantity_from_drive(spec.quantity, raw)
    return read


def _sdo_selector(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    text = f"0x{r.axis.value(80) or 0:08X}"
    return lambda: text


def _statusword(axis: AxisRuntime) -> Callable[[], int]:
    """The statusword for a status poll (from a PDO when the bus has them), handed to the
    drive's sequences too: a drive that fell back is noticed whoever read it (rule 3)."""
    port, drive = axis.need_port(), axis.drive

    def read() -> int:
        sw = port.read_status(STATUSWORD, 0)
        if drive is not None:
            drive.observe(sw)
        return sw
    return read


def _object(r: Resolved) -> ReadPlan:
    """A raw object (09 15 50 52 61); 10 from a PDO when the bus has them."""
    assert r.axis is not None and r.spec.obj is not None
    port, obj = r.axis.need_port(), r.spec.obj
    if r.spec.number == 10:  # tcp_bridge.backends.pdo_status
        return _statusword(r.axis)
    return lambda: port.read(obj.index, obj.subindex)


_POWER_ON = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})


def _inhibit(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    drive = r.axis.need_drive()
    # Spec 3.5, 04: "0 = Power OFF, 1 = Power ON". QUICK STOP ACTIVE keeps the power
    # stage on (CiA 402-2 6.4.1; with 605Ah = 5..8, the EPOS4's default 6, it stays
    # there at rest), so it answers 1 too: 0 would claim less than the drive holds.
    # A move still needs OPERATION ENABLED (S04=1 ends the quick stop first).
    return lambda: int(drive.state() in _POWER_ON)


def _mode(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port = r.axis.need_port()
    return lambda: port.read(0x6060, 0)


def _position(r: Resolved) -> ReadPlan:
    # Only the reads that convert a position build the axis's scaling: a status
    # poll (R10, R82...) does not pay for it (issue 14: many clients polling).
    assert r.axis is not None
    port, scaling = r.axis.need_port(), r.axis.scaling()
    index = 0x6062 if r.axis.device is DeviceCode.C_DC_NANOTEC else 0x6064
    return lambda: scaling.position_from_drive(port.read_status(index, 0))


def _position_window(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port, scaling = r.axis.need_port(), r.axis.scaling()
    return lambda: scaling.from_drive(port.read(0x6067, 0))


def _velocity(r: Resolved) -> ReadPlan:
    axis = r.axis
    assert axis is not None
    port, scaling = axis.need_port(), axis.scaling()

    def read() -> float:
        # In the user's frame: the sign of the motion that R12 shows (22 applied).
        raw = port.read_status(0x606C, 0)
        return axis.with_units(scaling).velocity_from_drive(raw) * scaling.inversion or 0.0
    return read


def _general_error(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port = r.axis.need_port()
    return lambda: port.read(0x1001, 0)


def _display_limit(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port, scaling = r.axis.need_port(), r.axis.scaling()
    obj = r.spec.object_for(scaling.inversion)
    assert obj is not None
    return lambda: scaling.position_from_drive(port.read(obj.index, obj.subindex))


def _sdo_access(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port = r.axis.need_port()
    selector = SdoSelector.from_value(r.axis.value(80) or 0)
    size, signed = object_type(selector.index, selector.subindex)
    signed = signed and size == selector.length
    drive = r.axis.drive if (selector.index, selector.subindex) == (STATUSWORD, 0) else None

    def read() -> int:
        value = port.read(selector.index, selector.subindex, size=selector.length,
                          signed=signed)
        if drive is not None and selector.length >= 2:
            drive.observe(value & 0xFFFF)
        return value
    return read


def _end_switch(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    port = r.axis.need_port()
    return lambda: int(bool(port.read_status(0x60FD, 0) & LIMIT_INPUTS))


def _status_bit(r: Resolved) -> ReadPlan:
    assert r.axis is not None and r.spec.bit is not None
    statusword, bit = _statusword(r.axis), r.spec.bit
    return lambda: (statusword() >> bit) & 1


def _target_reached(r: Resolved) -> ReadPlan:
    assert r.axis is not None
    if r.axis.cyclic is not None:  # the bridge's own profile (issue 26)
        from .cyclic_moves import cyclic_target_reached
        return cyclic_target_reached(r.axis)
    port, statusword = r.axis.need_port(), _statusword(r.axis)

    def read() -> int:
        sw = statusword()
        if not sw & Sw.TARGET_REACHED:
            return 0
        if sw & Sw.OP_MODE_12 and not sw & Sw.OP_MODE_13:
            return 1  # reached, attained or at zero speed, whatever the mode, no error
        mode = port.read_status(MODES_DISPLAY, 0)
        if mode == Mode.HOMING:
            return 0  # interrupted (bit 12 low) or failed (bit 13): not in target
        if mode == Mode.PROFILE_VELOCITY:
            return int(bool(sw & Sw.OP_MODE_12))  # "speed is zero"
        return 1
    return read


def _moving_ack(r: Resolved) -> ReadPlan:
    axis = r.axis
    assert axis is not None
    return lambda: axis.moving_ack


def _detailed_error(r: Resolved) -> ReadPlan:
    axis = r.axis
    assert axis is not None
    port, inversion = axis.need_port(), axis.scaling().inversion

    def read() -> int:
        if axis.device in (DeviceCode.C_DC_TECHNOSOFT_CAN, DeviceCode.C_DC_TECHNOSOFT_EC):
            mer = port.read(0x2000, 0)
            bits = sum(1 << out for bit, out in _TECHNOSOFT_MER.items() if mer >> bit & 1)
            return in_user_frame(bits, inversion)
        code = port.read(0x603F, 0)
        try:
            inputs = port.read(0x60FD, 0)
        except NodeSilent:
            raise
        except DeviceFailure:
            inputs = 0  # no digital inputs object (an abort): only the error code counts
        side = 0
        if code == SOFTWARE_LIMIT_ERROR:
            # The side whose limit (607Dh) the position (6064h) is nearer to.
            position = port.read(0x6064, 0)
            low, high = port.read(0x607D, 1), port.read(0x607D, 2)
            side = 9 if abs(position - low) < abs(position - high) else 8
        return in_user_frame(detailed_error_from_code(code, inputs, side), inversion)
    return read


READS: Final[Mapping[str, Callable[[Resolved], ReadPlan]]] = {
    "parameter": _parameter, "device_code": _parameter, "sdo_selector": _sdo_selector,
    "sdo": _object, "inhibit": _inhibit, "mode": _mode, "position": _position,
    "position_window": _position_window, "velocity": _velocity,
    "general_error": _general_error, "display_limit": _display_limit,
    "sdo_access": _sdo_access, "end_switch": _end_switch, "status_bit": _status_bit,
    "target_reached": _target_reached, "moving_ack": _moving_ack,
    "detailed_error": _detailed_error,
}
"""R handlers by rule; 91 and 99 are answered by the engine (no axis)."""

__all__: Final = ["READS", "ReadPlan", "Value", "detailed_error_from_code", "in_user_frame"]
