"""Why a request was answered CAN or NAK, in the log at ``-v`` (issue 34 item 5, issue 31).

A PSI reply carries no reason: 30 bytes, ``2 S 2 CAN`` (spec 2.2.2). The reason
was only printed with command 91 (debug print) on, which is a switch for every
client at once. :class:`ReasonLog` gives each refused request **one line** at
INFO (``serve -v``) on the ``tcp_bridge.replies`` logger::

    axis 2 S02 (2S02=abc): CAN: bad value 'abc': not a decimal or 0x-hex number: ...

the axis and command, the request as the client sent it (printable, cut at
:data:`MAX_REQUEST` characters), the reply and the reason: the text of the
exception that :meth:`tcp_bridge.server.BridgeServer._answer` turned into the
reply, whatever raised it (the parser, the tables, a CANopen abort, a silent
bus, an EtherCAT slave that has no such object), so every backend is covered in
that one place.

**Rate limit** (chosen; a client polling a silent axis at 10 Hz would write
10 lines a second): one line per *kind of refusal* per :data:`INTERVAL`
seconds, a kind being (axis, S or R, command, reply, exception type, reason
with its numbers left out: "silent for 10.1 s" and "for 10.6 s" are one). The
refusals of a kind within the interval after its line are counted, and the
kind's next line says how many were not logged (``(12 more like it not
logged)``). At most :data:`MAX_KINDS` kinds are remembered (the least recently
logged is forgotten first), so a client sending junk to every axis and command
costs bounded memory, and at most that many lines per interval.

Pure apart from the logger: the clock is injected.
"""
from __future__ import annotations

import logging
import re
import time
from collections import OrderedDict
from typing import Callable, Dict, Final, Hashable, Optional, Tuple

from .wire import Line, Request, Status

log = logging.getLogger("tcp_bridge.replies")

INTERVAL: Final = 5.0  # seconds between two lines of one kind of refusal
MAX_KINDS: Final = 1024
MAX_REQUEST: Final = 40  # characters of the request shown (a request is at most ~30)

Kind = Tuple[Hashable, ...]
_DIGITS = re.compile(r"\d+(\.\d+)?")


def request_text(item: Line) -> str:
    """The request as a person reads it: printable ASCII, the rest escaped, cut short."""
    raw = item.head if not isinstance(item, (bytes, bytearray)) else bytes(item)
    text = "".join(chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}" for b in raw[:MAX_REQUEST])
    return text + ("..." if len(raw) > MAX_REQUEST else "")


def one_line(text: str) -> str:
    """``text`` on one line: runs of white space one space, other control characters escaped."""
    text = " ".join(text.split())
    return "".join(c if c.isprintable() else f"\\x{ord(c):02x}" for c in text)


class ReasonLog:
    """One rate-limited log line per refused request (module docstring)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, *,
                 interval: float = INTERVAL, max_kinds: int = MAX_KINDS,
                 logger: logging.Logger = log) -> None:
        self.clock = clock
        self.interval = interval
        self.max_kinds = max(1, max_kinds)
        self.logger = logger
        # kind -> (time of its last line, refusals not logged since)
        self._kinds: "OrderedDict[Kind, Tuple[float, int]]" = OrderedDict()

    def refused(self, item: Line, request: Optional[Request], exc: BaseException,
                status: Status) -> Optional[str]:
        """Log why ``item`` was answered ``status``; returns the line, or None if held back."""
        if not self.logger.isEnabledFor(logging.INFO):
            return None
        axis: Optional[int] = getattr(request or exc, "axis", None)
        letter: Optional[str] = getattr(request or exc, "kind", None)
        cmd: Optional[int] = getattr(request or exc, "cmd", None)
        why = one_line(str(exc) or type(exc).__name__)
        # Numbers vary within one kind of refusal ("silent for 10.1 s", "for 10.6 s").
        kind: Kind = (axis, letter, cmd, status, type(exc).__name__, _DIGITS.sub("#", why))
        now = self.clock()
        last = self._kinds.get(kind)
        if last is not None and now - last[0] < self.interval:
            self._kinds[kind] = (last[0], last[1] + 1)
            return None
        held = last[1] if last is not None else 0
        self._kinds[kind] = (now, 0)
        self._kinds.move_to_end(kind)
        while len(self._kinds) > self.max_kinds:
            self._kinds.popitem(last=False)
        who = f"axis {axis}" if axis is not None else "axis ?"
        command = f"{letter}{cmd:02d}" if letter is not None and cmd is not None else "?"
        line = f"{who} {command} ({request_text(item)}): {status.name}: {why}"
        if held:
            line += f" ({held} more like it not logged)"
        self.logger.info("%s", line)
        return line

    def pending(self) -> Dict[Kind, int]:
        """Refusals counted but not yet logged, by kind (tests)."""
        return {k: n for k, (_, n) in self._kinds.items() if n}


__all__ = ["INTERVAL", "MAX_KINDS", "ReasonLog", "one_line", "request_text"]
