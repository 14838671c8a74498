"""Reference implementations written from the guide, independent of our codec.

``calc_field_crc`` is a line-by-line port of the guide's ``CalcFieldCRC``
(EPOS4 Communication Guide 2.2.3, Figure 2-6). ``reference_frame`` builds a
frame the way 2.2.2 and 2.2.4 describe it, using that CRC. Tests use these to
check our codec; they must never import from epos_link.
"""
from __future__ import annotations


def calc_field_crc(words: list[int]) -> int:
    crc = 0
    for c in words:  # while (numberOfWords--)
        shifter = 0x8000  # Initialize BitX to Bit15
        while True:
            carry = crc & 0x8000  # Check if Bit15 of CRC is set
            crc = (crc << 1) & 0xFFFF  # CRC = CRC * 2
            if c & shifter:
                crc += 1  # CRC = CRC + 1, if BitX is set in c
            if carry:
                crc ^= 0x1021  # CRC = CRC XOR G(x), if carry is true
            shifter >>= 1
            if not shifter:
                break
    return crc


def crc_words(opcode: int, data: bytes) -> list[int]:
    """dataArray of 2.2.3: [Len<<8 | OpCode, Data[0], ..., Data[n-1], 0x0000]."""
    assert len(data) % 2 == 0
    words = [(len(data) // 2) << 8 | opcode]
    words += [data[i] | data[i + 1] << 8 for i in range(0, len(data), 2)]  # low byte first
    return words + [0x0000]  # the ZeroWord


def reference_frame(opcode: int, data: bytes) -> bytes:
    crc = calc_field_crc(crc_words(opcode, data))
    body = [opcode, len(data) // 2, *data, crc & 0xFF, crc >> 8]
    stuffed: list[int] = []
    for b in body:
        stuffed.append(b)
        if b == 0x90:  # 2.2.4: DLE between OpCode and CRC is doubled
            stuffed.append(0x90)
    return bytes([0x90, 0x02, *stuffed])


# The guide's example frames, 2.2.9, Tables 2-5 and 2-6 (transmission order as printed).
GUIDE_REQUEST = bytes.fromhex("90 02 60 02 01 B0 30 00 2E 62")
GUIDE_ANSWER = bytes.fromhex("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")
