"""``epos-link sim --usb`` as a user meets it: start it, copy the line it prints, run
``umockdev-wrapper epos-link read usb:// ...`` in that environment; pull the cable
with a line on its standard input."""
from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator

import pytest

from epos_link.simulator.usb_link import unavailable_reason

EPOS_LINK = str(Path(sys.executable).with_name("epos-link"))
WAIT = 60.0


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epos_link", *args], capture_output=True,
                          text=True, timeout=WAIT)


@pytest.mark.parametrize("args, message", [
    (["--serial", "123"], "--serial applies to --usb only"),
    (["--usb", "--baud", "115200"], "does not apply to --usb"),
    (["--usb", "--serial", "A,A"], "different serial numbers"),
    (["--usb", "--serial", "A B"], "expected serial numbers"),
    (["--usb", "--tcp", "127.0.0.1:0"], "not allowed with argument"),
])
def test_bad_usb_arguments_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    out = cli("sim", *args)
    assert out.returncode == 2 and message in out.stderr and "Traceback" not in out.stderr


def test_without_umockdev_sim_usb_says_what_to_install(tmp_path: Path) -> None:
    env = dict(os.environ, PATH=str(tmp_path), EPOS_LINK_GI_PYTHON=str(tmp_path / "python3"))
    out = subprocess.run([sys.executable, "-m", "epos_link", "sim", "--usb"], capture_output=True,
                         text=True, timeout=WAIT, env=env)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "umockdev-wrapper not found" in out.stderr and "apt install umockdev" in out.stderr


_lines: "dict[int, queue.Queue[str]]" = {}


def read_line(proc: subprocess.Popen[str]) -> str:
    """The simulator's next line, waiting at most WAIT (a thread reads its stdout)."""
    if proc.pid not in _lines:
        q: "queue.Queue[str]" = queue.Queue()
        _lines[proc.pid] = q
        assert proc.stdout is not None
        stdout = proc.stdout
        threading.Thread(target=lambda: [q.put(line) for line in stdout], daemon=True).start()
    try:
        return _lines[proc.pid].get(timeout=WAIT).strip()
    except queue.Empty:
        raise AssertionError("the simulator printed nothing") from None


@pytest.fixture
def served() -> Iterator[tuple[subprocess.Popen[str], dict[str, str]]]:
    with serving("--drives", "2") as running:
        yield running


@contextlib.contextmanager
def serving(*options: str) -> Iterator[tuple[subprocess.Popen[str], dict[str, str]]]:
    reason = unavailable_reason()
    if reason:
        pytest.skip(f"USB testbed unavailable: {reason}")
    proc = subprocess.Popen([EPOS_LINK, "sim", "--usb", *options], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        line = read_line(proc)
        # listening on usb://?serial=SIM00001: run programs as UMOCKDEV_DIR=... umockdev-wrapper PROGRAM
        match = re.fullmatch(r"listening on (\S+): run programs as UMOCKDEV_DIR=(\S+) "
                             r"umockdev-wrapper PROGRAM", line)
        assert match, line
        assert match.group(1) == "usb://?serial=SIM00001"
        yield proc, dict(os.environ, UMOCKDEV_DIR=match.group(2))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            assert proc.wait(WAIT) == 0
        finally:
            if proc.poll() is None:
                proc.kill()


def wrapped(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["umockdev-wrapper", EPOS_LINK, *args], capture_output=True, text=True,
                          timeout=WAIT, env=env)


def test_the_docs_example_reads_the_name_over_usb(
        served: tuple[subprocess.Popen[str], dict[str, str]]) -> None:
    _, env = served
    out = wrapped(env, "read", "usb://", "0", "0x1008", "0", "--type", "str")
    assert out.returncode == 0, out.stderr
    assert '"EPOS4"' in out.stdout
    out = wrapped(env, "read", "usb://", "2", "0x1008", "0", "--type", "str")  # behind the gateway
    assert out.returncode == 0 and '"EPOS4"' in out.stdout, out.stderr
    out = wrapped(env, "ports")
    assert "usb://?serial=SIM00001" in out.stdout and "24E7:3B01" in out.stdout


def test_unplug_and_replug_on_standard_input(
        served: tuple[subprocess.Popen[str], dict[str, str]]) -> None:
    proc, env = served
    assert proc.stdin is not None
    read_line(proc)  # the drives line
    proc.stdin.write("unplug\n")
    proc.stdin.flush()
    assert read_line(proc) == "unplugged usb://?serial=SIM00001"
    out = wrapped(env, "read", "usb://", "0", "0x1008", "0", "--type", "str")
    assert out.returncode == 2 and "no EPOS4 USB device" in out.stderr
    proc.stdin.write("replug\n")
    proc.stdin.flush()
    assert re.fullmatch(r"replugged usb://\?serial=SIM00001 at /dev/bus/usb/001/\d{3}", read_line(proc))
    out = wrapped(env, "read", "usb://", "0", "0x1008", "0", "--type", "str")
    assert out.returncode == 0 and '"EPOS4"' in out.stdout, out.stderr


def test_sigusr1_unplugs_and_sigusr2_replugs(
        served: tuple[subprocess.Popen[str], dict[str, str]]) -> None:
    proc, env = served
    read_line(proc)  # the drives line
    proc.send_signal(signal.SIGUSR1)
    assert read_line(proc) == "unplugged usb://?serial=SIM00001"
    proc.send_signal(signal.SIGUSR2)
    assert read_line(proc).startswith("replugged usb://?serial=SIM00001 at /dev/bus/usb/001/")
    out = wrapped(env, "read", "usb://", "0", "0x1000", "0", "--type", "u32")
    assert out.returncode == 0, out.stderr


def test_trace_records_the_usb_traffic(tmp_path: Path) -> None:
    trace = tmp_path / "usb.txt"
    with serving("--trace", str(trace)) as (_, env):
        out = wrapped(env, "read", "usb://", "0", "0x1000", "0", "--type", "u32")
        assert out.returncode == 0, out.stderr
    text = trace.read_text()
    # ReadObject 0x1000/0 to node 0 (guide 2.1.1.1: op code 0x60, Len 2 words)
    assert re.search(r"TX 90 02 60 02 00 00 10 00", text), text
    assert re.search(r"RX 90 02 00 04 00 00 00 00", text), text


def test_silent_simulator_times_out_as_a_message() -> None:
    with serving("--silent") as (_, env):
        out = wrapped(env, "read", "usb://", "0", "0x1000", "0", "--timeout", "0.2")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "no answer" in out.stderr
