"""The bridge's safety rule and the CiA 402 sequences: the one place that moves a drive.

Every controlword the bridge writes, every NMT command it sends and every move
it starts goes through :class:`Cia402` (power, modes and stop in
:mod:`.drive`, disable and NMT reset under rule 1 in :mod:`.lowering`, the
start of a move in :mod:`.start`, a node that another master put in NMT
Stopped in :mod:`.nmt_stopped`). Commands cite this
module (:mod:`tcp_bridge.plan.axis`: 00, 04, 07, 16, 17, 85 and the slave
moves of 29/30 and 90). Synchronous code for a bus worker thread; every wait
polls the statusword (6041h) and is bounded by a
:class:`~tcp_bridge.cia402_words.Deadline`; running out of time raises
:class:`~tcp_bridge.errors.DeviceFailure`, answered NAK. References: CiA 402-2
V4.0 section 6.4 (6.4.1.3 controlword, 6.4.1.4 statusword, state table), 6.6
homing, 6.7 profile position, 6.9 profile velocity; CiA 301 7.2.8 (NMT); PSI
gateway spec rev 2.3, command table (section 4).

The safety rule
===============

1. **The bridge never lowers the state of an axis that reports OPERATION
   ENABLED, and never sends it an NMT reset, unless a client asked for exactly
   that**: S04=0 (disable) or S16=1 (reset node). (S17, fault reset, acts only
   on a drive in FAULT, which is not enabled.) Even then a moving axis is first
   brought to rest with halt (cw bit 8, profile deceleration 6084h) and the
   bridge waits for standstill (sw bit 10 with halt set) within
   ``ack_timeout``; if it does not come to rest the request is NAK and the axis
   stays enabled and halted. Disable is then Disable Operation (07h) before
   Shutdown (06h): on an EPOS4, Shutdown switches the drive function off without
   a ramp (605Bh = 0), Disable Operation ramps first (605Ch = 1). A drive on its
   quick stop ramp is let finish before anything else (enable included), and no
   NMT reset goes to an axis whose velocity (606Ch) is not zero, as a drive that
   lost power coasts. The guard is :meth:`Cia402._lower` (:mod:`.lowering`).
2. **Motion starts only on a move command** (S00=1, 2, 3, 9; S90). Enable
   enters OPERATION ENABLED with halt set; stop (S00=8) sets halt and clears the
   target velocity 60FFh; a mode change (S07, or a move in another mode) halts
   first and leaves halt set. A move releases halt in the same controlword
   write that gives the drive its *own* new set-point, so no earlier target or
   velocity is ever resumed.
3. **A power cycle is detected from evidence, never from a timeout**: the
   node's boot-up message (CAN backend), or the drive no longer holding the
   values the bridge wrote to it (read back at each enable). A fall back to
   SWITCH ON DISABLED after the bridge saw the drive powered is a reason to
   look: the next enable writes the stored parameters again (a quick stop
   input ends there too, so it alone is not taken for a power cycle), and the
   velocity unit (60A9h) is read again. After real evidence the next enable
   does what spec 04 says ("If PowerCycle then NodeReset and WriteParameter
   before enable sequence"): NMT reset, wait for the node, write the
   parameters, enable. An axis in OPERATION ENABLED is never reset by it. The
   first enable after the bridge starts writes the stored parameters, without
   a reset.
4. **A move's answer tells the truth.** ACK means the drive accepted the move:
   profile position acknowledged the new set-point (sw bit 12 after the rising
   edge of cw bit 4); profile velocity holds the new target velocity with halt
   released; homing shows "in progress" or "attained". NAK means the move did
   not start, or, if the node went silent during the write that starts it, that
   the outcome is unknown ("outcome unknown" in the log): every axis of the
   move is then halted, at once or, if the node is still silent, before the
   next command to that axis runs. When the answer to a start write is lost
   or garbled (a CRC error is a lost answer), the bridge reads the drive back
   (controlword, statusword, 60FFh) before it answers, and a lost poll after
   the start write is read again. Writes before the start write are
   idempotent and start nothing, so a lost answer there is tried again (for
   up to half of ``ack_timeout``). A relative move (S00=2) goes its distance
   from where each axis stands when it starts, halted moves included: the
   bridge adds it to the position demand value 6062h (6064h on a drive
   without it) and starts an absolute move, as a relative set-point (cw bit
   6) counts from the preceding target (CiA 402-2 6.7; see :mod:`.start`).
"""
from ..cia402_words import (CONTROLWORD, MODES_DISPLAY, STATUSWORD, TARGET_VELOCITY, Cw,
                            Deadline, Mode, Sw, Timing, decode_state)
from .drive import (CLIENT_REQUESTS, Cia402, OutcomeUnknown, Restore, SafetyRefusal, State,
                    Why)
from .start import HomingMove, Move, PositionMove, VelocityMove

__all__ = ["CLIENT_REQUESTS", "CONTROLWORD", "Cia402", "Cw", "Deadline", "HomingMove",
           "MODES_DISPLAY", "Mode", "Move", "OutcomeUnknown", "PositionMove", "Restore",
           "STATUSWORD", "SafetyRefusal", "State", "Sw", "TARGET_VELOCITY", "Timing",
           "VelocityMove", "Why", "decode_state"]
