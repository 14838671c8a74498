"""The state file: the S-command values kept across restarts, written atomically.

Written by one background thread (:class:`StateFileWriter`), never by the
caller: a bus worker that stores a parameter must not wait for an fsync.
Snapshots that pile up while a write is in progress are coalesced, the newest
wins. A write is atomic (temporary file, fsync, rename), so the file holds
either the old or the new content.
"""
from __future__ import annotations

import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Callable, Dict, Optional, Tuple

log = logging.getLogger("tcp_bridge.tables.parameters")

Snapshot = Dict[int, Dict[int, int]]


class StateFileWriter:
    """One thread that writes the newest submitted snapshot; older pending ones are dropped.

    A write that fails is logged at ERROR and not retried by itself: the next
    change writes the whole state again. The thread starts with the first
    snapshot; after :meth:`close` a late snapshot is written by the caller.
    """

    def __init__(self, write: Callable[[Snapshot], None], name: str) -> None:
        self._write = write
        self._name = name
        self._cond = threading.Condition()
        self._pending: Optional[Tuple[int, Snapshot]] = None
        self._latest = 0  # newest version submitted
        self._busy = False
        self._closed = False
        self._thread: Optional[threading.Thread] = None

    def submit(self, version: int, snapshot: Snapshot) -> None:
        with self._cond:
            if version <= self._latest:
                return  # a newer snapshot (which includes this change) is already queued
            self._latest = version
            if not self._closed:
                self._pending = (version, snapshot)
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, daemon=True,
                                                    name="state-file")
                    self._thread.start()
                self._cond.notify_all()
                return
        self._write_logged(snapshot)  # after close: nobody else will

    def flush(self, timeout: Optional[float] = None) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None and not self._busy, timeout)

    def close(self, timeout: float = 10.0) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                log.error("state file %s: still writing after %g s at shutdown", self._name,
                          timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                if self._pending is None:
                    return  # closed, and everything is written
                _, snapshot = self._pending
                self._pending = None
                self._busy = True
            try:
                self._write_logged(snapshot)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _write_logged(self, snapshot: Snapshot) -> None:
        try:
            self._write(snapshot)
        except OSError as exc:
            log.error("state file %s: cannot write it (%s); the parameters set since its last "
                      "write are in effect but NOT persisted: they are lost at restart unless "
                      "a later write succeeds", self._name, exc)
        except Exception:  # a bug: never kill the writer thread
            log.exception("state file %s: write failed", self._name)


def check_writable(path: Path) -> None:
    """OSError unless :func:`write_atomically` can write ``path``: its directory is
    created if missing, and a temporary file is made there and removed."""
    if path.exists() and not path.is_file():
        raise IsADirectoryError(21, "not a regular file", str(path))
    existing = next((p for p in path.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise NotADirectoryError(20, f"{existing} is not a directory", str(existing))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.unlink(tmp)


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` so that ``path`` holds either the old or the new content."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
