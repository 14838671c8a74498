"""The controlword in an EtherCAT output image never takes a drive back up by itself.

On CAN the bridge writes 6040h by SDO: each write is one command, given once. On
EtherCAT the controlword is process data: the value the bridge last wrote
(:meth:`~tcp_bridge.backends.ethercat_node.EthercatNode.download` puts 6040h into
the output image) goes out again every cycle. CiA 402-2 6.4.1 defines the device
control commands by the controlword's value, not by its change (fault reset,
bit 7, is the one edge); whether the EPOS4 acts again on a repeated, unchanged
value is in no public maxon source, so the bridge assumes it does (**chosen**,
the safe reading). Then, once a drive has left OPERATION ENABLED on its own (a
quick stop input, its 6007h reaction to a lost connection, a fault reset by
another tool), a stale "enable operation" in the image is a command: from QUICK
STOP ACTIVE with 605Ah = 5..8 (the EPOS4's default is 6) it is transition 16
back to OPERATION ENABLED, where CSP would jump to the last set-point; from
SWITCHED ON it is transition 4. That would raise an axis's state without a
client asking (motion rule 1's mirror image).

So a cycle hook (:meth:`ControlwordHold.check`, before the outputs go out), for
each slave that maps 6040h out and 6041h in: once the drive showed OPERATION
ENABLED under the image's "enable operation", and its statusword later shows any
other state while the image still says "enable operation", the image's
controlword becomes the command that keeps that state (CiA 402-2 6.4.1, with
halt): QUICK STOP ACTIVE quick stop (0x0002), SWITCHED ON switch on (0x0007),
READY TO SWITCH ON shutdown (0x0006), any other state disable voltage (0x0000,
no fault reset edge). The next 6040h the bridge writes (a client's S04=1, whose
enable sequence starts from the state the drive is in) replaces it as usual.
"""
from __future__ import annotations

import logging
from typing import Any, Dict, Mapping, Optional

from epos_link.cia402 import State

from ..cia402_words import Cw, decode_state
from . import ethercat_pdo as pdo

log = logging.getLogger("tcp_bridge.backends.ethercat")

CONTROLWORD, STATUSWORD = (0x6040, 0), (0x6041, 0)
_COMMAND_BITS = 0x008F  # bits 0..3 and 7: the device control command (CiA 402-2 6.4.1.2)
_ENABLE_OPERATION = 0x000F
_HOLD: Mapping[State, int] = {
    State.QUICK_STOP_ACTIVE: 0x0002,  # quick stop: no transition out of QUICK STOP ACTIVE
    State.SWITCHED_ON: 0x0007,  # switch on
    State.READY_TO_SWITCH_ON: 0x0006,  # shutdown
}
_DISABLE_VOLTAGE = 0x0000


def hold_command(state: State) -> int:
    """The controlword that keeps a drive in ``state`` (with halt set)."""
    return int(_HOLD.get(state, _DISABLE_VOLTAGE) | Cw.HALT)


class ControlwordHold:
    """The rule of the module docstring, for every slave of one master."""

    def __init__(self, cycle: Any, layouts: Mapping[int, Optional[pdo.Layout]]) -> None:
        self.cycle = cycle
        self.entries = {p: (layout.outputs[CONTROLWORD], layout.inputs[STATUSWORD])
                        for p, layout in layouts.items()
                        if layout is not None and CONTROLWORD in layout.outputs
                        and STATUSWORD in layout.inputs}
        self._established: Dict[int, bool] = {}

    def commanded(self, position: int) -> None:
        """The bridge wrote 6040h of ``position`` (under the cycle lock): it goes out as
        written, and counts as established once the drive shows OPERATION ENABLED."""
        self._established[position] = False

    def check(self, _cycle: int) -> None:
        """The cycle hook (run under the cycle lock, before the outputs are sent)."""
        for position, (cw_entry, sw_entry) in self.entries.items():
            image = self.cycle.outputs[position]
            cw = pdo.get(image, cw_entry, False)
            if cw & _COMMAND_BITS != _ENABLE_OPERATION:
                self._established[position] = False
                continue
            state = decode_state(pdo.get(self.cycle.inputs[position], sw_entry, False))
            if state is State.OPERATION_ENABLED:
                self._established[position] = True
            elif self._established.get(position):
                held = hold_command(state)
                pdo.put(image, cw_entry, held.to_bytes(cw_entry.size, "little"))
                self._established[position] = False
                log.warning("ethercat: slave %d left OPERATION ENABLED by itself (now %s); "
                            "its controlword is 0x%04X from now on, not enable operation, "
                            "until a client enables it (S04=1)", position, state.name, held)
