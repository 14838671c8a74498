"""canopen's own SDO interface through an EPOS4 USB/RS232 gateway.

``connect_node(url, node_id)`` returns a canopen ``RemoteNode`` (or
``BaseNode402``) whose ``.sdo`` is an :class:`EposSdoClient`: canopen's
``SdoBase`` with ``upload``/``download`` carried by :class:`EposClient`, the
same trick canopen's own ``SdoServer`` uses. Everything built on ``SdoBase``
works unchanged: ``node.sdo['Statusword'].raw``, ``.phys``, ``.bits``,
``.desc``, records and arrays, ``var.open()`` (text or binary, as canopen's),
``node.store()``, the PDO configuration (``node.pdo.read()``), and
``BaseNode402`` with ``setup_402_state_machine()``: the PDO configuration is
read by SDO, as canopen does, and the state machine then runs on SDO, since no
PDO arrives through the gateway.

What the gateway carries (guide chapter 5): SDO, as ReadObject/WriteObject and
segmented reads; NMT, as SendNMTService. :mod:`epos_link.canopen_gateway`
states what ``nmt.state``, ``nmt.wait_for_bootup()`` and
``network.scanner.search()`` mean through it. What it cannot carry: PDO
transmission and reception, SYNC, EMCY, heartbeat and node guarding, block
transfer, and a segmented write to a node other than the connected device
(guide 2.1.2.2). Those raise :class:`GatewayLimitationError` naming the
service, rather than canopen's "No actual Network object was assigned".

Every successful SDO transfer tells the link's NMT view that the node answered.

Errors are canopen's: a device error code becomes ``SdoAbortedError(code)``;
timeouts, framing and link failures become ``SdoCommunicationError``.
"""
from __future__ import annotations

import io
import threading
from typing import Any, Callable, Optional, Union

import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.profiles.p402 import BaseNode402, OperationMode
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from canopen.sdo.base import SdoBase

from .canopen_gateway import (GatewayLimitationError, GatewayNetwork, GatewayNmt, NmtView,
                              gateway_network, limitation as _limitation, nmt_view, probe)
from .client import EposClient
from .errors import (DeviceError, EposError, EposTimeoutError, GatewayNotSupportedError,
                     RemoteProtocolError, TransportError)


_SIZE_CACHE_LIMIT = 4096


class EposSdoClient(SdoBase):
    """canopen's SDO interface, carried by an :class:`EposClient`."""

    def __init__(self, client: EposClient, node_id: int, od: ObjectDictionary,
                 link_node: Optional[int] = None) -> None:
        super().__init__(0x600 + node_id, 0x580 + node_id, od)
        self.client = client
        self.canopen_id = node_id
        self._view: NmtView = nmt_view(client)
        # The node id put in the serial frames: 0 addresses the connected EPOS4
        # itself (guide chapter 5), whatever its CANopen id.
        self.node_id = node_id if link_node is None else link_node
        # _size() per object: the dictionary's lookup by number costs more than a
        # status poll's own Python (issue 10, bench/bridge.py).
        self._sizes: dict[tuple[int, int], Optional[int]] = {}

    def _call(self, fn: Callable[[], Any]) -> Any:
        try:
            result = fn()
        except DeviceError as exc:
            raise SdoAbortedError(exc.code) from exc
        except GatewayNotSupportedError as exc:
            raise GatewayLimitationError(str(exc)) from exc
        except (EposTimeoutError, RemoteProtocolError, TransportError) as exc:
            raise SdoCommunicationError(str(exc)) from exc
        self._view.answered(self.canopen_id)
        return result

    def _size(self, index: int, subindex: int) -> Optional[int]:
        """How to read an object: its size in bytes, or None for a segmented read.

        ReadObject (guide 2.1.1.1) is the transfer for values of up to 4 bytes,
        the one maxon's own library uses, and the only read the guide documents
        through the gateway for other nodes; its answer always carries 4 bytes,
        cut here to the object's size. So: a fixed size from the dictionary
        decides; a string or domain (no fixed size) is read segmented; an object
        the dictionary does not describe is read with ReadObject and its 4 data
        bytes are returned. Describe larger objects in the dictionary (pass the
        device's EDS) to read them whole.
        """
        key = (index, subindex)
        if key in self._sizes:
            return self._sizes[key]
        var = self.od.get_variable(index, subindex)
        size = 4 if var is None else len(var) // 8 if var.fixed_size else None
        if len(self._sizes) >= _SIZE_CACHE_LIMIT:
            self._sizes.clear()
        self._sizes[key] = size
        return size

    def upload(self, index: int, subindex: int) -> bytes:
        size = self._size(index, subindex)
        return bytes(self._call(lambda: self.client.upload(self.node_id, index, subindex, size)))

    def download(self, index: int, subindex: int, data: bytes, force_segment: bool = False) -> None:
        data = bytes(data)
        # canopen forces a segmented download for every DOMAIN; WriteObject carries
        # a value of up to 4 bytes just as well, so the flag only matters above that,
        # where the client picks a segmented write anyway.
        self._call(lambda: self.client.download(self.node_id, index, subindex, data))

    def open(self, index: int, subindex: int = 0, mode: str = "rb", encoding: str = "ascii",
             buffering: int = 1024, size: Optional[int] = None, block_transfer: bool = False,
             force_segment: bool = False, request_crc_support: bool = True) -> Any:
        """A file-like object over the whole value: reading uploads it at once,
        writing downloads it when the stream is closed."""
        if block_transfer:
            raise _limitation("SDO block transfer")
        binary = "b" in mode  # canopen's SdoClient.open: text unless "b"
        if "r" in mode:
            raw: io.IOBase = io.BytesIO(self.upload(index, subindex))
        elif "w" in mode:
            raw = _DownloadOnClose(lambda data: self.download(index, subindex, data, force_segment))
        else:
            raise ValueError(f"mode {mode!r}: use 'r' or 'w', with 'b' or 't'")
        if binary:
            return raw
        return io.TextIOWrapper(raw, encoding=encoding, line_buffering=buffering == 1)  # type: ignore[arg-type]


class _DownloadOnClose(io.BytesIO):
    def __init__(self, send: Callable[[bytes], None]) -> None:
        super().__init__()
        self._send = send

    def close(self) -> None:
        if not self.closed:
            data = self.getvalue()
            super().close()
            self._send(data)


class _GatewayNodeMixin:
    """Shared by the RemoteNode and BaseNode402 flavours: SDO on the gateway."""

    _epos_client: EposClient
    _link_node: Optional[int] = None
    _shared_url: Optional[str] = None  # opened by URL: the link is shared (_LINKS)
    _owns_link = True  # False for a node of network.add_node: the network's link

    def add_sdo(self, rx_cobid: int, tx_cobid: int) -> EposSdoClient:
        # RemoteNode.__init__ calls this; building the client here (instead of
        # replacing node.sdo afterwards) keeps the PDO maps on the same client.
        client = EposSdoClient(self._epos_client, self.id, self.object_dictionary,  # type: ignore[attr-defined]
                               self._link_node)
        self.sdo_channels.append(client)  # type: ignore[attr-defined]
        return client

    def _attach_gateway(self) -> None:
        node: Any = self
        network = gateway_network(self._epos_client)  # one per link, as one bus
        network.nodes.setdefault(node.id, node)
        node.nmt = GatewayNmt(node.id, self._epos_client)
        node.network = network
        for part in (node.sdo, node.pdo, node.tpdo, node.rpdo, node.nmt, node.emcy):
            part.network = network
        for pdo_map in list(node.tpdo.map.values()) + list(node.rpdo.map.values()):
            pdo_map.wait_for_reception = _refuse_reception  # instance only
        node.emcy.wait = _refuse_emcy

    @property
    def epos_client(self) -> EposClient:
        return self._epos_client

    def close(self) -> None:
        """Close the link (and the client) this node was opened with. A node opened by
        URL releases the link instead: it closes with the last such node. A node of
        ``network.add_node`` leaves the link to the nodes that opened it."""
        if self._shared_url is not None:
            url, self._shared_url = self._shared_url, None
            _LINKS.release(url, self._epos_client)
        elif self._owns_link:
            self._owns_link = False
            self._epos_client.close()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _refuse_reception(timeout: float = 10) -> float:
    raise _limitation("PDO reception")


def _refuse_emcy(emcy_code: Optional[int] = None, timeout: float = 10) -> Any:
    raise _limitation("EMCY reception")


class EposRemoteNode(_GatewayNodeMixin, canopen.RemoteNode):
    def __init__(self, node_id: int, od: Any, client: EposClient,
                 link_node: Optional[int] = None) -> None:
        self._epos_client = client
        self._link_node = link_node
        canopen.RemoteNode.__init__(self, node_id, od)
        self._attach_gateway()


class EposNode402(_GatewayNodeMixin, BaseNode402):
    """BaseNode402 over SDO alone. The state machine's timeouts are widened for
    a serial link: each step is a WriteObject and polls of ReadObject (about
    2 ms a round trip at 115200 baud, more through the gateway)."""

    TIMEOUT_SWITCH_OP_MODE = 2.0
    TIMEOUT_SWITCH_STATE_FINAL = 2.0
    TIMEOUT_SWITCH_STATE_SINGLE = 1.0
    TIMEOUT_CHECK_TPDO = 0.2
    TIMEOUT_HOMING_DEFAULT = 30
    INTERVAL_CHECK_STATE = 0.005

    def __init__(self, node_id: int, od: Any, client: EposClient,
                 link_node: Optional[int] = None) -> None:
        self._epos_client = client
        self._link_node = link_node
        BaseNode402.__init__(self, node_id, od)
        self._attach_gateway()

    def setup_pdos(self, upload: bool = True) -> None:
        """canopen's, after one probe when the NMT state is not known yet.

        canopen asserts that the node is PRE-OPERATIONAL or OPERATIONAL before
        reading the PDO configuration by SDO. On a bus a heartbeat tells; here
        the gateway can only ask, so a node never heard from is probed once
        (read of 1000h) and is PRE-OPERATIONAL if it answers. A node this
        adapter stopped is not probed: canopen's assertion stands.
        """
        if upload and self.nmt.state == "INITIALISING":
            assert self.id is not None  # set by __init__
            probe(self._epos_client, self.id)
        super().setup_pdos(upload)

    # PDOs never arrive through the gateway, so values "from the last TPDO"
    # would be stale forever: the state machine always uses SDO, and the
    # "not configured in PDOs" warnings do not apply.
    def _init_tpdo_values(self) -> None:
        pass

    def _init_rpdo_pointers(self) -> None:
        pass

    def _check_controlword_configured(self) -> None:
        pass

    def _check_statusword_configured(self) -> None:
        pass

    def _check_op_mode_configured(self) -> None:
        pass

    @property
    def statusword(self) -> int:
        return int(self.sdo[0x6041].raw)

    @property
    def op_mode(self) -> str:
        return str(OperationMode.CODE2NAME[self.sdo[0x6061].raw])

    @op_mode.setter
    def op_mode(self, mode: str) -> None:
        BaseNode402.op_mode.fset(self, mode)  # type: ignore[attr-defined]


def default_eds() -> str:
    """The simulator's EPOS4 EDS, the default object dictionary."""
    from .simulator.od import EDS_PATH

    return str(EDS_PATH)


def connect_node(url: Union[str, EposClient], node_id: int,
                 od: Union[str, ObjectDictionary, None] = None, *, profile: Optional[str] = None,
                 gateway_node_id: Optional[int] = None, **client_options: Any) -> Any:
    """A canopen node reached through the EPOS4 at ``url`` (any epos_link URL) or
    through an open :class:`EposClient` shared by several nodes.

    Several nodes of one link in one program: call it again with the same ``url``
    (the link is opened once and shared, see :class:`_Links`), with
    ``node.epos_client``, or use ``node.network.add_node(id, od)``.

    ``node_id`` 0 (or the EPOS4's own id) is the connected EPOS4 itself; any other
    id is a node on its CAN bus. ``od`` is an EDS/DCF path or an ObjectDictionary;
    by default the shipped EPOS4 EDS. ``profile="402"`` returns a ``BaseNode402``.
    ``client_options`` go to :meth:`EposClient.open` (timeout, retries, baudrate, trace).
    """
    if profile not in (None, "402"):
        raise ValueError(f"profile must be None or '402', got {profile!r}")
    if not 0 <= node_id <= 127:
        raise ValueError(f"node id must be 0..127, got {node_id}")
    if isinstance(url, EposClient):
        client = url
    else:
        client = _LINKS.acquire(url, client_options)
    if gateway_node_id is not None:
        client.gateway_node_id = gateway_node_id
    try:
        link_node: Optional[int] = None
        canopen_id = node_id
        if node_id == 0:
            # canopen needs a real node id: ask the EPOS4 for its own (0x2000).
            canopen_id = own_node_id(client)
            nmt_view(client).answered(canopen_id)
            client.gateway_node_id = canopen_id
            link_node = 0
        if od is None:
            od = default_eds()
        if isinstance(od, str):
            from .simulator.od import add_value_descriptions

            od = canopen.import_od(od, canopen_id)
            add_value_descriptions(od)
        cls = EposNode402 if profile == "402" else EposRemoteNode
        node = cls(canopen_id, od, client, link_node)
    except Exception:
        if not isinstance(url, EposClient):
            _LINKS.release(url, client)
        raise
    if not isinstance(url, EposClient):
        node._shared_url = url
    return node


class _Links:
    """The links ``connect_node`` opened by URL, shared by the nodes opened on each.

    A link serves one host at a time (the EPOS4 answers one request at a time, guide
    2.2.1; a serial port is opened exclusively, and ``epos-link sim --tcp`` takes one
    connection): a second ``connect_node(url, ...)`` in one program reuses the
    first's :class:`EposClient`, as ``connect_node(node.epos_client, ...)`` does.
    The link closes when the last node opened by URL is closed. The options of the
    call that opened it (timeout, retries, baudrate, trace) hold for all its nodes.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open: dict[str, tuple[EposClient, int]] = {}  # url -> (client, holders)

    def acquire(self, url: str, options: dict[str, Any]) -> EposClient:
        with self._lock:
            client, holders = self._open.get(url, (None, 0))
            if client is None:
                client = EposClient.open(url, **options)
            self._open[url] = (client, holders + 1)
            return client

    def release(self, url: str, client: EposClient) -> None:
        with self._lock:
            held, holders = self._open.get(url, (None, 0))
            if held is not client:
                return
            if holders > 1:
                self._open[url] = (client, holders - 1)
                return
            del self._open[url]
        client.close()


_LINKS = _Links()


NODE_ID_OBJECT = 0x2000  # maxon EPOS4: Node-ID (DIP switch or software setting)


def own_node_id(client: EposClient) -> int:
    """The connected EPOS4's own CANopen node id, read from 0x2000 of node 0."""
    try:
        value = client.read_object(0, NODE_ID_OBJECT, 0)[0]
    except DeviceError as exc:
        raise SdoAbortedError(exc.code) from exc
    except EposError as exc:
        raise SdoCommunicationError(f"cannot read the EPOS4's node id: {exc}") from exc
    if not 1 <= value <= 127:
        raise SdoCommunicationError(f"the EPOS4 reports node id {value}, not 1..127")
    return value


__all__ = ["EposNode402", "EposRemoteNode", "EposSdoClient", "GatewayLimitationError",
           "GatewayNetwork", "connect_node", "default_eds", "own_node_id"]
