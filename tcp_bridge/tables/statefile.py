"""The state file: the S-command values kept across restarts, durable before the ACK.

**The guarantee** (issue 35): a request whose ACK changed stored state is on
disk before that ACK leaves; a bridge killed at any instant (``kill -9``, power
loss) restarts with every value it ACKed, never an older one.

* A write is atomic and durable: a temporary file in the same directory, its
  contents fsynced, renamed over the file (``os.replace``, atomic on POSIX),
  then the directory fsynced so that the rename itself survives a crash
  (rename(2) alone is not durable; see fsync(2): "Calling fsync() does not
  necessarily ensure that the entry in the directory containing the file has
  also reached disk. For that an explicit fsync() on a file descriptor for the
  directory is also needed."). The file holds the old or the new content.
* Written by one background thread (:class:`StateFileWriter`), never by the
  caller: a bus worker that stores a parameter must not wait for an fsync.
  Snapshots that arrive while a write is in progress are batched into the
  next write (the newest includes them all), and each change's waiter is
  released when the write that holds it is on disk (group commit): the ACK
  waits, the bus does not (:meth:`StateFileWriter.written`).
* A write that fails (disk full, directory gone) releases its waiters too,
  logged at ERROR: the value is in effect, so the reply is still ACK (spec
  2.2.2: NAK means not executed). The guarantee holds again from the next
  write that succeeds, which writes the whole state.
* Temporary files left by a bridge killed in the middle of a write are removed
  at start (:func:`remove_stale_temporaries`).
"""
from __future__ import annotations

import asyncio
import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

log = logging.getLogger("tcp_bridge.tables.parameters")

Snapshot = Dict[int, Dict[int, int]]
TEMPORARY_SUFFIX = ".tmp"  # a temporary is ".NAME.<random>.tmp" beside the file NAME


def _temporary_prefix(path: Path) -> str:
    return f".{path.name}."


class StateFileWriter:
    """One thread that writes the newest submitted snapshot; older pending ones are dropped.

    A write that fails is logged at ERROR and not retried by itself: the next
    change writes the whole state again. The thread starts with the first
    snapshot; after :meth:`close` a late snapshot is written by the caller.
    Versions are the store's change counter: :meth:`when_written` and
    :meth:`written` tell when the write holding a version has ended.
    """

    def __init__(self, write: Callable[[Snapshot], None], name: str) -> None:
        self._write = write
        self._name = name
        self._cond = threading.Condition()
        self._pending: Optional[Tuple[int, Snapshot]] = None
        self._latest = 0  # newest version submitted
        self._done = 0  # newest version whose write has ended (on disk, or failed and logged)
        self._waiters: List[Tuple[int, Callable[[], None]]] = []
        self._busy = False
        self._closed = False
        self._thread: Optional[threading.Thread] = None

    def when_written(self, version: int, callback: Callable[[], None]) -> bool:
        """Call ``callback`` (from the writer's thread) once the write holding
        ``version`` has ended; False, and no call, if it already has."""
        with self._cond:
            if version <= self._done:
                return False
            self._waiters.append((version, callback))
            return True

    async def written(self, version: int, timeout: float) -> bool:
        """Wait, without blocking the event loop, until the write holding
        ``version`` has ended; False if it has not after ``timeout`` seconds."""
        loop = asyncio.get_running_loop()
        done: "asyncio.Future[None]" = loop.create_future()

        def release() -> None:
            if not done.done():
                done.set_result(None)

        def wake() -> None:
            try:
                loop.call_soon_threadsafe(release)
            except RuntimeError:  # the loop has closed: nobody is waiting any more
                pass
        if not self.when_written(version, wake):
            return True
        try:
            await asyncio.wait_for(done, timeout)
        except asyncio.TimeoutError:
            return False
        return True

    def _ended(self, version: int) -> None:
        """The write of ``version`` ended: release the waiters it covers."""
        with self._cond:
            self._done = max(self._done, version)
            ready = [cb for v, cb in self._waiters if v <= self._done]
            self._waiters = [(v, cb) for v, cb in self._waiters if v > self._done]
        for callback in ready:
            try:
                callback()
            except Exception:  # a waiter's bug must not kill the writer thread
                log.exception("state file %s: a waiter failed", self._name)

    def submit(self, version: int, snapshot: Snapshot) -> None:
        with self._cond:
            if version <= self._latest:
                return  # a newer snapshot (which includes this change) is already queued
            self._latest = version
            closed = self._closed
            if not closed:
                self._pending = (version, snapshot)
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, daemon=True,
                                                    name="state-file")
                    self._thread.start()
                self._cond.notify_all()
        if closed:
            self._write_logged(snapshot)  # after close: nobody else will
            self._ended(version)

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
                version, snapshot = self._pending
                self._pending = None
                self._busy = True
            try:
                self._write_logged(snapshot)
            finally:
                self._ended(version)
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
    fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=TEMPORARY_SUFFIX,
                               dir=path.parent)
    os.close(fd)
    os.unlink(tmp)


def remove_stale_temporaries(path: Path) -> List[Path]:
    """Remove the temporary files of ``path`` a killed writer left (``.NAME.*.tmp``
    beside it, as :func:`write_atomically` names them); returns those removed.
    Called at start, before the store writes anything."""
    prefix = _temporary_prefix(path)
    removed: List[Path] = []
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        if entry.name.startswith(prefix) and entry.name.endswith(TEMPORARY_SUFFIX) \
                and len(entry.name) > len(prefix) + len(TEMPORARY_SUFFIX):
            try:
                entry.unlink()
            except FileNotFoundError:
                continue
            except OSError as exc:
                log.warning("state file %s: cannot remove the stale temporary %s (%s)",
                            path, entry.name, exc.strerror or exc)
                continue
            removed.append(entry)
    if removed:
        log.info("state file %s: removed %d temporary file(s) left by an interrupted write",
                 path, len(removed))
    return removed


def _fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable (fsync(2) of the directory)."""
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    fd = os.open(directory, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` so that ``path`` holds either the old or the new content, and
    the new content is on disk when this returns (file and directory fsynced)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=TEMPORARY_SUFFIX,
                               dir=path.parent)
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
    _fsync_directory(path.parent)
