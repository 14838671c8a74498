"""One object per axis: everything the bridge knows about it (:class:`AxisRuntime`).

Its stored parameters (spec 3, through the :class:`ParameterStore`), the values
that requests resolved but not yet executed will store (:meth:`promise`: the
state that later requests are resolved against, issue 22 "arrival order"),
its units and identity, the values written to its drive this session (motion
rule 3), R86, the followers its running move started (29/30: a stop or
disable of a master acts on them), and the CiA 402 sequences of its drive
(:class:`~tcp_bridge.motion.Cia402`, which holds a halt owed after a move
whose outcome was unknown). Command plans (:mod:`.reads`, :mod:`.writes`,
:mod:`.moves`) read this state when a request is resolved, on the event loop,
and fix the values they use then; the bus thread only adds what the drive
itself tells (its velocity unit, its answers).
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any, Dict, Final, Optional, Tuple

from ..bus.health import NodeHealth
from ..bus.sdo import NodeSilent, SdoPort
from ..errors import DeviceFailure, InvalidCommand
from ..motion import Cia402, Timing
from ..motion.cyclic import CyclicSender
from ..tables.axes import AxisConfig, DeviceCode, from_stored, parameter_spec
from ..tables.commands import COMMANDS, ObjectRef, Quantity
from ..tables.parameters import ParameterStore
from ..tables.units import DriveUnits, Number, Scaling, velocity_exponent
from .tickets import Ticket

log = logging.getLogger("tcp_bridge.plan")

VELOCITY_UNIT: Final = ObjectRef(0x60A9)  # EPOS4: SI unit velocity
IDENTITY: Final = ObjectRef(0x1018, 1)  # CiA 301 7.5.2.21: identity object, vendor-ID
MAXON_VENDOR_ID: Final = 0x000000FB  # maxon motor ag (CiA vendor-ID list; maxon's EDS files)
_DEVICE_CODES: Final = {int(code): code for code in DeviceCode}


@dataclass(frozen=True)
class Follower:
    """A slave that makes its master's move: the axis and its direction (30)."""

    axis: "AxisRuntime"
    direction: int


class AxisRuntime:
    """The state of one axis, and its drive's sequences (module docstring)."""

    def __init__(self, config: AxisConfig, params: ParameterStore, port: Optional[SdoPort],
                 timing: Timing, **cia402_options: object) -> None:
        self.config = config
        self.addr = config.addr
        self.params = params
        self.port = port
        self.drive = Cia402(port, timing, **cia402_options) if port is not None else None  # type: ignore[arg-type]
        self._moving_ack = 0  # command 86 of an axis without a drive (the drive keeps it)
        self.velocity_exponent: Optional[int] = None  # EPOS4 60A9h prefix, once read
        self.unit_error: Optional[str] = None
        self.vendor_id: Optional[int] = None  # 1018h/1, read at start-up and after a reset
        self._scaling_memo: Optional[Tuple[Tuple[Any, ...], Scaling]] = None
        # Values resolved but not yet executed, by parameter: (ticket, stored value).
        self._pending: Dict[int, Tuple[Ticket, int]] = {}
        self._lock = threading.Lock()  # _pending: promised on the loop, kept on a bus thread
        # The axes the running move of this axis started (29/30), and the master
        # whose move this axis follows: a stop or disable of the master acts on them.
        self.followers: Tuple[Follower, ...] = ()
        self.leader: Optional["AxisRuntime"] = None
        # The axes of the profile line (90) this axis's move is on (tcp_bridge.plan.moves).
        self.line: Tuple["AxisRuntime", ...] = ()
        # Profile objects of a slave that followed its master's profile, with the
        # values to put back before it moves on its own (tcp_bridge.plan.moves).
        self.borrowed_profile: Dict[ObjectRef, int] = {}
        self.compare_parameters = True  # motion.Restore.ignore_differences
        if port is not None and self.drive is not None:
            self.drive.listeners.append(self._on_drive_event)
            self.drive.coasting = self._coasting
            # canopen backend with heartbeat_ms: the drive's heartbeat consumer (issue 23).
            self.drive.supervision = getattr(port.node, "supervision", None)
        nmt = getattr(getattr(port, "node", None), "nmt", None)
        if self.drive is not None and nmt is not None and hasattr(nmt, "add_heartbeat_callback"):
            drive = self.drive
            # CiA 301 7.2.8.3.2.4: a boot-up message is a heartbeat with state 0.
            nmt.add_heartbeat_callback(lambda state: drive.note_bootup() if state == 0 else None)

    def _on_drive_event(self, event: str) -> None:
        """motion.Cia402 listener: what a power cycle or reset makes stale."""
        self.velocity_exponent, self.unit_error = None, None  # 60A9h: read it again
        if event == "reset":  # the drive's RAM values are gone: nothing of ours is left
            self.written.clear()
            self.borrowed_profile.clear()
            self.vendor_id = None

    def _coasting(self) -> bool:
        """Whether the axis still turns (606Ch above 1 rpm on an EPOS4, not 0 elsewhere)."""
        raw = self.need_port().read(0x606C, 0)
        if self.device is DeviceCode.C_DC_MAXON_EPOS4 and self.velocity_exponent is not None:
            return abs(raw) > 10 ** -self.velocity_exponent
        return raw != 0

    @property
    def moving_ack(self) -> int:
        """Command 86: 1 once the drive accepted a move, kept by the drive that took it
        (:meth:`tcp_bridge.motion.Cia402.move`)."""
        return self.drive.moving_ack if self.drive is not None else self._moving_ack

    @moving_ack.setter
    def moving_ack(self, value: int) -> None:
        if self.drive is not None:
            self.drive.moving_ack = value
        else:
            self._moving_ack = value

    @property
    def written(self) -> Dict[ObjectRef, int]:
        """The last value the bridge wrote to each object of this drive (any command, 81
        included), kept by the port that wrote it: what a drive that kept its RAM
        values still holds (motion rule 3)."""
        return self.port.written if self.port is not None else {}

    @property
    def cyclic(self) -> Optional[CyclicSender]:
        """cyclic = "csp" (issue 26): the bus's set-point thread, which moves this axis.
        Asked of the node each time: a bus that could not be opened at start-up has none
        until its probes open it (tcp_bridge.backends.reopen.LateNode)."""
        if self.config.cyclic is None:
            return None
        return getattr(getattr(self.port, "node", None), "cyclic", None)

    @property
    def health(self) -> Optional[NodeHealth]:
        """This axis's node on its bus (fail-fast buses, :mod:`tcp_bridge.bus.health`):
        whether it is declared silent, why a request is refused now."""
        return self.port.health if self.port is not None else None

    # -- the state later requests see (arrival order) ------------------------------

    def value(self, cmd: int) -> Optional[int]:
        """Parameter ``cmd`` in stored form as every request resolved so far leaves it."""
        with self._lock:
            pending = self._pending.get(cmd)
        return pending[1] if pending is not None else self.params.get(self.addr, cmd)

    def values(self, cmds: Tuple[int, ...]) -> Tuple[Optional[int], ...]:
        """:meth:`value` of several parameters at one instant (the status poll's path)."""
        with self._lock:
            pending = {c: self._pending[c][1] for c in cmds if c in self._pending} \
                if self._pending else None
        base = self.params.values(self.addr, cmds)
        if not pending:
            return base
        return tuple(pending.get(c, b) for c, b in zip(cmds, base))

    def user(self, cmd: int) -> Optional[Number]:
        stored = self.value(cmd)
        if stored is None:
            return None
        return from_stored(COMMANDS[cmd], stored, self.config.position_factor)

    def promise(self, cmd: int, stored: int, ticket: Ticket) -> None:
        """A resolved write of ``cmd`` that its bus job will store (or not)."""
        with self._lock:
            self._pending[cmd] = (ticket, stored)

    def keep(self, cmd: int, ticket: Ticket, stored: Optional[int]) -> None:
        """The job of ``ticket`` ended: store ``stored`` (None: it failed)."""
        if stored is not None:
            self.params.set(self.addr, cmd, stored)
        with self._lock:
            if self._pending.get(cmd, (None, 0))[0] is ticket:
                del self._pending[cmd]

    def abandon(self, ticket: Ticket, failure: BaseException) -> None:
        """A promised write that never ran: later requests resolved against it fail."""
        with self._lock:
            for cmd, (t, _) in list(self._pending.items()):
                if t is ticket:
                    del self._pending[cmd]
        ticket.settle(failure)

    def tickets(self) -> Tuple[Ticket, ...]:
        """The writes not yet executed whose values a request resolved now would use."""
        with self._lock:
            return tuple(t for t, _ in self._pending.values())

    # -- units -------------------------------------------------------------------

    @property
    def device(self) -> DeviceCode:
        return _DEVICE_CODES.get(self.value(19), DeviceCode.C_DC_NOT_DEFINED)  # type: ignore[arg-type]

    def scaling(self) -> Scaling:
        """The axis's conversions as resolved now; for an EPOS4 with the velocity prefix
        last read (:meth:`with_units` completes it on the bus thread)."""
        # Built for every position poll: kept while 22, 25, 19 and the prefix stay.
        key = (*self.values((22, 25, 19)), self.velocity_exponent)
        memo = self._scaling_memo  # one tuple: the bus worker may replace it meanwhile
        if memo is not None and memo[0] == key:
            return memo[1]
        inversion, offset = key[0], self.user(25)
        scaling = Scaling(self.config.position_factor, -1 if inversion == -1 else 1,
                          float(offset) if offset is not None else 0.0)
        if self.device is DeviceCode.C_DC_MAXON_EPOS4:
            ipr = self.config.increments_per_revolution
            if ipr is None:
                raise InvalidCommand(f"axis {self.addr}: device 5 needs "
                                     "increments_per_revolution in the axis table")
            scaling = Scaling(scaling.factor, scaling.inversion, scaling.offset,
                              DriveUnits(ipr, self.velocity_exponent or 0))
        self._scaling_memo = (key, scaling)
        return scaling

    def with_units(self, scaling: Scaling, quantity: Quantity = Quantity.VELOCITY) -> Scaling:
        """``scaling`` (fixed when the request was resolved) with the drive's velocity
        unit, read from an EPOS4 the first time a velocity needs it (bus thread)."""
        if quantity is not Quantity.VELOCITY or scaling.units == DriveUnits():
            return scaling
        self._read_velocity_unit()
        if self.velocity_exponent == scaling.units.velocity_exponent:
            return scaling
        units = DriveUnits(scaling.units.increments_per_revolution, self.velocity_exponent or 0)
        return Scaling(scaling.factor, scaling.inversion, scaling.offset, units)

    def drive_scaling(self, quantity: Quantity = Quantity.VELOCITY) -> Scaling:
        """:meth:`scaling` now, with the drive's units (bus thread)."""
        return self.with_units(self.scaling(), quantity)

    def _read_velocity_unit(self) -> None:
        if self.velocity_exponent is not None:
            return
        if self.unit_error is None:
            raw = self.need_port().read(VELOCITY_UNIT.index, VELOCITY_UNIT.subindex)
            try:
                self.velocity_exponent = velocity_exponent(raw)
                log.info("axis %d: velocity unit 0x%08X (rpm x 10^%d)", self.addr, raw,
                         self.velocity_exponent)
                return
            except ValueError as exc:
                self.unit_error = f"axis {self.addr}: {exc}; velocity commands are refused"
                log.error("%s", self.unit_error)
        raise DeviceFailure(self.unit_error)

    def probe_units(self) -> None:
        """At start-up: read the identity (1018h/1), 60A9h (logged by
        :meth:`_read_velocity_unit`) and compare the main sensor resolution
        3000h/05h with the axis table; read-only."""
        port = self.need_port()
        self.read_identity()
        try:
            self._read_velocity_unit()
        except NodeSilent:
            raise
        except DeviceFailure:
            pass  # an unknown unit is logged; the axis's velocity commands answer NAK
        ipr = self.config.increments_per_revolution
        try:
            resolution = port.read(0x3000, 5)
        except NodeSilent:
            raise
        except DeviceFailure:
            return  # no such object: nothing to compare
        if ipr is not None and resolution != ipr:
            log.warning("axis %d: the drive's main sensor resolution (3000h/05h) is %d "
                        "increments per revolution, the axis table says %d "
                        "(increments_per_revolution): velocities would be wrong by %.3gx",
                        self.addr, resolution, ipr, resolution / ipr)

    def read_identity(self) -> Optional[int]:
        """The drive's vendor-ID (1018h/1), kept until a reset; None if it has none."""
        if self.vendor_id is None:
            try:
                self.vendor_id = self.need_port().read(IDENTITY.index, IDENTITY.subindex)
            except NodeSilent:
                raise
            except DeviceFailure:
                return None
        return self.vendor_id

    def is_maxon(self) -> bool:
        """Whether the drive told us it is a maxon drive (1018h/1 read at start-up)."""
        return self.vendor_id == MAXON_VENDOR_ID

    # -- access ------------------------------------------------------------------

    def need_port(self) -> SdoPort:
        if self.port is None:
            raise InvalidCommand(f"axis {self.addr} has no drive (internal axis, node 0)")
        return self.port

    def need_drive(self) -> Cia402:
        self.need_port()
        assert self.drive is not None
        return self.drive

    def parameter_object(self, cmd: int) -> Optional[ObjectRef]:
        """The SDO object behind parameter ``cmd`` on this device, None if internal only
        (26 is "only internal for Technosoft and Copley", 63 "only Nanotec")."""
        spec = parameter_spec(cmd)
        if cmd in BRIDGE_PROFILE and self.config.cyclic is not None:
            return None  # the bridge's own profile (issue 26): a CSP drive may lack them
        if cmd == 26 and self.device in _NOT_INTERNAL_26:
            return None
        if cmd == 63 and self.device is not DeviceCode.C_DC_NANOTEC:
            return None
        return spec.obj if self.port is not None else None

    def forget_followers(self) -> None:
        """This axis's move ended (a stop, a disable, a new move): it leads nobody."""
        for f in self.followers:
            if f.axis.leader is self:
                f.axis.leader = None
        self.followers = ()

    def lead(self, followers: Tuple[Follower, ...]) -> None:
        """A move of this axis started ``followers`` with it (and ends any line it was on)."""
        self.forget_followers()
        self.line = ()
        if self.leader is not None:  # moving on its own now: its old master no longer leads it
            leader = self.leader
            leader.followers = tuple(f for f in leader.followers if f.axis is not self)
            self.leader = None
        self.followers = followers
        for f in followers:
            if f.axis.leader is not None and f.axis.leader is not self:
                old = f.axis.leader
                old.followers = tuple(g for g in old.followers if g.axis is not f.axis)
            f.axis.leader = self


# 02 target, 05 velocity, 06 acceleration, 26-28 limits: kept by the bridge for a cyclic
# axis, whose profile it computes; never written to its drive (607Ah, 6081h, 6083h, 607Fh,
# 60C5h, 6085h). 02 too: in CSP 607Ah is the live set-point the stream owns, so after a
# first cyclic move an S02 written to the drive would be refused (plan.writes) or, in any
# other mode, be a value the next move never reads (it uses the bridge's 02).
BRIDGE_PROFILE: Final = frozenset({2, 5, 6, 26, 27, 28})
_NOT_INTERNAL_26: Final = {DeviceCode.C_DC_TECHNOSOFT_CAN, DeviceCode.C_DC_TECHNOSOFT_EC,
                           DeviceCode.C_DC_COBLEY_CAN}

__all__ = ["AxisRuntime", "Follower", "IDENTITY", "MAXON_VENDOR_ID", "VELOCITY_UNIT"]
