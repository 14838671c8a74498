"""Typed SDO access to one node, over anything with canopen's SdoBase interface.

The command layer never sees a backend: it gets a *node*, an object with

* ``node.sdo.upload(index, subindex) -> bytes`` and
  ``node.sdo.download(index, subindex, data: bytes)`` (canopen's ``SdoBase``,
  which a ``canopen.RemoteNode`` has and the epos_link SDO adapter provides);
* ``node.nmt.state = "RESET"`` (canopen's ``NmtMaster``) for command 16, and
  ``"OPERATIONAL"`` for a node found in NMT Stopped (:mod:`tcp_bridge.motion`).

:class:`SdoPort` adds the data types of the CiA 301 / CiA 402 objects the
gateway uses (so a U16 controlword goes out as 2 bytes and a statusword comes
back unsigned), turns every failure into :class:`~tcp_bridge.errors.DeviceFailure`
(answered NAK), and logs each transfer when command 91 "debug print" is on (a
:class:`Switch` it reads, never a call back up). It records the outcome of every
transfer in its node's :class:`~tcp_bridge.bus.health.NodeHealth` (fail-fast
buses; :func:`silence_of` tells a silent bus's device from a silent node), and
keeps the last value it wrote to each object (:attr:`SdoPort.written`: what a
drive that kept its RAM values still holds, motion rule 3). The port calls
nothing above it: whoever reads the statusword hands it to the drive's
sequences itself (:meth:`tcp_bridge.motion.Cia402.observe`).

A garbled answer is not silence (issue 24): a CRC error, a frame cut short, or
bytes that never made an answer (:func:`garbled`) prove the device is there and
answered; the noise was on the wire. So, as the ``epos_link`` client retries it
(its ``retries``, a bus option), the port tries such a transfer again, up to
:data:`GARBLED_RETRIES` more times, and the probes of :mod:`tcp_bridge.bus.failfast`
do the same. A silent device (a timeout with no byte back, a link failure) gets
no extra try: fail-fast is kept for a device that really says nothing. A
transfer whose every try was garbled counts as the device's silence: a link
that garbles everything is as unusable as a silent one.

Repeating a transfer whose answer was garbled repeats one the device has
executed, which the client already does once: a read is harmless; a write
stores the same value again, and a CiA 402 command acts on the state machine's
current state or on an edge of a controlword bit (CiA 402-2 6.3.1, 6.7.1), which the
same word written twice does not make.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Dict, Final, NoReturn, Optional, Tuple, TypeVar

from epos_link.cia402 import describe_statusword

from ..errors import DeviceFailure, NeedsBus, NodeSilent
from ..tables.commands import ObjectRef
from .health import NodeHealth, Silence

log = logging.getLogger("tcp_bridge.bus.sdo")
T = TypeVar("T")

# (size in bytes, signed) by (index, subindex); subindex None = every subindex.
# Sources: CiA 301 V4.2 7.5.2 (1001h, 1016h), CiA 402-2 V4.0 object descriptions;
# 2000h: Technosoft motion error register (U16); 200Dh: Nanotec (assumed U8).
OBJECT_TYPES: Final[Dict[Tuple[int, Optional[int]], Tuple[int, bool]]] = {
    (0x1001, None): (1, False), (0x2000, None): (2, False), (0x200D, None): (1, False),
    (0x603F, None): (2, False), (0x6040, None): (2, False), (0x6041, None): (2, False),
    (0x605A, None): (2, True), (0x6060, None): (1, True), (0x6061, None): (1, True),
    (0x6062, None): (4, True), (0x6064, None): (4, True), (0x6065, None): (4, False),
    (0x6067, None): (4, False), (0x606C, None): (4, True), (0x607A, None): (4, True),
    (0x607C, None): (4, True), (0x607D, None): (4, True), (0x607F, None): (4, False),
    (0x6081, None): (4, False), (0x6083, None): (4, False), (0x6084, None): (4, False),
    (0x6085, None): (4, False), (0x6098, None): (1, True), (0x6099, None): (4, False),
    (0x609A, None): (4, False), (0x60C5, None): (4, False), (0x60FD, None): (4, False),
    (0x60FE, None): (4, False), (0x60FF, None): (4, True), (0x6502, None): (4, False),
    # maxon EPOS4 (EPOS4 EDS): SI unit velocity, main sensor resolution, encoder pulses.
    (0x60A9, None): (4, False), (0x3000, 5): (4, False), (0x3010, 1): (4, False),
    # Heartbeat supervision (issue 23): CiA 301 7.5.2.19 1016h; CiA 402-2 6007h.
    (0x1016, 0): (1, False), (0x1016, None): (4, False), (0x6007, None): (2, True),
}


SDO_TIMEOUT_ABORT: Final = 0x05040000  # CiA 301: SDO protocol timed out (a gateway's answer)


def object_type(index: int, subindex: int) -> Tuple[int, bool]:
    """(size, signed) of an object; unknown objects are 4 unsigned bytes."""
    return OBJECT_TYPES.get((index, subindex)) or OBJECT_TYPES.get((index, None)) or (4, False)


def object_name(node: Any, index: int, subindex: int) -> str:
    """`` Statusword``: the object's name for the debug log (command 91), from the
    node's object dictionary, else the shipped EPOS4 EDS (CiA 402 names are the
    profile's); empty when neither knows it. Called only with debug print on."""
    try:
        var = node.object_dictionary.get_variable(index, subindex)
        if var is not None:
            return f" {var.name}"
    except Exception:  # no dictionary, or one of another shape: fall back
        pass
    try:
        from epos_link.tools.objects import load_directory

        name = load_directory().name_of(index, subindex)
    except Exception:  # the shipped EDS is unreadable: the log line stays without
        return ""
    return f" {name}" if name else ""


def encode(value: int, size: int, signed: bool) -> bytes:
    """Little-endian ``size`` bytes; :class:`ValueError` when ``value`` does not fit."""
    return int(value).to_bytes(size, "little", signed=signed)


def decode(data: bytes, size: int, signed: bool) -> int:
    """The integer in the first ``size`` bytes (fewer if the answer is shorter)."""
    return int.from_bytes(bytes(data[:size]), "little", signed=signed)


# Exceptions that mean the bus's device itself gave no usable answer (issue 12,
# tcp_bridge.bus.health): the epos_link client's timeout and link failures, a CAN
# adapter's errors. An SDO abort, even 0x05040000, is an answer from the link.
_LINK_FAILURES: Final = frozenset({"EposTimeoutError", "TransportError", "RemoteProtocolError",
                                   "CanError"})


def silence_of(exc: BaseException) -> Optional[Silence]:
    """Who was silent when a transfer failed with ``exc``: the bus's device, the node, or
    None (the node answered, with an abort). See :mod:`tcp_bridge.bus.health`."""
    seen = 0
    cause: Optional[BaseException] = exc
    while cause is not None and seen < 8:  # the adapter wraps the client's error (from exc)
        names = {cls.__name__ for cls in type(cause).__mro__}
        if names & _LINK_FAILURES or isinstance(cause, OSError):
            return Silence.LINK
        seen += 1
        cause = cause.__cause__ or cause.__context__
    code = getattr(exc, "code", None)
    if not isinstance(code, int) or code == SDO_TIMEOUT_ABORT:
        return Silence.NODE
    return None


# With 5% of reply bytes corrupted, half the 14-byte ReadObject answers are
# garbled (1 - 0.95**14); the client's two tries then fail together one time in
# four (0.51**2). Three more transfers, eight tries in all, leave one read in
# 200 (0.51**8 = 0.005); each garbled try costs one exchange, or the client's
# timeout when the garbling hid the answer's length (guide 2.2.7: 500 ms).
GARBLED_RETRIES: Final = 3


def garbled(exc: BaseException) -> bool:
    """True if ``exc`` (or what it wraps) is a damaged answer: an ``epos_link``
    ``RemoteProtocolError``, or a timeout after bytes that made no answer."""
    seen = 0
    cause: Optional[BaseException] = exc
    while cause is not None and seen < 8:  # the adapter wraps the client's error (from exc)
        names = {cls.__name__ for cls in type(cause).__mro__}
        if "RemoteProtocolError" in names:
            return True
        if "EposTimeoutError" in names:
            return bool(getattr(cause, "heard", False))
        seen += 1
        cause = cause.__cause__ or cause.__context__
    return False


def retry_garbled(transfer: Callable[[], T], on_garbled: Callable[[Exception], None]
                  = lambda exc: None) -> T:
    """``transfer()``, tried again after a garbled answer, up to :data:`GARBLED_RETRIES`
    times (``on_garbled`` is told each); any other failure is raised at once."""
    for attempt in range(GARBLED_RETRIES + 1):
        try:
            return transfer()
        except Exception as exc:
            if attempt == GARBLED_RETRIES or not garbled(exc):
                raise
            on_garbled(exc)
    raise AssertionError("unreachable")  # pragma: no cover


def _is_device_error(exc: BaseException) -> bool:
    # canopen.SdoError (aborts, timeouts), python-can errors, OS errors, and
    # whatever an SDO adapter raises for a failed transfer (epos_link errors).
    if isinstance(exc, (OSError, TimeoutError)):
        return True
    names = {cls.__name__ for cls in type(exc).__mro__}
    return bool(names & {"SdoError", "CanError", "EposError", "NmtError"})


class Switch:
    """A flag read without a call: command 91 "debug print", set by the engine and read by
    every port before it logs a transfer."""

    __slots__ = ("on",)

    def __init__(self, on: bool = False) -> None:
        self.on = on


class SdoPort:
    """Integer reads and writes of one node's objects; failures become DeviceFailure."""

    def __init__(self, node: Any, *, name: str = "node", debug: Optional[Switch] = None,
                 health: Optional[NodeHealth] = None) -> None:
        self.node = node
        self.name = name
        self._debug = debug if debug is not None else Switch()
        # Told the outcome of every transfer (tcp_bridge.bus.health: fail-fast buses).
        self.health = health
        # The last value written through this port to each object (any command, 81
        # included): what a drive that kept its RAM values still holds (motion rule 3).
        self.written: Dict[ObjectRef, int] = {}
        # PDO-fed status (canopen backend, pdo = true; tcp_bridge.backends.pdo_status):
        # told the end of every transfer, consulted by read_status().
        self.feed: Any = getattr(node, "status_feed", None)
        self._pdo_only = False  # within pdo_only(): no SDO transfer at all

    def upload(self, index: int, subindex: int) -> bytes:
        if self._pdo_only:
            raise NeedsBus(f"0x{index:04X}/{subindex}")
        try:
            data = retry_garbled(lambda: bytes(self.node.sdo.upload(index, subindex)),
                                 lambda exc: self._trace("upload", index, subindex, None, exc))
        except Exception as exc:
            self._transferred((index, subindex))
            self._trace("upload", index, subindex, None, exc)
            self._raise_failure("read", index, subindex, exc)
        self._transferred((index, subindex))
        if self.health is not None:
            self.health.record(None)
        if self._debug.on:
            self._trace("upload", index, subindex, data, None)
        return data

    def download(self, index: int, subindex: int, data: bytes) -> None:
        if self._pdo_only:
            raise NeedsBus(f"0x{index:04X}/{subindex}")
        try:
            retry_garbled(lambda: self.node.sdo.download(index, subindex, bytes(data)),
                          lambda exc: self._trace("download", index, subindex, data, exc))
        except Exception as exc:
            self._transferred(None)  # it may have arrived
            self._trace("download", index, subindex, data, exc)
            self._raise_failure("write", index, subindex, exc)
        self._transferred(None)
        if self.health is not None:
            self.health.record(None)
        if self._debug.on:
            self._trace("download", index, subindex, data, None)

    def _transferred(self, key: Optional[Tuple[int, int]]) -> None:
        if self.feed is not None:
            self.feed.note_transfer(key)

    def pdo_only(self, plan: Callable[[], Any]) -> Any:
        """Run ``plan`` answering only from PDOs; :class:`NeedsBus` at its first SDO.
        For the event loop (tcp_bridge.bus.shared_reads rule 5): it never blocks there."""
        self._pdo_only = True
        try:
            return plan()
        finally:
            self._pdo_only = False

    def read_status(self, index: int, subindex: int = 0) -> int:
        """A read for a status poll (R10 R12 R14 R82 R83 R84): the newest PDO value if
        it counts (:meth:`StatusFeed.value`), else :meth:`read` by SDO. Sequences that
        wait for the drive use :meth:`read`."""
        value = self.feed.value(index, subindex) if self.feed is not None else None
        if value is None:
            return self.read(index, subindex)
        if self._debug.on:
            note = f" [{describe_statusword(value)}]" if (index, subindex) == (0x6041, 0) else ""
            log.info("%s PDO 0x%04X/%d%s = %d%s", self.name, index, subindex,
                     object_name(self.node, index, subindex), value, note)
        return value

    def read(self, index: int, subindex: int = 0, *, size: Optional[int] = None,
             signed: Optional[bool] = None) -> int:
        t_size, t_signed = object_type(index, subindex)
        return decode(self.upload(index, subindex), size or t_size,
                      t_signed if signed is None else signed)

    def write(self, index: int, subindex: int, value: int, *, size: Optional[int] = None,
              signed: Optional[bool] = None) -> None:
        t_size, t_signed = object_type(index, subindex)
        size = size or t_size
        signed = t_signed if signed is None else signed
        try:
            data = encode(value, size, signed)
        except OverflowError:
            # An unsigned object written with a negative number, or too big: the
            # command layer range-checks first, so this is a drive-side refusal.
            raise DeviceFailure(f"{self.name}: {value} does not fit 0x{index:04X}/{subindex} "
                                f"({size} bytes, {'signed' if signed else 'unsigned'})") from None
        self.download(index, subindex, data)
        self.written[ObjectRef(index, subindex)] = decode(data, size, signed)

    def nmt_reset(self) -> None:
        """NMT "reset node" (CiA 301 7.2.8.3.2.1), unconfirmed by definition."""
        self._nmt("RESET", "reset node")

    def nmt_start(self) -> None:
        """NMT "start remote node" (CiA 301 7.2.8.3.2.1): a node in NMT Stopped answers
        SDO again (EPOS4 Communication Guide, Table 3-13). Unconfirmed, like every NMT
        command; when and why the bridge sends it: :meth:`tcp_bridge.motion.Cia402.halt`."""
        self._nmt("OPERATIONAL", "start remote node")

    def _nmt(self, state: str, what: str) -> None:
        # canopen's NmtMaster: setting ``state`` sends the command that leads there.
        nmt = getattr(self.node, "nmt", None)
        try:
            if nmt is None:
                raise DeviceFailure(f"{self.name}: no NMT service")
            nmt.state = state
        except DeviceFailure:
            raise
        except Exception as exc:
            if not _is_device_error(exc) and not isinstance(exc, (ValueError, AttributeError)):
                raise
            raise DeviceFailure(f"{self.name}: NMT {what} failed: {exc}") from exc
        if self._debug.on:
            log.info("%s NMT %s", self.name, what)

    def _raise_failure(self, what: str, index: int, subindex: int, exc: Exception) -> NoReturn:
        if isinstance(exc, DeviceFailure) or not _is_device_error(exc):
            raise exc  # a bug, not a device answer, surfaces as is (still answered NAK)
        code = getattr(exc, "code", None)
        text = f"{self.name}: {what} 0x{index:04X}/{subindex} failed: {exc}"
        if self.health is not None:
            self.health.record(silence_of(exc), str(exc))
        if not isinstance(code, int) or code == SDO_TIMEOUT_ABORT:
            raise NodeSilent(text, code if isinstance(code, int) else None) from exc
        raise DeviceFailure(text, code) from exc

    def _trace(self, what: str, index: int, subindex: int, data: Optional[bytes],
               exc: Optional[BaseException]) -> None:
        if not self._debug.on:
            return
        shown = "" if data is None else " " + data.hex(" ")
        if data is not None and index == 0x6041 and subindex == 0 and len(data) >= 2:
            shown += f" [{describe_statusword(int.from_bytes(data[:2], 'little'))}]"
        outcome = f" -> {type(exc).__name__}: {exc}" if exc is not None else ""
        log.info("%s SDO %s 0x%04X/%d%s%s%s", self.name, what, index, subindex,
                 object_name(self.node, index, subindex), shown, outcome)
