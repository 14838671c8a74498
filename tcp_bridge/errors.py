"""The error tree of tcp_bridge.

::

    BridgeError
     +-- InvalidCommand (ValueError)      reply CAN: unparseable line, unknown axis or
     |    |                               command, bad value, not readable / not writable
     |    +-- LineTooLong                 a request line above the splitter's limit
     +-- DeviceFailure                    reply NAK: the device transfer failed or the
     |    |                               node is absent (spec 2.2.2 / 2.3.2, "SDO ACK/NAK")
     |    +-- NodeSilent                  the node did not answer at all (timeout, link
     |    |                               failure), as opposed to an SDO abort (tcp_bridge.bus.sdo)
     |    +-- OutcomeUnknown              the node went silent after a write that starts a
     |    |                               move (tcp_bridge.motion rule 4)
     |    +-- SafetyRefusal               the bridge refused to lower an axis's state or to
     |    |                               reset it (tcp_bridge.motion rule 1)
     |    +-- SilentLink                  reply NAK at once: the bus's device or the node
     |    |                               is declared silent (tcp_bridge.bus.health); nothing sent
     |    +-- DependencyFailed            reply NAK, nothing sent: resolved against an earlier
     |    |                               write that was not executed (tcp_bridge.plan.job)
     |    +-- Superseded                  reply NAK: a stop of one of its axes arrived before
     |                                    this move's stages all began; those not begun never
     |                                    do, the begun ones are halted (tcp_bridge.bus.order)
     +-- ReplyOverflow (ValueError)       reply NAK: a value read from the device cannot be
     |                                    written into the 30-byte reply (spec 2.2.2)
     +-- MalformedReply (ValueError)      client side: a reply that is not the 30-byte
     |                                    format of spec 2.2.2 / 2.3.2
     +-- ConfigError (ValueError)         the axis table or the state file is not valid
     |                                    (start-up only: one line naming it, exit 2)
     +-- BusUnavailable (OSError)         a bus's device or adapter cannot be opened now
                                          (unplugged, refused, powered off): not a mistake
                                          of the table; serve opens it again later
                                          (tcp_bridge.backends.reopen)

A backend raises what its library promises (canopen's ``SdoAbortedError`` and
``SdoCommunicationError``, e.g. the EtherCAT backend's ``SlaveUnreachable``; python-can's
``CanError``; ``epos_link``'s ``EposError`` tree): :class:`tcp_bridge.bus.sdo.SdoPort`
turns each into :class:`DeviceFailure` or :class:`NodeSilent` at the one seam.

Not a reply, an internal signal: :class:`NeedsBus` (a read answered from PDOs on
the event loop needs an SDO transfer after all: it is queued on its bus instead;
:mod:`tcp_bridge.bus.shared_reads` rule 5).

The spec (PSI TCP-IP to CANopen gateway, rev 2.3, 2.2.2) has three answers:
ACK (executed), NAK (not executed; the drive did not answer) and CAN (the
command is not valid). :func:`tcp_bridge.wire.status_for` maps this tree
onto them, so the server has exactly one place that turns an exception into a
reply.

:class:`InvalidCommand` carries the parts of the request header that could be
recognised (``axis``, ``kind``, ``cmd``; each may be ``None``) so that even a
rejected request is answered with its own header, e.g. ``3 S 2<CAN><CR>``.
"""
from __future__ import annotations

from typing import Optional


class BridgeError(Exception):
    """Base of every error raised by tcp_bridge."""


class InvalidCommand(BridgeError, ValueError):
    """The request is not a valid command; the gateway answers CAN (spec 2.2.2).

    ``axis``, ``kind`` (``"S"`` or ``"R"``) and ``cmd`` are whatever could be
    recognised from the request, ``None`` for the parts that could not.
    """

    def __init__(
        self,
        message: str,
        *,
        axis: Optional[int] = None,
        kind: Optional[str] = None,
        cmd: Optional[int] = None,
    ) -> None:
        super().__init__(message)
        self.axis = axis
        self.kind = kind
        self.cmd = cmd


class LineTooLong(InvalidCommand):
    """A request line longer than the splitter's ``max_line`` bytes.

    ``head`` holds the first ``max_line`` bytes of the line, from which the
    header fields (``axis``, ``kind``, ``cmd``) were recognised if possible.
    """

    def __init__(
        self,
        message: str,
        *,
        head: bytes = b"",
        limit: int = 0,
        axis: Optional[int] = None,
        kind: Optional[str] = None,
        cmd: Optional[int] = None,
    ) -> None:
        super().__init__(message, axis=axis, kind=kind, cmd=cmd)
        self.head = bytes(head)
        self.limit = limit


class DeviceFailure(BridgeError):
    """The device transfer failed or the node is absent; the gateway answers NAK.

    ``code`` is the CANopen SDO abort code when there was one.
    """

    def __init__(self, message: str, code: Optional[int] = None) -> None:
        super().__init__(message)
        self.code = code


class SilentLink(DeviceFailure):
    """Refused without a transfer: the bus's device, or the node, was declared silent
    and no probe has heard it since (:mod:`tcp_bridge.bus.health`, fail-fast buses)."""


class NodeSilent(DeviceFailure):
    """The node did not answer at all (timeout, link failure), as opposed to an abort.

    Silence is not evidence of a power cycle (tcp_bridge.motion, rule 3): a
    write that went unanswered may or may not have arrived, which the motion
    sequences find out by reading the drive back (rule 4).
    """


class Superseded(DeviceFailure):
    """A stop (S00=8, S90=0, S04=0, S16, S17) of one of this move's axes arrived after it,
    before every stage of the move began: the stages not begun never begin, the begun
    ones are halted (:mod:`tcp_bridge.bus.order`). Answered NAK: not executed whole."""


class NeedsBus(Exception):
    """A read planned to answer from PDOs on the event loop needs the bus after all
    (:mod:`tcp_bridge.bus.shared_reads` rule 5): queue it. Never a reply."""


class OutcomeUnknown(DeviceFailure):
    """The node went silent after a write that starts a move (motion rule 4)."""


class SafetyRefusal(DeviceFailure):
    """The bridge refused to lower the state of an axis or to reset it (motion rule 1)."""


class ConfigError(BridgeError, ValueError):
    """The axis table or the state file is not valid; raised at start-up only."""


class ReplyOverflow(BridgeError, ValueError):
    """A value whose integer part does not fit into the 30-byte reply (spec 2.2.2).

    The command itself was valid, so the gateway answers NAK, not CAN.
    """


class MalformedReply(BridgeError, ValueError):
    """Bytes received by a client that are not a 30-byte reply of spec 2.2.2 / 2.3.2."""


class DependencyFailed(DeviceFailure):
    """An earlier request whose value this one was resolved against was not executed."""


class BusUnavailable(BridgeError, OSError):
    """A bus's device or adapter cannot be opened now: a port that is missing, busy or
    refused, a CAN interface that is down. A configuration mistake is a ConfigError."""
