"""``tcp-bridge serve --simulate --ethercat N`` (issue 26): EtherCAT axes after the CAN ones
on a veth pair where the machine allows it; one line and exit 2 where it does not; the
simulated slaves and the veth pair gone after every exit, the second signal's included."""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import List

import pytest

from tcp_bridge import cli as bridge_cli
from tcp_bridge.backends import ethercat_sim
from tcp_bridge.wire import Status
from tests.helpers import wait_until

ROOT = Path(__file__).resolve().parent.parent


def one_line_exit_2(argv: List[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert bridge_cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("tcp-bridge: "), err
    return err


def test_ethercat_needs_simulate(capsys: pytest.CaptureFixture[str]) -> None:
    err = one_line_exit_2(["serve", "--config", "axes.toml", "--ethercat", "1"], capsys)
    assert "needs --simulate" in err


@pytest.mark.parametrize("count", ["0", "65"])
def test_a_slave_count_out_of_range_is_refused(count: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    if count == "0":  # argparse: positive_int
        with pytest.raises(SystemExit) as exited:
            bridge_cli.main(["serve", "--simulate", "--ethercat", count])
        assert exited.value.code == 2
    else:
        assert "1..64" in one_line_exit_2(["serve", "--simulate", "--ethercat", count], capsys)


@pytest.mark.parametrize("missing, words", [
    ("root", "needs root: CAP_NET_ADMIN"), ("ip", "iproute2"), ("pysoem", "pysoem")])
def test_where_the_machine_does_not_allow_it_one_line_says_why(
        missing: str, words: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    if missing == "root":
        monkeypatch.setattr(ethercat_sim.os, "geteuid", lambda: 1000)
    else:
        monkeypatch.setattr(ethercat_sim.os, "geteuid", lambda: 0)
        monkeypatch.setattr(ethercat_sim.shutil, "which",
                            lambda name: None if name == missing else "/usr/sbin/ip")
        monkeypatch.setattr(ethercat_sim.importlib.util, "find_spec",
                            lambda name: None if name == missing else object())
    monkeypatch.setattr(ethercat_sim, "SimulatedEthercat",
                        lambda n: pytest.fail("started on a machine that does not allow it"))
    err = one_line_exit_2(["serve", "--simulate", "--ethercat", "1"], capsys)
    assert "--ethercat " in err and words in err, err


def children_serving(peer: str) -> List[int]:
    """Pids of processes whose command line names the veth end ``peer``."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmdline = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if peer.encode() in cmdline and b"--ethercat" in cmdline:
                found.append(int(entry.name))
    return found


def link_exists(name: str) -> bool:
    return subprocess.run(["ip", "link", "show", name], capture_output=True,
                          timeout=30).returncode == 0


# A bridge whose shutdown hangs (the engine's close waits a minute), so that the second
# signal finds it shutting down and exits at once (os._exit, past main's finally).
SLOW_CLOSE = """
import sys, time
from tcp_bridge import engine

close = engine.Engine.close
def slow(self, wait=True):
    time.sleep(60 if "--slow-close" in sys.argv else 0)
    close(self, wait)
engine.Engine.close = slow
from tcp_bridge.cli import main
sys.exit(main([a for a in sys.argv[1:] if a != "--slow-close"]))
"""


@pytest.mark.skipif(ethercat_sim.unavailable_reason() is not None,
                    reason=f"EtherCAT on veth: {ethercat_sim.unavailable_reason()}")
@pytest.mark.parametrize("signals, status", [(1, 0), (2, 128 + signal.SIGINT)])
def test_serve_simulate_ethercat_adds_axes_and_cleans_up(signals: int, status: int) -> None:
    proc = subprocess.Popen([sys.executable, "-c", SLOW_CLOSE, "serve", "--simulate",
                             "--axes", "1", "--ethercat", "2", "--port", "0",
                             "--maintenance-port", "-1"] + (["--slow-close"] if signals == 2 else []),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peer, master = f"tbs{proc.pid}", f"tbm{proc.pid}"
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert "axes 1=can1/1, 2=ethercat/1, 3=ethercat/2;" in line, line
        assert f"on veth {peer}" in proc.stdout.readline()  # type: ignore[union-attr]
        address = line.split("listening on ")[1].split(" ")[0]
        assert link_exists(master) and len(children_serving(peer)) == 1

        def answers() -> bool:
            replies = bridge_cli.send(address, ["2R10", "3R10"], timeout=30)
            return all(r.status is Status.ACK for r in replies)
        wait_until(answers, timeout=60, why="the EtherCAT axes never answered")
    finally:
        proc.send_signal(signal.SIGINT)
        if signals == 2:
            assert proc.stdout.readline().startswith(  # type: ignore[union-attr]
                "tcp-bridge: shutting down")
            time.sleep(0.3)
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    assert not link_exists(master) and not link_exists(peer)
    wait_until(lambda: not children_serving(peer), timeout=30,
               why="the simulated slaves outlived the bridge")


@pytest.mark.skipif(ethercat_sim.unavailable_reason() is not None,
                    reason=f"EtherCAT on veth: {ethercat_sim.unavailable_reason()}")
def test_the_cycle_counts_are_printed_at_close_without_v() -> None:
    """Issue 34 item 7: docs/hardware.md promises the cycle's counts at close (cycles,
    short working counters, frames lost, overruns, latest start); the user stopped
    ``serve --simulate --ethercat 1`` with Ctrl-C and saw them only with -v."""
    proc = subprocess.Popen([sys.executable, "-m", "tcp_bridge.cli", "serve", "--simulate",
                             "--axes", "1", "--ethercat", "1", "--port", "0",
                             "--maintenance-port", "-1"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert "2=ethercat/1" in line, line
        address = line.split("listening on ")[1].split(" ")[0]

        def answers() -> bool:
            return bridge_cli.send(address, ["2R10"], timeout=30)[0].status is Status.ACK
        wait_until(answers, timeout=60, why="the EtherCAT axis never answered")
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    counts = [line for line in err.splitlines() if "ethercat: " in line and " cycles, " in line]
    assert len(counts) == 1, err
    assert re.search(r"ethercat: [1-9]\d* cycles, \d+ with a short working counter, \d+ without "
                     r"a frame, \d+ overruns, latest start \d+\.\d\d ms after its deadline$",
                     counts[0]), counts[0]
