"""Issue 23, must-show 3: a bridge killed with SIGKILL during a velocity move stops the drive.

``tcp-bridge serve`` (canopen backend, ``heartbeat_ms = 100``) and the
simulated drives run in separate processes on one cross-process CAN bus. A
client enables axis 2 and starts a velocity move; the bridge is killed with
SIGKILL; a listener on the bus sees the drive's EMCY 8130h ("heartbeat error",
CiA 301 Table 21) no later than three heartbeat periods (the consumer time)
plus one after the last heartbeat, and the drive, read by SDO once the bridge
is gone, is in quick stop (or past it, in SWITCH ON DISABLED) and comes to
rest. Without ``heartbeat_ms`` the same kill leaves the drive turning.

Times are taken from the bus's own frame timestamps (the last heartbeat, the
EMCY), not from the kill, so a loaded machine that is slow to deliver SIGKILL
does not make the test flaky; the waits around them allow 10x.

Needs two parts that are built in parallel (issue 23): the simulated drives'
heartbeat consumer (EMCY 8130h and 6007h on a missed heartbeat) and a way to
run the simulator in its own process on a CAN bus that other processes can
join. Until both are there the tests skip; :func:`simulator_process` is the
one place to complete at merge.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional

import pytest

from tests.helpers import psi_ask, wait_until

PERIOD_MS = 100
NODE = 2
EMCY_HEARTBEAT = 0x8130


def bus_options() -> Optional[Dict[str, Any]]:
    """The python-can options of a bus that several processes can share, or None."""
    raw = os.environ.get("BRIDGE_E2E_CAN")  # e.g. "udp_multicast:239.74.163.2"
    if raw:
        interface, _, channel = raw.partition(":")
        return {"interface": interface, "channel": channel}
    return None


def simulator_process(options: Dict[str, Any], tmp: Path) -> subprocess.Popen:
    """Start the simulated drive ``NODE`` in its own process on the bus of ``options``.

    To complete at merge: the simulator's cross-process CAN link (another
    engineer's part of issue 23) and its heartbeat consumer.
    """
    pytest.skip("no command yet runs the simulator, with its heartbeat consumer, on a "
                "cross-process CAN bus (issue 23: completed at merge)")


def write_table(tmp: Path, options: Dict[str, Any], heartbeat: bool) -> Path:
    lines = ["[bridge]", "ack_timeout = 5.0", "", "[bus.can1]", 'backend = "canopen"',
             'eds = "default"']
    lines += [f"{k} = {v!r}".replace("'", '"') for k, v in options.items()]
    if heartbeat:
        lines.append(f"heartbeat_ms = {PERIOD_MS}")
    lines += ["", "[[axis]]", "addr = 1", "device = 5", f"node_id = {NODE}",
              "position_factor = 1000", "increments_per_revolution = 2000"]
    path = tmp / "axes.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def bus() -> Iterator[Dict[str, Any]]:
    options = bus_options()
    if options is None:
        pytest.skip("set BRIDGE_E2E_CAN=interface:channel to a bus several processes share")
    yield options


def serve(table: Path, port: int) -> subprocess.Popen:
    log = table.with_suffix(".log")
    with log.open("w") as out:  # a file, not a pipe nobody drains once it serves
        bridge = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                                   str(table), "--port", str(port), "--maintenance-port", "-1"],
                                  stdout=out, stderr=subprocess.STDOUT, text=True)
    wait_until(lambda: "listening on" in log.read_text() or bridge.poll() is not None, 60,
               "the bridge never listened")
    assert bridge.poll() is None, log.read_text()
    return bridge


def start_velocity_move(port: int) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        for line in ("1S04=1", "1S05=5", "1S06=50", "1S00=3"):
            reply = psi_ask(sock, line)
            assert reply.status.name == "ACK", (line, reply)


def run_and_kill(bus: Dict[str, Any], tmp_path: Path, heartbeat: bool) -> List[Any]:
    """Serve, move, SIGKILL the bridge; the frames seen on the bus up to 4 s later."""
    import can

    sim = simulator_process(bus, tmp_path)
    listener = can.Bus(**bus)
    bridge: Optional[subprocess.Popen] = None
    try:
        port = free_port()
        bridge = serve(write_table(tmp_path, bus, heartbeat), port)
        start_velocity_move(port)
        time.sleep(0.5)
        while listener.recv(0) is not None:
            pass  # only what follows the kill
        os.kill(bridge.pid, signal.SIGKILL)
        bridge.wait(30)
        frames, end = [], time.monotonic() + 4.0
        while time.monotonic() < end:
            message = listener.recv(0.1)
            if message is not None:
                frames.append(message)
        return frames
    finally:
        if bridge is not None and bridge.poll() is None:
            bridge.kill()
        listener.shutdown()
        sim.terminate()
        sim.wait(30)


def test_a_killed_bridge_stops_the_drive_within_four_periods(
        bus: Dict[str, Any], tmp_path: Path) -> None:
    frames = run_and_kill(bus, tmp_path, heartbeat=True)
    beats = [m for m in frames if m.arbitration_id == 0x700 + 127]
    emcy = [m for m in frames if m.arbitration_id == 0x80 + NODE
            and int.from_bytes(bytes(m.data[:2]), "little") == EMCY_HEARTBEAT]
    assert emcy, "no EMCY 8130h after the bridge died"
    last_beat = beats[-1].timestamp if beats else None
    if last_beat is not None:  # the kill may land between two heartbeats: none after it
        assert emcy[0].timestamp - last_beat <= (3 + 1) * PERIOD_MS / 1000
    wait_until(lambda: drive_at_rest(bus), 10, "the drive did not come to rest")


def test_without_heartbeat_a_killed_bridge_leaves_the_drive_turning(
        bus: Dict[str, Any], tmp_path: Path) -> None:
    frames = run_and_kill(bus, tmp_path, heartbeat=False)
    assert not [m for m in frames if m.arbitration_id == 0x80 + NODE]
    assert not drive_at_rest(bus)


def drive_at_rest(options: Dict[str, Any]) -> bool:
    """The drive's statusword and velocity, read by SDO now that the bridge is gone."""
    import canopen

    network = canopen.Network()
    network.connect(**options)
    try:
        node = network.add_node(NODE, canopen.ObjectDictionary())
        statusword = int.from_bytes(node.sdo.upload(0x6041, 0)[:2], "little")
        velocity = int.from_bytes(node.sdo.upload(0x606C, 0)[:4], "little", signed=True)
        quick_stop_or_after = statusword & 0x6F == 0x07 or statusword & 0x4F == 0x40
        return quick_stop_or_after and velocity == 0
    finally:
        network.disconnect()
