"""What makes one simulated slave differ from a plain EPOS4: the ``--quirk`` options. Pure.

``epos-link sim --ethercat IFACE --slaves N --quirk POSITION:NAME[=VALUE] ...``

Real slave stacks differ from the manuals in small ways, and a master must cope
with them (issue 31). Each quirk names the slave by its position (1 = first):

``no-ca``
    the SII does not offer SDO Complete Access (CoE details bit 5 clear,
    ETG.2010 Table 4), so SOEM reads the PDO assignment object by object.
``ca-no-pad``
    the slave offers Complete Access (as the EPOS4 does, guide Table 4-16) but
    answers it without the padding byte after subindex 0 (:mod:`.coe`), as an
    independent slave stack did in issue 31: SOEM's ``config_map`` misreads the
    PDO assignment and reports a mailbox or packet error.
``no-6067`` (any ``no-XXXX``, hexadecimal index)
    the dictionary has no such object: every access aborts with 0x06020000
    "object does not exist" (CiA 301 Table 22). 6067h (position window) is
    optional for CSP in CiA 402-2, and so are 607Dh, 6085h and others.
``late=SECONDS``
    the answer to a CoE download of 1010h (store parameters) or 1011h (restore
    default parameters) comes that many seconds late; meanwhile the process
    data runs on. The EPOS4 writes its parameters to flash for such a request
    (issue 31 saw seconds); the mailbox holds the answer until it is done.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, FrozenSet, Iterable

__all__ = ["Quirks", "QuirkError", "parse_quirks", "SLOW_OBJECTS"]

SLOW_OBJECTS = frozenset({0x1010, 0x1011})


class QuirkError(ValueError):
    """A ``--quirk`` that cannot be understood (the CLI prints it in one line)."""


@dataclass(frozen=True)
class Quirks:
    offer_ca: bool = True
    ca_padding: bool = True
    missing: FrozenSet[int] = field(default_factory=frozenset)
    late: float = 0.0


def _one(quirks: Quirks, name: str) -> Quirks:
    if name == "no-ca":
        return replace(quirks, offer_ca=False)
    if name == "ca-no-pad":
        return replace(quirks, offer_ca=True, ca_padding=False)
    if name.startswith("late="):
        try:
            seconds = float(name[5:])
        except ValueError:
            raise QuirkError(f"late= takes seconds, not {name[5:]!r}") from None
        if not 0 <= seconds <= 60:
            raise QuirkError(f"late= must be 0..60 s, not {seconds:g}")
        return replace(quirks, late=seconds)
    if name.startswith("no-"):
        try:
            index = int(name[3:], 16)
        except ValueError:
            raise QuirkError(f"{name!r}: no- takes a hexadecimal object index (no-6067)") from None
        if not 0x1000 <= index <= 0xFFFF or index in (0x6040, 0x6041):
            raise QuirkError(f"{name!r}: not an object a drive can lack (0x1000..0xFFFF, not "
                             "the controlword or statusword)")
        return replace(quirks, missing=quirks.missing | {index})
    raise QuirkError(f"unknown quirk {name!r} (no-ca, ca-no-pad, no-XXXX, late=SECONDS)")


def parse_quirks(specs: Iterable[str], slaves: int) -> Dict[int, Quirks]:
    """``["2:ca-no-pad", "2:no-6067"]`` -> {2: Quirks(...)}; QuirkError says what is wrong."""
    out: Dict[int, Quirks] = {}
    for spec in specs:
        position, sep, name = spec.partition(":")
        if not sep or not position.strip().isdigit():
            raise QuirkError(f"--quirk {spec!r}: write POSITION:NAME, e.g. 2:ca-no-pad")
        slave = int(position)
        if not 1 <= slave <= slaves:
            raise QuirkError(f"--quirk {spec!r}: there is no slave {slave} (1..{slaves})")
        out[slave] = _one(out.get(slave, Quirks()), name.strip())
    return out
