"""EPOS4 default units: positions in increments, velocities in rpm, accelerations in rpm/s.

Pure: no clocks, no I/O. This module is the ONE place that knows how the
simulated EPOS4 turns its objects' numbers into motion, and the helper a
bridge or a test uses to convert user units (``increments_per_revolution``).

Sources and choices:

* Position (6064h, 607Ah, 607Dh, 30B0h, 30B1h) is in increments of the main
  sensor. 3000h:05 "Main sensor resolution" is read-only and, for a digital
  incremental encoder, 4 x 3010h:01 "Digital incremental encoder 1 number of
  pulses" (quadrature). The EPOS4 computes it from the sensor configuration
  (public EPOS4 drivers read 3000h:05 back "[quadcounts/revolution]" and call
  it "Main Sensor Resolution (given in [increments/revolution])", EPOS4
  Firmware Specification 6.2.52).
* Velocity (6081h, 607Fh, 6080h, 60FFh, 606Ch, 6099h:01/02) is in the unit of
  60A9h "SI unit velocity", default 0x00B44700 = rpm (EPOS4 Firmware
  Specification 6.2.129 as quoted by public drivers). 60A9h is writable; its
  most significant byte is a power-of-ten prefix. maxon's velocity notation
  defines four prefixes: the EPOS Command Library (Definitions.h,
  "VelocityNotation") has VN_STANDARD = 0, VN_DECI = -1, VN_CENTI = -2 and
  VN_MILLI = -3, i.e. prefix bytes 0x00, 0xFF, 0xFE, 0xFD (rpm down to
  milli-rpm) with the low three bytes 0xB44700. Any other value (micro-rpm
  and below included) is refused with 0x06090030 (value range of parameter
  exceeded), the abort an EPOS4 gives for a value outside an object's range.
* Changing 60A9h does not rescale the stored velocity objects: their numbers
  are read in the new unit from then on (**chosen**; the manuals we have do
  not say what the EPOS4 does).
* Acceleration (6083h, 6084h, 6085h, 609Ah, 60C5h) is in rpm/s; 60AAh "SI unit
  acceleration" is fixed at 0x00C00300 (read-only here).

Conversions: ``inc/s = v * 10**prefix * increments_per_revolution / 60`` and
``inc/s^2 = a * increments_per_revolution / 60``.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Protocol

__all__ = [
    "ACCELERATION_UNIT",
    "ENCODER_PULSES",
    "MAIN_SENSOR_RESOLUTION",
    "SI_UNIT_ACCELERATION",
    "SI_UNIT_VELOCITY",
    "VELOCITY_PREFIXES",
    "VELOCITY_UNIT_RPM",
    "Units",
    "increments_per_revolution",
    "units_of",
    "velocity_exponent",
]

SI_UNIT_VELOCITY = 0x60A9
SI_UNIT_ACCELERATION = 0x60AA
MAIN_SENSOR_RESOLUTION = (0x3000, 0x05)
ENCODER_PULSES = (0x3010, 0x01)

VELOCITY_UNIT_RPM = 0x00B44700  # 60A9h default: prefix 0, revolution (B4h) per minute (47h)
ACCELERATION_UNIT = 0x00C00300  # 60AAh: rpm/s, fixed

# Prefix byte -> power of ten: maxon's velocity notation (Definitions.h VN_*).
VELOCITY_PREFIXES: Mapping[int, int] = MappingProxyType({
    0x00: 0, 0xFF: -1, 0xFE: -2, 0xFD: -3,
})

QUADRATURE = 4  # increments per encoder pulse (A/B edges)


class IntStore(Protocol):
    def get_int(self, index: int, subindex: int = 0) -> int: ...


def velocity_exponent(si_unit: int) -> int:
    """The power of ten of a 60A9h value, or ValueError if the EPOS4 would refuse it."""
    prefix, unit = (si_unit >> 24) & 0xFF, si_unit & 0x00FFFFFF
    if unit != VELOCITY_UNIT_RPM or prefix not in VELOCITY_PREFIXES or not 0 <= si_unit < 1 << 32:
        raise ValueError(f"SI unit velocity 0x{si_unit:08X} is not rpm with a prefix 10^0..10^-3")
    return VELOCITY_PREFIXES[prefix]


def increments_per_revolution(store: IntStore) -> int:
    """Main sensor increments per motor revolution: 4 x 3010h:01 (= 3000h:05)."""
    return QUADRATURE * store.get_int(*ENCODER_PULSES)


@dataclass(frozen=True)
class Units:
    """The conversion factors of one drive at one moment."""

    increments_per_revolution: int
    velocity_exponent: int = 0  # 60A9h prefix: velocity unit = 10**exponent rpm

    @property
    def inc_s_per_velocity_unit(self) -> float:
        return 10.0 ** self.velocity_exponent * self.increments_per_revolution / 60.0

    @property
    def inc_s2_per_acceleration_unit(self) -> float:
        return self.increments_per_revolution / 60.0

    def velocity_to_inc_s(self, velocity: float) -> float:
        """A velocity object's number (rpm x 10^prefix) in increments per second."""
        return velocity * self.inc_s_per_velocity_unit

    def velocity_from_inc_s(self, inc_s: float) -> float:
        return inc_s / self.inc_s_per_velocity_unit

    def acceleration_to_inc_s2(self, acceleration: float) -> float:
        """An acceleration object's number (rpm/s) in increments per second squared."""
        return acceleration * self.inc_s2_per_acceleration_unit


def units_of(store: IntStore) -> Units:
    """The units a drive's store holds now (60A9h and the encoder)."""
    return Units(increments_per_revolution(store), velocity_exponent(store.get_int(SI_UNIT_VELOCITY)))
