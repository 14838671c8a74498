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

PDOs and not SDOs: the gateway of the EPOS4 that ``record`` reads through is an
SDO client of the node on its default SDO channel (600h/580h + node id); a
second SDO client on that channel would take the gateway's answers for its
own (CiA 301 7.2.4: one client per SDO channel).
"""
import struct
import sys
import time

import can

PAUSE = 0.02  # between frames: each state change is taken before the next command


def move(host_port: str, node_id: int, target: int) -> None:
    host, port = host_port.rsplit(":", 1)
    with can.Bus(interface="socketcand", host=host, port=int(port), channel="can0") as bus:
        def send(can_id: int, data: bytes) -> None:
            bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
            time.sleep(PAUSE)

        send(0x000, bytes([0x01, node_id]))                        # NMT start remote node
        for controlword in (0x06, 0x07, 0x0F):                     # shutdown, switch on, enable
            send(0x300 + node_id, struct.pack("<Hb", controlword, 1))  # RxPDO 2: mode 1 = pp
        send(0x400 + node_id, struct.pack("<Hi", 0x0F, target))   # RxPDO 3: the target ...
        send(0x400 + node_id, struct.pack("<Hi", 0x1F, target))   # ... and the new set-point


if __name__ == "__main__":
    move(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
    print(f"node {sys.argv[2]}: moving to {sys.argv[3]}")
