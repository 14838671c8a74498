"""Tests of tcp_bridge.wire: splitter, parser, 30-byte replies.

Golden bytes are copied from the byte tables of the PSI document
(shared/seeds/PSI_TCP_Interface_Documentation.txt, rev 2.3), sections 2.2.1,
2.2.2, 2.3.1 and 2.3.2, never produced by our own encoder.
"""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Callable, List, Sequence, Union

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcp_bridge.errors import (
    BridgeError,
    DeviceFailure,
    InvalidCommand,
    LineTooLong,
    MalformedReply,
    ReplyOverflow,
)
from tcp_bridge.wire import (
    REPLY_SIZE,
    LineSplitter,
    ReadRequest,
    Reply,
    Status,
    WriteRequest,
    decode_reply,
    format_error_reply,
    format_read_reply,
    format_read_status,
    format_request,
    format_status_reply,
    format_value,
    format_write_reply,
    parse_item,
    parse_request,
    recognise_header,
    status_for,
)

NUL23 = bytes(23)

# Spec 2.2.1 "writeBuffer" column: "3S02=12" + CR. (The table prints 0x34 for
# the second command digit but labels it "2"; the text and the example
# "sets the target position of axis 3 to 12" confirm 0x32.)
SPEC_221_WRITE = bytes.fromhex("33 53 30 32 3D 31 32 0D")
# Spec 2.2.2: "3 S 2" ACK CR, then NUL up to 30 bytes.
SPEC_222_WRITE_ACK = bytes.fromhex("33 20 53 20 32 06 0D") + NUL23
# Spec 2.3.1: "3R02" + CR.
SPEC_231_READ = bytes.fromhex("33 52 30 32 0D")
# Spec 2.3.2: "3 R 2=12.8" ACK CR + 18 NUL.
SPEC_232_READ_VALUE = bytes.fromhex("33 20 52 20 32 3D 31 32 2E 38 06 0D") + bytes(18)
# Spec 2.3.2: "3 R 2" ACK / NAK / CAN, CR + 23 NUL.
SPEC_232_READ_STATUS = {
    Status.ACK: bytes.fromhex("33 20 52 20 32 06 0D") + NUL23,
    Status.NAK: bytes.fromhex("33 20 52 20 32 15 0D") + NUL23,
    Status.CAN: bytes.fromhex("33 20 52 20 32 18 0D") + NUL23,
}


# --- helpers -------------------------------------------------------------------

Norm = Union[bytes, tuple]


def norm(items: Sequence[object]) -> List[Norm]:
    """Splitter items in a comparable form (exceptions do not compare by value)."""
    out: List[Norm] = []
    for item in items:
        if isinstance(item, LineTooLong):
            out.append(("too long", item.head, item.axis, item.kind, item.cmd))
        else:
            assert isinstance(item, bytes)
            out.append(item)
    return out


def feed_whole(data: bytes, max_line: int = 64) -> List[Norm]:
    return norm(LineSplitter(max_line).feed(data))


def feed_bytewise(data: bytes, max_line: int = 64) -> List[Norm]:
    s = LineSplitter(max_line)
    items: list = []
    for i in range(len(data)):
        items += s.feed(data[i:i + 1])
    return norm(items)


def feed_with_trailing(data: bytes, max_line: int = 64) -> List[Norm]:
    """Feed, then an unterminated request: it must not appear yet."""
    return norm(LineSplitter(max_line).feed(data + b"3R0"))


FEEDERS: List[Callable[..., List[Norm]]] = [feed_whole, feed_bytewise, feed_with_trailing]


# --- golden bytes from the spec -------------------------------------------------


def test_spec_221_write_request_parses() -> None:
    assert LineSplitter().feed(SPEC_221_WRITE) == [b"3S02=12"]
    assert parse_request(b"3S02=12") == WriteRequest(axis=3, cmd=2, value="12")
    assert format_request(WriteRequest(3, 2, "12")) == SPEC_221_WRITE


def test_spec_222_write_reply() -> None:
    assert format_write_reply(3, 2, Status.ACK) == SPEC_222_WRITE_ACK
    assert decode_reply(SPEC_222_WRITE_ACK) == Reply(3, "S", 2, Status.ACK)


def test_spec_231_read_request_parses() -> None:
    assert LineSplitter().feed(SPEC_231_READ) == [b"3R02"]
    assert parse_request(b"3R02") == ReadRequest(axis=3, cmd=2)
    assert format_request(ReadRequest(3, 2)) == SPEC_231_READ


def test_spec_232_read_reply_with_value() -> None:
    assert format_read_reply(3, 2, 12.8) == SPEC_232_READ_VALUE
    assert format_read_reply(3, 2, "12.8") == SPEC_232_READ_VALUE
    assert decode_reply(SPEC_232_READ_VALUE) == Reply(3, "R", 2, Status.ACK, "12.8")


@pytest.mark.parametrize("status", list(Status))
def test_spec_232_read_reply_without_value(status: Status) -> None:
    assert format_read_status(3, 2, status) == SPEC_232_READ_STATUS[status]
    assert format_status_reply(ReadRequest(3, 2), status) == SPEC_232_READ_STATUS[status]
    assert decode_reply(SPEC_232_READ_STATUS[status]) == Reply(3, "R", 2, status)


def test_spec_232_example_12_819() -> None:
    # Spec 2.3.2 prose: 3 R 2=12.819<ACK><CR>
    assert format_read_reply(3, 2, 12.819) == b"3 R 2=12.819\x06\r".ljust(30, b"\x00")


def test_status_bytes() -> None:
    # Spec 2.2.2: "ACK" (0x06); "NAK" (0x15); "CAN" (0x18)
    assert (Status.ACK, Status.NAK, Status.CAN) == (0x06, 0x15, 0x18)


# --- the splitter --------------------------------------------------------------

TOO_LONG_1 = ("too long", b"1" * 64, None, None, None)

SPLITTER_CASES = [
    # (name, stream, expected items)
    ("one request", b"3R02\r", [b"3R02"]),
    ("two in one segment", b"3R02\r3S02=12\r", [b"3R02", b"3S02=12"]),
    ("CRLF", b"3R02\r\n3R12\r\n", [b"3R02", b"3R12"]),
    ("bare LF", b"3R02\n3R12\n", [b"3R02", b"3R12"]),
    ("LF CR", b"3R02\n\r3R12\n\r", [b"3R02", b"3R12"]),
    ("NUL padded telegrams", SPEC_221_WRITE.ljust(30, b"\0") * 2, [b"3S02=12"] * 2),
    ("NUL and LF after CR", b"3R02\r\0\n\0\0\n3R12\r", [b"3R02", b"3R12"]),
    ("NUL before the first request", b"\0\0\x003R02\r", [b"3R02"]),
    ("empty lines dropped", b"\r\r\n\n\r", []),
    ("NUL inside a line is kept", b"3R\x0002\r", [b"3R\x0002"]),
    ("junk line then good", b"garbage\r3R02\r", [b"garbage", b"3R02"]),
    ("unterminated stays pending", b"3R02\r3R1", [b"3R02"]),
    ("line at the limit", b"1" * 64 + b"\r", [b"1" * 64]),
    ("line over the limit", b"1" * 65 + b"\r3R02\r", [TOO_LONG_1, b"3R02"]),
    ("long junk then good", b"1" * 500 + b"\n3R02\r", [TOO_LONG_1, b"3R02"]),
    ("overlong keeps header", b"3S02=" + b"1" * 100 + b"\r",
     [("too long", (b"3S02=" + b"1" * 100)[:64], 3, "S", 2)]),
    ("two overlong lines", (b"2" * 70 + b"\r") * 2,
     [("too long", b"2" * 64, None, None, None)] * 2),
]


@pytest.mark.parametrize("feeder", FEEDERS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("name,stream,expected", SPLITTER_CASES, ids=[c[0] for c in SPLITTER_CASES])
def test_splitter_cases(feeder: Callable[..., List[Norm]], name: str, stream: bytes,
                        expected: List[Norm]) -> None:
    assert feeder(stream) == expected


def test_splitter_overlong_reported_once_without_terminator() -> None:
    s = LineSplitter(max_line=8)
    items = s.feed(b"3S02=123456")
    assert norm(items) == [("too long", b"3S02=123", 3, "S", 2)]
    assert s.feed(b"7" * 1000) == []  # still discarding, nothing buffered
    assert s.feed(b"\r3R02\r") == [b"3R02"]


def test_splitter_memory_is_bounded() -> None:
    s = LineSplitter(max_line=16)
    for _ in range(100):
        s.feed(b"x" * 1000)
    assert len(s._buf) <= 16


def test_splitter_rejects_tiny_limit() -> None:
    with pytest.raises(ValueError):
        LineSplitter(max_line=7)


def test_overlong_line_gets_one_can_reply() -> None:
    (item,) = LineSplitter().feed(b"3S02=" + b"1" * 100 + b"\r")
    with pytest.raises(LineTooLong) as info:
        parse_item(item)
    assert format_error_reply(info.value) == b"3 S 2\x18\r".ljust(30, b"\0")


stream_bytes = st.binary(max_size=300) | st.lists(
    st.sampled_from([b"3R02", b"3S02=12", b"\r", b"\n", b"\0", b"1" * 40, b"x", b"60s99=-1.5"]),
    max_size=40,
).map(b"".join)


@given(data=stream_bytes, cuts=st.lists(st.integers(0, 300), max_size=20))
def test_any_split_gives_the_same_items(data: bytes, cuts: List[int]) -> None:
    points = sorted({c for c in cuts if c <= len(data)})
    s = LineSplitter(max_line=32)
    items: list = []
    prev = 0
    for p in points + [len(data)]:
        items += s.feed(data[prev:p])
        prev = p
    assert norm(items) == feed_whole(data, 32)


@given(before=stream_bytes, line=st.binary(max_size=40) | st.sampled_from(
    [b"3R10", b"\x003R10", b"1" * 32, b"1" * 33, b"", b"3R\n10", b"3R\r10"]))
def test_one_line_per_read_gives_what_the_general_path_gives(before: bytes, line: bytes) -> None:
    # feed() takes a short cut for a read that is one whole request ending in CR.
    s = LineSplitter(max_line=32)
    items = s.feed(before) + s.feed(line + b"\r")
    assert norm(items) == feed_bytewise(before + line + b"\r", 32)  # never the short cut


@given(data=stream_bytes)
def test_random_bytes_only_yield_lines_or_protocol_errors(data: bytes) -> None:
    for item in LineSplitter(max_line=32).feed(data):
        if isinstance(item, bytes):
            assert item and len(item) <= 32
            assert b"\r" not in item and b"\n" not in item and item[:1] != b"\0"
        try:
            request = parse_item(item)
        except InvalidCommand as exc:
            reply = format_error_reply(exc)
            assert len(reply) == REPLY_SIZE
            assert decode_reply(reply).status is Status.CAN
        else:
            assert parse_request(format_request(request)[:-1]) == request


# --- the parser ----------------------------------------------------------------

VALID = [
    (b"3S02=12", WriteRequest(3, 2, "12")),
    (b"3s2=12", WriteRequest(3, 2, "12")),  # spec 2.2.1: "work also with s"
    (b"3r02", ReadRequest(3, 2)),  # spec 2.3.1: "work also with r"
    (b"60R99", ReadRequest(60, 99)),
    (b"1R0", ReadRequest(1, 0)),
    (b"03R02", ReadRequest(3, 2)),
    (b"1S00=1", WriteRequest(1, 0, "1")),
    (b"3S02=-1.5", WriteRequest(3, 2, "-1.5")),
    (b"3S02=+.5", WriteRequest(3, 2, "+.5")),
    (b"3S02=12.", WriteRequest(3, 2, "12.")),
    (b"3S80=0x607A0004", WriteRequest(3, 80, "0x607A0004")),
    (b"3S80=0XabCD", WriteRequest(3, 80, "0XabCD")),
    (b"3S03=1", WriteRequest(3, 3, "1")),  # unknown commands are the command layer's job
]


@pytest.mark.parametrize("line,expected", VALID)
def test_parse_valid(line: bytes, expected: object) -> None:
    assert parse_request(line) == expected


INVALID = [
    # (line, echoed header of the CAN reply)
    (b"3S02=1x", b"3 S 2"),
    (b"3S02=", b"3 S 2"),
    (b"3S02", b"3 S 2"),
    (b"3S02= 1", b"3 S 2"),
    (b"3S02=1 ", b"3 S 2"),
    (b"3S02=1e5", b"3 S 2"),
    (b"3S02=1,5", b"3 S 2"),
    (b"3S02=--1", b"3 S 2"),
    (b"3S02=.", b"3 S 2"),
    (b"3S02=0x", b"3 S 2"),
    (b"3S02=-0x10", b"3 S 2"),
    (b"3S02=1=2", b"3 S 2"),
    (b"3S02=nan", b"3 S 2"),
    (b"3S02=\xc3\xa4", b"3 S 2"),
    (b"3R02=5", b"3 R 2"),
    (b"3R02 ", b"3 R ?"),
    (b"3R02\x00", b"3 R ?"),
    (b"3S0 2=1", b"3 S ?"),
    (b"3S002=1", b"3 S ?"),
    (b"3S=1", b"3 S ?"),
    (b"3R", b"3 R ?"),
    (b"3X02", b"3 ? ?"),
    (b"3\tR02", b"3 ? ?"),
    (b"0R02", b"0 R 2"),
    (b"61R02", b"61 R 2"),
    (b"99S02=1", b"99 S 2"),
    (b"123R02", b"? ? ?"),
    (b" 3R02", b"? ? ?"),
    (b"R02", b"? ? ?"),
    (b"", b"? ? ?"),
    (b"\xc3\xa4", b"? ? ?"),
    (b"3R\xff2", b"3 R ?"),
]


@pytest.mark.parametrize("line,header", INVALID)
def test_parse_invalid_answers_can_with_recognised_header(line: bytes, header: bytes) -> None:
    with pytest.raises(InvalidCommand) as info:
        parse_request(line)
    assert format_error_reply(info.value) == (header + b"\x18\r").ljust(30, b"\0")


def test_kept_parses_are_bounded_and_junk_is_never_kept() -> None:
    from tcp_bridge.wire.requests import _parse_known
    _parse_known.cache_clear()
    for line, _ in INVALID:
        with pytest.raises(InvalidCommand):
            parse_item(line)
    assert _parse_known.cache_info().currsize == 0
    for axis in range(1, 61):
        for cmd in range(100):
            assert parse_item(b"%dR%02d" % (axis, cmd)) == ReadRequest(axis, cmd)
    assert parse_item(b"3R10") is parse_item(b"3R10")  # kept: the same immutable request
    assert _parse_known.cache_info().currsize == _parse_known.cache_info().maxsize


def test_recognise_header() -> None:
    assert recognise_header(b"3s02=1x") == (3, "S", 2)
    assert recognise_header(b"45r7") == (45, "R", 7)
    assert recognise_header(b"xyz") == (None, None, None)


def test_requests_validate_when_built() -> None:
    for bad in (lambda: ReadRequest(0, 2), lambda: ReadRequest(61, 2),
                lambda: ReadRequest(3, 100), lambda: WriteRequest(3, 2, "1x")):
        with pytest.raises(InvalidCommand):
            bad()


@given(axis=st.integers(1, 60), cmd=st.integers(0, 99),
       value=st.from_regex(r"\A[+-]?[0-9]{1,10}(\.[0-9]{0,6})?\Z|\A0x[0-9a-fA-F]{1,8}\Z"),
       write=st.booleans())
def test_request_round_trip(axis: int, cmd: int, value: str, write: bool) -> None:
    request = WriteRequest(axis, cmd, value) if write else ReadRequest(axis, cmd)
    (line,) = LineSplitter().feed(format_request(request))
    assert isinstance(line, bytes) and parse_request(line) == request


# --- replies -------------------------------------------------------------------

@pytest.mark.parametrize("value,text", [
    (12.819, "12.819"),
    (12.0, "12"),
    (-12.0, "-12"),
    (1e-7, "0.0000001"),
    (0.1 + 0.2, "0.3"),
    (1e19, "10000000000000000000"),
    (-0.0, "0"),
    (12, "12"),
    (-2147483648, "-2147483648"),
    (True, "1"),
])
def test_format_value(value: float, text: str) -> None:
    assert format_value(value) == text


@pytest.mark.parametrize("value,max_len,text", [
    (123456.123456789, 10, "123456.123"),
    (9.99, 2, "10"),
    (-0.00000001, 5, "0"),
    (2.5, 1, "2"),  # half-even, and never an exponent
])
def test_format_value_drops_fraction_digits_to_fit(value: float, max_len: int, text: str) -> None:
    assert format_value(value, max_len) == text


@pytest.mark.parametrize("value", [1e20, -1e19, float("nan"), float("inf"), 10**20])
def test_format_value_overflow(value: float) -> None:
    with pytest.raises(ReplyOverflow):
        format_value(value)


def test_read_reply_uses_the_room_of_its_header() -> None:
    reply = format_read_reply(3, 2, 1234567.1234567891)
    assert len(reply) == 30 and reply.startswith(b"3 R 2=1234567.12345679\x06\r")
    with pytest.raises(ReplyOverflow):
        format_read_reply(60, 99, 10**20)
    with pytest.raises(ReplyOverflow):
        format_read_reply(60, 99, "x" * 21)


def test_error_reply_status_mapping() -> None:
    assert status_for(InvalidCommand("x")) is Status.CAN
    assert status_for(LineTooLong("x")) is Status.CAN
    assert status_for(DeviceFailure("no answer", code=0x05040000)) is Status.NAK
    assert status_for(ReplyOverflow("x")) is Status.NAK
    assert status_for(RuntimeError("bug")) is Status.NAK
    request = WriteRequest(3, 2, "12")
    assert format_error_reply(DeviceFailure("x"), request) == b"3 S 2\x15\r".ljust(30, b"\0")
    assert format_error_reply(InvalidCommand("x"), request) == b"3 S 2\x18\r".ljust(30, b"\0")
    assert format_error_reply(DeviceFailure("x")) == b"? ? ?\x15\r".ljust(30, b"\0")


def test_error_tree() -> None:
    assert issubclass(InvalidCommand, (BridgeError, ValueError))
    assert issubclass(LineTooLong, InvalidCommand)
    assert issubclass(DeviceFailure, BridgeError) and not issubclass(DeviceFailure, ValueError)
    assert issubclass(MalformedReply, (BridgeError, ValueError))


DECODABLE = [
    # Spec 2.2.2 prose shows "3 S 02<ACK>": accepted as command 2.
    (b"3 S 02\x06\r", Reply(3, "S", 2, Status.ACK)),
    (b"3 s 2\x06\r", Reply(3, "S", 2, Status.ACK)),
    (b"3 S 10\x18\r", Reply(3, "S", 10, Status.CAN)),  # spec 2.2.2
    (b"3 R 0\x18\r", Reply(3, "R", 0, Status.CAN)),  # spec 2.3.2
    (b"3 R 2=12.819\x06\r", Reply(3, "R", 2, Status.ACK, "12.819")),
    (b"? ? ?\x18\r", Reply(None, None, None, Status.CAN)),
    (b"3 ? ?\x18\r", Reply(3, None, None, Status.CAN)),
]


@pytest.mark.parametrize("body,reply", DECODABLE)
def test_decode_reply(body: bytes, reply: Reply) -> None:
    assert decode_reply(body.ljust(30, b"\0")) == reply


MALFORMED = [
    b"3 S 2\x06\r".ljust(29, b"\0"),
    b"3 S 2\x06\r".ljust(31, b"\0"),
    b"3 S 2\x06".ljust(30, b"\0"),  # no CR
    b"3 S 2\x06\rX".ljust(30, b"\0"),  # junk after CR
    b"3 S 2\x07\r".ljust(30, b"\0"),  # not a status byte
    b"3 S 2\r".ljust(30, b"\0"),  # no status
    b"3  S 2\x06\r".ljust(30, b"\0"),
    b"3 S 2=5\x06\r".ljust(30, b"\0"),  # a write reply has no value
    b"3 R 2=5\x15\r".ljust(30, b"\0"),  # a NAK has no value
    b"3 R 2=\x06\r".ljust(30, b"\0"),
    b"? ? ?\x06\r".ljust(30, b"\0"),  # an ACK needs a header
    b"? S 2\x18\r".ljust(30, b"\0"),  # parts are recognised left to right
    b"3 X 2\x06\r".ljust(30, b"\0"),
    b"300 S 2\x06\r".ljust(30, b"\0"),
    b"3 R 2=1\x002\x06\r".ljust(30, b"\0"),
    b"\0" * 30,
]


@pytest.mark.parametrize("data", MALFORMED)
def test_decode_reply_is_strict(data: bytes) -> None:
    with pytest.raises(MalformedReply):
        decode_reply(data)


header_part = st.integers(0, 99)
replies = st.one_of(
    st.builds(Reply, header_part, st.sampled_from(["S", "R"]), header_part, st.sampled_from(Status)),
    st.builds(Reply, header_part, st.just("R"), header_part, st.just(Status.ACK),
              st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), min_size=1,
                       max_size=18)),
    st.builds(Reply, st.none(), st.none(), st.none(), st.sampled_from([Status.NAK, Status.CAN])),
)


@given(reply=replies)
def test_reply_round_trip(reply: Reply) -> None:
    data = reply.encode()
    assert len(data) == REPLY_SIZE
    assert decode_reply(data) == reply


@given(axis=st.integers(1, 60), cmd=st.integers(0, 99),
       value=st.integers() | st.floats(allow_nan=True, allow_infinity=True))
@settings(max_examples=300)
def test_read_replies_are_always_30_bytes(axis: int, cmd: int, value: float) -> None:
    try:
        data = format_read_reply(axis, cmd, value)
    except ReplyOverflow:
        return
    assert len(data) == REPLY_SIZE
    reply = decode_reply(data)
    assert (reply.axis, reply.kind, reply.cmd, reply.status) == (axis, "R", cmd, Status.ACK)
    assert reply.value is not None and "e" not in reply.value.lower()
    if isinstance(value, int):
        assert int(reply.value) == value
    else:
        assert float(reply.value) == pytest.approx(value, rel=1e-12, abs=1e-9)
    assert format_read_reply(axis, cmd, value) == data  # a kept reply is the same


@given(axis=st.integers(1, 60), cmd=st.integers(0, 99), value=st.integers(-2**31, 2**31 - 1))
def test_a_float_reply_equals_the_reply_of_the_same_integer(axis: int, cmd: int,
                                                            value: int) -> None:
    # Kept float replies are looked up by value, and 2.0 == 2: never mixed up.
    assert format_read_reply(axis, cmd, float(value)) == format_read_reply(axis, cmd, value)
    assert format_read_reply(axis, cmd, value + 0.5).rstrip(b"\0").endswith(b".5\x06\r")


@given(data=st.binary(min_size=30, max_size=30))
def test_random_replies_decode_or_raise_malformed(data: bytes) -> None:
    try:
        reply = decode_reply(data)
    except MalformedReply:
        return
    # Not always byte-identical ("02" re-encodes as "2"), but stable from then on.
    assert decode_reply(reply.encode()) == reply


# --- sans-I/O ------------------------------------------------------------------

FORBIDDEN = {"socket", "asyncio", "threading", "time", "serial", "usb", "can", "canopen",
             "selectors"}


@pytest.mark.parametrize("module", ["errors", "wire/__init__", "wire/lines", "wire/requests",
                                    "wire/replies", "tables/commands", "tables/units"])
def test_pure_modules_import_no_io(module: str) -> None:
    import tcp_bridge

    source = (Path(tcp_bridge.__file__).parent / f"{module}.py").read_text()
    imported = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            imported.add(node.module.split(".")[0])
    assert not imported & FORBIDDEN


@given(axis=st.integers(0, 99), cmd=st.integers(0, 99),
       value=st.integers() | st.integers(-10**25, 10**25) | st.booleans())
@settings(max_examples=300)
def test_an_int_read_reply_is_the_bytes_of_its_reply(axis: int, cmd: int, value: int) -> None:
    # format_read_reply writes int values without building a Reply (the status
    # poll's path): the bytes, and the overflow refusal, must be Reply's own.
    try:
        expected = Reply(axis, "R", cmd, Status.ACK, str(int(value))).encode()
    except ReplyOverflow:
        with pytest.raises(ReplyOverflow):
            format_read_reply(axis, cmd, value)
        return
    assert format_read_reply(axis, cmd, value) == expected
