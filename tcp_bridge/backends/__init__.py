"""Backends: how a bus of the axis table is reached; a registry imported lazily.

Like python-can's ``can.interfaces``, the registry maps a name to
``"module:factory"`` and imports the module only when a bus uses it, so a
missing optional dependency breaks only its own backend. More backends can be
added by installed packages through the ``tcp_bridge.backends`` entry point
group.

A factory is called as ``factory(bus: BusConfig, axes: list[AxisConfig])``
and returns a :class:`Backend`: ``node(node_id)`` gives an object with
canopen's SDO interface (``node.sdo.upload/download``, ``node.nmt.state``),
``close()`` releases the bus. Every backend presents that same interface, so
there is one command implementation (:mod:`tcp_bridge.engine`).

=========  ==================================================================
canopen    python-can with any interface and channel, a ``canopen.Network``
epos       an EPOS4 reached by an ``epos_link`` URL, its CAN gateway for the
           other nodes (through ``epos_link.connect_node``)
sim        the embedded simulated EPOS4 and drives behind it (over the epos path,
           or on its CAN bus through canopen)
instant    in-process fake CiA 402 drives that answer at once (tests, bench)
ethercat   EtherCAT slaves with CoE (EPOS4 EtherCAT) on a network card, through
           pysoem (optional: ``pip install 'epos-link[ethercat]'``)
=========  ==================================================================
"""
from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Protocol, Sequence

from ..tables.axes import ConfigError

if TYPE_CHECKING:
    from ..tables.axes import AxisConfig, BusConfig

BACKENDS: Dict[str, str] = {
    "canopen": "tcp_bridge.backends.canopen_bus:CanopenBackend",
    "epos": "tcp_bridge.backends.epos:EposBackend",
    "sim": "tcp_bridge.backends.sim:open_sim",
    "instant": "tcp_bridge.backends.instant:InstantBackend",
    "ethercat": "tcp_bridge.backends.ethercat:EthercatBackend",
}
ENTRY_POINT_GROUP = "tcp_bridge.backends"


class Backend(Protocol):
    def node(self, node_id: int) -> Any: ...

    def close(self) -> None: ...


def _entry_points() -> Dict[str, str]:
    from importlib.metadata import entry_points

    if sys.version_info >= (3, 10):
        found = entry_points(group=ENTRY_POINT_GROUP)
    else:  # pragma: no cover
        found = entry_points().get(ENTRY_POINT_GROUP, [])
    return {ep.name: ep.value for ep in found}


def known_backends() -> List[str]:
    """The names a table's ``backend`` may take: the built-in ones and the entry points'."""
    return sorted({*BACKENDS, *_entry_points()})


def factory_for(name: str) -> Callable[..., Backend]:
    """The factory registered for ``name``; ConfigError if there is none or it cannot load."""
    target = BACKENDS.get(name) or _entry_points().get(name)
    if target is None:
        raise ConfigError(f"unknown backend {name!r}; known: {', '.join(known_backends())}")
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"backend {name!r} is not available: {exc}") from None
    return getattr(module, attr)


def open_backend(bus: "BusConfig", axes: Sequence["AxisConfig"]) -> Backend:
    """Create the backend of ``bus`` for ``axes`` (those of the table on that bus)."""
    return factory_for(bus.backend)(bus, list(axes))
