"""The emulated EPOS4's USB device side (pure): descriptors, packets, the URB life cycle.

Descriptor fields are checked at the offsets of USB 2.0 tables 9-8 (device),
9-10 (configuration), 9-12 (interface) and 9-13 (endpoint), and read back
through pyusb's own descriptor parser where it has one.
"""
from __future__ import annotations

import errno
import struct
from typing import Optional

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from epos_link.simulator import usb_model as m
from epos_link.simulator.usb_model import Unit, Urb, UsbError

GUIDE_READ_HOME_POSITION = bytes.fromhex("90026002 01B03000 2E62")  # guide 2.2.9, request


def test_device_descriptor_fields() -> None:
    d = m.device_descriptor()
    assert len(d) == d[0] == 18 and d[1] == 1            # bLength, DEVICE
    assert struct.unpack_from("<H", d, 2)[0] == 0x0200    # bcdUSB 2.00 (guide 2.3.1)
    assert struct.unpack_from("<HH", d, 8) == (0x24E7, 0x3B01)
    assert d[7] == 64                                     # bMaxPacketSize0
    assert (d[14], d[15], d[16], d[17]) == (1, 2, 3, 1)   # strings 1..3, one configuration


def test_configuration_has_one_vendor_interface_with_bulk_0x01_and_0x81() -> None:
    c = m.configuration_descriptor()
    assert c[1] == 2 and struct.unpack_from("<H", c, 2)[0] == len(c) == 32
    assert c[4] == 1                                      # bNumInterfaces
    intf = c[9:18]
    assert intf[1] == 4 and intf[4] == 2 and intf[5] == 0xFF  # 2 endpoints, vendor class
    eps = [c[18:25], c[25:32]]
    assert [(e[1], e[2], e[3] & 3, struct.unpack_from("<H", e, 4)[0]) for e in eps] == [
        (5, 0x01, 2, 64), (5, 0x81, 2, 64)]


def test_the_transport_finds_the_endpoints_in_these_descriptors() -> None:
    """pyusb parses the same bytes libusb reads from sysfs; our endpoint search agrees."""
    from epos_link.transports.usb import find_bulk_endpoints

    class Ep:
        def __init__(self, raw: bytes) -> None:
            self.bEndpointAddress, self.bmAttributes = raw[2], raw[3]
            self.wMaxPacketSize = struct.unpack_from("<H", raw, 4)[0]

    class Intf(list):  # type: ignore[type-arg]
        bInterfaceClass = 0xFF
        bInterfaceNumber = 0

    c = m.configuration_descriptor()
    intf, ep_in, ep_out = find_bulk_endpoints([Intf([Ep(c[18:25]), Ep(c[25:32])])])
    assert (ep_in.bEndpointAddress, ep_out.bEndpointAddress, ep_in.wMaxPacketSize) == (0x81, 0x01, 64)


def test_string_descriptors() -> None:
    assert m.string_descriptor("EPOS4") == bytes([12, 3]) + "EPOS4".encode("utf-16-le")


@pytest.mark.parametrize("size, expected", [
    (0, [0]), (1, [1]), (63, [63]), (64, [64, 0]), (65, [64, 1]), (128, [64, 64, 0]), (200, [64, 64, 64, 8]),
])
def test_a_transfer_ends_with_a_short_packet(size: int, expected: list[int]) -> None:
    assert [len(p) for p in m.packets(bytes(size))] == expected


def in_urb(key: int, length: int = 64) -> Urb:
    return Urb(key=key, type=m.URB_TYPE_BULK, endpoint=m.EP_IN, buffer_length=length)


def out_urb(key: int, length: int) -> Urb:
    return Urb(key=key, type=m.URB_TYPE_BULK, endpoint=m.EP_OUT, buffer_length=length)


def reap_all(unit: Unit, conn: m.Connection) -> list[Urb]:
    out = []
    while (urb := unit.reap(conn)) is not None:
        out.append(urb)
    return out


def test_bulk_out_completes_at_once_and_goes_to_the_device_side() -> None:
    unit = Unit("S1")
    conn = unit.connect()
    unit.submit(conn, out_urb(1, len(GUIDE_READ_HOME_POSITION)), GUIDE_READ_HOME_POSITION)
    assert list(unit.received) == [GUIDE_READ_HOME_POSITION]
    [urb] = reap_all(unit, conn)
    assert urb.key == 1 and urb.status == 0 and urb.data == GUIDE_READ_HOME_POSITION


def test_an_answer_fills_a_waiting_in_urb_up_to_its_short_packet() -> None:
    unit = Unit("S1")
    conn = unit.connect()
    unit.submit(conn, in_urb(7, 512), b"")
    assert unit.reap(conn) is None                       # nothing yet: EAGAIN
    unit.answer(b"A" * 70)                               # 64 + 6: ends at the short packet
    [urb] = reap_all(unit, conn)
    assert urb.data == b"A" * 70 and urb.status == 0


def test_a_long_answer_spreads_over_one_packet_reads_and_nothing_leaks_into_the_next() -> None:
    unit = Unit("S1")
    conn = unit.connect()
    unit.answer(b"x" * 100)
    unit.answer(b"second")
    got = []
    for key in range(4):
        unit.submit(conn, in_urb(key), b"")
        got += [u.data for u in reap_all(unit, conn)]
    assert got[:3] == [b"x" * 64, b"x" * 36, b"second"]


def test_discard_completes_with_enoent_and_a_later_answer_waits_for_the_next_urb() -> None:
    unit = Unit("S1")
    conn = unit.connect()
    unit.submit(conn, in_urb(1), b"")
    unit.discard(conn, 1)                                 # libusb: the read timed out
    [urb] = reap_all(unit, conn)
    assert urb.status == -errno.ENOENT and urb.data == b""
    unit.answer(b"late")                                  # the answer comes after all
    unit.submit(conn, in_urb(2), b"")
    [urb] = reap_all(unit, conn)
    assert urb.key == 2 and urb.data == b"late"
    with pytest.raises(UsbError) as info:
        unit.discard(conn, 99)
    assert info.value.errno == errno.EINVAL


def test_unplug_makes_every_call_enodev_and_drops_queued_bytes() -> None:
    unit = Unit("S1")
    conn = unit.connect()
    unit.submit(conn, in_urb(1), b"")
    unit.answer(b"queued for nobody")
    unit.unplug()
    for call in (lambda: unit.reap(conn), lambda: unit.submit(conn, in_urb(2), b""),
                 lambda: unit.discard(conn, 1), unit.connect):
        with pytest.raises(UsbError) as info:
            call()
        assert info.value.errno == errno.ENODEV
    assert unit.answer(b"after the pull") == []
    unit.replug()
    fresh = unit.connect()
    with pytest.raises(UsbError):
        unit.reap(conn)                                   # the old file stays dead
    unit.submit(fresh, in_urb(3), b"")
    assert unit.reap(fresh) is None                       # nothing from before the pull


def control(unit: Unit, setup: bytes, length: int = 255) -> Urb:
    conn = unit.connect()
    urb = Urb(key=1, type=m.URB_TYPE_CONTROL, endpoint=0, buffer_length=8 + length)
    unit.submit(conn, urb, setup + bytes(length))
    [done] = reap_all(unit, conn)
    return done


def get_descriptor(kind: int, index: int, langid: int = 0, length: int = 255) -> bytes:
    return struct.pack("<BBHHH", 0x80, 6, kind << 8 | index, langid, length)


@pytest.mark.parametrize("index, text", [(1, m.MANUFACTURER), (2, m.PRODUCT), (3, "0123ABC")])
def test_string_descriptors_over_control_urbs(index: int, text: str) -> None:
    urb = control(Unit("0123ABC"), get_descriptor(3, index, 0x0409))
    assert urb.status == 0 and urb.data[2:].decode("utf-16-le") == text


def test_langids_and_truncation_to_wlength() -> None:
    assert control(Unit("S"), get_descriptor(3, 0)).data == bytes([4, 3, 0x09, 0x04])
    assert control(Unit("S"), get_descriptor(1, 0, length=8)).data == m.device_descriptor()[:8]


def test_unknown_requests_stall() -> None:
    assert control(Unit("S"), struct.pack("<BBHHH", 0xC0, 0x42, 0, 0, 4)).status == -errno.EPIPE
    assert control(Unit("S"), get_descriptor(3, 9)).status == -errno.EPIPE


def test_bad_urbs_are_refused() -> None:
    unit = Unit("S")
    conn = unit.connect()
    with pytest.raises(UsbError):
        unit.submit(conn, Urb(key=1, type=m.URB_TYPE_BULK, endpoint=0x82, buffer_length=64), b"")
    with pytest.raises(UsbError):
        unit.submit(conn, Urb(key=1, type=m.URB_TYPE_CONTROL, endpoint=0, buffer_length=4), b"1234")


def test_answers_are_bounded_while_nobody_reads() -> None:
    unit = Unit("S")
    for _ in range(m.MAX_QUEUED_IN // 100 + 10):
        unit.answer(bytes(100))
    assert unit.dropped_in > 0 and unit._queued <= m.MAX_QUEUED_IN


def test_sysfs_text_ends_values_with_a_newline_and_makes_a_node() -> None:
    text = m.sysfs_device(Unit("SN1"), 1, 5, "1-1")
    assert "N: bus/usb/001/005" in text and "A: serial=SN1\\n" in text
    assert "H: descriptors=" + m.sysfs_descriptors().hex() in text


def test_ioctl_numbers_match_linux_usbdevice_fs_h_on_x86_64() -> None:
    if struct.calcsize("P") != 8:
        pytest.skip("the numbers below are those of a 64-bit Linux")
    # values as printed by a C program with <linux/usbdevice_fs.h> on x86_64
    assert (m.USBDEVFS_SUBMITURB, m.USBDEVFS_REAPURBNDELAY, m.USBDEVFS_DISCARDURB,
            m.USBDEVFS_CLAIMINTERFACE, m.USBDEVFS_GET_CAPABILITIES, m.USBDEVFS_CONTROL,
            m.USBDEVFS_GETDRIVER, m.USBDEVFS_DISCONNECT_CLAIM) == (
        0x8038550A, 0x4008550D, 0x550B, 0x8004550F, 0x8004551A, 0xC0185500, 0x41045508, 0x8108551B)


@settings(max_examples=200, deadline=None)
@given(answers=st.lists(st.binary(max_size=300), min_size=1, max_size=5),
       sizes=st.lists(st.sampled_from([64, 128, 512, 4096]), min_size=1, max_size=8))
def test_any_urb_sizes_get_the_answers_whole_and_in_order(answers: list[bytes], sizes: list[int]) -> None:
    unit = Unit("S")
    conn = unit.connect()
    for a in answers:
        unit.answer(a)
    got = b""
    key = 0
    for _ in range(200):
        key += 1
        unit.submit(conn, in_urb(key, sizes[key % len(sizes)]), b"")
        done: Optional[Urb] = unit.reap(conn)
        if done is None:
            unit.discard(conn, key)
            assert unit.reap(conn) is not None
            break
        assert done.status == 0
        got += done.data
    assert got == b"".join(answers)
