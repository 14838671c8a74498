"""A simulated EPOS4: its own CiA 402 drive, and drives behind its CAN gateway.

:class:`Epos4Simulator` answers MAXON SERIAL V2 bytes (:meth:`receive`) the way
the guide describes: requests for node 0 or its own node id are executed on its
own object dictionary; any other node id is forwarded as an SDO over a
python-can ``virtual`` bus (chapter 5), where each simulated drive is a canopen
``LocalNode`` over the same drive model. Other code in the process can join that
bus with ``canopen.Network().connect(interface="virtual", channel=sim.channel)``.

Time: by default the drives run in real time (``time.monotonic``); pass a
:class:`~epos_link.simulator.drive.VirtualClock` to step time in tests.

NMT (guide 3.3.3, Table 3-13), per simulated drive:

* after a reset (power-up, :meth:`Epos4Simulator.power_cycle`, NMT reset node
  or reset communication) a drive is initialising: "while initialization is
  active, no communication is supported" (guide 3.3.3.5, Table 3-13), so its
  CAN SDO server is silent for ``boot_time`` real seconds (default 0); "upon
  completion" it sends its boot-up message, COB-ID 0x700 + node id with one
  data byte 0x00, and is Pre-Operational;
* statusword bit 9 (remote) is 1 exactly while the drive is Operational
  (Table 3-13, footnote 3);
* in Stopped a drive's CAN SDO server does not answer (Table 3-13: only NMT,
  LSS and heartbeat), so the gateway reports 0x05040000 after its timeout;
* in Operational a drive sends its transmit PDOs on the virtual bus
  (:mod:`epos_link.simulator.pdo`: event-driven, mapped through 0x1800/0x1A00
  as on an EPOS4) and acts on its receive PDOs (:mod:`epos_link.simulator.rpdo`:
  1400h-1403h/1600h-1603h as maxon's EDS, controlword in each); the serial
  gateway carries no PDOs (guide chapter 5);
* EMCY (1014h) at every fault and fault reset, in Pre-Operational and
  Operational; heartbeat producer (1017h) in Pre-Operational, Operational and
  Stopped; heartbeat consumer (1016h) with the 6007h reaction to a lost
  heartbeat (:mod:`epos_link.simulator.comm`, one listener for all frames and
  one timer thread, :class:`~epos_link.simulator.heartbeat.HeartbeatTicker`,
  on ``comm_clock``, default ``time.monotonic``);
* **chosen**: the serial link (node 0 or the device's own id) keeps working
  in every NMT state. Table 3-13 describes the CAN interface; USB/RS232 is a
  separate channel (the guide's "Wrong NMT state error" 0x0F00FFC0 is not
  tied to it anywhere), and a host must be able to start a stopped node.
"""
from __future__ import annotations

import itertools
import threading
import time
from typing import Any, Callable, Iterable, Optional

import can
import canopen
from canopen.sdo import SdoAbortedError

from ..codes import ErrorCode, NmtCommand
from .device import Abort, DeviceProtocol
from .drive import Drive
from .nmt import NmtState, next_state
from .canbus import DEFAULT_BITRATE, sdo_answer_due, wait_until
from .pdo import TICK, PdoTicker, TransmitPdos
from .comm import DriveComm, FrameListener
from .heartbeat import HeartbeatTicker
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
    """One drive: object store, CiA 402 model, NMT state and (behind the gateway) its LocalNode."""

    def __init__(self, node_id: int, clock: Callable[[], float],
                 comm_clock: Callable[[], float] = time.monotonic) -> None:
        self.node_id = node_id
        self.store = ObjectStore(load_object_dictionary(node_id))
        self.store.set(NODE_ID_OBJECT, 0, node_id)
        self.drive = Drive(self.store, clock=clock)
        self.drive.on_power_up = self._reset_done
        self.nmt_state = NmtState.PRE_OPERATIONAL
        # How a reset ends: Epos4Simulator sets it (boot_time); default at once.
        self.boot: Callable[["SimulatedDrive"], None] = SimulatedDrive.booted
        self.boot_timer: Optional[threading.Timer] = None
        self.local_node: Optional[canopen.LocalNode] = None
        self.network: Optional[canopen.Network] = None  # where boot-up messages and PDOs go
        self.tpdo = TransmitPdos(self.store)
        self.wake_ticker: Callable[[], None] = lambda: None  # the PDO ticker samples now
        # The serial thread and the CAN notifier thread both reach this store.
        self.lock = threading.RLock()
        for name in ("read", "write"):
            setattr(self.store, name, _locked(self.lock, getattr(self.store, name)))
        write = self.store.write

        def write_and_touch(index: int, subindex: int, data: bytes) -> None:
            write(index, subindex, data)
            self.tpdo.touch()  # a quiet drive samples its PDO data at the next tick
            self.wake_ticker()
        self.store.write = write_and_touch  # type: ignore[method-assign]
        self.comm = DriveComm(self, comm_clock)  # RPDO, EMCY, heartbeat (comm_clock: heartbeats)
        self.heartbeat_tick = self.comm.tick

    def attach(self, node: canopen.LocalNode, network: canopen.Network,
               bitrate: Optional[int] = DEFAULT_BITRATE) -> None:
        """Serve CAN SDO through ``node`` on ``network``, silent while NMT Stopped; each
        answer no sooner than the bus at ``bitrate`` carries it (epos_link.simulator.canbus;
        None: at once)."""
        serve = node.sdo.on_request

        def on_request(can_id: int, data: bytearray, timestamp: float) -> None:
            # Table 3-13: no SDO in Stopped, no communication while initialising.
            if self.nmt_state not in (NmtState.STOPPED, NmtState.INITIALISING):
                wait_until(sdo_answer_due(timestamp, len(data), bitrate))
                serve(can_id, data, timestamp)

        # An instance attribute, set before add_node subscribes it to the bus.
        node.sdo.on_request = on_request  # type: ignore[method-assign]
        # canopen's NmtSlave starts its own heartbeat producer on a 1017h write, with a
        # state it never updates; the drive's producer is epos_link.simulator.heartbeat.
        if node.nmt.on_write in node._write_callbacks:
            node._write_callbacks.remove(node.nmt.on_write)
        self.local_node = node
        self.network = network
        network.add_node(node)

    @property
    def next_sample(self) -> float:
        """When the PDO ticker must sample this drive again (-inf: at its next tick)."""
        return self.tpdo.next_sample if self.transmitting else float("inf")

    def send_pdos(self, now: float) -> None:
        """Send the transmit PDOs that are due (:class:`~epos_link.simulator.pdo.PdoTicker`),
        under the drive's lock, so none shows the drive before an SDO write that was
        answered before it was sent."""
        with self.lock:
            network = self.network
            if self.nmt_state is not NmtState.OPERATIONAL or network is None:
                return  # the PDOs were reset when it left Operational (_set_state)
            if not self.tpdo.wants_sample(now):
                return  # at rest and untouched (epos_link.simulator.pdo, QUIET)
            self.drive.sync()
            for cob_id, data in self.tpdo.due(now):
                network.send_message(cob_id, data)

    def nmt(self, command: int) -> None:
        with self.lock:
            if command == NmtCommand.RESET_NODE:
                self.drive.reset_node(self.drive.clock() if self.drive.clock else None)
                return  # _reset_done() goes on
            if command == NmtCommand.RESET_COMMUNICATION:
                self._reset_done("reset communication")
                return
            if self.nmt_state is not NmtState.INITIALISING:
                self._set_state(next_state(self.nmt_state, command))

    def power_cycle(self) -> None:
        """The supply is switched off and on: saved parameters, counter 0, boot-up."""
        with self.lock:
            self.drive.power_cycle(self.drive.clock() if self.drive.clock else None)

    def _reset_done(self, cause: str) -> None:
        self.store.set(NODE_ID_OBJECT, 0, self.node_id)
        self.tpdo.reset()  # the PDO objects are back at their saved values
        self.comm.reset()  # so are RPDO, EMCY and heartbeat objects: supervision starts again
        self._set_state(NmtState.INITIALISING)
        self.boot(self)

    def booted(self) -> None:
        """Initialisation complete: boot-up message, then Pre-Operational."""
        with self.lock:
            if self.nmt_state is not NmtState.INITIALISING:
                return
            self._set_state(NmtState.PRE_OPERATIONAL)
            network = self.network
        if network is not None:
            try:
                # CiA 301 7.2.8.3.2.1: boot-up = COB-ID 0x700 + node id, one byte 0x00.
                network.send_message(0x700 + self.node_id, b"\x00")
            except can.CanError:  # the simulator was closed meanwhile: nobody to tell
                pass

    @property
    def transmitting(self) -> bool:
        """Whether it may send PDOs now (Operational); read without the lock by the ticker."""
        return self.nmt_state is NmtState.OPERATIONAL

    def _set_state(self, state: NmtState) -> None:
        self.nmt_state = state
        self.drive.remote = state is NmtState.OPERATIONAL  # statusword bit 9
        if state is NmtState.OPERATIONAL:
            self.tpdo.touch()
            self.wake_ticker()
        else:
            self.tpdo.reset()  # nothing is sent outside Operational


class Epos4Simulator:
    """The device behind the serial link; thread-safe, one command at a time."""

    def __init__(self, node_id: int = 1, drives: Iterable[int] = (), *,
                 clock: Optional[Callable[[], float]] = None, channel: Optional[str] = None,
                 gateway_timeout: float = 0.3, segment_size: int = 255,
                 initiate_carries_data: bool = True, boot_time: float = 0.0,
                 pdo_tick: float = TICK, can_bitrate: Optional[int] = DEFAULT_BITRATE,
                 comm_clock: Callable[[], float] = time.monotonic) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError("node id must be 1..127")
        if not boot_time >= 0:
            raise ValueError("boot time must be 0 or more seconds")
        if can_bitrate is not None and not can_bitrate > 0:
            raise ValueError("the CAN bit rate must be positive (or None: frames take no time)")
        self.node_id = node_id
        self.boot_time = boot_time
        self._boot_lock = threading.Lock()  # boot timers against close()
        self.clock = clock or time.monotonic
        self._lock = threading.Lock()
        self.own = SimulatedDrive(node_id, self.clock, comm_clock)
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
            self.drives[nid] = SimulatedDrive(nid, self.clock, comm_clock)
        for nid, sim in self.drives.items():
            sim.boot = self._boot
            sim.attach(make_local_node(sim.store, nid), self._drive_net, can_bitrate)
        for nid in self.drives:  # powered up: each drive says so (CiA 301 boot-up)
            self._drive_net.send_message(0x700 + nid, b"\x00")
        self._drive_net.subscribe(0, self._on_nmt)
        self._pdo: Optional[PdoTicker] = PdoTicker(lambda: tuple(self.drives.values()),
                                                   self.clock, tick=pdo_tick)
        self._heartbeat: Optional[HeartbeatTicker] = HeartbeatTicker(
            lambda: tuple(self.drives.values()), comm_clock)
        for sim in self.drives.values():
            sim.wake_ticker = self._pdo.wake
            sim.comm.wake_timer = self._heartbeat.wake
        self._listener = FrameListener(self.drives)
        assert self._drive_net.notifier is not None  # connect_virtual started it
        self._drive_net.notifier.add_listener(self._listener)
        self.gateway: Optional[CanGateway] = CanGateway(connect_virtual(self.channel),
                                                        timeout=gateway_timeout,
                                                        answers=self._answers_sdo)
        self.device = DeviceProtocol(self, node_id=node_id, segment_size=segment_size,
                                     initiate_carries_data=initiate_carries_data)

    # -- the serial side ---------------------------------------------------------------

    def receive(self, data: bytes) -> list[bytes]:
        with self._lock:
            return self.device.receive(data)

    def reset(self) -> None:
        with self._lock:
            self.device.reset()

    def frame_timeout(self, index: int) -> float:
        """Guide 2.2.7: 2005h (RS232) / 2006h (USB) frame timeout, ms in the dictionary, in s."""
        return self.own.store.get_int(index) / 1000.0

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

    def _answers_sdo(self, node: int) -> bool:
        """A drive of this simulator that serves SDO now (Table 3-13, as attach())."""
        sim = self.drives.get(node)
        return sim is not None and sim.nmt_state not in (NmtState.STOPPED, NmtState.INITIALISING)

    def _boot(self, sim: SimulatedDrive) -> None:
        """After a reset: silent for ``boot_time``, then the boot-up message.

        Lock order: a drive's lock may be held when this runs; ``_boot_lock``
        is never held while a drive's lock is taken.
        """
        with self._boot_lock:
            if sim.boot_timer is not None:
                sim.boot_timer.cancel()  # one pending boot per drive: the last reset counts
                sim.boot_timer = None
            at_once = self.boot_time <= 0 or self._drive_net is None
            if not at_once:
                timer = threading.Timer(self.boot_time, lambda: self._booted(sim, timer))
                timer.daemon = True
                sim.boot_timer = timer
                timer.start()
        if at_once:
            sim.booted()

    def _booted(self, sim: SimulatedDrive, timer: threading.Timer) -> None:
        with self._boot_lock:
            if sim.boot_timer is not timer:  # cancelled, or replaced by a later reset
                return
            sim.boot_timer = None
        sim.booted()

    # -- conveniences ----------------------------------------------------------------------

    def drive(self, node_id: int) -> Drive:
        return self.drives[node_id].drive

    def power_cycle(self, node_id: int) -> None:
        """Fault injection: switch drive ``node_id`` off and on (see :meth:`SimulatedDrive.power_cycle`)."""
        self.drives[node_id].power_cycle()

    def nmt_state(self, node_id: int) -> NmtState:
        return self.drives[node_id].nmt_state

    def increments_per_revolution(self, node_id: int) -> int:
        """Main sensor increments per motor revolution of drive ``node_id`` (3000h:05)."""
        sim = self.drives[node_id]
        with sim.lock:
            return sim.drive.increments_per_revolution

    def close(self) -> None:
        if self._pdo is not None:
            self._pdo.close()
            self._pdo = None
        if self._heartbeat is not None:
            self._heartbeat.close()
            self._heartbeat = None
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
            for sim in self.drives.values():
                sim.network = None
        if net is not None:
            net.disconnect()

    def __enter__(self) -> "Epos4Simulator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
