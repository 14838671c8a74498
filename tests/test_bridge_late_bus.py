"""A bus that cannot be opened at start-up (issue 24 point 2): ``tcp-bridge serve`` starts
with the buses it can open, answers NAK for the axes of the missing one, opens it in the
background, and serves it once its device appears; a misconfigured bus still refuses to
start. The ``serve`` tests run the real command line; the unit tests use the engine."""
from __future__ import annotations

import logging
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterator, List

import pytest

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink
from tcp_bridge.backends.reopen import UnopenedBackend
from tcp_bridge.engine import build_engine
from tcp_bridge.errors import BusUnavailable
from tcp_bridge.tables.axes import AxisTable
from tcp_bridge.wire import Status
from tests.helpers import wait_until

WAIT = 60.0  # far above what any step needs (a loaded 2-core machine)


def free_port() -> int:
    """A port nothing listens on now (connections to it are refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def two_buses(port: int) -> str:
    """Bus can1: the embedded simulator (axes 1, 2); bus can2: an EPOS4 at socket://PORT
    behind which node 2 is a drive (axes 3, 4)."""
    return (f'[bridge]\nprobe_interval = 0.1\n'
            f'[bus.can1]\nbackend = "sim"\n'
            f'[bus.can2]\nbackend = "epos"\nurl = "socket://127.0.0.1:{port}"\n'
            f'timeout = 0.5\ngateway_node_id = 1\n'
            '[[axis]]\nnode_id = 1\n[[axis]]\nnode_id = 2\n'
            '[[axis]]\nnode_id = 1\nbus_offset = 100000\n'
            '[[axis]]\nnode_id = 2\nbus_offset = 100000\n')


@pytest.fixture()
def serve(tmp_path: Path) -> Iterator[Any]:
    procs: List[subprocess.Popen[str]] = []

    def start(config: str) -> "tuple[subprocess.Popen[str], str]":
        path = tmp_path / "axes.toml"
        path.write_text(config)
        proc = subprocess.Popen(
            [sys.executable, "-m", "tcp_bridge.cli", "serve", "--config", str(path), "--port", "0",
             "--maintenance-port", "0", "--state-file", str(tmp_path / "state.toml")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(proc)
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert "listening on" in line, line + proc.stderr.read()  # type: ignore[union-attr]
        return proc, line.split("listening on ")[1].split()[0]

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=WAIT)


def statuses(address: str, *lines: str) -> List[Status]:
    from tcp_bridge.cli import send

    return [r.status for r in send(address, list(lines))]


def test_serve_starts_without_a_missing_bus_and_opens_it_when_its_device_appears(serve: Any) -> None:
    port = free_port()
    proc, address = serve(two_buses(port))
    # The bus that opened serves; the missing bus's axes answer NAK, at once.
    assert statuses(address, "1R10", "2R10", "2R04") == [Status.ACK] * 3
    started = time.monotonic()
    assert statuses(address, "3R10", "4R10", "4S04=1") == [Status.NAK] * 3
    assert time.monotonic() - started < WAIT / 4  # no transfer waited on: refused at once
    # Its device appears (the converter's port opens): within a few probes, ACK, no restart.
    sim = Epos4Simulator(1, [2])
    link = TcpLink(sim, port=port).start()
    try:
        wait_until(lambda: statuses(address, "4R10") == [Status.ACK], timeout=WAIT,
                   why="the late bus's axis never answered ACK")
        assert statuses(address, "3R10", "4R10", "1R10", "2R10") == [Status.ACK] * 4
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT)
    finally:
        link.close()
        sim.close()
    assert proc.returncode == 0
    # Logged once with the reason when it could not be opened, once when it answers.
    refused = [line for line in err.splitlines() if "cannot open" in line]
    assert len(refused) == 1, err
    assert f"bus can2: cannot open socket://127.0.0.1:{port}" in refused[0]
    assert "answer NAK" in refused[0]
    assert sum("bus can2: device answers again" in line for line in err.splitlines()) == 1, err


@pytest.mark.parametrize("bus, words", [
    ('backend = "epos"\nurl = "socket://127.0.0.1:1"\nspeed = 3\n', "speed"),
    ('backend = "nosuch"\n', "unknown backend 'nosuch'"),
])
def test_a_misconfigured_bus_still_refuses_to_start(tmp_path: Path, bus: str, words: str) -> None:
    path = tmp_path / "axes.toml"
    path.write_text(f'[bus.can1]\n{bus}[[axis]]\nnode_id = 1\n')
    p = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config", str(path),
                        "--port", "0", "--maintenance-port", "0"],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 2 and words in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr


# -- the engine and the stand-in backend ------------------------------------------------------


def test_build_engine_declares_the_missing_bus_silent_from_the_start(
        caplog: pytest.LogCaptureFixture) -> None:
    table = AxisTable.from_mapping({
        "bus": {"can1": {"backend": "instant"},
                "can2": {"backend": "epos", "url": f"socket://127.0.0.1:{free_port()}"}},
        "axis": [{"node_id": 1}, {"node_id": 1, "bus_offset": 100000}]})
    with caplog.at_level(logging.WARNING):
        engine = build_engine(table)
    try:
        assert not engine.guards["can1"].health.silent and engine.guards["can2"].health.silent
        refusal = engine.guards["can2"].refusal(1)
        assert refusal is not None and "Connection refused" in str(refusal)
        unopened = [b for b in engine.backends if isinstance(b, UnopenedBackend)]
        assert [b.name for b in unopened] == ["can2"]
    finally:
        engine.close()
    assert sum("cannot open" in r.getMessage() for r in caplog.records) == 1


def test_late_nodes_raise_bus_unavailable_until_the_backend_opens() -> None:
    attempts: List[int] = []
    real: List[Any] = []

    class Nmt:
        def __init__(self) -> None:
            self.callbacks: List[Any] = []
            self.state = "PRE-OPERATIONAL"

        def add_heartbeat_callback(self, callback: Any) -> None:
            self.callbacks.append(callback)

    class Real:
        def __init__(self) -> None:
            self.probed = 0
            self.waits: List[Any] = []
            self.nmt = Nmt()

        def node(self, node_id: int) -> Any:
            return SimpleNamespace(sdo=f"sdo of {node_id}", nmt=self.nmt)

        def attach_wait(self, hook: Any) -> None:
            self.waits.append(hook)

        def probe(self) -> None:
            self.probed += 1

        def close(self) -> None:
            pass

    def opener() -> Any:
        attempts.append(1)
        if len(attempts) < 3:
            raise BusUnavailable("bus can2: cannot open /dev/ttyUSB9: No such file or directory")
        real.append(Real())
        return real[0]

    backend = UnopenedBackend("can2", opener, "bus can2: cannot open /dev/ttyUSB9: gone")
    node = backend.node(4)
    node.nmt.add_heartbeat_callback(len)  # as tcp_bridge.plan.axis does at start-up
    backend.attach_wait(print)
    assert backend.why == "cannot open /dev/ttyUSB9: gone"  # the log line names the bus
    with pytest.raises(BusUnavailable):
        node.sdo
    with pytest.raises(BusUnavailable):
        node.nmt.state = "RESET"
    for _ in range(2):
        with pytest.raises(BusUnavailable, match="No such file"):
            backend.probe()
    assert backend.why == "cannot open /dev/ttyUSB9: No such file or directory"
    backend.probe()  # opens, then the real backend's own probe
    assert len(attempts) == 3 and real[0].probed == 1 and real[0].waits == [print]
    assert node.sdo == "sdo of 4" and real[0].nmt.callbacks == [len]  # handed over once
    node.nmt.state = "RESET"
    assert real[0].nmt.state == "RESET"
    backend.probe()
    assert len(attempts) == 3  # opened once


def _csp_table(bus: dict) -> AxisTable:  # type: ignore[type-arg]
    name = "ethercat" if bus["backend"] == "ethercat" else "can2"
    offset = 1000000 if name == "ethercat" else 100000
    return AxisTable.from_mapping({"bus": {name: bus}, "axis": [
        {"node_id": 1, "internal": True, "device": 5, "increments_per_revolution": 2000,
         "bus_offset": offset}]})


def _pysoem_missing() -> bool:
    try:
        import pysoem  # noqa: F401
    except ImportError:
        return True
    return False


@pytest.mark.parametrize("bus", [
    {"backend": "canopen", "interface": "socketcan", "channel": "nocan9", "heartbeat_ms": 200},
    pytest.param({"backend": "ethercat", "interface": "nonexist0"},
                 marks=pytest.mark.skipif(_pysoem_missing(), reason="pysoem: the [ethercat] extra")),
], ids=["canopen", "ethercat"])
def test_an_internal_csp_axis_on_a_bus_missing_at_start_up_gets_its_stream_once_open(
        bus: dict) -> None:  # type: ignore[type-arg]
    """A bridge started while the EtherCAT slaves did not answer yet (a loaded machine, a
    line powered later) exited 2 with 'bus ethercat cannot stream set-points': the
    stand-in nodes of a bus opened later have no set-point thread. Now the bus is silent
    (NAK) until its probes open it, and the axis then streams through the real one."""
    engine = build_engine(_csp_table(bus))
    try:
        name = "ethercat" if bus["backend"] == "ethercat" else "can2"
        assert engine.guards[name].health.silent
        axis = engine.axes[1]
        assert axis.cyclic is None  # nothing to stream through yet ...
        assert axis.drive is not None and axis.drive.rest is not None  # ... its rest is there
        stand_in = next(b for b in engine.backends if isinstance(b, UnopenedBackend))
        sender = object()
        real = SimpleNamespace(node=lambda node_id: SimpleNamespace(
            cyclic=sender, sdo=None, nmt=SimpleNamespace(add_heartbeat_callback=lambda cb: None)),
            close=lambda: None)
        stand_in._opener = lambda: real  # the device appeared
        stand_in.probe()
        assert axis.cyclic is sender
    finally:
        engine.close()


def test_a_csp_axis_on_a_missing_bus_that_could_never_stream_is_still_a_table_mistake() -> None:
    table = AxisTable.from_mapping({
        "bus": {"can2": {"backend": "epos", "url": f"socket://127.0.0.1:{free_port()}"}},
        "axis": [{"node_id": 1, "internal": True, "device": 5,
                  "increments_per_revolution": 2000, "bus_offset": 100000}]})
    with pytest.raises(Exception, match="cannot stream set-points"):
        build_engine(table)
