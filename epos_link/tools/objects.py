"""Names and types of objects, from an object dictionary (EDS or DCF).

The tools look objects up here by index or by name and decode or encode their
values by the type the dictionary gives them. The dictionary is parsed by
canopen's ``import_od`` (CiA 306 EDS/DCF; no parser of our own); by default it
is the EPOS4 EDS shipped with the simulator, or whatever ``--eds FILE`` names.

Policy:

* A name matches case-insensitively with any run of blanks and punctuation
  read as one ``_``: ``"Position actual value"``, ``position_actual_value``.
  A subentry is ``RECORD.SUB`` (``"Identity object.Serial number"``), or its
  own name when only one object has it. An ambiguous or unknown name raises
  :class:`ObjectLookupError` naming the candidates.
* An address is ``INDEX``, ``INDEX/SUB`` or ``INDEX:SUB`` (decimal or 0x-hex:
  ``0x6064``, ``0x1018/4``); :meth:`ObjectDirectory.locate` is the one parser of
  an OBJECT word for every command (``read``, ``write``, ``watch``, ``record``),
  so all of them accept the same forms. A word whose part before the ``/`` is not
  a number is a name (names may hold a ``/``).
* Types are the CiA 301 data types (CiA 301 7.1.6, Table 44) under short
  names (``u32``, ``i16``, ``str``...). An object that is not in the
  dictionary has no type: the caller decides (and says) what it falls back to.
* Values up to 4 bytes travel by ReadObject/WriteObject (guide 2.1.1.1,
  2.1.2.1), whose data field is always 4 bytes: decoders take the type's
  size from the front and ignore the padding.

Pure: no I/O beyond reading the dictionary file it is given.
"""
from __future__ import annotations

import argparse
import difflib
import math
import re
import struct
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Optional, Union

import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable, datatypes

from ..capture import CaptureFormatError, parse_hex
from ..errors import LocalProtocolError

Value = Union[int, float, bool, str, bytes]


class ObjectLookupError(LocalProtocolError, LookupError):
    """An object name or index that the dictionary does not have, or has twice,
    or a dictionary file that cannot be read: a usage error, nothing was sent."""


@dataclass(frozen=True)
class ValueType:
    """A CiA 301 data type: its short name, code, size in bytes (None: any length)."""

    name: str
    code: int
    size: Optional[int]
    kind: str  # "int", "float", "bool", "str", "bytes"
    signed: bool = False

    @property
    def small(self) -> bool:
        """Fits a ReadObject/WriteObject data field (4 bytes)."""
        return self.size is not None and self.size <= 4

    def decode(self, data: bytes) -> Value:
        """The value in ``data``; a ReadObject answer's padding is ignored."""
        if self.size is not None:
            if len(data) < self.size:
                raise LocalProtocolError(
                    f"{len(data)} bytes cannot hold a {self.name} ({self.size} bytes)")
            data = data[:self.size]
        if self.kind == "int":
            return int.from_bytes(data, "little", signed=self.signed)
        if self.kind == "bool":
            return bool(data[0])
        if self.kind == "float":
            return float(struct.unpack("<f" if self.size == 4 else "<d", data)[0])
        if self.kind == "str":
            if self.code == datatypes.UNICODE_STRING:
                return data.decode("utf-16-le", errors="replace").rstrip("\x00")
            # VISIBLE_STRING is ISO 646 (CiA 301 7.1.6.3); latin-1 never fails.
            return data.rstrip(b"\x00").decode("latin-1")
        return bytes(data)

    def encode(self, value: Value) -> bytes:
        if self.kind == "int":
            assert self.size is not None
            bits = 8 * self.size
            lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if self.signed else (0, (1 << bits) - 1)
            number = int(value)
            if not lo <= number <= hi:
                raise LocalProtocolError(f"{value!s} is out of range for {self.name} ({lo}..{hi})")
            return number.to_bytes(self.size, "little", signed=self.signed)
        if self.kind == "bool":
            return b"\x01" if value else b"\x00"
        if self.kind == "float":
            return struct.pack("<f" if self.size == 4 else "<d", float(value))
        if self.kind == "str":
            text = value.decode("latin-1") if isinstance(value, bytes) else str(value)
            if self.code == datatypes.UNICODE_STRING:
                return text.encode("utf-16-le")
            try:
                return text.encode("latin-1")
            except UnicodeEncodeError:
                raise LocalProtocolError(f"{text!r} has characters a VISIBLE_STRING cannot hold") from None
        return bytes(value) if isinstance(value, (bytes, bytearray)) else str(value).encode()

    def parse(self, text: str) -> Value:
        """A value typed on the command line: decimal or 0x-hex numbers, text, hex bytes."""
        if self.kind == "int":
            return _parse_number(text)
        if self.kind == "bool":
            low = text.strip().lower()
            if low in ("1", "true", "on", "yes"):
                return True
            if low in ("0", "false", "off", "no"):
                return False
            raise LocalProtocolError(f"{text!r} is not a boolean (0/1, true/false)")
        if self.kind == "float":
            try:
                number = float(text)
            except ValueError:
                raise LocalProtocolError(f"{text!r} is not a number") from None
            if not math.isfinite(number):
                raise LocalProtocolError(f"{text!r} is not a finite number")
            return number
        if self.kind == "str":
            return text
        try:
            return parse_hex(text)
        except CaptureFormatError as exc:
            raise LocalProtocolError(str(exc)) from None

    def format(self, value: Value) -> str:
        """The value for a person: integers with their hex, strings quoted."""
        if self.kind == "int":
            assert self.size is not None and isinstance(value, int)
            return f"{value} (0x{value & ((1 << 8 * self.size) - 1):0{2 * self.size}X})"
        if self.kind == "str":
            return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'
        if self.kind == "bytes":
            assert isinstance(value, bytes)
            return value.hex(" ").upper() if value else "(empty)"
        return str(value)


def _parse_number(text: str) -> int:
    t = text.strip().replace("_", "")
    negative = t.startswith("-")
    digits = t[1:] if negative else t
    try:
        value = int(digits[2:], 16) if digits[:2].lower() == "0x" else int(digits, 10)
    except ValueError:
        raise LocalProtocolError(f"{text!r} is not a decimal or 0x-hex number") from None
    return -value if negative else value


_TYPES = [
    ValueType("bool", datatypes.BOOLEAN, 1, "bool"),
    ValueType("i8", datatypes.INTEGER8, 1, "int", True),
    ValueType("i16", datatypes.INTEGER16, 2, "int", True),
    ValueType("i32", datatypes.INTEGER32, 4, "int", True),
    ValueType("i64", datatypes.INTEGER64, 8, "int", True),
    ValueType("u8", datatypes.UNSIGNED8, 1, "int"),
    ValueType("u16", datatypes.UNSIGNED16, 2, "int"),
    ValueType("u32", datatypes.UNSIGNED32, 4, "int"),
    ValueType("u64", datatypes.UNSIGNED64, 8, "int"),
    ValueType("f32", datatypes.REAL32, 4, "float"),
    ValueType("f64", datatypes.REAL64, 8, "float"),
    ValueType("str", datatypes.VISIBLE_STRING, None, "str"),
    ValueType("ustr", datatypes.UNICODE_STRING, None, "str"),
    ValueType("bytes", datatypes.OCTET_STRING, None, "bytes"),
    ValueType("domain", datatypes.DOMAIN, None, "bytes"),
]
TYPES: dict[str, ValueType] = {t.name: t for t in _TYPES}
TYPE_BY_CODE: dict[int, ValueType] = {t.code: t for t in _TYPES}
# The odd CiA 301 integer widths, decoded by size like the others.
for _code, _size, _signed in ((datatypes.INTEGER24, 3, True), (datatypes.UNSIGNED24, 3, False),
                              (datatypes.INTEGER40, 5, True), (datatypes.UNSIGNED40, 5, False),
                              (datatypes.INTEGER48, 6, True), (datatypes.UNSIGNED48, 6, False),
                              (datatypes.INTEGER56, 7, True), (datatypes.UNSIGNED56, 7, False)):
    TYPE_BY_CODE[_code] = ValueType(("i" if _signed else "u") + str(8 * _size), _code, _size, "int", _signed)
TYPE_NAMES = list(TYPES)


def type_named(name: str) -> ValueType:
    try:
        return TYPES[name]
    except KeyError:
        raise argparse.ArgumentTypeError(f"unknown type {name!r}: one of {', '.join(TYPES)}") from None


@dataclass(frozen=True)
class ObjectInfo:
    """One entry of the dictionary (a VAR, or one subentry of a RECORD/ARRAY)."""

    index: int
    subindex: int
    name: str
    type: Optional[ValueType]
    access: str  # "ro", "rw", "wo", "const", ... as the EDS says; "" when unknown

    @property
    def readable(self) -> bool:
        return not self.access or "r" in self.access or self.access == "const"

    @property
    def writable(self) -> bool:
        return not self.access or "w" in self.access

    @property
    def address(self) -> str:
        return f"0x{self.index:04X}/0x{self.subindex:02X}"


OBJECT_FORMS = ('name an object as the dictionary does ("Position actual value", '
                'position_actual_value, RECORD.SUB) or by INDEX or INDEX/SUBINDEX (0x6064, 0x1018/4)')
_ADDRESS = re.compile(r"\s*(-?(?:0[xX][0-9a-fA-F][0-9a-fA-F_]*|[0-9][0-9_]*))\s*(?:([/:])\s*(.*?))?\s*")


def parse_address(text: str) -> Optional[tuple[int, Optional[int]]]:
    """``INDEX``, ``INDEX/SUB`` or ``INDEX:SUB`` as numbers (SUB None when absent);
    None when ``text`` is not an address but a name. Out of range or a SUB that is
    not a number raises :class:`ObjectLookupError`."""
    m = _ADDRESS.fullmatch(text)
    if not m:
        return None
    index = _parse_number(m.group(1))
    if not 0 <= index <= 0xFFFF:
        raise ObjectLookupError(f"{text!r}: the index is not 0..0xFFFF")
    if m.group(2) is None:
        return index, None
    try:
        sub = _parse_number(m.group(3))
    except LocalProtocolError:
        raise ObjectLookupError(f"{text!r}: the subindex {m.group(3)!r} is not a decimal "
                                f"or 0x-hex number") from None
    if not 0 <= sub <= 0xFF:
        raise ObjectLookupError(f"{text!r}: the subindex is not 0..0xFF")
    return index, sub


def _norm(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def _info(var: ODVariable) -> ObjectInfo:
    name = var.name
    parent = var.parent
    if isinstance(parent, (ODRecord, ODArray)):
        name = f"{parent.name}.{var.name}"
    return ObjectInfo(var.index, var.subindex, name, TYPE_BY_CODE.get(var.data_type) if var.data_type is not None else None,
                      var.access_type or "")


class ObjectDirectory:
    """Index and name lookups over one object dictionary."""

    def __init__(self, od: ObjectDictionary, source: str = "") -> None:
        self.od = od
        self.source = source
        self._names: dict[str, list[tuple[int, Optional[int]]]] = {}
        for obj in od.values():
            if isinstance(obj, ODVariable):
                self._add(obj.name, obj.index, 0)
                continue
            self._add(obj.name, obj.index, None)
            for sub in obj.values():
                self._add(f"{obj.name}.{sub.name}", obj.index, sub.subindex)
                if sub.subindex:  # "Highest sub-index supported" is in every record
                    self._add(sub.name, obj.index, sub.subindex)

    def _add(self, name: str, index: int, subindex: Optional[int]) -> None:
        entries = self._names.setdefault(_norm(name), [])
        if (index, subindex) not in entries:
            entries.append((index, subindex))

    def variables(self) -> list[ObjectInfo]:
        """Every entry, in index and subindex order."""
        out = []
        for index in sorted(self.od.indices):
            obj = self.od[index]
            if isinstance(obj, ODVariable):
                out.append(_info(obj))
            else:
                out.extend(_info(obj[s]) for s in sorted(obj.subindices))
        return out

    def variable(self, index: int, subindex: int) -> Optional[ODVariable]:
        obj = self.od.get(index)
        if isinstance(obj, ODVariable):
            return obj if subindex == 0 else None  # a VAR has subindex 0 only (CiA 301 7.4.3)
        if isinstance(obj, (ODRecord, ODArray)):
            try:
                return obj.get(subindex)
            except (KeyError, TypeError):
                return None
        return None

    def find(self, index: int, subindex: int) -> Optional[ObjectInfo]:
        """The entry at index/subindex, or None when the dictionary lacks it."""
        var = self.variable(index, subindex)
        return _info(var) if var is not None else None

    def name_of(self, index: int, subindex: int) -> Optional[str]:
        info = self.find(index, subindex)
        return info.name if info else None

    def locate(self, text: str, subindex: Optional[int] = None) -> tuple[int, int, Optional[ObjectInfo]]:
        """An OBJECT word (an address or a name, module docstring) and a separate
        SUBINDEX, if any: ``(index, subindex, entry)``, the entry None when the
        dictionary lacks an addressed object (the caller says what it does then)."""
        address = parse_address(text)
        if address is None:
            info = self.resolve(text, subindex)
            return info.index, info.subindex, info
        index, sub = address
        if sub is not None and subindex is not None:
            raise ObjectLookupError(f"{text!r} names its subindex: give no SUBINDEX after it")
        sub = sub if sub is not None else (subindex if subindex is not None else 0)
        if not 0 <= sub <= 0xFF:
            raise ObjectLookupError(f"subindex {sub} is not 0..0xFF")
        return index, sub, self.find(index, sub)

    def resolve(self, name: str, subindex: Optional[int] = None) -> ObjectInfo:
        """The entry called ``name`` (``subindex`` picks one of a record's)."""
        hits = self._names.get(_norm(name), [])
        if len(hits) > 1:
            where = ", ".join(f"0x{i:04X}" + (f"/0x{s:02X}" if s is not None else "") for i, s in hits)
            raise ObjectLookupError(f"{name!r} names several objects ({where}): use RECORD.SUB or the index")
        if not hits:
            close = difflib.get_close_matches(_norm(name), list(self._names), n=3, cutoff=0.6)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise ObjectLookupError(f"no object named {name!r} in {self.source or 'the dictionary'}"
                                    f"{hint} ({OBJECT_FORMS})")
        index, sub = hits[0]
        if sub is None:
            obj = self.od[index]
            if subindex is None and isinstance(obj, (ODRecord, ODArray)):
                subs = ", ".join(f"{s}={obj[s].name!r}" for s in sorted(obj.subindices))
                raise ObjectLookupError(f"{obj.name!r} (0x{index:04X}) has subentries: give a SUBINDEX ({subs})")
            sub = subindex if subindex is not None else 0  # a VAR is its own subindex 0
        elif subindex is not None and subindex != sub:
            raise ObjectLookupError(f"{name!r} is subindex {sub}, not {subindex}")
        info = self.find(index, sub)
        if info is None:
            raise ObjectLookupError(f"0x{index:04X} has no subindex {sub} in {self.source or 'the dictionary'}")
        return info


STATUSWORD = 0x6041


def meaning(index: int, subindex: int, value: Value) -> Optional[str]:
    """What a value means beyond its number, where the profile says: the CiA 402
    state and flags of a statusword (CiA 402-2 6.4.1.4). Every tool that shows
    a value (read, monitor, decode) adds this, so a statusword never stands raw."""
    if index == STATUSWORD and subindex == 0 and isinstance(value, int):
        from ..cia402 import describe_statusword

        return describe_statusword(value)
    return None


def default_eds() -> Path:
    """The EPOS4 EDS shipped in the package (the simulator's object dictionary)."""
    from importlib import resources

    return Path(str(resources.files("epos_link.simulator") / "epos4.eds"))


@lru_cache(maxsize=4)
def _load(path: str, node_id: int) -> ObjectDirectory:
    try:
        od = canopen.import_od(path, node_id)
    except FileNotFoundError:
        raise ObjectLookupError(f"object dictionary {path}: no such file") from None
    except Exception as exc:  # canopen raises many kinds on a bad file
        raise ObjectLookupError(f"object dictionary {path}: cannot parse it ({type(exc).__name__}: {exc})") from None
    return ObjectDirectory(od, Path(path).name)


def load_directory(path: Optional[str] = None, node_id: int = 1) -> ObjectDirectory:
    """The directory of ``path`` (an EDS or DCF), by default the shipped EPOS4 EDS.
    ``$NODEID`` in the file becomes ``node_id``."""
    return _load(str(path or default_eds()), node_id)


__all__ = ["OBJECT_FORMS", "ObjectDirectory", "ObjectInfo", "ObjectLookupError", "TYPES", "TYPE_BY_CODE", "TYPE_NAMES",
           "ValueType", "default_eds", "load_directory", "meaning", "parse_address", "type_named"]
