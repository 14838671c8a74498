"""The ``sim`` backend with ``link = "can"``: the canopen backend on the embedded simulator's
virtual CAN bus, so PDO-fed status can be tried without a CAN adapter (issue 14)."""
from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tcp_bridge.tables.axes import AxisTable, ConfigError, simulated_increments_per_revolution
from tcp_bridge.backends.sim import SimCanBackend
from tcp_bridge.engine import build_engine
from tcp_bridge.wire import Status, decode_reply, parse_request
from tests.helpers import wait_until


def table(**bus: object) -> AxisTable:
    return AxisTable.from_mapping({
        "bus": {"can1": {"backend": "sim", **bus}},
        "axis": [{"device": 5, "node_id": n, "position_factor": 1000,
                  "increments_per_revolution": simulated_increments_per_revolution()}
                 for n in (1, 2, 3)],
    })


def test_status_polls_come_from_pdos_of_the_simulated_drives() -> None:
    engine = build_engine(table(link="can", pdo=True, pdo_max_age=1.0))
    try:
        backend = engine.backends[0]
        assert isinstance(backend, SimCanBackend)
        wait_until(lambda: all(f.value(0x6041) is not None for f in backend.pdo.feeds.values()),
                   why="no PDOs from the simulated drives")
        shared = engine.shared["can1"]
        for axis in (1, 2, 3):  # the EPOS4 itself too: it is a node on its own CAN bus
            reply = decode_reply(engine.execute_sync(parse_request(b"%dR10" % axis)))
            assert reply.status is Status.ACK
            assert int(reply.value or "") == backend.drive(axis).statusword

        async def polls() -> list:
            return [await engine.execute(parse_request(b"%dR10" % axis)) for axis in (1, 2, 3)]
        assert all(decode_reply(r).status is Status.ACK for r in asyncio.run(polls()))
        assert shared.fast >= 1  # answered from PDOs on the loop, without the bus
    finally:
        engine.close()


def test_without_pdo_the_can_link_reads_by_sdo() -> None:
    engine = build_engine(table(link="can"))
    try:
        reply = decode_reply(engine.execute_sync(parse_request(b"2R12")))
        assert reply.status is Status.ACK and reply.value == "0"
    finally:
        engine.close()


@pytest.mark.parametrize("bus,message", [
    ({"pdo": True}, "pdo only with link = \"can\""),
    ({"link": "can", "baud": 115200}, "['baud'] do not apply to link = \"can\""),
    ({"link": "serial"}, "sim link must be \"inprocess\", \"pty\" or \"can\", not 'serial'"),
    ({"link": "CAN", "pdo": True}, "sim link must be \"inprocess\", \"pty\" or \"can\", not 'CAN'"),
])
def test_options_in_the_wrong_place_are_one_config_error(bus: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        build_engine(table(**bus))


def test_a_config_file_with_a_simulated_can_bus_serves(tmp_path: Path) -> None:
    cfg = tmp_path / "sim-can.toml"
    cfg.write_text('[bus.can1]\nbackend = "sim"\nlink = "can"\npdo = true\n'
                   '[[axis]]\nnode_id = 1\n[[axis]]\nnode_id = 2\n')
    engine = build_engine(AxisTable.load(cfg))
    try:
        assert decode_reply(engine.execute_sync(parse_request(b"2R10"))).status is Status.ACK
    finally:
        engine.close()
