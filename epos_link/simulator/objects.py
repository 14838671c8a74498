"""Which objects of the simulated EPOS4 are live, and which writes it refuses.

The generic CiA 301 checks (existence, access, length, EDS range) are in
:mod:`~epos_link.simulator.od`. This module adds, in one table, the rules an
EPOS4 has on top of them, as hooks on the store:

=============  ====================================================================
6041h, 6061h,  read from the drive model (statusword, mode display, position
6062h, 6064h,  demand and actual, velocity in the unit of 60A9h)
606Ch
607Ah          target position: handed to the drive model, which follows it at
               once in cyclic synchronous position mode (8)
3000h:05       main sensor resolution = 4 x 3010h:01 (read-only, see units)
6040h, 6060h,  handed to the drive model (controlword, mode, target velocity);
60FFh          (followed at once in csv, mode 9); 6060h refuses modes outside 6502h with 06090030h
60A9h          SI unit velocity: rpm with a prefix 10^0..10^-3, else 06090030h
3010h:01       encoder pulses: the drive re-plans in the new units
6098h          homing method: only maxon's methods (homing.py), else 06090030h
1003h:00       error history: 0 clears it, anything else 06090030h
2100h          simulator command (faults, power cycle, block/release), else 06090030h
=============  ====================================================================
"""
from __future__ import annotations

from enum import IntEnum
from typing import Protocol

from canopen import SdoAbortedError

from .faults import clear_history
from .homing import SUPPORTED_METHODS
from .od import ABORT_RANGE, ObjectStore, Value
from .units import ENCODER_PULSES, MAIN_SENSOR_RESOLUTION, SI_UNIT_VELOCITY, increments_per_revolution, velocity_exponent

__all__ = ["Mode", "install_object_rules"]


class Mode(IntEnum):
    """Supported modes of operation, 6060h (CiA 402-2 6.3.1); 6502h = 0x1A5
    (bits 0 pp, 2 pv, 5 hm, 7 csp, 8 csv). An EPOS4 also has cst (10), which
    the simulator does not model: 6060h refuses it."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9


class DriveModel(Protocol):
    @property
    def statusword(self) -> int: ...

    @property
    def mode(self) -> Mode: ...

    @property
    def position(self) -> int: ...

    @property
    def demand_position(self) -> int: ...

    @property
    def velocity(self) -> int: ...

    def on_controlword(self, value: Value) -> None: ...

    def on_mode(self, value: Value) -> None: ...

    def on_target_position(self, value: Value) -> None: ...

    def on_target_velocity(self, value: Value) -> None: ...

    def on_units_changed(self) -> None: ...

    def on_simulator_command(self, value: Value) -> None: ...


def install_object_rules(store: ObjectStore, drive: DriveModel) -> None:
    s = store
    s.add_read_hook(0x6041, 0, lambda: drive.statusword)
    s.add_read_hook(0x6061, 0, lambda: int(drive.mode))
    s.add_read_hook(0x6062, 0, lambda: drive.demand_position)
    s.add_read_hook(0x6064, 0, lambda: drive.position)
    s.add_read_hook(0x606C, 0, lambda: drive.velocity)
    s.add_read_hook(*MAIN_SENSOR_RESOLUTION, lambda: increments_per_revolution(s))
    s.add_write_hook(0x6040, 0, drive.on_controlword)
    s.add_write_hook(0x6060, 0, drive.on_mode)
    s.add_write_hook(0x607A, 0, drive.on_target_position)
    s.add_write_hook(0x60FF, 0, drive.on_target_velocity)
    s.add_write_hook(0x2100, 0, drive.on_simulator_command)

    def on_velocity_unit(value: Value) -> None:
        try:
            velocity_exponent(int(value))  # type: ignore[arg-type]
        except (ValueError, TypeError):
            raise SdoAbortedError(ABORT_RANGE) from None
        s.set(SI_UNIT_VELOCITY, 0, value)
        drive.on_units_changed()

    def on_encoder_pulses(value: Value) -> None:
        s.set(*ENCODER_PULSES, value)
        drive.on_units_changed()

    def on_homing_method(value: Value) -> None:
        if value not in SUPPORTED_METHODS:
            raise SdoAbortedError(ABORT_RANGE)

    def on_error_history(value: Value) -> None:
        # CiA 301 7.5.2.4: only 0 may be written to sub 0; it deletes the history.
        if value != 0:
            raise SdoAbortedError(ABORT_RANGE)
        clear_history(s)

    s.add_write_hook(SI_UNIT_VELOCITY, 0, on_velocity_unit)
    s.add_write_hook(*ENCODER_PULSES, on_encoder_pulses)
    s.add_write_hook(0x6098, 0, on_homing_method)
    s.add_write_hook(0x1003, 0, on_error_history)
