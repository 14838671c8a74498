"""The command table of the PSI gateway, revision 2.3 (spec section 4), as data.

Each TCP command number maps to a frozen :class:`CommandSpec`. Columns of the
spec's table and where they went:

====================  ==========================================================
spec column           CommandSpec field
====================  ==========================================================
TCP Cmd               ``number``, ``name``
Internal parameter    ``parameter`` (the number), ``scaled`` (the ``*`` mark:
                      "internally stored as an integer value, the factor is given
                      in parameter Position UserUnit factor", spec 3.6)
SDO (ACK/NAK)         ``obj``; a second object in parentheses is ``also_obj``
                      (06: deceleration written too) or ``inverted_obj`` (33/34:
                      read instead when the axis is inverted); ``needs_sdo``
Read/Write            ``readable``, ``writable``
Unit                  ``unit``, ``user_units``, ``choices``
Explanation           ``kind``, ``offset_inversion``, ``note``
====================  ==========================================================

``needs_sdo`` means the command talks to the drive, so ACK/NAK reports whether
the drive answered (spec 2.2.2: "The ACK/NAK is only relevant ... if the field
in the SDO (ACK/NAK) column ... is colored"). The colours did not survive in
our copy of the spec; the rule used is "an object is given", with the
exceptions commented at their rows.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import TYPE_CHECKING, Final, FrozenSet, Mapping, Optional, Tuple

from ..errors import InvalidCommand

if TYPE_CHECKING:
    from ..wire import Request

INT8: Final = (-(2**7), 2**7 - 1)
INT16: Final = (-(2**15), 2**15 - 1)
INT32: Final = (-(2**31), 2**31 - 1)
UINT32: Final = (0, 2**32 - 1)


class CommandKind(Enum):
    """What the gateway does for a command (from the table's explanation column)."""

    SEQUENCE = "sequence"  # "This command is a whole sequence" (00, 04, 07)
    ACTION = "action"  # a one-shot write that stores nothing (16, 17, 85, 90)
    SDO = "sdo"  # direct access to one drive object
    PARAMETER = "parameter"  # an internal parameter (spec 3), maybe mirrored to an object
    STATUS_BIT = "status_bit"  # one bit of the statusword 0x6041 (82, 83, 84)
    INTERNAL = "internal"  # gateway state outside the parameter array (86, 91, 99)


class Quantity(Enum):
    """What a user-unit value measures; velocities and accelerations convert by the
    drive's units (:class:`tcp_bridge.tables.units.Scaling`), the rest by the factor."""

    OTHER = "other"  # positions, distances, windows: user * factor
    VELOCITY = "velocity"  # user/s: inc/s, or rpm on an EPOS4
    ACCELERATION = "acceleration"  # user/s^2: inc/s^2, or rpm/s on an EPOS4


class ValueType(Enum):
    """How the value text of a write is parsed (see tcp_bridge.tables.units.parse_value)."""

    INT = "int"  # codes, bit fields, raw drive units; decimal or 0x-hex
    FLOAT = "float"  # user units
    TEXT = "text"  # read-only text (99 SW Version)


@dataclass(frozen=True)
class ObjectRef:
    """A CANopen object dictionary entry, ``0x607D/2`` in the spec's notation."""

    index: int
    subindex: int = 0

    def __str__(self) -> str:
        return f"0x{self.index:04X}/{self.subindex}"


@dataclass(frozen=True)
class CommandSpec:
    """One row of the spec's command table (section 4)."""

    number: int
    name: str
    readable: bool
    writable: bool
    kind: CommandKind
    obj: Optional[ObjectRef] = None
    parameter: Optional[int] = None  # "Internal parameter" column
    unit: str = ""
    value_type: ValueType = ValueType.INT
    scaled: bool = False  # "*": stored as round(user value * position factor)
    user_units: bool = False  # unit "UserUnits...": converted with the position factor
    offset_inversion: bool = False  # drive value converted with offset and axis inversion
    needs_sdo: bool = False
    also_obj: Optional[ObjectRef] = None
    inverted_obj: Optional[ObjectRef] = None
    quantity: "Quantity" = Quantity.OTHER
    bit: Optional[int] = None  # statusword bit of a STATUS_BIT command
    choices: Optional[FrozenSet[int]] = None
    value_range: Tuple[int, int] = INT32  # for INT; FLOAT is range-checked after scaling
    note: str = ""

    @property
    def index(self) -> Optional[int]:
        return None if self.obj is None else self.obj.index

    @property
    def subindex(self) -> Optional[int]:
        return None if self.obj is None else self.obj.subindex

    def allows(self, kind: str) -> bool:
        """Whether the R/W column permits a request of ``kind`` "S" or "R"."""
        return self.writable if kind.upper() == "S" else self.readable

    def object_for(self, inversion: int) -> Optional[ObjectRef]:
        """The object to access on an axis with this inversion (1 or -1); 33/34 swap."""
        if inversion == -1 and self.inverted_obj is not None:
            return self.inverted_obj
        return self.obj


def _o(index: int, subindex: int = 0) -> ObjectRef:
    return ObjectRef(index, subindex)


_K = CommandKind
_F = ValueType.FLOAT
_V = Quantity.VELOCITY
_A = Quantity.ACCELERATION
_STATUSWORD = _o(0x6041)
_CONTROLWORD = _o(0x6040)

_TABLE: Tuple[CommandSpec, ...] = (
    CommandSpec(0, "Move", False, True, _K.SEQUENCE, _CONTROLWORD, needs_sdo=True,
                choices=frozenset({1, 2, 3, 8, 9}),
                unit="1=absolute 2=relative 3=velocity 8=stop 9=home"),
    # 02 and 05 give their object in parentheses; the 2.2.2 / 2.3.2 examples
    # show "3 S 02<NAK>" and "3 R 2<NAK>", so the drive is involved: needs_sdo.
    # Offset and inversion apply when the target goes to 0x607A, so that a
    # finished move reads back the same value with 12 Position.
    CommandSpec(2, "Target Position", True, True, _K.PARAMETER, _o(0x607A), 6, "UserUnits",
                _F, scaled=True, user_units=True, offset_inversion=True, needs_sdo=True,
                note="converted before writing SDO"),
    CommandSpec(4, "Inhibit", True, True, _K.SEQUENCE, _CONTROLWORD, needs_sdo=True,
                choices=frozenset({0, 1}), unit="0=power off 1=power on",
                note="enable: after a power cycle NodeReset and WriteParameter first"),
    CommandSpec(5, "Velocity", True, True, _K.PARAMETER, _o(0x6081), 7, "UserUnits/sec",
                _F, scaled=True, user_units=True, needs_sdo=True, quantity=_V),
    CommandSpec(6, "Acceleration", True, True, _K.PARAMETER, _o(0x6083), 8, "UserUnits/sec^2",
                _F, scaled=True, user_units=True, needs_sdo=True, also_obj=_o(0x6084),
                quantity=_A),
    CommandSpec(7, "Mode of operation", True, True, _K.SEQUENCE, _o(0x6060), needs_sdo=True,
                choices=frozenset({1, 3, 6}), unit="1=profile position 3=profile velocity 6=homing"),
    CommandSpec(9, "Quick-Stop option", True, True, _K.SDO, _o(0x605A), needs_sdo=True,
                value_range=INT16),  # CiA 402: 0x605A is INTEGER16
    CommandSpec(10, "Status", True, False, _K.SDO, _STATUSWORD, needs_sdo=True),
    # 11 and 18 leave the object blank: the registers depend on the device code
    # (spec 3.5). They are read from the drive all the same.
    CommandSpec(11, "Detailed Error", True, False, _K.SDO, needs_sdo=True),
    CommandSpec(12, "Position", True, False, _K.SDO, _o(0x6064), unit="UserUnits", value_type=_F,
                user_units=True, offset_inversion=True, needs_sdo=True,
                note="Nanotec reads 0x6062"),
    CommandSpec(13, "In Position Window", True, False, _K.SDO, _o(0x6067), unit="UserUnits",
                value_type=_F, user_units=True, needs_sdo=True),
    # No unit in the table; read in the unit of 05 (UserUnits/sec), so that
    # a running S00=3 reads back as its own velocity.
    CommandSpec(14, "Actual Velocity", True, False, _K.SDO, _o(0x606C), unit="UserUnits/sec",
                value_type=_F, user_units=True, needs_sdo=True, quantity=_V),
    CommandSpec(15, "Mode of operation display", True, False, _K.SDO, _o(0x6061), needs_sdo=True),
    # NMT has no confirmation (CiA 301), so there is nothing to NAK.
    # 16 and 17 are actions: only 1 asks for them ("3S16=0" must not reset a node).
    CommandSpec(16, "Reset Node", False, True, _K.ACTION, choices=frozenset({1}),
                note="NMT reset node (CAN only)"),
    CommandSpec(17, "Reset Error", False, True, _K.ACTION, _CONTROLWORD, needs_sdo=True,
                choices=frozenset({1}), note="fault reset in the controlword"),
    CommandSpec(18, "General Error", True, False, _K.SDO, needs_sdo=True),
    CommandSpec(19, "Device Code", True, True, _K.PARAMETER, parameter=2,
                choices=frozenset(range(5))),  # spec 3.5: C_DC_NOT_DEFINED .. C_DC_COBLEY_CAN
    CommandSpec(20, "Scale_N", True, True, _K.PARAMETER, parameter=10),
    CommandSpec(21, "Scale_Z", True, True, _K.PARAMETER, parameter=11),
    CommandSpec(22, "Axis Inversion", True, True, _K.PARAMETER, parameter=12,
                choices=frozenset({1, -1}), unit="1=normal -1=inverted"),
    # 23/24 are in drive direction, scaled only; 33/34 show them with offset and inversion.
    CommandSpec(23, "Limit Positive", True, True, _K.PARAMETER, _o(0x607D, 2), 13, "UserUnits",
                _F, scaled=True, user_units=True, needs_sdo=True),
    CommandSpec(24, "Limit Negative", True, True, _K.PARAMETER, _o(0x607D, 1), 14, "UserUnits",
                _F, scaled=True, user_units=True, needs_sdo=True),
    # The offset is itself stored scaled; it is never offset or inverted.
    CommandSpec(25, "Offset", True, True, _K.PARAMETER, parameter=15, unit="UserUnits",
                value_type=_F, scaled=True, user_units=True,
                note="offset position is converted before writing SDO"),
    CommandSpec(26, "Max Velocity", True, True, _K.PARAMETER, _o(0x607F), 16, "UserUnits/sec",
                _F, scaled=True, user_units=True, needs_sdo=True, quantity=_V,
                note="only internal for Technosoft and Copley"),
    CommandSpec(27, "Max Acceleration", True, True, _K.PARAMETER, _o(0x60C5), 17,
                "UserUnits/sec^2", _F, scaled=True, user_units=True, needs_sdo=True,
                quantity=_A),
    CommandSpec(28, "QuickStop Accel", True, True, _K.PARAMETER, _o(0x6085), 18,
                "UserUnits/sec^2", _F, scaled=True, user_units=True, needs_sdo=True,
                quantity=_A),
    CommandSpec(29, "Slave Axis (AxAddr)", True, True, _K.PARAMETER, parameter=19,
                value_range=(0, 60)),  # an AxAddr (spec 3.1); 0 = none
    CommandSpec(30, "Slave Axis direction", True, True, _K.PARAMETER, parameter=20,
                choices=frozenset({1, -1}), unit="1=normal -1=inverted"),
    CommandSpec(31, "Possible Modes of operation", True, False, _K.PARAMETER, parameter=21,
                choices=frozenset({1, 2, 3}), unit="1=profile position 2=profile velocity 3=both"),
    CommandSpec(32, "Dynamic Limits", True, False, _K.PARAMETER, parameter=22,
                choices=frozenset({0, 1}), unit="0=static 1=dynamic"),
    CommandSpec(33, "Display Limit Positive", True, False, _K.SDO, _o(0x607D, 2),
                unit="UserUnits", value_type=_F, user_units=True, offset_inversion=True,
                needs_sdo=True, inverted_obj=_o(0x607D, 1),
                note="calculated with offset and axis inversion"),
    CommandSpec(34, "Display Limit Negative", True, False, _K.SDO, _o(0x607D, 1),
                unit="UserUnits", value_type=_F, user_units=True, offset_inversion=True,
                needs_sdo=True, inverted_obj=_o(0x607D, 2),
                note="calculated with offset and axis inversion"),
    CommandSpec(40, "Homing Mode", True, True, _K.PARAMETER, _o(0x6098), 25, needs_sdo=True,
                value_range=INT8),  # CiA 402: homing method is INTEGER8
    CommandSpec(41, "Homing Velocity (switch)", True, True, _K.PARAMETER, _o(0x6099, 1), 26,
                "UserUnits/sec", _F, scaled=True, user_units=True, needs_sdo=True, quantity=_V),
    CommandSpec(42, "Homing Velocity (index)", True, True, _K.PARAMETER, _o(0x6099, 2), 27,
                "UserUnits/sec", _F, scaled=True, user_units=True, needs_sdo=True, quantity=_V),
    CommandSpec(43, "Homing Acceleration", True, True, _K.PARAMETER, _o(0x609A), 28,
                "UserUnits/sec^2", _F, scaled=True, user_units=True, needs_sdo=True,
                quantity=_A),
    CommandSpec(50, "Read Inputs", True, False, _K.SDO, _o(0x60FD), needs_sdo=True),
    CommandSpec(52, "Set Digital Outputs", True, True, _K.SDO, _o(0x60FE, 1), needs_sdo=True,
                value_range=UINT32),  # CiA 402: 0x60FE is UNSIGNED32
    CommandSpec(53, "Output function", True, True, _K.PARAMETER, _o(0x60FE, 2), 30,
                needs_sdo=True, value_range=UINT32),
    CommandSpec(54, "Output delay time", True, True, _K.PARAMETER, parameter=31, unit="ms",
                value_range=(0, INT32[1])),
    CommandSpec(56, "Control Brake", True, True, _K.PARAMETER, parameter=32,
                choices=frozenset({0, 1}), unit="1=control brake 0=no controlled brake"),
    CommandSpec(60, "Encoder Type", True, True, _K.PARAMETER, parameter=35,
                choices=frozenset({0, 1, 2}), unit="0=INC 1=SSI 2=BiSS"),
    CommandSpec(61, "Encoder Position", True, False, _K.SDO, _o(0x6064), unit="System units",
                needs_sdo=True),
    CommandSpec(62, "Following Error setting", True, True, _K.PARAMETER, _o(0x6065), 36,
                needs_sdo=True, value_range=UINT32),  # CiA 402: 0x6065 is UNSIGNED32
    CommandSpec(63, "Encoder direction", True, True, _K.PARAMETER, _o(0x200D), 37,
                needs_sdo=True, note="only Nanotec"),
    CommandSpec(80, "Set SDO Index", True, True, _K.PARAMETER, parameter=38, unit="0xXXXXSSLL",
                value_range=UINT32, note="index/subindex/length for command 81"),
    # The object of 81 is whatever 80 selected; its data may be signed or unsigned.
    CommandSpec(81, "Perform SDO Access", True, True, _K.SDO, needs_sdo=True,
                value_range=(INT32[0], UINT32[1]), note="object selected by command 80"),
    # Statusword bits from table 4.a. The table names no end-switch bit, and
    # bit 11 "Internal Limit Active" is also set while a drive limits current or
    # velocity, so 83 reads the limit switch inputs of 60FDh instead (bit 0
    # negative, bit 1 positive; CiA 402-2 60FDh), see tcp_bridge.plan.axis. The
    # row keeps the spec's own column.
    CommandSpec(82, "Motion /Target reached", True, False, _K.STATUS_BIT, _STATUSWORD,
                needs_sdo=True, bit=10, choices=frozenset({0, 1}), unit="0=motion 1=in target"),
    CommandSpec(83, "Endswitch hit", True, False, _K.STATUS_BIT, _STATUSWORD, needs_sdo=True,
                bit=11, choices=frozenset({0, 1}), unit="0=no hit 1=switch hit",
                note="the spec's column; the bridge reads 60FDh bits 0 and 1"),
    CommandSpec(84, "Error Bit", True, False, _K.STATUS_BIT, _STATUSWORD, needs_sdo=True,
                bit=3, choices=frozenset({0, 1}), unit="0=ok 1=error"),
    # The SDO column is "-", but writing every parameter is all SDO transfers.
    CommandSpec(85, "Write Parameters", False, True, _K.ACTION, needs_sdo=True,
                note="write all parameters to the controller"),
    CommandSpec(86, "Moving Acknowledgement", True, True, _K.INTERNAL,
                choices=frozenset({0, 1}), unit="0=not started 1=started",
                note="set 0 before moving"),
    CommandSpec(90, "Combined Move", False, True, _K.ACTION, choices=frozenset({0, 1, 2}),
                unit="0=stop 1=LINR move 2=LINA to zero", note="internal axes only (spec 3.2)"),
    CommandSpec(91, "Debug Print", True, True, _K.INTERNAL, choices=frozenset({0, 1}),
                unit="1=active 0=inactive", note="global parameter, default 0"),
    CommandSpec(99, "SW Version", True, False, _K.INTERNAL, value_type=ValueType.TEXT,
                note="PSI command interpreter version"),
)

COMMANDS: Final[Mapping[int, CommandSpec]] = MappingProxyType({c.number: c for c in _TABLE})
"""Every command of spec rev 2.3, section 4, by number."""

OWN_RULES: Final[Mapping[int, str]] = MappingProxyType({
    0: "move", 4: "inhibit", 7: "mode", 11: "detailed_error", 12: "position",
    13: "position_window", 14: "velocity", 16: "reset_node", 17: "fault_reset",
    18: "general_error", 19: "device_code", 33: "display_limit", 34: "display_limit",
    80: "sdo_selector", 81: "sdo_access", 82: "target_reached", 83: "end_switch",
    85: "write_parameters", 86: "moving_ack", 90: "combined_move", 91: "debug", 99: "version",
})
"""The rows with a rule of their own, by the name of their handler in :mod:`tcp_bridge.plan`;
every other row is handled by its kind (``CommandKind.value``)."""


def rule_of(spec: CommandSpec) -> str:
    """The name of the handler of ``spec``: its own rule, else its kind."""
    return OWN_RULES.get(spec.number, spec.kind.value)


def lookup(cmd: int) -> CommandSpec:
    """The spec of command ``cmd``; :class:`InvalidCommand` if the table has none."""
    try:
        return COMMANDS[cmd]
    except KeyError:
        raise InvalidCommand(f"unknown command {cmd}", cmd=cmd) from None


def resolve(request: "Request") -> CommandSpec:
    """The spec for ``request`` after checking the R/W column (spec 2.2.2 / 2.3.2).

    Raises :class:`InvalidCommand` (answered CAN, e.g. "3 S 10<CAN>": STATUS is
    not writable) carrying the request's header.
    """
    spec = COMMANDS.get(request.cmd)
    if spec is None:
        why = f"unknown command {request.cmd}"
    elif not spec.allows(request.kind):
        what = "writable" if request.kind == "S" else "readable"
        why = f"command {request.cmd} ({spec.name}) is not {what}"
    else:
        return spec
    raise InvalidCommand(why, axis=request.axis, kind=request.kind, cmd=request.cmd)


@dataclass(frozen=True)
class SdoSelector:
    """The value of command 80, ``0xXXXXSSLL``: index, subindex, length in bytes."""

    index: int
    subindex: int
    length: int

    def __post_init__(self) -> None:
        if not (0 <= self.index <= 0xFFFF and 0 <= self.subindex <= 0xFF):
            raise InvalidCommand(f"bad SDO object 0x{self.index:X}/{self.subindex}")
        # An expedited SDO carries 1..4 bytes (CiA 301), the only kind 81 can use.
        if not 1 <= self.length <= 4:
            raise InvalidCommand(f"SDO length must be 1..4 bytes, not {self.length}")

    @classmethod
    def from_value(cls, value: int) -> "SdoSelector":
        if not UINT32[0] <= value <= UINT32[1]:
            raise InvalidCommand(f"command 80 value {value} is not an unsigned 32-bit number")
        return cls(value >> 16, (value >> 8) & 0xFF, value & 0xFF)

    def to_value(self) -> int:
        return self.index << 16 | self.subindex << 8 | self.length
