"""EtherCAT frames and datagrams (ETG.1000.4 / IEC 61158-4-12 clause 5): parse and build.

Pure: bytes in, dataclasses out, and back. A frame on the wire::

    Ethernet header   dst(6) src(6) EtherType 0x88A4 (2, big endian)
    EtherCAT header   2 bytes, little endian: length (bits 0..10), type (bits 12..15, 1 = datagrams)
    datagram 1..n     cmd(1) idx(1) address(4) len(2) irq(2) data(len) wkc(2)
    padding           up to the Ethernet minimum of 60 bytes (without FCS)

In a datagram's ``len`` field bits 0..10 are the data length, bit 14 "circulating"
and bit 15 "more datagrams follow". The address is ADP (position or station
address, 2 bytes) then ADO (register offset, 2 bytes), or one 32-bit logical
address for LRD/LWR/LRW. All fields are little endian.

Errors: :class:`FrameError` (a ``ValueError``) for anything that is not a
well-formed EtherCAT frame; the caller drops such a frame, as an ESC does.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

__all__ = ["ETHERTYPE", "Command", "Datagram", "FrameError", "build_frame", "parse_frame"]

ETHERTYPE = 0x88A4
_ETH_HEADER = 14
_DATAGRAM_HEADER = 10
_MIN_FRAME = 60  # Ethernet minimum without FCS


class FrameError(ValueError):
    """Not a well-formed EtherCAT frame."""


class Command(IntEnum):
    """Datagram command types (ETG.1000.4 Table 12)."""

    NOP = 0
    APRD = 1   # auto increment physical read
    APWR = 2
    APRW = 3
    FPRD = 4   # configured address physical read
    FPWR = 5
    FPRW = 6
    BRD = 7    # broadcast read
    BWR = 8
    BRW = 9
    LRD = 10   # logical memory read
    LWR = 11
    LRW = 12
    ARMW = 13  # auto increment physical read, multiple write
    FRMW = 14  # configured address physical read, multiple write


@dataclass
class Datagram:
    """One datagram; ``data`` and ``wkc`` (and ``address`` for auto increment) change
    as the frame passes the slaves."""

    command: int
    index: int
    address: int  # 32 bits: ADP | ADO << 16, or the logical address
    data: bytearray
    wkc: int = 0
    irq: int = 0
    circulating: bool = False

    @property
    def adp(self) -> int:
        return self.address & 0xFFFF

    @property
    def ado(self) -> int:
        return self.address >> 16


def parse_frame(frame: bytes) -> tuple[bytes, list[Datagram]]:
    """Split an Ethernet frame into its header (14 bytes) and its datagrams."""
    if len(frame) < _ETH_HEADER + 2:
        raise FrameError(f"frame of {len(frame)} bytes is too short")
    if struct.unpack_from(">H", frame, 12)[0] != ETHERTYPE:
        raise FrameError("not EtherType 0x88A4")
    (header,) = struct.unpack_from("<H", frame, _ETH_HEADER)
    length, kind = header & 0x07FF, header >> 12
    if kind != 1:
        raise FrameError(f"EtherCAT frame type {kind} is not 1 (datagrams)")
    body = frame[_ETH_HEADER + 2:_ETH_HEADER + 2 + length]
    if len(body) < length:
        raise FrameError(f"EtherCAT header says {length} bytes, the frame holds {len(body)}")
    datagrams: list[Datagram] = []
    offset, more = 0, True
    while more:
        if offset + _DATAGRAM_HEADER > len(body):
            raise FrameError("datagram header runs past the frame")
        command, index, address, flags, irq = struct.unpack_from("<BBIHH", body, offset)
        size = flags & 0x07FF
        start = offset + _DATAGRAM_HEADER
        if start + size + 2 > len(body):
            raise FrameError("datagram data runs past the frame")
        (wkc,) = struct.unpack_from("<H", body, start + size)
        datagrams.append(Datagram(command, index, address, bytearray(body[start:start + size]),
                                  wkc, irq, bool(flags & 0x4000)))
        more = bool(flags & 0x8000)
        offset = start + size + 2
    return bytes(frame[:_ETH_HEADER]), datagrams


def build_frame(ethernet: bytes, datagrams: list[Datagram]) -> bytes:
    """The frame with these datagrams, padded to the Ethernet minimum."""
    if len(ethernet) != _ETH_HEADER:
        raise ValueError("the Ethernet header is 14 bytes")
    if not datagrams:
        raise ValueError("a frame holds at least one datagram")
    parts = []
    for n, d in enumerate(datagrams):
        if len(d.data) > 0x07FF:
            raise ValueError("a datagram holds at most 2047 data bytes")
        flags = len(d.data) | (0x4000 if d.circulating else 0) | (0x8000 if n < len(datagrams) - 1 else 0)
        parts.append(struct.pack("<BBIHH", d.command, d.index, d.address & 0xFFFFFFFF, flags, d.irq))
        parts.append(bytes(d.data))
        parts.append(struct.pack("<H", d.wkc & 0xFFFF))
    body = b"".join(parts)
    if len(body) > 0x07FF:
        raise ValueError("an EtherCAT frame body holds at most 2047 bytes")
    frame = ethernet + struct.pack("<H", len(body) | 0x1000) + body
    return frame + bytes(max(0, _MIN_FRAME - len(frame)))
