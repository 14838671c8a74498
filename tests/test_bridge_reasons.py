"""Every CAN and NAK reply has its reason in the log at ``-v`` (issue 34 item 5; issue 31's
bullet for EtherCAT): one line, axis, command, why; rate-limited (tcp_bridge/reasons.py).

As the user met it: ``2S02=abc`` and ``2S02=1.5e1`` answered CAN and nothing said why.
Here the same requests go to a bridge over a real socket, and the log is read."""
from __future__ import annotations

import asyncio
import logging
import socket
import threading
from typing import List

import pytest

from tcp_bridge.errors import DeviceFailure, InvalidCommand, LineTooLong, SilentLink
from tcp_bridge.reasons import MAX_REQUEST, ReasonLog, request_text
from tcp_bridge.server import BridgeServer, ServerOptions
from tcp_bridge.wire import ReadRequest, Status, WriteRequest
from tcp_bridge.tables.axes import simulated_increments_per_revolution
from tests.bridge_sim import SimBridge
from tests.helpers import psi_ask


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def logged(caplog: pytest.LogCaptureFixture) -> List[str]:
    return [r.getMessage() for r in caplog.records if r.name == "tcp_bridge.replies"]


# -- the pure part -------------------------------------------------------------------------


def test_one_line_per_kind_then_the_count_of_those_held_back(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="tcp_bridge.replies")
    clock = Clock()
    reasons = ReasonLog(clock, interval=5.0)
    silent = SilentLink("bus can1: device silent for 1.2 s (timeout); answered at once")
    request = ReadRequest(2, 10)
    assert reasons.refused(b"2R10", request, silent, Status.NAK) is not None
    for k in range(9):  # a client polling at 10 Hz: the numbers in the reason change
        clock.now += 0.1
        later = SilentLink(f"bus can1: device silent for {1.3 + k / 10:.1f} s (timeout); "
                           "answered at once")
        assert reasons.refused(b"2R10", request, later, Status.NAK) is None
    other = DeviceFailure("SDO abort 0x06020000: Object does not exist")
    assert reasons.refused(b"2R10", request, other, Status.NAK) is not None  # another reason
    clock.now += 5.0
    last = reasons.refused(b"2R10", request, silent, Status.NAK)
    assert last is not None and last.endswith("(9 more like it not logged)")
    assert logged(caplog) == [
        "axis 2 R10 (2R10): NAK: bus can1: device silent for 1.2 s (timeout); answered at once",
        "axis 2 R10 (2R10): NAK: SDO abort 0x06020000: Object does not exist",
        "axis 2 R10 (2R10): NAK: bus can1: device silent for 1.2 s (timeout); answered at once "
        "(9 more like it not logged)"]


def test_nothing_is_formatted_below_info(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="tcp_bridge.replies")
    reasons = ReasonLog(Clock())
    assert reasons.refused(b"2S02=abc", WriteRequest(2, 2, "12"), InvalidCommand("bad"),
                           Status.CAN) is None
    assert logged(caplog) == [] and reasons.pending() == {}


def test_junk_is_bounded_escaped_and_one_line(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="tcp_bridge.replies")
    reasons = ReasonLog(Clock(), max_kinds=8)
    for axis in range(1, 51):  # a hostile client: a new kind per request
        reasons.refused(f"{axis}R10".encode(), ReadRequest(axis, 10),
                        DeviceFailure("no"), Status.NAK)
    assert len(reasons._kinds) == 8
    line = reasons.refused(b"\x01\x02" + b"x" * 200, None,
                           InvalidCommand("not a request:\nline two\r"), Status.CAN)
    assert line is not None and "\n" not in line and "\r" not in line
    assert line.startswith("axis ? ? (\\x01\\x02xxx") and "...): CAN: not a request: line two" \
        in line
    assert len(request_text(b"y" * 500)) == MAX_REQUEST + 3
    overlong = LineTooLong("line too long", head=b"3S02=" + b"9" * 100, limit=100, axis=3,
                           kind="S", cmd=2)
    line = reasons.refused(overlong, None, overlong, Status.CAN)
    assert line is not None and line.startswith("axis 3 S02 (3S02=999")


# -- as the user met it: a bridge over a socket ---------------------------------------------


def test_bad_values_and_refusals_are_logged_with_their_reason(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="tcp_bridge.replies")
    ipr = simulated_increments_per_revolution()
    axes = [{"device": 5, "node_id": n, "position_factor": 1000,
             "increments_per_revolution": ipr} for n in (1, 2, 3)]
    b = SimBridge(drives=(2,), axes=axes)  # node 3 is configured but not on the bus
    try:
        for line in ("2S02=abc", "2S02=1.5e1", "2S10=1", "7R10", "2R77"):
            assert b.ask(line).status is Status.CAN
        assert b.ask("3R12").status is Status.NAK
    finally:
        b.close()
    found = logged(caplog)
    assert found[:5] == [
        "axis 2 S02 (2S02=abc): CAN: bad value 'abc': not a decimal or 0x-hex number: "
        "b'2S02=abc'",
        "axis 2 S02 (2S02=1.5e1): CAN: bad value '1.5e1': not a decimal or 0x-hex number: "
        "b'2S02=1.5e1'",
        "axis 2 S10 (2S10=1): CAN: command 10 (Status) is not writable",
        "axis 7 R10 (7R10): CAN: axis 7 is not configured",
        "axis 2 R77 (2R77): CAN: unknown command 77"]
    assert len(found) == 6 and found[5].startswith("axis 3 R12 (3R12): NAK: "), found
    assert "0x05040000" in found[5] or "silent" in found[5], found[5]


def test_an_ethercat_refusal_is_logged_with_the_slaves_abort(
        caplog: pytest.LogCaptureFixture) -> None:
    """Issue 31's bullet: an object missing on an EtherCAT slave, in the log at -v."""
    from tests.test_bridge_ethercat_engine import EcatBridge

    caplog.set_level(logging.INFO, logger="tcp_bridge.replies")
    bridge = EcatBridge()
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = BridgeServer(bridge.engine, ServerOptions(ports=(0,)))
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(30)
        del bridge.slave(2).drive.values[(0x603F, 0)]  # this slave has no error code object
        with socket.create_connection(server.addresses[0], timeout=30) as sock:
            assert psi_ask(sock, "2R11").status is Status.NAK
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(60)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()
    found = logged(caplog)
    assert len(found) == 1 and found[0].startswith("axis 2 R11 (2R11): NAK: "), found
    assert "0x06020000" in found[0] and "Object does not exist" in found[0], found
