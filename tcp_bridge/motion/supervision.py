"""Heartbeat supervision of one drive: the drive watches the bridge and stops when it dies.

Why (issue 23): a velocity move outlived a crashed bridge. With
``heartbeat_ms`` on a ``canopen`` bus the bridge produces a CiA 301 heartbeat
(:mod:`tcp_bridge.backends.heartbeat`) and makes each drive a *consumer* of
it; a drive that misses it for the consumer time sends EMCY 8130h ("life guard
error or heartbeat error", CiA 301 V4.2 Table 21) and reacts as its abort
connection option code says (CiA 402-2 object 6007h).

What is written, through the drive's :class:`~tcp_bridge.bus.sdo.SdoPort`,
before the bridge first enables the drive or starts a move on it
(:meth:`tcp_bridge.motion.Cia402.ensure_supervised`), in this order:

1. ``6007h`` abort connection option code, INTEGER16 (CiA 402-2: 1 fault
   signal, 2 disable voltage, 3 quick stop; 0 "no action" is not offered). It
   goes first, so that the consumer, once on, already has the reaction asked for.
2. ``1016h:01`` consumer heartbeat time, UNSIGNED32 (CiA 301 V4.2 7.5.2.19:
   bits 31..24 reserved 0, bits 23..16 the producer's node-ID, bits 15..0 the
   time in ms). Read first: if it already holds exactly this entry nothing is
   written. **Chosen**: only sub-index 1 is used (the EPOS4 has one consumer
   entry); an entry for another producer there is replaced, with a warning in
   the log. A non-zero entry is switched off (0) before the new one is written,
   as a device may refuse to change a running entry or to hold two entries for
   one node-ID (CiA 301: abort 06040043h).

Once per power-up: every event the drive's :class:`~tcp_bridge.motion.Cia402`
reports to its listeners (a boot-up message, other evidence of a power cycle,
the bridge's own NMT reset, a fall back to SWITCH ON DISABLED) makes the
supervision *stale*, and the next enable or move writes it again; in between
it costs nothing. A generation counter, not a flag, so that a boot-up seen on
the CAN notifier thread during a write on the bus thread is not lost.

**Chosen** (safety first): when the writes fail (a drive without 1016h aborts
06020000h), the enable or move is refused (NAK) and the log says why. The
bridge never runs an axis unsupervised on a bus where the table asked for
supervision.

At a clean shutdown :meth:`Supervision.release` writes ``1016h:01 = 0`` on
every drive whose entry the bridge wrote, before the producer stops, so the
drives are left as the clients left them and do not trip. 6007h is left as
written: without a consumer it has no effect on a heartbeat.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Dict, Final, Optional

from ..bus.sdo import NodeSilent, SdoPort
from ..errors import DeviceFailure

log = logging.getLogger("tcp_bridge.motion")

CONSUMER_HEARTBEAT_TIME: Final = 0x1016  # CiA 301 7.5.2.19, ARRAY of UNSIGNED32
CONSUMER_SUB: Final = 1
PRODUCER_HEARTBEAT_TIME: Final = 0x1017  # CiA 301 7.5.2.20, UNSIGNED16
ABORT_CONNECTION: Final = 0x6007  # CiA 402-2, INTEGER16

# What makes a drive stop when the bridge dies (issue 30 finding 5): S81 leaves these
# alone on a supervised axis. On a heartbeat bus: the consumer (1016h), the drive's own
# heartbeat (1017h, CiA 301: 0 switches it off, which the bridge's lost-drive watch
# would see as a lost drive) and the reaction (6007h). On EtherCAT the SM watchdog's
# time and divider are ESC registers 0420h/0400h (ETG.1000.4 6.3), which no CoE SDO
# reaches (S81 is an SDO), so there only 6007h, the drive's reaction to the watchdog.
HEARTBEAT_OBJECTS: Final = frozenset({CONSUMER_HEARTBEAT_TIME, PRODUCER_HEARTBEAT_TIME,
                                      ABORT_CONNECTION})
WATCHDOG_OBJECTS: Final = frozenset({ABORT_CONNECTION})

# abort_connection = "..." in the bus table -> 6007h value (CiA 402-2 object 6007h).
ABORT_CONNECTION_CODES: Final[Dict[str, int]] = {
    "quick_stop": 3, "disable_voltage": 2, "fault": 1}


@dataclass(frozen=True)
class HeartbeatSettings:
    """A bus's heartbeat: the bridge's producer, and what each drive is told to watch."""

    period_ms: int  # producer heartbeat time (CiA 301 1017h semantics)
    producer_id: int  # the node-ID the bridge's heartbeat carries (COB-ID 700h + id)
    consumer_ms: int  # 1016h time on each drive
    abort_connection: int  # 6007h value

    @property
    def consumer_entry(self) -> int:
        """The 1016h:01 value: producer node-ID in bits 23..16, time in ms in 15..0."""
        return (self.producer_id << 16) | self.consumer_ms


class Supervision:
    """One drive's heartbeat consumer, as the bridge sets it up (module docstring)."""

    def __init__(self, settings: HeartbeatSettings, node_id: int,
                 beat: Optional[Callable[[], None]] = None) -> None:
        self.settings = settings
        self.node_id = node_id
        # One heartbeat frame now (the producer's): see _configure.
        self._beat = beat
        self._generation = 0  # bumped by stale()
        self._done = -1  # the generation the last successful setup belongs to
        self.written = False  # 1016h:01 written this session: released at a clean shutdown

    @property
    def configured(self) -> bool:
        return self._done == self._generation

    def stale(self) -> None:
        """The drive may have lost its settings (boot-up, reset): set them up again."""
        self._generation += 1

    def ensure(self, port: SdoPort) -> None:
        """Set up the drive's consumer unless done since its last power-up; raises the
        port's DeviceFailure (answered NAK) when the drive refuses."""
        if self.configured:
            return
        generation = self._generation
        try:
            self._configure(port)
        except DeviceFailure as exc:
            log.error("%s: refused: the heartbeat supervision the bus table asks for "
                      "(1016h:01 = 0x%08X, 6007h = %d) could not be set up: %s", port.name,
                      self.settings.consumer_entry, self.settings.abort_connection, exc)
            raise
        self._done = generation

    def _configure(self, port: SdoPort) -> None:
        s = self.settings
        port.write(ABORT_CONNECTION, 0, s.abort_connection, size=2, signed=True)
        entry = s.consumer_entry
        held = port.read(CONSUMER_HEARTBEAT_TIME, CONSUMER_SUB, size=4, signed=False)
        if held == entry:
            self.written = True
            self._activate()
            return
        if held & 0xFFFF:
            if (held >> 16) & 0xFF != s.producer_id:
                log.warning("%s: 1016h:01 watched node %d (%d ms); replaced by the bridge's "
                            "heartbeat (node %d, %d ms)", port.name, (held >> 16) & 0xFF,
                            held & 0xFFFF, s.producer_id, s.consumer_ms)
            port.write(CONSUMER_HEARTBEAT_TIME, CONSUMER_SUB, 0, size=4, signed=False)
        self.written = True  # a lost answer may still have set it: released at shutdown
        try:
            port.write(CONSUMER_HEARTBEAT_TIME, CONSUMER_SUB, entry, size=4, signed=False)
        except NodeSilent:
            raise
        except DeviceFailure:
            self.written = False  # refused (an abort): the drive holds no entry of ours
            raise
        self._activate()
        log.info("%s: heartbeat consumer on: node %d every %d ms, at most %d ms silence, "
                 "then 6007h = %d", port.name, s.producer_id, s.period_ms, s.consumer_ms,
                 s.abort_connection)

    def _activate(self) -> None:
        """A consumer watches only from the first heartbeat it receives after it was
        configured (CiA 301 V4.2 7.2.8.3.2.2: "activated by the first reception"): a
        bridge killed within one period after the write would leave the drive
        unwatched (issue 30: a bridge that arms a drive it found moving and is killed
        right after its first answer). So one heartbeat goes out now, after the
        drive's answer to the 1016h write; an extra frame only restarts the
        consumer's timer."""
        if self._beat is not None:
            try:
                self._beat()
            except Exception as exc:  # a bus error: the periodic heartbeat follows anyway
                log.warning("heartbeat not sent after setting up node %d's consumer (%s)",
                            self.node_id, exc)

    def release(self, port: SdoPort) -> None:
        """Clean shutdown: switch the consumer off (1016h:01 = 0), if the bridge set it."""
        if not self.written:
            return
        port.write(CONSUMER_HEARTBEAT_TIME, CONSUMER_SUB, 0, size=4, signed=False)
        self.written = False
        self.stale()


__all__ = ["ABORT_CONNECTION", "ABORT_CONNECTION_CODES", "CONSUMER_HEARTBEAT_TIME",
           "HEARTBEAT_OBJECTS", "HeartbeatSettings", "PRODUCER_HEARTBEAT_TIME", "Supervision",
           "WATCHDOG_OBJECTS"]
