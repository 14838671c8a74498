"""The per-axis parameter arrays (spec 3, 4) and the state file that keeps them.

Spec 3: "the axis parameters are stored in an array", one per axis, in stored
form (integers; the ``*`` parameters of spec 4 as ``round(user * factor)``).
The arrays start from the axis table (:mod:`tcp_bridge.axes`: defaults and
TOML values). Parameters changed with S commands are kept in a JSON state
file, written atomically (temporary file, fsync, rename) after every change
and overlaid on the table at start, as the controller keeps them across
restarts. Only S-command values go to the file, so later edits of the TOML
take effect for the rest.

A state file that cannot be written (disk full, directory gone, no rights)
does not undo the change and does not turn the reply into NAK: the value is
in the arrays, and for a drive parameter in the drive, so the command *was*
executed (spec 2.2.2: NAK means not executed). The failure is logged at
ERROR with the file's name every time; the next successful write persists
the whole snapshot, so nothing is lost once the file is writable again.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Dict, Final, Optional

from .axes import (DEFAULTS, PARAMETER_NAMES, AxisTable, ConfigError, DeviceCode, from_stored,
                   to_stored)
from .commands import COMMANDS
from .units import Number, Scaling

log = logging.getLogger(__name__)


class ParameterStore:
    """The per-axis parameter arrays: TOML values overlaid with the state file.

    Thread-safe: bus worker threads read and write it. Values are in stored
    form (integers); :meth:`user` converts. Only values set by S commands go
    to the state file, so later edits of the TOML take effect for the rest.
    """

    FORMAT: Final = "tcp-bridge-state"
    VERSION: Final = 1

    def __init__(self, table: AxisTable, state_file: Optional[Path] = None) -> None:
        self.table = table
        self.state_file = state_file if state_file is not None else table.settings.state_file
        self._lock = threading.Lock()  # the arrays; held briefly (the event loop reads too)
        self._file_lock = threading.Lock()  # the state file; held while writing it
        self._version = 0  # of the arrays' S-command values
        self._written = 0  # version in the state file
        self._base: Dict[int, Dict[int, int]] = {}
        for addr, axis in table.axes.items():
            values = {19: int(axis.device)}
            for cmd, default in DEFAULTS.items():
                user = axis.parameters.get(cmd, default)
                if user is not None:
                    values[cmd] = to_stored(COMMANDS[cmd], user, axis.position_factor)
            self._base[addr] = values
        self._overrides: Dict[int, Dict[int, int]] = {addr: {} for addr in table.axes}
        if self.state_file is not None:
            self._load()

    # -- access ---------------------------------------------------------------

    def get(self, addr: int, cmd: int) -> Optional[int]:
        """The stored value of parameter ``cmd`` of axis ``addr``, None if unset."""
        with self._lock:
            value = self._overrides[addr].get(cmd)
            return self._base[addr].get(cmd) if value is None else value

    def user(self, addr: int, cmd: int) -> Optional[Number]:
        stored = self.get(addr, cmd)
        if stored is None:
            return None
        return from_stored(COMMANDS[cmd], stored, self.table.axes[addr].position_factor)

    def set(self, addr: int, cmd: int, stored: int) -> None:
        """Store a value set by an S command and persist the state file.

        The file is written outside the arrays' lock, so readers never wait for
        a disk; of two concurrent writers the newer snapshot wins.
        """
        with self._lock:
            self._overrides[addr][cmd] = int(stored)
            self._version += 1
            version = self._version
            snapshot = {a: dict(v) for a, v in self._overrides.items() if v}
        if self.state_file is None:
            return
        with self._file_lock:
            if version > self._written:
                try:
                    self._save(snapshot)
                except OSError as exc:
                    log.error("state file %s: cannot write it (%s); axis %d parameter %d = %d "
                              "is in effect but NOT persisted: it is lost at restart unless a "
                              "later write succeeds", self.state_file, exc, addr, cmd, stored)
                    return
                self._written = version

    def set_user(self, addr: int, cmd: int, user: Number) -> int:
        stored = to_stored(COMMANDS[cmd], user, self.table.axes[addr].position_factor)
        self.set(addr, cmd, stored)
        return stored

    def scaling(self, addr: int) -> Scaling:
        """Conversion parameters of the axis now: factor, inversion (22), offset (25)."""
        axis = self.table.axes[addr]
        inversion = self.get(addr, 22)
        offset = self.user(addr, 25)
        return Scaling(axis.position_factor, -1 if inversion == -1 else 1,
                       float(offset) if offset is not None else 0.0)

    def device(self, addr: int) -> DeviceCode:
        code = self.get(addr, 19)
        try:
            return DeviceCode(code)
        except ValueError:
            return DeviceCode.C_DC_NOT_DEFINED

    def snapshot(self, addr: int) -> Dict[int, int]:
        with self._lock:
            return {**self._base[addr], **self._overrides[addr]}

    # -- state file -------------------------------------------------------------

    def _load(self) -> None:
        assert self.state_file is not None
        try:
            text = self.state_file.read_text(encoding="utf-8")
        except FileNotFoundError:
            return
        except OSError as exc:
            raise ConfigError(f"cannot read state file {self.state_file}: {exc}") from None
        try:
            data = json.loads(text)
            if data.get("format") != self.FORMAT or data.get("version") != self.VERSION:
                raise ValueError("not a tcp-bridge state file of version 1")
            axes = data["axes"]
            for key, entry in axes.items():
                addr = int(key)
                axis = self.table.axes.get(addr)
                if axis is None:
                    log.warning("state file: axis %d is no longer configured; ignored", addr)
                    continue
                if entry.get("position_factor") != axis.position_factor:
                    log.warning("state file: axis %d had position factor %s, now %d; its "
                                "stored parameters are ignored", addr,
                                entry.get("position_factor"), axis.position_factor)
                    continue
                for cmd_key, value in entry["parameters"].items():
                    cmd = int(cmd_key)
                    if cmd not in PARAMETER_NAMES or not isinstance(value, int):
                        raise ValueError(f"bad entry {cmd_key}={value!r} for axis {addr}")
                    self._overrides[addr][cmd] = value
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ConfigError(f"state file {self.state_file} is damaged ({exc}); "
                              "move it away to start from the axis table") from None

    def _save(self, overrides: Dict[int, Dict[int, int]]) -> None:
        assert self.state_file is not None
        data = {
            "format": self.FORMAT,
            "version": self.VERSION,
            "axes": {
                str(addr): {
                    "position_factor": self.table.axes[addr].position_factor,
                    "parameters": {str(c): v for c, v in sorted(values.items())},
                }
                for addr, values in sorted(overrides.items())
            },
        }
        write_atomically(self.state_file, json.dumps(data, indent=1) + "\n")


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
