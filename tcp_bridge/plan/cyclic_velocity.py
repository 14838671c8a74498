"""Velocity moves of internal axes in CSV (issue 26, PSI spec 3.2): S00=3 of a cyclic axis.

A cyclic axis (``cyclic = "csp"``) moves to positions in cyclic synchronous
position mode (:mod:`.cyclic_moves`); its velocity moves run in cyclic
synchronous velocity mode (CiA 402-2 mode 9, CSV), where the drive follows its
target velocity 60FFh as it comes. The bridge makes the ramp
(:class:`tcp_bridge.motion.profile.VelocityRamp`) and the bus's cyclic sender
sends its sample every cycle (CAN: RPDO4 remapped to 60FFh alone; EtherCAT:
60FFh in the outputs), never the controlword.

* The velocity is 05 (its sign the direction, as for a profile velocity
  move), its magnitude bounded by 26; the ramp's rate 06 bounded by 27; a
  stop's rate 28, else 06. No 05 or no acceleration is CAN. Converted with
  the axis's position factor and the drive's velocity unit (60A9h on an EPOS4),
  and inverted on an inverted axis, like S00=3 of any axis.
* On the bus worker, before the stream: the drive enabled and supervised, 60FFh
  mapped; a drive not yet in CSV gets 60FFh = 0 and then mode 9 (the mode
  change brings it to rest first, :meth:`tcp_bridge.motion.drive.Cia402.set_mode`),
  so entering CSV moves nothing; a drive already in CSV (a run that ended on a
  bus error holds its last set-point) starts the ramp from the 60FFh it holds.
  The ACK comes once the first set-points went out and the drive still shows
  OPERATION ENABLED.
* S00=8, S90=0, S04=0 ramp the set-point down to 0 at 28 (never a step); the
  run ends at 0 and the drive holds 0 in CSV. A position move (S00=1/2, S90)
  then switches back to mode 8 with 607Ah = the actual position.
* A new S00=3 while the axis is on a run is refused (stop it first), as a new
  line is (**chosen**: simplest; a changed 05 needs a stop and a new move).
* R82 of a velocity run is what it is for a profile velocity move of any
  axis (:mod:`tcp_bridge.plan.reads`: bit 10 "velocity reached" with bit 12
  "speed is zero"): 1 only once the run has ended and 606Ch is 0; 0 while the
  axis runs, even at 05 (:func:`tcp_bridge.plan.cyclic_moves.cyclic_target_reached`).
"""
from __future__ import annotations

import math
from typing import Callable

from ..cia402_words import MODES_DISPLAY, TARGET_VELOCITY, Deadline
from ..errors import DeviceFailure, InvalidCommand
from ..motion.cyclic import CSV_MODE
from ..motion.profile import VelocityRamp
from ..tables.units import Scaling
from .axis import AxisRuntime
from .cyclic_moves import left_the_line


def _velocity_factor(s: Scaling) -> float:
    """Drive velocity units (60FFh) per user unit/s: inc/s, or rpm with 60A9h's prefix."""
    ipr = s.units.increments_per_revolution
    if ipr is None:
        return float(s.factor)
    return s.factor * 60.0 / ipr / 10.0 ** s.units.velocity_exponent


def _magnitude(value: object) -> float:
    return abs(float(value)) if value is not None else 0.0  # type: ignore[arg-type]


def velocity_move(axis: AxisRuntime) -> Callable[[], None]:
    """The bus job of S00=3 on a cyclic axis (module doc); InvalidCommand now if unset."""
    velocity = axis.user(5)
    if velocity is None:
        raise InvalidCommand(f"axis {axis.addr}: no velocity (S05) set", cmd=0)
    speed, bound = _magnitude(velocity), _magnitude(axis.user(26))
    if bound:
        speed = min(speed, bound)
    accelerations = [_magnitude(axis.user(n)) for n in (6, 27)]
    acceleration = min([a for a in accelerations if a] or [0.0])
    if not acceleration:
        raise InvalidCommand(f"axis {axis.addr}: no acceleration (S06/S27) set for its "
                             "cyclic profile", cmd=0)
    stop = _magnitude(axis.user(28)) or acceleration
    signed = math.copysign(speed, float(velocity))
    axis.scaling().velocity_to_drive(signed)  # range checked now (CAN if out of range)
    sender = axis.cyclic
    assert sender is not None
    node = axis.config.node_id

    def run() -> None:
        drive, port = axis.need_drive(), axis.need_port()
        if sender.active(node) is not None:
            raise DeviceFailure(f"axis {axis.addr}: still on a cyclic move; stop it first")
        drive.require_enabled()
        drive.ensure_supervised()
        deadline = Deadline(drive._clock, drive.timing.ack_timeout)
        scaling = axis.with_units(axis.scaling())
        k = _velocity_factor(scaling)
        sender.transport.prepare_velocity(node)
        if port.read(MODES_DISPLAY, 0) == CSV_MODE:
            start = float(port.read(TARGET_VELOCITY, 0))  # the set-point it holds
        else:
            port.write(TARGET_VELOCITY, 0, 0)  # entering CSV holds still
            drive.set_mode(CSV_MODE, deadline)
            start = 0.0
        ramp = VelocityRamp(sender.clock() + sender.cycle, start, signed * k * scaling.inversion,
                            acceleration * k, stop * k)
        axis.moving_ack = 0
        sender.start((node,), ramp, max(deadline.time_left(), 10 * sender.cycle),
                     on_end=left_the_line([axis]))
        drive.require_enabled()  # the drive took the first set-points
        axis.moving_ack = 1
    return run


__all__ = ["velocity_move"]
