"""Store and restore parameters (1010h, 1011h) of the simulated EPOS4's object store.

CiA 301 V4.2 7.5.2.13 "Store parameters" and 7.5.2.14 "Restore default
parameters", subindex 1 ("all parameters") of each. :class:`SavedParameters` is
mixed into :class:`~epos_link.simulator.od.ObjectStore`; it is pure (no
clock, no files, no locks), like the store:

* A read of 1010h/01 or 1011h/01 gives 1 (bit 0: the device saves, or
  restores, parameters on command).
* Writing the signature "save" (:data:`SAVE_SIGNATURE`) to 1010h/01 keeps a
  snapshot of every writable entry outside :data:`NOT_SAVED` in
  ``saved``; any other value aborts with 0800 0020 ("data cannot be
  transferred or stored", CiA 301 Table 22).
* Writing "load" (:data:`LOAD_SIGNATURE`) to 1011h/01 forgets the snapshot;
  the defaults become effective after the next reset, not at once
  (7.5.2.14). Any other value aborts with 0800 0020.
* ``on_save``, when set, gets a copy of ``saved`` after either command, so a
  simulator can persist it; :meth:`SavedParameters.load_saved` adopts such a
  copy again, like a power-up.
* :meth:`SavedParameters.reset` (NMT reset node) puts every value
  back to its EDS default overlaid with the saved parameters.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING

from canopen import SdoAbortedError
from canopen.objectdictionary import ObjectDictionary, ODVariable

if TYPE_CHECKING:  # od imports this module at run time; Value is only a type here
    from .od import ReadHook, Value, WriteHook

__all__ = ["ABORT_STORE", "LOAD_SIGNATURE", "NOT_SAVED", "SAVE_SIGNATURE", "SavedParameters",
           "key_text"]

# CiA 301 Table 22 (guide Table 6-21): data cannot be transferred or stored to the application.
ABORT_STORE = 0x08000020

# CiA 301 7.5.2.13 / 7.5.2.14: "save" and "load" in ISO 8859 as UNSIGNED32, little endian.
SAVE_SIGNATURE = 0x65766173
LOAD_SIGNATURE = 0x64616F6C

# Writable entries that are commands, process data or the error history rather than parameters,
# so "Save all parameters" leaves them out (indices, every subindex).
NOT_SAVED: frozenset[int] = frozenset({0x1003, 0x1010, 0x1011, 0x2100, 0x6040, 0x607A, 0x60FF})


def key_text(index: int, subindex: int) -> str:
    """The snapshot key of an entry, e.g. ``"0x6081:00"``."""
    return f"0x{index:04X}:{subindex:02X}"


class SavedParameters:
    """The store-and-restore half of :class:`~epos_link.simulator.od.ObjectStore`."""

    # Provided by ObjectStore, the class this is mixed into.
    od: ObjectDictionary
    _defaults: dict[tuple[int, int], Value]
    _values: dict[tuple[int, int], Value]

    if TYPE_CHECKING:
        def _variables(self) -> Iterator[ODVariable]: ...

        def add_read_hook(self, index: int, subindex: int, hook: ReadHook) -> None: ...

        def add_write_hook(self, index: int, subindex: int, hook: WriteHook) -> None: ...

    def _install_store_objects(self) -> None:
        """Nothing saved yet; serve 1010h/01 and 1011h/01 where the dictionary has them."""
        # Parameters kept by the last "save" (keys as key_text); reset() restores them.
        self.saved: dict[str, Value] = {}
        # Called with a copy of ``saved`` after "save" or "load" so a simulator can persist it.
        self.on_save: Callable[[dict[str, Value]], None] | None = None
        for index, handler in ((0x1010, self._on_save), (0x1011, self._on_load)):
            if index in self.od and 1 in getattr(self.od[index], "subindices", {}):
                # Read: bit 0 = 1, "the device saves parameters on command".
                self.add_read_hook(index, 1, lambda: 1)
                self.add_write_hook(index, 1, handler)

    def snapshot(self) -> dict[str, Value]:
        """The current parameters: writable entries outside :data:`NOT_SAVED`."""
        out: dict[str, Value] = {}
        for var in self._variables():
            if var.writable and var.index not in NOT_SAVED:
                out[key_text(var.index, var.subindex)] = self._values[(var.index, var.subindex)]
        return out

    def _on_save(self, value: Value) -> None:
        if value != SAVE_SIGNATURE:
            raise SdoAbortedError(ABORT_STORE)
        self.saved = self.snapshot()
        if self.on_save is not None:
            self.on_save(dict(self.saved))

    def _on_load(self, value: Value) -> None:
        # CiA 301 7.5.2.14: defaults become effective after the next reset.
        if value != LOAD_SIGNATURE:
            raise SdoAbortedError(ABORT_STORE)
        self.saved = {}
        if self.on_save is not None:
            self.on_save({})

    def load_saved(self, saved: Mapping[str, Value]) -> None:
        """Adopt a snapshot (e.g. read back from disk) and apply it, like a power-up.

        Keys that are unknown, not writable or in :data:`NOT_SAVED` are ignored,
        so a snapshot from an older EDS still loads.
        """
        self.saved = {k: v for k, v in saved.items() if k in self._saveable_keys()}
        self.reset()

    def _saveable_keys(self) -> "frozenset[str]":
        return frozenset(key_text(v.index, v.subindex) for v in self._variables()
                         if v.writable and v.index not in NOT_SAVED)

    def reset(self) -> None:
        """Values back to EDS defaults overlaid with the saved parameters (NMT reset node)."""
        self._values = dict(self._defaults)
        for var in self._variables():
            key = key_text(var.index, var.subindex)
            if key in self.saved:
                self._values[(var.index, var.subindex)] = self.saved[key]
