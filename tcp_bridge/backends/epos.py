"""``epos``: an EPOS4 by any ``epos_link`` URL; its CAN gateway reaches the other nodes.

Bus options::

    url = "/dev/ttyACM0"      # any epos_link URL: serial path, usb://, socket://, sim://
    baudrate = 115200         # serial links only
    timeout = 0.5             # seconds per request (EposClient)
    retries = 1
    gateway_node_id = 1       # the EPOS4's own node id (default: the first axis's)
    eds = "none"              # "default" (EPOS4 EDS), a path, or "none"

One ``EposClient`` is shared by all nodes of the bus (it is thread-safe and
the bus worker serialises the traffic anyway); each axis gets a canopen
node from ``epos_link.connect_node`` with canopen's ``SdoBase`` interface.
"""
from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Sequence

from ..errors import BusUnavailable
from ..tables.axes import AxisConfig, BusConfig, ConfigError
from .canopen_bus import object_dictionary
from .heartbeat import refuse_heartbeat


# An EPOS4 answers a ReadObject within milliseconds (USB, or RS232 at 115200 Bd:
# ~2 ms of wire time); 0.2 s leaves room for a loaded host and still lets a
# probe every 0.25 s notice a device that came back within about a second.
PROBE_TIMEOUT = 0.2
# Bus options given to EposClient.open (eds and gateway_node_id are taken first).
OPTIONS = frozenset({"url", "baudrate", "timeout", "retries", "late_answer_timeout", "trace"})


class EposBackend:
    def __init__(self, bus: BusConfig, axes: Sequence[AxisConfig] = (), *,
                 client: Optional[Any] = None) -> None:
        from epos_link.client import EposClient
        from epos_link.transports import known_scheme

        self.name = bus.name
        options: Dict[str, Any] = dict(bus.options)
        refuse_heartbeat(bus.name, options, "epos")
        self.eds = options.pop("eds", "none")
        gateway = options.pop("gateway_node_id", axes[0].node_id if axes else None)
        if client is None:
            unknown = sorted(set(options) - OPTIONS)
            if unknown:  # else a transport would refuse them, like a port that is not there
                raise ConfigError(f"bus {bus.name}: unknown epos options {unknown}; known: "
                                  f"{', '.join(sorted(OPTIONS | {'eds', 'gateway_node_id'}))}")
            url = options.pop("url", None)
            if not isinstance(url, str):
                raise ConfigError(f"bus {bus.name}: the epos backend needs url = \"...\"")
            if not known_scheme(url):
                # A mistyped URL is not a device that is away: no silent bus for it.
                raise ConfigError(f"bus {bus.name}: url: {url!r} has no known scheme (a "
                                  f"device path, usb://, socket://, rfc2217://, sim://, ...)")
            try:
                client = EposClient.open(url, gateway_node_id=gateway, **options)
            except Exception as exc:  # TransportError, OSError, bad options
                # A transport error already says "cannot open URL: why": name the URL once.
                why = str(exc) if url in str(exc) else f"cannot open {url}: {exc}"
                if isinstance(exc, OSError):  # TransportError too: not there now
                    raise BusUnavailable(f"bus {bus.name}: {why}") from None
                raise ConfigError(f"bus {bus.name}: {why}") from None
        self.client = client
        self.url: str = getattr(client.transport, "url", "") or f"bus {bus.name}'s link"
        self.baudrate: Optional[int] = options.get("baudrate")
        self.nodes: Dict[int, Any] = {}

    def node(self, node_id: int) -> Any:
        from epos_link.canopen_adapter import connect_node

        node = self.nodes.get(node_id)
        if node is None:
            node = connect_node(self.client, node_id, object_dictionary(self.eds, node_id))
            self.nodes[node_id] = node
        return node

    def attach_wait(self, hook: Callable[[], None]) -> None:
        """Call ``hook`` whenever the client starts to wait on the link (tcp_bridge.bus.workers:
        a reply is handed over while the link carries the next request)."""
        self.client.on_wait = hook

    def probe(self) -> None:
        """Does the EPOS4 itself answer? (Fail-fast buses, :mod:`tcp_bridge.bus.failfast`.)

        Reads its device type, 1000h/00h, as node 0: the device on the link
        itself (Communication Guide, chapter 5 gateway addressing), so an absent
        node behind it cannot make the link look silent. One attempt with a
        short timeout: a failed probe is simply tried again later. After a
        transport failure the client reopens the link first, so this is also
        what reopens a USB/serial port that came back.
        """
        self.client.read_object(0, 0x1000, 0, timeout=min(self.client.timeout, PROBE_TIMEOUT),
                                retries=0)

    def patient_probe(self) -> None:
        """:meth:`probe` with the wait of an ordinary request (``timeout``, 0.5 s by default)
        instead of the short one: ``tcp-bridge check`` calls a device silent only when
        ``serve``'s requests would find it silent too (issue 34: a device answering in
        0.3 s was "silent" to check, which probed for 0.2 s, and served by serve)."""
        self.client.read_object(0, 0x1000, 0, timeout=self.client.timeout, retries=0)

    def describe_silence(self, why: str) -> str:
        """One line for a failed :meth:`probe`: the device, its URL, what to check."""
        from epos_link.transports import silence_hint

        return (f"the EPOS4 at {self.url} does not answer ({why}): "
                f"{silence_hint(self.url, self.baudrate)}")

    def close(self) -> None:
        self.client.close()
