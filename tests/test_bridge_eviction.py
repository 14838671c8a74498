"""Who loses a slot when all are taken (issue 24 point 10, must show 6).

The policy is in :mod:`tcp_bridge.server`'s docstring: an active client (a request
in flight or answered within ``active_window``) is never evicted by a newcomer; the
idle and the silent go first, by how long they have said nothing; the newcomer is
refused when nobody else can go; one host holds at most ``max_per_host`` slots.

Real loopback sockets; other client hosts are other loopback addresses
(127.0.0.2, 127.0.0.3: all of 127.0.0.0/8 is loopback on Linux). No duration is
asserted; waits are bounded far above their expected value.
"""
from __future__ import annotations

import logging
import socket
import subprocess
import sys
import threading
import time
from typing import List

import pytest

from tcp_bridge.server import ServerOptions, default_max_per_host
from tcp_bridge.wire import Status
from tests.test_bridge_server import Running, exchange, make_engine, named, write_config
from tests.test_bridge_slots import closed_unanswered

OK = [named("1 R 86=0", Status.ACK)]


def connect_from(r: Running, host: str) -> socket.socket:
    sock = socket.create_connection(r.addresses[0], timeout=10, source_address=(host, 0))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


class Poller:
    """A client that polls ``1R86`` every ``period`` s on one connection and records
    every reply, or the error that ended it."""

    def __init__(self, r: Running, period: float) -> None:
        self.sock = r.connect()
        self.sock.settimeout(10)
        self.port = self.sock.getsockname()[1]
        self.period = period
        self.replies: List[List[bytes]] = []
        self.failure = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "Poller":
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.replies.append(exchange(self.sock, b"1R86"))
            except (OSError, AssertionError) as exc:  # closed: the server evicted us
                self.failure = f"after {len(self.replies)} polls: {exc!r}"
                return
            self._stop.wait(self.period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(30)
        self.sock.close()


# --- must show 6: a burst of 200 connections never disconnects an active client ------------


@pytest.mark.parametrize("period", [1.0, 0.02])
@pytest.mark.parametrize("max_per_host", [None, 64])  # the default cap (32), and no cap
def test_a_burst_of_200_connections_never_disconnects_a_polling_client(
        period: float, max_per_host: object, caplog: pytest.LogCaptureFixture) -> None:
    r = Running(make_engine(), max_connections=64, max_per_host=max_per_host)
    burst: List[socket.socket] = []
    poller = Poller(r, period)
    try:
        with caplog.at_level(logging.WARNING, logger="tcp_bridge.server"):
            poller.start()
            # The burst starts between two polls, as in the issue (its connections'
            # clocks are newer than the poller's last request).
            time.sleep(min(period / 2, 0.5))
            for _ in range(200):
                burst.append(socket.create_connection(r.addresses[0], timeout=10))
            # The burst is over once the server has seen every connection: it holds
            # its full share of slots, evicting and refusing the rest.
            time.sleep(2.5 * period if period > 0.1 else 0.5)
            polls = len(poller.replies)
            deadline = time.monotonic() + 30
            while len(poller.replies) < polls + 2 and not poller.failure:
                assert time.monotonic() < deadline, "the poller stopped getting replies"
                time.sleep(0.01)
        poller.stop()
        assert poller.failure == ""  # never disconnected
        assert all(reply == OK for reply in poller.replies)
        assert "closing ('127.0.0.1', %d)" % poller.port not in caplog.text
        assert "silent since it connected" in caplog.text  # the burst churned its own slots
        # After the burst a new client is served: it takes a silent connection's slot.
        with r.connect() as late:
            assert exchange(late, b"1R86") == OK
    finally:
        poller.stop()
        for sock in burst:
            sock.close()
        r.stop()


# --- the ranking ---------------------------------------------------------------------------


def test_the_idle_go_before_the_silent(caplog: pytest.LogCaptureFixture) -> None:
    # Ranked by the time each last said something: robust to a slow machine, since a
    # stall only makes more connections evictable, never changes their order.
    r = Running(make_engine(), max_connections=3, max_per_host=3, active_window=0.3)
    try:
        with caplog.at_level(logging.WARNING, logger="tcp_bridge.server"):
            idle, active = r.connect(), r.connect()
            assert exchange(idle, b"1R86") == OK
            time.sleep(0.4)  # idle is idle now
            silent = r.connect()  # connected after idle's last request
            assert exchange(active, b"1R86") == OK
            with r.connect() as first:  # the idle goes, though the silent came later
                assert closed_unanswered(idle)
                assert exchange(first, b"1R86") == OK
                assert exchange(active, b"1R86") == OK
                with r.connect() as second:  # then the silent
                    assert closed_unanswered(silent)
                    assert exchange(second, b"1R86") == OK
                    assert exchange(first, b"1R86") == OK and exchange(active, b"1R86") == OK
        assert "idle for" in caplog.text and "silent since it connected" in caplog.text
        for sock in (idle, silent, active):
            sock.close()
    finally:
        r.stop()


def test_a_newcomer_is_refused_when_every_connection_is_active(
        caplog: pytest.LogCaptureFixture) -> None:
    r = Running(make_engine(), max_connections=2, max_per_host=2)  # active_window 10 s
    try:
        with caplog.at_level(logging.WARNING, logger="tcp_bridge.server"):
            with connect_from(r, "127.0.0.1") as a, connect_from(r, "127.0.0.2") as b:
                assert exchange(a, b"1R86") == exchange(b, b"1R86") == OK
                with connect_from(r, "127.0.0.3") as newcomer:
                    assert closed_unanswered(newcomer)
                assert exchange(a, b"1R86") == exchange(b, b"1R86") == OK
        assert "all 2 connections are taken, and each is active" in caplog.text
    finally:
        r.stop()


def test_one_host_cannot_take_every_slot(caplog: pytest.LogCaptureFixture) -> None:
    r = Running(make_engine(), max_connections=4, max_per_host=2)
    socks: List[socket.socket] = []
    try:
        with caplog.at_level(logging.WARNING, logger="tcp_bridge.server"):
            a1, a2 = connect_from(r, "127.0.0.1"), connect_from(r, "127.0.0.1")
            socks += [a1, a2]
            assert exchange(a1, b"1R86") == exchange(a2, b"1R86") == OK
            a3 = connect_from(r, "127.0.0.1")  # its host is at the cap, both active
            socks.append(a3)
            assert closed_unanswered(a3)
            assert "its host already holds 2 connections" in caplog.text
            # Another host gets the slots the first could not take.
            b1, b2 = connect_from(r, "127.0.0.2"), connect_from(r, "127.0.0.2")
            socks += [b1, b2]
            assert exchange(b2, b"1R86") == OK
            # A third host, all slots taken: only b1 (silent) can go.
            c1 = connect_from(r, "127.0.0.3")
            socks.append(c1)
            assert closed_unanswered(b1)
            assert exchange(c1, b"1R86") == OK
            # A burst from the first host never touches the other hosts' slots.
            for _ in range(20):
                burst = connect_from(r, "127.0.0.1")
                socks.append(burst)
                assert closed_unanswered(burst)
            for sock in (a1, a2, b2, c1):
                assert exchange(sock, b"1R86") == OK
    finally:
        for sock in socks:
            sock.close()
        r.stop()


# --- the cap's default and its checks ------------------------------------------------------


def test_max_per_host_default_and_checks() -> None:
    assert ServerOptions().max_per_host == 32 == default_max_per_host(64)
    assert default_max_per_host(1) == 1 and default_max_per_host(5) == 3
    assert ServerOptions(max_connections=8, max_per_host=8).max_per_host == 8
    for bad in (0, 9, 2.0, True, "4"):
        with pytest.raises(ValueError, match="max_per_host: must be an integer 1..8"):
            ServerOptions(max_connections=8, max_per_host=bad)  # type: ignore[arg-type]
    for bad_window in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="active_window"):
            ServerOptions(active_window=bad_window)


@pytest.mark.parametrize("args,message", [
    (["--max-per-host", "65"], "--max-per-host 65 is more than --max-connections 64"),
    (["--max-per-host", "0"], "argument --max-per-host: 0 is not a positive integer"),
    (["--max-per-host", "x"], "argument --max-per-host:"),
])
def test_max_per_host_mistakes_are_one_line(tmp_path: object, args: List[str],
                                            message: str) -> None:
    config = write_config(tmp_path)  # type: ignore[arg-type]
    proc = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                           str(config), "--port", "0", "--maintenance-port", "-1", *args],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1 and message in proc.stderr
