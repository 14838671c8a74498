"""A simulated EPOS4: its own CiA 402 drive, and drives behind its CAN gateway.

:class:`Epos4Simulator` answers MAXON SERIAL V2 bytes (:meth:`receive`) the way
the guide describes: requests for node 0 or its own node id are executed on its
own object dictionary; any other node id is forwarded as an SDO over a
python-can ``virtual`` bus (chapter 5), where each simulated drive is a canopen
``LocalNode`` over the same drive model. Other code in the process can join that
bus with ``canopen.Network().connect(interface="virtual", channel=sim.channel)``.

Time: by default the drives run in real time (``time.monotonic``); pass a
:class:`~epos_link.simulator.drive.VirtualClock` to step time in tests.

NMT resets (guide 3.3.3.5, Table 3-13): a node reset or communication reset
"while initialization is active" does not communicate and, "upon completion",
sends a boot-up message (COB-ID 700h + node id, one byte 00h, as canopen's
``NmtSlave`` sends it) before entering Pre-Operational. ``boot_time`` (real
seconds, default 0: boot-up sent at once) is how long a reset drive leaves
SDO requests on the CAN bus unanswered before its boot-up message.
"""
from __future__ import annotations

import itertools
import threading
import time
from typing import Any, Callable, Iterable, Optional

import canopen
from canopen.sdo import SdoAbortedError

from ..codes import ErrorCode, NmtCommand
from .device import Abort, DeviceProtocol
from .drive import Drive
from .gateway import SDO_TIMEOUT_ABORT, CanGateway, connect_virtual
from .od import ObjectStore, load_object_dictionary, make_local_node

_channels = itertools.count(1)
NMT_SPECIFIERS = frozenset(int(c) for c in NmtCommand)
NODE_ID_OBJECT = 0x2000  # maxon: Node-ID (the DIP switch value on a real EPOS4)
HOME_POSITION = 0x30B0


def _locked(lock: threading.RLock, fn: Callable[..., Any]) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        with lock:
            return fn(*args, **kwargs)
    return call


class SimulatedDrive:
    """One drive: object store, CiA 402 model and (behind the gateway) its LocalNode."""

    def __init__(self, node_id: int, clock: Callable[[], float]) -> None:
        self.node_id = node_id
        self.store = ObjectStore(load_object_dictionary(node_id))
        self.store.set(NODE_ID_OBJECT, 0, node_id)
        self.drive = Drive(self.store, clock=clock)
        self.local_node: Optional[canopen.LocalNode] = None
        self.booting = False  # after an NMT reset, until the boot-up message
        self.boot_timer: Optional[threading.Timer] = None
        # The serial thread and the CAN notifier thread both reach this store.
        self.lock = threading.RLock()
        for name in ("read", "write"):
            setattr(self.store, name, _locked(self.lock, getattr(self.store, name)))

    def nmt(self, command: int) -> None:
        with self.lock:
            self._nmt(command)

    def _nmt(self, command: int) -> None:
        if command == NmtCommand.RESET_NODE:
            self.drive.power_cycle(self.drive.clock() if self.drive.clock else None)
            self.store.set(NODE_ID_OBJECT, 0, self.node_id)


def _silent_while_booting(sim: SimulatedDrive) -> None:
    """Wrap the LocalNode's SDO server (before it joins the network, which binds
    the method) so that a booting drive leaves requests unanswered."""
    assert sim.local_node is not None
    serve = sim.local_node.sdo.on_request

    def on_request(can_id: int, data: bytearray, timestamp: float) -> None:
        if not sim.booting:
            serve(can_id, data, timestamp)

    sim.local_node.sdo.on_request = on_request  # type: ignore[method-assign]


class Epos4Simulator:
    """The device behind the serial link; thread-safe, one command at a time."""

    def __init__(self, node_id: int = 1, drives: Iterable[int] = (), *,
                 clock: Optional[Callable[[], float]] = None, channel: Optional[str] = None,
                 gateway_timeout: float = 0.3, segment_size: int = 255,
                 initiate_carries_data: bool = True, boot_time: float = 0.0) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError("node id must be 1..127")
        if not boot_time >= 0:
            raise ValueError("boot time must be 0 or more seconds")
        self.node_id = node_id
        self.boot_time = boot_time
        self._boot_lock = threading.Lock()  # boot timers against close()
        self.clock = clock or time.monotonic
        self._lock = threading.Lock()
        self.own = SimulatedDrive(node_id, self.clock)
        self.drives: dict[int, SimulatedDrive] = {node_id: self.own}
        remote = sorted(set(drives) - {node_id})
        for nid in remote:
            if not 1 <= nid <= 127:
                raise ValueError(f"drive node id {nid} must be 1..127")
        self.channel = channel or f"epos-sim-{id(self):x}-{next(_channels)}"
        # The CAN side: every drive, the EPOS4 itself included, is a LocalNode
        # on the virtual bus, so CAN clients reach them all directly.
        self._drive_net: Optional[canopen.Network] = connect_virtual(self.channel)
        for nid in remote:
            self.drives[nid] = SimulatedDrive(nid, self.clock)
        for nid, sim in self.drives.items():
            sim.local_node = make_local_node(sim.store, nid)
            _silent_while_booting(sim)
            self._drive_net.add_node(sim.local_node)
        self._drive_net.subscribe(0, self._on_nmt)
        self.gateway: Optional[CanGateway] = CanGateway(connect_virtual(self.channel),
                                                        timeout=gateway_timeout)
        self.device = DeviceProtocol(self, node_id=node_id, segment_size=segment_size,
                                     initiate_carries_data=initiate_carries_data)

    # -- the serial side ---------------------------------------------------------------

    def receive(self, data: bytes) -> list[bytes]:
        with self._lock:
            return self.device.receive(data)

    def reset(self) -> None:
        with self._lock:
            self.device.reset()

    # -- ObjectAccess for the device protocol ---------------------------------------------

    def _is_local(self, node: int) -> bool:
        return node in (0, self.node_id)

    def read(self, node: int, index: int, subindex: int) -> bytes:
        if self._is_local(node):
            try:
                return self.own.store.read(index, subindex)
            except SdoAbortedError as exc:
                raise Abort(exc.code) from None
        if self.gateway is None:
            raise Abort(SDO_TIMEOUT_ABORT)
        return self.gateway.read(node, index, subindex)

    def write(self, node: int, index: int, subindex: int, data: bytes, *,
              expedited: bool = True) -> None:
        if self._is_local(node):
            try:
                self.own.store.write(index, subindex, data)
            except SdoAbortedError as exc:
                raise Abort(exc.code) from None
            return
        if self.gateway is None:
            raise Abort(SDO_TIMEOUT_ABORT)
        self.gateway.write(node, index, subindex, data, expedited=expedited)

    def nmt(self, node: int, command: int) -> None:
        # SendNMTService goes to the CAN bus (node 0 = all nodes) and to this
        # device itself when it is addressed.
        if not 0 <= node <= 127:
            raise Abort(ErrorCode.GENERAL_PARAMETER_ERROR)  # no such CANopen node id
        if command not in NMT_SPECIFIERS:
            raise Abort(ErrorCode.COMMAND_UNKNOWN)  # not a CS of Table 3-14
        if node == self.node_id:
            self.own.nmt(command)
            self._boot(self.own, command)
        elif self.gateway is not None:
            # Node 0 is "all nodes": on the bus, where this device hears it too.
            self.gateway.nmt(node, command)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """NMT frames on the CAN bus reach the simulated drives (canopen's own
        NmtSlave only tracks the state; a reset node also resets the drive)."""
        if len(data) < 2:
            return
        command, target = data[0], data[1]
        for nid, sim in self.drives.items():
            if target in (0, nid):
                sim.nmt(command)
                self._boot(sim, command)

    def _boot(self, sim: SimulatedDrive, command: int) -> None:
        """After a reset: silent for ``boot_time``, then the boot-up message."""
        if command not in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            return
        with self._boot_lock:
            if sim.boot_timer is not None:
                sim.boot_timer.cancel()  # one pending boot per drive: the last reset counts
                sim.boot_timer = None
            if self.boot_time <= 0:
                self._send_bootup(sim)
                return
            sim.booting = True
            timer = threading.Timer(self.boot_time, lambda: self._booted(sim, timer))
            timer.daemon = True
            sim.boot_timer = timer
            timer.start()

    def _booted(self, sim: SimulatedDrive, timer: threading.Timer) -> None:
        with self._boot_lock:
            if sim.boot_timer is not timer:  # cancelled, or replaced by a later reset
                return
            sim.boot_timer = None
            self._send_bootup(sim)

    def _send_bootup(self, sim: SimulatedDrive) -> None:
        sim.booting = False
        if self._drive_net is not None:  # closed: nobody to tell
            self._drive_net.send_message(0x700 + sim.node_id, b"\x00")

    # -- conveniences ----------------------------------------------------------------------

    def drive(self, node_id: int) -> Drive:
        return self.drives[node_id].drive

    def close(self) -> None:
        with self._boot_lock:
            for sim in self.drives.values():
                if sim.boot_timer is not None:
                    sim.boot_timer.cancel()
                    sim.boot_timer = None
        if self.gateway is not None:
            self.gateway.close()
            self.gateway.network.disconnect()
            self.gateway = None
        with self._boot_lock:
            net, self._drive_net = self._drive_net, None
        if net is not None:
            net.disconnect()

    def __enter__(self) -> "Epos4Simulator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
