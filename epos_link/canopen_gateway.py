"""What canopen's network services become through an EPOS4 USB/RS232 gateway.

The gateway (guide chapter 5) forwards SDO (ReadObject/WriteObject and
segmented reads) and NMT commands (SendNMTService, guide Table 3-14). It forwards
no CAN frame towards the host: no heartbeat, no boot-up message, no EMCY, no
PDO. This module gives canopen's ``Network``, ``NmtMaster`` and
``NodeScanner`` the meaning they can have with that much:

NMT state, as far as the gateway can know it (one :class:`NmtView` per link,
shared by every node object opened on the same :class:`EposClient`). The facts
used are those of guide 3.3.3.5, Table 3-13: a node enters Pre-Operational by
itself once initialised and sends a boot-up message; it answers SDO in
Pre-Operational and Operational, not in Stopped nor while initialising; Reset
Node and Reset Communication lead through initialisation to Pre-Operational.

* unknown until the node first answers an SDO request; canopen spells
  unknown ``INITIALISING``, as it does on a bus before any heartbeat;
* ``PRE-OPERATIONAL`` once the node has answered an SDO request, unless this
  adapter has sent an NMT command for another state;
* ``OPERATIONAL``, ``STOPPED`` or ``PRE-OPERATIONAL`` once this adapter has
  sent the command for that state (Table 3-14) and the gateway acknowledged
  it, as canopen's ``NmtMaster`` does on a bus; an SDO answer does not
  override it;
* after a reset (node or communication) sent through the gateway: unknown
  again until the node answers an SDO request, then ``PRE-OPERATIONAL``.

Commands to node 0 (all nodes) apply to every node, those seen later included.
A command sent by someone else (another master, a power cycle) is not seen.

``wait_for_bootup(timeout)`` means: after a reset sent through this gateway,
wait until the node answers SDO again: it reads 1000h (the device type, a
mandatory object of every CANopen node, as ``epos-link scan`` does) until an
answer comes. Any failure counts as "still booting": the gateway's SDO
timeout, a link timeout, even a dropped link (resetting the EPOS4 at the
other end of the cable may drop its USB link; the client reopens the link on
the next request). It
raises canopen's ``NmtError`` when the node has not answered within
``timeout`` (plus at most one request timeout), and
:class:`GatewayLimitationError` when no reset was sent through this link,
since the boot-up message itself never reaches the host.

``network.scanner.search(limit)`` probes node ids 1..limit as ``epos-link
scan`` does (:meth:`EposClient.scan`: ReadObject 1000h, short timeout, no
retry) and fills ``scanner.nodes`` as canopen does on a bus. It returns when
done: each absent node costs the gateway's SDO timeout.

``network.add_node(node_id, od)`` adds a node reached through the same
gateway, as canopen adds a ``RemoteNode`` to a bus: one :class:`GatewayNetwork`
per link (:func:`gateway_network`), shared by every node object opened on its
:class:`EposClient`, so ``node.network.add_node(3)`` and ``network[3]`` work as
on a bus. ``add_node(..., upload_eds=True)`` (0x1021 read by a raw SDO client)
and a ``RemoteNode`` built for a CAN bus are refused, naming what to do.

Anything else that needs a raw CAN frame raises
:class:`GatewayLimitationError`, naming the service.
"""
from __future__ import annotations

import threading
import time
import weakref
from dataclasses import dataclass
from typing import Any, Callable, Optional

import canopen
from canopen.network import NodeScanner
from canopen.nmt import NmtError, NmtMaster
from canopen.sdo import SdoCommunicationError

from .client import EposClient
from .codes import NmtCommand
from .errors import (DeviceError, EposError, EposTimeoutError, GatewayNotSupportedError,
                     RemoteProtocolError, TransportError)

NMT_COB_ID = 0x000
SDO_RESPONSE_BASE = 0x580  # guide Table 3-15: SDO1 (tx), server to client
DEVICE_TYPE = 0x1000  # mandatory on every CANopen node (our EDS: [MandatoryObjects])

# canopen's NMT state codes (canopen.nmt.NMT_STATES, the heartbeat's state byte).
UNKNOWN, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0, 4, 5, 127
_RESETS = frozenset({NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION})
_COMMANDED = {NmtCommand.START_REMOTE_NODE: OPERATIONAL, NmtCommand.STOP_REMOTE_NODE: STOPPED,
              NmtCommand.ENTER_PRE_OPERATIONAL: PRE_OPERATIONAL}


class GatewayLimitationError(SdoCommunicationError, GatewayNotSupportedError):
    """A CANopen service that the EPOS4 USB/RS232 gateway cannot carry."""


def limitation(what: str) -> GatewayLimitationError:
    return GatewayLimitationError(
        f"{what} cannot be carried by the EPOS4 USB/RS232 gateway: it forwards only SDO "
        "(ReadObject/WriteObject, segmented reads) and NMT (SendNMTService); use a CAN "
        "adapter for PDO, SYNC, EMCY and heartbeat")


@dataclass
class _Known:
    commanded: Optional[int] = None  # the state an acknowledged NMT command leads to
    answered: bool = False  # answered SDO since the last reset sent through the gateway
    resetting: bool = False  # a reset was sent and the node has not answered since


class NmtView:
    """Each node's NMT state as far as the gateway can know it (rules in the
    module docstring). Thread-safe; at most 128 entries (node ids 0..127)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._nodes: dict[int, _Known] = {}
        self._all = _Known()  # what broadcast commands said, for nodes not seen yet

    def _get(self, node: int) -> _Known:
        known = self._nodes.get(node)
        if known is None:
            known = self._nodes[node] = _Known(self._all.commanded, False, self._all.resetting)
        return known

    def state(self, node: int) -> int:
        """canopen's state code: 0 (unknown), 4, 5 or 127. Node 0 (all nodes):
        what the broadcast commands said."""
        with self._lock:
            known = self._nodes.get(node, self._all)
            if known.resetting:
                return UNKNOWN
            if known.commanded is not None:
                return known.commanded
            return PRE_OPERATIONAL if known.answered else UNKNOWN

    def resetting(self, node: int) -> bool:
        with self._lock:
            return self._nodes.get(node, self._all).resetting

    def answered(self, node: int) -> None:
        """The node answered an SDO request: it is alive and not STOPPED."""
        if node == 0:  # "all nodes" answers nothing; the EPOS4 itself has its own id
            return
        with self._lock:
            known = self._get(node)
            known.answered, known.resetting = True, False

    def sent(self, node: int, command: int) -> None:
        """The gateway acknowledged NMT ``command`` to ``node`` (0: all nodes)."""
        with self._lock:
            targets = [self._all, *self._nodes.values()] if node == 0 else [self._get(node)]
            for known in targets:
                if command in _RESETS:
                    # A reset node initialises, then enters Pre-Operational by
                    # itself (guide Table 3-13): earlier commands no longer hold.
                    known.commanded, known.answered, known.resetting = None, False, True
                elif command in _COMMANDED:
                    known.commanded = _COMMANDED[NmtCommand(command)]


_views: "weakref.WeakKeyDictionary[EposClient, NmtView]" = weakref.WeakKeyDictionary()
_views_lock = threading.Lock()


def nmt_view(client: EposClient) -> NmtView:
    """The one :class:`NmtView` of the link ``client`` drives."""
    with _views_lock:
        view = _views.get(client)
        if view is None:
            view = _views[client] = NmtView()
        return view


def probe(client: EposClient, node: int, timeout: Optional[float] = None) -> bool:
    """Whether ``node`` answers a read of 1000h (no retry); an answer is noted
    in the link's :class:`NmtView`. Every failure means "not answering"; a
    broken link is reopened by the client on the next request."""
    try:
        client.read_object(node, DEVICE_TYPE, 0, timeout=timeout, retries=0)
    except (DeviceError, EposTimeoutError, RemoteProtocolError, TransportError):
        return False
    nmt_view(client).answered(node)
    return True


class GatewayNmt(NmtMaster):
    """canopen's ``NmtMaster`` whose state is the link's :class:`NmtView`.

    Commands go through the network (SendNMTService), which records them in
    the view once the gateway acknowledged them.
    """

    BOOTUP_POLL_INTERVAL = 0.02  # s between probes that failed at once
    clock: Callable[[], float] = staticmethod(time.monotonic)  # type: ignore[assignment]
    sleep: Callable[[float], None] = staticmethod(time.sleep)  # type: ignore[assignment]

    def __init__(self, node_id: int, client: EposClient) -> None:
        self._view = nmt_view(client)
        self._client = client
        super().__init__(node_id)

    @property  # type: ignore[override]
    def _state(self) -> int:
        return self._view.state(self.id)

    @_state.setter
    def _state(self, value: int) -> None:
        # canopen writes its guess here before the command is even sent; the
        # view only takes what the gateway acknowledged (GatewayNetwork.send_message).
        pass

    def wait_for_heartbeat(self, timeout: float = 10) -> str:
        raise limitation("heartbeat")

    def wait_for_bootup(self, timeout: float = 10) -> None:
        """After a reset sent through the gateway: wait until the node answers SDO."""
        if self.id == 0:
            raise limitation("the boot-up messages of all nodes (wait on each node's nmt)")
        if not self._view.resetting(self.id):
            raise limitation("the boot-up message (wait_for_bootup() through the gateway waits "
                             "for a node reset through it to answer SDO again; no reset was sent)")
        deadline = self.clock() + timeout
        while True:
            started = self.clock()
            if probe(self._client, self.id):
                return
            now = self.clock()
            if now >= deadline:
                raise NmtError("Timeout waiting for boot-up message")
            if now - started < self.BOOTUP_POLL_INTERVAL:  # failed at once: do not hammer
                self.sleep(min(self.BOOTUP_POLL_INTERVAL, deadline - now))

    def start_node_guarding(self, period: float) -> None:
        raise limitation("node guarding")


class GatewayScanner(NodeScanner):
    """canopen's ``NodeScanner`` whose ``search`` probes through the gateway."""

    network: "GatewayNetwork"

    def search(self, limit: int = 127) -> None:
        """Probe node ids 1..``limit`` as ``epos-link scan`` does; each node that
        answers is added to ``nodes``, as its SDO response would be on a bus."""
        client = self.network.client
        try:
            found = client.scan(range(1, limit + 1))
        except TransportError as exc:
            raise SdoCommunicationError(f"scan through the gateway failed: {exc}") from exc
        view = nmt_view(client)
        for info in found:
            view.answered(info.node)
            self.on_message_received(SDO_RESPONSE_BASE + info.node)


class GatewayNetwork(canopen.Network):
    """Stands in for a CAN network: NMT goes through SendNMTService, the scanner
    probes by SDO, anything else that needs raw CAN frames raises
    :class:`GatewayLimitationError`."""

    def __init__(self, client: EposClient) -> None:
        super().__init__(bus=None)
        self.client = client
        self.scanner = GatewayScanner(self)
        self.nmt = GatewayNmt(0, client)  # canopen's broadcast NmtMaster(0)
        self.nmt.network = self

    def add_node(self, node: Any, object_dictionary: Any = None,
                 upload_eds: bool = False) -> Any:
        """canopen's ``add_node``: a node of this link, reached through its gateway.

        ``node`` is a node id (with ``object_dictionary``: an EDS/DCF path or an
        ObjectDictionary, by default the shipped EPOS4 EDS) or a node object that
        :func:`epos_link.connect_node` made for this link."""
        from .canopen_adapter import connect_node

        if upload_eds:
            raise limitation("upload_eds (0x1021 read by a raw SDO client): pass the "
                             "node's EDS as object_dictionary")
        if isinstance(node, int):
            node = connect_node(self.client, node, object_dictionary)
            node._owns_link = False  # as on a bus: the network's nodes do not own the link
        elif getattr(node, "epos_client", None) is not self.client:
            raise TypeError(
                f"{type(node).__name__} {node.id} was built for a CAN bus; through the gateway "
                f"add it by id, network.add_node({node.id}, od), or connect_node(client, "
                f"{node.id}, od)")
        self.nodes[node.id] = node
        return node

    def connect(self, *args: Any, **kwargs: Any) -> "GatewayNetwork":
        raise limitation("a CAN bus connection")

    def subscribe(self, can_id: int, callback: Callable[..., Any]) -> None:
        # Registering interest is harmless (pdo.read() does it); nothing will arrive.
        super().subscribe(can_id, callback)

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if can_id == NMT_COB_ID and len(data) >= 2:
            command, node = data[0], data[1]
            try:
                self.client.nmt(node, command)
            except EposError as exc:
                raise SdoCommunicationError(f"NMT through the gateway failed: {exc}") from exc
            nmt_view(self.client).sent(node, command)
            return
        raise limitation(describe_cob_id(can_id))

    def send_periodic(self, can_id: int, data: bytes, period: float, remote: bool = False) -> Any:
        raise limitation(f"periodic CAN frames (COB-ID 0x{can_id:03X}: PDO, SYNC or heartbeat)")


_networks_lock = threading.Lock()  # not _views_lock: a new network takes that one


def gateway_network(client: EposClient) -> GatewayNetwork:
    """The one :class:`GatewayNetwork` of the link ``client`` drives.

    Kept on the client itself (a reference cycle the collector frees with it),
    not in a registry: the network holds its client and its nodes.
    """
    with _networks_lock:
        network = getattr(client, "_canopen_network", None)
        if network is None:
            network = GatewayNetwork(client)
            client._canopen_network = network  # type: ignore[attr-defined]
        return network


def describe_cob_id(can_id: int) -> str:
    """What a raw CAN frame would have been, by the default connection set (guide Table 3-15)."""
    function = can_id & 0x780
    kinds = {0x080: "a SYNC or EMCY message", 0x100: "a TIME message",
             0x580: "a raw SDO frame", 0x600: "a raw SDO frame", 0x700: "a heartbeat or node guarding frame"}
    kind = kinds.get(function, "a PDO" if 0x180 <= function <= 0x500 else "a raw CAN frame")
    return f"{kind} (COB-ID 0x{can_id:03X})"
