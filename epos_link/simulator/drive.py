"""A CiA 402 servo drive model behind an :class:`~epos_link.simulator.od.ObjectStore`.

Pure: no clocks, threads or I/O. Time is a float the caller passes in
(``update(now)`` / ``advance(dt)``), or a callable given as ``clock`` that the
store calls before every SDO access (``time.monotonic`` for real time, a
:class:`VirtualClock` for tests and fast simulation).

This module holds time, resets and power-up; the rest of :class:`Drive` is
mixed in, for the size of the module only: the state machine, 6040h, 6060h
and faults from :mod:`~epos_link.simulator.statemachine`, what a client reads
from :mod:`~epos_link.simulator.observation`, set-points from
:mod:`~epos_link.simulator.setpoints`, the motion from
:mod:`~epos_link.simulator.kinematics` and
:mod:`~epos_link.simulator.monitors`.

What is modelled (CiA 402-2 V4.0 sections in brackets), in EPOS4 units
(:mod:`~epos_link.simulator.units`: increments, rpm, rpm/s):

* the power state machine with transitions 0..16 [6.4.1], see
  :mod:`epos_link.cia402`; the option codes [6.4.1.3]: 605Ah quick stop,
  605Bh shutdown (transition 8), 605Ch disable operation (transition 5),
  605Dh halt, 605Eh fault reaction. With option "slow down ramp" (605Bh/605Ch
  = 1) the drive ramps down on 6084h and only then makes the transition: the
  statusword shows OPERATION ENABLED until standstill [6.4.1];
* profile position mode 1 [6.7]: absolute/relative (cw bit 6), new set-point
  (bit 4) with the set-point acknowledge handshake (sw bit 12) and a one-entry
  buffer, change set immediately (bit 5), halt (bit 8), target reached (bit 10);
* profile velocity mode 3 [6.9]: 60FFh with 6083h/6084h ramps, bit 10 =
  velocity reached, bit 12 = speed is zero;
* homing mode 6 [6.6]: travels at the homing speeds to virtual switches
  (:mod:`~epos_link.simulator.homing`), statusword bits 13/12/10 as in the
  6.6 table; halt (bit 8) or a falling bit 4 interrupts it [6.6.1.1] (0/0/1
  at rest), a switch that is not fitted makes it fail (1/0/1 at rest);
* cyclic synchronous position mode 8 (csp): in OPERATION ENABLED a new 607Ah
  is the position demand at once, no bit 4 handshake, and halt is not
  evaluated (csp "uses no mode specific bits of the controlword", CiA 402-2
  csp "use of controlword and statusword", as drive manuals quote it, e.g.
  Parker SLVD-N 13.1.11.2, Nanotec N5 "Cyclic Synchronous Position");
  statusword bit 10 reserved (0), bit 12 "drive follows the command value",
  bit 13 following error. See :mod:`~epos_link.simulator.kinematics`;
* cyclic synchronous velocity mode 9 (csv): in OPERATION ENABLED 60FFh is the
  velocity demand at once (within 60C5h), halt not evaluated; statusword bit
  10 reserved (0), bit 12 "drive follows the command value", bit 13 reserved;
* trapezoidal profiles in closed form (:mod:`~epos_link.simulator.motion`),
  velocity 6081h <= 607Fh, 6080h, accelerations 6083h/6084h/6085h <= 60C5h,
  planned in :mod:`~epos_link.simulator.kinematics` (which ramp for which state);
* the monitors (:mod:`~epos_link.simulator.monitors`): 8A82h where a pv move
  passes 607Dh, the following error 8611h from 6065h/6066h, the position
  window 6067h/6068h for target reached; a blocked axis
  (:meth:`Drive.block_axis`) makes 6062h and 6064h differ;
* what matters for safety, in :attr:`Drive.safety`
  (:mod:`~epos_link.simulator.safety`): motion starts, power stage switched
  off while moving, resets while moving.

The axis and the counter: the motion profile runs in the frame of the
physical axis; 6064h is that position plus an offset. Homing sets the
offset (counter := 30B0h), a power cycle or NMT reset node sets it so the
incremental counter reads 0 again, while the axis stays (or coasts on).

Decisions a client may notice (**chosen** where the manuals are silent):

* With the power stage off (any state but OPERATION ENABLED, QUICK STOP
  ACTIVE and a powered fault reaction) the axis coasts to rest on
  :attr:`Drive.coast_deceleration` (rpm/s, default 2000): the drive cannot
  brake it. Shutdown with 605Bh = 0 (default) and disable voltage do that.
* 605Ah defaults to 6 (quick stop ramp 6085h, then stay in QUICK STOP ACTIVE),
  as maxon's EDS for firmware 0110h gives it (CiA 402's own default is 2).
  Option codes 3, 4, 7, 8 (current/voltage limit) behave like 2 and 6.
  605Bh = 0, 605Ch = 1, 605Dh = 1, 605Eh = 2 are the EPOS4 defaults as public
  EPOS4 configuration code quotes the Firmware Specification (6.2.97..6.2.100).
* While a 605Bh/605Ch ramp runs, new set-points are ignored, enable
  operation is ignored, and shutdown, disable voltage or quick stop replace
  the pending transition.
* Set-points, 607Dh clamps and relative targets: see
  :mod:`~epos_link.simulator.setpoints`.
* Releasing halt resumes the pp move to the pending target, and a pv move to
  60FFh: both count as motion starts.
* Statusword bit 4 (voltage enabled) is 1 while the power stage is on. Bit 9
  (remote) is ``Drive.remote``: False after power-up; the simulator sets it
  while NMT is Operational (guide Table 3-13, footnote 3). Bit 15 (maxon:
  position referenced to home) is set by a completed homing.
* Faults (:mod:`~epos_link.simulator.faults`) are one-shot: a fault reset
  always succeeds.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable

from canopen import SdoAbortedError

from ..cia402 import T_INITIALISED, State
from .clock import VirtualClock
from .faults import (
    BLOCK_COMMAND,
    FAULTS,
    POWER_CYCLE_COMMAND,
    RELEASE_COMMAND,
    SIMULATOR_COMMANDS,
    FaultSpec,
)
from .homing import HomingStatus, Leg, VirtualSwitches
from .data_recorder import DataRecorder
from .kinematics import Kinematics
from .motion import Profile, hold
from .objects import Mode, install_object_rules
from .observation import Observation
from .od import ABORT_RANGE, ObjectStore, Value, load_object_dictionary
from .safety import EventKind, SafetyLog
from .setpoints import SetPoints
from .statemachine import StateMachine

__all__ = ["FAULTS", "Drive", "FaultSpec", "Mode", "SIMULATOR_COMMANDS", "VirtualClock"]


class Drive(StateMachine, Observation, SetPoints, Kinematics):
    """The CiA 402 drive: state machine, modes and motion, served through ``store``.

    ``store`` defaults to a fresh store over the shipped EDS (node 1). With
    ``clock`` the drive catches up with ``clock()`` before every store access;
    without it, time moves only by ``update``/``advance``. ``self_test_time``
    delays transition 1 so NOT_READY_TO_SWITCH_ON can be observed.
    ``on_power_up(cause)`` is called after a power cycle or NMT reset node.
    """

    def __init__(self, store: ObjectStore | None = None, *,
                 clock: Callable[[], float] | None = None, start: float | None = None,
                 self_test_time: float = 0.0, switches: VirtualSwitches | None = None,
                 coast_deceleration: float = 2000.0) -> None:
        self.store = store if store is not None else ObjectStore(load_object_dictionary())
        self.clock = clock
        self.remote = False
        self.warning = False
        self.switches = switches if switches is not None else VirtualSwitches()
        self.coast_deceleration = float(coast_deceleration)  # rpm/s, power stage off
        self.safety = SafetyLog()
        self.on_power_up: Callable[[str], None] | None = None
        # (error code, 1001h) at every error event and fault reset (code 0): the EMCY
        # producer (CiA 301 7.2.7, guide 3.3.3.4: once per error event).
        self.on_error: Callable[[int, int], None] | None = None
        # (time, transition number, new state), newest last.
        self.history: deque[tuple[float, int, State]] = deque(maxlen=256)
        self._self_test_time = float(self_test_time)
        self._profile: Profile = hold(0.0, 0.0)
        self._in_event = False  # the run loop is raising a fault at an earlier instant
        self._blocked_at: float | None = None  # a blocked axis stands here (monitors.py)
        install_object_rules(self.store, self)
        # The EPOS4's own data recorder (31E0h-31E9h): sampled in the drive's time, below.
        self.recorder = DataRecorder(self.store, lambda: self._now)
        self._power_up(start if start is not None else (clock() if clock is not None else 0.0))
        if clock is not None:
            self.store.before_access = self.sync

    # -- time ------------------------------------------------------------------------

    @property
    def now(self) -> float:
        """Time of the last update."""
        return self._now

    def update(self, now: float | None = None) -> None:
        """Advance the model to ``now`` (default: ``clock()``). Earlier times are ignored."""
        if now is None:
            if self.clock is None:
                raise ValueError("update() needs a time when the drive has no clock")
            now = self.clock()
        if now < self._now:
            return
        # The data recorder samples at its own instants: the model stands at each in turn
        # (epos_link.simulator.data_recorder, "Time").
        for t in self.recorder.sample_times(now):
            if t > self._now:
                self._run_until(t)
                self._now = t
            self.recorder.take(t)
        self._run_until(now)
        self._now = now

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError("time cannot run backwards")
        self.update(self._now + dt)

    def sync(self) -> None:
        """Catch up with the clock, if there is one (the store's ``before_access``).

        Not while an event of the run loop is being handled: that event happens
        at its own instant, before the clock's.
        """
        if self.clock is not None and not self._in_event:
            self.update(self.clock())

    # -- resets ------------------------------------------------------------------------

    def power_cycle(self, now: float | None = None) -> None:
        """Power lost and back: saved parameters, counter 0, state machine from transition 0."""
        self._reset(EventKind.POWER_CYCLE, now)

    def reset_node(self, now: float | None = None) -> None:
        """NMT reset node: the same as a power cycle (guide Table 3-13), counted if moving."""
        self._reset(EventKind.NMT_RESET, now)

    def _reset(self, kind: EventKind, now: float | None) -> None:
        if now is not None:
            self.update(now)
        else:
            self.sync()
        v = self.velocity_increments
        self._record(kind, kind.value, v)
        if kind is EventKind.NMT_RESET and v != 0.0:
            self._record(EventKind.RESET_WHILE_MOVING, "NMT reset node", v)
        self.store.reset()
        self._power_up(self._now)
        if self.on_power_up is not None:
            self.on_power_up(kind.value)

    # -- commands ----------------------------------------------------------------------

    def write_controlword(self, controlword: int) -> None:
        """Checked write of 6040h through the store (same path as an SDO download)."""
        self.store.write_value(0x6040, 0, controlword)

    def set_mode(self, mode: int) -> None:
        """Checked write of 6060h through the store."""
        self.store.write_value(0x6060, 0, int(mode))

    def on_units_changed(self) -> None:
        """60A9h or the encoder changed: the running profile is re-planned in the new units."""
        if self._state is State.OPERATION_ENABLED:
            self._plan()

    def on_simulator_command(self, value: Value) -> None:
        kind = SIMULATOR_COMMANDS.get(value) if isinstance(value, int) else None
        if kind is None:
            raise SdoAbortedError(ABORT_RANGE)
        if kind == POWER_CYCLE_COMMAND:
            self.power_cycle()
        elif kind == BLOCK_COMMAND:
            self.block_axis()
        elif kind == RELEASE_COMMAND:
            self.release_axis()
        else:
            self.inject_fault(kind)

    # -- internals: power-up -------------------------------------------------------------

    def _power_up(self, t: float) -> None:
        self._now = float(t)
        self._offset = -self._physical()  # the incremental counter starts at 0
        self._cw = 0
        self._target: float | None = None  # pp target being approached (physical frame)
        self._buffer: float | None = None  # pp set-point waiting for the current move
        self._last_target: int | None = None  # base of relative set-points (counter frame)
        self._target_reached = False  # 0 after power-up until a first target is reached
        self._ack = False
        self._clamped = False
        self._homed = False
        self._homing_status = HomingStatus.IDLE
        self._legs: deque[Leg] = deque()
        self._following_error = False
        self._error_since: float | None = None  # following error above 6065h since (monitors.py)
        self._settle_at: float | None = None  # end of the 6068h position window time
        self._fault: FaultSpec | None = None
        self._powered_at_fault = False
        self._pending: tuple[int, State] | None = None  # transition waiting for a ramp
        self._goal = False  # heading for motion (for counting motion starts)
        self.remote = False  # NMT pre-operational after boot-up
        mode = self.store.get_int(0x6060)
        self._mode = Mode(mode) if mode in Mode._value2member_map_ else Mode.PROFILE_POSITION
        self._self_test_until = self._now + self._self_test_time
        self._state = State.NOT_READY_TO_SWITCH_ON
        self._transition(*T_INITIALISED)
        self._plan()
        self._run_until(self._now)

    def _demand(self) -> float:
        """The position demand (the profile), physical frame."""
        return self._profile.state_at(self._now)[0]

    def _physical(self) -> float:
        """The actual position, physical frame: the demand unless the axis is blocked."""
        return self._blocked_at if self._blocked_at is not None else self._demand()

    def _record(self, kind: EventKind, detail: str, velocity: float) -> None:
        self.safety.record(self._now, kind, detail, velocity)
