"""The EtherCAT Slave Controller's memory as the master sees it (ETG.1000.4, Beckhoff
"EtherCAT Slave Controller, Section II: register description"). Pure.

:class:`Esc` is 4 KiB of registers plus 8 KiB of process RAM (0x1000..0x2FFF).
It does what an ESC does in hardware, and leaves the rest to its owner
(:class:`~epos_link.simulator.ethercat.slave.EthercatSlave`, the "PDI side"):

* read-only registers (type, revision, features, DL status, AL status and
  code, SM status, EEPROM status and data) ignore master writes;
* the SII EEPROM interface (0x0500..0x050F): a read command (0x0502 bits
  8..10 = 001) with a word address in 0x0504 fills 0x0508..0x050F with 8 bytes
  (status bit 6: 8-byte reads) at once; it is never busy. **chosen**: write and
  reload commands are ignored (the simulated EEPROM is read-only);
* SyncManagers (0x0800 + 8n: start, length, control, status, activate): in
  mailbox mode (control bits 0..1 = 10) a master write to a full write-mailbox
  or a read from an empty read-mailbox is refused (no working counter); writing
  the last byte fills the mailbox, reading the last byte empties it. In
  buffered mode a write covering the last byte is "buffer written" (the
  process-data watchdog trigger when control bit 6 is set). **chosen**: one
  buffer instead of three, which a master cannot tell apart;
* FMMUs (0x0600 + 16n) map logical addresses to physical ones byte-wise
  (bit-granular mappings are not needed by the EPOS4's byte-aligned PDOs).

Events go to the owner through ``on_write(first, last)``,
``on_sm_filled(n)``, ``on_sm_emptied(n)`` and ``before_sm_read(n)``.
"""
from __future__ import annotations

import struct
from typing import Callable, Optional

__all__ = ["Esc", "MEMORY_SIZE", "AL_CONTROL", "AL_STATUS", "AL_STATUS_CODE", "DL_STATUS",
           "EEPROM_CONTROL", "SM_BASE", "FMMU_BASE", "PD_WATCHDOG", "WATCHDOG_DIVIDER",
           "PD_WATCHDOG_STATUS", "STATION_ADDRESS"]

MEMORY_SIZE = 0x3000
STATION_ADDRESS = 0x0010
DL_STATUS = 0x0110
AL_CONTROL = 0x0120
AL_STATUS = 0x0130
AL_STATUS_CODE = 0x0134
PDI_CONTROL = 0x0140
WATCHDOG_DIVIDER = 0x0400
PD_WATCHDOG = 0x0420
PD_WATCHDOG_STATUS = 0x0440
EEPROM_CONFIG = 0x0500
EEPROM_CONTROL = 0x0502
EEPROM_ADDRESS = 0x0504
EEPROM_DATA = 0x0508
FMMU_BASE = 0x0600
FMMU_COUNT = 3
SM_BASE = 0x0800
SM_COUNT = 4
EEPROM_READ_8 = 0x0040  # status: the ESC reads 8 bytes at a time

# Master-writable register ranges (inclusive); everything from 0x1000 is process RAM.
_WRITABLE = ((0x0010, 0x0011), (0x0100, 0x0103), (0x0108, 0x0109), (0x0120, 0x0121),
             (0x0200, 0x0203), (0x0300, 0x0313), (0x0400, 0x0401), (0x0410, 0x0411),
             (0x0420, 0x0421), (0x0442, 0x0443), (0x0500, 0x0500), (0x0502, 0x050B),
             (0x0600, 0x06FF), (0x0800, 0x087F), (0x0900, 0x09FF), (0x1000, MEMORY_SIZE - 1))


def _writable_mask() -> bytes:
    mask = bytearray(MEMORY_SIZE)
    for first, last in _WRITABLE:
        mask[first:last + 1] = b"\x01" * (last + 1 - first)
    for n in range(SM_COUNT):  # SM status and PDI control bytes belong to the ESC / PDI
        mask[SM_BASE + 8 * n + 5] = 0
        mask[SM_BASE + 8 * n + 7] = 0
    return bytes(mask)


_MASK = _writable_mask()


class Esc:
    """One ESC: its memory and the hardware behaviour of registers, SII, SMs and FMMUs."""

    def __init__(self, eeprom: bytes) -> None:
        self.memory = bytearray(MEMORY_SIZE)
        self.eeprom = eeprom
        self.mailbox_full = [False] * SM_COUNT
        # The PDI's "deactivate SyncManager" (ESC register 0x0807 + 8n, bit 0): a master
        # write into a deactivated SM's buffer is refused (no working counter).
        self.sm_deactivated = [False] * SM_COUNT
        self.on_write: Callable[[int, int], None] = lambda first, last: None
        self.on_sm_filled: Callable[[int], None] = lambda n: None
        self.on_sm_emptied: Callable[[int], None] = lambda n: None
        self.before_sm_read: Callable[[int], None] = lambda n: None
        # ESC information (0x0000..0x000F): type, revision, build, FMMUs, SMs, RAM (KiB),
        # port descriptor (two MII ports), features (bit 2 DC: **chosen** off, not simulated).
        self.memory[0x0000:0x000A] = struct.pack("<BBHBBBBH", 0x11, 0x02, 0x0001, FMMU_COUNT,
                                                 SM_COUNT, 8, 0x0F, 0x0000)
        self.set_u16(PDI_CONTROL, 0x0005)  # **chosen**: an SPI PDI, which masters only print
        self.set_u16(WATCHDOG_DIVIDER, 2498)  # 25 MHz / (2498 + 2) = 100 us (ESC default)
        self.set_u16(0x0410, 1000)            # PDI watchdog 100 ms
        self.set_u16(PD_WATCHDOG, 1000)       # process data watchdog 100 ms (ESC default)
        self.set_u16(AL_STATUS, 0x0001)       # INIT
        self.set_u16(EEPROM_CONTROL, EEPROM_READ_8)

    # -- plain register access (the PDI side) ----------------------------------------------

    def u16(self, address: int) -> int:
        return int(struct.unpack_from("<H", self.memory, address)[0])

    def set_u16(self, address: int, value: int) -> None:
        struct.pack_into("<H", self.memory, address, value & 0xFFFF)

    def sm(self, n: int) -> tuple[int, int, int, bool]:
        """SyncManager ``n``: (start, length, control, enabled)."""
        start, length, control, _status, activate = struct.unpack_from("<HHBBB", self.memory,
                                                                      SM_BASE + 8 * n)
        return start, length, control, bool(activate & 1)

    def sm_area(self, n: int) -> bytearray:
        start, length, _control, _enabled = self.sm(n)
        return self.memory[start:start + length]

    def fill_sm(self, n: int, data: bytes) -> None:
        """The PDI writes a whole SM buffer; a mailbox becomes full."""
        start, length, control, _ = self.sm(n)
        self.memory[start:start + length] = data[:length].ljust(length, b"\x00")
        if control & 0x03 == 0x02:
            self._set_full(n, True)

    def empty_mailbox(self, n: int) -> None:
        """The PDI has read SM ``n``'s mailbox."""
        self._set_full(n, False)

    def _set_full(self, n: int, full: bool) -> None:
        self.mailbox_full[n] = full
        status = SM_BASE + 8 * n + 5
        self.memory[status] = (self.memory[status] & ~0x08) | (0x08 if full else 0)

    # -- master access (EtherCAT datagrams) ----------------------------------------------------

    def _overlapping_sms(self, first: int, last: int) -> list[tuple[int, int, int, int]]:
        hits = []
        for n in range(SM_COUNT):
            start, length, control, enabled = self.sm(n)
            if enabled and length and start <= last and first < start + length:
                hits.append((n, start, start + length - 1, control))
        return hits

    def read(self, address: int, length: int) -> Optional[bytes]:
        """Master read; None when the ESC refuses it (an empty read-mailbox)."""
        if length == 0:
            return b""
        last = address + length - 1
        if address < 0 or last >= MEMORY_SIZE:
            return bytes(length)  # **chosen**: beyond the memory reads zeros
        sms = self._overlapping_sms(address, last)
        for n, _start, _end, control in sms:
            if control & 0x03 == 0x02 and not control & 0x04 and not self.mailbox_full[n]:
                return None
            if control & 0x03 == 0x00 and not control & 0x04:
                self.before_sm_read(n)
        if address <= EEPROM_CONTROL + 1 and last >= EEPROM_CONTROL:
            self._refresh_eeprom_status()
        data = bytes(self.memory[address:last + 1])
        for n, _start, end, control in sms:
            if control & 0x03 == 0x02 and not control & 0x04 and last >= end:
                self._set_full(n, False)
                self.on_sm_emptied(n)
        return data

    def write(self, address: int, data: bytes) -> bool:
        """Master write; False when the ESC refuses it (a full write-mailbox)."""
        if not data:
            return True
        last = address + len(data) - 1
        if address < 0 or last >= MEMORY_SIZE:
            return True  # **chosen**: beyond the memory is ignored
        sms = self._overlapping_sms(address, last)
        for n, _start, _end, control in sms:
            if control & 0x03 == 0x02 and control & 0x04 and self.mailbox_full[n]:
                return False
            if self.sm_deactivated[n]:
                return False
        for offset, byte in enumerate(data):
            if _MASK[address + offset]:
                self.memory[address + offset] = byte
        if address <= EEPROM_CONTROL + 1 and last >= EEPROM_CONTROL:
            self._eeprom_command()
        for n in range(SM_COUNT):  # a disabled SyncManager forgets its buffer state
            base = SM_BASE + 8 * n
            if address <= base + 7 and last >= base and not self.sm(n)[3]:
                self._set_full(n, False)
        self.on_write(address, last)
        for n, _start, end, control in sms:
            if control & 0x04 and last >= end:
                if control & 0x03 == 0x02:
                    self._set_full(n, True)
                self.on_sm_filled(n)
        return True

    # -- logical access through the FMMUs ------------------------------------------------

    def fmmus(self) -> list[tuple[int, int, int, int]]:
        """Active FMMUs: (logical start, length, physical start, type bits 0 read / 1 write)."""
        active = []
        for n in range(FMMU_COUNT):
            base = FMMU_BASE + 16 * n
            log, length, _sb, _eb, phys, _pb, kind, enable = struct.unpack_from(
                "<IHBBHBBB", self.memory, base)
            if enable & 1 and length:
                active.append((log, length, phys, kind & 0x03))
        return active

    def logical(self, address: int, data: bytearray, read: bool, write: bool) -> int:
        """An LRD/LWR/LRW at ``address``: copies through the FMMUs; returns the
        working counter increment (read 1, write 2)."""
        wkc = 0
        end = address + len(data)
        mapped = [(log, length, phys, kind) for log, length, phys, kind in self.fmmus()
                  if log < end and address < log + length]
        if write:
            for log, length, phys, kind in mapped:
                if kind & 0x02:
                    first, stop = max(log, address), min(log + length, end)
                    if self.write(phys + first - log, bytes(data[first - address:stop - address])):
                        wkc = 2
        if read:
            for log, length, phys, kind in mapped:
                if kind & 0x01:
                    first, stop = max(log, address), min(log + length, end)
                    got = self.read(phys + first - log, stop - first)
                    if got is not None:
                        data[first - address:stop - address] = got
                        wkc |= 1
        return wkc

    # -- the SII EEPROM interface ----------------------------------------------------------------

    def _refresh_eeprom_status(self) -> None:
        status = self.u16(EEPROM_CONTROL)
        self.set_u16(EEPROM_CONTROL, (status & 0x0701) | EEPROM_READ_8)  # never busy, no error

    def _eeprom_command(self) -> None:
        control = self.u16(EEPROM_CONTROL)
        if control & 0x0700 == 0x0100:  # read
            word = struct.unpack_from("<I", self.memory, EEPROM_ADDRESS)[0]
            chunk = self.eeprom[2 * word:2 * word + 8]
            self.memory[EEPROM_DATA:EEPROM_DATA + 8] = chunk.ljust(8, b"\xff")
        self.set_u16(EEPROM_CONTROL, EEPROM_READ_8)  # done at once: command bits read 0
