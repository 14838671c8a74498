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

The command layer uses ``node.sdo.upload/download``, so without ``pdo`` the
EDS matters for tools, not for the bridge; "none" gives an empty dictionary.
With ``pdo = true`` the TPDOs are mapped through canopen's PDO API, which needs
the dictionary's 1800h/1A00h objects (and the mapped objects): an EDS is
required.
"""
from __future__ import annotations

import errno
import os
from typing import Any, Callable, Dict, Optional, Sequence

import canopen

from ..errors import BusUnavailable
from ..tables.axes import AxisConfig, BusConfig, ConfigError
from .pdo_status import PdoSettings, PdoStatus, StatusFeed


class FedNode(canopen.RemoteNode):  # type: ignore[misc]
    """A RemoteNode that may carry a :class:`StatusFeed` (``pdo = true``), which
    :class:`tcp_bridge.bus.sdo.SdoPort` consults for status reads."""

    status_feed: Optional[StatusFeed] = None


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
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # a quick notifier stop on close
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

    def node(self, node_id: int) -> FedNode:
        node = self.nodes.get(node_id)
        if node is None:
            node = FedNode(node_id, object_dictionary(self.eds, node_id))
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            node.sdo.MAX_RETRIES = self.sdo_retries
            self.network.add_node(node)
            if self.pdo is not None:
                node.status_feed = self.pdo.add(node)
            self.nodes[node_id] = node
        return node

    def attach_worker(self, post: Callable[[Callable[[], Any]], None]) -> None:
        """Called by the engine with its bus worker's ``post``: PDO mappings are set there."""
        if self.pdo is not None:
            self.pdo.attach_worker(post)

    def close(self) -> None:
        try:
            self.network.disconnect()
        except Exception:  # already gone (adapter unplugged): nothing left to release
            pass
