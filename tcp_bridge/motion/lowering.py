"""Rule 1 of :mod:`tcp_bridge.motion`, enforced here: lowering the state of a drive
(S04=0) and the NMT reset (S16=1, and enable after a power cycle). Mixed into
:class:`~tcp_bridge.motion.drive.Cia402`.

**The bridge never lowers the state of an axis that reports OPERATION ENABLED,
and never sends it an NMT reset, unless a client asked for exactly that**:
S04=0 (:meth:`Lowering.disable`) or S16=1 (:meth:`Lowering.reset_node`); who
asked is a :class:`Why`. Every lowering passes the guard :meth:`Lowering._lower`:
without a client's request it raises :class:`SafetyRefusal` (NAK); with one, a
moving axis is first brought to rest with halt (cw bit 8, profile deceleration
6084h) and the bridge waits for standstill (sw bit 10 with halt set) within
``ack_timeout``; if it does not come to rest the request is NAK and the axis
stays enabled and halted. A drive on its quick stop ramp is let finish (sw bit
10). Disable is then Disable Operation (07h) before Shutdown (06h): on an EPOS4,
Shutdown switches the drive function off without a ramp (605Bh = 0), Disable
Operation ramps first (605Ch = 1; option codes, CiA 402-2 6.4.1.3). No NMT
reset goes to an axis whose velocity (606Ch) is not zero, as a drive that lost
power coasts: NMT is unconfirmed (CiA 301 7.2.8.3.2.1), so the wait comes
before it.

An NMT reset also serves rule 3: the boot-up it causes is not taken for a power
cycle, and the next enable writes the parameters back
(:meth:`~tcp_bridge.motion.drive.Cia402.enable`).
"""
from __future__ import annotations

from enum import Enum
from typing import TYPE_CHECKING, Final, Optional

from epos_link.cia402 import State

from ..cia402_words import Cw, Deadline, Sw
from ..errors import DeviceFailure, SafetyRefusal
from ..bus.sdo import NodeSilent
from .nmt_stopped import answering

if TYPE_CHECKING:
    from .drive import Cia402


class Why(Enum):
    """Who asked for a lowering of the state (rule 1)."""

    CLIENT_DISABLE = "S04=0"
    CLIENT_RESET_NODE = "S16=1"
    POWER_CYCLE = "enable after a power cycle"  # never allowed on an enabled axis


CLIENT_REQUESTS: Final = frozenset({Why.CLIENT_DISABLE, Why.CLIENT_RESET_NODE})


class Lowering:
    """The lowering half of :class:`~tcp_bridge.motion.drive.Cia402` (rule 1).

    Its methods take ``self: "Cia402"``, as :class:`~tcp_bridge.motion.start.MoveStarts`
    explains.
    """

    # What an NMT reset changes of rule 3's state (set up by Cia402.__init__).
    power_cycle_evidence: Optional[str]
    restore_pending: bool
    _own_reset_until: float

    def _lower(self: "Cia402", why: Why, deadline: Deadline,  # type: ignore[misc]
               state: Optional[State] = None) -> State:
        """The guard every lowering passes: refuse on an enabled axis unless a client
        asked; bring an enabled axis to rest first; let a quick stop finish."""
        state = self.state() if state is None else state
        if state is State.OPERATION_ENABLED:
            if why not in CLIENT_REQUESTS:
                raise SafetyRefusal(f"{self.port.name}: refused ({why.value}): the axis is "
                                    "enabled and no client asked to disable or reset it")
            self.bring_to_rest(deadline)
        elif state is State.QUICK_STOP_ACTIVE:
            self._end_of_quick_stop(deadline)
        return state

    def _end_of_quick_stop(self: "Cia402", deadline: Deadline) -> None:  # type: ignore[misc]
        # Still on its quick stop ramp, maybe: let it finish (sw bit 10).
        self.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                         "end of quick stop")

    def bring_to_rest(self: "Cia402", deadline: Deadline) -> None:  # type: ignore[misc]
        """Halt (cw bit 8) and wait for standstill (sw bit 10) within ``deadline``.

        An axis moved by the bridge's own profile (``rest`` set, issue 26) is
        brought to rest by that profile's stop ramp instead: halt is not evaluated
        in CSP and the drive need not set bit 10 there."""
        if self.rest is not None:
            self.rest(deadline)
            return
        state = self.state()
        if state is State.QUICK_STOP_ACTIVE:  # stopping already: never undo it
            self._end_of_quick_stop(deadline)
            return
        self.write_while_enabled(Cw.ENABLE_OPERATION | Cw.HALT, state)
        self.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                         "standstill after halt (the axis stays enabled and halted)")

    def disable(self: "Cia402") -> None:  # type: ignore[misc]
        """S04=0: at rest first, then Disable Operation (07h), then Shutdown (06h)."""
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        state = self._lower(Why.CLIENT_DISABLE, deadline)
        if state is State.OPERATION_ENABLED:
            self._step(Cw.SWITCH_ON, State.SWITCHED_ON, deadline)  # disable operation
            state = State.SWITCHED_ON
        if state is State.SWITCHED_ON:
            self._step(Cw.SHUTDOWN, State.READY_TO_SWITCH_ON, deadline)
        elif state is State.QUICK_STOP_ACTIVE:  # at rest (_lower): disable voltage
            self._expect(None)
            self._step(Cw.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED, deadline)
        # not ready, switch on disabled, ready, fault: the drive function is already off

    def reset_node(self: "Cia402", why: Why, wait: bool = False) -> None:  # type: ignore[misc]
        """NMT reset node (S16=1, or enable after a power cycle with ``wait``).

        Never to an axis that still moves: an enabled one is halted first (a
        client's S16 only), one that coasts with its power stage off (606Ch not
        zero) is waited for. NMT is unconfirmed (CiA 301 7.2.8.3.2.1): S16
        answers once it is sent; the power-cycle path waits for the node to boot
        (:meth:`wait_for_node`). Either way the next enable writes the
        parameters back first. A client's S16 to a node in NMT Stopped makes it
        answer first (:mod:`.nmt_stopped`), so that it can be halted before the reset.
        """
        deadline = Deadline(self._clock, self.timing.ack_timeout)
        found = answering(self.port, self.state) if why is Why.CLIENT_RESET_NODE else None
        state = self._lower(why, deadline, found)
        if state is not State.OPERATION_ENABLED:
            self._wait_coasting(deadline)
        self._expect(None)
        grace = self.timing.reset_delay + self.timing.reset_timeout + 1.0
        self._own_reset_until = self._clock() + grace
        self.port.nmt_reset()
        self.power_cycle_evidence = None
        self.restore_pending = True
        self._tell("reset")
        if wait:
            self.wait_for_node()
            self._own_reset_until = self._clock() + 1.0  # its boot-up may still be in flight

    def _wait_coasting(self: "Cia402", deadline: Deadline) -> None:  # type: ignore[misc]
        while True:
            try:
                if not self.coasting():
                    return
            except NodeSilent:
                raise
            except DeviceFailure:
                return  # no velocity actual value (an abort): nothing to wait for
            if deadline.expired():
                raise SafetyRefusal(f"{self.port.name}: refused an NMT reset: the axis still "
                                    "moves (606Ch is not zero)")
            self._sleep(max(self.timing.poll_interval, 0.01))


__all__ = ["CLIENT_REQUESTS", "Lowering", "SafetyRefusal", "Why"]
