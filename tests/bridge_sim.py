"""A bridge on a simulated EPOS4, served on loopback TCP, with answers that can be lost.

For end-to-end tests written the way a user meets a problem: a TCP client
talks to the bridge (``tcp_bridge.server``), which reaches the simulated EPOS4
and the drives behind its CAN gateway through the real ``epos`` path
(``EposClient`` over MAXON SERIAL V2, ``epos_link.connect_node``). The link
is an in-process :class:`LossyTransport`, so a test can lose the answers to
chosen requests after the device executed them, as a noisy cable does.

These tests watch the simulated drives themselves (positions, state history,
motion starts), so they run on the simulator only; ``tests/test_bridge_e2e.py``
is the scenario that also runs on hardware (``EPOS_URL``, ``CAN_CHANNEL``).
"""
from __future__ import annotations

import asyncio
import socket
import threading
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence

from epos_link.client import EposClient
from epos_link.framing import decode_frames
from epos_link.messages import Message, WriteObject, decode_request
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import FaultInjector, LinkOptions
from epos_link.simulator.transport import SimTransport
from tcp_bridge.tables.axes import AxisTable, BusConfig, simulated_increments_per_revolution
from tcp_bridge.backends.epos import EposBackend
from tcp_bridge.engine import Engine
from tcp_bridge.wire import Reply
from tcp_bridge.server import BridgeServer, ServerOptions
from tests.helpers import AskOk, psi_ask, wait_until

TIMING = {"ack_timeout": 2.0, "state_timeout": 1.0, "reset_timeout": 3.0, "reset_delay": 0.05,
          "poll_interval": 0.002}
Rule = Callable[[Message], bool]
# The simulated gateway's SDO timeout: how long it waits for a drive on its CAN bus before
# it answers 0x05040000 itself. A drive answers in about a millisecond, but on a loaded
# 2-core machine its answer (a python-can notifier thread, then the drive's SDO server)
# once took longer than the 0.1 s used here before (issue 32: a quick-stop test and an
# inverted-axis test NAKed "node 2 silent"). 1 s is ten times the worst seen; only the
# tests of a node that never answers (NMT Stopped, absent) wait for it.
# (The client_timeout of 0.1 s is no race: sim:// answers within the write, so only an
# answer the test drops on purpose is ever waited for.)
GATEWAY_TIMEOUT = 1.0


def controlword_write(node: int, *, bits: int = 0) -> Rule:
    """A rule matching WriteObject of the controlword (6040h) of ``node`` with ``bits`` set."""
    def match(message: Message) -> bool:
        return (isinstance(message, WriteObject) and message.node == node
                and message.index == 0x6040
                and int.from_bytes(message.data[:2], "little") & bits == bits)
    return match


class LossyTransport(SimTransport):
    """``sim://`` whose answers to chosen requests are lost after the device ran them."""

    def __init__(self, simulator: Epos4Simulator) -> None:
        super().__init__(simulator)
        self._rule: Optional[Rule] = None
        self._to_drop = 0
        self._silence_rule: Optional[Rule] = None
        self._silent_node: Optional[int] = None
        self._silent = False
        self.dropped: List[Message] = []
        self.requests: List[Message] = []

    def lose_answers(self, rule: Rule, count: int) -> None:
        """The next ``count`` requests matching ``rule`` are executed, unanswered."""
        self._rule, self._to_drop = rule, count

    def go_silent_after(self, rule: Rule, node: int) -> None:
        """The next request matching ``rule`` is executed, unanswered; from then on
        ``node`` hears nothing (requests are neither executed nor answered) until
        :meth:`speak`, as a drive whose cable was pulled."""
        self._silence_rule, self._silent_node = rule, node

    def add_noise(self, options: LinkOptions) -> None:
        """From now on every answer goes through the faults of ``epos-link sim``
        (:class:`LinkOptions`: ``corrupt``, ``drop``; ``seed`` makes them reproducible)."""
        self.faults = FaultInjector(options)

    def speak(self) -> None:
        self._silence_rule, self._silent_node, self._silent = None, None, False

    def write(self, data: bytes) -> None:
        messages = [decode_request(f) for f in decode_frames(bytes(data))]
        self.requests.extend(messages)
        if self._silent and any(getattr(m, "node", None) == self._silent_node for m in messages):
            return  # the node hears nothing
        if self._silence_rule is not None and any(self._silence_rule(m) for m in messages):
            self._silent = True
            self.simulator.receive(bytes(data))  # executed; its answer and the rest lost
            return
        drop = (self._to_drop > 0 and self._rule is not None
                and any(self._rule(m) for m in messages))
        if not drop:
            super().write(data)
            return
        self._to_drop -= 1
        self.dropped.extend(messages)
        self.simulator.receive(bytes(data))  # the device executes it; the answer is lost


class SimBridge(AskOk):
    """Simulator + bridge server on its own event loop thread + one TCP client."""

    def __init__(self, drives: Sequence[int] = (2, 3), *, gateway: int = 1,
                 axes: Optional[List[Dict[str, Any]]] = None, timing: Optional[Dict[str, Any]] = None,
                 client_timeout: float = 0.1, gateway_timeout: float = GATEWAY_TIMEOUT) -> None:
        self.sim = Epos4Simulator(gateway, list(drives), gateway_timeout=gateway_timeout)
        self.transport = LossyTransport(self.sim)
        self.client = EposClient(self.transport, gateway_node_id=gateway, timeout=client_timeout,
                                 late_answer_timeout=client_timeout)
        ipr = simulated_increments_per_revolution()
        self.axes = axes if axes is not None else [
            {"device": 5, "node_id": n, "position_factor": 1000, "increments_per_revolution": ipr}
            for n in (gateway, *drives)]
        self.timing = {**TIMING, **(timing or {})}
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.engine: Engine
        self.server: BridgeServer
        self.sock: socket.socket
        self.start()

    # -- the bridge: start, restart ------------------------------------------------------

    def start(self) -> None:
        table = AxisTable.from_mapping({"bridge": self.timing,
                                        "bus": {"can1": {"backend": "epos"}},
                                        "axis": self.axes})
        backend = EposBackend(BusConfig("can1", "epos", {}), list(table.axes.values()),
                              client=self.client)
        nodes = {a.addr: backend.node(a.node_id) for a in table.axes.values()}
        self.engine = Engine(table, nodes)  # the backend (and its client) outlive a restart
        self.server = BridgeServer(self.engine, ServerOptions(ports=(0, 0)))
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result(10)
        self.sock = socket.create_connection(self.server.addresses[0], timeout=30)

    def stop(self) -> None:
        self.sock.close()
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(30)

    def restart(self) -> None:
        """The bridge process restarts; the drives keep running."""
        self.stop()
        self.start()

    def close(self) -> None:
        self.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()
        self.client.close()
        self.sim.close()

    # -- a client's view -------------------------------------------------------------------

    def ask(self, line: str) -> Reply:
        return psi_ask(self.sock, line)

    # -- the drive's view ------------------------------------------------------------------

    def drive(self, node: int) -> Any:
        return self.sim.drive(node)

    def now(self, node: int) -> Any:
        """The drive of ``node`` brought up to the present (under its lock): read
        ``.position``, ``.velocity``, ``.state`` of the result."""
        sim = self.sim.drives[node]
        with sim.lock:
            sim.drive.sync()
        return sim.drive

    def position(self, node: int) -> int:
        return int(self.now(node).position)

    def positions(self, *nodes: int) -> List[int]:
        """The positions of several drives at one and the same instant."""
        sims = [self.sim.drives[n] for n in nodes]
        for sim in sims:
            sim.lock.acquire()
        try:
            t = self.sim.clock()
            for sim in sims:
                sim.drive.update(t)  # no drive is past t: we hold every lock
            return [int(sim.drive.position) for sim in sims]
        finally:
            for sim in sims:
                sim.lock.release()

    def velocity(self, node: int) -> float:
        """The axis velocity in increments per second (606Ch is in rpm on an EPOS4)."""
        return float(self.now(node).velocity_increments)

    # -- another master on the same drives ------------------------------------------------

    def other_master_write(self, node: int, index: int, sub: int, value: int, size: int) -> None:
        """Write ``value`` (``size`` bytes, two's complement if negative) to object
        ``index``/``sub`` of drive ``node`` as another master does, bypassing the bridge,
        which is not told: for a drive behind the gateway an SDO download on the
        drives' CAN bus (another CANopen master), for the gateway's own node a write to
        its dictionary (maxon's studio on its USB port). The drive checks it as any SDO
        download; a refusal raises :class:`epos_link.simulator.device.Abort` with the
        SDO abort code (CiA 301 7.2.4.3.17)."""
        data = (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")
        self.sim.write(node, index, sub, data)

    def other_master_read(self, node: int, index: int, sub: int, *, signed: bool = False) -> int:
        """Read object ``index``/``sub`` of drive ``node`` the same way (an SDO upload)."""
        return int.from_bytes(self.sim.read(node, index, sub), "little", signed=signed)

    def wait_until(self, what: Callable[[], bool], timeout: float = 10.0, why: str = "") -> None:
        wait_until(what, timeout, why or "condition never became true")


def power_ups(b: SimBridge, node: int) -> int:
    """How often the drive went through transition 0 (an NMT reset or power-up)."""
    return sum(1 for _, number, _ in b.drive(node).history if number == 0)


def starts(b: SimBridge, node: int) -> int:
    """Motion starts the simulated drive accepted (set-points, velocity goals, homings)."""
    return int(b.now(node).motion_starts)


def run_velocity_move(b: SimBridge, axis: int, speed: str = "5", direction: int = 1) -> None:
    """Enable ``axis`` and start a velocity move; wait until the drive turns in
    ``direction`` (-1 on an axis inverted with S22=-1)."""
    b.ok(f"{axis}S04=1", f"{axis}S05={speed}", f"{axis}S06=50", f"{axis}S00=3")
    b.wait_until(lambda: b.velocity(axis) * direction > 0,
                 why="the velocity move never started")


def opcodes(messages: Iterable[Message]) -> List[str]:
    return [type(m).__name__ for m in messages]
