"""The socketcand protocol, pure: commands in, replies and frames out (no I/O).

Source: linux-can socketcand ``doc/protocol.md`` ("Socketcand protocol"), and
its reference server ``src/state_nobus.c`` / ``src/state_raw.c`` where the two
differ; python-can's ``can.interfaces.socketcand`` client is the compatibility
test. Every message is ASCII between ``<`` and ``>``; there are no line ends.

A connection's modes (protocol.md "Mode NO_BUS", "Mode BCM", "Mode RAW")::

    connect -> "< hi >"           NO_BUS
    < open can0 >   -> < ok >     BCM    (another bus name: < error could not open bus >, closed)
    < rawmode >     -> < ok >     RAW    (every frame on the bus is sent to the client)
    < bcmmode >     -> < ok >     BCM    (from RAW)
    < echo >        -> < echo >          (BCM and RAW)
    < send ID LEN B0 .. >                a data frame onto the bus (BCM and RAW)
    < sendrtr ID DLC >                   a remote frame onto the bus (BCM and RAW)

Frames to a RAW client, as ``state_raw.c`` prints them (protocol.md writes the
data bytes with spaces; the reference server and python-can's parser use none)::

    < frame 123 23.424242 11223344 >      standard id: 3 hex digits, extended: 8
    < rtr 123 23.424242 4 >               remote frame with its DLC (protocol.md)
    < error 004 23.424242 >               error frame: its error class (state_raw.c)

``ID`` in ``send`` is hex and extended exactly when written with 8 digits
(``state_raw.c``: ``element_length(buf, 2) == 8``); ``LEN`` is decimal 0..8.

**Chosen** where the reference server is silent or only logs:

* a command the server does not support (the BCM cyclic jobs and filters,
  CONTROL and ISO-TP modes, CAN FD, bus configuration) and a malformed ``send``
  are answered ``< error TEXT >`` (``state_raw.c`` answers unknown commands so,
  and only logs a bad ``send``); the connection goes on;
* text outside ``< >`` is skipped, as ``receive_command()`` skips what comes
  before a ``<``;
* a command longer than :data:`MAX_COMMAND` characters without its ``>`` ends
  the connection (:class:`CommandTooLong`): the stream cannot be trusted to
  resynchronise, and the buffer stays bounded.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Final, List, Optional, Tuple

MAX_COMMAND: Final = 256  # the longest valid command ("< send 1FFFFFFF 8 ff .. ff >") is 44
HI: Final = "< hi >"
OK: Final = "< ok >"
ECHO: Final = "< echo >"
SFF_MASK: Final = 0x7FF  # 11-bit identifier (CAN 2.0A)
EFF_MASK: Final = 0x1FFFFFFF  # 29-bit identifier (CAN 2.0B)


class SocketcandError(ValueError):
    """A command the server cannot carry out; its text goes into ``< error TEXT >``."""


class CommandTooLong(SocketcandError):
    """No ``>`` within :data:`MAX_COMMAND` characters: the connection is ended."""


@dataclass(frozen=True)
class Frame:
    """One classic CAN frame as socketcand carries it."""

    can_id: int
    data: bytes = b""
    extended: bool = False
    remote: bool = False
    error: bool = False
    dlc: int = -1  # -1: len(data); a remote frame carries a DLC and no data

    def __post_init__(self) -> None:
        if self.dlc == -1:
            object.__setattr__(self, "dlc", len(self.data))
        if not 0 <= self.can_id <= (EFF_MASK if self.extended or self.error else SFF_MASK):
            raise SocketcandError(f"identifier {self.can_id:X} out of range")
        if len(self.data) > 8 or not 0 <= self.dlc <= 8:
            raise SocketcandError("a classic CAN frame carries 0..8 bytes")
        if self.remote and self.data:
            raise SocketcandError("a remote frame carries no data")
        if not self.remote and self.dlc != len(self.data):
            raise SocketcandError(f"length {self.dlc} but {len(self.data)} data bytes")


def error_reply(text: str) -> str:
    """``< error TEXT >``, with any ``<``/``>`` in ``text`` taken out (they would end it)."""
    clean = " ".join(text.replace("<", " ").replace(">", " ").split())
    return f"< error {clean} >"


def _timestamp(seconds: float) -> str:
    """``SECS.USECS`` as ``state_raw.c`` prints a timeval (``%ld.%06ld``)."""
    secs, usecs = divmod(max(0, round(seconds * 1_000_000)), 1_000_000)
    return f"{secs}.{usecs:06d}"


def format_frame(frame: Frame, timestamp: float) -> str:
    """What a RAW client receives for ``frame`` seen on the bus at ``timestamp``."""
    when = _timestamp(timestamp)
    if frame.error:
        return f"< error {frame.can_id & EFF_MASK:03X} {when} >"
    ident = f"{frame.can_id:08X}" if frame.extended else f"{frame.can_id:03X}"
    if frame.remote:
        return f"< rtr {ident} {when} {frame.dlc} >"
    return f"< frame {ident} {when} {frame.data.hex().upper()} >"


def _identifier(text: str) -> Tuple[int, bool]:
    try:
        value = int(text, 16)
    except ValueError:
        raise SocketcandError(f"bad identifier {text}") from None
    return value, len(text) == 8


def _number(text: str, what: str) -> int:
    if not text.isdigit():
        raise SocketcandError(f"bad {what} {text}")
    return int(text)


def parse_send(words: List[str]) -> Frame:
    """``send ID LEN B0 ..`` or ``sendrtr ID DLC`` (protocol.md "Send a single frame")."""
    if words[0] == "sendrtr":
        if len(words) != 3:
            raise SocketcandError("syntax: < sendrtr can_id can_dlc >")
        can_id, extended = _identifier(words[1])
        return Frame(can_id, extended=extended, remote=True, dlc=_number(words[2], "dlc"))
    if len(words) < 3:
        raise SocketcandError("syntax: < send can_id can_dlc [data]* >")
    can_id, extended = _identifier(words[1])
    length = _number(words[2], "length")
    if len(words) != 3 + length:
        raise SocketcandError(f"length {length} but {len(words) - 3} data bytes")
    try:
        data = bytes(int(b, 16) for b in words[3:] if len(b) <= 2)
    except ValueError:
        raise SocketcandError("data bytes are hex 00..FF") from None
    if len(data) != length:
        raise SocketcandError("data bytes are hex 00..FF")
    return Frame(can_id, data, extended=extended)


class CommandReader:
    """Splits the client's byte stream into the texts of its ``< .. >`` commands."""

    def __init__(self, limit: int = MAX_COMMAND) -> None:
        self.limit = limit
        self._buffer = bytearray()

    def feed(self, data: bytes) -> List[str]:
        """The commands completed by ``data`` (without their ``<`` and ``>``), in order."""
        self._buffer += data
        commands: List[str] = []
        while True:
            start = self._buffer.find(b"<")
            if start < 0:
                self._buffer.clear()  # nothing here can start a command (receive_command())
                return commands
            del self._buffer[:start]
            end = self._buffer.find(b">")
            if end < 0:
                if len(self._buffer) > self.limit:
                    raise CommandTooLong(f"no '>' within {self.limit} characters")
                return commands
            if end + 1 > self.limit:
                raise CommandTooLong(f"a command longer than {self.limit} characters")
            commands.append(self._buffer[1:end].decode("ascii", "replace").strip())
            del self._buffer[:end + 1]


class Mode(enum.Enum):
    NO_BUS = "no bus"
    BCM = "bcm"
    RAW = "raw"


@dataclass
class Outcome:
    """What one command asks of the server."""

    replies: List[str] = field(default_factory=list)
    frame: Optional[Frame] = None  # to put onto the bus
    entered_raw: bool = False  # the client has just been told < ok > to < rawmode >
    close: bool = False  # end the connection after the replies


class Session:
    """One client's protocol state: :meth:`handle` each command text of :class:`CommandReader`."""

    def __init__(self, bus_name: str = "can0") -> None:
        self.bus_name = bus_name
        self.mode = Mode.NO_BUS

    @property
    def receives_frames(self) -> bool:
        """RAW mode: "every frame on the bus will immediately be received" (protocol.md)."""
        return self.mode is Mode.RAW

    def handle(self, text: str) -> Outcome:
        words = text.split()
        if not words:
            return Outcome([error_reply("empty command")])
        verb = words[0]
        if self.mode is Mode.NO_BUS:
            if verb != "open" or len(words) != 2:
                return Outcome([error_reply(f"unknown command {verb}: open a bus first")])
            if words[1] != self.bus_name:
                # state_nobus.c: an unknown bus is an error and the end of the connection.
                return Outcome([error_reply("could not open bus")], close=True)
            self.mode = Mode.BCM
            return Outcome([OK])
        if verb == "echo" and len(words) == 1:
            return Outcome([ECHO])
        if verb in ("send", "sendrtr"):
            try:
                return Outcome(frame=parse_send(words))
            except SocketcandError as exc:
                return Outcome([error_reply(f"{verb}: {exc}")])
        if verb == "rawmode" and len(words) == 1:
            entered = self.mode is not Mode.RAW
            self.mode = Mode.RAW
            return Outcome([OK], entered_raw=entered)
        if verb == "bcmmode" and len(words) == 1:
            self.mode = Mode.BCM
            return Outcome([OK])
        return Outcome([error_reply(f"unknown command {verb[:32]}")])


__all__ = ["CommandReader", "CommandTooLong", "ECHO", "Frame", "HI", "MAX_COMMAND", "Mode",
           "OK", "Outcome", "Session", "SocketcandError", "error_reply", "format_frame",
           "parse_send"]
