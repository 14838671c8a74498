"""``epos-link watch`` against ``epos-link sim --tcp``: ``--once`` tables, the table per
refresh on a pipe, exit codes, and a silent link in one line (epos_link/tools/watch.py).
The screen on a real terminal is tests/test_watch_tmux.py."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from typing import Callable, Iterator

import pytest

WAIT = 60.0  # generous: a loaded 2-core machine


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epos_link", *args], capture_output=True, text=True,
                          timeout=WAIT, env=_env())


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("COLUMNS", None)  # the width off a terminal is watch's own default, 120
    return env


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "sim", "--tcp", "127.0.0.1:0",
                             "--drives", "2"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    assert line.startswith("listening on "), line
    try:
        yield line.split()[-1]
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0


def test_once_shows_the_default_objects_of_a_drive(url: str) -> None:
    out = cli("watch", url, "--node", "2", "--once")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == f"epos-link watch {url} node 2"
    assert lines[1].split() == ["OBJECT", "NAME", "VALUE", "UNIT", "AGE", "RATE"]
    rows = {line[:11]: line for line in lines[2:]}
    assert list(rows) == ["0x6041/0x00", "0x6061/0x00", "0x6064/0x00", "0x606C/0x00", "0x1001/0x00",
                          "0x603F/0x00"]
    # The names are the shipped EDS's; a drive after power-up is switch on disabled
    # (CiA 402-2 6.4.1.1), in profile position mode (6061h default 1).
    assert "Statusword                  0x0040 switch on disabled" in rows["0x6041/0x00"]
    assert "Modes of operation display  1 profile position (pp)" in rows["0x6061/0x00"]
    assert rows["0x6064/0x00"].split()[-4:-2] == ["0", "inc"]
    assert rows["0x606C/0x00"].split()[-4:-2] == ["0", "rpm"]  # 60A9h = 0x00B44700
    assert "Error code                  0x0000 No error" in rows["0x603F/0x00"]
    assert all(line.endswith("-") and len(line) <= 120 for line in lines[2:])  # one read: no rate yet


def test_objects_by_name_and_index_with_options_between(url: str) -> None:
    out = cli("watch", url, "--node", "2", "--once", "Identity object.Vendor-ID", "0x1018/4", "0x1008")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()[2:]
    assert [line.split("  ")[0] for line in lines] == ["0x1018/0x01", "0x1018/0x04", "0x1008/0x00"]
    assert "251" in lines[0] and '"EPOS4"' in lines[2]


def test_a_device_error_shows_in_its_row_and_once_exits_1(url: str) -> None:
    out = cli("watch", url, "--node", "2", "--once", "Statusword", "0x5FFF")
    assert out.returncode == 1
    assert "0x5FFF/0x00" in out.stdout and "! 0x06020000 Object does not exist error" in out.stdout
    assert "switch on disabled" in out.stdout  # the other rows go on
    assert "0x5FFF/0x00 is not in the object dictionary" in out.stderr  # as `read` warns


def test_an_unknown_name_is_a_usage_error(url: str) -> None:
    out = cli("watch", url, "--node", "2", "--once", "Postion actual value")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.startswith("epos-link watch: no object named 'Postion actual value'")
    assert "position_actual_value" in out.stderr  # the hint


def test_a_pipe_gets_one_table_per_refresh_until_sigterm(url: str) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "watch", url, "--node", "2", "--period", "0.1",
                             "Position actual value"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=_env())
    assert proc.stdout is not None
    try:
        titles = 0
        while titles < 3:
            line = proc.stdout.readline()
            assert line, proc.stderr.read() if proc.stderr else ""
            titles += line.startswith("epos-link watch ")
        assert "\x1b" not in line
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=WAIT)
    assert proc.returncode == 0, err
    assert err == ""


def test_a_silent_link_is_one_line_and_exit_2() -> None:
    """A TCP port that accepts and never answers: the EPOS4 there is silent."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        held: list[socket.socket] = []
        threading.Thread(target=lambda: held.append(server.accept()[0]), daemon=True).start()
        out = cli("watch", f"socket://127.0.0.1:{port}", "--node", "2", "--once", "--timeout", "0.2",
                  "--retries", "0")
        for conn in held:
            conn.close()
    assert out.returncode == 2
    assert out.stdout == ""
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"epos-link watch: the EPOS4 at socket://127.0.0.1:{port} "
                                                   "does not answer"), out.stderr


def test_the_docs_show_the_captured_screen() -> None:
    """README.md and docs/epos-link.md show docs/watch-screen.txt, the screen that
    tests/test_watch_tmux.py captured (EPOS_LINK_SCREEN_DUMP), as it is."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    screen = (root / "docs" / "watch-screen.txt").read_text(encoding="utf-8")
    assert "operation enabled" in screen and "OBJECT       NAME" in screen
    for page in ("README.md", "docs/epos-link.md"):
        assert "```text\n" + screen + "```" in (root / page).read_text(encoding="utf-8"), page


def test_the_url_is_required_and_objects_are_not() -> None:
    out = cli("watch")
    assert out.returncode == 2
    assert out.stderr == ("epos-link watch: the following arguments are required: URL "
                          "(see epos-link watch --help)\n")


def test_a_dead_link_is_one_status_line_and_watch_recovers_when_it_is_back() -> None:
    """The simulator goes away while watch runs, then comes back on the same port: the
    rows say ``! link down`` (no class name, no cut cause), one line under the title says
    why, RATE falls (successful reads only), AGE goes on growing, and the table comes back."""
    import queue
    import re
    import time

    from epos_link.simulator.core import Epos4Simulator
    from epos_link.simulator.link import TcpLink

    sim = Epos4Simulator(1, [2])
    link = TcpLink(sim).start()
    port, url = link.port, link.url
    proc = subprocess.Popen([sys.executable, "-m", "epos_link", "watch", url, "--node", "2", "--period", "0.1",
                             "Statusword", "Position actual value"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**_env(), "COLUMNS": "130"})
    tables: "queue.Queue[list[str]]" = queue.Queue()

    def collect() -> None:
        assert proc.stdout is not None
        table: list[str] = []
        for line in proc.stdout:
            if line.strip():
                table.append(line.rstrip("\n"))
            elif table:
                tables.put(table)
                table = []

    def next_table(test: Callable[[list[str]], bool]) -> list[str]:
        deadline = time.monotonic() + WAIT
        while True:
            table = tables.get(timeout=max(0.1, deadline - time.monotonic()))
            if test(table):
                return table
            assert time.monotonic() < deadline, table

    def rate(line: str) -> float:
        return float(line.split()[-1].removesuffix("/s"))

    def age(line: str) -> float:
        return float(line.split()[-2].removesuffix("s"))

    threading.Thread(target=collect, daemon=True).start()
    try:
        up = next_table(lambda t: len(t) == 4 and "switch on disabled" in t[2] and t[2].endswith("/s"))
        assert rate(up[2]) > 0
        link.close()
        down = next_table(lambda t: t[1].startswith("! link down"))
        assert down[1] == "! link down: connection refused; reconnecting at each read", down
        row = re.compile(r"0x60\w\w/0x00  \S.*  ! link down +(inc +)?\d+\.\ds +\d+\.\d/s")
        assert all(row.fullmatch(line) for line in down[3:]), down
        later = next_table(lambda t: t[1].startswith("! link down") and age(t[3]) >= age(down[3]) + 0.5)
        assert rate(later[3]) < rate(down[3]) and age(later[4]) > age(down[4]), (down, later)
        assert "Error" not in "".join(later) and "~" not in "".join(later)
        link = TcpLink(sim, port=port).start()  # back, on the same port
        back = next_table(lambda t: len(t) == 4 and "switch on disabled" in t[2])
        assert back[3].split()[-4:-2] == ["0", "inc"], back
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=WAIT)
        link.close()
        sim.close()
    assert proc.returncode == 0 and err == "", err
