"""Where each mapped object sits in an EtherCAT slave's process data. Pure: no I/O.

A CoE slave's process data is the concatenation, in order, of the PDOs assigned
to its sync managers: 1C12h lists the RxPDOs (master -> slave, the outputs),
1C13h the TxPDOs (slave -> master, the inputs); each PDO (1600h.., 1A00h..) lists
its entries as ``index << 16 | subindex << 8 | bit length`` (ETG.1000.6 5.6.7.4
"Sync Manager PDO Assignment", CiA 301 7.5.2.36 / 7.5.2.38 PDO mapping, which
CoE takes over). SOEM builds the slave's I/O map from the same objects
(``ecx_readPDOmap``), so offsets counted here from the slave's own objects match
``slave.input`` / ``slave.output`` byte for byte; :func:`layout_problem` checks
the totals against the sizes SOEM found before a layout is trusted.

An entry of index 0 is padding (a gap of its bit length: CiA 301 7.4.8.2
"dummy mapping"). Only byte-aligned entries of 8, 16 or 32 bits are offered
as objects; others (bits of a digital-input word) are counted, not offered.

**Chosen** (the EPOS4 Firmware Specification's default mapping is not quoted
here): the backend never writes a mapping, it reads the one the slave has, the
maxon defaults or whatever EPOS Studio (or a simulator) configured, so the
bridge and the slave cannot disagree about it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

Key = Tuple[int, int]  # (index, subindex)
Upload = Callable[[int, int], bytes]  # an SDO upload of the slave

RXPDO_ASSIGN = 0x1C12  # SM2, outputs
TXPDO_ASSIGN = 0x1C13  # SM3, inputs


@dataclass(frozen=True)
class Entry:
    """One mapped object: ``offset`` and ``size`` in bytes within its image."""

    index: int
    subindex: int
    offset: int
    size: int


@dataclass(frozen=True)
class Layout:
    """The mapped objects of one slave's outputs (RxPDOs) and inputs (TxPDOs)."""

    outputs: Dict[Key, Entry]
    inputs: Dict[Key, Entry]
    output_bytes: int
    input_bytes: int


def entries(words: Sequence[int]) -> Tuple[Dict[Key, Entry], int]:
    """The objects of a concatenation of mapping entries, and the total size in bytes."""
    found: Dict[Key, Entry] = {}
    bit = 0
    for word in words:
        index, subindex, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        if index != 0 and bit % 8 == 0 and bits in (8, 16, 32):
            found.setdefault((index, subindex), Entry(index, subindex, bit // 8, bits // 8))
        bit += bits
    return found, (bit + 7) // 8


def _u(data: bytes) -> int:
    return int.from_bytes(bytes(data), "little")


def read_assignment(upload: Upload, assign: int) -> List[int]:
    """The mapping words of every PDO assigned in ``assign`` (1C12h or 1C13h), in order."""
    words: List[int] = []
    for position in range(1, _u(upload(assign, 0)[:1]) + 1):
        pdo = _u(upload(assign, position)[:2])
        for entry in range(1, _u(upload(pdo, 0)[:1]) + 1):
            words.append(_u(upload(pdo, entry)[:4]))
    return words


def read_layout(upload: Upload) -> Layout:
    """The slave's layout, from its assignment and mapping objects (by SDO)."""
    outputs, output_bytes = entries(read_assignment(upload, RXPDO_ASSIGN))
    inputs, input_bytes = entries(read_assignment(upload, TXPDO_ASSIGN))
    return Layout(outputs, inputs, output_bytes, input_bytes)


def layout_problem(layout: Layout, output_bytes: int, input_bytes: int) -> Optional[str]:
    """Why ``layout`` does not describe an image of these sizes (None: it does)."""
    if (layout.output_bytes, layout.input_bytes) != (output_bytes, input_bytes):
        return (f"its PDO mapping makes {layout.output_bytes} output and {layout.input_bytes} "
                f"input bytes, the process data has {output_bytes} and {input_bytes}")
    return None


def get(image: "bytes | bytearray", entry: Entry, signed: bool) -> int:
    return int.from_bytes(bytes(image[entry.offset:entry.offset + entry.size]), "little",
                          signed=signed)


def put(image: bytearray, entry: Entry, data: bytes) -> None:
    """Store ``data`` (exactly ``entry.size`` bytes) at the entry's place."""
    if len(data) != entry.size:
        raise ValueError(f"0x{entry.index:04X}/{entry.subindex} is {entry.size} bytes, "
                         f"not {len(data)}")
    image[entry.offset:entry.offset + entry.size] = data
