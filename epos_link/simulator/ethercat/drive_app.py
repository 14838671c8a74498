"""A simulated EPOS4 drive behind an EtherCAT slave: object store, CiA 402 model, lock.

The drive is the same model as on CAN (:mod:`epos_link.simulator.drive` over the
shipped dictionary, ``epos4.eds``); only the PDO mapping defaults differ: 1600h
and 1A00h are set to the EtherCAT default of :mod:`.pdo` at power-up.

The process-data watchdog's reaction (``on_leave_op("watchdog")``) follows
6007h "abort connection option code" (CiA 402-2 6007h, default 3 in maxon's
EDS), as the CAN heartbeat loss does (:mod:`epos_link.simulator.comm`):
2 disable voltage, 3 quick stop, 0 nothing. **chosen**: 1 ("fault signal")
also quick-stops; the simulator has no EtherCAT fault code of its own, and our
sources name none. **chosen**: a commanded exit from OP (the master writes a
lower state) reacts the same way, so no axis keeps moving without a master.
While the slave is in OP the statusword's bit 9 (remote) is 1, as in NMT
Operational on CAN.

Defaults as the EPOS4's (``epos4.eds``): 605Ah quick stop option code 6 (stay in
QUICK STOP ACTIVE after the ramp, so "enable operation" there is transition 16
back up, CiA 402-2 6.4.1.3), 6007h 3 (quick stop when the connection is lost).
An SDO upload of 6040h answers the last controlword the drive received, by
process data or SDO: that is what a new master reads of a dead one's command.

Differences of one slave (:mod:`.quirks`): Complete Access offered or not, its
padding byte, objects the dictionary lacks, late answers to store/restore.

**Chosen** (a test hook, like the CAN drive's 2100h simulator commands): writing
:data:`QUICK_STOP_INPUT` (9) to 2100h activates the EPOS4's quick stop input
(a digital input configured as "quick stop", EPOS4 Firmware Specification,
digital input functionalities), :data:`QUICK_STOP_RELEASE` (10) releases it.
An input is a level: while it is active the drive makes the quick stop command
itself, and every controlword it receives counts as quick stop (bit 2 low); once
released, the drive stays in QUICK STOP ACTIVE (605Ah = 6) until the master
commands otherwise.

``on_event`` receives one dict per thing a test wants to see in every cycle
(:meth:`EthercatDrive.events`): each frame of outputs the drive took in OP with
its state before and after, the target position it took against the actual
position before it; leaving and entering OP; the quick stop input.
"""
from __future__ import annotations

import struct
import threading
import time
from typing import Any, Callable, Dict, Optional

from ...cia402 import Command
from ..drive import Drive
from ..od import ObjectStore, load_object_dictionary
from .coe import SdoAbort
from .pdo import DEFAULT_RX, DEFAULT_TX, mapping_value
from .quirks import SLOW_OBJECTS, Quirks
from .slave import EthercatSlave

__all__ = ["EthercatDrive", "QUICK_STOP_INPUT", "QUICK_STOP_RELEASE"]

ABORT_CONNECTION = 0x6007
ABORT_NO_OBJECT = 0x06020000
SIMULATOR_COMMAND = 0x2100
QUICK_STOP_INPUT = 9
QUICK_STOP_RELEASE = 10
_QUICK_STOP_BIT = 0x0004  # controlword bit 2, active low (CiA 402-2 6.4.1.3)
_REACTIONS = {1: Command.QUICK_STOP, 2: Command.DISABLE_VOLTAGE, 3: Command.QUICK_STOP}
Event = Dict[str, Any]


class EthercatDrive:
    """One drive and its slave; ``read``/``write`` are the CoE object access, under ``lock``."""

    def __init__(self, position: int, clock: Callable[[], float] = time.monotonic,
                 quirks: Quirks = Quirks(),
                 on_event: Optional[Callable[[Event], None]] = None) -> None:
        self.position = position
        self.lock = threading.RLock()
        self.store = ObjectStore(load_object_dictionary(position))
        self.drive = Drive(self.store, clock=clock)
        self.quirks = quirks
        self.on_event = on_event
        self.watchdog_reactions = 0
        self.quick_stop_input = False  # the EPOS4's quick stop input (docstring, chosen)
        self._default_mapping()
        self.slave = EthercatSlave(self, serial=position, on_enter_op=self._enter_op,
                                   on_leave_op=self._leave_op,
                                   complete_access=quirks.offer_ca, ca_padding=quirks.ca_padding,
                                   reply_delay=self._reply_delay,
                                   apply_outputs=self._apply_outputs)

    def _default_mapping(self) -> None:
        for pdo, entries in ((0x1600, DEFAULT_RX), (0x1A00, DEFAULT_TX)):
            for n, entry in enumerate(entries, start=1):
                self.store.set(pdo, n, mapping_value(*entry))
            self.store.set(pdo, 0, len(entries))

    def read(self, index: int, subindex: int) -> bytes:
        if index in self.quirks.missing:
            raise SdoAbort(ABORT_NO_OBJECT)
        with self.lock:
            return self.store.read(index, subindex)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        if index in self.quirks.missing:
            raise SdoAbort(ABORT_NO_OBJECT)
        with self.lock:
            command = int.from_bytes(data, "little") if index == SIMULATOR_COMMAND else 0
            if command == QUICK_STOP_INPUT:
                self.quick_stop_input = True
                self._event("quick_stop_input", before=self.drive.state.name)
                self.drive.device_control(Command.QUICK_STOP)
                return
            if command == QUICK_STOP_RELEASE:
                self.quick_stop_input = False
                self._event("quick_stop_release", state=self.drive.state.name)
                return
            self.store.write(index, subindex, data)

    def _reply_delay(self, message: bytes) -> float:
        """Seconds the answer to this CoE message is held (quirk ``late``)."""
        if not self.quirks.late or len(message) < 6:
            return 0.0
        command, index = message[2], struct.unpack_from("<H", message, 3)[0]
        is_download = command >> 5 == 1
        return self.quirks.late if is_download and index in SLOW_OBJECTS else 0.0

    # -- process data, under the lock (slave docstring: apply_outputs) --------------------

    def _apply_outputs(self, changed: "list[tuple[int, int, bytes]]") -> None:
        with self.lock:
            drive = self.drive
            drive.sync()
            before, actual = drive.state, drive.position
            taken: Event = {}
            for index, subindex, value in changed:
                given = value  # as the master sent it
                if (index, subindex) == (0x6040, 0) and self.quick_stop_input:
                    value = (int.from_bytes(value, "little") & ~_QUICK_STOP_BIT).to_bytes(2, "little")
                try:
                    self.store.write(index, subindex, value)
                except Exception:  # refused by the dictionary: skipped (slave docstring)
                    continue
                if (index, subindex) == (0x6040, 0):
                    taken["cw"] = int.from_bytes(given, "little")
                elif (index, subindex) == (0x607A, 0):
                    taken["sp"] = int.from_bytes(value, "little", signed=True)
                elif (index, subindex) == (0x60FF, 0):
                    taken["tv"] = int.from_bytes(value, "little", signed=True)
            if self.on_event is not None:
                self._event("outputs", before=before.name, after=drive.state.name,
                            actual=actual, mode=int(drive.mode), **taken)

    def _event(self, kind: str, **fields: Any) -> None:
        if self.on_event is not None:
            self.on_event({"t": self.drive.clock() if self.drive.clock else 0.0,
                           "slave": self.position, "event": kind, **fields})

    def _enter_op(self) -> None:
        with self.lock:
            self.drive.remote = True
            self._event("enter_op", state=self.drive.state.name)

    def _leave_op(self, cause: str) -> None:
        with self.lock:
            self.drive.remote = False
            if cause == "watchdog":
                self.watchdog_reactions += 1
            before = self.drive.state
            option = self.store.get_int(ABORT_CONNECTION) if ABORT_CONNECTION in self.store.od else 3
            command = _REACTIONS.get(option)
            if command is not None:
                self.drive.device_control(command)
            self._event("leave_op", cause=cause, before=before.name, after=self.drive.state.name)
