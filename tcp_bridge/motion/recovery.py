"""Recovery sequences of one drive: fault reset (S17) and the wait for a node that an
NMT reset restarts (mixed into :class:`~tcp_bridge.motion.drive.Cia402`).

CiA 402-2 6.4.1 (transition 15: fault reset on the rising edge of controlword bit
7); CiA 301 7.2.8.3.2.1 (NMT reset node is unconfirmed, so the node is polled
until it shows the state a drive boots into).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from epos_link.cia402 import State

from ..cia402_words import CONTROLWORD, Cw, Sw, decode_state
from ..errors import DeviceFailure

if TYPE_CHECKING:
    from .drive import Cia402


class Recovery:
    """The recovery half of :class:`~tcp_bridge.motion.drive.Cia402`."""

    def fault_reset(self: "Cia402") -> None:  # type: ignore[misc]
        """S17: rising edge of cw bit 7 (transition 15), then cw 00h; no-op without a fault."""
        sw = self.statusword()
        if decode_state(sw) is State.FAULT_REACTION_ACTIVE:
            sw = self.wait_status(lambda s: decode_state(s) is State.FAULT,
                                  self.timing.state_timeout, "FAULT after fault reaction")
        if not sw & Sw.FAULT:
            return  # a reset must never disable a running axis
        self._expect(None)
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)  # bit 7 low: the edge is ours
        self.port.write(CONTROLWORD, 0, Cw.FAULT_RESET)
        self.wait_status(lambda s: not s & Sw.FAULT, self.timing.state_timeout,
                         "fault cleared")
        self.port.write(CONTROLWORD, 0, Cw.DISABLE_VOLTAGE)

    def wait_for_node(self: "Cia402") -> None:  # type: ignore[misc]
        """After an NMT reset: wait ``reset_delay``, then poll until the node shows the
        state a drive boots into (SWITCH ON DISABLED, or FAULT if it boots faulty).

        Powered states would be the node before the reset took effect, and a
        silent node is still booting; both are waited out within ``reset_timeout``.
        """
        self._sleep(self.timing.reset_delay)
        deadline = self._clock() + self.timing.reset_timeout
        booted = (State.SWITCH_ON_DISABLED, State.FAULT)
        while True:
            try:
                state = self.state()
                if state in booted:
                    return
                why = f"still {state.name}"
            except DeviceFailure as exc:
                why = str(exc)
            if self._clock() >= deadline:
                raise DeviceFailure(f"{self.port.name}: not back {self.timing.reset_timeout:g} s "
                                    f"after NMT reset ({why})")
            self._sleep(max(self.timing.poll_interval, 0.01))


__all__ = ["Recovery"]
