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
    if not stamp.exists() or dev.installed_extras(stamp.read_text(), want) is None:
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
    commands: list = []
    monkeypatch.setattr(dev.subprocess, "call",
                        lambda cmd, cwd=None, env=None: commands.append(cmd) or calls.append(cmd[2])
                        or codes[cmd[2]])
    assert dev.run_tests([]) == 1 and calls == ["mypy"]
    calls.clear()
    codes["mypy"] = 0
    assert dev.run_tests([]) == 0 and calls == ["mypy", "pytest"]
    # the whole suite: every test (no -m filter: the slow ones too), on xdist workers
    assert commands[-1][3:] == ["-n", str(dev.WORKERS), "--dist", "loadgroup"]
    calls.clear()
    assert dev.run_tests(["-k", "framing"]) == 0 and calls == ["pytest"]
    assert commands[-1][3:] == ["-k", "framing"]  # the user's arguments, alone


@pytest.mark.parametrize("exit_code, expected", [(0, 0), (1, 1), (5, 1)])
def test_pytest_collecting_nothing_fails_the_run(monkeypatch: pytest.MonkeyPatch,
                                                 exit_code: int, expected: int) -> None:
    """pytest's exit 5 (no tests collected) must never count as a pass."""
    monkeypatch.setattr(dev.subprocess, "call", lambda cmd, cwd=None, env=None: exit_code)
    assert dev.run_tests(["-k", "no such test"]) == expected


def test_tests_run_with_the_bytecode_cache_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 32: PYTHONDONTWRITEBYTECODE would make every run compile every module again;
    no PYTHONPYCACHEPREFIX of ours either, which would hide the bytecode pip and Python's
    installer wrote (dev.py test_env)."""
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    monkeypatch.delenv("PYTHONPYCACHEPREFIX", raising=False)
    env = dev.test_env()
    assert "PYTHONDONTWRITEBYTECODE" not in env and "PYTHONPYCACHEPREFIX" not in env


def test_the_packages_are_marked_typed() -> None:
    assert (ROOT / "epos_link" / "py.typed").exists() and (ROOT / "tcp_bridge" / "py.typed").exists()
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text()


# -- a quick first start (issue 34 item 6) ----------------------------------------------------


class FakeVenv:
    """dev.py's paths moved to a temporary checkout; pip calls recorded, not run."""

    def __init__(self, root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        (root / "pyproject.toml").write_text("[project]\nname = 'x'\n")
        venv_dir = root / ".venv"
        (venv_dir / "bin").mkdir(parents=True)
        (venv_dir / "bin" / "python").write_text("")
        for name, value in (("ROOT", root), ("VENV", venv_dir), ("PY", venv_dir / "bin" / "python"),
                            ("STAMP", venv_dir / ".installed")):
            monkeypatch.setattr(dev, name, value)
        self.root = root
        self.calls: List[List[str]] = []
        monkeypatch.setattr(dev.subprocess, "run",
                            lambda cmd, check=False: self.calls.append(cmd))

    def installs(self) -> List[str]:
        """The -e target of each pip install, and whether pip was quiet."""
        return [("-q " if "-q" in c else "") + c[-1].replace(str(self.root), "ROOT")
                for c in self.calls]


def test_start_installs_only_what_the_bridge_needs_and_shows_pips_progress(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """104 s to `listening` on a fresh clone, mypy, hypothesis, matplotlib and pysoem
    installed to start a bridge, one line of progress: what the user met."""
    env = FakeVenv(tmp_path, monkeypatch)
    dev.ensure_env(dev.start_extras(["--axes", "3"]), quiet=False)
    assert env.installs() == ["ROOT"]  # no extras at all; pip not -q: its progress shows
    assert "pip's progress below" in capsys.readouterr().out
    dev.ensure_env(dev.start_extras([]), quiet=False)
    assert len(env.calls) == 1  # installed already: starts at once
    dev.ensure_env(dev.start_extras(["--ethercat", "2"]), quiet=False)
    assert env.installs()[-1] == "ROOT[ethercat]"  # --ethercat needs pysoem
    dev.ensure_env()  # dev.py test: the rest, kept what was there
    assert env.installs()[-1] == "-q ROOT[epics,epics-clients,ethercat,plot,test]"
    dev.ensure_env(dev.start_extras([]), quiet=False)
    assert len(env.calls) == 3  # a start after a test run reinstalls nothing


def test_the_stamp_follows_pyproject_and_reads_the_older_format(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env = FakeVenv(tmp_path, monkeypatch)
    dev.STAMP.write_text(dev.pyproject_hash())  # the older dev.py: all three extras
    dev.ensure_env()
    assert env.calls == []
    dev.ensure_env(())
    assert env.calls == []
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'y'\n")
    dev.ensure_env(())  # pyproject changed: reinstalled, with every extra that was there
    assert env.installs() == ["-q ROOT[epics,epics-clients,ethercat,plot,test]"]
    assert dev.STAMP.read_text() == f"{dev.pyproject_hash()}\nextras: epics,epics-clients,ethercat,plot,test\n"


def test_dev_py_test_installs_the_tools_of_the_skipping_tests_where_it_may(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    present = {"tmux"}
    monkeypatch.setattr(dev.shutil, "which",
                        lambda name: f"/usr/bin/{name}" if name in present | {"apt-get"} else None)
    runs: List[List[str]] = []

    def apt(cmd: List[str], **kwargs: object) -> subprocess.CompletedProcess:
        runs.append(cmd)
        assert kwargs["env"]["DEBIAN_FRONTEND"] == "noninteractive"  # type: ignore[index]
        if "install" in cmd and any("update" in c for c in runs):
            present.update({"tshark", "chromium", "ip"})
        return subprocess.CompletedProcess(cmd, 0 if any("update" in c for c in runs) else 100)

    monkeypatch.setattr(dev.os, "geteuid", lambda: 0)
    assert dev.ensure_tools(apt) == []
    assert [c[3] for c in runs] == ["install", "update", "install"]  # an old list: update once
    assert runs[0][-3:] == ["tshark", "chromium", "iproute2"]
    monkeypatch.setattr(dev.os, "geteuid", lambda: 1000)
    present.clear()
    runs.clear()
    assert dev.ensure_tools(apt) == ["tshark", "tmux", "chromium", "iproute2"] and runs == []
    assert "as root: apt-get install tshark tmux chromium iproute2" in capsys.readouterr().out
