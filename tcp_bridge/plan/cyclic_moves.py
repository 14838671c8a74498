"""Moves of internal axes in CSP (issue 26, PSI spec 3.2 and command 90): what each
drive is told, fixed when the request is resolved; the stream is :mod:`tcp_bridge.motion.cyclic`.

* 90=1 LINR: every internal axis by its own 02, relative to where it stands;
  90=2 LINA: every internal axis to user position 0; both on one straight
  line (:func:`tcp_bridge.motion.profile.plan_line`), starting and arriving
  together. S00=1/2 of one cyclic axis is a line of that axis alone.
* Limits, in user units and converted with the axis's position factor: the
  velocity is 05, bounded by 26 (either alone if only one is set); the
  acceleration 06, bounded by 27; a stop's deceleration 28, else the
  acceleration. No velocity or no acceleration is CAN (nothing to move with).
  These values are kept by the bridge, never written to the drive
  (:data:`tcp_bridge.plan.axis.BRIDGE_PROFILE`).
* 90=0, S00=8 and S04=0 stop the line the axis is on (all its axes together,
  staying on the line: :mod:`tcp_bridge.motion.profile`, chosen).
* On the bus worker, before the stream: every axis enabled and supervised
  (heartbeat consumer), its RPDO mapped, 607Ah written with its actual
  position 6064h, then mode 8 (so that entering CSP moves nothing), then the
  run, whose first set-point is that same position. The ACK comes once the
  first set-points went out and every drive still shows OPERATION ENABLED.
* R82 of a cyclic axis: its latest run has ended and the actual position
  6064h is within the position window 6067h of the run's target (a drive in
  CSP need not set statusword bit 10); after a velocity run, 606Ch is 0.

Velocity moves (S00=3) of a cyclic axis run in CSV: :mod:`.cyclic_velocity`.
"""
from __future__ import annotations

import logging
from typing import Callable, List, Optional, Sequence, Tuple

from epos_link.cia402 import State

from ..cia402_words import MODES_DISPLAY, Cw, Deadline
from ..bus.sdo import NodeSilent
from ..errors import DeviceFailure, InvalidCommand
from ..motion.cyclic import CSP_MODE, CyclicSender
from ..motion.profile import AxisLimits, VelocityRamp, plan_line
from ..tables.axes import DEFAULT_POSITION_WINDOW
from .axis import AxisRuntime

log = logging.getLogger("tcp_bridge.plan")

POSITION_ACTUAL = 0x6064
TARGET_POSITION = 0x607A
POSITION_WINDOW = 0x6067
VELOCITY_ACTUAL = 0x606C

Target = Callable[[int], int]  # drive position where the axis stands -> its target


def _bounded(value: Optional[float], bound: Optional[float]) -> Optional[float]:
    values = [abs(v) for v in (value, bound) if v is not None and v != 0]
    return min(values) if values else None


def limits(axis: AxisRuntime) -> AxisLimits:
    """The axis's profile limits in increments (module doc); InvalidCommand without."""
    factor = axis.config.position_factor
    velocity = _bounded(axis.user(5), axis.user(26))
    acceleration = _bounded(axis.user(6), axis.user(27))
    if velocity is None or acceleration is None:
        raise InvalidCommand(f"axis {axis.addr}: no velocity (S05/S26) or acceleration "
                             "(S06/S27) set for its cyclic profile")
    stop = _bounded(axis.user(28), None) or acceleration
    return AxisLimits(velocity * factor, acceleration * factor, stop * factor)


def sender_of(axes: Sequence[AxisRuntime]) -> CyclicSender:
    sender = axes[0].cyclic
    assert sender is not None and all(a.cyclic is sender for a in axes)
    return sender


def relative_target(axis: AxisRuntime, user: Optional[float]) -> Target:
    if user is None:
        raise InvalidCommand(f"axis {axis.addr}: no target position (S02) set")
    scaling = axis.scaling()
    distance = scaling.to_drive(user) * scaling.inversion  # a distance: never offset
    return lambda here: here + distance


def absolute_target(axis: AxisRuntime, user: Optional[float]) -> Target:
    if user is None:
        raise InvalidCommand(f"axis {axis.addr}: no target position (S02) set")
    raw = axis.scaling().position_to_drive(user)
    return lambda here: raw


def line_move(axes: Sequence[AxisRuntime], targets: Sequence[Target]) -> Callable[[], None]:
    """The bus job that moves ``axes`` on one line to ``targets`` (module doc)."""
    fixed = [limits(a) for a in axes]  # resolved now: later S05/S06 do not change it
    sender = sender_of(axes)

    def run() -> None:
        drives = [a.need_drive() for a in axes]
        for axis in axes:
            if sender.active(axis.config.node_id) is not None:
                raise DeviceFailure(f"axis {axis.addr}: still on a cyclic move; stop it first")
        for drive in drives:
            drive.require_enabled()
            drive.ensure_supervised()
        deadline = Deadline(drives[0]._clock, drives[0].timing.ack_timeout)
        starts: List[int] = []
        for axis, drive in zip(axes, drives):
            port = axis.need_port()
            sender.transport.prepare(axis.config.node_id)
            here = port.read(POSITION_ACTUAL, 0)
            port.write(TARGET_POSITION, 0, here)  # entering CSP holds where it stands
            if port.read(MODES_DISPLAY, 0) != CSP_MODE:
                drive.set_mode(CSP_MODE, deadline)
            starts.append(here)
        ends = [target(here) for target, here in zip(targets, starts)]
        for drive, end in zip(drives, ends):
            drive._within_limits(end)  # 607Dh: never sent beyond it (motion.start)
        for axis in axes:
            axis.moving_ack = 0
        line = plan_line(starts, ends, fixed, sender.clock() + sender.cycle)
        nodes = tuple(a.config.node_id for a in axes)
        sender.start(nodes, line, max(deadline.time_left(), 10 * sender.cycle),
                     on_end=left_the_line(axes))
        for drive in drives:
            drive.require_enabled()  # the drive took the first set-points
        for axis in axes:
            axis.moving_ack = 1
    return run


def left_the_line(axes: Sequence[AxisRuntime]) -> Callable[[int, str], None]:
    """What a run records when one of its drives leaves OPERATION ENABLED or is lost
    (:class:`~tcp_bridge.motion.cyclic.CyclicSender`, "a line is one motion"): that
    axis's R86 becomes 0 (its move was not made; the others' moves were accepted and
    are ramped down as by a stop), and the log names the axis (issue 30 finding 2)."""
    by_node = {a.config.node_id: a for a in axes}
    left: List[AxisRuntime] = []  # the axes that left, in order: the first ended the line

    def ended(node: int, why: str) -> None:
        axis = by_node.get(node)
        if axis is None:
            return
        axis.moving_ack = 0
        if left:  # a second drive out of the same line (both slaves lost in a stall)
            log.error("axis %d left its cyclic move too (%s); its move was not made", axis.addr,
                      why)
        else:
            others = [a.addr for a in axes if a is not axis]
            log.error("axis %d left its cyclic move (%s)%s", axis.addr, why,
                      f"; axes {others} on its line ramp down at 28" if others else "")
        left.append(axis)
    return ended


def stop_cyclic(axis: AxisRuntime) -> bool:
    """S00=8, S90=0, S04=0: the axis's line ramps down; False if it was not on one."""
    if axis.cyclic is None:
        return False
    return bool(axis.cyclic.stop([axis.config.node_id]))


def wait_stopped(axis: AxisRuntime, timeout: float) -> None:
    """Before a disable: the axis's stop ramp has ended (nothing streams to it)."""
    if axis.cyclic is None:
        return
    run = axis.cyclic.active(axis.config.node_id)
    if run is None:
        return
    wait = max(0.0, run.line.end_time - axis.cyclic.clock()) + timeout
    if not run.ended.wait(wait):
        raise DeviceFailure(f"axis {axis.addr}: its cyclic stop ramp did not end within "
                            f"{wait:g} s; the axis stays enabled")


def install_rest(axis: AxisRuntime) -> None:
    """How a cyclic axis comes to rest before a disable, reset or mode change (motion
    rule 1): its line's stop ramp, then halt set and velocity 606Ch zero."""
    drive, port = axis.drive, axis.port
    if axis.config.cyclic is None or drive is None or port is None:
        return  # (its sender may come later: a bus opened after start-up)

    def rest(deadline: Deadline) -> None:
        stop_cyclic(axis)
        wait_stopped(axis, deadline.time_left())
        state = drive.state()
        if state is State.OPERATION_ENABLED:  # a quick stop is never undone
            drive.write_while_enabled(Cw.ENABLE_OPERATION | Cw.HALT, state)  # rule 2: halted
        while port.read(VELOCITY_ACTUAL, 0) != 0:
            if deadline.expired():
                raise DeviceFailure(f"{port.name}: still moving (606Ch) after its cyclic stop "
                                    "ramp; the axis stays enabled")
            drive._sleep(max(drive.timing.poll_interval, 0.005))
    drive.rest = rest


def cyclic_target_reached(axis: AxisRuntime) -> Callable[[], int]:
    """R82 of a cyclic axis (module doc)."""
    port = axis.need_port()
    sender = axis.cyclic
    assert sender is not None

    def read() -> int:
        run = sender.last(axis.config.node_id)
        if run is None:
            return 0  # never moved by the bridge: no target of ours to be in
        if not run.ended.is_set():
            return 0
        if isinstance(run.line, VelocityRamp):  # CSV: at rest, as R82 of a pv move
            return int(port.read(VELOCITY_ACTUAL, 0) == 0)
        index = run.nodes.index(axis.config.node_id)
        target = round(run.line.targets[index])
        return int(abs(port.read(POSITION_ACTUAL, 0) - target) <= position_window(axis))
    return read


def position_window(axis: AxisRuntime) -> int:
    """6067h, or the axis table's position_window when the drive has none (CiA 402-2
    leaves 6067h optional for CSP; issue 31): the object's absence (SDO abort 06020000h
    "object does not exist") is not a failure of R82."""
    try:
        return int(axis.need_port().read(POSITION_WINDOW, 0))
    except NodeSilent:
        raise
    except DeviceFailure as exc:
        if exc.code not in (0x06020000, 0x06090011):
            raise
    window = axis.config.position_window
    return DEFAULT_POSITION_WINDOW if window is None else window



def plan_cyclic_line(internal: Sequence[AxisRuntime], how: int) -> Tuple[AxisRuntime,
                                                                        Callable[[], None]]:
    """90=1 / 90=2 of cyclic internal axes: the first axis (whose bus runs it) and the job."""
    if how == 1:
        targets = [relative_target(a, a.user(2)) for a in internal]
    else:
        targets = [absolute_target(a, 0.0) for a in internal]
    for axis in internal:
        axis.lead(())
    return internal[0], line_move(internal, targets)


__all__ = ["absolute_target", "cyclic_target_reached", "install_rest", "left_the_line",
           "limits", "line_move",
           "plan_cyclic_line", "relative_target", "stop_cyclic", "wait_stopped"]
