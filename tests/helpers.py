"""Shared test habits: feed a stream three ways (h11's test_io style); ask a PSI bridge;
wait for a condition another thread brings about."""
from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any, Callable, Iterator, Tuple

if TYPE_CHECKING:
    import socket

    from tcp_bridge.wire import Reply


def three_ways(stream: bytes, junk: bytes = b"\x11\x22\x33") -> Iterator[tuple[str, list[bytes], bytes]]:
    """(label, chunks, prefix-junk): whole, byte by byte, and with junk before and after."""
    yield "whole", [stream], b""
    yield "bytewise", [stream[i:i + 1] for i in range(len(stream))], b""
    yield "junk", [junk + stream + junk], junk


def feed_all(decoder_factory: Callable, chunks: list[bytes]) -> tuple[list, list]:
    """Feed chunks into a FrameDecoder; return (frames, errors) until the end of input."""
    from epos_link.errors import RemoteProtocolError
    from epos_link.framing import NEED_DATA

    dec = decoder_factory()
    frames: list = []
    errors: list = []

    def drain() -> None:
        while True:
            try:
                item = dec.next_frame()
            except RemoteProtocolError as exc:
                errors.append(exc)
                continue
            if item is NEED_DATA:
                return
            frames.append(item)

    for chunk in chunks:
        dec.feed(chunk)
        drain()
    dec.close()
    drain()
    return frames, errors


def psi_ask(sock: "socket.socket", line: str) -> "Reply":
    """Send one PSI request line (CR-terminated) and read its 30-byte reply (spec 2.2)."""
    from tcp_bridge.wire import REPLY_SIZE, decode_reply

    sock.sendall(line.encode() + b"\r")
    data = b""
    while len(data) < REPLY_SIZE:
        chunk = sock.recv(REPLY_SIZE - len(data))
        assert chunk, "bridge closed the connection"
        data += chunk
    return decode_reply(data)


def wait_until(what: Callable[[], object], timeout: float = 10.0,
               why: str = "condition never became true") -> None:
    """Poll ``what`` until it is true; fail with ``why`` after ``timeout`` seconds, a bound
    far above what the condition needs (tests never assert tight wall-clock bounds)."""
    deadline = time.monotonic() + timeout
    while not what():
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.005)


class AskOk:
    """``ok`` and ``poll`` for a test bridge whose ``ask(line)`` returns a Reply: one
    copy for tests/bridge_sim.py and the EtherCAT engine tests."""

    def ask(self, line: str) -> "Reply":
        raise NotImplementedError

    def ok(self, *lines: str) -> str:
        """Ask each line; each must be ACKed; the last reply's value."""
        from tcp_bridge.wire import Status

        value = ""
        for line in lines:
            reply = self.ask(line)
            assert reply.status is Status.ACK, (line, reply)
            value = reply.value or ""
        return value

    def poll(self, line: str, want: str, timeout: float = 10.0) -> None:
        wait_until(lambda: self.ok(line) == want, timeout, f"{line} never became {want}")


@contextlib.contextmanager
def canopen_node_on_simulator(node_id: int, node_class: Any = None) -> Iterator[Tuple[Any, Any]]:
    """An ``Epos4Simulator`` with drive ``node_id`` behind it, and a canopen node of
    ``node_class`` (default ``canopen.RemoteNode``) for it on the simulator's virtual
    CAN bus, with the shipped EDS: ``(simulator, node)``; both closed afterwards."""
    import canopen

    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.od import EDS_PATH

    sim = Epos4Simulator(1, [node_id])
    net = canopen.Network()
    net.connect(interface="virtual", channel=sim.channel, receive_own_messages=False)
    node = (node_class or canopen.RemoteNode)(node_id, str(EDS_PATH))
    node.sdo.RESPONSE_TIMEOUT = 1.0
    net.add_node(node)
    try:
        yield sim, node
    finally:
        net.disconnect()
        sim.close()
