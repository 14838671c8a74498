"""``epos-link monitor DEVICE_URL (--pty | --tcp HOST:PORT)``: watch an application talk to an EPOS4.

::

    $ epos-link monitor /dev/ttyUSB0 --pty --record cap.txt
    listening on /dev/pts/7
    (000.000000) TX ReadObject             node 1 0x6064/0x00 Position actual value crc ok
    (000.000912) RX Answer                 node 1 0x6064/0x00 Position actual value = 1000 (0x000003E8) ok crc ok 0.912 ms

The application opens the printed path (or ``socket://HOST:PORT``) instead of
the device; :mod:`epos_link.tools.proxy` copies every byte both ways
unchanged, and this module shows one line per frame (:mod:`epos_link.tools.view`),
names and values from the object dictionary (``--eds``, default the shipped
EPOS4 EDS). Bytes that are not a frame are shown, never hidden.

Outputs: ``--record FILE`` writes the capture format that ``replay://`` and
``decode`` read; ``--pcapng FILE`` writes Wireshark's format, ``-`` to standard
output (then the lines go to standard error), so that
``epos-link monitor URL --tcp :0 --pcapng - | wireshark -k -i -`` works;
``--json`` prints one JSON object per frame instead of text. The
``listening on ...`` line goes to standard error, so it shows when standard
output is redirected.
Stop with Ctrl-C (or SIGTERM); exit 0, or 2 when the device link failed.
"""
from __future__ import annotations

import argparse
import errno
import json
import os
import queue
import signal
import sys
import threading
import time
from typing import IO, Any, BinaryIO, Optional

from ..capture import CaptureWriter
from ..errors import EposError
from .common import URL_HELP, baud_rate
from .export import interface_description, write_event
from .frames import FrameEvent, LinkDecoder
from .objects import load_directory
from .view import TIME_MODES, Clock, format_event, use_colour


def host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("url", metavar="DEVICE_URL", help="the device: " + URL_HELP)
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="offer a pseudo-terminal to the application")
    where.add_argument("--tcp", type=host_port, metavar="HOST:PORT",
                       help="listen on TCP (the application opens socket://HOST:PORT); port 0 picks one")
    parser.add_argument("--record", metavar="FILE", help="write a capture (replay://FILE, decode FILE)")
    parser.add_argument("--pcapng", metavar="FILE", help="write pcapng for Wireshark; - for standard output")
    parser.add_argument("--json", action="store_true", help="one JSON object per frame")
    parser.add_argument("-t", dest="time_mode", choices=TIME_MODES, default="z",
                        help="timestamps as candump: a absolute, A absolute with date, d delta, z zero-based (default)")
    parser.add_argument("-x", dest="hex", action="store_true", help="add the wire bytes in hex")
    parser.add_argument("--eds", metavar="FILE", help="object dictionary for names and types "
                        "(default: the shipped EPOS4 EDS)")
    parser.add_argument("--baud", type=baud_rate, default=None, help="the device's baud rate (serial ports)")


class Display:
    """Turns proxy items into lines, capture records and pcapng packets."""

    def __init__(self, args: argparse.Namespace, text_out: IO[str], start_wall: float,
                 record: Optional[CaptureWriter], pcap: Any) -> None:
        self.args = args
        self.out = text_out
        self.colour = use_colour(text_out)
        self.clock = Clock(args.time_mode, start_wall)
        self.start_wall = start_wall
        self.record = record
        self.pcap = pcap
        self.decoder = LinkDecoder(load_directory(args.eds))
        self.missed_reported = 0

    def _line(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()

    def event(self, event: FrameEvent) -> None:
        if self.pcap is not None:
            write_event(self.pcap, event, self.start_wall)
        if self.args.json:
            value = self.clock.value(event.time)
            self._line(json.dumps(event.as_json(value)))
        else:
            self._line(format_event(event, self.clock, colour=self.colour, hex_bytes=self.args.hex))

    def chunk(self, t: float, direction: str, data: bytes) -> None:
        if self.record is not None:
            self.record.write(t, direction, data)
        for event in self.decoder.feed(t, direction, data):
            self.event(event)

    def note(self, t: float, text: str) -> None:
        if self.record is not None:
            self.record.comment(f"{t:.6f} {text}")
        if self.args.json:
            self._line(json.dumps({"time": round(self.clock.value(t), 6), "note": text}))
        else:
            self._line(f"{self.clock.text(t)} -- {text}")

    def missed(self, t: float, total: int) -> None:
        if total > self.missed_reported:
            self.note(t, f"display fell behind: {total - self.missed_reported} bytes not shown "
                         "(they were forwarded)")
            self.missed_reported = total

    def close(self, t: float) -> None:
        for event in self.decoder.close(t):
            self.event(event)


def _open_outputs(args: argparse.Namespace, url: str, start_wall: float
                  ) -> tuple[Optional[IO[str]], Optional[CaptureWriter], Optional[BinaryIO], Any]:
    from .pcapng import PcapngWriter

    record_file = pcap_file = None
    record = pcap = None
    if args.record:
        record_file = open(args.record, "w", encoding="utf-8")
        record = CaptureWriter(record_file, comments=[
            f"source: epos-link monitor of {url}, TX host to device, RX device to host",
            f"url: {url}", *([f"baud: {args.baud}"] if args.baud else []),
            f"start: {start_wall:.6f} (Unix time of 0.000000)"])
    if args.pcapng:
        pcap_file = sys.stdout.buffer if args.pcapng == "-" else open(args.pcapng, "wb")
        pcap = PcapngWriter(pcap_file, if_name=url, if_description=interface_description(url, args.baud),
                            speed=args.baud)
    return record_file, record, pcap_file, pcap


def run(args: argparse.Namespace, ready: Optional[threading.Event] = None) -> int:
    from ..transports import open_transport
    from .proxy import Chunk, Note, Proxy, PtyFront, TcpFront

    prog = "epos-link monitor"
    text_out = sys.stderr if args.pcapng == "-" else sys.stdout
    try:
        load_directory(args.eds)
    except EposError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    try:
        device = open_transport(args.url, **({"baudrate": args.baud} if args.baud else {}))
    except (EposError, OSError) as exc:
        # The transports' messages already name the URL ("cannot open /dev/ttyUSB0: ..."):
        # say it once.
        text = str(exc) if args.url in str(exc) else f"cannot open {args.url}: {exc}"
        print(f"{prog}: {text}", file=sys.stderr)
        return 2
    try:
        front = TcpFront(*args.tcp) if args.tcp else PtyFront()
    except OSError as exc:
        device.close()
        # One line as `epos-link sim` says it, with the address once and what to do,
        # not Python's "[Errno 98] ... (while attempting to bind on address (...))".
        where = f"on {args.tcp[0]}:{args.tcp[1]}" if args.tcp else "on a pty"
        why = os.strerror(exc.errno) if exc.errno and exc.errno > 0 else str(exc)
        hint = ("; another program listens there: stop it, or choose another port "
                "(port 0 picks a free one)") if exc.errno == errno.EADDRINUSE else ""
        print(f"{prog}: cannot listen {where}: {why}{hint}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    start_wall = time.time()
    try:
        record_file, record, pcap_file, pcap = _open_outputs(args, args.url, start_wall)
    except OSError as exc:
        front.close()
        device.close()
        print(f"{prog}: cannot write: {exc}", file=sys.stderr)
        return 2
    display = Display(args, text_out, start_wall, record, pcap)
    proxy = Proxy(front, device, clock=lambda: time.monotonic() - t0)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        signal.signal(signal.SIGINT, lambda *_: stop.set())
    proxy.start()
    # Standard error: the user needs this line when standard output is a file, a pipe
    # or /dev/null (``monitor ... --record cap.txt > /dev/null &``), and --json output
    # stays one JSON object per line.
    print(f"listening on {front.where}", file=sys.stderr, flush=True)
    if ready is not None:
        ready.set()
    def handle(item: object) -> None:
        if isinstance(item, Chunk):
            display.chunk(item.time, item.direction, item.data)
        elif isinstance(item, Note):
            display.note(item.time, item.text)
        display.missed(time.monotonic() - t0, proxy.missed_bytes)

    try:
        while not stop.is_set() and not proxy.stopped:
            try:
                item = proxy.items.get(timeout=0.2)
            except queue.Empty:
                continue
            handle(item)
    except BrokenPipeError:
        pass  # the reader of standard output went away (head, a closed Wireshark)
    finally:
        proxy.stop()
        front.close()
        device.close()
        try:
            while not proxy.items.empty():
                handle(proxy.items.get_nowait())
            display.close(time.monotonic() - t0)
        except (BrokenPipeError, ValueError):
            pass
        for fh in (record_file, pcap_file if pcap_file is not sys.stdout.buffer else None):
            if fh is not None:
                fh.close()
    if proxy.error is not None:
        print(f"{prog}: link error: {proxy.error}", file=sys.stderr)
        return 2
    return 0


__all__ = ["Display", "add_arguments", "host_port", "run"]
