"""``epos-link watch URL [--node N] [OBJECT...]``: a live table of objects in the terminal.

::

    epos-link watch socket://127.0.0.1:4001 --node 2
    epos-link watch /dev/ttyACM0 --node 1 Statusword 0x6064 "Velocity actual value" 0x1018/4

Reads each object in turn through :class:`epos_link.client.EposClient` (one
request in flight, as the client's rules say), every ``--period`` seconds
(default 0.25), and redraws the table in place; ``q`` quits, so does Ctrl-C.
The table (columns, decoding, units, age and rate) is :mod:`epos_link.tools.watch_table`.
Objects are named as ``epos-link read`` names them (:func:`epos_link.tools.access.resolve_target`),
by name or by ``INDEX`` or ``INDEX/SUBINDEX``; with none named, the statusword
(6041h), modes of operation display (6061h), position and velocity actual values
(6064h, 606Ch), error register (1001h) and error code (603Fh). The velocity unit
is read once from the node's 60A9h, or is the EDS's default (rpm) when the node
has none.

Terminal handling: on a terminal, the table is drawn on the alternate screen
with ANSI escapes (home, erase to end of line and of screen: ECMA-48 CUP, EL,
ED; xterm's private mode 1049) with the cursor hidden, and standard input is put
in cbreak mode (no echo, one key at a time, Ctrl-C still a signal) so that a
``q`` is seen without Enter. Whatever ends the loop (``q``, Ctrl-C, SIGTERM,
SIGHUP, an error), the terminal is given back as it was found, the table's last
screen vanishing with the alternate screen as in ``top`` or ``less``.

The width is the terminal's own, asked at each draw (a resize is followed), not
$COLUMNS (see :func:`_terminal_size`).

Not a terminal (**chosen**): when standard output is a pipe or file, one table
per refresh is printed, plain, each followed by a blank line, until Ctrl-C or
SIGTERM, as ``top -b`` does; a log of a drive is then one redirection away.
``--once`` prints one table and exits, on a terminal or not.

Failures: a failed read shows in its row (``! timeout``) and the others go on;
a failed link shows ``! link down`` in every row and why once, under the title
(``! link down: connection refused; reconnecting at each read``), while the
client reopens it at each read (:mod:`epos_link.link`) until it is back;
if no object at all can be read in the first round and the EPOS4 on the link
does not answer either, that is one line and exit 2, as for ``epos-link read``.
Exit codes: 0 after ``q``, Ctrl-C or SIGTERM; with ``--once``, 0 when every
object was read, 1 when the device answered an error code for one, 2 when one
read timed out or the link failed; 2 for usage errors.
"""
from __future__ import annotations

import argparse
import os
import select
import shutil
import signal
import sys
import time
from types import FrameType
from typing import Any, Callable, Iterator, Optional, TextIO

from ..client import EposClient
from ..errors import DeviceError, EposError, EposTimeoutError, TransportError
from .access import Target, _node, read_value, resolve_target
from .common import add_link_options, add_url, device_silent, guarded, open_client, positive_float, require_device
from .objects import load_directory
from .watch_table import LINK_DOWN, Row, Watched, link_cause, render, unit_of, velocity_unit

DEFAULT_OBJECTS = ("0x6041", "0x6061", "0x6064", "0x606C", "0x1001", "0x603F")
DEFAULT_PERIOD = 0.25
REDRAW = 0.5  # the longest a screen waits between draws, so ages move on a long --period
OFF_TERMINAL_WIDTH = 120  # the width of tables printed to a pipe or file, unless $COLUMNS says
SI_UNIT_VELOCITY = 0x60A9
QUIT_KEYS = frozenset("qQ")

# ANSI/ECMA-48 sequences: alternate screen on/off (xterm private mode 1049),
# cursor hide/show (DECTCEM), cursor home (CUP), erase to end of line (EL) and
# of screen (ED).
ENTER, LEAVE = "\x1b[?1049h\x1b[?25l", "\x1b[?25h\x1b[?1049l"
HOME, ERASE_LINE, ERASE_BELOW = "\x1b[H", "\x1b[K", "\x1b[J"


def _intermixed(parser: argparse.ArgumentParser) -> None:
    """Let OBJECT words follow options (``URL --node 2 Statusword``): argparse matches
    a ``nargs="*"`` positional as soon as it can (Python 3.11 here: empty, right after
    URL) and then rejects later words as unrecognized. The subparser (made by
    :mod:`epos_link.cli`) parses intermixed instead (``parse_intermixed_args``, as the
    argparse documentation suggests for this); the guard lets
    ``parse_known_intermixed_args`` call the plain parse it is built on."""
    plain = parser.parse_known_args
    inside = False

    def parse_known_args(args: Any = None, namespace: Any = None) -> Any:
        nonlocal inside
        if inside:
            return plain(args, namespace)
        inside = True
        try:
            return parser.parse_known_intermixed_args(args, namespace)
        finally:
            inside = False

    setattr(parser, "parse_known_args", parse_known_args)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _intermixed(parser)
    add_url(parser)
    parser.add_argument("--node", type=_node, default=0, metavar="N",
                        help="CANopen node id: 0 = the connected EPOS4 (default), 1..127 = via its gateway")
    parser.add_argument("objects", metavar="OBJECT", nargs="*", default=[],
                        help='an object by name ("Position actual value") or INDEX[/SUBINDEX] '
                        "(0x6064, 0x1018/4); default: statusword, mode, position, velocity, errors")
    parser.add_argument("--period", type=positive_float, default=DEFAULT_PERIOD, metavar="SECONDS",
                        help=f"time between refreshes (default {DEFAULT_PERIOD:g})")
    parser.add_argument("--once", action="store_true", help="print one table and exit")
    parser.add_argument("--eds", metavar="FILE",
                        help="object dictionary (EDS or DCF) for names and types (default: the shipped EPOS4 EDS)")
    add_link_options(parser)


def resolve(args: argparse.Namespace, text: str) -> Target:
    """One OBJECT word (NAME, INDEX or INDEX/SUBINDEX), resolved as ``epos-link read`` resolves it."""
    one = argparse.Namespace(eds=args.eds, node=args.node, object=text, type=None)
    return resolve_target(one, None)


def _silent(client: EposClient, args: argparse.Namespace, exc: EposTimeoutError) -> None:
    """Raise the one line of a silent EPOS4 if it is one (as ``epos-link read`` does)."""
    if args.node == 0:
        raise device_silent(args.url, args.baud, exc) from exc
    require_device(client, args.url, args.baud)


def read_velocity_unit(client: EposClient, args: argparse.Namespace) -> str:
    """The node's 60A9h as a unit, else the EDS default's (rpm on an EPOS4). The first
    request of the command: a silent link ends it here, in one line."""
    try:
        si_unit = int.from_bytes(client.read_object(args.node, SI_UNIT_VELOCITY, 0)[:4], "little")
    except EposTimeoutError as exc:
        _silent(client, args, exc)
    except EposError:  # a node without 60A9h, or a garbled answer: the dictionary's default
        pass
    else:
        return velocity_unit(si_unit)
    var = load_directory(args.eds, max(args.node, 1)).variable(SI_UNIT_VELOCITY, 0)
    default = var.default if var is not None else None
    return velocity_unit(default) if isinstance(default, int) else "?"


class Watch:
    """The objects, their rows, and one round of reads."""

    def __init__(self, client: EposClient, targets: list[Target], velocity: str,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.client = client
        self.targets = targets
        self.clock = clock
        self.rows = [Row(Watched(t.index, t.subindex, t.name or "", unit_of(t.index, t.subindex, velocity)))
                     for t in targets]
        self.failures: list[Optional[EposError]] = [None] * len(targets)
        self.link_down: Optional[str] = None  # why, while the link itself fails
        self.first = clock()  # when the first round began

    def read(self, index: int) -> None:
        """Read row ``index`` once and record the outcome."""
        target, row = self.targets[index], self.rows[index]
        try:
            value = target.type.decode(read_value(self.client, target))
        except DeviceError as exc:
            self.failures[index] = exc
            row.failure(f"0x{exc.code:08X} {exc.name}", self.clock())
        except EposTimeoutError as exc:
            self.failures[index] = exc
            row.failure("timeout", self.clock())
        except TransportError as exc:
            # The same for every row: each says "link down", the status line says why
            # once. The client reopens the link at the next read (epos_link.link).
            self.failures[index] = exc
            self.link_down = link_cause(str(exc), self.client.transport.url)
            row.failure(LINK_DOWN, self.clock())
            return
        except EposError as exc:
            self.failures[index] = exc
            row.failure(str(exc) or type(exc).__name__, self.clock())
        else:
            self.failures[index] = None
            row.reading(value, self.clock())
        self.link_down = None  # the link carried the request (even one that timed out): it is up

    def round(self, between: Callable[[], bool] = lambda: False) -> bool:
        """Read every row; ``between()`` is asked after each read, True stops the round
        (a key pressed). Returns whether the round was stopped."""
        for i in range(len(self.rows)):
            self.read(i)
            if between():
                return True
        return False

    def lines(self, width: int, title: str = "", *, live: bool = True) -> list[str]:
        """The table now; ``live=False``: ages as of each row's read (``--once``)."""
        status = f"! {LINK_DOWN}: {self.link_down}; reconnecting at each read" if self.link_down else ""
        return render(self.rows, self.clock() if live else None, width, title, status)

    def exit_code(self) -> int:
        """Of ``--once``: 0 all read, 1 a device error code, 2 a timeout or link failure."""
        if any(f is not None and not isinstance(f, DeviceError) for f in self.failures):
            return 2
        return 1 if any(self.failures) else 0


class Stop(Exception):
    """SIGTERM or SIGHUP: leave the loop as after ``q``."""


def _stop(signum: int, frame: Optional[FrameType]) -> None:
    raise Stop(signal.Signals(signum).name)


class Screen:
    """A terminal on standard output: alternate screen, hidden cursor, cbreak input."""

    def __init__(self, out: TextIO, keys: Optional[int]) -> None:
        self.out = out
        self.keys = keys  # the file descriptor keys are read from, None: no keys
        self._saved: Optional[list] = None  # type: ignore[type-arg]

    def __enter__(self) -> "Screen":
        if self.keys is not None:
            import termios
            import tty

            self._saved = termios.tcgetattr(self.keys)
            tty.setcbreak(self.keys)
        self.out.write(ENTER)
        self.out.flush()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.out.write(LEAVE)
            self.out.flush()
        except OSError:  # a terminal that hung up (SIGHUP) takes no more output
            pass
        finally:
            if self._saved is not None and self.keys is not None:
                import termios

                try:
                    termios.tcsetattr(self.keys, termios.TCSADRAIN, self._saved)
                except termios.error:  # nor its modes
                    pass

    def draw(self, lines: list[str], height: int) -> None:
        # Home, each line over the old one with the rest of it erased, then erase
        # below: no flicker of a full clear. The last line gets no newline, so a
        # table as tall as the terminal does not scroll it.
        shown = lines[:max(1, height)]
        self.out.write(HOME + (ERASE_LINE + "\r\n").join(shown) + ERASE_LINE + ERASE_BELOW)
        self.out.flush()

    def key(self, timeout: float) -> Optional[str]:
        """A key pressed within ``timeout`` seconds (0: only one already waiting)."""
        if self.keys is None:
            if timeout > 0:
                time.sleep(timeout)
            return None
        ready, _, _ = select.select([self.keys], [], [], max(0.0, timeout))
        if not ready:
            return None
        data = os.read(self.keys, 64)
        return data.decode("latin-1") if data else None

    def quit_pressed(self, timeout: float = 0.0) -> bool:
        key = self.key(timeout)
        return key is not None and any(k in QUIT_KEYS for k in key)


def _title(args: argparse.Namespace, live: bool) -> str:
    where = "the connected EPOS4" if args.node == 0 else f"node {args.node}"
    text = f"epos-link watch {args.url} {where}"
    if args.once:
        return text
    return text + f", every {args.period:g} s" + ("; q quits" if live else "")


def _width() -> int:
    """The terminal's width ($COLUMNS first, as :func:`shutil.get_terminal_size` reads
    it), or :data:`OFF_TERMINAL_WIDTH` when standard output is not a terminal."""
    return shutil.get_terminal_size((OFF_TERMINAL_WIDTH, 24)).columns


def _terminal_size(out: TextIO) -> os.terminal_size:
    """The size of the terminal drawn on, as the terminal says it (TIOCGWINSZ), not
    $COLUMNS: an exported $COLUMNS is a size the terminal once had (ncurses programs
    export it; a shell or tmux pane started from one inherits it) and would keep a
    resized or narrow terminal's lines too wide, wrapping."""
    try:
        return os.get_terminal_size(out.fileno())
    except (OSError, ValueError):
        return shutil.get_terminal_size()


def _rounds(first: float, period: float, clock: Callable[[], float]) -> Iterator[float]:
    """The start of each round after the one that began at ``first``: every ``period``
    s, never catching up on rounds missed while reads were slow (a late round starts
    the next period from itself)."""
    start = first
    while True:
        start = max(start + period, clock())
        yield start


def _live(watch: Watch, args: argparse.Namespace, out: TextIO) -> int:
    keys = sys.stdin.fileno() if sys.stdin is not None and sys.stdin.isatty() else None
    title = _title(args, keys is not None)
    with Screen(out, keys) as screen:

        def draw() -> None:
            size = _terminal_size(out)  # each time: the terminal may have been resized
            screen.draw(watch.lines(size.columns, title), size.lines)

        draw()
        for start in _rounds(watch.first, args.period, watch.clock):
            # Between rounds: keys, and the ages kept moving on a long --period.
            while (left := start - watch.clock()) > 0:
                if screen.quit_pressed(min(left, REDRAW)):
                    return 0
                draw()
            if watch.round(screen.quit_pressed):
                return 0
            draw()
    return 0


def _batch(watch: Watch, args: argparse.Namespace, out: TextIO) -> int:
    def table() -> None:
        out.write("\n".join(watch.lines(_width(), _title(args, False))) + "\n\n")
        out.flush()

    table()
    for start in _rounds(watch.first, args.period, watch.clock):
        delay = start - watch.clock()
        if delay > 0:
            time.sleep(delay)
        watch.round()
        table()
    return 0


def run(args: argparse.Namespace) -> int:
    prog = "epos-link watch"
    out = sys.stdout

    def body() -> int:
        targets = [resolve(args, text) for text in args.objects or DEFAULT_OBJECTS]
        with open_client(args) as client:
            wants_unit = any(unit_of(t.index, t.subindex, "v") == "v" for t in targets)
            watch = Watch(client, targets, read_velocity_unit(client, args) if wants_unit else "")
            watch.round()
            first = watch.failures[0]
            if isinstance(first, EposTimeoutError) and all(isinstance(f, EposTimeoutError) for f in watch.failures):
                _silent(client, args, first)  # no answer at all: a silent EPOS4?
            if args.once:
                out.write("\n".join(watch.lines(_width(), _title(args, False), live=False)) + "\n")
                return watch.exit_code()
            previous = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGHUP)}
            try:
                return (_live if out.isatty() else _batch)(watch, args, out)
            except (KeyboardInterrupt, Stop):
                return 0
            finally:
                for s, handler in previous.items():
                    signal.signal(s, handler)

    return guarded(prog, body)


__all__ = ["DEFAULT_OBJECTS", "Screen", "Watch", "add_arguments", "resolve", "run"]
