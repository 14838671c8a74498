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

The simulator runs as ``epos-link sim --can-server``: its CAN bus is served
over socketcand, which the bridge (canopen backend, ``interface =
"socketcand"``) and the test's listener join.

The same scenario as a user tries it, docs/simulator.md "Try the
drive-stops-when-the-bridge-dies scenario", runs here too: its console block,
command by command with the doc tests' runner (tests/doc_blocks.py), against
the table the checkout ships (``tcp_bridge/example_heartbeat_axes.toml``).
"""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple


from tests.doc_blocks import ROOT, Block, parse, rewrite_ports, run, workdir
from tests.helpers import psi_ask, wait_until

PERIOD_MS = 100
NODE = 2
EMCY_HEARTBEAT = 0x8130


SERVED = re.compile(r"socketcand at ([0-9.]+):(\d+)")


def simulator_process(tmp: Path) -> Tuple[Optional["subprocess.Popen[str]"], Dict[str, Any]]:
    """``epos-link sim --drives 2 --can-server 127.0.0.1:0`` in its own process: the
    process and the python-can options of its CAN bus (socketcand, issue 23).

    ``BRIDGE_E2E_CAN=interface:channel`` runs the same test on another bus that
    several processes share (a vcan, real hardware): then no simulator is started
    and the drive ``NODE`` on it must be an EPOS4 that may move.
    """
    raw = os.environ.get("BRIDGE_E2E_CAN")
    if raw:
        interface, _, channel = raw.partition(":")
        return None, {"interface": interface, "channel": channel}
    out = (tmp / "sim.log").open("w+")
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "sim", "--tcp", "127.0.0.1:0",
                             "--drives", str(NODE), "--can-server", "127.0.0.1:0"],
                            stdout=out, stderr=subprocess.STDOUT, text=True)

    def served() -> bool:
        return SERVED.search((tmp / "sim.log").read_text()) is not None or proc.poll() is not None

    wait_until(served, 60, "the simulator never served its CAN bus")
    found = SERVED.search((tmp / "sim.log").read_text())
    assert found and proc.poll() is None, (tmp / "sim.log").read_text()
    return proc, {"interface": "socketcand", "host": found.group(1), "port": int(found.group(2)),
                  "channel": "can0"}


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


def is_heartbeat_emcy(message: Any) -> bool:
    return bool(message.arbitration_id == 0x80 + NODE
                and int.from_bytes(bytes(message.data[:2]), "little") == EMCY_HEARTBEAT)


def run_and_kill(tmp_path: Path, heartbeat: bool) -> Tuple[List[Any], bool]:
    """Serve, move, SIGKILL the bridge; the frames seen on the bus up to 4 s later (ten
    times the consumer time; with ``heartbeat``, up to the drive's EMCY 8130h, all that
    its test looks at: issue 32), and whether the drive is then at rest in quick stop
    (or past it)."""
    import can

    sim, bus = simulator_process(tmp_path)
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
                if heartbeat and is_heartbeat_emcy(message):
                    break
        if heartbeat:
            wait_until(lambda: drive_at_rest(bus), 10, "the drive did not come to rest")
        return frames, drive_at_rest(bus)
    finally:
        if bridge is not None and bridge.poll() is None:
            bridge.kill()
        listener.shutdown()
        if sim is not None:
            sim.terminate()
            sim.wait(30)


def test_a_killed_bridge_stops_the_drive_within_four_periods(tmp_path: Path) -> None:
    frames, at_rest = run_and_kill(tmp_path, heartbeat=True)
    beats = [m for m in frames if m.arbitration_id == 0x700 + 127]
    emcy = [m for m in frames if is_heartbeat_emcy(m)]
    assert emcy, "no EMCY 8130h after the bridge died"
    last_beat = beats[-1].timestamp if beats else None
    if last_beat is not None:  # the kill may land between two heartbeats: none after it
        assert emcy[0].timestamp - last_beat <= (3 + 1) * PERIOD_MS / 1000
    assert at_rest


def test_without_heartbeat_a_killed_bridge_leaves_the_drive_turning(tmp_path: Path) -> None:
    frames, at_rest = run_and_kill(tmp_path, heartbeat=False)
    assert not [m for m in frames if m.arbitration_id == 0x80 + NODE]
    assert not at_rest


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


SCENARIO_DOC = ROOT / "docs" / "simulator.md"
SCENARIO_TABLE = Path("tcp_bridge") / "example_heartbeat_axes.toml"
TABLE_PORT = re.compile(r"^port = (\d+)$", re.MULTILINE)


def scenario_block() -> Block:
    """The console block of docs/simulator.md that serves the shipped heartbeat table."""
    found = [b for b in parse(SCENARIO_DOC) if any(str(SCENARIO_TABLE) in c.text for c in b.commands)]
    assert len(found) == 1, [b.id for b in found]
    return found[0]


def test_the_documented_scenario_runs_as_the_docs_show(tmp_path: Path) -> None:
    """docs/simulator.md's block, run as test_docs_commands.py runs a block (free ports in
    place of the documented ones), in a directory whose copy of the shipped table names
    the simulator's rewritten CAN port: check finds the drive and names the heartbeat, a
    velocity move turns it, and after ``kill -9`` of the bridge it is in QUICK STOP ACTIVE
    at rest."""
    block = scenario_block()
    assert block.skip is not None and block.skip.startswith("tested by tests/" + Path(__file__).name)
    texts = [c.text for c in block.commands]
    assert any(t.startswith("kill -9 %") for t in texts), texts  # the point of the scenario
    assert any("quick stop active" in line for c in block.commands for line in c.expected)
    ports = rewrite_ports(block, {})
    table = (ROOT / SCENARIO_TABLE).read_text()
    (can_port,) = [int(p) for p in TABLE_PORT.findall(table)]
    assert can_port in ports, f"the table's port {can_port} is not the block's --can-server port"
    own = tmp_path / SCENARIO_TABLE.parent
    own.mkdir()
    for entry in (ROOT / SCENARIO_TABLE.parent).iterdir():
        if entry.name != SCENARIO_TABLE.name:
            (own / entry.name).symlink_to(entry)
    (tmp_path / SCENARIO_TABLE).write_text(TABLE_PORT.sub(f"port = {ports[can_port]}", table))
    failures = run(block, ports, workdir(tmp_path))
    assert not failures, "\n\n".join(failures)
