"""Injectable faults of the simulated EPOS4 and its error history (1003h).

Pure. Codes, error register bits and reactions follow the EPOS4
Firmware Specification's error table (section 7.2 "Error codes"), as
transcribed in public EPOS4 code (the manual itself is not among our
sources): 0x8A80 negative limit switch, 0x8A81 positive limit switch, 0x8A82
software position limit, 0x8A88 STO, 0x8611 following error, 0x8130 CAN
heartbeat error (the heartbeat consumer, not a 2100h command); their names
are in :data:`epos_link.codes.DEVICE_ERRORS`. The table's
reaction column says what the drive does: "f" = the fault reaction of 605Eh
(default: quick stop ramp), "d" = disable the power stage at once.

Error register 1001h: bit 0 "generic" is set with every error (CiA 301
7.5.2.2), bit 7 is maxon's "motion error" (the table's error register
column), bit 4 "communication error" (CiA 301). 60FDh digital inputs: bit
0 negative limit switch, bit 1 positive limit switch, bit 2 home switch
(CiA 402-2 60FDh).

1003h "Pre-defined error field" (CiA 301 7.5.2.4): sub 0 is the number of
errors; writing 0 clears the history, any other value is refused with
0x06090030. Subs 1..:data:`HISTORY_DEPTH` hold the newest error first
(error code in the low 16 bits). The depth (8) is **chosen**, as the EDS declares it.

Simulator conveniences, decided here once: an injected fault is one-shot
(a fault reset always succeeds and clears 603Fh, 1001h and the 60FDh bits the
fault set); the history survives a fault reset but not a power cycle or NMT
reset node (it is not saved).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import Mapping, Protocol

from ..codes import describe_device_error

__all__ = [
    "BLOCK_COMMAND", "FAULTS", "FaultSpec", "HISTORY_DEPTH", "POWER_CYCLE_COMMAND", "RELEASE_COMMAND",
    "Reaction",
    "SIMULATOR_COMMANDS", "clear_history", "push_history",
]

HISTORY_DEPTH = 8
ERROR_HISTORY = 0x1003


class Reaction(Enum):
    """The reaction column of the EPOS4 error table."""

    FAULT_REACTION = "f"  # as 605Eh fault reaction option code says
    DISABLE = "d"  # power stage off at once


@dataclass(frozen=True)
class FaultSpec:
    """What an injected fault leaves in the dictionary until a fault reset."""

    error_code: int  # 603Fh
    error_register: int  # 1001h
    digital_inputs: int = 0  # 60FDh bits the fault sets
    reaction: Reaction = Reaction.FAULT_REACTION
    internal_limit: bool = False  # statusword bit 11 while the fault is present

    @property
    def name(self) -> str:
        """As in the EPOS4 error table (:data:`epos_link.codes.DEVICE_ERRORS`)."""
        return describe_device_error(self.error_code)


_GENERIC, _COMMUNICATION, _MOTION = 0x01, 0x10, 0x80

FAULTS: Mapping[str, FaultSpec] = MappingProxyType({
    "limit_negative": FaultSpec(0x8A80, _GENERIC | _MOTION, 0x1,
                                internal_limit=True),
    "limit_positive": FaultSpec(0x8A81, _GENERIC | _MOTION, 0x2,
                                internal_limit=True),
    "software_limit": FaultSpec(0x8A82, _GENERIC | _MOTION,
                                internal_limit=True),
    "sto": FaultSpec(0x8A88, _GENERIC, reaction=Reaction.DISABLE),
    "following_error": FaultSpec(0x8611, _GENERIC | _MOTION),
    # The heartbeat consumer's event with 6007h = 1 "fault signal" (CiA 402-2 6007h);
    # 1001h bit 4 "communication error" (CiA 301 7.5.2.2). epos_link.simulator.comm.
    "heartbeat": FaultSpec(0x8130, _GENERIC | _COMMUNICATION),
})

POWER_CYCLE_COMMAND = "power_cycle"
BLOCK_COMMAND = "block_axis"  # the load jams: 6064h stops, 6062h goes on (monitors.py)
RELEASE_COMMAND = "release_axis"

# Values of the write-only 2100h "Simulator command" (see epos4.eds). 1..3 keep
# their old meaning; 6 is not a fault but a power loss and return; 7/8 block and
# release the axis.
SIMULATOR_COMMANDS: Mapping[int, str] = MappingProxyType({
    1: "limit_positive", 2: "limit_negative", 3: "following_error",
    4: "software_limit", 5: "sto", 6: POWER_CYCLE_COMMAND, 7: BLOCK_COMMAND, 8: RELEASE_COMMAND,
})


class _Store(Protocol):
    def get_int(self, index: int, subindex: int = 0) -> int: ...

    def set(self, index: int, subindex: int, value: int) -> None: ...


def push_history(store: _Store, error_code: int) -> None:
    """Newest error into 1003h:01, older ones shift down, the oldest falls off."""
    count = store.get_int(ERROR_HISTORY, 0)
    for sub in range(min(count + 1, HISTORY_DEPTH), 1, -1):
        store.set(ERROR_HISTORY, sub, store.get_int(ERROR_HISTORY, sub - 1))
    store.set(ERROR_HISTORY, 1, error_code & 0xFFFF)
    store.set(ERROR_HISTORY, 0, min(count + 1, HISTORY_DEPTH))


def clear_history(store: _Store) -> None:
    for sub in range(1, HISTORY_DEPTH + 1):
        store.set(ERROR_HISTORY, sub, 0)
    store.set(ERROR_HISTORY, 0, 0)
