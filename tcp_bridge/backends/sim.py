"""``sim``: the embedded simulated EPOS4, reached through the epos path.

The bus's first axis is the simulated EPOS4 itself (its node id is the
gateway's), the others are simulated drives on the EPOS4's CAN gateway
(``epos_link.simulator.core.Epos4Simulator``). The bridge reaches them
exactly as it reaches real hardware with the ``epos`` backend: MAXON SERIAL V2
frames through an ``EposClient`` and ``epos_link.connect_node``, so the whole
chain runs.

Bus options::

    link = "inprocess"   # "inprocess" (sim:// transport, instant), "pty" or "can"
    baud = 115200        # with link = "pty": pace the simulated wire like a UART
    timeout = 0.5        # EposClient request timeout
    gateway_timeout = 0.3  # the simulated gateway's SDO timeout for absent nodes
    can_server = "127.0.0.1:0"  # also serve the simulated CAN bus over socketcand

With ``link = "can"`` the bridge reaches every simulated node, the EPOS4 itself
included, directly on the simulator's virtual CAN bus through the ``canopen``
backend, as it reaches drives through a CAN adapter: so PDO-fed status can be
tried without hardware. The ``canopen`` backend's own options apply then
(:data:`CAN_OPTIONS`: ``pdo = true``, ``eds``, ``sdo_timeout`` ...).

With ``can_server = "HOST:PORT"`` (either link; ``tcp-bridge serve --simulate
--can-server HOST:PORT``) the simulator's CAN bus is also served over the
socketcand protocol (:mod:`epos_link.simulator.socketcand`, port 0: a free one),
so ``python -m can.logger -i socketcand`` or a canopen script in another process
sees the drives' traffic; the backend's ``can_server`` attribute says where.
"""
from __future__ import annotations

from typing import Any, Dict, Final, List, Optional, Sequence, Tuple

from ..tables.axes import AxisConfig, BusConfig, ConfigError
from .canopen_bus import CanopenBackend
from .epos import EposBackend
from .heartbeat import HEARTBEAT_OPTIONS

CAN_OPTIONS: Final = ("eds", "sdo_timeout", "sdo_retries", "pdo", "pdo_max_age",
                      "pdo_event_timer", "pdo_inhibit_time", "cycle_ms", *HEARTBEAT_OPTIONS)


def _start_can_server(bus: str, options: Dict[str, Any], simulator: Any) -> Any:
    """The socketcand server of ``can_server = "HOST:PORT"`` (taken out of ``options``), or None."""
    text = options.pop("can_server", None)
    if text is None:
        return None
    from epos_link.simulator.socketcand import SocketcandServer, listen_error, parse_address

    try:
        host, port = parse_address(str(text))
    except ValueError as exc:
        raise ConfigError(f"bus {bus}: can_server: {exc}") from None
    try:
        return SocketcandServer(simulator.channel, host, port).start()
    except OSError as exc:
        raise ConfigError(f"bus {bus}: can_server: cannot listen on {host} port {port}: "
                          f"{listen_error(exc)}") from None


def _pop_nodes(options: Dict[str, Any], axes: Sequence[AxisConfig]) -> Tuple[int, List[int], float]:
    """(the EPOS4's node id, the drives behind it, the gateway's timeout) of a sim bus,
    taken out of ``options``: the first axis is the EPOS4 unless ``gateway_node_id``."""
    node_ids = [a.node_id for a in axes] or [1]
    gateway = int(options.pop("gateway_node_id", node_ids[0]))
    gateway_timeout = float(options.pop("gateway_timeout", 0.3))
    return gateway, [n for n in node_ids if n != gateway], gateway_timeout


def open_sim(bus: BusConfig, axes: Sequence[AxisConfig] = ()) -> Any:
    """The backend registry's factory for ``sim``: over the epos path, or (``link = "can"``)
    on the simulator's CAN bus."""
    if bus.options.get("link") == "can":
        return SimCanBackend(bus, axes)
    return SimBackend(bus, axes)


class SimCanBackend(CanopenBackend):
    """``link = "can"``: the canopen backend on the embedded simulator's virtual CAN bus."""

    def __init__(self, bus: BusConfig, axes: Sequence[AxisConfig] = ()) -> None:
        from epos_link.simulator.core import Epos4Simulator

        options: Dict[str, Any] = dict(bus.options)
        options.pop("link")
        can = {key: options.pop(key) for key in CAN_OPTIONS if key in options}
        gateway, drives, gateway_timeout = _pop_nodes(options, axes)
        server_option = {k: options.pop(k) for k in ("can_server",) if k in options}
        if options:
            raise ConfigError(f"bus {bus.name}: options {sorted(options)} do not apply to "
                              f"link = \"can\" (it takes {', '.join(CAN_OPTIONS)}, can_server)")
        self.simulator = Epos4Simulator(gateway, drives, gateway_timeout=gateway_timeout)
        self.can_server: Any = None
        try:
            self.can_server = _start_can_server(bus.name, server_option, self.simulator)
            super().__init__(BusConfig(bus.name, "canopen", {
                "interface": "virtual", "channel": self.simulator.channel,
                "receive_own_messages": False, **can}), axes)
        except BaseException:
            self._close_simulator()
            raise

    def drive(self, node_id: int) -> Any:
        """The simulated drive model of ``node_id`` (fault injection in tests)."""
        return self.simulator.drive(node_id)

    def _close_simulator(self) -> None:
        if self.can_server is not None:
            self.can_server.close()
        self.simulator.close()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._close_simulator()


class SimBackend:
    def __init__(self, bus: BusConfig, axes: Sequence[AxisConfig] = ()) -> None:
        from epos_link.client import EposClient
        from epos_link.simulator.core import Epos4Simulator

        options: Dict[str, Any] = dict(bus.options)
        gateway, drives, gateway_timeout = _pop_nodes(options, axes)
        link = options.pop("link", "inprocess")
        if link not in ("inprocess", "pty"):
            raise ConfigError(f"bus {bus.name}: sim link must be \"inprocess\", \"pty\" "
                              f"or \"can\", not {link!r}")
        misplaced = sorted(key for key in CAN_OPTIONS if key in options)
        if misplaced:
            raise ConfigError(f"bus {bus.name}: {', '.join(misplaced)} only with link = \"can\" "
                              "(the canopen backend on the simulator's CAN bus)")
        baud: Optional[int] = options.pop("baud", None)
        timeout = float(options.pop("timeout", 0.5))
        server_option = {k: options.pop(k) for k in ("can_server",) if k in options}
        if options:
            raise ConfigError(f"bus {bus.name}: unknown sim options {sorted(options)}")
        self.simulator = Epos4Simulator(gateway, drives, gateway_timeout=gateway_timeout)
        self.link: Any = None
        self.can_server: Any = None
        try:
            self.can_server = _start_can_server(bus.name, server_option, self.simulator)
            if link == "pty":
                from epos_link.simulator.link import LinkOptions, PtyLink

                self.link = PtyLink(self.simulator, LinkOptions(baud=baud)).start()
                client = EposClient.open(self.link.path, baudrate=baud or 115200,
                                         gateway_node_id=gateway, timeout=timeout)
            elif link == "inprocess":
                from epos_link.simulator.transport import SimTransport

                client = EposClient(SimTransport(self.simulator), gateway_node_id=gateway,
                                    timeout=timeout)
            else:  # pragma: no cover - refused above
                raise AssertionError(link)
            self.epos = EposBackend(BusConfig(bus.name, "epos", {}), axes, client=client)
        except BaseException:
            self._close_simulator()
            raise

    def node(self, node_id: int) -> Any:
        return self.epos.node(node_id)

    def probe(self) -> None:
        """The simulated EPOS4 itself answers (see :meth:`EposBackend.probe`)."""
        self.epos.probe()

    def patient_probe(self) -> None:
        self.epos.patient_probe()

    def drive(self, node_id: int) -> Any:
        """The simulated drive model of ``node_id`` (fault injection in tests)."""
        return self.simulator.drive(node_id)

    def _close_simulator(self) -> None:
        if self.link is not None:
            self.link.close()
        if self.can_server is not None:
            self.can_server.close()
        self.simulator.close()

    def close(self) -> None:
        try:
            self.epos.close()
        finally:
            self._close_simulator()
