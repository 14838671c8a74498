"""The simulated EPOS4's object dictionary and a data store with CiA 301 access rules.

The dictionary itself comes from the shipped ``epos4.eds`` through canopen's
``import_od`` (no hand parser). :class:`ObjectStore` keeps the values and
serves SDO-like access, raising ``canopen.SdoAbortedError(code)`` with the
exact CiA 301 abort code (CiA 301 V4.2 7.2.4.3.17, Table 22; EPOS4
Communication Guide chapter 6, Table 6-21). It is shared by two front ends:

* the serial-side simulator calls :meth:`ObjectStore.read` and
  :meth:`ObjectStore.write` with raw bytes by index and subindex;
* a ``canopen.LocalNode`` is wired to the same store with
  :func:`attach_local_node` (or built by :func:`make_local_node`).

Order of the checks, first failure wins::

    index not in the dictionary                   0602 0000  object does not exist
    subindex not in the object (VAR: subindex!=0) 0609 0011  subindex error
    read of a write-only object                   0601 0001  write only error
    write to a read-only or const object          0601 0002  read only error
    write whose length does not fit (see below)   0607 0010  service parameter error
    value outside LowLimit..HighLimit of the EDS  0609 0030  value range error
    a hook's own refusal (e.g. 1010h not "save")  whatever the hook raises

Write lengths, decided once here and relied on by the gateway simulator: a
write of exactly the type's size is accepted. A 4-byte write to a smaller
integer type is accepted when the surplus bytes are zero padding, or, for a
signed type holding a negative value, 0xFF sign extension; this is what an
EPOS4 WriteObject (always 4 data bytes) and a CANopen expedited download
without size indication carry. Every other length aborts with 0607 0010.
Strings and domains take any length.

The store is pure: it has no clock and no locks. Live objects (statusword,
actual position, ...) are served by read hooks; objects with side effects
(controlword, modes of operation, ...) by write hooks, both registered by the
drive model (:mod:`epos_link.simulator.drive`). ``before_access``, when set,
runs before every checked access so a drive can catch up with a clock.
Callers that use the store from several threads must serialise access.

Store and restore parameters (1010h "save", 1011h "load", reset to the saved
values) live in :mod:`epos_link.simulator.store_restore`, whose
:class:`~epos_link.simulator.store_restore.SavedParameters` the store is
built on; its names are re-exported here.
"""
from __future__ import annotations

import functools
import os
import pickle
import struct
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import Union

import canopen
from canopen import SdoAbortedError
from canopen.objectdictionary import (
    ObjectDictionary,
    ODArray,
    ODRecord,
    ODVariable,
    datatypes,
)

from .store_restore import (
    ABORT_STORE,
    LOAD_SIGNATURE,
    NOT_SAVED,
    SAVE_SIGNATURE,
    SavedParameters,
    key_text,
)

__all__ = [
    "EDS_PATH",
    "SAVE_SIGNATURE",
    "LOAD_SIGNATURE",
    "NOT_SAVED",
    "ObjectStore",
    "SdoAbortedError",
    "Value",
    "attach_local_node",
    "load_object_dictionary",
    "make_local_node",
    # Also from store_restore (with the three signatures/sets above), importable here as before.
    "ABORT_STORE",
    "key_text",
]

Value = Union[int, float, str, bytes]


def _value(decoded: Union[Value, bytearray]) -> Value:
    """canopen decodes DOMAIN/OCTET_STRING to a bytearray; a Value is immutable."""
    return bytes(decoded) if isinstance(decoded, bytearray) else decoded
ReadHook = Callable[[], Value]
WriteHook = Callable[[Value], None]

# CiA 301 abort codes used here (Table 22; guide Table 6-21).
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_RANGE = 0x06090030
# ABORT_STORE (08000020h), for a refused "save"/"load", is in store_restore.

EDS_PATH: Path = Path(str(resources.files("epos_link.simulator") / "epos4.eds"))

_INT_SIZES = {
    datatypes.INTEGER8: 1, datatypes.INTEGER16: 2, datatypes.INTEGER32: 4,
    datatypes.UNSIGNED8: 1, datatypes.UNSIGNED16: 2, datatypes.UNSIGNED32: 4,
    datatypes.BOOLEAN: 1,
}


def load_object_dictionary(node_id: int = 1, path: Union[str, Path] = EDS_PATH) -> ObjectDictionary:
    """Parse the shipped EDS (or ``path``) with canopen; ``$NODEID`` becomes ``node_id``.

    Each call returns a dictionary of its own (a simulated drive changes its
    defaults), but the file is parsed once per process, node id and version of the
    file: a copy of the parsed dictionary costs 1 ms, a parse 15 ms, and a simulator
    builds one per drive (issue 32: the test suite builds thousands)."""
    stat = os.stat(path)
    return pickle.loads(_parsed(str(path), node_id, path == EDS_PATH, stat.st_mtime_ns,
                                stat.st_size))


@functools.lru_cache(maxsize=64)
def _parsed(path: str, node_id: int, shipped: bool, _mtime_ns: int, _size: int) -> bytes:
    od = canopen.import_od(path, node_id)
    od.node_id = node_id  # import_eds sets it only from a [DeviceComissioning] section
    add_value_descriptions(od)
    _own_serial_number(od, node_id)
    if shipped:
        from .data_recorder import add_recorder_objects  # the XDD's 31E0h-31E9h, not in the EDS

        add_recorder_objects(od)
    return pickle.dumps(od)


# Serial numbers of simulated units: this base plus the node id. A real unit's
# 1018h/04 is unique (CiA 301 V4.2, object 1018h "identity"), so tools that tell drives apart by
# their identity (tcp-bridge check, epos-link scan) must see them differ; the
# name (1008h) is the product name, "EPOS4" on every unit, as on real ones.
SIMULATED_SERIAL_BASE = 0x5E000000


def _own_serial_number(od: ObjectDictionary, node_id: int) -> None:
    identity = od.get(0x1018)
    if not isinstance(identity, (ODRecord, ODArray)) or 4 not in identity.subindices:
        return  # an EDS without the serial number sub-entry
    serial = identity[4]
    serial.default = SIMULATED_SERIAL_BASE + node_id


# CiA 306 EDS files have no place for value descriptions; canopen's ``.desc``
# needs them, so the CiA 402 ones are added here (CiA 402 6060h, 605Ah).
VALUE_DESCRIPTIONS: dict[int, dict[int, str]] = {
    0x6060: {1: "Profile Position Mode", 3: "Profile Velocity Mode", 6: "Homing Mode",
             8: "Cyclic Synchronous Position Mode", 9: "Cyclic Synchronous Velocity Mode"},
    0x6061: {1: "Profile Position Mode", 3: "Profile Velocity Mode", 6: "Homing Mode",
             8: "Cyclic Synchronous Position Mode", 9: "Cyclic Synchronous Velocity Mode"},
    0x605A: {0: "Disable drive function", 1: "Slow down on slow down ramp",
             2: "Slow down on quick stop ramp", 5: "Slow down on slow down ramp and stay",
             6: "Slow down on quick stop ramp and stay"},
}


def add_value_descriptions(od: ObjectDictionary) -> None:
    for index, texts in VALUE_DESCRIPTIONS.items():
        if index in od:
            var = od[index]
            if isinstance(var, ODVariable):
                for value, text in texts.items():
                    var.add_value_description(value, text)


def _type_size(var: ODVariable) -> int | None:
    """Size in bytes of a fixed-size type, None for strings and domains."""
    if var.data_type in datatypes.DATA_TYPES:
        return None
    return len(var) // 8


class ObjectStore(SavedParameters):
    """Values of one object dictionary, with CiA 301 SDO access rules.

    ``read``/``write`` are the checked, byte-level SDO view. ``get``/``set``
    are the unchecked, typed view for the drive model itself (it may set
    read-only objects such as 1001h). ``read_value``/``write_value`` are the
    checked view with typed values, handy in tests and tools. ``saved``,
    ``on_save``, ``snapshot``, ``load_saved`` and ``reset`` (1010h/1011h)
    come from :class:`~epos_link.simulator.store_restore.SavedParameters`.
    """

    def __init__(self, od: ObjectDictionary) -> None:
        self.od = od
        self._defaults: dict[tuple[int, int], Value] = {}
        for var in self._variables():
            self._defaults[(var.index, var.subindex)] = self._default_of(var)
        self._values: dict[tuple[int, int], Value] = dict(self._defaults)
        self._read_hooks: dict[tuple[int, int], ReadHook] = {}
        self._write_hooks: dict[tuple[int, int], WriteHook] = {}
        self.before_access: Callable[[], None] | None = None
        self._install_store_objects()  # saved, on_save; 1010h/1011h (store_restore)

    # -- dictionary lookups ---------------------------------------------------

    def _variables(self) -> Iterator[ODVariable]:
        for obj in self.od.values():
            if isinstance(obj, ODVariable):
                yield obj
            else:
                yield from (obj[sub] for sub in obj)

    @staticmethod
    def _default_of(var: ODVariable) -> Value:
        if var.value is not None:
            return var.value
        if var.default is not None:
            return var.default
        if var.data_type in (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING):
            return ""
        if var.data_type in datatypes.DATA_TYPES:
            return b""
        if var.data_type in datatypes.FLOAT_TYPES:
            return 0.0
        return 0

    def variable(self, index: int, subindex: int) -> ODVariable:
        """The dictionary entry, or SdoAbortedError 06020000h / 06090011h."""
        if index not in self.od:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            # A simple variable has only subindex 0 (guide 3.3.1).
            if subindex != 0:
                raise SdoAbortedError(ABORT_NO_SUBINDEX)
            return obj
        assert isinstance(obj, (ODArray, ODRecord))
        if subindex not in obj.subindices:
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        return obj.subindices[subindex]

    # -- hooks ------------------------------------------------------------------

    def add_read_hook(self, index: int, subindex: int, hook: ReadHook) -> None:
        """Serve reads of an entry from ``hook()`` (a typed value) instead of the store."""
        self.variable(index, subindex)
        self._read_hooks[(index, subindex)] = hook

    def add_write_hook(self, index: int, subindex: int, hook: WriteHook) -> None:
        """Call ``hook(value)`` on every checked write, after the generic checks.

        The hook may raise SdoAbortedError; the value is stored only if it returns.
        """
        self.variable(index, subindex)
        self._write_hooks[(index, subindex)] = hook

    # -- unchecked typed access (for the drive model) ---------------------------

    def get(self, index: int, subindex: int = 0) -> Value:
        """Current value, from a read hook if there is one. No access checks."""
        key = (index, subindex)
        hook = self._read_hooks.get(key)
        if hook is not None:
            return hook()
        try:
            return self._values[key]
        except KeyError:
            self.variable(index, subindex)  # raises the right abort
            raise

    def get_int(self, index: int, subindex: int = 0) -> int:
        value = self.get(index, subindex)
        if not isinstance(value, int):
            raise TypeError(f"0x{index:04X}:{subindex:02X} is not an integer object")
        return value

    def set(self, index: int, subindex: int, value: Value) -> None:
        """Store a value without access checks or hooks (for read-only outputs)."""
        self.variable(index, subindex)
        self._values[(index, subindex)] = value

    # -- checked byte-level access (the SDO view) --------------------------------

    def read(self, index: int, subindex: int) -> bytes:
        """SDO upload: the entry's bytes, exactly the type's size (strings: their length)."""
        var = self.variable(index, subindex)
        if not var.readable:
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        if self.before_access is not None:
            self.before_access()
        return self._encode(var, self.get(index, subindex))

    def write(self, index: int, subindex: int, data: bytes) -> None:
        """SDO download of raw bytes, with the length rules of the module docstring."""
        var = self.variable(index, subindex)
        if not var.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        value = self._decode_write(var, bytes(data))
        self._check_range(var, value)
        if self.before_access is not None:
            self.before_access()
        hook = self._write_hooks.get((index, subindex))
        if hook is not None:
            hook(value)
        self._values[(index, subindex)] = value

    def read_value(self, index: int, subindex: int = 0) -> Value:
        """Checked read, decoded to a Python value."""
        var = self.variable(index, subindex)
        return _value(var.decode_raw(self.read(index, subindex)))

    def write_value(self, index: int, subindex: int, value: Value) -> None:
        """Checked write of a Python value, encoded at the type's exact size."""
        var = self.variable(index, subindex)
        if not var.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        self.write(index, subindex, self._encode(var, value))

    # -- encoding -----------------------------------------------------------------

    @staticmethod
    def _encode(var: ODVariable, value: Value) -> bytes:
        try:
            return var.encode_raw(value)
        except (struct.error, ValueError, TypeError) as exc:
            # A value that does not fit its type is out of range (CiA 301 06090030h).
            raise SdoAbortedError(ABORT_RANGE) from exc

    @staticmethod
    def fit_length(var: ODVariable, data: bytes) -> bytes:
        """``data`` cut to the type's size under the padding rule, else abort 06070010h.

        Exact size: unchanged. 4 bytes for a 1- or 2-byte integer: the surplus
        must be zeros, or 0xFF sign extension of a negative signed value.
        Strings and domains: unchanged, any length.
        """
        size = _type_size(var)
        if size is None or len(data) == size:
            return data
        if len(data) == 4 and size < 4 and var.data_type in _INT_SIZES:
            head, surplus = data[:size], data[size:]
            if surplus == bytes(len(surplus)):
                return head
            signed = var.data_type in datatypes.SIGNED_TYPES
            if signed and surplus == b"\xff" * len(surplus) and head[-1] & 0x80:
                return head
        raise SdoAbortedError(ABORT_LENGTH)

    @classmethod
    def _decode_write(cls, var: ODVariable, data: bytes) -> Value:
        return _value(var.decode_raw(cls.fit_length(var, data)))

    @staticmethod
    def _check_range(var: ODVariable, value: Value) -> None:
        if not isinstance(value, (int, float)):
            return
        if var.min is not None and value < var.min:
            raise SdoAbortedError(ABORT_RANGE)
        if var.max is not None and value > var.max:
            raise SdoAbortedError(ABORT_RANGE)


def attach_local_node(node: canopen.LocalNode, store: ObjectStore) -> None:
    """Serve every SDO access of ``node`` from ``store`` (same abort codes).

    Uses ``add_read_callback``/``add_write_callback``: LocalNode calls read
    callbacks first and re-encodes the returned value, so the read callback
    returns the decoded value; the write callback raises SdoAbortedError to
    refuse. ``store`` should hold ``node.object_dictionary`` (or an equal one).

    One more step is needed: ``LocalNode.set_data`` rejects any length other
    than a number type's exact size (06070010h) *before* the callbacks run,
    which would refuse an expedited download with the size not indicated (4
    bytes, CiA 301 7.2.4.3.3) to a U8/U16 object, the frame an EPOS4 gateway
    sends for WriteObject. So the node's ``set_data`` is wrapped, on this
    instance only, to apply :meth:`ObjectStore.fit_length` first, after the
    object-exists and read-only checks so the abort codes keep their order.
    """

    def on_read(index: int, subindex: int, od: ODVariable, **_: object) -> Value:
        return _value(od.decode_raw(store.read(index, subindex)))

    def on_write(index: int, subindex: int, od: ODVariable, data: bytes, **_: object) -> None:
        store.write(index, subindex, bytes(data))

    node.add_read_callback(on_read)
    node.add_write_callback(on_write)

    original_set_data = node.set_data

    def set_data(index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        var = store.variable(index, subindex)
        if not var.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        original_set_data(index, subindex, store.fit_length(var, bytes(data)), check_writable)

    node.set_data = set_data  # type: ignore[method-assign]


def make_local_node(store: ObjectStore, node_id: int | None = None) -> canopen.LocalNode:
    """A LocalNode over the store's own dictionary, wired with :func:`attach_local_node`."""
    nid = node_id if node_id is not None else (store.od.node_id or 1)
    node = canopen.LocalNode(nid, store.od)
    attach_local_node(node, store)
    return node
