"""The per-axis parameter arrays (spec 3, 4) and the state file that keeps them.

Spec 3: "the axis parameters are stored in an array", one per axis, in stored
form (integers; the ``*`` parameters of spec 4 as ``round(user * factor)``).
The arrays start from the axis table (:mod:`tcp_bridge.tables.axes`: defaults and
TOML values). Parameters changed with S commands are kept in a JSON state
file, written atomically (temporary file, fsync, rename) after every change
and overlaid on the table at start, as the controller keeps them across
restarts. Only S-command values go to the file, so later edits of the TOML
take effect for the rest.

The file is written by one background thread (:class:`StateFileWriter`), never
by the caller: a bus worker that stores a parameter must not wait for an
fsync. Snapshots that pile up while a write is in progress are batched, the
newest wins; :meth:`ParameterStore.close` (called by the engine at shutdown)
writes the last one. The engine holds a write's ACK until the write holding
its change is on disk (:meth:`ParameterStore.written`; the guarantee is in
:mod:`tcp_bridge.tables.statefile`). Temporary files a killed bridge left are
removed at start.

The state file is checked at start-up: one that cannot be written (its
directory cannot be created, no rights, not a regular file) is refused with
:class:`~tcp_bridge.tables.axes.ConfigError`, and so is a damaged one (not
UTF-8, not JSON, not our format, or a value its parameter cannot hold: each is
checked as the same value in an S command is), with one line that names the
file and says to move it away. One that becomes unwritable later (disk
full, directory gone) does not undo the change and does not turn the reply into NAK: the value is
in the arrays, and for a drive parameter in the drive, so the command *was*
executed (spec 2.2.2: NAK means not executed). The failure is logged at
ERROR with the file's name every time; the next successful write persists
the whole snapshot, so nothing is lost once the file is writable again.
"""
from __future__ import annotations

import json
import logging
import threading
from decimal import Decimal
from pathlib import Path
from typing import Dict, Final, Optional, Tuple

from .axes import (DEFAULTS, PARAMETER_NAMES, AxisTable, ConfigError, DeviceCode, from_stored,
                   parameter_spec, to_stored)
from .commands import COMMANDS
from .statefile import (StateFileWriter, check_writable, remove_stale_temporaries,
                        write_atomically)
from .units import Number, Scaling, parse_value
from ..errors import InvalidCommand

log = logging.getLogger(__name__)
_DEVICE_CODES: Final = {int(code): code for code in DeviceCode}


class ParameterStore:
    """The per-axis parameter arrays: TOML values overlaid with the state file.

    Thread-safe: bus worker threads read and write it. Values are in stored
    form (integers); :meth:`user` converts. Only values set by S commands go
    to the state file, so later edits of the TOML take effect for the rest.
    """

    FORMAT: Final = "tcp-bridge-state"
    VERSION: Final = 1

    def __init__(self, table: AxisTable, state_file: Optional[Path] = None, *,
                 read_only: bool = False) -> None:
        self.table = table
        self.state_file = state_file if state_file is not None else table.settings.state_file
        self._lock = threading.Lock()  # the arrays; held briefly (the event loop reads too)
        self._version = 0  # of the arrays' S-command values
        self._base: Dict[int, Dict[int, int]] = {}
        for addr, axis in table.axes.items():
            values = {19: int(axis.device)}
            for cmd, default in DEFAULTS.items():
                user = axis.parameters.get(cmd, default)
                if user is not None:
                    values[cmd] = to_stored(COMMANDS[cmd], user, axis.position_factor)
            self._base[addr] = values
        self._overrides: Dict[int, Dict[int, int]] = {addr: {} for addr in table.axes}
        self._writer: Optional[StateFileWriter] = None
        if self.state_file is not None:
            try:
                check_writable(self.state_file)  # at start-up, not at the first S command
            except OSError as exc:
                raise ConfigError(f"{table.source}: [bridge] state_file: {self.state_file} "
                                  f"cannot be written ({exc.strerror or exc})") from None
            if read_only:  # a tool beside a running bridge: its temporaries are not stale
                self._load()
                return
            remove_stale_temporaries(self.state_file)
            self._load()
            self._writer = StateFileWriter(self._save, str(self.state_file))

    # -- access ---------------------------------------------------------------

    def get(self, addr: int, cmd: int) -> Optional[int]:
        """The stored value of parameter ``cmd`` of axis ``addr``, None if unset."""
        with self._lock:
            value = self._overrides[addr].get(cmd)
            return self._base[addr].get(cmd) if value is None else value

    def values(self, addr: int, cmds: Tuple[int, ...]) -> Tuple[Optional[int], ...]:
        """:meth:`get` of several parameters at one instant (one lock)."""
        with self._lock:
            overrides, base = self._overrides[addr], self._base[addr]
            return tuple(base.get(c) if overrides.get(c) is None else overrides[c] for c in cmds)

    def user(self, addr: int, cmd: int) -> Optional[Number]:
        stored = self.get(addr, cmd)
        if stored is None:
            return None
        return from_stored(COMMANDS[cmd], stored, self.table.axes[addr].position_factor)

    def set(self, addr: int, cmd: int, stored: int) -> None:
        """Store a value set by an S command; the state file follows in the background."""
        with self._lock:
            self._overrides[addr][cmd] = int(stored)
            self._version += 1
            version = self._version
            snapshot = {a: dict(v) for a, v in self._overrides.items() if v}
        if self._writer is not None:
            self._writer.submit(version, snapshot)

    @property
    def version(self) -> int:
        """How many S-command values were stored so far (each :meth:`set` adds one)."""
        with self._lock:
            return self._version

    async def written(self, version: int, timeout: float) -> bool:
        """Wait (on the event loop) until the state file write that holds change
        ``version`` has ended: on disk, or failed and logged. True at once without
        a state file; False if it has not ended after ``timeout`` seconds."""
        if self._writer is None:
            return True
        return await self._writer.written(version, timeout)

    def flush(self, timeout: Optional[float] = None) -> bool:
        """Wait until every value set so far was written (or failed); False on timeout."""
        return self._writer.flush(timeout) if self._writer is not None else True

    def close(self, timeout: float = 10.0) -> None:
        """Write the last snapshot and stop the writer thread."""
        if self._writer is not None:
            self._writer.close(timeout)

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
        return _DEVICE_CODES.get(self.get(addr, 19), DeviceCode.C_DC_NOT_DEFINED)  # type: ignore[arg-type]

    def snapshot(self, addr: int) -> Dict[int, int]:
        with self._lock:
            return {**self._base[addr], **self._overrides[addr]}

    # -- state file -------------------------------------------------------------

    def _load(self) -> None:
        assert self.state_file is not None
        try:
            raw = self.state_file.read_bytes()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise ConfigError(f"cannot read state file {self.state_file}: {exc}") from None
        try:
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise ValueError(f"not UTF-8 text: byte 0x{raw[exc.start]:02X} at offset "
                                 f"{exc.start}") from None
            try:
                data = json.loads(text)
            except RecursionError:  # json nests by recursion: "[[[[..." too deep for it
                raise ValueError("nested too deeply to be a state file") from None
            if not isinstance(data, dict):
                raise ValueError("not a tcp-bridge state file of version 1")
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
                    if cmd not in PARAMETER_NAMES or isinstance(value, bool) \
                            or not isinstance(value, int):
                        raise ValueError(f"bad entry {cmd_key}={value!r} for axis {addr}")
                    problem = _stored_problem(cmd, value, axis.position_factor)
                    if problem:
                        raise ValueError(f"axis {addr} parameter {cmd_key}={value}: {problem}")
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


def _stored_problem(cmd: int, stored: int, factor: int) -> str:
    """Why ``stored`` cannot be parameter ``cmd`` of an axis with ``factor`` ("": it can).

    A value in the state file is checked as the same value in an S command or
    in the axis table is (:func:`~tcp_bridge.tables.units.parse_value`, then
    the scaled range): the file is ours, but it may have been edited or damaged,
    and an unchecked value surfaces only later, as a NAK or a CAN without a log line.
    """
    spec = parameter_spec(cmd)
    try:
        user = from_stored(spec, stored, factor)
        text = str(user) if isinstance(user, int) else format(Decimal(repr(user)), "f")
        if to_stored(spec, parse_value(spec, text), factor) != stored:
            return "not a value this parameter can hold"
    except InvalidCommand as exc:
        return str(exc)
    return ""
