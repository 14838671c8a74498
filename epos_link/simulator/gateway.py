"""The simulated EPOS4's CAN gateway (guide chapter 5, Table 5-20).

A request for a node other than 0 or the device's own id is translated into a
CiA 301 SDO transfer on the CAN bus, here a python-can ``virtual`` bus that the
simulated drives (and any other program in the process) share.

ReadObject and InitiateSegmentedRead become an SDO upload (expedited or
segmented, as the server chooses). WriteObject becomes an expedited download.
The guide does not document the CAN frame the real gateway sends for
WriteObject, whose data field is always 4 bytes, to an object smaller than 4
bytes. We choose **expedited download with the size not indicated** (command
specifier 0x22: e=1, s=0), so the server takes the 4 bytes and applies the
object's own size; the choice lives in :data:`WRITE_OBJECT_CS` and
:meth:`CanGateway.write` only. A node that does not answer within the
gateway's timeout is reported with the SDO abort code 0x05040000 (SDO protocol
timed out).

**Late hosts.** The timeout is what a node that does not answer costs (a scan pays
it per absent node). A node of this simulator that is there to answer (``answers``)
is given :data:`HOST_LATE` instead: on a CAN bus its answer takes a millisecond, and
here it is late only when the host's threads are (a loaded machine once answered
in 0.375 s, after the 0.3 s timeout, and an object that does not exist read as
"SDO protocol timed out": tests/test_monitor_tmux.py).
"""
from __future__ import annotations

import struct
import threading
from typing import Any, Callable, Optional

import canopen
from canopen.sdo import SdoAbortedError, SdoClient, SdoCommunicationError

from .device import Abort

SDO_TIMEOUT_ABORT = 0x05040000
HOST_LATE = 5.0  # s: the wait for a simulated node that answers (module docstring)
WRITE_OBJECT_CS = 0x22  # initiate download, expedited, size not indicated (CiA 301 7.2.4.3.3)
_RESPONSE_DOWNLOAD = 0x60
_RESPONSE_ABORT = 0x80


class _GatewaySdoClient(SdoClient):
    """canopen's SDO client, minus its error log on abort: an absent node is an
    expected answer here (0x05040000 back to the host), not an error."""

    def abort(self, abort_code: int = 0x08000000) -> None:
        request = bytearray(8)
        request[0] = _RESPONSE_ABORT  # client abort: command specifier 0x80 (CiA 301 7.2.4.3.17)
        struct.pack_into("<L", request, 4, abort_code)
        self.send_request(request)


class CanGateway:
    """Forwards object access for remote nodes as SDO on a canopen Network."""

    def __init__(self, network: canopen.Network, *, timeout: float = 0.3,
                 answers: Optional[Callable[[int], bool]] = None) -> None:
        self.network = network
        self.timeout = timeout
        self.answers = answers or (lambda node: False)
        self._clients: dict[int, SdoClient] = {}
        self._lock = threading.Lock()

    def _client(self, node: int) -> SdoClient:
        if not 1 <= node <= 127:
            raise Abort(0x06040043)  # no such CANopen node id: general parameter error
        client = self._clients.get(node)
        if client is None:
            client = _GatewaySdoClient(0x600 + node, 0x580 + node, canopen.ObjectDictionary())
            client.MAX_RETRIES = 1
            client.network = self.network
            self.network.subscribe(client.tx_cobid, client.on_response)
            self._clients[node] = client
        # An instance attribute: this gateway's timeout, or the late host's (docstring).
        client.RESPONSE_TIMEOUT = max(self.timeout, HOST_LATE) if self.answers(node) \
            else self.timeout
        return client

    def read(self, node: int, index: int, subindex: int) -> bytes:
        with self._lock:
            client = self._client(node)
            try:
                return bytes(client.upload(index, subindex))
            except SdoAbortedError as exc:
                raise Abort(exc.code) from None
            except SdoCommunicationError:
                raise Abort(SDO_TIMEOUT_ABORT) from None

    def write(self, node: int, index: int, subindex: int, data: bytes, *,
              expedited: bool = True) -> None:
        with self._lock:
            client = self._client(node)
            try:
                if expedited and len(data) <= 4:
                    request = struct.pack("<BHB", WRITE_OBJECT_CS, index, subindex) + data.ljust(4, b"\0")
                    response = client.request_response(request)
                    if response[0] != _RESPONSE_DOWNLOAD:
                        raise Abort(0x05040001)  # unexpected command specifier
                else:
                    client.download(index, subindex, data, force_segment=True)
            except SdoAbortedError as exc:
                raise Abort(exc.code) from None
            except SdoCommunicationError:
                raise Abort(SDO_TIMEOUT_ABORT) from None

    def nmt(self, node: int, command: int) -> None:
        # NMT node control: COB-ID 0, CS then node id (guide Table 3-14).
        self.network.send_message(0, bytes((command & 0xFF, node & 0xFF)))

    def close(self) -> None:
        for client in self._clients.values():
            try:
                self.network.unsubscribe(client.tx_cobid, client.on_response)
            except Exception:  # unsubscribing a closed network must not mask the shutdown
                pass
        self._clients.clear()


def connect_virtual(channel: str, **kwargs: Any) -> canopen.Network:
    """A canopen Network on a python-can virtual channel."""
    network = canopen.Network()
    # The notifier thread polls the bus with this timeout; stopping waits for
    # one cycle, so a short cycle makes closing the simulator quick.
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel, receive_own_messages=False, **kwargs)
    return network


__all__ = ["CanGateway", "connect_virtual", "HOST_LATE", "SDO_TIMEOUT_ABORT", "WRITE_OBJECT_CS"]
