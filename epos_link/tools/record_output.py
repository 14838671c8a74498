"""Where ``epos-link record`` puts its samples: the checks before anything is sent,
and the writing after.

Policy (a recording may be minutes of waiting for a trigger and cannot be taken
again, so nothing about its outputs is left to be found out at the end):

* **Before** anything is sent: at least one output (``--csv`` or ``--plot``),
  else one line and exit 2 (**chosen** over printing the CSV by default: a
  recording nobody asked to keep is a mistake, and thousands of rows on a
  terminal are no place for one); each plot's format, and matplotlib for PNG or
  SVG; and that each path can be written: its directory exists and takes files,
  and the path is no directory nor a file we may not write. Checked without
  creating anything (``os.stat``/``os.access``), so a failed start leaves no
  empty files behind. The reason is the operating system's words, as the write
  would have said them (``No such file or directory``, ``Is a directory``,
  ``Not a directory``, ``Permission denied``).
* **After**: every output is written even if another fails (a full disk, a plot
  backend's error), and the failures are one line that also names what was
  written, so the samples that could be kept are found.
"""
from __future__ import annotations

import argparse
import errno
import importlib
import os
import stat
import sys
from dataclasses import dataclass, field
from typing import Optional, Sequence

from .recording import Channel, Value, write_csv

PROG = "epos-link record"
PLOT_SUFFIXES = (".png", ".svg", ".html", ".htm")


def _unwritable(path: str) -> Optional[str]:
    """Why ``path`` cannot be written as a new or replaced file, or None."""
    try:
        st: Optional[os.stat_result] = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:  # ENOTDIR: a part of the path is a file
        return os.strerror(exc.errno) if exc.errno else str(exc)
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            return os.strerror(errno.EISDIR)
        return None if os.access(path, os.W_OK) else os.strerror(errno.EACCES)
    parent = os.path.dirname(path) or "."
    try:
        parent_st = os.stat(parent)
    except OSError as exc:
        return os.strerror(exc.errno) if exc.errno else str(exc)
    if not stat.S_ISDIR(parent_st.st_mode):
        return os.strerror(errno.ENOTDIR)
    if not os.access(parent, os.W_OK | os.X_OK):
        return os.strerror(errno.EACCES)
    return None


def check_outputs(args: argparse.Namespace) -> Optional[str]:
    """The one line (without the program's name) that refuses to start, or None."""
    if not args.csv and not args.plot:
        return ("nothing would keep the samples: give --csv FILE (- for standard output) "
                "and/or --plot FILE")
    for path in args.plot:
        if not path.lower().endswith(PLOT_SUFFIXES):
            return f"--plot {path}: a plot is .png, .svg or .html"
    if any(p.lower().endswith((".png", ".svg")) for p in args.plot):
        try:
            importlib.import_module("matplotlib")
        except ImportError:
            return ("PNG and SVG plots need matplotlib: pip install 'epos-link[plot]' "
                    "(or pip install matplotlib); an .html plot needs nothing")
    for path in ([args.csv] if args.csv and args.csv != "-" else []) + list(args.plot):
        reason = _unwritable(path)
        if reason is not None:
            return f"cannot write {path}: {reason}"
    return None


@dataclass
class Written:
    """What :func:`write_outputs` wrote, and what it could not (path, reason)."""

    paths: list[str] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)

    def failure_line(self, prog: str = PROG) -> str:
        """One line for standard error: what failed, and what was kept."""
        what = "; ".join(f"cannot write {path}: {reason}" for path, reason in self.failed)
        kept = f"wrote {', '.join(self.paths)}" if self.paths else "nothing was written"
        return f"{prog}: {what}; {kept}"


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno:
        return exc.strerror or os.strerror(exc.errno)
    return f"{type(exc).__name__}: {exc}"


def write_outputs(args: argparse.Namespace, channels: list[Channel],
                  rows: Sequence[tuple[float, Sequence[Value]]], title: str, *,
                  triggered: bool = True) -> Written:
    """The CSV, then each plot; one failing does not stop the others.

    The plots break their lines where ``args.period`` slots were missed, and mark the
    trigger at time 0 unless the recording was not ``triggered`` (epos_link.tools.plot)."""
    out = Written()
    if args.csv == "-":
        write_csv(sys.stdout, channels, rows)
    elif args.csv:
        try:
            with open(args.csv, "w", newline="", encoding="utf-8") as f:
                write_csv(f, channels, rows)
            out.paths.append(args.csv)
        except OSError as exc:  # a full disk, a file removed or locked meanwhile
            out.failed.append((args.csv, _reason(exc)))
    if args.plot:
        from .plot import panels, write_plot

        found = panels(channels, rows, period=getattr(args, "period", 0.0) or 0.0)
        for path in args.plot:
            try:
                write_plot(path, found, title, trigger=0.0 if triggered else None)
                out.paths.append(path)
            # OSError: the file; ValueError, RuntimeError: what matplotlib's backends
            # raise on a figure they cannot render. Anything else is a bug and keeps
            # its traceback (the CSV, written first, is on disk by then).
            except (OSError, ValueError, RuntimeError) as exc:
                out.failed.append((path, _reason(exc)))
    return out


__all__ = ["Written", "check_outputs", "write_outputs"]
