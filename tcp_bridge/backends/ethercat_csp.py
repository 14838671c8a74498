"""Internal axes in CSP on an ``ethercat`` bus: set-points made on the process-data cycle.

The CAN bus streams CSP set-points from a thread of its own
(:class:`tcp_bridge.motion.cyclic.CyclicSender`). On EtherCAT the backend
already has a thread that sends the process data every ``cycle_ms``
(:mod:`.ethercat_cycle`), and a cycle hook runs on it before the outputs go
out. :class:`CycleSender` is the same sender (the same runs, stop ramps,
ACK-when-started and error rules) with that hook as its loop: every cycle
samples the profile at that moment and puts 607Ah into the output image of
that very cycle. **Chosen** over a second thread at ``cycle_ms``: one clock,
no beat between two loops (a second thread would hand a set-point over up to
a cycle late, or two in one cycle), and no extra thread to watch.

What protects the drives when the bridge dies is the slaves' process-data
(SyncManager 2) watchdog, ``watchdog_ms``: no frames, no set-points, and each
slave leaves OP for SAFE-OP with AL status 0x001B (ETG.1000.6 Table 11) and
its drive reacts per 6007h "abort connection option code" (CiA 402-2 6007h;
3, quick stop, is maxon's default). The same holds if only the cycle thread
stalls, since the set-points and the frames are one thing here. So an
EtherCAT bus with cyclic axes needs no heartbeat (``heartbeat_ms`` is not an
ethercat option at all).

:class:`EthercatSetpoints` never writes the controlword: 6040h in the outputs
keeps what the bridge's enable wrote through ``node.sdo.download`` (which the
backend routes to the process image). Writing "enable operation" every cycle
would undo a quick stop (CiA 402-2 transition 16; :class:`CanopenSetpoints`
says more). A slave that is lost (out of OP) or a link that is down ends the
run (a transport error, logged): the drive holds its last set-point or is in
its own watchdog reaction, and a set-point stream must not resume behind it
when the recovery brings the slave back to OP. The sender looks at
:meth:`EthercatSetpoints.statuswords` before each cycle's set-points: a lost slave ends
its part of the run and the rest of its line ramps down (:mod:`tcp_bridge.motion.cyclic`).

A slave whose drive left OPERATION ENABLED by itself (:mod:`.ethercat_hold`: its
outputs follow the drive) gets no more set-points from a run: 607Ah stays equal
to its actual position, 60FFh 0, whatever the run's line says, so that no jump
waits for the next enable.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, Iterable, Mapping, Optional

from ..errors import DeviceFailure
from ..motion.cyclic import CyclicSender, Seen

log = logging.getLogger("tcp_bridge.motion")

TARGET_POSITION = 0x607A
TARGET_VELOCITY = 0x60FF
POSITION_ACTUAL = 0x6064
STATUSWORD = 0x6041


class EthercatSetpoints:
    """:class:`~tcp_bridge.motion.cyclic.Setpoints` through an ethercat backend's PDOs."""

    def __init__(self, backend: Any) -> None:
        self.backend = backend

    def prepare(self, node: int) -> None:
        """607Ah must be in the slave's RxPDO mapping (1C12h assignment): CSP needs it."""
        layout = self.backend.layouts.get(node)
        if layout is None:
            raise DeviceFailure(f"slave {node}: its PDO mapping is unknown (logged at opening), "
                                "so the target position 607Ah cannot be sent cyclically")
        if (TARGET_POSITION, 0) not in layout.outputs:
            raise DeviceFailure(f"slave {node}: the target position 607Ah is not mapped in its "
                                "outputs (RxPDO, 1C12h); CSP needs it in the process data")

    def prepare_velocity(self, node: int) -> None:
        """CSV: 60FFh must be in the slave's outputs (the EPOS4's factory mapping has it)."""
        layout = self.backend.layouts.get(node)
        if layout is None or (TARGET_VELOCITY, 0) not in layout.outputs:
            raise DeviceFailure(f"slave {node}: the target velocity 60FFh is not mapped in its "
                                "outputs (RxPDO, 1C12h); CSV needs it in the process data")

    def _check(self, nodes: Iterable[int]) -> None:
        cycle = self.backend.cycle
        if cycle.link_down:
            raise DeviceFailure(f"no EtherCAT frame comes back on {self.backend.interface}")
        for node in nodes:
            why = cycle.lost.get(node)
            if why is not None:
                raise DeviceFailure(why)

    def _held(self, node: int) -> bool:
        hold = getattr(self.backend, "hold", None)
        return hold is not None and hold.holding(node)

    def write_targets(self, targets: Mapping[int, int]) -> None:
        self._check(targets)
        for node, position in targets.items():
            if not self._held(node):  # a held drive's 607Ah follows its position
                self.backend.node(node).cyclic_target(position)  # 607Ah only, never 6040h

    def write_velocities(self, velocities: Mapping[int, int]) -> None:
        self._check(velocities)
        for node, velocity in velocities.items():
            if not self._held(node):
                self.backend.node(node).pdo_write(TARGET_VELOCITY, 0, velocity)  # 60FFh only

    def statuswords(self, nodes: Iterable[int]) -> Dict[int, Seen]:
        """Each slave's statusword 6041h from this cycle's inputs (issue 30 finding 2,
        "a line is one motion"); why it is lost (out of OP, the link down) instead; None
        for a slave that does not map 6041h in (then only its own reaction stops it)."""
        cycle = self.backend.cycle
        out: Dict[int, Seen] = {}
        for node in nodes:
            if cycle.link_down:
                out[node] = f"no EtherCAT frame comes back on {self.backend.interface}"
                continue
            why = cycle.lost.get(node)
            if why is not None:
                out[node] = why
                continue
            layout = self.backend.layouts.get(node)
            out[node] = (self.backend.node(node).pdo_read(STATUSWORD)
                         if layout is not None and (STATUSWORD, 0) in layout.inputs else None)
        return out

    def read_actual(self, nodes: Iterable[int]) -> Dict[int, int]:
        out: Dict[int, int] = {}
        for n in nodes:
            node = self.backend.node(n)
            try:
                out[n] = node.pdo_read(POSITION_ACTUAL)
            except KeyError:  # not in the inputs: by CoE SDO
                out[n] = int.from_bytes(node.sdo.upload(POSITION_ACTUAL, 0)[:4], "little",
                                        signed=True)
        return out


class CycleSender(CyclicSender):
    """A :class:`CyclicSender` whose loop is a cycle hook (module docstring, chosen)."""

    def __init__(self, bus: str, transport: Any, cycle_s: float,
                 add_hook: Callable[[Callable[[int], None]], None],
                 remove_hook: Callable[[Callable[[int], None]], None]) -> None:
        super().__init__(bus, transport, cycle_s)
        self._add_hook, self._remove_hook = add_hook, remove_hook
        self._hooked = False

    def add_beat(self, period_s: float, send: Callable[[], None]) -> None:
        raise NotImplementedError("an EtherCAT bus has no heartbeat: the SM watchdog watches")

    def begin(self) -> None:
        if not self._hooked and not self._stop.is_set():
            self._hooked = True
            self._add_hook(self._on_cycle)

    def kill(self) -> None:
        """Nothing more is written into the outputs (the cycle itself goes on)."""
        self._stop.set()
        if self._hooked:
            self._remove_hook(self._on_cycle)
            self._hooked = False

    def alive(self) -> bool:
        return self._hooked and not self._stop.is_set()

    def start(self, nodes: Any, line: Any, timeout: float,
              on_end: Optional[Callable[[int, str], None]] = None) -> Any:
        if self._stop.is_set():
            raise DeviceFailure(f"bus {self.bus}: the cyclic set-points have ended")
        return super().start(nodes, line, timeout, on_end)

    def _on_cycle(self, count: int) -> None:
        if self._stop.is_set():
            return
        try:
            self._cycle()
        except Exception:  # a bug: the runs end (the drives hold), the hook stays
            log.exception("bus %s: cyclic set-points failed; the cyclic moves end here",
                          self.bus)
            with self._lock:
                for run in list(self._runs):
                    run.failure = "internal error"
                    self._end(run)


__all__ = ["CycleSender", "EthercatSetpoints"]
