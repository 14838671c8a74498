"""``epos-link record``: sample objects of one node over time, to CSV and a plot.

::

    epos-link record URL --node N OBJECT... [--period S] [--duration S] [--pre S]
                     [--trigger now|move|OBJECT>LEVEL|OBJECT<LEVEL] [--csv FILE] [--plot FILE]...

An OBJECT is named as ``epos-link read`` names it: by name (``"Position actual
value"``, ``position_actual_value``, ``RECORD.SUB``) or index, ``0x6064`` or with
its subindex ``0x1018/4``. The pure parts (schedule, triggers, ring buffer, CSV)
are :mod:`epos_link.tools.recording`; the plots :mod:`epos_link.tools.plot`.

Traffic (what ``--trace`` shows, what the tests count): before sampling, when a
velocity object is recorded, one ReadObject of 60A9h "SI unit velocity" for the
column's unit. Then per sample, one ReadObject per object (objects of more than
4 bytes: one segmented read), back to back in the order named: N objects = N
transfers, nothing else. An object the trigger names that is not among the
OBJECTs, or the statusword for ``--trigger move``, is added as a last column
(and so read every sample). ``--on-drive`` leaves the sampling to the EPOS4's own
data recorder (31E0h-31E9h) and reads its buffers back afterwards: up to 4
objects, 500 samples, 0.4 ms at the fastest (:mod:`epos_link.tools.record_on_drive`).

Time: each row's time is the host's monotonic clock at the middle of that row's
reads (from the start of the first request to the end of the last answer),
minus the trigger row's; the link's latency is therefore in every row alike.
With ``--period`` the rows are due on a fixed grid; a row the link cannot
take in time skips its slot (counted in the summary), it is never sent in a
burst to catch up.

Progress goes to standard error (a line per phase; on a terminal one line kept
up to date); the summary to standard output. Ctrl-C writes what was recorded
and exits 130. The outputs (at least one of ``--csv`` and ``--plot``) are
checked before anything is sent and written after, each on its own
(:mod:`epos_link.tools.record_output`).
"""
from __future__ import annotations

import argparse
import re
import sys
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, TextIO

from ..client import EposClient
from ..errors import DeviceError, EposError, LocalProtocolError
from .access import Target, _node, read_value
from .common import (add_link_options, add_url, guarded, non_negative_int, open_client,
                     parse_float, parse_int, report)
from .objects import TYPES, ObjectDirectory, load_directory
from .recording import (SI_UNIT_VELOCITY, STATUSWORD, VELOCITY_OBJECTS, Channel, Crossing,
                        Immediate, MoveStart, Phase, Recorder, Sample, Schedule, Trigger,
                        column_name, median_interval, unit_of, velocity_unit)
from .record_on_drive import add_arguments as add_on_drive
from .record_on_drive import plan, record_on_drive
from .record_on_drive import summary as drive_summary
from .record_output import PROG, check_outputs, write_outputs

PROGRESS_EVERY = 0.25  # seconds between updates of a terminal's progress line


def _seconds(text: str) -> float:
    value = parse_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError("must be 0 or more seconds")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("--node", type=_node, required=True, metavar="N",
                        help="CANopen node id: 0 = the connected EPOS4, 1..127 = via its gateway")
    parser.add_argument("objects", metavar="OBJECT", nargs="+",
                        help='object name or index: "Position actual value", statusword, 0x606C, 0x1018/4')
    parser.add_argument("--period", type=_seconds, default=0.0, metavar="S",
                        help="sample period in seconds (default 0: as fast as the link allows)")
    parser.add_argument("--duration", type=_seconds, default=5.0, metavar="S",
                        help="seconds recorded after the trigger (default 5)")
    parser.add_argument("--pre", type=_seconds, default=0.0, metavar="S",
                        help="seconds kept before the trigger (default 0)")
    parser.add_argument("--trigger", default="now", metavar="WHEN",
                        help="now (default); move: the statusword shows a move starting; "
                        "OBJECT>LEVEL or OBJECT<LEVEL: the value crosses LEVEL upwards or downwards")
    parser.add_argument("--csv", metavar="FILE", help="write the samples as CSV (- for standard output); "
                        "--csv or --plot is needed, and every FILE is checked before anything is sent")
    parser.add_argument("--plot", metavar="FILE", action="append", default=[],
                        help="draw the recording: FILE.png or .svg (matplotlib) or .html (self-contained); "
                        "may be given more than once")
    parser.add_argument("--eds", metavar="FILE",
                        help="object dictionary (EDS or DCF) for names and types (default: the shipped EPOS4 EDS)")
    parser.add_argument("--max-samples", type=non_negative_int, default=None, metavar="N",
                        help=argparse.SUPPRESS)
    add_on_drive(parser)
    add_link_options(parser)


# --- objects and the trigger ----------------------------------------------------------


def resolve(directory: ObjectDirectory, node: int, text: str) -> Target:
    """OBJECT as ``read`` takes it: a name, INDEX or INDEX/SUB (:meth:`ObjectDirectory.locate`)."""
    index, sub, info = directory.locate(text)
    if info is None or info.type is None:
        raise LocalProtocolError(f"0x{index:04X}/0x{sub:02X} is not in the object dictionary "
                                 f"({directory.source}): record needs its type (--eds FILE)")
    if info.type.kind not in ("int", "float", "bool"):
        raise LocalProtocolError(f"{info.name} is a {info.type.name}: record samples numbers only")
    return Target(node, index, sub, info, info.type)


def parse_trigger(text: str, targets: list[Target], directory: ObjectDirectory,
                  node: int) -> Trigger:
    """The trigger; an object it names that is not recorded is appended to ``targets``."""
    def column(target: Target) -> int:
        for k, t in enumerate(targets):
            if (t.index, t.subindex) == (target.index, target.subindex):
                return k
        targets.append(target)
        return len(targets) - 1

    word = text.strip()
    if word == "now":
        return Immediate()
    if word == "move":
        return MoveStart(column(resolve(directory, node, f"0x{STATUSWORD[0]:04X}")))
    m = re.fullmatch(r"(.+?)\s*([<>])\s*(\S+)", word)
    if not m:
        raise LocalProtocolError(f"--trigger {text!r}: now, move, OBJECT>LEVEL or OBJECT<LEVEL")
    try:
        level = float(parse_int(m.group(3))) if re.fullmatch(r"-?0[xX][0-9a-fA-F]+", m.group(3)) \
            else parse_float(m.group(3))
    except argparse.ArgumentTypeError as exc:
        raise LocalProtocolError(f"--trigger {text!r}: {exc}") from None
    return Crossing(column(resolve(directory, node, m.group(1))), level, m.group(2) == ">")


def channels_of(client: EposClient, targets: Sequence[Target]) -> list[Channel]:
    """The columns; one read of 60A9h when a velocity object is recorded (its unit)."""
    velocity = ""
    if any(t.index in VELOCITY_OBJECTS for t in targets):
        node = targets[0].node
        try:
            si_unit = TYPES["u32"].decode(client.read_object(node, SI_UNIT_VELOCITY, 0))
            velocity = velocity_unit(si_unit) if isinstance(si_unit, int) else ""
        except DeviceError:
            velocity = ""  # no 60A9h: the column says no unit rather than a guess
    return [Channel(t.index, t.subindex, column_name(t.name, t.index, t.subindex),
                    unit_of(t.index, velocity)) for t in targets]


# --- the sampling loop ----------------------------------------------------------------


@dataclass
class Outcome:
    recorder: Recorder
    schedule: Schedule
    interrupted: bool = False
    error: Optional[Exception] = None  # the link failed part-way: what came before is kept


def sample_loop(read_row: Callable[[], tuple], recorder: Recorder, schedule: Schedule,
                clock: Callable[[], float] = time.monotonic,
                sleep: Callable[[float], None] = time.sleep,
                progress: Optional[Callable[[Recorder, float], None]] = None,
                errors: tuple[type[Exception], ...] = (EposError,)) -> Outcome:
    """Sample until the recorder is done; Ctrl-C ends it with what was recorded, and so
    does one of ``errors`` (the link's: EposError here, the bridge's in
    :mod:`tcp_bridge.record`), kept in the outcome."""
    outcome = Outcome(recorder, schedule)
    try:
        while recorder.phase is not Phase.DONE:
            due = schedule.due(clock())
            wait = due - clock()
            if wait > 0:
                sleep(wait)
            start = clock()
            values = read_row()
            end = clock()
            schedule.taken(max(due, start) if schedule.period else start, end)
            recorder.add(Sample((start + end) / 2, values))
            if progress is not None:
                progress(recorder, end)
    except KeyboardInterrupt:
        outcome.interrupted = True
    except errors as exc:
        outcome.error = exc
    return outcome


class Progress:
    """Progress on standard error: one line per phase, or one live line on a terminal."""

    def __init__(self, out: TextIO, what: str, duration: float) -> None:
        self.out = out
        self.live = out.isatty()
        self.what = what
        self.duration = duration
        self._shown: Optional[Phase] = None
        self._last = float("-inf")
        self._start: Optional[float] = None

    def __call__(self, recorder: Recorder, now: float) -> None:
        if self._start is None:
            self._start = now
        phase = recorder.phase
        if self.live:
            if now - self._last < PROGRESS_EVERY and phase is self._shown:
                return
            self._last, self._shown = now, phase
            if phase is Phase.WAITING:
                text = f"waiting for the trigger: {self.what}, {now - self._start:.1f} s"
            else:
                done = now - (recorder.trigger_time or now)
                text = f"recording: {min(done, self.duration):.1f} of {self.duration:g} s, {len(recorder.after)} samples"
            self.out.write(f"\r{text}\x1b[K")
        elif phase is not self._shown and phase is not Phase.DONE:
            self._shown = phase
            if phase is Phase.WAITING:
                self.out.write(f"waiting for the trigger: {self.what}...\n")
            else:
                self.out.write(f"triggered; recording {self.duration:g} s\n")
        self.out.flush()

    def end(self) -> None:
        if self.live and self._shown is not None:
            self.out.write("\r\x1b[K")
            self.out.flush()


# --- the command ----------------------------------------------------------------------


def summary(outcome: Outcome, channels: list[Channel], written: list[str]) -> str:
    """The one summary line (shared with ``tcp-bridge record``)."""
    rec = outcome.recorder
    times = [s.time for s in rec.samples]
    gap = median_interval(times)
    parts = [f"recorded {len(times)} samples ({len(rec.before)} before the trigger) of "
             f"{len(channels)} object{'s' if len(channels) != 1 else ''}"]
    if gap is not None:
        parts.append(f"median interval {gap * 1000:.1f} ms")
    if outcome.schedule.period:
        parts.append(f"{outcome.schedule.missed} slot{'s' if outcome.schedule.missed != 1 else ''} missed")
    if rec.trigger_time is None:
        parts.append("not triggered")
    if rec.truncated:
        parts.append("stopped at the sample limit")
    if outcome.interrupted:
        parts.append("interrupted")
    if outcome.error is not None:
        parts.append("stopped by an error")
    line = ", ".join(parts)
    return line + (f"; wrote {', '.join(written)}" if written else "")


# SDO aborts that a node's answers going to another client cause (CiA 301 Table 22): the
# gateway waits for an answer another client took (timed out), or gets one meant for
# another client's transfer (command specifier, toggle bit, sequence number).
SDO_CHANNEL_ABORTS = {0x05040000: "SDO protocol timed out", 0x05040001: "command specifier",
                      0x05030000: "toggle bit not alternated", 0x05040003: "sequence number"}


def channel_taken(error: EposError, node: int, samples: int) -> Optional[str]:
    """Why reads of a node that answered before now fail with an SDO protocol abort, or
    None. CiA 301 7.2.4: one client per SDO channel; the EPOS4's gateway is a client of
    the node's default channel (600h/580h + node id), so any other client of that node
    on the same CAN bus (a bridge, a canopen script, another master) takes its answers
    (issue 34: record stopped after 10 samples with a bare "SDO protocol timed out")."""
    code = getattr(error, "code", None)
    if node == 0 or samples == 0 or code not in SDO_CHANNEL_ABORTS:
        return None
    return (f"node {node} answered {samples} samples, then its SDO transfer failed "
            f"(0x{code:08X}): another SDO client of node {node} on that CAN bus, such as a "
            f"tcp-bridge or a canopen script, probably uses its default SDO channel "
            f"(0x{0x600 + node:03X}/0x{0x580 + node:03X}, CiA 301 7.2.4: one client per "
            "channel) and takes the answers. Record through that program instead "
            "(tcp-bridge record HOST:PORT AXIS for a bridge's axis), or stop its SDO traffic "
            "to the node (docs/epos-link.md, \"Recording a move\")")


def run(args: argparse.Namespace) -> int:
    refused = check_outputs(args)  # before anything is sent (record_output's docstring)
    if refused is not None:
        print(f"{PROG}: {refused}", file=sys.stderr)
        return 2

    def body() -> int:
        directory = load_directory(args.eds, max(args.node, 1))
        targets = [resolve(directory, args.node, text) for text in args.objects]
        named = list(targets)
        trigger = parse_trigger(args.trigger, targets, directory, args.node)
        if args.on_drive:
            return _on_drive(args, named, trigger, targets)
        limits = {"max_samples": args.max_samples} if args.max_samples else {}
        recorder = Recorder(trigger, args.duration, args.pre, **limits)
        with open_client(args) as client:
            channels = channels_of(client, targets)

            def read_row() -> tuple:
                return tuple(t.type.decode(read_value(client, t)) for t in targets)

            progress = Progress(sys.stderr, trigger.describe(channels), args.duration)
            outcome = sample_loop(read_row, recorder, Schedule(args.period), progress=progress)
            progress.end()
        title = f"node {args.node}: " + ", ".join(ch.name for ch in channels)
        written = write_outputs(args, channels, outcome.recorder.rows(), title,
                                triggered=outcome.recorder.trigger_time is not None)
        print(summary(outcome, channels, written.paths),
              file=sys.stderr if args.csv == "-" else sys.stdout)
        if written.failed:
            print(written.failure_line(), file=sys.stderr)
        if outcome.error is not None:
            assert isinstance(outcome.error, EposError)
            code = report(PROG, outcome.error)  # after the files are written: what stopped it
            hint = channel_taken(outcome.error, args.node, len(outcome.recorder.samples))
            if hint is not None:
                print(f"{PROG}: {hint}", file=sys.stderr)
            return 2 if written.failed else code
        if written.failed:
            return 2
        return 130 if outcome.interrupted else 0

    return guarded(PROG, body)


def _on_drive(args: argparse.Namespace, targets: list[Target], trigger: Trigger,
              trigger_targets: list[Target]) -> int:
    """``--on-drive``: the EPOS4's own recorder records (:mod:`.record_on_drive`)."""
    config = plan(targets, trigger, trigger_targets, args.period, args.duration, args.pre)
    with open_client(args) as client:
        channels = channels_of(client, targets)
        recording = record_on_drive(client, args.node, targets, config,
                                    say=lambda text: print(text, file=sys.stderr, flush=True))
    title = f"node {args.node} (the drive's recorder): " + ", ".join(ch.name for ch in channels)
    written = write_outputs(args, channels, recording.rows(), title)
    print(drive_summary(recording, channels, written.paths),
          file=sys.stderr if args.csv == "-" else sys.stdout)
    if written.failed:
        print(written.failure_line(), file=sys.stderr)
        return 2
    return 130 if recording.interrupted else 0


__all__ = ["Outcome", "Progress", "SDO_CHANNEL_ABORTS", "add_arguments", "channel_taken",
           "channels_of", "parse_trigger", "resolve", "run", "sample_loop", "summary"]
