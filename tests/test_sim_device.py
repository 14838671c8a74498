"""simulator/device.py: the device side of the protocol against a dict of objects."""
from __future__ import annotations

import pytest

from epos_link.codes import ErrorCode
from epos_link.framing import decode_frames
from epos_link.messages import (
    InitiateSegmentedRead, InitiateSegmentedReadAnswer, InitiateSegmentedWrite, ReadObject,
    SegmentRead, SegmentReadAnswer, SegmentWrite, SegmentWriteAnswer, SendNMTService,
    StatusAnswer, WriteObject, decode_answer,
)
from epos_link.simulator.device import Abort, DeviceProtocol
from tests.reference import GUIDE_ANSWER, GUIDE_REQUEST, reference_frame


class DictAccess:
    def __init__(self) -> None:
        self.objects: dict[tuple[int, int, int], bytes] = {
            (1, 0x30B0, 0): (0x9001).to_bytes(4, "little"),
            (1, 0x1008, 0): b"EPOS4 simulated drive, a long name",
            (2, 0x1008, 0): b"EPOS4",
        }
        self.nmt_calls: list[tuple[int, int]] = []

    def _key(self, node: int, index: int, sub: int) -> tuple[int, int, int]:
        return (1 if node == 0 else node, index, sub)

    def read(self, node: int, index: int, subindex: int) -> bytes:
        try:
            return self.objects[self._key(node, index, subindex)]
        except KeyError:
            raise Abort(0x06020000) from None

    def write(self, node: int, index: int, subindex: int, data: bytes, *, expedited: bool) -> None:
        self.objects[self._key(node, index, subindex)] = data

    def nmt(self, node: int, command: int) -> None:
        self.nmt_calls.append((node, command))


def exchange(dev: DeviceProtocol, request, request_type=None):  # type: ignore[no-untyped-def]
    (wire,) = dev.receive(request.encode())
    (frame,) = decode_frames(wire)
    return decode_answer(frame, request_type or request)


def test_guide_example_byte_for_byte() -> None:
    dev = DeviceProtocol(DictAccess())
    assert dev.receive(GUIDE_REQUEST) == [GUIDE_ANSWER]


def test_byte_by_byte_and_junk() -> None:
    dev = DeviceProtocol(DictAccess())
    out: list[bytes] = []
    for b in b"\x00\xff" + GUIDE_REQUEST + b"\x12":
        out += dev.receive(bytes([b]))
    assert out == [GUIDE_ANSWER]


def test_bad_crc_and_unknown_opcode_get_error_frames() -> None:
    dev = DeviceProtocol(DictAccess())
    (wire,) = dev.receive(bytes.fromhex("90 02 60 02 01 B0 30 00 2E 63"))
    assert decode_answer(decode_frames(wire)[0], WriteObject) == StatusAnswer(ErrorCode.CRC_ERROR)
    (wire,) = dev.receive(reference_frame(0x55, b""))
    assert decode_answer(decode_frames(wire)[0], WriteObject) == StatusAnswer(ErrorCode.ILLEGAL_COMMAND)
    assert dev.receive(GUIDE_REQUEST) == [GUIDE_ANSWER]


def test_missing_object_abort() -> None:
    dev = DeviceProtocol(DictAccess())
    ans = exchange(dev, ReadObject(1, 0x1234, 0))
    assert ans.error_code == 0x06020000


@pytest.mark.parametrize("carries,segment", [(True, 255), (False, 255), (True, 8), (False, 8)])
def test_segmented_read(carries: bool, segment: int) -> None:
    dev = DeviceProtocol(DictAccess(), segment_size=segment, initiate_carries_data=carries)
    first = exchange(dev, InitiateSegmentedRead(1, 0x1008, 0))
    assert isinstance(first, InitiateSegmentedReadAnswer) and first.error_code == 0
    data, toggle = bytearray(first.data), False
    while len(data) < first.object_length:
        seg = exchange(dev, SegmentRead(toggle))
        assert isinstance(seg, SegmentReadAnswer) and seg.toggle == toggle
        data += seg.data
        toggle = not toggle
        if seg.last:
            break
    assert bytes(data) == b"EPOS4 simulated drive, a long name"


def test_segmented_read_toggle_error() -> None:
    dev = DeviceProtocol(DictAccess(), segment_size=4, initiate_carries_data=False)
    exchange(dev, InitiateSegmentedRead(1, 0x1008, 0))
    assert exchange(dev, SegmentRead(True)).error_code == ErrorCode.TOGGLE_ERROR


def test_segmented_write_and_gateway_refusal() -> None:
    access = DictAccess()
    dev = DeviceProtocol(access, node_id=1)
    payload = bytes(range(200)) + bytes(100)
    assert exchange(dev, InitiateSegmentedWrite(0, 0x2100, 1, length=300)).error_code == 0
    ans1 = exchange(dev, SegmentWrite(payload[:255], toggle=False, last=False))
    ans2 = exchange(dev, SegmentWrite(payload[255:], toggle=True, last=True))
    assert ans1 == SegmentWriteAnswer(0, 255, False) and ans2 == SegmentWriteAnswer(0, 45, True)
    assert access.objects[(1, 0x2100, 1)] == payload
    # Guide 2.1.2.2: segmented writes are not forwarded through the gateway.
    assert exchange(dev, InitiateSegmentedWrite(2, 0x2100, 1, length=8)).error_code != 0


def test_write_object_and_nmt() -> None:
    access = DictAccess()
    dev = DeviceProtocol(access)
    assert exchange(dev, WriteObject(2, 0x6040, 0, b"\x06\x00\x00\x00")).error_code == 0
    assert access.objects[(2, 0x6040, 0)] == b"\x06\x00\x00\x00"
    assert exchange(dev, SendNMTService(2, 0x81)).error_code == 0
    assert access.nmt_calls == [(2, 0x81)]


def test_backend_exception_becomes_an_error_answer() -> None:
    class Broken(DictAccess):
        def read(self, node: int, index: int, subindex: int) -> bytes:
            raise RuntimeError("boom")

    dev = DeviceProtocol(Broken())
    assert exchange(dev, ReadObject(1, 0x30B0, 0)).error_code == ErrorCode.GENERAL_ERROR
