"""What ``tcp-bridge check`` concludes from what an axis's drive answered, without I/O.

:mod:`tcp_bridge.check` reads a few objects of every configured drive
(:class:`Reading`); :func:`judge` compares them with the axis table and gives
one :class:`Verdict` per axis, :func:`row` and :func:`as_json` show it. The
first failing rule decides:

=============== =============================================================
no bus          the bus of the axis could not be opened (adapter, URL, driver)
device silent   the bus's own device (the EPOS4 on the link) does not answer a
                read of itself: wrong port or baud rate, no power. Its nodes
                are not asked, so none is called absent for it
absent          the node did not answer its first read (0x1000 device type,
                mandatory in CiA 301 V4.2 7.5.2.1): wrong node id, bit rate,
                cabling, power
wrong device    the node is not a CiA 402 drive (0x1000 bits 0..15 are the
                device profile number, 402 for drives: CiA 301 7.5.2.1), it
                shows no CiA 402 state in its statusword 6041h (CiA 402-2
                6.4.1.4), or device 5 answers with a vendor-ID other than
                maxon's 0x000000FB (0x1018/01; the EPOS4 EDS's VendorNumber)
units unknown   device 5 only: 60A9h (SI unit velocity) is not rpm with a
                prefix the bridge knows, or 60A9h or 3000h/05h (main sensor
                resolution) cannot be read (see :mod:`tcp_bridge.tables.units`)
units mismatch  device 5 only: 3000h/05h differs from the axis table's
                ``increments_per_revolution``, so every velocity the bridge
                sends would be off by their ratio
found           the axis answers as configured
no drive        an internal axis with node id 0 (spec 3): nothing to ask
=============== =============================================================

Vendor-IDs are checked for device 5 only: the other device codes of spec 3.5
name a vendor whose CiA vendor-ID this project has no source for.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Dict, Final, Mapping, Optional, Tuple

from epos_link.cia402 import state_from_statusword

from .tables.axes import AxisConfig, DeviceCode
from .cia402_words import Mode
from .tables.units import Scaling, velocity_exponent

CIA402_PROFILE: Final = 402  # 0x1000 bits 0..15 (CiA 301 V4.2 7.5.2.1)
MAXON_VENDOR_ID: Final = 0x000000FB  # 0x1018/01 of an EPOS4 (EPOS4 EDS, VendorNumber)


class Verdict(Enum):
    FOUND = "found"
    NO_DRIVE = "no drive"
    ABSENT = "absent"
    NO_BUS = "no bus"
    DEVICE_SILENT = "device silent"
    WRONG_DEVICE = "wrong device"
    UNITS_UNKNOWN = "units unknown"
    UNITS_MISMATCH = "units mismatch"

    @property
    def ok(self) -> bool:
        """The axis answers as configured (exit status 0 needs this for every axis)."""
        return self in (Verdict.FOUND, Verdict.NO_DRIVE)


@dataclass
class Reading:
    """What one node answered. ``None``: not read; ``failures`` says why, by object."""

    silent: Optional[str] = None  # the node did not answer at all: why
    device_type: Optional[int] = None  # 0x1000
    name: Optional[str] = None  # 0x1008
    vendor_id: Optional[int] = None  # 0x1018/01
    product_code: Optional[int] = None  # 0x1018/02
    revision: Optional[int] = None  # 0x1018/03
    serial: Optional[int] = None  # 0x1018/04
    statusword: Optional[int] = None  # 6041h
    mode: Optional[int] = None  # 6061h
    position: Optional[int] = None  # 6064h, increments
    velocity_unit: Optional[int] = None  # 60A9h (EPOS4)
    sensor_resolution: Optional[int] = None  # 3000h/05h (EPOS4)
    # What stops the drive if the bridge dies, as read from it (tcp_bridge.check).
    supervision: Optional[str] = None
    failures: Dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class AxisReport:
    """One row of the check: the axis, its verdict and what was read."""

    axis: AxisConfig
    verdict: Verdict
    detail: str
    reading: Reading
    scaling: Scaling = Scaling()

    @property
    def ok(self) -> bool:
        return self.verdict.ok

    @property
    def state(self) -> Optional[str]:
        sw = self.reading.statusword
        state = None if sw is None else state_from_statusword(sw)
        return None if state is None else state.name.replace("_", " ").lower()

    @property
    def position(self) -> Optional[float]:
        raw = self.reading.position
        return None if raw is None else self.scaling.position_from_drive(raw)

    @property
    def units(self) -> str:
        """How the drive counts velocities, as far as known."""
        if self.axis.device is not DeviceCode.C_DC_MAXON_EPOS4:
            return "inc/s"
        unit = self.reading.velocity_unit
        try:
            exponent = None if unit is None else velocity_exponent(unit)
        except ValueError:
            exponent = None
        rpm = "rpm?" if exponent is None else "rpm" if exponent == 0 else f"1e{exponent} rpm"
        return f"{rpm}, {_text(self.reading.sensor_resolution)} inc/rev"


def _text(value: Optional[int]) -> str:
    return "?" if value is None else str(value)


def _hex(value: Optional[int]) -> Optional[str]:
    return None if value is None else f"0x{value:08X}"


def no_bus(axis: AxisConfig, why: str) -> AxisReport:
    return AxisReport(axis, Verdict.NO_BUS, why, Reading())


def device_silent(axis: AxisConfig, why: str) -> AxisReport:
    return AxisReport(axis, Verdict.DEVICE_SILENT, why, Reading())


def no_drive(axis: AxisConfig) -> AxisReport:
    return AxisReport(axis, Verdict.NO_DRIVE, "internal axis without a drive (node id 0)",
                      Reading())


def judge(axis: AxisConfig, reading: Reading, scaling: Scaling = Scaling()) -> AxisReport:
    """The verdict on one axis from what its node answered (rules: module docstring)."""
    verdict, detail = _verdict(axis, reading)
    return AxisReport(axis, verdict, detail, reading, scaling)


def _verdict(axis: AxisConfig, r: Reading) -> Tuple[Verdict, str]:
    where = f"node {axis.node_id} on {axis.bus}"
    if r.silent is not None:
        return Verdict.ABSENT, (f"{where} did not answer ({r.silent}); check its node id, "
                                "the bit rate, the cabling and its power")
    if r.device_type is not None and r.device_type & 0xFFFF != CIA402_PROFILE:
        return Verdict.WRONG_DEVICE, (f"{where} has device type 0x{r.device_type:08X}: profile "
                                      f"{r.device_type & 0xFFFF}, not a CiA 402 drive")
    if r.statusword is None or state_from_statusword(r.statusword) is None:
        why = r.failures.get("6041h") or f"0x{r.statusword:04X} codes no CiA 402 state"
        return Verdict.WRONG_DEVICE, f"{where}: no CiA 402 statusword 6041h ({why})"
    if axis.device is not DeviceCode.C_DC_MAXON_EPOS4:
        return Verdict.FOUND, ""
    if r.vendor_id != MAXON_VENDOR_ID:
        got = r.failures.get("1018h/01") if r.vendor_id is None else f"0x{r.vendor_id:08X}"
        return Verdict.WRONG_DEVICE, (f"{where}: vendor-ID {got}, but device 5 is a maxon "
                                      f"EPOS4 (0x{MAXON_VENDOR_ID:08X})")
    return _epos4_units(axis, r)


def _epos4_units(axis: AxisConfig, r: Reading) -> Tuple[Verdict, str]:
    if r.velocity_unit is None:
        return Verdict.UNITS_UNKNOWN, f"60A9h (velocity unit) unreadable: {r.failures.get('60A9h')}"
    try:
        velocity_exponent(r.velocity_unit)
    except ValueError as exc:
        return Verdict.UNITS_UNKNOWN, f"{exc}; velocity commands of this axis would answer NAK"
    if r.sensor_resolution is None:
        return Verdict.UNITS_UNKNOWN, ("3000h/05h (main sensor resolution) unreadable: "
                                       f"{r.failures.get('3000h/05')}")
    ipr = axis.increments_per_revolution
    if r.sensor_resolution != ipr:
        return Verdict.UNITS_MISMATCH, (
            f"the drive's main sensor resolution (3000h/05h) is {r.sensor_resolution} inc/rev, "
            f"the axis table says increments_per_revolution = {ipr}: velocities and "
            f"accelerations would be off by {r.sensor_resolution}/{ipr}")
    return Verdict.FOUND, ""


# -- output -------------------------------------------------------------------------------

# maxon's abbreviations of the modes of operation (6061h, CiA 402-2 6.3.1).
MODE_NAMES: Final[Mapping[int, str]] = {Mode.PROFILE_POSITION: "PPM", Mode.PROFILE_VELOCITY: "PVM", Mode.HOMING: "HMM"}
HEADER: Final = ("axis", "bus/node", "verdict", "device", "serial", "state", "mode",
                 "position", "units")
WIDTHS: Final = (4, 9, 14, 10, 10, 19, 4, 12, 0)


def _cells(report: AxisReport) -> Tuple[str, ...]:
    r, axis = report.reading, report.axis
    mode = "" if r.mode is None else MODE_NAMES.get(r.mode, str(r.mode))
    node = f"{axis.bus}/{axis.node_id}"
    position = "" if report.position is None else f"{report.position:g}"
    unknown = report.verdict in (Verdict.NO_BUS, Verdict.DEVICE_SILENT, Verdict.ABSENT,
                                 Verdict.NO_DRIVE)
    return (str(axis.addr), node, report.verdict.value, r.name or "",
            "" if r.serial is None else f"{r.serial:#x}", report.state or "", mode, position,
            "" if unknown else report.units)


def table(reports: "list[AxisReport]") -> str:
    """One row per axis, a detail line under each that is not ok; a detail that
    several axes share (their bus's, which names it) under the first of them only."""
    lines = [_line(HEADER)]
    shown = set()
    for report in reports:
        lines.append(_line(_cells(report)))
        if report.detail and not report.ok and report.detail not in shown:
            shown.add(report.detail)
            lines.append(f"     {report.detail}")
    return "\n".join(lines)


def _line(cells: Tuple[str, ...]) -> str:
    return " ".join(c.ljust(w) for c, w in zip(cells, WIDTHS)).rstrip()


def as_json(report: AxisReport) -> str:
    """One JSON object: ``addr`` and ``verdict`` always, then what was read."""
    r, axis = report.reading, report.axis
    data: Dict[str, Any] = {
        "addr": axis.addr, "verdict": report.verdict.value, "ok": report.ok,
        "detail": report.detail, "bus": axis.bus, "node_id": axis.node_id,
        "device": int(axis.device), "device_name": r.name,
        "device_type": _hex(r.device_type), "vendor_id": _hex(r.vendor_id),
        "product_code": _hex(r.product_code), "revision": _hex(r.revision),
        "serial": _hex(r.serial), "statusword": None if r.statusword is None else
        f"0x{r.statusword:04X}", "state": report.state, "mode": r.mode,
        "position_increments": r.position, "position": report.position,
        "velocity_unit": _hex(r.velocity_unit), "sensor_resolution": r.sensor_resolution,
        "increments_per_revolution": axis.increments_per_revolution,
        "supervision": r.supervision, "unreadable": dict(r.failures),
    }
    return json.dumps(data)
