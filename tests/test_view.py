"""epos_link.tools.view: candump-style times, colours only on a terminal, hex on request."""
from __future__ import annotations

import io

import pytest

from epos_link.tools.frames import LinkDecoder
from epos_link.tools.objects import load_directory
from epos_link.tools.view import RED, RESET, Clock, format_event, use_colour

REQUEST = bytes.fromhex("90 02 60 02 01 B0 30 00 2E 62")                   # guide Table 2-5
ANSWER = bytes.fromhex("90 02 00 04 00 00 00 00 01 90 90 00 00 9A 5C")    # guide Table 2-6
ERROR = bytes.fromhex("90 02 00 04 00 00 02 06 00 00 00 00 57 64")        # 0x06020000, as the simulator sends


def events(answer: bytes = ANSWER):  # type: ignore[no-untyped-def]
    d = LinkDecoder(load_directory())
    return d.feed(10.0, "TX", REQUEST) + d.feed(10.0025, "RX", answer)


def test_plain_line() -> None:
    tx, rx = events()
    clock = Clock("z")
    assert format_event(tx, clock) == ("(010.000000) TX ReadObject                     "
                                       "node 1 0x30B0/0x00 Home position crc ok")
    line = format_event(rx, clock)
    assert line.startswith("(010.002500) RX Answer(ReadObject)             node 1 0x30B0/0x00 Home position "
                           "= 36865 (0x00009001) ok crc ok 2.500 ms")
    assert "\x1b" not in line


def test_hex_and_errors() -> None:
    tx, rx = events(ERROR)
    line = format_event(rx, Clock("z"), hex_bytes=True)
    assert "error 0x06020000 Object does not exist error" in line
    assert line.endswith("[90 02 00 04 00 00 02 06 00 00 00 00 57 64]")
    coloured = format_event(rx, Clock("z"), colour=True)
    assert coloured.startswith(RED) and coloured.endswith(RESET)
    assert format_event(tx, Clock("z"), colour=True).startswith("\x1b[36m")  # TX cyan


@pytest.mark.parametrize("mode,first,second", [
    ("z", "(010.000000)", "(010.002500)"),
    ("d", "(000.000000)", "(000.002500)"),
    ("a", "(1700000010.000000)", "(1700000010.002500)"),
])
def test_time_modes(mode: str, first: str, second: str) -> None:
    tx, rx = events()
    clock = Clock(mode, start_wall=1_700_000_000.0)
    assert format_event(tx, clock).startswith(first)
    assert format_event(rx, clock).startswith(second)


def test_colour_only_on_a_terminal_without_no_color() -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert use_colour(Tty(), env={})
    assert not use_colour(Tty(), env={"NO_COLOR": "1"})
    assert use_colour(Tty(), env={"NO_COLOR": ""})  # no-color.org: set and not empty
    assert not use_colour(io.StringIO(), env={})
