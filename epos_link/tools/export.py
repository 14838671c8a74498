"""``epos-link export CAPTURE -o FILE.pcapng``: a capture for Wireshark.

Each frame becomes one packet with the bytes as on the wire (bytes that are not
a frame become packets too, so nothing is lost); the direction is in the packet
flags (TX outbound, RX inbound). The interface description carries the URL
and baud rate: ``--url`` and ``--baud``, else what the capture's comments say
(``# url: ...``, ``# baud: ...``, ``# source: epos-link trace of URL, ...``).
Times are the capture's, from ``# start: UNIXTIME`` (written by ``monitor
--record``) or else from the file's modification time less the last record's.
Open the result with the dissector of ``epos-link wireshark path``.
"""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
from typing import Optional

from ..capture import Capture, CaptureFormatError, Direction, read_capture
from .common import baud_rate, parse_float
from .frames import FrameEvent, LinkDecoder
from .pcapng import PcapngWriter

DEFAULT_BAUD = 115200  # guide 2.2.6: the RS232 default
# pcapng (IETF draft-ietf-opsawg-pcapng, 4.3): a timestamp is 64 bits of units since
# 1970; our writer's unit is the nanosecond (if_tsresol 9).
PCAPNG_TIME_LIMIT_NS = 2 ** 64


def capture_field(capture: Capture, key: str) -> Optional[str]:
    """The value of a ``# key: value`` comment, if the capture has one."""
    prefix = key + ":"
    for text in capture.comments:
        if text.lower().startswith(prefix):
            return text[len(prefix):].strip()
    return None


def capture_url(capture: Capture) -> Optional[str]:
    url = capture_field(capture, "url")
    if url:
        return url
    for text in capture.comments:
        m = re.match(r"source: epos-link (?:trace|monitor) of (\S+?),?(\s|$)", text)
        if m:
            return m.group(1)
    return None


def interface_description(url: Optional[str], baud: Optional[int]) -> str:
    return f"MAXON SERIAL V2 {url or 'unknown link'}" + (f" at {baud} baud" if baud else "")


def write_event(writer: PcapngWriter, event: FrameEvent, start_wall: float) -> None:
    """One packet for one frame (or run of non-frame bytes)."""
    if not event.raw:
        return
    outbound = None if event.direction is None else event.direction == Direction.TX.value
    # Two roundings, not one: a double holds Unix time in ns only to ~256 ns.
    time_ns = int(round(start_wall * 1e9)) + int(round(event.time * 1e9))
    writer.packet(time_ns, event.raw, outbound=outbound,
                  comment="" if event.is_frame else f"not a frame: {event.decoded.problem}")


def export(capture: Capture, out: "object", *, url: Optional[str], baud: Optional[int],
           start_wall: float) -> int:
    """Write the capture's frames to the binary stream ``out``; returns the packet count."""
    writer = PcapngWriter(out, if_name=url or "maxon", if_description=interface_description(url, baud),  # type: ignore[arg-type]
                          speed=baud)
    decoder = LinkDecoder()
    count = 0
    last = 0.0
    for record in capture.records:
        last = record.time
        for event in decoder.feed(record.time, record.direction, record.data):
            write_event(writer, event, start_wall)
            count += 1
    for event in decoder.close(last):
        write_event(writer, event, start_wall)
        count += 1
    return count


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="CAPTURE", help="a capture file (epos-link capture format)")
    parser.add_argument("-o", "--output", required=True, metavar="FILE.pcapng",
                        help="the pcapng file to write, - for standard output")
    parser.add_argument("--url", help="the link's URL for the interface description")
    parser.add_argument("--baud", type=baud_rate, help="the link's baud rate (default: the capture's, "
                        f"else {DEFAULT_BAUD} for serial ports)")
    parser.add_argument("--start", type=parse_float, metavar="UNIXTIME",
                        help="Unix time of the capture's time 0")


def run(args: argparse.Namespace) -> int:
    prog = "epos-link export"
    try:
        with open(args.capture, encoding="utf-8") as fh:
            capture = read_capture(fh)
        mtime = os.path.getmtime(args.capture)
    except UnicodeDecodeError:
        print(f"{prog}: {args.capture} is not a capture file (hex text, see epos_link/capture.py)",
              file=sys.stderr)
        return 2
    except (OSError, CaptureFormatError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if not capture.records:
        print(f"{prog}: {args.capture} holds no records", file=sys.stderr)
        return 2
    url = args.url or capture_url(capture)
    baud = args.baud
    if baud is None:
        text = capture_field(capture, "baud")
        baud = int(text) if text and text.isdigit() else None
    if baud is None and url and "://" not in url:
        baud = DEFAULT_BAUD  # a serial device path: the guide's default rate
    span = PCAPNG_TIME_LIMIT_NS / 1e9  # seconds, about 584 years
    far = next((r.time for r in capture.records if not abs(r.time) < span), None)
    if far is not None:
        print(f"{prog}: {args.capture}: a record at {far:g} s is farther from the capture's "
              f"start than a pcapng timestamp reaches (2**64 ns, 584 years)", file=sys.stderr)
        return 2
    start = args.start
    if start is None:
        text = capture_field(capture, "start")
        try:
            start = float(text.split()[0]) if text else math.nan
        except ValueError:
            start = math.nan
        if not math.isfinite(start):  # none, garbage, "nan" or "inf": the file's own time
            start = mtime - capture.records[-1].time
    latest = start + max(record.time for record in capture.records)
    if not latest * 1e9 < PCAPNG_TIME_LIMIT_NS:
        print(f"{prog}: {args.capture}: a record at Unix time {latest:g} is past what a pcapng "
              f"timestamp holds (2**64 ns, the year 2554); --start sets the time of 0",
              file=sys.stderr)
        return 2
    try:
        if args.output == "-":
            count = export(capture, sys.stdout.buffer, url=url, baud=baud, start_wall=start)
        else:
            with open(args.output, "wb") as out:
                count = export(capture, out, url=url, baud=baud, start_wall=start)
    except OSError as exc:
        print(f"{prog}: cannot write {args.output}: {exc}", file=sys.stderr)
        return 2
    if args.output != "-":
        print(f"wrote {count} packets to {args.output}", file=sys.stderr)
    return 0


__all__ = ["add_arguments", "capture_field", "capture_url", "export", "run", "write_event"]
