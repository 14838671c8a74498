"""``tcp-bridge record``: record an axis through a running bridge, as a PSI client.

::

    tcp-bridge record HOST:PORT AXIS [COMMAND...] [--period S] [--duration S] [--pre S]
                      [--trigger now|move|COMMAND>LEVEL|COMMAND<LEVEL] [--csv FILE] [--plot FILE]...

Why a client of the bridge and not of the drive: while a bridge serves an axis, the
drive's default SDO channel (600h/580h + node id) is the bridge's (or its EPOS4
gateway's), and CiA 301 7.2.4 allows one client per SDO channel; a second client
(``epos-link record`` through the same EPOS4, a canopen script) takes the bridge's
answers for its own and the bridge its answers (issue 34: ``record`` stopped after
10 samples with a bare "SDO protocol timed out"). Here every sample is ordinary PSI
read requests (``2R12``, spec 2.3), on one connection, answered by the bridge's
own transfers: they take their place in its arrival order, share a transfer with
identical reads of other clients (:mod:`tcp_bridge.bus.shared_reads`), are answered
from PDOs where the bus has them, and can never move anything (only R commands are
sent).

A COMMAND is a readable command of the PSI table (:mod:`tcp_bridge.tables.commands`)
by number (``12``, ``R12``) or by its name in the table (``position``, ``status``,
``actual_velocity``, matched as ``epos-link`` matches object names: case, spaces and
underscores aside). Default: ``12 14 10`` (position and actual velocity in the
axis's user units, the statusword). Values are the reply's text as a number.

Everything after the requests is ``epos-link record``'s, reused, not copied:
triggers, schedule and ring buffer (:mod:`epos_link.tools.recording`; ``move`` needs
the statusword R10, added as a last column when not named), the sampling loop and
progress (:mod:`epos_link.tools.record`), the checks of the outputs before anything
is sent and the CSV and plots after (:mod:`epos_link.tools.record_output`,
:mod:`epos_link.tools.plot`). A row's time is the host's monotonic clock at the
middle of that row's requests, which go out together (one write) and are answered
in order (the bridge answers a connection's requests in order, tcp_bridge.server).

A reply that is not ACK ends the recording with what came before, written, and one
line saying why: NAK (the bridge could not read the drive) exit 1, CAN (the request
is not valid, e.g. no such axis) exit 2, a connection that fails exit 2.
"""
from __future__ import annotations

import argparse
import re
import socket
import sys
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

from epos_link.tools.record import Outcome, Progress, sample_loop, summary
from epos_link.tools.record_output import check_outputs, write_outputs
from epos_link.tools.recording import (STATUSWORD, Channel, Crossing, Immediate, MoveStart,
                                       Recorder, Schedule, Trigger, Value)

from .client import parse_address
from .cli_types import address, positive_seconds
from .errors import MalformedReply
from .tables.commands import COMMANDS, CommandKind, CommandSpec, Quantity, ValueType
from .wire import REPLY_SIZE, Reply, Status, decode_reply

PROG = "tcp-bridge record"
DEFAULT_COMMANDS = ("12", "14", "10")
STATUS_COMMAND = 10  # R10 Status: the statusword 6041h (spec section 4)


class RefusedRead(Exception):
    """The bridge answered a read NAK or CAN."""

    def __init__(self, request: str, reply: Reply) -> None:
        self.request, self.reply = request, reply
        why = {Status.NAK: "NAK (the bridge could not read it from the drive; its log says why)",
               Status.CAN: "CAN (not a valid request: no such axis or command?)"}
        super().__init__(f"{request}: {why.get(reply.status, reply.status.name)}")


# --- commands and the trigger (pure) -------------------------------------------------


def _key(text: str) -> str:
    return re.sub(r"[\s_/]+", "", text.lower())


def command_of(text: str) -> CommandSpec:
    """A readable command by number (``12``, ``R12``) or table name; ValueError if none."""
    word = text.strip()
    m = re.fullmatch(r"[Rr]?(\d{1,2})", word)
    if m:
        spec = COMMANDS.get(int(m.group(1)))
        if spec is None:
            raise ValueError(f"{text!r}: no command {int(m.group(1))} in the PSI table")
    else:
        found = [c for c in COMMANDS.values() if _key(c.name) == _key(word)]
        if not found:
            raise ValueError(f"{text!r}: no command of that name (a number such as 12, "
                             "or a name such as position, status, actual_velocity)")
        spec = found[0]
    if not spec.readable:
        raise ValueError(f"{text!r}: command {spec.number} ({spec.name}) is not readable")
    if spec.value_type is ValueType.TEXT:
        raise ValueError(f"{text!r}: command {spec.number} ({spec.name}) is text; "
                         "record samples numbers only")
    return spec


def channel_of(spec: CommandSpec) -> Channel:
    """The CSV column of a command: its name and R number, in the axis's units."""
    unit = ""
    if spec.user_units:
        unit = {Quantity.VELOCITY: "user units/s",
                Quantity.ACCELERATION: "user units/s^2"}.get(spec.quantity, "user units")
    # R10 is the statusword itself: the column gets its CiA 402 state (recording.py);
    # R82-R84 are single bits of it, not the word.
    index, sub = STATUSWORD if spec.number == STATUS_COMMAND else (
        (spec.index or 0, spec.subindex or 0) if spec.kind is CommandKind.SDO else (0, 0))
    return Channel(index, sub, f"{spec.name.lower()} (R{spec.number})", unit)


def parse_trigger(text: str, specs: List[CommandSpec]) -> Trigger:
    """The trigger; a command it names that is not recorded is appended to ``specs``."""
    def column(spec: CommandSpec) -> int:
        for k, s in enumerate(specs):
            if s.number == spec.number:
                return k
        specs.append(spec)
        return len(specs) - 1

    word = text.strip()
    if word == "now":
        return Immediate()
    if word == "move":
        return MoveStart(column(COMMANDS[STATUS_COMMAND]))
    m = re.fullmatch(r"(.+?)\s*([<>])\s*(\S+)", word)
    if not m:
        raise ValueError(f"--trigger {text!r}: now, move, COMMAND>LEVEL or COMMAND<LEVEL")
    try:
        level = float(m.group(3))
    except ValueError:
        raise ValueError(f"--trigger {text!r}: {m.group(3)!r} is not a number") from None
    return Crossing(column(command_of(m.group(1))), level, m.group(2) == ">")


def value_of(text: Optional[str]) -> Value:
    """A reply's value as a number (int when it is one): the bridge formats numbers only
    for these commands (tcp_bridge.wire.format_value)."""
    if text is None:
        raise MalformedReply("a read reply without a value")
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            raise MalformedReply(f"{text!r} is not a number") from None


# --- the session (I/O) -----------------------------------------------------------------


@dataclass
class Session:
    """One connection to the bridge; one row = the requests in one write, replies in order."""

    sock: socket.socket
    axis: int
    specs: Sequence[CommandSpec]

    @classmethod
    def open(cls, where: str, axis: int, specs: Sequence[CommandSpec],
             timeout: float) -> "Session":
        host, port = parse_address(where)
        return cls(socket.create_connection((host, port), timeout=timeout), axis, specs)

    def row(self) -> Tuple[Value, ...]:
        requests = [f"{self.axis}R{spec.number}" for spec in self.specs]
        self.sock.sendall(b"".join(r.encode("ascii") + b"\r" for r in requests))
        values = []
        for request, spec in zip(requests, self.specs):
            reply = self._reply()
            if reply.status is not Status.ACK:
                raise RefusedRead(request, reply)
            if (reply.axis, reply.cmd) != (self.axis, spec.number):
                raise MalformedReply(f"{request}: the reply is for {reply.axis} R{reply.cmd}")
            values.append(value_of(reply.value))
        return tuple(values)

    def _reply(self) -> Reply:
        data = b""
        while len(data) < REPLY_SIZE:
            chunk = self.sock.recv(REPLY_SIZE - len(data))
            if not chunk:
                raise MalformedReply(f"connection closed after {len(data)} bytes of a reply")
            data += chunk
        return decode_reply(data)

    def close(self) -> None:
        self.sock.close()


def record(session: Session, recorder: Recorder, schedule: Schedule,
           progress: Optional[Progress] = None) -> Outcome:
    """Sample through ``session`` until the recorder is done (or an error, or Ctrl-C)."""
    return sample_loop(session.row, recorder, schedule, progress=progress,
                       errors=(OSError, MalformedReply, RefusedRead))


# --- the command -----------------------------------------------------------------------


def _axis(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 1 <= value <= 99:
        raise argparse.ArgumentTypeError(f"{text!r} is not an axis (AxAddr 1..99, spec 2.2)")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError("must be 0 or more seconds")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("address", metavar="HOST:PORT", type=address,
                   help="the bridge's PSI port, e.g. 127.0.0.1:1913 (maintenance)")
    p.add_argument("axis", metavar="AXIS", type=_axis, help="the axis (AxAddr) to record")
    p.add_argument("commands", metavar="COMMAND", nargs="*",
                   help="readable PSI commands by number or name (default: 12 14 10, "
                        "position, actual velocity, status)")
    p.add_argument("--period", type=_seconds, default=0.0, metavar="S",
                   help="sample period in seconds (default 0: as fast as the bridge answers)")
    p.add_argument("--duration", type=_seconds, default=5.0, metavar="S",
                   help="seconds recorded after the trigger (default 5)")
    p.add_argument("--pre", type=_seconds, default=0.0, metavar="S",
                   help="seconds kept before the trigger (default 0)")
    p.add_argument("--trigger", default="now", metavar="WHEN",
                   help="now (default); move: the statusword (R10) shows a move starting; "
                        "COMMAND>LEVEL or COMMAND<LEVEL: the value crosses LEVEL")
    p.add_argument("--csv", metavar="FILE", help="write the samples as CSV (- for standard "
                   "output); --csv or --plot is needed")
    p.add_argument("--plot", metavar="FILE", action="append", default=[],
                   help="FILE.png or .svg (matplotlib) or .html; may be given more than once")
    p.add_argument("--timeout", type=positive_seconds, default=10.0, metavar="SECONDS",
                   help="bound for connecting and for each reply (default 10)")
    p.add_argument("--max-samples", type=int, default=None, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    refused = check_outputs(args)  # before anything is sent (record_output's docstring)
    try:
        if refused is not None:
            raise ValueError(refused)
        specs = [command_of(t) for t in (args.commands or DEFAULT_COMMANDS)]
        trigger = parse_trigger(args.trigger, specs)
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    channels = [channel_of(s) for s in specs]
    limits = {"max_samples": args.max_samples} if args.max_samples else {}
    recorder = Recorder(trigger, args.duration, args.pre, **limits)
    try:
        session = Session.open(args.address, args.axis, specs, args.timeout)
    except OSError as exc:
        print(f"{PROG}: {args.address}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    try:
        progress = Progress(sys.stderr, trigger.describe(channels), args.duration)
        outcome = record(session, recorder, Schedule(args.period), progress)
        progress.end()
    finally:
        session.close()
    title = f"axis {args.axis} through the bridge at {args.address}: " + ", ".join(
        ch.name for ch in channels)
    written = write_outputs(args, channels, outcome.recorder.rows(), title,
                            triggered=outcome.recorder.trigger_time is not None)
    print(summary(outcome, channels, written.paths),
          file=sys.stderr if args.csv == "-" else sys.stdout)
    if written.failed:
        print(written.failure_line(PROG), file=sys.stderr)
    error = outcome.error
    if error is not None:
        if isinstance(error, OSError):
            print(f"{PROG}: {args.address}: {error.strerror or error}", file=sys.stderr)
        else:
            print(f"{PROG}: {error}", file=sys.stderr)
        refused_read = isinstance(error, RefusedRead) and error.reply.status is Status.NAK
        return 1 if refused_read and not written.failed else 2
    if written.failed:
        return 2
    return 130 if outcome.interrupted else 0


__all__ = ["DEFAULT_COMMANDS", "RefusedRead", "Session", "add_arguments", "channel_of",
           "command_of", "parse_trigger", "record", "run", "value_of"]
