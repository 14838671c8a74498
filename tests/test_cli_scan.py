"""``epos-link scan``: nodes printed as they are found, progress on a terminal,
--node-timeout honoured; against the simulator over TCP."""
from __future__ import annotations

import os
import select
import subprocess
import sys
import time
from typing import Iterator

import pytest

from epos_link.client import EposClient
from epos_link.errors import DeviceError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import LinkOptions, TcpLink

WAIT = 60.0


@pytest.fixture()
def bus() -> Iterator[TcpLink]:
    sim = Epos4Simulator(1, [2, 3])
    link = TcpLink(sim).start()
    try:
        yield link
    finally:
        link.close()
        sim.close()


def test_nodes_are_printed_as_they_are_found(bus: TcpLink) -> None:
    # Nodes 4..127 are absent: each costs the gateway's SDO timeout (0.3 s), so the
    # scan is busy with them for over 30 s, ten times the wait for node 3's line.
    proc = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "scan", bus.url, "--nodes", "1-3,4-127"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for _ in range(3):
            ready, _, _ = select.select([proc.stdout], [], [], WAIT)
            assert ready
            lines.append(proc.stdout.readline())  # type: ignore[union-attr]
        still_running = proc.poll() is None
    finally:
        proc.kill()
        proc.communicate(timeout=WAIT)
    assert [line.split()[1] for line in lines] == ["1", "2", "3"]
    assert 'name="EPOS4"' in lines[0]
    assert still_running, "the found nodes came only at the end"


def test_a_scan_that_is_not_on_a_terminal_shows_no_progress_line(bus: TcpLink) -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", bus.url, "--nodes", "1-4"],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 0 and len(p.stdout.splitlines()) == 3 and "\r" not in p.stderr


@pytest.mark.skipif(os.name != "posix", reason="needs a pseudo-terminal")
def test_progress_on_a_terminal(bus: TcpLink) -> None:
    master, slave = os.openpty()
    try:
        p = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", bus.url, "--nodes", "2,5"],
                           stdout=subprocess.PIPE, stderr=slave, text=True, timeout=WAIT)
        os.close(slave)
        slave = -1
        progress = b""
        while select.select([master], [], [], 0.5)[0]:
            try:
                chunk = os.read(master, 65536)
            except OSError:
                break
            if not chunk:
                break
            progress += chunk
    finally:
        os.close(master)
        if slave >= 0:
            os.close(slave)
    assert p.returncode == 0 and p.stdout.startswith("node   2")
    text = progress.decode(errors="replace")
    assert "\rscanning node 2 (1/2), 0 found" in text and "scanning node 5 (2/2), 1 found" in text
    assert "1 of 2 nodes answered in" in text


def test_node_timeout_is_honoured() -> None:
    """A device that answers after 0.3 s: found with --node-timeout 2, absent with 0.05."""
    sim = Epos4Simulator(1, [])
    link = TcpLink(sim, LinkOptions(delay=0.3)).start()
    try:
        slow = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", link.url, "--nodes", "1",
                               "--node-timeout", "2", "--timeout", "2"], capture_output=True, text=True, timeout=WAIT)
        fast = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", link.url, "--nodes", "1",
                               "--node-timeout", "0.05"], capture_output=True, text=True, timeout=WAIT)
    finally:
        link.close()
        sim.close()
    assert slow.returncode == 0 and slow.stdout.startswith("node   1"), slow.stderr
    assert fast.returncode == 2 and "no node answered" in fast.stderr


class Listening:
    """A simulated EPOS4 that counts the request frames it receives."""

    def __init__(self, sim: Epos4Simulator) -> None:
        self.sim = sim
        self.frames = 0

    def receive(self, data: bytes) -> list[bytes]:
        self.frames += data.count(b"\x90\x02")  # DLE STX starts each frame (guide 2.2.3)
        return self.sim.receive(data)

    def reset(self) -> None:
        self.sim.reset()


def test_a_silent_link_is_one_line_and_no_node_is_tried() -> None:
    """The EPOS4 reads and never answers (wrong baud rate, a dead converter): the scan asks
    the EPOS4 itself (node 0) first and stops there, instead of 127 nodes timing out."""
    sim = Epos4Simulator(1, [2])
    device = Listening(sim)
    link = TcpLink(device, LinkOptions(silent=True)).start()
    try:
        started = time.monotonic()
        p = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", link.url],
                           capture_output=True, text=True, timeout=WAIT)
        took = time.monotonic() - started
    finally:
        link.close()
        sim.close()
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.splitlines() == [p.stderr.strip()], p.stderr  # one line
    assert f"epos-link scan: the EPOS4 at {link.url} does not answer" in p.stderr
    assert "baud rate" in p.stderr and "power" in p.stderr and "no node answered" not in p.stderr
    assert device.frames <= 2  # node 0's read and its one retry: no node was tried
    assert took < WAIT / 2  # about 2 s; 76 s before (every node timed out)


def test_bad_node_list_is_a_usage_error() -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link.cli", "scan", "sim://", "--nodes", "1-200"],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 2 and "node ids are 0..127" in p.stderr and "Traceback" not in p.stderr


def test_the_sim_gateway_timeout_is_what_an_absent_node_costs() -> None:
    """``epos-link sim --gateway-timeout MS`` (tests/test_docs_commands.py scans 127 nodes
    with 20 ms): an absent node is answered 0x05040000 only after that long (1 s here,
    0.3 s without the option), and a node there to answer does so at once. A lower
    bound only: a loaded machine can make a wait longer, never shorter."""
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "sim", "--tcp", "127.0.0.1:0",
                             "--drives", "2", "--gateway-timeout", "1000"],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    url = proc.stdout.readline().split()[-1]
    try:
        with EposClient.open(url, timeout=WAIT) as client:
            started = time.monotonic()
            with pytest.raises(DeviceError) as absent:
                client.read_object(9, 0x1000, 0)
            took = time.monotonic() - started
            found = client.read_object(2, 0x1000, 0)
    finally:
        proc.terminate()
        proc.communicate(timeout=WAIT)
    assert absent.value.code == 0x05040000  # SDO protocol timed out
    assert took >= 1.0
    assert found == bytes.fromhex("92010200")  # node 2's device type: it answers at once


@pytest.mark.parametrize("value", ["0", "-5", "nan", "60001"])
def test_a_bad_sim_gateway_timeout_is_one_line(value: str) -> None:
    p = subprocess.run([sys.executable, "-m", "epos_link", "sim", "--gateway-timeout", value],
                       capture_output=True, text=True, timeout=WAIT)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "--gateway-timeout" in p.stderr, p.stderr
