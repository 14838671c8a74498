"""``canopen``: a CAN adapter through python-can, one ``canopen.RemoteNode`` per axis.

Bus options (``[bus.can1]`` in the axis table); everything not listed here is
passed to ``canopen.Network.connect``, i.e. to ``can.Bus``, so any python-can
interface works::

    interface = "socketcan"   # or "pcan", "kvaser", "slcan", "virtual", ...
    channel = "can0"
    bitrate = 500000          # spec 1.1 lists the PSI rates: 125k, 250k, 500k, 1M
    eds = "default"           # the shipped EPOS4 EDS; a path; or "none"
    sdo_timeout = 0.3         # seconds per SDO response (canopen's RESPONSE_TIMEOUT)
    sdo_retries = 1           # canopen's MAX_RETRIES (1: no retry)
    pdo = false               # true: status from TPDOs (tcp_bridge.backends.pdo_status)
    pdo_max_age = 0.1         # seconds: an older PDO value is read by SDO instead
    pdo_event_timer = 0.05    # seconds (at most 0.05): each drive sends at least this often
    pdo_inhibit_time = 0.01   # seconds between two position/velocity PDOs of a drive
    heartbeat_ms = 100        # the bridge's heartbeat, which the drives watch (unset: none)
    heartbeat_node_id = 127   # its node-ID; heartbeat_consumer_ms, abort_connection:
                              # see tcp_bridge.backends.heartbeat
    cycle_ms = 10             # the set-point cycle of internal axes in CSP (cyclic = "csp")

A bus served over the socketcand protocol (linux-can socketcand, or
``epos-link sim --can-server`` / ``tcp-bridge serve --simulate --can-server``,
which serve the simulated drives' bus) is reached through python-can's
``socketcand`` interface::

    interface = "socketcand"
    host = "127.0.0.1"
    port = 29536
    channel = "can0"          # the bus name the server announces

python-can's client retries a refused connection for 10 s, logging every try,
and waits without bound for the server's greeting; so the backend first
connects once itself (:func:`check_socketcand`): nothing listening is one line
at once, and the bus is opened again later like an unplugged adapter; a server
that does not greet with ``< hi >`` is a ConfigError.

The command layer uses ``node.sdo.upload/download``, so without ``pdo`` the
EDS matters for tools, not for the bridge; "none" gives an empty dictionary.
With ``pdo = true`` the TPDOs are mapped through canopen's PDO API, which needs
the dictionary's 1800h/1A00h objects (and the mapped objects): an EDS is
required. With ``heartbeat_ms`` each drive stops (quick stop by default) when
the bridge's heartbeat stops (issue 23; :mod:`.heartbeat`,
:mod:`tcp_bridge.motion.supervision`).

A bus with internal axes in CSP (``cyclic = "csp"``, issue 26) gets a set-point
thread (:class:`tcp_bridge.motion.cyclic.CyclicSender`, RPDO3 every
``cycle_ms``) and must have ``heartbeat_ms``: when the bridge dies, only the
drives' heartbeat consumers stop them (ConfigError without it). An EDS is
needed for the RPDO mapping.
"""
from __future__ import annotations

import errno
import os
import socket
from typing import Any, Callable, Dict, Optional, Sequence

import canopen

from ..motion.cyclic import CanopenSetpoints, CyclicSender
from ..motion.supervision import Supervision
from ..errors import BusUnavailable
from ..tables.axes import AxisConfig, BusConfig, ConfigError
from .heartbeat import HeartbeatProducer, heartbeat_settings
from .pdo_status import PdoSettings, PdoStatus, StatusFeed


class FedNode(canopen.RemoteNode):  # type: ignore[misc]
    """A RemoteNode that may carry a :class:`StatusFeed` (``pdo = true``), which
    :class:`tcp_bridge.bus.sdo.SdoPort` consults for status reads."""

    status_feed: Optional[StatusFeed] = None
    supervision: Optional[Supervision] = None  # heartbeat_ms: the drive's consumer
    cyclic: Optional[CyclicSender] = None  # cyclic = "csp": the bus's set-point thread


def _pdo_settings(bus: str, options: Dict[str, Any]) -> Optional[PdoSettings]:
    enabled = options.pop("pdo", False)
    names = ("pdo_max_age", "pdo_event_timer", "pdo_inhibit_time")
    given = {name[len("pdo_"):]: options.pop(name) for name in names if name in options}
    if not isinstance(enabled, bool):
        raise ConfigError(f"bus {bus}: pdo must be true or false")
    if not enabled:
        return None
    for name, value in given.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"bus {bus}: pdo_{name} must be a number of seconds")
    try:
        return PdoSettings(**{k: float(v) for k, v in given.items()})
    except ValueError as exc:
        raise ConfigError(f"bus {bus}: {exc}") from None


# What a SocketCAN failure usually means on Linux (docs/hardware.md, "SocketCAN").
_HINTS: Dict[int, str] = {
    errno.EAFNOSUPPORT: "no SocketCAN here: sudo modprobe can_raw; a container needs the "
                        "host's CAN interfaces",
    errno.ENODEV: "no such CAN interface (ip -details link show; is the adapter plugged in?)",
    errno.ENETDOWN: "the interface is down: sudo ip link set {channel} up type can bitrate 500000",
}


def _reason(exc: BaseException, channel: Any) -> str:
    """The adapter's error in the OS's words, with a hint for the usual SocketCAN cases."""
    code = getattr(exc, "errno", None)
    if isinstance(code, int) and code > 0:
        hint = _HINTS.get(code)
        return os.strerror(code) + (f" ({hint.format(channel=channel)})" if hint else "")
    return str(exc)


SOCKETCAND_GREETING = b"< hi >"  # socketcand doc/protocol.md, "Mode NO_BUS"


def check_socketcand(bus: str, options: Dict[str, Any], timeout: float = 3.0) -> None:
    """Return when a socketcand server greets at ``options``' host and port.

    Nothing listening there is :class:`BusUnavailable` (the bus is opened again
    later, as an unplugged adapter); a server that does not greet, or no host or
    port, is a ConfigError."""
    host, port = options.get("host"), options.get("port")
    if host is None or port is None:
        raise ConfigError(f"bus {bus}: interface socketcand needs host and port")
    where = f"{host}:{port}"
    try:
        with socket.create_connection((str(host), int(port)), timeout=timeout) as probe:
            greeting = b""
            while len(greeting) < len(SOCKETCAND_GREETING):
                chunk = probe.recv(len(SOCKETCAND_GREETING) - len(greeting))
                if not chunk:
                    break
                greeting += chunk
    except socket.timeout:
        greeting = b""
    except ValueError as exc:  # a port that is not a number
        raise ConfigError(f"bus {bus}: no socketcand server at {where}: {exc}") from None
    except OSError as exc:  # nothing listens (yet): serve opens it again later
        raise BusUnavailable(f"bus {bus}: no socketcand server at {where}: "
                             f"{_reason(exc, '')}") from None
    if greeting != SOCKETCAND_GREETING:
        raise ConfigError(f"bus {bus}: {where} is not a socketcand server (it did not "
                          f"greet with {SOCKETCAND_GREETING.decode()})")


def _not_there(exc: BaseException) -> bool:
    """The adapter is missing or down now (OSError, python-can's CanInitializationError),
    as opposed to an option or interface name the configuration got wrong."""
    import can

    if isinstance(exc, can.CanInterfaceNotImplementedError):
        return False
    return isinstance(exc, (OSError, can.CanInitializationError))


def object_dictionary(eds: Any, node_id: int) -> Any:
    """The dictionary of a node: ``"default"`` (EPOS4 EDS), ``"none"`` or an EDS/DCF path."""
    if eds in (None, "none", ""):
        return canopen.ObjectDictionary()
    if eds == "default":
        from epos_link.simulator.od import EDS_PATH

        eds = str(EDS_PATH)
    try:
        return canopen.import_od(str(eds), node_id)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot load EDS {eds}: {exc}") from None


class CanopenBackend:
    """One ``canopen.Network`` on one python-can bus."""

    def __init__(self, bus: BusConfig, axes: Sequence[AxisConfig] = ()) -> None:
        options: Dict[str, Any] = dict(bus.options)
        self.name = bus.name
        self.eds = options.pop("eds", "default")
        self.sdo_timeout = float(options.pop("sdo_timeout", 0.3))
        self.sdo_retries = int(options.pop("sdo_retries", 1))
        settings = _pdo_settings(bus.name, options)
        if settings is not None and self.eds in (None, "none", ""):
            raise ConfigError(f"bus {bus.name}: pdo = true needs an EDS (eds = \"default\" "
                              "or a path), for the PDO objects 1800h/1A00h")
        self.pdo: Optional[PdoStatus] = PdoStatus(bus.name, settings) if settings else None
        heartbeat = heartbeat_settings(bus.name, options, axes)
        self.cyclic_nodes = frozenset(a.node_id for a in axes if a.cyclic is not None)
        cycle_ms = options.pop("cycle_ms", 10)
        if isinstance(cycle_ms, bool) or not isinstance(cycle_ms, (int, float)) \
                or not 1 <= cycle_ms <= 1000:
            raise ConfigError(f"bus {bus.name}: cycle_ms must be a number 1..1000, not "
                              f"{cycle_ms!r}")
        if self.cyclic_nodes and heartbeat is None:
            raise ConfigError(f"bus {bus.name}: internal axes (moved in CSP, spec 3.2) need "
                              "heartbeat_ms: a drive in CSP holds its last set-point, and only "
                              "its heartbeat consumer stops it when the bridge dies; profile = "
                              "\"drive\" keeps the drive's own profile modes")
        if self.cyclic_nodes and self.eds in (None, "none", ""):
            raise ConfigError(f"bus {bus.name}: cyclic axes need an EDS (eds = \"default\" or a "
                              "path), for the RPDO mapping 1402h/1602h")
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # a quick notifier stop on close
        if options.get("interface") == "socketcand":
            check_socketcand(bus.name, options)
        try:
            self.network.connect(**options)
        except Exception as exc:  # python-can raises CanError, OSError, ValueError, ImportError...
            why = (f"bus {bus.name}: cannot open CAN interface "
                   f"{options.get('interface', '(python-can default)')} "
                   f"{options.get('channel', '')}: {_reason(exc, options.get('channel', 'can0'))}")
            if _not_there(exc):  # serve opens it again later (tcp_bridge.backends.reopen)
                raise BusUnavailable(why) from None
            raise ConfigError(why) from None
        self.nodes: Dict[int, FedNode] = {}
        self.heartbeat: Optional[HeartbeatProducer] = (
            HeartbeatProducer(bus.name, self.network, heartbeat) if heartbeat else None)
        self.cyclic: Optional[CyclicSender] = None
        if self.cyclic_nodes and heartbeat is not None:
            # The drives' statuswords come as often as the heartbeat goes; a drive silent
            # for twice the consumer time is lost (chosen: a drive judges the bridge
            # lost after the consumer time; a loaded host that reads a statusword late
            # must not end a line, so the bridge gives the drive twice that).
            setpoints = CanopenSetpoints(self.network, heartbeat.period_ms / 1000.0,
                                         2 * heartbeat.consumer_ms / 1000.0)
            self.cyclic = CyclicSender(bus.name, setpoints, cycle_ms / 1000.0)

    def node(self, node_id: int) -> FedNode:
        node = self.nodes.get(node_id)
        if node is None:
            node = FedNode(node_id, object_dictionary(self.eds, node_id))
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            node.sdo.MAX_RETRIES = self.sdo_retries
            self.network.add_node(node)
            if self.pdo is not None:
                node.status_feed = self.pdo.add(node)
            if self.heartbeat is not None:
                node.supervision = self.heartbeat.supervision(node_id)
            if node_id in self.cyclic_nodes:
                node.cyclic = self.cyclic
            self.nodes[node_id] = node
        return node

    def attach_worker(self, post: Callable[[Callable[[], Any]], None]) -> None:
        """Called by the engine with its bus worker's ``post``: PDO mappings are set there.
        The bridge serves this bus from now on: its heartbeat starts (``tcp-bridge check``
        never attaches, so it sends nothing)."""
        if self.heartbeat is not None:
            # With cyclic axes the set-point thread sends the heartbeat itself: a stalled
            # thread then stops it, and the drives react (tcp_bridge.motion.cyclic).
            self.heartbeat.start(driver=self.cyclic)
        if self.cyclic is not None:
            self.cyclic.begin()
        if self.pdo is not None:
            self.pdo.attach_worker(post)

    def close(self) -> None:
        """Called after the bus worker stopped: the drives' heartbeat consumers are
        switched off before the heartbeat stops (a clean shutdown trips nothing)."""
        if self.cyclic is not None:
            self.cyclic.finish_runs()  # cyclic moves ramp down while the heartbeat goes on
        if self.heartbeat is not None:
            self.heartbeat.stop(self.nodes.values())
        if self.cyclic is not None:
            self.cyclic.kill()
        try:
            self.network.disconnect()
        except Exception:  # already gone (adapter unplugged): nothing left to release
            pass
