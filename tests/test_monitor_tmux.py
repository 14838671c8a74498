"""The monitor's screen on a real terminal, captured through tmux (issue 11, Must show 4).

docs/monitor.md shows a capture made this way."""
from __future__ import annotations

import os
import shlex
import shutil
import socket
import subprocess
import sys
import time
import uuid
from typing import Iterator

import pytest

from epos_link.client import EposClient
from epos_link.errors import DeviceError
from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink

TMUX = shutil.which("tmux")
pytestmark = pytest.mark.skipif(TMUX is None, reason="tmux is not installed (Debian: apt-get install tmux)")
WAIT = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Screen:
    """One tmux session running one command on a 160x24 terminal."""

    def __init__(self, command: str) -> None:
        self.name = f"epos-link-{uuid.uuid4().hex[:8]}"
        subprocess.run([TMUX, "new-session", "-d", "-s", self.name, "-x", "160", "-y", "24", command],  # type: ignore[list-item]
                       check=True, timeout=WAIT)

    def capture(self, *, escapes: bool = False) -> str:
        args = [TMUX, "capture-pane", "-p", "-t", self.name] + (["-e"] if escapes else [])
        return subprocess.run(args, capture_output=True, text=True, timeout=WAIT).stdout  # type: ignore[arg-type]

    def wait_for(self, text: str) -> str:
        deadline = time.monotonic() + WAIT
        while True:
            screen = self.capture()
            if text in screen:
                return screen
            assert time.monotonic() < deadline, f"{text!r} never appeared on:\n{screen}"
            time.sleep(0.1)

    def close(self) -> None:
        subprocess.run([TMUX, "kill-session", "-t", self.name], capture_output=True, timeout=WAIT)  # type: ignore[list-item]


@pytest.fixture(params=["colour", "NO_COLOR"])
def screen(request: pytest.FixtureRequest) -> Iterator[tuple[Screen, int, bool]]:
    port = free_port()
    sim = Epos4Simulator(1, [2])
    link = TcpLink(sim).start()
    env = "NO_COLOR=1 " if request.param == "NO_COLOR" else "TERM=xterm-256color "
    cmd = (f"env {env}{shlex.quote(sys.executable)} -m epos_link.cli monitor "
           f"{link.url} --tcp 127.0.0.1:{port}; sleep 30")
    s = Screen(cmd)
    try:
        yield s, port, request.param == "colour"
    finally:
        s.close()
        link.close()
        sim.close()


def test_monitor_screen_in_tmux(screen: tuple[Screen, int, bool]) -> None:
    s, port, colour = screen
    s.wait_for(f"listening on socket://127.0.0.1:{port}")
    with EposClient.open(f"socket://127.0.0.1:{port}") as client:
        client.write_object(2, 0x6081, 0, (1500).to_bytes(4, "little"))
        client.read_object(2, 0x6081, 0)
        with pytest.raises(DeviceError):
            client.read_object(2, 0x5FFF, 0)
    text = s.wait_for("Object does not exist error")
    assert "TX WriteObject                    node 2 0x6081/0x00 Profile velocity = 1500 (0x000005DC) crc ok" in text
    assert "RX Answer(ReadObject)             node 2 0x6081/0x00 Profile velocity = 1500 (0x000005DC) ok crc ok" in text
    raw = s.capture(escapes=True)
    if colour:
        assert "\x1b[36m" in raw and "\x1b[32m" in raw  # TX cyan, RX green
        assert "31m" in raw  # the error answer in red (tmux may split "1;31m" in two)
    else:
        assert "\x1b[" not in raw  # NO_COLOR: plain
    if os.environ.get("EPOS_LINK_SCREEN_DUMP") and colour:
        with open(os.environ["EPOS_LINK_SCREEN_DUMP"], "w", encoding="utf-8") as fh:
            fh.write(text)
