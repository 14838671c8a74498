"""One row of the status page: what one axis's reads answered, decoded for a person.

Pure (no I/O, no clock): :mod:`tcp_bridge.status.sampler` passes in the reply values
(the text after ``=`` of an ACK, exactly what a client reads) or the error that a
read raised, and gets a JSON-ready dict.

Decoding, with the sources:

* CiA 402 state from the statusword (R10): CiA 402-2 6.4.1.4, table of the
  statusword's state bits (:func:`epos_link.cia402.state_from_statusword`);
* mode from 6061h modes of operation display (R15): CiA 402-2 6.3.1, codes 1 pp,
  3 pv, 6 hm, 8 csp, 9 csv, 10 cst (maxon EPOS4 Firmware Specification,
  "Modes of operation");
* error bits (R11, spec 4.b "Interpreting Detailed Error Register"): bit names as
  the PSI specification's table gives them; bits 0 and 14 have no name there.

**The condition** (issue 34: a status page that says why): each row has a
``condition`` ``{"kind", "text", "reason"}`` for its state cell, worst first:

==============  =====================================================================
kind            when (this sample)
==============  =====================================================================
``no bus``      the bus's device or adapter cannot be opened (``cannot open ...``)
``bus silent``  the bus's device does not answer (the whole bus is refused at once,
                :mod:`tcp_bridge.bus.health`)
``silent``      this node does not answer: declared silent, or its SDO timed out
                (abort 0x05040000, CiA 301 7.2.4.3.17)
``error``       any other failed read (an SDO abort, a value that does not fit)
``fault``       the statusword says FAULT (CiA 402-2 6.4.1.4); the reason is the
                R11 error bits by name
``ok``          none of these: the text is the CiA 402 state
==============  =====================================================================

The reason is said once, even when every read of the sample failed for it; the
numbers that differ between reads ("silent for 10.1 s", "10.2 s") do not make it
two. "target reached" (R82) is shown only where it means something: in
OPERATION ENABLED (CiA 402-2 6.4.1.4: bit 10 is about the target of a running
mode); a disabled axis at rest has no target (``None``), not "no".
"""
from __future__ import annotations

import re
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Dict, Final, List, Mapping, Optional, Tuple

from epos_link.cia402 import state_from_statusword

if TYPE_CHECKING:
    from ..tables.axes import AxisConfig

# Spec 4.b: Detailed Error Register (R11), bit -> description.
ERROR_BITS: Final[Mapping[int, str]] = MappingProxyType({
    15: "STO fault", 13: "under-voltage", 12: "over-voltage", 11: "over temperature",
    10: "over-current", 9: "negative software limit", 8: "positive software limit",
    7: "negative limit switch", 6: "positive limit switch", 5: "feedback error",
    4: "communication error", 3: "following error", 2: "encoder error", 1: "short circuit",
})

# CiA 402-2 6.3.1: modes of operation (display), 6061h.
MODES: Final[Mapping[int, str]] = MappingProxyType({
    1: "profile position", 3: "profile velocity", 6: "homing",
    8: "cyclic sync position", 9: "cyclic sync velocity", 10: "cyclic sync torque",
})


def error_names(bits: int) -> List[str]:
    """The spec 4.b names of the bits set in ``bits``, highest bit first."""
    return [ERROR_BITS.get(b, f"bit {b}") for b in range(15, -1, -1) if bits >> b & 1]


def state_name(statusword: int) -> str:
    state = state_from_statusword(statusword)
    return "unknown" if state is None else state.name.lower().replace("_", " ")


def mode_name(mode: int) -> str:
    return MODES.get(mode, f"mode {mode}")


SDO_TIMED_OUT: Final = 0x05040000  # CiA 301 7.2.4.3.17, "SDO protocol timed out"
# The words of tcp_bridge.bus.health's refusals: "bus can1: device silent for 1.2 s (why);
# answered at once, ..." and "bus can1: node 5 silent for ...".
_REFUSAL = re.compile(r"^bus (?P<bus>\S+): (?P<link>device|node \d+) silent for [\d.]+ s "
                      r"\((?P<why>.*)\); answered at once")
_NUMBERS = re.compile(r"\d+(\.\d+)?")


def failure_kind(exc: BaseException) -> Tuple[str, str]:
    """(kind, reason) of a failed read: ``no bus``, ``bus silent``, ``silent`` or ``error``
    (module docstring). The reason is said without the bus's name twice."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    m = _REFUSAL.match(text)
    if m is not None:
        why = m.group("why")
        if m.group("link") == "device":
            if why.startswith("cannot open"):
                return "no bus", f"bus {m.group('bus')}: {why}"
            return "bus silent", f"bus {m.group('bus')}: its device does not answer ({why})"
        return "silent", f"{m.group('link')} on bus {m.group('bus')} does not answer ({why})"
    if getattr(exc, "code", None) == SDO_TIMED_OUT:
        return "silent", text
    return "error", text


_RANK: Final = {"no bus": 0, "bus silent": 1, "silent": 2, "error": 3}


def condition(state: Optional[str], failures: Mapping[int, BaseException],
              error_bits: Optional[List[str]]) -> Dict[str, str]:
    """The state cell: ``{"kind", "text", "reason"}`` (module docstring)."""
    found: Dict[str, Tuple[str, str]] = {}  # the reason without numbers -> (kind, reason)
    for cmd in sorted(failures):
        kind, reason = failure_kind(failures[cmd])
        found.setdefault(_NUMBERS.sub("#", reason), (kind, reason))
    if found:
        worst = min(found.values(), key=lambda kr: _RANK[kr[0]])
        reasons = [worst[1]] + [r for k, r in found.values() if r != worst[1]]
        text = worst[0] if state is None else f"{state}; {worst[0]}"
        return {"kind": worst[0], "text": text, "reason": "; ".join(reasons)}
    if state == "fault":
        why = ", ".join(error_bits) if error_bits else "see R11 (not read yet) and 603Fh"
        return {"kind": "fault", "text": "fault", "reason": why}
    return {"kind": "ok", "text": state or "", "reason": ""}


def _int(text: Optional[str]) -> Optional[int]:
    try:
        return None if text is None else int(text, 0)
    except ValueError:
        return None


def _float(text: Optional[str]) -> Optional[float]:
    try:
        return None if text is None else float(text)
    except ValueError:
        return None


def row(config: "AxisConfig", values: Mapping[int, Optional[str]], *, t: float,
        errors: Mapping[int, BaseException], last_error: Optional[Mapping[str, Any]],
        has_drive: bool = True) -> Dict[str, Any]:
    """The JSON object of one axis (see docs/bridge.md, "A live status page").

    ``values``: reply text by command number (None: not read this sample, or it
    failed); ``errors``: the failures of this sample by command number;
    ``last_error``: the newest failure not yet followed by an answer to its command
    ({"t", "cmd", "error"}) or None.
    """
    statusword = _int(values.get(10)) if 10 not in errors else None
    state = None if statusword is None else state_name(statusword)
    mode = _int(values.get(15))
    bits = _int(values.get(11))
    reached = _int(values.get(82))
    names = None if bits is None else error_names(bits)
    return {
        "addr": config.addr,
        "bus": config.bus,
        "node": config.node_id,
        "has_drive": has_drive,
        "t": t,
        "statusword": statusword,
        "state": state,
        "condition": condition(state, errors, names) if has_drive
        else {"kind": "ok", "text": "no drive", "reason": ""},
        "mode": mode,
        "mode_name": None if mode is None else mode_name(mode),
        "position": _float(values.get(12)),
        "velocity": _float(values.get(14)),
        "target_reached": None if reached is None or state != "operation enabled"
        else bool(reached),
        "error_bits": bits,
        "errors": names,
        "moving_ack": _int(values.get(86)),
        "failed": {str(cmd): failure_kind(exc)[1] for cmd, exc in sorted(errors.items())},
        "last_error": None if last_error is None else dict(last_error),
    }
