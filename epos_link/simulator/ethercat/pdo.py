"""EtherCAT process data of a simulated EPOS4: the SM PDO assignment objects and the
PDO layout (ETG.1000.6 5.6.7.4, CiA 301 7.4.8). Pure.

The CANopen dictionary (``epos4.eds``) has no 1C00h/1C12h/1C13h, so
:class:`EthercatObjects` adds them in front of it:

* 1C00h "sync manager communication type": 4 SMs: 1 mailbox out, 2 mailbox in,
  3 process data outputs, 4 process data inputs (ro);
* 1C12h "RxPDO assign" (SM2) and 1C13h "TxPDO assign" (SM3): subindex 0 the
  count, then PDO mapping indices (1600h..1603h, 1A00h..1A03h); writable only
  in PRE-OP (ETG.1000.6: in SAFE-OP and OP 0x08000022 "wrong device state"),
  like the mapping objects 1600h..1603h/1A00h..1A03h themselves.

Default mapping (**chosen**; public EPOS4 material names these objects but our
sources do not give maxon's EtherCAT default byte for byte):

* RxPDO 1600h: controlword 6040h, target position 607Ah, target velocity 60FFh,
  modes of operation 6060h (11 bytes);
* TxPDO 1A00h: statusword 6041h, position actual value 6064h, velocity actual
  value 606Ch, modes of operation display 6061h, error code 603Fh (13 bytes).

:class:`PdoLayout` is read once at PRE-OP -> SAFE-OP: each entry is index,
subindex and a bit length that must be a multiple of 8 (**chosen**: the
EPOS4's objects are whole bytes); index 0 is a gap of that many bits.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable

from .coe import ObjectAccess, SdoAbort

__all__ = ["DEFAULT_RX", "DEFAULT_TX", "EthercatObjects", "PdoEntry", "PdoLayout",
           "read_layout", "mapping_value"]

ABORT_NO_OBJECT = 0x06020000
ABORT_SUBINDEX = 0x06090011
ABORT_READ_ONLY = 0x06010002
ABORT_RANGE = 0x06090030
ABORT_STATE = 0x08000022
ABORT_MAPPING = 0x06040041
SM_TYPES = (1, 2, 3, 4)
RX_ASSIGN, TX_ASSIGN = 0x1C12, 0x1C13
RX_PDOS, TX_PDOS = range(0x1600, 0x1604), range(0x1A00, 0x1A04)

DEFAULT_RX = ((0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6060, 0, 8))
DEFAULT_TX = ((0x6041, 0, 16), (0x6064, 0, 32), (0x606C, 0, 32), (0x6061, 0, 8), (0x603F, 0, 16))


def mapping_value(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry (CiA 301 7.4.8): index << 16 | subindex << 8 | length in bits."""
    return (index << 16) | (subindex << 8) | bits


@dataclass(frozen=True)
class PdoEntry:
    index: int
    subindex: int
    bits: int


@dataclass(frozen=True)
class PdoLayout:
    outputs: tuple[PdoEntry, ...]  # RxPDO: master -> slave, SM2
    inputs: tuple[PdoEntry, ...]   # TxPDO: slave -> master, SM3

    @property
    def output_size(self) -> int:
        return sum(e.bits for e in self.outputs) // 8

    @property
    def input_size(self) -> int:
        return sum(e.bits for e in self.inputs) // 8

    def pack_inputs(self, objects: ObjectAccess) -> bytes:
        parts = []
        for e in self.inputs:
            size = e.bits // 8
            parts.append(bytes(size) if e.index == 0 else
                         bytes(objects.read(e.index, e.subindex))[:size].ljust(size, b"\x00"))
        return b"".join(parts)

    def split_outputs(self, data: bytes) -> list[tuple[PdoEntry, bytes]]:
        out, offset = [], 0
        for e in self.outputs:
            size = e.bits // 8
            if e.index:
                out.append((e, bytes(data[offset:offset + size])))
            offset += size
        return out


def _u(data: bytes) -> int:
    return int.from_bytes(data, "little")


def read_layout(objects: ObjectAccess) -> PdoLayout:
    """The PDOs assigned to SM2 and SM3 now (SdoAbort(0x06040041) if an entry is not byte-sized)."""
    def side(assign: int) -> tuple[PdoEntry, ...]:
        entries = []
        for n in range(1, _u(objects.read(assign, 0)) + 1):
            pdo = _u(objects.read(assign, n))
            for k in range(1, _u(objects.read(pdo, 0)) + 1):
                value = _u(objects.read(pdo, k))
                entry = PdoEntry(value >> 16, (value >> 8) & 0xFF, value & 0xFF)
                if entry.bits % 8 or not entry.bits:
                    raise SdoAbort(ABORT_MAPPING)
                entries.append(entry)
        return tuple(entries)
    return PdoLayout(side(RX_ASSIGN), side(TX_ASSIGN))


class EthercatObjects:
    """1C00h, 1C12h and 1C13h in front of the drive's dictionary; PDO configuration
    only while ``configurable()`` (PRE-OP)."""

    def __init__(self, base: ObjectAccess, configurable: Callable[[], bool]) -> None:
        self.base = base
        self.configurable = configurable
        self.assign = {RX_ASSIGN: [0x1600], TX_ASSIGN: [0x1A00]}

    def read(self, index: int, subindex: int) -> bytes:
        if index == 0x1C00:
            if subindex > len(SM_TYPES):
                raise SdoAbort(ABORT_SUBINDEX)
            return bytes([len(SM_TYPES) if subindex == 0 else SM_TYPES[subindex - 1]])
        if index in self.assign:
            pdos = self.assign[index]
            if subindex == 0:
                return bytes([len(pdos)])
            if subindex > 4:
                raise SdoAbort(ABORT_SUBINDEX)
            return struct.pack("<H", pdos[subindex - 1] if subindex <= len(pdos) else 0)
        return self.base.read(index, subindex)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        if index == 0x1C00:
            raise SdoAbort(ABORT_READ_ONLY)
        if index in self.assign or index in RX_PDOS or index in TX_PDOS:
            if not self.configurable():
                raise SdoAbort(ABORT_STATE)
        if index not in self.assign:
            self.base.write(index, subindex, data)
            return
        pdos, allowed = self.assign[index], (RX_PDOS if index == RX_ASSIGN else TX_PDOS)
        if subindex > 4:
            raise SdoAbort(ABORT_SUBINDEX)
        value = _u(data)
        if subindex == 0:
            if value > 4 or value > len(pdos) and 0 in pdos[:value]:
                raise SdoAbort(ABORT_RANGE)
            del pdos[value:]
            return
        if value not in allowed or len(data) > 2 and _u(data[2:]):
            raise SdoAbort(ABORT_RANGE)
        while len(pdos) < subindex:
            pdos.append(0)
        pdos[subindex - 1] = value
