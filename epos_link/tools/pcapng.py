"""pcapng, Wireshark's capture format, written and read with the standard library.

Layout (IETF draft-ietf-opsawg-pcapng, sections 4.1 to 4.3), little endian::

    Section Header Block     0x0A0D0D0A  byte-order magic 0x1A2B3C4D, version 1.0
    Interface Description    0x00000001  link type 147 (LINKTYPE_USER0), snaplen 0,
                                         if_name, if_description (URL, baud),
                                         if_speed (bit/s), if_tsresol 9 (nanoseconds)
    Enhanced Packet Block    0x00000006  one per frame as on the wire (stuffed),
                                         epb_flags bits 0-1: 01 inbound (device to
                                         host), 10 outbound (host to device)

Every block is padded to 32 bits and ends with its own length repeated.
Wireshark turns the direction flags into ``frame.p2p_dir`` (0 sent, 1 received).
The writer flushes after every block so a reader on a pipe
(``wireshark -k -i -``) sees each packet at once. Pure: it writes to the
binary stream it is given.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import BinaryIO, Iterator, Optional

LINKTYPE_USER0 = 147
SHB_TYPE = 0x0A0D0D0A
IDB_TYPE = 0x00000001
EPB_TYPE = 0x00000006
BYTE_ORDER_MAGIC = 0x1A2B3C4D

OPT_END = 0
OPT_COMMENT = 1
SHB_USERAPPL = 4
IF_NAME = 2
IF_DESCRIPTION = 3
IF_SPEED = 8
IF_TSRESOL = 9
EPB_FLAGS = 2

FLAG_INBOUND = 0x1   # device to host (RX)
FLAG_OUTBOUND = 0x2  # host to device (TX)


class PcapngError(ValueError):
    """A file that is not pcapng as this module writes it."""


def _pad(data: bytes) -> bytes:
    return data + b"\x00" * (-len(data) % 4)


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + _pad(value)


def _options(opts: list[tuple[int, bytes]]) -> bytes:
    if not opts:
        return b""
    return b"".join(_option(c, v) for c, v in opts) + struct.pack("<HH", OPT_END, 0)


def _block(block_type: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", block_type, total) + body + struct.pack("<I", total)


class PcapngWriter:
    """Writes one section with one interface; :meth:`packet` adds a frame."""

    def __init__(self, stream: BinaryIO, *, if_name: str = "maxon", if_description: str = "",
                 speed: Optional[int] = None, application: str = "epos-link",
                 linktype: int = LINKTYPE_USER0) -> None:
        self._stream = stream
        shb = struct.pack("<IHHq", BYTE_ORDER_MAGIC, 1, 0, -1) + _options(
            [(SHB_USERAPPL, application.encode())])
        opts = [(IF_NAME, if_name.encode())]
        if if_description:
            opts.append((IF_DESCRIPTION, if_description.encode()))
        if speed:
            opts.append((IF_SPEED, struct.pack("<Q", speed)))
        opts.append((IF_TSRESOL, bytes((9,))))  # 10^-9 s
        idb = struct.pack("<HHI", linktype, 0, 0) + _options(opts)
        self._write(_block(SHB_TYPE, shb) + _block(IDB_TYPE, idb))

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._stream.flush()

    def packet(self, time_ns: int, data: bytes, *, outbound: Optional[bool] = None,
               comment: str = "") -> None:
        """One packet; ``outbound`` True for host to device, False for device to host."""
        opts: list[tuple[int, bytes]] = []
        if outbound is not None:
            opts.append((EPB_FLAGS, struct.pack("<I", FLAG_OUTBOUND if outbound else FLAG_INBOUND)))
        if comment:
            opts.append((OPT_COMMENT, comment.encode()))
        ts = max(0, int(time_ns))
        body = struct.pack("<IIIII", 0, ts >> 32, ts & 0xFFFFFFFF, len(data), len(data))
        self._write(_block(EPB_TYPE, body + _pad(bytes(data)) + _options(opts)))


@dataclass(frozen=True)
class Packet:
    time_ns: int
    data: bytes
    flags: Optional[int]


@dataclass(frozen=True)
class Interface:
    linktype: int
    options: dict[int, bytes]


def _parse_options(data: bytes) -> dict[int, bytes]:
    out: dict[int, bytes] = {}
    pos = 0
    while pos + 4 <= len(data):
        code, length = struct.unpack_from("<HH", data, pos)
        if code == OPT_END:
            break
        out[code] = data[pos + 4:pos + 4 + length]
        pos += 4 + length + (-length % 4)
    return out


def read_pcapng(data: bytes) -> tuple[list[Interface], list[Packet]]:
    """Interfaces and packets of a little-endian pcapng file (what the writer makes)."""
    interfaces: list[Interface] = []
    packets: list[Packet] = []
    pos = 0
    while pos < len(data):
        if pos + 12 > len(data):
            raise PcapngError(f"truncated block at byte {pos}")
        btype, total = struct.unpack_from("<II", data, pos)
        if total < 12 or total % 4 or pos + total > len(data):
            raise PcapngError(f"bad block length {total} at byte {pos}")
        body = data[pos + 8:pos + total - 4]
        if btype == SHB_TYPE:
            if struct.unpack_from("<I", body)[0] != BYTE_ORDER_MAGIC:
                raise PcapngError("not a little-endian pcapng section")
        elif btype == IDB_TYPE:
            linktype = struct.unpack_from("<H", body)[0]
            interfaces.append(Interface(linktype, _parse_options(body[8:])))
        elif btype == EPB_TYPE:
            _, hi, lo, caplen, _ = struct.unpack_from("<IIIII", body)
            payload = body[20:20 + caplen]
            opts = _parse_options(body[20 + caplen + (-caplen % 4):])
            flags = struct.unpack("<I", opts[EPB_FLAGS])[0] if EPB_FLAGS in opts else None
            packets.append(Packet((hi << 32) | lo, bytes(payload), flags))
        pos += total
    return interfaces, packets


def iter_packets(data: bytes) -> Iterator[Packet]:
    return iter(read_pcapng(data)[1])


__all__ = ["FLAG_INBOUND", "FLAG_OUTBOUND", "LINKTYPE_USER0", "Packet", "PcapngError",
           "PcapngWriter", "read_pcapng"]
