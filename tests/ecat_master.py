"""A few lines of EtherCAT master for the pure slave tests: datagrams through a Segment."""
from __future__ import annotations

import struct
from typing import Optional

from epos_link.simulator.ethercat.frame import Command, Datagram, build_frame, parse_frame
from epos_link.simulator.ethercat.segment import Segment

ETH = b"\xff" * 6 + b"\x01\x01\x01\x01\x01\x01" + b"\x88\xa4"  # as SOEM sends (broadcast, 01:01:..)
STATION = 0x1001


def xfer(seg: Segment, command: int, adp: int, ado: int, data: bytes = b"", length: int = 0,
         now: float = 0.0) -> Datagram:
    """One datagram through the segment; the datagram as it came back."""
    dg = Datagram(command, 0x42, (adp & 0xFFFF) | (ado << 16), bytearray(data or bytes(length)))
    reply = seg.handle(build_frame(ETH, [dg]), now)
    assert reply is not None
    _eth, (out,) = parse_frame(reply)
    return out


def logical(seg: Segment, command: int, address: int, data: bytes, now: float = 0.0) -> Datagram:
    dg = Datagram(command, 0x43, address, bytearray(data))
    reply = seg.handle(build_frame(ETH, [dg]), now)
    assert reply is not None
    return parse_frame(reply)[1][0]


def fpwr(seg: Segment, ado: int, data: bytes, station: int = STATION, now: float = 0.0) -> int:
    return xfer(seg, Command.FPWR, station, ado, data, now=now).wkc


def fprd(seg: Segment, ado: int, length: int, station: int = STATION, now: float = 0.0) -> bytes:
    dg = xfer(seg, Command.FPRD, station, ado, length=length, now=now)
    assert dg.wkc == 1, f"FPRD 0x{ado:04X} wkc {dg.wkc}"
    return bytes(dg.data)


def sii_read(seg: Segment, word: int, station: int = STATION) -> bytes:
    """8 bytes of SII from word ``word`` through the EEPROM interface (0x0502..0x050F)."""
    assert fpwr(seg, 0x0502, struct.pack("<HI", 0x0100, word), station) == 1
    status = struct.unpack("<H", fprd(seg, 0x0502, 2, station))[0]
    assert not status & 0x8000  # not busy
    return fprd(seg, 0x0508, 8, station)


def al_request(seg: Segment, state: int, station: int = STATION, now: float = 0.0) -> tuple[int, int]:
    fpwr(seg, 0x0120, struct.pack("<H", state), station, now)
    return struct.unpack("<H", fprd(seg, 0x0130, 2, station))[0], \
        struct.unpack("<H", fprd(seg, 0x0134, 2, station))[0]


def sm(start: int, length: int, control: int, enable: int = 1) -> bytes:
    return struct.pack("<HHBBBB", start, length, control, 0, enable, 0)


def to_preop(seg: Segment, station: int = STATION, position: int = 0) -> None:
    xfer(seg, Command.APWR, -position, 0x0010, struct.pack("<H", station))
    fpwr(seg, 0x0800, sm(0x1000, 48, 0x26) + sm(0x1030, 48, 0x22), station)
    assert al_request(seg, 2, station) == (2, 0)


def sdo(seg: Segment, request: bytes, station: int = STATION) -> bytes:
    """One CoE message (after the mailbox header) out through SM0, the answer's CoE part back."""
    message = struct.pack("<HHBB", len(request), 0, 0, 0x03 | 0x10) + request
    assert fpwr(seg, 0x1000, message.ljust(48, b"\x00"), station) == 1
    status = fprd(seg, 0x080D, 1, station)[0]
    assert status & 0x08, "no answer in SM1"
    answer = fprd(seg, 0x1030, 48, station)
    length = struct.unpack_from("<H", answer)[0]
    assert answer[5] & 0x0F == 0x03, f"mailbox type {answer[5] & 0x0F}"
    return answer[6:6 + length]


def upload(seg: Segment, index: int, sub: int, station: int = STATION) -> tuple[int, bytes]:
    """(first command byte, whole value) of an SDO upload, segmented if it needs to be."""
    reply = sdo(seg, struct.pack("<HBHBI", 0x2000, 0x40, index, sub, 0), station)
    command = reply[2]
    if command == 0x80:
        return command, reply[6:10]
    if command & 0x02:
        return command, reply[6:6 + 4 - ((command >> 2) & 3)]
    size = struct.unpack_from("<I", reply, 6)[0]
    data, toggle = bytearray(reply[10:]), 0
    while len(data) < size:
        seg_reply = sdo(seg, struct.pack("<HB7x", 0x2000, 0x60 | toggle << 4), station)
        c = seg_reply[2]
        assert (c >> 4) & 1 == toggle
        chunk = seg_reply[3:]
        if c & 1 and len(chunk) == 7:
            chunk = chunk[:7 - ((c >> 1) & 7)]
        data += chunk
        toggle ^= 1
        if c & 1:
            break
    return command, bytes(data[:size])


def first_dg(frame: Optional[bytes]) -> Datagram:
    assert frame is not None
    return parse_frame(frame)[1][0]
