"""A node that another master put in NMT Stopped: how a stop or a reset still reaches it.

In NMT Stopped a node "will be forced to stop PDO and SDO communication"; it
answers NMT (and LSS, heartbeat) only (EPOS4 Communication Guide 3.3.3.5,
Table 3-13; CiA 301 7.3.2.2.1). Its drive function is not touched: a velocity
move goes on. So every SDO the bridge sends it is lost: behind the EPOS4's
gateway as abort 0x05040000 "SDO protocol timed out" (guide chapter 5), on a
CAN bus as no response at all. Without help a stop (S00=8, S90=0, the halts
the bridge sends itself) and a client's reset (S16=1) would answer NAK and
leave the axis moving.

The policy, for stops and S16 only (:meth:`Cia402.halt`, :meth:`Cia402.reset_node`):

1. The first read of the statusword fails because *the node* is silent
   (:func:`tcp_bridge.bus.sdo.silence_of` says :attr:`Silence.NODE`; when the
   bus's device itself is silent, no NMT command would go out either).
2. The bridge cannot tell a stopped node from an absent or booting one
   beforehand: the gateway says 0x05040000 for all three, and it forwards no
   heartbeat (guide chapter 5), so its NMT view knows only the commands sent
   through it, never another master's. It does not need to: it sends **Start
   Remote Node** (CS 01h, Table 3-14) and reads again. An answer now is the
   evidence that the node was in NMT Stopped: logged at WARNING, naming it.
   No answer: the node is absent (or booting); the original failure is raised.
3. Then the stop or reset goes on as usual: halt; for S16, standstill first,
   then the NMT reset (rule 1 of :mod:`tcp_bridge.motion`).

Why Start Remote Node is safe to send on a guess:

* to an absent node, or one still initialising, it does nothing: NMT is
  unconfirmed (CiA 301 7.2.8.3.2.1) and an initialising node takes no NMT
  state command (Table 3-13: "no communication is supported");
* to a node that was in Stopped it is transition 5 (Table 3-13): only the
  communication state changes. Unlike Reset Node it leaves the CiA 402 state
  machine and the RAM values alone, so the drive stays enabled and can be
  halted on its profile deceleration (rule 1: no reset of a moving axis);
* to a node that was silent for another reason but is in Pre-Operational it
  enables its PDOs (transition 2). Enter Pre-Operational (CS 80h, transition
  6) would also end Stopped, but to a node that is Operational it would *take
  away* the PDOs that another master, or the bridge's own ``pdo = true``
  status feed (:mod:`tcp_bridge.backends.pdo_status`, which sets Operational
  itself), may be using to control or watch a moving axis. Adding PDOs is the
  harmless direction; Operational is also the state the bridge's CAN backend
  puts its nodes in.

Never for other commands: a read or a move to a node in NMT Stopped answers
NAK (fail-fast, :mod:`tcp_bridge.bus.health`, may then refuse them at once); a
client that wants the node back sends a stop or S16, which the fail-fast guard
never refuses (:mod:`tcp_bridge.engine`, ``Job.urgent``).
"""
from __future__ import annotations

import logging
from typing import Callable, TypeVar

from ..errors import DeviceFailure
from ..bus.health import Silence
from ..bus.sdo import NodeSilent, SdoPort, silence_of

log = logging.getLogger("tcp_bridge.motion")

T = TypeVar("T")


def answering(port: SdoPort, read: Callable[[], T]) -> T:
    """``read()``; if the node is silent, Start Remote Node and ``read()`` once more.

    Raises the first failure when the node does not answer after the Start
    either (absent, booting), or when the bus's device itself is silent.
    """
    try:
        return read()
    except NodeSilent as exc:
        if silence_of(exc) is not Silence.NODE:
            raise
        silent = exc
    # Raised outside the handlers below, so that ``silent`` keeps its own cause
    # (silence_of reads it) and gains no misleading context.
    try:
        port.nmt_start()
    except DeviceFailure as exc:
        log.warning("%s: no SDO answer, and NMT start remote node could not be sent (%s)",
                    port.name, exc)
        started = False
    else:
        started = True
    if started:
        try:
            value = read()
        except NodeSilent:
            log.warning("%s: no SDO answer, not even after NMT start remote node: the node "
                        "is absent or still booting, not in NMT Stopped", port.name)
        else:
            log.warning("%s: found in NMT Stopped (no SDO answer until the bridge sent NMT "
                        "start remote node; another master stopped it?): it is Operational "
                        "now", port.name)
            return value
    raise silent

__all__ = ["answering"]
