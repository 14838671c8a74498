"""EposClient: read and write objects of an EPOS4 and of the CANopen nodes behind it.

The client builds on :class:`epos_link.link.Link`, which owns the exchange
itself: one request in flight, each request's deadline, retries and reopening
the transport, and dropping late answers (guide 2.2.1, 2.2.7). Those rules are
stated in :mod:`epos_link.link`, with the code that implements them; this
module adds what is asked for and how: objects, segmented transfers, NMT and
the node scan. The two modules are the only places with clocks, retries and
locks; framing, messages and the segmented-transfer state machines are pure.

Gateway addressing (guide chapter 5): node id 0 is the device on the USB/RS232
link, as is its own (DIP switch) node id; any other id is forwarded to that
node as an SDO. The gateway does not forward segmented writes (guide 2.1.2.2),
so :meth:`EposClient.download` of more than 4 bytes to another node raises
:class:`GatewayNotSupportedError` before anything is sent.

Segmented transfers (guide 2.1.1.2-2.1.1.3, 2.1.2.2-2.1.2.3) are one call
each: the link's lock covers every segment, and its retry rules apply to the
transfer as a whole. A segmented transfer that fails part-way is restarted
from its Initiate request, never resumed; a device "Toggle error"
(0x05030000) during one is retried the same way as a "CRC error".

Scanning: a node that does not answer leaves the link out of step until the
gateway's late answer comes (see "Late answers" in :mod:`epos_link.link`), so
a scan with a short per-node timeout still costs, per absent node, the
gateway's own SDO timeout.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Iterable, Optional, Union

from .codes import MAX_SEGMENT, ErrorCode, NmtCommand
from .errors import (
    DeviceError,
    EposTimeoutError,
    GatewayNotSupportedError,
    LocalProtocolError,
    RemoteProtocolError,
    TransportError,
)
from .link import DEFAULT_RETRIES, DEFAULT_TIMEOUT, WAKE_EARLY, ClientStats, Link
from .messages import (
    ANSWER_TYPES,
    AnyAnswer,
    Message,
    ReadObject,
    ReadObjectAnswer,
    SendNMTService,
    StatusAnswer,
    WriteObject,
)
from .segmented import DEFAULT_MAX_LENGTH, SegmentedRead, SegmentedWrite
from .transports.base import Transport

DEFAULT_SCAN_TIMEOUT = 0.1
_FRAME_CACHE_LIMIT = 4096

# Within a segmented transfer a lost answer desynchronises the toggle bit; "CRC
# error" (our request arrived damaged) is retried as for any request (epos_link.link).
_RETRY_CODES_SEGMENTED = frozenset({ErrorCode.CRC_ERROR, ErrorCode.TOGGLE_ERROR})

NMT_COMMANDS: dict[str, NmtCommand] = {
    "start": NmtCommand.START_REMOTE_NODE,
    "stop": NmtCommand.STOP_REMOTE_NODE,
    "preop": NmtCommand.ENTER_PRE_OPERATIONAL,
    "reset": NmtCommand.RESET_NODE,
    "reset-comm": NmtCommand.RESET_COMMUNICATION,
}
# A reset may stop the device before it answers; sending it twice would reset twice.
_NO_RETRY_NMT = frozenset({NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION})


@dataclass(frozen=True)
class NodeInfo:
    """What :meth:`EposClient.scan` learns about a node that answered.

    ``device_type`` is object 0x1000; ``name`` is 0x1008 (None if the node
    has none); the rest are 0x1018 subindices 1-4 (None when missing).
    """

    node: int
    device_type: int
    name: Optional[str] = None
    vendor_id: Optional[int] = None
    product_code: Optional[int] = None
    revision: Optional[int] = None
    serial_number: Optional[int] = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _u32(data: bytes) -> int:
    return int.from_bytes(data[:4], "little")


def _check_node(node: int) -> None:
    # CANopen node ids are 1..127 (CiA 301); 0 addresses the gateway itself.
    if not isinstance(node, int) or not 0 <= node <= 127:
        raise LocalProtocolError(f"node id {node!r} is not 0..127")


class EposClient(Link):
    """A thread-safe client over one :class:`Transport`; closing it closes the transport.

    ``gateway_node_id`` is the connected device's own node id, when known: a
    segmented write to it is executed locally, so it is allowed like node 0.
    """

    def __init__(self, transport: Transport, *, gateway_node_id: Optional[int] = None,
                 timeout: float = DEFAULT_TIMEOUT, retries: int = DEFAULT_RETRIES,
                 segment_size: int = MAX_SEGMENT, max_upload: int = DEFAULT_MAX_LENGTH,
                 late_answer_timeout: float = DEFAULT_TIMEOUT) -> None:
        super().__init__(transport, timeout=timeout, retries=retries,
                         late_answer_timeout=late_answer_timeout)
        if gateway_node_id is not None:
            _check_node(gateway_node_id)
        self.gateway_node_id = gateway_node_id
        self.segment_size = segment_size
        self.max_upload = max_upload
        # Encoded ReadObject frames and their names: the hot path encodes nothing.
        self._read_frames: dict[tuple[int, int, int], tuple[bytes, str]] = {}

    @classmethod
    def open(cls, url: str, *, trace: Optional[str] = None, baudrate: Optional[int] = None,
             gateway_node_id: Optional[int] = None, timeout: float = DEFAULT_TIMEOUT,
             retries: int = DEFAULT_RETRIES, late_answer_timeout: float = DEFAULT_TIMEOUT,
             **transport_options: Any) -> "EposClient":
        """Open ``url`` (see :func:`epos_link.transports.open_transport`); ``trace``
        names a capture file that records the traffic."""
        from .transports import open_transport

        if baudrate is not None:
            transport_options["baudrate"] = baudrate
        transport = open_transport(url, **transport_options)
        if trace:
            from .transports.trace import trace_to_file

            try:
                transport = trace_to_file(transport, trace)
            except TransportError:
                transport.close()
                raise
        return cls(transport, gateway_node_id=gateway_node_id, timeout=timeout, retries=retries,
                   late_answer_timeout=late_answer_timeout)

    # --- one request, one call -----------------------------------------------

    def request(self, message: Message, *, timeout: Optional[float] = None,
                retries: Optional[int] = None) -> AnyAnswer:
        """Send any request of guide 2.1 and return its decoded answer.

        A non-zero error code raises :class:`DeviceError`. Segmented requests
        sent this way are not retried as a transfer: use upload/download.
        """
        frame = message.encode()
        answer_type = ANSWER_TYPES[type(message)]
        what = _where(message)

        def op(t: float) -> AnyAnswer:
            answer = self._exchange(frame, answer_type, t, what)
            if answer.error_code:
                raise DeviceError(answer.error_code, what)
            return answer  # type: ignore[no-any-return]

        return self._call(op, timeout, retries)

    # --- objects ---------------------------------------------------------------

    def read_object(self, node: int, index: int, subindex: int, *, timeout: Optional[float] = None,
                    retries: Optional[int] = None) -> bytes:
        """ReadObject (0x60, guide 2.1.1.1): the 4 data bytes of the answer, padding included."""
        key = (node, index, subindex)
        cached = self._read_frames.get(key)
        if cached is None:
            _check_node(node)
            cached = (ReadObject(node, index, subindex).encode(),
                      "ReadObject " + _address(node, index, subindex))
            if len(self._read_frames) >= _FRAME_CACHE_LIMIT:
                self._read_frames.clear()
            self._read_frames[key] = cached
        frame, what = cached

        def op(t: float) -> bytes:
            answer = self._exchange(frame, ReadObjectAnswer, t, what)
            if answer.error_code:
                raise DeviceError(answer.error_code, what)
            return answer.data  # type: ignore[no-any-return]

        return self._call(op, timeout, retries)

    def write_object(self, node: int, index: int, subindex: int, data: bytes, *,
                     timeout: Optional[float] = None, retries: Optional[int] = None) -> None:
        """WriteObject (0x68, guide 2.1.2.1): up to 4 bytes, zero padded to the field's 4."""
        _check_node(node)
        data = bytes(data)
        if len(data) > 4:
            raise LocalProtocolError(f"WriteObject carries at most 4 bytes, got {len(data)}: use download()")
        frame = WriteObject(node, index, subindex, data.ljust(4, b"\x00")).encode()
        what = "WriteObject " + _address(node, index, subindex)

        def op(t: float) -> None:
            answer = self._exchange(frame, StatusAnswer, t, what)
            if answer.error_code:
                raise DeviceError(answer.error_code, what)

        self._call(op, timeout, retries)

    def upload(self, node: int, index: int, subindex: int, size: Optional[int] = None, *,
               timeout: Optional[float] = None, retries: Optional[int] = None) -> bytes:
        """Read an object of any size.

        ``size`` 0..4: one ReadObject, the first ``size`` bytes returned.
        ``size`` None or above 4: a segmented read (guide 2.1.1.2-2.1.1.3); the
        whole object is returned, whatever its length.
        """
        if size is not None and 0 <= size <= 4:
            return self.read_object(node, index, subindex, timeout=timeout, retries=retries)[:size]
        _check_node(node)

        def op(t: float) -> bytes:
            machine = SegmentedRead(node, index, subindex, max_length=self.max_upload)
            self._run(machine, machine.start(), t)
            return machine.data

        return self._call(op, timeout, retries, _RETRY_CODES_SEGMENTED)

    def download(self, node: int, index: int, subindex: int, data: bytes, *,
                 timeout: Optional[float] = None, retries: Optional[int] = None) -> None:
        """Write an object of any size: WriteObject up to 4 bytes, else a segmented
        write (guide 2.1.2.2-2.1.2.3), which only node 0 or the gateway's own id accept."""
        data = bytes(data)
        if len(data) <= 4:
            self.write_object(node, index, subindex, data, timeout=timeout, retries=retries)
            return
        _check_node(node)
        if node != 0 and node != self.gateway_node_id:
            raise GatewayNotSupportedError(
                f"segmented write of {len(data)} bytes to node {node}: the EPOS4 gateway does not "
                f"forward InitiateSegmentedWrite/SegmentWrite to other nodes (guide 2.1.2.2). "
                f"Connect to node {node} directly and use node id 0, or pass its id as "
                f"gateway_node_id if it is the connected device")

        def op(t: float) -> None:
            machine = SegmentedWrite(node, index, subindex, data, segment_size=self.segment_size)
            self._run(machine, machine.start(), t)

        self._call(op, timeout, retries, _RETRY_CODES_SEGMENTED)

    def _run(self, machine: Union[SegmentedRead, SegmentedWrite], request: Optional[Message],
             timeout: float) -> None:
        while request is not None:
            answer = self._exchange(request.encode(), ANSWER_TYPES[type(request)], timeout,
                                    type(request).__name__ + " " + machine.where())
            request = machine.receive(answer)

    # --- network ---------------------------------------------------------------

    def nmt(self, node: int, command: Union[NmtCommand, int, str], *,
            timeout: Optional[float] = None, retries: Optional[int] = None) -> None:
        """SendNMTService (0x70): ``command`` is an :class:`NmtCommand`, its value, or one
        of ``start stop preop reset reset-comm``; node 0 addresses all nodes (guide Table 3-14).
        Resets are not retried unless ``retries`` says so."""
        if isinstance(command, str):
            try:
                cs = NMT_COMMANDS[command.lower()]
            except KeyError:
                raise LocalProtocolError(
                    f"NMT command {command!r} is not one of {', '.join(NMT_COMMANDS)}") from None
        else:
            try:
                cs = NmtCommand(command)
            except ValueError:
                raise LocalProtocolError(f"NMT command specifier 0x{command:02X} is unknown") from None
        _check_node(node)
        if retries is None and cs in _NO_RETRY_NMT:
            retries = 0
        self.request(SendNMTService(node, cs), timeout=timeout, retries=retries)

    def scan(self, nodes: Iterable[int] = range(1, 128), *,
             timeout: float = DEFAULT_SCAN_TIMEOUT) -> list[NodeInfo]:
        """The nodes that answer a read of 0x1000 within ``timeout`` (no retry), with
        their name (0x1008) and identity (0x1018 sub 1-4) read at the normal timeout."""
        found: list[NodeInfo] = []
        for node in nodes:
            _check_node(node)
            try:
                device_type = _u32(self.read_object(node, 0x1000, 0, timeout=timeout, retries=0))
            except (DeviceError, EposTimeoutError, RemoteProtocolError):
                continue  # absent, or not a CANopen node we can talk to
            found.append(self._identify(node, device_type))
        return found

    def _identify(self, node: int, device_type: int) -> NodeInfo:
        name: Optional[str] = None
        try:
            name = self.upload(node, 0x1008, 0).rstrip(b"\x00").decode("latin-1")
        except (DeviceError, RemoteProtocolError, EposTimeoutError):
            pass  # 0x1008 is optional in CiA 301
        identity: list[Optional[int]] = []
        for sub in range(1, 5):
            try:
                identity.append(_u32(self.read_object(node, 0x1018, sub)))
            except (DeviceError, RemoteProtocolError, EposTimeoutError):
                identity.append(None)
        return NodeInfo(node, device_type, name, *identity)


def _address(node: int, index: int, subindex: int) -> str:
    return f"node {node} 0x{index:04X}/0x{subindex:02X}"


def _where(message: Message) -> str:
    name = type(message).__name__
    if hasattr(message, "index"):
        return f"{name} " + _address(message.node, message.index, message.subindex)  # type: ignore[attr-defined]
    if isinstance(message, SendNMTService):
        return f"{name} node {message.node} command 0x{message.command:02X}"
    return name


# DEFAULT_TIMEOUT, DEFAULT_RETRIES, WAKE_EARLY and ClientStats live in epos_link.link;
# they are re-exported here, where callers have always imported them from.
__all__ = ["DEFAULT_TIMEOUT", "DEFAULT_RETRIES", "DEFAULT_SCAN_TIMEOUT", "WAKE_EARLY",
           "ClientStats", "EposClient", "NMT_COMMANDS", "NodeInfo"]
