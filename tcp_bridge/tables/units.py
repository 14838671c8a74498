"""User units, drive units and value parsing for the PSI gateway, without I/O.

Spec 3.6: the "Position UserUnit factor" (1, 10, 100, 1000, ...) says how user
values are "scaled and stored in SDO objects", because the gateway keeps only
integers. Conventions used here (``factor`` > 0, ``inversion`` 1 or -1 from
command 22, ``offset`` in user units from command 25)::

    user-unit value   drive = round(user * factor)                    05 06 13 23..28 41..43
                      user  = drive / factor
    position          drive = round((user - offset) * factor) * inversion   02 -> 0x607A
                      user  = drive * inversion / factor + offset            12
    display limits    inversion  1: 33 from 0x607D/2, 34 from 0x607D/1       33 34
                      inversion -1: 33 from 0x607D/1, 34 from 0x607D/2
                      each converted as a position

Velocities and accelerations (05 06 14 26-28 41-43 and the velocity of a
00=3 move) depend on the drive. Devices 1-4 count them in increments per
second (per second squared), so they convert with the factor like any other
user-unit value. A maxon EPOS4 (device 5) counts velocities in rpm and
accelerations in rpm/s (EPOS4 Firmware Specification 6.2.129 / 6.2.130 as quoted by
public EPOS4 drivers: 60A9h SI unit velocity, default 0x00B44700 = rpm; 60AAh SI
unit acceleration, fixed at rpm/s; see epos_link/simulator/units.py), where a revolution is the main
sensor's resolution in increments (3000h/05h; 4 x 3010h/01h pulses for an
incremental encoder). So, with ``ipr`` the axis's ``increments_per_revolution``
and ``10**e`` the power-of-ten prefix in the most significant byte of 60A9h::

    velocity       rpm   = user/s * factor * 60 / ipr,  drive = rpm / 10**e
    acceleration   rpm/s = user/s^2 * factor * 60 / ipr

So a finished move to ``S02=x`` reads back ``R12 = x``, and an inverted axis
shows its drive's minimum limit as its positive limit (the parenthesised
objects of 33/34 in the spec's table). Stored parameters marked ``*`` hold
``round(user * factor)`` (spec 4 footnote).

Arithmetic is decimal, from the shortest text of each float, so 1.0005 mm at
factor 1000 is 1000.5 -> 1001 as a person computes it, and rounding is half away
from zero, so inverting an axis never changes a magnitude. Results outside
INTEGER32 raise :class:`InvalidCommand` (answered CAN).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from functools import lru_cache
from typing import Final, Optional, Tuple, Union

from .commands import INT32, CommandSpec, Quantity, ValueType
from ..errors import InvalidCommand
from ..wire import NUMBER_RE

Number = Union[int, float]


def _dec(value: Number) -> Decimal:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"expected a number, not {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise InvalidCommand(f"{value!r} is not a finite number")
    return Decimal(value) if isinstance(value, int) else Decimal(repr(value))


def _to_int32(d: Decimal, what: str, sign: int = 1) -> int:
    # ROUND_HALF_UP is decimal's "half away from zero"; the sign is applied
    # after rounding so that inversion never changes a magnitude.
    n = int(d.to_integral_value(rounding=ROUND_HALF_UP)) * sign
    if not INT32[0] <= n <= INT32[1]:
        raise InvalidCommand(f"{what} {n} is outside INTEGER32")
    return n


RPM: Final = 0x00B44700  # 60A9h: prefix 00 (10^0), B4h revolutions, 47h per minute
# Prefixes the bridge knows for 60A9h (CiA 402-2 6.2 / CiA 303-2 notation, a
# signed power of ten in the most significant byte): 10^0 down to 10^-3, the
# four maxon's velocity notation defines (EPOS Command Library, Definitions.h
# VN_STANDARD .. VN_MILLI). Another prefix leaves the axis's velocity unit
# unknown: velocity commands are refused rather than scaled by a guess.
VELOCITY_EXPONENTS: Final = frozenset(range(-3, 1))


def velocity_exponent(unit: int) -> int:
    """The power of ten of a 60A9h value in rpm; :class:`ValueError` for any other unit."""
    if unit & 0x00FFFFFF != RPM & 0x00FFFFFF:
        raise ValueError(f"velocity unit 0x{unit:08X} is not rpm (expected 0x..B44700)")
    exponent = int.from_bytes(bytes([unit >> 24 & 0xFF]), "little", signed=True)
    if exponent not in VELOCITY_EXPONENTS:
        raise ValueError(f"velocity unit 0x{unit:08X}: prefix 10^{exponent} is not supported")
    return exponent


@dataclass(frozen=True)
class DriveUnits:
    """How a drive counts velocities and accelerations (see the module docstring)."""

    increments_per_revolution: Optional[int] = None  # None: inc/s (devices 1-4)
    velocity_exponent: int = 0  # EPOS4 60A9h prefix: drive value = rpm / 10**exponent

    def __post_init__(self) -> None:
        ipr = self.increments_per_revolution
        if ipr is not None and (isinstance(ipr, bool) or not isinstance(ipr, int) or ipr <= 0):
            raise ValueError(f"increments_per_revolution must be a positive integer, not {ipr!r}")
        if self.velocity_exponent not in VELOCITY_EXPONENTS:
            raise ValueError(f"velocity prefix 10^{self.velocity_exponent} is not supported")


@dataclass(frozen=True)
class Scaling:
    """The conversion parameters of one axis (spec 3.6, commands 22 and 25)."""

    factor: int = 1
    inversion: int = 1
    offset: float = 0.0
    units: DriveUnits = DriveUnits()

    def __post_init__(self) -> None:
        if isinstance(self.factor, bool) or not isinstance(self.factor, int) or self.factor <= 0:
            raise ValueError(f"position factor must be a positive integer, not {self.factor!r}")
        if self.inversion not in (1, -1):
            raise ValueError(f"axis inversion must be 1 or -1, not {self.inversion!r}")
        _dec(self.offset)  # rejects NaN and infinity

    def to_drive(self, user: Number) -> int:
        """``round(user * factor)``: a user-unit value (not a position) for the drive."""
        return _to_int32(_dec(user) * self.factor, "scaled value")

    def from_drive(self, raw: int) -> float:
        """``raw / factor``: a drive value (not a position) in user units."""
        return float(_dec(raw) / self.factor)

    def _per_rev(self) -> Decimal:
        """Drive rpm per user unit per second (EPOS4), from ``factor`` and ``ipr``."""
        ipr = self.units.increments_per_revolution
        assert ipr is not None
        return Decimal(self.factor) * 60 / ipr

    def velocity_to_drive(self, user: Number) -> int:
        """A velocity in user units/s for the drive (inc/s, or rpm with its prefix)."""
        if self.units.increments_per_revolution is None:
            return self.to_drive(user)
        rpm = _dec(user) * self._per_rev()
        return _to_int32(rpm.scaleb(-self.units.velocity_exponent), "velocity")

    def velocity_from_drive(self, raw: int) -> float:
        """A drive velocity (inc/s, or rpm with its prefix) in user units/s."""
        if self.units.increments_per_revolution is None:
            return self.from_drive(raw)
        rpm = _dec(raw).scaleb(self.units.velocity_exponent)
        return float(rpm / self._per_rev())

    def acceleration_to_drive(self, user: Number) -> int:
        """An acceleration in user units/s^2 for the drive (inc/s^2, or rpm/s)."""
        if self.units.increments_per_revolution is None:
            return self.to_drive(user)
        return _to_int32(_dec(user) * self._per_rev(), "acceleration")

    def acceleration_from_drive(self, raw: int) -> float:
        if self.units.increments_per_revolution is None:
            return self.from_drive(raw)
        return float(_dec(raw) / self._per_rev())

    def quantity_to_drive(self, quantity: Quantity, user: Number) -> int:
        """A user value of ``quantity`` in drive units (velocity, acceleration, or factor)."""
        if quantity is Quantity.VELOCITY:
            return self.velocity_to_drive(user)
        if quantity is Quantity.ACCELERATION:
            return self.acceleration_to_drive(user)
        return self.to_drive(user)

    def quantity_from_drive(self, quantity: Quantity, raw: int) -> float:
        """A drive value of ``quantity`` in user units: :meth:`quantity_to_drive` back."""
        if quantity is Quantity.VELOCITY:
            return self.velocity_from_drive(raw)
        if quantity is Quantity.ACCELERATION:
            return self.acceleration_from_drive(raw)
        return self.from_drive(raw)

    def position_to_drive(self, user: Number) -> int:
        """``round((user - offset) * factor) * inversion``: a user position for the drive."""
        return _to_int32((_dec(user) - _dec(self.offset)) * self.factor, "position", self.inversion)

    def position_from_drive(self, raw: int) -> float:
        """``raw * inversion / factor + offset``: a drive position in user units (12)."""
        return _position_from_drive(self, raw)

    def display_limits(self, raw_min: int, raw_max: int) -> Tuple[float, float]:
        """(33 Display Limit Positive, 34 Display Limit Negative) from 0x607D/1, /2.

        Which object each command reads is ``CommandSpec.object_for(inversion)``.
        """
        low = self.position_from_drive(raw_min)
        high = self.position_from_drive(raw_max)
        return (high, low) if self.inversion == 1 else (low, high)


# R12 is polled many times a second and a position at rest does not change: the
# decimal arithmetic (~10 us) runs once per (scaling, raw value). Bounded.
@lru_cache(maxsize=1024, typed=True)
def _position_from_drive(scaling: Scaling, raw: int) -> float:
    return float(_dec(raw) * scaling.inversion / scaling.factor + _dec(scaling.offset))


def stored_parameter(user: Number, factor: int) -> int:
    """The integer kept for a ``*`` parameter (spec 4 footnote): ``round(user * factor)``."""
    return Scaling(factor).to_drive(user)


def parse_value(spec: CommandSpec, text: str) -> Number:
    """The value of a write request for command ``spec``; :class:`InvalidCommand` if bad.

    INT commands take a decimal or 0x-hex integer; "1.0" is accepted as 1 (a
    client formatting with %f), "1.5" is not. FLOAT (user-unit) commands take a
    decimal only. The result is checked against ``spec.choices`` and, for INT,
    ``spec.value_range``; user-unit values are range-checked once scaled (see
    :class:`Scaling`). The error carries ``cmd`` only: answer it with the
    request's header (``protocol.format_error_reply(exc, request)``).
    """

    def invalid(why: str) -> InvalidCommand:
        return InvalidCommand(f"command {spec.number} ({spec.name}): {why}", cmd=spec.number)

    # The request grammar is checked again: this is a public function, and
    # Decimal alone would take "1e999999" or "NaN".
    if not isinstance(text, str) or not NUMBER_RE.fullmatch(text):
        raise invalid(f"{text!r} is not a decimal or 0x-hex number")
    is_hex = text[:2] in ("0x", "0X")
    number = int(text, 16) if is_hex else Decimal(text)
    if spec.value_type is ValueType.TEXT:
        raise invalid("takes no value")
    if spec.value_type is ValueType.FLOAT:
        if is_hex:
            raise invalid(f"{text!r}: user-unit values are decimal")
        result: Number = float(number)
        if not math.isfinite(result):
            raise invalid(f"{text!r} is out of range")
        if spec.choices is not None and result not in spec.choices:
            raise invalid(f"{text!r} is not one of {sorted(spec.choices)}")
        return result
    if isinstance(number, Decimal):
        if number != number.to_integral_value():
            raise invalid(f"{text!r} is not an integer")
        number = int(number)
    if spec.choices is not None and number not in spec.choices:
        raise invalid(f"{number} is not one of {sorted(spec.choices)}")
    low, high = spec.value_range
    if not low <= number <= high:
        raise invalid(f"{number} is outside {low}..{high}")
    return number
