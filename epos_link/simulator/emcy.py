"""The EMCY producer of a simulated drive (CiA 301 V4.2 7.2.7, guide 3.3.3.4). Pure.

Frame (CiA 301 7.2.7.3.1): COB-ID from 1014h (default 80h + node id, as
maxon's EPOS4 EDS; bit 31 = 1: no EMCY), 8 data bytes: error code (UNSIGNED16,
little endian), error register 1001h (UNSIGNED8), 5 bytes manufacturer
specific error code, zeros here (**chosen**: no public maxon source says what
an EPOS4 puts there).

When (guide 3.3.3.4: "an Emergency Telegram may be sent only once per error
event"): at every error the drive model raises (``Drive.on_error``, from
``Drive.inject_fault``), at a fault reset with error code 0000h "error reset
or no error" (CiA 301 Table 21), and for the communication errors of
:mod:`~epos_link.simulator.rpdo` and :mod:`~epos_link.simulator.heartbeat`.
Only in NMT Pre-Operational and Operational (guide Table 3-13: Stopped has no
EMCY; initialising, no communication at all); an error event in those states
is not sent later (**chosen**).
"""
from __future__ import annotations

import struct
from typing import Final, Optional, Tuple

from .od import ObjectStore

__all__ = ["COB_ID_EMCY", "COMMUNICATION_ERROR", "ERROR_REGISTER", "GENERIC_ERROR", "emcy_frame"]

COB_ID_EMCY: Final = 0x1014
ERROR_REGISTER: Final = 0x1001
GENERIC_ERROR: Final = 0x01  # 1001h bit 0 (CiA 301 7.5.2.2)
COMMUNICATION_ERROR: Final = 0x10  # 1001h bit 4
_NOT_VALID: Final = 1 << 31
_EMCY = struct.Struct("<HB5s")


def emcy_frame(store: ObjectStore, code: int, register: int) -> Optional[Tuple[int, bytes]]:
    """(COB-ID, 8 data bytes) of an EMCY, or None when 1014h says the EMCY is not valid."""
    cob_id = store.get_int(COB_ID_EMCY) if COB_ID_EMCY in store.od else 0x80 + (store.od.node_id or 0)
    if cob_id & _NOT_VALID:
        return None
    return cob_id & 0x7FF, _EMCY.pack(code & 0xFFFF, register & 0xFF, bytes(5))
