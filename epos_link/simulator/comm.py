"""A simulated drive's CAN communication objects besides SDO and TPDO: RPDO, EMCY, heartbeat.

:class:`DriveComm` joins :mod:`~epos_link.simulator.rpdo`,
:mod:`~epos_link.simulator.emcy` and :mod:`~epos_link.simulator.heartbeat` to one
:class:`~epos_link.simulator.core.SimulatedDrive`: its NMT state, its bus
connection and its lock. Frames reach it from the simulator's one listener on
the bus (:meth:`on_frame`, python-can's notifier thread); time from the
simulator's :class:`~epos_link.simulator.heartbeat.HeartbeatTicker`
(:meth:`tick`).

NMT (guide Table 3-13): RPDOs only in Operational; EMCY in Pre-Operational and
Operational; heartbeats sent in Pre-Operational, Operational and Stopped, and
consumed in those states too; nothing while initialising.

A lost heartbeat (CiA 301 7.2.8.3.2.2) raises "CAN heartbeat error" 8130h
(:data:`epos_link.codes.DEVICE_ERRORS`) and the drive reacts as 6007h "abort
connection option code" says (CiA 402-2 6007h; default 3, maxon's EDS):

* 1 "fault signal": :meth:`Drive.inject_fault` ``"heartbeat"`` (603Fh, 1001h,
  1003h, FAULT through the 605Eh fault reaction; its EMCY comes from there);
* 0 "no action", 2 "disable voltage", 3 "quick stop": EMCY 8130h with 1001h
  plus bits 0 and 4 (generic, communication), then the device control command
  (:meth:`Drive.device_control`): quick stop ramps down on 6085h into QUICK
  STOP ACTIVE and on as 605Ah says. **chosen**: without a fault the error is
  not stored in 603Fh, 1001h or 1003h, our sources do not say it is;
* **chosen**: the NMT state does not change. CiA 301's error behaviour object
  1029h (pre-operational on a communication error) is not in maxon's EPOS4
  EDS.

The drives share one connection to the bus, and python-can does not hand a
connection its own frames: a heartbeat or TPDO of one simulated drive does not
reach another simulated drive's consumer or RPDO (a limitation; frames from
any other program on the channel do).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable, Dict, Final

import can

from ..cia402 import Command
from .emcy import COMMUNICATION_ERROR, ERROR_REGISTER, GENERIC_ERROR, emcy_frame
from .heartbeat import HEARTBEAT_BASE, Heartbeats
from .nmt import NmtState
from .rpdo import ReceivePdos

if TYPE_CHECKING:
    from .core import SimulatedDrive

__all__ = ["ABORT_CONNECTION", "DriveComm", "EMCY_HEARTBEAT", "FrameListener"]

ABORT_CONNECTION: Final = 0x6007
EMCY_HEARTBEAT: Final = 0x8130  # EPOS4 "CAN heartbeat error"
_EMCY_STATES: Final = frozenset({NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL})
_HEARTBEAT_STATES: Final = frozenset({NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL,
                                      NmtState.STOPPED})
_COMMANDS: Final = {2: Command.DISABLE_VOLTAGE, 3: Command.QUICK_STOP}


class DriveComm:
    """RPDO, EMCY and heartbeat of one simulated drive."""

    def __init__(self, sim: "SimulatedDrive", clock: Callable[[], float]) -> None:
        self.sim = sim
        self.clock = clock
        self.wake_timer: Callable[[], None] = lambda: None  # the heartbeat ticker looks again
        self.rpdo = ReceivePdos(sim.store)
        self.heartbeats = Heartbeats(sim.store, clock, on_change=lambda: self.wake_timer())
        sim.drive.on_error = self.emcy

    def reset(self) -> None:
        """A reset: the objects are back at their saved values; supervision starts again."""
        with self.sim.lock:
            self.rpdo.reset()
            self.heartbeats.reset()
        self.wake_timer()

    def _send(self, cob_id: int, data: bytes) -> None:
        network = self.sim.network
        if network is not None:
            try:
                network.send_message(cob_id, data)
            except can.CanError:  # the simulator is closing: nobody to tell
                pass

    def emcy(self, code: int, register: int) -> None:
        """Send an EMCY (``Drive.on_error``, and the errors found here), if the NMT state allows."""
        if self.sim.nmt_state not in _EMCY_STATES:
            return
        frame = emcy_frame(self.sim.store, code, register)
        if frame is not None:
            self._send(*frame)

    def on_frame(self, cob_id: int, data: bytes) -> None:
        """A frame from the bus (the notifier thread), at the time of its arrival."""
        now = self.clock()
        with self.sim.lock:
            state = self.sim.nmt_state
            if HEARTBEAT_BASE < cob_id <= HEARTBEAT_BASE + 127 and len(data) == 1:
                if state in _HEARTBEAT_STATES and self.heartbeats.heard(cob_id - HEARTBEAT_BASE, now):
                    self.wake_timer()
                return
            if state is not NmtState.OPERATIONAL:
                return
            error = self.rpdo.receive(cob_id, data)
            if error is not None:
                register = self.sim.store.get_int(ERROR_REGISTER) | GENERIC_ERROR | COMMUNICATION_ERROR
                self.emcy(error, register)

    def tick(self, now: float) -> float:
        """Send the heartbeat if due and react to lost ones; returns when to look again."""
        with self.sim.lock:
            state = self.sim.nmt_state
            if state not in _HEARTBEAT_STATES:
                return math.inf  # initialising: the reset starts the timers again
            beat, lost, next_at = self.heartbeats.due(now)
            if beat:
                # CiA 301 7.2.8.3.2.2: one byte, the NMT state (7Fh, 05h, 04h).
                self._send(HEARTBEAT_BASE + self.sim.node_id, bytes([state.value]))
            for _ in lost:
                self._connection_lost()
        return next_at

    def _connection_lost(self) -> None:
        drive, store = self.sim.drive, self.sim.store
        option = store.get_int(ABORT_CONNECTION) if ABORT_CONNECTION in store.od else 0
        if option == 1:
            drive.inject_fault("heartbeat")  # its EMCY goes out through Drive.on_error
            return
        self.emcy(EMCY_HEARTBEAT, store.get_int(ERROR_REGISTER) | GENERIC_ERROR | COMMUNICATION_ERROR)
        command = _COMMANDS.get(option)
        if command is not None:
            drive.device_control(command)


class FrameListener(can.Listener):
    """Every frame on the bus to every drive's RPDOs and heartbeat consumers (their
    COB-IDs are configurable, so no fixed subscription fits)."""

    def __init__(self, drives: Dict[int, "SimulatedDrive"]) -> None:
        self.drives = drives

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        for sim in tuple(self.drives.values()):
            sim.comm.on_frame(msg.arbitration_id, bytes(msg.data))
