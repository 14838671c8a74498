"""The mailbox (ETG.1000.6 5.6) and a CoE SDO server (ETG.1000.6 5.6.2, CiA 301 SDO). Pure.

A mailbox message::

    mailbox header  length(2) address(2) channel/priority(1) type(bits 0..3)|counter(bits 4..6)(1)
    CoE header      number(bits 0..8)|service(bits 12..15)(2): 2 = SDO request, 3 = SDO response
    SDO             command(1) index(2) subindex(1) data(4) [more data: normal transfers]

``length`` counts the bytes after the mailbox header. Services:

* upload (command 0x40): expedited (0x43 | (4 - n) << 2) up to 4 bytes; else
  normal (0x41 + complete size, then as many bytes as the mailbox holds) and
  upload segments (request 0x60 | toggle; response toggle | last, data after one
  command byte; a last segment shorter than 7 bytes is padded to 7 and bits
  1..3 give the unused bytes, as CiA 301 7.2.4.3.5);
* download: expedited (0x23 | (4 - n) << 2, or 0x22/0x27 without size: the
  four bytes), normal (0x21 + size + data) and download segments (toggle |
  (7 - n) << 1 | last, 0x20 | toggle answers); the object is written when all
  bytes are there;
* complete access upload (command 0x50, bit 4 "complete access", ETG.1000.6
  5.6.2.1.1 and 5.6.2.2.1; the EPOS4 offers it: guide Table 4-16 "SDO Complete
  Access"): subindex 0 or 1 to the object's subindex 0 value, all subindices in
  one transfer: subindex 0 as 16 bits (the 8-bit count and a padding byte, as
  SOEM's ``ec_PDOassignt``/``ec_PDOdesct``/``ec_SMcommtypet`` read it: ``uint8 n;
  uint8 nu1;``), then subindices 1..n, each in its own size. ``ca_padding=False``
  leaves the padding byte out, as some slave stacks do (issue 31: a KickCAT
  slave), which makes SOEM's ``config_map`` misread the PDO assignment.
  **chosen**: a complete access download aborts with 0x06010000 "unsupported
  access" (no master of ours writes that way);
* any failure answers an SDO abort (CoE service 2, "SDO request", as ETG.1000.6
  5.6.2.7 has it; 0x80, index, subindex, code: CiA 301
  Table 22, guide Table 6-21); an unknown command aborts with 0x05040001.

Other mailbox types, and CoE services other than SDO requests, answer a
mailbox error (type 0, ETG.1000.6 Table 29: 0x0002 unsupported protocol,
0x0004 service not supported).

Objects come from an :class:`ObjectAccess`; a failure is any exception with
an integer ``code`` (e.g. canopen's ``SdoAbortedError``), which becomes the
abort code; any other exception aborts with 0x08000000 "general error".
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Optional, Protocol

__all__ = ["ObjectAccess", "SdoAbort", "SdoServer", "MailboxHeader", "mailbox_message",
           "parse_mailbox", "MBX_ERROR", "MBX_COE", "ABORT_TOGGLE", "ABORT_COMMAND",
           "ABORT_UNSUPPORTED", "ABORT_GENERAL"]

MBX_ERROR, MBX_COE = 0x00, 0x03
COE_SDO_REQUEST, COE_SDO_RESPONSE = 2, 3
ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED = 0x06010000
ABORT_LENGTH = 0x06070010
ABORT_GENERAL = 0x08000000
MBXERR_UNSUPPORTED_PROTOCOL = 0x0002
MBXERR_SERVICE_NOT_SUPPORTED = 0x0004
MBXERR_SIZE_TOO_SHORT = 0x0006


class ObjectAccess(Protocol):
    def read(self, index: int, subindex: int) -> bytes: ...

    def write(self, index: int, subindex: int, data: bytes) -> None: ...


class SdoAbort(Exception):
    """An SDO abort with its CiA 301 code."""

    def __init__(self, code: int) -> None:
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


@dataclass(frozen=True)
class MailboxHeader:
    length: int
    address: int
    channel: int
    kind: int
    counter: int


def parse_mailbox(buffer: bytes) -> tuple[MailboxHeader, bytes]:
    """The header and the ``length`` data bytes of a mailbox buffer (ValueError if short)."""
    if len(buffer) < 6:
        raise ValueError("a mailbox message has a 6-byte header")
    length, address, channel, kind = struct.unpack_from("<HHBB", buffer)
    if 6 + length > len(buffer):
        raise ValueError(f"mailbox length {length} exceeds the buffer")
    return MailboxHeader(length, address, channel & 0x3F, kind & 0x0F, (kind >> 4) & 0x07), \
        bytes(buffer[6:6 + length])


def mailbox_message(kind: int, counter: int, data: bytes) -> bytes:
    return struct.pack("<HHBB", len(data), 0, 0, (kind & 0x0F) | ((counter & 0x07) << 4)) + data


def mailbox_error(detail: int) -> tuple[int, bytes]:
    return MBX_ERROR, struct.pack("<HH", 0x0001, detail)


def _code(exc: Exception) -> int:
    code = getattr(exc, "code", None)
    return code if isinstance(code, int) and 0 < code <= 0xFFFFFFFF else ABORT_GENERAL


class SdoServer:
    """Answers mailbox messages (type and data) with one reply each; keeps the state
    of one segmented transfer. ``mailbox_size`` is the SM1 (send) mailbox size."""

    def __init__(self, objects: ObjectAccess, mailbox_size: int, *,
                 ca_padding: bool = True) -> None:
        self.objects = objects
        self.mailbox_size = mailbox_size
        self.ca_padding = ca_padding
        self._upload: Optional[tuple[int, int, bytes, int]] = None  # index, sub, data, toggle
        self._download: Optional[tuple[int, int, int, bytearray, int]] = None  # + size, toggle
        self._last: Optional[tuple[int, int]] = None  # the object of a running segmented transfer

    @property
    def _room(self) -> int:
        """SDO data bytes after the 6-byte mailbox, 2-byte CoE and 1-byte command headers."""
        return self.mailbox_size - 9

    def handle(self, kind: int, data: bytes) -> tuple[int, bytes]:
        """(reply type, reply data) for one received message."""
        if kind != MBX_COE:
            return mailbox_error(MBXERR_UNSUPPORTED_PROTOCOL)
        if len(data) < 2:
            return mailbox_error(MBXERR_SIZE_TOO_SHORT)
        (coe,) = struct.unpack_from("<H", data)
        if coe >> 12 != COE_SDO_REQUEST:
            return mailbox_error(MBXERR_SERVICE_NOT_SUPPORTED)
        sdo = data[2:]
        if len(sdo) < 1:
            return mailbox_error(MBXERR_SIZE_TOO_SHORT)
        try:
            reply = self._sdo(sdo)
        except SdoAbort as exc:
            self._upload = self._download = None
            index, sub = (struct.unpack_from("<HB", sdo, 1) if len(sdo) >= 4 else (0, 0))
            if self._last is not None:
                index, sub = self._last
            # ETG.1000.6 5.6.2.7 "Abort SDO Transfer": its CoE header names the service
            # SDO *request* (2), not response; SOEM's ecx_SDOread takes an abort only so
            # (a response of the same index is read as data: "data container too small").
            return MBX_COE, struct.pack("<H", COE_SDO_REQUEST << 12) + struct.pack(
                "<BHBI", 0x80, index, sub, exc.code)
        return MBX_COE, struct.pack("<H", COE_SDO_RESPONSE << 12) + reply

    def _sdo(self, sdo: bytes) -> bytes:
        command = sdo[0]
        ccs = command >> 5
        self._last = None
        if ccs in (1, 2):
            if len(sdo) < 8:
                raise SdoAbort(ABORT_COMMAND)
            index, sub = struct.unpack_from("<HB", sdo, 1)
            self._upload = self._download = None
            if command & 0x10:  # complete access
                if ccs == 1 or sub > 1:
                    raise SdoAbort(ABORT_UNSUPPORTED)
                return self._send_value(index, sub, self._complete(index, sub))
            return self._initiate_upload(index, sub) if ccs == 2 else \
                self._initiate_download(command, index, sub, sdo)
        if ccs == 3:
            return self._upload_segment(command)
        if ccs == 0:
            return self._download_segment(command, sdo)
        if ccs == 4:  # an abort from the master: forget the transfer; no answer is due,
            self._upload = self._download = None  # **chosen**: we answer it with itself
            return bytes(sdo[:8]).ljust(8, b"\x00")
        raise SdoAbort(ABORT_COMMAND)

    def _call_read(self, index: int, sub: int) -> bytes:
        try:
            return bytes(self.objects.read(index, sub))
        except SdoAbort:
            raise
        except Exception as exc:  # the store's abort (canopen SdoAbortedError) or a bug
            raise SdoAbort(_code(exc)) from None

    def _call_write(self, index: int, sub: int, data: bytes) -> None:
        try:
            self.objects.write(index, sub, data)
        except SdoAbort:
            raise
        except Exception as exc:
            raise SdoAbort(_code(exc)) from None

    def _complete(self, index: int, first: int) -> bytes:
        """The object's subindices ``first``..n in one buffer (module docstring)."""
        count = self._call_read(index, 0)[:1]
        if not count:
            raise SdoAbort(ABORT_UNSUPPORTED)
        out = bytearray()
        if first == 0:
            out += count + (b"\x00" if self.ca_padding else b"")
        for sub in range(1, count[0] + 1):
            out += self._call_read(index, sub)
        return bytes(out)

    def _initiate_upload(self, index: int, sub: int) -> bytes:
        return self._send_value(index, sub, self._call_read(index, sub))

    def _send_value(self, index: int, sub: int, value: bytes) -> bytes:
        if 0 < len(value) <= 4:
            return struct.pack("<BHB", 0x43 | ((4 - len(value)) << 2), index, sub) + value.ljust(4, b"\x00")
        first = value[:self._room - 7]  # after index(2), subindex(1), size(4)
        if len(first) < len(value):
            self._upload = (index, sub, value[len(first):], 0)
        return struct.pack("<BHBI", 0x41, index, sub, len(value)) + first

    def _upload_segment(self, command: int) -> bytes:
        if self._upload is None:
            raise SdoAbort(ABORT_COMMAND)
        index, sub, rest, toggle = self._upload
        self._last = (index, sub)
        if (command >> 4) & 1 != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        chunk, rest = rest[:self._room], rest[self._room:]
        last = not rest
        self._upload = None if last else (index, sub, rest, toggle ^ 1)
        unused = max(0, 7 - len(chunk))
        return bytes([(toggle << 4) | (unused << 1) | int(last)]) + chunk.ljust(7, b"\x00")

    def _initiate_download(self, command: int, index: int, sub: int, sdo: bytes) -> bytes:
        ok = struct.pack("<BHBI", 0x60, index, sub, 0)
        if command & 0x02:  # expedited
            n = 4 - ((command >> 2) & 0x03) if command & 0x01 else 4
            self._call_write(index, sub, bytes(sdo[4:4 + n]))
            return ok
        if not command & 0x01:
            raise SdoAbort(ABORT_LENGTH)  # **chosen**: a normal download must give its size
        (size,) = struct.unpack_from("<I", sdo, 4)
        data = bytearray(sdo[8:8 + size])
        if len(data) >= size:
            self._call_write(index, sub, bytes(data[:size]))
        else:
            self._download = (index, sub, size, data, 0)
        return ok

    def _download_segment(self, command: int, sdo: bytes) -> bytes:
        if self._download is None:
            raise SdoAbort(ABORT_COMMAND)
        index, sub, size, data, toggle = self._download
        self._last = (index, sub)
        if (command >> 4) & 1 != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        payload = sdo[1:]
        if len(payload) <= 7:  # CiA 301: bits 1..3 = bytes without data in a 7-byte segment
            payload = payload[:7 - ((command >> 1) & 0x07)]
        data += payload
        if command & 0x01:
            self._download = None
            if len(data) < size:
                raise SdoAbort(ABORT_LENGTH)
            self._call_write(index, sub, bytes(data[:size]))
        else:
            self._download = (index, sub, size, data, toggle ^ 1)
        return bytes([0x20 | (toggle << 4)]) + bytes(7)
