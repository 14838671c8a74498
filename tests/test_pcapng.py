"""epos_link.tools.pcapng: the blocks of the pcapng draft, written and read back."""
from __future__ import annotations

import io
import struct

from hypothesis import given
from hypothesis import strategies as st

from epos_link.tools.pcapng import (
    FLAG_INBOUND,
    FLAG_OUTBOUND,
    IF_DESCRIPTION,
    IF_SPEED,
    IF_TSRESOL,
    LINKTYPE_USER0,
    PcapngWriter,
    read_pcapng,
)


def test_block_layout_follows_the_draft() -> None:
    out = io.BytesIO()
    w = PcapngWriter(out, if_name="/dev/ttyUSB0", if_description="MAXON SERIAL V2 /dev/ttyUSB0 at 115200 baud",
                     speed=115200)
    w.packet(1_700_000_000_123_456_789, bytes.fromhex("9002600201B030002E62"), outbound=True)
    data = out.getvalue()
    # Section Header Block: type 0x0A0D0D0A, byte-order magic 0x1A2B3C4D, version 1.0, length -1.
    btype, length, magic, major, minor, section = struct.unpack_from("<IIIHHq", data)
    assert (btype, magic, major, minor, section) == (0x0A0D0D0A, 0x1A2B3C4D, 1, 0, -1)
    assert struct.unpack_from("<I", data, length - 4)[0] == length  # trailing length
    assert length % 4 == 0
    # Interface Description Block: type 1, LINKTYPE_USER0 = 147.
    btype, _, linktype = struct.unpack_from("<IIH", data, length)
    assert (btype, linktype) == (1, 147)
    interfaces, packets = read_pcapng(data)
    assert interfaces[0].linktype == LINKTYPE_USER0
    assert interfaces[0].options[IF_TSRESOL] == b"\x09"  # nanoseconds
    assert interfaces[0].options[IF_DESCRIPTION].endswith(b"at 115200 baud")
    assert struct.unpack("<Q", interfaces[0].options[IF_SPEED])[0] == 115200
    assert packets[0].time_ns == 1_700_000_000_123_456_789
    assert packets[0].flags == FLAG_OUTBOUND  # bits 0-1 = 10: outbound
    assert packets[0].data == bytes.fromhex("9002600201B030002E62")


@given(st.lists(st.tuples(st.integers(0, 2**63), st.binary(max_size=600), st.sampled_from([None, True, False])),
                max_size=20))
def test_round_trip(packets: list[tuple[int, bytes, object]]) -> None:
    out = io.BytesIO()
    w = PcapngWriter(out)
    for t, data, outbound in packets:
        w.packet(t, data, outbound=outbound)  # type: ignore[arg-type]
    _, back = read_pcapng(out.getvalue())
    assert [(p.time_ns, p.data) for p in back] == [(t, d) for t, d, _ in packets]
    flags = {None: None, True: FLAG_OUTBOUND, False: FLAG_INBOUND}
    assert [p.flags for p in back] == [flags[o] for _, _, o in packets]  # type: ignore[index]
