from hypothesis import given, strategies as st

from epos_link.crc import frame_crc, swap_pairs
from tests.reference import calc_field_crc, crc_words


def test_guide_vectors() -> None:
    # 2.2.9 Table 2-5: ReadObject 0x30B0/0 on node 1 -> CRC 0x622E
    data = bytes.fromhex("01 B0 30 00")
    assert calc_field_crc(crc_words(0x60, data)) == 0x622E
    assert frame_crc(0x60, 2, data) == 0x622E
    # Table 2-6: the answer, data words 0x0000 0x0000 0x9001 0x0000 -> CRC 0x5C9A
    data = bytes.fromhex("00 00 00 00 01 90 00 00")
    assert calc_field_crc([0x0400, 0x0000, 0x0000, 0x9001, 0x0000, 0x0000]) == 0x5C9A
    assert frame_crc(0x00, 4, data) == 0x5C9A


@given(st.integers(0, 255), st.binary(max_size=286).filter(lambda b: len(b) % 2 == 0))
def test_crc_hqx_matches_the_guides_bitwise_algorithm(opcode: int, data: bytes) -> None:
    assert frame_crc(opcode, len(data) // 2, data) == calc_field_crc(crc_words(opcode, data))


def test_swap_pairs() -> None:
    assert swap_pairs(b"\x01\x02\x03\x04") == b"\x02\x01\x04\x03"
