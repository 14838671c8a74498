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
"""
from __future__ import annotations

from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Dict, Final, List, Mapping, Optional

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
        errors: Mapping[int, str], last_error: Optional[Mapping[str, Any]],
        has_drive: bool = True) -> Dict[str, Any]:
    """The JSON object of one axis (see docs/bridge.md, "A live status page").

    ``values``: reply text by command number (None: not read this sample, or it
    failed); ``errors``: the failures of this sample by command number;
    ``last_error``: the newest failure of any sample ({"t", "cmd", "error"}) or None.
    """
    statusword = _int(values.get(10))
    mode = _int(values.get(15))
    bits = _int(values.get(11))
    reached = _int(values.get(82))
    return {
        "addr": config.addr,
        "bus": config.bus,
        "node": config.node_id,
        "has_drive": has_drive,
        "t": t,
        "statusword": statusword,
        "state": None if statusword is None else state_name(statusword),
        "mode": mode,
        "mode_name": None if mode is None else mode_name(mode),
        "position": _float(values.get(12)),
        "velocity": _float(values.get(14)),
        "target_reached": None if reached is None else bool(reached),
        "error_bits": bits,
        "errors": None if bits is None else error_names(bits),
        "moving_ack": _int(values.get(86)),
        "failed": {str(cmd): why for cmd, why in sorted(errors.items())},
        "last_error": None if last_error is None else dict(last_error),
    }
