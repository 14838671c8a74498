"""00 Move and 90 Combined Move, with the slaves that follow (29/30), and what a stop or
disable of a master does to them; this module works out *what* each drive is told,
in drive units, when the request is resolved. *How* a move starts, and the safety
rules around it, are :meth:`tcp_bridge.motion.Cia402.move` and
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
* homing (00=9): each axis homes with its own method and speeds (40-43);
* stop (00=8) and disable (04=0) of the master act on the slaves its move
  started (:attr:`AxisRuntime.followers`), whatever 29 says by then: they are
  halted (a disable halts them and leaves them enabled; only the master was
  asked to lose power).

Every value (targets, velocities, the slaves and their directions) is taken
from the state the earlier requests left, when the request is resolved, so a
write that arrives later (S02, S22, S29 from another port) cannot change a
move already accepted. A master and a slave on the same bus move in one bus
job, started back to back; a slave on another bus is a companion job of the
engine, gated on the master's acceptance (:mod:`.job`).
"""
from __future__ import annotations

import logging
from functools import partial
from dataclasses import dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from ..bus.sdo import NodeSilent
from ..errors import DeviceFailure, InvalidCommand
from ..motion import HomingMove, Move, PositionMove, VelocityMove
from ..motion.together import Together
from ..tables.commands import COMMANDS, ObjectRef
from ..tables.units import Number, Scaling
from .axis import AxisRuntime, Follower
from .cyclic_moves import (absolute_target, line_move, plan_cyclic_line, relative_target,
                           stop_cyclic)
from .cyclic_velocity import velocity_move
from .writes import check_resolution, refuse_cyclic_coupling

log = logging.getLogger("tcp_bridge.plan")

PROFILE_VELOCITY = ObjectRef(0x6081)
PROFILE_ACCELERATION = ObjectRef(0x6083)
PROFILE_DECELERATION = ObjectRef(0x6084)
Profile = Dict[ObjectRef, Number]


@dataclass(frozen=True)
class Part:
    """One axis's share of a move on another bus: what it runs, and its halt."""

    axis: AxisRuntime
    run: Callable[[], None]
    halt: Optional[Callable[[], None]]


@dataclass(frozen=True)
class MovePlan:
    """A move (or stop) of the request's axis, and its companions on other buses."""

    run: Callable[[], None]
    companions: Tuple[Part, ...] = ()
    halt: Optional[Callable[[], None]] = None  # halts what ``run`` started
    stopping: bool = False  # a stop: never gated, every axis is tried (urgent)


def _what(axis: AxisRuntime, how: int, direction: int,
          value: Optional[Number]) -> Callable[[], Move]:
    """The move of ``axis`` in drive units, checked now, built on the bus thread
    (a velocity needs the drive's unit, which an EPOS4 tells the first time)."""
    scaling = axis.scaling()
    if how in (1, 2):
        if value is None:
            raise InvalidCommand(f"axis {axis.addr}: no target position (S02) set", cmd=0)
        user = value * direction
        if how == 1:
            raw = scaling.position_to_drive(user)
        else:  # a distance: inverted and scaled, never offset
            raw = scaling.to_drive(user) * scaling.inversion
        move = PositionMove(raw, relative=how == 2)
        return lambda: move
    if how == 3:
        if value is None:
            raise InvalidCommand(f"axis {axis.addr}: no velocity (S05) set", cmd=0)
        velocity = value

        def build(s: Scaling) -> VelocityMove:
            raw = s.velocity_to_drive(velocity * direction) * s.inversion
            check_resolution(axis.addr, COMMANDS[5], velocity, raw, s)
            return VelocityMove(raw)
        build(scaling)  # range and resolution checked now
        return lambda: build(axis.with_units(scaling))
    return lambda: HomingMove()


def _value(axis: AxisRuntime, how: int) -> Optional[Number]:
    return axis.user(2) if how in (1, 2) else axis.user(5) if how == 3 else None


def _slave(master: AxisRuntime, axes: Mapping[int, AxisRuntime]) -> Optional[Follower]:
    slave = axes.get(master.value(29) or 0)
    if slave is None or slave is master or slave.port is None:
        return None
    return Follower(slave, -1 if master.value(30) == -1 else 1)


def halt_all(axes: Sequence[AxisRuntime]) -> None:
    """Halt every axis, whatever the others answer; the first failure is raised last."""
    failure: Optional[BaseException] = None
    for axis in axes:
        try:
            if stop_cyclic(axis):  # a CSP line ramps down on its profile (issue 26)
                continue
            axis.need_drive().halt()
        except (DeviceFailure, NodeSilent) as exc:
            failure = failure or exc
    if failure is not None:
        raise failure


def _halt(axis: AxisRuntime) -> Optional[Callable[[], None]]:
    return (lambda: halt_all([axis])) if axis.drive is not None else None


def line_of(axis: AxisRuntime) -> List[AxisRuntime]:
    """The axes that move as one motion with ``axis`` by the requests so far (arrival
    order): its followers, its leader, the other axes of its profile line (90). A stop
    of one of them is a stop of that motion (issue 30, :mod:`tcp_bridge.motion.together`)."""
    others = [f.axis for f in axis.followers]
    if axis.leader is not None:
        others.append(axis.leader)
    others += [a for a in axis.line if axis in a.line]  # still on the same line
    return [a for a in dict.fromkeys(others) if a is not axis]


def _end_line(axis: AxisRuntime, why: str) -> None:
    drive = axis.need_drive()
    together = drive.together
    if together is not None:
        together.end(drive, why, by_client=True)


def plan_stop(master: AxisRuntime, then: Optional[Callable[[], None]] = None,
              why: str = "S00=8") -> MovePlan:
    """00=8 (``then`` None) or 04=0 (``then`` the disable): the master, the followers
    its move started and the other axes of its line (a profile line or master/slave
    move, :func:`line_of`: a stop of one of them is a stop of the motion) are halted;
    those on its bus in its own job, first."""
    master.need_drive()
    others = line_of(master)
    for axis in (master, *others):  # the motion ends here: it leads nobody now
        axis.line = ()
        axis.forget_followers()
    near = [a for a in others if a.config.bus == master.config.bus]
    far = tuple(Part(a, partial(halt_all, [a]), None)
                for a in others if a.config.bus != master.config.bus)
    reason = f"stopped by a client's {why} of axis {master.addr}"
    if then is None:
        def halt() -> None:
            _end_line(master, reason)
            halt_all([master, *near])
        return MovePlan(halt, far, stopping=True)
    disable = then

    def halt_then_disable() -> None:
        _end_line(master, reason)
        if near:
            halt_all(near)
        disable()
    return MovePlan(halt_then_disable, far, stopping=True)


def plan_move(master: AxisRuntime, how: int, axes: Mapping[int, AxisRuntime]) -> MovePlan:
    """00 Move: 1 absolute, 2 relative, 3 velocity, 8 stop, 9 home."""
    master.need_drive()  # CAN for an axis without a drive
    if how == 8:
        return plan_stop(master)
    slave = _slave(master, axes)
    if slave is not None:  # a 29 from before the axis was cyclic (the state file)
        refuse_cyclic_coupling(master.addr, slave.axis.addr, master.params.table.axes)
    if master.cyclic is not None:
        return _plan_cyclic_move(master, how)
    value = _value(master, how)
    master_move = _what(master, how, 1, value)
    followers = (slave,) if slave is not None else ()
    moves: List[Tuple[AxisRuntime, Callable[[], Move]]] = [(master, master_move)]
    companions: Tuple[Part, ...] = ()
    near: List[AxisRuntime] = []
    if slave is not None:
        slave.axis.need_drive()
        slave_move = _what(slave.axis, how, slave.direction, value)
        if slave.axis.config.bus == master.config.bus:
            moves.append((slave.axis, slave_move))
            near.append(slave.axis)
        else:
            profile = stored_profile(master)
    # Master and slave are one motion (issue 30): either leaving it halts the other.
    together = Together([master.need_drive(), slave.axis.need_drive()],
                        ends_at_target=how != 3) if slave is not None else None
    if slave is not None and slave.axis.config.bus != master.config.bus:
        companions = (Part(slave.axis, _single(slave.axis, slave_move, profile, together),
                           _halt(slave.axis)),)
    master_profile_user = (master.user(5), master.user(6))
    master.lead(followers)

    def move() -> None:
        if near:
            share_profile(master, near, master_profile_user)
        elif master.borrowed_profile:
            give_back_profile(master)
        _start(moves, together)
    return MovePlan(move, companions, _halt_near(master, near))


def _halt_near(master: AxisRuntime, near: Sequence[AxisRuntime]) -> Callable[[], None]:
    axes = [master, *near]
    return lambda: halt_all(axes)


def _single(axis: AxisRuntime, what: Callable[[], Move], profile: Optional[Profile],
            together: Optional[Together] = None) -> Callable[[], None]:
    """A companion's move: with its master's profile (a slave) or its own."""
    def move() -> None:
        if profile is not None:
            _write_profile(axis, profile)
        elif axis.borrowed_profile:
            give_back_profile(axis)
        _start([(axis, what)], together)
    return move


def _start(moves: Sequence[Tuple[AxisRuntime, Callable[[], Move]]],
           together: Optional[Together] = None) -> None:
    """The drives start the moves and keep R86 (:meth:`tcp_bridge.motion.Cia402.move`)."""
    pairs = [(axis.need_drive(), what()) for axis, what in moves]
    pairs[0][0].move(pairs, together)


def _plan_cyclic_move(axis: AxisRuntime, how: int) -> MovePlan:
    """S00=1/2 of an axis in CSP: a line of that axis alone (:mod:`.cyclic_moves`);
    S00=3 a velocity ramp in CSV (:mod:`.cyclic_velocity`)."""
    if how == 3:
        run = velocity_move(axis)
        axis.lead(())
        return MovePlan(run, halt=lambda: halt_all([axis]))
    if how not in (1, 2):
        raise InvalidCommand(f"axis {axis.addr}: S00={how} is not available in cyclic "
                             f"mode {axis.config.cyclic!r} (only 1, 2, 3 and 8)", cmd=0)
    target = (absolute_target if how == 1 else relative_target)(axis, axis.user(2))
    axis.lead(())
    return MovePlan(line_move([axis], [target]), halt=lambda: halt_all([axis]))


def plan_combined(internal: Sequence[AxisRuntime], how: int) -> MovePlan:
    """Spec 90 with 3.2: 0 stop, 1 LINR (relative by each 02), 2 LINA to zero.

    Internal axes in CSP (issue 26) move on one line through the bus's cyclic
    thread, as one job of the first axis's bus (:mod:`.cyclic_moves`); 0 stops
    that line. Others are each given their own profile position move."""
    if internal and internal[0].cyclic is not None:
        if how == 0:
            first = internal[0]
            return MovePlan(lambda: None, (Part(first, partial(halt_all, list(internal)),
                                                None),), stopping=True)
        first, run = plan_cyclic_line(internal, how)
        return MovePlan(lambda: None,
                        (Part(first, run, partial(halt_all, list(internal))),))
    parts = []
    # The axes of a line in their own profile modes are one motion (issue 30).
    together = Together([a.need_drive() for a in internal]) \
        if how != 0 and len(internal) > 1 else None
    for axis in internal:
        if how == 0:
            parts.append(Part(axis, partial(_stop_line_axis, axis), None))
            continue
        what = _what(axis, 2, 1, axis.user(2)) if how == 1 else _what(axis, 1, 1, 0.0)
        axis.lead(())
        axis.line = tuple(internal) if together is not None else ()
        parts.append(Part(axis, _single(axis, what, None, together), _halt(axis)))
    return MovePlan(lambda: None, tuple(parts), stopping=how == 0)


def _stop_line_axis(axis: AxisRuntime) -> None:
    """90=0 of one axis of a profile line: its line is ended by a client (logged)."""
    _end_line(axis, "stopped by a client's 90=0")
    halt_all([axis])


def stored_profile(master: AxisRuntime) -> Optional[Profile]:
    """The master's profile from its 05 and 06 alone (no drive access, for a slave on
    another bus); None unless both are set."""
    velocity, acceleration = master.user(5), master.user(6)
    if velocity is None or acceleration is None:
        return None
    return {PROFILE_VELOCITY: abs(velocity), PROFILE_ACCELERATION: acceleration,
            PROFILE_DECELERATION: acceleration}


def share_profile(master: AxisRuntime, slaves: Sequence[AxisRuntime],
                  user: Tuple[Optional[Number], Optional[Number]]) -> None:
    """Write the master's profile (``user``: its 05 and 06 when the move was resolved,
    else its drive's values) into each slave, keeping the slave's own to give back."""
    port = master.need_port()
    velocity, acceleration = user
    profile: Profile = {}
    if velocity is not None:
        profile[PROFILE_VELOCITY] = abs(velocity)
    else:
        raw = port.read(PROFILE_VELOCITY.index, 0)
        profile[PROFILE_VELOCITY] = master.drive_scaling().velocity_from_drive(raw)
    for obj in (PROFILE_ACCELERATION, PROFILE_DECELERATION):
        if acceleration is not None:
            profile[obj] = acceleration
        else:
            profile[obj] = master.scaling().acceleration_from_drive(port.read(obj.index, 0))
    for slave in slaves:
        _write_profile(slave, profile)


def _write_profile(slave: AxisRuntime, profile: Profile) -> None:
    port = slave.need_port()
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


def give_back_profile(axis: AxisRuntime) -> None:
    """Before a slave moves on its own: its own profile values back into its drive."""
    port = axis.need_port()
    for obj, raw in list(axis.borrowed_profile.items()):
        port.write(obj.index, obj.subindex, raw)
        del axis.borrowed_profile[obj]


__all__ = ["MovePlan", "Part", "give_back_profile", "halt_all", "line_of", "plan_combined",
           "plan_move",
           "plan_stop", "share_profile", "stored_profile"]
