"""The error tree of epos_link.

::

    EposError
     +-- LocalProtocolError (ValueError)      we were asked to send something illegal
     |    +-- GatewayNotSupportedError        a service the EPOS4 gateway cannot forward
     +-- RemoteProtocolError                  the peer sent bytes that break the protocol
     |    +-- JunkBytesError                  bytes outside any frame
     |    +-- CrcError                        a whole frame whose CRC does not match
     |    +-- StuffingError                   0x90 followed by neither 0x90 nor 0x02
     |    +-- FrameLengthError                Len above 143 words
     |    +-- TruncatedFrameError             a frame cut off by a new DLE STX or end of input
     |    +-- MessageFormatError              a good frame whose payload is not the message
     +-- DeviceError                          the device answered with an error code (.code)
     +-- EposTimeoutError (TimeoutError)      no complete answer before the deadline
     +-- TransportError (OSError)             the link itself failed (unplugged, closed, ...)

Decoders raise; they never log and return None. Communication errors (remote
protocol errors, timeouts, transport errors) may be retried; local protocol
errors and device errors are final.
"""
from __future__ import annotations

from typing import Optional


class EposError(Exception):
    """Base of every error raised by epos_link."""


class LocalProtocolError(EposError, ValueError):
    """We tried to build or send something the protocol does not allow."""


class GatewayNotSupportedError(LocalProtocolError):
    """The EPOS4 gateway cannot forward this service to a remote node (guide 2.1.2)."""


class RemoteProtocolError(EposError):
    """The peer sent bytes that violate MAXON SERIAL V2 framing or message layout.

    ``raw`` holds the bytes the decoder discarded because of this error, so a
    debugging tool can show them.
    """

    def __init__(self, message: str, raw: bytes = b"") -> None:
        super().__init__(message)
        self.raw = bytes(raw)


class JunkBytesError(RemoteProtocolError):
    """Bytes that are not part of any frame (before a DLE STX, or left at the end)."""


class CrcError(RemoteProtocolError):
    """A complete frame whose CRC does not match. ``frame`` is still decoded."""

    def __init__(self, message: str, raw: bytes = b"", frame: "Optional[object]" = None) -> None:
        super().__init__(message, raw)
        self.frame = frame


class StuffingError(RemoteProtocolError):
    """DLE (0x90) inside a frame followed by something other than DLE or STX (guide 2.2.4)."""


class FrameLengthError(RemoteProtocolError):
    """The Len field exceeds the guide's maximum of 143 words (guide 2.2.2)."""


class TruncatedFrameError(RemoteProtocolError):
    """A frame ended early: a new DLE STX arrived, or the input ended."""


class MessageFormatError(RemoteProtocolError):
    """A frame with a good CRC whose payload does not fit the expected message."""


class DeviceError(EposError):
    """The device answered with a non-zero communication error code (guide chapter 6)."""

    def __init__(self, code: int, context: str = "") -> None:
        from .codes import describe_error

        self.code = code
        self.name = describe_error(code)
        text = f"0x{code:08X} {self.name}"
        super().__init__(f"{context}: {text}" if context else text)


class EposTimeoutError(EposError, TimeoutError):
    """No complete, valid answer arrived before the deadline.

    ``heard`` is True when bytes did come back but made no valid answer (a
    damaged answer: its DLE STX or its length garbled), False for silence: a
    caller may retry the one and fail fast on the other.
    """

    def __init__(self, message: str = "", *, heard: bool = False) -> None:
        super().__init__(message)
        self.heard = heard


class TransportError(EposError, OSError):
    """The underlying link failed: port missing, unplugged, closed, permission denied."""
