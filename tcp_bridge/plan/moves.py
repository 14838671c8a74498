"""Command 00 Move in drive units, for one axis and the slaves that follow it (29/30).

This module only works out *what* each drive is told (targets, velocities and
profiles, converted with each axis's own units); *how* a move starts, and the
safety rules around it, are :meth:`tcp_bridge.motion.Cia402.move` and
:meth:`~tcp_bridge.motion.Cia402.halt`.

Slave axes (spec 29 Slave Axis, 30 Slave Axis direction): a slave makes the
same move as its master in user units, mirrored when 30 is -1:

* absolute (00=1): the slave's target is the master's 02 times the direction,
  converted with the slave's own factor, offset and inversion;
* relative (00=2): the master's 02 is a distance, times the direction;
* velocity (00=3): the master's 05 times the direction;
* the slave borrows its master's profile in user units (05 velocity, 06
  acceleration and deceleration), so both run the same trapezoid. The slave's
  own profile values go back to its drive before it next moves on its own;
* homing (00=9): each axis homes with its own method and speeds (40-43), as a
  gantry's two sides each find their own switch; positions are not kept
  together while homing. Home the slave alone first if it must not move with
  its master;
* stop (00=8) halts both.

A master and a slave on the same bus move in **one bus job**: both are
prepared, then their start writes go out back to back
(:meth:`~tcp_bridge.motion.Cia402.move`), so they start a few SDO round trips
apart. A slave on another bus moves as a companion job of the engine
(:mod:`tcp_bridge.engine`), gated on the master's acceptance.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Sequence, Tuple

from ..tables.commands import COMMANDS, ObjectRef
from ..errors import DeviceFailure, InvalidCommand
from ..motion import HomingMove, Move, PositionMove, VelocityMove
from .axis import check_resolution
from ..bus.sdo import NodeSilent
from ..tables.units import Number

if TYPE_CHECKING:
    from .axis import AxisOps

log = logging.getLogger(__name__)

PROFILE_VELOCITY = ObjectRef(0x6081)
PROFILE_ACCELERATION = ObjectRef(0x6083)
PROFILE_DECELERATION = ObjectRef(0x6084)


@dataclass(frozen=True)
class Follower:
    """A slave that makes its master's move: the axis and its direction (30)."""

    ops: "AxisOps"
    direction: int


def check_move(ops: "AxisOps", how: int, direction: int = 1,
               target: Optional[Number] = None) -> None:
    """Everything about a move that can be checked without the drive (CAN if bad)."""
    _what(ops, how, direction, target, check_only=True)


def _what(ops: "AxisOps", how: int, direction: int, target: Optional[Number],
          check_only: bool = False) -> Optional[Move]:
    """The move of ``ops`` in drive units; ``target`` (user units) for a slave."""
    if how in (1, 2):
        user = ops.params.user(ops.addr, 2) if target is None else target
        if user is None:
            raise InvalidCommand(f"axis {ops.addr}: no target position (S02) set", cmd=0)
        user = user * direction
        scaling = ops.scaling()
        if how == 1:
            raw = scaling.position_to_drive(user)
        else:  # a distance: inverted and scaled, never offset
            raw = scaling.to_drive(user) * scaling.inversion
        return PositionMove(raw, relative=how == 2)
    if how == 3:
        velocity = ops.params.user(ops.addr, 5) if target is None else target
        if velocity is None:
            raise InvalidCommand(f"axis {ops.addr}: no velocity (S05) set", cmd=0)
        scaling = ops.scaling() if check_only else ops.drive_scaling()
        raw = scaling.velocity_to_drive(velocity * direction) * scaling.inversion
        check_resolution(ops.addr, COMMANDS[5], velocity, raw, scaling)
        return VelocityMove(raw)
    if how == 9:
        return HomingMove()
    return None  # 8: stop


def plan_move(ops: "AxisOps", how: int, followers: Sequence[Follower] = (),
              target: Optional[Number] = None, direction: int = 1,
              profile: Optional[Dict[ObjectRef, Number]] = None) -> Callable[[], None]:
    """00 Move: 1 absolute, 2 relative, 3 velocity, 8 stop, 9 home.

    ``followers`` are slaves on the same bus, moved in the same job. ``target``
    and ``direction`` are given when ``ops`` is itself a slave on another bus
    (a companion job) or an internal axis of command 90; ``profile`` is then its
    master's (:func:`stored_profile`), borrowed for the move.
    """
    drive = ops._drive()
    for f in followers:
        f.ops._drive()
    master_target = target
    if how in (1, 2) and target is None:
        master_target = ops.params.user(ops.addr, 2)
    elif how == 3 and target is None:
        master_target = ops.params.user(ops.addr, 5)
    check_move(ops, how, direction, target)
    for f in followers:
        check_move(f.ops, how, f.direction, master_target)
    if how == 8:
        return lambda: halt_all([ops, *(f.ops for f in followers)])

    def move() -> None:
        axes = [(ops, direction, target)] + [(f.ops, f.direction, master_target)
                                             for f in followers]
        if followers:
            share_profile(ops, [f.ops for f in followers])
        elif profile is not None:
            _write_profile(ops, profile)
        elif ops.borrowed_profile:
            give_back_profile(ops)
        moves = []
        for axis, sign, value in axes:
            what = _what(axis, how, sign, value)
            assert what is not None
            moves.append((axis._drive(), what))
        for axis, _, _ in axes:
            axis.moving_ack = 0  # spec 86: 0 before the move ...

        def accepted(i: int) -> None:
            axes[i][0].moving_ack = 1  # ... and 1 once the drive accepted it
        drive.move(moves, accepted)
    return move


def _profile_in_user_units(master: "AxisOps") -> Dict[ObjectRef, Number]:
    """The master's profile (05, 06) in user units: stored values, else its drive's."""
    port = master._port()
    velocity = master.params.user(master.addr, 5)
    acceleration = master.params.user(master.addr, 6)
    profile: Dict[ObjectRef, Number] = {}
    if velocity is not None:
        profile[PROFILE_VELOCITY] = abs(velocity)
    else:
        raw = port.read(PROFILE_VELOCITY.index, 0)
        profile[PROFILE_VELOCITY] = master.drive_scaling().velocity_from_drive(raw)
    accel_scaling = master.scaling()
    for obj in (PROFILE_ACCELERATION, PROFILE_DECELERATION):
        if acceleration is not None:
            profile[obj] = acceleration
        else:
            profile[obj] = accel_scaling.acceleration_from_drive(port.read(obj.index, 0))
    return profile


def stored_profile(master: "AxisOps") -> Optional[Dict[ObjectRef, Number]]:
    """The master's profile from its stored 05 and 06 alone (no drive access, for a
    slave on another bus); None unless both are stored."""
    velocity = master.params.user(master.addr, 5)
    acceleration = master.params.user(master.addr, 6)
    if velocity is None or acceleration is None:
        return None
    return {PROFILE_VELOCITY: abs(velocity), PROFILE_ACCELERATION: acceleration,
            PROFILE_DECELERATION: acceleration}


def share_profile(master: "AxisOps", slaves: Sequence["AxisOps"]) -> None:
    """Write the master's profile into each slave, keeping the slave's own to give back."""
    profile = _profile_in_user_units(master)
    for slave in slaves:
        _write_profile(slave, profile)


def _write_profile(slave: "AxisOps", profile: Dict[ObjectRef, Number]) -> None:
    port = slave._port()
    scaling = slave.drive_scaling()
    writes: List[Tuple[ObjectRef, int]] = []
    for obj, user in profile.items():
        convert = (scaling.velocity_to_drive if obj == PROFILE_VELOCITY
                   else scaling.acceleration_to_drive)
        writes.append((obj, convert(user)))
    for obj, raw in writes:
        if obj not in slave.borrowed_profile:
            slave.borrowed_profile[obj] = port.read(obj.index, obj.subindex)
        port.write(obj.index, obj.subindex, raw)


def give_back_profile(ops: "AxisOps") -> None:
    """Before a slave moves on its own: its own profile values back into its drive."""
    port = ops._port()
    for obj, raw in list(ops.borrowed_profile.items()):
        port.write(obj.index, obj.subindex, raw)
        del ops.borrowed_profile[obj]


def halt_all(axes: Sequence["AxisOps"]) -> None:
    """Halt every axis, whatever the others answer; the first failure is raised last."""
    failure: Optional[BaseException] = None
    for ops in axes:
        try:
            ops._drive().halt()
        except (DeviceFailure, NodeSilent) as exc:
            failure = failure or exc
    if failure is not None:
        raise failure


__all__ = ["Follower", "check_move", "give_back_profile", "halt_all", "plan_move",
           "share_profile", "stored_profile"]
