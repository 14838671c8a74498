"""framing.py: the guide's frames, three-way feeding, damaged streams, properties."""
from __future__ import annotations

import pytest
from hypothesis import given, settings, strategies as st

from epos_link.errors import (
    CrcError,
    FrameLengthError,
    JunkBytesError,
    LocalProtocolError,
    RemoteProtocolError,
    StuffingError,
    TruncatedFrameError,
)
from epos_link.framing import NEED_DATA, Frame, FrameDecoder, decode_frames, encode_frame
from tests.helpers import feed_all, three_ways
from tests.reference import GUIDE_ANSWER, GUIDE_REQUEST, reference_frame

REQ_FRAME = Frame(0x60, bytes.fromhex("01 B0 30 00"), 0x622E)
ANS_FRAME = Frame(0x00, bytes.fromhex("00 00 00 00 01 90 00 00"), 0x5C9A)


def test_encode_guide_request() -> None:
    assert encode_frame(0x60, bytes.fromhex("01 B0 30 00")) == GUIDE_REQUEST


def test_encode_guide_answer_is_stuffed() -> None:
    assert encode_frame(0x00, ANS_FRAME.data) == GUIDE_ANSWER


@pytest.mark.parametrize("stream,expected", [
    (GUIDE_REQUEST, [REQ_FRAME]),
    (GUIDE_ANSWER, [ANS_FRAME]),
    (GUIDE_REQUEST + GUIDE_ANSWER, [REQ_FRAME, ANS_FRAME]),
])
def test_three_ways(stream: bytes, expected: list[Frame]) -> None:
    for label, chunks, junk in three_ways(stream):
        frames, errors = feed_all(FrameDecoder, chunks)
        assert frames == expected, label
        if junk:
            assert [type(e) for e in errors] == [JunkBytesError, JunkBytesError], label
            assert b"".join(e.raw for e in errors) == junk + junk
        else:
            assert errors == [], label


BAD_CRC = bytes.fromhex("90 02 60 02 01 B0 30 00 2E 63")
# Damaged streams (pymodbus style): (name, stream, expected error types in order, good frames)
DAMAGED = [
    ("junk in front", b"\xAA\x55" + GUIDE_REQUEST, [JunkBytesError], [REQ_FRAME]),
    ("bad crc then good", BAD_CRC + GUIDE_ANSWER, [CrcError], [ANS_FRAME]),
    ("lone DLE in frame", bytes.fromhex("90 02 60 02 01 90 30 00 2E 62") + GUIDE_REQUEST,
     [StuffingError, JunkBytesError], [REQ_FRAME]),
    ("truncated by new sync", GUIDE_REQUEST[:6] + GUIDE_ANSWER,
     [TruncatedFrameError], [ANS_FRAME]),
    ("truncated at end", GUIDE_REQUEST + GUIDE_ANSWER[:9], [TruncatedFrameError], [REQ_FRAME]),
    ("oversize len", bytes.fromhex("90 02 60 91 00 00") + GUIDE_REQUEST,
     [FrameLengthError, JunkBytesError], [REQ_FRAME]),
    ("junk after", GUIDE_REQUEST + b"\x01\x02", [JunkBytesError], [REQ_FRAME]),
    ("lone DLE at end", GUIDE_REQUEST + b"\x90", [JunkBytesError], [REQ_FRAME]),
    ("DLE DLE STX in junk is a sync", b"\x90" + GUIDE_REQUEST, [JunkBytesError], [REQ_FRAME]),
    # The last CRC byte damaged into a lone DLE pairs with the next sync's DLE.
    ("lone DLE as last CRC byte", bytes.fromhex("90 02 60 02 01 B0 30 00 2E 90") + GUIDE_ANSWER,
     [CrcError], [ANS_FRAME]),
    # A frame cut off right after a lone DLE, the next frame's bytes read as its data.
    ("cut after a lone DLE", bytes.fromhex("90 02 00 04 00 00 00 00 01 90") + GUIDE_ANSWER,
     [CrcError], [ANS_FRAME]),
    # Issue 35: cut after the opcode and a lone DLE, which pairs with the next sync's DLE
    # as a stuffed Len of 0x90 (144 words, too long): the length path gives the sync back.
    ("cut after opcode and a lone DLE", bytes.fromhex("90 02 00 90") + GUIDE_REQUEST,
     [FrameLengthError], [REQ_FRAME]),
    ("lone DLE as Len before a bad frame", bytes.fromhex("90 02 00 90") + BAD_CRC + GUIDE_ANSWER,
     [FrameLengthError, CrcError], [ANS_FRAME]),
]


@pytest.mark.parametrize("name,stream,errs,good", DAMAGED, ids=[d[0] for d in DAMAGED])
def test_damaged_streams(name: str, stream: bytes, errs: list[type], good: list[Frame]) -> None:
    for label, chunks, junk in three_ways(stream, junk=b""):
        frames, errors = feed_all(FrameDecoder, chunks)
        assert frames == good, label
        assert [type(e) for e in errors] == errs, label


def test_bad_crc_frame_is_still_decoded() -> None:
    frames, errors = feed_all(FrameDecoder, [BAD_CRC])
    assert frames == []
    (err,) = errors
    assert isinstance(err, CrcError)
    assert err.frame == Frame(0x60, bytes.fromhex("01 B0 30 00"), 0x632E, crc_ok=False)
    assert err.raw == BAD_CRC


@pytest.mark.parametrize("damage", [b"\x01", b"\x90\x90", b"\x90\x02\x60\x02\x01\x90\x30"])
def test_no_byte_is_lost_or_reported_twice(damage: bytes) -> None:
    stream = b"\x01" + BAD_CRC + damage + GUIDE_REQUEST[:5] + GUIDE_ANSWER + b"\x07"
    frames, errors = feed_all(FrameDecoder, [stream])
    reported = sum(len(e.raw) for e in errors) + len(GUIDE_ANSWER)
    assert reported == len(stream)
    assert frames == [ANS_FRAME]


def test_junk_is_bounded() -> None:
    dec = FrameDecoder(max_junk=64)
    seen = 0
    for _ in range(1000):
        dec.feed(b"\x55" * 100)
        while True:
            try:
                if dec.next_frame() is NEED_DATA:
                    break
            except JunkBytesError as exc:
                seen += len(exc.raw)
        assert dec.pending < 64 + 100
    assert seen >= 1000 * 100 - 64


def test_feed_refuses_unbounded_pending() -> None:
    dec = FrameDecoder(max_pending=1000)
    dec.feed(b"\x00" * 1000)
    with pytest.raises(LocalProtocolError):
        dec.feed(b"\x00")


@pytest.mark.parametrize("opcode,data", [(0x100, b""), (0x60, b"\x01"), (0x60, bytes(288))])
def test_encode_refuses_bad_frames(opcode: int, data: bytes) -> None:
    with pytest.raises(LocalProtocolError):
        encode_frame(opcode, data)


def test_max_length_frame() -> None:
    data = bytes(range(256)) + bytes(30)  # 286 bytes = 143 words, one 0x90 inside
    assert decode_frames(encode_frame(0x00, data)) == [
        Frame(0x00, data, decode_frames(encode_frame(0x00, data))[0].crc)]


words = st.binary(max_size=286).filter(lambda b: len(b) % 2 == 0)
dle_heavy = st.lists(st.sampled_from([b"\x90", b"\x02", b"\x90\x90", b"\x00", b"\x90\x02"]),
                     max_size=80).map(b"".join).map(lambda b: b[: len(b) // 2 * 2][:286])


@given(st.integers(0, 255), st.one_of(words, dle_heavy))
def test_round_trip_and_reference(opcode: int, data: bytes) -> None:
    wire = encode_frame(opcode, data)
    assert wire == reference_frame(opcode, data)
    (frame,) = decode_frames(wire)
    assert (frame.opcode, frame.data, frame.crc_ok) == (opcode, data, True)


@given(st.lists(st.tuples(st.integers(0, 255), st.one_of(words, dle_heavy)), min_size=1,
                max_size=5), st.data())
def test_arbitrary_chunking(messages: list[tuple[int, bytes]], data: st.DataObject) -> None:
    stream = b"".join(encode_frame(op, d) for op, d in messages)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=20)))
    chunks = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)])]
    frames, errors = feed_all(FrameDecoder, chunks)
    assert errors == []
    assert [(f.opcode, f.data) for f in frames] == messages


@settings(max_examples=300)
@given(st.lists(st.one_of(st.binary(max_size=40), st.sampled_from(
    [b"\x90", b"\x90\x02", b"\x90\x90", b"\x90\x02\x60\x02", GUIDE_REQUEST, GUIDE_ANSWER])),
    max_size=30))
def test_random_bytes_only_raise_protocol_errors(chunks: list[bytes]) -> None:
    dec = FrameDecoder(max_junk=50)
    for chunk in chunks:
        dec.feed(chunk)
        while True:
            try:
                if dec.next_frame() is NEED_DATA:
                    break
            except RemoteProtocolError:
                pass
        assert dec.pending <= 50 + 600 + len(chunk)
    dec.close()
    for _ in range(100):
        try:
            if dec.next_frame() is NEED_DATA:
                break
        except RemoteProtocolError:
            pass
    assert dec.pending == 0


@settings(max_examples=400)
@given(st.integers(0, 255), st.one_of(words, dle_heavy), st.data())
def test_a_damaged_frame_never_hides_the_next(opcode: int, data: bytes, draw: st.DataObject) -> None:
    """One byte of a frame replaced (or the frame cut short): the next good frame survives."""
    wire = bytearray(encode_frame(opcode, data))
    pos = draw.draw(st.integers(2, len(wire) - 1))
    if draw.draw(st.booleans()):
        wire[pos] = draw.draw(st.integers(0, 255))
    else:
        del wire[pos:]
    frames, _ = feed_all(FrameDecoder, [bytes(wire) + GUIDE_ANSWER])
    assert frames[-1:] == [ANS_FRAME]


def _chunked(stream: bytes, cuts: list[int]) -> list[bytes]:
    cuts = sorted(c % (len(stream) + 1) for c in cuts)
    return [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)])]


def _reported(errors: list[RemoteProtocolError]) -> list[tuple[str, bytes]]:
    """Errors with adjacent junk runs merged: how junk is split into runs of at most
    max_junk bytes is the one thing allowed to depend on the chunking."""
    out: list[tuple[str, bytes]] = []
    for e in errors:
        if out and isinstance(e, JunkBytesError) and out[-1][0] == "JunkBytesError":
            out[-1] = (out[-1][0], out[-1][1] + e.raw)
        else:
            out.append((type(e).__name__, e.raw))
    return out


# Pieces a damaged stream is made of: anything, DLE/STX runs, cut or changed frames.
_dle_runs = st.lists(st.sampled_from([b"\x90", b"\x02", b"\x90\x90", b"\x00", b"\x90\x02",
                                      b"\x04", b"\x60", b"\x90\x90\x02"]),
                     max_size=20).map(b"".join)


@st.composite
def _damaged_frame(draw: st.DrawFn) -> bytes:
    wire = bytearray(encode_frame(draw(st.integers(0, 255)), draw(st.one_of(words, dle_heavy))))
    pos = draw(st.integers(2, len(wire) - 1))
    if draw(st.booleans()):
        wire[pos] = draw(st.integers(0, 255))
    else:
        del wire[pos:]
    return bytes(wire)


any_prefix = st.lists(st.one_of(st.binary(max_size=30), _dle_runs, _damaged_frame()),
                      max_size=4).map(b"".join)


@settings(max_examples=300, deadline=None)
@given(any_prefix, st.integers(0, 255), st.one_of(words, dle_heavy),
       st.lists(st.integers(0, 2000), max_size=8))
def test_any_bytes_then_a_valid_frame_decode_that_frame(
        prefix: bytes, opcode: int, data: bytes, cuts: list[int]) -> None:
    """Issue 35: whatever came before, a valid frame is decoded, and the frames and
    errors are the same fed whole, byte by byte and in chunks of any size."""
    stream = prefix + encode_frame(opcode, data)
    whole = feed_all(FrameDecoder, [stream])
    assert [(f.opcode, f.data, f.crc_ok) for f in whole[0][-1:]] == [(opcode, data, True)]
    for chunks in ([stream[i:i + 1] for i in range(len(stream))], _chunked(stream, cuts)):
        frames, errors = feed_all(FrameDecoder, chunks)
        assert frames == whole[0]
        assert _reported(errors) == _reported(whole[1])


def test_the_issue_35_example_decodes_its_read_object() -> None:
    """`90 02 00 | 90` is a frame cut after its opcode and a lone DLE; the guide's
    ReadObject request (2.2.9, Table 2-5) follows and must come out, however fed."""
    stream = bytes.fromhex("90 02 00 90 90 02 60 02 01 B0 30 00 2E 62")
    for label, chunks, _ in three_ways(stream):
        frames, errors = feed_all(FrameDecoder, chunks)
        assert frames == [REQ_FRAME], label
        assert errors[0].raw == bytes.fromhex("90 02 00 90") or label == "junk", label


def _answer(value: bytes) -> bytes:
    return encode_frame(0x00, bytes(4) + value)


def test_escaped_dle_then_stx_in_data_does_not_hide_the_next_frames() -> None:
    """Frame A carries 0x90 0x02 as data (stuffed 90 90 02) and its last byte became a
    lone DLE: B and C must come out, fed whole, byte by byte or with junk."""
    a = bytearray(_answer(b"\x90\x02\x11\x22"))
    a[-1] = 0x90
    b, c = _answer(b"\x01\x00\x00\x00"), _answer(b"\x02\x00\x00\x00")
    for label, chunks, _ in three_ways(bytes(a) + b + c):
        frames, errors = feed_all(FrameDecoder, chunks)
        assert [f.data[4] for f in frames] == [1, 2], label
        assert errors, label


def test_a_lost_dle_at_the_end_of_a_frame_does_not_hide_the_next() -> None:
    """A's CRC ends in an escaped 0x90 (90 90); one of those DLEs is lost, so A's last
    DLE pairs with B's sync DLE. A still checks out, and B must too."""
    value = next(v for v in range(1 << 16) if _answer(v.to_bytes(4, "little")).endswith(b"\x90\x90"))
    a, b = _answer(value.to_bytes(4, "little")), _answer(b"\x01\x00\x00\x00")
    for label, chunks, _ in three_ways(a[:-1] + b):
        frames, _ = feed_all(FrameDecoder, chunks)
        assert [f.data[4:] for f in frames] == [value.to_bytes(4, "little"), b"\x01\x00\x00\x00"], label


def test_a_bad_frame_ending_in_an_escaped_dle_is_reported_at_once() -> None:
    """No waiting for a byte that may never come: a host must see the CRC error now."""
    # An answer with value 04030201 whose CRC high byte was damaged into 0x90 (stuffed).
    wire = bytes.fromhex("90 02 00 04 00 00 00 00 01 02 03 04 CB 90 90")
    dec = FrameDecoder()
    errors = []
    for byte in bytes(wire):
        dec.feed(bytes([byte]))
        try:
            assert dec.next_frame() is NEED_DATA
        except CrcError as exc:
            errors.append(exc)
    assert len(errors) == 1


def test_wanted_tells_a_reader_how_many_bytes_the_frame_still_needs() -> None:
    # Guide 2.2.3 example answer: 90 02 00 04, then 8 data bytes and the CRC (2).
    frame = reference_frame(0x00, bytes(8))
    decoder = FrameDecoder()
    assert decoder.wanted == 1  # outside a frame: anything may come
    seen = []
    for i, byte in enumerate(frame):
        decoder.feed(bytes([byte]))
        assert decoder.next_frame() is NEED_DATA or i == len(frame) - 1
        seen.append(decoder.wanted)
    # after DLE STX: opcode and length (2); after the length: 8 data + 2 CRC bytes
    assert seen[1] == 2 and seen[3] == 10
    assert all(w >= 1 for w in seen)
    assert all(seen[i] <= len(frame) - 1 - i or seen[i] == 1 for i in range(len(frame)))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 255), st.binary(max_size=40).map(lambda b: b + b"\0" * (len(b) % 2)))
def test_wanted_never_overstates_what_is_left(opcode: int, data: bytes) -> None:
    # A reader that waits for `wanted` bytes must never wait for bytes that will
    # not come: stuffed DLEs (0x90 0x90) can only make the rest longer.
    frame = reference_frame(opcode, data)
    decoder = FrameDecoder()
    for i, byte in enumerate(frame):
        decoder.feed(bytes([byte]))
        decoder.next_frame()
        left = len(frame) - 1 - i
        assert 1 <= decoder.wanted and (decoder.wanted <= left or left == 0)
