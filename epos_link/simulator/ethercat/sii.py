"""The SII EEPROM image of a simulated EPOS4 (ETG.1000.6 5.4, ETG.2010): pure data.

Word addresses of the fixed part (ETG.1000.6 Table 16) that a master reads::

    0x0000..0x0006  ESC configuration area (PDI control, PDI config, alias, ...)
    0x0007          checksum: CRC-8 (x^8+x^2+x+1, preset 0xFF) over bytes 0..13
    0x0008/0x000A   vendor id / product code (32 bit each)
    0x000C/0x000E   revision number / serial number
    0x0014..0x0017  bootstrap mailbox: receive offset, size, send offset, size
    0x0018..0x001B  standard mailbox: receive (SM0) offset, size, send (SM1) offset, size
    0x001C          mailbox protocols (bit 2: CoE)
    0x003E/0x003F   EEPROM size (KiBit - 1) / version (1)
    0x0040...       categories: type (word), size in words (word), data; 0xFFFF ends

Categories written: strings (10), general (30), FMMU (40), SyncManager (41).
No PDO categories: SOEM and other masters read the PDO assignment of a CoE
slave from 1C12h/1C13h (ETG.1000.6 5.6.7.4).

Identity and SyncManager layout (**chosen** from the one public EPOS4 ESI dump
found, "EPOS4 Micro 24/5 EtherCAT": vendor 0xFB, product code 0x69500000,
revision 0x01700000; SM0 0x1000, 48 bytes, control 0x26; SM1 0x1030, 48 bytes,
control 0x22; SM2 0x1060, control 0x64 (buffered, ECAT write, watchdog on);
SM3 0x10F0, control 0x20). The guide's Table 4-16 gives the SM and FMMU roles:
SM0 mailbox out, SM1 mailbox in, SM2 outputs, SM3 inputs; FMMU0 outputs, FMMU1
inputs, FMMU2 mailbox status. CoE details: SDO, PDO assign and PDO configuration,
**chosen** without SDO information and complete access (not simulated).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

__all__ = ["MAXON_VENDOR_ID", "EPOS4_PRODUCT_CODE", "EPOS4_REVISION", "MailboxLayout",
           "SyncManagerDefault", "DEFAULT_MAILBOX", "SYNC_MANAGERS", "crc8", "build_sii"]

MAXON_VENDOR_ID = 0x000000FB
EPOS4_PRODUCT_CODE = 0x69500000
EPOS4_REVISION = 0x01700000
MAILBOX_COE = 0x0004  # word 0x001C, bit 2
CATEGORY_STRINGS, CATEGORY_GENERAL, CATEGORY_FMMU, CATEGORY_SM = 10, 30, 40, 41
COE_DETAILS = 0x01 | 0x04 | 0x08  # SDO, PDO assign, PDO configuration
COE_COMPLETE_ACCESS = 0x20  # SOEM ECT_COEDET_SDOCA


@dataclass(frozen=True)
class MailboxLayout:
    receive_offset: int  # SM0: master -> slave
    receive_size: int
    send_offset: int     # SM1: slave -> master
    send_size: int


@dataclass(frozen=True)
class SyncManagerDefault:
    start: int
    length: int
    control: int
    enable: int


DEFAULT_MAILBOX = MailboxLayout(0x1000, 48, 0x1030, 48)
SYNC_MANAGERS = (
    SyncManagerDefault(0x1000, 48, 0x26, 1),  # mailbox out, ECAT writes, mailbox mode
    SyncManagerDefault(0x1030, 48, 0x22, 1),  # mailbox in, ECAT reads
    SyncManagerDefault(0x1060, 0, 0x64, 1),   # outputs, buffered, watchdog trigger
    SyncManagerDefault(0x10F0, 0, 0x20, 1),   # inputs, buffered
)


def crc8(data: bytes) -> int:
    """ETG.1000.6 5.4: CRC over the ESC configuration area, polynomial 0x07, preset 0xFF."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def build_sii(serial: int, *, name: str = "EPOS4", vendor: int = MAXON_VENDOR_ID,
              product: int = EPOS4_PRODUCT_CODE, revision: int = EPOS4_REVISION,
              mailbox: MailboxLayout = DEFAULT_MAILBOX, ca: bool = True) -> bytes:
    """The EEPROM contents, little endian words, as a master reads them."""
    config = struct.pack("<7H", 0x0C08, 0, 0, 0, 0, 0, 0)  # PDI control: **chosen**, any PDI
    header = bytearray(config + struct.pack("<H", crc8(config)))
    header += struct.pack("<IIII", vendor, product, revision, serial)
    header += bytes(8)  # 0x0010..0x0013: execution delay, port delays, reserved
    header += struct.pack("<4H", mailbox.receive_offset, mailbox.receive_size,
                          mailbox.send_offset, mailbox.send_size)  # bootstrap: same as standard
    header += struct.pack("<4H", mailbox.receive_offset, mailbox.receive_size,
                          mailbox.send_offset, mailbox.send_size)
    header += struct.pack("<H", MAILBOX_COE)
    header += bytes(0x3E * 2 - len(header))
    header += struct.pack("<HH", 0x000F, 0x0001)  # 16 KiBit, version 1
    strings = [name.encode("ascii"), b"maxon EPOS4 (simulated)"]
    text = bytes([len(strings)]) + b"".join(bytes([len(s)]) + s for s in strings)
    # General (ETG.2010 Table 4): group, image, order, name (string indices), reserved,
    # CoE/FoE/EoE/SoE details, DS402 channels, SysmanClass, flags, current on E-bus, ...
    coe = COE_DETAILS | (COE_COMPLETE_ACCESS if ca else 0)
    general = bytes([0, 0, 2, 1, 0, coe, 0, 0, 0, 1, 0, 0]) + bytes(20)
    fmmu = bytes([1, 2, 3, 0xFF])  # outputs, inputs, mailbox status, unused
    sms = b"".join(struct.pack("<HHBBBB", sm.start, sm.length, sm.control, 0, sm.enable, 0)
                   for sm in SYNC_MANAGERS)
    body = (_category(CATEGORY_STRINGS, text) + _category(CATEGORY_GENERAL, general)
            + _category(CATEGORY_FMMU, fmmu) + _category(CATEGORY_SM, sms) + b"\xff\xff")
    return bytes(header) + body
