"""The socketcand protocol, pure (epos_link.simulator.socketcand_wire).

Golden texts come from linux-can socketcand: doc/protocol.md and the formats
src/state_raw.c prints; python-can's socketcand client is the second reader.
"""
from __future__ import annotations

import pytest
from can.interfaces.socketcand.socketcand import (convert_ascii_message_to_can_message,
                                                  convert_can_message_to_ascii_message)
import can

from epos_link.simulator.socketcand_wire import (ECHO, OK, CommandReader, CommandTooLong, Frame,
                                                 Mode, Session, SocketcandError, error_reply,
                                                 format_frame, parse_send)
from tests.helpers import three_ways

# -- frames to the client --------------------------------------------------------------------


@pytest.mark.parametrize("frame, when, text", [
    # state_raw.c: "< frame %03X %ld.%06ld " then "%02X" per byte, then " >"
    (Frame(0x123, bytes([0x11, 0x22, 0x33, 0x44])), 23.424242, "< frame 123 23.424242 11223344 >"),
    (Frame(0x1AAAAAAA, b"\x01\xf1", extended=True), 1.5, "< frame 1AAAAAAA 1.500000 01F1 >"),
    (Frame(0x5, extended=True), 7.0, "< frame 00000005 7.000000  >"),
    (Frame(0x123), 0.000001, "< frame 123 0.000001  >"),
    # protocol.md "RTR frame transmission": < rtr can_id seconds.useconds can_dlc >
    (Frame(0x123, remote=True, dlc=4), 23.424242, "< rtr 123 23.424242 4 >"),
    # state_raw.c: "< error %03X %ld.%06ld >" with the error class
    (Frame(0x4, error=True), 2.25, "< error 004 2.250000 >"),
])
def test_frames_are_formatted_as_the_reference_server_prints_them(frame: Frame, when: float,
                                                                  text: str) -> None:
    assert format_frame(frame, when) == text


def test_timestamps_round_to_the_microsecond_without_overflowing() -> None:
    assert format_frame(Frame(0x1), 9.9999999).split()[3] == "10.000000"


@pytest.mark.parametrize("frame", [
    Frame(0x7FF, bytes(range(8))), Frame(0x0), Frame(0x1FFFFFFF, b"\xff", extended=True),
])
def test_python_can_reads_what_we_send(frame: Frame) -> None:
    msg = convert_ascii_message_to_can_message(format_frame(frame, 12.5))
    assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id, msg.timestamp) == \
        (frame.can_id, frame.data, frame.extended, 12.5)


def test_python_can_reads_an_error_frame_as_one() -> None:
    msg = convert_ascii_message_to_can_message(format_frame(Frame(0x4, error=True), 1.0))
    assert msg.is_error_frame and msg.arbitration_id == 0x4


# -- frames from the client ------------------------------------------------------------------


@pytest.mark.parametrize("text, frame", [
    ("send 123 0", Frame(0x123)),  # protocol.md: "ID: 123, no data"
    ("send 1AAAAAAA 2 1 F1", Frame(0x1AAAAAAA, b"\x01\xf1", extended=True)),  # protocol.md
    ("send 00000123 1 ff", Frame(0x123, b"\xff", extended=True)),  # 8 digits: extended
    ("sendrtr 123 0", Frame(0x123, remote=True, dlc=0)),  # protocol.md sendrtr
    ("sendrtr 1AAAAAAA 2", Frame(0x1AAAAAAA, extended=True, remote=True, dlc=2)),
])
def test_send_commands_of_the_protocol_description(text: str, frame: Frame) -> None:
    assert parse_send(text.split()) == frame


@pytest.mark.parametrize("msg", [
    can.Message(arbitration_id=0x602, data=[0x40, 0, 0x10, 0, 0, 0, 0, 0], is_extended_id=False),
    can.Message(arbitration_id=0x18FF00AA, data=[1, 2], is_extended_id=True),
    can.Message(arbitration_id=0x80, data=[], is_extended_id=False),
])
def test_we_read_what_python_can_sends(msg: can.Message) -> None:
    text = convert_can_message_to_ascii_message(msg)
    (command,) = CommandReader().feed(text.encode())
    frame = parse_send(command.split())
    assert (frame.can_id, frame.data, frame.extended) == (msg.arbitration_id, bytes(msg.data),
                                                          msg.is_extended_id)


@pytest.mark.parametrize("text", [
    "send", "send 123", "send xyz 0", "send 123 2 11", "send 123 1 11 22", "send 123 9 " + "0 " * 9,
    "send 123 1 100", "send 123 1 zz", "send 800 0", "send 20000000 0", "send 123 -1",
    "sendrtr 123", "sendrtr 123 9", "sendrtr 123 1 11",
])
def test_malformed_sends_are_errors(text: str) -> None:
    with pytest.raises(SocketcandError):
        parse_send(text.split())


# -- the command stream -----------------------------------------------------------------------

STREAM = b"< open can0 >< rawmode >< send 123 2 11 22 >< echo >"
COMMANDS = ["open can0", "rawmode", "send 123 2 11 22", "echo"]


@pytest.mark.parametrize("label, chunks, junk", list(three_ways(STREAM, junk=b"hi\r\n")))
def test_commands_fed_three_ways(label: str, chunks: list[bytes], junk: bytes) -> None:
    reader = CommandReader()
    got = [command for chunk in chunks for command in reader.feed(chunk)]
    assert got == COMMANDS, label


def test_text_outside_brackets_is_skipped() -> None:
    # socketcand's receive_command() drops what comes before a '<'.
    assert CommandReader().feed(b"\r\n>> junk< echo >\n") == ["echo"]


def test_a_command_without_end_is_bounded() -> None:
    reader = CommandReader(limit=64)
    assert reader.feed(b"<" + b"x" * 60) == []
    with pytest.raises(CommandTooLong):
        reader.feed(b"x" * 10)
    with pytest.raises(CommandTooLong):
        CommandReader(limit=64).feed(b"<" + b"y" * 100 + b">")


def test_non_ascii_is_an_unknown_command_not_a_crash() -> None:
    (command,) = CommandReader().feed("< séнd >".encode())
    session = Session()
    session.handle("open can0")
    assert session.handle(command).replies[0].startswith("< error unknown command")


# -- one connection's modes -----------------------------------------------------------------


def test_the_handshake_python_can_expects() -> None:
    session = Session("can0")
    assert session.handle("open can0").replies == [OK] and session.mode is Mode.BCM
    assert not session.receives_frames  # BCM mode: nothing without a subscription
    outcome = session.handle("rawmode")
    assert outcome.replies == [OK] and outcome.entered_raw and session.receives_frames
    assert session.handle("echo").replies == [ECHO]
    assert session.handle("bcmmode").replies == [OK] and not session.receives_frames


def test_another_bus_is_refused_and_closes() -> None:
    outcome = Session("can0").handle("open vcan1")
    assert outcome.close and outcome.replies == ["< error could not open bus >"]


@pytest.mark.parametrize("text", ["", "rawmode", "echo", "send 123 0", "open"])
def test_nothing_but_open_before_a_bus_is_open(text: str) -> None:
    outcome = Session().handle(text)
    assert not outcome.close and outcome.frame is None
    assert outcome.replies[0].startswith("< error ")


@pytest.mark.parametrize("text", ["add 1 0 123 0", "subscribe 0 0 123", "filter 0 0 123 0",
                                  "controlmode", "isotpmode", "fdsend 123 0 0", "statistics 10",
                                  "send 123 1", "echo now"])
def test_unsupported_or_malformed_commands_are_errors_and_the_session_goes_on(text: str) -> None:
    session = Session()
    session.handle("open can0")
    session.handle("rawmode")
    outcome = session.handle(text)
    assert outcome.replies[0].startswith("< error ") and outcome.replies[0].endswith(" >")
    assert not outcome.close and outcome.frame is None and session.receives_frames
    assert session.handle("send 123 1 aa").frame == Frame(0x123, b"\xaa")


def test_an_error_text_cannot_end_its_reply_early() -> None:
    assert error_reply("bad <x> here") == "< error bad x here >"
