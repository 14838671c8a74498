"""The output image of an EtherCAT slave never takes its drive up by itself: the drive decides.

On CAN the bridge writes 6040h by SDO: each write is one command, given once. On
EtherCAT the controlword is process data: the value in the output image goes out
again every cycle, and whatever a new master puts there first is a command.
CiA 402-2 6.4.1 defines the device control commands by the controlword's value,
not by its change (fault reset, bit 7, is the one edge); whether the EPOS4 acts
again on a repeated, unchanged value is in no public maxon source, so the bridge
assumes it does (**chosen**, the safe reading; the simulated slave does so,
:mod:`epos_link.simulator.ethercat.slave`). A stale "enable operation" is then
transition 16 out of QUICK STOP ACTIVE (605Ah = 5..8; the EPOS4's default is 6),
or transition 4 out of SWITCHED ON; with it an old 607Ah in CSP is a jump
(issue 31: a new bridge after a crash, a slave back from SAFE-OP after a stall
or a cable pull).

So an output object of a slave is either **commanded** (the bridge wrote it for a
client: :meth:`ControlwordHold.commanded`) or **follows the drive**: every cycle,
right after the inputs of that cycle came in and before the next outputs go
out (:meth:`ControlwordHold.check`, :mod:`.ethercat_cycle` rule 2), each
following object is set from what the drive shows now:

* 6040h controlword: the command that keeps the state the statusword shows
  (CiA 402-2 6.4.1, with halt): OPERATION ENABLED enable operation (0x010F: no
  motion, see below), QUICK STOP ACTIVE quick stop (0x0102, no transition out),
  SWITCHED ON switch on (0x0107), READY TO SWITCH ON shutdown (0x0106), any
  other state disable voltage (0x0100, no fault reset edge). It never raises
  the state;
* 607Ah target position = 6064h position actual value, 60FFh target velocity = 0,
  6060h modes of operation = 6061h display (when the slave maps them): entering
  OP or being enabled later moves nothing and changes no mode.

Every object of a slave follows the drive when the backend opens (a new bridge
never sends the dead one's command), when the slave dropped out of OP (the
recovery asks for OP only with an image that follows the drive,
:mod:`.ethercat_cycle` rule 3), and when a drive left OPERATION ENABLED by itself
while its controlword said "enable operation" (a quick stop input, a fault,
another tool): once the drive showed OPERATION ENABLED under the commanded
"enable operation" and its statusword then shows any other state. A write of
the bridge (a client's S04=1 and the writes of its moves) makes that object
commanded again; the enable sequence starts from the state the drive is in.
"""
from __future__ import annotations

import logging
from typing import Any, Dict, Mapping, Optional, Set, Tuple

from epos_link.cia402 import State

from ..cia402_words import Cw, decode_state
from . import ethercat_pdo as pdo

log = logging.getLogger("tcp_bridge.backends.ethercat")
Key = Tuple[int, int]

CONTROLWORD, STATUSWORD = (0x6040, 0), (0x6041, 0)
_COMMAND_BITS = 0x008F  # bits 0..3 and 7: the device control command (CiA 402-2 6.4.1.2)
_ENABLE_OPERATION = 0x000F
_HOLD: Mapping[State, int] = {
    State.OPERATION_ENABLED: 0x000F,  # enable operation: stays, halted, set-point = actual
    State.QUICK_STOP_ACTIVE: 0x0002,  # quick stop: no transition out of QUICK STOP ACTIVE
    State.SWITCHED_ON: 0x0007,  # switch on
    State.READY_TO_SWITCH_ON: 0x0006,  # shutdown
}
_DISABLE_VOLTAGE = 0x0000
TARGET_POSITION, POSITION_ACTUAL = (0x607A, 0), (0x6064, 0)
TARGET_VELOCITY = (0x60FF, 0)
MODES, MODES_DISPLAY = (0x6060, 0), (0x6061, 0)
FOLLOWING = (CONTROLWORD, TARGET_POSITION, TARGET_VELOCITY, MODES)
# The input each output follows (60FFh is 0, the controlword comes from 6041h).
FOLLOWS = {CONTROLWORD: STATUSWORD, TARGET_POSITION: POSITION_ACTUAL, MODES: MODES_DISPLAY}


def hold_command(state: State) -> int:
    """The controlword that keeps a drive in ``state`` (with halt set)."""
    return int(_HOLD.get(state, _DISABLE_VOLTAGE) | Cw.HALT)


class ControlwordHold:
    """The rule of the module docstring, for every slave of one master.

    Called under the cycle's lock (:mod:`.ethercat_cycle`): :meth:`check` by the
    cycle, :meth:`commanded` by the node's writes, :meth:`follow` by the recovery."""

    def __init__(self, cycle: Any, layouts: Mapping[int, Optional[pdo.Layout]]) -> None:
        self.cycle = cycle
        self.layouts = {p: layout for p, layout in layouts.items()
                        if layout is not None and CONTROLWORD in layout.outputs
                        and STATUSWORD in layout.inputs}
        self.entries = {p: (layout.outputs[CONTROLWORD], layout.inputs[STATUSWORD])
                        for p, layout in self.layouts.items()}
        self._established: Dict[int, bool] = {}
        self._following: Dict[int, Set[Key]] = {}
        self._shown: Dict[int, State] = {}  # the state last logged, per following slave
        self._why: Dict[int, str] = {}  # why it follows its drive (for the log)
        for position in self.layouts:
            self.follow(position, "the bridge starts")

    def follow(self, position: int, why: str) -> None:
        """Every output object of ``position`` follows its drive from the next check."""
        layout = self.layouts.get(position)
        if layout is None:
            return
        self._following[position] = {k for k in FOLLOWING if k in layout.outputs}
        self._established[position] = False
        self._shown.pop(position, None)
        self._why[position] = why

    def commanded(self, position: int, key: Key = CONTROLWORD) -> None:
        """The bridge wrote ``key`` of ``position`` into the image: it goes out as written
        (a controlword counts as established once the drive shows OPERATION ENABLED)."""
        following = self._following.get(position)
        if following is not None:
            following.discard(key)
        if key == CONTROLWORD:
            self._established[position] = False

    def holding(self, position: int) -> bool:
        """The slave's controlword follows its drive (no client has taken it up since)."""
        return CONTROLWORD in self._following.get(position, ())

    def check(self, _cycle: int) -> None:
        """After each cycle's inputs came in, before the next outputs go out."""
        for position, layout in self.layouts.items():
            image, inputs = self.cycle.outputs[position], self.cycle.inputs[position]
            cw_entry, sw_entry = self.entries[position]
            state = decode_state(pdo.get(inputs, sw_entry, False))
            following = self._following.get(position, set())
            if following:
                self._follow(position, layout, image, inputs, state, following)
            if CONTROLWORD in following:
                continue
            cw = pdo.get(image, cw_entry, False)
            if cw & _COMMAND_BITS != _ENABLE_OPERATION:
                self._established[position] = False
                continue
            if state is State.OPERATION_ENABLED:
                self._established[position] = True
            elif self._established.get(position):
                self.follow(position, "left OPERATION ENABLED by itself")
                self._follow(position, layout, image, inputs, state, self._following[position])
                log.warning("ethercat: slave %d left OPERATION ENABLED by itself (now %s); "
                            "its outputs hold it there (controlword 0x%04X, set-point = actual "
                            "position) until a client enables it (S04=1)", position, state.name,
                            hold_command(state))
                self._shown[position] = state

    def _follow(self, position: int, layout: pdo.Layout, image: bytearray, inputs: bytes,
                state: State, following: Set[Key]) -> None:
        if CONTROLWORD in following:
            held = hold_command(state)
            entry = layout.outputs[CONTROLWORD]
            pdo.put(image, entry, held.to_bytes(entry.size, "little"))
            if self._shown.get(position) is not state:
                self._shown[position] = state
                log.info("ethercat: slave %d shows %s: its controlword is 0x%04X (%s), its "
                         "set-point its actual position, until a client enables it (S04=1)",
                         position, state.name, held, self._why.get(position, ""))
        for target, source in ((TARGET_POSITION, POSITION_ACTUAL), (MODES, MODES_DISPLAY)):
            if target in following and source in layout.inputs:
                value = bytes(inputs[layout.inputs[source].offset:][:layout.inputs[source].size])
                entry = layout.outputs[target]
                if target == MODES and not any(value):
                    continue  # mode display 0: no mode yet, the image keeps its own
                pdo.put(image, entry, value[:entry.size].ljust(entry.size, b"\0"))
        if TARGET_VELOCITY in following:
            entry = layout.outputs[TARGET_VELOCITY]
            pdo.put(image, entry, bytes(entry.size))
