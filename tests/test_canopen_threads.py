"""Two threads on one node through the gateway never interleave frames (issue 5).

canopen's own SdoClient is not thread-safe; ours holds the link for a whole
transfer. The traffic is recorded and checked: every request is followed by
its answer before the next request starts.
"""
from __future__ import annotations

import io
import threading

from epos_link import canopen_adapter
from epos_link.capture import Direction, read_capture
from epos_link.client import EposClient
from epos_link.framing import NEED_DATA, FrameDecoder
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import PtyLink
from epos_link.transports import open_transport
from epos_link.transports.trace import TracingTransport


def test_threads_share_one_node() -> None:
    with Epos4Simulator(1, [2]) as sim:
        link = PtyLink(sim).start()
        log = io.StringIO()
        client = EposClient(TracingTransport(open_transport(link.path), log), timeout=1.0)
        node = canopen_adapter.connect_node(client, 2)
        errors: list[BaseException] = []

        def worker(index: int, base: int) -> None:
            try:
                for i in range(60):
                    node.sdo[index].raw = base + i
                    assert node.sdo[index].raw == base + i
                    assert node.sdo["Manufacturer device name"].raw == "EPOS4"  # segmented
            except BaseException as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=worker, args=(0x607A, 1000)),
                   threading.Thread(target=worker, args=(0x30B0, -5000))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        client.close()
        link.close()
    assert not errors, errors
    # Strict alternation: TX frame, its RX answer, TX, RX, ... never TX TX.
    # A read may carry part of a frame: decode each direction as a stream and
    # note the direction each time a frame completes.
    decoders = {d: FrameDecoder() for d in Direction}
    directions = []
    for record in read_capture(log.getvalue()).records:
        dec = decoders[record.direction]
        dec.feed(record.data)
        while dec.next_frame() is not NEED_DATA:
            directions.append(record.direction)
    assert len(directions) >= 2 * 60 * 2 * 3
    assert directions == [Direction.TX, Direction.RX] * (len(directions) // 2)


def test_gateway_limitations_are_named() -> None:
    import pytest

    from epos_link.canopen_adapter import GatewayLimitationError
    from epos_link.simulator.transport import open_sim

    with EposClient(open_sim("sim://?drives=2")) as client:
        node = canopen_adapter.connect_node(client, 2)
        node.pdo.read()
        for action, what in [(lambda: node.tpdo[1].transmit(), "PDO"),
                             (lambda: node.tpdo[1].wait_for_reception(0.1), "PDO reception"),
                             (lambda: node.emcy.wait(timeout=0.1), "EMCY"),
                             (lambda: node.nmt.wait_for_heartbeat(0.1), "heartbeat"),
                             (lambda: node.network.sync.transmit(), "SYNC"),
                             (lambda: node.sdo.download(0x1008, 0, b"123456"), "segmented")]:
            with pytest.raises(GatewayLimitationError, match=what):
                action()
        node.nmt.state = "OPERATIONAL"  # NMT goes through SendNMTService
