"""Two threads share one client: one request in flight at a time, each gets its own answer.

The responder holds every answer back for a moment and counts bytes that arrive
meanwhile: a second request sent before the first answer would show there.
"""
from __future__ import annotations

import threading

import pytest

from epos_link.client import EposClient
from epos_link.transports import open_transport
from epos_link.transports.serial import open_serial
from tests.responder import PtyResponder, SocketResponder, read_pair

ROUNDS = 40
SCRIPT = dict([
    read_pair(1, 0x6064, 0, (111).to_bytes(4, "little")),
    read_pair(2, 0x606C, 0, (222).to_bytes(4, "little")),
])


@pytest.mark.parametrize("kind", ["socket", "pty"])
def test_two_threads_do_not_interleave(kind: str) -> None:
    responder = (SocketResponder if kind == "socket" else PtyResponder)(SCRIPT, delay=0.001)
    with responder as dev:
        link = open_transport(dev.url) if kind == "socket" else open_serial(dev.path)  # type: ignore[attr-defined]
        client = EposClient(link, timeout=5.0, retries=0)  # answers come in ms
        results: dict[int, list[int]] = {1: [], 2: []}
        errors: list[BaseException] = []
        start = threading.Barrier(2)

        def worker(node: int, index: int) -> None:
            try:
                start.wait()
                for _ in range(ROUNDS):
                    results[node].append(int.from_bytes(client.read_object(node, index, 0), "little"))
            except BaseException as exc:  # reported below, in the main thread
                errors.append(exc)

        threads = [threading.Thread(target=worker, args=(1, 0x6064)),
                   threading.Thread(target=worker, args=(2, 0x606C))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        client.close()
    assert not errors, errors
    assert results == {1: [111] * ROUNDS, 2: [222] * ROUNDS}
    assert dev.requests == 2 * ROUNDS
    assert dev.interleaved == 0
    assert not dev.unexpected
