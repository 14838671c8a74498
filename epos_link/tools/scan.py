"""``epos-link scan URL [--nodes 1-127] [--node-timeout S] [--json]``: the nodes that answer.

Each node is tried in turn with a ReadObject of 0x1000 (device type, CiA 301
7.5.2.1); one that answers is identified (0x1008 name, 0x1018 identity) and
printed at once, so a long scan shows its results as they come. On a terminal
a progress line on standard error says which node is being tried.

Time per node: ``--node-timeout`` is how long to wait for each node's answer.
An absent node behind the gateway is answered by the gateway itself, with
0x05040000 "SDO protocol timed out", after its own SDO timeout; until then the
EPOS4 takes no other request (guide 2.2.1). The client waits for that late
answer (see :mod:`epos_link.link`) so it is never taken for the next node's;
that wait is ``--node-timeout`` too when it is longer than the client's default.
So an absent node costs the longer of ``--node-timeout`` and the gateway's
timeout: a shorter ``--node-timeout`` cannot make the gateway faster, and a
scan that skipped that wait would report nodes that are not there.

Before any node, the EPOS4 on the link is asked for its own device type
(:func:`~epos_link.tools.common.require_device`): a silent link (wrong port or
baud rate, no power) is one line and exit 2 within a few seconds, instead of
every node timing out in turn. Exit codes: 0 some node answered, 2 none did,
the link is silent, or the command is wrong; 130 interrupted (Ctrl-C), after one
line saying which node was being tried and which had answered (a long scan stopped
half way still says what it found).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from typing import IO, Optional

from ..client import DEFAULT_SCAN_TIMEOUT, EposClient, NodeInfo
from .common import (add_link_options, add_url, guarded, open_client, parse_int, positive_float,
                     require_device)


def node_list(text: str) -> list[int]:
    """``1-127``, ``1,2,5`` or a mix (``1-4,10``)."""
    nodes: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            first = parse_int(lo)
            nodes.extend(range(first, parse_int(hi) + 1) if hi else [first])
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a node list like 1-127 or 1,2,5") from None
    if not nodes:
        raise argparse.ArgumentTypeError(f"{text!r} names no node")
    bad = [n for n in nodes if not 0 <= n <= 127]
    if bad:
        raise argparse.ArgumentTypeError(f"node ids are 0..127, got {bad[0]}")
    return nodes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_url(parser)
    parser.add_argument("--nodes", type=node_list, default=list(range(1, 128)), metavar="LIST",
                        help="node ids to try: 1-127 (default), 1,2,5, 0-3,10")
    parser.add_argument("--node-timeout", type=positive_float, default=DEFAULT_SCAN_TIMEOUT, metavar="SECONDS",
                        help=f"how long to wait for each node's answer (default {DEFAULT_SCAN_TIMEOUT:g}); "
                        "an absent node behind the gateway still costs the gateway's SDO timeout")
    parser.add_argument("--json", action="store_true", help="one JSON object per node found")
    parser.add_argument("--no-progress", action="store_true", help="no progress line on a terminal")
    add_link_options(parser)


def format_node(info: NodeInfo) -> str:
    ids = " ".join(f"{k}=0x{v:08X}" for k, v in (
        ("vendor", info.vendor_id), ("product", info.product_code),
        ("revision", info.revision), ("serial", info.serial_number)) if v is not None)
    name = json.dumps(info.name) if info.name is not None else "-"
    return f"node {info.node:3d}  type=0x{info.device_type:08X}  name={name}  {ids}".rstrip()


class Progress:
    """One line on a terminal, rewritten in place; nothing when not a terminal."""

    def __init__(self, stream: IO[str], enabled: bool) -> None:
        self.stream = stream
        self.enabled = enabled
        self._width = 0

    def show(self, text: str) -> None:
        if self.enabled:
            self.stream.write("\r" + text.ljust(self._width))
            self.stream.flush()
            self._width = len(text)

    def clear(self) -> None:
        if self.enabled and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0


@dataclass
class Tally:
    """How far a scan got: kept by the caller, so an interrupted scan can say it."""
    tried: int = 0                      # nodes whose answer (or silence) is known
    trying: Optional[int] = None        # the node asked last, not yet known
    found: list[NodeInfo] = field(default_factory=list)

    def interrupted(self, total: int, seconds: float) -> str:
        found = ", ".join(str(info.node) for info in self.found)
        return ((f"interrupted while trying node {self.trying}: " if self.trying is not None
                 else "interrupted: ")
                + f"{self.tried} of {total} nodes tried in {seconds:.1f} s, "
                + (f"{len(self.found)} answered ({found})" if self.found else "none answered"))


def scan(client: EposClient, nodes: list[int], node_timeout: float, *, json_lines: bool,
         out: IO[str], progress: Progress, tally: Optional[Tally] = None) -> list[NodeInfo]:
    """Try each node, print each one found at once; returns those found (also kept in
    ``tally``, with how far the scan got, for a caller that is interrupted)."""
    now = time.monotonic
    start = now()
    tally = Tally() if tally is None else tally
    found = tally.found
    client.late_answer_timeout = max(client.late_answer_timeout, node_timeout)
    for i, node in enumerate(nodes, 1):
        tally.trying = node  # before the progress names it: a Ctrl-C then says so too
        progress.show(f"scanning node {node} ({i}/{len(nodes)}), {len(found)} found, {now() - start:.1f} s")
        infos = client.scan([node], timeout=node_timeout)
        tally.tried, tally.trying = i, None
        for info in infos:
            found.append(info)
            progress.clear()
            out.write((json.dumps(info.as_dict()) if json_lines else format_node(info)) + "\n")
            out.flush()
    progress.clear()
    return found


def run(args: argparse.Namespace) -> int:
    prog = "epos-link scan"

    def body() -> int:
        progress = Progress(sys.stderr, not args.no_progress and sys.stderr.isatty())
        started = time.monotonic()
        tally = Tally()
        try:
            with open_client(args) as client:
                require_device(client, args.url, args.baud)
                found = scan(client, args.nodes, args.node_timeout, json_lines=args.json,
                             out=sys.stdout, progress=progress, tally=tally)
        except KeyboardInterrupt:
            # Ctrl-C: what the scan learnt so far is one line, not a traceback or nothing.
            progress.clear()
            print(f"{prog}: {tally.interrupted(len(args.nodes), time.monotonic() - started)}",
                  file=sys.stderr)
            return 130
        if not found:
            print(f"{prog}: no node answered on {args.url}", file=sys.stderr)
            return 2
        if progress.enabled:
            print(f"{len(found)} of {len(args.nodes)} nodes answered in "
                  f"{time.monotonic() - started:.1f} s", file=sys.stderr)
        return 0

    return guarded(prog, body)


__all__ = ["Tally", "add_arguments", "format_node", "node_list", "run", "scan"]
