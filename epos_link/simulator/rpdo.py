"""Receive PDOs of a simulated drive, configured like an EPOS4's (1400h-1403h, 1600h-1603h).

Objects (CiA 301 V4.2 7.5.2.35 RPDO communication, 7.5.2.36 RPDO mapping):
14xxh sub 1 COB-ID (bit 31 = 1: not valid), sub 2 transmission type; 16xxh
sub 0 number of mapped objects, subs 1..8 ``index << 16 | subindex << 8 |
length in bits``. Defaults as maxon's EDS for the EPOS4 (firmware 0110h,
``maxon_motor_EPOS4_0110h_6551h_0000h_0000h.eds`` as published in
github.com/lfelipem/maxon_epos4_ros1): all four valid, COB-IDs 200h, 300h,
400h, 500h + node id, type 255; RPDO1 controlword, RPDO2 controlword + modes
of operation, RPDO3 controlword + target position, RPDO4 controlword + target
velocity. The guide's default connection set (3.4, Table 3-15) lists the
same four COB-IDs.

SDO download rules: those of the transmit side
(:func:`epos_link.simulator.pdo.install_mapping_rules`: the mapping changes
only while the PDO is not valid and sub 0 is 0, mapped objects exist, are
mappable, have their own length and fit 64 bits; a valid PDO keeps its
COB-ID), and a receive PDO maps only objects that can be written (06040041h).

Reception, with what is **chosen** where CiA 301 leaves it to the device:

* only in NMT Operational (guide 3.3.3.5, Table 3-13), only a valid PDO;
* only the event-driven transmission types 254/255 are acted upon at once;
  the synchronous types (0..240) wait for a SYNC, which the simulator does not
  consume, so such a PDO is not processed (chosen, as the transmit side);
* length (CiA 301 7.2.2.2, as CANopenNode's ``CO_PDO_receive`` implements it):
  fewer data bytes than mapped: not processed, EMCY 8210h "PDO not processed
  due to length error"; more: the first bytes are used, EMCY 8220h "PDO length
  exceeded". The EMCY goes out once per error event: not again for the same
  error until a frame of the right length came (chosen). The drive does not go into FAULT and 1001h and
  603Fh are not changed for it (chosen: the EPOS4 error table names 8210h but
  our sources do not give its reaction);
* the mapped objects are written through the store, as an SDO download
  would (the drive model's write hooks run), under the drive's lock; a value
  the store refuses (out of range) is skipped, the others are written
  (chosen; CiA 301 does not say). The controlword (6040h) is written last,
  so that RPDO3's new set-point bit sees the target position of the same
  frame (chosen: a drive evaluates a frame as a whole).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Final, Optional, Tuple

from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from .od import ObjectStore
from .pdo import COB_ID_MASK, EVENT_DRIVEN, NOT_VALID, install_mapping_rules, mapped_variable

__all__ = ["EMCY_PDO_LENGTH", "EMCY_PDO_LENGTH_EXCEEDED", "ReceivePdos"]

EMCY_PDO_LENGTH: Final = 0x8210  # CiA 301 Table 21: PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED: Final = 0x8220  # CiA 301 Table 21: PDO length exceeded
CONTROLWORD: Final = 0x6040


@dataclass(frozen=True)
class _Plan:
    """One valid, event-driven RPDO as configured."""

    number: int
    objects: Tuple[Tuple[ODVariable, int, int], ...]  # (variable, offset, bytes), the controlword last
    size: int  # bytes mapped


class ReceivePdos:
    """The RPDOs of one drive's object store: mapping rules and what a frame writes."""

    def __init__(self, store: ObjectStore) -> None:
        self.store = store
        self.refuse_mapping = False
        self.numbers: Tuple[int, ...] = tuple(
            n for n in range(512) if 0x1400 + n in store.od and 0x1600 + n in store.od)
        self._plans: Optional[Dict[int, _Plan]] = None  # by COB-ID; None: read the objects again
        self._length_error: Dict[int, int] = {}  # RPDO number -> the EMCY sent for it last
        for n in self.numbers:
            install_mapping_rules(store, 0x1400 + n, 0x1600 + n, self.changed,
                                  lambda: self.refuse_mapping, receive=True)

    def changed(self) -> None:
        """The configuration changed or was reset: plan again at the next frame."""
        self._plans = None

    def reset(self) -> None:
        self._plans = None
        self._length_error.clear()

    def _plan(self) -> Dict[int, _Plan]:
        get = self.store.get_int
        plans: Dict[int, _Plan] = {}
        for n in self.numbers:
            cob_id = get(0x1400 + n, 1)
            if cob_id & NOT_VALID or get(0x1400 + n, 2) not in EVENT_DRIVEN:
                continue
            entries = [get(0x1600 + n, sub) for sub in range(1, get(0x1600 + n, 0) + 1)]
            objects, offset = [], 0
            for entry in entries:
                if entry:
                    objects.append((mapped_variable(self.store, entry), offset, (entry & 0xFF) // 8))
                    offset += (entry & 0xFF) // 8
            objects.sort(key=lambda o: o[0].index == CONTROLWORD)  # stable: the rest in order
            plans.setdefault(cob_id & COB_ID_MASK, _Plan(n, tuple(objects), offset))
        return plans

    def receive(self, cob_id: int, data: bytes) -> Optional[int]:
        """Apply a frame on ``cob_id``; the caller holds the drive's lock and has checked NMT
        Operational. Returns the EMCY error code to send (length error), else None."""
        if self._plans is None:
            self._plans = self._plan()
        plan = self._plans.get(cob_id)
        if plan is None:
            return None
        if len(data) != plan.size:
            emcy = EMCY_PDO_LENGTH if len(data) < plan.size else EMCY_PDO_LENGTH_EXCEEDED
            first = self._length_error.get(plan.number) != emcy
            self._length_error[plan.number] = emcy
            if len(data) < plan.size:
                return emcy if first else None
        else:
            emcy, first = None, False
            self._length_error.pop(plan.number, None)
        for var, offset, size in plan.objects:
            try:
                self.store.write(var.index, var.subindex, bytes(data[offset:offset + size]))
            except SdoAbortedError:
                continue  # a value the object refuses: that one is not written
        return emcy if first else None
