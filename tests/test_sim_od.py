"""The shipped EDS and ObjectStore: dictionary contents, CiA 301 abort codes, LocalNode wiring.

Abort codes are those of CiA 301 V4.2 Table 22 as printed in the EPOS4
Communication Guide, chapter 6, Table 6-21.
"""
from __future__ import annotations

import ast
import struct
from pathlib import Path

import canopen
import pytest
from canopen import SdoAbortedError
from canopen.objectdictionary import ODVariable, datatypes
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.simulator import od as od_module
from epos_link.simulator.od import (
    EDS_PATH,
    LOAD_SIGNATURE,
    SAVE_SIGNATURE,
    ObjectStore,
    attach_local_node,
    load_object_dictionary,
    make_local_node,
)

OD = load_object_dictionary(1)

U8, U16, U32 = datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32
I8, I16, I32 = datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32
VS = datatypes.VISIBLE_STRING

# (index, subindex, data type, access) the brief asks the EDS to hold.
REQUIRED = [
    (0x1000, 0, U32, "ro"), (0x1001, 0, U8, "ro"), (0x1008, 0, VS, "const"),
    (0x1009, 0, VS, "const"), (0x100A, 0, VS, "const"),
    (0x1010, 0, U8, "ro"), (0x1010, 1, U32, "rw"),
    (0x1018, 0, U8, "ro"), (0x1018, 1, U32, "ro"), (0x1018, 2, U32, "ro"),
    (0x1018, 3, U32, "ro"), (0x1018, 4, U32, "ro"),
    (0x2000, 0, U8, "rw"), (0x2005, 0, U16, "rw"), (0x2006, 0, U16, "rw"),
    (0x2100, 0, U32, "wo"), (0x30B0, 0, I32, "rw"), (0x603F, 0, U16, "ro"),
    (0x6040, 0, U16, "rw"), (0x6041, 0, U16, "ro"), (0x605A, 0, I16, "rw"),
    (0x6060, 0, I8, "rw"), (0x6061, 0, I8, "ro"), (0x6062, 0, I32, "ro"),
    (0x6064, 0, I32, "ro"), (0x6065, 0, U32, "rw"), (0x6067, 0, U32, "rw"),
    (0x606C, 0, I32, "ro"), (0x607A, 0, I32, "rw"), (0x607C, 0, I32, "rw"),
    (0x607D, 1, I32, "rw"), (0x607D, 2, I32, "rw"), (0x607F, 0, U32, "rw"),
    (0x6081, 0, U32, "rw"), (0x6083, 0, U32, "rw"), (0x6084, 0, U32, "rw"),
    (0x6085, 0, U32, "rw"), (0x6098, 0, I8, "rw"), (0x6099, 1, U32, "rw"),
    (0x6099, 2, U32, "rw"), (0x609A, 0, U32, "rw"), (0x60C5, 0, U32, "rw"),
    (0x60FD, 0, U32, "ro"), (0x60FE, 1, U32, "rw"), (0x60FE, 2, U32, "rw"),
    (0x60FF, 0, I32, "rw"), (0x6502, 0, U32, "ro"),
]


def fresh() -> ObjectStore:
    return ObjectStore(OD)


def abort_of(fn, *args) -> int:
    with pytest.raises(SdoAbortedError) as info:
        fn(*args)
    return info.value.code


# -- the EDS ---------------------------------------------------------------------


def test_eds_ships_inside_the_package() -> None:
    assert EDS_PATH.name == "epos4.eds"
    assert EDS_PATH.parent == Path(od_module.__file__).parent
    assert EDS_PATH.is_file()


@pytest.mark.parametrize(("index", "sub", "data_type", "access"), REQUIRED)
def test_eds_holds_required_objects(index: int, sub: int, data_type: int, access: str) -> None:
    var = fresh().variable(index, sub)
    assert (var.data_type, var.access_type) == (data_type, access)


def test_eds_identity_values() -> None:
    s = fresh()
    assert s.read_value(0x1000) == 0x00020192  # CiA 402 servo drive
    assert s.read_value(0x1008) == "EPOS4"
    assert s.read_value(0x1018, 1) == 0x000000FB  # maxon motor's vendor id
    assert s.read_value(0x1018, 0) == 4
    assert s.read_value(0x6502) == 0x1A5  # pp, pv, hm, csp, csv (CiA 402-2 6502h bits 0, 2, 5, 7, 8)


def test_eds_node_id_substitution() -> None:
    od = canopen.import_od(str(EDS_PATH), 5)
    assert od[0x2000].default == 5
    assert od[0x1200][1].default == 0x605 and od[0x1200][2].default == 0x585
    assert load_object_dictionary(7).node_id == 7


def test_eds_limits_and_fast_defaults() -> None:
    s = fresh()
    assert (s.variable(0x6060, 0).min, s.variable(0x6060, 0).max) == (1, 10)
    assert s.variable(0x6081, 0).max == s.variable(0x607F, 0).max
    assert s.read_value(0x6081) == 1000 and s.read_value(0x6083) == 10000
    assert s.read_value(0x2005) == 500 and s.read_value(0x2006) == 500


# -- reads --------------------------------------------------------------------------


@pytest.mark.parametrize(("index", "sub", "size"), [
    (0x1001, 0, 1), (0x6040, 0, 2), (0x1000, 0, 4), (0x6060, 0, 1), (0x607D, 1, 4)])
def test_read_returns_exact_size(index: int, sub: int, size: int) -> None:
    assert len(fresh().read(index, sub)) == size


def test_read_string_and_signed() -> None:
    s = fresh()
    assert s.read(0x1008, 0) == b"EPOS4"
    assert s.read(0x607D, 1) == struct.pack("<i", -(1 << 31))


# -- abort codes ---------------------------------------------------------------------


@pytest.mark.parametrize(("op", "index", "sub", "data", "code"), [
    ("read", 0x5000, 0, None, 0x06020000),  # object does not exist
    ("write", 0x5000, 0, b"\0", 0x06020000),
    ("read", 0x6040, 1, None, 0x06090011),  # VAR: only subindex 0
    ("read", 0x1018, 5, None, 0x06090011),
    ("write", 0x607D, 3, b"\0\0\0\0", 0x06090011),
    ("read", 0x2100, 0, None, 0x06010001),  # write only
    ("write", 0x6041, 0, b"\0\0", 0x06010002),  # read only
    ("write", 0x1008, 0, b"EPOS5", 0x06010002),  # const
    ("write", 0x1018, 0, b"\4", 0x06010002),  # sub0 of a record is read only
    ("write", 0x6040, 0, b"\6", 0x06070010),  # too short
    ("write", 0x6040, 0, b"\6\0\0", 0x06070010),  # 3 bytes is never right
    ("write", 0x6081, 0, b"\0\0\0\0\0", 0x06070010),  # too long
    ("write", 0x6040, 0, b"\6\0\1\0", 0x06070010),  # non-zero surplus
    ("write", 0x6060, 0, b"\x0b", 0x06090030),  # above HighLimit
    ("write", 0x6060, 0, b"\x00", 0x06090030),  # below LowLimit
    ("write", 0x6081, 0, struct.pack("<I", 0), 0x06090030),
    ("write", 0x6083, 0, struct.pack("<I", 100_000_001), 0x06090030),  # above HighLimit
    ("write", 0x2000, 0, b"\x80", 0x06090030),  # node id 128
    ("write", 0x1010, 1, b"abcd", 0x08000020),  # not the "save" signature
    ("write", 0x1011, 1, b"save", 0x08000020),  # not the "load" signature
])
def test_abort_codes(op: str, index: int, sub: int, data: bytes | None, code: int) -> None:
    s = fresh()
    if op == "read":
        assert abort_of(s.read, index, sub) == code
    else:
        assert abort_of(s.write, index, sub, data) == code


def test_read_only_check_comes_before_length_check() -> None:
    assert abort_of(fresh().write, 0x6041, 0, b"\0\0\0\0\0") == 0x06010002


def test_refused_write_keeps_old_value() -> None:
    s = fresh()
    with pytest.raises(SdoAbortedError):
        s.write(0x6060, 0, b"\x0b")
    assert s.read_value(0x6060) == 1


# -- write lengths: the padding rule --------------------------------------------------


@pytest.mark.parametrize(("index", "data", "value"), [
    (0x6040, b"\x0f\x00", 0x000F),  # exact size
    (0x6040, b"\x0f\x00\x00\x00", 0x000F),  # 4 bytes, zero padding (WriteObject)
    (0x2000, b"\x05\x00\x00\x00", 5),  # U8 padded
    (0x605A, b"\x06\x00\x00\x00", 6),  # I16 positive, zero padding
    (0x6098, b"\xfe\xff\xff\xff", -2),  # I8 negative, sign extension
    (0x6098, b"\xfe\x00\x00\x00", -2),  # I8 negative, zero padding
    (0x6081, b"\x10\x27\x00\x00", 10000),
])
def test_padding_accepted(index: int, data: bytes, value: int) -> None:
    s = fresh()
    s.write(index, 0, data)
    assert s.read_value(index) == value


@pytest.mark.parametrize(("index", "data"), [
    (0x6040, b"\x0f\x00\xff\xff"),  # unsigned: sign extension is not padding
    (0x6098, b"\x05\xff\xff\xff"),  # positive signed value with 0xFF surplus
    (0x6098, b"\xfe\xff\xff\x00"),  # mixed surplus
    (0x605A, b"\x06\x00\x00"),  # 3 bytes
    (0x2000, b"\x05\x00"),  # 2 bytes to a U8: only exact or 4
])
def test_padding_refused(index: int, data: bytes) -> None:
    assert abort_of(fresh().write, index, 0, data) == 0x06070010


def test_fit_length_strings_take_any_length() -> None:
    var = fresh().variable(0x1008, 0)
    assert ObjectStore.fit_length(var, b"a much longer name") == b"a much longer name"


# -- typed and unchecked access, hooks ---------------------------------------------------


def test_set_bypasses_access_rules() -> None:
    s = fresh()
    s.set(0x1001, 0, 0x81)
    assert s.read(0x1001, 0) == b"\x81"
    assert s.get(0x1001) == 0x81


def test_write_value_encodes_at_type_size() -> None:
    s = fresh()
    s.write_value(0x607A, 0, -5)
    assert s.read(0x607A, 0) == struct.pack("<i", -5)
    assert abort_of(s.write_value, 0x607A, 0, 1 << 40) == 0x06090030  # does not fit I32


def test_hooks() -> None:
    s = fresh()
    seen: list[object] = []
    s.add_read_hook(0x6064, 0, lambda: 1234)
    s.add_write_hook(0x6065, 0, seen.append)
    assert s.read_value(0x6064) == 1234
    s.write_value(0x6065, 0, 77)
    assert seen == [77] and s.read_value(0x6065) == 77

    def refuse(value: object) -> None:
        raise SdoAbortedError(0x08000022)

    s.add_write_hook(0x6067, 0, refuse)
    assert abort_of(s.write_value, 0x6067, 0, 5) == 0x08000022
    assert s.read_value(0x6067) == 10  # not stored
    assert abort_of(s.add_read_hook, 0x5555, 0, lambda: 0) == 0x06020000


def test_before_access_runs_on_checked_access_only() -> None:
    s = fresh()
    calls: list[int] = []
    s.before_access = lambda: calls.append(1)
    s.read(0x6041, 0)
    s.write(0x6040, 0, b"\0\0")
    s.get(0x6041)
    assert len(calls) == 2


# -- store / restore parameters (CiA 301 7.5.2.13/14) -----------------------------------


def test_save_and_reset() -> None:
    s = fresh()
    persisted: list[dict[str, object]] = []
    s.on_save = persisted.append
    assert s.read_value(0x1010, 1) == 1  # saves on command
    s.write_value(0x6081, 0, 2500)
    s.write_value(0x6040, 0, 0x0F)  # process data: not saved
    s.write(0x1010, 1, b"save")
    assert struct.unpack("<I", b"save")[0] == SAVE_SIGNATURE
    assert persisted[-1]["0x6081:00"] == 2500
    assert "0x6040:00" not in persisted[-1]
    s.write_value(0x6081, 0, 3000)
    s.reset()
    assert s.read_value(0x6081) == 2500
    assert s.read_value(0x6040) == 0


def test_restore_defaults_takes_effect_on_reset() -> None:
    s = fresh()
    s.write_value(0x6081, 0, 2500)
    s.write_value(0x1010, 1, SAVE_SIGNATURE)
    s.write_value(0x1011, 1, LOAD_SIGNATURE)
    assert s.read_value(0x6081) == 2500
    s.reset()
    assert s.read_value(0x6081) == 1000


def test_load_saved_ignores_unknown_and_readonly_keys() -> None:
    s = fresh()
    s.load_saved({"0x6081:00": 1234, "0x7777:00": 1, "0x6041:00": 5, "0x6040:00": 6})
    assert s.read_value(0x6081) == 1234
    assert s.read_value(0x6040) == 0
    assert s.saved == {"0x6081:00": 1234}


# -- LocalNode wiring ------------------------------------------------------------------


class FakeNetwork:
    """Captures what an SdoServer sends; enough for on_request without a bus."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.sent.append((can_id, bytes(data)))


def node_with_store(node_id: int = 1) -> tuple[canopen.LocalNode, ObjectStore, FakeNetwork]:
    s = ObjectStore(load_object_dictionary(node_id))
    node = make_local_node(s)
    net = FakeNetwork()
    node.sdo.network = net  # type: ignore[assignment]
    return node, s, net


def test_local_node_upload_download_share_the_store() -> None:
    node, s, _ = node_with_store()
    node.sdo.download(0x6081, 0, struct.pack("<I", 4321))
    assert s.read_value(0x6081) == 4321
    s.write_value(0x607A, 0, -99)
    assert node.sdo.upload(0x607A, 0) == struct.pack("<i", -99)
    assert node.sdo[0x1008].raw == "EPOS4"
    s.add_read_hook(0x6041, 0, lambda: 0x0237)
    assert node.sdo[0x6041].raw == 0x0237


@pytest.mark.parametrize(("op", "index", "sub", "data", "code"), [
    ("up", 0x5000, 0, None, 0x06020000),
    ("up", 0x6040, 3, None, 0x06090011),
    ("up", 0x1018, 9, None, 0x06090011),
    ("up", 0x2100, 0, None, 0x06010001),
    ("down", 0x6041, 0, b"\0\0", 0x06010002),
    ("down", 0x6040, 0, b"\0", 0x06070010),
    ("down", 0x6060, 0, b"\x0b", 0x06090030),
    ("down", 0x6060, 0, b"\x0b\x00\x00\x00", 0x06090030),
    ("down", 0x1010, 1, b"nope", 0x08000020),
])
def test_local_node_abort_codes(op: str, index: int, sub: int, data: bytes | None, code: int) -> None:
    node, _, _ = node_with_store()
    if op == "up":
        assert abort_of(node.sdo.upload, index, sub) == code
    else:
        assert abort_of(node.sdo.download, index, sub, data) == code


def test_local_node_accepts_padded_download() -> None:
    node, s, _ = node_with_store()
    node.sdo.download(0x6040, 0, b"\x06\x00\x00\x00")
    assert s.read_value(0x6040) == 6
    assert abort_of(node.sdo.download, 0x6040, 0, b"\x06\x00\x01\x00") == 0x06070010


def test_attach_to_foreign_local_node() -> None:
    s = fresh()
    node = canopen.LocalNode(3, OD)
    attach_local_node(node, s)
    node.sdo.download(0x2005, 0, b"\x64\x00")
    assert s.read_value(0x2005) == 100


# Frames of CiA 301 7.2.4.3: command specifier, index (LE), subindex, 4 data bytes.

def request(cs: int, index: int, sub: int, data: bytes = b"") -> bytes:
    return struct.pack("<BHB", cs, index, sub) + data.ljust(4, b"\0")


def test_sdo_server_expedited_download_size_not_indicated() -> None:
    """0x22 = initiate download, e=1, s=0: the EPOS4 gateway's WriteObject frame."""
    node, s, net = node_with_store(2)
    node.sdo.on_request(0x602, request(0x22, 0x6040, 0, b"\x06\x00\x00\x00"), 0.0)
    assert net.sent == [(0x582, request(0x60, 0x6040, 0))]
    assert s.read_value(0x6040) == 6


def test_sdo_server_expedited_download_size_indicated() -> None:
    node, s, net = node_with_store()
    node.sdo.on_request(0x601, request(0x2B, 0x2005, 0, b"\x2c\x01"), 0.0)  # n=2
    assert net.sent[-1] == (0x581, request(0x60, 0x2005, 0))
    assert s.read_value(0x2005) == 300


@pytest.mark.parametrize(("frame", "code"), [
    (request(0x22, 0x6041, 0, b"\0\0\0\0"), 0x06010002),
    (request(0x22, 0x6040, 0, b"\x06\x00\x01\x00"), 0x06070010),
    (request(0x40, 0x2100, 0), 0x06010001),
    (request(0x40, 0x1234, 0), 0x06020000),
    (request(0x22, 0x6060, 0, b"\x0b\0\0\0"), 0x06090030),
])
def test_sdo_server_abort_frames(frame: bytes, code: int) -> None:
    node, _, net = node_with_store()
    node.sdo.on_request(0x601, frame, 0.0)
    cs, index, sub, sent_code = struct.unpack("<BHBI", net.sent[-1][1])
    assert (cs, index, sub, sent_code) == (0x80, frame[1] | frame[2] << 8, frame[3], code)


def test_sdo_server_expedited_upload() -> None:
    node, _, net = node_with_store()
    node.sdo.on_request(0x601, request(0x40, 0x1000, 0), 0.0)
    assert net.sent[-1] == (0x581, request(0x43, 0x1000, 0, struct.pack("<I", 0x00020192)))


# -- properties ----------------------------------------------------------------------------

WRITABLE = [(v.index, v.subindex) for v in fresh()._variables() if v.writable]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(WRITABLE + [(0x6041, 0), (0x5000, 0), (0x6040, 7)]),
       st.binary(max_size=6))
def test_any_write_either_succeeds_or_aborts(key: tuple[int, int], data: bytes) -> None:
    s = fresh()
    try:
        s.write(key[0], key[1], data)
    except SdoAbortedError as exc:
        assert exc.code in {0x06020000, 0x06090011, 0x06010002, 0x06070010,
                            0x06090030, 0x08000020}
        return
    var: ODVariable = s.variable(*key)
    if var.readable and key[0] not in (0x1010, 0x1011):
        assert s.read(*key) == ObjectStore.fit_length(var, data)


# -- purity ---------------------------------------------------------------------------------

FORBIDDEN = {"serial", "usb", "socket", "asyncio", "threading", "time", "select"}


@pytest.mark.parametrize("module", ["od", "store_restore", "drive", "statemachine", "motion"])
def test_pure_modules_import_no_io(module: str) -> None:
    source = (Path(od_module.__file__).parent / f"{module}.py").read_text()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        else:
            continue
        assert not {n.split(".")[0] for n in names} & FORBIDDEN, names
