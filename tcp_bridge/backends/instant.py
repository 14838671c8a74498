"""``instant``: in-process fake CiA 402 drives that answer every SDO at once.

For tests of the command layer and for measuring the bridge's own cost
(``bench/bridge.py``). Each :class:`FakeNode` is a dict of objects with
canopen's ``sdo.upload/download`` and ``nmt.state``, plus a minimal CiA 402
model: the state machine steps at once, a profile position set-point
(controlword bit 4 rising) is acknowledged and reached at once, a velocity
move runs at its target velocity until halted, homing sets the position to 0.
It is *not* the simulator (see ``epos_link.simulator``); it exists so the
engine can be tested without threads or clocks.

Bus options: ``absent = [node ids]`` makes nodes that never answer
(``canopen.SdoCommunicationError``), as an unplugged drive does.
"""
from __future__ import annotations

import threading
from typing import Any, Dict, List, Sequence, Tuple

from canopen import SdoAbortedError, SdoCommunicationError

from ..bus.sdo import decode, object_type

# (statusword bits without 4/9/10/12) by state name
_SW = {"SOD": 0x0040, "RTSO": 0x0021, "SO": 0x0023, "OE": 0x0027, "QS": 0x0007, "FAULT": 0x0008}
_DEFAULTS: Dict[Tuple[int, int], int] = {
    (0x1001, 0): 0, (0x603F, 0): 0, (0x6040, 0): 0, (0x605A, 0): 2, (0x6060, 0): 1,
    (0x6062, 0): 0, (0x6064, 0): 0, (0x6065, 0): 2000, (0x6067, 0): 10, (0x606C, 0): 0,
    (0x607A, 0): 0, (0x607D, 1): -(2**31), (0x607D, 2): 2**31 - 1, (0x607F, 0): 50000,
    (0x6081, 0): 1000, (0x6083, 0): 10000, (0x6084, 0): 10000, (0x6085, 0): 50000,
    (0x6098, 0): 37, (0x6099, 1): 100, (0x6099, 2): 10, (0x609A, 0): 1000,
    (0x60C5, 0): 1000000, (0x60FD, 0): 0, (0x60FE, 1): 0, (0x60FE, 2): 0, (0x60FF, 0): 0,
    (0x2000, 0): 0, (0x2100, 0): 0,
    (0x60A9, 0): 0x00B44700, (0x3010, 1): 500, (0x3000, 5): 2000,  # EPOS4: rpm, encoder
}
_READ_ONLY = {(0x1001, 0), (0x603F, 0), (0x6041, 0), (0x6061, 0), (0x6062, 0), (0x6064, 0),
              (0x606C, 0), (0x60FD, 0), (0x3000, 5)}


class _Nmt:
    def __init__(self, node: "FakeNode") -> None:
        self._node = node
        self._state = "PRE-OPERATIONAL"

    @property
    def state(self) -> str:
        return self._state

    @state.setter
    def state(self, value: str) -> None:
        if self._node.absent:
            return  # NMT is unconfirmed: nobody notices
        if value == "RESET":
            self._node.power_cycle()
        self._state = "PRE-OPERATIONAL" if value.startswith("RESET") else value


class FakeNode:
    """One fake drive; ``sdo`` is itself (``upload``/``download``)."""

    def __init__(self, node_id: int, *, absent: bool = False) -> None:
        self.node_id = node_id
        self.absent = absent
        self.sdo = self
        self.nmt = _Nmt(self)
        self.log: List[Tuple[str, int, int, bytes]] = []  # every SDO, for tests
        self.resets = 0
        self._lock = threading.Lock()
        self.power_cycle()
        self.resets = 0

    def power_cycle(self) -> None:
        self.values = dict(_DEFAULTS)
        self.state = "SOD"
        self.ack = False
        self.reached = True
        self.homed = False
        self.velocity_moving = False
        self.resets += 1

    # -- CiA 402 model -------------------------------------------------------------

    @property
    def mode(self) -> int:
        return self.values[(0x6060, 0)]

    @property
    def statusword(self) -> int:
        sw = _SW[self.state] | 0x0200  # remote
        if self.state in ("OE", "QS"):
            sw |= 0x0010
        halted = bool(self.values[(0x6040, 0)] & 0x100)
        if self.mode == 3:
            if self.state == "OE" and self.velocity_moving and not halted:
                sw |= 0x0400  # velocity reached, speed not zero
            else:
                sw |= 0x1400  # target reached, speed is zero
        else:
            if self.reached or halted:
                sw |= 0x0400
            if (self.mode == 1 and self.ack) or (self.mode == 6 and self.homed):
                sw |= 0x1000
        return sw

    def inject_fault(self, code: int = 0x8611) -> None:
        self.state = "FAULT"
        self.values[(0x603F, 0)] = code
        self.values[(0x1001, 0)] = 0x81

    def _controlword(self, cw: int, previous: int) -> None:
        st, low = self.state, cw & 0x8F
        if st == "FAULT":
            if cw & 0x80 and not previous & 0x80:
                self.state = "SOD"
                self.values[(0x603F, 0)] = 0
                self.values[(0x1001, 0)] = 0
            return
        if low & 0x02 == 0:
            self.state = "SOD"  # disable voltage
        elif low & 0x06 == 0x02:
            self.state = "SOD" if st in ("SOD", "RTSO", "SO") else "QS"  # quick stop
        elif low & 0x87 == 0x06:
            self.state = "RTSO"  # shutdown
        elif low & 0x8F == 0x07 and st in ("RTSO", "OE"):
            self.state = "SO"
        elif low & 0x8F == 0x0F and st in ("RTSO", "SO", "OE"):
            self.state = "OE"
        if self.state != "OE":
            self.velocity_moving = False
            self.ack = False
            return
        rising = cw & ~previous
        if self.mode == 1:
            if rising & 0x10:
                target = self.values[(0x607A, 0)]
                if cw & 0x40:
                    target += self.values[(0x6064, 0)]
                self.values[(0x6064, 0)] = self.values[(0x6062, 0)] = target  # instant move
                self.ack = True
                self.reached = True
            elif not cw & 0x10:
                self.ack = False
        elif self.mode == 6 and rising & 0x10:
            self.values[(0x6064, 0)] = self.values[(0x6062, 0)] = 0
            self.homed = True
        elif self.mode == 3:
            self.velocity_moving = self.values[(0x60FF, 0)] != 0

    # -- canopen SdoBase interface -----------------------------------------------------

    def upload(self, index: int, subindex: int) -> bytes:
        with self._lock:
            if self.absent:
                raise SdoCommunicationError("No SDO response received")
            key = (index, subindex)
            if key == (0x6041, 0):
                value = self.statusword
            elif key == (0x6061, 0):
                value = self.mode
            elif key == (0x2100, 0):
                raise SdoAbortedError(0x06010001)
            elif key in self.values:
                value = self.values[key]
            else:
                raise SdoAbortedError(0x06020000)
            size, signed = object_type(index, subindex)
            data = int(value).to_bytes(size, "little", signed=signed)
            self.log.append(("upload", index, subindex, data))
            return data

    def download(self, index: int, subindex: int, data: bytes, force_segment: bool = False) -> None:
        with self._lock:
            if self.absent:
                raise SdoCommunicationError("No SDO response received")
            key = (index, subindex)
            self.log.append(("download", index, subindex, bytes(data)))
            if key in _READ_ONLY:
                raise SdoAbortedError(0x06010002)
            if key not in self.values:
                raise SdoAbortedError(0x06020000)
            size, signed = object_type(index, subindex)
            if len(data) != size:
                raise SdoAbortedError(0x06070010)
            value = decode(data, size, signed)
            if key == (0x2100, 0):
                self.inject_fault()
                return
            if key == (0x6060, 0) and value not in (1, 3, 6):
                raise SdoAbortedError(0x06090030)
            previous = self.values[(0x6040, 0)]
            self.values[key] = value
            if key == (0x6040, 0):
                self._controlword(value, previous)
            elif key == (0x60FF, 0) and self.mode == 3 and self.state == "OE":
                self.velocity_moving = value != 0


class InstantBackend:
    """A bus of :class:`FakeNode` s, created on demand."""

    def __init__(self, bus: Any = None, axes: Sequence[Any] = ()) -> None:
        options = dict(getattr(bus, "options", {}) or {})
        from .heartbeat import refuse_heartbeat

        refuse_heartbeat(getattr(bus, "name", "?"), options, "instant")  # no CAN bus here
        self._absent = set(options.get("absent", ()))
        self.nodes: Dict[int, FakeNode] = {}
        self.closed = False

    def node(self, node_id: int) -> FakeNode:
        if node_id not in self.nodes:
            self.nodes[node_id] = FakeNode(node_id, absent=node_id in self._absent)
        return self.nodes[node_id]

    def close(self) -> None:
        self.closed = True
