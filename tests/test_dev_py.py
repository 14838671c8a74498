"""``python3 dev.py start``: the simulator unless an axis table is given; Ctrl-C and
SIGTERM reach the bridge once and its clean exit is awaited."""
from __future__ import annotations

import hashlib
import importlib.util
import signal
import socket
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import List

import pytest

from tcp_bridge.cli import send

ROOT = Path(__file__).resolve().parent.parent


def load_dev() -> ModuleType:
    spec = importlib.util.spec_from_file_location("dev", ROOT / "dev.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


dev = load_dev()


@pytest.mark.parametrize("args, simulate", [
    ([], True),
    (["--axes", "5"], True),
    (["--config", "axes.toml"], False),
    (["--config=axes.toml", "--port", "0"], False),
    (["--simulate", "--axes", "2"], False),  # given once by the user, not twice
    (["--ethercat", "2"], True),  # simulated EtherCAT slaves too: passed through
])
def test_simulate_only_without_a_source_of_axes(args: List[str], simulate: bool) -> None:
    cmd = dev.bridge_command(args)
    assert Path(cmd[0]).name == "tcp-bridge" and cmd[1] == "serve"
    added = cmd[2:len(cmd) - len(args)]
    assert cmd[len(cmd) - len(args):] == args  # the user's arguments, unchanged, last
    assert added == (["--simulate"] if simulate else [])


def require_ready_venv() -> None:
    stamp = ROOT / ".venv" / ".installed"
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if not stamp.exists() or stamp.read_text() != want:
        pytest.skip("dev.py would (re)install .venv first; run the suite through dev.py test")


def start(*args: str) -> subprocess.Popen[str]:
    require_ready_venv()
    return subprocess.Popen([sys.executable, str(ROOT / "dev.py"), "start", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_reaches_the_bridge_once_and_its_clean_exit_is_awaited(signum: int) -> None:
    proc = start("--port", "0", "--maintenance-port", "-1", "--axes", "2")
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert "listening on" in line, line
        address = line.split("listening on ")[1].split(" ")[0]
        assert send(address, ["2R99"], timeout=10)[0].status.name == "ACK"
        proc.send_signal(signum)  # to dev.py only: the bridge is in its own process group
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "shutting down" in out  # the bridge's clean path ...
    assert "second signal; exiting now" not in out + err  # ... after exactly one signal
    host, port = address.rsplit(":", 1)
    with pytest.raises(OSError):  # and it is gone, not orphaned
        socket.create_connection((host, int(port)), timeout=5).close()


def test_start_with_config_serves_with_the_buses_it_cannot_open_named() -> None:
    """No CAN adapter and no EPOS4 on /dev/ttyACM0 here (example_axes.toml: can1
    socketcan can0, can2 epos): the bridge still serves (issue 24: its axes answer NAK
    and the buses are opened again in the background), naming each bus once."""
    proc = start("--config", "tcp_bridge/example_axes.toml", "--port", "0",
                 "--maintenance-port", "-1")
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert "listening on" in line, line
        address = line.split("listening on ")[1].split(" ")[0]
        reply = send(address, ["1R10"], timeout=10)[0]
        assert reply.status.name == "NAK"  # its bus is not there: refused at once
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert err.count("bus can1: cannot open") == 1 and err.count("bus can2: cannot open") == 1, err


def test_the_whole_suite_runs_mypy_first_and_a_type_error_fails_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 24: `dev.py test` (what .ci/run calls) runs mypy over both packages before
    pytest, and a mypy failure fails it; with pytest arguments only pytest runs."""
    calls: list = []
    codes = {"mypy": 1, "pytest": 0}
    monkeypatch.setattr(dev.subprocess, "call",
                        lambda cmd, cwd=None: calls.append(cmd[2]) or codes[cmd[2]])
    assert dev.run_tests([]) == 1 and calls == ["mypy"]
    calls.clear()
    codes["mypy"] = 0
    assert dev.run_tests([]) == 0 and calls == ["mypy", "pytest"]
    calls.clear()
    assert dev.run_tests(["-k", "framing"]) == 0 and calls == ["pytest"]


def test_the_packages_are_marked_typed() -> None:
    assert (ROOT / "epos_link" / "py.typed").exists() and (ROOT / "tcp_bridge" / "py.typed").exists()
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text()
