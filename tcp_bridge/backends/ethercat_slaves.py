"""What an EtherCAT slave offers the bridge: Complete Access, and the CiA 402 objects. Pure.

Independent slave stacks differ from the EPOS4 in small ways (issue 31), and the
bridge must start on them, saying in one line what it cannot do.

**Complete Access.** SOEM reads a slave's PDO assignment (1C00h, 1C12h/1C13h and
the mapping objects) with SDO Complete Access when the slave's SII offers it
(CoE details bit 5, ETG.2010 Table 4; SOEM ``ecx_map_coe_soe``: ``CoEdetails &
ECT_COEDET_SDOCA``), and reads the answer into structures whose 8-bit subindex 0
is followed by a padding byte (SOEM ``ec_PDOassignt``: ``uint8 n; uint8 nu1;
uint16 index[]``; ETG.1000.6 5.6.2.2: subindex 0 is transferred as 16 bits). A
slave that leaves the padding byte out makes ``config_map`` misread the
assignment and report an SDO, mailbox or packet error (``ConfigMapError``), or map
an image of the wrong size. The backend then configures once more with CA
turned off for every slave (pysoem ``_disable_complete_access``, as SOEM users do
for Elmo drives); its own transfers never use CA. :func:`ca_problem` says, for
``tcp-bridge check`` (read only, no ``config_map``), whether a slave's CA answer
is one that SOEM would misread.

**Objects.** :data:`MANDATORY` lists what an axis cannot do without an object
(one line each, naming slave, object and what it disables); :data:`OPTIONAL`
lists the objects CiA 402-2 leaves optional, with the default the bridge uses
instead. The position window 6067h is optional for CSP: R82 of a cyclic axis on
a slave without it uses the axis table's ``position_window`` (increments,
:data:`tcp_bridge.tables.axes.DEFAULT_POSITION_WINDOW`).
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Tuple

Upload = Callable[[int, int], bytes]

ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
COE_DETAILS_CA = 0x20  # ETG.2010 Table 4 CoE details bit 5, SOEM ECT_COEDET_SDOCA
CATEGORY_GENERAL = 30  # ETG.2010 Table 3
SII_CATEGORIES = 0x40  # the first category's word address (ETG.1000.6 Table 16)

MANDATORY: Dict[Tuple[int, int], str] = {
    (0x6040, 0): "controlword: the axis cannot be enabled (S04) or moved",
    (0x6041, 0): "statusword: no state (R10), no enable (S04), no move",
    (0x6060, 0): "modes of operation: no mode change (S07, CSP/CSV moves)",
    (0x6061, 0): "modes of operation display: no mode change (S07, R15)",
    (0x6064, 0): "position actual value: no position (R12), no position move",
    (0x607A, 0): "target position: no position move (S00=1/2, S90)",
    (0x60FF, 0): "target velocity: no velocity move (S00=3)",
}
OPTIONAL: Dict[Tuple[int, int], str] = {
    (0x6067, 0): "position window: R82 of a cyclic axis uses the axis table's "
                 "position_window instead; R13 is NAK",
    (0x607D, 1): "software position limits: none are checked by the drive; S23/S24 are NAK",
    (0x6085, 0): "quick stop deceleration: the drive's own quick stop ramp; S28 is NAK",
    (0x606C, 0): "velocity actual value: R14 is NAK; a CSV move starts from 0",
    (0x6065, 0): "following error window: S62 is NAK",
    (0x60FD, 0): "digital inputs: R11 shows no limit switch, R50 is NAK",
}


def missing_objects(upload: Upload, aborted: Callable[[BaseException], Optional[int]]
                    ) -> List[Tuple[Tuple[int, int], bool, str]]:
    """(object, mandatory, what it disables) for each object the slave answers with
    "object does not exist" (CiA 301 abort 06020000h / 06090011h). ``aborted(exc)``
    gives an exception's abort code, None for any other failure (not counted)."""
    out = []
    for table, mandatory in ((MANDATORY, True), (OPTIONAL, False)):
        for key, what in table.items():
            try:
                upload(*key)
            except Exception as exc:
                if aborted(exc) in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
                    out.append((key, mandatory, what))
    return out


def missing_line(position: int, key: Tuple[int, int], mandatory: bool, what: str) -> str:
    """One line for one missing object."""
    index, sub = key
    name = f"{index:04X}h" + (f"/{sub}" if sub else "")
    kind = "mandatory" if mandatory else "optional"
    return f"slave {position}: no {name} ({kind}): {what}"


def expected_ca(upload: Upload, index: int) -> bytes:
    """What a complete access upload of ``index`` from subindex 0 must answer, from
    plain uploads: subindex 0 padded to 16 bits, then subindices 1..n (module doc)."""
    count = bytes(upload(index, 0))[:1]
    out = bytearray(count + b"\0")
    for sub in range(1, (count[0] if count else 0) + 1):
        out += bytes(upload(index, sub))
    return bytes(out)


def ca_problem(answer: bytes, expected: bytes) -> Optional[str]:
    """Why a complete access answer is one SOEM would misread, or None if it is right."""
    answer = bytes(answer)
    if answer == expected:
        return None
    if expected and answer == expected[:1] + expected[2:]:
        return (f"it answers Complete Access without the padding byte after subindex 0 "
                f"({len(answer)} bytes, {len(expected)} expected)")
    return f"its Complete Access answer differs ({answer.hex()} for {expected.hex()})"


def sii_coe_details(read_word: Callable[[int], int], limit: int = 512) -> Optional[int]:
    """The CoE details byte of the SII's general category (ETG.2010 Table 4: byte 5
    of the category's data), or None if the SII has none. ``read_word(address)``
    reads one 16-bit word; the walk stops at 0xFFFF or after ``limit`` words."""
    address = SII_CATEGORIES
    while address < SII_CATEGORIES + limit:
        kind = read_word(address)
        if kind == 0xFFFF:
            return None
        size = read_word(address + 1)
        if kind == CATEGORY_GENERAL:
            return (read_word(address + 2 + 2) >> 8) & 0xFF  # data bytes 4 and 5
        address += 2 + size
    return None
