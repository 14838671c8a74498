"""epos_link.tools.objects: names and CiA 301 types from the shipped EDS (and a DCF)."""
from __future__ import annotations

import struct
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from epos_link.errors import LocalProtocolError
from epos_link.tools.objects import TYPES, ObjectLookupError, load_directory


@pytest.fixture(scope="module")
def od():  # type: ignore[no-untyped-def]
    return load_directory()


@pytest.mark.parametrize("name", ["Position actual value", "position_actual_value", "POSITION-ACTUAL  value"])
def test_names_match_loosely(od, name: str) -> None:  # type: ignore[no-untyped-def]
    info = od.resolve(name)
    # CiA 402: 6064h Position actual value, INTEGER32, ro.
    assert (info.index, info.subindex, info.type.name, info.access) == (0x6064, 0, "i32", "ro")
    assert not info.writable and info.readable


def test_record_subentries(od) -> None:  # type: ignore[no-untyped-def]
    # CiA 301 1018h Identity object, sub 4 Serial number (UNSIGNED32).
    assert od.resolve("Identity object.Serial number").address == "0x1018/0x04"
    assert od.resolve("Serial number").address == "0x1018/0x04"  # unique on its own
    assert od.resolve("Identity object", 1).name == "Identity object.Vendor-ID"
    with pytest.raises(ObjectLookupError, match="has subentries: give a SUBINDEX"):
        od.resolve("Identity object")


def test_ambiguous_and_unknown_names(od) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ObjectLookupError, match="several objects"):
        od.resolve("Transmission type")  # RPDO1 and TPDO1 communication parameters
    with pytest.raises(ObjectLookupError, match="did you mean 'profile_velocity'"):
        od.resolve("Profile velocty")
    assert isinstance(ObjectLookupError("x"), LocalProtocolError)


def test_index_lookup_and_strings(od) -> None:  # type: ignore[no-untyped-def]
    assert od.find(0x1008, 0).type.name == "str"  # VISIBLE_STRING
    assert od.find(0x5FFF, 0) is None
    assert od.find(0x6064, 1) is None  # a VAR has no subindex 1
    assert od.name_of(0x6081, 0) == "Profile velocity"


def test_bad_eds_is_a_lookup_error(tmp_path: Path) -> None:
    with pytest.raises(ObjectLookupError, match="no such file"):
        load_directory(str(tmp_path / "missing.eds"))


@pytest.mark.parametrize("name,data,value", [
    ("i32", bytes.fromhex("9CFFFFFF"), -100),
    ("u16", bytes.fromhex("0F00AAAA"), 15),          # ReadObject padding is ignored (guide 2.1.1.1)
    ("i8", b"\xFB\x00\x00\x00", -5),
    ("bool", b"\x01\x00\x00\x00", True),
    ("f32", struct.pack("<f", 1.5), 1.5),
    ("str", b"EPOS4\x00\x00", "EPOS4"),
    ("bytes", b"\x01\x02", b"\x01\x02"),
    ("u64", (2**40 + 3).to_bytes(8, "little"), 2**40 + 3),
])
def test_decode(name: str, data: bytes, value: object) -> None:
    assert TYPES[name].decode(data) == value


def test_encode_range_and_parse_errors() -> None:
    with pytest.raises(LocalProtocolError, match="out of range for u8"):
        TYPES["u8"].encode(256)
    with pytest.raises(LocalProtocolError, match="not a decimal or 0x-hex number"):
        TYPES["i32"].parse("1.5")
    with pytest.raises(LocalProtocolError, match="not a boolean"):
        TYPES["bool"].parse("maybe")
    with pytest.raises(LocalProtocolError, match="finite"):
        TYPES["f32"].parse("nan")
    with pytest.raises(LocalProtocolError, match="cannot hold a i32"):
        TYPES["i32"].decode(b"\x01")
    assert TYPES["u16"].parse("0x1F") == 31 and TYPES["i16"].parse("-5") == -5
    assert TYPES["bytes"].parse("01 02 ff") == b"\x01\x02\xff"


@given(st.sampled_from(["i8", "i16", "i32", "i64", "u8", "u16", "u32", "u64"]), st.data())
def test_integer_round_trip(name: str, data: st.DataObject) -> None:
    typ = TYPES[name]
    bits = 8 * typ.size
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if typ.signed else (0, (1 << bits) - 1)
    value = data.draw(st.integers(lo, hi))
    encoded = typ.encode(value)
    assert len(encoded) == typ.size and typ.decode(encoded + b"\xEE" * 3) == value
    assert typ.parse(str(value)) == value


@pytest.mark.parametrize("text, address", [
    ("0x6064", (0x6064, None)), ("24676", (0x6064, None)), ("0x1018/4", (0x1018, 4)),
    ("0x1018/0x04", (0x1018, 4)), (" 0x1018 : 4 ", (0x1018, 4)),
    ("Position actual value", None), ("Identity object.Serial number", None), ("a/b", None)])
def test_object_words_are_addresses_or_names(text: str, address: object) -> None:
    from epos_link.tools.objects import parse_address

    assert parse_address(text) == address


@pytest.mark.parametrize("text, words", [("0x10000", "index is not 0..0xFFFF"),
                                         ("0x1018/0x100", "subindex is not 0..0xFF"),
                                         ("0x1018/four", "'four' is not a decimal")])
def test_bad_addresses_say_what_is_wrong(od, text: str, words: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ObjectLookupError, match=words):
        od.locate(text)


def test_locate_is_one_parser_for_both_subindex_forms(od) -> None:  # type: ignore[no-untyped-def]
    slash, separate = od.locate("0x1018/4"), od.locate("0x1018", 4)
    assert slash == separate and slash[2].name == "Identity object.Serial number"
    with pytest.raises(ObjectLookupError, match="names its subindex"):
        od.locate("0x1018/4", 4)
    with pytest.raises(ObjectLookupError, match=r"INDEX/SUBINDEX \(0x6064, 0x1018/4\)"):
        od.locate("no such thing at all")
