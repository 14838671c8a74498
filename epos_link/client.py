"""EposClient: read and write objects of an EPOS4 and of the CANopen nodes behind it.

The client is the only place with clocks, retries and locks; framing,
messages and the segmented-transfer state machines are pure.

Exchanges (guide 2.2.1: the EPOS4 is a slave and answers every request, one at
a time):

* one request in flight per client: a lock covers a whole call, retries and
  every segment of a segmented transfer included, so threads sharing a client
  never interleave frames;
* before each request the transport's stale input is discarded;
* each request has its own deadline, by default the device's 500 ms frame
  timeout (guide 2.2.7, objects 0x2005/0x2006).

Gateway addressing (guide chapter 5): node id 0 is the device on the USB/RS232
link, as is its own (DIP switch) node id; any other id is forwarded to that
node as an SDO. The gateway does not forward segmented writes (guide 2.1.2.2),
so :meth:`EposClient.download` of more than 4 bytes to another node raises
:class:`GatewayNotSupportedError` before anything is sent.

Errors and retries:

* communication errors (:class:`RemoteProtocolError`, :class:`EposTimeoutError`,
  :class:`TransportError`) and a device answering "CRC error" (0x05040004,
  our request arrived damaged) are retried, ``retries`` times (default 1);
  after a :class:`TransportError` the next attempt first reopens the link;
* a segmented transfer that fails part-way is restarted from its Initiate
  request, never resumed; a device "Toggle error" (0x05030000) during one is
  retried the same way;
* any other :class:`DeviceError` and every :class:`LocalProtocolError` are final.

Late answers: answers carry no request id, so an answer that comes after its
request timed out could be taken for the next request's. A request that timed
out in silence (no byte at all came back) leaves the link "out of step": before
the next request the client waits up to ``late_answer_timeout`` (default
500 ms, the device's frame timeout) for that late answer and drops it. A
timeout with garbage received means the answer came and was damaged, so there
is nothing to wait for; its :class:`EposTimeoutError` says so (``heard``), so a
caller can tell a damaged answer from silence. A scan with a short per-node timeout therefore still
costs, per absent node, the gateway's own SDO timeout.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass, field
from types import TracebackType
from typing import Any, Callable, Iterable, Optional, Type, TypeVar, Union, cast

from .codes import MAX_SEGMENT, ErrorCode, NmtCommand, OpCode
from .errors import (
    CrcError,
    DeviceError,
    EposTimeoutError,
    GatewayNotSupportedError,
    JunkBytesError,
    LocalProtocolError,
    MessageFormatError,
    RemoteProtocolError,
    TransportError,
    TruncatedFrameError,
)
from .framing import NEED_DATA, Frame, FrameDecoder
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

_log = logging.getLogger(__name__)
T = TypeVar("T")

DEFAULT_TIMEOUT = 0.5  # guide 2.2.7: RS232/USB frame timeout, 500 ms by default
DEFAULT_RETRIES = 1
DEFAULT_SCAN_TIMEOUT = 0.1
READ_CHUNK = 4096  # one read takes whatever has arrived, up to a few frames
# The shortest answer frame: DLE STX, op code, length, the 4-byte error code that
# every answer starts with, CRC (guide 2.2.2 frame, 2.1 answers).
MIN_ANSWER_FRAME = 10
# An answer's frame size where the guide fixes it: ReadObject answers Len 4 words,
# error answers included (2.1.1.1; fixtures/client_error_answer.txt). Other answers
# vary (segmented) or are the shortest (10 bytes).
_ANSWER_FRAME: dict[type, int] = {ReadObjectAnswer: 14}
# The first wait for an answer ends this many bytes before its end. A thread that
# slept through the whole exchange (2 ms at 115200 Bd) wakes up slower than one
# that woke just before the last bytes came: status polls (node.sdo.upload in a
# loop) on the simulator in its own process over a pty at 115200 Bd, 427 against
# 438 ReadObject/s (medians of 6 runs of 2 s, waiting for 14 against 12 bytes
# first). An adapter that hands over a whole answer in one USB packet has it all
# at the first wake-up anyway.
WAKE_EARLY = 2
_FRAME_CACHE_LIMIT = 4096

# "CRC error": the device got our request damaged; sending it again is right.
_RETRY_CODES = frozenset({ErrorCode.CRC_ERROR})
# Within a segmented transfer a lost answer desynchronises the toggle bit.
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


@dataclass
class ClientStats:
    """What the link cost: calls made, retries spent, and the errors that caused them."""

    calls: int = 0
    retries: int = 0
    failures: dict[str, int] = field(default_factory=dict)  # error type name -> count

    def failed(self, exc: BaseException) -> None:
        name = type(exc).__name__
        self.failures[name] = self.failures.get(name, 0) + 1


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


class EposClient:
    """A thread-safe client over one :class:`Transport`; closing it closes the transport.

    ``gateway_node_id`` is the connected device's own node id, when known: a
    segmented write to it is executed locally, so it is allowed like node 0.
    """

    def __init__(self, transport: Transport, *, gateway_node_id: Optional[int] = None,
                 timeout: float = DEFAULT_TIMEOUT, retries: int = DEFAULT_RETRIES,
                 segment_size: int = MAX_SEGMENT, max_upload: int = DEFAULT_MAX_LENGTH,
                 late_answer_timeout: float = DEFAULT_TIMEOUT) -> None:
        if timeout <= 0:
            raise ValueError("timeout must be positive")
        if retries < 0:
            raise ValueError("retries must be 0 or more")
        if gateway_node_id is not None:
            _check_node(gateway_node_id)
        self.transport = transport
        self.gateway_node_id = gateway_node_id
        self.timeout = timeout
        self.retries = retries
        self.segment_size = segment_size
        self.max_upload = max_upload
        self._lock = threading.Lock()
        self._decoder = FrameDecoder()
        self._needs_reopen = False
        self._late_answer_due = False
        self.late_answer_timeout = late_answer_timeout
        self.stats = ClientStats()
        # Called (on the calling thread) each time the client starts to wait on the
        # link: once a request frame has been written (its answer takes at least the
        # request's wire time), and before it waits for a late answer. A caller may
        # use that time (tcp_bridge.bus.workers hands a finished reply to its event loop).
        self.on_wait: Optional[Callable[[], None]] = None
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

    # --- context and life cycle ----------------------------------------------

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> "EposClient":
        return self

    def __exit__(self, exc_type: Optional[Type[BaseException]], exc: Optional[BaseException],
                 tb: Optional[TracebackType]) -> None:
        self.close()

    # --- one exchange, one call ----------------------------------------------

    def _exchange(self, frame: bytes, answer_type: Any, timeout: float, what: str = "") -> Any:
        """Send one request frame and return its decoded answer; no retries here.

        ``what`` names the request in a timeout message."""
        transport, decoder = self.transport, self._decoder
        on_wait = self.on_wait
        if self._late_answer_due:
            if on_wait is not None:
                on_wait()
            self._swallow_late_answer()
        transport.reset_input()
        decoder.reset()
        transport.write(frame)
        if on_wait is not None:
            on_wait()
        # What to wait for before looking (SerialTransport.read_some): the answer's
        # size where the guide fixes it, and never more than that, since a frame the
        # decoder opened on noise may claim more than the real answer that follows.
        first = _ANSWER_FRAME.get(answer_type, MIN_ANSWER_FRAME) - WAKE_EARLY
        deadline = time.monotonic() + timeout
        read, next_frame, feed = transport.read_some, decoder.next_frame, decoder.feed
        heard = False
        while True:
            try:
                item = next_frame()
            except (JunkBytesError, TruncatedFrameError):
                # Noise before the answer, or a DLE STX in it: the decoder has
                # already resynchronised on the next frame, which may be ours.
                continue
            if item is NEED_DATA:
                left = deadline - time.monotonic()
                if left <= 0:
                    held = decoder.pending
                    # Silence, not garbage: the device may still answer (a gateway
                    # waiting for an absent node's SDO takes its own time).
                    self._late_answer_due = not heard
                    raise EposTimeoutError(
                        f"{what or 'request'}: no answer within {timeout:g} s"
                        + (f" ({held} bytes of an incomplete answer)" if held else ""),
                        heard=heard)
                data = read(READ_CHUNK, left, min(decoder.wanted, first) if heard else first)
                if data:
                    heard = True
                    feed(data)
                continue
            got = cast(Frame, item)
            if got.opcode != OpCode.ANSWER:
                raise MessageFormatError(
                    f"op code 0x{got.opcode:02X} where an answer (0x00) was expected", got.data)
            return answer_type.from_payload(got.data)

    def _swallow_late_answer(self) -> None:
        """Wait (at most ``late_answer_timeout``) for the answer to a request that
        timed out in silence, and drop it.

        The device answers every request (guide 2.2.1) and answers carry no
        request id, so a late answer would otherwise be taken for the next
        request's: after a silent timeout the link is out of step until it comes.
        """
        self._late_answer_due = False
        decoder = self._decoder
        deadline = time.monotonic() + self.late_answer_timeout
        while True:
            try:
                if decoder.next_frame() is not NEED_DATA:
                    _log.debug("dropped a late answer")
                    return
            except (CrcError, TruncatedFrameError, MessageFormatError):
                return  # the late answer came, damaged: the link is in step again
            except RemoteProtocolError:
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                return
            data = self.transport.read(READ_CHUNK, left)
            if data:
                decoder.feed(data)

    def _call(self, op: Callable[[float], T], timeout: Optional[float], retries: Optional[int],
              retry_codes: frozenset[int] = _RETRY_CODES) -> T:
        """Run ``op(timeout)`` under the lock, retrying communication errors."""
        t = self.timeout if timeout is None else timeout
        attempts = 1 + (self.retries if retries is None else retries)
        with self._lock:
            last: Optional[BaseException] = None
            self.stats.calls += 1
            for attempt in range(attempts):
                if attempt:
                    assert last is not None
                    self.stats.retries += 1
                    self.stats.failed(last)
                    _log.debug("retry %d/%d after %s", attempt, attempts - 1, last)
                try:
                    if self._needs_reopen:
                        self._reopen()
                    return op(t)
                except TransportError as exc:
                    self._needs_reopen = True
                    last = exc
                except (RemoteProtocolError, EposTimeoutError) as exc:
                    last = exc
                except DeviceError as exc:
                    if exc.code not in retry_codes:
                        raise
                    last = exc
            assert last is not None
            self.stats.failed(last)
            raise last

    def _reopen(self) -> None:
        try:
            self.transport.reopen()
        except NotImplementedError as exc:
            raise TransportError(f"{self.transport.url}: the link failed and cannot be reopened") from exc
        self._needs_reopen = False
        _log.info("reopened %s", self.transport.url)

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


__all__ = ["DEFAULT_TIMEOUT", "DEFAULT_RETRIES", "EposClient", "NMT_COMMANDS", "NodeInfo"]
