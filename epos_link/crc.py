"""CRC-CCITT of MAXON SERIAL V2 (guide 2.2.2 and 2.2.3).

The guide's ``CalcFieldCRC`` feeds 16-bit words MSB first through the
polynomial x^16+x^12+x^5+1 and appends a zero word (the augmented form).
That is exactly CRC-16/XMODEM of the words serialised high byte first, which
``binascii.crc_hqx`` computes in C. The first word is ``Len << 8 | OpCode``
(``dataArray[0]: HighByte(Len) + LowByte(OpCode)``); the data words follow
as received (low byte first on the wire), so on the wire the bytes of each
pair are swapped before the CRC sees them.
"""
from __future__ import annotations

from binascii import crc_hqx


def swap_pairs(data: bytes) -> bytes:
    """Swap the two bytes of every 16-bit word (length must be even)."""
    out = bytearray(len(data))
    out[0::2] = data[1::2]
    out[1::2] = data[0::2]
    return bytes(out)


def frame_crc(opcode: int, length_words: int, data: bytes) -> int:
    """CRC over OpCode, Len and the unstuffed data words of one frame."""
    return crc_hqx(swap_pairs(bytes((opcode, length_words)) + data), 0)
