"""A profile position move of one drive over CAN, as an application commands it: by PDO.

Run: .venv/bin/python examples/pp_move.py HOST:PORT NODE TARGET
HOST:PORT is a socketcand server (``epos-link sim --can-server HOST:PORT``).
The script starts the node (NMT start, CiA 301 7.2.8.3.2.1), then enables it in
profile position mode and sends it to TARGET increments (CiA 402-2 6.6) with
the EPOS4's default receive PDOs (its EDS, 1601h and 1602h): RxPDO 2
(controlword, modes of operation) and RxPDO 3 (controlword, target position).
The profile is the drive's own (6081h, 6083h, 6084h). It returns as soon as the
move has started; docs/epos-link.md records such a move with ``epos-link
record`` through the EPOS4's serial link.

The drive decides: each step waits for the drive's statusword in its TxPDO 1
(COB-ID 180h + node, the EPOS4 default mapping 1A00h:01 = 6041h) to show the
state the step asked for (CiA 402-2 6.4.1.4: ready to switch on, switched on,
operation enabled) and, for the move, the set-point acknowledge (statusword
bit 12, CiA 402-2 6.6.1.2), rather than sleeping and hoping. A step the drive
does not take within :data:`STEP_TIMEOUT` ends the script with one line and
exit 1.

Closing cleanly: the script returns only after the drive has acknowledged the
last frame, the new set-point, so nothing it sent can be lost at the close; it
then reads the bus until it is quiet for :data:`QUIET` seconds (at most
:data:`DRAIN_MAX`) before it closes, so its close is normally an orderly one.
(A close with frames still unread makes the kernel reset the connection; the
simulator's socketcand server takes every frame sent before a reset all the
same, as a CAN bus would: epos_link/simulator/socketcand.py.)

PDOs and not SDOs: the gateway of the EPOS4 that ``record`` reads through is an
SDO client of the node on its default SDO channel (600h/580h + node id); a
second SDO client on that channel would take the gateway's answers for its
own (CiA 301 7.2.4: one client per SDO channel).
"""
import logging
import struct
import sys
import time
from typing import Callable, Optional

import can

STEP_TIMEOUT = 5.0  # seconds for the drive to show a step (it takes a few ms)
QUIET = 0.02  # seconds without a frame: the bus is quiet, close
DRAIN_MAX = 0.2  # seconds of reading at most (a moving drive sends TPDOs all along)
STATE_MASK = 0x6F  # statusword bits 0-3, 5, 6: the CiA 402 state (CiA 402-2 Table 30)
READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED = 0x21, 0x23, 0x27
SET_POINT_ACKNOWLEDGE = 1 << 12


class DriveDidNotFollow(Exception):
    """The drive did not show a step within STEP_TIMEOUT."""


class Drive:
    """The node as the application sees it: frames out, its statusword from TxPDO 1 in."""

    def __init__(self, bus: can.BusABC, node_id: int) -> None:
        self.bus = bus
        self.node_id = node_id
        self.statusword: Optional[int] = None  # the newest TxPDO 1 seen

    def send(self, can_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def _take(self, msg: Optional[can.Message]) -> None:
        if msg is not None and msg.arbitration_id == 0x180 + self.node_id and len(msg.data) >= 2:
            self.statusword = struct.unpack_from("<H", msg.data)[0]

    def wait_for(self, shows: Callable[[int], bool], what: str) -> int:
        """Read the bus until the statusword shows ``what`` (a TxPDO 1 after the command)."""
        deadline = time.monotonic() + STEP_TIMEOUT
        while time.monotonic() < deadline:
            self._take(self.bus.recv(0.05))
            if self.statusword is not None and shows(self.statusword):
                return self.statusword
        seen = "nothing" if self.statusword is None else f"statusword 0x{self.statusword:04X}"
        raise DriveDidNotFollow(f"node {self.node_id} did not show {what} within "
                                f"{STEP_TIMEOUT:g} s (TxPDO 1: {seen})")

    def drain(self) -> None:
        """Read until the bus is quiet (or DRAIN_MAX), so the close finds nothing unread."""
        end = time.monotonic() + DRAIN_MAX
        while time.monotonic() < end:
            msg = self.bus.recv(QUIET)
            if msg is None:
                return
            self._take(msg)


def in_state(state: int) -> Callable[[int], bool]:
    return lambda sw: sw & STATE_MASK == state


def move(host_port: str, node_id: int, target: int) -> None:
    host, port = host_port.rsplit(":", 1)
    with can.Bus(interface="socketcand", host=host, port=int(port), channel="can0") as bus:
        drive = Drive(bus, node_id)
        rx2, rx3 = 0x300 + node_id, 0x400 + node_id
        drive.send(0x000, bytes([0x01, node_id]))  # NMT start: its TPDOs go out at once
        drive.send(rx2, struct.pack("<Hb", 0x06, 1))  # shutdown; mode 1 = pp
        drive.wait_for(in_state(READY_TO_SWITCH_ON), "ready to switch on")
        drive.send(rx2, struct.pack("<Hb", 0x07, 1))  # switch on
        drive.wait_for(in_state(SWITCHED_ON), "switched on")
        drive.send(rx2, struct.pack("<Hb", 0x0F, 1))  # enable operation
        drive.wait_for(in_state(OPERATION_ENABLED), "operation enabled")
        drive.send(rx3, struct.pack("<Hi", 0x0F, target))  # the target ...
        drive.send(rx3, struct.pack("<Hi", 0x1F, target))  # ... and the new set-point
        drive.wait_for(lambda sw: bool(sw & SET_POINT_ACKNOWLEDGE)
                       and in_state(OPERATION_ENABLED)(sw), "the set-point acknowledged")
        drive.drain()


if __name__ == "__main__":
    # python-can's socketcand client warns "Got incomplete message" whenever a TCP read
    # ends inside a frame's text, which a stream does; it then reads the rest. Not a fault.
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    try:
        move(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
    except DriveDidNotFollow as exc:
        print(f"pp_move: {exc}", file=sys.stderr)
        sys.exit(1)
    print(f"node {sys.argv[2]}: moving to {sys.argv[3]}")
