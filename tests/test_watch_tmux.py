"""``epos-link watch`` on a real terminal, through tmux (issue 25, Must show 2).

A simulated EPOS4 with drive 2 serves one TCP link, which watch holds; the test
moves the drive by writing its object store in this process (the link serves one
host at a time, as an EPOS4's USB port does), which is what an application with
the port would do with WriteObject. The screen must show the statusword's state
and a position that changes; ``q`` must end watch with exit 0 and give the
terminal back: the tty modes as ``stty -g`` saw them before, tmux's alternate
screen off and the cursor shown again.

``EPOS_LINK_SCREEN_DUMP=docs/watch-screen.txt`` writes the screen it saw while
the drive moved: README.md and docs/epos-link.md show that file.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import pytest

from epos_link.simulator.core import Epos4Simulator
from epos_link.simulator.link import TcpLink
from tests.test_monitor_tmux import TMUX, WAIT

pytestmark = pytest.mark.skipif(TMUX is None, reason="tmux is not installed (Debian: apt-get install tmux)")
WIDTH, HEIGHT = 140, 16
POSITION = re.compile(r"^0x6064/0x00  Position actual value +(-?\d+) +inc ", re.M)


class Pane:
    """One tmux session running one shell command."""

    def __init__(self, command: str, width: int = WIDTH, height: int = HEIGHT) -> None:
        self.name = f"epos-watch-{os.getpid()}-{time.monotonic_ns() % 10**6}"
        subprocess.run([TMUX, "new-session", "-d", "-s", self.name, "-x", str(width), "-y", str(height),  # type: ignore[list-item]
                        command], check=True, timeout=WAIT)

    def capture(self) -> str:
        return subprocess.run([TMUX, "capture-pane", "-p", "-t", self.name],  # type: ignore[list-item]
                              capture_output=True, text=True, timeout=WAIT).stdout

    def flag(self, name: str) -> str:
        """A tmux format variable of the pane (``alternate_on``, ``cursor_flag``)."""
        return subprocess.run([TMUX, "display-message", "-p", "-t", self.name, f"#{{{name}}}"],  # type: ignore[list-item]
                              capture_output=True, text=True, timeout=WAIT).stdout.strip()

    def wait_for(self, test: "re.Pattern[str] | str") -> str:
        deadline = time.monotonic() + WAIT
        while True:
            screen = self.capture()
            if (test in screen) if isinstance(test, str) else test.search(screen):
                return screen
            assert time.monotonic() < deadline, f"{test!r} never appeared on:\n{screen}"
            time.sleep(0.1)

    def keys(self, *keys: str) -> None:
        subprocess.run([TMUX, "send-keys", "-t", self.name, *keys], check=True, timeout=WAIT)  # type: ignore[list-item]

    def close(self) -> None:
        subprocess.run([TMUX, "kill-session", "-t", self.name], capture_output=True, timeout=WAIT)  # type: ignore[list-item]


@pytest.fixture
def drive_link() -> Iterator[tuple[Epos4Simulator, str]]:
    sim = Epos4Simulator(1, [2])
    link = TcpLink(sim).start()
    try:
        yield sim, link.url
    finally:
        link.close()
        sim.close()


def start_a_velocity_move(sim: Epos4Simulator) -> None:
    """Profile velocity mode, enable (controlword 6 then 15, CiA 402-2 6.4.1.3), 1000 rpm."""
    store = sim.drives[2].store
    store.write(0x6060, 0, (3).to_bytes(1, "little", signed=True))
    store.write(0x6040, 0, (0x06).to_bytes(2, "little"))
    store.write(0x6040, 0, (0x0F).to_bytes(2, "little"))
    store.write(0x60FF, 0, (1000).to_bytes(4, "little", signed=True))


def test_watch_shows_a_moving_drive_and_q_quits(drive_link: tuple[Epos4Simulator, str], tmp_path: Path) -> None:
    sim, url = drive_link
    before, after = tmp_path / "before", tmp_path / "after"
    watch = f"{shlex.quote(sys.executable)} -m epos_link.cli watch {url} --node 2"
    pane = Pane(f"cd {shlex.quote(os.getcwd())}; stty -g > {before}; {watch}; echo exit=$?; "
                f"stty -g > {after}; sleep 60")
    try:
        first = pane.wait_for("switch on disabled")
        assert first.startswith(f"epos-link watch {url} node 2, every 0.25 s; q quits\n")
        assert pane.flag("alternate_on") == "1" and pane.flag("cursor_flag") == "0"
        start_a_velocity_move(sim)
        screen = pane.wait_for("operation enabled")
        assert "3 profile velocity (pv)" in pane.wait_for("3 profile velocity (pv)")
        # the position changes from one refresh to the next
        seen: set[int] = set()
        deadline = time.monotonic() + WAIT
        while len(seen) < 3:
            screen = pane.capture()
            match = POSITION.search(screen)
            if match:
                seen.add(int(match.group(1)))
            assert time.monotonic() < deadline, f"the position did not change: {seen}\n{screen}"
            time.sleep(0.3)
        screen = pane.wait_for(re.compile(r"Velocity actual value +1000 +rpm"))
        # 0x0437: operation enabled (CiA 402-2 6.4.1.4), bit 10 target reached: at speed
        assert re.search(r"^0x6041/0x00  Statusword +0x0437 operation enabled, voltage enabled, "
                         r"target reached +\d+\.\ds +\d+\.\d/s$", screen, re.M), screen
        if os.environ.get("EPOS_LINK_SCREEN_DUMP"):
            Path(os.environ["EPOS_LINK_SCREEN_DUMP"]).write_text(
                "\n".join(line.rstrip() for line in screen.rstrip().splitlines()) + "\n", encoding="utf-8")
        pane.keys("q")
        done = pane.wait_for("exit=")
        assert "exit=0" in done
        assert "OBJECT" not in done  # the table went with the alternate screen
        assert pane.flag("alternate_on") == "0" and pane.flag("cursor_flag") == "1"
        deadline = time.monotonic() + WAIT
        while not after.exists() or not after.read_text():
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert after.read_text() == before.read_text()  # echo and line mode are back
    finally:
        pane.close()


def test_a_narrow_terminal_never_cuts_a_number(drive_link: tuple[Epos4Simulator, str]) -> None:
    """60 columns, as in the report (``1867~``, ``0x12~``, while UNIT, AGE and RATE kept
    their room): NAME shrinks and RATE goes, and the numbers stay whole. A stale
    $COLUMNS (ncurses programs export one; a tmux server started from one hands it to
    every pane) does not override what the terminal says its width is."""
    sim, url = drive_link
    watch = f"{shlex.quote(sys.executable)} -m epos_link.cli watch {url} --node 2"
    pane = Pane(f"cd {shlex.quote(os.getcwd())}; COLUMNS=130 {watch}; sleep 60", width=60, height=10)
    try:
        pane.wait_for("0x0040~")
        start_a_velocity_move(sim)
        screen = pane.wait_for(re.compile(r"^0x6041/0x00  Statusword    0x0437~ ", re.M))
        header = next(line for line in screen.splitlines() if line.startswith("OBJECT"))
        assert header.split() == ["OBJECT", "NAME", "VALUE", "UNIT", "AGE"], screen  # RATE made room
        position = re.search(r"^0x6064/0x00  Position ac~  (-?\d+)(\S*) +inc +\d+\.\ds$", screen, re.M)
        assert position and position.group(2) == "", screen  # the whole number, no ~
        assert re.search(r"^0x606C/0x00  Velocity ac~  1000 +rpm ", pane.wait_for("1000"), re.M)
        assert all(len(line) <= 60 for line in screen.splitlines())
    finally:
        pane.close()
