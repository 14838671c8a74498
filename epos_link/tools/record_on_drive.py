"""``epos-link record --on-drive``: the recording is made by the EPOS4's own data recorder.

The drive samples in its control cycle, every ``--period`` (10 us steps, 0.4 ms at
the fastest), where the serial link manages about 2 ms per object; the host only
configures the recorder, arms it, waits, and reads the buffers back. The facts of
the recorder (objects 31E0h-31E9h, from maxon's XDD files, and what is not in
them) are :mod:`epos_link.data_recorder`.

Steps, all through the same link and gateway as every other command (node 0: the
EPOS4 itself; 1..127: a node behind its gateway; the buffers are segmented reads,
which the gateway forwards as SDO uploads):

1. stop the recorder (31E4h:01 = 0), so its configuration may change;
2. the variables: each OBJECT as ``(index << 16) | (subindex << 8)`` in
   31E0h:01..04 (at most 4), the others 0;
3. the period (31E1h:01, in 10 us) and the number of samples (31E1h:02):
   ``--pre`` and ``--duration`` at that period, the trigger sample included,
   at most 500; the preceding samples (31E2h:06);
4. the trigger (31E2h:01..05), from ``--trigger`` as ``record`` takes it:

   ==================  ============================================================
   ``now``             start with the trigger forced (31E4h:01 = 3)
   ``OBJECT>LEVEL``    mode 3 "rising over value", high = ceil(LEVEL) - 1: the first
                       sample at or above LEVEL after one below it, as ``record``'s
                       crossing (integers: v >= L  <=>  v > ceil(L) - 1)
   ``OBJECT<LEVEL``    mode 4 "falling under value", high = floor(LEVEL) + 1
   ``move``            mode 9 "rising edge" of the statusword (6041h) masked to bit
                       12, high 1000h, low 0: the set-point acknowledge rises
                       (profile position, CiA 402-2 6.6.1.2). **Chosen**: the drive
                       has one trigger; ``record``'s other sign of a move (bit 10
                       falling) is not watched.
   ==================  ============================================================

5. start (31E4h:01 = 1, or 3 for ``now``), then read the recorder's statusword
   (31E4h:02) every :data:`POLL` seconds: bit 1 "triggered", bit 0 "running";
   waiting for the trigger has no time limit (Ctrl-C), recording after it at most
   ten times its length plus :data:`SLACK` (then: one line, exit 2);
6. read the number of samples (31E5h:01) and each channel's buffer (31E6h..:01),
   int32 samples, oldest first, the trigger sample at index "preceding" (the
   choices of epos_link.data_recorder); each sample is shown with its object's
   type (a u16 statusword as 0..65535);
7. write the CSV and plots exactly as ``record`` does
   (:mod:`epos_link.tools.record_output`): time from the trigger, negative before.

Ctrl-C stops the recorder (31E4h:01 = 0) and writes what it holds. Any link or
device error is reported as for ``record``.
"""
from __future__ import annotations

import argparse
import math
import struct
import sys
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

from .. import data_recorder as facts
from ..client import EposClient
from ..data_recorder import Control, RecorderStatus, TriggerMode
from ..errors import LocalProtocolError
from .access import Target
from .recording import STATUSWORD, Channel, Crossing, Immediate, MoveStart, Trigger, Value

POLL = 0.05  # seconds between reads of the recorder's statusword
SLACK = 5.0  # seconds beyond ten times the recording's length before giving up
SET_POINT_ACKNOWLEDGE = 1 << 12


@dataclass(frozen=True)
class Plan:
    """What is written to the recorder (steps 2-5 of the module docstring)."""

    variables: tuple[int, ...]  # 31E0h:01..04
    period: int  # 31E1h:01, 10 us
    samples: int  # 31E1h:02
    preceding: int  # 31E2h:06
    trigger_variable: int  # 31E2h:01
    mode: TriggerMode
    high: int  # u32 patterns, as 31E2h:03/04 hold them
    low: int
    mask: int
    control: Control

    @property
    def period_seconds(self) -> float:
        return self.period * facts.PERIOD_UNIT

    def writes(self) -> list[tuple[int, int, int, int]]:
        """(index, subindex, value, size in bytes), in the order they are written."""
        out: list[tuple[int, int, int, int]] = [(facts.CONTROL, facts.CONTROLWORD_SUB,
                                                 int(Control.STOP), 2)]
        out += [(facts.VARIABLE_INDEX, k + 1, v, 4) for k, v in enumerate(self.variables)]
        out += [(facts.CONFIGURATION, facts.PERIOD_SUB, self.period, 2),
                (facts.CONFIGURATION, facts.MAX_SAMPLES_SUB, self.samples, 2),
                (facts.TRIGGER, facts.TRIGGER_VARIABLE, self.trigger_variable, 4),
                (facts.TRIGGER, facts.TRIGGER_MODE, int(self.mode), 1),
                (facts.TRIGGER, facts.TRIGGER_HIGH, self.high, 4),
                (facts.TRIGGER, facts.TRIGGER_LOW, self.low, 4),
                (facts.TRIGGER, facts.TRIGGER_MASK, self.mask, 4),
                (facts.TRIGGER, facts.PRECEDING, self.preceding, 2)]
        return out


def _numeric_32(target: Target) -> None:
    if target.type.kind not in ("int", "bool") or (target.type.size or 8) > 4:
        raise LocalProtocolError(f"{target.name or hex(target.index)} is a {target.type.name}: "
                                 "the drive's recorder takes integer objects of up to 32 bits")


def plan(targets: Sequence[Target], trigger: Trigger, trigger_targets: Sequence[Target],
         period: float, duration: float, pre: float) -> Plan:
    """The recorder's configuration; LocalProtocolError (one line) when it cannot hold it.

    ``trigger_targets``: every target the trigger's columns index (``targets`` plus any
    the trigger added), as :func:`epos_link.tools.record.parse_trigger` built them."""
    if len(targets) > facts.CHANNELS:
        raise LocalProtocolError(f"--on-drive records at most {facts.CHANNELS} objects "
                                 f"(31E0h:01..04), got {len(targets)}")
    for target in targets:
        _numeric_32(target)
    if period == 0:  # the shortest period that holds --pre and --duration
        span = pre + duration
        period = max(facts.PERIOD_MIN, math.ceil(span / (facts.MAX_SAMPLES - 1) / facts.PERIOD_UNIT
                                                 - 1e-9)) * facts.PERIOD_UNIT
    try:
        units = facts.period_units(period)
    except ValueError as exc:
        raise LocalProtocolError(f"--period with --on-drive: {exc}") from None
    step = units * facts.PERIOD_UNIT
    preceding = round(pre / step)
    after = math.floor(duration / step + 1e-9) + 1  # the trigger sample, then to --duration
    total = preceding + after
    if preceding > facts.PRECEDING_MAX or total > facts.MAX_SAMPLES:
        raise LocalProtocolError(
            f"--on-drive keeps at most {facts.MAX_SAMPLES} samples per object: --pre {pre:g} "
            f"--duration {duration:g} at --period {step:g} needs {total}; give a longer "
            "--period or a shorter --duration")
    variables = [facts.encode_variable(t.index, t.subindex) for t in targets]
    variables += [0] * (facts.CHANNELS - len(variables))
    mode, high, low, mask, control = TriggerMode.IS_VALUE, 0, 0, 0xFFFFFFFF, Control.START
    trigger_variable = 0
    if isinstance(trigger, Immediate):
        control = Control.START_FORCED
        trigger_variable = variables[0]
    elif isinstance(trigger, MoveStart):
        trigger_variable = facts.encode_variable(*STATUSWORD)
        mode, high, low, mask = (TriggerMode.RISING_EDGE, SET_POINT_ACKNOWLEDGE, 0,
                                 SET_POINT_ACKNOWLEDGE)
    elif isinstance(trigger, Crossing):
        watched = trigger_targets[trigger.column]
        _numeric_32(watched)
        trigger_variable = facts.encode_variable(watched.index, watched.subindex)
        try:
            if trigger.rising:
                mode, high = TriggerMode.RISING_OVER_VALUE, facts.unsigned32(
                    math.ceil(trigger.level) - 1)
            else:
                mode, high = TriggerMode.FALLING_UNDER_VALUE, facts.unsigned32(
                    math.floor(trigger.level) + 1)
        except ValueError as exc:
            raise LocalProtocolError(f"--trigger level: {exc}") from None
    return Plan(tuple(variables), units, total, preceding, trigger_variable, mode, high, low,
                mask, control)


def _write(client: EposClient, node: int, index: int, sub: int, value: int, size: int) -> None:
    fmt = {1: "<B", 2: "<H", 4: "<I"}[size]
    client.write_object(node, index, sub, struct.pack(fmt, value))


def _read_u16(client: EposClient, node: int, index: int, sub: int) -> int:
    return int(struct.unpack_from("<H", client.read_object(node, index, sub))[0])


@dataclass
class DriveRecording:
    samples: list[tuple[Value, ...]]
    preceding: int
    period: float
    triggered: bool
    interrupted: bool = False

    def rows(self) -> list[tuple[float, tuple[Value, ...]]]:
        origin = self.preceding if self.triggered else len(self.samples) - 1
        return [((k - origin) * self.period, row) for k, row in enumerate(self.samples)]


def record_on_drive(client: EposClient, node: int, targets: Sequence[Target], config: Plan,
                    say: Callable[[str], None] = lambda text: None,
                    clock: Callable[[], float] = time.monotonic,
                    sleep: Callable[[float], None] = time.sleep) -> DriveRecording:
    """Steps 1-6 of the module docstring; Ctrl-C stops the recorder and reads what it has."""
    for index, sub, value, size in config.writes():
        _write(client, node, index, sub, value, size)
    _write(client, node, facts.CONTROL, facts.CONTROLWORD_SUB, config.control, 2)
    say("waiting for the trigger (in the drive)...")
    interrupted = False
    status = RecorderStatus(0)
    limit: Optional[float] = None
    try:
        while True:
            status = RecorderStatus(_read_u16(client, node, facts.CONTROL, facts.STATUSWORD_SUB))
            if status & RecorderStatus.TRIGGERED and limit is None:
                say(f"triggered; the drive records {config.samples} samples every "
                    f"{config.period_seconds * 1000:g} ms")
                limit = clock() + 10 * config.samples * config.period_seconds + SLACK
            if not status & RecorderStatus.RUNNING:
                break
            if limit is not None and clock() > limit:
                raise LocalProtocolError(
                    f"the drive's recorder of node {node} still runs "
                    f"{10 * config.samples * config.period_seconds + SLACK:g} s after its trigger "
                    f"(31E4h:02 = 0x{int(status):04X})")
            sleep(POLL)
    except KeyboardInterrupt:
        interrupted = True
        _write(client, node, facts.CONTROL, facts.CONTROLWORD_SUB, Control.STOP, 2)
        status = RecorderStatus(_read_u16(client, node, facts.CONTROL, facts.STATUSWORD_SUB))
    count = _read_u16(client, node, facts.DATA, facts.RECORDED_SUB)
    columns = []
    for k, target in enumerate(targets):
        raw = facts.decode_buffer(client.upload(node, facts.BUFFERS[k], facts.COMPLETE_SUB))
        columns.append([_typed(target, v) for v in raw[:count]])
    samples = [tuple(c[i] for c in columns) for i in range(min((len(c) for c in columns),
                                                                default=0))]
    return DriveRecording(samples, config.preceding, config.period_seconds,
                          bool(status & RecorderStatus.TRIGGERED), interrupted)


def _typed(target: Target, sample: int) -> Value:
    """A signed 32-bit sample as its object's type reads it (a u16 as 0..65535)."""
    size = target.type.size or 4
    if target.type.kind == "bool":
        return bool(sample)
    if target.type.signed:
        return facts.signed32(sample)
    return sample & ((1 << (8 * size)) - 1)


def summary(recording: DriveRecording, channels: Sequence[Channel], written: list[str]) -> str:
    n = len(recording.samples)
    before = min(recording.preceding, n) if recording.triggered else n
    parts = [f"recorded {n} samples ({before} before the trigger) of {len(channels)} "
             f"object{'s' if len(channels) != 1 else ''} in the drive, every "
             f"{recording.period * 1000:g} ms"]
    if not recording.triggered:
        parts.append("not triggered")
    if recording.interrupted:
        parts.append("interrupted")
    line = ", ".join(parts)
    return line + (f"; wrote {', '.join(written)}" if written else "")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--on-drive", action="store_true",
                        help="record with the EPOS4's own data recorder (31E0h-31E9h): up to 4 "
                             "objects, 500 samples, --period in 10 us steps from 0.4 ms")


__all__ = ["DriveRecording", "Plan", "add_arguments", "plan", "record_on_drive", "summary"]
