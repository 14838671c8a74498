"""The fields of a motor record that the bridge serves, as data (pure).

Types and menus follow epics-modules/motor ``motorApp/MotorSrc/motorRecord.dbd``
(``field(NAME, DBF_...)``, ``menu(motorSPMG)`` ...) so that clients written for a
real IOC (pyepics ``epics.Motor``, ophyd ``EpicsMotor``, ophyd-async ``Motor``,
NICOS, Phoebus screens) find every field they connect to, with the type they
expect. DBF_ULONG (MSTA, MMAP) is served as a CA long, as caproto's own motor
field group does (``caproto.server.records.MotorFields``); DBF_*LINK and
DBF_STRING fields are CA strings.

Each field has a *role*:

``live``
    the bridge writes it from the axis (readbacks, DMOV, MSTA ...); CA: read only
``put``
    a client's put is a request (:mod:`tcp_bridge.epics.axis` says what each does)
``meta``
    a writable property of the record itself that no drive holds (EGU, PREC, DESC,
    the alarm severity menus): kept in memory, as an IOC keeps it until a reboot
``fixed``
    a field of the record that this bridge does not implement (backlash, retries,
    jogging, encoder ratio, gains ...): served read only with the value that makes
    the real record behave as the bridge does (BDST 0: no backlash; RTRY 0: no
    retries), so a put is refused by the client's CA library, never silently ignored.

The SinqMotor extension PVs of PSI's IOCs (NICOS ``nicos_sinq`` SinqMotor:
``motorpv + ':Enable'``, ``':EnableRBV'``, ``':CanDisable'``, ``':EncoderType'``,
``':StatusProblem'``, ``':Reset'``, ``'-MsgTxt'``; ``':Connected'`` as issue 33
asks) are listed in :data:`EXTRAS`.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import Any, Final, Mapping, Optional, Tuple


class Kind(Enum):
    """The CA type a field is served as."""

    DOUBLE = "double"
    FLOAT = "float"
    SHORT = "short"
    LONG = "long"
    ENUM = "enum"
    STRING = "string"
    CHARS = "chars"  # a char waveform holding text (the SinqMotor message)


@dataclass(frozen=True)
class Field:
    name: str
    kind: Kind
    role: str  # "live", "put", "meta", "fixed"
    default: Any = 0
    menu: Tuple[str, ...] = ()


# motorRecord.dbd menus.
DIR_MENU: Final = ("Pos", "Neg")
SET_MENU: Final = ("Use", "Set")
SPMG_MENU: Final = ("Stop", "Pause", "Move", "Go")
FOFF_MENU: Final = ("Variable", "Frozen")
TORQ_MENU: Final = ("Disable", "Enable")
UEIP_MENU: Final = ("No", "Yes")
STUP_MENU: Final = ("OFF", "ON", "BUSY")
RMOD_MENU: Final = ("Default", "Arithmetic", "Geometric", "In-Position")
YESNO_MENU: Final = ("NO", "YES")
OMSL_MENU: Final = ("supervisory", "closed_loop")
SEVR_MENU: Final = ("NO_ALARM", "MINOR", "MAJOR", "INVALID")
# EPICS base menuAlarmStat (dbCommon STAT), in order.
STAT_MENU: Final = ("NO_ALARM", "READ", "WRITE", "HIHI", "HIGH", "LOLO", "LOW", "STATE", "COS",
                    "COMM", "TIMEOUT", "HWLIMIT", "CALC", "SCAN", "LINK", "SOFT", "BAD_SUB",
                    "UDF", "DISABLE", "SIMM", "READ_ACCESS", "WRITE_ACCESS")

SPMG_STOP, SPMG_PAUSE, SPMG_MOVE, SPMG_GO = range(4)

# MSTA bits, motor.h ``msta_field`` (LSB first): what each means there.
MSTA_DIRECTION = 1 << 0  # (last) 0 = negative, 1 = positive
MSTA_DONE = 1 << 1  # a motion is complete
MSTA_PLUS_LS = 1 << 2  # plus limit switch has been hit
MSTA_HOME = 1 << 3  # the home signal is on
MSTA_POSITION = 1 << 5  # position maintenance enabled (closed loop on)
MSTA_SLIP_STALL = 1 << 6  # slip/stall detected
MSTA_PRESENT = 1 << 8  # encoder is present
MSTA_PROBLEM = 1 << 9  # driver stopped polling / a problem
MSTA_MOVING = 1 << 10  # non-zero velocity present
MSTA_GAIN_SUPPORT = 1 << 11  # motor supports closed-loop position control
MSTA_COMM_ERR = 1 << 12  # controller communication error
MSTA_MINUS_LS = 1 << 13  # minus limit switch has been hit
MSTA_HOMED = 1 << 14  # axis has been homed

_D, _F, _S, _L, _E, _T = Kind.DOUBLE, Kind.FLOAT, Kind.SHORT, Kind.LONG, Kind.ENUM, Kind.STRING


def _f(name: str, kind: Kind, role: str, default: Any = 0, menu: Tuple[str, ...] = ()) -> Field:
    return Field(name, kind, role, default, menu)


FIELDS: Final[Tuple[Field, ...]] = (
    # Motion: every put here is a request (tcp_bridge.epics.axis).
    _f("VAL", _D, "put"), _f("DVAL", _D, "put"), _f("RVAL", _L, "put"), _f("RLV", _D, "put"),
    _f("TWF", _S, "put"), _f("TWR", _S, "put"), _f("TWV", _D, "meta", 1.0),
    _f("STOP", _S, "put"), _f("SPMG", _E, "put", SPMG_GO, SPMG_MENU),
    _f("HOMF", _S, "put"), _f("HOMR", _S, "put"), _f("CNEN", _E, "put", 0, TORQ_MENU),
    _f("SYNC", _S, "put"),
    # Coordinates and calibration.
    _f("OFF", _D, "put"), _f("DIR", _E, "put", 0, DIR_MENU), _f("SET", _E, "put", 0, SET_MENU),
    _f("SSET", _S, "put"), _f("SUSE", _S, "put"), _f("FOFF", _E, "put", 0, FOFF_MENU),
    _f("FOF", _S, "put"), _f("VOF", _S, "put"),
    _f("HLM", _D, "put"), _f("LLM", _D, "put"), _f("DHLM", _D, "put"), _f("DLLM", _D, "put"),
    # Speeds: 05, 06, 26 of the PSI table.
    _f("VELO", _D, "put"), _f("ACCL", _D, "put", 0.2), _f("VMAX", _D, "put"),
    # The record's own description of itself.
    _f("EGU", _T, "meta", ""), _f("PREC", _S, "meta", 3), _f("DESC", _T, "meta", ""),
    _f("HLSV", _E, "meta", 0, SEVR_MENU), _f("MDEL", _D, "meta"), _f("ADEL", _D, "meta"),
    _f("HOPR", _D, "meta"), _f("LOPR", _D, "meta"),
    # Readbacks and status, from the axis.
    _f("RBV", _D, "live"), _f("DRBV", _D, "live"), _f("RRBV", _L, "live"), _f("RMP", _L, "live"),
    _f("REP", _L, "live"), _f("DIFF", _D, "live"), _f("RDIF", _L, "live"),
    _f("DMOV", _S, "live", 1), _f("MOVN", _S, "live"), _f("MSTA", _L, "live"),
    _f("LVIO", _S, "live"), _f("HLS", _S, "live"), _f("LLS", _S, "live"),
    _f("RHLS", _S, "live"), _f("RLLS", _S, "live"), _f("TDIR", _S, "live"),
    _f("CDIR", _S, "live"), _f("ATHM", _S, "live"), _f("MIP", _S, "live"),
    _f("MISS", _S, "live"), _f("LVAL", _D, "live"), _f("LDVL", _D, "live"),
    _f("LRVL", _L, "live"), _f("LRLV", _D, "live"), _f("LSPG", _E, "live", SPMG_GO, SPMG_MENU),
    _f("RVEL", _L, "live"), _f("RCNT", _S, "live"),
    _f("STAT", _E, "live", 0, STAT_MENU), _f("SEVR", _E, "live", 0, SEVR_MENU),
    # Implemented by the drive's own profile or not at all: read only, honest values.
    _f("MRES", _D, "fixed", 1.0), _f("ERES", _D, "fixed", 1.0), _f("RRES", _D, "fixed", 1.0),
    _f("SREV", _L, "fixed", 200), _f("UREV", _D, "fixed", 200.0), _f("S", _D, "fixed"),
    _f("SBAS", _D, "fixed"), _f("SMAX", _D, "fixed"), _f("VBAS", _D, "fixed"),
    _f("BDST", _D, "fixed"), _f("BVEL", _D, "fixed"), _f("BACC", _D, "fixed", 0.5),
    _f("SBAK", _D, "fixed"), _f("FRAC", _F, "fixed", 1.0), _f("RDBD", _D, "fixed", 1.0),
    _f("SPDB", _D, "fixed"), _f("RTRY", _S, "fixed"), _f("RMOD", _E, "fixed", 0, RMOD_MENU),
    _f("DLY", _D, "fixed"), _f("UEIP", _E, "fixed", 0, UEIP_MENU),
    _f("URIP", _E, "fixed", 0, UEIP_MENU), _f("NTM", _E, "fixed", 1, YESNO_MENU),
    _f("NTMF", _S, "fixed", 2), _f("HVEL", _D, "fixed"), _f("JVEL", _D, "fixed"),
    _f("JAR", _D, "fixed"), _f("JOGF", _S, "fixed"), _f("JOGR", _S, "fixed"),
    _f("PCOF", _D, "fixed"), _f("ICOF", _D, "fixed"), _f("DCOF", _D, "fixed"),
    _f("STUP", _E, "fixed", 0, STUP_MENU), _f("OMSL", _E, "fixed", 0, OMSL_MENU),
    _f("LOCK", _E, "fixed", 0, YESNO_MENU), _f("IGSET", _S, "fixed"), _f("PP", _S, "fixed"),
    _f("CARD", _S, "fixed"), _f("VERS", _F, "fixed", 6.9), _f("OUT", _T, "fixed", ""),
    _f("DOL", _T, "fixed", ""), _f("RDBL", _T, "fixed", ""), _f("RLNK", _T, "fixed", ""),
    _f("STOO", _T, "fixed", ""), _f("DINP", _T, "fixed", ""), _f("RINP", _T, "fixed", ""),
    _f("INIT", _T, "fixed", ""), _f("PREM", _T, "fixed", ""), _f("POST", _T, "fixed", ""),
    _f("DTYP", _T, "fixed", "tcp-bridge"), _f("RTYP", _T, "fixed", "motor"),
    _f("NAME", _T, "fixed", ""), _f("ALST", _D, "fixed"), _f("MLST", _D, "fixed"),
    _f("HHSV", _E, "fixed", 0, SEVR_MENU), _f("LLSV", _E, "fixed", 0, SEVR_MENU),
    _f("HSV", _E, "fixed", 0, SEVR_MENU), _f("LSV", _E, "fixed", 0, SEVR_MENU),
    _f("HIHI", _D, "fixed"), _f("LOLO", _D, "fixed"), _f("HIGH", _D, "fixed"),
    _f("LOW", _D, "fixed"), _f("DISA", _S, "fixed"), _f("DISV", _S, "fixed", 1),
)

BY_NAME: Final[Mapping[str, Field]] = MappingProxyType({f.name: f for f in FIELDS})
assert len(BY_NAME) == len(FIELDS), "a field is listed twice"

# Fields whose alarm state is the record's (STAT/SEVR): every field of a real record
# carries them (dbCommon), so every channel of the record shares one alarm.

# The SinqMotor extension PVs: suffix -> field (``put``: a request; ``live``: read only).
EXTRAS: Final[Tuple[Tuple[str, Field], ...]] = (
    (":Enable", Field("Enable", _S, "put")),
    (":EnableRBV", Field("EnableRBV", _S, "live")),
    (":CanDisable", Field("CanDisable", _S, "fixed", 1)),
    (":Connected", Field("Connected", _S, "live")),
    (":Reset", Field("Reset", _S, "put")),
    (":StatusProblem", Field("StatusProblem", _S, "live")),
    (":EncoderType", Field("EncoderType", _T, "fixed", "incremental")),
    ("-MsgTxt", Field("MsgTxt", Kind.CHARS, "live", "")),
)
MESSAGE_SIZE: Final = 200  # characters of -MsgTxt (a char waveform); longer texts are cut


def menu_index(field: Field, value: Any) -> int:
    """The index of an enum field's value (an index or one of its strings)."""
    if isinstance(value, str):
        return field.menu.index(value)
    return int(value)


def writable(field: Field) -> bool:
    return field.role in ("put", "meta")


def find(name: str) -> Optional[Field]:
    return BY_NAME.get(name)
