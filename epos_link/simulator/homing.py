"""Homing of the simulated EPOS4 (CiA 402-2 6.6), planned as legs of travel.

Pure. The simulator has no real switches, so each drive has
:class:`VirtualSwitches`, settable from Python (``drive.switches``): where its
limit switches, home switch, mechanical end stops and encoder index pulses
are, in increments of the physical axis. The physical axis is the frame of
the position counter at power-up; a homing or a power cycle moves the
counter, not the axis, so the switches stay where they are.

A homing is a list of :class:`Leg` s, each a profile position move at one
speed, all on the homing acceleration 609Ah:

1. the search: towards the switch or end stop at 6099h:01 "speed for switch
   search". A switch is passed and the axis stops on 609Ah beyond it (the
   deceleration starts at the switch); an end stop stops the axis at once.
2. the zero search, at 6099h:02 "speed for zero search": to the next index
   pulse away from the switch (methods with index), or back to the switch
   edge (methods without); methods 33/34 are this leg alone.
3. the home offset move 30B1h (if not 0), relative, at 6099h:01.

Then the position counter is set to 30B0h "home position" (EPOS4 Firmware
Specification 6.2.66/6.2.67, as quoted by public drivers: "the position that
will be set as zero position", "a moving distance in a homing procedure").
That the counter is set *after* the offset move is **chosen**.

Methods (6098h): exactly the sixteen maxon defines. maxon's EPOS Command
Library (Definitions.h, "Homing method" HM_* constants, as shipped with
public EPOS drivers) names 35 actual position, 17/18 negative/positive limit
switch, 1/2 the same and index, 23/27 home switch positive/negative speed,
7/11 the same and index, -3/-4 current threshold positive/negative speed,
-1/-2 the same and index, 34/33 index positive/negative speed; the EPOS4
adds 37 (actual position, CiA 402-2 V4). Any other value (the CiA 402-2
variants 3..6, 8..10, 12..14, 19..22, 24..26, 28..32) is refused with
06090030h like any value outside an object's range. The end stop stands in
for 30B2h "current threshold for homing mode" (-1..-4); 35 and 37 complete at
once without motion. Simplification, **chosen**: the home switch methods
approach the switch from the side the axis is on and search the index (or
edge) backwards.

A homing that fails: a limit or home switch set to ``None`` is not fitted.
The search for it then runs on to the end stop in its direction (for the
home switch methods the direction in the name: positive for 7 and 23,
negative for 11 and 27), where the axis stops and
the homing ends in error: statusword bit 13 "homing error", bit 10 = 1 once
the velocity is 0 (CiA 402-2 6.6, table of bits 13/12/10: 1 0 1 "homing
error occurred, velocity is 0"). **Chosen**: the drive raises no fault and
stays in OPERATION ENABLED (a real axis pushed against a stop would likely
also trip the following error 8611h; ``inject_fault`` models that).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

__all__ = ["HomingStatus", "Leg", "SUPPORTED_METHODS", "VirtualSwitches", "plan_homing"]

# maxon Definitions.h HM_*: CURRENT_THRESHOLD_POSITIVE_SPEED(_AND_INDEX) = -3 (-1),
# NEGATIVE -4 (-2); LIMIT_SWITCH 17/18, _AND_INDEX 1/2; HOME_SWITCH_POSITIVE_SPEED
# 23 (_AND_INDEX 7), NEGATIVE 27 (11); INDEX_POSITIVE/NEGATIVE_SPEED 34/33; 35.
CURRENT_THRESHOLD = frozenset({-1, -2, -3, -4})
LIMIT_SWITCH = frozenset({1, 2, 17, 18})
HOME_SWITCH = frozenset({7, 11, 23, 27})
INDEX_ONLY = frozenset({33, 34})
ACTUAL_POSITION = frozenset({35, 37})
SUPPORTED_METHODS = CURRENT_THRESHOLD | LIMIT_SWITCH | HOME_SWITCH | INDEX_ONLY | ACTUAL_POSITION
WITH_INDEX = frozenset({-1, -2, 1, 2, 7, 11}) | INDEX_ONLY


class HomingStatus(Enum):
    """Statusword bits 13/12/10 in homing mode (CiA 402-2 6.6, table of bits)."""

    IDLE = "interrupted or not started"  # 0 0 1
    RUNNING = "in progress"  # 0 0 0
    DONE = "completed"  # 0 1 1
    ERROR = "error"  # 1 0 (bit 10 = velocity is 0)


@dataclass
class VirtualSwitches:
    """Where the simulated axis meets its switches (increments, physical frame).

    Defaults are **chosen** for a 2000 increments/revolution encoder: limit
    switches at +-5 revolutions, the home switch half a revolution positive,
    end stops a further half revolution out, an index pulse every revolution
    at ``index_phase``. A switch set to ``None`` is not fitted: a homing that
    searches for it fails at the end stop.
    """

    negative_limit: float | None = -10_000.0  # None: not fitted
    positive_limit: float | None = 10_000.0
    home_switch: float | None = 1_000.0
    negative_stop: float = -11_000.0
    positive_stop: float = 11_000.0
    index_phase: float = 0.0

    def next_index(self, position: float, direction: int, increments_per_revolution: int) -> float:
        """The first index pulse strictly beyond ``position`` in ``direction`` (+1/-1)."""
        ipr = float(max(increments_per_revolution, 1))
        k = (position - self.index_phase) / ipr
        step = math.floor(k) + 1 if direction > 0 else math.ceil(k) - 1
        return self.index_phase + step * ipr


@dataclass(frozen=True)
class Leg:
    target: float  # increments, physical frame
    speed: float  # increments per second
    what: str
    fails: bool = False  # the homing ends in error when this leg ends (no switch found)


def plan_homing(method: int, position: float, switches: VirtualSwitches, *,
                increments_per_revolution: int, switch_speed: float, zero_speed: float,
                acceleration: float, offset_move: float) -> list[Leg]:
    """The legs of a homing from ``position``; [] for the methods without motion.

    Speeds in increments/s, acceleration in increments/s^2 (all > 0).
    """
    if method not in SUPPORTED_METHODS:
        raise ValueError(f"homing method {method} is not supported")
    if method in ACTUAL_POSITION:
        return []
    ipr = increments_per_revolution
    legs: list[Leg] = []
    if method in INDEX_ONLY:
        direction = 1 if method == 34 else -1
        legs.append(Leg(switches.next_index(position, direction, ipr), zero_speed, "index search"))
    else:
        direction, found, hard = _switch_of(method, position, switches)
        if found is None:  # the switch is not fitted: the search ends on the end stop
            stop = switches.positive_stop if direction > 0 else switches.negative_stop
            return [Leg(stop, switch_speed, "switch search (no switch found)", fails=True)]
        switch = found
        if hard:
            legs.append(Leg(switch, switch_speed, "end stop search"))
        else:
            overshoot = switch_speed * switch_speed / (2.0 * acceleration)
            legs.append(Leg(switch + direction * overshoot, switch_speed, "switch search"))
        if method in WITH_INDEX:
            target = switches.next_index(switch, -direction, ipr)
            legs.append(Leg(target, zero_speed, "index search"))
        elif not hard:
            legs.append(Leg(switch, zero_speed, "switch edge search"))
    if offset_move:
        legs.append(Leg(legs[-1].target + offset_move, switch_speed, "home offset move"))
    return legs


def _switch_of(method: int, position: float,
               sw: VirtualSwitches) -> tuple[int, float | None, bool]:
    """(search direction, switch position or None if not fitted, is it a hard end stop)."""
    if method in CURRENT_THRESHOLD:
        positive = method in (-1, -3)
        return (1, sw.positive_stop, True) if positive else (-1, sw.negative_stop, True)
    if method in LIMIT_SWITCH:
        positive = method in (2, 18)
        return (1, sw.positive_limit, False) if positive else (-1, sw.negative_limit, False)
    if sw.home_switch is None:
        # "positive speed" (7, 23) / "negative speed" (11, 27): the first search direction.
        return (1 if method in (7, 23) else -1), None, False
    direction = 1 if sw.home_switch >= position else -1
    return direction, sw.home_switch, False
