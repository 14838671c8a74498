"""Issue 30, findings 4 and 5: the drives' supervision stays true across a clean
shutdown, a restart and S81, with ``tcp-bridge serve`` (canopen backend,
``heartbeat_ms``) and the simulated drives in separate processes, as they were seen.

* SIGTERM (a clean shutdown) during a profile velocity move: the move is ramped
  down before the drive's heartbeat consumer is switched off; it was left turning,
  unwatched.
* A bridge that starts and finds the drive enabled and turning (moved by another
  master here) arms the drive's consumer before it answers anything about the axis:
  killed with SIGKILL after its first answer, the drive stops (EMCY 8130h). It was
  not armed until a client's S04=1 or move, and the kill left the axis turning.
* S81 into 1016h (consumer) or 6007h (abort connection option) of a supervised,
  moving drive is NAK, and a SIGKILL afterwards still stops it.

The processes, the bus and the drive's view are those of
``tests/test_bridge_heartbeat_e2e.py`` (``epos-link sim --can-server``; the bridge
and the test join its CAN bus over socketcand).
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Tuple

import pytest

from tests.helpers import psi_ask, wait_until
from tests.test_bridge_heartbeat_e2e import (EMCY_HEARTBEAT, NODE, drive_at_rest, free_port,
                                             serve, simulator_process, start_velocity_move,
                                             write_table)

CONSUMER_SELECTOR = 0x1016 << 16 | 1 << 8 | 4  # S80: 1016h/01, 4 bytes (PSI spec 80)
ABORT_SELECTOR = 0x6007 << 16 | 0 << 8 | 2  # S80: 6007h/00, 2 bytes


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[Dict[str, Any]]:
    sim, options = simulator_process(tmp_path)
    try:
        yield options
    finally:
        if sim is not None:
            sim.terminate()
            sim.wait(30)


def sdo(options: Dict[str, Any], *writes: Tuple[int, int, int, int]) -> Dict[str, int]:
    """As another master on the bus: SDO downloads (index, sub, value, size), then the
    drive's statusword, velocity (606Ch) and consumer entry (1016h:01) read back."""
    import canopen

    network = canopen.Network()
    network.connect(**options)
    try:
        node = network.add_node(NODE, canopen.ObjectDictionary())
        node.sdo.RESPONSE_TIMEOUT = 2.0
        for index, sub, value, size in writes:
            node.sdo.download(index, sub, (value & ((1 << 8 * size) - 1)).to_bytes(size, "little"))
        return {"statusword": int.from_bytes(node.sdo.upload(0x6041, 0)[:2], "little"),
                "velocity": int.from_bytes(node.sdo.upload(0x606C, 0)[:4], "little", signed=True),
                "consumer": int.from_bytes(node.sdo.upload(0x1016, 1)[:4], "little")}
    finally:
        network.disconnect()


def ask(port: int, *lines: str) -> List[str]:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        return [psi_ask(sock, line).status.name for line in lines]


def kill_and_listen(bridge: "subprocess.Popen[str]", options: Dict[str, Any]) -> List[Any]:
    """SIGKILL the bridge; the drive's EMCY frames seen in the 4 s that follow."""
    import can

    listener = can.Bus(**options)
    try:
        os.kill(bridge.pid, signal.SIGKILL)
        bridge.wait(30)
        frames, end = [], time.monotonic() + 4.0
        while time.monotonic() < end:
            message = listener.recv(0.1)
            if message is not None and message.arbitration_id == 0x80 + NODE:
                frames.append(message)
        return frames
    finally:
        listener.shutdown()


def heartbeat_emcy(frames: List[Any]) -> bool:
    return any(int.from_bytes(bytes(m.data[:2]), "little") == EMCY_HEARTBEAT for m in frames)


def stop(bridge: Optional["subprocess.Popen[str]"]) -> None:
    if bridge is not None and bridge.poll() is None:
        bridge.kill()
        bridge.wait(30)


def test_sigterm_ramps_a_velocity_move_down_before_the_consumer_is_released(
        tmp_path: Path, bus: Dict[str, Any]) -> None:
    port = free_port()
    bridge = serve(write_table(tmp_path, bus, heartbeat=True), port)
    try:
        start_velocity_move(port)
        time.sleep(0.3)
        assert sdo(bus)["velocity"] != 0
        bridge.send_signal(signal.SIGTERM)
        assert bridge.wait(60) == 0
        seen = sdo(bus)
        assert seen["consumer"] == 0  # released: a clean shutdown trips nothing ...
        assert seen["velocity"] == 0  # ... and leaves nothing turning unwatched
        assert seen["statusword"] & 0x6F == 0x27  # at rest by halt, still enabled
    finally:
        stop(bridge)


def test_a_bridge_that_finds_a_drive_turning_supervises_it_before_answering(
        tmp_path: Path, bus: Dict[str, Any]) -> None:
    # Another master enables the drive and starts a profile velocity move (CiA 402-2
    # 6.9: mode 3, 60FFh, then enable operation without halt).
    sdo(bus, (0x6060, 0, 3, 1), (0x6083, 0, 10000, 4), (0x60FF, 0, 200, 4),
        (0x6040, 0, 0x06, 2), (0x6040, 0, 0x07, 2), (0x6040, 0, 0x0F, 2))
    wait_until(lambda: sdo(bus)["velocity"] != 0, 10, "the other master's move never started")
    port = free_port()
    bridge = serve(write_table(tmp_path, bus, heartbeat=True), port)
    try:
        assert ask(port, "1R10") == ["ACK"]  # its first answer about the axis
        frames = kill_and_listen(bridge, bus)
        assert heartbeat_emcy(frames), "the drive did not react to the bridge's death"
        wait_until(lambda: drive_at_rest(bus), 10, "the drive did not come to rest")
    finally:
        stop(bridge)


def test_s81_cannot_switch_a_moving_drive_s_supervision_off(
        tmp_path: Path, bus: Dict[str, Any]) -> None:
    port = free_port()
    bridge = serve(write_table(tmp_path, bus, heartbeat=True), port)
    try:
        start_velocity_move(port)
        assert ask(port, f"1S80={CONSUMER_SELECTOR}", "1S81=0",
                   f"1S80={ABORT_SELECTOR}", "1S81=0") == ["ACK", "NAK", "ACK", "NAK"]
        assert "1016" in bridge_log(tmp_path) and "supervision" in bridge_log(tmp_path)
        frames = kill_and_listen(bridge, bus)
        assert heartbeat_emcy(frames), "the drive did not react to the bridge's death"
        wait_until(lambda: drive_at_rest(bus), 10, "the drive did not come to rest")
    finally:
        stop(bridge)


def bridge_log(tmp_path: Path) -> str:
    return (tmp_path / "axes.log").read_text()
