"""A silent bus seen from EPICS (issue 33, Must show 4), the way a user meets it: the
bridge's EPOS4 (``epos-link sim --tcp`` in its own process) stops answering (SIGSTOP,
as a hung or unplugged device), and a pyepics client watching the record sees
STAT = COMM, SEVR = INVALID and the reason in ``-MsgTxt``; when the device answers
again (SIGCONT) the alarm clears. The bound is ten times the second the issue asks for.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.epics_harness import ROOT, Console, Served, no_client

REASON = no_client("epics")
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")


def wait_for(what, timeout: float, why: str):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while True:
        value = what()
        if value:
            return value
        assert time.monotonic() < deadline, f"{why} (within {timeout} s)"
        time.sleep(0.05)


def test_a_silent_bus_raises_the_alarm_and_the_message_within_a_second_and_clears(
        tmp_path: Path) -> None:
    sim = subprocess.Popen([sys.executable, "-m", "epos_link.cli", "sim", "--tcp",
                            "127.0.0.1:0", "--drives", "2"], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    bridge = console = None
    try:
        assert sim.stdout is not None
        url = re.search(r"listening on (\S+)", sim.stdout.readline())
        assert url, "epos-link sim did not say where it listens"
        config = tmp_path / "axes.toml"
        config.write_text(f'[bus.can1]\nbackend = "epos"\nurl = "{url.group(1)}"\n'
                          'timeout = 0.3\n\n[[axis]]\nnode_id = 2\nposition_factor = 1000\n')
        bridge = Served(["--config", str(config)])
        console = Console(bridge.env)
        assert console("monitor", "TST:m1.SEVR") is True  # a client watches the record
        assert console("severity", "TST:m1.RBV") == [0, 0]
        assert console("get", "TST:m1-MsgTxt", as_string=True) == ""

        os.kill(sim.pid, signal.SIGSTOP)  # the device falls silent
        t = time.monotonic()
        wait_for(lambda: console("get", "TST:m1.SEVR", as_string=True) == "INVALID", 10,
                 "SEVR never became INVALID")
        took = time.monotonic() - t
        assert console("get", "TST:m1.STAT", as_string=True) == "COMM"
        assert console("severity", "TST:m1.RBV") == [9, 3]  # every field: COMM, INVALID
        message = console("get", "TST:m1-MsgTxt", as_string=True)
        print(f"\n-MsgTxt: {message!r}")
        assert message.startswith("axis 1"), message  # the axis, and why (no answer)
        assert console("get", "TST:m1:Connected") == 0
        assert console("get", "TST:m1.MSTA") & (1 << 12)  # motor.h CNTRL_COMM_ERR
        print(f"\nsilent bus: SEVR INVALID after {took:.2f} s")

        os.kill(sim.pid, signal.SIGCONT)  # it answers again
        wait_for(lambda: console("get", "TST:m1.SEVR", as_string=True) == "NO_ALARM", 10,
                 "the alarm never cleared")
        assert console("get", "TST:m1.STAT", as_string=True) == "NO_ALARM"
        assert console("get", "TST:m1-MsgTxt", as_string=True) == ""
        assert console("get", "TST:m1:Connected") == 1
    finally:
        if console is not None:
            console.close()
        if bridge is not None:
            bridge.close()
        os.kill(sim.pid, signal.SIGCONT)
        sim.terminate()
        sim.wait(30)
