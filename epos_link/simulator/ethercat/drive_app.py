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
"""
from __future__ import annotations

import threading
import time
from typing import Callable

from ...cia402 import Command
from ..drive import Drive
from ..od import ObjectStore, load_object_dictionary
from .pdo import DEFAULT_RX, DEFAULT_TX, mapping_value
from .slave import EthercatSlave

__all__ = ["EthercatDrive"]

ABORT_CONNECTION = 0x6007
_REACTIONS = {1: Command.QUICK_STOP, 2: Command.DISABLE_VOLTAGE, 3: Command.QUICK_STOP}


class EthercatDrive:
    """One drive and its slave; ``read``/``write`` are the CoE object access, under ``lock``."""

    def __init__(self, position: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.lock = threading.RLock()
        self.store = ObjectStore(load_object_dictionary(position))
        self.drive = Drive(self.store, clock=clock)
        self.watchdog_reactions = 0
        self._default_mapping()
        self.slave = EthercatSlave(self, serial=position, on_enter_op=self._enter_op,
                                   on_leave_op=self._leave_op)

    def _default_mapping(self) -> None:
        for pdo, entries in ((0x1600, DEFAULT_RX), (0x1A00, DEFAULT_TX)):
            for n, entry in enumerate(entries, start=1):
                self.store.set(pdo, n, mapping_value(*entry))
            self.store.set(pdo, 0, len(entries))

    def read(self, index: int, subindex: int) -> bytes:
        with self.lock:
            return self.store.read(index, subindex)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        with self.lock:
            self.store.write(index, subindex, data)

    def _enter_op(self) -> None:
        with self.lock:
            self.drive.remote = True

    def _leave_op(self, cause: str) -> None:
        with self.lock:
            self.drive.remote = False
            if cause == "watchdog":
                self.watchdog_reactions += 1
            option = self.store.get_int(ABORT_CONNECTION) if ABORT_CONNECTION in self.store.od else 3
            command = _REACTIONS.get(option)
            if command is not None:
                self.drive.device_control(command)
