"""The pure EtherCAT slave core: frames, registers, SII, CoE SDO, ESM, FMMUs, watchdog.

Golden facts come from ETG.1000.4/6 as SOEM uses them (ethercatbase.c, ethercatmain.c,
ethercatconfig.c, ethercatcoe.c), not from our encoder.
"""
from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings, strategies as st

from epos_link.simulator.ethercat.coe import SdoAbort
from epos_link.simulator.ethercat.frame import (Command, Datagram, FrameError, build_frame,
                                                parse_frame)
from epos_link.simulator.ethercat.segment import Segment
from epos_link.simulator.ethercat.sii import crc8
from epos_link.simulator.ethercat.slave import EthercatSlave
from tests.ecat_master import (ETH, STATION, al_request, fprd, fpwr, logical, sdo, sii_read,
                               sm, to_preop, upload, xfer)


class Objects:
    """A dictionary of raw values standing in for the drive's object store."""

    def __init__(self) -> None:
        self.values: dict[tuple[int, int], bytes] = {
            (0x1018, 1): struct.pack("<I", 0xFB), (0x6041, 0): b"\x40\x02",
            (0x6064, 0): struct.pack("<i", -5), (0x606C, 0): bytes(4), (0x6061, 0): b"\x08",
            (0x603F, 0): bytes(2), (0x2100, 0): bytes(range(100)),
        }
        for index, entries in ((0x1600, (0x60400010, 0x607A0020, 0x60FF0020, 0x60600008)),
                               (0x1A00, (0x60410010, 0x60640020, 0x606C0020, 0x60610008,
                                         0x603F0010))):
            self.values[(index, 0)] = bytes([len(entries)])
            for n, e in enumerate(entries, 1):
                self.values[(index, n)] = struct.pack("<I", e)

    def read(self, index: int, sub: int) -> bytes:
        if (index, sub) not in self.values:
            raise SdoAbort(0x06020000)
        return self.values[(index, sub)]

    def write(self, index: int, sub: int, data: bytes) -> None:
        if index == 0x6060 and data == b"\x00":
            raise SdoAbort(0x06090030)
        self.values[(index, sub)] = bytes(data)


def segment(n: int = 1) -> tuple[Segment, list[Objects]]:
    objects = [Objects() for _ in range(n)]
    return Segment([EthercatSlave(o, serial=i + 1) for i, o in enumerate(objects)]), objects


# -- frames ---------------------------------------------------------------------------------

def test_frame_layout_is_as_etg1000_4_draws_it() -> None:
    # A BRD of 2 bytes at ADO 0x0000, index 0x11 (SOEM's ecx_BRD of ECT_REG_TYPE), by hand.
    raw = ETH + bytes([0x0E, 0x10]) + bytes([7, 0x11, 0, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 0])
    ethernet, (dg,) = parse_frame(raw + bytes(60 - len(raw)))
    assert ethernet == ETH and (dg.command, dg.index, dg.adp, dg.ado, dg.wkc) == (7, 0x11, 0, 0, 0)
    assert build_frame(ETH, [dg]) == raw + bytes(60 - len(raw))


@pytest.mark.parametrize("raw", [
    b"", ETH, ETH[:12] + b"\x08\x00" + bytes(50),           # too short, not 0x88A4
    ETH + bytes([0x0E, 0x20]) + bytes(14),                    # type 2, not datagrams
    ETH + bytes([0x40, 0x10]) + bytes(14),                    # length past the frame
    ETH + bytes([0x0E, 0x10]) + bytes([7, 0, 0, 0, 0, 0, 9, 0, 0, 0, 0, 0, 0, 0]),  # data past
    ETH + bytes([0x0C, 0x10]) + bytes([7, 0, 0, 0, 0, 0, 0, 0x80, 0, 0, 0, 0]),      # "more", none
])
def test_damaged_frames_raise_frame_error_and_the_segment_drops_them(raw: bytes) -> None:
    with pytest.raises(FrameError):
        parse_frame(raw)
    assert segment()[0].handle(raw, 0.0) is None


def test_processed_frame_has_the_locally_administered_bit_in_its_source_mac() -> None:
    seg, _ = segment()
    reply = seg.handle(build_frame(ETH, [Datagram(Command.BRD, 1, 0, bytearray(2))]), 0.0)
    assert reply is not None and reply[6] == 0x03 and reply[7:12] == ETH[7:12]


# -- addressing and working counters ---------------------------------------------------------

def test_broadcast_read_counts_every_slave_and_ors_their_data() -> None:
    seg, _ = segment(3)
    dg = xfer(seg, Command.BRD, 0, 0x0000, length=2)  # SOEM ecx_detect_slaves: wkc = slaves
    assert dg.wkc == 3 and dg.data == bytearray([0x11, 0x02])
    assert dg.adp == 3  # each slave incremented the position


def test_auto_increment_reaches_the_slave_at_each_position() -> None:
    seg, _ = segment(3)
    for position in range(3):  # SOEM: ADP = 1 - slave, i.e. 0, -1, -2
        assert xfer(seg, Command.APWR, -position, 0x0010, struct.pack("<H", 0x1001 + position)).wkc == 1
    for position in range(3):
        dg = xfer(seg, Command.APRD, -position, 0x0010, length=2)
        assert dg.wkc == 1 and struct.unpack("<H", dg.data)[0] == 0x1001 + position
    assert xfer(seg, Command.APRD, -3, 0x0010, length=2).wkc == 0  # nobody at position 3
    assert fprd(seg, 0x0010, 2, station=0x1002) == b"\x02\x10"
    assert xfer(seg, Command.FPRD, 0x7777, 0x0010, length=2).wkc == 0


def test_read_write_commands_count_three_and_return_the_old_value() -> None:
    seg, _ = segment()
    xfer(seg, Command.APWR, 0, 0x0010, struct.pack("<H", STATION))
    dg = xfer(seg, Command.FPRW, STATION, 0x0420, struct.pack("<H", 500))
    assert dg.wkc == 3 and struct.unpack("<H", dg.data)[0] == 1000  # the ESC default, 100 ms
    assert fprd(seg, 0x0420, 2) == struct.pack("<H", 500)


def test_armw_reads_at_the_addressed_slave_and_writes_the_others() -> None:
    seg, _ = segment(2)
    xfer(seg, Command.APWR, 0, 0x0010, b"\x01\x10")
    xfer(seg, Command.APWR, -1, 0x0010, b"\x02\x10")
    fpwr(seg, 0x0910, b"\x33" * 4, station=0x1001)
    dg = xfer(seg, Command.ARMW, 0, 0x0910, length=4)
    assert dg.wkc == 2 and dg.data == b"\x33" * 4
    assert fprd(seg, 0x0910, 4, station=0x1002) == b"\x33" * 4


def test_read_only_registers_ignore_writes_and_dl_status_shows_the_line() -> None:
    seg, _ = segment(2)
    xfer(seg, Command.APWR, 0, 0x0010, b"\x01\x10")
    xfer(seg, Command.APWR, -1, 0x0010, b"\x02\x10")
    assert fpwr(seg, 0x0000, b"\xAA\xBB", station=0x1001) == 1  # counted, not stored
    assert fprd(seg, 0x0000, 2, station=0x1001) == b"\x11\x02"
    fpwr(seg, 0x0130, b"\x08\x00", station=0x1001)
    assert fprd(seg, 0x0130, 2, station=0x1001) == b"\x01\x00"
    first = struct.unpack("<H", fprd(seg, 0x0110, 2, station=0x1001))[0]
    last = struct.unpack("<H", fprd(seg, 0x0110, 2, station=0x1002))[0]
    # SOEM ecx_config_init: (topology & 0x0300) == 0x0200 -> port 0 open, 0x0C00 -> port 1
    assert first & 0x0300 == 0x0200 and first & 0x0C00 == 0x0800
    assert last & 0x0300 == 0x0200 and last & 0x0C00 != 0x0800


# -- SII -----------------------------------------------------------------------------------------

def test_sii_reads_through_the_eeprom_interface() -> None:
    seg, _ = segment()
    xfer(seg, Command.APWR, 0, 0x0010, struct.pack("<H", STATION))
    assert struct.unpack("<H", fprd(seg, 0x0502, 2))[0] & 0x0040  # 8-byte reads (EC_ESTAT_R64)
    config = sii_read(seg, 0x0000) + sii_read(seg, 0x0004)
    assert config[14] == crc8(config[:14])
    vendor, product = struct.unpack("<II", sii_read(seg, 0x0008))
    revision, serial = struct.unpack("<II", sii_read(seg, 0x000C))
    assert (vendor, product, revision, serial) == (0xFB, 0x69500000, 0x01700000, 1)
    rx_offset, rx_size, tx_offset, tx_size = struct.unpack("<4H", sii_read(seg, 0x0018))
    assert (rx_offset, rx_size, tx_offset, tx_size) == (0x1000, 48, 0x1030, 48)
    assert struct.unpack("<H", sii_read(seg, 0x001C)[:2])[0] & 0x0004  # CoE
    category, words = struct.unpack("<HH", sii_read(seg, 0x0040)[:4])
    assert category == 10 and words > 0  # strings first


# -- ESM --------------------------------------------------------------------------------------------

def test_esm_needs_the_mailbox_sync_managers_for_pre_op() -> None:
    seg, _ = segment()
    xfer(seg, Command.APWR, 0, 0x0010, struct.pack("<H", STATION))
    assert al_request(seg, 2) == (0x11, 0x0016)  # invalid mailbox configuration
    assert al_request(seg, 4) == (0x11, 0x0016)  # no acknowledge: a higher state is ignored
    fpwr(seg, 0x0800, sm(0x1000, 48, 0x26) + sm(0x1030, 48, 0x22))
    assert al_request(seg, 0x12) == (2, 0)       # acknowledged, then PRE-OP


@pytest.mark.parametrize("request_, code", [(8, 0x0011), (4 | 0x10, 0x0011), (3, 0x0013), (5, 0x0012)])
def test_esm_refuses_what_it_cannot_do(request_: int, code: int) -> None:
    seg, _ = segment()
    xfer(seg, Command.APWR, 0, 0x0010, struct.pack("<H", STATION))
    fpwr(seg, 0x0800, sm(0x1000, 48, 0x26) + sm(0x1030, 48, 0x22))
    if request_ & 0x10:  # from INIT straight to SAFE-OP
        request_ &= 0x0F
    assert al_request(seg, request_) == (0x11, code)


def test_esm_checks_the_process_data_sync_managers_against_the_mapping() -> None:
    seg, _ = segment()
    to_preop(seg)
    assert al_request(seg, 4) == (0x12, 0x001D)  # no SM2
    fpwr(seg, 0x0810, sm(0x1060, 11, 0x64) + sm(0x10F0, 12, 0x20))
    assert al_request(seg, 0x14) == (0x12, 0x001E)  # SM3 one byte short of 13
    fpwr(seg, 0x0818, sm(0x10F0, 13, 0x20))
    assert al_request(seg, 0x14) == (4, 0)
    assert al_request(seg, 8) == (8, 0)
    assert al_request(seg, 1) == (1, 0)  # down in one step is always allowed


# -- CoE -----------------------------------------------------------------------------------------

def test_sdo_expedited_upload_and_download() -> None:
    seg, objects = segment()
    to_preop(seg)
    assert upload(seg, 0x1018, 1) == (0x43, b"\xFB\x00\x00\x00")
    reply = sdo(seg, struct.pack("<HBHBI", 0x2000, 0x2F, 0x6060, 0, 8))  # 1 byte, expedited
    assert reply[2] == 0x60 and objects[0].values[(0x6060, 0)] == b"\x08"
    reply = sdo(seg, struct.pack("<HBHBI", 0x2000, 0x2F, 0x6060, 0, 0))
    assert reply[2] == 0x80 and struct.unpack_from("<HBI", reply, 3) == (0x6060, 0, 0x06090030)
    assert upload(seg, 0x1234, 0) == (0x80, struct.pack("<I", 0x06020000))


def test_sdo_segmented_upload_and_download_of_100_bytes() -> None:
    seg, objects = segment()
    to_preop(seg)
    assert upload(seg, 0x2100, 0) == (0x41, bytes(range(100)))
    value = bytes(range(200, 250)) + bytes(range(50))
    # normal download: size 100, as much as fits, then segments (SOEM ecx_SDOwrite)
    first = 48 - 6 - 10
    assert sdo(seg, struct.pack("<HBHBI", 0x2000, 0x21, 0x2100, 0, 100) + value[:first])[2] == 0x60
    rest, toggle = value[first:], 0
    while rest:
        chunk, rest = rest[:48 - 9], rest[48 - 9:]
        command = (toggle << 4) | (0 if rest else 1)
        if len(chunk) < 7:
            command |= (7 - len(chunk)) << 1
        assert sdo(seg, struct.pack("<HB", 0x2000, command) + chunk.ljust(7, b"\x00"))[2] == 0x20 | toggle << 4
        toggle ^= 1
    assert objects[0].values[(0x2100, 0)] == value


def test_sdo_toggle_error_aborts() -> None:
    seg, _ = segment()
    to_preop(seg)
    upload_reply = sdo(seg, struct.pack("<HBHBI", 0x2000, 0x40, 0x2100, 0, 0))
    assert upload_reply[2] == 0x41
    reply = sdo(seg, struct.pack("<HB7x", 0x2000, 0x70))  # toggle 1 first: wrong
    assert reply[2] == 0x80 and struct.unpack_from("<HBI", reply, 3) == (0x2100, 0, 0x05030000)


def test_pdo_assignment_objects_and_their_state_rule() -> None:
    seg, _ = segment()
    to_preop(seg)
    assert upload(seg, 0x1C00, 0)[1] == b"\x04" and upload(seg, 0x1C00, 3)[1] == b"\x03"
    assert upload(seg, 0x1C12, 1)[1] == b"\x00\x16" and upload(seg, 0x1C13, 1)[1] == b"\x00\x1A"
    fpwr(seg, 0x0810, sm(0x1060, 11, 0x64) + sm(0x10F0, 13, 0x20))
    assert al_request(seg, 4) == (4, 0)
    reply = sdo(seg, struct.pack("<HBHBI", 0x2000, 0x2F, 0x1C12, 0, 0))
    assert struct.unpack_from("<I", reply, 6)[0] == 0x08000022  # not in SAFE-OP


def test_other_mailbox_types_get_a_mailbox_error() -> None:
    seg, _ = segment()
    to_preop(seg)
    message = struct.pack("<HHBB", 4, 0, 0, 0x04) + b"\x01\x00\x00\x00"  # FoE
    fpwr(seg, 0x1000, message.ljust(48, b"\x00"))
    answer = fprd(seg, 0x1030, 48)
    assert answer[5] & 0x0F == 0 and struct.unpack_from("<HH", answer, 6) == (1, 0x0002)
    assert xfer(seg, Command.FPRD, STATION, 0x1030, length=48).wkc == 0  # read: empty now


# -- process data and the watchdog ------------------------------------------------------------------

def to_op(seg: Segment, now: float = 0.0) -> None:
    to_preop(seg)
    fpwr(seg, 0x0810, sm(0x1060, 11, 0x64) + sm(0x10F0, 13, 0x20))
    # SOEM: FMMU0 outputs (type 2) at logical 0, FMMU1 inputs (type 1) after them
    fpwr(seg, 0x0600, struct.pack("<IHBBHBBB3x", 0, 11, 0, 7, 0x1060, 0, 2, 1)
         + struct.pack("<IHBBHBBB3x", 11, 13, 0, 7, 0x10F0, 0, 1, 1))
    assert al_request(seg, 4, now=now) == (4, 0)
    assert al_request(seg, 8, now=now) == (8, 0)


def test_lrw_writes_outputs_in_op_and_reads_inputs() -> None:
    seg, objects = segment()
    to_op(seg)
    outputs = struct.pack("<HiiB", 0x000F, 1234, 0, 8)
    dg = logical(seg, Command.LRW, 0, outputs + bytes(13))
    assert dg.wkc == 3  # SOEM expectedWKC = outputs * 2 + inputs
    assert dg.data[11:] == struct.pack("<HiiBH", 0x0240, -5, 0, 8, 0)
    assert objects[0].values[(0x6040, 0)] == b"\x0F\x00"
    assert objects[0].values[(0x607A, 0)] == struct.pack("<i", 1234)
    assert logical(seg, Command.LRD, 11, bytes(13)).wkc == 1
    assert logical(seg, Command.LWR, 0, outputs).wkc == 2
    assert logical(seg, Command.LRW, 100, bytes(4)).wkc == 0  # nothing mapped there


def test_outputs_are_ignored_in_safe_op() -> None:
    seg, objects = segment()
    to_op(seg)
    al_request(seg, 4)
    logical(seg, Command.LRW, 0, struct.pack("<HiiB", 0x000F, 99, 0, 8) + bytes(13))
    assert (0x6040, 0) not in objects[0].values


def test_watchdog_drops_op_to_safe_op_with_0x001b() -> None:
    seg, _ = segment()
    to_op(seg, now=10.0)
    left: list[str] = []
    seg.slaves[0].on_leave_op = left.append
    for k in range(1, 20):  # cycles every 50 ms keep it alive
        logical(seg, Command.LRW, 0, bytes(24), now=10.0 + 0.05 * k)
    assert fprd(seg, 0x0130, 2, now=10.95) == b"\x08\x00" and left == []
    seg.tick(11.0)  # 50 ms since the last cycle
    assert left == []
    seg.tick(11.06)  # 110 ms: the default 100 ms (0x0400 = 2498, 0x0420 = 1000) are over
    assert left == ["watchdog"]
    assert fprd(seg, 0x0130, 2) == b"\x14\x00" and fprd(seg, 0x0134, 2) == b"\x1b\x00"
    assert fprd(seg, 0x0440, 1)[0] & 1 == 0
    assert al_request(seg, 8) == (0x14, 0x001B)   # no acknowledge: stays
    assert al_request(seg, 0x18, now=11.1) == (8, 0)  # acknowledged: back to OP


def test_watchdog_time_follows_its_registers_and_sm2_bit_6() -> None:
    seg, _ = segment()
    to_op(seg)
    slave = seg.slaves[0]
    assert slave.watchdog_time() == pytest.approx(0.1)
    fpwr(seg, 0x0420, struct.pack("<H", 200))
    assert slave.watchdog_time() == pytest.approx(0.02)
    fpwr(seg, 0x0814, b"\x24")  # SM2 control without bit 6: no watchdog
    assert slave.watchdog_time() is None


# -- robustness ------------------------------------------------------------------------------------

def test_several_datagrams_in_one_frame_are_all_processed() -> None:
    seg, _ = segment(2)
    dgs = [Datagram(Command.BRD, 1, 0, bytearray(2)),
           Datagram(Command.APWR, 2, 0 | 0x0010 << 16, bytearray(b"\x01\x10")),
           Datagram(Command.FPRD, 3, 0x1001 | 0x0130 << 16, bytearray(2))]
    reply = seg.handle(build_frame(ETH, dgs), 0.0)
    assert reply is not None
    _eth, out = parse_frame(reply)
    assert [(d.index, d.wkc) for d in out] == [(1, 2), (2, 1), (3, 1)]
    assert out[2].data == b"\x01\x00"


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=120))
def test_random_bytes_parse_or_raise_frame_error(raw: bytes) -> None:
    for candidate in (raw, ETH + raw):
        try:
            parse_frame(candidate)
        except FrameError:
            pass


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(list(Command)), st.integers(0, 0xFFFFFFFF),
                          st.binary(max_size=64)), min_size=1, max_size=12))
def test_random_datagrams_never_break_the_slaves(ops: list[tuple[int, int, bytes]]) -> None:
    seg, _ = segment(2)
    to_preop(seg)  # mailbox live, so random writes also reach the CoE server
    for n, (command, address, data) in enumerate(ops):
        reply = seg.handle(build_frame(ETH, [Datagram(command, n, address, bytearray(data))]), n * 0.01)
        assert reply is not None
        seg.tick(n * 0.01 + 0.5)


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=0, max_size=42))
def test_random_mailbox_messages_get_an_answer(body: bytes) -> None:
    seg, _ = segment()
    to_preop(seg)
    message = struct.pack("<HHBB", len(body), 0, 0, 0x03) + body
    assert fpwr(seg, 0x1000, message.ljust(48, b"\x00")) == 1
    assert fprd(seg, 0x080D, 1)[0] & 0x08  # every message is answered: SDO, abort or error
