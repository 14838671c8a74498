"""What a simulated drive did that matters for safety: the observables of a test.

Pure and bounded. A :class:`~epos_link.simulator.drive.Drive` records here,
so a test can prove that an axis never moved when it should not have, and
moved exactly once when it should (issue 10):

``motion_starts`` (int)
    One per start of motion, counted when the drive accepts it:

    * each profile position set-point the drive acknowledges (sw bit 12),
      buffered ones included, even while an earlier move still runs;
    * each homing start (rising edge of cw bit 4 in mode 6);
    * each time the drive's goal goes from rest to motion without a new
      set-point: a profile velocity goal going from 0 to non-zero (60FFh
      written, halt released, operation enabled or mode 3 selected with
      60FFh != 0), or a halted pp move resuming when halt is released.

``unsafe_stops`` (bounded sequence of :class:`DriveEvent`)
    One per moment the power stage was switched off while the axis moved
    (shutdown with 605Bh = 0, disable voltage, quick stop option 0, fault
    reaction "disable drive function", STO, power loss). The axis then
    coasts: the drive cannot brake it.

``resets_while_moving`` (int)
    NMT reset node (or reset communication) received while the axis moved.

``events`` (bounded deque of :class:`DriveEvent`)
    All of the above, plus faults, resets and power cycles, oldest first.

These survive resets and power cycles of the simulated drive: they belong
to the test, not to the device. Velocities are in increments per second,
whatever 60A9h says.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

__all__ = ["DriveEvent", "EventKind", "SafetyLog"]

MAX_EVENTS = 1024
MAX_UNSAFE_STOPS = 256


class EventKind(Enum):
    MOTION_START = "motion start"
    UNSAFE_STOP = "power stage disabled while moving"
    RESET_WHILE_MOVING = "NMT reset while moving"
    NMT_RESET = "NMT reset"
    POWER_CYCLE = "power cycle"
    FAULT = "fault"


@dataclass(frozen=True)
class DriveEvent:
    time: float
    kind: EventKind
    detail: str
    velocity: float  # increments per second at that moment

    def __str__(self) -> str:
        return f"{self.time:.6f} {self.kind.value}: {self.detail} (v = {self.velocity:.1f} inc/s)"


class SafetyLog:
    """Counters and a bounded event log; see the module docstring."""

    def __init__(self) -> None:
        self.events: deque[DriveEvent] = deque(maxlen=MAX_EVENTS)
        self.unsafe_stops: deque[DriveEvent] = deque(maxlen=MAX_UNSAFE_STOPS)
        self.motion_starts = 0
        self.resets_while_moving = 0

    def record(self, time: float, kind: EventKind, detail: str, velocity: float) -> DriveEvent:
        event = DriveEvent(time, kind, detail, velocity)
        self.events.append(event)
        if kind is EventKind.MOTION_START:
            self.motion_starts += 1
        elif kind is EventKind.UNSAFE_STOP:
            self.unsafe_stops.append(event)
        elif kind is EventKind.RESET_WHILE_MOVING:
            self.resets_while_moving += 1
        return event

    def of_kind(self, kind: EventKind) -> list[DriveEvent]:
        return [e for e in self.events if e.kind is kind]
