"""The bridge's CiA 301 heartbeat on a ``canopen`` bus: bus options, producer, clean release.

Bus options (``[bus.can1]``, ``canopen`` backend and ``sim`` with ``link = "can"``)::

    heartbeat_ms = 100               # produce a heartbeat every 100 ms (unset: none, as before)
    heartbeat_node_id = 127          # the node-ID it carries; no axis of the bus may use it
    heartbeat_consumer_ms = 300      # what each drive waits for (default 3 x heartbeat_ms)
    abort_connection = "quick_stop"  # 6007h: "quick_stop" (3), "disable_voltage" (2), "fault" (1)

The producer (CiA 301 V4.2 7.2.8.3.2.2) sends COB-ID 700h + node-ID with one
data byte, the producer's NMT state: 05h, Operational (the bridge is a master
that is always running). It is python-can's cyclic send task
(``canopen.Network.send_periodic``; on SocketCAN the kernel's broadcast
manager sends it, which stops when the bridge's process ends, however it ends).
It starts when the engine attaches to the bus, before any request, so a drive
set up to watch it never sees a gap; ``tcp-bridge check`` opens buses without
attaching, and sends nothing.

Each drive's consumer is set up by :mod:`tcp_bridge.motion.supervision`
before the bridge first enables or moves it. **Chosen** limits of the consumer
time: at least 2 x ``heartbeat_ms`` (one late frame of a loaded host must not
trip a drive) and at most 4 x ``heartbeat_ms`` (issue 23: a drive stops within
a few periods of the bridge's death); ``heartbeat_ms`` is 10..10000 ms, so
the consumer time fits 1016h's 16 bits. **Chosen** default node-ID 127, the
highest CANopen node-ID (CiA 301 7.3.2: 1..127), as drives are usually
numbered from 1.

What a heartbeat proves is that the bridge's process runs, not that it
serves: a bridge that hangs with its process alive keeps the drives running.
On a bus with cyclic axes the set-point thread sends it (``start(driver=...)``),
so that a stalled set-point stream also stops the heartbeat.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Dict, Iterable, Optional, Sequence

from ..bus.sdo import SdoPort
from ..cia402_words import Deadline, Sw
from ..errors import DeviceFailure
from ..motion.supervision import ABORT_CONNECTION_CODES, HeartbeatSettings, Supervision
from ..tables.axes import AxisConfig, ConfigError

log = logging.getLogger("tcp_bridge.backends.heartbeat")

HEARTBEAT_OPTIONS = ("heartbeat_ms", "heartbeat_node_id", "heartbeat_consumer_ms",
                     "abort_connection")
DEFAULT_NODE_ID = 127
DEFAULT_FACTOR = 3
MIN_FACTOR, MAX_FACTOR = 2, 4
PERIOD_RANGE = (10, 10000)
OPERATIONAL = 0x05  # CiA 301 7.2.8.3.2.2, Table 44: heartbeat state Operational
REST_TIMEOUT = 10.0  # seconds a moving drive is given to halt at shutdown (chosen: as
# CyclicSender.finish_runs bounds a cyclic stop ramp)


def _int(bus: str, name: str, value: Any, low: int, high: int, unit: str = "") -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError(f"bus {bus}: {name} must be an integer {low}..{high}{unit}, "
                          f"not {value!r}")
    return value


def heartbeat_settings(bus: str, options: Dict[str, Any],
                       axes: Sequence[AxisConfig] = ()) -> Optional[HeartbeatSettings]:
    """The heartbeat options taken out of ``options``; None without ``heartbeat_ms``."""
    given = {name: options.pop(name) for name in HEARTBEAT_OPTIONS if name in options}
    if "heartbeat_ms" not in given:
        if given:
            raise ConfigError(f"bus {bus}: {', '.join(sorted(given))} need heartbeat_ms "
                              "(the period of the bridge's heartbeat)")
        return None
    period = _int(bus, "heartbeat_ms", given["heartbeat_ms"], *PERIOD_RANGE, " (ms)")
    producer = _int(bus, "heartbeat_node_id", given.get("heartbeat_node_id", DEFAULT_NODE_ID),
                    1, 127)
    taken = sorted({a.addr for a in axes if a.node_id == producer})
    if taken:
        raise ConfigError(f"bus {bus}: heartbeat_node_id {producer} is the node id of axis "
                          f"{taken[0]}; give the bridge's heartbeat a free node id "
                          "(heartbeat_node_id = ...)")
    consumer = _int(bus, "heartbeat_consumer_ms",
                    given.get("heartbeat_consumer_ms", DEFAULT_FACTOR * period),
                    MIN_FACTOR * period, MAX_FACTOR * period,
                    f" (ms: {MIN_FACTOR} to {MAX_FACTOR} x heartbeat_ms)")
    reaction = given.get("abort_connection", "quick_stop")
    if reaction not in ABORT_CONNECTION_CODES:
        raise ConfigError(f"bus {bus}: abort_connection must be one of "
                          f"{', '.join(repr(k) for k in ABORT_CONNECTION_CODES)}, not "
                          f"{reaction!r}")
    return HeartbeatSettings(period, producer, consumer, ABORT_CONNECTION_CODES[reaction])


def refuse_heartbeat(bus: str, options: Dict[str, Any], backend: str) -> None:
    """ConfigError if ``options`` hold a heartbeat option on a bus that cannot carry it."""
    given = sorted(name for name in HEARTBEAT_OPTIONS if name in options)
    if given:
        why = (" (an EPOS4 gateway forwards SDO only: the host's heartbeat cannot reach the "
               "CAN bus; docs/hardware.md, \"When the host dies\")" if backend == "epos" else "")
        raise ConfigError(f"bus {bus}: {given[0]} only on a canopen bus, not {backend}{why}")


class HeartbeatProducer:
    """The bridge's heartbeat on one ``canopen.Network``, and the drives that watch it."""

    def __init__(self, bus: str, network: Any, settings: HeartbeatSettings) -> None:
        self.bus = bus
        self.network = network
        self.settings = settings
        self._task: Any = None
        self._driven = False  # sent by a bus thread's add_beat (cyclic axes) instead
        self._stopped = False

    @property
    def running(self) -> bool:
        return self._task is not None or (self._driven and not self._stopped)

    def supervision(self, node_id: int) -> Supervision:
        return Supervision(self.settings, node_id, beat=self.beat)

    def start(self, driver: Any = None) -> None:
        """Heartbeat from now on: python-can's periodic task, or, with ``driver`` (the
        bus's :class:`~tcp_bridge.motion.cyclic.CyclicSender`), that thread's own beat,
        so that a set-point thread that stalls stops the heartbeat as well."""
        if self._task is not None or self._driven:
            return
        s = self.settings
        if driver is not None:
            self._driven = True
            driver.add_beat(s.period_ms / 1000.0, self.beat)
        else:
            self._task = self.network.send_periodic(0x700 + s.producer_id,
                                                    bytes([OPERATIONAL]), s.period_ms / 1000.0)
        log.info("bus %s: heartbeat of node %d every %d ms", self.bus, s.producer_id,
                 s.period_ms)

    def beat(self) -> None:
        """One heartbeat frame (CiA 301 7.2.8.3.2.2), unless stopped."""
        if not self._stopped:
            self.network.send_message(0x700 + self.settings.producer_id, bytes([OPERATIONAL]))

    def stop(self, nodes: Iterable[Any], rest_timeout: float = REST_TIMEOUT) -> None:
        """Clean shutdown: bring every supervised drive to rest, switch off its consumer,
        then stop the heartbeat (issue 30 finding 4: a profile velocity move was left
        turning with its consumer released, so that nothing stopped it afterwards)."""
        for node in nodes:
            supervision: Optional[Supervision] = getattr(node, "supervision", None)
            if supervision is None:
                continue
            port = SdoPort(node, name=f"bus {self.bus} node {supervision.node_id}")
            if supervision.written and getattr(node, "cyclic", None) is None \
                    and not _brought_to_rest(port, rest_timeout):
                continue  # its consumer stays on: it reacts (6007h) once the heartbeat ends
            try:
                supervision.release(port)
            except DeviceFailure as exc:
                log.warning("%s: its heartbeat consumer could not be switched off (%s): it "
                            "reacts (6007h) when the heartbeat stops now", port.name, exc)
        self._stopped = True
        task, self._task = self._task, None
        if task is not None:
            try:
                task.stop()
            except Exception:  # the adapter is gone: nothing is sent anyway
                pass


def _brought_to_rest(port: SdoPort, timeout: float) -> bool:
    """A drive the bridge supervised, at shutdown: halted (cw bit 8 and 60FFh = 0, as
    S00=8; CiA 402-2 6.4.1.3 halt ramps at 6084h) and at standstill (sw bit 10 with
    halt set) before its consumer is switched off, as cyclic moves ramp down before
    it (:meth:`~tcp_bridge.motion.cyclic.CyclicSender.finish_runs`); a quick stop
    is let finish. False (logged) if it did not come to rest within ``timeout``:
    then its consumer is left on, and the drive's own reaction (6007h) stops it
    when the heartbeat ends. Cyclic axes rest on their own ramps, not here."""
    from ..motion import Cia402, State, Timing

    drive = Cia402(port, Timing(ack_timeout=timeout, state_timeout=timeout))
    deadline = Deadline(time.monotonic, timeout)
    try:
        state = drive.state()
        if state is State.OPERATION_ENABLED:
            drive.halt()
            drive.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                              "standstill after halt")
        elif state is State.QUICK_STOP_ACTIVE:
            drive.wait_status(lambda sw: bool(sw & Sw.TARGET_REACHED), deadline.time_left(),
                              "end of quick stop")
    except DeviceFailure as exc:
        log.warning("%s: not at rest at shutdown (%s): its heartbeat consumer is left on, so "
                    "it reacts (6007h) when the heartbeat stops now", port.name, exc)
        return False
    return True


__all__ = ["HEARTBEAT_OPTIONS", "HeartbeatProducer", "heartbeat_settings", "refuse_heartbeat"]
