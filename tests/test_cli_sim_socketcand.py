"""``epos-link sim --can-server``, ``tcp-bridge serve --simulate --can-server``: the simulated
CAN bus seen from other processes, as a user runs them."""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

from tcp_bridge.cli import send
from tcp_bridge.wire import Status
from tests.helpers import wait_until

SERVED = re.compile(r"CAN bus served over socketcand at (\S+):(\d+) \(channel can0\)")

# A third process: canopen over socketcand reads drive 2's device type and statusword.
READER = textwrap.dedent("""
    import sys, canopen
    network = canopen.Network()
    network.connect(interface="socketcand", host=sys.argv[1], port=int(sys.argv[2]),
                    channel="can0")
    node = network.add_node(2, canopen.ObjectDictionary())
    node.sdo.RESPONSE_TIMEOUT = 5.0
    print(node.sdo.upload(0x1000, 0).hex(), node.sdo.upload(0x6041, 0).hex())
    network.disconnect()
""")


def _stop(proc: "subprocess.Popen[str]", sig: int = signal.SIGTERM) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        # Both stop within a second here; 60 s because a can.logger on a loaded
        # 2-core machine once took over 15 s to exit on SIGINT.
        return proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


@pytest.fixture
def sim() -> Iterator[Tuple[str, int, str]]:
    """``epos-link sim --tcp 127.0.0.1:0 --drives 2 --can-server 127.0.0.1:0``: the CAN
    server's host and port, the serial link's URL."""
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "sim", "--tcp", "127.0.0.1:0",
                             "--drives", "2", "--can-server", "127.0.0.1:0"],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        found = [m for m in map(SERVED.search, lines) if m]
        assert found, lines
        yield found[0].group(1), int(found[0].group(2)), lines[0].split()[-1]
        assert _stop(proc) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def test_can_logger_in_a_second_process_records_a_third_process_sdo_reads(
        sim: Tuple[str, int, str], tmp_path: Path) -> None:
    host, port, serial = sim
    log_file = tmp_path / "bus.log"
    # python-can 4.6: bus keyword arguments after --bus-kwargs (can/cli.py, _BusKwargsAction).
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "socketcand",
                               "-c", "can0", "-f", str(log_file),
                               "--bus-kwargs", f"host={host}", f"port={port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert logger.stdout is not None
        assert logger.stdout.readline().startswith("Connected to SocketCanDaemonBus")
        reader = subprocess.run([sys.executable, "-c", READER, host, str(port)],
                                capture_output=True, text=True, timeout=60)
        assert reader.returncode == 0, reader.stderr
        device_type, statusword = reader.stdout.split()
        assert device_type == "92010200"  # 0x00020192: CiA 402 drive (EPOS4 EDS)
        # The simulated EPOS4's gateway (a serial request -> SDO on CAN) shows up too.
        out = subprocess.run([sys.executable, "-m", "epos_link", "read", serial, "2", "0x1008",
                              "0", "--type", "str"], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0 and "EPOS4" in out.stdout, out.stderr
        # The logger writes what it has read when it stops: give it time to read the last
        # answers (they are on its socket within milliseconds; 1 s is far more).
        time.sleep(1.0)
    finally:
        _stop(logger, signal.SIGINT)
    # can.logger's .log format is candump's: "(TIMESTAMP) can0 602#4000100000000000"
    text = log_file.read_text()
    frames = re.findall(r"\b([0-9A-F]{3})#([0-9A-F]*)", text)
    assert ("602", "4000100000000000") in frames, text
    assert ("602", "4041600000000000") in frames, text
    answers = [data for cob, data in frames if cob == "582"]
    assert "4300100092010200" in answers, text
    assert any(a.startswith("4B416000" + statusword.upper()) for a in answers), text
    order = [cob for cob, _ in frames if cob in ("602", "582")]
    assert order[:4] == ["602", "582", "602", "582"]  # each request, then its answer
    assert ("602", "4008100000000000") in frames, text  # the gateway's upload of 1008h


def test_bridge_reads_the_simulator_through_socketcand(sim: Tuple[str, int, str],
                                                       tmp_path: Path) -> None:
    host, port, _ = sim
    table = tmp_path / "axes.toml"
    table.write_text(textwrap.dedent(f"""
        [bus.can1]
        backend = "canopen"
        interface = "socketcand"
        host = "{host}"
        port = {port}
        channel = "can0"
        sdo_timeout = 2.0

        [[axis]]
        addr = 2
        device = "maxon_epos4"
        node_id = 2
        position_factor = 1000
        increments_per_revolution = 2048
    """))
    bridge = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--config",
                               str(table), "--port", "0", "--maintenance-port", "-1"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert bridge.stdout is not None
        line = bridge.stdout.readline()
        assert "listening on" in line, (line, bridge.stderr.read() if bridge.poll() else "")
        address = line.split("listening on ")[1].split()[0]
        replies = send(address, ["2R10", "2R12"])
        assert [r.status for r in replies] == [Status.ACK, Status.ACK], replies
        assert replies[1].value is not None
        assert _stop(bridge, signal.SIGINT) == 0
    finally:
        if bridge.poll() is None:
            bridge.kill()


def test_bridge_with_nothing_listening_is_one_line(tmp_path: Path) -> None:
    """Nothing listens at the socketcand address: one line at once (python-can's own
    client would retry for 10 s, logging each try), and the bus counts as
    unplugged (issue 24: serve starts and opens it later; check says "no bus")."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: refused
        table = tmp_path / "axes.toml"
        table.write_text(f'[bus.can1]\nbackend = "canopen"\ninterface = "socketcand"\n'
                         f'host = "127.0.0.1"\nport = {port}\nchannel = "can0"\n\n'
                         '[[axis]]\naddr = 2\ndevice = "maxon_epos4"\nnode_id = 2\n'
                         'position_factor = 1000\nincrements_per_revolution = 2048\n')
        out = subprocess.run([sys.executable, "-m", "tcp_bridge.cli", "check", "--config",
                              str(table)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out
    why = f"bus can1: no socketcand server at 127.0.0.1:{port}: Connection refused"
    assert out.stdout.count(why) == 1 and "no bus" in out.stdout, out.stdout
    assert "Traceback" not in out.stderr


def test_serve_simulate_prints_where_its_can_bus_is_served() -> None:
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                             "--axes", "2", "--port", "0", "--maintenance-port", "-1",
                             "--can-server", "127.0.0.1:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        lines: List[str] = [proc.stdout.readline(), proc.stdout.readline()]
        served = SERVED.search(lines[1])
        assert "listening on" in lines[0] and served, lines
        import can

        bus = can.Bus(interface="socketcand", host=served.group(1), port=int(served.group(2)),
                      channel="can0")
        try:
            address = lines[0].split("listening on ")[1].split()[0]
            assert send(address, ["2R10"])[0].status is Status.ACK
            seen = set()
            for _ in range(50):
                msg = bus.recv(0.2)
                if msg is None:
                    break
                seen.add(msg.arbitration_id)
            assert {0x602, 0x582} <= seen  # the bridge's SDO to drive 2, over the gateway
        finally:
            bus.shutdown()
        assert _stop(proc, signal.SIGINT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.parametrize("argv, message", [
    (["epos_link", "sim", "--can-server", "nowhere"], "expected HOST:PORT"),
    (["epos_link", "sim", "--can-server", "nosuch.invalid:0"], "--can-server cannot listen"),
    (["tcp_bridge.cli", "serve", "--simulate", "--can-server", "h:99999"], "expected HOST:PORT"),
    (["tcp_bridge.cli", "serve", "--config", "x.toml", "--can-server", ":0"], "needs --simulate"),
])
def test_bad_can_server_arguments_are_one_line(argv: List[str], message: str) -> None:
    out = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and message in out.stderr and "Traceback" not in out.stderr
    assert out.stderr.count("\n") == 1, out.stderr


def test_basenode402_script_in_a_second_process_enables_and_moves_through_pdos(
        sim: Tuple[str, int, str]) -> None:
    """Issue 23, must-show 1: canopen's usual ``BaseNode402`` script, in this (a second)
    process, on the bus ``epos-link sim --can-server`` serves: PDO configuration read
    from the drive, NMT Operational, the state machine through RPDO1 to OPERATION
    ENABLED, then a profile position move through RPDO3 to target reached."""
    import canopen

    from epos_link.simulator.od import EDS_PATH

    host, port, _ = sim
    network = canopen.Network()
    network.connect(interface="socketcand", host=host, port=port, channel="can0")
    try:
        node = canopen.BaseNode402(2, str(EDS_PATH))
        node.sdo.RESPONSE_TIMEOUT = 5.0
        network.add_node(node)
        node.tpdo.read()
        node.rpdo.read()
        # read_pdos=False: the PDOs were just read; canopen's own read asserts an NMT
        # view of PRE-OPERATIONAL, which it has only after hearing a boot-up.
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        wait_until(lambda: node.tpdo_values.get(0x6041, 0) & 0x0200 != 0, 30.0, "the statusword TPDO")
        for state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"):
            node.state = state  # canopen waits for the statusword TPDO itself
        assert node.state == "OPERATION ENABLED"
        rpdo = node.rpdo[3]  # maxon's RPDO3: controlword + target position
        rpdo["Controlword"].raw = 0x000F
        rpdo["Target position"].raw = 4000
        rpdo.transmit()
        rpdo["Controlword"].raw = 0x001F  # new set-point, absolute
        rpdo.transmit()
        wait_until(lambda: node.tpdo_values.get(0x6041, 0) & 0x0400 != 0
              and node.sdo[0x6064].raw == 4000, 30.0, "target reached at 4000")
        rpdo["Controlword"].raw = 0x000F
        rpdo.transmit()
        node.state = "SWITCH ON DISABLED"
    finally:
        network.disconnect()
