"""The client fixtures are sound: every frame's CRC is the guide's (bit-wise port in
tests/reference.py, independent of our codec), except the frames marked ``bad-crc``
on purpose, and every file says where its bytes come from."""
from __future__ import annotations

from pathlib import Path

import pytest

from tests.reference import calc_field_crc, crc_words

FIXTURES = sorted((Path(__file__).parent.parent / "fixtures").glob("client_*.txt"))


def reference_frames(stream: bytes) -> list[tuple[int, bytes, int]]:
    """(opcode, data, crc) of every complete frame, written from guide 2.2.2/2.2.4 alone.

    Bytes outside frames and frames cut off by a new DLE STX are skipped.
    """
    frames = []
    i = 0
    while True:
        start = stream.find(b"\x90\x02", i)
        if start < 0:
            return frames
        body = bytearray()
        j = start + 2
        need = 2
        while len(body) < need and j < len(stream):
            b = stream[j]
            if b == 0x90:
                if j + 1 < len(stream) and stream[j + 1] == 0x90:
                    body.append(0x90)
                    j += 2
                else:
                    break  # DLE STX (or damage): this frame is cut off
            else:
                body.append(b)
                j += 1
            if len(body) == 2:
                need = 2 + 2 * body[1] + 2
        if len(body) == need:
            frames.append((body[0], bytes(body[2:-2]), body[-2] | body[-1] << 8))
        i = j if j > start + 2 else start + 2


@pytest.mark.parametrize("path", FIXTURES, ids=[p.name for p in FIXTURES])
def test_fixture_frames_have_the_guides_crc(path: Path) -> None:
    text = path.read_text()
    assert "# source:" in text
    marked_bad = text.count("bad-crc")
    for direction in ("TX", "RX"):
        stream = b"".join(bytes.fromhex(line.split("#")[0].split(None, 2)[2])
                          for line in text.splitlines()
                          if line and not line.startswith("#") and line.split()[1] == direction)
        frames = reference_frames(stream)
        if direction == "TX":
            assert frames, "a conversation starts with the host's request"
        bad = [f for f in frames if calc_field_crc(crc_words(f[0], f[1])) != f[2]]
        if direction == "RX":
            assert len(bad) == marked_bad
        else:
            assert not bad


def test_there_are_fixtures() -> None:
    assert len(FIXTURES) >= 10
